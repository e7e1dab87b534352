//! Diagnostic: the inverse stage's objective at a run's checkpoint, over every training view
//! (no step), so that two runs of one scene can be compared on the losses themselves rather
//! than on one logged iteration's view. Prints the mean of each term and of the total, and
//! with several runs a paired comparison of the totals against the first run.
//!
//!     cargo run --release --example probe_objective -- DATA RUN [RUN ...]
//!
//! `SEED=s` changes the cache's rays, the backgrounds and the consistency samples (default 7);
//! every run is scored on the same draws.

use anyhow::Context;
use radiogs::io::dataset::Dataset;
use radiogs::train::inverse::{InverseLosses, objective_per_view};
use std::path::PathBuf;

fn terms(l: &InverseLosses) -> [(&'static str, f64); 12] {
    [
        ("total", l.total as f64),
        ("pbr_l1", l.pbr_l1 as f64),
        ("pbr_dssim", l.pbr_dssim as f64),
        ("sh_l1", l.sh_l1 as f64),
        ("sh_dssim", l.sh_dssim as f64),
        ("mask", l.mask as f64),
        ("normal", l.normal as f64),
        ("smooth", l.smooth as f64),
        ("chroma", l.albedo_chroma as f64),
        ("env_prior", l.env_prior as f64),
        ("rc", l.rc.total as f64),
        ("psnr_pbr", l.psnr_pbr as f64),
    ]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        anyhow::bail!("usage: probe_objective DATA RUN [RUN ...]");
    }
    let data = PathBuf::from(&args[1]);
    let seed: u64 = match std::env::var("SEED") {
        Ok(v) => v.parse().with_context(|| format!("SEED={v}: not an integer"))?,
        Err(_) => 7,
    };
    let mut totals: Vec<Vec<f64>> = Vec::new();
    for run in &args[2..] {
        let run = PathBuf::from(run);
        let mut cfg = radiogs::eval::load_run_config(&run)?;
        cfg.out = run.clone();
        let dataset = Dataset::open_downscaled(&data, cfg.resolution)?;
        let per_view = objective_per_view(&cfg, &dataset, seed)?;
        let n = per_view.len() as f64;
        let mut line = format!("{:<40}", run.display());
        let mut sums = [0.0f64; 12];
        for l in &per_view {
            for (sum, (_, v)) in sums.iter_mut().zip(terms(l)) {
                *sum += v;
            }
        }
        for ((name, _), sum) in terms(&InverseLosses::default()).iter().zip(sums) {
            line += &format!(" {name}={:.5}", sum / n);
        }
        println!("{line}");
        totals.push(per_view.iter().map(|l| l.total as f64).collect());
    }
    // Paired: the same views and draws, so the per-view differences' spread is the noise.
    for (k, t) in totals.iter().enumerate().skip(1) {
        let d: Vec<f64> = t.iter().zip(&totals[0]).map(|(a, b)| a - b).collect();
        let n = d.len() as f64;
        let mean = d.iter().sum::<f64>() / n;
        let sd = (d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
        let lower = d.iter().filter(|&&x| x < 0.0).count();
        println!(
            "run {} − run 1: total {mean:+.5} ± {:.5} (standard error), lower on {lower} of {} views",
            k + 1,
            sd / n.sqrt(),
            d.len()
        );
    }
    Ok(())
}
