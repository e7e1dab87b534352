//! Forward tracing: per ray, gather the k nearest hits beyond the last composited (t, index) key,
//! composite them front to back, repeat until T < min_transmittance or no hits remain.
//!
//! C = Σ_j T_j α_j c_j, T_j = Π_{k<j} (1 − α_k); the same weights w_j = T_j α_j give depth
//! Σ w_j t_j, normal Σ w_j n_j and feature channels Σ w_j f_j. c_j = max(SH_j(d̂) + 0.5, 0) at the
//! ray's unit direction d̂ (the basis is evaluated once per ray).
//!
//! Parallel decomposition: rayon over rays (each ray independent, no shared writes), taken in a
//! coherent order (`coherent_order`: runs of rays sharing an origin, by the Morton code of the
//! origin) so consecutive rays reuse the nodes and leaves in cache; outputs are put back in the
//! callers' order.
//! Nothing is saved for the backward pass: it re-casts the rays.

use crate::camera::Camera;
use crate::sh::{self, SH_COEFFS};
use crate::shade::incident::decode;
use crate::surfels::Surfels;
use crate::trace::bvh::{Hit, PreparedRay, Tracer};
use crate::trace::{Features, MAX_CHUNK, Ray, RayOutput, TraceSettings};
use rayon::prelude::*;

/// Visit the composited hits of one ray in order: `f(hit, T_before)`; returns the final T.
/// `hint` sees each hit's surfel index as the traversal finds it (to prefetch its data).
#[inline]
pub(crate) fn march(tracer: &Tracer, r: &PreparedRay, hint: impl Fn(u32), mut f: impl FnMut(&Hit, f32)) -> f32 {
    let k = tracer.settings.chunk.clamp(1, MAX_CHUNK);
    let min_t = tracer.settings.min_transmittance;
    let mut trans = 1.0f32;
    let mut after = (f32::NEG_INFINITY, 0u32);
    let mut buf = [Hit::default(); MAX_CHUNK];
    loop {
        let n = tracer.gather(r, after, k, (trans, min_t), &mut buf, &hint);
        for h in &buf[..n] {
            f(h, trans);
            trans *= 1.0 - h.alpha;
            if trans < min_t {
                return trans;
            }
        }
        if n < k {
            return trans;
        }
        after = (buf[n - 1].t, buf[n - 1].index);
    }
}

/// SH colour of a surfel for a precomputed basis (degree-limited), before and after the clamp.
#[inline(always)]
pub(crate) fn sh_colour(coeffs: &[[f32; 3]; SH_COEFFS], basis: &[f32; SH_COEFFS], ncoef: usize) -> [f32; 3] {
    let mut c = [0.5f32; 3];
    for k in 0..ncoef {
        for ch in 0..3 {
            c[ch] += coeffs[k][ch] * basis[k];
        }
    }
    c
}

/// A hint to bring `p`'s cache line in (no effect off x86-64).
#[inline(always)]
pub(crate) fn prefetch<T>(p: &T) {
    prefetch_byte(p as *const T as *const u8);
}

/// A hint to bring in every cache line `s` touches: its first byte, one every 64 and its last
/// (a 192-byte SH array 4-byte aligned can touch four lines).
#[inline(always)]
pub(crate) fn prefetch_all<T>(s: &[T]) {
    let bytes = std::mem::size_of_val(s);
    if bytes == 0 {
        return;
    }
    let p = s.as_ptr() as *const u8;
    let mut at = 0;
    while at < bytes {
        prefetch_byte(p.wrapping_add(at));
        at += 64;
    }
    prefetch_byte(p.wrapping_add(bytes - 1));
}

#[inline(always)]
fn prefetch_byte(p: *const u8) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch is a hint; it never faults and reads nothing observable.
    unsafe {
        std::arch::x86_64::_mm_prefetch(p as *const i8, std::arch::x86_64::_MM_HINT_T0);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

pub(crate) fn unit(d: [f32; 3]) -> ([f32; 3], f32) {
    let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-20);
    (d.map(|x| x / len), len)
}

