//! Training: configuration, stages, density control, checkpoints.
pub mod checkpoint;
pub mod consistency;
pub mod config;
pub mod densify;
pub mod init;
pub mod interrupt;
pub mod material;
pub mod nvs;

use crate::io::dataset::Dataset;
use config::{Stage, TrainConfig};

/// `radiogs train`: validate, write `RUN/config.toml`, run the requested stage(s).
pub fn run(cfg: &TrainConfig) -> anyhow::Result<()> {
    cfg.validate()?;
    if cfg.stage != Stage::Nvs {
        return Err(crate::NotBuilt("radiogs train --stage init|inverse|all is not built yet (issue 7)").into());
    }
    let dataset = Dataset::open(&cfg.data)?;
    std::fs::create_dir_all(&cfg.out).map_err(|e| crate::Error::io(&cfg.out, e))?;
    cfg.save(&cfg.out.join("config.toml"))?;
    eprintln!("{}", dataset.summary());
    match cfg.stage {
        Stage::Nvs => {
            let summary = nvs::run(cfg, &dataset, true)?;
            let text = serde_json::to_string_pretty(&summary)?;
            crate::io::atomic::write_atomic(&cfg.out.join("train_summary.json"), text.as_bytes())?;
            if summary.interrupted {
                eprintln!(
                    "interrupted at iteration {}: checkpoint written to {}; continue with --resume",
                    summary.iterations,
                    nvs::checkpoint_path(&cfg.out).display()
                );
            } else {
                eprintln!(
                    "nvs: {} iterations in {:.1} s ({:.1} it/s), {} surfels, last PSNR {:.2} dB → {}",
                    summary.iterations,
                    summary.seconds,
                    summary.iterations as f64 / summary.seconds.max(1e-9),
                    summary.surfels,
                    summary.last_psnr,
                    cfg.out.join("point_cloud.ply").display()
                );
            }
            Ok(())
        }
        Stage::Init | Stage::Inverse | Stage::All => {
            Err(crate::NotBuilt("radiogs train --stage init|inverse|all is not built yet (issue 7)").into())
        }
    }
}
