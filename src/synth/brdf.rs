//! The material model radiogs recovers (DESIGN §1), evaluated and sampled for path tracing:
//!
//!   f(ω_o, ω_i) = (1 − E(n·ω_o, r))·a/π + F·D·G / (4 (n·ω_i)(n·ω_o))
//!   D = α² / (π ((n·h)²(α² − 1) + 1)²),  α = r²            (GGX)
//!   G = 1 / (1 + Λ(n·ω_i) + Λ(n·ω_o)),  Λ(c) = (√(1 + α²(1/c² − 1)) − 1)/2   (height-correlated Smith)
//!   F = f0 + (1 − f0)(1 − ω_o·h)⁵,  f0 = 0.04                 (Schlick)
//!
//! The diffuse lobe is weighted by 1 − E(n·ω_o, r), E the specular lobe's directional albedo
//! (the split-sum LUT): the same layering as the inverse model (shade/brdf.rs) and Blender's
//! Principled BSDF. No multiple-scattering compensation; cosines clamped to [1e-6, 1].
//! Sampling: a one-sample mixture of cosine-weighted diffuse and GGX D-sampling (h ∝ D·(n·h),
//! ω_i = reflect(ω_o, h), pdf = D (n·h) / (4 |ω_o·h|)); the mixture pdf is what MIS sees.

use super::sampling::{Frame, cosine_hemisphere};
use glam::Vec3;
use std::f32::consts::PI;

pub const F0: f32 = 0.04;
/// Smallest roughness used in evaluation (α = 1e-4): keeps D finite in f32.
pub const MIN_ROUGHNESS: f32 = 0.01;

/// Material parameters at one shading point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bsdf {
    /// Linear base colour (diffuse albedo).
    pub albedo: Vec3,
    /// Perceptual roughness r in [0, 1] (α = r²).
    pub roughness: f32,
    /// 1 for the radiogs model; 0 turns the specular lobe off (pure Lambert, used by tests).
    pub specular: f32,
}

#[inline]
fn clamp_cos(c: f32) -> f32 {
    c.clamp(1e-6, 1.0)
}

/// GGX normal distribution with α = r².
#[inline]
pub fn ggx_d(noh: f32, roughness: f32) -> f32 {
    let r = roughness.max(MIN_ROUGHNESS);
    let a2 = (r * r) * (r * r);
    let d = noh * noh * (a2 - 1.0) + 1.0;
    a2 / (PI * d * d)
}

/// Height-correlated Smith visibility G/(4 (n·ω_i)(n·ω_o)) = 1 / (2 (NoL·A_v + NoV·A_l)),
/// A_x = √(x²(1 − α²) + α²) (as shade/brdf.rs, in f32).
#[inline]
pub fn smith_visibility(nol: f32, nov: f32, roughness: f32) -> f32 {
    let r = roughness.max(MIN_ROUGHNESS);
    let a2 = (r * r) * (r * r);
    let al = (nol * nol * (1.0 - a2) + a2).sqrt();
    let av = (nov * nov * (1.0 - a2) + a2).sqrt();
    0.5 / (nol * av + nov * al)
}

#[inline]
pub fn schlick_f(voh: f32) -> f32 {
    F0 + (1.0 - F0) * (1.0 - voh).max(0.0).powi(5)
}

impl Bsdf {
    /// f(ω_o, ω_i) for unit vectors and the unit shading normal n; zero below either horizon.
    pub fn eval(&self, n: Vec3, wo: Vec3, wi: Vec3) -> Vec3 {
        let nol = n.dot(wi);
        let nov = n.dot(wo);
        if nol <= 0.0 || nov <= 0.0 {
            return Vec3::ZERO;
        }
        if self.specular <= 0.0 {
            return self.albedo * (1.0 / PI);
        }
        let (nol, nov) = (clamp_cos(nol), clamp_cos(nov));
        let kd = 1.0
            - self.specular * (1.0 - crate::shade::brdf::diffuse_weight(nov as f64, self.roughness as f64).0 as f32);
        let diffuse = self.albedo * (kd / PI);
        let h = (wo + wi).normalize();
        let noh = n.dot(h).clamp(0.0, 1.0);
        let voh = wo.dot(h).clamp(0.0, 1.0);
        let spec = schlick_f(voh) * ggx_d(noh, self.roughness) * smith_visibility(nol, nov, self.roughness);
        diffuse + Vec3::splat(self.specular * spec)
    }

    /// Probability of choosing the specular lobe when sampling, from ω_o's Fresnel vs albedo.
    pub fn specular_probability(&self, nov: f32) -> f32 {
        if self.specular <= 0.0 {
            return 0.0;
        }
        let fs = schlick_f(nov.clamp(0.0, 1.0));
        let lum = 0.2126 * self.albedo.x + 0.7152 * self.albedo.y + 0.0722 * self.albedo.z;
        (fs / (fs + lum.max(0.0) + 1e-6)).clamp(0.2, 0.8)
    }

