//! Backward rasterisation, exact for the order the forward pass used.
//!
//! Per pixel the forward's blended hits in blend order with their T_before are replayed from
//! its record (`render_recorded`) or listed by re-running its window (`composite_two_pixels`);
//! the list is then walked back to front, 16 hits at a time (SIMD
//! across hits: each hit's terms are gathered from its candidate, the suffix sums below are
//! in-register scans, and the 16 gradient rows are written through a transpose). With
//! every output written as O = Σ_j w_j q_j + T_n b (w_j = α_j T_j), ∂O/∂α_j = T_j q_j −
//! (Σ_{k>j} w_k q_k + T_n b)/(1 − α_j). All outputs share that form with the combined
//! q_j = v_C·c_j + v_F·f_j + v_A' + v_D·z_j + v_N·n_j + v_dist·g_j, where
//! v_D = v_depth/A and v_A' = v_alpha − v_depth·D/A² (depth = D/A), and for the distortion
//! Σ_{i<j} w_i w_j (m_i − m_j)²: g_j = ∂/∂w_j = m_j² A − 2 m_j M1 + M2 (totals over the
//! pixel) and ∂/∂m_j = 2 w_j (m_j A − M1). Then α = o·G (no gradient when clamped at 0.99),
//! G = e^{−ρ/2}, and either ρ₃, z through (u, v) = h.xy/h.z, h = k × l, k = x·Tw − Tu,
//! l = y·Tw − Tv, or ρ₂ = 2|μ₂D − pixel|² with z = Tw.z.
//!
//! Parallel decomposition: rayon over rows of tiles. Each (tile, surfel) pair owns one
//! gradient row (tile-major, so a tile writes a contiguous slice, no atomics); rows are then
//! summed per surfel (rayon over surfels, via `sorted_of_gen`) and pushed through the
//! projection backward.

use super::forward::{
    PK_MEAN, PK_OP, PK_TU, PK_TV, PK_TW, TileData, composite_two_pixels, load16, splat_alpha, splat_cross, splat_finish,
};
use super::lanes;
use super::project::{ProjGrad, SurfelGradSlots, project_backward_one};
use super::tiles::{self, split_by_offsets};
use super::{BackwardOutput, Features, ForwardState, MAX_FEATURES, NOT_RECORDED, RasterSettings, RenderGrads, TILE};
use crate::camera::Camera;
use crate::surfels::{SurfelGrads, Surfels};
use rayon::prelude::*;
use wide::f32x16;

const ROW_TU: usize = 0;
const ROW_TV: usize = 3;
const ROW_TW: usize = 6;
const ROW_MEAN2D: usize = 9;
const ROW_OPACITY: usize = 11;
const ROW_COLOUR: usize = 12;
const ROW_NORMAL: usize = 15;
/// Columns every row has; then, with `RasterSettings::abs_centre_gradient`, two columns of
/// Σ over pixels of |that pixel's ∂L/∂(centre)| per axis (pixel units, AbsGS's statistic);
/// then the feature channels.
const ROW_FIXED: usize = 18;
const ROW_ABS_MEAN2D: usize = 18;
const ROW_MAX_FIXED: usize = 20;

/// Column of the first feature channel.
fn feature_column(s: &RasterSettings) -> usize {
    if s.abs_centre_gradient { ROW_MAX_FIXED } else { ROW_FIXED }
}

