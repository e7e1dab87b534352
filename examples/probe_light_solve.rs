//! Diagnostic: can the light be solved for directly if surfaces of one colour share one
//! albedo? Per surfel the observed diffuse radiance is L_i = a_c(i) ⊙ (A_i·E + B_i) with A_i the
//! cached cosine-weighted visibility binned into the texels of a coarse 16 × 8 env E, B_i the
//! cached indirect light, and c(i) a cluster of surfels (k-means on the log chromaticity of
//! their radiance). Solved by alternating least squares (cluster albedo in closed form, E by a
//! smoothed linear solve per channel; residuals relative to L), then compared with the
//! dataset's light like `eval` (`compare_light`, no albedo scale). The specular lobe is left out.
//!
//!     cargo run --release --example probe_light_solve -- RUN DATA [K]
//!
//! Settings by environment variable:
//! - `OBS=pixels`: L_i is the blend-weighted mean of the training pixels the surfel is
//!   composited into (raster backward with the linear pixel colours as the feature gradient),
//!   instead of its SH colour averaged over the training cameras in front of it; rows are
//!   weighted by the surfel's total blend weight instead of opacity × area.
//! - `CLUSTER=truth`: clusters are the true materials (nearest object of `README.json`).
//! - `INIT=truth`: start at the true light and material albedo (needs `CLUSTER=truth`) and
//!   print the loss and the per-material terms there; `ITERS=0` stops at the truth.
//! - `ITERS=n` (60), `SMOOTH=λ` (1e-3, the env's smoothness weight relative to the data).
//! - `DUMP=file.csv`: one row per surfel (position, normal, opacity, weight, both radiances,
//!   indirect term, sky term, nearest object and its signed distance).
//! - `SAVE_LIGHT=file.exr`: the solved 16 × 8 light.
//!
//! Finding (BENCHMARKS.md, session 29): on cornell even the true clusters do not give the light
//! back; the fit is flat along albedo × s, light ÷ s per direction and channel.
#[path = "common/blend_weights.rs"]
mod blend_weights;
#[path = "common/scene_readme.rs"]
mod scene_readme;

use anyhow::Context;
use radiogs::envmap::EnvMap;
use radiogs::io::dataset::{Dataset, Split};
use radiogs::pbr_scene::PbrScene;
use radiogs::shade::brdf::diffuse_weight;
use radiogs::shade::incident::decode;
use std::path::PathBuf;

