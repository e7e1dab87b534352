//! Sixteen-lane helpers the backward pass uses to work on 16 blended hits at once: masked
//! gathers from per-candidate arrays and a transposed add of per-hit gradient columns into the
//! hits' (tile, surfel) gradient rows. AVX-512 or AVX2 when the build has it, plain loops otherwise
//! (same results either way: a gather and a transpose do no arithmetic).

use wide::f32x16;

/// Sixteen indices, the first `live` of them in use, all below `limit` (checked once when
/// built, so each gather from an array of at least `limit` entries needs one comparison).
pub(crate) struct Gather16 {
    idx: [u32; 16],
    live: usize,
    limit: usize,
}

impl Gather16 {
    /// Panics if a live index is ≥ limit.
    #[inline(always)]
    pub fn new(idx: [u32; 16], live: usize, limit: usize) -> Self {
        let max = idx[..live].iter().fold(0u32, |m, &i| m.max(i));
        assert!(live <= 16 && (live == 0 || (max as usize) < limit) && limit <= i32::MAX as usize);
        Gather16 { idx, live, limit }
    }

    /// base[idx[l]] for the live lanes, 0 elsewhere (those lanes read no memory). Panics if
    /// `base` is shorter than the limit.
    #[inline(always)]
    pub fn from(&self, base: &[f32]) -> f32x16 {
        assert!(base.len() >= self.limit);
        #[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
        {
            use std::arch::x86_64::*;
            // SAFETY: avx512f is enabled at compile time; every live index is below `limit`
            // (checked in `new`) ≤ base.len(), and masked-off lanes touch no memory.
            unsafe {
                let vi = _mm512_loadu_si512(self.idx.as_ptr() as *const _);
                let m: __mmask16 = ((1u32 << self.live) - 1) as u16;
                let g = _mm512_mask_i32gather_ps::<4>(_mm512_setzero_ps(), m, vi, base.as_ptr());
                std::mem::transmute::<__m512, f32x16>(g)
            }
        }
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2", not(target_feature = "avx512f")))]
        {
            use std::arch::x86_64::*;
            // SAFETY: avx2 is enabled at compile time; every live index is below `limit`
            // (checked in `new`) ≤ base.len(), and masked-off lanes touch no memory. Two
            // 8-lane gathers instead of 16 scalar loads assembled through the stack.
            unsafe {
                let lanes = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
                let live = _mm256_set1_epi32(self.live as i32);
                let m_lo = _mm256_castsi256_ps(_mm256_cmpgt_epi32(live, lanes));
                let m_hi = _mm256_castsi256_ps(_mm256_cmpgt_epi32(live, _mm256_add_epi32(lanes, _mm256_set1_epi32(8))));
                let i_lo = _mm256_loadu_si256(self.idx.as_ptr() as *const __m256i);
                let i_hi = _mm256_loadu_si256(self.idx.as_ptr().add(8) as *const __m256i);
                let zero = _mm256_setzero_ps();
                let lo = _mm256_mask_i32gather_ps::<4>(zero, base.as_ptr(), i_lo, m_lo);
                let hi = _mm256_mask_i32gather_ps::<4>(zero, base.as_ptr(), i_hi, m_hi);
                let mut out = [0.0f32; 16];
                _mm256_storeu_ps(out.as_mut_ptr(), lo);
                _mm256_storeu_ps(out.as_mut_ptr().add(8), hi);
                f32x16::new(out)
            }
        }
        #[cfg(not(all(target_arch = "x86_64", any(target_feature = "avx512f", target_feature = "avx2"))))]
        {
            f32x16::new(std::array::from_fn(|l| if l < self.live { base[self.idx[l] as usize] } else { 0.0 }))
        }
    }
}

