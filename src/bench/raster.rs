//! `radiogs bench raster`: rasteriser throughput, peak memory and sorting error.
//!
//! Scenes (fixed seed 2024): N surfels with centres uniform in the cube [−1, 1]³, seen by a
//! camera at distance 3.5 looking at the origin (horizontal fov 0.7 rad). Scales per axis
//! log-uniform in [0.5, 1.5] × s₀ with s₀ = (8/N)^{1/3} (the mean spacing), random rotations,
//! opacity uniform in [0.1, 0.9], SH degree 3 with DC from a uniform random colour and the
//! other coefficients uniform in [−0.2, 0.2]. Two-sided mode (no surfels culled as back faces).
//! Outputs: all on (colour, alpha, depth, median depth, normal, distortion). Backward: random
//! per-pixel gradients on every output. `--train-scene` / `--train-only` add the training-like
//! scene of [`train_scene`]. Reported: wall times (fastest repeat) and mean CPU time per repeat
//! (all threads; on a shared machine it measures the work rather than the share received).
//! Throughput is per tile-list evaluation (`evals`: per pixel, its tile's list up to early stop,
//! the figure issue 4's targets count); `evals done` is what the compositor evaluated, each
//! pixel going through its tile quarter's list only.

use crate::camera::Camera;
use crate::raster::{self, RasterSettings, RenderGrads};
use crate::surfels::Surfels;
use glam::Vec3;
use rand::{RngExt, SeedableRng};
use std::time::Instant;

#[derive(clap::Args, Debug, Clone)]
pub struct RasterBenchArgs {
    /// Timed repetitions per case (the fastest is reported).
    #[arg(long, default_value_t = 3, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1_000_000))]
    pub repeats: usize,
    /// Only the small scene (10k surfels at 256²).
    #[arg(long)]
    pub quick: bool,
    /// Also run the training-like scene (see [`train_scene`]): 50k small surfels (radius 1–4 px)
    /// on three sphere surfaces at 200², as in the nvs stage.
    #[arg(long)]
    pub train_scene: bool,
    /// Only the training-like scene.
    #[arg(long)]
    pub train_only: bool,
    /// Sorting windows to measure.
    #[arg(long, value_delimiter = ',', default_values_t = vec![1usize, 4, 8, 16])]
    pub k: Vec<usize>,
    /// Forward + backward without the hit record (the backward re-runs every pixel's sorting
    /// window), instead of as training runs it (`render_recorded`, the backward replays).
    #[arg(long)]
    pub rerun: bool,
}

pub fn scene(n: usize, seed: u64) -> Surfels {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let s0 = (8.0 / n as f32).cbrt();
    let mut s = Surfels { sh_degree: 3, ..Default::default() };
    for _ in 0..n {
        let mean: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
        let sc: [f32; 2] = std::array::from_fn(|_| s0 * rng.random_range(0.5f32.ln()..1.5f32.ln()).exp());
        let q: [f32; 4] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
        let q = if q.iter().map(|v| v * v).sum::<f32>() < 1e-4 { [1.0, 0.0, 0.0, 0.0] } else { q };
        let o = rng.random_range(0.1..0.9f32);
        s.push(mean, sc, q, o, [rng.random(), rng.random(), rng.random()], [0.5; 3], 0.5);
        let last = s.sh.len() - 1;
        for k in 1..16 {
            for ch in 0..3 {
                s.sh[last][k][ch] = rng.random_range(-0.2..0.2);
            }
        }
    }
    s
}

