//! The PBR image loss of the PBR stages, forward and backward: the rasterised linear PBR
//! channels composited over the linear background, sRGB-encoded, against the sRGB ground
//! truth with weight·(L1 + 0.2·D-SSIM) (RadioGS / IRGS).

use super::consistency::{encode, encode_derivative};
use crate::loss::{self, Ssim};

/// Reused buffers.
#[derive(Default)]
pub struct PbrImageLoss {
    linear: Vec<[f32; 3]>,
    srgb: Vec<[f32; 3]>,
    v_srgb: Vec<[f32; 3]>,
    ssim: Ssim,
}

/// Unweighted terms and the PSNR of the sRGB PBR image.
#[derive(Clone, Copy, Debug, Default)]
pub struct PbrImageTerms {
    pub l1: f32,
    pub dssim: f32,
    pub psnr: f32,
}

impl PbrImageLoss {
    /// `features` holds `channels` values per pixel with the linear PBR colour first and
    /// `alpha` the rendered opacity. With `weight` > 0 the gradients are added into
    /// `v_features` (the same layout) and `v_alpha` (through the background term).
    #[allow(clippy::too_many_arguments)]
    pub fn evaluate(
        &mut self,
        features: &[f32],
        channels: usize,
        alpha: &[f32],
        bg: [f32; 3],
        gt: &[[f32; 3]],
        (w, h): (usize, usize),
        weight: f32,
        v_features: &mut [f32],
        v_alpha: &mut [f32],
    ) -> PbrImageTerms {
        let np = w * h;
        let bg_lin = bg.map(crate::io::image::srgb_to_linear);
        self.linear.clear();
        self.linear.extend((0..np).map(|p| {
            let f = &features[p * channels..p * channels + 3];
            [0, 1, 2].map(|k| f[k] + (1.0 - alpha[p]) * bg_lin[k])
        }));
        self.srgb.clear();
        self.srgb.extend(self.linear.iter().map(|c| c.map(encode)));
        let mut terms = PbrImageTerms { psnr: loss::psnr(&self.srgb, gt), ..Default::default() };
        if weight <= 0.0 {
            return terms;
        }
        self.v_srgb.clear();
        self.v_srgb.resize(np, [0.0; 3]);
        terms.l1 = loss::l1_rgb(&self.srgb, gt, None, weight, &mut self.v_srgb);
        terms.dssim = self.ssim.dssim_loss(&self.srgb, gt, w, h, weight * 0.2, &mut self.v_srgb);
        for p in 0..np {
            let mut va = 0.0;
            for k in 0..3 {
                let v = self.v_srgb[p][k] * encode_derivative(self.linear[p][k]);
                v_features[p * channels + k] += v;
                va -= v * bg_lin[k];
            }
            v_alpha[p] += va;
        }
        terms
    }
}
