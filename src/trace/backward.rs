//! Backward of [`crate::trace::trace`] by re-casting each ray (nothing is stored between the
//! passes; [`trace_backward_recorded`] instead replays the hits a
//! [`crate::trace::forward::trace_recorded`] forward kept — the consistency step's rays, where
//! the second cast was a third of the step): the re-cast gathers the ray's composited hits into
//! a per-thread scratch list, then
//! walks them back to front with suffix sums S_j = Σ_{k>j} T_k α_k x_k of every payload x
//! (colour or features, depth, normal):
//!
//!   ∂X/∂α_j = T_j x_j − S_j / (1 − α_j),   ∂T_final/∂α_j = −T_final / (1 − α_j),
//!   ∂X/∂x_j = T_j α_j.
//!
//! Then α = min(0.99, o·G) (no gradient through the clamp), G = exp(−(u² + v²)/2),
//! u = t_u·p/s_u, v = t_v·p/s_v, p = o + t d − μ, t = n·(μ − o)/(n·d), R = [t_u t_v n] from the
//! quaternion, o = sigmoid(θ); c = max(SH(d̂) + 0.5, 0) (clamped channels pass no gradient); the
//! SH direction gradient is summed per ray and pushed through d̂ = d/|d| once.
//!
//! Parallel decomposition: rayon over fixed blocks of rays (in the forward's coherent order,
//! a function of the rays alone); each block borrows a gradient buffer from a pool (about one
//! per thread) that keeps the records of the surfels it touched compactly (a slot per surfel,
//! first-touch order) and returns them as a list sorted by surfel. The lists are added into
//! `v_surfels` in block order, threads taking disjoint surfel ranges, so the gradients are
//! bitwise deterministic whatever the thread count or
//! scheduling (no atomics, no per-hit locking).

use crate::sh::{self, SH_COEFFS};
use crate::shade::incident::decode_with_derivative;
use crate::surfels::{SurfelGrads, Surfels, rotation_from_quat, rotation_from_quat_backward, sigmoid};
use crate::trace::bvh::{PreparedRay, Tracer};
use crate::trace::forward::{HitRecord, RecordedHit, coherent_order, march, prefetch, prefetch_all, sh_colour, unit};
use crate::trace::{ALPHA_MAX, Features, Ray, RayGrad};
use rayon::prelude::*;
use std::sync::Mutex;

/// Rays per block (the unit of work and of the deterministic reduction).
const RAYS_PER_BLOCK: usize = 256;
/// Blocks traced in parallel before their gradient lists are merged.
const BLOCKS_PER_WAVE: usize = 64;
/// Surfels per parallel task of the merge.
const MERGE_RANGE: usize = 2048;
// Offsets in a gradient record: means 3, log_scales 2, quats 4, opacity 1, then SH, features.
const O_MEAN: usize = 0;
const O_SCALE: usize = 3;
const O_QUAT: usize = 5;
const O_OPACITY: usize = 9;
const O_SH: usize = 10;

/// A per-thread gradient buffer: the records of the surfels one block of rays touched, stored
/// compactly in first-touch order (a block's few thousand records stay in L2; a dense
/// surfels × stride buffer spread them over tens of MB and every first touch missed the cache).
struct GradBuf {
    /// Per surfel: its record's slot in `data`, or `NO_SLOT`.
    slot_of: Vec<u32>,
    /// Per slot: the surfel.
    touched: Vec<u32>,
    data: Vec<f32>,
    hits: Vec<RecordedHit>,
    feat_scratch: Vec<f32>,
}

const NO_SLOT: u32 = u32::MAX;

impl GradBuf {
    fn new(n: usize) -> Self {
        GradBuf {
            slot_of: vec![NO_SLOT; n],
            touched: Vec::new(),
            data: Vec::new(),
            hits: Vec::new(),
            feat_scratch: Vec::new(),
        }
    }
    #[inline]
    fn record(&mut self, i: usize, stride: usize) -> &mut [f32] {
        let mut slot = self.slot_of[i] as usize;
        if slot == NO_SLOT as usize {
            slot = self.touched.len();
            self.slot_of[i] = slot as u32;
            self.touched.push(i as u32);
            self.data.resize(self.data.len() + stride, 0.0);
        }
        &mut self.data[slot * stride..(slot + 1) * stride]
    }
}

