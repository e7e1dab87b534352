//! Incident-direction sampling about a normal n (directions point away from the surface).
//!
//! * [`fibonacci_hemisphere`]: RadioGS/IRGS's deterministic spiral, re-rotated about n by a
//!   random angle every call. Point i of S has cos-elevation z_i and azimuth
//!   φ_i = i·π(3 − √5) + rotation (golden angle). Two ways to honour the 10° elevation floor:
//!   - [`ElevationFloor::Spread`] (default): z_i = 1 − (1 − z_min)(i + ½)/S, i.e. the S points
//!     are equal-solid-angle cells of the spherical cap z ≥ z_min = sin 10°. The returned
//!     per-sample weight is the cell's solid angle 2π(1 − z_min)/S, so Σ_s w·g(ω_s) estimates
//!     ∫_{z ≥ z_min} g dω (the band below 10° is dropped: for a white Lambert surface under a
//!     constant sky the estimate is (1 − z_min²)·L = 0.970·L).
//!   - [`ElevationFloor::Clamp`] (what IRGS's `fibonacci_sphere_sampling` does):
//!     z_i = max(1 − 2i/(2S − 1), z_min), weight 2π/S: the spiral covers the whole hemisphere and
//!     the points below 10° are lifted onto the 10° ring; the estimator is DESIGN's (2π/S)·Σ.
//!     With z_i reaching only 1/(2S − 1) and the lifted cosines, the furnace estimate is ≈ 1.038·L
//!     for S = 64 (0.8 % from the spiral, 3 % from the lift).
//!
//!   Both weights are returned by the function, so the caller never hard-codes 2π/S.
//! * [`fibonacci_cap_jittered`]: the Spread spiral with each point jittered within its band,
//!   for estimators that mix it with other samples (relighting's map samples).
//! * [`uniform_hemisphere`] (pdf 1/2π), [`cosine_hemisphere`] (pdf cos/π).
//! * [`ggx_vndf_sample`] / [`ggx_vndf_pdf`]: Heitz 2018 visible-normal sampling of the GGX lobe
//!   (α = r², exact Smith G1 for the visible-normal density), reflected about the sampled
//!   micro-normal: pdf(ω_i) = G1(ω_o)·D(h) / (4·NoV). Directions can land below the horizon
//!   (the caller's max(0, n·ω) zeroes them); the pdf integrates to 1 over the sphere.
//! * [`mixture_sample`] / [`mixture_pdf`]: one-sample mixture p·GGX + (1 − p)·cosine.
//!
//! Scalar maths in f64, directions stored as f32.

use super::{V3, add, dot, frame, normalize, scale, to32, to64};
use rand::RngExt;
use std::f64::consts::PI;

/// The elevation floor of the Fibonacci directions, in degrees above the tangent plane.
pub const MIN_ELEVATION_DEG: f64 = 10.0;

/// How the Fibonacci spiral honours the elevation floor (see the module note).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum ElevationFloor {
    #[default]
    Spread,
    Clamp,
}

#[inline]
fn to_world(n: [f32; 3], l: V3) -> [f32; 3] {
    let (t, b) = frame(n);
    to32(add(add(scale(to64(t), l[0]), scale(to64(b), l[1])), scale(to64(n), l[2])))
}

/// Writes `out.len()` Fibonacci directions about the unit normal `n`, rotated by `rotation`
/// radians about n, with the elevation floor `min_elevation_deg`. Returns the solid angle each
/// direction stands for (the estimator weight).
pub fn fibonacci_hemisphere(
    n: [f32; 3],
    rotation: f64,
    min_elevation_deg: f64,
    floor: ElevationFloor,
    out: &mut [[f32; 3]],
) -> f64 {
    match floor {
        ElevationFloor::Spread => fibonacci_cap_jittered(n, rotation, min_elevation_deg, || 0.5, out),
        ElevationFloor::Clamp => {
            let s = out.len();
            let z_min = cap_z_min(min_elevation_deg);
            spiral(n, rotation, out, |fi| (1.0 - 2.0 * fi / (2.0 * s as f64 - 1.0)).max(z_min));
            if s == 0 { 0.0 } else { 2.0 * PI / s as f64 }
        }
    }
}

