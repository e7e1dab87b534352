//! Shading: the BRDF, hemisphere sampling, the split-sum approximation and the per-surfel
//! rendering equation (DESIGN §1), each with its backward pass beside the forward.
//!
//! Conventions shared by the files here: every direction points *away* from the surface
//! (ω_o towards the camera, ω_i / ω_s towards the light); vectors are used as given (no
//! renormalisation inside), so gradients are with respect to the vectors as passed in and the
//! caller chains any normalisation. The scalar maths runs in f64 (it costs the same as f32
//! for scalar code and lets the gradient checks run tight); storage stays f32. SIMD lanes are
//! f64 too, but for the inverse iteration's linearised PBR shading, whose f32 lanes
//! (`float_lanes.rs`) take 40–45 % less time and are bounded against the f64 ones by a test.

pub mod brdf;
pub mod brdf_lanes;
pub mod env_sampling;
pub mod float_lanes;
pub mod incident;
pub mod pbr;
pub mod sampling;
pub mod splitsum;
pub mod traced_specular;

pub(crate) type V3 = [f64; 3];

#[inline]
pub(crate) fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
#[inline]
pub(crate) fn add(a: V3, b: V3) -> V3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
#[inline]
pub(crate) fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
#[inline]
pub(crate) fn scale(a: V3, s: f64) -> V3 {
    [a[0] * s, a[1] * s, a[2] * s]
}
#[inline]
pub(crate) fn to64(a: [f32; 3]) -> V3 {
    [a[0] as f64, a[1] as f64, a[2] as f64]
}
#[inline]
pub(crate) fn to32(a: V3) -> [f32; 3] {
    [a[0] as f32, a[1] as f32, a[2] as f32]
}
#[inline]
pub(crate) fn normalize(a: V3) -> V3 {
    let l = dot(a, a).sqrt();
    if l > 0.0 { scale(a, 1.0 / l) } else { [0.0, 0.0, 1.0] }
}

/// An orthonormal frame [t, b, n] about a unit normal (Duff et al. 2017, branchless).
#[inline]
pub fn frame(n: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let s = if n[2] >= 0.0 { 1.0f32 } else { -1.0 };
    let a = -1.0 / (s + n[2]);
    let b = n[0] * n[1] * a;
    ([1.0 + s * n[0] * n[0] * a, s * b, -s * n[0]], [b, s + n[1] * n[1] * a, -n[1]])
}

#[cfg(test)]
pub(crate) mod testutil {
    use rand::{RngExt, SeedableRng};
    pub fn rng(seed: u64) -> rand_pcg::Pcg64 {
        rand_pcg::Pcg64::seed_from_u64(seed)
    }
    /// A random unit vector.
    pub fn unit(rng: &mut rand_pcg::Pcg64) -> [f64; 3] {
        loop {
            let v: [f64; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f64));
            let l = super::dot(v, v).sqrt();
            if l > 0.1 && l < 1.0 {
                return super::scale(v, 1.0 / l);
            }
        }
    }
    /// A random unit vector in the hemisphere of `n` with n·v ≥ min_cos.
    pub fn unit_in(rng: &mut rand_pcg::Pcg64, n: [f64; 3], min_cos: f64) -> [f64; 3] {
        loop {
            let v = unit(rng);
            if super::dot(v, n) >= min_cos {
                return v;
            }
        }
    }
    /// Relative-or-absolute closeness for gradient checks.
    pub fn close(a: f64, b: f64, rel: f64, abs: f64) -> bool {
        (a - b).abs() <= abs + rel * a.abs().max(b.abs())
    }
}
