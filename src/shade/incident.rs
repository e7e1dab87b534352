//! The per-surfel incident-light cache of DESIGN §1: for every surfel, S directions on its
//! normal's hemisphere (Fibonacci, a per-surfel random rotation, the 10° floor), the traced
//! visibility V_s (the ray's final transmittance) and indirect radiance L_ind,s (the ray's
//! composited SH radiance). It is refreshed by tracing without gradients; the consistency
//! step overwrites the rows it traces with gradients.
//!
//! Colour space: SH radiance is trained on sRGB images (2DGS), so a traced ray's composited
//! SH colour is sRGB-encoded; the cache stores it decoded to linear, as the rendering
//! equation needs. (Decoding after compositing, not per hit: the difference is second order
//! where a ray's hits differ in colour, and it keeps the tracer's payload unchanged.)
//!
//! Rays leave from μ + offset·n: 2D surfels of a flat patch are nearly coplanar, and rays
//! from the exact centre at the 10° floor would hit the neighbours' disks at tiny t. They
//! also skip surfels whose centre lies less than a margin above the tangent plane at μ: a
//! trained surface is several translucent, tilted layers deep, and rays leaving it hit its
//! own layers (a sphere's top saw ~3 % of its hemisphere blocked by itself, a flat floor ~8 %),
//! which showed up as false indirect light and shadow.

use super::env_sampling::{EnvSampler, mixture_directions};
use super::pbr::{CachedFootprints, PbrInputs};
use super::sampling::{ElevationFloor, MIN_ELEVATION_DEG, fibonacci_hemisphere};
use crate::envmap::{EnvMap, PackedFootprint};
use crate::surfels::Surfels;
use crate::trace::{Features, HitRecord, Ray, RayOutput, Tracer, trace, trace_recorded, visibility_ramp};
use rand::RngExt;
use rayon::prelude::*;

/// Cached incident light: N surfels × S samples, surfel-major.
#[derive(Clone, Debug, Default)]
pub struct IncidentCache {
    pub samples: usize,
    /// Solid angle per sample (the Fibonacci estimator weight).
    pub weight: f32,
    /// Per-sample estimator weights (N·S) when [`importance`](Self::importance) drew part of
    /// the directions from a map; empty when every sample weighs `weight`.
    pub sample_weights: Vec<f32>,
    /// Draw this many of each surfel's S directions from a known map's light (relighting), the
    /// rest Fibonacci, mixed by the balance heuristic (`env_sampling`); `None` in training.
    pub importance: Option<EnvImportance>,
    pub dirs: Vec<[f32; 3]>,
    pub visibility: Vec<f32>,
    /// Linear radiance.
    pub indirect: Vec<[f32; 3]>,
    /// Env footprints of `dirs` for maps of `footprint_size` (width, height), made by
    /// [`prepare_footprints`](Self::prepare_footprints); empty until then and after a refresh.
    pub footprints: Vec<PackedFootprint>,
    pub footprint_size: (usize, usize),
}

/// Which map the cache importance-samples, and how many of each surfel's directions.
#[derive(Clone, Debug)]
pub struct EnvImportance {
    pub sampler: EnvSampler,
    pub samples: usize,
}

impl EnvImportance {
    /// Draw the share `share` of `samples` directions from `env`'s peaks; `None` when that is
    /// no direction or the map has no peaks (then every direction is Fibonacci).
    pub fn of_map(env: &EnvMap, samples: usize, share: f32) -> Option<EnvImportance> {
        let n_env = (share.clamp(0.0, 1.0) * samples as f32).round() as usize;
        if n_env == 0 {
            return None;
        }
        EnvSampler::new(env).map(|sampler| EnvImportance { sampler, samples: n_env })
    }
}

/// A texel-less map of `size` (width, height): footprints only need the size.
fn footprint_grid(size: (usize, usize)) -> EnvMap {
    EnvMap { width: size.0, height: size.1, texels: Vec::new() }
}

/// sRGB-encoded → linear for a traced colour (no clamp above 1: SH colours may exceed it).
#[inline]
pub fn decode(c: f32) -> f32 {
    crate::io::image::srgb_to_linear(c.max(0.0))
}

/// d decode / dc.
#[inline]
pub fn decode_derivative(c: f32) -> f32 {
    decode_with_derivative(c).1
}

/// (decode(c), d decode / dc) with one power: above the linear segment
/// d/dc t^2.4 = 2.4/1.055 · t^2.4 / t for t = (c + 0.055)/1.055.
#[inline]
pub fn decode_with_derivative(c: f32) -> (f32, f32) {
    let c = c.max(0.0);
    if c <= 0.040_45 {
        (c / 12.92, 1.0 / 12.92)
    } else {
        let t = (c + 0.055) / 1.055;
        let v = crate::io::image::pow_2_4(t);
        (v, 2.4 / 1.055 * v / t)
    }
}