/// Backward pass: adds ∂L/∂(parameters) into `v_surfels` (means, quats, log_scales,
/// opacity_logits, sh) and ∂L/∂features into `v_features` (N × channels).
#[allow(clippy::too_many_arguments)]
pub fn render_backward(
    surfels: &Surfels,
    camera: &Camera,
    settings: &RasterSettings,
    features: Option<Features>,
    state: &ForwardState,
    grads: &RenderGrads,
    v_surfels: &mut SurfelGrads,
    v_features: Option<&mut [f32]>,
) -> BackwardOutput {
    let n = surfels.len();
    assert_eq!(v_surfels.len(), n, "gradient buffer must have one entry per surfel");
    let nch = features.map_or(0, |f| f.channels);
    if let Some(f) = features {
        assert!(f.channels <= MAX_FEATURES);
        assert_eq!(f.data.len(), n * nch);
    }
    let bins = &state.tiles;
    let feat0 = feature_column(settings);
    let stride = feat0 + nch;
    let npairs = bins.ids.len();
    let mut rows = vec![0.0f32; npairs * stride];
    if state.width > 0 && state.height > 0 {
        let row_offsets: Vec<u32> =
            (0..=bins.tiles_y).map(|ty| bins.offsets[(ty * bins.tiles_x) as usize] * stride as u32).collect();
        // Largest rows first (see `rows_largest_first`); nothing to count.
        tiles::rows_largest_first(
            split_by_offsets(&mut rows, &row_offsets),
            &bins.row_pairs(),
            || (TileData::default(), [PixelHits::default(), PixelHits::default()]),
            |(td, hits), ty, chunk| {
                backward_tile_row(state, camera, settings, features, grads, ty as u32, chunk, stride, td, hits);
                (0, 0)
            },
        );
    }

    // Sum the pair rows per surfel, then the projection backward.
    let campos = camera.position();
    let proj = &state.proj;
    let mut v_mean2d = vec![[0.0f32; 2]; n];
    let mut v_mean2d_abs = vec![[0.0f32; 2]; n];
    (
        v_surfels.means.par_iter_mut(),
        v_surfels.log_scales.par_iter_mut(),
        v_surfels.quats.par_iter_mut(),
        v_surfels.opacity_logits.par_iter_mut(),
        v_surfels.sh.par_iter_mut(),
        v_mean2d.par_iter_mut(),
        v_mean2d_abs.par_iter_mut(),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(i, (vm, vs, vq, vo, vsh, vm2, vabs))| {
            if bins.pair_offsets[i] == bins.pair_offsets[i + 1] {
                return;
            }
            let mut acc = [0.0f32; ROW_MAX_FIXED];
            row_sum(&rows, bins, i, stride, &mut acc[..feat0]);
            let g = ProjGrad {
                v_tu: [acc[ROW_TU], acc[ROW_TU + 1], acc[ROW_TU + 2]],
                v_tv: [acc[ROW_TV], acc[ROW_TV + 1], acc[ROW_TV + 2]],
                v_tw: [acc[ROW_TW], acc[ROW_TW + 1], acc[ROW_TW + 2]],
                v_mean2d: [acc[ROW_MEAN2D], acc[ROW_MEAN2D + 1]],
                v_opacity: acc[ROW_OPACITY],
                v_colour: [acc[ROW_COLOUR], acc[ROW_COLOUR + 1], acc[ROW_COLOUR + 2]],
                v_normal: [acc[ROW_NORMAL], acc[ROW_NORMAL + 1], acc[ROW_NORMAL + 2]],
            };
            let slots = SurfelGradSlots { means: vm, log_scales: vs, quats: vq, opacity_logit: vo, sh: vsh };
            *vm2 = project_backward_one(surfels, i, camera, campos, proj, &g, slots);
            // Pixel units → the NDC-like units of v_mean2d (× W/2, H/2); zero when not computed.
            *vabs =
                [acc[ROW_ABS_MEAN2D] * 0.5 * camera.width as f32, acc[ROW_ABS_MEAN2D + 1] * 0.5 * camera.height as f32];
        });
    if let Some(vf) = v_features
        && nch > 0
    {
        assert_eq!(vf.len(), n * nch);
        vf.par_chunks_mut(nch).enumerate().for_each(|(i, out)| {
            let mut acc = [0.0f32; ROW_MAX_FIXED + MAX_FEATURES];
            row_sum(&rows, bins, i, stride, &mut acc[..stride]);
            for ch in 0..nch {
                out[ch] += acc[feat0 + ch];
            }
        });
    }
    BackwardOutput { v_mean2d, v_mean2d_abs }
}

/// Sum surfel i's (tile, surfel) rows over their first `out.len()` columns into `out`.
fn row_sum(rows: &[f32], bins: &super::tiles::TileBins, i: usize, stride: usize, out: &mut [f32]) {
    let m = out.len();
    // The rows sit wherever their tiles' depth sorts put them, and each surfel's projection
    // backward is long enough that the core never reaches the next surfel's loads early: ask
    // for the rows of the surfel two ahead now, so their cache misses overlap this work
    // (measured: the training backward −15 %, BENCHMARKS.md session 16).
    #[cfg(target_arch = "x86_64")]
    if i + 3 < bins.pair_offsets.len() {
        use std::arch::x86_64::{_MM_HINT_T0, _mm_prefetch};
        for g in bins.pair_offsets[i + 2]..bins.pair_offsets[i + 3] {
            let at = bins.sorted_of_gen[g as usize] as usize * stride;
            for line in (0..m).step_by(16) {
                // SAFETY: prefetching is a hint; the address is inside `rows`.
                unsafe { _mm_prefetch::<_MM_HINT_T0>(rows.as_ptr().add(at + line) as *const i8) };
            }
        }
    }
    for g in bins.pair_offsets[i]..bins.pair_offsets[i + 1] {
        let p = bins.sorted_of_gen[g as usize] as usize;
        for (o, r) in out.iter_mut().zip(&rows[p * stride..p * stride + m]) {
            *o += *r;
        }
    }
}