/// Trace `rays` through the surfels (the tracer must be built/refitted for these surfels).
/// With `features`, the feature channels are composited into `out_features` (rays × channels)
/// and `radiance` is left zero; without, SH radiance is the payload.
///
/// Panics if `out` (or `out_features`) does not match the ray count, or `features.data` is not
/// surfels × channels (programming errors, not user input).
pub fn trace(
    tracer: &Tracer,
    surfels: &Surfels,
    rays: &[Ray],
    features: Option<Features>,
    out: &mut [RayOutput],
    out_features: Option<&mut [f32]>,
) {
    check_inputs(tracer, surfels, rays, out);
    let ncoef = sh::coeff_count(surfels.sh_degree);
    // Rays are traced in a coherent order (neighbouring origins and directions one after
    // another share the nodes and leaves they load) and the outputs put back in place.
    let order = coherent_order(rays);
    let ch = match (&features, &out_features) {
        (Some(f), Some(of)) => {
            assert_eq!(f.data.len(), surfels.len() * f.channels, "trace: features are not surfels × channels");
            assert_eq!(of.len(), rays.len() * f.channels, "trace: out_features is not rays × channels");
            f.channels
        }
        _ => 0,
    };
    let n = rays.len();
    let mut sorted = vec![RayOutput::default(); n];
    let mut sorted_features = vec![0.0f32; n * ch];
    match features.filter(|_| ch > 0) {
        Some(f) => sorted
            .par_iter_mut()
            .zip(sorted_features.par_chunks_mut(ch))
            .zip(order.par_iter())
            .with_min_len(32)
            .for_each(|((o, of), &k)| {
                *o = trace_one(tracer, surfels, &rays[k as usize], ncoef, Some((f.data, ch, of)), None)
            }),
        None => sorted.par_iter_mut().zip(order.par_iter()).with_min_len(32).for_each(|(o, &k)| {
            *o = trace_one(tracer, surfels, &rays[k as usize], ncoef, None, None);
        }),
    }
    let mut out_features = out_features;
    for (j, &k) in order.iter().enumerate() {
        let k = k as usize;
        out[k] = sorted[j];
        if let Some(of) = out_features.as_deref_mut().filter(|_| ch > 0) {
            of[k * ch..(k + 1) * ch].copy_from_slice(&sorted_features[j * ch..(j + 1) * ch]);
        }
    }
}

/// The hits each ray composited in a forward pass (with the transmittance in front of each)
/// and the coherent order it ran in, kept so that the backward need not cast the rays again
/// ([`crate::trace::backward::trace_backward_recorded`]). Reused between calls.
#[derive(Clone, Debug, Default)]
pub struct HitRecord {
    pub(crate) order: Vec<u32>,
    /// Per ray (caller's index): its hits' range in `hits`.
    pub(crate) spans: Vec<(u32, u32)>,
    pub(crate) hits: Vec<RecordedHit>,
    /// Per ray: the final transmittance.
    pub(crate) t_final: Vec<f32>,
    chunks: Vec<Vec<RecordedHit>>,
}

/// One composited hit as the forward saw it: the hit, the transmittance in front of it and the
/// surfel's SH colour along the ray before the clamp (so the backward need not load the SH
/// coefficients again).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct RecordedHit {
    pub hit: Hit,
    pub trans: f32,
    pub colour: [f32; 3],
}

/// Rays per parallel task of [`trace_recorded`] (their hit lists are joined in order).
const RECORD_CHUNK: usize = 64;