/// A deterministic rotation angle in [0, 2π) for surfel `i` at refresh `seed`.
pub fn rotation_for(seed: u64, i: usize) -> f64 {
    let mut x = seed ^ (i as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    x ^= x >> 33;
    x = x.wrapping_mul(0xff51_afd7_ed55_8ccd);
    x ^= x >> 33;
    x = x.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
    x ^= x >> 33;
    (x >> 11) as f64 / (1u64 << 53) as f64 * std::f64::consts::TAU
}

/// Where a surfel's incident rays start and which hits they skip (scene units): origin
/// μ + offset·n; with `skip_margin` m, hits on surfels whose centre lies less than m above the
/// tangent plane at μ are ignored ([`Ray::skip_below`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct RayStart {
    pub offset: f32,
    pub skip_margin: Option<f32>,
}

impl RayStart {
    /// An origin offset and no skipping.
    pub fn offset_only(offset: f32) -> RayStart {
        RayStart { offset, skip_margin: None }
    }
}

/// Writes the S rays of surfel `i` (origin μ + offset·n, Fibonacci directions rotated by
/// `rotation`, the skip plane of `start`) and returns the per-sample solid angle.
pub fn surfel_rays(
    surfels: &Surfels,
    i: usize,
    start: RayStart,
    rotation: f64,
    dirs: &mut [[f32; 3]],
    rays: &mut [Ray],
) -> f32 {
    let n = surfels.normal(i);
    let w = fibonacci_hemisphere(n, rotation, MIN_ELEVATION_DEG, ElevationFloor::Spread, dirs);
    ray_fan(surfels, i, start, dirs, rays);
    w as f32
}

/// Surfel `i`'s rays along `dirs` (origin μ + offset·n, the skip plane of `start`).
fn ray_fan(surfels: &Surfels, i: usize, start: RayStart, dirs: &[[f32; 3]], rays: &mut [Ray]) {
    let n = surfels.normal(i);
    let m = surfels.means[i];
    let offset = start.offset;
    let origin = [m[0] + offset * n[0], m[1] + offset * n[1], m[2] + offset * n[2]];
    let skip_below = match start.skip_margin {
        Some(margin) => crate::trace::skip_plane_above(n, m, margin),
        None => [0.0; 4],
    };
    for (r, d) in rays.iter_mut().zip(dirs.iter()) {
        *r = Ray { origin, dir: *d, skip_below };
    }
}

/// Which surfels each cached ray composited and with what weight (T·α), so that the indirect
/// light can be composited again from new per-surfel radiance without tracing the rays again
/// (multi-bounce relighting). Ray k of the cache owns `surfel[start[k]..start[k + 1]]`.
#[derive(Clone, Debug, Default)]
pub struct CachedHits {
    pub start: Vec<usize>,
    pub surfel: Vec<u32>,
    pub weight: Vec<f32>,
}

/// Surfels traced per batch by [`IncidentCache::refresh_recorded`]: bounds the full hit
/// records (32 bytes a hit) kept before they are compacted to 8 bytes a hit.
const RECORD_BATCH_SURFELS: usize = 2048;

impl CachedHits {
    /// Composite per-surfel `radiance` (N × 3, linear) along every ray into `out` (one per ray).
    pub fn composite(&self, radiance: &[f32], out: &mut [[f32; 3]]) {
        debug_assert_eq!(out.len() + 1, self.start.len());
        out.par_iter_mut().enumerate().with_min_len(1024).for_each(|(k, o)| {
            let (a, b) = (self.start[k], self.start[k + 1]);
            let mut c = [0.0f32; 3];
            for (&i, &w) in self.surfel[a..b].iter().zip(&self.weight[a..b]) {
                let r = &radiance[3 * i as usize..][..3];
                c[0] += w * r[0];
                c[1] += w * r[1];
                c[2] += w * r[2];
            }
            *o = c;
        });
    }
}

/// Writes the S rays and directions of each surfel in `rows` (S = `dirs.len() / rows.len()`,
/// rotations of refresh `seed`); returns the per-sample solid angle of the Fibonacci
/// directions. With `importance`, part of each surfel's directions come from the map and
/// `sample_weights` (same length as `dirs`) gets every sample's estimator weight.
#[allow(clippy::too_many_arguments)]
fn rows_rays(
    surfels: &Surfels,
    rows: &[u32],
    start: RayStart,
    seed: u64,
    importance: Option<&EnvImportance>,
    dirs: &mut [[f32; 3]],
    sample_weights: &mut [f32],
    rays: &mut [Ray],
) -> f32 {
    let s = dirs.len() / rows.len().max(1);
    let Some(imp) = importance else {
        let weights: Vec<f32> = dirs
            .par_chunks_mut(s)
            .zip(rays.par_chunks_mut(s))
            .zip(rows.par_iter())
            .map(|((d, r), &i)| surfel_rays(surfels, i as usize, start, rotation_for(seed, i as usize), d, r))
            .collect();
        return weights.first().copied().unwrap_or(0.0);
    };
    dirs.par_chunks_mut(s)
        .zip(sample_weights.par_chunks_mut(s))
        .zip(rays.par_chunks_mut(s))
        .zip(rows.par_iter())
        .for_each(|(((d, w), r), &i)| surfel_rays_importance(surfels, i as usize, start, seed, imp, d, w, r));
    fibonacci_weight(s)
}

