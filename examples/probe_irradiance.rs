//! Diagnostic: what the per-surfel shading gets wrong, per material and face, for every
//! surfel within 15 mm of its nearest true object and facing the way that surface does.
//!
//! 1. Visibility: each cached direction (above the true surface) re-tested against all the
//!    true objects from the surfel's foot point on the true surface. The cached transmittance
//!    where the truth is blocked (a leak: the indirect light a ray delivers is scaled by 1 − T,
//!    so leaks make the indirect light short and the direct light bright), and 1 − T where the
//!    truth is free (false shadow); blocked rays also by distance to the true hit.
//! 2. Direct irradiance (linear RGB, opacity-weighted mean) under the run's `envmap.exr` (else
//!    the dataset's training env at the run's env size), from the shader's own estimate down to the truth, one change
//!    at a time: ours (cached directions and transmittance, our normal, the env box-filtered as
//!    the shader reads it) → the env point-sampled → exact visibility (dense directions about
//!    our normal with the shader's 10° floor) → no floor → the true normal (the truth); with
//!    the faces' opacity-weighted mean normal and mean tilt from the true one.
//! 3. The normals again, by distance from the foot point to the nearest other object (a crease
//!    or contact), with the centres' mean signed distance to the true surface.
//!
//!     cargo run --release --example probe_irradiance -- RUN DATA
//!
//! `SKIP_MARGIN=m` overrides the run's `ray_skip_margin` (× extent; 0 = off).

#[path = "common/probe_run.rs"]
mod probe_run;
#[path = "common/scene_readme.rs"]
mod scene_readme;

use radiogs::pbr_scene::PbrScene;
use radiogs::shade::sampling::{ElevationFloor, MIN_ELEVATION_DEG, fibonacci_hemisphere};
use std::collections::BTreeMap;

#[derive(Default, Clone, Copy)]
struct Tally {
    surfels: usize,
    free: usize,
    blocked: usize,
    /// Σ T over truly blocked rays.
    leaked: f64,
    /// Σ (1 − T) over truly free rays.
    shadowed: f64,
    /// Blocked rays with T > 0.5.
    leaks: usize,
    /// Free rays with T < 0.5.
    false_blocks: usize,
}

impl Tally {
    fn merge(&mut self, o: &Tally) {
        let Tally { surfels, free, blocked, leaked, shadowed, leaks, false_blocks } = *o;
        self.surfels += surfels;
        self.free += free;
        self.blocked += blocked;
        self.leaked += leaked;
        self.shadowed += shadowed;
        self.leaks += leaks;
        self.false_blocks += false_blocks;
    }
    fn add_ray(&mut self, blocked: bool, t: f64) {
        if blocked {
            self.blocked += 1;
            self.leaked += t;
            self.leaks += (t > 0.5) as usize;
        } else {
            self.free += 1;
            self.shadowed += 1.0 - t;
            self.false_blocks += (t < 0.5) as usize;
        }
    }
}

