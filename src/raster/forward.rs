//! Forward rasterisation: per-pixel compositing in each ray's own hit-depth order.
//!
//! Per pixel (x, y) and tile candidate (rows Tu, Tv, Tw of the splat-to-pixel transform):
//! k = x·Tw − Tu, l = y·Tw − Tv, h = k × l, (u, v) = (h.x, h.y)/h.z, ρ₃ = u² + v²,
//! ρ₂ = f|μ₂D − pixel|² (the 2DGS low-pass fallback; f = `filter_inv_square`, 2DGS: 2). If ρ₃ ≤ ρ₂ the hit is
//! the ray–plane one, ρ = ρ₃, z = Tw·(u, v, 1); else ρ = ρ₂, z = Tw.z (centre depth).
//! Skipped: h.z = 0 (ray parallel to the plane), z < near, α = min(0.99, o·e^{−ρ/2}) < α_min.
//!
//! Ordering (HDGS): candidates arrive in the tile's centre-depth order; each hit goes into a
//! window of K entries sorted by z. When a hit arrives and the window is full, the window's
//! nearest entry is blended first; at the end the window is flushed nearest-first. K = 1 is
//! exactly the plain 2DGS order. Blending: w = α T, T ← T(1 − α), stopping before a blend
//! that would take T below `transmittance_min` (that hit is not blended), and, for display
//! frames, right after a blend that took T below `display_stop` (off by default: the pixel
//! then misses at most that T times the colour behind it).
//!
//! Outputs: colour Σ w c + T·bg, alpha Σ w (= 1 − T, summed to avoid cancellation), depth Σ w z / α, median depth (z of the last
//! blend made while T > 0.5), normal Σ w n, distortion Σ_{i<j} w_i w_j (m_i − m_j)² (2DGS) in
//! closed form A·M2 − M1² (A, M1, M2 the final sums of w, w d, w d², d = m − m of the first
//! blend: the shift keeps the difference from cancelling when the hits' m agree),
//! features Σ w f, and (forward only) the surface-aware depth of GauS-SLAM.
//!
//! Parallel decomposition: rayon over rows of tiles; inside a tile, pixel by pixel over the
//! list of the pixel's tile quarter (8 × 8: the tile's candidates whose pixel box and footprint
//! (the bin's quarter mask) reach it, in tile order, so the hits and their order are the tile list's), 16 candidates at a time
//! (f32x16, one structure of arrays per group, transposed from per-surfel packed records). A
//! division-free test of ρ against the cut-off skips groups that cannot hit before the divide.
//! The window is per hit: scalars for K = 1, for K ≤ 16 three AVX-512 registers (branchless
//! insert and pop; without AVX-512, three AVX2 registers for K ≤ 8), otherwise a ring buffer.
//! With AVX-512 pixels go in pairs (two independent window chains); with AVX2 alone one at a
//! time (a pair's state spills out of 16 registers). The blend is scalar, inlined into the window loop:
//! that loop waits on the window's compare → permute chain, and the blend's arithmetic fills
//! those cycles (a separate 16-hit SIMD blend pass measured no faster). Nothing per pixel is saved: the
//! backward pass re-runs `composite_pixel`. Narrow unrecorded frames with the default K (relit
//! and display frames) go sixteen pixels at a time instead ([`block`]: SIMD over a 4 × 4 block,
//! one candidate at a time, bit-identical).

use super::project::{self, Projected};
use super::tiles::{self, TileBins};
use super::{
    Features, ForwardState, MAX_FEATURES, MAX_WINDOW, NOT_RECORDED, PixelHitRecord, RasterSettings, RecordedHit,
    RenderOutput, RowHits, TILE,
};
use crate::camera::Camera;
use crate::surfels::Surfels;
use rayon::prelude::*;
use std::cell::{Ref, RefCell};
use wide::{f32x8, f32x16};

mod block;

/// Lanes of a packed candidate record (`Projected::packed`).
pub(crate) const PK_TU: usize = 0;
pub(crate) const PK_TV: usize = 3;
pub(crate) const PK_TW: usize = 6;
pub(crate) const PK_MEAN: usize = 9;
pub(crate) const PK_OP: usize = 11;
pub(crate) const PK_RHO: usize = 12;
/// What `eval16` reads: the lanes before the box.
const PK_FIELDS: usize = 13;
/// The pixel box (`Projected::pixels`): x0 | x1 << 16 and y0 | y1 << 16 as bit patterns.
const PK_BOX_X: usize = 13;
const PK_BOX_Y: usize = 14;

/// A padding record: zero opacity and a −∞ ρ cut-off (never hit).
const PADDING: [f32; 16] = {
    let mut r = [0.0f32; 16];
    r[PK_RHO] = f32::NEG_INFINITY;
    r
};

/// Candidates 16 at a time, each group one vector per record lane (structure of arrays per
/// group: what `eval16` reads), the last group padded with never-hit records. Groups are
/// transposed on first use (`group`): on deep scenes a tile's pixels all stop (T < 1e-4) long
/// before the end of its list (random 100k scene at 800²: 18 % of the quarter lists' entries
/// are ever reached), so transposing whole lists up front was most of a tile's load.
#[derive(Default, Clone, Debug)]
pub(crate) struct Candidates {
    pub n: usize,
    /// Each entry's index in the tile list.
    pub slot: Vec<u32>,
    /// The groups transposed so far (interior mutability: compositing holds the tile shared,
    /// with its blend closures).
    groups: RefCell<Vec<[f32x16; PK_FIELDS]>>,
}

impl Candidates {
    /// Take the entries now in `slot`; their groups are transposed when first asked for.
    fn reset(&mut self) {
        self.n = self.slot.len();
        self.groups.get_mut().clear();
    }

    /// Group `g` (entries 16g .. 16g + 16), transposing it from `records` on first use.
    /// Groups are asked for in order from 0, so `g` is at most the count transposed.
    #[inline(always)]
    fn group(&self, g: usize, records: &[[f32; 16]]) -> Ref<'_, [f32x16; PK_FIELDS]> {
        if g >= self.groups.borrow().len() {
            debug_assert_eq!(g, self.groups.borrow().len(), "groups are asked for in order");
            self.transpose_next(records);
        }
        Ref::map(self.groups.borrow(), |groups| &groups[g])
    }

    #[inline(never)]
    fn transpose_next(&self, records: &[[f32; 16]]) {
        let mut groups = self.groups.borrow_mut();
        let start = groups.len() * 16;
        let chunk = &self.slot[start..(start + 16).min(self.n)];
        let rows: [f32x16; 16] =
            std::array::from_fn(|l| f32x16::new(chunk.get(l).map_or(PADDING, |&j| records[j as usize])));
        let cols = super::lanes::transpose(rows);
        groups.push(std::array::from_fn(|f| cols[f]));
    }
}

/// Side of a tile quarter in pixels.
pub(crate) const QUARTER: u32 = TILE / 2;

/// One tile's candidates: per candidate its packed record (`records`, what the backward
/// gathers from) and, per quarter of the tile (8 × 8 pixels: 0 top left, 1 top right, 2 bottom
/// left, 3 bottom right), the candidates whose pixel box (`Projected::pixels`) and footprint
/// (`TileBins::quarter_masks`) both reach it, in tile order. A pixel evaluates only its quarter's list: every other candidate has α < α_min
/// there, so the hits and their order are those of the whole list, at a fraction of the
/// evaluations when surfels are small (training).
#[derive(Default, Clone, Debug)]
pub(crate) struct TileData {
    pub n: usize,
    pub ids: Vec<u32>,
    pub records: Vec<[f32; 16]>,
    pub origin: (u32, u32),
    pub quarters: [Candidates; 4],
    /// Colour and normal per candidate (`load_shading`: the backward's; the forward blends
    /// per-surfel rows, `blend_rows`).
    pub colour: Vec<[f32; 3]>,
    pub normal: Vec<[f32; 3]>,
    /// What the forward blends per candidate (`load_blend_rows`, copied from the per-surfel
    /// `blend_rows`). The tile keeps its own copy: blending straight from the per-surfel rows
    /// (a gather per blend) cost training-like scenes 1 ms a frame (BENCHMARKS.md, session 25).
    pub blend_rows: Vec<f32x16>,
    /// The rows' first 8 lanes, instead of `blend_rows` when they hold everything blended
    /// (`NARROW` in [`PixelSums::blend`]).
    pub blend_rows8: Vec<f32x8>,
}

/// Lanes of a blend row: colour 0..3, normal 3..6, 1 at 6, features from 7.
const BLEND_ONE: usize = 6;
const BLEND_FEAT: usize = 7;
/// Feature channels that fit in a blend row; more are blended channel by channel.
const ROW_FEATURES: usize = 16 - BLEND_FEAT;
/// Feature channels that fit in the first 8 lanes (a narrow row).
const NARROW_FEATURES: usize = 8 - BLEND_FEAT;