    /// Solid-angle density of [`Bsdf::sample`] producing ω_i.
    pub fn pdf(&self, n: Vec3, wo: Vec3, wi: Vec3) -> f32 {
        let nov = n.dot(wo);
        let nol = n.dot(wi);
        if nov <= 0.0 {
            return 0.0;
        }
        let ps = self.specular_probability(nov);
        let pd = if nol > 0.0 { nol / PI } else { 0.0 };
        let pspec = if ps > 0.0 { ggx_pdf(n, wo, wi, self.roughness) } else { 0.0 };
        ps * pspec + (1.0 - ps) * pd
    }

    /// Sample ω_i given three uniforms: returns (ω_i, f(ω_o, ω_i), mixture pdf); None when the
    /// sample falls below the horizon or has zero density (the path ends).
    pub fn sample(&self, n: Vec3, wo: Vec3, u: [f32; 3]) -> Option<(Vec3, Vec3, f32)> {
        let nov = n.dot(wo);
        if nov <= 0.0 {
            return None;
        }
        let frame = Frame::new(n);
        let ps = self.specular_probability(nov);
        let wi = if u[0] < ps {
            let h = frame.to_world(ggx_sample_h(u[1], u[2], self.roughness));
            2.0 * wo.dot(h) * h - wo
        } else {
            frame.to_world(cosine_hemisphere(u[1], u[2]))
        };
        let wi = wi.normalize();
        if n.dot(wi) <= 0.0 {
            return None;
        }
        let pdf = self.pdf(n, wo, wi);
        if !(pdf > 0.0 && pdf.is_finite()) {
            return None;
        }
        Some((wi, self.eval(n, wo, wi), pdf))
    }
}

/// GGX half-vector in the local frame, density D(h)(n·h) over the hemisphere.
pub fn ggx_sample_h(u1: f32, u2: f32, roughness: f32) -> Vec3 {
    let r = roughness.max(MIN_ROUGHNESS);
    let a2 = (r * r) * (r * r);
    let cos2 = ((1.0 - u1) / (1.0 + (a2 - 1.0) * u1)).clamp(0.0, 1.0);
    let cos_t = cos2.sqrt();
    let sin_t = (1.0 - cos2).max(0.0).sqrt();
    let phi = 2.0 * PI * u2;
    Vec3::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t)
}

