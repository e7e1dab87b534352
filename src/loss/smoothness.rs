//! Edge-aware smoothness of a per-pixel map (albedo, roughness, normal), RadioGS/IRGS
//! `first_order_edge_aware_loss(data, img)`:
//!   L = mean over (data channel d, pixel p) of  Σ_{k∈{x,y}} |S_k ∗ D_d|(p) · exp(−|S_k ∗ I_d|(p))
//! with S_k the normalised Sobel filters (kornia `spatial_gradient`, order 1: taps
//! [[−1,0,1],[−2,0,2],[−1,0,1]] / 8 and its transpose) under **replicate** padding, I the GT image.
//! A 3-channel map pairs channel d with image channel d; a 1-channel map broadcasts against the
//! 3 image channels (weight = mean over channels of exp(−|S_k ∗ I_c|)), as torch broadcasting does.
//! An optional mask multiplies the data first (RadioGS: `data * gt_mask`), so D = data · m.
//! Backward: v_g = sign(g)·W / (C N); scattered back through the Sobel taps with the same clamped
//! indices (adjoint of replicate padding), then times m.
//! Decomposition: the image weights and the per-pixel terms (rayon over rows), then the scatter
//! through the taps in three passes of disjoint three-row windows (rayon over windows). Scratch
//! (weights, gradients) lives in [`EdgeAwareSmoothness`].

use rayon::prelude::*;

const KV: [f32; 3] = [1.0, 2.0, 1.0];

/// Sobel responses (x, y) of channel `c` of an interleaved `ch`-channel image at (x, y), replicate
/// padding.
#[inline]
fn sobel(img: &[f32], ch: usize, c: usize, w: usize, h: usize, x: usize, y: usize) -> (f32, f32) {
    let xm = x.saturating_sub(1);
    let xp = (x + 1).min(w - 1);
    let ys = [y.saturating_sub(1), y, (y + 1).min(h - 1)];
    let xs = [xm, x, xp];
    let at = |xx: usize, yy: usize| img[(yy * w + xx) * ch + c];
    let mut gx = 0.0;
    let mut gy = 0.0;
    for k in 0..3 {
        gx += KV[k] * (at(xp, ys[k]) - at(xm, ys[k]));
        gy += KV[k] * (at(xs[k], ys[2]) - at(xs[k], ys[0]));
    }
    (gx / 8.0, gy / 8.0)
}

#[derive(Default, Clone)]
pub struct EdgeAwareSmoothness {
    /// exp(−|S_k ∗ I|) per pixel and image channel: [wx0, wx1, wx2, wy0, wy1, wy2].
    weights: Vec<[f32; 6]>,
    masked: Vec<f32>,
    v_masked: Vec<f32>,
    /// Per pixel and channel: ∂L/∂ of its (x, y) Sobel responses.
    v_sobel: Vec<[f32; 2]>,
    width: usize,
    height: usize,
}

impl EdgeAwareSmoothness {
    pub fn new() -> Self {
        Self::default()
    }

