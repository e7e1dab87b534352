//! Diagnostic: where does a run's direct light in the shadows come from? Each surfel gets six
//! direct-irradiance estimates (luminance), one value per surfel, rasterised as features with
//! the run's settings and compared pixel by pixel with the true irradiance at the true surface
//! point each pixel sees (the true light box-filtered to 64 × 128 texels, exact visibility
//! against the scene's analytic objects, the true normal). The estimates, from the truth to the
//! shader's, change one thing at a time:
//! - the truth at the surfel's foot point on the true surface (what shading once per surfel and
//!   compositing costs by itself);
//! - the shader's estimator (its cached directions, the 10°-floor spiral's solid angle per
//!   sample) with the true light and the exact visibility, weighted by the true normal's cosine,
//!   then by ours (the directions, drawn about our normal, are the same);
//! - the same with the cached (traced) visibility: the shader under the true light;
//! - the same under the learned light;
//! - the learned light with the exact visibility and normal (texel sums).
//!
//! Printed per bin of the pixel's shadow depth (its visible share of the unoccluded direct
//! light), each ratio over the truth divided by the fully lit bin's (the learned light's scale is
//! free); beside them the per-pixel truth blurred by a Gaussian of σ = 1, 2, 3 px inside the
//! mask, as `tools/diag/direct_share.py` does. Needs a README.json object list (a `radiogs
//! synth` scene or `../shared/data`'s); VIEWS test views, 6 by default, about a minute on 2
//! cores. Session 72, synthetic spheres at the defaults, deep shadow (share < 0.2) / 0.2–0.5:
//! truth at the feet 1.55 / 1.03, the estimator 1.26 / 1.00 with the true normal's cosine and
//! 1.93 / 1.07 with ours, with the cached visibility 2.38 / 1.20, under the learned light 2.65 /
//! 1.31.
//!
//!     cargo run --release --example probe_shadow_blur -- RUN DATA [VIEWS]

#[path = "common/scene_readme.rs"]
mod scene_readme;

use anyhow::Context;
use radiogs::io::dataset::{Dataset, Split};
use radiogs::raster::{self, Features, Outputs, RasterSettings};
use radiogs::shade::sampling::MIN_ELEVATION_DEG;
use rayon::prelude::*;
use std::path::PathBuf;