impl TileData {
    /// Load the list `ids` of the tile whose first pixel is `origin`, with the quarters each
    /// candidate's footprint touches (`masks`, from `TileBins::quarter_masks`).
    pub fn load(&mut self, p: &Projected, ids: &[u32], masks: &[u8], origin: (u32, u32)) {
        debug_assert_eq!(ids.len(), masks.len());
        self.n = ids.len();
        self.origin = origin;
        self.ids.clear();
        self.ids.extend_from_slice(ids);
        self.records.clear();
        self.records.extend(ids.iter().map(|&i| p.packed[i as usize]));
        // Which quarters each candidate reaches (its footprint's quarters and its pixel box's:
        // the box decides where the bin did not compute the footprint), appended without
        // branches (the outcomes are unpredictable).
        let n = ids.len();
        let mut lens = [0usize; 4];
        for quarter in &mut self.quarters {
            quarter.slot.clear();
            quarter.slot.resize(n, 0);
        }
        let (ox, oy) = origin;
        let (mid_x, mid_y) = (ox + QUARTER, oy + QUARTER);
        let (end_x, end_y) = (ox + TILE - 1, oy + TILE - 1);
        // Boxes are stored in 16 bits: beyond that every candidate goes to every quarter.
        let huge = end_x > u16::MAX as u32 || end_y > u16::MAX as u32;
        for (j, (r, &mask)) in self.records.iter().zip(masks).enumerate() {
            let (xs, ys) = (r[PK_BOX_X].to_bits(), r[PK_BOX_Y].to_bits());
            let (bx0, bx1, by0, by1) = (xs & 0xffff, xs >> 16, ys & 0xffff, ys >> 16);
            let left = (bx0 < mid_x) & (bx1 >= ox);
            let right = (bx0 <= end_x) & (bx1 >= mid_x);
            let top = (by0 < mid_y) & (by1 >= oy);
            let bottom = (by0 <= end_y) & (by1 >= mid_y);
            for (q, inside) in [left & top, right & top, left & bottom, right & bottom].into_iter().enumerate() {
                self.quarters[q].slot[lens[q]] = j as u32;
                lens[q] += ((inside | huge) & (mask >> q & 1 != 0)) as usize;
            }
        }
        for (quarter, &len) in self.quarters.iter_mut().zip(&lens) {
            quarter.slot.truncate(len);
            quarter.reset();
        }
    }

    /// Gather the candidates' blend rows (after `load`; for the forward).
    pub fn load_blend_rows(&mut self, rows: &[f32x16]) {
        self.blend_rows.clear();
        self.blend_rows.extend(self.ids.iter().map(|&i| rows[i as usize]));
    }

    /// Gather the candidates' narrow blend rows (after `load`).
    pub fn load_blend_rows8(&mut self, rows: &[f32x8]) {
        self.blend_rows8.clear();
        self.blend_rows8.extend(self.ids.iter().map(|&i| rows[i as usize]));
    }

    /// Gather the candidates' colour and normal (after `load`; for the backward).
    pub fn load_shading(&mut self, p: &Projected) {
        self.colour.clear();
        if !p.colour.is_empty() {
            self.colour.extend(self.ids.iter().map(|&i| p.colour[i as usize]));
        }
        self.normal.clear();
        self.normal.extend(self.ids.iter().map(|&i| p.normal[i as usize]));
    }
}

/// What the forward blends per surfel, one 16-lane row each: colour, normal, 1 (for Σ w), then
/// up to `ROW_FEATURES` feature channels; a hit is blended with one 16-lane multiply-add.
/// Built once per surfel per render; a tile then copies one row per candidate instead of
/// gathering colour and normal and assembling the row (a large surfel sits in many tiles).
fn blend_rows(p: &Projected, features: Option<Features>) -> Vec<f32x16> {
    (0..p.normal.len()).into_par_iter().map(|id| f32x16::new(blend_row(p, features, id))).collect()
}

/// The rows' first 8 lanes (colour, normal, 1, at most one feature), for narrow renders.
fn blend_rows8(p: &Projected, features: Option<Features>) -> Vec<f32x8> {
    (0..p.normal.len()).into_par_iter().map(|id| f32x8::new(blend_row(p, features, id))).collect()
}

/// Surfel `id`'s blend row in L lanes: the features that fit are copied (the caller blends
/// the others channel by channel).
#[inline(always)]
fn blend_row<const L: usize>(p: &Projected, features: Option<Features>, id: usize) -> [f32; L] {
    let mut row = [0.0f32; L];
    if let Some(c) = p.colour.get(id) {
        row[..3].copy_from_slice(c);
    }
    row[3..6].copy_from_slice(&p.normal[id]);
    row[BLEND_ONE] = 1.0;
    if let Some(fe) = features
        && fe.channels <= L - BLEND_FEAT
    {
        let nch = fe.channels;
        row[BLEND_FEAT..BLEND_FEAT + nch].copy_from_slice(&fe.data[id * nch..(id + 1) * nch]);
    }
    row
}

/// Ring-buffer size of the window (a power of two ≥ MAX_WINDOW).
pub(crate) const RING: usize = 32;
/// The forward composites pixels one at a time, not in pairs, without AVX-512: with AVX2's 16
/// vector registers two pixels' windows and sums spill (relit spheres frame at 400²: 5–8 %
/// faster alone; with AVX-512's 32 registers the pair overlaps its two window chains).
const SINGLE: bool = cfg!(not(target_feature = "avx512f"));
const _: () = assert!(RING >= MAX_WINDOW && RING.is_power_of_two());

/// Depth and α of sixteen candidates evaluated at once (all the window needs; the backward
/// recomputes the rest of a blended hit from its candidate).
#[derive(Default)]
pub(crate) struct Lanes {
    pub z: [f32; 16],
    pub alpha: [f32; 16],
}

#[inline(always)]
pub(crate) fn load16(v: &[f32], j: usize) -> f32x16 {
    f32x16::new(v[j..j + 16].try_into().unwrap())
}

/// One pixel centre against 16 candidates (lane-wise): the ray–splat terms k, l, h.z, the
/// hit's (u, v), ρ and z, and which branch (ray–plane or screen-space filter) decided.
/// `eval16` (from the tile arrays) and the backward (from gathered candidates) both compute it
/// with `splat_finish(splat_cross(…))`, so their decisions and values agree bit for bit.
pub(crate) struct SplatEval {
    pub k: [f32x16; 3],
    pub l: [f32x16; 3],
    pub hz: f32x16,
    pub u: f32x16,
    pub v: f32x16,
    pub rho: f32x16,
    pub z: f32x16,
    /// All-ones lanes: the ray–plane branch (ρ₃ ≤ ρ₂).
    pub is3d: f32x16,
}

/// The division-free first half of a splat evaluation ([`splat_finish`] completes it): k, l,
/// h = k × l and the filter's ρ₂. Kept apart: the tile loop compiled to measurably slower code
/// when the group test below the divide was its only exit (BENCHMARKS.md, session 21).
pub(crate) struct SplatCross {
    k: [f32x16; 3],
    l: [f32x16; 3],
    h: [f32x16; 3],
    rho2: f32x16,
}

/// Pixel centres per lane: one pixel's splatted against sixteen candidates (`eval16`, the
/// backward), or sixteen pixels' against one candidate splatted (the pixel blocks of [`block`]).
#[inline(always)]
pub(crate) fn splat_cross(
    pxv: f32x16,
    pyv: f32x16,
    tu: [f32x16; 3],
    tv: [f32x16; 3],
    tw: [f32x16; 3],
    mean2d: [f32x16; 2],
    filter_inv_square: f32,
) -> SplatCross {
    let k = [pxv * tw[0] - tu[0], pxv * tw[1] - tu[1], pxv * tw[2] - tu[2]];
    let l = [pyv * tw[0] - tv[0], pyv * tw[1] - tv[1], pyv * tw[2] - tv[2]];
    let hx = k[1] * l[2] - k[2] * l[1];
    let hy = k[2] * l[0] - k[0] * l[2];
    let hz = k[0] * l[1] - k[1] * l[0];
    let dx = mean2d[0] - pxv;
    let dy = mean2d[1] - pyv;
    let rho2 = f32x16::splat(filter_inv_square) * (dx * dx + dy * dy);
    SplatCross { k, l, h: [hx, hy, hz], rho2 }
}

impl SplatCross {
    /// Lanes that may have ρ ≤ `rho_max` (a superset: ρ = min(ρ₃, ρ₂), and ρ₃ = |h_xy|²/h_z² is
    /// compared without the divide, whose rounding the cut-off's 10⁻³ margin covers).
    #[inline(always)]
    fn may_reach(&self, rho_max: f32x16) -> f32x16 {
        let [hx, hy, hz] = self.h;
        let near_plane = (hx * hx + hy * hy).simd_le(rho_max * (hz * hz));
        near_plane | self.rho2.simd_le(rho_max)
    }
}

/// The second half: (u, v), ρ, the branch and z. `eval16` and the backward both run
/// `splat_finish(splat_cross(…))`, so their decisions and values agree bit for bit.
#[inline(always)]
pub(crate) fn splat_finish(c: SplatCross, tw: [f32x16; 3]) -> SplatEval {
    let SplatCross { k, l, h: [hx, hy, hz], rho2 } = c;
    let inv = f32x16::ONE / hz;
    let u = hx * inv;
    let v = hy * inv;
    let rho3 = u * u + v * v;
    let is3d = rho3.simd_le(rho2);
    let rho = is3d.select(rho3, rho2);
    let z = is3d.select(u * tw[0] + v * tw[1] + tw[2], tw[2]);
    SplatEval { k, l, hz, u, v, rho, z, is3d }
}

/// e^x for x ≤ 0, inlined: `wide`'s `f32x16::exp` operation for operation (the same
/// range reduction, polynomial and 2^r), so a hit's value is bit for bit the same, without its
/// overflow, NaN and subnormal branches. `wide`'s is a call, 8–10 % of a relit frame's samples.
/// x is clamped at −87 so that 2^r stays a normal number: such lanes give α < 10⁻³⁷ either way,
/// never a hit (a hit needs ρ ≤ 2 ln(255·o) < 12, x > −6).
#[inline(always)]
pub(crate) fn exp_nonpositive(x: f32x16) -> f32x16 {
    let splat = f32x16::splat;
    let x = x.fast_max(splat(-87.0));
    let r = (x * f32x16::LOG2_E).round_ties_even();
    // ln 2 split in two (fdlibm's range reduction, as `wide`).
    let y = r.mul_neg_add(splat(0.693_359_375), x);
    let y = r.mul_neg_add(splat(-2.121_944_40e-4), y);
    let (c0, c1, c2) = (splat(1.0 / 2.0), splat(1.0 / 6.0), splat(1.0 / 24.0));
    let (c3, c4, c5) = (splat(1.0 / 120.0), splat(1.0 / 720.0), splat(1.0 / 5040.0));
    let y2 = y * y;
    let y4 = y2 * y2;
    let z = c3.mul_add(y, c2).mul_add(y2, c5.mul_add(y, c4).mul_add(y4, c1.mul_add(y, c0)));
    let z = z.mul_add(y * y, y);
    // 2^r from its bit pattern (r ∈ [−126, 0]: a normal exponent).
    let pow2 = f32_from_bits(f32_bits(r + splat(127.0 + 8_388_608.0)) << 23);
    (z + f32x16::ONE) * pow2
}