/// What the backward reads of a surfel per hit, packed into one cache line (the scene's
/// separate arrays cost four scattered loads per hit) with the exponentials done once.
#[derive(Clone, Copy, Default)]
#[repr(C, align(64))]
struct SurfelGeometry {
    mean: [f32; 3],
    quat: [f32; 4],
    scale: [f32; 2],
    opacity: f32,
}

/// Gradients of a loss on the outputs of [`crate::trace::trace`] (same tracer, surfels, rays,
/// features). `grads[r]` is ∂L/∂(ray r's RayOutput); `v_features_out` (rays × channels) is
/// ∂L/∂(its composited features) when features are traced. Adds (+=) into `v_surfels` (same
/// shape as the surfels; means, log_scales, quats, opacity_logits and the active SH
/// coefficients) and `v_surfel_features` (surfels × channels); writes ∂L/∂origin and
/// ∂L/∂dir of each ray into `v_rays`.
///
/// Panics on mismatched buffer lengths (programming errors).
#[allow(clippy::too_many_arguments)]
pub fn trace_backward(
    tracer: &Tracer,
    surfels: &Surfels,
    rays: &[Ray],
    features: Option<Features>,
    grads: &[RayGrad],
    v_features_out: Option<&[f32]>,
    v_surfels: &mut SurfelGrads,
    v_surfel_features: Option<&mut [f32]>,
    v_rays: Option<&mut [Ray]>,
) {
    backward(
        tracer,
        surfels,
        rays,
        features,
        grads,
        v_features_out,
        v_surfels,
        v_surfel_features,
        v_rays,
        None,
        MERGE_RANGE,
    );
}

/// [`trace_backward`] for rays traced by [`crate::trace::forward::trace_recorded`] (SH
/// radiance payload) with the surfels and tracer unchanged since: the recorded hits replace
/// the second cast of every ray. Bitwise the same gradients.
pub fn trace_backward_recorded(
    tracer: &Tracer,
    surfels: &Surfels,
    rays: &[Ray],
    grads: &[RayGrad],
    v_surfels: &mut SurfelGrads,
    v_rays: Option<&mut [Ray]>,
    record: &HitRecord,
) {
    assert_eq!(record.spans.len(), rays.len(), "trace_backward_recorded: the record is of another ray set");
    backward(tracer, surfels, rays, None, grads, None, v_surfels, None, v_rays, Some(record), MERGE_RANGE);
}

