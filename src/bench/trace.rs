//! `radiogs bench trace`: BVH build / refit times and rays per second of the tracer.
//!
//! Scenes (fixed seeds):
//! - `surface`: 100k surfels on 8 spheres (centres uniform in [−0.6, 0.6]³, radii uniform in
//!   [0.2, 0.5]), points uniform on each sphere (count ∝ area), normal = outward radial, random
//!   spin about it; scale = sqrt(mean squared distance to the 3 nearest neighbours) ×
//!   uniform[0.8, 1.2] per axis; opacity uniform [0.2, 1.0]; SH degree 3, coefficients uniform
//!   ±0.2 (DC from uniform colours). Like a trained object: closed surfaces, outward normals.
//! - `volume`: 100k surfels uniform in [−1, 1]³, random orientations, kNN scales as above,
//!   opacity uniform [0.05, 1.0] — a harder, unstructured case.
//!
//! - `--ply FILE`: a trained scene (a run's point_cloud.ply) instead, reported as `ply`.
//!
//! Rays: 2048 random surfels × 64 directions uniform on the hemisphere of the surfel's normal,
//! starting at the surfel's centre (RadioGS's radiometric-consistency batch), 131072 rays.

use crate::surfels::{Surfels, mean_sq_dist_3nn, quat_with_normal};
use crate::trace::{
    HitRecord, Ray, RayGrad, RayOutput, TraceSettings, Tracer, trace, trace_backward, trace_backward_recorded,
    trace_recorded,
};
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;
use std::path::PathBuf;
use std::time::Instant;

#[derive(clap::Args, Debug, Clone)]
pub struct TraceBenchArgs {
    /// Which built-in scenes to measure.
    #[arg(long, value_enum, default_value = "both")]
    pub scene: SceneChoice,
    /// Measure a trained scene (e.g. a run's point_cloud.ply) instead of the built-in ones.
    #[arg(long, conflicts_with = "scene")]
    pub ply: Option<PathBuf>,
    /// Timed repetitions of the forward (the backward and build take fewer); the median counts.
    #[arg(long, default_value_t = 5, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1_000_000))]
    pub repeats: usize,
    /// Hits gathered per traversal (TraceSettings::chunk).
    #[arg(long, default_value_t = TraceSettings::default().chunk)]
    pub chunk: usize,
    /// Rays skip surfels less than this (scene units) above their start surfel's tangent
    /// plane, as the PBR stages' rays do (`ray_skip_margin` × extent); 0 = off.
    #[arg(long, default_value_t = 0.0)]
    pub skip_margin: f32,
    /// Back faces within this many degrees past edge-on are still hit (the PBR stages'
    /// `--trace-grazing`); 0 = strict one-sided culling.
    #[arg(long, default_value_t = 0.0)]
    pub grazing: f32,
    /// Composite the hits' colours decoded to linear, as the inverse stage's tracer does
    /// (`TraceSettings::linear_radiance`: an sRGB decode per hit and channel).
    #[arg(long)]
    pub linear_radiance: bool,
}

#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq)]
pub enum SceneChoice {
    Surface,
    Volume,
    Both,
}

const N: usize = 100_000;

fn unit(v: [f32; 3]) -> [f32; 3] {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-20);
    v.map(|x| x / l)
}

fn random_unit(rng: &mut Pcg64) -> [f32; 3] {
    loop {
        let v: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
        let l2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
        if l2 > 1e-4 && l2 <= 1.0 {
            return unit(v);
        }
    }
}

