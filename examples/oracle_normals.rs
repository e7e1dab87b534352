//! Experiment: how much of the per-surfel shading error is the surfels' own normals? Writes a
//! copy of a run whose surfels are turned (minimal rotation, the normal's side kept) to one of:
//! - `DATA=dir` (the oracle): the surface normal of the nearest true object of the dataset's
//!   README.json, for surfels within 3 cm of it; with `SNAP=d` (scene units) also every surfel
//!   up to d inside an object, and each of those moved onto the true surface (a geometry oracle:
//!   the surfels nvs put behind a glossy surface brought to it);
//! - `CONSENSUS=dir` (a dataset): the blend-weighted mean of the depth-derived normals
//!   (finite differences of the rendered expected depth) of the training pixels the surfel is
//!   composited into, where that weight exceeds `MIN_WEIGHT` (default 1 pixel);
//! - otherwise: the normal of the plane through its neighbours' centres (opacity-weighted PCA
//!   within radius R), where that neighbourhood is flat (`FLAT`: smallest / middle eigenvalue
//!   below 0.05).
//!
//! Rewrites `point_cloud.ply` and the `params` of `checkpoint.bin` / `checkpoint_inverse.bin`
//! where present; copies `config.toml` and `envmap.exr`. `oracle_split` or `probe_irradiance` on the
//! copy, or an inverse stage resumed from it, then show what the normals change.
//!
//!     cargo run --release --example oracle_normals -- RUN OUT [R (scene units, default 0.04)]

#[path = "common/blend_weights.rs"]
mod blend_weights;
#[path = "common/scene_readme.rs"]
mod scene_readme;

use anyhow::Context;
use radiogs::surfels::{Surfels, rotation_from_quat};
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(args.len() >= 3, "usage: oracle_normals RUN OUT [R]");
    let (run, out) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]));
    let radius: f32 = args.get(3).map(|v| v.parse()).transpose().context("R")?.unwrap_or(0.04);
    let mode = match (std::env::var("DATA"), std::env::var("CONSENSUS")) {
        (Ok(d), _) => {
            let snap = env_number("SNAP", 0.0)?;
            anyhow::ensure!(snap.is_finite() && snap >= 0.0, "SNAP={snap}: must be a distance ≥ 0 (scene units)");
            Mode::Truth(scene_readme::load(std::path::Path::new(&d))?, snap)
        }
        (_, Ok(d)) => Mode::Consensus { data: PathBuf::from(d), min_weight: env_number("MIN_WEIGHT", 1.0)? },
        // `FLAT`: the largest smallest / middle eigenvalue ratio counted as flat.
        _ => Mode::Plane { radius, flat_ratio: env_number("FLAT", 0.05)? },
    };
    std::fs::create_dir_all(&out)?;
    for f in ["config.toml", "envmap.exr"] {
        if run.join(f).is_file() {
            let bytes = std::fs::read(run.join(f)).with_context(|| format!("{}", run.join(f).display()))?;
            radiogs::io::atomic::write_atomic(&out.join(f), &bytes)?;
        }
    }
    let cfg = radiogs::eval::load_run_config(&run)?;
    if run.join("point_cloud.ply").is_file() {
        let mut s = radiogs::io::ply::read_ply(&run.join("point_cloud.ply"))?;
        let f = radiogs::io::ply::read_ply_filter_inv_square(&run.join("point_cloud.ply"))?;
        // Oriented (one-sided) surfels: the PLY of a PBR stage.
        adjust(&mut s, &mode, cfg.window, f.unwrap_or(2.0), false)?;
        radiogs::io::ply::write_ply_trained(&out.join("point_cloud.ply"), &s, f)?;
    }
    for name in ["checkpoint.bin", "checkpoint_inverse.bin"] {
        let path = run.join(name);
        if !path.is_file() {
            continue;
        }
        let mut c = radiogs::train::checkpoint::Checkpoint::load(&path)?;
        let mut s = c.get_surfels(&path, "params")?;
        // The nvs checkpoint renders as its stage did; the inverse one one-sided.
        let two_sided = name == "checkpoint.bin" && cfg.two_sided;
        adjust(&mut s, &mode, cfg.window, cfg.filter_inv_square, two_sided)?;
        c.put_surfels("params", &s);
        c.save(&out.join(name))?;
    }
    Ok(())
}