/// The lanes' bit patterns as integers.
#[inline(always)]
fn f32_bits(x: f32x16) -> wide::i32x16 {
    // SAFETY: f32x16 and i32x16 are both 64-byte vectors of 16 plain 32-bit lanes (same size
    // and alignment); every bit pattern is a valid value of either.
    unsafe { std::mem::transmute::<f32x16, wide::i32x16>(x) }
}

/// Integer lanes reinterpreted as f32 (the inverse of [`f32_bits`]).
#[inline(always)]
fn f32_from_bits(x: wide::i32x16) -> f32x16 {
    // SAFETY: as in `f32_bits`.
    unsafe { std::mem::transmute::<wide::i32x16, f32x16>(x) }
}

/// (G = e^{−ρ/2}, α = min(0.99, o·G), lanes where the clamp bit).
#[inline(always)]
pub(crate) fn splat_alpha(rho: f32x16, opacity: f32x16) -> (f32x16, f32x16, f32x16) {
    let g = exp_nonpositive(f32x16::splat(-0.5) * rho);
    let a = opacity * g;
    let clamp = f32x16::splat(0.99);
    (g, a.fast_min(clamp), a.simd_gt(clamp))
}

/// Evaluate candidates j0..j0 + 16 of the tile at pixel centre (px, py) (SIMD over
/// candidates; forward and backward make identical decisions through `splat_cross` / `splat_finish`).
/// Returns the hit mask; `out` is only written when the mask is non-zero.
#[inline(always)]
pub(crate) fn eval16(
    td: &Candidates,
    records: &[[f32; 16]],
    j0: usize,
    px: f32,
    py: f32,
    s: &RasterSettings,
    out: &mut Lanes,
) -> u32 {
    let (near, alpha_min) = (s.near, s.alpha_min);
    let g = td.group(j0 / 16, records);
    let tw = [g[PK_TW], g[PK_TW + 1], g[PK_TW + 2]];
    let c = splat_cross(
        f32x16::splat(px),
        f32x16::splat(py),
        [g[PK_TU], g[PK_TU + 1], g[PK_TU + 2]],
        [g[PK_TV], g[PK_TV + 1], g[PK_TV + 2]],
        tw,
        [g[PK_MEAN], g[PK_MEAN + 1]],
        s.filter_inv_square,
    );
    // Cheap conservative pre-test (no divide, no exp): most groups of a tile's list miss a
    // given pixel.
    let rho_max = g[PK_RHO];
    if c.may_reach(rho_max).to_bitmask() == 0 {
        return 0;
    }
    let e = splat_finish(c, tw);
    let ok = e.hz.simd_ne(f32x16::ZERO) & e.z.simd_ge(f32x16::splat(near));
    if (ok & e.rho.simd_le(rho_max)).to_bitmask() == 0 {
        return 0;
    }
    let (_, alpha, _) = splat_alpha(e.rho, g[PK_OP]);
    let ok = ok & alpha.simd_ge(f32x16::splat(alpha_min));
    let mut mask = ok.to_bitmask();
    let rest = td.n - j0;
    if rest < 16 {
        mask &= (1u32 << rest) - 1;
    }
    if mask != 0 {
        out.z = e.z.to_array();
        out.alpha = alpha.to_array();
    }
    mask
}

/// The per-pixel window of (z, slot, α) entries sorted by ascending z. The slot is the
/// caller's: an index into a pool of full hit records (backward), or the candidate's index in
/// the tile list (forward, which needs nothing else of a hit: no pool to fill).
pub(crate) trait Window {
    fn len(&self) -> usize;
    /// Slot of the nearest entry (len > 0).
    fn front_slot(&self) -> usize;
    /// z of the nearest entry (len > 0).
    fn front_z(&self) -> f32;
    /// α of the nearest entry (len > 0).
    fn front_alpha(&self) -> f32;
    /// Drop the nearest entry (len > 0).
    fn pop_front(&mut self);
    /// Insert after every entry with z' ≤ z (earlier arrivals win ties). z is never NaN: a hit
    /// needs z ≥ near.
    fn insert(&mut self, z: f32, slot: u32, alpha: f32);
    /// `pop_front` then `insert` (len > 0): what a full window does for every further hit.
    #[inline(always)]
    fn replace_front(&mut self, z: f32, slot: u32, alpha: f32) {
        self.pop_front();
        self.insert(z, slot, alpha);
    }
}

/// Up to 32 entries in a ring buffer sorted from `head`; insertion shifts 12 bytes per entry.
/// Candidates arrive in roughly increasing depth, so most insertions append.
#[derive(Clone, Copy)]
pub(crate) struct RingWindow {
    wz: [f32; RING],
    ws: [u32; RING],
    wa: [f32; RING],
    head: usize,
    len: usize,
}

impl RingWindow {
    fn new() -> Self {
        RingWindow { wz: [0.0; RING], ws: [0; RING], wa: [0.0; RING], head: 0, len: 0 }
    }
}

impl Window for RingWindow {
    #[inline(always)]
    fn len(&self) -> usize {
        self.len
    }
    #[inline(always)]
    fn front_slot(&self) -> usize {
        self.ws[self.head] as usize
    }
    #[inline(always)]
    fn front_z(&self) -> f32 {
        self.wz[self.head]
    }
    #[inline(always)]
    fn front_alpha(&self) -> f32 {
        self.wa[self.head]
    }
    #[inline(always)]
    fn pop_front(&mut self) {
        self.head = (self.head + 1) & (RING - 1);
        self.len -= 1;
    }
    #[inline(always)]
    fn insert(&mut self, z: f32, slot: u32, alpha: f32) {
        const M: usize = RING - 1;
        let (head, wz, ws, wa) = (self.head, &mut self.wz, &mut self.ws, &mut self.wa);
        let mut pos = self.len;
        while pos > 0 && wz[(head + pos - 1) & M] > z {
            wz[(head + pos) & M] = wz[(head + pos - 1) & M];
            ws[(head + pos) & M] = ws[(head + pos - 1) & M];
            wa[(head + pos) & M] = wa[(head + pos - 1) & M];
            pos -= 1;
        }
        wz[(head + pos) & M] = z;
        ws[(head + pos) & M] = slot;
        wa[(head + pos) & M] = alpha;
        self.len += 1;
    }
}

/// K = 1 (the plain 2DGS order): one entry in scalars. A hit then blends the previous one and
/// takes its place, with none of the register window's compare → permute chain.
pub(crate) struct SingleWindow {
    z: f32,
    slot: u32,
    alpha: f32,
    full: bool,
}

impl SingleWindow {
    fn new() -> Self {
        SingleWindow { z: 0.0, slot: 0, alpha: 0.0, full: false }
    }
}

impl Window for SingleWindow {
    #[inline(always)]
    fn len(&self) -> usize {
        self.full as usize
    }
    #[inline(always)]
    fn front_slot(&self) -> usize {
        self.slot as usize
    }
    #[inline(always)]
    fn front_z(&self) -> f32 {
        self.z
    }
    #[inline(always)]
    fn front_alpha(&self) -> f32 {
        self.alpha
    }
    #[inline(always)]
    fn pop_front(&mut self) {
        self.full = false;
    }
    #[inline(always)]
    fn insert(&mut self, z: f32, slot: u32, alpha: f32) {
        debug_assert!(!self.full, "SingleWindow holds one entry");
        (self.z, self.slot, self.alpha, self.full) = (z, slot, alpha, true);
    }
}

/// Up to 16 entries held in three AVX-512 registers (lanes at or above len hold z = +∞): the
/// insertion point is one compare and a few mask-register operations, the shift one masked
/// lane permute and one masked move per register, so an unpredictable insertion depth costs
/// no branch misses (the ring's shift loop mispredicts on every out-of-order hit).
#[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
#[derive(Clone, Copy)]
pub(crate) struct RegWindow {
    z: std::arch::x86_64::__m512,
    s: std::arch::x86_64::__m512i,
    a: std::arch::x86_64::__m512,
    len: usize,
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
impl RegWindow {
    /// Every register: the lanes in `moved` take lane `index` of the old register, then the
    /// lane in `here` takes the new entry (insert and replace_front differ only in the masks
    /// and the direction).
    #[inline(always)]
    fn shift_and_place(
        &mut self,
        moved: std::arch::x86_64::__mmask16,
        index: std::arch::x86_64::__m512i,
        here: std::arch::x86_64::__mmask16,
        zv: std::arch::x86_64::__m512,
        slot: u32,
        alpha: f32,
    ) {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx512f is enabled at compile time.
        unsafe {
            let z1 = _mm512_mask_permutexvar_ps(self.z, moved, index, self.z);
            self.z = _mm512_mask_mov_ps(z1, here, zv);
            let s1 = _mm512_mask_permutexvar_epi32(self.s, moved, index, self.s);
            self.s = _mm512_mask_mov_epi32(s1, here, _mm512_set1_epi32(slot as i32));
            let a1 = _mm512_mask_permutexvar_ps(self.a, moved, index, self.a);
            self.a = _mm512_mask_mov_ps(a1, here, _mm512_set1_ps(alpha));
        }
    }

