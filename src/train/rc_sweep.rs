//! The consistency's surfels under `--rc-order sweep`: every surfel once per pass, B at a time,
//! in one random order drawn from the seed (sampling without replacement). With as many rays
//! as the cache has samples, the traced rows then refresh the cache in that order, and the
//! cache's own re-tracing has nothing left to do when a pass (N/B iterations) is no longer
//! than the cache's age limit. The order stays the same from pass to pass so that each row is
//! re-traced every N/B iterations exactly: a new order per pass spaced a row's two traces
//! anywhere from 1 to 2N/B iterations apart, and the cache re-traced the rows that fell
//! behind (42 of the 105 s it took under random batches; BENCHMARKS.md, session 92).
//!
//! The batch of iteration `it` (1-based) is positions (it − 1)·B .. it·B of the repeated
//! order: a resumed run picks exactly what an uninterrupted one would, with no state in the
//! checkpoint.

use rand::{RngExt, SeedableRng};

/// The order (drawn once per seed and surfel count, not once per batch).
#[derive(Default)]
pub struct RcSweep {
    drawn_for: Option<(u64, usize)>,
    order: Vec<u32>,
}

impl RcSweep {
    /// The surfels of iteration `it` (≥ 1) for `n` surfels and batch size `b` (≤ n) into `out`.
    pub fn batch(&mut self, seed: u64, it: u32, n: usize, b: usize, out: &mut Vec<u32>) {
        out.clear();
        let b = b.min(n);
        let first = (it.max(1) as u64 - 1) * b as u64;
        if self.drawn_for != Some((seed, n)) {
            self.shuffle(seed, n);
        }
        out.extend((first..first + b as u64).map(|g| self.order[(g % n as u64) as usize]));
    }

    /// Fisher–Yates over 0..n from the seed's own random stream.
    fn shuffle(&mut self, seed: u64, n: usize) {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed.wrapping_mul(0x2545_f491_4f6c_dd1d) ^ 0x5eed_5eed);
        self.order.clear();
        self.order.extend(0..n as u32);
        for i in (1..n).rev() {
            let j = rng.random_range(0..=i);
            self.order.swap(i, j);
        }
        self.drawn_for = Some((seed, n));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_pass_visits_every_surfel_once_and_batches_resume() {
        let (n, b) = (1000usize, 64usize);
        let mut sweep = RcSweep::default();
        let mut batch = Vec::new();
        let mut seen = Vec::new();
        // Three passes (with batches straddling the pass boundaries, as 1000 % 64 ≠ 0).
        for it in 1..=(3 * n / b) as u32 + 1 {
            sweep.batch(7, it, n, b, &mut batch);
            assert_eq!(batch.len(), b);
            seen.extend_from_slice(&batch);
        }
        for p in 0..3 {
            let mut pass = seen[p * n..(p + 1) * n].to_vec();
            // The same order every pass: each surfel comes back every n / b iterations exactly.
            assert_eq!(pass, seen[..n], "pass {p} repeats the order");
            pass.sort_unstable();
            assert_eq!(pass, (0..n as u32).collect::<Vec<_>>(), "pass {p} visits each surfel once");
        }
        assert_ne!(seen[..n], (0..n as u32).collect::<Vec<_>>(), "the order is shuffled");

        // A fresh sweep (a resumed run) picks the same batch at any iteration, in any order.
        let mut resumed = RcSweep::default();
        for it in [40u32, 3, 17, 16] {
            resumed.batch(7, it, n, b, &mut batch);
            let g = (it as usize - 1) * b;
            assert_eq!(batch, seen[g..g + b], "iteration {it}");
        }
        // Another seed, another order; a batch larger than n is clamped to n.
        resumed.batch(8, 1, n, b, &mut batch);
        assert_ne!(batch, seen[..b]);
        resumed.batch(7, 2, 10, 50, &mut batch);
        assert_eq!(batch.len(), 10);
        let mut sorted = batch.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..10).collect::<Vec<u32>>());
    }
}