/// Training-like scene: N surfels on the surfaces of three spheres (radii 0.5–0.8 about points
/// within the unit cube), normals outward, scales log-uniform so that the screen radius is
/// 1–4 px at 200² (camera distance 3.5, fov 0.7: f ≈ 275 px, s·f/3.5 ∈ [1, 4]), opacity
/// uniform in [0.5, 1.0] (trained surfaces are mostly opaque), SH as in [`scene`].
pub fn train_scene(n: usize, seed: u64) -> Surfels {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let spheres = [([-0.4f32, 0.1, 0.2], 0.6f32), ([0.5, -0.2, -0.3], 0.5), ([0.1, 0.4, 0.5], 0.8)];
    let f = 200.0 / (2.0 * (0.35f32).tan());
    let (smin, smax) = (3.5 / f, 4.0 * 3.5 / f);
    let mut s = Surfels { sh_degree: 3, ..Default::default() };
    for _ in 0..n {
        let (c, r) = spheres[rng.random_range(0..3usize)];
        let d = loop {
            let d: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
            let l2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            if l2 > 1e-3 && l2 <= 1.0 {
                let l = l2.sqrt();
                break [d[0] / l, d[1] / l, d[2] / l];
            }
        };
        let mean = [c[0] + r * d[0], c[1] + r * d[1], c[2] + r * d[2]];
        let sc: [f32; 2] = std::array::from_fn(|_| rng.random_range(smin.ln()..smax.ln()).exp());
        // Rotation taking +z to the outward normal d (axis z × d, half-angle form).
        let q = if d[2] < -0.999 { [0.0, 1.0, 0.0, 0.0] } else { [1.0 + d[2], -d[1], d[0], 0.0] };
        let o = rng.random_range(0.5..1.0f32);
        s.push(mean, sc, q, o, [rng.random(), rng.random(), rng.random()], [0.5; 3], 0.5);
        let last = s.sh.len() - 1;
        for k in 1..16 {
            for ch in 0..3 {
                s.sh[last][k][ch] = rng.random_range(-0.2..0.2);
            }
        }
    }
    s
}

/// CPU time (user + system, all threads) of this process in seconds, from /proc (10 ms ticks):
/// on a shared machine it measures the work done, where wall time measures the share received.
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(f64::NAN);
    (tick(11) + tick(12)) / 100.0
}

fn peak_rss_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse::<f64>().ok())
        .map_or(f64::NAN, |kib| kib / 1024.0)
}