const TABLE_HEIGHT: usize = 64;
const CHANNELS: usize = 6;
const BINS: [f64; 5] = [0.0, 0.2, 0.5, 0.8, 1.01];

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        anyhow::bail!("usage: probe_shadow_blur RUN DATA [VIEWS]");
    }
    let (run, data) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]));
    let nviews: usize = match args.get(3) {
        Some(v) => v.parse().with_context(|| format!("VIEWS: {v} is not a count"))?,
        None => 6,
    };
    let scene = radiogs::pbr_scene::PbrScene::from_run(&run)?
        .with_context(|| format!("{}: no envmap.exr (run the inverse stage first)", run.display()))?;
    let readme = scene_readme::load(&data)?;
    let true_env = radiogs::envmap::EnvMap::load(&readme.train_env_path(&data))?;
    let table = texel_table(&true_env);
    let objects = &readme.objects;

    // The true irradiance (luminance) at a surface point with normal n, and its unoccluded value.
    let irradiance = |p: [f64; 3], n: [f64; 3], table: &[([f64; 3], f64)]| -> (f64, f64) {
        let o = [0, 1, 2].map(|k| p[k] + 1e-4 * n[k]);
        let (mut lit, mut free) = (0.0, 0.0);
        for &(d, weight) in table {
            let cos = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
            if cos <= 0.0 {
                continue;
            }
            free += weight * cos;
            if !objects.iter().any(|obj| obj.ray_entry(o, d).is_some()) {
                lit += weight * cos;
            }
        }
        (lit, free)
    };
    // Foot point and true normal of a world point on its nearest object.
    let surface = |p: [f64; 3]| -> ([f64; 3], [f64; 3]) {
        let obj = &objects[scene_readme::nearest(objects, p)];
        let e = 1e-5;
        let d0 = obj.sdf(p);
        let g = [0, 1, 2].map(|k| {
            let mut q = p;
            q[k] += e;
            (obj.sdf(q) - d0) / e
        });
        let len = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt().max(1e-12);
        let n = g.map(|x| x / len);
        ([0, 1, 2].map(|k| p[k] - d0 * n[k]), n)
    };

    // Per surfel, four irradiance estimates (luminance): the truth at its foot point; the
    // shader's estimator (its cached directions, visibility and normal, the 10°-floor spiral's
    // per-sample solid angle) under the true light and under the learned one; the learned light
    // with the true visibility and normal at the foot point.
    let learned_table = texel_table(&scene.env);
    let learned_lum = |d: [f32; 3]| luminance(scene.env.lookup(d));
    let true_lum = |d: [f32; 3]| luminance(true_env.lookup(d));
    let cap = 2.0 * std::f64::consts::PI * (1.0 - MIN_ELEVATION_DEG.to_radians().sin());
    let s = &scene.surfels;
    let ns = scene.cache.samples;
    let per_surfel: Vec<f32> = (0..s.len())
        .into_par_iter()
        .flat_map_iter(|i| {
            let (foot, n) = surface(s.means[i].map(|x| x as f64));
            let truth = irradiance(foot, n, &table).0;
            let learned_true_vis = irradiance(foot, n, &learned_table).0;
            let nn = s.normal(i);
            let (mut under_true, mut under_learned, mut exact_vis, mut exact_vis_normal) = (0.0, 0.0, 0.0, 0.0);
            let o = [0, 1, 2].map(|k| foot[k] + 1e-4 * n[k]);
            for q in i * ns..(i + 1) * ns {
                let dir = scene.cache.dirs[q];
                let cos = (nn[0] * dir[0] + nn[1] * dir[1] + nn[2] * dir[2]).max(0.0) as f64;
                let weight = cos * scene.cache.visibility[q] as f64 * cap / ns as f64;
                under_true += true_lum(dir) * weight;
                under_learned += learned_lum(dir) * weight;
                // The same directions with the exact visibility from the foot point (our
                // normal; then the true normal).
                let dd = dir.map(|x| x as f64);
                let true_cos = n[0] * dd[0] + n[1] * dd[1] + n[2] * dd[2];
                if true_cos > 0.0 && !objects.iter().any(|obj| obj.ray_entry(o, dd).is_some()) {
                    exact_vis += true_lum(dir) * cos * cap / ns as f64;
                    exact_vis_normal += true_lum(dir) * true_cos * cap / ns as f64;
                }
            }
            [truth, under_true, under_learned, learned_true_vis, exact_vis, exact_vis_normal].map(|x| x as f32)
        })
        .collect();
    let settings = RasterSettings {
        window: scene.window,
        filter_inv_square: scene.filter_inv_square,
        two_sided: false,
        outputs: Outputs::none(),
        ..RasterSettings::default()
    };
    let ds = Dataset::open(&data)?;
    // Per bin: pixels, Σ per-pixel truth, Σ truth blurred at σ = 1, 2, 3 px, Σ each rasterised
    // estimate.
    let mut bins = vec![[0.0f64; 5 + CHANNELS]; BINS.len() - 1];
    for view in ds.views(Split::Test).iter().take(nviews) {
        let cam = &view.camera;
        let (w, h) = (cam.width as usize, cam.height as usize);
        let gt = view.load_image()?;
        let (out, _) = raster::render(s, cam, &settings, Some(Features { data: &per_surfel, channels: CHANNELS }));
        // Per pixel: the true surface point seen through its centre, and its irradiance.
        let truth: Vec<Option<(f64, f64)>> = (0..w * h)
            .into_par_iter()
            .map(|p| {
                let (o, d) = cam.ray((p % w) as f32 + 0.5, (p / w) as f32 + 0.5);
                let (o, d) = (o.to_array().map(|x| x as f64), d.to_array().map(|x| x as f64));
                let t = objects.iter().filter_map(|obj| obj.ray_entry(o, d)).fold(f64::INFINITY, f64::min);
                if !t.is_finite() || gt.data[p * 4 + 3] < 0.99 || out.alpha[p] < 0.99 {
                    return None;
                }
                let (foot, n) = surface([0, 1, 2].map(|k| o[k] + t * d[k]));
                Some(irradiance(foot, n, &table))
            })
            .collect();
        let lit: Vec<f64> = truth.iter().map(|t| t.map_or(0.0, |t| t.0)).collect();
        let mask: Vec<f64> = truth.iter().map(|t| if t.is_some() { 1.0 } else { 0.0 }).collect();
        let blurred: Vec<Vec<f64>> =
            [1.0, 2.0, 3.0].iter().map(|&sigma| masked_blur(&lit, &mask, w, h, sigma)).collect();
        for p in 0..w * h {
            let Some((l, free)) = truth[p] else { continue };
            let share = l / free.max(1e-12);
            let Some(b) = BINS.windows(2).position(|e| share >= e[0] && share < e[1]) else { continue };
            let row = &mut bins[b];
            row[0] += 1.0;
            row[1] += l;
            for k in 0..3 {
                row[2 + k] += blurred[k][p];
            }
            for c in 0..CHANNELS {
                row[5 + c] += (out.features[p * CHANNELS + c] / out.alpha[p]) as f64;
            }
        }
    }
    println!(
        "{}: surfels {}, views {nviews}; irradiance per surfel, rasterised, over the truth per pixel (÷ the lit bin's ratio)",
        run.display(),
        s.len()
    );
    println!(
        "shadow depth | pixels | truth blurred σ = 1 / 2 / 3 px | truth at feet | shader, true light | shader, learned light | learned light, true visibility | shader's directions, true light and visibility | the same, true normal"
    );
    let lit = *bins.last().expect("bins");
    let ratio =
        |row: &[f64; 5 + CHANNELS], k: usize| (row[k] / row[1].max(1e-12)) / (lit[k] / lit[1].max(1e-12)).max(1e-12);
    for (k, row) in bins.iter().enumerate() {
        println!(
            "[{:.1}, {:.1}) | {} | {:.3} / {:.3} / {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3}",
            BINS[k],
            BINS[k + 1].min(1.0),
            row[0],
            ratio(row, 2),
            ratio(row, 3),
            ratio(row, 4),
            ratio(row, 5),
            ratio(row, 6),
            ratio(row, 7),
            ratio(row, 8),
            ratio(row, 9),
            ratio(row, 10)
        );
    }
    Ok(())
}