    #[inline(always)]
    fn new() -> Self {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx512f is enabled at compile time.
        unsafe {
            RegWindow { z: _mm512_set1_ps(f32::INFINITY), s: _mm512_setzero_si512(), a: _mm512_setzero_ps(), len: 0 }
        }
    }
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
impl Window for RegWindow {
    #[inline(always)]
    fn len(&self) -> usize {
        self.len
    }
    #[inline(always)]
    fn front_slot(&self) -> usize {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx512f is enabled at compile time.
        unsafe { _mm_cvtsi128_si32(_mm512_castsi512_si128(self.s)) as u32 as usize }
    }
    #[inline(always)]
    fn front_z(&self) -> f32 {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx512f is enabled at compile time.
        unsafe { _mm512_cvtss_f32(self.z) }
    }
    #[inline(always)]
    fn front_alpha(&self) -> f32 {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx512f is enabled at compile time.
        unsafe { _mm512_cvtss_f32(self.a) }
    }
    #[inline(always)]
    fn pop_front(&mut self) {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx512f is enabled at compile time.
        unsafe {
            // Lanes move down one; lane 15 takes +∞ (index 16: the second source), keeping
            // every lane at or above len at +∞.
            let left = _mm512_setr_epi32(1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16);
            self.z = _mm512_permutex2var_ps(self.z, left, _mm512_set1_ps(f32::INFINITY));
            self.s = _mm512_permutexvar_epi32(left, self.s);
            self.a = _mm512_permutexvar_ps(left, self.a);
            self.len -= 1;
        }
    }
    #[inline(always)]
    fn insert(&mut self, z: f32, slot: u32, alpha: f32) {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx512f is enabled at compile time.
        unsafe {
            let zv = _mm512_set1_ps(z);
            // Lanes holding a depth > z: a run from the insertion point to lane 15 (the window
            // is sorted and lanes at or above len hold +∞). The run moves up one lane and z
            // lands at its start. Masks stay in mask registers: the compare → permute chain is
            // what successive inserts wait on.
            let greater = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(self.z, zv);
            let moved = _kshiftli_mask16::<1>(greater);
            let here = _kandn_mask16(moved, greater);
            let right = _mm512_setr_epi32(0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14);
            self.shift_and_place(moved, right, here, zv, slot, alpha);
            self.len += 1;
        }
    }
    /// Pop and insert in one shift: the entries nearer than z move down one lane, z lands
    /// after them, the farther ones stay (one masked permute per register instead of the
    /// pop's and the insert's two). With p the first lane deeper than z: lanes below p − 1 take
    /// their upper neighbour and z goes to p − 1; when z is nearer than the front (p = 0) it
    /// takes the popped front's lane, as pop-then-insert puts it there.
    #[inline(always)]
    fn replace_front(&mut self, z: f32, slot: u32, alpha: f32) {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx512f is enabled at compile time.
        unsafe {
            let zv = _mm512_set1_ps(z);
            let greater = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(self.z, zv);
            // Lanes [0, max(p, 1)): the nearer run, lane 0 always in it.
            let before = _kor_mask16(_knot_mask16(greater), 1);
            let shift = _kshiftri_mask16::<1>(before);
            let here = _kxor_mask16(before, shift);
            let left = _mm512_setr_epi32(1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 15);
            self.shift_and_place(shift, left, here, zv, slot, alpha);
        }
    }
}

/// Up to 8 entries in three AVX2 registers: the AVX-512 `RegWindow`'s branch-free insert and pop for
/// machines without AVX-512 (there the ring's shift loop, which mispredicts on every
/// out-of-order hit, was the costliest part of a relit frame). Masks are whole lanes (all ones
/// or zero) moved by the same lane permute as the data; lanes at or above len hold z = +∞.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
#[derive(Clone, Copy)]
pub(crate) struct RegWindow8 {
    z: std::arch::x86_64::__m256,
    s: std::arch::x86_64::__m256i,
    a: std::arch::x86_64::__m256,
    len: usize,
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl RegWindow8 {
    /// Every register: the lanes in `moved` take lane `index` of the old register, then the
    /// lane in `here` takes the new entry (as the AVX-512 `RegWindow`'s).
    #[inline(always)]
    fn shift_and_place(
        &mut self,
        moved: std::arch::x86_64::__m256,
        index: std::arch::x86_64::__m256i,
        here: std::arch::x86_64::__m256,
        zv: std::arch::x86_64::__m256,
        slot: u32,
        alpha: f32,
    ) {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx2 is enabled at compile time.
        unsafe {
            let z1 = _mm256_blendv_ps(self.z, _mm256_permutevar8x32_ps(self.z, index), moved);
            self.z = _mm256_blendv_ps(z1, zv, here);
            let s = _mm256_castsi256_ps(self.s);
            let s1 = _mm256_blendv_ps(s, _mm256_castsi256_ps(_mm256_permutevar8x32_epi32(self.s, index)), moved);
            let slot_v = _mm256_castsi256_ps(_mm256_set1_epi32(slot as i32));
            self.s = _mm256_castps_si256(_mm256_blendv_ps(s1, slot_v, here));
            let a1 = _mm256_blendv_ps(self.a, _mm256_permutevar8x32_ps(self.a, index), moved);
            self.a = _mm256_blendv_ps(a1, _mm256_set1_ps(alpha), here);
        }
    }

    #[inline(always)]
    fn new() -> Self {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx2 is enabled at compile time.
        unsafe {
            RegWindow8 { z: _mm256_set1_ps(f32::INFINITY), s: _mm256_setzero_si256(), a: _mm256_setzero_ps(), len: 0 }
        }
    }
}

#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
impl Window for RegWindow8 {
    #[inline(always)]
    fn len(&self) -> usize {
        self.len
    }
    #[inline(always)]
    fn front_slot(&self) -> usize {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx2 is enabled at compile time.
        unsafe { _mm256_cvtsi256_si32(self.s) as u32 as usize }
    }
    #[inline(always)]
    fn front_z(&self) -> f32 {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx2 is enabled at compile time.
        unsafe { _mm256_cvtss_f32(self.z) }
    }
    #[inline(always)]
    fn front_alpha(&self) -> f32 {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx2 is enabled at compile time.
        unsafe { _mm256_cvtss_f32(self.a) }
    }
    #[inline(always)]
    fn pop_front(&mut self) {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx2 is enabled at compile time.
        unsafe {
            // Lanes move down one; lane 7 takes +∞, keeping every lane at or above len at +∞.
            let left = _mm256_setr_epi32(1, 2, 3, 4, 5, 6, 7, 7);
            let top = _mm256_castsi256_ps(_mm256_setr_epi32(0, 0, 0, 0, 0, 0, 0, -1));
            self.z = _mm256_blendv_ps(_mm256_permutevar8x32_ps(self.z, left), _mm256_set1_ps(f32::INFINITY), top);
            self.s = _mm256_permutevar8x32_epi32(self.s, left);
            self.a = _mm256_permutevar8x32_ps(self.a, left);
            self.len -= 1;
        }
    }
    #[inline(always)]
    fn insert(&mut self, z: f32, slot: u32, alpha: f32) {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx2 is enabled at compile time.
        unsafe {
            let zv = _mm256_set1_ps(z);
            // Lanes holding a depth > z: a run from the insertion point to lane 7. The run
            // moves up one lane (lane i takes lane i − 1: the mask moved with it) and z lands
            // at its start.
            let greater = _mm256_cmp_ps::<_CMP_GT_OQ>(self.z, zv);
            let right = _mm256_setr_epi32(0, 0, 1, 2, 3, 4, 5, 6);
            let not_first = _mm256_castsi256_ps(_mm256_setr_epi32(0, -1, -1, -1, -1, -1, -1, -1));
            let moved = _mm256_and_ps(_mm256_permutevar8x32_ps(greater, right), not_first);
            let here = _mm256_andnot_ps(moved, greater);
            self.shift_and_place(moved, right, here, zv, slot, alpha);
            self.len += 1;
        }
    }
    /// Pop and insert in one shift (as the AVX-512 `RegWindow`'s): with p the first lane
    /// deeper than z, lanes below p − 1 take their upper neighbour and z goes to p − 1 (lane
    /// 0 when z is nearer than the front).
    #[inline(always)]
    fn replace_front(&mut self, z: f32, slot: u32, alpha: f32) {
        use std::arch::x86_64::*;
        // SAFETY: this type exists only when avx2 is enabled at compile time.
        unsafe {
            let zv = _mm256_set1_ps(z);
            // Lanes [0, max(p, 1)): the nearer run, lane 0 always in it.
            let not_greater = _mm256_cmp_ps::<_CMP_LE_OQ>(self.z, zv);
            let first = _mm256_castsi256_ps(_mm256_setr_epi32(-1, 0, 0, 0, 0, 0, 0, 0));
            let before = _mm256_or_ps(not_greater, first);
            // shift[i] = before[i + 1] (lane 7: none).
            let left = _mm256_setr_epi32(1, 2, 3, 4, 5, 6, 7, 7);
            let not_last = _mm256_castsi256_ps(_mm256_setr_epi32(-1, -1, -1, -1, -1, -1, -1, 0));
            let shift = _mm256_and_ps(_mm256_permutevar8x32_ps(before, left), not_last);
            let here = _mm256_xor_ps(before, shift);
            self.shift_and_place(shift, left, here, zv, slot, alpha);
        }
    }
}

/// Composite one pixel through the sorted window: `blend(li, z, α, T_before)` for every
/// blended hit in blend order, li its index in the tile list. The forward and the backward both
/// call this (or `composite_two_pixels`), so they blend the same hits in the same order.
/// Returns (T_final, candidates evaluated).
#[inline(always)]
pub(crate) fn composite_pixel(
    td: &TileData,
    px: f32,
    py: f32,
    s: &RasterSettings,
    k: usize,
    blend: impl FnMut(usize, f32, f32, f32),
) -> (f32, Evaluated) {
    composite_one_pixel(td, (px, py), s, k, blend)
}

/// Two pixels (the second only if `two`) through their own windows in one pass over the
/// tile's candidates. Each window's insert is a compare → mask → permute chain that the next
/// insert waits on; two independent chains let the core overlap them. Per pixel the hits,
/// their order and T are exactly those of compositing it alone.
#[inline(always)]
pub(crate) fn composite_two_pixels(
    td: &TileData,
    p: [(f32, f32); 2],
    two: bool,
    s: &RasterSettings,
    k: usize,
    blend0: impl FnMut(usize, f32, f32, f32),
    blend1: impl FnMut(usize, f32, f32, f32),
) -> [(f32, Evaluated); 2] {
    // Scalars for K = 1, registers for K ≤ 16 with AVX-512 (K ≤ 8 with AVX2), else the ring
    // buffer.
    if k == 1 {
        return composite_with([SingleWindow::new(), SingleWindow::new()], td, p, two, s, k, blend0, blend1);
    }
    #[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
    if k <= 16 {
        return composite_with([RegWindow::new(), RegWindow::new()], td, p, two, s, k, blend0, blend1);
    }
    // Without AVX-512 (the default K = 8 fits one AVX2 register per field).
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if k <= 8 {
        return composite_with([RegWindow8::new(), RegWindow8::new()], td, p, two, s, k, blend0, blend1);
    }
    composite_with([RingWindow::new(), RingWindow::new()], td, p, two, s, k, blend0, blend1)
}

/// Candidates one pixel evaluated: in its quarter's list, and the entries of the whole tile
/// list up to the same stop (what compositing over the tile list would have evaluated).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Evaluated {
    pub performed: u32,
    pub tile_list: u32,
}

/// One pixel's state in the candidate loop.
struct PixelRun<W> {
    window: W,
    t: f32,
    /// Still compositing (not stopped by the T cut-off, or not in use).
    live: bool,
    /// Candidates evaluated (set when the pixel stops early).
    evaluated: Evaluated,
    lanes: Lanes,
}

impl<W: Window> PixelRun<W> {
    /// Take the lowest hit of `mask` (non-zero) in the current group (candidate j0 + l) and
    /// clear its bit: when the window is full, blend its nearest entry first, or stop (clearing
    /// the whole mask) if that blend would take T below the cut-off, or right after it if it
    /// took T below the display stop.
    #[inline(always)]
    fn take_next(
        &mut self,
        mask: &mut u32,
        j0: usize,
        slots: &[u32],
        k: usize,
        stop: Stop,
        blend: &mut impl FnMut(usize, f32, f32, f32),
    ) {
        let l = mask.trailing_zeros() as usize;
        *mask &= *mask - 1;
        let slot = slots[j0 + l];
        if self.window.len() == k {
            let alpha = self.window.front_alpha();
            let next = self.t * (1.0 - alpha);
            if next < stop.before {
                self.stop(mask, j0 + l, slot);
                return;
            }
            blend(self.window.front_slot(), self.window.front_z(), alpha, self.t);
            self.t = next;
            if next < stop.after {
                self.stop(mask, j0 + l, slot);
                return;
            }
            self.window.replace_front(self.lanes.z[l], slot, self.lanes.alpha[l]);
        } else {
            self.window.insert(self.lanes.z[l], slot, self.lanes.alpha[l]);
        }
    }

