//! The `radiogs` command line: parse, call the library, print. Errors are one clear line and
//! a non-zero exit code (2 for commands that are not built yet).

use clap::{CommandFactory, FromArgMatches, Subcommand};
use radiogs::commands::{demo, export, info, render};

#[derive(clap::Parser, Debug)]
#[command(
    name = "radiogs",
    version,
    about = "Inverse rendering with radiometrically consistent 2D Gaussian surfels, on the CPU"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Render a built-in scene with the reference path tracer into a dataset with every GT pass.
    Synth(radiogs::synth::SynthArgs),
    /// Train surfels (geometry, radiance, materials, light) from a dataset of posed images.
    Train(radiogs::train::config::TrainConfig),
    /// Render views of a trained run or of a PLY file from a camera file.
    Render(render::RenderArgs),
    /// Put a trained scene under a new environment map (surfel finetune or ray-traced PBR).
    Relight(radiogs::relight::RelightArgs),
    /// Evaluate a run against a dataset's test views (NVS, albedo, normals, relighting) as JSON.
    Eval(radiogs::eval::EvalArgs),
    /// Write a run's surfels as a 2DGS/3DGS-compatible PLY (with material fields).
    Export(export::ExportArgs),
    /// Measure speed and memory of the rasteriser, tracer or training.
    #[command(subcommand)]
    Bench(radiogs::bench::BenchCommand),
    /// Synthesise the built-in scene, train, relight, evaluate and write an HTML report.
    Demo(demo::DemoArgs),
    /// Print a one-line summary of a dataset folder or a surfel PLY.
    Info(info::InfoArgs),
}

/// Keep freed memory in the process (glibc): every rendered view allocates and frees image-
/// and pair-sized buffers of a few MiB, and returning them to the kernel each time cost ~10 %
/// of a training iteration in page faults and TLB-shootdown interrupts (perf, BENCHMARKS.md).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn keep_freed_memory() {
    unsafe extern "C" {
        fn mallopt(param: i32, value: i32) -> i32;
    }
    const M_TRIM_THRESHOLD: i32 = -1;
    const M_MMAP_THRESHOLD: i32 = -3;
    // SAFETY: mallopt only changes allocator tuning; called before any other thread exists.
    unsafe {
        mallopt(M_MMAP_THRESHOLD, 32 << 20);
        mallopt(M_TRIM_THRESHOLD, i32::MAX);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn keep_freed_memory() {}

fn main() {
    keep_freed_memory();
    tracing_subscriber::fmt().with_writer(std::io::stderr).with_target(false).init();
    let matches = Cli::command().get_matches();
    let cli = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    let result = match &cli.command {
        Command::Synth(args) => radiogs::synth::run(args),
        Command::Train(cfg) => {
            // Flags typed on the command line override a --config file; defaults do not.
            let sub = matches.subcommand_matches("train").expect("train matches");
            let explicit: Vec<String> = sub
                .ids()
                .filter(|id| sub.value_source(id.as_str()) == Some(clap::parser::ValueSource::CommandLine))
                .map(|id| id.to_string())
                .collect();
            radiogs::train::config::TrainConfig::resolve(cfg, &explicit)
                .map_err(anyhow::Error::from)
                .and_then(|cfg| radiogs::train::run(&cfg))
        }
        Command::Render(args) => render::run(args),
        Command::Relight(args) => radiogs::relight::run(args),
        Command::Eval(args) => radiogs::eval::run(args),
        Command::Export(args) => export::run(args),
        Command::Bench(cmd) => radiogs::bench::run(cmd),
        Command::Demo(args) => demo::run(args),
        Command::Info(args) => info::run(args),
    };
    if let Err(err) = result {
        if err.downcast_ref::<radiogs::NotBuilt>().is_some() {
            eprintln!("radiogs: {err}");
            std::process::exit(2);
        }
        eprintln!("error: {err:#}");
        std::process::exit(1);
    }
}
