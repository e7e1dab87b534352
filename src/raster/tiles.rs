//! Binning of projected surfels into 16 × 16 tiles, each tile's list sorted by centre depth
//! (ties by surfel index), so every pixel receives its candidates in the plain 2DGS order.
//!
//! Layout: the (tile, surfel) pairs are stored tile after tile (`offsets`, `ids`). A surfel's
//! pairs are also numbered in generation order (surfel by surfel, tiles of its rectangle row
//! by row: `pair_offsets`), and `sorted_of_gen` maps that number to the pair's position in the
//! tile-major list, so the backward pass can write per-pair gradient rows tile by tile and sum
//! them per surfel afterwards without atomics.
//!
//! A surfel joins only the tiles of its bounding box that its α ≥ α_min footprint touches
//! ([`Footprint`]): dropped pairs would evaluate to α < α_min at every pixel anyway. Each pair
//! also carries which quarters (8 × 8) of its tile the footprint touches (`quarter_masks`):
//! the compositor lists a candidate only in those (`forward::TileData::load`).
//!
//! Parallel decomposition: the per-surfel tile lists (with the footprint test) are built with
//! rayon over chunks of surfels; the surfels that have pairs are put in depth order once (a
//! serial radix sort, [`depth_order`]), and the pairs are scattered in that order (in parallel
//! over bands of tiles): each tile's list comes out sorted with no per-tile sort.

use super::TILE;
use super::forward::QUARTER;
use super::project::Projected;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU32, Ordering};

#[derive(Clone, Debug, Default)]
pub struct TileBins {
    pub tiles_x: u32,
    pub tiles_y: u32,
    /// Tile t's pairs are `ids[offsets[t]..offsets[t + 1]]`.
    pub offsets: Vec<u32>,
    /// Surfel index of each pair, tile-major, depth-sorted within a tile.
    pub ids: Vec<u32>,
    /// Per pair (as `ids`): the quarters of the tile its footprint touches, bit q for quarter
    /// q (0 top left, 1 top right, 2 bottom left, 3 bottom right); 0b1111 where the footprint
    /// was not computed.
    pub quarter_masks: Vec<u8>,
    /// Surfel i's pairs in generation order are numbers `pair_offsets[i]..pair_offsets[i + 1]`.
    pub pair_offsets: Vec<u32>,
    /// Generation number → position in `ids`.
    pub sorted_of_gen: Vec<u32>,
}

impl TileBins {
    /// Each row of tiles' (tile, surfel) pairs: roughly what compositing it costs.
    pub(crate) fn row_pairs(&self) -> Vec<u32> {
        (0..self.tiles_y)
            .map(|ty| self.offsets[((ty + 1) * self.tiles_x) as usize] - self.offsets[(ty * self.tiles_x) as usize])
            .collect()
    }
}

/// A slice of u32 viewed as atomics for the time of its exclusive borrow (what the unstable
/// `AtomicU32::from_mut_slice` does): lets threads store to disjoint but interleaved entries.
fn as_atomic(v: &mut [u32]) -> &[AtomicU32] {
    // SAFETY: AtomicU32 has the size, alignment and bit validity of u32, and the returned view
    // borrows `v` exclusively, so nothing else reads or writes it meanwhile.
    unsafe { std::slice::from_raw_parts(v.as_mut_ptr() as *const AtomicU32, v.len()) }
}

/// Split a slice into consecutive pieces at `offsets` (offsets[0] = 0, last = len).
/// Inlined everywhere: left as one shared function, it changed how the backward's tile loop
/// compiled (a spill in its hot loop, 10 % slower; BENCHMARKS.md, session 25).
#[inline(always)]
pub(crate) fn split_by_offsets<'a, T>(mut data: &'a mut [T], offsets: &[u32]) -> Vec<&'a mut [T]> {
    let mut out = Vec::with_capacity(offsets.len().saturating_sub(1));
    for w in offsets.windows(2) {
        let (a, b) = std::mem::take(&mut data).split_at_mut((w[1] - w[0]) as usize);
        out.push(a);
        data = b;
    }
    out
}