    /// Stop compositing at candidate j of the quarter list (slot in the tile list).
    #[cold]
    fn stop(&mut self, mask: &mut u32, j: usize, slot: u32) {
        self.live = false;
        self.evaluated = Evaluated { performed: j as u32 + 1, tile_list: slot + 1 };
        *mask = 0;
    }

    /// Blend what the window still holds, nearest first.
    #[inline(always)]
    fn flush(&mut self, stop: Stop, blend: &mut impl FnMut(usize, f32, f32, f32)) {
        while self.live && self.window.len() > 0 {
            let alpha = self.window.front_alpha();
            let next = self.t * (1.0 - alpha);
            if next < stop.before {
                break;
            }
            blend(self.window.front_slot(), self.window.front_z(), alpha, self.t);
            self.t = next;
            if next < stop.after {
                break;
            }
            self.window.pop_front();
        }
    }
}

/// When compositing stops: before a blend that would take T below `before`
/// (`RasterSettings::transmittance_min`), or after one that took it below `after`
/// (`RasterSettings::display_stop`, 0 = never).
#[derive(Clone, Copy)]
struct Stop {
    before: f32,
    after: f32,
}

impl Stop {
    fn of(s: &RasterSettings) -> Stop {
        Stop { before: s.transmittance_min, after: s.display_stop }
    }
}

/// The per-pixel loop: evaluate the tile's candidates 16 at a time, insert each hit into the
/// window (its slot: the candidate's index in the tile list); when the window is full, blend
/// its nearest entry first (stopping before a blend that would take T below the cut-off); at
/// the end flush the window nearest-first.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn composite_with<W: Window>(
    windows: [W; 2],
    td: &TileData,
    p: [(f32, f32); 2],
    two: bool,
    s: &RasterSettings,
    k: usize,
    mut blend0: impl FnMut(usize, f32, f32, f32),
    mut blend1: impl FnMut(usize, f32, f32, f32),
) -> [(f32, Evaluated); 2] {
    let stop = Stop::of(s);
    // The pixels' quarter of the tile (a pair never straddles two: pairs start at even x).
    let quarter = |q: (f32, f32)| {
        let right = q.0 - td.origin.0 as f32 >= QUARTER as f32;
        let below = q.1 - td.origin.1 as f32 >= QUARTER as f32;
        right as usize + 2 * below as usize
    };
    let list = &td.quarters[quarter(p[0])];
    debug_assert!(!two || quarter(p[1]) == quarter(p[0]), "a pixel pair straddles two quarters");
    let all = Evaluated { performed: list.n as u32, tile_list: td.n as u32 };
    let [w0, w1] = windows;
    let mut a = PixelRun { window: w0, t: 1.0, live: true, evaluated: all, lanes: Lanes::default() };
    let mut b = PixelRun { window: w1, t: 1.0, live: two, evaluated: all, lanes: Lanes::default() };
    let mut j0 = 0;
    while j0 < list.n && (a.live || b.live) {
        let records = &td.records;
        let mut ma = if a.live { eval16(list, records, j0, p[0].0, p[0].1, s, &mut a.lanes) } else { 0 };
        let mut mb = if b.live { eval16(list, records, j0, p[1].0, p[1].1, s, &mut b.lanes) } else { 0 };
        // Alternate the two pixels' hits so their window chains interleave.
        while (ma | mb) != 0 {
            if ma != 0 {
                a.take_next(&mut ma, j0, &list.slot, k, stop, &mut blend0);
            }
            if mb != 0 {
                b.take_next(&mut mb, j0, &list.slot, k, stop, &mut blend1);
            }
        }
        j0 += 16;
    }
    a.flush(stop, &mut blend0);
    b.flush(stop, &mut blend1);
    [(a.t, a.evaluated), (b.t, b.evaluated)]
}

/// One pixel through its window (what [`composite_with`] does for a pixel alone): fewer
/// live registers than the pair loop, which on AVX2's 16 registers spills the pixels' sums.
#[inline(always)]
fn composite_one_with<W: Window>(
    window: W,
    td: &TileData,
    p: (f32, f32),
    s: &RasterSettings,
    k: usize,
    mut blend: impl FnMut(usize, f32, f32, f32),
) -> (f32, Evaluated) {
    let stop = Stop::of(s);
    let right = p.0 - td.origin.0 as f32 >= QUARTER as f32;
    let below = p.1 - td.origin.1 as f32 >= QUARTER as f32;
    let list = &td.quarters[right as usize + 2 * below as usize];
    let all = Evaluated { performed: list.n as u32, tile_list: td.n as u32 };
    let mut a = PixelRun { window, t: 1.0, live: true, evaluated: all, lanes: Lanes::default() };
    let mut j0 = 0;
    while j0 < list.n && a.live {
        let mut ma = eval16(list, &td.records, j0, p.0, p.1, s, &mut a.lanes);
        while ma != 0 {
            a.take_next(&mut ma, j0, &list.slot, k, stop, &mut blend);
        }
        j0 += 16;
    }
    a.flush(stop, &mut blend);
    (a.t, a.evaluated)
}

/// One pixel with the window [`composite_two_pixels`] would pick for K.
#[inline(always)]
pub(crate) fn composite_one_pixel(
    td: &TileData,
    p: (f32, f32),
    s: &RasterSettings,
    k: usize,
    blend: impl FnMut(usize, f32, f32, f32),
) -> (f32, Evaluated) {
    if k == 1 {
        return composite_one_with(SingleWindow::new(), td, p, s, k, blend);
    }
    #[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
    if k <= 16 {
        return composite_one_with(RegWindow::new(), td, p, s, k, blend);
    }
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if k <= 8 {
        return composite_one_with(RegWindow8::new(), td, p, s, k, blend);
    }
    composite_one_with(RingWindow::new(), td, p, s, k, blend)
}

/// Normalised depth for the distortion loss (2DGS): m = far/(far − near) · (1 − near/z).
#[inline(always)]
pub(crate) fn norm_depth(z: f32, near: f32, far: f32) -> f32 {
    far / (far - near) * (1.0 - near / z)
}

/// One pixel's running sums in the forward.
#[derive(Default)]
struct PixelSums {
    /// Σ w · blend row: colour, normal, Σ w (rather than 1 − T: no cancellation when α is
    /// tiny) and the features that fit.
    row: f32x16,
    /// The row's first 8 lanes when blending narrow rows (`row` is then unused).
    row8: f32x8,
    /// Features beyond the row, channel by channel.
    features: [f32; MAX_FEATURES],
    /// Σ w z.
    depth: f32,
    /// Σ w d and Σ w d² with d = m − `m_first` (distortion = A·M2 − M1², shift-invariant).
    m1: f32,
    m2: f32,
    m_first: f32,
    median: f32,
    /// Surface-aware depth: Σ w ẑ and Σ w ẑ² (see `RenderOutput::surface_depth`).
    surface: f32,
    surface2: f32,
}

impl PixelSums {
    /// Add one hit. `LEAN`: only the blend row (colour, normal, Σ w, the row's features), for
    /// renders that ask for no depth, median, distortion or surface depth and whose features
    /// fit the row ([`lean_outputs`]): a relit or evaluation frame then skips their per-hit
    /// work and the settings tests, which are reloaded each hit. `NARROW` (with `LEAN`, at most
    /// one feature channel): the row's first 8 lanes, one AVX2 multiply-add instead of two.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn blend<const LEAN: bool, const NARROW: bool>(
        &mut self,
        td: &TileData,
        s: &RasterSettings,
        features: Option<Features>,
        li: usize,
        z: f32,
        alpha: f32,
        t: f32,
    ) {
        let wgt = alpha * t;
        if NARROW {
            self.row8 = td.blend_rows8[li].mul_add(f32x8::splat(wgt), self.row8);
            return;
        }
        self.row = td.blend_rows[li].mul_add(f32x16::splat(wgt), self.row);
        if LEAN {
            return;
        }
        self.depth += wgt * z;
        if s.outputs.distortion {
            let m = norm_depth(z, s.near, s.far);
            // T is exactly 1 until the first blend with α > 0; a blend before it weighs
            // nothing, so moving the reference there changes no sum.
            self.m_first = if t == 1.0 { m } else { self.m_first };
            let d = m - self.m_first;
            self.m1 += d * wgt;
            self.m2 += d * d * wgt;
        }
        if t > 0.5 {
            self.median = z;
        }
        if s.outputs.surface_depth {
            // GauS-SLAM: hits behind the running median are pulled toward it by their distance
            // in units of the spread of what is already blended (Σ_{earlier} w = 1 − T).
            let dm = self.median;
            let zhat = if self.surface > 0.0 {
                let var = ((self.surface2 - 2.0 * self.surface * dm) / (1.0 - t) + dm * dm).max(1e-7);
                let conf = (-(z - dm) * (z - dm) / (4.0 * var)).exp();
                conf * z + (1.0 - conf) * dm
            } else {
                z
            };
            self.surface += wgt * zhat;
            self.surface2 += wgt * zhat * zhat;
        }
        if let Some(fe) = features
            && fe.channels > ROW_FEATURES
        {
            let nch = fe.channels;
            let id = td.ids[li] as usize;
            let src = &fe.data[id * nch..(id + 1) * nch];
            for ch in 0..nch {
                self.features[ch] += wgt * src[ch];
            }
        }
    }

