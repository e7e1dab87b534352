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
    #[arg(long, default_value_t = 7)]
    pub repeats: usize,
    /// Only the rasterised frames (skip the traced set-up; for profiling).
    #[arg(long)]
    pub raster_only: bool,
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
    let cfg = crate::eval::load_run_config(&args.run)?;
    let surfels = crate::eval::load_run_surfels(&args.run)?;
    let dataset = crate::io::dataset::Dataset::open_downscaled(&cfg.data, cfg.resolution)?;
    let Some(view) = dataset.test.first().or(dataset.train.first()) else {
        anyhow::bail!("{}: the run's dataset has no views", cfg.data.display());
    };
    let repeats = args.repeats.max(1);
    let mut raster_ms = serde_json::Map::new();
    for &size in &args.sizes {
        let cam = view.camera.scaled(size, size);
        let settings = relit_frame_settings(&cfg);
        let _ = raster::render(&surfels, &cam, &settings, None);
        let times: Vec<f64> = (0..repeats)
            .map(|_| {
                let t = Instant::now();
                let _ = raster::render(&surfels, &cam, &settings, None);
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        let ms = median(times);
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
