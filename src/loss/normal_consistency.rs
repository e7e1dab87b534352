//! Normal consistency (2DGS): rendered normals against normals of the rendered depth map.
//!
//! Depth normals (2DGS `depth_to_normal`): back-project every pixel centre with the camera,
//!   P(x, y) = o + z(x, y) · d(x, y),  d = Rᵀ((x + ½ − cx)/fx, (y + ½ − cy)/fy, 1)
//! (z is the camera-space depth along the optical axis), take central differences
//!   Δr = P(x, y+1) − P(x, y−1),  Δc = P(x+1, y) − P(x−1, y),
//! and n_d = normalize(Δr × Δc) (this faces the camera); border pixels get n_d = 0.
//! Loss (2DGS; RadioGS uses the same): per pixel l = w (1 − n_r · (a n_d)) with n_r the rendered
//! normal **not renormalised**, a an optional detached factor on n_d (2DGS multiplies `surf_normal`
//! by the detached rendered alpha) and w an optional pixel weight (GT alpha on masked object data):
//!   L = 1/N Σ_p w_p (1 − n_r,p · a_p n_d,p).
//! Backward: ∂L/∂n_r = −w a n_d / N; ∂L/∂n_d = −w a n_r / N, then through the normalisation
//! (v_c = (v_n − n (n·v_n)) / |c|, |c| floored at 1e-12 as `F.normalize`), the cross product
//! (v_Δr = Δc × v_c, v_Δc = v_c × Δr), the differences (gathered per pixel from its four
//! neighbours, so rows run in parallel without write conflicts) and the back-projection
//! (v_z = v_P · d).
//! Parallel: rayon over rows in each pass. Saved between forward and backward (same call): the
//! back-projected points, cross products and depth normals in [`NormalConsistency`] scratch.

use crate::camera::Camera;
use glam::Vec3;
use rayon::prelude::*;

const NORM_EPS: f32 = 1e-12;

#[inline]
fn ray_dir(rt: &glam::Mat3, cam: &Camera, x: usize, y: usize) -> Vec3 {
    *rt * Vec3::new((x as f32 + 0.5 - cam.cx) / cam.fx, (y as f32 + 0.5 - cam.cy) / cam.fy, 1.0)
}

fn back_project(cam: &Camera, depth: &[f32], points: &mut [[f32; 3]]) {
    let w = cam.width as usize;
    let rt = cam.rotation.transpose();
    let o = cam.position();
    points.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, p) in row.iter_mut().enumerate() {
            *p = (o + depth[y * w + x] * ray_dir(&rt, cam, x, y)).to_array();
        }
    });
}

/// Cross products c = Δr × Δc and normals n = c / max(|c|, ε) of the interior pixels; borders 0.
fn cross_and_normals(points: &[[f32; 3]], w: usize, h: usize, cross: &mut [[f32; 3]], normals: &mut [[f32; 3]]) {
    cross.par_chunks_mut(w).zip(normals.par_chunks_mut(w)).enumerate().for_each(|(y, (crow, nrow))| {
        for x in 0..w {
            if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                crow[x] = [0.0; 3];
                nrow[x] = [0.0; 3];
                continue;
            }
            let p = |xx: usize, yy: usize| Vec3::from(points[yy * w + xx]);
            let dr = p(x, y + 1) - p(x, y - 1);
            let dc = p(x + 1, y) - p(x - 1, y);
            let c = dr.cross(dc);
            crow[x] = c.to_array();
            nrow[x] = (c / c.length().max(NORM_EPS)).to_array();
        }
    });
}

/// World-space normals of a depth map (2DGS `depth_to_normal`, pixel centres at +½); border 0.
/// `depth` and `out` hold `cam.width × cam.height` pixels.
pub fn depth_to_normal(cam: &Camera, depth: &[f32], out: &mut [[f32; 3]]) {
    let (w, h) = (cam.width as usize, cam.height as usize);
    assert_eq!(depth.len(), w * h);
    assert_eq!(out.len(), w * h);
    let mut points = vec![[0.0; 3]; w * h];
    let mut cross = vec![[0.0; 3]; w * h];
    back_project(cam, depth, &mut points);
    cross_and_normals(&points, w, h, &mut cross, out);
}