/// [`trace`] with SH radiance as the payload, keeping every ray's hits in `record` for
/// [`crate::trace::backward::trace_backward_recorded`]. Same outputs as `trace`.
pub fn trace_recorded(tracer: &Tracer, surfels: &Surfels, rays: &[Ray], out: &mut [RayOutput], record: &mut HitRecord) {
    check_inputs(tracer, surfels, rays, out);
    let ncoef = sh::coeff_count(surfels.sh_degree);
    let n = rays.len();
    record.order = coherent_order(rays);
    let tasks = n.div_ceil(RECORD_CHUNK);
    record.chunks.resize_with(tasks, Vec::new);
    let mut sorted = vec![RayOutput::default(); n];
    let mut counts = vec![0u32; n];
    sorted
        .par_chunks_mut(RECORD_CHUNK)
        .zip(counts.par_chunks_mut(RECORD_CHUNK))
        .zip(record.order.par_chunks(RECORD_CHUNK))
        .zip(record.chunks.par_iter_mut())
        .for_each(|(((outs, counts), ids), hits)| {
            hits.clear();
            for ((o, c), &k) in outs.iter_mut().zip(counts.iter_mut()).zip(ids) {
                let before = hits.len();
                *o = trace_one(tracer, surfels, &rays[k as usize], ncoef, None, Some(hits));
                *c = (hits.len() - before) as u32;
            }
        });
    record.hits.clear();
    for c in &record.chunks {
        record.hits.extend_from_slice(c);
    }
    record.spans.resize(n, (0, 0));
    record.t_final.resize(n, 1.0);
    let mut start = 0u32;
    for (j, &k) in record.order.iter().enumerate() {
        let k = k as usize;
        record.spans[k] = (start, start + counts[j]);
        start += counts[j];
        record.t_final[k] = sorted[j].transmittance;
        out[k] = sorted[j];
    }
}

/// Programming errors the forward passes refuse: an output per ray, a tracer of this scene.
fn check_inputs(tracer: &Tracer, surfels: &Surfels, rays: &[Ray], out: &[RayOutput]) {
    assert_eq!(out.len(), rays.len(), "trace: out has {} entries for {} rays", out.len(), rays.len());
    assert!(
        !tracer.count_mismatch(surfels),
        "trace: tracer built for {} surfels, scene has {}",
        tracer.count,
        surfels.len()
    );
}

/// A tracing order in which consecutive rays start close together: runs of rays with the same
/// origin (a surfel's batch of directions, a camera's pixels) are ordered by a Morton code of
/// that origin (10 bits per axis over the rays' bounds), ties by the run's first index
/// (deterministic); within a run the caller's order is kept. Below 64 rays: as given.
///
/// The directions are deliberately not sorted: on the `surface` bench scene ordering each run
/// by a direction code as well made the forward 12–20 % slower than the caller's (random)
/// direction order, and on the other scenes no faster (BENCHMARKS.md, session 23). Only the
/// runs are sorted, so the order costs a scan plus a sort of one key per origin.
pub(crate) fn coherent_order(rays: &[Ray]) -> Vec<u32> {
    let n = rays.len();
    if n < 64 {
        return (0..n as u32).collect();
    }
    // Runs of bitwise-equal origins (so NaN origins never merge).
    let same = |a: &Ray, b: &Ray| a.origin.map(f32::to_bits) == b.origin.map(f32::to_bits);
    let mut starts: Vec<u32> = Vec::with_capacity(n / 16 + 1);
    starts.push(0);
    for i in 1..n {
        if !same(&rays[i], &rays[i - 1]) {
            starts.push(i as u32);
        }
    }
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for &s in &starts {
        for a in 0..3 {
            let x = rays[s as usize].origin[a];
            if x.is_finite() {
                lo[a] = lo[a].min(x);
                hi[a] = hi[a].max(x);
            }
        }
    }
    // `as u32` saturates (NaN → 0), so odd rays only land in odd places.
    let quantise = |x: f32, a: usize| {
        if hi[a] > lo[a] { ((x - lo[a]) / (hi[a] - lo[a]) * 1023.0) as u32 } else { 0 }
    };
    let morton = |o: [f32; 3]| {
        let q: [u32; 3] = std::array::from_fn(|a| quantise(o[a], a));
        let mut k = 0u64;
        for b in (0..10).rev() {
            for &x in &q {
                k = (k << 1) | ((x >> b) & 1) as u64;
            }
        }
        k
    };
    // Key: Morton code above the run's first index (unique, so the sort is deterministic).
    let mut runs: Vec<(u64, u32)> = starts
        .iter()
        .enumerate()
        .map(|(r, &s)| ((morton(rays[s as usize].origin) << 32) | s as u64, r as u32))
        .collect();
    runs.par_sort_unstable();
    let mut order = Vec::with_capacity(n);
    for &(_, r) in &runs {
        let r = r as usize;
        let end = starts.get(r + 1).copied().unwrap_or(n as u32);
        order.extend(starts[r]..end);
    }
    order
}

