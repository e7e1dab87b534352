//! Adaptive density control, as 2DGS (`gaussian_model.py`: densify_and_clone, densify_and_split,
//! prune_points, reset_opacity; `train.py` for the schedule).
//!
//! Statistics: per surfel, the norm of its view-space (NDC) positional gradient is accumulated
//! over the views in which it is visible, with a view count, and the maximum screen radius.
//! `densify_and_prune`, with ḡ = accum / count (0 when never seen) and s_max = max(s_u, s_v):
//! - clone: ḡ ≥ threshold and s_max ≤ percent_dense · extent → an identical copy is appended;
//! - split: ḡ ≥ threshold and s_max > percent_dense · extent (original surfels only, not the
//!   clones); with `abs_grad_threshold` > 0 (AbsGS, as PGSR and GOF use it) the split test is
//!   instead ḡ_abs ≥ abs_grad_threshold, ḡ_abs the mean of the homodirectional statistic
//!   (per pixel |∂L/∂μ₂D| summed, so the pixels of a large surfel that pull its centre opposite
//!   ways do not cancel: on textureless walls such surfels otherwise never split) → 2 new surfels at μ + z_u s_u t_u + z_v s_v t_v (z ~ N(0, 1): a sample of the 2D
//!   Gaussian in its tangent plane), scales / (0.8 · 2), other parameters copied; the original
//!   is removed;
//! - prune: opacity < min_opacity, and when `max_screen_size` is given (2DGS: 20 px after the
//!   first opacity reset) also max screen radius > max_screen_size or s_max > 0.1 · extent.
//!
//! New surfels get zero Adam moments (2DGS `cat_tensors_to_optimizer` appends zeros) and zero
//! max radius; surviving surfels keep their moments; the gradient accumulators are reset to zero
//! afterwards (2DGS `densification_postfix`). Final order: kept originals, clones, split samples.
//! `reset_opacity`: opacity ← min(opacity, cap) in logit space (2DGS: cap 0.01; radiogs's default
//! `opacity_reset_cap` 0.2), opacity moments zeroed.
//! Serial over surfels (it runs every 100 iterations); random numbers from the caller's Pcg64
//! in a fixed order, so a seed gives one result.

use crate::optim::SurfelAdam;
use crate::surfels::{Surfels, logit, rotation_from_quat, sigmoid};
use rand::RngExt;

/// Per-surfel densification statistics, row-aligned with the surfels.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DensifyStats {
    /// Σ over views of |∂L/∂μ_ndc| (2D view-space positional gradient, NDC units as 3DGS/2DGS:
    /// the pixel-space gradient times (W/2, H/2)).
    pub grad_accum: Vec<f32>,
    /// Σ over views of the AbsGS statistic |(Σ_pixels |∂L_p/∂x|, Σ_pixels |∂L_p/∂y|)| (NDC units).
    pub abs_accum: Vec<f32>,
    /// Number of views in which the surfel was visible.
    pub denom: Vec<f32>,
    /// Largest screen-space radius (pixels) seen since the last densification.
    pub max_radii: Vec<f32>,
}

impl DensifyStats {
    pub fn new(n: usize) -> Self {
        DensifyStats { grad_accum: vec![0.0; n], abs_accum: vec![0.0; n], denom: vec![0.0; n], max_radii: vec![0.0; n] }
    }

    pub fn len(&self) -> usize {
        self.denom.len()
    }
    pub fn is_empty(&self) -> bool {
        self.denom.is_empty()
    }

