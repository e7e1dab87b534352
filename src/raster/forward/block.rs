//! Narrow frames (colour, normal, alpha, at most one feature; no record) sixteen pixels at a
//! time: SIMD over a 4 × 4 block of one tile quarter, one candidate at a time, instead of
//! one pixel over sixteen candidates.
//!
//! Why: one pixel evaluates its quarter's candidates sixteen at a time, and most groups hold
//! only a few that reach it. A block evaluates each candidate that reaches its 4 × 4 pixels
//! (its pixel box tested first) once for all of them: on the relit spheres frame 9 of the 16
//! pixels hit a candidate that reaches the block. Here the sixteen pixels' windows
//! are vectors, one per depth level, kept sorted far to near (level 0 the farthest; empty
//! levels hold z = −∞ at the near end, α = 0). A hit first takes the window's nearest level
//! out (blended if real: the full window's front), then bubbles in from the far end with
//! compare-and-select per level, so no lane branches on where it lands.
//!
//! Per pixel the hits, their order, the stops and every sum are those of
//! [`super::composite_one_pixel`] with the same window (earlier arrivals stay nearer on equal z;
//! a full window blends its front before the new hit goes in), operation for operation: the
//! frames are bit-identical (tested).

use super::{
    Evaluated, PK_BOX_X, PK_BOX_Y, PK_MEAN, PK_OP, PK_RHO, PK_TU, PK_TV, PK_TW, QUARTER, Stop, TileData, splat_alpha,
    splat_cross, splat_finish,
};
use crate::raster::{MAX_WINDOW, RasterSettings};
use wide::{f32x8, f32x16};

/// Pixels of a block: `BLOCK_W` × `BLOCK_H`, lane l at (l mod `BLOCK_W`, l div `BLOCK_W`)
/// (4 × 4 measured as fast as 8 × 2; BENCHMARKS.md, session 47).
pub(crate) const BLOCK_W: u32 = 4;
pub(crate) const BLOCK_H: u32 = 4;
/// The window size blocks composite with (the default K; other windows go pixel by pixel).
pub(crate) const BLOCK_K: usize = 8;

/// The sixteen pixels' windows: per level (0 farthest) the entries' z, tile-list slot (as the
/// bits of an f32 lane) and α.
struct BlockWindow<const K: usize> {
    z: [f32x16; K],
    slot: [f32x16; K],
    alpha: [f32x16; K],
}

/// Lanes set in `mask` (a lane-wise all-ones / zero vector) as bits.
#[inline(always)]
fn bits(mask: f32x16) -> u32 {
    mask.to_bitmask()
}