fn trace_one(
    tracer: &Tracer,
    surfels: &Surfels,
    ray: &Ray,
    ncoef: usize,
    mut feat: Option<(&[f32], usize, &mut [f32])>,
    mut record: Option<&mut Vec<RecordedHit>>,
) -> RayOutput {
    let r = PreparedRay::from_ray(ray);
    let basis = sh::basis(unit(ray.dir).0);
    let mut o = RayOutput::default();
    let linear = tracer.settings.linear_radiance;
    // The payload loads are scattered: ask for each hit's as the traversal finds it.
    let feat_data: Option<(&[f32], usize)> = feat.as_ref().map(|(data, ch, _)| (*data, *ch));
    let hint = |i: u32| match feat_data {
        Some((data, ch)) => prefetch_all(&data[i as usize * ch..][..ch]),
        None => prefetch_all(&surfels.sh[i as usize][..ncoef]),
    };
    let t_final = march(tracer, &r, hint, |h, trans| {
        let w = trans * h.alpha;
        let i = h.index as usize;
        let n = tracer.slot_normal(h.slot);
        // From behind: the hit is a back face (two-sided or a back occluder), maybe dark.
        let from_behind = n[0] * r.d[0] + n[1] * r.d[1] + n[2] * r.d[2] > 0.0;
        let (back, dark) = match from_behind.then(|| tracer.back_face(h.slot)).flatten() {
            Some(dark) => (true, dark),
            None => (false, false),
        };
        match feat.as_mut() {
            Some((data, ch, of)) => {
                if !dark {
                    let f = &data[i * *ch..(i + 1) * *ch];
                    for c in 0..*ch {
                        of[c] += w * f[c];
                    }
                }
            }
            None => {
                let c = if dark { [0.0; 3] } else { sh_colour(&surfels.sh[i], &basis, ncoef) };
                if let Some(rec) = record.as_deref_mut() {
                    rec.push(RecordedHit { hit: *h, trans, colour: c });
                }
                for ch in 0..3 {
                    let col = c[ch].max(0.0);
                    o.radiance[ch] += w * if linear { decode(col) } else { col };
                }
            }
        }
        o.depth += w * h.t;
        let s = if back { -w } else { w };
        for a in 0..3 {
            o.normal[a] += s * n[a];
        }
    });
    o.transmittance = t_final;
    o
}

/// Render a camera view through the tracer: row-major colours and alpha = 1 − T per pixel.
/// Camera rays start at the camera centre (hits at t ≤ settings.t_min are ignored).
pub fn render_camera_traced(surfels: &Surfels, camera: &Camera, settings: &TraceSettings) -> (Vec<[f32; 3]>, Vec<f32>) {
    let tracer = Tracer::build(surfels, settings);
    let (w, h) = (camera.width as usize, camera.height as usize);
    let rays: Vec<Ray> = (0..w * h)
        .into_par_iter()
        .map(|k| {
            let (o, d) = camera.ray((k % w) as f32 + 0.5, (k / w) as f32 + 0.5);
            Ray { origin: o.to_array(), dir: d.to_array(), ..Default::default() }
        })
        .collect();
    let mut out = vec![RayOutput::default(); rays.len()];
    trace(&tracer, surfels, &rays, None, &mut out, None);
    (out.iter().map(|o| o.radiance).collect(), out.iter().map(|o| 1.0 - o.transmittance).collect())
}