#[inline(always)]
fn get3(v: &[[f32; 3]], i: usize) -> [f32; 3] {
    if v.is_empty() { [0.0; 3] } else { v[i] }
}
#[inline(always)]
fn get1(v: &[f32], i: usize) -> f32 {
    if v.is_empty() { 0.0 } else { v[i] }
}

/// One pixel's blended hits in blend order, as a structure of arrays padded to a multiple of
/// 16 (padding: α = T = 0, z = 1, so it carries no weight and no division by zero).
#[derive(Default)]
struct PixelHits {
    li: Vec<u32>,
    z: Vec<f32>,
    alpha: Vec<f32>,
    t: Vec<f32>,
    len: usize,
}

impl PixelHits {
    /// Room for every candidate of a tile of `n` (a pixel blends each at most once).
    fn reserve_tile(&mut self, n: usize) {
        let cap = n.div_ceil(16) * 16 + 16;
        if self.li.len() < cap {
            self.li.resize(cap, 0);
            self.z.resize(cap, 1.0);
            self.alpha.resize(cap, 0.0);
            self.t.resize(cap, 0.0);
        }
    }
    #[inline(always)]
    fn push(&mut self, li: usize, z: f32, alpha: f32, t: f32) {
        let j = self.len;
        self.li[j] = li as u32;
        self.z[j] = z;
        self.alpha[j] = alpha;
        self.t[j] = t;
        self.len = j + 1;
    }
    /// Pad the last group of 16.
    fn pad(&mut self) {
        for j in self.len..self.len.div_ceil(16) * 16 {
            self.li[j] = 0;
            self.z[j] = 1.0;
            self.alpha[j] = 0.0;
            self.t[j] = 0.0;
        }
    }
}

/// Per-pixel output gradients (zero for outputs that are off).
struct PixelGrads {
    colour: [f32; 3],
    alpha: f32,
    depth: f32,
    median: f32,
    normal: [f32; 3],
    distortion: f32,
    features: [f32; MAX_FEATURES],
    any_feature: bool,
}

impl PixelGrads {
    fn is_zero(&self) -> bool {
        self.colour == [0.0; 3]
            && self.alpha == 0.0
            && self.depth == 0.0
            && self.median == 0.0
            && self.normal == [0.0; 3]
            && self.distortion == 0.0
            && !self.any_feature
    }
}