/// Both backwards; `merge_range` is the number of surfels per parallel merge task (results do
/// not depend on it; the tests check that).
#[allow(clippy::too_many_arguments)]
pub(crate) fn backward(
    tracer: &Tracer,
    surfels: &Surfels,
    rays: &[Ray],
    features: Option<Features>,
    grads: &[RayGrad],
    v_features_out: Option<&[f32]>,
    v_surfels: &mut SurfelGrads,
    mut v_surfel_features: Option<&mut [f32]>,
    v_rays: Option<&mut [Ray]>,
    record: Option<&HitRecord>,
    merge_range: usize,
) {
    let n = surfels.len();
    let merge_range = merge_range.max(1);
    assert_eq!(grads.len(), rays.len(), "trace_backward: {} grads for {} rays", grads.len(), rays.len());
    assert_eq!(v_surfels.len(), n, "trace_backward: v_surfels has {} surfels, scene {}", v_surfels.len(), n);
    assert!(
        !tracer.count_mismatch(surfels),
        "trace_backward: tracer built for {} surfels, scene has {}",
        tracer.count,
        n
    );
    let (channels, fdata, vfo) = match features {
        Some(f) if f.channels > 0 => {
            assert_eq!(f.data.len(), n * f.channels, "trace_backward: features are not surfels × channels");
            let vfo = v_features_out.unwrap_or(&[]);
            assert!(vfo.is_empty() || vfo.len() == rays.len() * f.channels, "trace_backward: v_features_out size");
            (f.channels, f.data, vfo)
        }
        _ => (0, &[][..], &[][..]),
    };
    let use_features = features.is_some();
    let ncoef = if use_features { 0 } else { sh::coeff_count(surfels.sh_degree) };
    let o_feat = O_SH + 3 * ncoef;
    let stride = o_feat + channels;
    if let Some(vsf) = v_surfel_features.as_deref() {
        assert_eq!(vsf.len(), n * channels, "trace_backward: v_surfel_features is not surfels × channels");
    }
    let pool: Mutex<Vec<GradBuf>> = Mutex::new(Vec::new());
    let want_rays = v_rays.is_some();
    let geometry: Vec<SurfelGeometry> = (0..n)
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| SurfelGeometry {
            mean: surfels.means[i],
            quat: surfels.quats[i],
            scale: surfels.scale(i),
            opacity: sigmoid(surfels.opacity_logits[i]),
        })
        .collect();
    let ctx = Ctx {
        tracer,
        surfels,
        geometry: &geometry,
        ncoef,
        channels,
        fdata,
        vfo,
        o_feat,
        stride,
        use_features,
        want_rays,
        record,
    };

    // One block of rays: accumulate into a pooled dense buffer, then hand back the touched
    // records as a sparse list (first-touch order) and clear the buffer. Which buffer a block
    // borrows does not matter (it is all zeros), so the sparse lists depend only on the rays.
    let process = |ids: &[u32], mut vr: Option<&mut [Ray]>| -> Sparse {
        let mut buf = pool.lock().unwrap().pop().unwrap_or_else(|| GradBuf::new(n));
        for (k, &r) in ids.iter().enumerate() {
            // Per-hit surfel loads are scattered: ask for the next ray's while this one runs.
            if let (Some(rec), Some(&next)) = (record, ids.get(k + 1)) {
                let (a, b) = rec.spans[next as usize];
                for rh in &rec.hits[a as usize..b as usize] {
                    prefetch(&ctx.geometry[rh.hit.index as usize]);
                }
            }
            let r = r as usize;
            let g = ctx.ray_backward(r, &rays[r], &grads[r], &mut buf);
            if let Some(vr) = vr.as_deref_mut() {
                vr[k] = g;
            }
        }
        // Records sorted by surfel, so the merge can hand out surfel ranges to threads.
        let mut by_surfel: Vec<u32> = (0..buf.touched.len() as u32).collect();
        by_surfel.sort_unstable_by_key(|&slot| buf.touched[slot as usize]);
        let mut sparse =
            Sparse { index: Vec::with_capacity(by_surfel.len()), data: Vec::with_capacity(buf.data.len()) };
        for &slot in &by_surfel {
            let slot = slot as usize;
            sparse.index.push(buf.touched[slot]);
            sparse.data.extend_from_slice(&buf.data[slot * stride..(slot + 1) * stride]);
        }
        for &i in &buf.touched {
            buf.slot_of[i as usize] = NO_SLOT;
        }
        buf.touched.clear();
        buf.data.clear();
        pool.lock().unwrap().push(buf);
        sparse
    };
    // Deterministic reduction: blocks have fixed boundaries (independent of the thread count
    // and scheduling) and their sparse lists are added into `v_surfels` in block order, a wave
    // of blocks at a time (bounds the memory held by the lists). Threads take disjoint surfel
    // ranges, each walking every list's sorted sub-range, so each surfel's sum keeps block order.
    let mut merge = |lists: &[Sparse]| {
        let range_of = |sp: &Sparse, lo: usize, hi: usize| {
            sp.index.partition_point(|&i| (i as usize) < lo)..sp.index.partition_point(|&i| (i as usize) < hi)
        };
        let vs = &mut *v_surfels;
        vs.means
            .par_chunks_mut(merge_range)
            .zip(vs.log_scales.par_chunks_mut(merge_range))
            .zip(vs.quats.par_chunks_mut(merge_range))
            .zip(vs.opacity_logits.par_chunks_mut(merge_range))
            .zip(vs.sh.par_chunks_mut(merge_range))
            .enumerate()
            .for_each(|(ri, ((((means, log_scales), quats), opacity_logits), sh))| {
                let lo = ri * merge_range;
                for sp in lists {
                    for e in range_of(sp, lo, lo + means.len()) {
                        let i = sp.index[e] as usize - lo;
                        let g = &sp.data[e * stride..(e + 1) * stride];
                        for a in 0..3 {
                            means[i][a] += g[O_MEAN + a];
                        }
                        for a in 0..2 {
                            log_scales[i][a] += g[O_SCALE + a];
                        }
                        for a in 0..4 {
                            quats[i][a] += g[O_QUAT + a];
                        }
                        opacity_logits[i] += g[O_OPACITY];
                        for k in 0..ncoef {
                            for ch in 0..3 {
                                sh[i][k][ch] += g[O_SH + 3 * k + ch];
                            }
                        }
                    }
                }
            });
        if let Some(vsf) = v_surfel_features.as_deref_mut().filter(|_| channels > 0) {
            vsf.par_chunks_mut(merge_range * channels).enumerate().for_each(|(ri, vsf)| {
                let lo = ri * merge_range;
                for sp in lists {
                    for e in range_of(sp, lo, lo + vsf.len() / channels) {
                        let i = sp.index[e] as usize - lo;
                        for c in 0..channels {
                            vsf[i * channels + c] += sp.data[e * stride + o_feat + c];
                        }
                    }
                }
            });
        }
    };
    // Blocks follow the same coherent ray order as the forward pass (a fixed function of the
    // rays, so the reduction stays deterministic).
    let computed;
    let order: &[u32] = match record {
        Some(rec) => &rec.order,
        None => {
            computed = coherent_order(rays);
            &computed
        }
    };
    let wave = RAYS_PER_BLOCK * BLOCKS_PER_WAVE;
    match v_rays {
        Some(vr) => {
            assert_eq!(vr.len(), rays.len(), "trace_backward: v_rays has {} entries for {} rays", vr.len(), rays.len());
            let mut sorted = vec![Ray::default(); rays.len()];
            for (ow, vw) in order.chunks(wave).zip(sorted.chunks_mut(wave)) {
                let lists: Vec<Sparse> = ow
                    .par_chunks(RAYS_PER_BLOCK)
                    .zip(vw.par_chunks_mut(RAYS_PER_BLOCK))
                    .map(|(ids, vr)| process(ids, Some(vr)))
                    .collect();
                merge(&lists);
            }
            for (&k, g) in order.iter().zip(sorted) {
                vr[k as usize] = g;
            }
        }
        None => {
            for ow in order.chunks(wave) {
                let lists: Vec<Sparse> = ow.par_chunks(RAYS_PER_BLOCK).map(|ids| process(ids, None)).collect();
                merge(&lists);
            }
        }
    }
}