const W: usize = 16;
const H: usize = 8;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(args.len() >= 3, "usage: probe_light_solve RUN DATA [K]");
    let (run, data) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]));
    let k: usize = args.get(3).map(|s| s.parse()).transpose().context("K: not a whole number")?.unwrap_or(6);
    anyhow::ensure!(k >= 1, "K must be at least 1");
    let smooth: f64 = std::env::var("SMOOTH").ok().map(|s| s.parse()).transpose()?.unwrap_or(1e-3);
    let scene = PbrScene::from_run(&run)?.context("no envmap")?;
    let ds = Dataset::open(&data)?;
    let readme = scene_readme::load(&data)?;
    let gt_env = EnvMap::load(&readme.train_env_path(&data))?;
    let centres: Vec<[f32; 3]> = ds.views(Split::Train).iter().map(|v| v.camera.position().to_array()).collect();
    let s = &scene.surfels;
    let cache = &scene.cache;
    let ns = cache.samples;
    let grid = EnvMap::constant(W, H, [1.0; 3]);
    let scale = cache.weight as f64 / std::f64::consts::PI;
    // Per surfel: observed radiance / Lambert weight, binned sky term, indirect term, weight.
    struct Row {
        l: [f64; 3],
        l_sh: [f64; 3],
        a: Vec<(usize, f64)>,
        b: [f64; 3],
        w: f64,
        owner: usize,
    }
    // OBS=pixels: each surfel's observed radiance is the blend-weighted mean of the (linear)
    // training pixels it is composited into, Σ_p w_ip GT_p / Σ_p w_ip, from the raster
    // backward with the pixel colours as the feature gradient.
    let pixel_obs: Option<Vec<[f64; 4]>> = if std::env::var("OBS").as_deref() == Ok("pixels") {
        use radiogs::raster::{Outputs, RasterSettings};
        let settings = RasterSettings {
            window: scene.window,
            filter_inv_square: scene.filter_inv_square,
            two_sided: false,
            outputs: Outputs { colour: true, ..Outputs::none() },
            ..RasterSettings::default()
        };
        let mut blend = blend_weights::BlendSums::new(s);
        for view in ds.views(Split::Train) {
            let img = view.load_image()?;
            blend.add_view(s, &view.camera, &settings, |_| {
                let mut v = vec![0.0f32; img.pixel_count() * 4];
                for p in 0..img.pixel_count() {
                    if img.data[p * 4 + 3] > 0.99 {
                        for c in 0..3 {
                            v[p * 4 + c] = radiogs::io::image::srgb_to_linear(img.data[p * 4 + c]);
                        }
                        v[p * 4 + 3] = 1.0;
                    }
                }
                Ok(v)
            })?;
        }
        let acc = blend.sums;
        Some(acc)
    } else {
        None
    };
    let mut rows = Vec::new();
    let mut index = Vec::new();
    for i in 0..s.len() {
        let op = s.opacity(i);
        if op < 0.3 {
            continue;
        }
        let n = s.normal(i);
        let mu = s.means[i];
        let (mut sum, mut count) = ([0.0f64; 3], 0);
        for o in &centres {
            let d = [mu[0] - o[0], mu[1] - o[1], mu[2] - o[2]];
            let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let ndd = d[0] * n[0] + d[1] * n[1] + d[2] * n[2];
            if ndd >= 0.0 {
                continue;
            }
            let c = radiogs::sh::eval(&s.sh[i], s.sh_degree, [d[0] / len, d[1] / len, d[2] / len]);
            let wgt = diffuse_weight((-ndd / len) as f64, 0.6).0;
            for ch in 0..3 {
                sum[ch] += decode(c[ch]) as f64 / wgt;
            }
            count += 1;
        }
        if count == 0 {
            continue;
        }
        let mut l = sum.map(|x| x / count as f64);
        let l_sh = l;
        let mut wt = op as f64 * (s.scale(i)[0] * s.scale(i)[1]) as f64;
        if let Some(obs) = &pixel_obs {
            let o = obs[i];
            if o[3] < 1.0 {
                continue; // blended into less than one pixel's worth
            }
            let kd = diffuse_weight(0.8, 0.6).0;
            l = [o[0] / o[3] / kd, o[1] / o[3] / kd, o[2] / o[3] / kd];
            wt = o[3];
        }
        let mut bins = vec![0.0f64; W * H];
        let mut b = [0.0f64; 3];
        for q in i * ns..(i + 1) * ns {
            let d = cache.dirs[q];
            let cos = (d[0] * n[0] + d[1] * n[1] + d[2] * n[2]).max(0.0) as f64;
            if cos <= 0.0 {
                continue;
            }
            let (x, y) = grid.dir_to_pixel(d);
            let (xi, yi) = ((x as usize).min(W - 1), (y as usize).min(H - 1));
            bins[yi * W + xi] += scale * cos * cache.visibility[q] as f64;
            for ch in 0..3 {
                b[ch] += scale * cos * cache.indirect[q][ch] as f64;
            }
        }
        let a: Vec<(usize, f64)> = bins.iter().enumerate().filter(|(_, v)| **v > 0.0).map(|(j, v)| (j, *v)).collect();
        let sc = s.scale(i);
        let owner = scene_readme::nearest(&readme.objects, mu.map(|x| x as f64));
        index.push(i);
        let _ = sc;
        rows.push(Row { l, l_sh, a, b, w: wt, owner });
    }
    anyhow::ensure!(!rows.is_empty(), "{}: no surfel with opacity ≥ 0.3 is seen by a training camera", run.display());
    println!("{} surfels used", rows.len());
    if let Ok(path) = std::env::var("DUMP") {
        let mut out = String::from("i,x,y,z,nx,ny,nz,op,w,lr,lg,lb,sr,sg,sb,br,bg,bb,sky,owner,sdf\n");
        for (q, r) in rows.iter().enumerate() {
            let i = index[q];
            let m = s.means[i];
            let n = s.normal(i);
            let sky: f64 = r.a.iter().map(|x| x.1).sum();
            let sdf = readme.objects[r.owner].sdf(m.map(|x| x as f64));
            out += &format!(
                "{i},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
                m[0],
                m[1],
                m[2],
                n[0],
                n[1],
                n[2],
                s.opacity(i),
                r.w,
                r.l[0],
                r.l[1],
                r.l[2],
                r.l_sh[0],
                r.l_sh[1],
                r.l_sh[2],
                r.b[0],
                r.b[1],
                r.b[2],
                sky,
                readme.objects[r.owner].object,
                sdf
            );
        }
        radiogs::io::atomic::write_atomic(std::path::Path::new(&path), out.as_bytes())?;
    }
    // k-means on log chromaticity.
    let feat: Vec<[f64; 2]> = rows
        .iter()
        .map(|r| {
            let g = r.l[1].max(1e-4);
            [(r.l[0].max(1e-4) / g).ln(), (r.l[2].max(1e-4) / g).ln()]
        })
        .collect();
    // k-means++ init with a fixed seed, weighted by surfel weight.
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
    let mut centres_k: Vec<[f64; 2]> = vec![feat[rng.random_range(0..feat.len())]];
    while centres_k.len() < k {
        let dist: Vec<f64> = (0..feat.len())
            .map(|x| rows[x].w * centres_k.iter().map(|c| d2(feat[x], *c)).fold(f64::MAX, f64::min))
            .collect();
        let total: f64 = dist.iter().sum();
        if total <= 0.0 {
            break; // every remaining surfel sits on a centre already
        }
        let mut t = rng.random_range(0.0..total);
        let mut pick = 0;
        for (x, d) in dist.iter().enumerate() {
            t -= d;
            if t <= 0.0 {
                pick = x;
                break;
            }
        }
        centres_k.push(feat[pick]);
    }
    let k = centres_k.len();
    let mut cluster = vec![0usize; rows.len()];
    for _ in 0..50 {
        for (i, f) in feat.iter().enumerate() {
            cluster[i] = (0..k).min_by(|&x, &y| d2(*f, centres_k[x]).total_cmp(&d2(*f, centres_k[y]))).unwrap();
        }
        let mut acc = vec![[0.0f64; 3]; k];
        for (i, f) in feat.iter().enumerate() {
            let w = rows[i].w;
            acc[cluster[i]][0] += w * f[0];
            acc[cluster[i]][1] += w * f[1];
            acc[cluster[i]][2] += w;
        }
        for c in 0..k {
            if acc[c][2] > 0.0 {
                centres_k[c] = [acc[c][0] / acc[c][2], acc[c][1] / acc[c][2]];
            }
        }
    }
    let objects = &readme.objects;
    let mut k = k;
    if std::env::var("CLUSTER").as_deref() == Ok("truth") {
        let mut names: Vec<String> = objects.iter().map(|o| o.material.clone()).collect();
        names.sort();
        names.dedup();
        k = names.len();
        for (i, r) in rows.iter().enumerate() {
            cluster[i] = names.iter().position(|n| *n == objects[r.owner].material).unwrap();
        }
    }
    for c in 0..k {
        let mut per: Vec<(String, usize)> = Vec::new();
        for (i, r) in rows.iter().enumerate() {
            if cluster[i] != c {
                continue;
            }
            let name = &objects[r.owner].material;
            match per.iter_mut().find(|(n, _)| n == name) {
                Some(e) => e.1 += 1,
                None => per.push((name.clone(), 1)),
            }
        }
        per.sort_by(|x, y| y.1.cmp(&x.1));
        println!("cluster {c}: {:?}", per);
    }
    // Alternating least squares, per channel; relative residuals.
    let nb = W * H;
    let mut env = vec![[1.0f64; 3]; nb];
    let rw: Vec<[f64; 3]> = rows.iter().map(|r| r.l.map(|x| r.w / (x + 0.02).powi(2))).collect();
    let mut albedo = vec![[0.5f64; 3]; k];
    let from_truth = std::env::var("INIT").as_deref() == Ok("truth");
    if from_truth {
        let small = gt_env.resample(W, H);
        for p in 0..nb {
            env[p] = small.texels[p].map(|x| x as f64);
        }
        let mut names: Vec<String> = objects.iter().map(|o| o.material.clone()).collect();
        names.sort();
        names.dedup();
        for (c, name) in names.iter().enumerate() {
            if let scene_readme::BaseColor::Rgb(rgb) = readme.materials[name].base_color_linear {
                albedo[c] = rgb;
            }
        }
        let mut loss = 0.0;
        let total_w: f64 = rw.iter().map(|x| x[0] + x[1] + x[2]).sum::<f64>() / 3.0;
        for (i, r) in rows.iter().enumerate() {
            for ch in 0..3 {
                let sh: f64 = r.a.iter().map(|&(j, v)| v * env[j][ch]).sum::<f64>() + r.b[ch];
                loss += rw[i][ch] * (r.l[ch] - albedo[cluster[i]][ch] * sh).powi(2);
            }
        }
        println!("loss at the truth {:.5}", loss / total_w);
        for (c, name) in names.iter().enumerate() {
            let (mut lo, mut sky, mut ind, mut cnt) = ([0.0f64; 3], [0.0f64; 3], [0.0f64; 3], 0.0);
            for (i, r) in rows.iter().enumerate() {
                if cluster[i] != c {
                    continue;
                }
                cnt += 1.0;
                for ch in 0..3 {
                    lo[ch] += r.l[ch];
                    sky[ch] += r.a.iter().map(|&(j, v)| v * env[j][ch]).sum::<f64>();
                    ind[ch] += r.b[ch];
                }
            }
            let m = |v: [f64; 3]| v.map(|x| x / cnt);
            let (lo, sky, ind) = (m(lo), m(sky), m(ind));
            let pred: [f64; 3] = std::array::from_fn(|ch| albedo[c][ch] * (sky[ch] + ind[ch]));
            println!(
                "  {name}: observed {lo:.3?} predicted {pred:.3?} (direct irradiance/pi {sky:.3?}, indirect {ind:.3?})"
            );
        }
    }
    let iterations: usize = std::env::var("ITERS").ok().map(|s| s.parse()).transpose()?.unwrap_or(60);
    for it in 0..iterations {
        // Albedo per cluster.
        let mut num = vec![[0.0f64; 3]; k];
        let mut den = vec![[0.0f64; 3]; k];
        for (i, r) in rows.iter().enumerate() {
            for ch in 0..3 {
                let sh: f64 = r.a.iter().map(|&(j, v)| v * env[j][ch]).sum::<f64>() + r.b[ch];
                num[cluster[i]][ch] += rw[i][ch] * r.l[ch] * sh;
                den[cluster[i]][ch] += rw[i][ch] * sh * sh;
            }
        }
        for c in 0..k {
            for ch in 0..3 {
                albedo[c][ch] = if den[c][ch] > 0.0 { (num[c][ch] / den[c][ch]).clamp(0.03, 0.95) } else { 0.5 };
            }
        }
        // Env per channel: min Σ rw (L − a B − a A·E)² + smooth·Σ_i rw · |∇E|².
        let total_w: f64 = rw.iter().map(|x| x[0] + x[1] + x[2]).sum::<f64>() / 3.0;
        let mut loss = 0.0;
        for ch in 0..3 {
            let mut m = vec![0.0f64; nb * nb];
            let mut rhs = vec![0.0f64; nb];
            for (i, r) in rows.iter().enumerate() {
                let a = albedo[cluster[i]][ch];
                let w = rw[i][ch];
                let t = r.l[ch] - a * r.b[ch];
                for &(p, vp) in &r.a {
                    rhs[p] += w * a * vp * t;
                    for &(q, vq) in &r.a {
                        m[p * nb + q] += w * a * a * vp * vq;
                    }
                }
            }
            let lam = smooth * total_w;
            for y in 0..H {
                for x in 0..W {
                    let p = y * W + x;
                    let mut nbrs = vec![y * W + (x + 1) % W];
                    if y + 1 < H {
                        nbrs.push((y + 1) * W + x);
                    }
                    for q in nbrs {
                        m[p * nb + p] += lam;
                        m[q * nb + q] += lam;
                        m[p * nb + q] -= lam;
                        m[q * nb + p] -= lam;
                    }
                    m[p * nb + p] += 1e-6 * lam;
                }
            }
            let e = cholesky_solve(&m, &rhs, nb).context("solve")?;
            for p in 0..nb {
                env[p][ch] = e[p].max(1e-3);
            }
            for (i, r) in rows.iter().enumerate() {
                let a = albedo[cluster[i]][ch];
                let sh: f64 = r.a.iter().map(|&(j, v)| v * env[j][ch]).sum::<f64>() + r.b[ch];
                loss += rw[i][ch] * (r.l[ch] - a * sh).powi(2);
            }
        }
        if it % 10 == 9 || it == 0 {
            println!("iteration {}: weighted loss {:.5}", it + 1, loss / total_w);
        }
    }
    for c in 0..k {
        println!("cluster {c} albedo {:.3?}", albedo[c]);
    }
    let ours = EnvMap { width: W, height: H, texels: env.iter().map(|t| t.map(|x| x as f32)).collect() };
    if let Ok(path) = std::env::var("SAVE_LIGHT") {
        ours.save(std::path::Path::new(&path))?;
    }
    let cmp = radiogs::eval::compare_light(&ours, &gt_env, [1.0; 3]);
    println!("light error {:.3}", cmp.log_error);
    for l in &cmp.normals {
        let r: [f32; 3] = std::array::from_fn(|c| l.ours[c] / l.gt[c]);
        println!("  {} ours/gt {:.2?}", l.normal, r);
    }
    let run_env = &scene.env;
    let cmp = radiogs::eval::compare_light(run_env, &gt_env, [1.0; 3]);
    println!("the run's own light (unscaled) error {:.3}", cmp.log_error);
    for l in &cmp.normals {
        let r: [f32; 3] = std::array::from_fn(|c| l.ours[c] / l.gt[c]);
        println!("  {} ours/gt {:.2?}", l.normal, r);
    }
    Ok(())
}

fn d2(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)
}

fn cholesky_solve(m: &[f64], b: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0f64; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut s = m[i * n + j];
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            if i == j {
                if s <= 0.0 {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    let mut y = vec![0.0; n];
    for i in 0..n {
        let mut s = b[i];
        for k in 0..i {
            s -= l[i * n + k] * y[k];
        }
        y[i] = s / l[i * n + i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        let mut s = y[i];
        for k in i + 1..n {
            s -= l[k * n + i] * x[k];
        }
        x[i] = s / l[i * n + i];
    }
    Some(x)
}