#[allow(clippy::too_many_arguments)]
fn backward_tile_row(
    state: &ForwardState,
    camera: &Camera,
    s: &RasterSettings,
    features: Option<Features>,
    grads: &RenderGrads,
    ty: u32,
    chunk: &mut [f32],
    stride: usize,
    td: &mut TileData,
    hits: &mut [PixelHits; 2],
) {
    let bins = &state.tiles;
    let proj = &state.proj;
    let (w, h) = (camera.width, camera.height);
    let k = s.k();
    let nch = features.map_or(0, |f| f.channels);
    let o = s.outputs;
    let row_start = bins.offsets[(ty * bins.tiles_x) as usize];
    let y0 = ty * TILE;
    let y1 = (y0 + TILE).min(h);
    let has_f = nch > 0 && !grads.v_features.is_empty();
    let row_record = state.record.as_ref().map(|r| &r.rows[ty as usize]);
    for tx in 0..bins.tiles_x {
        let t = (ty * bins.tiles_x + tx) as usize;
        let (p0, p1) = (bins.offsets[t], bins.offsets[t + 1]);
        if p0 == p1 {
            continue;
        }
        let ids = &bins.ids[p0 as usize..p1 as usize];
        let tile_rows = &mut chunk[(p0 - row_start) as usize * stride..(p1 - row_start) as usize * stride];
        td.load(proj, ids, &bins.quarter_masks[p0 as usize..p1 as usize], (tx * TILE, ty * TILE));
        td.load_shading(proj);
        hits[0].reserve_tile(td.n);
        hits[1].reserve_tile(td.n);
        let x0 = tx * TILE;
        let x1 = (x0 + TILE).min(w);
        let pixel_grads = |x: u32, y: u32| {
            let pix = (y * w + x) as usize;
            let mut pg = PixelGrads {
                colour: if o.colour { get3(&grads.v_colour, pix) } else { [0.0; 3] },
                alpha: get1(&grads.v_alpha, pix),
                depth: if o.depth { get1(&grads.v_depth, pix) } else { 0.0 },
                median: if o.median_depth { get1(&grads.v_median_depth, pix) } else { 0.0 },
                normal: if o.normal { get3(&grads.v_normal, pix) } else { [0.0; 3] },
                distortion: if o.distortion { get1(&grads.v_distortion, pix) } else { 0.0 },
                features: [0.0; MAX_FEATURES],
                any_feature: false,
            };
            if has_f {
                pg.features[..nch].copy_from_slice(&grads.v_features[pix * nch..(pix + 1) * nch]);
                pg.any_feature = pg.features[..nch].iter().any(|&g| g != 0.0);
            }
            (!pg.is_zero()).then_some(pg)
        };
        for y in y0..y1 {
            // Pixels in pairs, as the forward composites them (`composite_two_pixels`).
            for x in (x0..x1).step_by(2) {
                let mut todo: [Option<(u32, PixelGrads)>; 2] = [None, None];
                let mut count = 0;
                for xx in x..(x + 2).min(x1) {
                    let Some(pg) = pixel_grads(xx, y) else { continue };
                    // A recorded pixel replays the forward's hits; the others re-run the window.
                    let local = ((y - y0) * w + xx) as usize;
                    match row_record.map(|r| (r, r.spans[local])).filter(|&(_, span)| span != NOT_RECORDED) {
                        Some((row, (a, b))) => {
                            if a < b {
                                let h = &mut hits[0];
                                h.len = 0;
                                for rh in &row.hits[a as usize..b as usize] {
                                    h.push(rh.li as usize, rh.z, rh.alpha, rh.t);
                                }
                                h.pad();
                                let (px, py) = (xx as f32 + 0.5, y as f32 + 0.5);
                                pixel_backward(td, s, features, h, row.t_final[local], px, py, &pg, tile_rows, stride);
                            }
                        }
                        None => {
                            todo[count] = Some((xx, pg));
                            count += 1;
                        }
                    }
                }
                if count == 0 {
                    continue;
                }
                let centre =
                    |i: usize| todo[i].as_ref().map_or((0.0, 0.0), |(xx, _)| (*xx as f32 + 0.5, y as f32 + 0.5));
                let pf = [centre(0), centre(1)];
                let [ha, hb] = hits;
                ha.len = 0;
                hb.len = 0;
                let [(ta, _), (tb, _)] = composite_two_pixels(
                    td,
                    pf,
                    count == 2,
                    s,
                    k,
                    #[inline(always)]
                    |li, z, alpha, t| ha.push(li, z, alpha, t),
                    #[inline(always)]
                    |li, z, alpha, t| hb.push(li, z, alpha, t),
                );
                for (i, (h, tf)) in [(ha, ta), (hb, tb)].into_iter().enumerate().take(count) {
                    if h.len == 0 {
                        continue;
                    }
                    h.pad();
                    let pg = &todo[i].as_ref().unwrap().1;
                    pixel_backward(td, s, features, h, tf, pf[i].0, pf[i].1, pg, tile_rows, stride);
                }
            }
        }
    }
}

