//! The specular lobe of [`super::brdf`] for eight samples of one surfel at once (eight f64 or
//! f32 lanes, [`FloatLanes`]), forward and backward side by side: most of the per-sample
//! rendering equation's arithmetic is here, and a surfel's samples share n, ω_o and r ([`Lobe`]
//! holds what they share, Smith's ω_o factor included; `pbr.rs` calls it on blocks of eight
//! samples).
//!
//! The formulas are `brdf.rs`'s, rearranged for lanes: the per-surfel parts are hoisted, and the
//! per-sample divisions share reciprocals: the backward takes two square roots and four
//! divisions a sample where the scalar code takes three and eleven, the forward two and two
//! (f64 divisions and roots are slow, and on AVX2 each f64x8 operation is two; −3 to −4 % of
//! each shading pass, BENCHMARKS.md session 88). The results equal the scalar lobe to rounding,
//! not bit for bit; `brdf.rs` stays the reference and the tests here compare the f64 lanes
//! against it on random and edge cases (the f32 lanes are bounded against the f64 ones in
//! `pbr/linearised.rs`, the only f32 user).

use super::V3;
use super::brdf::{ALPHA2_MIN, COS_EPS, F0, alpha2};
use super::float_lanes::FloatLanes;
use std::f64::consts::PI;
use wide::f64x8;

/// Samples per call.
pub const LANES: usize = 8;

/// Eight unit directions ω_i, structure of arrays.
pub type Dirs8 = [[f64; LANES]; 3];

#[inline]
fn splat<L: FloatLanes>(x: f64) -> L {
    L::splat(x)
}

