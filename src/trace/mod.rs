//! The differentiable surfel ray tracer (issue 6): a BVH over the surfels' disks, k-nearest
//! gathering in exact per-ray depth order, and a backward pass that re-casts each ray.
//!
//! - [`bvh`]: bounds of each surfel's α ≥ 1/255 disk, binned-SAH build, refit, quality measure,
//!   and the node traversal (k-nearest gathering and a closest-hit traversal for the benchmark).
//! - [`forward`]: [`trace`] (per-ray radiance / features, transmittance, depth, normal) and
//!   [`render_camera_traced`].
//! - [`backward`]: [`trace_backward`], gradients to the surfels, features and rays.
//!
//! Hit (DESIGN §2): t = n·(μ − o)/(n·d), p = o + t d − μ, u = t_u·p/s_u, v = t_v·p/s_v,
//! G = exp(−(u² + v²)/2), α = min(0.99, o·G), hits with α < 1/255 are skipped. Valid hits have
//! t_min < t ≤ t_max. Hits are composited front to back in the order of (t, surfel index) — the
//! index breaks ties deterministically — and compositing stops right after the hit that brings
//! T below `min_transmittance` (that hit is included).

pub mod backward;
pub mod bvh;
pub mod forward;
#[cfg(test)]
mod reference;
#[cfg(test)]
mod tests;

pub use backward::{trace_backward, trace_backward_recorded};
pub use bvh::Tracer;
pub use forward::{HitRecord, render_camera_traced, trace, trace_recorded};

/// Smallest α composited (and the opacity below which a surfel has no bounds).
pub const ALPHA_MIN: f32 = 1.0 / 255.0;
/// Largest α of one hit (keeps 1 − α away from zero for the backward pass).
pub const ALPHA_MAX: f32 = 0.99;
/// Largest supported gathering chunk.
pub const MAX_CHUNK: usize = 64;

/// How rays are traced. `Default` gives the DESIGN values.
#[derive(Clone, Debug, PartialEq)]
pub struct TraceSettings {
    /// Hits gathered per traversal (k nearest beyond the last composited depth), 1..=64.
    /// Results do not depend on it (hits are composited in exact order either way); 32 rather
    /// than RadioGS's 16 because each further chunk re-traverses the tree from the root, and rays
    /// through trained scenes pass ~23 candidate hits (measured: forward 1.15–1.3× faster).
    pub chunk: usize,
    /// Stop after the transmittance drops below this (RadioGS: 0.03).
    pub min_transmittance: f32,
    /// Flip back faces instead of culling them (plain 2DGS); default culls (normals point out).
    pub two_sided: bool,
    /// With `two_sided`: back faces still occlude (α, depth, flipped normal) but carry no
    /// payload (zero radiance, zero features). Surfels no camera saw may face the wrong way:
    /// culled, they let light through; composited, their unobserved SH colours add light.
    pub dark_back_faces: bool,
    /// One-sided tracing (`two_sided` false): the surfels flagged here (indexed as the surfels,
    /// of their length) are also hit from behind, as dark occluders like `dark_back_faces`'.
    /// For surfels no camera saw, whose orientation is a guess: culled, a wrongly oriented one
    /// lets light through; these block it without adding unobserved colour.
    pub back_occluders: Option<std::sync::Arc<[bool]>>,
    /// Hits at t ≤ t_min are ignored: the self-intersection offset for rays leaving a surface.
    pub t_min: f32,
    /// Hits beyond t_max are ignored.
    pub t_max: f32,
    /// `Tracer::needs_rebuild` turns true once the refitted tree's SAH cost exceeds this
    /// multiple of its cost right after the build.
    pub rebuild_ratio: f32,
    /// Decode each hit's SH colour (sRGB) to linear radiance before compositing, so the
    /// payload is the light arriving along the ray (the PBR stages' indirect light), not an
    /// sRGB picture: decoding a composite instead darkens partial hits (the EOTF is convex).
    pub linear_radiance: bool,
    /// One-sided tracing: sin γ of a grazing tolerance γ. A face seen from behind at most γ
    /// past edge-on (0 < n·d̂ < sin γ) is still hit, composited like a two-sided back face
    /// (its colour, the normal flipped); back occluders stay dark. A fuzzy surfel shell seen
    /// nearly edge-on shows back faces among its tilted surfels, and culling them lets rays
    /// that graze an object leak through it. 0 = strict culling.
    pub grazing_sin: f32,
    /// Shading's visibility ramp t₀ ([`visibility_ramp`]): a ray whose final transmittance is
    /// below t₀ counts as fully blocked, its composited radiance scaled to the full coverage.
    /// 0 = off (the visibility is the transmittance).
    pub opaque_below: f32,
}

