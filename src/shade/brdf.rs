//! The dielectric BRDF of DESIGN §1 (simplified Disney, as RadioGS/IRGS), with the diffuse
//! base under the specular layer as Blender's Principled BSDF layers them:
//!
//!     f(ω_o, ω_i) = (1 − E(NoV, r))·a/π + F·D·G / (4·NoL·NoV)
//!     E(NoV, r) = ∫ F·D·G/(4·NoL·NoV)·NoL dω_i = F0·A + B   (the split-sum LUT)
//!     D = α² / (π·(NoH²(α² − 1) + 1)²),          α = r²           (GGX)
//!     G = 1/(1 + Λ(NoL) + Λ(NoV)), Λ(x) = (√(1 + α²(1/x² − 1)) − 1)/2  (height-correlated Smith)
//!     F = f0 + (1 − f0)(1 − VoH)⁵,                f0 = 0.04        (Schlick)
//!
//! with h = (ω_o + ω_i)/|ω_o + ω_i| and every cosine clamped to [1e-6, 1] (the gradient of a
//! clamped cosine is zero). G/(4·NoL·NoV) is evaluated as the visibility term
//! V = 1/(2·(NoL·A_v + NoV·A_l)) ([`smith_visibility`]), bounded at grazing angles.
//! α² is floored at 1e-12 (r < 1e-3 behaves as r = 1e-3, zero roughness gradient there).
//!
//! Why the (1 − E) weight: the shared datasets are rendered by Cycles, whose Principled BSDF
//! scales the base layer by one minus the specular layer's directional albedo (its
//! `closure_layering_weight`). Plain Lambert + GGX is up to 15 % brighter at grazing views, a
//! bias the learned albedo absorbs and relighting then shows (BENCHMARKS.md, session 17). It
//! also makes the lobe energy-conserving: a white surface reflects exactly 1 − E + E = 1.
//! DESIGN §1 has plain a/π; README lists the difference.
//!
//! Scalar, per sample; nothing is saved for the backward (it recomputes the few terms). The
//! shading runs the lobe eight samples at a time through `brdf_lanes.rs`, which mirrors this
//! code operation for operation; this file is its reference.

use super::{V3, add, dot, scale};
use std::f64::consts::PI;

/// Fresnel reflectance at normal incidence of the dielectric.
pub const F0: f64 = 0.04;
/// Lower clamp of every cosine.
pub const COS_EPS: f64 = 1e-6;
pub(crate) const ALPHA2_MIN: f64 = 1e-12;

#[inline]
pub(crate) fn clamp_cos(x: f64) -> (f64, f64) {
    // Returns the clamped value and the derivative of the clamp (1 inside, 0 outside).
    if x < COS_EPS {
        (COS_EPS, 0.0)
    } else if x > 1.0 {
        (1.0, 0.0)
    } else {
        (x, 1.0)
    }
}

/// x⁵ and x⁴ by explicit products (the lane kernels in `brdf_lanes.rs` repeat this order).
#[inline]
pub(crate) fn pow5(x: f64) -> f64 {
    let x2 = x * x;
    x2 * x2 * x
}
#[inline]
pub(crate) fn pow4(x: f64) -> f64 {
    let x2 = x * x;
    x2 * x2
}

/// GGX normal distribution D(NoH) with α² given.
#[inline]
pub fn ggx_d(noh: f64, alpha2: f64) -> f64 {
    let t = noh * noh * (alpha2 - 1.0) + 1.0;
    alpha2 / (PI * t * t)
}

/// α² = r⁴ with the floor.
#[inline]
pub fn alpha2(r: f64) -> f64 {
    (r * r * r * r).max(ALPHA2_MIN)
}

/// Intermediate terms shared by forward and backward.
struct Terms {
    nol: f64,
    nov: f64,
    noh: f64,
    voh: f64,
    dnol: f64,
    dnov: f64,
    dnoh: f64,
    dvoh: f64,
    h: V3,
    s_len: f64,
}

#[inline]
fn terms(n: V3, wo: V3, wi: V3) -> Terms {
    let s = add(wo, wi);
    let s_len = dot(s, s).sqrt();
    // ω_o = −ω_i has no half vector; use n (only reachable at both cosines clamped).
    let h = if s_len > 1e-12 { scale(s, 1.0 / s_len) } else { n };
    let (nol, dnol) = clamp_cos(dot(n, wi));
    let (nov, dnov) = clamp_cos(dot(n, wo));
    let (noh, dnoh) = clamp_cos(dot(n, h));
    let (voh, dvoh) = clamp_cos(dot(wo, h));
    let live = if s_len > 1e-12 { 1.0 } else { 0.0 };
    Terms { nol, nov, noh, voh, dnol, dnov, dnoh: dnoh * live, dvoh: dvoh * live, h, s_len }
}

