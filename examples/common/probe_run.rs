//! The `RUN DATA` arguments of the probe examples: the run's training config (with
//! `SKIP_MARGIN=m` overriding its `ray_skip_margin`, × extent), scene extent, surfels and how
//! its traced rays treat back faces.
//! Included by several example binaries, each using part of it.
#![allow(dead_code)]

use anyhow::Context;
use std::path::PathBuf;

pub struct ProbeRun {
    pub run: PathBuf,
    pub data: PathBuf,
    pub cfg: radiogs::train::config::TrainConfig,
    pub extent: f32,
    pub surfels: radiogs::surfels::Surfels,
    pub back_faces: radiogs::train::inverse::BackFaces,
}

/// Parse `RUN DATA` from the command line of example `name` and load the run.
pub fn from_args(name: &str) -> anyhow::Result<ProbeRun> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        anyhow::bail!("usage: {name} RUN DATA");
    }
    let (run, data) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]));
    let mut cfg = radiogs::eval::load_run_config(&run)?;
    if let Ok(v) = std::env::var("SKIP_MARGIN") {
        cfg.ray_skip_margin = v.parse().context("SKIP_MARGIN")?;
    }
    let extent = radiogs::pbr_scene::scene_extent(&run);
    let surfels = radiogs::eval::load_run_surfels(&run)?;
    let back_faces =
        radiogs::train::inverse::BackFaces::of_run(&run, cfg.trace_back_faces, surfels.len())?.of_config(&cfg);
    Ok(ProbeRun { run, data, cfg, extent, surfels, back_faces })
}

/// Print the cache's size and where its rays start (the probes' first line).
pub fn print_cache(surfels: usize, samples: usize, start: radiogs::shade::incident::RayStart) {
    println!(
        "{surfels} surfels, {samples} samples, ray offset {:.4}, skip margin {:?} (scene units)",
        start.offset, start.skip_margin
    );
}