/// Density over ω_i (whole sphere) of reflecting ω_o about a D-sampled half-vector.
pub fn ggx_pdf(n: Vec3, wo: Vec3, wi: Vec3, roughness: f32) -> f32 {
    let hsum = wo + wi;
    if hsum.length_squared() < 1e-12 {
        return 0.0;
    }
    let h = hsum.normalize();
    let noh = n.dot(h);
    let voh = wo.dot(h).abs();
    if noh <= 0.0 || voh <= 1e-8 {
        return 0.0;
    }
    ggx_d(noh, roughness) * noh / (4.0 * voh)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::sampling::{pixel_rng, uniform};

    /// Integrate g over the sphere with a midpoint rule in (cos θ, φ) about `n` = +z, refined
    /// near the pole where GGX lobes concentrate: cos θ = 1 − s² for s ∈ [0, √2].
    fn sphere_integral(g: impl Fn(Vec3) -> f64, ns: usize, nphi: usize) -> f64 {
        sphere_integral_about(Vec3::Z, g, ns, nphi)
    }

    /// The same with the grid's pole at `pole` (put it where the integrand peaks).
    fn sphere_integral_about(pole: Vec3, g: impl Fn(Vec3) -> f64, ns: usize, nphi: usize) -> f64 {
        let frame = Frame::new(pole);
        let smax = 2f64.sqrt();
        let mut acc = 0.0;
        for i in 0..ns {
            let s = (i as f64 + 0.5) / ns as f64 * smax;
            let c = 1.0 - s * s;
            let jac = 2.0 * s * smax / ns as f64; // d(cos θ) = 2 s ds
            let st = (1.0 - c * c).max(0.0).sqrt();
            for j in 0..nphi {
                let phi = (j as f64 + 0.5) / nphi as f64 * 2.0 * std::f64::consts::PI;
                let d = Vec3::new((st * phi.cos()) as f32, (st * phi.sin()) as f32, c as f32);
                acc += g(frame.to_world(d)) * jac * 2.0 * std::f64::consts::PI / nphi as f64;
            }
        }
        acc
    }

    fn dir(theta_deg: f32) -> Vec3 {
        let t = theta_deg.to_radians();
        Vec3::new(t.sin(), 0.0, t.cos())
    }

    #[test]
    fn ggx_sampling_pdf_integrates_to_one() {
        let n = Vec3::Z;
        for &r in &[0.1f32, 0.3, 0.6, 1.0] {
            for &th in &[0.0f32, 40.0, 75.0] {
                let wo = dir(th);
                let mirror = Vec3::new(-wo.x, -wo.y, wo.z);
                let total = sphere_integral_about(mirror, |wi| ggx_pdf(n, wo, wi, r) as f64, 1200, 400);
                // D-sampled half-vectors with ω_o·h < 0 reflect to nothing (the path ends), so
                // the density integrates to P(ω_o·h > 0): 1 at normal incidence, less at grazing.
                let mut rng = pixel_rng(9, 0, 0);
                let m = 100_000;
                let kept = (0..m)
                    .filter(|_| ggx_sample_h(uniform(&mut rng), uniform(&mut rng), r).dot(wo) > 0.0)
                    .count() as f64
                    / m as f64;
                assert!((total - kept).abs() < 0.01, "r {r} θ {th}: ∫pdf = {total}, P(ω_o·h > 0) = {kept}");
                if th == 0.0 {
                    assert!((total - 1.0).abs() < 0.01, "r {r}: ∫pdf = {total}");
                }
                let b = Bsdf { albedo: Vec3::splat(0.5), roughness: r, specular: 1.0 };
                // The mixture pdf loses the GGX mass reflected below the horizon, never more.
                let mix = sphere_integral(|wi| b.pdf(n, wo, wi) as f64, 1200, 400);
                assert!(mix <= 1.0 + 0.01 && mix > 0.75, "r {r} θ {th}: ∫mixture = {mix}");
            }
        }
    }

    #[test]
    fn directional_albedo_at_most_one() {
        let n = Vec3::Z;
        for &r in &[0.05f32, 0.1, 0.2, 0.4, 0.6, 0.8, 1.0] {
            for &th in &[0.0f32, 30.0, 60.0, 85.0] {
                let wo = dir(th);
                // Specular lobe alone (albedo 0), and the brightest albedo radiogs allows (0.8).
                let spec = Bsdf { albedo: Vec3::ZERO, roughness: r, specular: 1.0 };
                let full = Bsdf { albedo: Vec3::splat(0.8), roughness: r, specular: 1.0 };
                let es = sphere_integral(|wi| (spec.eval(n, wo, wi).x * n.dot(wi).max(0.0)) as f64, 1500, 400);
                let ef = sphere_integral(|wi| (full.eval(n, wo, wi).x * n.dot(wi).max(0.0)) as f64, 1500, 400);
                assert!(es > 0.0 && es <= 1.0, "r {r} θ {th}: specular albedo {es}");
                assert!(ef <= 1.0, "r {r} θ {th}: total albedo {ef}");
                // The diffuse part is the albedo times what the specular layer leaves, 1 − E.
                // (E from the half-vector quadrature, exact also for the sharp lobes this grid
                // about n resolves poorly.)
                let e =
                    crate::shade::brdf::directional_albedo_reference(th.to_radians().cos() as f64, r as f64, 0.04, 200);
                // The specular lobe is the inverse model's (the same masking term): its albedo
                // matches that quadrature where the sphere grid resolves the lobe (not r < 0.2,
                // not 85°).
                if r >= 0.2 && th <= 60.0 {
                    assert!((es - e).abs() < 0.03 * e + 1e-3, "r {r} θ {th}: specular albedo {es} vs model {e}");
                }
                assert!(
                    (ef - es - 0.8 * (1.0 - e)).abs() < 0.01,
                    "r {r} θ {th}: diffuse part {} vs {}",
                    ef - es,
                    0.8 * (1.0 - e)
                );
            }
        }
    }

    #[test]
    fn sampled_estimator_matches_quadrature() {
        // E[f cos / pdf] over the sampler equals ∫ f cos dω: pdf and sampler agree.
        let n = Vec3::Z;
        let mut rng = pixel_rng(3, 0, 0);
        for &r in &[0.15f32, 0.5, 0.9] {
            let b = Bsdf { albedo: Vec3::new(0.6, 0.3, 0.1), roughness: r, specular: 1.0 };
            let wo = dir(50.0);
            let quad = sphere_integral(|wi| (b.eval(n, wo, wi).y * n.dot(wi).max(0.0)) as f64, 1500, 400);
            let m = 200_000;
            let mut acc = 0.0f64;
            for _ in 0..m {
                let u = [uniform(&mut rng), uniform(&mut rng), uniform(&mut rng)];
                if let Some((wi, f, pdf)) = b.sample(n, wo, u) {
                    assert!((b.pdf(n, wo, wi) - pdf).abs() <= 1e-4 * pdf);
                    acc += (f.y * n.dot(wi) / pdf) as f64;
                }
            }
            let mc = acc / m as f64;
            assert!((mc - quad).abs() < 0.01 * quad.max(0.1), "r {r}: MC {mc} vs quadrature {quad}");
        }
    }
}