    /// Add one view: `v_means2d_ndc[i]` the 2D positional gradient of surfel i (NDC units),
    /// `v_abs_ndc[i]` its AbsGS per-axis sums of per-pixel absolute values (same units), `radii[i]`
    /// its screen radius in pixels (≤ 0: not visible in this view, ignored).
    pub fn add_view(&mut self, v_means2d_ndc: &[[f32; 2]], v_abs_ndc: &[[f32; 2]], radii: &[f32]) {
        assert_eq!(v_means2d_ndc.len(), self.len());
        assert_eq!(v_abs_ndc.len(), self.len());
        assert_eq!(radii.len(), self.len());
        for i in 0..self.len() {
            if radii[i] > 0.0 {
                let g = v_means2d_ndc[i];
                self.grad_accum[i] += (g[0] * g[0] + g[1] * g[1]).sqrt();
                let a = v_abs_ndc[i];
                self.abs_accum[i] += (a[0] * a[0] + a[1] * a[1]).sqrt();
                self.denom[i] += 1.0;
                self.max_radii[i] = self.max_radii[i].max(radii[i]);
            }
        }
    }

    /// Mean accumulated gradient per surfel (0 where never visible).
    pub fn mean_grad(&self, i: usize) -> f32 {
        if self.denom[i] > 0.0 { self.grad_accum[i] / self.denom[i] } else { 0.0 }
    }

    /// Mean accumulated AbsGS statistic per surfel (0 where never visible).
    pub fn mean_abs_grad(&self, i: usize) -> f32 {
        if self.denom[i] > 0.0 { self.abs_accum[i] / self.denom[i] } else { 0.0 }
    }

