//! The shared core of the albedo priors that pull each surfel towards the mean albedo of its
//! neighbourhood of bins: on the SH colour's chromaticity plane (`albedo_chroma.rs`) and in
//! space (`albedo_voxel.rs`).
//!
//! Each taking-part surfel i has a bin and a weight w_i (opacity × disk area, so the visible
//! layer sets the targets); its target ā(i) is the w-weighted mean albedo over its bin's
//! neighbourhood. Loss = λ · Σ_i w_i Σ_c min(|a_ic − ā_c(i)|, cap) / Σ_i w_i, with the gradient
//! through ā too; a finite cap lets differences beyond it (edges between materials) go free.
//! Neighbourhoods must be symmetric (k is around j exactly when j is around k): the gradient
//! through the targets gathers over the same neighbourhoods.

use crate::surfels::Surfels;

/// Surfels below this opacity carry colours nothing constrains (BENCHMARKS.md session 29).
pub const MIN_OPACITY: f32 = 0.3;

/// A surfel that takes no part in the prior.
pub const OUT: u32 = u32::MAX;

/// Bins and their neighbourhoods: `gather` sums each bin's neighbourhood (itself included).
pub trait Neighbourhoods {
    fn bins(&self) -> usize;
    fn gather<const N: usize>(&self, per_bin: &[[f64; N]], out: &mut Vec<[f64; N]>);
}

/// A surfel's share of what is seen: opacity × disk area.
pub fn surfel_weight(surfels: &Surfels, i: usize) -> f32 {
    let s = surfels.scale(i);
    surfels.opacity(i) * s[0] * s[1]
}

/// Buffers of the loss, kept between iterations.
#[derive(Default)]
pub struct BinnedMean {
    /// Per bin: Σ w·a (3) and Σ w, then the same summed over each neighbourhood.
    sums: Vec<[f64; 4]>,
    around: Vec<[f64; 4]>,
    /// Per bin: Σ w_i·sign(a_i − ā) / W over its surfels, per channel (for ā's gradient).
    pull: Vec<[f64; 3]>,
    /// `pull` summed over each bin's neighbourhood.
    pull_around: Vec<[f64; 3]>,
}

impl BinnedMean {
    /// The loss (λ included) for surfels in bins `bin` (or [`OUT`]) with weights `weight`, each
    /// channel's difference capped at `cap` (infinite: plain L1); its gradient is added to
    /// `v_albedo` (per surfel, albedo units).
    pub fn loss(
        &mut self,
        bin: &[u32],
        weight: &[f32],
        bins: &impl Neighbourhoods,
        albedo: &[[f32; 3]],
        lambda: f32,
        cap: f32,
        v_albedo: &mut [[f32; 3]],
    ) -> f32 {
        let cap = cap as f64;
        self.sums.clear();
        self.sums.resize(bins.bins(), [0.0; 4]);
        let mut total_weight = 0.0f64;
        for (i, (&k, &w)) in bin.iter().zip(weight).enumerate() {
            if k == OUT {
                continue;
            }
            let sums = &mut self.sums[k as usize];
            for ch in 0..3 {
                sums[ch] += (w * albedo[i][ch]) as f64;
            }
            sums[3] += w as f64;
            total_weight += w as f64;
        }
        if total_weight <= 0.0 {
            return 0.0;
        }
        bins.gather(&self.sums, &mut self.around);
        let scale = lambda as f64 / total_weight;
        let mut loss = 0.0f64;
        self.pull.clear();
        self.pull.resize(bins.bins(), [0.0; 3]);
        for (i, (&k, &w)) in bin.iter().zip(weight).enumerate() {
            if k == OUT {
                continue;
            }
            let (target, w) = (&self.around[k as usize], w as f64);
            for ch in 0..3 {
                let d = albedo[i][ch] as f64 - target[ch] / target[3];
                loss += w * d.abs().min(cap);
                let sign = if d.abs() >= cap {
                    0.0
                } else if d > 0.0 {
                    1.0
                } else if d < 0.0 {
                    -1.0
                } else {
                    0.0
                };
                v_albedo[i][ch] += (scale * w * sign) as f32;
                self.pull[k as usize][ch] += w * sign / target[3];
            }
        }
        // Through the targets: ā of bin k moves with every a_j around k by w_j / W_k, so surfel
        // j receives −w_j Σ over the bins k around its own of pull_k.
        bins.gather(&self.pull, &mut self.pull_around);
        for (i, (&k, &w)) in bin.iter().zip(weight).enumerate() {
            if k == OUT {
                continue;
            }
            let (w, around) = (w as f64, &self.pull_around[k as usize]);
            for ch in 0..3 {
                v_albedo[i][ch] -= (scale * w * around[ch]) as f32;
            }
        }
        (scale * loss) as f32
    }
}

/// Test helper: the gradient of `loss(albedo, grad)` against f64 central differences of it, per
/// albedo component. Components within eps of a kink of |·| (the one-sided slopes disagree) are
/// skipped; returns (checked, kinks).
#[cfg(test)]
pub fn check_gradient(
    albedo: &[[f32; 3]],
    mut loss: impl FnMut(&[[f32; 3]], &mut [[f32; 3]]) -> f32,
) -> (usize, usize) {
    let mut grad = vec![[0.0f32; 3]; albedo.len()];
    loss(albedo, &mut grad);
    let (mut checked, mut kinks) = (0, 0);
    let eps = 1e-3;
    for i in 0..albedo.len() {
        for ch in 0..3 {
            let mut f = |delta: f32| {
                let mut a = albedo.to_vec();
                a[i][ch] += delta;
                loss(&a, &mut vec![[0.0f32; 3]; albedo.len()]) as f64
            };
            let (lo, mid, hi) = (f(-eps), f(0.0), f(eps));
            let (left, right) = ((mid - lo) / eps as f64, (hi - mid) / eps as f64);
            if (left - right).abs() > 1e-3 {
                kinks += 1;
                continue;
            }
            checked += 1;
            let fd = (hi - lo) / (2.0 * eps as f64);
            let an = grad[i][ch] as f64;
            assert!((fd - an).abs() < 5e-4 + 1e-2 * an.abs(), "surfel {i} ch {ch}: fd {fd} analytic {an}");
        }
    }
    (checked, kinks)
}

/// Test helper: `n` surfels in a unit box with random opacities (some under [`MIN_OPACITY`]),
/// scales and albedos.
#[cfg(test)]
pub fn random_surfels(n: usize, seed: u64) -> (Surfels, Vec<[f32; 3]>) {
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut s = Surfels::random_in_box(n, [0.0; 3], [1.0; 3], seed);
    let mut albedo = Vec::new();
    for i in 0..s.len() {
        s.opacity_logits[i] = rng.random_range(-0.5..3.0);
        s.log_scales[i] = [rng.random_range(-3.0..-1.0), rng.random_range(-3.0..-1.0)];
        albedo.push([0; 3].map(|_| rng.random_range(0.05..0.8)));
    }
    (s, albedo)
}
