//! The specular lobe of [`super::brdf`] for eight samples of one surfel at once (f64x8), forward
//! and backward side by side: most of the per-sample rendering equation's arithmetic is here
//! (three square roots and four divisions a sample), and a surfel's samples share n, ω_o and r
//! ([`Lobe`] holds what they share; `pbr.rs` calls it on blocks of eight samples).
//!
//! Every expression mirrors the scalar code in `brdf.rs` operation for operation (no fused
//! multiply–adds), so each lane is bitwise the scalar result; `brdf.rs` stays the reference and
//! the tests here compare against it on random and edge cases.

use super::V3;
use super::brdf::{ALPHA2_MIN, COS_EPS, F0, alpha2};
use std::f64::consts::PI;
use wide::f64x8;

/// Samples per call.
pub const LANES: usize = 8;

/// Eight unit directions ω_i, structure of arrays.
pub type Dirs8 = [[f64; LANES]; 3];

#[inline]
fn splat(x: f64) -> f64x8 {
    f64x8::splat(x)
}

#[inline]
fn dot3(a: [f64x8; 3], b: [f64x8; 3]) -> f64x8 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The clamped cosine and its derivative mask (1 inside [COS_EPS, 1], 0 outside), as
/// `brdf::clamp_cos`.
#[inline]
fn clamp_cos(x: f64x8) -> (f64x8, f64x8) {
    let below = x.simd_lt(splat(COS_EPS));
    let above = x.simd_gt(splat(1.0));
    let v = below.select(splat(COS_EPS), above.select(splat(1.0), x));
    let d = (below | above).select(splat(0.0), splat(1.0));
    (v, d)
}

/// The per-surfel constants of the lobe (the scalar code recomputes them per sample): build
/// one per surfel and view, then evaluate it on blocks of eight directions.
#[derive(Clone, Copy)]
pub struct Lobe {
    n: [f64x8; 3],
    wo: [f64x8; 3],
    nov: f64x8,
    dnov: f64x8,
    a2: f64x8,
    /// α² above its floor (the roughness gradient is zero below it).
    a2_live: bool,
    r: f64,
}

impl Lobe {
    #[inline]
    pub fn new(r: f64, n: V3, wo: V3) -> Lobe {
        let (nov, dnov) = super::brdf::clamp_cos(super::dot(n, wo));
        let r4 = r * r * r * r;
        Lobe {
            n: n.map(splat),
            wo: wo.map(splat),
            nov: splat(nov),
            dnov: splat(dnov),
            a2: splat(alpha2(r)),
            a2_live: r4 > ALPHA2_MIN,
            r,
        }
    }

    /// F·D·V of eight unit directions ω_i (`brdf::specular` per lane).
    #[inline]
    pub fn eval(&self, wi: [f64x8; 3]) -> f64x8 {
        let t = terms(self, wi);
        let tt = t.noh * t.noh * (self.a2 - splat(1.0)) + splat(1.0);
        let d = self.a2 / (splat(PI) * tt * tt);
        let f = splat(F0) + splat(1.0 - F0) * pow5_x8(splat(1.0) - t.voh);
        f * d * smith_visibility(t.nol, self.nov, self.a2).0
    }

    /// The lobe and its gradients for upstream gradients `v_spec` (one per lane; lanes whose
    /// result is not used should get 0 and any unit direction).
    #[inline]
    pub fn eval_with_backward(&self, wi: [f64x8; 3], v_spec: f64x8) -> LobeGrads {
        lobe_backward(self, wi, v_spec)
    }
}

/// [`Lobe::eval_with_backward`]'s result, in lanes (∂/∂ω_i is not needed by the shading and
/// not returned).
#[derive(Clone, Copy)]
pub struct LobeGrads {
    pub spec: f64x8,
    pub v_roughness: f64x8,
    pub v_n: [f64x8; 3],
    pub v_wo: [f64x8; 3],
}

/// Half vector and cosines of eight samples (`brdf::terms`).
struct Terms {
    nol: f64x8,
    noh: f64x8,
    voh: f64x8,
    dnol: f64x8,
    dnoh: f64x8,
    dvoh: f64x8,
    h: [f64x8; 3],
    s_len: f64x8,
    /// Lanes where s_len > 1e-12 (a half vector exists).
    live: f64x8,
}