/// The gradient records one block of rays produced: surfel indices and `stride` floats each.
struct Sparse {
    index: Vec<u32>,
    data: Vec<f32>,
}

struct Ctx<'a> {
    tracer: &'a Tracer,
    surfels: &'a Surfels,
    geometry: &'a [SurfelGeometry],
    ncoef: usize,
    channels: usize,
    fdata: &'a [f32],
    vfo: &'a [f32],
    o_feat: usize,
    stride: usize,
    use_features: bool,
    /// ∂L/∂(origin, dir) wanted: otherwise the SH direction terms are skipped.
    want_rays: bool,
    /// The forward pass's hits (then the rays are not cast again).
    record: Option<&'a HitRecord>,
}

#[inline(always)]
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

impl Ctx<'_> {
    /// Backward of one ray; returns ∂L/∂(origin, dir).
    fn ray_backward(&self, ray_index: usize, ray: &Ray, g: &RayGrad, buf: &mut GradBuf) -> Ray {
        let (tracer, surfels) = (self.tracer, self.surfels);
        let r = PreparedRay::from_ray(ray);
        let (dh, dlen) = unit(ray.dir);
        let basis = sh::basis(dh);
        let ch = self.channels;
        let use_features = self.use_features;
        let mut cast = std::mem::take(&mut buf.hits);
        cast.clear();
        // Recorded hits carry their SH colour; re-cast ones get it from the coefficients below.
        let (hits, t_final): (&[RecordedHit], f32) = match self.record {
            Some(rec) => {
                let (a, b) = rec.spans[ray_index];
                (&rec.hits[a as usize..b as usize], rec.t_final[ray_index])
            }
            None => {
                // The hits' scattered loads below (geometry, payload, gradient slot): asked for
                // as the traversal finds them.
                let slot_of = &buf.slot_of;
                let hint = |i: u32| {
                    let i = i as usize;
                    prefetch(&self.geometry[i]);
                    prefetch(&slot_of[i]);
                    if use_features {
                        prefetch_all(&self.fdata[i * ch..][..ch]);
                    } else {
                        prefetch_all(&surfels.sh[i][..self.ncoef]);
                    }
                };
                let t = march(tracer, &r, hint, |h, trans| cast.push(RecordedHit { hit: *h, trans, colour: [0.0; 3] }));
                (&cast, t)
            }
        };
        let recorded = self.record.is_some();
        let v_fo: &[f32] = if self.vfo.is_empty() { &[] } else { &self.vfo[ray_index * ch..(ray_index + 1) * ch] };
        let mut sfeat = std::mem::take(&mut buf.feat_scratch);
        sfeat.clear();
        sfeat.resize(ch, 0.0);
        // Suffix sums Σ_{k>j} T_k α_k x_k.
        let (mut s_rad, mut s_depth, mut s_norm) = ([0.0f32; 3], 0.0f32, [0.0f32; 3]);
        let mut v_o = [0.0f32; 3];
        let mut v_d = [0.0f32; 3];
        let mut v_basis = [0.0f32; SH_COEFFS];
        let (o, d) = (ray.origin, ray.dir);
        for rh in hits.iter().rev() {
            let (h, trans) = (&rh.hit, rh.trans);
            let i = h.index as usize;
            let alpha = h.alpha;
            let w = trans * alpha;
            let inv = 1.0 / (1.0 - alpha);
            // Recompute the hit's geometry from the parameters.
            let geo = &self.geometry[i];
            let rot = rotation_from_quat(geo.quat);
            let (tu, tv, nrm) = (rot[0], rot[1], rot[2]);
            let (sc, op, mu) = (geo.scale, geo.opacity, geo.mean);
            let b = dot(nrm, d);
            let (back, dark) = match (b > 0.0).then(|| tracer.back_face(h.slot)).flatten() {
                Some(dark) => (true, dark),
                None => (false, false),
            };
            let sign = if back { -1.0 } else { 1.0 };
            // A dark back face's payload is zero: it only occludes.
            let n_eff = nrm.map(|x| sign * x);
            let wv = [mu[0] - o[0], mu[1] - o[1], mu[2] - o[2]];
            let a = dot(nrm, wv);
            let t = a / b;
            let q = [o[0] + t * d[0] - mu[0], o[1] + t * d[1] - mu[1], o[2] + t * d[2] - mu[2]];
            let u = dot(tu, q) / sc[0];
            let v = dot(tv, q) / sc[1];
            let gauss = (-0.5 * (u * u + v * v)).exp();
            let raw = op * gauss;

            // ∂L/∂α_j from every payload, and the direct payload gradients.
            let mut v_alpha = -g.v_transmittance * t_final * inv;
            v_alpha += g.v_depth * (trans * h.t - s_depth * inv);
            s_depth += w * h.t;
            for a in 0..3 {
                v_alpha += g.v_normal[a] * (trans * n_eff[a] - s_norm[a] * inv);
                s_norm[a] += w * n_eff[a];
            }
            let rec_stride = self.stride;
            let rec = buf.record(i, rec_stride);
            if dark {
                // Zero payload: only the occlusion term Σ_{k>j} T_k α_k x_k / (1 − α_j) is left.
                if use_features {
                    for c in 0..ch {
                        let vf = if v_fo.is_empty() { 0.0 } else { v_fo[c] };
                        v_alpha -= vf * sfeat[c] * inv;
                    }
                } else {
                    for c in 0..3 {
                        v_alpha -= g.v_radiance[c] * s_rad[c] * inv;
                    }
                }
            } else if use_features {
                let f = &self.fdata[i * ch..(i + 1) * ch];
                for c in 0..ch {
                    let vf = if v_fo.is_empty() { 0.0 } else { v_fo[c] };
                    v_alpha += vf * (trans * f[c] - sfeat[c] * inv);
                    sfeat[c] += w * f[c];
                    rec[self.o_feat + c] += vf * w;
                }
            } else {
                let craw = if recorded { rh.colour } else { sh_colour(&surfels.sh[i], &basis, self.ncoef) };
                let linear = tracer.settings.linear_radiance;
                let mut v_c = [0.0f32; 3];
                for c in 0..3 {
                    let clamped = craw[c].max(0.0);
                    let (col, dcol) = if linear { decode_with_derivative(clamped) } else { (clamped, 1.0) };
                    v_alpha += g.v_radiance[c] * (trans * col - s_rad[c] * inv);
                    s_rad[c] += w * col;
                    if craw[c] > 0.0 {
                        v_c[c] = g.v_radiance[c] * w * dcol;
                    }
                }
                for k in 0..self.ncoef {
                    for c in 0..3 {
                        rec[O_SH + 3 * k + c] += v_c[c] * basis[k];
                    }
                }
                if self.want_rays {
                    let coeffs = &surfels.sh[i];
                    for k in 0..self.ncoef {
                        v_basis[k] += coeffs[k][0] * v_c[0] + coeffs[k][1] * v_c[1] + coeffs[k][2] * v_c[2];
                    }
                }
            }

            // α = min(0.99, o·G): the clamp blocks the gradient.
            let v_raw = if raw < ALPHA_MAX { v_alpha } else { 0.0 };
            let v_op = v_raw * gauss;
            let v_rho = -0.5 * gauss * op * v_raw;
            let (v_u, v_v) = (2.0 * u * v_rho, 2.0 * v * v_rho);
            let v_tu = q.map(|x| v_u * x / sc[0]);
            let v_tv = q.map(|x| v_v * x / sc[1]);
            let v_q: [f32; 3] = std::array::from_fn(|k| v_u * tu[k] / sc[0] + v_v * tv[k] / sc[1]);
            let v_logs = [-v_u * u, -v_v * v];
            // p = o + t d − μ
            let v_t = g.v_depth * w + dot(v_q, d);
            // t = a / b, a = n·(μ − o), b = n·d
            let v_a = v_t / b;
            let v_b = -v_t * t / b;
            let v_n: [f32; 3] = std::array::from_fn(|k| v_a * wv[k] + v_b * d[k] + sign * g.v_normal[k] * w);
            for k in 0..3 {
                v_o[k] += v_q[k] - v_a * nrm[k];
                v_d[k] += t * v_q[k] + v_b * nrm[k];
            }
            let v_mu: [f32; 3] = std::array::from_fn(|k| -v_q[k] + v_a * nrm[k]);
            let v_quat = rotation_from_quat_backward(geo.quat, [v_tu, v_tv, v_n]);
            for k in 0..3 {
                rec[O_MEAN + k] += v_mu[k];
            }
            rec[O_SCALE] += v_logs[0];
            rec[O_SCALE + 1] += v_logs[1];
            for k in 0..4 {
                rec[O_QUAT + k] += v_quat[k];
            }
            rec[O_OPACITY] += v_op * op * (1.0 - op);
        }
        // SH colours depend on d̂ = d/|d|: ∂/∂d = (I − d̂ d̂ᵀ) ∂/∂d̂ / |d|.
        if self.ncoef > 1 && self.want_rays {
            let jac = sh::basis_jacobian(dh);
            let mut v_dh = [0.0f32; 3];
            for k in 1..self.ncoef {
                for a in 0..3 {
                    v_dh[a] += v_basis[k] * jac[k][a];
                }
            }
            let dd = dot(v_dh, dh);
            for a in 0..3 {
                v_d[a] += (v_dh[a] - dd * dh[a]) / dlen;
            }
        }
        buf.hits = cast;
        buf.feat_scratch = sfeat;
        Ray { origin: v_o, dir: v_d, ..Default::default() }
    }
}
