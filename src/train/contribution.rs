//! Surfels that no training pixel sees: their largest blend weight w = α T over every pixel
//! of every training view. With `prune_contribution` > 0 (default 0) the inverse stage drops
//! those below it when it starts from the geometry stage.
//!
//! Why: a trained 2DGS surface is several translucent layers deep, and its hidden layers and
//! faint fringes stay in the scene: on the default spheres run 26 % of the 51k surfels never
//! reach a weight of 1/255 in any training pixel. They cost every later render, trace and
//! gradient (a relit frame blends them before its transmittance runs out) and their SH
//! colours and materials are fitted to nothing. Removing them changes the test views' pictures
//! by little (65 dB against the unpruned render at 1/255), but the inverse stage's metrics
//! end 0.1–0.4 dB lower (its rays pass where they were), so it is off by default
//! (BENCHMARKS.md, session 50).

use crate::camera::Camera;
use crate::raster::RasterSettings;
use crate::raster::blend_weights::BlendWeights;
use crate::surfels::Surfels;

/// Per surfel its largest blend weight over every pixel of `cameras` rendered with `settings`.
pub fn max_blend_weights(surfels: &Surfels, cameras: &[Camera], settings: &RasterSettings) -> Vec<f32> {
    let mut max_w = vec![0f32; surfels.len()];
    for cam in cameras {
        let bw = BlendWeights::compute(surfels, cam, settings);
        for (&id, &w) in bw.ids.iter().zip(&bw.weights) {
            let m = &mut max_w[id as usize];
            *m = m.max(w);
        }
    }
    max_w
}

/// Keep the surfels whose largest blend weight over `cameras` is at least `threshold`;
/// returns how many were dropped. A threshold of 0 keeps every surfel (and renders nothing).
/// Also drops the pruned surfels' entries of `flags` (one per surfel, or empty).
pub fn prune_unseen(
    surfels: &mut Surfels,
    cameras: &[Camera],
    settings: &RasterSettings,
    threshold: f32,
    flags: &mut Vec<bool>,
) -> usize {
    if !(threshold > 0.0) {
        return 0;
    }
    let max_w = max_blend_weights(surfels, cameras, settings);
    let keep: Vec<bool> = max_w.iter().map(|&w| w >= threshold).collect();
    let before = surfels.len();
    surfels.retain_mask(&keep);
    if !flags.is_empty() {
        let mut k = keep.iter();
        flags.retain(|_| *k.next().unwrap());
    }
    before - surfels.len()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::raster::{self, Outputs};
    use crate::surfels::quat_with_normal;
    use glam::Vec3;

    /// An opaque surface of two layers (2DGS clamps α at 0.99, so one layer leaves T ≥ 0.01),
    /// a disk hidden behind it, a faint disk and a visible one beside them.
    #[test]
    fn hidden_and_faint_surfels_are_dropped_and_the_rest_kept() {
        let mut s = Surfels { sh_degree: 0, ..Default::default() };
        let facing = quat_with_normal([0.0, -1.0, 0.0]);
        s.push([0.0, 0.0, 0.0], [0.3, 0.3], facing, 0.99, [1.0, 0.0, 0.0], [0.5; 3], 0.5);
        s.push([0.0, 0.01, 0.0], [0.3, 0.3], facing, 0.99, [1.0, 0.0, 0.0], [0.5; 3], 0.5);
        s.push([0.0, 0.05, 0.0], [0.05, 0.05], facing, 0.9, [0.0, 1.0, 0.0], [0.5; 3], 0.5);
        s.push([0.9, 0.0, 0.0], [0.1, 0.1], facing, 0.003, [0.0, 0.0, 1.0], [0.5; 3], 0.5);
        s.push([-0.9, 0.0, 0.0], [0.1, 0.1], facing, 0.5, [1.0, 1.0, 0.0], [0.5; 3], 0.5);
        let cam = Camera::look_at("front", Vec3::new(0.0, -4.0, 0.0), Vec3::ZERO, 64, 64, 0.8);
        let settings = RasterSettings {
            outputs: Outputs { colour: true, ..Outputs::none() },
            alpha_min: 0.0,
            ..Default::default()
        };
        let w = max_blend_weights(&s, std::slice::from_ref(&cam), &settings);
        // The front layer peaks near α = 0.99; the second shows at least 0.01 × 0.99 behind it
        // (more towards the rim); the small disk hidden behind both gets about T ≈ 1e-4 × 0.9
        // and the faint one at most its opacity.
        assert!(w[0] > 0.95 && w[1] > 0.009, "{w:?}");
        assert!(w[2] < 1e-3, "{w:?}");
        assert!(w[3] > 0.0 && w[3] <= 0.003 + 1e-6, "{w:?}");
        assert!(w[4] > 0.45 && w[4] <= 0.5 + 1e-6, "{w:?}");
        // The weights are the rasteriser's: the sum over surfels of one pixel's weights is its alpha.
        let (out, _) = raster::render(&s, &cam, &settings, None);
        let bw = BlendWeights::compute(&s, &cam, &settings);
        for px in [32 * 64 + 32, 32 * 64 + 4, 10] {
            let sum: f32 = (bw.offsets[px]..bw.offsets[px + 1]).map(|k| bw.weights[k as usize]).sum();
            assert!((sum - out.alpha[px]).abs() < 1e-5, "pixel {px}: {sum} vs {}", out.alpha[px]);
        }
        let mut pruned = s.clone();
        // Per-surfel flags follow their surfels.
        let mut flags = vec![false, true, true, false, true];
        assert_eq!(prune_unseen(&mut pruned, std::slice::from_ref(&cam), &settings, 1.0 / 255.0, &mut flags), 2);
        assert_eq!(pruned.means, vec![s.means[0], s.means[1], s.means[4]]);
        assert_eq!(flags, [false, true, true]);
        // Threshold 0 keeps everything.
        let mut all = s.clone();
        assert_eq!(prune_unseen(&mut all, &[cam], &settings, 0.0, &mut Vec::new()), 0);
        assert_eq!(all.len(), 5);
    }
}
