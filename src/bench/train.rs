//! `radiogs bench train`: nvs training throughput on a dataset (iterations per second) and the
//! time split (rasteriser forward / backward, losses, density control, optimiser), for
//! BENCHMARKS.md. The run goes to a temporary folder that is removed afterwards.

use crate::io::dataset::Dataset;
use crate::train::config::TrainConfig;
use std::path::PathBuf;

/// Measure nvs training speed on a dataset.
#[derive(clap::Args, Debug, Clone)]
pub struct TrainBenchArgs {
    /// Dataset folder.
    #[arg(long)]
    pub data: PathBuf,
    /// Iterations to time.
    #[arg(long, default_value_t = 300)]
    pub iters: u32,
    /// Initial surfel count (no densification during the bench, so this is the count timed).
    #[arg(long, default_value_t = 50_000)]
    pub surfels: usize,
    /// Start from these surfels (e.g. a trained run's point_cloud.ply) instead of random ones.
    #[arg(long)]
    pub ply: Option<PathBuf>,
}

pub fn run(args: &TrainBenchArgs) -> anyhow::Result<()> {
    let dataset = Dataset::open(&args.data)?;
    let out = std::env::temp_dir().join(format!("radiogs-bench-train-{}", std::process::id()));
    let cfg = TrainConfig {
        data: args.data.clone(),
        out: out.clone(),
        iters: args.iters,
        init_points: args.surfels,
        init_ply: args.ply.clone(),
        // A fixed surfel count: density control off, every regulariser on from the start.
        densify_until: 0,
        opacity_reset_every: u32::MAX / 2,
        dist_from: 0,
        normal_from: 0,
        checkpoint_every: 0,
        // 2DGS's position rates, as in the figures of earlier sessions (the scaling for short
        // runs would multiply them by 30000 / iters here).
        scale_position_lr: false,
        ..TrainConfig::default()
    };
    std::fs::create_dir_all(&out)?;
    let summary = crate::train::nvs::run(&cfg, &dataset, true);
    let _ = std::fs::remove_dir_all(&out);
    let summary = summary?;
    let it = summary.iterations as f64;
    let t = &summary.time_split;
    let report = serde_json::json!({
        "dataset": args.data.display().to_string(),
        "surfels": summary.surfels,
        "iterations": summary.iterations,
        "seconds": summary.seconds,
        "iterations_per_second": it / summary.seconds.max(1e-9),
        "ms_per_iteration": {
            "raster_forward": t.raster_forward / it * 1e3,
            "raster_backward": t.raster_backward / it * 1e3,
            "losses": t.losses / it * 1e3,
            "densify": t.densify / it * 1e3,
            "optimiser": t.optimiser / it * 1e3,
            "other": t.other / it * 1e3,
        },
    });
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}