/// Reusable scratch for the normal-consistency loss.
#[derive(Default, Clone)]
pub struct NormalConsistency {
    points: Vec<[f32; 3]>,
    cross: Vec<[f32; 3]>,
    n_depth: Vec<[f32; 3]>,
    v_dr: Vec<[f32; 3]>,
    v_dc: Vec<[f32; 3]>,
    /// [`Self::loss_mixed_depth`]: the mixed depth and its gradient.
    mixed: Vec<f32>,
    v_mixed: Vec<f32>,
}

impl NormalConsistency {
    pub fn new() -> Self {
        Self::default()
    }

    /// Depth normals of the last call (before the `alpha` factor).
    pub fn depth_normals(&self) -> &[[f32; 3]] {
        &self.n_depth
    }

    /// [`Self::loss`] on 2DGS's surface depth (1 − r)·`expected` + r·`median` (r =
    /// `depth_ratio` in [0, 1]); accumulates `weight · ∂L/∂depth` split by (1 − r, r) into
    /// `v_expected` and `v_median`, which may be empty when their share is 0 (r = 1 or r = 0).
    #[allow(clippy::too_many_arguments)]
    pub fn loss_mixed_depth(
        &mut self,
        cam: &Camera,
        (expected, median, ratio): (&[f32], &[f32], f32),
        rend_normal: &[[f32; 3]],
        alpha: Option<&[f32]>,
        pixel_weights: Option<&[f32]>,
        weight: f32,
        (v_expected, v_median): (&mut [f32], &mut [f32]),
        v_normal: &mut [[f32; 3]],
    ) -> f32 {
        let mut mixed = std::mem::take(&mut self.mixed);
        let mut v_mixed = std::mem::take(&mut self.v_mixed);
        let depth: &[f32] = if ratio == 0.0 {
            expected
        } else if ratio == 1.0 {
            median
        } else {
            mixed.clear();
            mixed.extend(expected.iter().zip(median).map(|(e, m)| (1.0 - ratio) * e + ratio * m));
            &mixed
        };
        v_mixed.clear();
        v_mixed.resize(depth.len(), 0.0);
        let l = self.loss(cam, depth, rend_normal, alpha, pixel_weights, weight, &mut v_mixed, v_normal);
        for (v, &d) in v_expected.iter_mut().zip(&v_mixed) {
            *v += (1.0 - ratio) * d;
        }
        for (v, &d) in v_median.iter_mut().zip(&v_mixed) {
            *v += ratio * d;
        }
        self.mixed = mixed;
        self.v_mixed = v_mixed;
        l
    }

