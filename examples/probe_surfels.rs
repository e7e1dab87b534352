//! Diagnostic: where a run's surfels sit against the true surfaces. For every surfel, the nearest
//! object of the dataset's README.json and its signed distance to it (negative inside), and the
//! angle between the surfel's normal and the surface normal there (the SDF's gradient; two-sided,
//! so a flipped normal counts as right). Prints per object:
//! - a histogram of signed distance in 5 mm bins from −40 to +40 mm, summed opacity of the
//!   surfels whose normal is within 20° of the surface normal (the ones that form a surface);
//! - per band (outside > 15 mm, surface ±15 mm, inside 15–30 mm, deep > 30 mm): surfel count,
//!   mean opacity, opacity-weighted mean normal error, share of opacity within 10°;
//! - the quartiles of the larger scale σ (mm) of surfels with opacity > 0.3 within 40 mm.
//!
//! Distances assume scene units of metres, as the shared datasets use.
//!
//!     cargo run --release --example probe_surfels -- RUN DATA

#[path = "common/scene_readme.rs"]
mod scene_readme;

use radiogs::surfels::sigmoid;
use std::path::PathBuf;

const BINS: usize = 16;
const BIN_MM: f64 = 5.0;
const BANDS: [&str; 4] = ["outside >15 mm", "surface ±15 mm", "inside 15–30 mm", "deep >30 mm"];

#[derive(Default, Clone)]
struct Band {
    count: usize,
    opacity: f64,
    /// Σ opacity · angle error (degrees).
    weighted_angle: f64,
    /// Σ opacity of surfels within 10° of the surface normal.
    within_10: f64,
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 3 {
        anyhow::bail!("usage: probe_surfels RUN DATA");
    }
    let (run, data) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]));
    let readme = scene_readme::load(&data)?;
    let objects = &readme.objects;
    anyhow::ensure!(!objects.is_empty(), "{}: README.json lists no objects", data.display());
    let s = radiogs::eval::load_run_surfels(&run)?;
    let mut hist = vec![[0.0f64; BINS]; objects.len()];
    let mut bands = vec![vec![Band::default(); BANDS.len()]; objects.len()];
    let mut scales: Vec<Vec<f64>> = vec![Vec::new(); objects.len()];
    for i in 0..s.len() {
        let p = s.means[i].map(|x| x as f64);
        let k = scene_readme::nearest(objects, p);
        let obj = &objects[k];
        let d = obj.sdf(p);
        // The surface normal: the SDF's central-difference gradient (boxes: the nearest face).
        let e = 1e-4;
        let g: [f64; 3] = std::array::from_fn(|c| {
            let (mut a, mut b) = (p, p);
            a[c] += e;
            b[c] -= e;
            (obj.sdf(a) - obj.sdf(b)) / (2.0 * e)
        });
        let gl = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt().max(1e-12);
        let n = s.normal(i);
        let cos = ((0..3).map(|c| n[c] as f64 * g[c]).sum::<f64>() / gl).abs().min(1.0);
        let angle = cos.acos().to_degrees();
        let o = sigmoid(s.opacity_logits[i]) as f64;
        let d_mm = d * 1000.0;
        let band = if d_mm > 15.0 {
            0
        } else if d_mm > -15.0 {
            1
        } else if d_mm > -30.0 {
            2
        } else {
            3
        };
        let b = &mut bands[k][band];
        b.count += 1;
        b.opacity += o;
        b.weighted_angle += o * angle;
        if angle < 10.0 {
            b.within_10 += o;
        }
        if angle < 20.0 {
            let bin = ((d_mm + BIN_MM * BINS as f64 / 2.0) / BIN_MM).floor();
            if (0.0..BINS as f64).contains(&bin) {
                hist[k][bin as usize] += o;
            }
        }
        if o > 0.3 && d_mm > -40.0 && d_mm < 40.0 {
            scales[k].push(s.log_scales[i][0].max(s.log_scales[i][1]).exp() as f64 * 1000.0);
        }
    }
    println!(
        "{} surfels of {}; signed distance to the nearest README object (mm, negative inside)",
        s.len(),
        run.display()
    );
    let lo = -(BIN_MM * BINS as f64 / 2.0);
    println!(
        "{:18} {}",
        "bin from (mm)",
        (0..BINS).map(|b| format!("{:>6}", lo + BIN_MM * b as f64)).collect::<String>()
    );
    for (k, obj) in objects.iter().enumerate() {
        println!("{:18} {}", obj.object, hist[k].iter().map(|v| format!("{v:6.0}")).collect::<String>());
    }
    println!();
    println!("{:18} {:>16} {:>7} {:>9} {:>9} {:>9}", "object", "band", "surfels", "opacity", "err°", "<10°");
    for (k, obj) in objects.iter().enumerate() {
        for (band, name) in BANDS.iter().enumerate() {
            let b = &bands[k][band];
            if b.count == 0 {
                continue;
            }
            println!(
                "{:18} {:>16} {:>7} {:>9.2} {:>9.1} {:>8.0}%",
                obj.object,
                name,
                b.count,
                b.opacity / b.count as f64,
                b.weighted_angle / b.opacity.max(1e-12),
                100.0 * b.within_10 / b.opacity.max(1e-12)
            );
        }
    }
    println!();
    for (k, obj) in objects.iter().enumerate() {
        let v = &mut scales[k];
        if v.is_empty() {
            continue;
        }
        v.sort_by(f64::total_cmp);
        let q = |f: f64| v[((v.len() - 1) as f64 * f).round() as usize];
        println!(
            "{:18} larger scale σ (mm), opacity > 0.3, within 40 mm: p25 {:.1} median {:.1} p75 {:.1} ({} surfels)",
            obj.object,
            q(0.25),
            q(0.5),
            q(0.75),
            v.len()
        );
    }
    Ok(())
}