/// The benchmark scenes described in the module note.
pub fn scene(kind: &str, seed: u64) -> Surfels {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut points = Vec::with_capacity(N);
    let mut normals = Vec::with_capacity(N);
    if kind == "surface" {
        let spheres: Vec<([f32; 3], f32)> = (0..8)
            .map(|_| (std::array::from_fn(|_| rng.random_range(-0.6..0.6f32)), rng.random_range(0.2..0.5f32)))
            .collect();
        let total: f32 = spheres.iter().map(|s| s.1 * s.1).sum();
        for (c, r) in &spheres {
            let count = ((r * r / total) * N as f32).round() as usize;
            for _ in 0..count {
                let n = random_unit(&mut rng);
                points.push([c[0] + r * n[0], c[1] + r * n[1], c[2] + r * n[2]]);
                normals.push(n);
            }
        }
        while points.len() < N {
            let n = random_unit(&mut rng);
            points.push(n.map(|x| 0.3 * x));
            normals.push(n);
        }
        points.truncate(N);
        normals.truncate(N);
    } else {
        for _ in 0..N {
            points.push(std::array::from_fn(|_| rng.random_range(-1.0..1.0f32)));
            normals.push(random_unit(&mut rng));
        }
    }
    let d2 = mean_sq_dist_3nn(&points);
    let mut s = Surfels::default();
    let min_op = if kind == "surface" { 0.2 } else { 0.05 };
    for i in 0..N {
        let q = quat_with_normal(normals[i]);
        let spin =
            glam::Quat::from_axis_angle(glam::Vec3::from(normals[i]), rng.random_range(0.0..std::f32::consts::TAU))
                * glam::Quat::from_xyzw(q[1], q[2], q[3], q[0]);
        let sc = d2[i].max(1e-10).sqrt();
        s.push(
            points[i],
            [sc * rng.random_range(0.8..1.2f32), sc * rng.random_range(0.8..1.2f32)],
            [spin.w, spin.x, spin.y, spin.z],
            rng.random_range(min_op..1.0f32),
            [rng.random(), rng.random(), rng.random()],
            [0.3; 3],
            0.5,
        );
        for k in 1..16 {
            s.sh[i][k] = std::array::from_fn(|_| rng.random_range(-0.2..0.2f32));
        }
    }
    s.sh_degree = 3;
    s
}

/// 2048 surfels × 64 hemisphere directions from their centres (skipping surfels less than
/// `skip_margin` above the start surfel's tangent plane when it is > 0).
pub fn hemisphere_rays(s: &Surfels, seed: u64, skip_margin: f32) -> Vec<Ray> {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut rays = Vec::with_capacity(2048 * 64);
    for _ in 0..2048 {
        let i = rng.random_range(0..s.len());
        let n = s.normal(i);
        let m = s.means[i];
        let skip_below = if skip_margin > 0.0 { crate::trace::skip_plane_above(n, m, skip_margin) } else { [0.0; 4] };
        for _ in 0..64 {
            let mut d = random_unit(&mut rng);
            if d[0] * n[0] + d[1] * n[1] + d[2] * n[2] < 0.0 {
                d = d.map(|x| -x);
            }
            rays.push(Ray { origin: s.means[i], dir: d, skip_below });
        }
    }
    rays
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// This process's user + system CPU seconds (Linux /proc, clock ticks of 10 ms); 0 elsewhere.
fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else { return 0.0 };
    // Fields after the ")" that ends the command name: utime and stime are the 12th and 13th.
    let rest = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |k: usize| f.get(k).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

/// Median wall seconds of `reps` runs, and the mean CPU seconds per run (the machine is shared:
/// CPU time / threads estimates the wall time on idle cores).
fn time<F: FnMut()>(reps: usize, mut f: F) -> (f64, f64) {
    f(); // warm-up
    let c0 = cpu_seconds();
    let wall = median(
        (0..reps)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64()
            })
            .collect(),
    );
    (wall, (cpu_seconds() - c0) / reps as f64)
}

