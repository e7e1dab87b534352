//! Training: configuration, stages, density control, checkpoints.
pub mod albedo_chroma;
pub mod checkpoint;
pub mod config;
pub mod consistency;
pub mod densify;
pub mod gauge;
pub mod init;
pub mod interrupt;
pub mod inverse;
pub mod light;
pub mod material;
pub mod nvs;
pub mod pbr_image;
pub mod pbr_init;

use crate::io::dataset::Dataset;
use config::{Stage, TrainConfig};

/// `radiogs train`: validate, write `RUN/config.toml`, run the requested stage(s).
pub fn run(cfg: &TrainConfig) -> anyhow::Result<()> {
    cfg.validate()?;
    let dataset = Dataset::open_downscaled(&cfg.data, cfg.resolution)?;
    std::fs::create_dir_all(&cfg.out).map_err(|e| crate::Error::io(&cfg.out, e))?;
    cfg.save(&cfg.out.join("config.toml"))?;
    eprintln!("{}", dataset.summary());
    let stages: &[Stage] = match cfg.stage {
        Stage::Nvs => &[Stage::Nvs],
        Stage::Init => &[Stage::Init],
        Stage::Inverse => &[Stage::Inverse],
        _ => &[Stage::Nvs, Stage::Inverse],
    };
    let mut summaries = serde_json::Map::new();
    for &stage in stages {
        let (name, summary) = match stage {
            Stage::Nvs => ("nvs", nvs::run(cfg, &dataset, true)?),
            Stage::Init => ("init", pbr_init::run(cfg, &dataset, true)?),
            _ => ("inverse", inverse::run(cfg, &dataset, true)?),
        };
        summaries.insert(name.to_string(), serde_json::to_value(&summary)?);
        let text = serde_json::to_string_pretty(&summaries)?;
        crate::io::atomic::write_atomic(&cfg.out.join("train_summary.json"), text.as_bytes())?;
        if summary.interrupted {
            let ckpt = match stage {
                Stage::Nvs => nvs::GeometryStage::Nvs.checkpoint(&cfg.out),
                Stage::Init => nvs::GeometryStage::Init.checkpoint(&cfg.out),
                _ => inverse::checkpoint_path(&cfg.out),
            };
            eprintln!(
                "interrupted in {name} at iteration {}: checkpoint written to {}; continue with --resume",
                summary.iterations,
                ckpt.display()
            );
            return Ok(());
        }
        let resumed = if summary.iterations_run == summary.iterations {
            String::new()
        } else {
            format!(" (resumed at iteration {})", summary.iterations - summary.iterations_run)
        };
        eprintln!(
            "{name}: {} iterations{resumed} in {:.1} s ({:.2} it/s), {} surfels, last PSNR {:.2} dB → {}",
            summary.iterations_run,
            summary.seconds,
            summary.iterations_run as f64 / summary.seconds.max(1e-9),
            summary.surfels,
            summary.last_psnr,
            cfg.out.display()
        );
    }
    Ok(())
}