#[inline]
fn terms(sf: &Lobe, wi: [f64x8; 3]) -> Terms {
    let s = [sf.wo[0] + wi[0], sf.wo[1] + wi[1], sf.wo[2] + wi[2]];
    let s_len = dot3(s, s).sqrt();
    let live_mask = s_len.simd_gt(splat(1e-12));
    let inv = splat(1.0) / s_len;
    let h: [f64x8; 3] = std::array::from_fn(|k| live_mask.select(s[k] * inv, sf.n[k]));
    let (nol, dnol) = clamp_cos(dot3(sf.n, wi));
    let (noh, dnoh) = clamp_cos(dot3(sf.n, h));
    let (voh, dvoh) = clamp_cos(dot3(sf.wo, h));
    let live = live_mask.select(splat(1.0), splat(0.0));
    Terms { nol, noh, voh, dnol, dnoh: dnoh * live, dvoh: dvoh * live, h, s_len, live: live_mask }
}

/// `brdf::smith_visibility`: (V, ∂V/∂NoL, ∂V/∂NoV, ∂V/∂α²).
#[inline]
fn smith_visibility(nol: f64x8, nov: f64x8, a2: f64x8) -> (f64x8, f64x8, f64x8, f64x8) {
    let one = splat(1.0);
    let al = (nol * nol * (one - a2) + a2).sqrt();
    let av = (nov * nov * (one - a2) + a2).sqrt();
    let den = nol * av + nov * al;
    let v = splat(0.5) / den;
    let k = -v / den;
    let d_nol = av + nov * nol * (one - a2) / al;
    let d_nov = al + nol * nov * (one - a2) / av;
    let d_a2 = nol * (one - nov * nov) / (splat(2.0) * av) + nov * (one - nol * nol) / (splat(2.0) * al);
    (v, k * d_nol, k * d_nov, k * d_a2)
}

#[inline]
fn load(wi: &Dirs8) -> [f64x8; 3] {
    [f64x8::from(wi[0]), f64x8::from(wi[1]), f64x8::from(wi[2])]
}

/// The lobe F·D·V (f0 = 0.04) of eight samples: `brdf::specular` per lane (the array form of
/// [`Lobe::eval`], which the tests compare with the scalar lobe bit for bit).
pub fn specular(r: f64, n: V3, wo: V3, wi: &Dirs8) -> [f64; LANES] {
    Lobe::new(r, n, wo).eval(load(wi)).to_array()
}

#[inline]
fn pow5_x8(x: f64x8) -> f64x8 {
    let x2 = x * x;
    x2 * x2 * x
}

#[inline]
fn pow4_x8(x: f64x8) -> f64x8 {
    let x2 = x * x;
    x2 * x2
}

/// The lobe and its gradients for eight samples (`brdf::specular_with_backward` per lane;
/// ∂/∂ω_i is not needed by the shading and not returned).
#[derive(Clone, Copy, Debug, Default)]
pub struct SpecularLanes {
    pub spec: [f64; LANES],
    pub v_roughness: [f64; LANES],
    pub v_n: [[f64; LANES]; 3],
    pub v_wo: [[f64; LANES]; 3],
}

/// Forward and backward of the lobe for upstream gradients `v_spec` (one per lane; lanes whose
/// result is not used should get 0 and any unit direction).
pub fn specular_with_backward(r: f64, n: V3, wo: V3, wi: &Dirs8, v_spec: &[f64; LANES]) -> SpecularLanes {
    let g = Lobe::new(r, n, wo).eval_with_backward(load(wi), f64x8::from(*v_spec));
    SpecularLanes {
        spec: g.spec.to_array(),
        v_roughness: g.v_roughness.to_array(),
        v_n: g.v_n.map(|x| x.to_array()),
        v_wo: g.v_wo.map(|x| x.to_array()),
    }
}