    /// The pixel's outputs (T_final `tf` for the background) at `at` in its row of tiles.
    #[inline(always)]
    fn write(&self, out: &mut RowOutputs, at: usize, tf: f32, s: &RasterSettings, nch: usize, narrow: bool) {
        let row = if narrow {
            let mut row = [0.0; 16];
            row[..8].copy_from_slice(&self.row8.to_array());
            row
        } else {
            self.row.to_array()
        };
        write_row(out, at, tf, s, nch, &row);
        let a = row[BLEND_ONE];
        if let Some(d) = out.depth.as_deref_mut() {
            d[at] = if a > 0.0 { self.depth / a } else { 0.0 };
        }
        if let Some(m) = out.median.as_deref_mut() {
            m[at] = self.median;
        }
        if let Some(d) = out.distortion.as_deref_mut() {
            d[at] = (a * self.m2 - self.m1 * self.m1).max(0.0);
        }
        if let Some(d) = out.surface.as_deref_mut() {
            d[at] = if a > 0.0 { self.surface / a } else { 0.0 };
        }
        if nch > ROW_FEATURES {
            out.features[at * nch..(at + 1) * nch].copy_from_slice(&self.features[..nch]);
        }
    }
}

/// A pixel's outputs from its blend-row sums (T_final `tf` for the background): alpha,
/// colour, normal and the features that fit the row (the rest are [`PixelSums::write`]'s).
#[inline(always)]
fn write_row(out: &mut RowOutputs, at: usize, tf: f32, s: &RasterSettings, nch: usize, row: &[f32; 16]) {
    out.alpha[at] = row[BLEND_ONE];
    if let Some(c) = out.colour.as_deref_mut() {
        c[at] = std::array::from_fn(|ch| row[ch] + tf * s.background[ch]);
    }
    if let Some(n) = out.normal.as_deref_mut() {
        n[at] = [row[3], row[4], row[5]];
    }
    if nch <= ROW_FEATURES {
        out.features[at * nch..(at + 1) * nch].copy_from_slice(&row[BLEND_FEAT..BLEND_FEAT + nch]);
    }
}

/// Render the surfels from `camera`. Panics if `features.data.len() != N × channels` or
/// channels > 16 (programming errors, not user input).
pub fn render(
    surfels: &Surfels,
    camera: &Camera,
    settings: &RasterSettings,
    features: Option<Features>,
) -> (RenderOutput, ForwardState) {
    render_impl(surfels, camera, settings, features, None, Compositor::Blocks)
}

/// How narrow, unrecorded frames are composited (every other render goes pixel by pixel).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Compositor {
    /// Sixteen pixels at a time ([`block`]).
    Blocks,
    /// One pixel at a time over sixteen candidates (tests: the blocks' reference).
    Pixels,
}

/// [`render`] with the compositor chosen (tests compare the two).
#[cfg(test)]
pub(crate) fn render_with(
    surfels: &Surfels,
    camera: &Camera,
    settings: &RasterSettings,
    features: Option<Features>,
    compositor: Compositor,
) -> (RenderOutput, ForwardState) {
    render_impl(surfels, camera, settings, features, None, compositor)
}

/// [`render`], keeping every pixel's blended hits in the state for [`crate::raster::render_backward`]
/// (which then need not re-run the pixels' sorting windows): for training. `reuse` is a record
/// taken back from an earlier state (or the default); its buffers are refilled.
pub fn render_recorded(
    surfels: &Surfels,
    camera: &Camera,
    settings: &RasterSettings,
    features: Option<Features>,
    reuse: PixelHitRecord,
) -> (RenderOutput, ForwardState) {
    render_impl(surfels, camera, settings, features, Some((reuse, RECORD_BUDGET_BYTES)), Compositor::Pixels)
}

/// [`render_recorded`] with another budget (tests: rows that do not fit).
#[cfg(test)]
pub(crate) fn render_recorded_with_budget(
    surfels: &Surfels,
    camera: &Camera,
    settings: &RasterSettings,
    features: Option<Features>,
    reuse: PixelHitRecord,
    budget_bytes: usize,
) -> (RenderOutput, ForwardState) {
    render_impl(surfels, camera, settings, features, Some((reuse, budget_bytes)), Compositor::Pixels)
}

/// A hit record holds at most about this much (16 bytes a hit): once a row of tiles has used
/// its share, its further pixels are not recorded and the backward re-runs their windows
/// (same results). Training at 200² needs 25–110 MiB; 100k surfels at 800² would need ~750 MiB.
pub const RECORD_BUDGET_BYTES: usize = 256 << 20;

/// Renders a sequence of training frames with [`render_recorded`], reusing one record's
/// buffers from frame to frame.
#[derive(Debug, Default)]
pub struct HitRecorder {
    spare: PixelHitRecord,
}

impl HitRecorder {
    pub fn render(
        &mut self,
        surfels: &Surfels,
        camera: &Camera,
        settings: &RasterSettings,
        features: Option<Features>,
    ) -> (RenderOutput, ForwardState) {
        render_recorded(surfels, camera, settings, features, std::mem::take(&mut self.spare))
    }
    /// Take the record back from a state (after its backward) for the next frame.
    pub fn recycle(&mut self, state: &mut ForwardState) {
        if let Some(record) = state.record.take() {
            self.spare = record;
        }
    }
}

fn render_impl(
    surfels: &Surfels,
    camera: &Camera,
    settings: &RasterSettings,
    features: Option<Features>,
    record: Option<(PixelHitRecord, usize)>,
    compositor: Compositor,
) -> (RenderOutput, ForwardState) {
    let (mut record, budget_bytes) = match record {
        Some((r, b)) => (Some(r), b),
        None => (None, 0),
    };
    let n = surfels.len();
    let (w, h) = (camera.width, camera.height);
    let nch = features.map_or(0, |f| f.channels);
    if let Some(f) = features {
        assert!(f.channels <= MAX_FEATURES, "at most {MAX_FEATURES} feature channels");
        assert_eq!(f.data.len(), n * f.channels, "features must be N × channels");
    }
    let proj = project::project(surfels, camera, settings);
    let bins = tiles::bin(&proj, w, h, settings.alpha_min, settings.filter_inv_square);
    // Narrow rows when they hold all a non-recording render blends (then no wide ones).
    let narrow = record.is_none() && lean_outputs(settings, nch) && nch <= NARROW_FEATURES;
    let rows = if narrow { Vec::new() } else { blend_rows(&proj, features) };
    let rows8: Option<Vec<f32x8>> = narrow.then(|| blend_rows8(&proj, features));
    let row_sets = (rows.as_slice(), rows8.as_deref());
    let mut out = RenderOutput::sized(w, h, nch, settings);
    let (evaluations_performed, evaluations) = if w == 0 || h == 0 {
        (0, 0)
    } else {
        // Each row of tiles writes its own slices of the outputs.
        let row_outputs = RowOutputs::split(&mut out, TILE * w, nch);
        let render_row = |td: &mut TileData, ty: usize, row_out: &mut RowOutputs, rec: Option<RowRecord>| {
            render_tile_row(&proj, &bins, camera, settings, features, ty as u32, row_out, td, row_sets, rec, compositor)
        };
        let row_pairs = bins.row_pairs();
        match record.as_mut() {
            Some(rec) => {
                rec.rows.resize_with(bins.tiles_y as usize, RowHits::default);
                let cap = budget_bytes / std::mem::size_of::<RecordedHit>() / bins.tiles_y.max(1) as usize;
                let rows: Vec<_> = row_outputs.into_iter().zip(rec.rows.iter_mut()).collect();
                tiles::rows_largest_first(
                    rows,
                    &row_pairs,
                    || (TileData::default(), Vec::new()),
                    |(td, pending), ty, (mut row_out, row)| render_row(td, ty, &mut row_out, Some((row, pending, cap))),
                )
            }
            None => tiles::rows_largest_first(row_outputs, &row_pairs, TileData::default, |td, ty, mut row_out| {
                render_row(td, ty, &mut row_out, None)
            }),
        }
    };
    let radii = proj.radius.clone();
    let visible = radii.iter().map(|&r| r > 0.0).collect();
    let state = ForwardState {
        width: w,
        height: h,
        proj,
        tiles: bins,
        radii,
        visible,
        evaluations,
        evaluations_performed,
        record,
    };
    (out, state)
}