    fn retain_mask(&mut self, keep: &[bool]) {
        let mut k = keep.iter();
        self.max_radii.retain(|_| *k.next().unwrap());
        let n = self.max_radii.len();
        self.grad_accum.clear();
        self.grad_accum.resize(n, 0.0);
        self.abs_accum.clear();
        self.abs_accum.resize(n, 0.0);
        self.denom.clear();
        self.denom.resize(n, 0.0);
    }
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DensifyConfig {
    /// ḡ threshold for clone/split (2DGS densify_grad_threshold 2e-4).
    pub grad_threshold: f32,
    /// ḡ_abs threshold for split (AbsGS: 8e-4); 0 = split on ḡ as 2DGS.
    pub abs_grad_threshold: f32,
    /// Prune below this opacity (0.05).
    pub min_opacity: f32,
    /// Clone/split boundary as a fraction of the scene extent (0.01).
    pub percent_dense: f32,
    /// World-space prune: s_max > this · extent (0.1).
    pub world_size_factor: f32,
}

impl Default for DensifyConfig {
    fn default() -> Self {
        DensifyConfig {
            grad_threshold: 2e-4,
            abs_grad_threshold: 0.0,
            min_opacity: 0.05,
            percent_dense: 0.01,
            world_size_factor: 0.1,
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DensifyReport {
    pub before: usize,
    pub cloned: usize,
    /// Originals that were split (each replaced by 2 samples).
    pub split: usize,
    /// Surfels removed by the prune rules (not counting split originals).
    pub pruned: usize,
    pub after: usize,
}

/// Standard normal sample (Box–Muller, one of the pair).
fn normal(rng: &mut rand_pcg::Pcg64) -> f32 {
    let u1 = 1.0 - rng.random::<f32>(); // (0, 1]
    let u2 = rng.random::<f32>();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f32::consts::PI * u2).cos()
}

/// Clone, split and prune (2DGS `densify_and_prune`); optimiser moments and statistics stay
/// row-aligned with the surfels. `max_screen_size`: Some(20.0) after the first opacity reset.
pub fn densify_and_prune(
    surfels: &mut Surfels,
    adam: &mut SurfelAdam,
    stats: &mut DensifyStats,
    cfg: &DensifyConfig,
    extent: f32,
    max_screen_size: Option<f32>,
    rng: &mut rand_pcg::Pcg64,
) -> DensifyReport {
    let n0 = surfels.len();
    assert!(adam.len() == n0 && stats.len() == n0, "optimiser state or statistics misaligned with surfels");
    let big = cfg.percent_dense * extent;
    let max_scale = |s: &Surfels, i: usize| s.log_scales[i][0].max(s.log_scales[i][1]).exp();
    let mut clone_idx = Vec::new();
    let mut split_idx = Vec::new();
    let mut split_sel = vec![false; n0];
    let use_abs = cfg.abs_grad_threshold > 0.0;
    for i in 0..n0 {
        let small = max_scale(surfels, i) <= big;
        let clone = small && stats.mean_grad(i) >= cfg.grad_threshold;
        let split = !small
            && if use_abs {
                stats.mean_abs_grad(i) >= cfg.abs_grad_threshold
            } else {
                stats.mean_grad(i) >= cfg.grad_threshold
            };
        if clone {
            clone_idx.push(i);
        } else if split {
            split_idx.push(i);
            split_sel[i] = true;
        }
    }
    surfels.append_copies(&clone_idx);
    // Split samples, sample-major as torch `repeat(N, 1)`: [all selected] × 2.
    let first_split = surfels.len();
    let rep: Vec<usize> = split_idx.iter().chain(split_idx.iter()).copied().collect();
    surfels.append_copies(&rep);
    let shrink = (0.8f32 * 2.0).ln();
    for (k, &i) in rep.iter().enumerate() {
        let r = first_split + k;
        let rot = rotation_from_quat(surfels.quats[i]);
        let s = surfels.scale(i);
        let (zu, zv) = (normal(rng), normal(rng));
        for c in 0..3 {
            surfels.means[r][c] += zu * s[0] * rot[0][c] + zv * s[1] * rot[1][c];
        }
        surfels.log_scales[r] = [surfels.log_scales[i][0] - shrink, surfels.log_scales[i][1] - shrink];
    }
    let added = clone_idx.len() + rep.len();
    adam.append_zeros(added);
    stats.max_radii.resize(n0 + added, 0.0);

    let n = surfels.len();
    let mut keep = vec![true; n];
    let mut pruned = 0;
    for i in 0..n {
        if i < n0 && split_sel[i] {
            keep[i] = false;
            continue;
        }
        let mut p = surfels.opacity(i) < cfg.min_opacity;
        if let Some(mss) = max_screen_size {
            p |= stats.max_radii[i] > mss || max_scale(surfels, i) > cfg.world_size_factor * extent;
        }
        if p {
            keep[i] = false;
            pruned += 1;
        }
    }
    surfels.retain_mask(&keep);
    adam.retain_mask(&keep);
    stats.retain_mask(&keep);
    DensifyReport { before: n0, cloned: clone_idx.len(), split: split_idx.len(), pruned, after: surfels.len() }
}

/// Remove the surfels whose flag is set, keeping optimiser state and statistics aligned.
pub fn prune_points(surfels: &mut Surfels, adam: &mut SurfelAdam, stats: &mut DensifyStats, remove: &[bool]) {
    let keep: Vec<bool> = remove.iter().map(|r| !r).collect();
    surfels.retain_mask(&keep);
    adam.retain_mask(&keep);
    stats.retain_mask(&keep);
}

/// Opacity reset (2DGS): opacity ← min(opacity, `cap`) (cap 0.01), opacity moments zeroed.
pub fn reset_opacity(surfels: &mut Surfels, adam: &mut SurfelAdam, cap: f32) {
    for o in surfels.opacity_logits.iter_mut() {
        *o = logit(sigmoid(*o).min(cap));
    }
    adam.reset_opacity_state();
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::LearningRates;
    use rand::SeedableRng;

    /// 12 surfels: per row a tag in roughness_logits (and its moments), sizes and gradients chosen
    /// so that rows 0–2 clone, 3–5 split, 6 is pruned for opacity, 7 for screen size, 8 for world
    /// size, 9 is never seen, 10–11 stay.
    fn setup() -> (Surfels, SurfelAdam, DensifyStats) {
        let mut s = Surfels::default();
        let small = 0.005; // ≤ 0.01 · extent (extent 1)
        let large = 0.05;
        for i in 0..12 {
            let sc = if (3..6).contains(&i) || i == 11 { large } else { small };
            let opacity = if i == 6 { 0.01 } else { 0.5 };
            let q = crate::surfels::quat_with_normal([0.3 * i as f32, 1.0, 0.5]);
            s.push([i as f32, 0.1 * i as f32, -0.2], [sc, 0.6 * sc], q, opacity, [0.5; 3], [0.3; 3], 0.5);
            s.roughness_logits[i] = 100.0 + i as f32;
        }
        s.log_scales[8] = [(0.2f32).ln(), (0.01f32).ln()]; // world-space huge
        let mut adam = SurfelAdam::new(&s, LearningRates::default());
        for i in 0..12 {
            adam.m.roughness_logits[i] = 1000.0 + i as f32;
            adam.v.roughness_logits[i] = 2000.0 + i as f32;
        }
        let mut st = DensifyStats::new(12);
        for i in 0..12 {
            st.grad_accum[i] = if i < 6 { 3e-4 * 2.0 } else { 1e-4 * 2.0 };
            st.denom[i] = if i == 9 { 0.0 } else { 2.0 };
            st.max_radii[i] = if i == 7 { 25.0 } else { 5.0 };
        }
        st.grad_accum[9] = 1.0; // never visible: mean gradient 0, no densification
        (s, adam, st)
    }

    #[test]
    fn optimiser_rows_follow_their_surfels() {
        let (mut s, mut adam, mut st) = setup();
        let orig = s.clone();
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let rep = densify_and_prune(&mut s, &mut adam, &mut st, &DensifyConfig::default(), 1.0, Some(20.0), &mut rng);
        assert_eq!(rep, DensifyReport { before: 12, cloned: 3, split: 3, pruned: 3, after: 12 - 3 - 3 + 3 + 6 });
        assert_eq!(adam.len(), s.len());
        assert_eq!(st.len(), s.len());
        // Kept originals (in order): 0, 1, 2, 9, 10, 11 with their own moments.
        let kept = [0usize, 1, 2, 9, 10, 11];
        for (row, &i) in kept.iter().enumerate() {
            assert_eq!(s.roughness_logits[row], 100.0 + i as f32);
            assert_eq!(adam.m.roughness_logits[row], 1000.0 + i as f32);
            assert_eq!(adam.v.roughness_logits[row], 2000.0 + i as f32);
            assert_eq!(s.means[row], orig.means[i]);
            assert_eq!(st.max_radii[row], 5.0);
        }
        // Then the clones of 0, 1, 2 (exact copies, fresh state), then split samples of 3, 4, 5 ×2.
        let new_src = [0usize, 1, 2, 3, 4, 5, 3, 4, 5];
        for (k, &i) in new_src.iter().enumerate() {
            let row = kept.len() + k;
            assert_eq!(s.roughness_logits[row], 100.0 + i as f32);
            assert_eq!(adam.m.roughness_logits[row], 0.0);
            assert_eq!(adam.v.roughness_logits[row], 0.0);
            assert_eq!(adam.m.means[row], [0.0; 3]);
            assert_eq!(st.max_radii[row], 0.0);
            if k < 3 {
                assert_eq!(s.means[row], orig.means[i]);
                assert_eq!(s.log_scales[row], orig.log_scales[i]);
            } else {
                assert_ne!(s.means[row], orig.means[i]);
            }
        }
        // Accumulators reset.
        assert!(st.grad_accum.iter().all(|&g| g == 0.0) && st.denom.iter().all(|&d| d == 0.0));
    }

    #[test]
    fn split_samples_lie_in_the_tangent_plane_with_shrunk_scales() {
        let mut s = Surfels::default();
        let mut normals = Vec::new();
        for i in 0..50 {
            let n = glam::Vec3::new((i as f32).sin(), (1.3 * i as f32).cos(), 0.4).normalize();
            normals.push(n);
            s.push(
                [0.0, 0.0, i as f32],
                [0.3, 0.1],
                crate::surfels::quat_with_normal(n.to_array()),
                0.5,
                [0.5; 3],
                [0.3; 3],
                0.5,
            );
        }
        let mut adam = SurfelAdam::new(&s, LearningRates::default());
        let mut st = DensifyStats::new(50);
        st.grad_accum.fill(1.0);
        st.denom.fill(1.0);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(2);
        let rep = densify_and_prune(&mut s, &mut adam, &mut st, &DensifyConfig::default(), 1.0, None, &mut rng);
        assert_eq!(rep.split, 50);
        assert_eq!(s.len(), 100);
        let (mut su, mut sv) = (0.0f64, 0.0f64);
        for r in 0..100 {
            let i = r % 50;
            let mu = glam::Vec3::new(0.0, 0.0, i as f32);
            let d = glam::Vec3::from(s.means[r]) - mu;
            assert!(d.dot(normals[i]).abs() < 1e-5, "sample {r} leaves the plane");
            assert!(d.length() > 0.0);
            let sc = s.scale(r);
            assert!((sc[0] - 0.3 / 1.6).abs() < 1e-6 && (sc[1] - 0.1 / 1.6).abs() < 1e-6);
            let rot = rotation_from_quat(s.quats[r]);
            su += (d.dot(glam::Vec3::from(rot[0])) as f64 / 0.3).powi(2);
            sv += (d.dot(glam::Vec3::from(rot[1])) as f64 / 0.1).powi(2);
        }
        // Offsets are N(0, s²) along each tangent axis: normalised variances near 1.
        assert!((su / 100.0 - 1.0).abs() < 0.4 && (sv / 100.0 - 1.0).abs() < 0.4, "{su} {sv}");
    }

    #[test]
    fn prune_removes_exactly_the_right_surfels() {
        // No densification (zero gradients): only the prune rules act.
        for mss in [None, Some(20.0)] {
            let (mut s, mut adam, mut st) = setup();
            st.grad_accum.fill(0.0);
            let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
            let rep = densify_and_prune(&mut s, &mut adam, &mut st, &DensifyConfig::default(), 1.0, mss, &mut rng);
            let expect: Vec<f32> = match mss {
                None => (0..12).filter(|&i| i != 6).map(|i| 100.0 + i as f32).collect(),
                Some(_) => (0..12).filter(|&i| ![6, 7, 8].contains(&i)).map(|i| 100.0 + i as f32).collect(),
            };
            assert_eq!(s.roughness_logits, expect);
            assert_eq!(rep.pruned, 12 - expect.len());
            let m_expect: Vec<f32> = expect.iter().map(|t| t + 900.0).collect();
            assert_eq!(adam.m.roughness_logits, m_expect);
        }
        // prune_points keeps everything aligned too.
        let (mut s, mut adam, mut st) = setup();
        let remove: Vec<bool> = (0..12).map(|i| i % 2 == 0).collect();
        prune_points(&mut s, &mut adam, &mut st, &remove);
        assert_eq!(s.roughness_logits, vec![101.0, 103.0, 105.0, 107.0, 109.0, 111.0]);
        assert_eq!(adam.v.roughness_logits, vec![2001.0, 2003.0, 2005.0, 2007.0, 2009.0, 2011.0]);
    }

    #[test]
    fn deterministic_per_seed() {
        let run = |seed| {
            let (mut s, mut adam, mut st) = setup();
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            densify_and_prune(&mut s, &mut adam, &mut st, &DensifyConfig::default(), 1.0, Some(20.0), &mut rng);
            s
        };
        assert_eq!(run(5), run(5));
        assert_ne!(run(5), run(6));
    }

    /// With the AbsGS threshold the homodirectional statistic decides the splits (large
    /// surfels) and only those: clones still follow the plain gradient.
    #[test]
    fn abs_gradient_decides_splits_only() {
        let (mut s, mut adam, mut st) = setup();
        // Large: 3, 4, 5 (plain gradient above), 11 (below). Small 7: plain below, abs above.
        for i in 0..12 {
            st.abs_accum[i] = 2.0 * if [4, 5, 7, 11].contains(&i) { 1e-3 } else { 1e-4 };
        }
        let cfg = DensifyConfig { abs_grad_threshold: 8e-4, ..DensifyConfig::default() };
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let r = densify_and_prune(&mut s, &mut adam, &mut st, &cfg, 1.0, None, &mut rng);
        // Clones 0, 1, 2 (small, plain ≥ 2e-4); splits 4, 5, 11 (large, abs ≥ 8e-4), not 3.
        assert_eq!((r.cloned, r.split), (3, 3));
        // Each split original is replaced by two samples; surfel 3 and the small 7 stay single.
        let count = |tag: f32| s.roughness_logits.iter().filter(|&&t| t == tag).count();
        for (tag, want) in [(100.0, 2), (103.0, 1), (104.0, 2), (105.0, 2), (107.0, 1), (111.0, 2)] {
            assert_eq!(count(tag), want, "surfel {}", tag - 100.0);
        }
    }

    #[test]
    fn stats_and_opacity_reset() {
        let mut st = DensifyStats::new(3);
        st.add_view(&[[3.0, 4.0], [1.0, 0.0], [9.0, 9.0]], &[[6.0, 8.0], [1.0, 0.0], [1.0, 1.0]], &[2.0, 7.0, 0.0]);
        st.add_view(&[[0.0, 1.0], [1.0, 0.0], [9.0, 9.0]], &[[0.0, 2.0], [0.0, 3.0], [1.0, 1.0]], &[4.0, 1.0, 0.0]);
        assert_eq!(st.grad_accum, vec![6.0, 2.0, 0.0]);
        assert_eq!(st.abs_accum, vec![12.0, 4.0, 0.0]);
        assert_eq!(st.mean_abs_grad(0), 6.0);
        assert_eq!(st.denom, vec![2.0, 2.0, 0.0]);
        assert_eq!(st.max_radii, vec![4.0, 7.0, 0.0]);
        assert_eq!(st.mean_grad(0), 3.0);
        assert_eq!(st.mean_grad(2), 0.0);

        let (mut s, mut adam, _) = setup();
        adam.m.opacity_logits.fill(1.0);
        adam.v.opacity_logits.fill(1.0);
        reset_opacity(&mut s, &mut adam, 0.01);
        for i in 0..s.len() {
            let o = s.opacity(i);
            assert!(o <= 0.01 + 1e-6);
            if i == 6 {
                assert!((o - 0.01).abs() < 1e-5); // 0.01 already: unchanged
            }
        }
        assert!(adam.m.opacity_logits.iter().chain(&adam.v.opacity_logits).all(|&v| v == 0.0));
        assert_eq!(adam.m.roughness_logits[3], 1003.0);

        // radiogs's default cap 0.2: opacities above it come down to it, those below stay.
        let (mut s, mut adam, _) = setup();
        reset_opacity(&mut s, &mut adam, 0.2);
        for i in 0..s.len() {
            let want = if i == 6 { 0.01 } else { 0.2 };
            assert!((s.opacity(i) - want).abs() < 1e-5, "row {i}: {}", s.opacity(i));
        }
    }
}

#[cfg(test)]
mod bench {
    use super::*;
    use crate::optim::LearningRates;
    use rand::SeedableRng;

    /// `cargo test --release --lib train::densify::bench -- --ignored --nocapture`
    #[test]
    #[ignore]
    fn bench_densify_50k() {
        let mut s = Surfels::random_in_box(50_000, [-1.0; 3], [1.0; 3], 1);
        let mut adam = SurfelAdam::new(&s, LearningRates::default());
        let mut st = DensifyStats::new(s.len());
        // About 10 % above the threshold.
        for i in 0..s.len() {
            st.grad_accum[i] = if i % 10 == 0 { 1e-3 } else { 1e-5 };
            st.denom[i] = 1.0;
        }
        let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
        let t = std::time::Instant::now();
        let rep = densify_and_prune(&mut s, &mut adam, &mut st, &DensifyConfig::default(), 2.0, Some(20.0), &mut rng);
        let ms = t.elapsed().as_secs_f64() * 1e3;
        println!("densify_and_prune, 50k surfels: {ms:.3} ms ({rep:?})");
    }
}
