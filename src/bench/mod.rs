//! `radiogs bench`: speed and memory figures for BENCHMARKS.md.

pub mod raster;
pub mod relight;
pub mod trace;
pub mod train;

/// Which part to measure.
#[derive(clap::Subcommand, Debug, Clone)]
pub enum BenchCommand {
    /// Rasteriser forward / backward throughput, memory and sorting error.
    Raster(raster::RasterBenchArgs),
    /// Ray tracer build, refit and rays per second.
    Trace(trace::TraceBenchArgs),
    /// Training iterations per second and the time split.
    Train(train::TrainBenchArgs),
    /// Relit rendering: rasterised frames per second, ray-traced PBR frame time.
    Relight(relight::RelightBenchArgs),
}

pub fn run(command: &BenchCommand) -> anyhow::Result<()> {
    match command {
        BenchCommand::Raster(args) => raster::run(args),
        BenchCommand::Trace(args) => trace::run(args),
        BenchCommand::Train(args) => train::run(args),
        BenchCommand::Relight(args) => relight::run(args),
    }
}