/// The light box-filtered to TABLE_HEIGHT rows (`EnvMap::box_downsample`; a map whose height
/// TABLE_HEIGHT does not divide is taken as it is): (direction, luminance × solid angle) per
/// texel.
fn texel_table(env: &radiogs::envmap::EnvMap) -> Vec<([f64; 3], f64)> {
    let factor = if env.height % TABLE_HEIGHT == 0 && env.width % (env.height / TABLE_HEIGHT) == 0 {
        env.height / TABLE_HEIGHT
    } else {
        1
    };
    let grid = env.box_downsample(factor);
    let mut table = Vec::with_capacity(grid.width * grid.height);
    for j in 0..grid.height {
        for i in 0..grid.width {
            let lum = luminance(grid.texels[j * grid.width + i]);
            table.push((grid.texel_dir(i, j).map(|x| x as f64), lum * grid.texel_solid_angle(j) as f64));
        }
    }
    table
}

/// Rec. 709 luminance of a linear RGB radiance.
fn luminance(l: [f32; 3]) -> f64 {
    (0.2126 * l[0] + 0.7152 * l[1] + 0.0722 * l[2]) as f64
}

/// Gaussian blur of `v` restricted to `mask` (normalised convolution), separable.
fn masked_blur(v: &[f64], mask: &[f64], w: usize, h: usize, sigma: f64) -> Vec<f64> {
    let r = (3.0 * sigma).ceil() as isize;
    let kernel: Vec<f64> = (-r..=r).map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp()).collect();
    let pass = |src: &[f64], horizontal: bool| -> Vec<f64> {
        let mut dst = vec![0.0; w * h];
        for y in 0..h as isize {
            for x in 0..w as isize {
                let mut acc = 0.0;
                for (k, kv) in (-r..=r).zip(&kernel) {
                    let (u, t) = if horizontal { (x + k, y) } else { (x, y + k) };
                    if u >= 0 && t >= 0 && (u as usize) < w && (t as usize) < h {
                        acc += kv * src[t as usize * w + u as usize];
                    }
                }
                dst[y as usize * w + x as usize] = acc;
            }
        }
        dst
    };
    let num: Vec<f64> = v.iter().zip(mask).map(|(a, m)| a * m).collect();
    let (num, den) = (pass(&pass(&num, true), false), pass(&pass(mask, true), false));
    num.iter().zip(&den).zip(mask).map(|((n, d), m)| if *m > 0.0 { n / d.max(1e-12) } else { 0.0 }).collect()
}