/// 16 × 16 transpose: out[l] lane c = cols[c] lane l.
#[inline(always)]
pub(crate) fn transpose(cols: [f32x16; 16]) -> [f32x16; 16] {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
    {
        use std::arch::x86_64::*;
        // SAFETY: avx512f is enabled at compile time; f32x16 and __m512 are both 64 bytes.
        unsafe {
            let r: [__m512; 16] = std::mem::transmute::<[f32x16; 16], [__m512; 16]>(cols);
            let pd = |x: __m512| _mm512_castps_pd(x);
            let ps = |x: __m512d| _mm512_castpd_ps(x);
            // Interleave pairs of rows, then pairs of pairs (2 × 2 and 4 × 4 blocks inside
            // each 128-bit lane), then move 128-bit blocks twice.
            let mut t = [_mm512_setzero_ps(); 16];
            for i in 0..8 {
                t[2 * i] = _mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
                t[2 * i + 1] = _mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
            }
            let mut u = [_mm512_setzero_ps(); 16];
            for q in 0..4 {
                let b = 4 * q;
                u[b] = ps(_mm512_unpacklo_pd(pd(t[b]), pd(t[b + 2])));
                u[b + 1] = ps(_mm512_unpackhi_pd(pd(t[b]), pd(t[b + 2])));
                u[b + 2] = ps(_mm512_unpacklo_pd(pd(t[b + 1]), pd(t[b + 3])));
                u[b + 3] = ps(_mm512_unpackhi_pd(pd(t[b + 1]), pd(t[b + 3])));
            }
            for h in 0..2 {
                let b = 8 * h;
                for i in 0..4 {
                    t[b + i] = _mm512_shuffle_f32x4::<0x88>(u[b + i], u[b + 4 + i]);
                    t[b + 4 + i] = _mm512_shuffle_f32x4::<0xdd>(u[b + i], u[b + 4 + i]);
                }
            }
            let mut out = [_mm512_setzero_ps(); 16];
            for i in 0..8 {
                out[i] = _mm512_shuffle_f32x4::<0x88>(t[i], t[8 + i]);
                out[8 + i] = _mm512_shuffle_f32x4::<0xdd>(t[i], t[8 + i]);
            }
            std::mem::transmute::<[__m512; 16], [f32x16; 16]>(out)
        }
    }
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2", not(target_feature = "avx512f")))]
    {
        use std::arch::x86_64::*;
        // Four 8 × 8 blocks of ymm halves; `wide`'s own transpose moves the 256 floats one at
        // a time (20 % of the raster backward's time on an AVX2-only VM, session 86).
        // SAFETY: avx2 is enabled at compile time; without avx512f f32x16 is #[repr(C)] of two
        // f32x8 (lanes 0–7, then 8–15), 64 bytes like [__m256; 2].
        unsafe {
            let r: [[__m256; 2]; 16] = std::mem::transmute::<[f32x16; 16], [[__m256; 2]; 16]>(cols);
            let block = |half: usize, c0: usize| -> [__m256; 8] {
                let m: [__m256; 8] = std::array::from_fn(|i| r[c0 + i][half]);
                transpose8(m)
            };
            let (a, b, c, d) = (block(0, 0), block(0, 8), block(1, 0), block(1, 8));
            let out: [[__m256; 2]; 16] =
                std::array::from_fn(|l| if l < 8 { [a[l], b[l]] } else { [c[l - 8], d[l - 8]] });
            std::mem::transmute::<[[__m256; 2]; 16], [f32x16; 16]>(out)
        }
    }
    #[cfg(not(all(target_arch = "x86_64", any(target_feature = "avx2", target_feature = "avx512f"))))]
    {
        f32x16::transpose(cols)
    }
}

/// 8 × 8 transpose of ymm rows: out[j] lane i = r[i] lane j. Pairs of rows interleaved, then
/// pairs of pairs, then the 128-bit halves exchanged.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2", not(target_feature = "avx512f")))]
#[inline(always)]
fn transpose8(r: [std::arch::x86_64::__m256; 8]) -> [std::arch::x86_64::__m256; 8] {
    use std::arch::x86_64::*;
    // SAFETY: avx2 (and so avx) is enabled at compile time; these are register shuffles.
    unsafe {
        let t: [__m256; 8] = std::array::from_fn(|i| {
            let (x, y) = (r[i & !1], r[i | 1]);
            if i % 2 == 0 { _mm256_unpacklo_ps(x, y) } else { _mm256_unpackhi_ps(x, y) }
        });
        // s[4h + q]: rows 4h..4h + 4 of columns q and q + 4.
        let s: [__m256; 8] = std::array::from_fn(|k| {
            let (h, q) = (k / 4, k % 4);
            let (x, y) = (t[4 * h + q / 2], t[4 * h + 2 + q / 2]);
            if q % 2 == 0 { _mm256_shuffle_ps::<0x44>(x, y) } else { _mm256_shuffle_ps::<0xEE>(x, y) }
        });
        std::array::from_fn(|j| {
            let (x, y) = (s[j % 4], s[4 + j % 4]);
            if j < 4 { _mm256_permute2f128_ps::<0x20>(x, y) } else { _mm256_permute2f128_ps::<0x31>(x, y) }
        })
    }
}