    /// Compute the image weights exp(−|S_k ∗ I|) of the GT image once, for several
    /// [`loss_prepared`](Self::loss_prepared) calls on the same view (albedo, roughness, normal).
    pub fn prepare(&mut self, gt: &[[f32; 3]], w: usize, h: usize) {
        assert_eq!(gt.len(), w * h);
        self.width = w;
        self.height = h;
        self.weights.resize(w * h, [0.0; 6]);
        if w * h == 0 {
            return;
        }
        let gt_flat = gt.as_flattened();
        self.weights.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, wt) in row.iter_mut().enumerate() {
                for c in 0..3 {
                    let (gx, gy) = sobel(gt_flat, 3, c, w, h, x, y);
                    wt[c] = (-gx.abs()).exp();
                    wt[3 + c] = (-gy.abs()).exp();
                }
            }
        });
    }

    /// `data`: interleaved `channels`-channel map (1 or 3), `w × h` pixels; `gt`: the GT image;
    /// `mask`: optional per-pixel factor applied to the data. Returns L and accumulates
    /// `weight · ∂L/∂data` into `v_data`. (= [`prepare`](Self::prepare) + `loss_prepared`.)
    #[allow(clippy::too_many_arguments)]
    pub fn loss(
        &mut self,
        data: &[f32],
        channels: usize,
        gt: &[[f32; 3]],
        w: usize,
        h: usize,
        mask: Option<&[f32]>,
        weight: f32,
        v_data: &mut [f32],
    ) -> f32 {
        self.prepare(gt, w, h);
        self.loss_prepared(data, channels, mask, weight, v_data)
    }

    /// The loss against the image given to the last [`prepare`](Self::prepare).
    pub fn loss_prepared(
        &mut self,
        data: &[f32],
        channels: usize,
        mask: Option<&[f32]>,
        weight: f32,
        v_data: &mut [f32],
    ) -> f32 {
        assert!(channels == 1 || channels == 3, "smoothness needs a 1- or 3-channel map");
        let (w, h) = (self.width, self.height);
        let n = w * h;
        assert_eq!(data.len(), n * channels, "data size does not match the prepared image");
        assert_eq!(v_data.len(), n * channels);
        if let Some(m) = mask {
            assert_eq!(m.len(), n);
        }
        if n == 0 {
            return 0.0;
        }
        self.masked.clear();
        match mask {
            Some(m) => self.masked.extend(data.iter().enumerate().map(|(i, &v)| v * m[i / channels])),
            None => self.masked.extend_from_slice(data),
        }
        self.v_masked.clear();
        self.v_masked.resize(n * channels, 0.0);
        let norm = 1.0 / (channels * n) as f32;
        let g = weight * norm;
        // Per pixel and channel: the loss term and the upstream gradients (v_gx, v_gy) of its two
        // Sobel responses (rayon over rows; the rows' sums added in row order: deterministic).
        self.v_sobel.clear();
        self.v_sobel.resize(n * channels, [0.0; 2]);
        let (weights, masked) = (&self.weights, &self.masked);
        let row_sums: Vec<f64> = self
            .v_sobel
            .par_chunks_mut(w * channels)
            .enumerate()
            .map(|(y, row)| {
                let mut acc = 0.0f64;
                for x in 0..w {
                    let wt = &weights[y * w + x];
                    for c in 0..channels {
                        let (wx, wy) = if channels == 3 {
                            (wt[c], wt[3 + c])
                        } else {
                            ((wt[0] + wt[1] + wt[2]) / 3.0, (wt[3] + wt[4] + wt[5]) / 3.0)
                        };
                        let (gx, gy) = sobel(masked, channels, c, w, h, x, y);
                        acc += (gx.abs() * wx + gy.abs() * wy) as f64;
                        row[x * channels + c] = [
                            g * wx * gx.signum() * (gx != 0.0) as u8 as f32 / 8.0,
                            g * wy * gy.signum() * (gy != 0.0) as u8 as f32 / 8.0,
                        ];
                    }
                }
                acc
            })
            .collect();
        let acc: f64 = row_sums.iter().sum();
        // Scatter through the taps (the adjoint of the replicate-padded filter). A row's taps
        // reach the rows beside it only, so rows three apart never write the same place: three
        // passes (centre rows y ≡ r mod 3), each over disjoint three-row windows in parallel.
        let stride = w * channels;
        let v_sobel = &self.v_sobel;
        for r in 0..3usize {
            // Windows of rows [y − 1, y + 1] around each centre y = r + 3j; at r = 0 the first
            // is rows 0..=1 (its centre is row 0), the rest are three rows each.
            let first_start = r.saturating_sub(1);
            let (_, rest) = self.v_masked.split_at_mut(first_start * stride);
            let window_rows = if r == 0 { 2 } else { 3 };
            let (head, tail) = rest.split_at_mut((window_rows.min(h - first_start)) * stride);
            let scatter = |win: &mut [f32], win_start: usize, y: usize| {
                let win_rows = win.len() / stride;
                for c in 0..channels {
                    for x in 0..w {
                        let [vgx, vgy] = v_sobel[(y * w + x) * channels + c];
                        let xm = x.saturating_sub(1);
                        let xp = (x + 1).min(w - 1);
                        let ys = [y.saturating_sub(1), y, (y + 1).min(h - 1)].map(|yy| yy - win_start);
                        debug_assert!(ys.iter().all(|&yy| yy < win_rows));
                        let xs = [xm, x, xp];
                        for k in 0..3 {
                            win[(ys[k] * w + xp) * channels + c] += KV[k] * vgx;
                            win[(ys[k] * w + xm) * channels + c] -= KV[k] * vgx;
                            win[(ys[2] * w + xs[k]) * channels + c] += KV[k] * vgy;
                            win[(ys[0] * w + xs[k]) * channels + c] -= KV[k] * vgy;
                        }
                    }
                }
            };
            if r < h {
                scatter(head, first_start, r);
            }
            let next_start = first_start + window_rows;
            tail.par_chunks_mut(3 * stride).enumerate().for_each(|(j, win)| {
                let start = next_start + 3 * j;
                let y = start + 1;
                if y < h {
                    scatter(win, start, y);
                }
            });
        }
        for (i, v) in v_data.iter_mut().enumerate() {
            *v += self.v_masked[i] * mask.map_or(1.0, |m| m[i / channels]);
        }
        (acc * norm as f64) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// Independent f64 reference: explicit replicate-padded image, 3×3 correlation, broadcasting.
    fn reference(data: &[f64], ch: usize, gt: &[[f32; 3]], w: usize, h: usize, mask: Option<&[f32]>) -> f64 {
        let kx = [[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]].map(|r: [f64; 3]| r.map(|v| v / 8.0));
        let grad = |f: &dyn Fn(isize, isize) -> f64, x: usize, y: usize| {
            let (mut gx, mut gy) = (0.0, 0.0);
            for j in 0..3 {
                for i in 0..3 {
                    let xx = (x as isize + i as isize - 1).clamp(0, w as isize - 1);
                    let yy = (y as isize + j as isize - 1).clamp(0, h as isize - 1);
                    gx += kx[j][i] * f(xx, yy);
                    gy += kx[i][j] * f(xx, yy);
                }
            }
            (gx, gy)
        };
        let mut s = 0.0;
        for c in 0..3 {
            let dc = if ch == 3 { c } else { 0 };
            for y in 0..h {
                for x in 0..w {
                    let d = |xx: isize, yy: isize| {
                        let i = yy as usize * w + xx as usize;
                        data[i * ch + dc] * mask.map_or(1.0, |m| m[i] as f64)
                    };
                    let im = |xx: isize, yy: isize| gt[yy as usize * w + xx as usize][c] as f64;
                    let (dx, dy) = grad(&d, x, y);
                    let (ix, iy) = grad(&im, x, y);
                    s += dx.abs() * (-ix.abs()).exp() + dy.abs() * (-iy.abs()).exp();
                }
            }
        }
        // torch: the product has 3 channels after broadcasting; mean over 3·N either way.
        s / (3 * w * h) as f64
    }

    #[test]
    fn matches_reference_and_finite_differences() {
        // Heights around the three-row windows of the scatter: 1, 2, 3 rows, and ≡ 0, 1, 2 mod 3.
        for (w, h) in [(13, 9), (5, 1), (4, 2), (6, 3), (7, 4), (3, 11)] {
            check_size(w, h);
        }
    }

    fn check_size(w: usize, h: usize) {
        let n = w * h;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(41 + (w * 100 + h) as u64);
        let gt: Vec<[f32; 3]> = (0..n).map(|_| [rng.random(), rng.random(), rng.random()]).collect();
        let mut mask: Vec<f32> = (0..n).map(|_| if rng.random::<f32>() < 0.8 { 1.0 } else { 0.0 }).collect();
        mask[n / 2] = 0.5;
        for ch in [1usize, 3] {
            for m in [None, Some(mask.as_slice())] {
                let data: Vec<f32> = (0..n * ch).map(|_| rng.random()).collect();
                let mut sm = EdgeAwareSmoothness::new();
                let mut v = vec![0.0f32; n * ch];
                let l = sm.loss(&data, ch, &gt, w, h, m, 0.9, &mut v);
                // The prepared path gives the same value and gradient.
                let mut v2 = vec![0.0f32; n * ch];
                assert_eq!(sm.loss_prepared(&data, ch, m, 0.9, &mut v2), l);
                assert_eq!(v, v2);
                let d64: Vec<f64> = data.iter().map(|&v| v as f64).collect();
                let r = reference(&d64, ch, &gt, w, h, m);
                assert!((l as f64 - r).abs() < 1e-5, "ch {ch}: {l} vs {r}");
                let hs = 1e-7;
                for i in 0..n * ch {
                    let mut a = d64.clone();
                    a[i] += hs;
                    let mut b = d64.clone();
                    b[i] -= hs;
                    let fd = 0.9 * (reference(&a, ch, &gt, w, h, m) - reference(&b, ch, &gt, w, h, m)) / (2.0 * hs);
                    assert!((fd - v[i] as f64).abs() < 2e-5, "{w}×{h} ch {ch} elem {i}: fd {fd:e} vs {:e}", v[i]);
                }
            }
        }
    }
}