/// The visibility and indirect-light scale of a ray with final transmittance `t` under the ramp
/// t₀ = `t0`: V = clamp((T − t₀)/(1 − t₀), 0, 1) and g = (1 − V)/(1 − T) = 1/(1 − min(T, t₀)),
/// so V + g·(1 − T) = 1: the light a leak lets through is taken from the sky and given to the
/// surfels the ray hit. Returns (V, g, dV/dT, dg/dT).
///
/// Why: a trained surface is a few translucent layers, and a ray through an opaque wall keeps
/// the 3–4 % transmittance the traversal stops at (and more between surfels), so shadows see a
/// few per cent of the sky; in a deep shadow that is a large share of its light.
#[inline]
pub fn visibility_ramp(t: f32, t0: f32) -> (f32, f32, f32, f32) {
    if t0 <= 0.0 {
        return (t, 1.0, 1.0, 0.0);
    }
    let t = t.clamp(0.0, 1.0);
    if t < t0 {
        let g = 1.0 / (1.0 - t);
        (0.0, g, 0.0, g * g)
    } else {
        let g = 1.0 / (1.0 - t0);
        ((t - t0) * g, g, g, 0.0)
    }
}

impl Default for TraceSettings {
    fn default() -> Self {
        TraceSettings {
            chunk: 32,
            min_transmittance: 0.03,
            two_sided: false,
            dark_back_faces: false,
            back_occluders: None,
            t_min: 1e-4,
            t_max: f32::INFINITY,
            rebuild_ratio: 1.5,
            linear_radiance: false,
            grazing_sin: 0.0,
            opaque_below: 0.0,
        }
    }
}

/// A ray: origin and unit direction. (The geometry uses `dir` as given; SH colours use it
/// normalised.)
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Ray {
    pub origin: [f32; 3],
    pub dir: [f32; 3],
    /// A plane (n, c): hits on surfels whose centre μ has n·μ < c are ignored. Rays leaving a
    /// surfel pass the surfel's tangent plane raised by a margin, so they skip the surface
    /// they start from — its own translucent layers and the tilted surfels in them — while
    /// anything rising above the plane still occludes. A zero normal (the default) ignores
    /// nothing. See [`skip_plane_above`].
    pub skip_below: [f32; 4],
}

/// The [`Ray::skip_below`] plane of rays leaving `point` on a surface of unit `normal`: its
/// tangent plane raised by `margin`.
pub fn skip_plane_above(normal: [f32; 3], point: [f32; 3], margin: f32) -> [f32; 4] {
    let height = normal[0] * point[0] + normal[1] * point[1] + normal[2] * point[2];
    [normal[0], normal[1], normal[2], height + margin]
}

/// Per-surfel feature channels composited instead of SH radiance: `data` is N × `channels`.
#[derive(Clone, Copy, Debug)]
pub struct Features<'a> {
    pub data: &'a [f32],
    pub channels: usize,
}

/// What one ray returns.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayOutput {
    /// Σ T_j α_j c_j with c_j = max(SH_j(dir) + 0.5, 0) (0 for dark back faces); zero when
    /// features are traced instead.
    pub radiance: [f32; 3],
    /// Final transmittance Π (1 − α_j) (alpha = 1 − T).
    pub transmittance: f32,
    /// Σ T_j α_j t_j (divide by 1 − T for the expected depth of the hit surface).
    pub depth: f32,
    /// Σ T_j α_j n_j (n_j flipped towards the ray origin when two-sided).
    pub normal: [f32; 3],
}

/// ∂L/∂(each field of [`RayOutput`]) for one ray.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayGrad {
    pub v_radiance: [f32; 3],
    pub v_transmittance: f32,
    pub v_depth: f32,
    pub v_normal: [f32; 3],
}