pub fn bin(p: &Projected, width: u32, height: u32, alpha_min: f32, filter_inv_square: f32) -> TileBins {
    let tiles_x = width.div_ceil(TILE);
    let tiles_y = height.div_ceil(TILE);
    let ntiles = (tiles_x * tiles_y) as usize;
    let n = p.rect.len();
    // Pass 1: each surfel's tiles (its rectangle row by row, minus the tiles its α ≥ α_min
    // region misses) in generation order, in parallel over chunks of surfels (the footprint
    // test is f64 work); chunks are joined in surfel order, so the result does not depend on
    // the thread count.
    let chunk = n.div_ceil(4 * rayon::current_num_threads()).max(2048);
    let footprints = || -> Vec<(Vec<u32>, Vec<u8>, Vec<u32>)> {
        (0..n.div_ceil(chunk))
            .into_par_iter()
            .map(|c| {
                let range = c * chunk..((c + 1) * chunk).min(n);
                let mut tiles_of: Vec<u32> = Vec::with_capacity(range.len() * 4);
                let mut masks_of: Vec<u8> = Vec::with_capacity(range.len() * 4);
                let mut ends: Vec<u32> = Vec::with_capacity(range.len());
                for i in range {
                    let r = p.rect[i];
                    if r[0] <= r[2] && r[1] <= r[3] {
                        // A one-row or one-column rectangle almost never loses a tile (the footprint
                        // is connected and spans its box): skip the test there, it costs more than
                        // it saves on the many small surfels of training (rand 10k: +0.06 %
                        // evaluations). Its quarters are then left to the pixel box
                        // (`TileData::load`).
                        let footprint = if r[2] > r[0] && r[3] > r[1] {
                            Footprint::new(p, i, alpha_min, filter_inv_square)
                        } else {
                            None
                        };
                        for ty in r[1]..=r[3] {
                            let Some(f) = footprint.as_ref() else {
                                tiles_of.extend((r[0]..=r[2]).map(|tx| ty * tiles_x + tx));
                                masks_of.extend((r[0]..=r[2]).map(|_| 0b1111u8));
                                continue;
                            };
                            // Per half row of tiles (a band of quarters) the footprint covers one
                            // or two runs of quarter columns; a tile joins when a quarter does.
                            let q = QUARTER as f64;
                            let band0 = (2 * ty) as f64 * q;
                            let runs = [f.runs(band0, band0 + q, q), f.runs(band0 + q, band0 + 2.0 * q, q)];
                            let touches = |band: usize, col: u32| runs[band].iter().any(|&(a, b)| a <= col && col <= b);
                            for tx in r[0]..=r[2] {
                                let (left, right) = (2 * tx, 2 * tx + 1);
                                let mask = touches(0, left) as u8
                                    | (touches(0, right) as u8) << 1
                                    | (touches(1, left) as u8) << 2
                                    | (touches(1, right) as u8) << 3;
                                if mask != 0 {
                                    tiles_of.push(ty * tiles_x + tx);
                                    masks_of.push(mask);
                                }
                            }
                        }
                    }
                    ends.push(tiles_of.len() as u32);
                }
                (tiles_of, masks_of, ends)
            })
            .collect()
    };
    // Surfels with a tile rectangle by (depth, index), sorted beside the footprint pass (the
    // sort is serial); those whose footprint then misses every tile are dropped below.
    let has_rect = |i: u32| {
        let r = p.rect[i as usize];
        r[0] <= r[2] && r[1] <= r[3]
    };
    let (parts, rect_order) = rayon::join(footprints, || depth_order(&p.depth, (0..n as u32).filter(|&i| has_rect(i))));
    let mut pair_offsets = Vec::with_capacity(n + 1);
    pair_offsets.push(0u32);
    let total: usize = parts.iter().map(|(t, _, _)| t.len()).sum();
    let mut pair_tiles: Vec<u32> = Vec::with_capacity(total);
    let mut pair_masks: Vec<u8> = Vec::with_capacity(total);
    let mut counts = vec![0u32; ntiles + 1];
    for (tiles_of, masks_of, ends) in &parts {
        let base = pair_tiles.len() as u32;
        pair_offsets.extend(ends.iter().map(|e| base + e));
        for &t in tiles_of {
            counts[t as usize + 1] += 1;
        }
        pair_tiles.extend_from_slice(tiles_of);
        pair_masks.extend_from_slice(masks_of);
    }
    drop(parts);
    for t in 0..ntiles {
        counts[t + 1] += counts[t];
    }
    let offsets = counts;
    // Surfels by (depth, index), then their pairs scattered in that order: every tile's list
    // comes out sorted by centre depth (ties by index) without a per-tile sort, and a pair's
    // generation number g is at hand when its position is chosen (`sorted_of_gen`).
    let mut order = rect_order;
    order.retain(|&i| pair_offsets[i as usize] < pair_offsets[i as usize + 1]);
    // The scatter in parallel over bands of tiles (each about an equal share of the pairs): a
    // band walks every surfel in depth order and places the pairs that fall in its tiles, so its
    // stretch of `ids` is its own. `sorted_of_gen` is indexed by pair, and a surfel's pairs can
    // fall in two bands: it is written through relaxed atomic stores (each entry once).
    let bands = rayon::current_num_threads().clamp(1, ntiles.max(1));
    let mut band_tiles = vec![0usize; bands + 1];
    for (b, bound) in band_tiles.iter_mut().enumerate().skip(1) {
        let want = (total as u64 * b as u64 / bands as u64) as u32;
        *bound = offsets[..=ntiles].partition_point(|&o| o < want).min(ntiles);
    }
    band_tiles[bands] = ntiles;
    // Per surfel in depth order (each has a pair): its pair range and its first and last tile
    // index (pairs run in tile order), read once here so that each band streams through them.
    let spans: Vec<[u32; 4]> = order
        .par_iter()
        .map(|&i| {
            let (g0, g1) = (pair_offsets[i as usize], pair_offsets[i as usize + 1]);
            [g0, g1, pair_tiles[g0 as usize], pair_tiles[g1 as usize - 1]]
        })
        .collect();
    let mut ids = vec![0u32; total];
    let mut quarter_masks = vec![0u8; total];
    let mut sorted_of_gen = vec![0u32; total];
    let sorted_shared = as_atomic(&mut sorted_of_gen);
    let band_starts: Vec<u32> = band_tiles.iter().map(|&t| offsets[t]).collect();
    let band_ids = split_by_offsets(&mut ids, &band_starts);
    let band_masks = split_by_offsets(&mut quarter_masks, &band_starts);
    band_ids.into_par_iter().zip(band_masks).enumerate().for_each(|(b, (ids, masks))| {
        let (tile0, tile1) = (band_tiles[b] as u32, band_tiles[b + 1] as u32);
        if tile0 == tile1 {
            return;
        }
        let base = offsets[tile0 as usize];
        let mut fill: Vec<u32> = offsets[tile0 as usize..tile1 as usize].iter().map(|&o| o - base).collect();
        for (&i, &[g0, g1, first, last]) in order.iter().zip(&spans) {
            if last < tile0 || first >= tile1 {
                continue;
            }
            let (g0, g1) = (g0 as usize, g1 as usize);
            for (g, &t) in (g0..g1).zip(&pair_tiles[g0..g1]) {
                if t >= tile0 && t < tile1 {
                    let slot = &mut fill[(t - tile0) as usize];
                    ids[*slot as usize] = i;
                    masks[*slot as usize] = pair_masks[g];
                    sorted_shared[g].store(base + *slot, Ordering::Relaxed);
                    *slot += 1;
                }
            }
        }
    });
    drop(pair_tiles);
    TileBins { tiles_x, tiles_y, offsets, ids, quarter_masks, pair_offsets, sorted_of_gen }
}

