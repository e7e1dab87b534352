//! Diagnostic: how noisy is the per-surfel rendering equation the albedo is fitted to? Renders
//! the test views' PBR image (linear) from the run's surfels, materials and light with the
//! incident cache traced under two seeds (11 and 12, or `SEEDS=a,b`; each refresh draws new
//! Fibonacci rotations), and reports, over the GT mask, the relative per-pixel difference
//! between the two: its RMS / √2 is the noise of one cache refresh, which the albedo tracks
//! between refreshes.
//!
//!     cargo run --release --example probe_cache_noise -- RUN DATA

#[path = "common/probe_run.rs"]
mod probe_run;

use anyhow::Context;
use radiogs::io::dataset::{Dataset, Split};
use radiogs::pbr_scene::PbrScene;

fn decode(c: f32) -> f64 {
    radiogs::io::image::srgb_to_linear(c) as f64
}

fn main() -> anyhow::Result<()> {
    let probe_run::ProbeRun { run, data, cfg, extent, surfels, back_faces } =
        probe_run::from_args("probe_cache_noise")?;
    let env = radiogs::envmap::EnvMap::load(&run.join("envmap.exr"))?;
    let start = cfg.ray_start(extent);
    let factor = radiogs::train::inverse::sample_factor(&cfg);
    let seeds: Vec<u64> = match std::env::var("SEEDS") {
        Ok(v) => v.split(',').map(|x| x.trim().parse()).collect::<Result<_, _>>().context("SEEDS")?,
        Err(_) => vec![11, 12],
    };
    if seeds.len() != 2 {
        anyhow::bail!("SEEDS: {} seeds given, the probe compares exactly two (e.g. SEEDS=11,12)", seeds.len());
    }
    let scenes: Vec<PbrScene> = seeds
        .iter()
        .map(|&seed| {
            let mut s = PbrScene::new(
                surfels.clone(),
                env.clone(),
                cfg.pbr_samples,
                start,
                cfg.window,
                factor,
                seed,
                back_faces.clone(),
            );
            s.specular = cfg.specular;
            s.filter_inv_square = cfg.filter_inv_square;
            s
        })
        .collect();
    let ds = Dataset::open(&data)?;
    let (mut sum_rel2, mut sum_rel2_ind, mut pixels) = (0.0f64, 0.0f64, 0usize);
    for view in ds.views(Split::Test) {
        let cam = &view.camera;
        let gt = view.load_image()?;
        let mask: Vec<f32> =
            gt.data.chunks_exact(gt.channels).map(|px| if gt.channels == 4 { px[3] } else { 1.0 }).collect();
        let imgs: Vec<_> = scenes.iter().map(|s| s.render(cam, [0.0; 3])).collect();
        for p in 0..mask.len() {
            if mask[p] < 0.99 || imgs[0].alpha[p] < 0.99 {
                continue;
            }
            let lum = |c: [f32; 3]| (0..3).map(|k| decode(c[k])).sum::<f64>() / 3.0;
            let ind = |c: [f32; 3]| (c[0] + c[1] + c[2]) as f64 / 3.0;
            let (a, b) = (lum(imgs[0].pbr[p]), lum(imgs[1].pbr[p]));
            if a + b > 1e-3 {
                sum_rel2 += ((a - b) / (0.5 * (a + b))).powi(2);
            }
            let (a, b) = (ind(imgs[0].indirect[p]), ind(imgs[1].indirect[p]));
            if a + b > 1e-3 {
                sum_rel2_ind += ((a - b) / (0.5 * (a + b))).powi(2);
            }
            pixels += 1;
        }
    }
    let n = pixels.max(1) as f64;
    println!(
        "{pixels} covered pixels, S = {}: relative noise of one refresh, PBR {:.4}, its indirect part {:.4}",
        cfg.pbr_samples,
        (sum_rel2 / n / 2.0).sqrt(),
        (sum_rel2_ind / n / 2.0).sqrt()
    );
    Ok(())
}
