//! Losses and regularisers, each with a hand-written backward pass beside its forward.
//!
//! Conventions shared by every loss here:
//! - images are pixel-major (`&[[f32; 3]]` colour or `&[f32]` single channel), width × height,
//!   row 0 at the top, pixel (x, y) at `y * width + x`;
//! - a loss returns its (unweighted) value and **accumulates** `weight · ∂loss/∂input` into the
//!   caller's `v_<name>` buffers (`v += weight · grad`), so several weighted losses can share one
//!   gradient image; zero the buffers once per iteration. Nothing is allocated per call beyond
//!   the reusable scratch structs (`Ssim`, `NormalConsistency`, `EdgeAwareSmoothness`).

pub mod env_prior;
pub mod l1;
pub mod mask;
pub mod normal_consistency;
pub mod normal_dispersion;
pub mod opacity_entropy;
pub mod sh_rest;
pub mod smoothness;
pub mod ssim;

pub use env_prior::{env_tv, white_light_prior};
pub use l1::{l1_gray, l1_rgb};
pub use mask::{mask_bce, mask_entropy};
pub use normal_consistency::{NormalConsistency, depth_to_normal};
pub use normal_dispersion::normal_dispersion;
pub use opacity_entropy::opacity_entropy;
pub use sh_rest::sh_rest_energy;
pub use smoothness::EdgeAwareSmoothness;
pub use ssim::{Ssim, psnr, psnr_masked, ssim_eval};

/// Timing helpers for the ignored benchmark tests: the machine is shared, so next to wall time
/// they report this process's CPU time (utime + stime from /proc/self/stat, 10 ms ticks).
#[cfg(test)]
pub(crate) mod bench_util {
    pub fn process_cpu_seconds() -> f64 {
        let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
        let rest = s.rsplit_once(')').map_or("", |(_, r)| r);
        let f: Vec<&str> = rest.split_whitespace().collect();
        let tick = |k: usize| f.get(k).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
        (tick(11) + tick(12)) / 100.0
    }

    /// (wall ms, CPU ms) per call of `f`, after 3 warm-up calls.
    pub fn time_ms(iters: usize, mut f: impl FnMut()) -> (f64, f64) {
        for _ in 0..3 {
            f();
        }
        let c = process_cpu_seconds();
        let t = std::time::Instant::now();
        for _ in 0..iters {
            f();
        }
        let wall = t.elapsed().as_secs_f64() * 1e3 / iters as f64;
        (wall, (process_cpu_seconds() - c) * 1e3 / iters as f64)
    }
}

#[cfg(test)]
mod bench {
    use super::bench_util::time_ms;
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// Per-call cost of the other losses on a 200² view (release):
    /// `cargo test --release --lib loss::bench -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn bench_losses_200() {
        let (w, h) = (200usize, 200usize);
        let n = w * h;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let img: Vec<[f32; 3]> = (0..n).map(|_| [rng.random(), rng.random(), rng.random()]).collect();
        let gt: Vec<[f32; 3]> = (0..n).map(|_| [rng.random(), rng.random(), rng.random()]).collect();
        let alpha: Vec<f32> = (0..n).map(|_| rng.random()).collect();
        let depth: Vec<f32> = (0..n).map(|_| 3.0 + 0.01 * rng.random::<f32>()).collect();
        let cam = crate::camera::Camera::look_at("b", glam::Vec3::new(0.0, -4.0, 1.0), glam::Vec3::ZERO, 200, 200, 0.7);
        let mut v3 = vec![[0.0f32; 3]; n];
        let mut v1 = vec![0.0f32; n];
        for threads in [1usize, 2] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| {
                let l1 = time_ms(200, || {
                    std::hint::black_box(l1_rgb(&img, &gt, Some(&alpha), 0.8, &mut v3));
                });
                let bce = time_ms(200, || {
                    std::hint::black_box(mask_bce(&alpha, &alpha, 1.0, &mut v1));
                });
                let mut nc = NormalConsistency::new();
                let ncm = time_ms(100, || {
                    std::hint::black_box(nc.loss(&cam, &depth, &img, Some(&alpha), Some(&alpha), 0.05, &mut v1, &mut v3));
                });
                let mut sm = EdgeAwareSmoothness::new();
                sm.prepare(&gt, w, h);
                let smp = time_ms(50, || {
                    std::hint::black_box(sm.loss_prepared(img.as_flattened(), 3, Some(&alpha), 0.2, v3.as_flattened_mut()));
                });
                let smm = time_ms(50, || {
                    std::hint::black_box(sm.loss(img.as_flattened(), 3, &gt, w, h, Some(&alpha), 0.2, v3.as_flattened_mut()));
                });
                let sm1 = time_ms(50, || {
                    std::hint::black_box(sm.loss(&alpha, 1, &gt, w, h, Some(&alpha), 0.1, &mut v1));
                });
                let env: Vec<[f32; 3]> = (0..64 * 128).map(|_| [rng.random(), rng.random(), rng.random()]).collect();
                let mut venv = vec![[0.0f32; 3]; 64 * 128];
                let envm = time_ms(200, || {
                    std::hint::black_box(env_tv(&env, 128, 64, 0.02, &mut venv));
                    std::hint::black_box(white_light_prior(&env, 0.01, &mut venv));
                });
                println!(
                    "200x200, {threads} thread(s), (wall ms, process CPU ms) per call: l1 {l1:.3?}, mask bce {bce:.3?}, \
                     normal consistency {ncm:.3?}, smoothness rgb {smm:.3?}, smoothness rgb with prepared weights {smp:.3?}, smoothness 1ch {sm1:.3?}, \
                     env tv+white 64x128 {envm:.3?}"
                );
            });
        }
    }
}