fn main() -> anyhow::Result<()> {
    let probe_run::ProbeRun { run, data, cfg, extent, surfels, back_faces, .. } =
        probe_run::from_args("probe_irradiance")?;
    let readme = scene_readme::load(&data)?;
    let env_path = readme.train_env_path(&data);
    let run_env = run.join("envmap.exr");
    // Without a recovered light, the dataset's at the run's env size (as `oracle_materials`).
    let env = if run_env.is_file() {
        radiogs::envmap::EnvMap::load(&run_env)?
    } else {
        radiogs::envmap::EnvMap::load(&env_path)?.resample(2 * cfg.env_height, cfg.env_height)
    };
    let shader_env = env.box_downsample(radiogs::train::inverse::sample_factor(&cfg));
    let start = cfg.ray_start(extent);
    let scene = PbrScene::new(surfels, env.clone(), cfg.pbr_samples, start, cfg.window, 1, cfg.seed, back_faces);
    println!("env {} × {} (shader reads {} × {})", env.width, env.height, shader_env.width, shader_env.height);
    let mut irradiance: BTreeMap<String, (f64, [[f64; 3]; STEPS])> = BTreeMap::new();
    // Per face: Σ opacity · our normal, Σ opacity · tilt from the true normal (degrees).
    let mut normals: BTreeMap<String, ([f64; 3], f64)> = BTreeMap::new();
    // Per face and band of distance from the foot point to the nearest other object (a
    // crease or contact): Σ opacity, Σ opacity · our normal, Σ opacity · tilt.
    let crease_edges = [0.0, 0.05, 0.1, 0.2, 0.4, f64::INFINITY];
    let mut by_crease: BTreeMap<(String, usize), CreaseBand> = BTreeMap::new();
    let mut dense = vec![[0.0f32; 3]; 1024];
    probe_run::print_cache(scene.surfels.len(), scene.cache.samples, start);
    let ns = scene.cache.samples;
    let mut by_material: BTreeMap<String, Tally> = BTreeMap::new();
    // Blocked rays by distance to the true hit (scene units).
    let edges = [0.0, 0.05, 0.1, 0.2, 0.5, 1.0, f64::INFINITY];
    let mut by_distance = vec![(0usize, 0.0f64); edges.len() - 1];
    let mut skipped = 0usize;
    for i in 0..scene.surfels.len() {
        let p = scene.surfels.means[i].map(|x| x as f64);
        let k = scene_readme::nearest(&readme.objects, p);
        let o = &readme.objects[k];
        let d = o.sdf(p);
        let e = 1e-5;
        let mut grad = [0.0f64; 3];
        for a in 0..3 {
            let mut q = p;
            q[a] += e;
            grad[a] = (o.sdf(q) - d) / e;
        }
        let gl = (grad[0] * grad[0] + grad[1] * grad[1] + grad[2] * grad[2]).sqrt().max(1e-12);
        let true_n = grad.map(|g| g / gl);
        let n = scene.surfels.normal(i).map(|x| x as f64);
        let facing = n[0] * true_n[0] + n[1] * true_n[1] + n[2] * true_n[2];
        if d.abs() > 0.015 || facing < 0.7 {
            skipped += 1;
            continue;
        }
        let foot = [0, 1, 2].map(|a| p[a] - d * true_n[a] + 1e-6 * true_n[a]);
        // The face: the true normal's dominant axis (a box's inner and outer sides differ).
        let axis = (0..3).max_by(|&a, &b| true_n[a].abs().total_cmp(&true_n[b].abs())).unwrap_or(2);
        let face = format!("{}{}", if true_n[axis] < 0.0 { '-' } else { '+' }, ['x', 'y', 'z'][axis]);
        let name = format!("{} ({} {face})", o.material, o.object);
        let weight = scene.surfels.opacity(i) as f64;
        let mut steps = [[0.0f64; 3]; STEPS];
        let w = scene.cache.weight as f64;
        for q in 0..ns {
            let d = scene.cache.dirs[i * ns + q];
            let cos = (n[0] * d[0] as f64 + n[1] * d[1] as f64 + n[2] * d[2] as f64).max(0.0);
            let t = scene.cache.visibility[i * ns + q] as f64;
            let (filtered, point) = (shader_env.lookup(d), env.lookup(d));
            for c in 0..3 {
                steps[0][c] += filtered[c] as f64 * t * cos * w;
                steps[1][c] += point[c] as f64 * t * cos * w;
            }
        }
        let free = |d: [f64; 3]| readme.objects.iter().all(|ob| ob.ray_entry(foot, d).is_none());
        let n32 = n.map(|x| x as f32);
        // Exact visibility about our normal: the shader's floor, then none; then the true normal.
        for (step, normal, floor_deg) in
            [(2, n32, MIN_ELEVATION_DEG), (3, n32, 0.0), (4, true_n.map(|x| x as f32), 0.0)]
        {
            let dw = fibonacci_hemisphere(normal, 0.0, floor_deg, ElevationFloor::Spread, &mut dense);
            for d in &dense {
                let dd = d.map(|x| x as f64);
                let cos = (normal[0] * d[0] + normal[1] * d[1] + normal[2] * d[2]).max(0.0) as f64;
                // The true surface blocks what lies below it.
                if dd[0] * true_n[0] + dd[1] * true_n[1] + dd[2] * true_n[2] <= 0.0 || !free(dd) {
                    continue;
                }
                let l = env.lookup(*d);
                for c in 0..3 {
                    steps[step][c] += l[c] as f64 * cos * dw;
                }
            }
        }
        let nm = normals.entry(name.clone()).or_insert(([0.0; 3], 0.0));
        for a in 0..3 {
            nm.0[a] += weight * n[a];
        }
        nm.1 += weight * facing.clamp(-1.0, 1.0).acos().to_degrees();
        let crease = (0..readme.objects.len())
            .filter(|&j| j != k)
            .map(|j| readme.objects[j].sdf(foot))
            .fold(f64::INFINITY, f64::min);
        let band = crease_edges.windows(2).position(|w| crease >= w[0] && crease < w[1]).unwrap_or(0);
        let c = by_crease.entry((name.clone(), band)).or_insert((0.0, [0.0; 3], 0.0, 0.0));
        c.0 += weight;
        c.3 += weight * d;
        for a in 0..3 {
            c.1[a] += weight * n[a];
        }
        c.2 += weight * facing.clamp(-1.0, 1.0).acos().to_degrees();
        let entry = irradiance.entry(name.clone()).or_insert((0.0, [[0.0; 3]; STEPS]));
        entry.0 += weight;
        for (acc, s) in entry.1.iter_mut().zip(&steps) {
            for c in 0..3 {
                acc[c] += weight * s[c];
            }
        }
        let tally = by_material.entry(name).or_default();
        tally.surfels += 1;
        for q in 0..ns {
            let dir = scene.cache.dirs[i * ns + q].map(|x| x as f64);
            if dir[0] * true_n[0] + dir[1] * true_n[1] + dir[2] * true_n[2] <= 0.0 {
                continue;
            }
            let hit = readme.objects.iter().filter_map(|ob| ob.ray_entry(foot, dir)).fold(f64::INFINITY, f64::min);
            let t = scene.cache.visibility[i * ns + q] as f64;
            tally.add_ray(hit.is_finite(), t);
            if hit.is_finite() {
                let b = edges.windows(2).position(|w| hit >= w[0] && hit < w[1]).unwrap_or(edges.len() - 2);
                by_distance[b].0 += 1;
                by_distance[b].1 += t;
            }
        }
    }
    println!("{skipped} surfels skipped (more than 15 mm off their nearest object or facing away from it)");
    println!(
        "material (object) | surfels | rays above the true surface | truly blocked | mean T where blocked | leaks T > 0.5 (of blocked) | mean 1 − T where free | false blocks T < 0.5 (of free)"
    );
    let mut all = Tally::default();
    for (name, t) in &by_material {
        print_row(name, t);
        all.merge(t);
    }
    print_row("all", &all);
    println!("distance to the true hit | blocked rays | mean T (leaked)");
    for (k, (count, sum)) in by_distance.iter().enumerate() {
        if *count > 0 {
            println!("[{:.2}, {:.2}) | {} | {:.3}", edges[k], edges[k + 1], count, sum / *count as f64);
        }
    }
    println!(
        "direct irradiance (RGB, opacity-weighted) | ours | env point-sampled | exact visibility | no 10° floor | true normal = truth | ours / truth | mean normal (opacity-weighted) | mean tilt °"
    );
    for (name, (wsum, steps)) in &irradiance {
        let m = |s: &[f64; 3]| s.map(|x| x / wsum.max(1e-12));
        let cells: Vec<String> = steps.iter().map(m).map(|v| format!("{:.3} {:.3} {:.3}", v[0], v[1], v[2])).collect();
        let ratio = [0, 1, 2].map(|c| steps[0][c] / steps[STEPS - 1][c].max(1e-12));
        let (nsum, tilt) = normals.get(name).copied().unwrap_or_default();
        let nl = (nsum[0] * nsum[0] + nsum[1] * nsum[1] + nsum[2] * nsum[2]).sqrt().max(1e-12);
        println!(
            "{name} | {} | {:.3} {:.3} {:.3} | {:+.3} {:+.3} {:+.3} | {:.1}",
            cells.join(" | "),
            ratio[0],
            ratio[1],
            ratio[2],
            nsum[0] / nl,
            nsum[1] / nl,
            nsum[2] / nl,
            tilt / wsum.max(1e-12)
        );
    }
    println!(
        "face | distance to the nearest other object | Σ opacity | mean normal | mean tilt ° | mean signed distance of the centres (mm, + outside)"
    );
    for ((name, band), (w, nsum, tilt, dsum)) in &by_crease {
        if *w < 50.0 {
            continue;
        }
        let nl = (nsum[0] * nsum[0] + nsum[1] * nsum[1] + nsum[2] * nsum[2]).sqrt().max(1e-12);
        println!(
            "{name} | [{:.2}, {:.2}) | {:.0} | {:+.3} {:+.3} {:+.3} | {:.1} | {:+.1}",
            crease_edges[*band],
            crease_edges[band + 1],
            w,
            nsum[0] / nl,
            nsum[1] / nl,
            nsum[2] / nl,
            tilt / w,
            1000.0 * dsum / w
        );
    }
    Ok(())
}

/// Σ opacity, Σ opacity · normal, Σ opacity · tilt (degrees), Σ opacity · signed distance.
type CreaseBand = (f64, [f64; 3], f64, f64);

/// Steps of the irradiance table, from the shader's estimate to the truth.
const STEPS: usize = 5;

fn print_row(name: &str, t: &Tally) {
    let rays = (t.free + t.blocked).max(1) as f64;
    println!(
        "{name} | {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3}",
        t.surfels,
        t.free + t.blocked,
        t.blocked as f64 / rays,
        t.leaked / t.blocked.max(1) as f64,
        t.leaks as f64 / t.blocked.max(1) as f64,
        t.shadowed / t.free.max(1) as f64,
        t.false_blocks as f64 / t.free.max(1) as f64,
    );
}