impl RenderOutput {
    /// Zeroed outputs for a w × h render: alpha always, the others when requested (empty
    /// otherwise), `nch` feature channels.
    fn sized(w: u32, h: u32, nch: usize, s: &RasterSettings) -> RenderOutput {
        let px = w as usize * h as usize;
        let o = s.outputs;
        let sized = |on: bool| if on { px } else { 0 };
        RenderOutput {
            width: w,
            height: h,
            alpha: vec![0.0; px],
            colour: vec![[0.0; 3]; sized(o.colour)],
            depth: vec![0.0; sized(o.depth)],
            median_depth: vec![0.0; sized(o.median_depth)],
            normal: vec![[0.0; 3]; sized(o.normal)],
            distortion: vec![0.0; sized(o.distortion)],
            surface_depth: vec![0.0; sized(o.surface_depth)],
            features: vec![0.0; px * nch],
        }
    }
}

/// One row of tiles' slices of the render's outputs (None: not requested), pixel-major
/// within the row; the compositor writes each pixel's sums straight into them.
struct RowOutputs<'a> {
    alpha: &'a mut [f32],
    colour: Option<&'a mut [[f32; 3]]>,
    depth: Option<&'a mut [f32]>,
    median: Option<&'a mut [f32]>,
    normal: Option<&'a mut [[f32; 3]]>,
    distortion: Option<&'a mut [f32]>,
    surface: Option<&'a mut [f32]>,
    /// `nch` values per pixel.
    features: &'a mut [f32],
}

impl<'a> RowOutputs<'a> {
    /// The outputs cut into rows of `row_px` pixels (the last may be shorter).
    fn split(out: &'a mut RenderOutput, row_px: u32, nch: usize) -> Vec<RowOutputs<'a>> {
        let row_px = row_px as usize;
        fn rows_of<T>(v: &mut [T], len: usize) -> impl Iterator<Item = Option<&mut [T]>> {
            let rows: Vec<_> = if v.is_empty() { Vec::new() } else { v.chunks_mut(len).map(Some).collect() };
            rows.into_iter().chain(std::iter::repeat_with(|| None))
        }
        let mut colour = rows_of(&mut out.colour, row_px);
        let mut depth = rows_of(&mut out.depth, row_px);
        let mut median = rows_of(&mut out.median_depth, row_px);
        let mut normal = rows_of(&mut out.normal, row_px);
        let mut distortion = rows_of(&mut out.distortion, row_px);
        let mut surface = rows_of(&mut out.surface_depth, row_px);
        let mut features = rows_of(&mut out.features, row_px * nch.max(1));
        out.alpha
            .chunks_mut(row_px)
            .map(|alpha| RowOutputs {
                alpha,
                colour: colour.next().flatten(),
                depth: depth.next().flatten(),
                median: median.next().flatten(),
                normal: normal.next().flatten(),
                distortion: distortion.next().flatten(),
                surface: surface.next().flatten(),
                features: features.next().flatten().unwrap_or_default(),
            })
            .collect()
    }
}

/// A row of tiles' hit record, a scratch list for the second pixel of a pair (whose blends
/// interleave with the first's) and the row's share of the record budget.
type RowRecord<'a> = (&'a mut RowHits, &'a mut Vec<RecordedHit>, usize);

/// Whether a render needs only the blend row per hit (see [`PixelSums::blend`]).
fn lean_outputs(s: &RasterSettings, nch: usize) -> bool {
    let o = s.outputs;
    !o.depth && !o.median_depth && !o.distortion && !o.surface_depth && nch <= ROW_FEATURES
}

/// A pixel pair's sums (the second only if `two`) through the compositor, one pixel at a time
/// where [`SINGLE`]. Inlined so the sums stay in registers across blends.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn composite_sums<const LEAN: bool, const NARROW: bool>(
    td: &TileData,
    pf: [(f32, f32); 2],
    two: bool,
    s: &RasterSettings,
    k: usize,
    features: Option<Features>,
    sa: &mut PixelSums,
    sb: &mut PixelSums,
) -> [(f32, Evaluated); 2] {
    if !SINGLE {
        return composite_two_pixels(
            td,
            pf,
            two,
            s,
            k,
            #[inline(always)]
            |li, z, alpha, t| sa.blend::<LEAN, NARROW>(td, s, features, li, z, alpha, t),
            #[inline(always)]
            |li, z, alpha, t| sb.blend::<LEAN, NARROW>(td, s, features, li, z, alpha, t),
        );
    }
    let ra = composite_one_pixel(
        td,
        pf[0],
        s,
        k,
        #[inline(always)]
        |li, z, alpha, t| sa.blend::<LEAN, NARROW>(td, s, features, li, z, alpha, t),
    );
    let rb = if two {
        composite_one_pixel(
            td,
            pf[1],
            s,
            k,
            #[inline(always)]
            |li, z, alpha, t| sb.blend::<LEAN, NARROW>(td, s, features, li, z, alpha, t),
        )
    } else {
        (1.0, Evaluated::default())
    };
    [ra, rb]
}

#[allow(clippy::too_many_arguments)]
// Not inlined into rayon's closure: profiles then name the forward's tile loop.
#[inline(never)]
fn render_tile_row(
    proj: &Projected,
    bins: &TileBins,
    camera: &Camera,
    s: &RasterSettings,
    features: Option<Features>,
    ty: u32,
    out: &mut RowOutputs,
    td: &mut TileData,
    // Per-surfel blend rows, and their narrow form when the render blends those instead.
    rows: (&[f32x16], Option<&[f32x8]>),
    mut record: Option<RowRecord>,
    compositor: Compositor,
) -> (u64, u64) {
    let w = camera.width;
    let h = camera.height;
    let k = s.k();
    let nch = features.map_or(0, |f| f.channels);
    let lean = lean_outputs(s, nch);
    // Not while recording: that path blends through the full row.
    let narrow = rows.1.is_some() && record.is_none();
    debug_assert!(!narrow || (lean && nch <= NARROW_FEATURES));
    // (performed, tile-list) evaluations.
    let mut evals = (0u64, 0u64);
    let y0 = ty * TILE;
    let y1 = (y0 + TILE).min(h);
    if let Some((row, _, _)) = record.as_mut() {
        let px = ((y1 - y0) * w) as usize;
        row.hits.clear();
        row.spans.clear();
        row.spans.resize(px, NOT_RECORDED);
        row.t_final.clear();
        row.t_final.resize(px, 1.0);
    }
    for tx in 0..bins.tiles_x {
        let t = (ty * bins.tiles_x + tx) as usize;
        let range = bins.offsets[t] as usize..bins.offsets[t + 1] as usize;
        let x0 = tx * TILE;
        let x1 = (x0 + TILE).min(w);
        // A tile without candidates is background (every other output starts at zero): what
        // the compositor would write for each pixel, without a pass through it per pixel.
        if range.is_empty() && record.is_none() {
            if let Some(colour) = out.colour.as_deref_mut() {
                for y in y0..y1 {
                    let row = ((y - y0) * w) as usize;
                    colour[row + x0 as usize..row + x1 as usize].fill(s.background);
                }
            }
            continue;
        }
        td.load(proj, &bins.ids[range.clone()], &bins.quarter_masks[range], (tx * TILE, ty * TILE));
        match rows {
            (_, Some(rows8)) if narrow => td.load_blend_rows8(rows8),
            (rows16, _) => td.load_blend_rows(rows16),
        }
        // Blocks for the default window (each K is its own unrolled copy).
        if narrow && compositor == Compositor::Blocks && k == block::BLOCK_K {
            for by in (y0..y1).step_by(block::BLOCK_H as usize) {
                for bx in (x0..x1).step_by(block::BLOCK_W as usize) {
                    let mut sums = [f32x8::ZERO; 16];
                    let (tf, evaluated) =
                        block::composite_block::<{ block::BLOCK_K }>(td, (bx, by), (x1, y1), s, &mut sums);
                    for (l, (sum, ev)) in sums.iter().zip(&evaluated).enumerate() {
                        let (x, y) = (bx + l as u32 % block::BLOCK_W, by + l as u32 / block::BLOCK_W);
                        if x < x1 && y < y1 {
                            let mut row = [0.0; 16];
                            row[..8].copy_from_slice(&sum.to_array());
                            write_row(out, ((y - y0) * w + x) as usize, tf[l], s, nch, &row);
                            evals.0 += ev.performed as u64;
                            evals.1 += ev.tile_list as u64;
                        }
                    }
                }
            }
            continue;
        }
        for y in y0..y1 {
            // Pixels in pairs (see `composite_two_pixels`); a lone last one when x1 − x0 is odd.
            for x in (x0..x1).step_by(2) {
                let two = x + 1 < x1;
                let (mut sa, mut sb) = (PixelSums::default(), PixelSums::default());
                let pf = [(x as f32 + 0.5, y as f32 + 0.5), (x as f32 + 1.5, y as f32 + 0.5)];
                let local = |x: u32| ((y - y0) * w + x) as usize;
                // Over its share of the budget a row stops recording (at most a pair's hits over).
                let recording = matches!(record.as_ref(), Some((row, _, cap)) if row.hits.len() <= *cap);
                let [(ta, eva), (tb, evb)] = match record.as_mut().filter(|_| recording) {
                    None if narrow => composite_sums::<true, true>(td, pf, two, s, k, features, &mut sa, &mut sb),
                    None if lean => composite_sums::<true, false>(td, pf, two, s, k, features, &mut sa, &mut sb),
                    None => composite_sums::<false, false>(td, pf, two, s, k, features, &mut sa, &mut sb),
                    Some((row, pending, _)) => {
                        let start_a = row.hits.len() as u32;
                        pending.clear();
                        let res = composite_two_pixels(
                            td,
                            pf,
                            two,
                            s,
                            k,
                            #[inline(always)]
                            |li, z, alpha, t| {
                                sa.blend::<false, false>(td, s, features, li, z, alpha, t);
                                row.hits.push(RecordedHit { li: li as u32, z, alpha, t });
                            },
                            #[inline(always)]
                            |li, z, alpha, t| {
                                sb.blend::<false, false>(td, s, features, li, z, alpha, t);
                                pending.push(RecordedHit { li: li as u32, z, alpha, t });
                            },
                        );
                        let end_a = row.hits.len() as u32;
                        row.spans[local(x)] = (start_a, end_a);
                        row.t_final[local(x)] = res[0].0;
                        if two {
                            row.hits.extend_from_slice(pending);
                            row.spans[local(x + 1)] = (end_a, row.hits.len() as u32);
                            row.t_final[local(x + 1)] = res[1].0;
                        }
                        res
                    }
                };
                sa.write(out, local(x), ta, s, nch, narrow);
                evals.0 += eva.performed as u64;
                evals.1 += eva.tile_list as u64;
                if two {
                    sb.write(out, local(x + 1), tb, s, nch, narrow);
                    evals.0 += evb.performed as u64;
                    evals.1 += evb.tile_list as u64;
                }
            }
        }
    }
    evals
}