/// The [`ElevationFloor::Spread`] spiral with each point's cos-elevation placed by `jitter` within
/// its band of equal solid angle: z_i = 1 − (1 − z_min)(i + ξ_i)/S (ξ_i = 0.5: the plain spiral).
/// With ξ_i uniform in [0, 1) the points together have density S/Ω_cap everywhere on the cap,
/// which an estimator mixing them with other samples needs (`env_sampling`).
pub fn fibonacci_cap_jittered(
    n: [f32; 3],
    rotation: f64,
    min_elevation_deg: f64,
    mut jitter: impl FnMut() -> f64,
    out: &mut [[f32; 3]],
) -> f64 {
    let s = out.len();
    if s == 0 {
        return 0.0;
    }
    let z_min = cap_z_min(min_elevation_deg);
    spiral(n, rotation, out, |fi| 1.0 - (1.0 - z_min) * (fi + jitter()) / s as f64);
    cap_solid_angle(min_elevation_deg) / s as f64
}

/// cos of the angle from the normal at the elevation floor.
fn cap_z_min(min_elevation_deg: f64) -> f64 {
    (min_elevation_deg.clamp(0.0, 89.0)).to_radians().sin()
}

/// Solid angle of the cap above the elevation floor, 2π(1 − sin floor).
pub fn cap_solid_angle(min_elevation_deg: f64) -> f64 {
    2.0 * PI * (1.0 - cap_z_min(min_elevation_deg))
}

/// The golden-angle spiral about n: point i at cos-elevation `z_of(i)`, azimuth
/// i·π(3 − √5) + rotation.
fn spiral(n: [f32; 3], rotation: f64, out: &mut [[f32; 3]], mut z_of: impl FnMut(f64) -> f64) {
    let golden = PI * (3.0 - 5f64.sqrt());
    let (t, b) = frame(n);
    let (t, b, nn) = (to64(t), to64(b), to64(n));
    for (i, o) in out.iter_mut().enumerate() {
        let fi = i as f64;
        let z = z_of(fi);
        let rad = (1.0 - z * z).max(0.0).sqrt();
        let phi = golden * fi + rotation;
        let l = [rad * phi.cos(), rad * phi.sin(), z];
        *o = to32(add(add(scale(t, l[0]), scale(b, l[1])), scale(nn, l[2])));
    }
}

/// [`fibonacci_hemisphere`] with a uniformly random rotation drawn from `rng`, the 10° floor
/// and the default (Spread) placement.
pub fn fibonacci_hemisphere_random<R: rand::Rng + ?Sized>(n: [f32; 3], rng: &mut R, out: &mut [[f32; 3]]) -> f64 {
    let rot = rng.random::<f64>() * 2.0 * PI;
    fibonacci_hemisphere(n, rot, MIN_ELEVATION_DEG, ElevationFloor::Spread, out)
}

/// Density of [`uniform_hemisphere`] per steradian.
pub const UNIFORM_HEMISPHERE_PDF: f64 = 1.0 / (2.0 * PI);

/// A uniform direction on n's hemisphere from two uniforms in [0, 1).
pub fn uniform_hemisphere(n: [f32; 3], u1: f64, u2: f64) -> [f32; 3] {
    let z = 1.0 - u1;
    let rad = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * u2;
    to_world(n, [rad * phi.cos(), rad * phi.sin(), z])
}

/// A cosine-distributed direction on n's hemisphere; pdf = max(0, n·ω)/π.
pub fn cosine_hemisphere(n: [f32; 3], u1: f64, u2: f64) -> [f32; 3] {
    let rad = u1.sqrt();
    let phi = 2.0 * PI * u2;
    to_world(n, [rad * phi.cos(), rad * phi.sin(), (1.0 - u1).max(0.0).sqrt()])
}

/// Density of [`cosine_hemisphere`].
pub fn cosine_pdf(n: [f32; 3], wi: [f32; 3]) -> f64 {
    dot(to64(n), to64(wi)).max(0.0) / PI
}

#[inline]
fn smith_g1_ggx(nov: f64, a2: f64) -> f64 {
    2.0 * nov / (nov + (a2 + (1.0 - a2) * nov * nov).sqrt())
}

