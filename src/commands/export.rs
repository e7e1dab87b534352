//! `radiogs export`: a run's surfels as a 2DGS/3DGS-layout PLY (+ material fields).

use std::path::PathBuf;

/// Write a run's surfels as a PLY file.
#[derive(clap::Args, Debug, Clone)]
pub struct ExportArgs {
    /// Trained run folder.
    #[arg(long)]
    pub run: PathBuf,
    /// Output PLY path.
    #[arg(long)]
    pub ply: PathBuf,
}

pub fn run(args: &ExportArgs) -> anyhow::Result<()> {
    let surfels = crate::eval::load_run_surfels(&args.run)?;
    let cfg = crate::eval::load_run_config(&args.run)?;
    crate::io::ply::write_ply_trained(&args.ply, &surfels, Some(cfg.filter_inv_square))?;
    println!("{} surfels → {}", surfels.len(), args.ply.display());
    Ok(())
}