/// As [`surfel_rays`], with `importance.samples` of the directions drawn from its map
/// (`env_sampling::mixture_directions`) and each sample's estimator weight in `weights`. The
/// Fibonacci rotation and the uniform numbers come from (`seed`, `i`): the same for any order
/// of calls.
#[allow(clippy::too_many_arguments)]
fn surfel_rays_importance(
    surfels: &Surfels,
    i: usize,
    start: RayStart,
    seed: u64,
    importance: &EnvImportance,
    dirs: &mut [[f32; 3]],
    weights: &mut [f32],
    rays: &mut [Ray],
) {
    let stream = rotation_for(seed ^ 0x5bd1_e995, i).to_bits() as u128;
    let mut rng = rand_pcg::Pcg64Mcg::new(((seed as u128) << 64) | stream);
    let n = surfels.normal(i);
    let rotation = rotation_for(seed, i);
    mixture_directions(
        n,
        rotation,
        Some(&importance.sampler),
        importance.samples,
        || rng.random::<f64>(),
        dirs,
        weights,
    );
    ray_fan(surfels, i, start, dirs, rays);
}

/// The Fibonacci estimator weight of S directions (the cap's solid angle / S).
fn fibonacci_weight(s: usize) -> f32 {
    (super::sampling::cap_solid_angle(MIN_ELEVATION_DEG) / s.max(1) as f64) as f32
}

impl IncidentCache {
    /// Size the cache for `n` surfels × `samples` and drop the footprints (a refresh follows).
    fn resize(&mut self, n: usize, samples: usize) {
        self.samples = samples;
        self.footprints.clear();
        if self.importance.is_some() {
            self.sample_weights.resize(n * samples, 0.0);
        } else {
            self.sample_weights.clear();
        }
        self.dirs.resize(n * samples, [0.0; 3]);
        self.visibility.resize(n * samples, 0.0);
        self.indirect.resize(n * samples, [0.0; 3]);
    }

    /// Draw later rows' directions with `importance` (the rows traced so far keep theirs and
    /// their weights), e.g. from a light that is being learned and grows peaks.
    pub fn set_importance(&mut self, importance: Option<EnvImportance>) {
        if importance.is_some() && self.sample_weights.len() != self.dirs.len() {
            // Every row so far is Fibonacci.
            self.sample_weights.clear();
            self.sample_weights.resize(self.dirs.len(), self.weight);
        }
        self.importance = importance;
    }

