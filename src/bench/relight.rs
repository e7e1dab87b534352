//! `radiogs bench relight`: how fast a relit scene renders. A finetuned relit run renders by
//! plain rasterisation (SH colour, back faces culled): frames per second at several sizes. A
//! ray-traced relit frame needs the per-surfel traced visibility / indirect light under the
//! new map (once per light) and the per-surfel shading for the view (every frame): both timed.

use crate::raster::{self, Outputs, RasterSettings};
use std::path::PathBuf;
use std::time::Instant;

/// Time relit rendering of a run (a relit run, or any run after the inverse stage).
#[derive(clap::Args, Debug, Clone)]
pub struct RelightBenchArgs {
    /// Run folder.
    #[arg(long)]
    pub run: PathBuf,
    /// Square image sizes for the rasterised frames.
    #[arg(long, value_delimiter = ',', default_values_t = vec![200u32, 400, 800])]
    pub sizes: Vec<u32>,
    /// Frames per size (the median is reported).
    #[arg(long, default_value_t = 7, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1_000_000))]
    pub repeats: usize,
    /// Only the rasterised frames (skip the traced set-up; for profiling).
    #[arg(long)]
    pub raster_only: bool,
    /// Also time display frames that stop compositing once T < this (0: only exact frames),
    /// and report how far their pixels are from the exact frame's.
    #[arg(long, default_value_t = raster::DISPLAY_STOP)]
    pub display_stop: f32,
}

/// How a display frame's colours differ from the exact frame's, in 8-bit levels of the
/// displayed value (SH colour is display-encoded, clipped to [0, 1]).
struct FrameDifference {
    max_levels: f32,
    /// Pixels whose largest channel difference exceeds one level.
    over_one: usize,
    /// PSNR of the display frame against the exact one (∞ when equal).
    psnr: f64,
}

fn frame_difference(exact: &[[f32; 3]], shown: &[[f32; 3]]) -> FrameDifference {
    let clip = |v: &[[f32; 3]]| -> Vec<[f32; 3]> { v.iter().map(|c| c.map(|x| x.clamp(0.0, 1.0))).collect() };
    let (exact, shown) = (clip(exact), clip(shown));
    let (mut max_levels, mut over_one) = (0.0f32, 0usize);
    for (a, b) in exact.iter().zip(&shown) {
        let px = (0..3).map(|c| (a[c] - b[c]).abs() * 255.0).fold(0.0f32, f32::max);
        max_levels = max_levels.max(px);
        over_one += (px > 1.0) as usize;
    }
    FrameDifference { max_levels, over_one, psnr: crate::loss::ssim::psnr(&shown, &exact) as f64 }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// How a relit run's frame is rasterised: SH colour only, back faces culled (the surfels are
/// oriented), white background, the run's window and screen-space filter.
pub fn relit_frame_settings(cfg: &crate::train::config::TrainConfig) -> RasterSettings {
    RasterSettings {
        window: cfg.window,
        filter_inv_square: cfg.filter_inv_square,
        two_sided: false,
        background: [1.0; 3],
        outputs: Outputs::colour_only(),
        ..RasterSettings::default()
    }
}

pub fn run(args: &RelightBenchArgs) -> anyhow::Result<()> {
    let max_side = crate::io::dataset::MAX_IMAGE_SIDE;
    if let Some(bad) = args.sizes.iter().find(|&&s| s == 0 || s > max_side) {
        anyhow::bail!("--sizes {bad}: each size must be in 1..={max_side}");
    }
    let cfg = crate::eval::load_run_config(&args.run)?;
    let surfels = crate::eval::load_run_surfels(&args.run)?;
    let dataset = crate::io::dataset::Dataset::open_downscaled(&cfg.data, cfg.resolution)?;
    let Some(view) = dataset.test.first().or(dataset.train.first()) else {
        anyhow::bail!("{}: the run's dataset has no views", cfg.data.display());
    };
    let repeats = args.repeats;
    if !(0.0..1.0).contains(&args.display_stop) {
        anyhow::bail!("--display-stop {}: must be in [0, 1)", args.display_stop);
    }
    let mut raster_ms = serde_json::Map::new();
    let mut display_ms = serde_json::Map::new();
    for &size in &args.sizes {
        let cam = view.camera.scaled(size, size);
        let settings = relit_frame_settings(&cfg);
        let display = RasterSettings { display_stop: args.display_stop, ..settings.clone() };
        let exact = raster::render(&surfels, &cam, &settings, None).0;
        let shown = raster::render(&surfels, &cam, &display, None).0;
        // Exact and display frames alternate, so that both see the same machine.
        let (mut times, mut display_times) = (Vec::new(), Vec::new());
        for _ in 0..repeats {
            let t = Instant::now();
            let _ = raster::render(&surfels, &cam, &settings, None);
            times.push(t.elapsed().as_secs_f64() * 1e3);
            if args.display_stop > 0.0 {
                let t = Instant::now();
                let _ = raster::render(&surfels, &cam, &display, None);
                display_times.push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
        let ms = median(times);
        if args.display_stop > 0.0 {
            let d = frame_difference(&exact.colour, &shown.colour);
            let dms = median(display_times);
            display_ms.insert(
                format!("{size}"),
                serde_json::json!({"ms": dms, "fps": 1e3 / dms, "max_levels": d.max_levels,
                    "pixels_over_one_level": d.over_one, "psnr_db": d.psnr}),
            );
        }
        // The pre-pass of a frame: projection and tile binning (the rest is compositing).
        let prepass: Vec<f64> = (0..repeats)
            .map(|_| {
                let t = Instant::now();
                let p = raster::project::project(&surfels, &cam, &settings);
                let _ = raster::tiles::bin(&p, size, size, settings.alpha_min, settings.filter_inv_square);
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        raster_ms.insert(
            format!("{size}"),
            serde_json::json!({"ms": ms, "fps": 1e3 / ms, "project_and_bin_ms": median(prepass)}),
        );
    }
    let mut report = serde_json::json!({
        "run": args.run.display().to_string(),
        "surfels": surfels.len(),
        "threads": rayon::current_num_threads(),
        "rasterised_relit_frame": raster_ms,
    });
    if args.display_stop > 0.0 {
        report["display_frame"] = serde_json::json!({"display_stop": args.display_stop, "sizes": display_ms});
    }
    if args.raster_only {
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    if let Some(scene_t) = {
        let t = Instant::now();
        crate::pbr_scene::PbrScene::from_run(&args.run)?.map(|s| (s, t.elapsed().as_secs_f64()))
    } {
        let (scene, setup) = scene_t;
        let cam = view.camera.clone();
        let _ = scene.render(&cam, [1.0; 3]);
        let times: Vec<f64> = (0..repeats)
            .map(|_| {
                let t = Instant::now();
                let _ = scene.render(&cam, [1.0; 3]);
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        report["traced_pbr"] = serde_json::json!({
            "size": format!("{}x{}", cam.width, cam.height),
            "incident_light_seconds": setup,
            "samples_per_surfel": scene.cache.samples,
            "frame_ms": median(times),
        });
    }
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}