    /// L = 1/N Σ w (1 − n_r · a n_d). `alpha`: optional detached factor on the depth normals
    /// (2DGS: rendered alpha); `pixel_weights`: optional w (GT alpha). Accumulates
    /// `weight · ∂L/∂depth` into `v_depth` and `weight · ∂L/∂rend_normal` into `v_normal`.
    #[allow(clippy::too_many_arguments)]
    pub fn loss(
        &mut self,
        cam: &Camera,
        depth: &[f32],
        rend_normal: &[[f32; 3]],
        alpha: Option<&[f32]>,
        pixel_weights: Option<&[f32]>,
        weight: f32,
        v_depth: &mut [f32],
        v_normal: &mut [[f32; 3]],
    ) -> f32 {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let n = w * h;
        assert_eq!(depth.len(), n, "depth size");
        assert_eq!(rend_normal.len(), n, "normal size");
        assert_eq!(v_depth.len(), n);
        assert_eq!(v_normal.len(), n);
        if let Some(a) = alpha {
            assert_eq!(a.len(), n);
        }
        if let Some(pw) = pixel_weights {
            assert_eq!(pw.len(), n);
        }
        if n == 0 {
            return 0.0;
        }
        for b in [&mut self.points, &mut self.cross, &mut self.n_depth, &mut self.v_dr, &mut self.v_dc] {
            b.resize(n, [0.0; 3]);
        }
        back_project(cam, depth, &mut self.points);
        cross_and_normals(&self.points, w, h, &mut self.cross, &mut self.n_depth);

        let inv_n = 1.0 / n as f32;
        let g = weight * inv_n;
        let (points, cross, n_depth) = (&self.points, &self.cross, &self.n_depth);
        // Loss, v_normal, and v_Δr / v_Δc per pixel.
        let sum: f64 = v_normal
            .par_chunks_mut(w)
            .zip(self.v_dr.par_chunks_mut(w))
            .zip(self.v_dc.par_chunks_mut(w))
            .enumerate()
            .map(|(y, ((vn_row, vdr_row), vdc_row))| {
                let mut acc = 0.0f64;
                for x in 0..w {
                    let i = y * w + x;
                    let wp = pixel_weights.map_or(1.0, |pw| pw[i]);
                    let a = alpha.map_or(1.0, |al| al[i]);
                    let nr = Vec3::from(rend_normal[i]);
                    let nd = Vec3::from(n_depth[i]);
                    acc += (wp * (1.0 - a * nr.dot(nd))) as f64;
                    let v_nr = -g * wp * a * nd;
                    vn_row[x] = (Vec3::from(vn_row[x]) + v_nr).to_array();
                    let interior = x > 0 && y > 0 && x + 1 < w && y + 1 < h;
                    if !interior {
                        vdr_row[x] = [0.0; 3];
                        vdc_row[x] = [0.0; 3];
                        continue;
                    }
                    let v_nd = -g * wp * a * nr;
                    let c = Vec3::from(cross[i]);
                    let len = c.length();
                    let v_c = if len > NORM_EPS { (v_nd - nd * nd.dot(v_nd)) / len } else { v_nd / NORM_EPS };
                    let p = |xx: usize, yy: usize| Vec3::from(points[yy * w + xx]);
                    let dr = p(x, y + 1) - p(x, y - 1);
                    let dc = p(x + 1, y) - p(x - 1, y);
                    vdr_row[x] = dc.cross(v_c).to_array();
                    vdc_row[x] = v_c.cross(dr).to_array();
                }
                acc
            })
            .sum();
        // Gather v_P from the four neighbours, then v_z = v_P · d.
        let (v_dr, v_dc) = (&self.v_dr, &self.v_dc);
        let rt = cam.rotation.transpose();
        v_depth.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, vz) in row.iter_mut().enumerate() {
                let mut vp = Vec3::ZERO;
                if y > 0 {
                    vp += Vec3::from(v_dr[(y - 1) * w + x]);
                }
                if y + 1 < h {
                    vp -= Vec3::from(v_dr[(y + 1) * w + x]);
                }
                if x > 0 {
                    vp += Vec3::from(v_dc[y * w + x - 1]);
                }
                if x + 1 < w {
                    vp -= Vec3::from(v_dc[y * w + x + 1]);
                }
                *vz += vp.dot(ray_dir(&rt, cam, x, y));
            }
        });
        (sum * inv_n as f64) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;
    use rand::{RngExt, SeedableRng};

    fn camera(w: u32, h: u32) -> Camera {
        Camera::look_at("t", Vec3::new(2.0, -3.0, 1.5), Vec3::new(0.1, 0.0, 0.2), w, h, 0.9)
    }

    /// Independent f64 reference of the whole loss (direct per-pixel formulas).
    fn reference(cam: &Camera, depth: &[f64], nr: &[[f64; 3]], alpha: &[f64], wts: &[f64]) -> f64 {
        let (w, h) = (cam.width as usize, cam.height as usize);
        let r = cam.rotation.as_dmat3();
        let o = cam.position().as_dvec3();
        let pt = |x: usize, y: usize| {
            let dc = DVec3::new(
                (x as f64 + 0.5 - cam.cx as f64) / cam.fx as f64,
                (y as f64 + 0.5 - cam.cy as f64) / cam.fy as f64,
                1.0,
            );
            o + depth[y * w + x] * (r.transpose() * dc)
        };
        let mut s = 0.0;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let nd = if x == 0 || y == 0 || x + 1 == w || y + 1 == h {
                    DVec3::ZERO
                } else {
                    let c = (pt(x, y + 1) - pt(x, y - 1)).cross(pt(x + 1, y) - pt(x - 1, y));
                    c / c.length().max(1e-12)
                };
                s += wts[i] * (1.0 - alpha[i] * DVec3::from(nr[i]).dot(nd));
            }
        }
        s / (w * h) as f64
    }

    #[test]
    fn depth_normals_of_a_plane_face_the_camera() {
        // A plane z = 0 seen from above: depth normals must be +z (towards the camera).
        let cam = Camera::look_at("t", Vec3::new(0.3, 0.2, 4.0), Vec3::new(0.0, 0.0, 0.0), 16, 12, 0.8);
        let (w, h) = (16usize, 12usize);
        let mut depth = vec![0.0f32; w * h];
        let fwd = cam.rotation.row(2);
        for y in 0..h {
            for x in 0..w {
                let (o, d) = cam.ray(x as f32 + 0.5, y as f32 + 0.5);
                let t = -o.z / d.z;
                depth[y * w + x] = t * d.dot(fwd);
            }
        }
        let mut n = vec![[0.0; 3]; w * h];
        depth_to_normal(&cam, &depth, &mut n);
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                let v = Vec3::from(n[y * w + x]);
                assert!((v - Vec3::Z).length() < 1e-3, "({x},{y}) {v}");
            }
        }
        assert_eq!(n[0], [0.0; 3]);
    }

    #[test]
    fn loss_and_gradients_match_finite_differences() {
        let (w, h) = (13u32, 9u32);
        let cam = camera(w, h);
        let n = (w * h) as usize;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(31);
        // A smooth-ish bumpy depth so normals are well defined, plus noise.
        let depth: Vec<f32> = (0..n)
            .map(|i| {
                let (x, y) = ((i % w as usize) as f32, (i / w as usize) as f32);
                3.5 + 0.1 * (0.7 * x).sin() + 0.05 * (0.9 * y).cos() + 0.05 * rng.random::<f32>()
            })
            .collect();
        let nr: Vec<[f32; 3]> =
            (0..n).map(|_| [rng.random::<f32>() - 0.5, rng.random::<f32>() - 0.5, rng.random::<f32>() - 0.5]).collect();
        let alpha: Vec<f32> = (0..n).map(|_| 0.5 + 0.5 * rng.random::<f32>()).collect();
        let mut wts: Vec<f32> = (0..n).map(|_| rng.random::<f32>()).collect();
        wts[3 * w as usize + 4] = 0.0; // a zero-weight interior pixel
        let mut nc = NormalConsistency::new();
        let mut vz = vec![0.0f32; n];
        let mut vn = vec![[0.0f32; 3]; n];
        let weight = 1.3;
        let l = nc.loss(&cam, &depth, &nr, Some(&alpha), Some(&wts), weight, &mut vz, &mut vn);
        let d64: Vec<f64> = depth.iter().map(|&v| v as f64).collect();
        let n64: Vec<[f64; 3]> = nr.iter().map(|p| p.map(|v| v as f64)).collect();
        let a64: Vec<f64> = alpha.iter().map(|&v| v as f64).collect();
        let w64: Vec<f64> = wts.iter().map(|&v| v as f64).collect();
        let r = reference(&cam, &d64, &n64, &a64, &w64);
        assert!((l as f64 - r).abs() < 1e-5, "{l} vs {r}");
        let hs = 1e-6;
        let maxz = vz.iter().fold(0.0f32, |a, b| a.max(b.abs())) as f64;
        for i in 0..n {
            let mut a = d64.clone();
            a[i] += hs;
            let mut b = d64.clone();
            b[i] -= hs;
            let fd = weight as f64 * (reference(&cam, &a, &n64, &a64, &w64) - reference(&cam, &b, &n64, &a64, &w64))
                / (2.0 * hs);
            assert!((fd - vz[i] as f64).abs() < 2e-3 * maxz + 1e-7, "depth {i}: fd {fd:e} vs {:e}", vz[i]);
        }
        for i in [0usize, 5, 14, 3 * 13 + 4, 60, n - 1] {
            for c in 0..3 {
                let mut a = n64.clone();
                a[i][c] += hs;
                let mut b = n64.clone();
                b[i][c] -= hs;
                let fd = weight as f64
                    * (reference(&cam, &d64, &a, &a64, &w64) - reference(&cam, &d64, &b, &a64, &w64))
                    / (2.0 * hs);
                assert!((fd - vn[i][c] as f64).abs() < 1e-6, "normal {i} {c}: fd {fd:e} vs {:e}", vn[i][c]);
            }
        }
        // Border pixels have zero depth normals, so no normal gradient there.
        assert_eq!(vn[0], [0.0; 3]);
    }

    /// The mixed-depth loss (2DGS `depth_ratio`): its gradients on the expected and the median
    /// depth against central differences of the f64 reference on the mixed depth, for r = 0.3,
    /// and r = 0 / 1 with the unused side empty.
    #[test]
    fn mixed_depth_gradients_match_finite_differences() {
        let (w, h) = (11u32, 8u32);
        let cam = camera(w, h);
        let n = (w * h) as usize;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(37);
        let bumpy = |rng: &mut rand_pcg::Pcg64, k: f32| -> Vec<f32> {
            (0..n)
                .map(|i| {
                    let (x, y) = ((i % w as usize) as f32, (i / w as usize) as f32);
                    3.5 + 0.1 * (k * x).sin() + 0.05 * (0.9 * y).cos() + 0.05 * rng.random::<f32>()
                })
                .collect()
        };
        let (exp_d, med_d) = (bumpy(&mut rng, 0.7), bumpy(&mut rng, 0.4));
        let nr: Vec<[f32; 3]> =
            (0..n).map(|_| [rng.random::<f32>() - 0.5, rng.random::<f32>() - 0.5, rng.random::<f32>() - 0.5]).collect();
        let alpha: Vec<f32> = (0..n).map(|_| 0.5 + 0.5 * rng.random::<f32>()).collect();
        let wts: Vec<f32> = (0..n).map(|_| rng.random::<f32>()).collect();
        let n64: Vec<[f64; 3]> = nr.iter().map(|p| p.map(|v| v as f64)).collect();
        let a64: Vec<f64> = alpha.iter().map(|&v| v as f64).collect();
        let w64: Vec<f64> = wts.iter().map(|&v| v as f64).collect();
        let weight = 0.8;
        for ratio in [0.3f32, 0.0, 1.0] {
            let mut nc = NormalConsistency::new();
            let mut ve = if ratio < 1.0 { vec![0.0f32; n] } else { vec![] };
            let mut vm = if ratio > 0.0 { vec![0.0f32; n] } else { vec![] };
            let mut vn = vec![[0.0f32; 3]; n];
            let l = nc.loss_mixed_depth(
                &cam,
                (&exp_d, &med_d, ratio),
                &nr,
                Some(&alpha),
                Some(&wts),
                weight,
                (&mut ve, &mut vm),
                &mut vn,
            );
            let r = ratio as f64;
            let loss64 = |e: &[f64], m: &[f64]| {
                let d: Vec<f64> = e.iter().zip(m).map(|(e, m)| (1.0 - r) * e + r * m).collect();
                reference(&cam, &d, &n64, &a64, &w64)
            };
            let e64: Vec<f64> = exp_d.iter().map(|&v| v as f64).collect();
            let m64: Vec<f64> = med_d.iter().map(|&v| v as f64).collect();
            assert!((l as f64 - loss64(&e64, &m64)).abs() < 1e-5, "ratio {ratio}: loss");
            let hs = 1e-6;
            let scale = ve.iter().chain(&vm).fold(0.0f32, |a, b| a.max(b.abs())) as f64;
            for (side, grads) in [(0, &ve), (1, &vm)] {
                for (i, &g) in grads.iter().enumerate() {
                    let (mut ep, mut mp, mut em, mut mm) = (e64.clone(), m64.clone(), e64.clone(), m64.clone());
                    if side == 0 {
                        ep[i] += hs;
                        em[i] -= hs;
                    } else {
                        mp[i] += hs;
                        mm[i] -= hs;
                    }
                    let fd = weight as f64 * (loss64(&ep, &mp) - loss64(&em, &mm)) / (2.0 * hs);
                    assert!(
                        (fd - g as f64).abs() < 2e-3 * scale + 1e-7,
                        "ratio {ratio}, side {side}, pixel {i}: fd {fd:e} vs {g:e}"
                    );
                }
            }
            assert!(scale > 1e-4, "ratio {ratio}: no depth gradient");
        }
    }
}
