//! The PBR image loss of the PBR stages, forward and backward: the rasterised linear PBR
//! channels composited over the linear background, sRGB-encoded, against the sRGB ground
//! truth with weight·(L1 + 0.2·D-SSIM) (RadioGS / IRGS).
//!
//! Clipped ground truth: the datasets' PNGs are linear radiance clipped to [0, 1], then
//! encoded (Blender's Standard view), so a stored 1 says "at least 1". With `clip_saturated`
//! such a channel is a lower bound: a rendered value above it is compared as equal and gets no
//! gradient, so the light and albedo are not pulled down to the clipped values (spheres: 6.6 % of
//! the covered training pixels clip, mostly in blue; BENCHMARKS.md session 36). Only pixels the
//! object covers fully count (ground-truth alpha ≥ `SATURATED`): a white background composites
//! to 1 as well, and there a brighter rendering (a floater) is an error.

use super::consistency::{encode, encode_derivative_given};
use crate::loss::{self, Ssim};
use rayon::prelude::*;

/// Reused buffers.
#[derive(Default)]
pub struct PbrImageLoss {
    linear: Vec<[f32; 3]>,
    srgb: Vec<[f32; 3]>,
    v_srgb: Vec<[f32; 3]>,
    ssim: Ssim,
    /// Per pixel: bit k set when channel k was clamped to its saturated ground truth.
    clipped: Vec<u8>,
    /// Treat saturated ground-truth channels as lower bounds (see the module comment).
    pub clip_saturated: bool,
}

/// A ground-truth channel at or above this (sRGB, 8-bit quantised) was clipped at 1.
pub const SATURATED: f32 = 1.0 - 0.5 / 255.0;

/// One rendered PBR image and its ground truth: `features` holds `channels` values per pixel
/// with the linear PBR colour first, `alpha` is the rendered opacity, `gt` the ground truth over
/// `bg` (sRGB) and `gt_alpha` its alpha; `size` is (width, height).
#[derive(Clone, Copy)]
pub struct PbrImage<'a> {
    pub features: &'a [f32],
    pub channels: usize,
    pub alpha: &'a [f32],
    pub bg: [f32; 3],
    pub gt: &'a [[f32; 3]],
    pub gt_alpha: &'a [f32],
    pub size: (usize, usize),
}

/// Unweighted terms and the PSNR of the sRGB PBR image.
#[derive(Clone, Copy, Debug, Default)]
pub struct PbrImageTerms {
    pub l1: f32,
    pub dssim: f32,
    pub psnr: f32,
}

impl PbrImageLoss {
    pub fn clipping(clip_saturated: bool) -> PbrImageLoss {
        PbrImageLoss { clip_saturated, ..Default::default() }
    }

    /// The loss of `img`; with `weight` > 0 the gradients are added into `v_features` (the
    /// features' layout) and `v_alpha` (through the background term).
    pub fn evaluate(
        &mut self,
        img: &PbrImage,
        weight: f32,
        v_features: &mut [f32],
        v_alpha: &mut [f32],
    ) -> PbrImageTerms {
        let (gt, channels, (w, h)) = (img.gt, img.channels, img.size);
        let np = w * h;
        let bg_lin = self.encode_and_clip(img);
        let mut terms = PbrImageTerms { psnr: loss::psnr(&self.srgb, gt), ..Default::default() };
        if weight <= 0.0 {
            return terms;
        }
        self.v_srgb.clear();
        self.v_srgb.resize(np, [0.0; 3]);
        terms.l1 = loss::l1_rgb(&self.srgb, gt, None, weight, &mut self.v_srgb);
        terms.dssim = self.ssim.dssim_loss(&self.srgb, gt, w, h, weight * 0.2, &mut self.v_srgb);
        let (clipped, v_srgb, linear, srgb) = (&self.clipped, &self.v_srgb, &self.linear, &self.srgb);
        v_features[..np * channels]
            .par_chunks_mut(channels)
            .zip(v_alpha[..np].par_iter_mut())
            .enumerate()
            .with_min_len(1024)
            .for_each(|(p, (vf, v_a))| {
                let mut va = 0.0;
                for k in 0..3 {
                    if clipped[p] & (1 << k) != 0 {
                        continue;
                    }
                    // Not clipped: srgb holds encode(linear).
                    let v = v_srgb[p][k] * encode_derivative_given(linear[p][k], srgb[p][k]);
                    vf[k] += v;
                    va -= v * bg_lin[k];
                }
                *v_a += va;
            });
        terms
    }