    pub fn len(&self) -> usize {
        self.visibility.len().checked_div(self.samples).unwrap_or(0)
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Trace every surfel's S rays (no gradients) and replace the whole cache; indirect light
    /// is the hit surfels' SH radiance (decoded to linear).
    pub fn refresh(&mut self, tracer: &Tracer, surfels: &Surfels, samples: usize, start: RayStart, seed: u64) {
        self.refresh_with(tracer, surfels, samples, start, seed, None);
    }

    /// As [`refresh`](Self::refresh); with `radiance` (N × 3, linear), the indirect light is
    /// that per-surfel radiance composited along each ray instead of the SH colour.
    pub fn refresh_with(
        &mut self,
        tracer: &Tracer,
        surfels: &Surfels,
        samples: usize,
        start: RayStart,
        seed: u64,
        radiance: Option<&[f32]>,
    ) {
        let n = surfels.len();
        self.resize(n, samples);
        if n == 0 || samples == 0 {
            return;
        }
        let all: Vec<u32> = (0..n as u32).collect();
        self.trace_rows(tracer, surfels, &all, start, seed, radiance);
    }

    /// As [`refresh_with`](Self::refresh_with), keeping every ray's hits: the indirect light
    /// is `radiance` composited along the rays, and the returned hits composite any other
    /// per-surfel radiance the same way ([`CachedHits::composite`]).
    pub fn refresh_recorded(
        &mut self,
        tracer: &Tracer,
        surfels: &Surfels,
        samples: usize,
        start: RayStart,
        seed: u64,
        radiance: &[f32],
    ) -> CachedHits {
        let n = surfels.len();
        let s = samples;
        self.resize(n, s);
        let mut hits = CachedHits { start: Vec::with_capacity(n * s + 1), ..Default::default() };
        hits.start.push(0);
        if n == 0 || s == 0 {
            return hits;
        }
        let mut record = HitRecord::default();
        let mut rays = Vec::new();
        let mut out = Vec::new();
        for first in (0..n).step_by(RECORD_BATCH_SURFELS) {
            let rows: Vec<u32> = (first as u32..n.min(first + RECORD_BATCH_SURFELS) as u32).collect();
            let m = rows.len();
            rays.clear();
            rays.resize(m * s, Ray::default());
            out.clear();
            out.resize(m * s, RayOutput::default());
            let span = first * s..(first + m) * s;
            let weights =
                if self.sample_weights.is_empty() { &mut [][..] } else { &mut self.sample_weights[span.clone()] };
            self.weight = rows_rays(
                surfels,
                &rows,
                start,
                seed,
                self.importance.as_ref(),
                &mut self.dirs[span],
                weights,
                &mut rays,
            );
            trace_recorded(tracer, surfels, &rays, &mut out, &mut record);
            for (q, o) in out.iter().enumerate() {
                let (v, g, _, _) = visibility_ramp(o.transmittance, tracer.settings.opaque_below);
                self.visibility[first * s + q] = v;
                let (a, b) = record.spans[q];
                for h in &record.hits[a as usize..b as usize] {
                    hits.surfel.push(h.hit.index);
                    hits.weight.push(h.trans * h.hit.alpha * g);
                }
                hits.start.push(hits.surfel.len());
            }
        }
        hits.composite(radiance, &mut self.indirect);
        hits
    }

    /// Re-trace only the listed surfels' rows (no gradients), with the directions a full
    /// [`refresh`](Self::refresh) of `seed` would give them; the cache keeps its size, and
    /// the rows' env footprints follow when they are kept.
    pub fn refresh_rows(&mut self, tracer: &Tracer, surfels: &Surfels, rows: &[u32], start: RayStart, seed: u64) {
        if self.len() != surfels.len() || self.samples == 0 || rows.is_empty() {
            return;
        }
        self.trace_rows(tracer, surfels, rows, start, seed, None);
        if self.footprints.len() == self.dirs.len() {
            let grid = footprint_grid(self.footprint_size);
            let s = self.samples;
            for &i in rows {
                let i = i as usize;
                for k in i * s..(i + 1) * s {
                    self.footprints[k] = grid.packed_footprint(self.dirs[k]);
                }
            }
        }
    }

    fn trace_rows(
        &mut self,
        tracer: &Tracer,
        surfels: &Surfels,
        rows: &[u32],
        start: RayStart,
        seed: u64,
        radiance: Option<&[f32]>,
    ) {
        let s = self.samples;
        let m = rows.len();
        let mut dirs = vec![[0.0f32; 3]; m * s];
        let mut weights = vec![0.0f32; if self.importance.is_some() { m * s } else { 0 }];
        let mut rays = vec![Ray::default(); m * s];
        self.weight =
            rows_rays(surfels, rows, start, seed, self.importance.as_ref(), &mut dirs, &mut weights, &mut rays);
        let mut out = vec![RayOutput::default(); m * s];
        let mut composited = vec![0.0f32; if radiance.is_some() { m * s * 3 } else { 0 }];
        match radiance {
            Some(data) => {
                trace(tracer, surfels, &rays, Some(Features { data, channels: 3 }), &mut out, Some(&mut composited))
            }
            None => trace(tracer, surfels, &rays, None, &mut out, None),
        }
        for (j, &i) in rows.iter().enumerate() {
            let i = i as usize;
            for q in 0..s {
                let (k, o) = (i * s + q, &out[j * s + q]);
                self.dirs[k] = dirs[j * s + q];
                if !self.sample_weights.is_empty() {
                    // Fibonacci rows (no importance now) weigh `weight` each.
                    self.sample_weights[k] = if weights.is_empty() { self.weight } else { weights[j * s + q] };
                }
                let (v, g, _, _) = visibility_ramp(o.transmittance, tracer.settings.opaque_below);
                self.visibility[k] = v;
                let indirect = if radiance.is_some() {
                    let c = &composited[3 * (j * s + q)..][..3];
                    [c[0], c[1], c[2]]
                } else if tracer.settings.linear_radiance {
                    o.radiance
                } else {
                    o.radiance.map(decode)
                };
                self.indirect[k] = indirect.map(|x| x * g);
            }
        }
    }

    /// Overwrite surfel `i`'s row (S samples) with freshly traced values.
    pub fn overwrite_row(&mut self, i: usize, dirs: &[[f32; 3]], visibility: &[f32], indirect: &[[f32; 3]]) {
        let s = self.samples;
        if dirs.len() != s || i >= self.len() {
            return;
        }
        self.dirs[i * s..(i + 1) * s].copy_from_slice(dirs);
        self.visibility[i * s..(i + 1) * s].copy_from_slice(visibility);
        self.indirect[i * s..(i + 1) * s].copy_from_slice(indirect);
        if !self.sample_weights.is_empty() {
            // The row's directions are Fibonacci ones now.
            self.sample_weights[i * s..(i + 1) * s].fill(self.weight);
        }
        if self.footprints.len() == self.dirs.len() {
            let grid = footprint_grid(self.footprint_size);
            for (f, &d) in self.footprints[i * s..(i + 1) * s].iter_mut().zip(dirs) {
                *f = grid.packed_footprint(d);
            }
        }
    }

    /// Make (or keep) the env footprints of every cached direction for maps of `env`'s size,
    /// so that [`inputs`](Self::inputs) hands them to the shading.
    pub fn prepare_footprints(&mut self, env: &EnvMap) {
        let size = (env.width, env.height);
        if self.footprints.len() == self.dirs.len() && self.footprint_size == size {
            return;
        }
        let grid = footprint_grid(size);
        self.footprints.resize(self.dirs.len(), PackedFootprint::default());
        self.footprints.par_iter_mut().zip(self.dirs.par_iter()).with_min_len(4096).for_each(|(f, &d)| {
            *f = grid.packed_footprint(d);
        });
        self.footprint_size = size;
    }

    /// Rendering-equation inputs over the whole cache.
    pub fn inputs<'a>(
        &'a self,
        albedo: &'a [[f32; 3]],
        roughness: &'a [f32],
        normal: &'a [[f32; 3]],
        view: &'a [[f32; 3]],
    ) -> PbrInputs<'a> {
        PbrInputs {
            albedo,
            roughness,
            normal,
            view,
            dirs: &self.dirs,
            visibility: &self.visibility,
            indirect: &self.indirect,
            samples: self.samples,
            weight: self.weight,
            sample_weights: (self.sample_weights.len() == self.dirs.len() && !self.dirs.is_empty())
                .then_some(&self.sample_weights[..]),
            specular: true,
            lambert: true,
            footprints: (self.footprints.len() == self.dirs.len()).then_some(CachedFootprints {
                data: &self.footprints,
                width: self.footprint_size.0,
                height: self.footprint_size.1,
            }),
        }
    }

    /// The solid angle sample `k` stands for (its estimator weight).
    #[inline]
    fn solid_angle(&self, k: usize) -> f32 {
        if self.sample_weights.is_empty() { self.weight } else { self.sample_weights[k] }
    }

    /// Cosine-weighted mean visibility of surfel `i` (ambient occlusion, for pictures).
    pub fn mean_visibility(&self, i: usize, normal: [f32; 3]) -> f32 {
        let s = self.samples;
        let (mut num, mut den) = (0.0f32, 0.0f32);
        for k in i * s..(i + 1) * s {
            let d = self.dirs[k];
            let c = (d[0] * normal[0] + d[1] * normal[1] + d[2] * normal[2]).max(0.0) * self.solid_angle(k);
            num += c * self.visibility[k];
            den += c;
        }
        if den > 0.0 { num / den } else { 1.0 }
    }

    /// Cosine-weighted mean indirect radiance of surfel `i` (linear): what the occluded part of
    /// a split-sum specular lobe sees.
    pub fn mean_indirect(&self, i: usize, normal: [f32; 3]) -> [f32; 3] {
        let s = self.samples;
        let (mut num, mut den) = ([0.0f32; 3], 0.0f32);
        for k in i * s..(i + 1) * s {
            let d = self.dirs[k];
            let c = (d[0] * normal[0] + d[1] * normal[1] + d[2] * normal[2]).max(0.0) * self.solid_angle(k);
            for ch in 0..3 {
                num[ch] += c * self.indirect[k][ch];
            }
            den += c;
        }
        if den > 0.0 { num.map(|x| x / den) } else { [0.0; 3] }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trace::TraceSettings;

    #[test]
    fn decode_derivative_matches_finite_differences() {
        for c in [0.01f32, 0.2, 0.5, 0.9, 1.3] {
            let h = 1e-3;
            let fd = (decode(c + h) - decode(c - h)) / (2.0 * h);
            assert!(
                (fd - decode_derivative(c)).abs() < 2e-3 * (1.0 + fd.abs()),
                "{c}: {fd} vs {}",
                decode_derivative(c)
            );
        }
        // Value and derivative from one power: the value is decode's, the derivative the f64
        // curve's 2.4/1.055 · t^1.4 to a few f32 roundings, on both segments and at the kink.
        for k in 0..=4000 {
            let c = -0.1 + 2.0 * k as f32 / 4000.0;
            let (v, d) = decode_with_derivative(c);
            assert_eq!(v.to_bits(), decode(c).to_bits(), "c {c}");
            let cc = c.max(0.0) as f64;
            let exact = if cc <= 0.040_45 { 1.0 / 12.92 } else { 2.4 / 1.055 * ((cc + 0.055) / 1.055).powf(1.4) };
            assert!((d as f64 - exact).abs() <= 1e-6 * exact, "c {c}: {d} vs {exact}");
        }
    }

    /// A bumpy floor (a layer of tilted, translucent surfels 2 cm thick) under an opaque disk:
    /// without the skip plane the floor's rays hit the floor's own surfels; with it every ray
    /// that misses the disk sees the sky, and the rays towards the disk are still blocked.
    #[test]
    fn skip_plane_removes_self_hits_of_a_bumpy_floor() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(12);
        let mut s = Surfels::default();
        for _ in 0..900 {
            let mean =
                [rng.random_range(-0.6..0.6f32), rng.random_range(-0.6..0.6f32), rng.random_range(-0.01..0.01f32)];
            let tilt = [rng.random_range(-0.35..0.35f32), rng.random_range(-0.35..0.35f32), 1.0];
            let sc = [rng.random_range(0.04..0.08f32), rng.random_range(0.04..0.08f32)];
            s.push(mean, sc, crate::surfels::quat_with_normal(tilt), 0.5, [0.5; 3], [0.3; 3], 0.5);
        }
        // The occluder: 0.4 above the floor's centre, facing down.
        let (disk_z, disk_sigma) = (0.4f32, 0.12f32);
        s.push(
            [0.0, 0.0, disk_z],
            [disk_sigma; 2],
            crate::surfels::quat_with_normal([0.0, 0.0, -1.0]),
            0.99,
            [0.5; 3],
            [0.3; 3],
            0.5,
        );
        // Rays start from flat floor surfels near the centre (the skip plane is their tangent
        // plane; a tilted one's would rise above the floor's far side and rightly see it).
        let first = s.len();
        for k in 0..6 {
            let mean = [0.05 * k as f32 - 0.12, 0.03 * k as f32 - 0.08, rng.random_range(-0.01..0.01f32)];
            s.push(mean, [0.06; 2], crate::surfels::quat_with_normal([0.0, 0.0, 1.0]), 0.5, [0.5; 3], [0.3; 3], 0.5);
        }
        let tracer = Tracer::build(&s, &TraceSettings::default());
        let rows: Vec<u32> = (first as u32..s.len() as u32).collect();
        assert!(rows.len() >= 3, "too few central floor surfels: {}", rows.len());
        let mut plain = IncidentCache::default();
        plain.refresh(&tracer, &s, 64, RayStart::offset_only(2e-3), 5);
        let mut skipping = IncidentCache::default();
        skipping.refresh(&tracer, &s, 64, RayStart { offset: 2e-3, skip_margin: Some(0.05) }, 5);
        let (mut self_hits, mut to_disk, mut free) = (0, 0, 0);
        for &i in &rows {
            let i = i as usize;
            let m = s.means[i];
            let o = [m[0], m[1], m[2] + 2e-3 * s.normal(i)[2]];
            for k in i * 64..(i + 1) * 64 {
                let d = plain.dirs[k];
                assert_eq!(d, skipping.dirs[k]);
                // Where the ray crosses the disk's plane, in units of σ.
                let t = (disk_z - o[2]) / d[2];
                let r = ((o[0] + t * d[0]).powi(2) + (o[1] + t * d[1]).powi(2)).sqrt() / disk_sigma;
                if r < 0.8 {
                    to_disk += 1;
                    assert!(
                        skipping.visibility[k] < 0.5,
                        "a ray towards the disk passed: T {}",
                        skipping.visibility[k]
                    );
                } else if r > 4.0 {
                    free += 1;
                    assert_eq!(skipping.visibility[k], 1.0, "a ray missing the disk was blocked");
                    self_hits += (plain.visibility[k] < 0.99) as usize;
                }
            }
        }
        assert!(to_disk >= 5 && free >= 100, "rays towards the disk {to_disk}, free {free}");
        assert!(
            self_hits * 10 >= free,
            "the bumpy floor should block its own rays without the skip: {self_hits}/{free}"
        );
    }

    /// Re-tracing a subset of rows gives those rows exactly what a full refresh with the same
    /// seed gives them and leaves the other rows alone; their footprints follow.
    /// The recorded hits composite a radiance exactly as the tracer's feature payload does,
    /// across the record's batches (more surfels than one batch), for any later radiance too.
    #[test]
    fn recorded_hits_composite_like_the_traced_payload() {
        use rand::{RngExt, SeedableRng};
        let n = RECORD_BATCH_SURFELS + 300;
        let s = Surfels::random_in_box(n, [-1.0; 3], [1.0; 3], 9);
        let tracer = Tracer::build(&s, &TraceSettings { linear_radiance: true, ..TraceSettings::default() });
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let first: Vec<f32> = (0..3 * n).map(|_| rng.random::<f32>()).collect();
        let second: Vec<f32> = (0..3 * n).map(|_| 2.0 * rng.random::<f32>()).collect();
        let start = RayStart { offset: 1e-3, skip_margin: Some(0.05) };
        let mut recorded = IncidentCache::default();
        let hits = recorded.refresh_recorded(&tracer, &s, 4, start, 7, &first);
        assert_eq!(hits.start.len(), 4 * n + 1);
        for radiance in [&first, &second] {
            let mut traced = IncidentCache::default();
            traced.refresh_with(&tracer, &s, 4, start, 7, Some(radiance));
            assert!(traced.visibility.iter().any(|&v| v < 0.5), "the test needs occlusion");
            assert_eq!(recorded.dirs, traced.dirs);
            assert_eq!(recorded.visibility, traced.visibility);
            assert_eq!(recorded.weight, traced.weight);
            let mut again = vec![[0.0f32; 3]; 4 * n];
            hits.composite(radiance, &mut again);
            for (k, (a, b)) in again.iter().zip(&traced.indirect).enumerate() {
                for c in 0..3 {
                    assert!((a[c] - b[c]).abs() <= 1e-6 * (1.0 + b[c].abs()), "ray {k}: {a:?} vs {b:?}");
                }
            }
            if std::ptr::eq(radiance, &first) {
                assert_eq!(recorded.indirect, again);
            }
        }
    }

    #[test]
    fn refreshing_some_rows_matches_a_full_refresh_there() {
        let s = Surfels::random_in_box(60, [-1.0; 3], [1.0; 3], 6);
        let tracer = Tracer::build(&s, &TraceSettings::default());
        let mut full = IncidentCache::default();
        full.refresh(&tracer, &s, 8, RayStart::offset_only(1e-3), 21);
        let mut partial = IncidentCache::default();
        partial.refresh(&tracer, &s, 8, RayStart::offset_only(1e-3), 4);
        let env = EnvMap::constant(16, 8, [1.0; 3]);
        partial.prepare_footprints(&env);
        let before = partial.clone();
        let rows = [2u32, 17, 18, 59];
        partial.refresh_rows(&tracer, &s, &rows, RayStart::offset_only(1e-3), 21);
        assert!(partial.visibility.iter().any(|&v| v < 1.0), "the test needs occlusion");
        for i in 0..s.len() {
            let r = i * 8..(i + 1) * 8;
            let want = if rows.contains(&(i as u32)) { &full } else { &before };
            assert!(partial.dirs[r.clone()] == want.dirs[r.clone()], "row {i}: directions");
            assert!(partial.visibility[r.clone()] == want.visibility[r.clone()], "row {i}: visibility");
            assert!(partial.indirect[r.clone()] == want.indirect[r.clone()], "row {i}: indirect");
            for k in r {
                assert_eq!(partial.footprints[k], env.packed_footprint(partial.dirs[k]), "row {i}: footprint");
            }
        }
    }

    /// Shading from the cached footprints equals shading that maps every direction itself
    /// (bit for bit), after a row is overwritten too; an env of another size ignores them.
    #[test]
    fn cached_footprints_give_the_same_shading() {
        use crate::shade::pbr::{Detach, SubsetGrads, shade_subset, shade_subset_backward};
        use rand::{RngExt, SeedableRng};
        let s = Surfels::random_in_box(40, [-1.0; 3], [1.0; 3], 4);
        let tracer = Tracer::build(&s, &TraceSettings::default());
        let mut cache = IncidentCache::default();
        cache.refresh(&tracer, &s, 8, RayStart::offset_only(1e-3), 9);
        let mut rg = rand_pcg::Pcg64::seed_from_u64(5);
        let mut env = EnvMap::constant(32, 16, [0.0; 3]);
        env.texels.iter_mut().for_each(|t| *t = [rg.random(), rg.random(), rg.random()]);
        let n = s.len();
        let albedo: Vec<[f32; 3]> = (0..n).map(|i| s.albedo(i)).collect();
        let rough: Vec<f32> = (0..n).map(|i| s.roughness(i)).collect();
        let normal: Vec<[f32; 3]> = (0..n).map(|i| s.normal(i)).collect();
        let view: Vec<[f32; 3]> = normal.iter().map(|nn| [nn[0], nn[1] + 0.3, nn[2]]).collect();
        let view: Vec<[f32; 3]> = view.iter().map(|v| crate::train::material::view_dir([0.0; 3], *v)).collect();
        let ids: Vec<u32> = (0..n as u32).collect();
        let v_up: Vec<[f32; 3]> = (0..n).map(|_| [rg.random(), rg.random(), rg.random()]).collect();
        let shade = |cache: &IncidentCache, env: &EnvMap| {
            let inp = cache.inputs(&albedo, &rough, &normal, &view);
            let (mut d, mut ind) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
            shade_subset(&inp, env, &ids, &mut d, &mut ind).unwrap();
            let mut g = SubsetGrads::default();
            shade_subset_backward(&inp, env, &ids, &v_up, &v_up, Detach::default(), &mut g).unwrap();
            (d, ind, g.v_normal, g.v_env, inp.footprints.is_some())
        };
        let plain = shade(&cache, &env);
        assert!(!plain.4);
        cache.prepare_footprints(&env);
        let cached = shade(&cache, &env);
        assert!(cached.4);
        assert!(plain.0 == cached.0 && plain.1 == cached.1 && plain.2 == cached.2 && plain.3 == cached.3);
        // A row overwritten with other directions: its footprints follow.
        let row: Vec<[f32; 3]> =
            (0..8).map(|k| crate::train::material::view_dir([0.0; 3], [k as f32 - 3.5, 1.0, 2.0])).collect();
        cache.overwrite_row(3, &row, &[0.5; 8], &[[0.2; 3]; 8]);
        let cached = shade(&cache, &env);
        cache.footprints.clear();
        let plain = shade(&cache, &env);
        assert!(plain.0 == cached.0 && plain.3 == cached.3, "after overwrite_row");
        // Another map size: the footprints are not used.
        cache.prepare_footprints(&env);
        let small = env.box_downsample(2);
        let with = shade(&cache, &small);
        cache.footprints.clear();
        let without = shade(&cache, &small);
        assert!(with.0 == without.0 && with.3 == without.3);
    }

    /// A learned light grows a sun midway (`set_importance` between row refreshes): rows traced
    /// afterwards mix map samples in and estimate each surfel's sunlit irradiance closer to the
    /// truth than the Fibonacci rows; rows not re-traced keep their directions and weights, and
    /// a light without peaks again gives Fibonacci rows of the plain weight.
    #[test]
    fn light_peaks_set_midway_weigh_new_rows_and_keep_old_ones() {
        let mut env = EnvMap::constant(64, 32, [0.05, 0.06, 0.08]);
        env.texels[7 * 64 + 20] = [900.0, 850.0, 700.0];
        env.texels[7 * 64 + 21] = [300.0, 280.0, 250.0];
        // Tiny, far-apart surfels facing every way: nothing occludes anything.
        let mut s = Surfels::random_in_box(48, [-100.0; 3], [100.0; 3], 4);
        s.log_scales.iter_mut().for_each(|l| *l = [-9.0, -9.0]);
        let tracer = Tracer::build(&s, &TraceSettings::default());
        let start = RayStart::offset_only(1e-3);
        let irradiance = |c: &IncidentCache, i: usize| -> f64 {
            let n = s.normal(i);
            (i * c.samples..(i + 1) * c.samples)
                .map(|k| {
                    let d = c.dirs[k];
                    let cos = (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]).max(0.0) as f64;
                    c.solid_angle(k) as f64 * c.visibility[k] as f64 * env.lookup(d)[0] as f64 * cos
                })
                .sum()
        };
        let mut truth = IncidentCache::default();
        truth.refresh(&tracer, &s, 4096, start, 1);
        let mut cache = IncidentCache::default();
        cache.refresh(&tracer, &s, 32, start, 2);
        let before = cache.clone();
        cache.set_importance(EnvImportance::of_map(&env, 32, 0.25));
        assert!(cache.importance.as_ref().is_some_and(|imp| imp.samples == 8));
        assert!(
            cache.sample_weights.len() == cache.dirs.len() && cache.sample_weights.iter().all(|&w| w == cache.weight)
        );
        let even: Vec<u32> = (0..s.len() as u32).step_by(2).collect();
        cache.refresh_rows(&tracer, &s, &even, start, 3);
        let (mut err_fib, mut err_mix) = (0.0, 0.0);
        for i in 0..s.len() {
            let row = i * 32..(i + 1) * 32;
            let e = (irradiance(&cache, i) - irradiance(&truth, i)).abs() / irradiance(&truth, i);
            if i % 2 == 1 {
                assert_eq!(cache.dirs[row.clone()], before.dirs[row.clone()]);
                assert!(cache.sample_weights[row].iter().all(|&w| w == cache.weight));
                err_fib += e;
            } else {
                assert!(cache.sample_weights[row].iter().any(|&w| w != cache.weight), "row {i} has no map samples");
                err_mix += e;
            }
        }
        // Measured: mixed rows 5.5 %, Fibonacci rows 38 % on average.
        let (err_mix, err_fib) = (err_mix / 24.0, err_fib / 24.0);
        assert!(
            err_mix < 0.1 && err_mix < 0.3 * err_fib,
            "mean relative error: mixed rows {err_mix}, Fibonacci {err_fib}"
        );
        // The light loses its peaks: re-traced rows are Fibonacci again, at the plain weight.
        cache.set_importance(EnvImportance::of_map(&EnvMap::constant(64, 32, [1.0; 3]), 32, 0.25));
        assert!(cache.importance.is_none());
        cache.refresh_rows(&tracer, &s, &even, start, 4);
        assert!(cache.sample_weights.iter().all(|&w| w == cache.weight));
    }

    #[test]
    fn a_lid_over_a_floor_blocks_the_upward_rays() {
        // A floor surfel facing up and a large opaque lid facing down above it: every ray of
        // the floor surfel that reaches the lid's disk is blocked; without the lid, all see sky.
        let mut s = Surfels::random_in_box(2, [0.0; 3], [0.0; 3], 1);
        s.means = vec![[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]];
        s.quats = vec![[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]]; // +z, and flipped to −z
        s.log_scales = vec![[-5.0, -5.0], [3.0, 3.0]];
        s.opacity_logits = vec![10.0, 10.0];
        s.sh.iter_mut().for_each(|c| *c = [[0.0; 3]; crate::sh::SH_COEFFS]);
        s.sh_degree = 0;
        assert!(s.normal(1)[2] < -0.99);
        let tracer = Tracer::build(&s, &TraceSettings::default());
        let mut cache = IncidentCache::default();
        cache.refresh(&tracer, &s, 16, RayStart::offset_only(1e-3), 7);
        for k in 0..16 {
            assert!(cache.visibility[k] < 0.05, "floor sample {k}: V = {}", cache.visibility[k]);
            // The lid's SH colour is 0.5 (sRGB) → linear ≈ 0.214, times its α ≈ 0.99.
            let want = decode(0.5) * (1.0 - cache.visibility[k]);
            assert!((cache.indirect[k][0] - want).abs() < 0.02, "{} vs {want}", cache.indirect[k][0]);
        }
        // The lid's own rays go down into empty space (the floor disk is tiny): all visible.
        for k in 16..32 {
            assert!(cache.visibility[k] > 0.99, "lid sample {k}: V = {}", cache.visibility[k]);
        }
        assert!((cache.weight - (2.0 * std::f32::consts::PI * (1.0 - 10f32.to_radians().sin()) / 16.0)).abs() < 1e-5);
    }
}