/// `DATA=dir`: the oracle instead — the surface normal of the true object nearest to p, when p
/// lies within 3 cm of it or, with `snap` > 0, up to `snap` inside it; with the signed distance.
fn oracle_normal(readme: &scene_readme::SceneReadme, p: [f32; 3], snap: f64) -> Option<([f64; 3], f64)> {
    let p = p.map(|x| x as f64);
    let o = &readme.objects[scene_readme::nearest(&readme.objects, p)];
    let d = o.sdf(p);
    if d > 0.03 || d < -(0.03f64.max(snap)) {
        return None;
    }
    let e = 1e-5;
    let g: [f64; 3] = std::array::from_fn(|a| {
        let mut q = p;
        q[a] += e;
        (o.sdf(q) - d) / e
    });
    let l = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt().max(1e-12);
    Some((g.map(|x| x / l), d))
}

/// `CONSENSUS=dir` (a dataset): each surfel's normal becomes the blend-weighted mean of the
/// depth-derived normals (finite differences of the rendered expected depth) of the training
/// pixels it is composited into, where that weight exceeds `MIN_WEIGHT` (default 1 pixel).
fn consensus(
    s: &mut Surfels,
    data: &std::path::Path,
    min_weight: f64,
    two_sided: bool,
    window: usize,
    filter: f32,
) -> anyhow::Result<()> {
    use radiogs::io::dataset::{Dataset, Split};
    use radiogs::raster::{Outputs, RasterSettings};
    let ds = Dataset::open(data)?;
    let settings = RasterSettings {
        window,
        filter_inv_square: filter,
        two_sided,
        outputs: Outputs { colour: true, depth: true, ..Outputs::none() },
        ..RasterSettings::default()
    };
    let mut blend = blend_weights::BlendSums::new(s);
    for view in ds.views(Split::Train) {
        let img = view.load_image()?;
        let cam = &view.camera;
        blend.add_view(s, cam, &settings, |out| {
            // `depth` is already Σ w z / α.
            let mut normals = vec![[0.0f32; 3]; out.depth.len()];
            radiogs::loss::normal_consistency::depth_to_normal(cam, &out.depth, &mut normals);
            let (w, h) = (cam.width as usize, cam.height as usize);
            // A pixel and its four neighbours on the surface: the finite differences stay on it.
            let covered = |p: usize| out.alpha[p] > 0.5 && img.data[p * 4 + 3] > 0.99;
            let mut v = vec![0.0f32; img.pixel_count() * 4];
            for p in 0..img.pixel_count() {
                let (x, y) = (p % w, p / w);
                if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                    continue;
                }
                if [p, p - 1, p + 1, p - w, p + w].into_iter().all(covered) && normals[p] != [0.0; 3] {
                    v[p * 4..p * 4 + 3].copy_from_slice(&normals[p]);
                    v[p * 4 + 3] = 1.0;
                }
            }
            Ok(v)
        })?;
    }
    let acc = blend.sums;
    let targets: Vec<Option<[f64; 3]>> = acc
        .iter()
        .map(|a| {
            let l = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
            (a[3] >= min_weight && l > 1e-9).then(|| [a[0] / l, a[1] / l, a[2] / l])
        })
        .collect();
    turn_all(s, &targets, "their pixels' depth normal");
    Ok(())
}

/// The quaternion of rotation `r` turned minimally so that its normal becomes `target` (same
/// hemisphere), and the angle turned (degrees); None when already there.
fn turned_to(r: [[f32; 3]; 3], target: [f64; 3]) -> Option<([f32; 4], f64)> {
    let nrm = r[2].map(|x| x as f64);
    let dot = (nrm[0] * target[0] + nrm[1] * target[1] + nrm[2] * target[2]).clamp(-1.0, 1.0);
    let axis = [
        nrm[1] * target[2] - nrm[2] * target[1],
        nrm[2] * target[0] - nrm[0] * target[2],
        nrm[0] * target[1] - nrm[1] * target[0],
    ];
    let sin = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
    if sin < 1e-9 {
        return None;
    }
    let k = axis.map(|x| x / sin);
    let rot = |v: [f64; 3]| -> [f64; 3] {
        let kv = k[0] * v[0] + k[1] * v[1] + k[2] * v[2];
        let kxv = [k[1] * v[2] - k[2] * v[1], k[2] * v[0] - k[0] * v[2], k[0] * v[1] - k[1] * v[0]];
        [0, 1, 2].map(|a| v[a] * dot + kxv[a] * sin + k[a] * kv * (1.0 - dot))
    };
    let cols = [rot(r[0].map(|x| x as f64)), rot(r[1].map(|x| x as f64)), rot(nrm)];
    Some((quat_from_columns(cols), dot.acos().to_degrees()))
}