/// Sorting error of the blend order (for `radiogs bench raster`), over every `step`-th pixel in
/// x and y: (weighted, unweighted) fraction of blended pairs (i before j) with z_i > z_j,
/// the weighted one with pair weight w_i·w_j (w = α T, the blending weights), i.e.
/// Σ_{i<j, z_i>z_j} w_i w_j / Σ_{i<j} w_i w_j summed over the sampled pixels.
pub fn sorting_error(state: &ForwardState, camera: &Camera, settings: &RasterSettings, step: u32) -> (f64, f64) {
    let bins = &state.tiles;
    let k = settings.k();
    let step = step.max(1);
    let ntiles = (bins.tiles_x * bins.tiles_y) as usize;
    let sums: Vec<[f64; 4]> = (0..ntiles)
        .into_par_iter()
        .map_init(
            || (TileData::default(), Vec::<(f32, f32)>::new()),
            |(td, list), t| {
                let (tx, ty) = (t as u32 % bins.tiles_x, t as u32 / bins.tiles_x);
                let range = bins.offsets[t] as usize..bins.offsets[t + 1] as usize;
                td.load(&state.proj, &bins.ids[range.clone()], &bins.quarter_masks[range], (tx * TILE, ty * TILE));
                let mut acc = [0.0f64; 4];
                for y in (ty * TILE..((ty + 1) * TILE).min(camera.height)).filter(|y| y % step == 0) {
                    for x in (tx * TILE..((tx + 1) * TILE).min(camera.width)).filter(|x| x % step == 0) {
                        list.clear();
                        composite_pixel(td, x as f32 + 0.5, y as f32 + 0.5, settings, k, |_, z, alpha, t| {
                            list.push((alpha * t, z))
                        });
                        for j in 0..list.len() {
                            for i in 0..j {
                                let w = list[i].0 as f64 * list[j].0 as f64;
                                acc[1] += w;
                                acc[3] += 1.0;
                                if list[i].1 > list[j].1 {
                                    acc[0] += w;
                                    acc[2] += 1.0;
                                }
                            }
                        }
                    }
                }
                acc
            },
        )
        .collect();
    let tot = sums.iter().fold([0.0f64; 4], |a, b| [a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3]]);
    (tot[0] / tot[1].max(1e-30), tot[2] / tot[3].max(1.0))
}

#[cfg(test)]
mod window_tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    #[test]
    fn single_window_matches_ring_window_at_k_1() {
        // The K = 1 path's window against the ring buffer under the forward's use: insert into
        // an empty window, pop before the next insert.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(12);
        let (mut ring, mut one) = (RingWindow::new(), SingleWindow::new());
        for slot in 0..2000u32 {
            if ring.len() == 1 && rng.random::<f32>() < 0.8 {
                assert_eq!(
                    (ring.front_slot(), ring.front_z(), ring.front_alpha()),
                    (one.front_slot(), one.front_z(), one.front_alpha())
                );
                ring.pop_front();
                one.pop_front();
            } else if ring.len() == 0 {
                let (z, alpha) = (rng.random::<f32>() - 0.2, rng.random::<f32>());
                ring.insert(z, slot * 977, alpha);
                one.insert(z, slot * 977, alpha);
            }
            assert_eq!(ring.len(), one.len());
        }
    }

    /// Drive a window and the ring window with the same random inserts (with ties, beyond and
    /// below every entry), pops and front replacements (the register windows' one-shift
    /// `replace_front` against the ring's pop then insert) for each K, comparing the whole order
    /// after every operation.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    fn matches_ring_window<W: Window + Copy>(new: impl Fn() -> W, ks: &[usize], seed: u64) {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        for &k in ks {
            let (mut ring, mut reg) = (RingWindow::new(), new());
            let mut slot = 0u32;
            for _ in 0..3000 {
                let z = match rng.random_range(0..10) {
                    0..3 => 0.5,
                    3 => 1.0 + rng.random::<f32>(),
                    4 => -rng.random::<f32>(),
                    _ => rng.random::<f32>(),
                };
                // Slots beyond u8 and u16: the forward stores tile-list indices.
                slot = slot.wrapping_add(1 + rng.random_range(0..100_000));
                let alpha = rng.random::<f32>();
                let op = rng.random::<f32>();
                if ring.len() > 0 && (ring.len() == k || op < 0.6) {
                    assert_eq!(ring.front_slot(), reg.front_slot());
                    assert_eq!(ring.front_z(), reg.front_z());
                    assert_eq!(ring.front_alpha(), reg.front_alpha());
                    if op < 0.3 {
                        ring.pop_front();
                        reg.pop_front();
                    } else {
                        ring.pop_front();
                        ring.insert(z, slot, alpha);
                        reg.replace_front(z, slot, alpha);
                    }
                } else {
                    ring.insert(z, slot, alpha);
                    reg.insert(z, slot, alpha);
                }
                assert_eq!(ring.len(), reg.len());
                // Compare the whole order by draining copies.
                let (mut a, mut b) = (ring, reg);
                while a.len() > 0 {
                    assert_eq!(a.front_slot(), b.front_slot(), "k = {k}");
                    assert_eq!((a.front_z(), a.front_alpha()), (b.front_z(), b.front_alpha()));
                    a.pop_front();
                    b.pop_front();
                }
            }
        }
    }

    /// The AVX2 register window (K ≤ 8) keeps exactly the ring window's order.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[test]
    fn avx2_register_window_matches_ring_window() {
        matches_ring_window(RegWindow8::new, &[1, 2, 3, 5, 7, 8], 13);
    }

    /// The AVX-512 register window (K ≤ 16) keeps exactly the ring window's order.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
    #[test]
    fn register_window_matches_ring_window() {
        matches_ring_window(RegWindow::new, &[1, 2, 5, 8, 16], 11);
    }
}

#[cfg(test)]
mod exp_tests {
    use super::*;

    /// The inlined exponential is `wide`'s bit for bit wherever a hit can be (x ≥ −87), and
    /// at most 2 ulp from f64 there; below −87 it stays tiny (no hit either way).
    #[test]
    fn exp_nonpositive_matches_wide_exp_bit_for_bit() {
        let mut checked = 0;
        let mut x = 0.0f32;
        let mut lanes = [0.0f32; 16];
        while x > -86.9 {
            for (l, v) in lanes.iter_mut().enumerate() {
                *v = x - l as f32 * 1.3e-3;
            }
            let (ours, theirs) = (exp_nonpositive(f32x16::new(lanes)), f32x16::new(lanes).exp());
            for l in 0..16 {
                let (a, b) = (ours.to_array()[l], theirs.to_array()[l]);
                assert_eq!(a.to_bits(), b.to_bits(), "x = {}", lanes[l]);
                let exact = (lanes[l] as f64).exp();
                assert!(((a as f64 - exact) / exact).abs() < 2.5e-7, "x = {}: {a} vs {exact}", lanes[l]);
            }
            checked += 16;
            x -= 0.0173;
        }
        assert!(checked > 50_000);
        // Edges: 0, −0, the clamp, far below it, −∞ and NaN (never hits: tiny or NaN-free).
        let edge = exp_nonpositive(f32x16::new([
            0.0,
            -0.0,
            -87.0,
            -200.0,
            f32::NEG_INFINITY,
            f32::NAN,
            -1e-30,
            -0.5,
            -5.5,
            -86.99,
            -3.0,
            -1.0,
            -2.0,
            -10.0,
            -20.0,
            -40.0,
        ]))
        .to_array();
        assert_eq!(edge[0], 1.0);
        assert_eq!(edge[1], 1.0);
        for &v in &edge[2..6] {
            assert!((0.0..1e-37).contains(&v), "{v}");
        }
        assert_eq!(edge[6], 1.0);
    }
}
