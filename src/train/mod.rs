//! Training: configuration, stages, density control, checkpoints.
pub mod albedo_chroma;
pub mod albedo_voxel;
pub mod binned_albedo;
pub mod checkpoint;
pub mod config;
pub mod consistency;
pub mod contribution;
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
pub mod rc_sweep;

use crate::io::dataset::{Dataset, Split};
use config::{Stage, TrainConfig};

/// Training reads the object's silhouette from the images' alpha. A first training image that
/// is opaque everywhere (RGB without alpha, or a baked background) makes the whole frame the
/// object: legal, rarely meant, so said once.
fn warn_if_opaque(dataset: &Dataset) -> crate::Result<()> {
    if let Some(view) = dataset.views(Split::Train).first() {
        let img = view.load_image()?;
        if img.data.chunks_exact(4).all(|px| px[3] >= 1.0) {
            tracing::warn!(
                "{}: every pixel is opaque (no alpha channel, or alpha 1 everywhere): the whole frame counts as the \
                 object; radiogs expects RGBA images with a transparent background, as the NeRF-synthetic scenes have",
                view.image_path.display()
            );
        }
    }
    Ok(())
}

/// `radiogs train`: validate, write `RUN/config.toml`, run the requested stage(s).
pub fn run(cfg: &TrainConfig) -> anyhow::Result<()> {
    cfg.validate()?;
    let dataset = Dataset::open_downscaled(&cfg.data, cfg.resolution)?;
    // A truncated or corrupt training image stops here, before anything is written (the
    // stages read the images again; a decode costs little beside an iteration).
    dataset.check_images(Split::Train)?;
    warn_if_opaque(&dataset)?;
    // Inputs the stages read later are read once here too, so that a bad file stops the run
    // before anything is written (an --env-init-map used to fail after the whole nvs stage).
    if let Some(path) = &cfg.env_init_map {
        crate::envmap::EnvMap::load(path)?;
    }
    if let Some(path) = &cfg.init_ply
        && !cfg.resume
    {
        crate::io::ply::read_ply(path)?;
    }
    if crate::io::same_path(&cfg.out, &cfg.data) {
        return Err(crate::Error::invalid(
            format!("--out {}", cfg.out.display()),
            "is the dataset folder; write the run somewhere else",
        )
        .into());
    }
    if !cfg.resume && !cfg.overwrite {
        refuse_trained_run(cfg)?;
    }
    std::fs::create_dir_all(&cfg.out).map_err(|e| crate::Error::io(&cfg.out, e))?;
    if !cfg.resume && matches!(cfg.stage, Stage::Nvs | Stage::Init | Stage::All) {
        remove_stale_inverse_outputs(&cfg.out)?;
    }
    if cfg.resume {
        warn_on_changed_data(cfg);
    }
    cfg.save(&cfg.out.join("config.toml"))?;
    eprintln!("{}", dataset.summary());
    let stages: &[Stage] = match cfg.stage {
        Stage::Nvs => &[Stage::Nvs],
        Stage::Init => &[Stage::Init],
        Stage::Inverse => &[Stage::Inverse],
        _ => &[Stage::Nvs, Stage::Inverse],
    };
    // A resumed stage that had nothing left to run keeps what the summary said about it.
    let summary_path = cfg.out.join("train_summary.json");
    let previous: serde_json::Map<String, serde_json::Value> = if cfg.resume {
        std::fs::read_to_string(&summary_path).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or_default()
    } else {
        Default::default()
    };
    let mut summaries = serde_json::Map::new();
    for &stage in stages {
        let (name, summary) = match stage {
            Stage::Nvs => ("nvs", nvs::run(cfg, &dataset, true)?),
            Stage::Init => ("init", pbr_init::run(cfg, &dataset, true)?),
            _ => ("inverse", inverse::run(cfg, &dataset, true)?),
        };
        if summary.iterations_run == 0 && !summary.interrupted {
            eprintln!("{name}: already complete ({} iterations) in {}", summary.iterations, cfg.out.display());
            if let Some(old) = previous.get(name) {
                summaries.insert(name.to_string(), old.clone());
                continue;
            }
        }
        summaries.insert(name.to_string(), serde_json::to_value(&summary)?);
        let text = serde_json::to_string_pretty(&summaries)?;
        crate::io::atomic::write_atomic(&summary_path, text.as_bytes())?;
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

/// A fresh run into a folder that holds a trained run would replace that run's files one by
/// one as the new stages write theirs; if the new run then fails, the folder mixes both. So
/// without `--overwrite` such a folder is refused before anything is written: the geometry
/// stages refuse any trained run's files, the inverse stage (which starts from the folder's
/// geometry checkpoint) only a previous inverse stage's.
fn refuse_trained_run(cfg: &TrainConfig) -> crate::Result<()> {
    let out = &cfg.out;
    let trained: &[&str] = match cfg.stage {
        Stage::Inverse => &["checkpoint_inverse.bin", "envmap.exr"],
        _ => &["checkpoint.bin", "checkpoint_init.bin", "checkpoint_inverse.bin", "point_cloud.ply", "envmap.exr"],
    };
    match trained.iter().find(|f| out.join(f).is_file()) {
        Some(f) => Err(crate::Error::invalid(
            format!("--out {}", out.display()),
            format!(
                "already holds a trained run ({f}); continue it with --resume, pass --overwrite to replace it, or \
                 choose another folder"
            ),
        )),
        None => Ok(()),
    }
}

/// A resumed run continues with the images it is given; say so when they are not the ones
/// (or not the resolution) the run was trained on. Datasets move, so this does not refuse.
fn warn_on_changed_data(cfg: &TrainConfig) {
    let Ok(saved) = crate::eval::load_run_config(&cfg.out) else { return };
    if !crate::io::same_path(&saved.data, &cfg.data) || saved.resolution != cfg.resolution {
        eprintln!(
            "warning: {} was trained on {} at -r {}; resuming on {} at -r {}",
            cfg.out.display(),
            saved.data.display(),
            saved.resolution,
            cfg.data.display(),
            cfg.resolution
        );
    }
}

/// The inverse stage's outputs in `run`. A fresh geometry stage makes them describe surfels
/// that are gone: left in place, `eval` and `render` would pair the new geometry with the old
/// light and materials (`envmap.exr` marks a run as inverse-trained).
const INVERSE_OUTPUTS: [&str; 4] =
    ["envmap.exr", "checkpoint_inverse.bin", "metrics_inverse.jsonl", "inverse_times.json"];

/// Remove [`INVERSE_OUTPUTS`] from `run`, saying which.
fn remove_stale_inverse_outputs(run: &std::path::Path) -> crate::Result<()> {
    let stale: Vec<&str> = INVERSE_OUTPUTS.into_iter().filter(|f| run.join(f).is_file()).collect();
    for f in &stale {
        let path = run.join(f);
        std::fs::remove_file(&path).map_err(|e| crate::Error::io(&path, e))?;
    }
    if !stale.is_empty() {
        eprintln!(
            "{}: a new geometry stage; removed the previous inverse stage's {} (train with --resume to continue a run instead)",
            run.display(),
            stale.join(", ")
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    /// Only the inverse stage's files go, and only those present.
    #[test]
    fn stale_inverse_outputs_are_removed_and_nothing_else() {
        let dir = crate::test_dir::TempDir::new("stale");
        for f in ["envmap.exr", "checkpoint_inverse.bin", "checkpoint.bin", "point_cloud.ply", "config.toml"] {
            std::fs::write(dir.join(f), "x").unwrap();
        }
        super::remove_stale_inverse_outputs(&dir).unwrap();
        let mut left: Vec<String> =
            std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().to_string()).collect();
        left.sort();
        assert_eq!(left, ["checkpoint.bin", "config.toml", "point_cloud.ply"]);
        super::remove_stale_inverse_outputs(&dir).unwrap();
    }
}