/// `f(state, row, item)` for every row of tiles, largest first by `cost`: one job per thread,
/// each taking the next row from a shared counter (with its own `init()` state), so that the
/// rows left at the end are the cheap ones. Rayon's halving split over rows in image order left
/// one thread idle for up to a whole row at the end (relit spheres frame at 400²: ≈ 3 ms of a
/// 50 ms tile loop). The forward and the backward both run their rows this way. Each row's outputs do not depend on the order. Returns the sums of the
/// rows' evaluation counts.
pub(crate) fn rows_largest_first<T: Send, S>(
    items: Vec<T>,
    cost: &[u32],
    init: impl Fn() -> S + Sync,
    f: impl Fn(&mut S, usize, T) -> (u64, u64) + Sync,
) -> (u64, u64) {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicUsize, Ordering};
    let mut order: Vec<usize> = (0..items.len()).collect();
    order.sort_by_key(|&r| (std::cmp::Reverse(cost.get(r).copied().unwrap_or(0)), r));
    let slots: Vec<Mutex<Option<T>>> = items.into_iter().map(|item| Mutex::new(Some(item))).collect();
    let next = AtomicUsize::new(0);
    let jobs = rayon::current_num_threads().min(order.len()).max(1);
    (0..jobs)
        .into_par_iter()
        .map(|_| {
            let mut state = init();
            let mut sums = (0u64, 0u64);
            while let Some(&row) = order.get(next.fetch_add(1, Ordering::Relaxed)) {
                // Each row is claimed once (the counter), so its lock is never contended.
                let item = slots[row].lock().unwrap_or_else(|e| e.into_inner()).take();
                if let Some(item) = item {
                    let r = f(&mut state, row, item);
                    sums = (sums.0 + r.0, sums.1 + r.1);
                }
            }
            sums
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
}

/// The surfels `ids` (ascending) ordered by (depth, index): a stable least-significant-digit
/// radix sort (three passes of 11, 11 and 10 bits) on an order-preserving integer form of the
/// depth, so ties keep index order. O(n), where a comparison sort of the keys was a fifth of a
/// relit frame's binning.
fn depth_order(depth: &[f32], ids: impl Iterator<Item = u32>) -> Vec<u32> {
    // Flip negatives entirely and positives' sign bit: the integers then order as the floats.
    let key = |i: u32| {
        let b = depth[i as usize].to_bits();
        if b >> 31 == 1 { !b } else { b | 1 << 31 }
    };
    let mut order: Vec<u32> = ids.collect();
    let mut counts = [[0u32; 2048]; 3];
    for &i in &order {
        let k = key(i);
        counts[0][(k & 0x7ff) as usize] += 1;
        counts[1][(k >> 11 & 0x7ff) as usize] += 1;
        counts[2][(k >> 22) as usize] += 1;
    }
    let mut scratch = vec![0u32; order.len()];
    for (pass, count) in counts.iter_mut().enumerate() {
        let shift = 11 * pass as u32;
        // Every key sharing this digit: the pass would only copy.
        if count.iter().any(|&c| c as usize == order.len()) {
            continue;
        }
        let mut start = 0u32;
        for c in count.iter_mut() {
            (*c, start) = (start, start + *c);
        }
        for &i in &order {
            let digit = (key(i) >> shift & 0x7ff) as usize;
            scratch[count[digit] as usize] = i;
            count[digit] += 1;
        }
        std::mem::swap(&mut order, &mut scratch);
    }
    order
}

/// The pixels where a surfel's α can reach α_min: the ray–disk region ρ₃ = u² + v² ≤ r² (an
/// ellipse in the image when the disk does not reach the camera plane) and the screen-space
/// filter circle ρ₂ = f|μ₂D − p|² ≤ r², r² = 2 ln(o / α_min), f = `filter_inv_square`. A tile of the bounding box that
/// neither touches is dropped from the surfel's list: every pixel of it would evaluate the
/// surfel to α < α_min and skip it, so images and gradients are unchanged.
///
/// For pixel p = (x, y, 1) the plane point is (u, v, 1) ∝ h = x·A + y·B + C with A = T_v × T_w,
/// B = T_w × T_u, C = T_u × T_v (the cross product the compositor evaluates), so ρ₃ ≤ r² is
/// the quadratic f(x, y) = h₀² + h₁² − r²·h₂² ≤ 0. When its 2 × 2 part is positive definite
/// (a bounded ellipse) each half row of tiles (a band of quarters) keeps the quarter columns
/// the ellipse's x interval within the band meets, and those the circle's does (`runs`); a
/// tile is kept when one of its quarters is. Other cases keep every tile and quarter.
/// f64, with the cells grown by half a pixel, r² by 1 % and the intervals by 10⁻³ px
/// (conservative).
struct Footprint {
    /// f(x, y) = qxx x² + 2 qxy x y + qyy y² + 2 lx x + 2 ly y + c.
    qxx: f64,
    qxy: f64,
    qyy: f64,
    lx: f64,
    ly: f64,
    c: f64,
    mean: [f64; 2],
    /// Squared radius of the filter circle.
    circle_r2: f64,
    ellipse: EllipseShape,
}

/// What `runs` needs of the ellipse f ≤ 0, computed once per surfel.
#[derive(Default)]
struct EllipseShape {
    /// The centre's y and f there (> 0: empty; NaN: degenerate).
    cy: f64,
    fc: f64,
    /// Half height.
    half_h: f64,
    /// The leftmost point lies at y = cy + lean, the rightmost at cy − lean.
    lean: f64,
    inv_qxx: f64,
}

impl Footprint {
    fn new(p: &Projected, i: usize, alpha_min: f32, filter_inv_square: f32) -> Option<Footprint> {
        let o = p.opacity(i) as f64;
        if !(alpha_min > 0.0) || !(o > 0.0) {
            return None;
        }
        let r2 = 2.0 * (o / alpha_min as f64).ln() * 1.01 + 1e-6;
        let v = |a: [f32; 3]| a.map(|x| x as f64);
        let (tu, tv, tw) = (v(p.tu(i)), v(p.tv(i)), v(p.tw(i)));
        let cross = |a: [f64; 3], b: [f64; 3]| {
            [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
        };
        let (a, b, c) = (cross(tv, tw), cross(tw, tu), cross(tu, tv));
        let w = [1.0, 1.0, -r2];
        let sum = |f: &dyn Fn(usize) -> f64| (0..3).map(|k| w[k] * f(k)).sum::<f64>();
        let (qxx, qxy, qyy) = (sum(&|k| a[k] * a[k]), sum(&|k| a[k] * b[k]), sum(&|k| b[k] * b[k]));
        let (lx, ly, cc) = (sum(&|k| a[k] * c[k]), sum(&|k| b[k] * c[k]), sum(&|k| c[k] * c[k]));
        let scale = qxx.abs().max(qyy.abs());
        let bounded = qxx > 0.0 && qyy > 0.0 && qxx * qyy - qxy * qxy > 1e-9 * scale * scale;
        let f = Footprint {
            qxx,
            qxy,
            qyy,
            lx,
            ly,
            c: cc,
            mean: p.mean2d(i).map(|x| x as f64),
            circle_r2: r2 / filter_inv_square as f64,
            ellipse: EllipseShape::default(),
        };
        if !bounded || !f.c.is_finite() || !f.mean[0].is_finite() || !f.mean[1].is_finite() {
            return None; // keep the whole rectangle
        }
        let mut f = f;
        let det = qxx * qyy - qxy * qxy;
        let (cx, cy) = ((qxy * ly - qyy * lx) / det, (qxy * lx - qxx * ly) / det);
        let fc = f.f(cx, cy);
        let half_w = (-fc * qyy / det).max(0.0).sqrt();
        let half_h = (-fc * qxx / det).max(0.0).sqrt();
        // Extremes in x where ∂f/∂y = 0: y − cy = −(qxy / qyy)(x − cx).
        f.ellipse = EllipseShape { cy, fc, half_h, lean: qxy / qyy * half_w, inv_qxx: 1.0 / qxx };
        Some(f)
    }

    /// The cells of side `t` (tiles or quarters) in the band of pixel rows y0 ≤ y ≤ y1 (cell
    /// edges: the cells' pixel centres grown by half a pixel) that the filter circle or the
    /// ellipse touches, as two inclusive runs of cell columns (a run with start > end is
    /// empty). A convex region meets the band in one x interval: for the ellipse it runs from
    /// its left boundary at the band's y nearest the leftmost point to its right boundary at the
    /// y nearest the rightmost point (the boundary is convex in y); for the circle from the
    /// centre's row.
    fn runs(&self, y0: f64, y1: f64, t: f64) -> [(u32, u32); 2] {
        debug_assert!(t > 0.0 && (t as u32).is_power_of_two());
        let inv_t = 1.0 / t;
        let run = |lo: f64, hi: f64| -> (u32, u32) {
            // A small absolute margin so that rounding never drops a touching tile.
            let (lo, hi) = (lo - 1e-3, hi + 1e-3);
            if !(lo <= hi) || hi < 0.0 {
                return (1, 0);
            }
            // t is a power of two: × 1/t is exactly ÷ t, without a divide's latency.
            (
                (lo.max(0.0) * inv_t).floor().min(u32::MAX as f64) as u32,
                (hi * inv_t).floor().min(u32::MAX as f64) as u32,
            )
        };
        // Filter circle.
        let dy = (y0 - self.mean[1]).max(0.0).max(self.mean[1] - y1);
        let circle = if dy * dy <= self.circle_r2 {
            let half = (self.circle_r2 - dy * dy).sqrt();
            run(self.mean[0] - half, self.mean[0] + half)
        } else {
            (1, 0)
        };
        let e = &self.ellipse;
        let ellipse = if e.fc.is_nan() {
            (0, u32::MAX) // degenerate numbers keep the row
        } else if e.fc > 0.0 {
            (1, 0) // empty
        } else {
            let (ya, yb) = (y0.max(e.cy - e.half_h), y1.min(e.cy + e.half_h));
            if ya.is_nan() || yb.is_nan() {
                (0, u32::MAX)
            } else if ya > yb {
                (1, 0)
            } else {
                // x roots of f(·, y) = 0: (−(qxy y + lx) ± √D) / qxx (− left, + right).
                let root = |y: f64, sign: f64| {
                    let b = self.qxy * y + self.lx;
                    let d = (b * b - self.qxx * (self.qyy * y * y + 2.0 * self.ly * y + self.c)).max(0.0).sqrt();
                    (-b + sign * d) * e.inv_qxx
                };
                let left = root((e.cy + e.lean).clamp(ya, yb), -1.0);
                let right = root((e.cy - e.lean).clamp(ya, yb), 1.0);
                if left.is_finite() && right.is_finite() { run(left, right) } else { (0, u32::MAX) }
            }
        };
        [circle, ellipse]
    }
    fn f(&self, x: f64, y: f64) -> f64 {
        self.qxx * x * x + 2.0 * self.qxy * x * y + self.qyy * y * y + 2.0 * (self.lx * x + self.ly * y) + self.c
    }
}

#[cfg(test)]
mod tests {
    use rand::{RngExt, SeedableRng};

    /// The radix order is the comparison order of (depth, index) for every kind of key: ties,
    /// ±0, negatives, huge and tiny magnitudes, keys sharing their low or high digits, empty
    /// and one-element inputs, and a subset of the indices.
    #[test]
    fn depth_order_is_the_sorted_depth_then_index_order() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        for case in 0..12 {
            let n = [0, 1, 2, 17, 300, 5000][case % 6];
            let depth: Vec<f32> = (0..n)
                .map(|_| match rng.random_range(0..6) {
                    0 => rng.random_range(0.1f32..10.0),
                    1 => [0.0, -0.0, 1.0, 2.5][rng.random_range(0..4)],
                    2 => -rng.random_range(0.0f32..5.0),
                    3 => rng.random_range(1e-30f32..1e-20) * if rng.random_bool(0.5) { 1.0 } else { -1.0 },
                    4 => rng.random_range(1e20f32..1e30),
                    // Same high digits, different low bits.
                    _ => f32::from_bits(0x4000_0000 | rng.random_range(0..4096u32)),
                })
                .collect();
            let ids: Vec<u32> = (0..n as u32).filter(|&i| case < 6 || i % 3 != 1).collect();
            let mut want = ids.clone();
            want.sort_by(|&a, &b| depth[a as usize].total_cmp(&depth[b as usize]).then(a.cmp(&b)));
            assert_eq!(super::depth_order(&depth, ids.into_iter()), want, "case {case}");
        }
    }
}