/// The specular lobe F·D·G/(4·NoL·NoV) with a given f0 (scalar; same for r, g, b).
#[inline]
pub fn specular_f0(r: f64, n: V3, wo: V3, wi: V3, f0: f64) -> f64 {
    let t = terms(n, wo, wi);
    let a2 = alpha2(r);
    let d = ggx_d(t.noh, a2);
    let f = f0 + (1.0 - f0) * pow5(1.0 - t.voh);
    f * d * smith_visibility(t.nol, t.nov, a2).0
}

/// Height-correlated Smith visibility of GGX, V = G₂/(4·NoL·NoV) with
/// G₂ = 1/(1 + Λ(NoL) + Λ(NoV)) (Heitz 2014; what Cycles' microfacet closures use):
///
///     V = 1 / (2·(NoL·A_v + NoV·A_l)),   A_x = √(x²(1 − α²) + α²)
///
/// Returns (V, ∂V/∂NoL, ∂V/∂NoV, ∂V/∂α²). Bounded unless both cosines vanish.
#[inline]
pub fn smith_visibility(nol: f64, nov: f64, a2: f64) -> (f64, f64, f64, f64) {
    let al = (nol * nol * (1.0 - a2) + a2).sqrt();
    let av = (nov * nov * (1.0 - a2) + a2).sqrt();
    let den = nol * av + nov * al;
    let v = 0.5 / den;
    // ∂V/∂x = −V·∂den/∂x / den.
    let k = -v / den;
    let d_nol = av + nov * nol * (1.0 - a2) / al;
    let d_nov = al + nol * nov * (1.0 - a2) / av;
    let d_a2 = nol * (1.0 - nov * nov) / (2.0 * av) + nov * (1.0 - nol * nol) / (2.0 * al);
    (v, k * d_nol, k * d_nov, k * d_a2)
}

/// The specular lobe with f0 = 0.04.
#[inline]
pub fn specular(r: f64, n: V3, wo: V3, wi: V3) -> f64 {
    specular_f0(r, n, wo, wi, F0)
}

/// Weight 1 − E(NoV, r) of the Lambert lobe (see the module note) and its derivatives
/// (∂/∂NoV, ∂/∂r) for the unclamped cosine NoV = n·ω_o; the clamped cosine and roughness
/// outside [0, 1] have zero derivative.
#[inline]
pub fn diffuse_weight(nov: f64, r: f64) -> (f64, f64, f64) {
    let (c, dc) = clamp_cos(nov);
    let lut = super::splitsum::BrdfLut::get().lookup(c, r);
    (1.0 - (F0 * lut.a + lut.b), -(F0 * lut.da_dnov + lut.db_dnov) * dc, -(F0 * lut.da_dr + lut.db_dr))
}

/// f(ω_o, ω_i) for albedo `a` (linear rgb), roughness `r`, normal `n`.
#[inline]
pub fn eval(a: V3, r: f64, n: V3, wo: V3, wi: V3) -> V3 {
    let s = specular(r, n, wo, wi);
    let kd = diffuse_weight(dot(n, wo), r).0 / PI;
    [a[0] * kd + s, a[1] * kd + s, a[2] * kd + s]
}

/// Gradients of [`eval`] for an upstream gradient `v_f` on the three channels of f.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BrdfGrads {
    pub v_albedo: V3,
    pub v_roughness: f64,
    pub v_n: V3,
    pub v_wo: V3,
    pub v_wi: V3,
}

/// Backward of [`eval`].
#[inline]
pub fn eval_backward(a: V3, r: f64, n: V3, wo: V3, wi: V3, v_f: V3) -> BrdfGrads {
    let v_spec = v_f[0] + v_f[1] + v_f[2];
    let mut g = specular_backward(r, n, wo, wi, v_spec);
    let (w, dw_dnov, dw_dr) = diffuse_weight(dot(n, wo), r);
    g.v_albedo = scale(v_f, w / PI);
    // The Lambert lobe's weight depends on NoV and r.
    let v_w = dot(v_f, a) / PI;
    g.v_roughness += v_w * dw_dr;
    g.v_n = add(g.v_n, scale(wo, v_w * dw_dnov));
    g.v_wo = add(g.v_wo, scale(n, v_w * dw_dnov));
    g
}