/// For each of the first `live` lanes l: rows[idx[l]·stride + off + c] += cols[c] lane l for
/// c < ncols (≤ 16). The live indices must be distinct (they are: a candidate is blended at
/// most once per pixel). Panics if a row range is out of bounds.
#[inline(always)]
pub(crate) fn add_columns(
    rows: &mut [f32],
    stride: usize,
    off: usize,
    idx: &[u32; 16],
    live: usize,
    cols: [f32x16; 16],
    ncols: usize,
) {
    debug_assert!(ncols <= 16 && off + ncols <= stride);
    if ncols <= 3 {
        // A transpose costs 64 shuffles whatever the column count: not worth it for a few.
        let c: [[f32; 16]; 3] = std::array::from_fn(|c| cols[c].to_array());
        for l in 0..live {
            let base = idx[l] as usize * stride + off;
            for (k, r) in rows[base..base + ncols].iter_mut().enumerate() {
                *r += c[k][l];
            }
        }
        return;
    }
    let per_hit = transpose(cols);
    for l in 0..live {
        let base = idx[l] as usize * stride + off;
        let row = &mut rows[base..base + ncols];
        #[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
        {
            use std::arch::x86_64::*;
            // SAFETY: avx512f is enabled at compile time; the masked load and store touch
            // exactly row[..ncols], which the slice above bounds-checked.
            unsafe {
                let m: __mmask16 = ((1u32 << ncols) - 1) as u16;
                let p = row.as_mut_ptr();
                let cur = _mm512_maskz_loadu_ps(m, p);
                let add = std::mem::transmute::<f32x16, __m512>(per_hit[l]);
                _mm512_mask_storeu_ps(p, m, _mm512_add_ps(cur, add));
            }
        }
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2", not(target_feature = "avx512f")))]
        {
            use std::arch::x86_64::*;
            let v = per_hit[l].to_array();
            // Whole groups of 8 as one ymm add each (AVX2's masked store is slow on AMD), the
            // rest one by one.
            let whole = ncols / 8 * 8;
            for g in (0..whole).step_by(8) {
                // SAFETY: avx2 is enabled at compile time; g + 8 ≤ ncols = row.len().
                unsafe {
                    let p = row.as_mut_ptr().add(g);
                    _mm256_storeu_ps(p, _mm256_add_ps(_mm256_loadu_ps(p), _mm256_loadu_ps(v.as_ptr().add(g))));
                }
            }
            for (r, a) in row[whole..].iter_mut().zip(&v[whole..]) {
                *r += a;
            }
        }
        #[cfg(not(all(target_arch = "x86_64", any(target_feature = "avx2", target_feature = "avx512f"))))]
        {
            let v = per_hit[l].to_array();
            for (r, a) in row.iter_mut().zip(v) {
                *r += a;
            }
        }
    }
}

/// Lane l gets x[l + S] (0 for l + S ≥ 16): lanes move down by S.
#[inline(always)]
fn shift_down<const S: i32>(x: f32x16) -> f32x16 {
    #[cfg(all(target_arch = "x86_64", target_feature = "avx512f"))]
    {
        use std::arch::x86_64::*;
        // SAFETY: avx512f is enabled at compile time; f32x16 and __m512i are both 64 bytes.
        unsafe {
            let v = std::mem::transmute::<f32x16, __m512i>(x);
            let r = match S {
                1 => _mm512_alignr_epi32::<1>(_mm512_setzero_si512(), v),
                2 => _mm512_alignr_epi32::<2>(_mm512_setzero_si512(), v),
                4 => _mm512_alignr_epi32::<4>(_mm512_setzero_si512(), v),
                8 => _mm512_alignr_epi32::<8>(_mm512_setzero_si512(), v),
                _ => unreachable!(),
            };
            std::mem::transmute::<__m512i, f32x16>(r)
        }
    }
    #[cfg(not(all(target_arch = "x86_64", target_feature = "avx512f")))]
    {
        let a = x.to_array();
        f32x16::new(std::array::from_fn(|l| if l + (S as usize) < 16 { a[l + S as usize] } else { 0.0 }))
    }
}