pub fn run(args: &RasterBenchArgs) -> anyhow::Result<()> {
    // The window sizes `render --k` takes.
    if let Some(bad) = args.k.iter().find(|k| !(1..=crate::raster::MAX_WINDOW).contains(k)) {
        anyhow::bail!("--k {bad}: each window must be in 1..={}", crate::raster::MAX_WINDOW);
    }
    let mut cases: Vec<(usize, u32, bool)> =
        if args.quick { vec![(10_000, 256, false)] } else { vec![(10_000, 256, false), (100_000, 800, false)] };
    if args.train_only {
        cases.clear();
    }
    if args.train_scene || args.train_only {
        cases.push((50_000, 200, true));
    }
    println!("rayon threads: {}", rayon::current_num_threads());
    println!(
        "{:>5} {:>7} {:>5} {:>3} {:>10} {:>12} {:>10} {:>12} {:>9} {:>9} {:>12} {:>12} {:>10} {:>10} {:>9}",
        "scene",
        "surfels",
        "res",
        "K",
        "fwd ms",
        "fwd Meval/s",
        "f+b ms",
        "f+b Meval/s",
        "fwd cpu",
        "f+b cpu",
        "evals",
        "evals done",
        "sort err w",
        "sort err",
        "peak MiB"
    );
    for (n, res, train) in cases {
        let s = if train { train_scene(n, 2024) } else { scene(n, 2024) };
        let cam = Camera::look_at("bench", Vec3::new(0.0, -3.5, 0.0), Vec3::ZERO, res, res, 0.7);
        let px = (res * res) as usize;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let mut r = |a: f32| rng.random_range(-a..a);
        let grads = RenderGrads {
            v_colour: (0..px).map(|_| [r(1.0), r(1.0), r(1.0)]).collect(),
            v_alpha: (0..px).map(|_| r(1.0)).collect(),
            v_depth: (0..px).map(|_| r(0.1)).collect(),
            v_median_depth: vec![],
            v_normal: (0..px).map(|_| [r(1.0), r(1.0), r(1.0)]).collect(),
            v_distortion: (0..px).map(|_| r(10.0)).collect(),
            v_features: vec![],
        };
        let mut v = s.zeros_like();
        for &k in &args.k {
            let set = RasterSettings { window: k, two_sided: true, ..Default::default() };
            let (mut best_f, mut best_fb) = (f64::INFINITY, f64::INFINITY);
            let (mut cpu_f, mut cpu_b) = (0.0, 0.0);
            let (mut evals, mut evals_done) = (0, 0);
            let mut sort = (0.0, 0.0);
            let mut record = raster::PixelHitRecord::default();
            let (mut record_mib, mut rows_over) = (0.0, 0);
            for rep in 0..args.repeats {
                let c0 = cpu_seconds();
                let t0 = Instant::now();
                let (out, st) = raster::render(&s, &cam, &set, None);
                let tf = t0.elapsed().as_secs_f64();
                let c1 = cpu_seconds();
                std::hint::black_box(&out);
                // Forward + backward as training runs them: the forward keeps its hits (its
                // record reused frame to frame), the backward replays them.
                let (st, tfr, cfr) = if args.rerun {
                    (st, tf, c1 - c0)
                } else {
                    drop(out);
                    let t0 = Instant::now();
                    let (out, st) = raster::render_recorded(&s, &cam, &set, None, std::mem::take(&mut record));
                    std::hint::black_box(&out);
                    (st, t0.elapsed().as_secs_f64(), cpu_seconds() - c1)
                };
                let c2 = cpu_seconds();
                v.fill_zero();
                let t1 = Instant::now();
                let b = raster::render_backward(&s, &cam, &set, None, &st, &grads, &mut v, None);
                let tb = t1.elapsed().as_secs_f64();
                // cpu_f: the plain forward; cpu_b: the backward and (recorded) forward it follows.
                cpu_f += c1 - c0;
                cpu_b += cfr + cpu_seconds() - c2 - (c1 - c0);
                std::hint::black_box(&b);
                best_f = best_f.min(tf);
                best_fb = best_fb.min(tfr + tb);
                let mut st = st;
                if let Some(r) = st.record.take() {
                    record_mib = r.bytes() as f64 / (1 << 20) as f64;
                    rows_over = r.pixels_not_recorded();
                    record = r;
                }
                evals = st.evaluations;
                evals_done = st.evaluations_performed;
                if rep == 0 {
                    sort = raster::forward::sorting_error(&st, &cam, &set, if res > 400 { 4 } else { 2 });
                }
            }
            let line = serde_json::json!({
                "bench": "raster", "scene": if train { "train" } else { "random" }, "surfels": n,
                "forward_cpu_s_mean": cpu_f / args.repeats as f64,
                "forward_backward_cpu_s_mean": (cpu_f + cpu_b) / args.repeats as f64, "res": res, "k": k,
                "forward_s": best_f, "forward_backward_s": best_fb, "evaluations": evals,
                "evaluations_performed": evals_done,
                "forward_evals_per_s": evals as f64 / best_f, "fb_evals_per_s": evals as f64 / best_fb,
                "sorting_error_weighted": sort.0, "sorting_error_pairs": sort.1, "peak_rss_mib": peak_rss_mib(),
                "hit_record_mib": record_mib, "hit_record_pixels_not_recorded": rows_over, "backward_reruns_windows": args.rerun,
            });
            println!(
                "{:>5} {:>7} {:>5} {:>3} {:>10.1} {:>12.1} {:>10.1} {:>12.1} {:>9.0} {:>9.0} {:>12} {:>12} {:>10.2e} {:>10.2e} {:>9.0}",
                if train { "train" } else { "rand" },
                n,
                res,
                k,
                best_f * 1e3,
                evals as f64 / best_f / 1e6,
                best_fb * 1e3,
                evals as f64 / best_fb / 1e6,
                cpu_f / args.repeats as f64 * 1e3,
                (cpu_f + cpu_b) / args.repeats as f64 * 1e3,
                evals,
                evals_done,
                sort.0,
                sort.1,
                peak_rss_mib()
            );
            eprintln!("{line}");
        }
    }
    Ok(())
}
