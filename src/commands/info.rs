//! `radiogs info`: one-line summaries of a dataset or a surfel PLY.

use crate::io::{dataset::Dataset, ply};
use std::path::PathBuf;

/// Summarise a dataset folder or a surfel PLY file.
#[derive(clap::Args, Debug, Clone)]
pub struct InfoArgs {
    /// Dataset folder (Blender or TensoIR layout).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Surfel PLY file.
    #[arg(long)]
    pub ply: Option<PathBuf>,
}

pub fn run(args: &InfoArgs) -> anyhow::Result<()> {
    if args.data.is_none() && args.ply.is_none() {
        anyhow::bail!("radiogs info needs --data DIR or --ply FILE");
    }
    if let Some(dir) = &args.data {
        let ds = Dataset::open(dir)?;
        // Touch one image and each GT pass so a broken file is reported now, not mid-training.
        if let Some(v) = ds.train.first() {
            v.load_image()?;
        }
        if let Some(v) = ds.test.first() {
            for pass in ds.passes_found() {
                v.load_pass(pass)?;
            }
        }
        println!("{}", ds.summary());
    }
    if let Some(path) = &args.ply {
        let s = ply::read_ply(path)?;
        let info = ply::read_ply_info(path)?;
        let (lo, hi) = s.bounds().unwrap_or(([0.0; 3], [0.0; 3]));
        println!(
            "{}: {} surfels, SH degree {}, bounds [{:.3}, {:.3}, {:.3}]–[{:.3}, {:.3}, {:.3}], material fields {}, screen-space filter 1/σ² {}",
            path.display(),
            s.len(),
            s.sh_degree,
            lo[0],
            lo[1],
            lo[2],
            hi[0],
            hi[1],
            hi[2],
            if info.has_material { "yes" } else { "no (defaults)" },
            match ply::read_ply_filter_inv_square(path)? {
                Some(f) => format!("{f} (recorded)"),
                None => "2 (not recorded: 2DGS's)".to_string(),
            }
        );
        if let Some(unseen) = ply::read_ply_unseen(path)? {
            println!(
                "  {} surfels flagged unseen (no training camera saw them)",
                unseen.iter().filter(|u| **u).count()
            );
        }
    }
    Ok(())
}
