//! How much each surfel contributes to the training views (its largest blend weight w = α T
//! over every training pixel), and what dropping the surfels below a threshold does to the
//! test views (against the unpruned render) and to the relit frame's time.
//!
//! Usage: `cargo run --release --example probe_contribution -- RUN [OUT_RUN]` (with OUT_RUN:
//! a copy of RUN whose point_cloud.ply keeps the surfels with max weight ≥ $TAU, default 1/255).
use radiogs::raster::{self, blend_weights::BlendWeights};
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let Some(run) = args.get(1).map(std::path::PathBuf::from) else {
        anyhow::bail!("usage: probe_contribution RUN [OUT_RUN]");
    };
    let cfg = radiogs::eval::load_run_config(&run)?;
    let surfels = radiogs::eval::load_run_surfels(&run)?;
    let dataset = radiogs::io::dataset::Dataset::open_downscaled(&cfg.data, cfg.resolution)?;
    let settings = radiogs::bench::relight::relit_frame_settings(&cfg);
    let n = surfels.len();
    let mut max_w = vec![0f32; n];
    let mut sum_w = vec![0f64; n];
    let t0 = Instant::now();
    for view in &dataset.train {
        let bw = BlendWeights::compute(&surfels, &view.camera, &settings);
        for (&id, &w) in bw.ids.iter().zip(&bw.weights) {
            let i = id as usize;
            max_w[i] = max_w[i].max(w);
            sum_w[i] += w as f64;
        }
    }
    println!("{} training views, {n} surfels, weights in {:.1} s", dataset.train.len(), t0.elapsed().as_secs_f64());
    for th in [0.0f32, 1e-4, 1e-3, 1.0 / 255.0, 0.01, 0.02, 0.05, 0.1] {
        let below = max_w.iter().filter(|&&w| w <= th).count();
        println!("max weight ≤ {th:.4}: {below} surfels ({:.1} %)", 100.0 * below as f64 / n as f64);
    }
    let test_cams: Vec<_> = dataset.test.iter().map(|v| v.camera.clone()).collect();
    let over_white = |out: &raster::RenderOutput| -> Vec<[f32; 3]> {
        out.colour.iter().zip(&out.alpha).map(|(c, &a)| c.map(|v| v + (1.0 - a))).collect()
    };
    let full: Vec<Vec<[f32; 3]>> =
        test_cams.iter().map(|c| over_white(&raster::render(&surfels, c, &settings, None).0)).collect();
    let frame_cam = test_cams[0].scaled(400, 400);
    let time = |s: &radiogs::surfels::Surfels| {
        let mut t: Vec<f64> = (0..7)
            .map(|_| {
                let t = Instant::now();
                std::hint::black_box(raster::render(s, &frame_cam, &settings, None));
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        t.sort_by(f64::total_cmp);
        t[3]
    };
    for th in [1e-3f32, 1.0 / 255.0, 0.01, 0.02, 0.05] {
        let keep: Vec<bool> = max_w.iter().map(|&w| w >= th).collect();
        let mut pruned = surfels.clone();
        pruned.retain_mask(&keep);
        let mut psnr = Vec::new();
        let mut worst = 0f32;
        for (c, f) in test_cams.iter().zip(&full) {
            let p = over_white(&raster::render(&pruned, c, &settings, None).0);
            psnr.push(radiogs::loss::ssim::psnr(&p, f));
            for (a, b) in p.iter().zip(f) {
                for k in 0..3 {
                    worst = worst.max((a[k] - b[k]).abs());
                }
            }
        }
        let mean = psnr.iter().sum::<f32>() / psnr.len() as f32;
        let (tf, tp) = (time(&surfels), time(&pruned));
        println!(
            "τ {th:.4}: keep {} of {n}; test views vs unpruned: PSNR {mean:.2} dB (min {:.2}), max |Δ| {worst:.3}; 400² frame {tf:.1} → {tp:.1} ms",
            pruned.len(),
            psnr.iter().copied().fold(f32::INFINITY, f32::min)
        );
    }
    if let Some(out) = args.get(2).map(std::path::PathBuf::from) {
        let tau: f32 = std::env::var("TAU").ok().and_then(|s| s.parse().ok()).unwrap_or(1.0 / 255.0);
        let keep: Vec<bool> = max_w.iter().map(|&w| w >= tau).collect();
        let mut pruned = surfels.clone();
        pruned.retain_mask(&keep);
        std::fs::create_dir_all(&out)?;
        for f in ["config.toml"] {
            std::fs::copy(run.join(f), out.join(f))?;
        }
        radiogs::io::ply::write_ply(&out.join("point_cloud.ply"), &pruned)?;
        println!("wrote {} surfels to {}", pruned.len(), out.display());
    }
    Ok(())
}