/// Backward of [`specular`] (v_albedo left zero).
#[inline]
pub fn specular_backward(r: f64, n: V3, wo: V3, wi: V3, v_spec: f64) -> BrdfGrads {
    specular_with_backward(r, n, wo, wi, v_spec).1
}

/// [`specular`] and its backward in one pass (the upstream gradient must not depend on the
/// value): returns (spec, gradients with v_albedo zero).
#[inline]
pub fn specular_with_backward(r: f64, n: V3, wo: V3, wi: V3, v_spec: f64) -> (f64, BrdfGrads) {
    let t = terms(n, wo, wi);
    let r4 = r * r * r * r;
    let a2 = alpha2(r);
    let tt = t.noh * t.noh * (a2 - 1.0) + 1.0;
    let d = a2 / (PI * tt * tt);
    let om = 1.0 - t.voh;
    let fr = F0 + (1.0 - F0) * pow5(om);
    let (vis, dvis_nol, dvis_nov, dvis_a2) = smith_visibility(t.nol, t.nov, a2);
    let spec = fr * d * vis;
    let vs = v_spec * spec;
    let v_fd = v_spec * fr * d;
    let v_nol = v_fd * dvis_nol * t.dnol;
    let v_nov = v_fd * dvis_nov * t.dnov;
    // Log-derivative of D (D > 0 always); α² is constant below its floor.
    let v_a2 = if r4 > ALPHA2_MIN { vs * (1.0 / a2 - 2.0 * t.noh * t.noh / tt) + v_fd * dvis_a2 } else { 0.0 };
    let v_noh = vs * (-4.0 * t.noh * (a2 - 1.0) / tt) * t.dnoh;
    let v_voh = v_spec * d * vis * (-5.0 * (1.0 - F0) * pow4(om)) * t.dvoh;
    let v_roughness = v_a2 * 4.0 * r * r * r;

    let mut v_n = add(scale(wi, v_nol), scale(wo, v_nov));
    v_n = add(v_n, scale(t.h, v_noh));
    let mut v_wo = scale(n, v_nov);
    let mut v_wi = scale(n, v_nol);
    v_wo = add(v_wo, scale(t.h, v_voh));
    // h = s/|s|: project the gradient on h's tangent plane.
    let v_h = add(scale(n, v_noh), scale(wo, v_voh));
    if t.s_len > 1e-12 {
        let hv = dot(t.h, v_h);
        let v_s = scale(add(v_h, scale(t.h, -hv)), 1.0 / t.s_len);
        v_wo = add(v_wo, v_s);
        v_wi = add(v_wi, v_s);
    }
    (spec, BrdfGrads { v_albedo: [0.0; 3], v_roughness, v_n, v_wo, v_wi })
}