pub fn run(args: &TraceBenchArgs) -> anyhow::Result<()> {
    anyhow::ensure!((1..=crate::trace::MAX_CHUNK).contains(&args.chunk), "bench trace: --chunk must be 1..=64");
    anyhow::ensure!(
        args.skip_margin.is_finite() && args.skip_margin >= 0.0,
        "bench trace: --skip-margin must be finite and ≥ 0"
    );
    anyhow::ensure!((0.0..=45.0).contains(&args.grazing), "bench trace: --grazing must be in [0, 45] degrees");
    let grazing_sin = args.grazing.to_radians().sin();
    let settings = TraceSettings {
        chunk: args.chunk,
        grazing_sin,
        linear_radiance: args.linear_radiance,
        ..TraceSettings::default()
    };
    let scenes: Vec<(&str, Surfels)> = match (&args.ply, args.scene) {
        (Some(path), _) => vec![("ply", crate::io::ply::read_ply(path)?)],
        (None, SceneChoice::Surface) => vec![("surface", scene("surface", 7))],
        (None, SceneChoice::Volume) => vec![("volume", scene("volume", 7))],
        (None, SceneChoice::Both) => vec![("surface", scene("surface", 7)), ("volume", scene("volume", 7))],
    };
    anyhow::ensure!(scenes.iter().all(|(_, s)| !s.is_empty()), "bench trace: the scene has no surfels");
    let reps = args.repeats;
    println!(
        "radiogs bench trace: {} threads, {} surfels, 2048 × 64 hemisphere rays from surfel centres{}",
        rayon::current_num_threads(),
        scenes[0].1.len(),
        if args.linear_radiance { ", colours decoded to linear" } else { "" }
    );
    for (kind, s) in scenes {
        let rays = hemisphere_rays(&s, 8, args.skip_margin);
        let nr = rays.len() as f64;
        let build = time(5, || {
            std::hint::black_box(Tracer::build(&s, &settings));
        });
        let mut tracer = Tracer::build(&s, &settings);
        // Refit after a small optimiser-like step on every surfel.
        let mut moved = s.clone();
        let mut rng = Pcg64::seed_from_u64(9);
        for m in moved.means.iter_mut() {
            for a in m.iter_mut() {
                *a += rng.random_range(-1e-3..1e-3f32);
            }
        }
        let refit = time(10, || tracer.refit(&moved));
        tracer.refit(&s);
        let mut out = vec![RayOutput::default(); rays.len()];
        let fwd = time(reps, || trace(&tracer, &s, &rays, None, &mut out, None));
        let mean_alpha = out.iter().map(|o| 1.0 - o.transmittance as f64).sum::<f64>() / nr;
        let done = out.iter().filter(|o| o.transmittance < settings.min_transmittance).count() as f64 / nr;
        let grads =
            vec![RayGrad { v_radiance: [1.0; 3], v_transmittance: 1.0, v_depth: 0.1, v_normal: [0.1; 3] }; rays.len()];
        let mut v = s.zeros_like();
        let bwd = time(reps.div_ceil(2), || trace_backward(&tracer, &s, &rays, None, &grads, None, &mut v, None, None));
        // The consistency step's path: the forward keeps its hits, the backward replays them.
        let mut record = HitRecord::default();
        let fwd_rec = time(reps, || trace_recorded(&tracer, &s, &rays, &mut out, &mut record));
        let bwd_rec =
            time(reps.div_ceil(2), || trace_backward_recorded(&tracer, &s, &rays, &grads, &mut v, None, &record));
        let closest = time(reps, || {
            let hits: usize =
                rays.par_iter().with_min_len(32).filter(|r| tracer.closest_hit(r.origin, r.dir).is_some()).count();
            std::hint::black_box(hits);
        });
        let th = rayon::current_num_threads() as f64;
        // M rays/s, wall and CPU-time estimate; a time below the clock's resolution (tiny
        // scenes: CPU time counts in ticks) has no rate.
        let rate = |t: (f64, f64)| {
            let show = |secs: f64| {
                if secs > 0.0 { format!("{:8.3} M rays/s", nr / secs / 1e6) } else { format!("{:>17}", "(too short)") }
            };
            (show(t.0), show(t.1 / th))
        };
        let fb = (fwd.0 + bwd.0, fwd.1 + bwd.1);
        println!(
            "{kind}: {} nodes, mean alpha {mean_alpha:.3}, rays reaching T < {}: {:.1}%",
            tracer.node_count(),
            settings.min_transmittance,
            done * 100.0
        );
        println!("  (wall | CPU-time/threads estimate for idle cores)");
        println!("  build            {:8.1} ms | {:8.1} ms", build.0 * 1e3, build.1 / th * 1e3);
        println!("  refit            {:8.2} ms | {:8.2} ms", refit.0 * 1e3, refit.1 / th * 1e3);
        let f = rate(fwd);
        println!("  forward          {} | {}", f.0, f.1);
        let f = rate(fb);
        println!("  forward+backward {} | {}", f.0, f.1);
        let f = rate(bwd);
        println!("  backward alone   {} | {}", f.0, f.1);
        let f = rate((fwd_rec.0 + bwd_rec.0, fwd_rec.1 + bwd_rec.1));
        println!("  recorded fwd+bwd {} | {}", f.0, f.1);
        let f = rate(bwd_rec);
        println!("  replayed bwd     {} | {}", f.0, f.1);
        let f = rate(closest);
        println!("  closest-hit      {} | {}", f.0, f.1);
        let ratio = |a: f64, b: f64| if b > 0.0 { format!("{:.2}x", a / b) } else { "(too short)".to_string() };
        println!("  forward / closest-hit time: {} (wall) {} (CPU)", ratio(fwd.0, closest.0), ratio(fwd.1, closest.1));
    }
    Ok(())
}