/// GGX visible-normal sample (Heitz 2018) reflected into an incident direction, for the view
/// direction `wo` (towards the camera) and roughness `r` (α = r²).
pub fn ggx_vndf_sample(n: [f32; 3], wo: [f32; 3], r: f64, u1: f64, u2: f64) -> [f32; 3] {
    let (t, b) = frame(n);
    let (t, b, nn, wo) = (to64(t), to64(b), to64(n), to64(wo));
    let alpha = super::brdf::alpha2(r).sqrt();
    let v = [dot(wo, t), dot(wo, b), dot(wo, nn).max(1e-6)];
    let vh = normalize([alpha * v[0], alpha * v[1], v[2]]);
    let lensq = vh[0] * vh[0] + vh[1] * vh[1];
    let t1 = if lensq > 0.0 { scale([-vh[1], vh[0], 0.0], 1.0 / lensq.sqrt()) } else { [1.0, 0.0, 0.0] };
    let t2 = [vh[1] * t1[2] - vh[2] * t1[1], vh[2] * t1[0] - vh[0] * t1[2], vh[0] * t1[1] - vh[1] * t1[0]];
    let rr = u1.sqrt();
    let phi = 2.0 * PI * u2;
    let p1 = rr * phi.cos();
    let mut p2 = rr * phi.sin();
    let s = 0.5 * (1.0 + vh[2]);
    p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * p2;
    let nh = add(add(scale(t1, p1), scale(t2, p2)), scale(vh, (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt()));
    let ne = normalize([alpha * nh[0], alpha * nh[1], nh[2].max(1e-9)]);
    let h = add(add(scale(t, ne[0]), scale(b, ne[1])), scale(nn, ne[2]));
    let wi = add(scale(h, 2.0 * dot(wo, h)), scale(wo, -1.0));
    to32(normalize(wi))
}

/// Density (per steradian of ω_i) of [`ggx_vndf_sample`].
pub fn ggx_vndf_pdf(n: [f32; 3], wo: [f32; 3], wi: [f32; 3], r: f64) -> f64 {
    let (n, wo, wi) = (to64(n), to64(wo), to64(wi));
    let s = add(wo, wi);
    let l = dot(s, s).sqrt();
    if l < 1e-12 {
        return 0.0;
    }
    let h = scale(s, 1.0 / l);
    let noh = dot(n, h);
    let voh = dot(wo, h);
    let nov = dot(n, wo).max(1e-6);
    if noh <= 0.0 || voh <= 0.0 {
        return 0.0;
    }
    let a2 = super::brdf::alpha2(r);
    smith_g1_ggx(nov, a2) * super::brdf::ggx_d(noh, a2) / (4.0 * nov)
}

/// One-sample mixture: with probability `p_spec` a GGX VNDF sample, otherwise cosine. `u0`
/// picks the component. Returns the direction and the mixture pdf.
pub fn mixture_sample(n: [f32; 3], wo: [f32; 3], r: f64, p_spec: f64, u0: f64, u1: f64, u2: f64) -> ([f32; 3], f64) {
    let wi = if u0 < p_spec { ggx_vndf_sample(n, wo, r, u1, u2) } else { cosine_hemisphere(n, u1, u2) };
    (wi, mixture_pdf(n, wo, wi, r, p_spec))
}

/// Density of [`mixture_sample`].
pub fn mixture_pdf(n: [f32; 3], wo: [f32; 3], wi: [f32; 3], r: f64, p_spec: f64) -> f64 {
    p_spec * ggx_vndf_pdf(n, wo, wi, r) + (1.0 - p_spec) * cosine_pdf(n, wi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shade::testutil::rng;
    use rand::RngExt;

    /// ∫ over the sphere of a density, (cos θ, φ) midpoint grid about z.
    fn integrate_sphere(nz: usize, f: impl Fn([f32; 3]) -> f64) -> f64 {
        let mut acc = 0.0;
        let nphi = 2 * nz;
        for iz in 0..nz {
            let z = -1.0 + 2.0 * (iz as f64 + 0.5) / nz as f64;
            let rad = (1.0 - z * z).sqrt();
            for ip in 0..nphi {
                let phi = 2.0 * PI * (ip as f64 + 0.5) / nphi as f64;
                acc += f([(rad * phi.cos()) as f32, (rad * phi.sin()) as f32, z as f32]);
            }
        }
        acc * 4.0 * PI / (nz * nphi) as f64
    }

    #[test]
    fn pdfs_integrate_to_one() {
        let n = [0.0f32, 0.0, 1.0];
        let u = integrate_sphere(400, |w| if w[2] > 0.0 { UNIFORM_HEMISPHERE_PDF } else { 0.0 });
        assert!((u - 1.0).abs() < 1e-3, "uniform {u}");
        let c = integrate_sphere(400, |w| cosine_pdf(n, w));
        assert!((c - 1.0).abs() < 1e-3, "cosine {c}");
        for &(r, nov) in &[(0.4, 0.8), (0.6, 0.3), (1.0, 0.05), (0.8, 1.0)] {
            let wo = [(1.0f64 - nov * nov).sqrt() as f32, 0.0, nov as f32];
            let g = integrate_sphere(1000, |w| ggx_vndf_pdf(n, wo, w, r));
            assert!((g - 1.0).abs() < 5e-3, "ggx r={r} NoV={nov}: {g}");
            let m = integrate_sphere(600, |w| mixture_pdf(n, wo, w, r, 0.5));
            assert!((m - 1.0).abs() < 5e-3, "mixture r={r}: {m}");
        }
    }

    /// χ² test of a sampler against its pdf on a (z, φ) grid over the sphere, bins with expected
    /// count < 5 pooled; expected counts by sub-cell quadrature of the pdf.
    fn chi2(sample: impl Fn(f64, f64, f64) -> [f32; 3], pdf: impl Fn([f32; 3]) -> f64, seed: u64) -> (f64, usize) {
        let (nz, nphi, count, sub) = (16usize, 32usize, 200_000usize, 12usize);
        let mut hist = vec![0usize; nz * nphi];
        let mut rg = rng(seed);
        for _ in 0..count {
            let w = sample(rg.random(), rg.random(), rg.random());
            let z = (w[2] as f64).clamp(-1.0, 1.0 - 1e-12);
            let phi = (w[1] as f64).atan2(w[0] as f64).rem_euclid(2.0 * PI);
            let iz = (((z + 1.0) / 2.0 * nz as f64) as usize).min(nz - 1);
            let ip = ((phi / (2.0 * PI) * nphi as f64) as usize).min(nphi - 1);
            hist[iz * nphi + ip] += 1;
        }
        let cell = 4.0 * PI / (nz * nphi) as f64;
        let (mut stat, mut dof, mut pooled_o, mut pooled_e) = (0.0, 0usize, 0.0, 0.0);
        for iz in 0..nz {
            for ip in 0..nphi {
                let mut e = 0.0;
                for a in 0..sub {
                    for b in 0..sub {
                        let z = -1.0 + 2.0 * (iz as f64 + (a as f64 + 0.5) / sub as f64) / nz as f64;
                        let phi = 2.0 * PI * (ip as f64 + (b as f64 + 0.5) / sub as f64) / nphi as f64;
                        let rad = (1.0 - z * z).sqrt();
                        e += pdf([(rad * phi.cos()) as f32, (rad * phi.sin()) as f32, z as f32]);
                    }
                }
                let e = e * cell / (sub * sub) as f64 * count as f64;
                let o = hist[iz * nphi + ip] as f64;
                if e < 5.0 {
                    pooled_o += o;
                    pooled_e += e;
                } else {
                    stat += (o - e) * (o - e) / e;
                    dof += 1;
                }
            }
        }
        if pooled_e > 5.0 {
            stat += (pooled_o - pooled_e) * (pooled_o - pooled_e) / pooled_e;
            dof += 1;
        }
        (stat, dof - 1)
    }

    #[test]
    fn ggx_sampler_chi2() {
        let n = [0.0f32, 0.0, 1.0];
        for (k, &(r, nov)) in [(0.5, 0.6), (0.8, 0.25), (0.35, 0.9)].iter().enumerate() {
            let wo = [((1.0f64 - nov * nov).sqrt()) as f32, 0.0, nov as f32];
            let (stat, dof) =
                chi2(|_, a, b| ggx_vndf_sample(n, wo, r, a, b), |w| ggx_vndf_pdf(n, wo, w, r), 10 + k as u64);
            let limit = dof as f64 + 5.0 * (2.0 * dof as f64).sqrt();
            assert!(stat < limit, "GGX r={r} NoV={nov}: χ² {stat:.1} over {dof} dof");
            let (stat, dof) = chi2(
                |u0, a, b| mixture_sample(n, wo, r, 0.3, u0, a, b).0,
                |w| mixture_pdf(n, wo, w, r, 0.3),
                20 + k as u64,
            );
            assert!(stat < dof as f64 + 5.0 * (2.0 * dof as f64).sqrt(), "mixture χ² {stat:.1} over {dof}");
        }
        // The test has teeth: the GGX samples judged against the cosine pdf must fail.
        let wo = [0.8f32, 0.0, 0.6];
        let (stat, dof) = chi2(|_, a, b| ggx_vndf_sample(n, wo, 0.3, a, b), |w| cosine_pdf(n, w), 3);
        assert!(stat > 10.0 * dof as f64);
        let (stat, dof) =
            chi2(|_, a, b| uniform_hemisphere(n, a, b), |w| if w[2] > 0.0 { UNIFORM_HEMISPHERE_PDF } else { 0.0 }, 4);
        assert!(stat < dof as f64 + 5.0 * (2.0 * dof as f64).sqrt(), "uniform χ² {stat}");
    }

    #[test]
    fn fibonacci_floor_and_coverage() {
        let mut rg = rng(5);
        let z_min = MIN_ELEVATION_DEG.to_radians().sin();
        for trial in 0..50 {
            let n = crate::shade::to32(crate::shade::testutil::unit(&mut rg));
            let mut dirs = vec![[0.0f32; 3]; 64];
            let w = fibonacci_hemisphere_random(n, &mut rg, &mut dirs);
            assert!((w - 2.0 * PI * (1.0 - z_min) / 64.0).abs() < 1e-12);
            let (t, b) = frame(n);
            // Equal-solid-angle cells of the cap: 4 z-bands × 4 azimuth sectors, 4 points each ideally.
            let mut cells = [0usize; 16];
            let mut mean = [0.0f64; 3];
            for d in &dirs {
                let d64 = to64(*d);
                assert!((dot(d64, d64) - 1.0).abs() < 1e-5);
                let z = dot(d64, to64(n));
                assert!(z >= z_min - 1e-5, "trial {trial}: elevation below the floor: {z}");
                let phi = dot(d64, to64(b)).atan2(dot(d64, to64(t))).rem_euclid(2.0 * PI);
                let band = (((1.0 - z) / (1.0 - z_min) * 4.0) as usize).min(3);
                let sector = ((phi / (2.0 * PI) * 4.0) as usize).min(3);
                cells[band * 4 + sector] += 1;
                mean = add(mean, scale(d64, 1.0 / 64.0));
            }
            assert!(cells.iter().all(|&c| (2..=6).contains(&c)), "uneven cover {cells:?}");
            // Uniform on the cap: E[n·ω] = (1 + z_min)/2, no tangential bias.
            assert!((dot(mean, to64(n)) - (1.0 + z_min) / 2.0).abs() < 2e-3);
            assert!(dot(mean, to64(t)).abs() < 0.03 && dot(mean, to64(b)).abs() < 0.03);
        }
        // The rotation really rotates; Clamp covers down to the 10° ring with weight 2π/S.
        let n = [0.0f32, 0.0, 1.0];
        let (mut a, mut c) = (vec![[0.0f32; 3]; 16], vec![[0.0f32; 3]; 16]);
        fibonacci_hemisphere(n, 0.0, 10.0, ElevationFloor::Spread, &mut a);
        fibonacci_hemisphere(n, 1.0, 10.0, ElevationFloor::Spread, &mut c);
        assert!((a[3][0] - c[3][0]).abs() > 1e-3);
        let w = fibonacci_hemisphere(n, 0.3, 10.0, ElevationFloor::Clamp, &mut c);
        assert!((w - 2.0 * PI / 16.0).abs() < 1e-12);
        assert!(c.iter().all(|d| d[2] as f64 >= z_min - 1e-6));
        assert!(c.iter().filter(|d| (d[2] as f64 - z_min).abs() < 1e-6).count() >= 2);
    }
}