    /// The loss terms without gradients (the same values as [`Self::evaluate`] with a
    /// positive weight).
    pub fn value(&mut self, img: &PbrImage) -> PbrImageTerms {
        let (gt, (w, h)) = (img.gt, img.size);
        let np = w * h;
        self.encode_and_clip(img);
        let l1 = if np == 0 {
            0.0
        } else {
            let sum: f64 = self
                .srgb
                .par_iter()
                .zip(gt)
                .with_min_len(1024)
                .map(|(s, g)| (0..3).map(|k| (s[k] - g[k]).abs() as f64).sum::<f64>())
                .sum();
            (sum / (3 * np) as f64) as f32
        };
        let dssim = if np == 0 { 0.0 } else { 1.0 - self.ssim.forward(&self.srgb, gt, w, h) };
        PbrImageTerms { l1, dssim, psnr: loss::psnr(&self.srgb, gt) }
    }

    /// The composited linear image into `linear`, its sRGB encoding into `srgb`, saturated
    /// ground-truth channels clamped there (flagged in `clipped`); returns the linear background.
    fn encode_and_clip(&mut self, img: &PbrImage) -> [f32; 3] {
        let PbrImage { features, channels, alpha, bg, gt, gt_alpha, size: (w, h) } = *img;
        let np = w * h;
        let bg_lin = bg.map(crate::io::image::srgb_to_linear);
        // Per pixel and independent (the sRGB encode's powf is the cost): rayon over pixels.
        self.linear.resize(np, [0.0; 3]);
        self.srgb.resize(np, [0.0; 3]);
        self.linear.par_iter_mut().zip(self.srgb.par_iter_mut()).enumerate().with_min_len(1024).for_each(
            |(p, (lin, srgb))| {
                let f = &features[p * channels..p * channels + 3];
                *lin = [0, 1, 2].map(|k| f[k] + (1.0 - alpha[p]) * bg_lin[k]);
                *srgb = lin.map(encode);
            },
        );
        self.clipped.clear();
        self.clipped.resize(np, 0);
        if self.clip_saturated {
            for (((s, g), bits), &a) in self.srgb.iter_mut().zip(gt).zip(self.clipped.iter_mut()).zip(gt_alpha) {
                if a < SATURATED {
                    continue;
                }
                for k in 0..3 {
                    // At most 1: an HDR ground truth above 1 is a value, not a clip.
                    if (SATURATED..=1.0).contains(&g[k]) && s[k] >= g[k] {
                        s[k] = g[k];
                        *bits |= 1 << k;
                    }
                }
            }
        }
        bg_lin
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// A small image with some ground-truth channels saturated; rendered values straddle 1.
    fn case(seed: u64) -> (Vec<f32>, Vec<f32>, Vec<[f32; 3]>, (usize, usize)) {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let (w, h, ch) = (6, 5, 4);
        let features: Vec<f32> = (0..w * h * ch).map(|_| rng.random_range(0.02..1.6)).collect();
        let alpha: Vec<f32> = (0..w * h).map(|_| rng.random_range(0.3..1.0)).collect();
        let gt: Vec<[f32; 3]> = (0..w * h)
            .map(|_| [0; 3].map(|_| if rng.random_bool(0.3) { 1.0 } else { rng.random_range(0.05..0.95) }))
            .collect();
        (features, alpha, gt, (w, h))
    }

    fn loss_of(clip: bool, f: &[f32], a: &[f32], gt: &[[f32; 3]], wh: (usize, usize)) -> f64 {
        loss_over(clip, f, a, [0.2, 0.5, 0.9], gt, &vec![1.0; a.len()], wh)
    }

    /// Ground-truth coverage for the finite-difference test: every fifth pixel an edge (0.5).
    fn coverage(n: usize) -> Vec<f32> {
        (0..n).map(|p| if p % 5 == 0 { 0.5 } else { 1.0 }).collect()
    }

    fn loss_over(
        clip: bool,
        f: &[f32],
        a: &[f32],
        bg: [f32; 3],
        gt: &[[f32; 3]],
        gt_alpha: &[f32],
        wh: (usize, usize),
    ) -> f64 {
        let mut l = PbrImageLoss { clip_saturated: clip, ..Default::default() };
        let (mut vf, mut va) = (vec![0.0; f.len()], vec![0.0; a.len()]);
        let t = l.evaluate(
            &PbrImage { features: f, channels: 4, alpha: a, bg, gt, gt_alpha, size: wh },
            1.0,
            &mut vf,
            &mut va,
        );
        (t.l1 + 0.2 * t.dssim) as f64
    }

    #[test]
    fn clipped_loss_gradients_match_finite_differences() {
        for clip in [false, true] {
            let (f, a, gt, wh) = case(7);
            let mut l = PbrImageLoss { clip_saturated: clip, ..Default::default() };
            let (mut vf, mut va) = (vec![0.0; f.len()], vec![0.0; a.len()]);
            let gt_alpha = coverage(a.len());
            l.evaluate(
                &PbrImage {
                    features: &f,
                    channels: 4,
                    alpha: &a,
                    bg: [0.2, 0.5, 0.9],
                    gt: &gt,
                    gt_alpha: &gt_alpha,
                    size: wh,
                },
                1.0,
                &mut vf,
                &mut va,
            );
            let loss_of = |clip, f: &[f32], a: &[f32], gt: &[[f32; 3]], wh| {
                loss_over(clip, f, a, [0.2, 0.5, 0.9], gt, &gt_alpha, wh)
            };
            let eps = 2e-3f32;
            let (mut checked, mut max_err, mut flat, mut edge_clips) = (0, 0.0f64, 0, 0);
            for i in (0..f.len()).filter(|i| i % 4 != 3) {
                let (mut fp, mut fm) = (f.clone(), f.clone());
                fp[i] += eps;
                fm[i] -= eps;
                let up = (loss_of(clip, &fp, &a, &gt, wh) - loss_of(clip, &f, &a, &gt, wh)) / eps as f64;
                let down = (loss_of(clip, &f, &a, &gt, wh) - loss_of(clip, &fm, &a, &gt, wh)) / eps as f64;
                // A kink of |·| or of the clamp inside ±eps: one-sided slopes disagree (by about
                // a channel's slope, ~1e-2); skip. The f32 loss (~0.5) rounds at ~3e-8 each
                // evaluation, so rounding alone moves a slope by up to ~6e-5 (2·3e-8 / eps).
                if (up - down).abs() > 1e-3 * up.abs().max(down.abs()).max(1e-4) + 1e-4 {
                    continue;
                }
                let fd = 0.5 * (up + down);
                max_err = max_err.max((fd - vf[i] as f64).abs() / fd.abs().max(1e-4));
                flat += (fd == 0.0) as usize;
                let (pixel, k) = (i / 4, i % 4);
                edge_clips += (gt_alpha[pixel] < 1.0 && gt[pixel][k] >= SATURATED && fd != 0.0) as usize;
                checked += 1;
            }
            assert!(checked >= f.len() / 2, "checked only {checked}");
            // Saturated channels of partly covered pixels are compared as values (not clamped).
            assert!(edge_clips > 0, "no partly covered saturated channel checked");
            // Clamped channels (flat loss) are among those checked only when clipping.
            assert_eq!(flat > 0, clip, "flat entries {flat}");
            assert!(max_err < 0.02, "clip {clip}: worst relative error {max_err}");
        }
    }

    #[test]
    fn a_saturated_channel_is_a_lower_bound() {
        let (w, h) = (8, 8);
        let gt = vec![[1.0, 0.5, 0.2]; w * h];
        let alpha = vec![1.0; w * h];
        // Red rendered at 1.7 (linear), the others exact.
        let g = |x: f32| crate::io::image::srgb_to_linear(x);
        let over: Vec<f32> = (0..w * h).flat_map(|_| [1.7, g(0.5), g(0.2), 0.0]).collect();
        let under: Vec<f32> = (0..w * h).flat_map(|_| [g(0.8), g(0.5), g(0.2), 0.0]).collect();
        assert!(loss_of(true, &over, &alpha, &gt, (w, h)) < 1e-6);
        assert!(loss_of(false, &over, &alpha, &gt, (w, h)) > 1e-2);
        // Below the clipped value the loss still counts.
        assert!(loss_of(true, &under, &alpha, &gt, (w, h)) > 1e-2);
        // A ground truth above 1 (HDR, not clipped) is a value: a brighter rendering costs.
        let hdr = vec![[1.5, 0.5, 0.2]; w * h];
        let brighter: Vec<f32> = (0..w * h).flat_map(|_| [4.0, g(0.5), g(0.2), 0.0]).collect();
        assert!(loss_of(true, &brighter, &alpha, &hdr, (w, h)) > 1e-2);
        let mut l = PbrImageLoss { clip_saturated: true, ..Default::default() };
        let (mut vf, mut va) = (vec![0.0; over.len()], vec![0.0; w * h]);
        l.evaluate(
            &PbrImage {
                features: &over,
                channels: 4,
                alpha: &alpha,
                bg: [0.0; 3],
                gt: &gt,
                gt_alpha: &alpha,
                size: (w, h),
            },
            1.0,
            &mut vf,
            &mut va,
        );
        assert!(vf.iter().step_by(4).all(|&v| v == 0.0), "no gradient through a clamped channel");
    }

    #[test]
    fn a_white_background_is_not_a_clip() {
        // The ground truth's background (alpha 0) over white is 1 in every channel: a floater
        // rendered brighter than white there still costs, and gets a gradient.
        let (w, h) = (8, 8);
        let white = vec![[1.0; 3]; w * h];
        let bright: Vec<f32> = (0..w * h).flat_map(|_| [0.9, 0.9, 0.9, 0.0]).collect();
        let rendered_alpha = vec![0.5; w * h];
        let covered = loss_over(true, &bright, &rendered_alpha, [1.0; 3], &white, &vec![1.0; w * h], (w, h));
        let background = loss_over(true, &bright, &rendered_alpha, [1.0; 3], &white, &vec![0.0; w * h], (w, h));
        assert!(covered < 1e-6, "{covered}");
        assert!(background > 1e-2, "{background}");
        // Partly covered pixels are not clips either.
        let edge = loss_over(true, &bright, &rendered_alpha, [1.0; 3], &white, &vec![0.6; w * h], (w, h));
        assert!(edge > 1e-2, "{edge}");
    }

    /// The gradient-free terms are the evaluated ones, with and without clipping, on an image
    /// big enough for SSIM's window.
    #[test]
    fn value_matches_evaluate() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
        let (w, h, ch) = (23, 17, 4);
        let features: Vec<f32> = (0..w * h * ch).map(|_| rng.random_range(0.0..1.4)).collect();
        let alpha: Vec<f32> = (0..w * h).map(|_| rng.random_range(0.2..1.0)).collect();
        let gt: Vec<[f32; 3]> = (0..w * h)
            .map(|_| [0; 3].map(|_| if rng.random_bool(0.2) { 1.0 } else { rng.random_range(0.0..1.0) }))
            .collect();
        let gt_alpha = coverage(w * h);
        for clip in [false, true] {
            let mut loss = PbrImageLoss::clipping(clip);
            let img = PbrImage {
                features: &features,
                channels: ch,
                alpha: &alpha,
                bg: [0.1, 0.2, 0.3],
                gt: &gt,
                gt_alpha: &gt_alpha,
                size: (w, h),
            };
            let (mut vf, mut va) = (vec![0.0; w * h * ch], vec![0.0; w * h]);
            let e = loss.evaluate(&img, 1.0, &mut vf, &mut va);
            let v = loss.value(&img);
            assert!(e.l1 > 0.05 && e.dssim > 0.05, "{e:?}");
            assert!((e.l1 - v.l1).abs() < 1e-6 && (e.dssim - v.dssim).abs() < 1e-6 && e.psnr == v.psnr, "{e:?} {v:?}");
        }
    }
}