/// Every surfel turned to the true surface's normal where [`oracle_normal`] gives one; with
/// `snap` > 0 each of those also moved onto the surface (p − d·n, d its signed distance).
fn to_truth(s: &mut Surfels, readme: &scene_readme::SceneReadme, snap: f64) {
    let found: Vec<Option<([f64; 3], f64)>> = s.means.iter().map(|&p| oracle_normal(readme, p, snap)).collect();
    if snap > 0.0 {
        let mut moved = 0usize;
        for (mean, f) in s.means.iter_mut().zip(&found) {
            if let Some((n, d)) = *f {
                *mean = std::array::from_fn(|a| (mean[a] as f64 - d * n[a]) as f32);
                moved += 1;
            }
        }
        println!("{moved} surfels moved onto the true surface (up to {snap} inside it)");
    }
    let targets: Vec<Option<[f64; 3]>> = found.iter().map(|f| f.map(|(n, _)| n)).collect();
    turn_all(s, &targets, "the true surface's normal");
}

/// Turn surfel i to `targets[i]` where it has one (on its normal's side), and report.
fn turn_all(s: &mut Surfels, targets: &[Option<[f64; 3]>], what: &str) {
    let (mut turned, mut turn_sum) = (0usize, 0.0f64);
    for (i, target) in targets.iter().enumerate() {
        let Some(mut target) = *target else { continue };
        let r = rotation_from_quat(s.quats[i]);
        if r[2][0] as f64 * target[0] + r[2][1] as f64 * target[1] + r[2][2] as f64 * target[2] < 0.0 {
            target = target.map(|x| -x);
        }
        if let Some((q, angle)) = turned_to(r, target) {
            s.quats[i] = q;
            turned += 1;
            turn_sum += angle;
        }
    }
    println!("{turned} of {} surfels turned to {what} (mean turn {:.1}°)", s.len(), turn_sum / turned.max(1) as f64);
}

/// Every surfel with a flat neighbourhood turned to its PCA plane.
fn flatten(s: &mut Surfels, radius: f32, flat_ratio: f64) {
    let n = s.len();
    let cell = radius;
    let key = |p: [f32; 3]| p.map(|x| (x / cell).floor() as i64);
    let mut grid: std::collections::HashMap<[i64; 3], Vec<usize>> = std::collections::HashMap::new();
    for i in 0..n {
        if s.opacity(i) > 0.1 {
            grid.entry(key(s.means[i])).or_default().push(i);
        }
    }
    let mut targets = vec![None; n];
    for (i, target) in targets.iter_mut().enumerate() {
        let p = s.means[i];
        let c = key(p);
        let mut w_sum = 0.0f64;
        let mut mean = [0.0f64; 3];
        let mut pts: Vec<([f64; 3], f64)> = Vec::new();
        for dz in -1..=1 {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    if let Some(list) = grid.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                        for &j in list {
                            let q = s.means[j];
                            let d2 = (0..3).map(|a| (q[a] - p[a]).powi(2)).sum::<f32>();
                            if d2 < radius * radius {
                                let w = s.opacity(j) as f64;
                                pts.push((q.map(|x| x as f64), w));
                                w_sum += w;
                                for a in 0..3 {
                                    mean[a] += w * q[a] as f64;
                                }
                            }
                        }
                    }
                }
            }
        }
        if pts.len() < 8 {
            continue;
        }
        mean = mean.map(|m| m / w_sum.max(1e-12));
        let mut cov = [[0.0f64; 3]; 3];
        for (q, w) in &pts {
            let d = [q[0] - mean[0], q[1] - mean[1], q[2] - mean[2]];
            for a in 0..3 {
                for b in 0..3 {
                    cov[a][b] += w * d[a] * d[b];
                }
            }
        }
        let (vals, vecs) = jacobi_eigen(cov);
        let order = {
            let mut o = [0, 1, 2];
            o.sort_by(|&a, &b| vals[a].total_cmp(&vals[b]));
            o
        };
        // Flat: the smallest spread well below the middle one.
        if vals[order[0]] > flat_ratio * vals[order[1]] {
            continue;
        }
        *target = Some([vecs[0][order[0]], vecs[1][order[0]], vecs[2][order[0]]]);
    }
    turn_all(s, &targets, "their neighbourhood's plane");
}