/// Reference directional albedo ∫ spec(ω_o, ω_i)·NoL dω_i (f0 given), by quadrature over the
/// half vector with a roughness-adapted polar grid: dω_i = 4·VoH·dω_h. Slow; tests only.
#[cfg(test)]
pub(crate) fn directional_albedo_reference(nov: f64, r: f64, f0: f64, nu: usize) -> f64 {
    let n = [0.0, 0.0, 1.0];
    let wo = [(1.0 - nov * nov).max(0.0).sqrt(), 0.0, nov];
    let alpha = alpha2(r).sqrt();
    let mut acc = 0.0;
    for iu in 0..nu {
        let u = (iu as f64 + 0.5) / nu as f64;
        let x = u / (1.0 - u);
        let theta = (alpha * x).atan();
        let dtheta = alpha / (1.0 + alpha * alpha * x * x) / ((1.0 - u) * (1.0 - u)) / nu as f64;
        for ip in 0..2 * nu {
            let phi = (ip as f64 + 0.5) / (2 * nu) as f64 * 2.0 * PI;
            let dphi = 2.0 * PI / (2 * nu) as f64;
            let h = [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()];
            let voh = dot(wo, h);
            if voh <= 0.0 {
                continue;
            }
            let wi = add(scale(h, 2.0 * voh), scale(wo, -1.0));
            let nol = wi[2];
            if nol <= 0.0 {
                continue;
            }
            acc += specular_f0(r, n, wo, wi, f0) * nol * 4.0 * voh * theta.sin() * dtheta * dphi;
        }
    }
    acc
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shade::normalize;
    use crate::shade::testutil::{close, rng, unit, unit_in};
    use rand::RngExt;

    /// Central-difference check of every input of `eval`, on the sum of w·f.
    fn check(a: V3, r: f64, n: V3, wo: V3, wi: V3, tag: &str) {
        let w = [0.7, -0.3, 1.1];
        let obj = |a: V3, r: f64, n: V3, wo: V3, wi: V3| dot(w, eval(a, r, n, wo, wi));
        let g = eval_backward(a, r, n, wo, wi, w);
        // The GGX peak of r ≈ 0 varies on scales ~α² in NoH: use a smaller step there.
        let eps = if r < 0.05 { 1e-9 } else { 1e-7 };
        let base = obj(a, r, n, wo, wi).abs().max(1e-3);
        // Absolute slack relative to the largest gradient component (components that cancel
        // down to ~1e-6 of the gradient's scale carry the FD's round-off).
        let gmax = [g.v_n, g.v_wo, g.v_wi].iter().flatten().fold(g.v_roughness.abs(), |m, x| m.max(x.abs()));
        let tol = |an: f64, fd: f64| close(an, fd, 2e-4, 1e-5 * base + 1e-7 * gmax);
        let fd_r = (obj(a, r + eps, n, wo, wi) - obj(a, r - eps, n, wo, wi)) / (2.0 * eps);
        // The Lambert weight's LUT clamps r at 1 (a kink a central difference straddles there).
        if r + eps <= 1.0 {
            assert!(tol(g.v_roughness, fd_r), "{tag}: v_r {} vs fd {}", g.v_roughness, fd_r);
        }
        for c in 0..3 {
            let e = |v: V3| {
                let mut p = v;
                p[c] += eps;
                let mut m = v;
                m[c] -= eps;
                (p, m)
            };
            let (p, m) = e(a);
            let fd = (obj(p, r, n, wo, wi) - obj(m, r, n, wo, wi)) / (2.0 * eps);
            assert!(tol(g.v_albedo[c], fd), "{tag}: v_a[{c}] {} vs {fd}", g.v_albedo[c]);
            let (p, m) = e(n);
            let fd = (obj(a, r, p, wo, wi) - obj(a, r, m, wo, wi)) / (2.0 * eps);
            assert!(tol(g.v_n[c], fd), "{tag}: v_n[{c}] {} vs {fd}", g.v_n[c]);
            let (p, m) = e(wo);
            let fd = (obj(a, r, n, p, wi) - obj(a, r, n, m, wi)) / (2.0 * eps);
            assert!(tol(g.v_wo[c], fd), "{tag}: v_wo[{c}] {} vs {fd}", g.v_wo[c]);
            let (p, m) = e(wi);
            let fd = (obj(a, r, n, wo, p) - obj(a, r, n, wo, m)) / (2.0 * eps);
            assert!(tol(g.v_wi[c], fd), "{tag}: v_wi[{c}] {} vs {fd}", g.v_wi[c]);
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rg = rng(1);
        for case in 0..200 {
            let n = unit(&mut rg);
            let wo = unit_in(&mut rg, n, 0.02);
            let wi = unit_in(&mut rg, n, 0.02);
            let r = rg.random_range(0.03..1.0);
            let a = [rg.random(), rg.random(), rg.random()];
            check(a, r, n, wo, wi, &format!("random {case}"));
        }
    }

    #[test]
    fn backward_edge_cases() {
        let n = [0.0, 0.0, 1.0];
        let a = [0.5, 0.2, 0.9];
        let tilt =
            |z: f64, phi: f64| normalize([(1.0 - z * z).sqrt() * phi.cos(), (1.0 - z * z).sqrt() * phi.sin(), z]);
        // Grazing ω_i and ω_o (cosines 1e-3 and 1e-5, above the clamp), all roughness ranges.
        for &r in &[0.02, 0.1, 0.5, 0.95, 0.999, 1.0] {
            check(a, r, n, tilt(1e-3, 0.3), tilt(0.6, 2.0), &format!("grazing wi r={r}"));
            check(a, r, n, tilt(0.7, 0.1), tilt(1e-5, 1.2), &format!("grazing wi2 r={r}"));
            check(a, r, n, tilt(2e-3, 0.0), tilt(3e-3, 3.0), &format!("both grazing r={r}"));
            // Below the clamp: the clamped cosine has no gradient; the rest still must match.
            check(a, r, n, tilt(0.5, 0.2), tilt(-0.2, 1.0), &format!("wi below r={r}"));
            check(a, r, n, tilt(-1e-7, 0.2), tilt(0.4, 1.0), &format!("wo at clamp r={r}"));
            // Near-mirror configuration (NoH → 1), where the GGX peak lives.
            check(a, r, n, tilt(0.6, 0.0), tilt(0.6 + 2e-3, PI + 5e-3), &format!("mirror r={r}"));
            // (NoH stays ≥ 5e-6 below 1 so the FD steps do not cross the NoH ≤ 1 clamp.)
        }
    }

    #[test]
    fn specular_reciprocal_and_lambert_part_weighted() {
        let mut rg = rng(2);
        for _ in 0..500 {
            let n = unit(&mut rg);
            let wo = unit_in(&mut rg, n, 0.0);
            let wi = unit_in(&mut rg, n, 0.0);
            let r: f64 = rg.random_range(0.0..1.0);
            let a = [rg.random(), rg.random(), rg.random()];
            let s1 = specular(r, n, wo, wi);
            assert!(close(s1, specular(r, n, wi, wo), 1e-10, 0.0));
            let f = eval(a, r, n, wo, wi);
            let w = diffuse_weight(dot(n, wo), r).0;
            for c in 0..3 {
                assert!(close(f[c], a[c] * w / PI + s1, 1e-12, 1e-15));
            }
        }
    }

    /// The Lambert weight is one minus the specular lobe's directional albedo (checked against
    /// an independent quadrature, not the LUT), so a white surface reflects all it receives.
    #[test]
    fn white_surface_conserves_energy() {
        for &r in &[0.1, 0.3, 0.5, 0.8, 1.0] {
            for &nov in &[0.1, 0.4, 0.8, 1.0] {
                let e = directional_albedo_reference(nov, r, F0, 200);
                let w = diffuse_weight(nov, r).0;
                assert!((w + e - 1.0).abs() < 5e-3, "r={r} NoV={nov}: 1 − E {w} vs quadrature E {e}");
                // (At grazing views a smooth dielectric reflects most: Schlick's F at 84° is 0.61.)
                assert!(w < 1.0 && w > 0.35, "r={r} NoV={nov}: 1 − E {w}");
            }
        }
    }

    #[test]
    fn directional_albedo_at_most_one() {
        for &r in &[0.05, 0.1, 0.2, 0.35, 0.5, 0.7, 0.85, 1.0] {
            for &nov in &[0.02, 0.1, 0.3, 0.6, 1.0] {
                let e = directional_albedo_reference(nov, r, 1.0, 200);
                assert!(e <= 1.0 && e > 0.0, "r={r} NoV={nov}: f0=1 albedo {e}");
                let e04 = directional_albedo_reference(nov, r, F0, 200);
                assert!(e04 < e && e04 > 0.0);
            }
        }
        // A smooth mirror-like lobe at normal incidence reflects f0·G ≈ f0 (G ≈ 1 there):
        // checks the quadrature itself is not trivially small.
        let e = directional_albedo_reference(1.0, 0.05, 1.0, 300);
        assert!(e > 0.9, "{e}");
    }

    /// The visibility term against G₂ = 1/(1 + Λ(NoL) + Λ(NoV)) written from Smith's Λ of GGX
    /// directly, Λ(x) = (√(1 + α² tan²θ) − 1)/2: the lobe Cycles renders the datasets with.
    #[test]
    fn visibility_is_height_correlated_smith() {
        let mut rg = rng(3);
        for _ in 0..500 {
            let (nol, nov): (f64, f64) = (rg.random_range(1e-3..1.0), rg.random_range(1e-3..1.0));
            let a2 = alpha2(rg.random_range(0.02..1.0));
            let lambda = |c: f64| ((1.0 + a2 * (1.0 - c * c) / (c * c)).sqrt() - 1.0) / 2.0;
            let g2 = 1.0 / (1.0 + lambda(nol) + lambda(nov));
            let v = smith_visibility(nol, nov, a2).0;
            assert!(close(v, g2 / (4.0 * nol * nov), 1e-9, 0.0), "NoL {nol} NoV {nov} α² {a2}: {v}");
        }
        // Grazing both ways stays finite.
        assert!(smith_visibility(COS_EPS, COS_EPS, alpha2(0.5)).0.is_finite());
    }
}