/// Composite the block whose top-left pixel is `(x0, y0)` (x0 and y0 a multiple of the
/// block's size from the tile origin: the block lies in one quarter); lanes at x ≥ `x_end`
/// or y ≥ `y_end` are outside the image and not composited (never live: they would only keep
/// the block going). Blends into `sums` (Σ w × narrow blend row per lane); returns each lane's final T and its
/// evaluation counts, as [`super::composite_one_pixel`] would.
#[inline(always)]
pub(super) fn composite_block<const K: usize>(
    td: &TileData,
    (x0, y0): (u32, u32),
    (x_end, y_end): (u32, u32),
    s: &RasterSettings,
    sums: &mut [f32x8; 16],
) -> ([f32; 16], [Evaluated; 16]) {
    const { assert!(K >= 1 && K <= MAX_WINDOW) };
    let right = x0 - td.origin.0 >= QUARTER;
    let below = y0 - td.origin.1 >= QUARTER;
    let list = &td.quarters[right as usize + 2 * below as usize];
    let stop = Stop::of(s);
    let lane = |l: usize| ((l as u32 % BLOCK_W), (l as u32 / BLOCK_W));
    // Pixel centres as the per-pixel path computes them: (x as f32) + 0.5.
    let pxv = f32x16::new(std::array::from_fn(|l| (x0 + lane(l).0) as f32 + 0.5));
    let pyv = f32x16::new(std::array::from_fn(|l| (y0 + lane(l).1) as f32 + 0.5));
    let inside = f32x16::new(std::array::from_fn(|l| {
        let (dx, dy) = lane(l);
        if x0 + dx < x_end && y0 + dy < y_end { f32::from_bits(u32::MAX) } else { 0.0 }
    }));
    let all = Evaluated { performed: list.n as u32, tile_list: td.n as u32 };
    let mut evaluated = [all; 16];
    let neg_inf = f32x16::splat(f32::NEG_INFINITY);
    let mut win = BlockWindow::<K> { z: [neg_inf; K], slot: [f32x16::ZERO; K], alpha: [f32x16::ZERO; K] };
    let mut live = inside;
    let mut t = f32x16::ONE;
    let (before, after) = (f32x16::splat(stop.before), f32x16::splat(stop.after));
    let (near, alpha_min) = (f32x16::splat(s.near), f32x16::splat(s.alpha_min));
    let front = K - 1;
    // The block's last pixel, for the candidates' pixel boxes (16-bit: beyond that the boxes
    // are clamped and not used, as in `TileData::load`).
    let (x_last, y_last) = (x0 + BLOCK_W - 1, y0 + BLOCK_H - 1);
    let boxes = x_last <= u16::MAX as u32 && y_last <= u16::MAX as u32;
    for j in 0..list.n {
        let li = list.slot[j];
        let r = &td.records[li as usize];
        // A candidate whose pixel box misses the block has no hit in it.
        let (xs, ys) = (r[PK_BOX_X].to_bits(), r[PK_BOX_Y].to_bits());
        if boxes && ((xs & 0xffff) > x_last || (xs >> 16) < x0 || (ys & 0xffff) > y_last || (ys >> 16) < y0) {
            continue;
        }
        let lanes = |f: usize| f32x16::splat(r[f]);
        let tw = [lanes(PK_TW), lanes(PK_TW + 1), lanes(PK_TW + 2)];
        let c = splat_cross(
            pxv,
            pyv,
            [lanes(PK_TU), lanes(PK_TU + 1), lanes(PK_TU + 2)],
            [lanes(PK_TV), lanes(PK_TV + 1), lanes(PK_TV + 2)],
            tw,
            [lanes(PK_MEAN), lanes(PK_MEAN + 1)],
            s.filter_inv_square,
        );
        let rho_max = lanes(PK_RHO);
        if bits(c.may_reach(rho_max) & live) == 0 {
            continue;
        }
        let e = splat_finish(c, tw);
        let ok = e.hz.simd_ne(f32x16::ZERO) & e.z.simd_ge(near) & e.rho.simd_le(rho_max) & live;
        if bits(ok) == 0 {
            continue;
        }
        let (_, alpha, _) = splat_alpha(e.rho, lanes(PK_OP));
        let hit = ok & alpha.simd_ge(alpha_min);
        if bits(hit) == 0 {
            continue;
        }
        // The nearest level leaves first: a full window's front is blended (or stops the
        // pixel), an empty level (α = 0) changes nothing.
        let fa = win.alpha[front];
        let next = t * (f32x16::ONE - fa);
        let stop_before = hit & next.simd_lt(before);
        let blended = hit & !stop_before;
        let real = blended & win.z[front].simd_ne(neg_inf);
        blend_lanes(td, sums, bits(real), fa * t, win.slot[front]);
        t = blended.select(next, t);
        let dead = stop_before | (blended & next.simd_lt(after));
        let dead_bits = bits(dead);
        if dead_bits != 0 {
            let mut m = dead_bits;
            while m != 0 {
                let l = m.trailing_zeros() as usize;
                m &= m - 1;
                evaluated[l] = Evaluated { performed: j as u32 + 1, tile_list: li + 1 };
            }
            live &= !dead;
        }
        // The hit bubbles in from the far end: at each level it takes the place of an entry
        // with z ≤ its own (that entry moves one level nearer), so equal depths keep their
        // arrival order; the last carry fills the vacated nearest level.
        let insert = hit & !dead;
        let (mut cz, mut cs, mut ca) = (e.z, f32x16::splat(f32::from_bits(li)), alpha);
        for level in 0..front {
            let m = insert & cz.simd_ge(win.z[level]);
            let (oz, os, oa) = (win.z[level], win.slot[level], win.alpha[level]);
            win.z[level] = m.select(cz, oz);
            win.slot[level] = m.select(cs, os);
            win.alpha[level] = m.select(ca, oa);
            cz = m.select(oz, cz);
            cs = m.select(os, cs);
            ca = m.select(oa, ca);
        }
        win.z[front] = insert.select(cz, win.z[front]);
        win.slot[front] = insert.select(cs, win.slot[front]);
        win.alpha[front] = insert.select(ca, win.alpha[front]);
        if bits(live) == 0 {
            break;
        }
    }
    // Flush nearest first, with the same stops.
    for level in (0..K).rev() {
        let real = live & win.z[level].simd_ne(neg_inf);
        if bits(real) == 0 {
            continue;
        }
        let a = win.alpha[level];
        let next = t * (f32x16::ONE - a);
        let blended = real & !next.simd_lt(before);
        blend_lanes(td, sums, bits(blended), a * t, win.slot[level]);
        t = blended.select(next, t);
        live = live & !(real & !blended) & !(blended & next.simd_lt(after));
    }
    (t.to_array(), evaluated)
}

/// For each lane in `mask`: its pixel's sums += weight × the narrow blend row of its slot
/// (the per-pixel path's `PixelSums::blend::<true, true>`, same multiply-add).
#[inline(always)]
fn blend_lanes(td: &TileData, sums: &mut [f32x8; 16], mut mask: u32, weight: f32x16, slot: f32x16) {
    if mask == 0 {
        return;
    }
    let (w, sl) = (weight.to_array(), slot.to_array());
    while mask != 0 {
        let l = mask.trailing_zeros() as usize;
        mask &= mask - 1;
        let row = td.blend_rows8[sl[l].to_bits() as usize];
        sums[l] = row.mul_add(f32x8::splat(w[l]), sums[l]);
    }
}