/// Exclusive suffix sums across lanes: lane l gets Σ_{m > l} x[m] (log-step scan).
#[inline(always)]
pub(crate) fn suffix_sum_exclusive(x: f32x16) -> f32x16 {
    let mut s = x + shift_down::<1>(x);
    s += shift_down::<2>(s);
    s += shift_down::<4>(s);
    s += shift_down::<8>(s);
    shift_down::<1>(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transpose_matches_definition() {
        let cols: [f32x16; 16] = std::array::from_fn(|c| f32x16::new(std::array::from_fn(|l| (c * 100 + l) as f32)));
        let t = transpose(cols);
        for l in 0..16 {
            for c in 0..16 {
                assert_eq!(t[l].to_array()[c], (c * 100 + l) as f32, "lane {l}, column {c}");
            }
        }
    }

    #[test]
    fn gather_masks_dead_lanes_and_add_columns_touches_only_its_rows() {
        let base: Vec<f32> = (0..40).map(|i| i as f32 * 0.5).collect();
        let idx: [u32; 16] = std::array::from_fn(|l| (39 - 2 * l) as u32);
        // Live counts on both sides of each 8-lane half (the AVX2 path gathers two halves).
        for live in [0, 1, 5, 7, 8, 9, 15, 16] {
            let g = Gather16::new(idx, live, 40).from(&base).to_array();
            for l in 0..16 {
                assert_eq!(g[l], if l < live { base[idx[l] as usize] } else { 0.0 }, "live {live}, lane {l}");
            }
        }
        // Column counts through the scalar path (≤ 3), the transposed path's whole groups of
        // 8 and its remainders; the rows' neighbouring entries and rows must not move.
        let idx: [u32; 16] = std::array::from_fn(|l| (19 - l) as u32);
        let cols: [f32x16; 16] = std::array::from_fn(|c| f32x16::new(std::array::from_fn(|l| (c * 16 + l) as f32)));
        for (ncols, off, stride, live) in [
            (3, 2, 7, 6),
            (4, 0, 4, 16),
            (5, 3, 9, 9),
            (8, 1, 10, 16),
            (11, 2, 13, 12),
            (16, 0, 16, 16),
            (16, 3, 21, 1),
        ] {
            let mut rows = vec![1.0f32; 20 * stride];
            add_columns(&mut rows, stride, off, &idx, live, cols, ncols);
            for r in 0..20 {
                for k in 0..stride {
                    let lane = 19 - r;
                    let want = if lane < live && (off..off + ncols).contains(&k) {
                        1.0 + ((k - off) * 16 + lane) as f32
                    } else {
                        1.0
                    };
                    assert_eq!(rows[r * stride + k], want, "{ncols} columns at {off}: row {r}, entry {k}");
                }
            }
        }
    }

    #[test]
    fn shift_down_moves_lanes() {
        let x = f32x16::new(std::array::from_fn(|l| l as f32 + 1.0));
        fn check<const S: i32>(x: f32x16) {
            let got = shift_down::<S>(x).to_array();
            for l in 0..16 {
                let want = if l + (S as usize) < 16 { (l + S as usize) as f32 + 1.0 } else { 0.0 };
                assert_eq!(got[l], want, "S = {S}, lane {l}");
            }
        }
        check::<1>(x);
        check::<2>(x);
        check::<4>(x);
        check::<8>(x);
    }

    #[test]
    fn exclusive_suffix_sum() {
        // Powers of two: every partial sum is exact in f32, so the scan order does not matter.
        let x = f32x16::new(std::array::from_fn(|l| (1u32 << l) as f32));
        let s = suffix_sum_exclusive(x).to_array();
        for l in 0..16 {
            assert_eq!(s[l], ((1u32 << 16) - (1u32 << (l + 1))) as f32, "suffix lane {l}");
        }
    }
}