/// The gradient rows of one pixel's blended hits, 16 hits at a time, back to front. With
/// w_j = α_j T_j and every output O = Σ_j w_j q_j + T_n b: ∂O/∂α_j = T_j q_j − S_j/(1 − α_j),
/// S_j = Σ_{k>j} w_k q_k + T_n b (a suffix sum: within a group across lanes, between groups
/// a running total). The hit's (u, v), G and branch are recomputed from its candidate with the
/// forward's own lane arithmetic (`splat_cross`, `splat_finish`), so they are the forward's values bit for bit.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn pixel_backward(
    td: &TileData,
    s: &RasterSettings,
    features: Option<Features>,
    hits: &PixelHits,
    tf: f32,
    pxf: f32,
    pyf: f32,
    pg: &PixelGrads,
    tile_rows: &mut [f32],
    stride: usize,
) {
    let o = s.outputs;
    let nch = features.map_or(0, |f| f.channels);
    let n = hits.len;
    let groups = n.div_ceil(16);
    let splat = f32x16::splat;
    let zero = f32x16::ZERO;
    let (near, far) = (s.near, s.far);
    let m_scale = splat(far / (far - near));
    let norm = |z: f32x16| m_scale * (f32x16::ONE - splat(near) / z);

    // Totals over the pixel: A = Σw, D = Σwz, M1 = Σwm, M2 = Σwm²; the median hit.
    let (mut a_tot, mut d_tot, mut m1, mut m2) = (zero, zero, zero, zero);
    let mut above_half = 0usize;
    for gi in 0..groups {
        let j = gi * 16;
        let (z, t) = (load16(&hits.z, j), load16(&hits.t, j));
        let wgt = load16(&hits.alpha, j) * t;
        a_tot += wgt;
        d_tot += wgt * z;
        if pg.distortion != 0.0 {
            let m = norm(z);
            m1 += wgt * m;
            m2 += wgt * m * m;
        }
        above_half += t.simd_gt(splat(0.5)).to_bitmask().count_ones() as usize;
    }
    let (a_tot, d_tot, m1, m2) = (a_tot.reduce_add(), d_tot.reduce_add(), m1.reduce_add(), m2.reduce_add());
    // T is non-increasing along the blend order, so the hits with T > 0.5 come first.
    let median_j = above_half.wrapping_sub(1);
    let (v_dd, v_a) =
        if a_tot > 0.0 { (pg.depth / a_tot, pg.alpha - pg.depth * d_tot / (a_tot * a_tot)) } else { (0.0, pg.alpha) };
    let dm_scale = far / (far - near) * near;

    let mut carry =
        tf * (pg.colour[0] * s.background[0] + pg.colour[1] * s.background[1] + pg.colour[2] * s.background[2]);
    for gi in (0..groups).rev() {
        let j = gi * 16;
        let live = (n - j).min(16);
        let li: [u32; 16] = hits.li[j..j + 16].try_into().unwrap();
        let tile_n = td.n;
        // Record starts 16·li (all < 16·(n − 1) + 1); lane f gathers from the records' lane f on.
        let at_record = lanes::Gather16::new(li.map(|i| 16 * i), live, 16 * tile_n.max(1) - 15);
        let (z, alpha, t) = (load16(&hits.z, j), load16(&hits.alpha, j), load16(&hits.t, j));
        let wgt = alpha * t;
        let mut q = splat(v_a) + splat(v_dd) * z;
        let mut v_z = wgt * splat(v_dd);
        let mut cols = [zero; 16];
        let mut extra = [zero; ROW_MAX_FIXED - 16 + MAX_FEATURES];
        let feat0 = feature_column(s);
        let at3 = |ch: u32| lanes::Gather16::new(li.map(|i| 3 * i + ch), live, 3 * tile_n);
        if o.colour {
            for ch in 0..3 {
                let c = at3(ch as u32).from(td.colour.as_flattened());
                q += splat(pg.colour[ch]) * c;
                cols[ROW_COLOUR + ch] = wgt * splat(pg.colour[ch]);
            }
        }
        if o.normal {
            for ch in 0..3 {
                let nv = at3(ch as u32).from(td.normal.as_flattened());
                q += splat(pg.normal[ch]) * nv;
                let g = wgt * splat(pg.normal[ch]);
                if ROW_NORMAL + ch < 16 {
                    cols[ROW_NORMAL + ch] = g;
                } else {
                    extra[ROW_NORMAL + ch - 16] = g;
                }
            }
        }
        if pg.distortion != 0.0 {
            let m = norm(z);
            q += splat(pg.distortion) * (m * m * splat(a_tot) - splat(2.0) * m * splat(m1) + splat(m2));
            let dm_dz = splat(dm_scale) / (z * z);
            v_z += splat(pg.distortion * 2.0) * wgt * (m * splat(a_tot) - splat(m1)) * dm_dz;
        }
        if pg.any_feature {
            let fe = features.unwrap();
            let ids: [u32; 16] = std::array::from_fn(|l| if l < live { td.ids[li[l] as usize] } else { 0 });
            // Row starts id·nch (all < (N − 1)·nch + 1); channel ch gathers from data[ch..].
            let rows_at = lanes::Gather16::new(ids.map(|i| i * nch as u32), live, fe.data.len() + 1 - nch);
            for ch in 0..nch {
                let f = rows_at.from(&fe.data[ch..]);
                q += splat(pg.features[ch]) * f;
                extra[feat0 - 16 + ch] = wgt * splat(pg.features[ch]);
            }
        }
        if median_j >= j && median_j < j + 16 {
            let mut vz = v_z.to_array();
            vz[median_j - j] += pg.median;
            v_z = f32x16::new(vz);
        }
        // ∂O/∂α_j; padding lanes (w = 0) add nothing to the running total and are not written.
        let wq = wgt * q;
        let suffix = splat(carry) + lanes::suffix_sum_exclusive(wq);
        carry += wq.reduce_add();
        let v_alpha = t * q - suffix / (f32x16::ONE - alpha);

        // α = o·G → ρ → (u, v) or μ₂D, and z.
        let records = td.records.as_flattened();
        let gat = |lane: usize| at_record.from(&records[lane..]);
        let tu = [gat(PK_TU), gat(PK_TU + 1), gat(PK_TU + 2)];
        let tv = [gat(PK_TV), gat(PK_TV + 1), gat(PK_TV + 2)];
        let tw = [gat(PK_TW), gat(PK_TW + 1), gat(PK_TW + 2)];
        let mean2d = [gat(PK_MEAN), gat(PK_MEAN + 1)];
        let op = gat(PK_OP);
        let e = splat_finish(
            splat_cross(f32x16::splat(pxf), f32x16::splat(pyf), tu, tv, tw, mean2d, s.filter_inv_square),
            tw,
        );
        let (g, _, clamped) = splat_alpha(e.rho, op);
        cols[ROW_OPACITY] = clamped.select(zero, g * v_alpha);
        let v_rho = clamped.select(zero, splat(-0.5) * g * op * v_alpha);
        // Ray–plane branch.
        let (u, v) = (e.u, e.v);
        let v_u = splat(2.0) * u * v_rho + tw[0] * v_z;
        let v_v = splat(2.0) * v * v_rho + tw[1] * v_z;
        let inv_hz = f32x16::ONE / e.hz;
        let v_h = [v_u * inv_hz, v_v * inv_hz, -(v_u * u + v_v * v) * inv_hz];
        let (kk, ll) = (e.k, e.l);
        let v_k = cross(ll, v_h);
        let v_l = cross(v_h, kk);
        let (px, py) = (splat(pxf), splat(pyf));
        let is3d = e.is3d;
        let tw_z = [u * v_z, v * v_z, v_z];
        for a in 0..3 {
            cols[ROW_TU + a] = is3d.select(-v_k[a], zero);
            cols[ROW_TV + a] = is3d.select(-v_l[a], zero);
            cols[ROW_TW + a] = is3d.select(px * v_k[a] + py * v_l[a] + tw_z[a], zero);
        }
        // Screen-space filter branch.
        let two_f = splat(2.0 * s.filter_inv_square);
        cols[ROW_MEAN2D] = is3d.select(zero, two_f * (mean2d[0] - px) * v_rho);
        cols[ROW_MEAN2D + 1] = is3d.select(zero, two_f * (mean2d[1] - py) * v_rho);
        cols[ROW_TW + 2] = is3d.select(cols[ROW_TW + 2], v_z);
        // This pixel's ∂L/∂(centre, pixels): Tu.z = x_pix · Tw.z (one branch's term is 0).
        if s.abs_centre_gradient {
            for a in 0..2 {
                let v_tz = cols[if a == 0 { ROW_TU + 2 } else { ROW_TV + 2 }];
                extra[ROW_ABS_MEAN2D + a - 16] = (v_tz * tw[2] + cols[ROW_MEAN2D + a]).abs();
            }
        }

        lanes::add_columns(tile_rows, stride, 0, &li, live, cols, 16);
        let n_extra = stride - 16;
        if n_extra <= 16 {
            lanes::add_columns(tile_rows, stride, 16, &li, live, extra[..16].try_into().unwrap(), n_extra);
        } else {
            lanes::add_columns(tile_rows, stride, 16, &li, live, extra[..16].try_into().unwrap(), 16);
            let mut rest = [zero; 16];
            rest[..n_extra - 16].copy_from_slice(&extra[16..n_extra]);
            lanes::add_columns(tile_rows, stride, 32, &li, live, rest, n_extra - 16);
        }
    }
}

#[inline(always)]
fn cross(a: [f32x16; 3], b: [f32x16; 3]) -> [f32x16; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}