#[inline]
fn lobe_backward(sf: &Lobe, wi: [f64x8; 3], v_spec: f64x8) -> LobeGrads {
    let t = terms(sf, wi);
    let one = splat(1.0);
    let a2 = sf.a2;
    let tt = t.noh * t.noh * (a2 - one) + one;
    let d = a2 / (splat(PI) * tt * tt);
    let om = one - t.voh;
    let fr = splat(F0) + splat(1.0 - F0) * pow5_x8(om);
    let (vis, dvis_nol, dvis_nov, dvis_a2) = smith_visibility(t.nol, sf.nov, a2);
    let spec = fr * d * vis;
    let vs = v_spec * spec;
    let v_fd = v_spec * fr * d;
    let v_nol = v_fd * dvis_nol * t.dnol;
    let v_nov = v_fd * dvis_nov * sf.dnov;
    let v_a2 = if sf.a2_live { vs * (one / a2 - splat(2.0) * t.noh * t.noh / tt) + v_fd * dvis_a2 } else { splat(0.0) };
    let v_noh = vs * (splat(-4.0) * t.noh * (a2 - one) / tt) * t.dnoh;
    let v_voh = v_spec * d * vis * (splat(-5.0 * (1.0 - F0)) * pow4_x8(om)) * t.dvoh;
    let r = splat(sf.r);
    let v_roughness = v_a2 * splat(4.0) * r * r * r;

    let (n, wo, h) = (sf.n, sf.wo, t.h);
    let mut v_n: [f64x8; 3] = std::array::from_fn(|k| wi[k] * v_nol + wo[k] * v_nov);
    for k in 0..3 {
        v_n[k] += h[k] * v_noh;
    }
    let mut v_wo: [f64x8; 3] = std::array::from_fn(|k| n[k] * v_nov);
    for k in 0..3 {
        v_wo[k] += h[k] * v_voh;
    }
    // h = s/|s|: the gradient projected on h's tangent plane, where h exists.
    let v_h: [f64x8; 3] = std::array::from_fn(|k| n[k] * v_noh + wo[k] * v_voh);
    let hv = dot3(h, v_h);
    let inv = one / t.s_len;
    for k in 0..3 {
        let v_s = (v_h[k] + h[k] * -hv) * inv;
        v_wo[k] = t.live.select(v_wo[k] + v_s, v_wo[k]);
    }
    LobeGrads { spec, v_roughness, v_n, v_wo }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shade::brdf;
    use crate::shade::testutil::{rng, unit, unit_in};
    use rand::RngExt;

    /// A unit vector 0–1° above the tangent plane of n.
    fn grazing(g: &mut rand_pcg::Pcg64, n: V3) -> V3 {
        loop {
            let v = unit(g);
            let c = crate::shade::dot(v, n);
            if c > 0.0 && c < 0.0175 {
                return v;
            }
        }
    }

    fn lanes_of(dirs: &[V3; LANES]) -> Dirs8 {
        std::array::from_fn(|k| std::array::from_fn(|j| dirs[j][k]))
    }

    /// Every lane equals the scalar lobe and its backward bit for bit, on random cases and on
    /// the edge cases of the scalar tests (grazing, below the horizon, mirror, tiny roughness,
    /// ω_i = −ω_o).
    #[test]
    fn lanes_are_the_scalar_lobe() {
        let mut g = rng(41);
        let mut cases = 0;
        for round in 0..400 {
            let n = unit(&mut g);
            let wo = if round % 7 == 0 { grazing(&mut g, n) } else { unit_in(&mut g, n, 0.0) };
            let r = match round % 5 {
                0 => 1e-4,
                1 => 0.02,
                _ => g.random_range(0.05..1.0),
            };
            let mut dirs: [V3; LANES] = std::array::from_fn(|_| unit(&mut g));
            // Edge lanes: the mirror direction, ω_i = −ω_o, grazing, exactly n.
            let m = crate::shade::sub(crate::shade::scale(n, 2.0 * crate::shade::dot(n, wo)), wo);
            dirs[1] = m;
            dirs[2] = wo.map(|x| -x);
            dirs[3] = grazing(&mut g, n);
            dirs[4] = n;
            let v: [f64; LANES] = std::array::from_fn(|_| g.random_range(-2.0..2.0));
            let lanes = lanes_of(&dirs);
            let fwd = specular(r, n, wo, &lanes);
            let both = specular_with_backward(r, n, wo, &lanes, &v);
            for j in 0..LANES {
                let (s, bg) = brdf::specular_with_backward(r, n, wo, dirs[j], v[j]);
                assert_eq!(fwd[j].to_bits(), brdf::specular(r, n, wo, dirs[j]).to_bits(), "fwd lane {j}");
                assert_eq!(both.spec[j].to_bits(), s.to_bits(), "spec lane {j} round {round}");
                assert_eq!(both.v_roughness[j].to_bits(), bg.v_roughness.to_bits(), "v_r lane {j} round {round}");
                for k in 0..3 {
                    assert_eq!(both.v_n[k][j].to_bits(), bg.v_n[k].to_bits(), "v_n lane {j} round {round}");
                    assert_eq!(both.v_wo[k][j].to_bits(), bg.v_wo[k].to_bits(), "v_wo lane {j} round {round}");
                }
                cases += 1;
            }
        }
        assert_eq!(cases, 400 * LANES);
    }
}