/// Where the normals are turned to.
enum Mode {
    Truth(scene_readme::SceneReadme, f64),
    Consensus { data: PathBuf, min_weight: f64 },
    Plane { radius: f32, flat_ratio: f64 },
}

fn adjust(s: &mut Surfels, mode: &Mode, window: usize, filter: f32, two_sided: bool) -> anyhow::Result<()> {
    match mode {
        Mode::Truth(readme, snap) => to_truth(s, readme, *snap),
        Mode::Consensus { data, min_weight } => consensus(s, data, *min_weight, two_sided, window, filter)?,
        Mode::Plane { radius, flat_ratio } => flatten(s, *radius, *flat_ratio),
    }
    Ok(())
}

/// Eigen-decomposition of a symmetric 3 × 3 matrix by Jacobi sweeps: (values, columns).
fn jacobi_eigen(mut a: [[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _ in 0..50 {
        let (mut p, mut q, mut big) = (0, 1, 0.0);
        for (i, j) in [(0, 1), (0, 2), (1, 2)] {
            if a[i][j].abs() > big {
                (p, q, big) = (i, j, a[i][j].abs());
            }
        }
        if big < 1e-18 {
            break;
        }
        let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
        let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
        let t = if theta == 0.0 { 1.0 } else { t };
        let c = 1.0 / (t * t + 1.0).sqrt();
        let s = t * c;
        let mut j = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        j[p][p] = c;
        j[q][q] = c;
        j[p][q] = s;
        j[q][p] = -s;
        // a ← Jᵀ a J, v ← v J
        let mul = |x: [[f64; 3]; 3], y: [[f64; 3]; 3]| {
            let mut r = [[0.0; 3]; 3];
            for i in 0..3 {
                for k in 0..3 {
                    r[i][k] = (0..3).map(|m| x[i][m] * y[m][k]).sum();
                }
            }
            r
        };
        let jt = [[j[0][0], j[1][0], j[2][0]], [j[0][1], j[1][1], j[2][1]], [j[0][2], j[1][2], j[2][2]]];
        a = mul(mul(jt, a), j);
        v = mul(v, j);
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// Quaternion (w, x, y, z) of the rotation whose columns are `cols` ([t_u, t_v, n]).
fn quat_from_columns(cols: [[f64; 3]; 3]) -> [f32; 4] {
    // m[r][c] = cols[c][r]
    let m = |r: usize, c: usize| cols[c][r];
    let tr = m(0, 0) + m(1, 1) + m(2, 2);
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [0.25 * s, (m(2, 1) - m(1, 2)) / s, (m(0, 2) - m(2, 0)) / s, (m(1, 0) - m(0, 1)) / s]
    } else if m(0, 0) > m(1, 1) && m(0, 0) > m(2, 2) {
        let s = (1.0 + m(0, 0) - m(1, 1) - m(2, 2)).sqrt() * 2.0;
        [(m(2, 1) - m(1, 2)) / s, 0.25 * s, (m(0, 1) + m(1, 0)) / s, (m(0, 2) + m(2, 0)) / s]
    } else if m(1, 1) > m(2, 2) {
        let s = (1.0 + m(1, 1) - m(0, 0) - m(2, 2)).sqrt() * 2.0;
        [(m(0, 2) - m(2, 0)) / s, (m(0, 1) + m(1, 0)) / s, 0.25 * s, (m(1, 2) + m(2, 1)) / s]
    } else {
        let s = (1.0 + m(2, 2) - m(0, 0) - m(1, 1)).sqrt() * 2.0;
        [(m(1, 0) - m(0, 1)) / s, (m(0, 2) + m(2, 0)) / s, (m(1, 2) + m(2, 1)) / s, 0.25 * s]
    };
    q.map(|x| x as f32)
}

/// The number in environment variable `name`, or `default` when it is unset; anything else
/// that does not parse is an error naming the variable.
fn env_number(name: &str, default: f64) -> anyhow::Result<f64> {
    match std::env::var(name) {
        Ok(v) => v.parse().with_context(|| format!("{name}={v}: not a number")),
        Err(_) => Ok(default),
    }
}