#[inline]
fn dot3<L: FloatLanes>(a: [L; 3], b: [L; 3]) -> L {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// The clamped cosine and its derivative mask (1 inside [COS_EPS, 1], 0 outside), as
/// `brdf::clamp_cos`.
#[inline]
fn clamp_cos<L: FloatLanes>(x: L) -> (L, L) {
    let below = x.lt(splat::<L>(COS_EPS));
    let above = x.gt(splat::<L>(1.0));
    let v = below.select(splat::<L>(COS_EPS), above.select(splat::<L>(1.0), x));
    let d = (below | above).select(splat::<L>(0.0), splat::<L>(1.0));
    (v, d)
}

/// The per-surfel constants of the lobe (the scalar code recomputes them per sample): build
/// one per surfel and view, then evaluate it on blocks of eight directions.
#[derive(Clone, Copy)]
pub struct Lobe<L: FloatLanes = f64x8> {
    n: [L; 3],
    wo: [L; 3],
    nov: L,
    dnov: L,
    a2: L,
    /// 1 − α², α²/π and 1/α².
    one_minus_a2: L,
    a2_over_pi: L,
    inv_a2: L,
    /// Smith's ω_o factor A_v = √(NoV²(1 − α²) + α²) and the per-surfel parts of V's
    /// derivatives: NoV(1 − α²)/A_v (in ∂den/∂NoV) and (1 − NoV²)/(2A_v) (in ∂den/∂α²).
    av: L,
    nov_term: L,
    a2_term: L,
    /// α² above its floor (the roughness gradient is zero below it).
    a2_live: bool,
    r: f64,
}

impl<L: FloatLanes> Lobe<L> {
    #[inline]
    pub fn new(r: f64, n: V3, wo: V3) -> Lobe<L> {
        let (nov, dnov) = super::brdf::clamp_cos(super::dot(n, wo));
        let r4 = r * r * r * r;
        let a2 = alpha2(r);
        let av = (nov * nov * (1.0 - a2) + a2).sqrt();
        Lobe {
            n: n.map(splat),
            wo: wo.map(splat),
            nov: splat::<L>(nov),
            dnov: splat::<L>(dnov),
            a2: splat::<L>(a2),
            one_minus_a2: splat::<L>(1.0 - a2),
            a2_over_pi: splat::<L>(a2 / PI),
            inv_a2: splat::<L>(1.0 / a2),
            av: splat::<L>(av),
            nov_term: splat::<L>(nov * (1.0 - a2) / av),
            a2_term: splat::<L>((1.0 - nov * nov) / (2.0 * av)),
            a2_live: r4 > ALPHA2_MIN,
            r,
        }
    }

    /// F·D·V of eight unit directions ω_i (`brdf::specular` per lane): D·V = α²/(π·tt²) ·
    /// 1/(2·den) with one division.
    #[inline]
    pub fn eval(&self, wi: [L; 3]) -> L {
        let t = terms(self, wi);
        let one = splat::<L>(1.0);
        let tt = tt_of(t.noh, self);
        let den = t.nol * self.av + self.nov * smith_al(t.nol, self);
        let f = splat::<L>(F0) + splat::<L>(1.0 - F0) * pow5_x8(one - t.voh);
        f * self.a2_over_pi * splat::<L>(0.5) / (tt * tt * den)
    }

    /// The lobe and its gradients for upstream gradients `v_spec` (one per lane; lanes whose
    /// result is not used should get 0 and any unit direction).
    #[inline]
    pub fn eval_with_backward(&self, wi: [L; 3], v_spec: L) -> LobeGrads<L> {
        lobe_backward(self, wi, v_spec)
    }
}

/// [`Lobe::eval_with_backward`]'s result, in lanes (∂/∂ω_i is not needed by the shading and
/// not returned).
#[derive(Clone, Copy)]
pub struct LobeGrads<L: FloatLanes = f64x8> {
    pub spec: L,
    pub v_roughness: L,
    pub v_n: [L; 3],
    pub v_wo: [L; 3],
}

/// Half vector and cosines of eight samples (`brdf::terms`).
struct Terms<L: FloatLanes> {
    nol: L,
    noh: L,
    voh: L,
    dnol: L,
    dnoh: L,
    dvoh: L,
    h: [L; 3],
    /// 1/|ω_o + ω_i|.
    inv_s: L,
    /// Lanes where s_len > 1e-12 (a half vector exists).
    live: L,
}

#[inline]
fn terms<L: FloatLanes>(sf: &Lobe<L>, wi: [L; 3]) -> Terms<L> {
    let s = [sf.wo[0] + wi[0], sf.wo[1] + wi[1], sf.wo[2] + wi[2]];
    let s_len = dot3(s, s).sqrt();
    let live_mask = s_len.gt(splat::<L>(1e-12));
    let inv = splat::<L>(1.0) / s_len;
    let h: [L; 3] = std::array::from_fn(|k| live_mask.select(s[k] * inv, sf.n[k]));
    let (nol, dnol) = clamp_cos(dot3(sf.n, wi));
    let (noh, dnoh) = clamp_cos(dot3(sf.n, h));
    let (voh, dvoh) = clamp_cos(dot3(sf.wo, h));
    let live = live_mask.select(splat::<L>(1.0), splat::<L>(0.0));
    Terms { nol, noh, voh, dnol, dnoh: dnoh * live, dvoh: dvoh * live, h, inv_s: inv, live: live_mask }
}

/// tt = 1 − NoH²(1 − α²) of D = α²/(π·tt²), never below its exact minimum α² (at NoH = 1):
/// in f32, 1 − α² rounds to 1 for α² < 6e-8 and a mirror sample would divide by zero. In exact
/// arithmetic the bound is never active, so the backward keeps tt's plain derivative.
#[inline]
fn tt_of<L: FloatLanes>(noh: L, sf: &Lobe<L>) -> L {
    (splat::<L>(1.0) - noh * noh * sf.one_minus_a2).max(sf.a2)
}

/// Smith's ω_i factor A_l = √(NoL²(1 − α²) + α²) (`brdf::smith_visibility`).
#[inline]
fn smith_al<L: FloatLanes>(nol: L, sf: &Lobe<L>) -> L {
    (nol * nol * sf.one_minus_a2 + sf.a2).sqrt()
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
fn pow5_x8<L: FloatLanes>(x: L) -> L {
    let x2 = x * x;
    x2 * x2 * x
}

#[inline]
fn pow4_x8<L: FloatLanes>(x: L) -> L {
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
fn lobe_backward<L: FloatLanes>(sf: &Lobe<L>, wi: [L; 3], v_spec: L) -> LobeGrads<L> {
    let t = terms(sf, wi);
    let one = splat::<L>(1.0);
    let a2 = sf.a2;
    let tt = tt_of(t.noh, sf);
    let al = smith_al(t.nol, sf);
    let den = t.nol * sf.av + sf.nov * al;
    // Three independent reciprocals (one shared division, 1/(tt·A_l·den), measured 12 % slower
    // in the linearised forward: its longer dependency chain outweighed the two divisions saved).
    let inv_tt = one / tt;
    let inv_al = one / al;
    let inv_den = one / den;
    let d = sf.a2_over_pi * inv_tt * inv_tt;
    let om = one - t.voh;
    let fr = splat::<L>(F0) + splat::<L>(1.0 - F0) * pow5_x8(om);
    // Smith (`brdf::smith_visibility`): V = 1/(2·den), ∂V/∂x = −V·∂den/∂x/den.
    let vis = splat::<L>(0.5) * inv_den;
    let k = -vis * inv_den;
    let dvis_nol = k * (sf.av + sf.nov * t.nol * sf.one_minus_a2 * inv_al);
    let dvis_nov = k * (al + t.nol * sf.nov_term);
    let spec = fr * d * vis;
    let vs = v_spec * spec;
    let v_fd = v_spec * fr * d;
    let v_nol = v_fd * dvis_nol * t.dnol;
    let v_nov = v_fd * dvis_nov * sf.dnov;
    let v_a2 = if sf.a2_live {
        let dvis_a2 = k * (t.nol * sf.a2_term + sf.nov * (one - t.nol * t.nol) * splat::<L>(0.5) * inv_al);
        vs * (sf.inv_a2 - splat::<L>(2.0) * t.noh * t.noh * inv_tt) + v_fd * dvis_a2
    } else {
        splat::<L>(0.0)
    };
    let v_noh = vs * (splat::<L>(-4.0) * t.noh * (a2 - one) * inv_tt) * t.dnoh;
    let v_voh = v_spec * d * vis * (splat::<L>(-5.0 * (1.0 - F0)) * pow4_x8(om)) * t.dvoh;
    let r = splat::<L>(sf.r);
    let v_roughness = v_a2 * splat::<L>(4.0) * r * r * r;

    let (n, wo, h) = (sf.n, sf.wo, t.h);
    let mut v_n: [L; 3] = std::array::from_fn(|k| wi[k] * v_nol + wo[k] * v_nov);
    for k in 0..3 {
        v_n[k] += h[k] * v_noh;
    }
    let mut v_wo: [L; 3] = std::array::from_fn(|k| n[k] * v_nov);
    for k in 0..3 {
        v_wo[k] += h[k] * v_voh;
    }
    // h = s/|s|: the gradient projected on h's tangent plane, where h exists.
    let v_h: [L; 3] = std::array::from_fn(|k| n[k] * v_noh + wo[k] * v_voh);
    let hv = dot3(h, v_h);
    for k in 0..3 {
        let v_s = (v_h[k] + h[k] * -hv) * t.inv_s;
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

    /// Every lane equals the scalar lobe and its backward to rounding (the lanes share
    /// reciprocals the scalar code divides by separately), on random cases and on the edge cases
    /// of the scalar tests (grazing, below the horizon, mirror, tiny roughness, ω_i = −ω_o).
    /// The tolerance is relative to each quantity's own scale: the lobe and the roughness
    /// gradient to their magnitude, a gradient vector's components to its largest component.
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
                let s_ref = brdf::specular(r, n, wo, dirs[j]);
                assert_eq!(s.to_bits(), s_ref.to_bits(), "the scalar lobe's two paths");
                // At the exact mirror direction (and at ω_i = −ω_o, where h falls back to n)
                // 1 − NoH is a rounding error (≈ 1e-16) against tt = 1 − NoH²(1 − α²) ≈ α², so both
                // codes carry a relative error ≈ 1e-16/α² there (1e-4 at the α² floor of 1e-12,
                // measured up to 2.3e-4 in v_wo; elsewhere 1e-12), and the lanes keep tt ≥ α², its
                // exact minimum, where the scalar code may round below it.
                let tol = if j == 1 || j == 2 { 1e-12 + 1e-14 / brdf::alpha2(r) } else { 1e-12 };
                let check = |got: f64, want: f64, scale: f64, what: &str| {
                    let err = (got - want).abs() / scale.max(f64::MIN_POSITIVE);
                    assert!(err <= tol, "{what} lane {j} round {round}: {got} vs {want}");
                };
                check(fwd[j], s_ref, s_ref.abs(), "fwd");
                check(both.spec[j], s, s.abs(), "spec");
                check(both.v_roughness[j], bg.v_roughness, bg.v_roughness.abs(), "v_r");
                let sn = bg.v_n.iter().fold(0f64, |a, b| a.max(b.abs()));
                let sw = bg.v_wo.iter().fold(0f64, |a, b| a.max(b.abs()));
                for k in 0..3 {
                    check(both.v_n[k][j], bg.v_n[k], sn, "v_n");
                    check(both.v_wo[k][j], bg.v_wo[k], sw, "v_wo");
                }
                cases += 1;
            }
        }
        assert_eq!(cases, 400 * LANES);
    }
}
