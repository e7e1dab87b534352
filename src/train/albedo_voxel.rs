//! Local albedo prior in space: surfels close to each other are pulled towards one albedo,
//! whichever way they face.
//!
//! Why: a thin part has one material on both sides, but each side sees its own half of the
//! light. Cornell's walls' outer faces alone see the courtyard's low sideways light, so that
//! light and those faces' albedo trade freely, and the image losses leave each face of a wall
//! its own albedo (the red wall's outer face 1.09 0.90 0.95 × the truth, its inner face 0.95
//! 1.11 1.49; BENCHMARKS.md sessions 33, 59). Tying surfels within a few centimetres ties the
//! two faces of a 5 cm wall, and everywhere else pulls the albedo towards its local mean, which
//! the edge-aware image smoothness does only within each view. Not in the published method
//! (`--lambda-albedo-voxel`, default 0.1, 0 = off): cornell relights 0.7–0.9 dB better and its
//! albedo gains 0.9–1.0 dB on three runs; spheres relights 0.12–0.16 dB better and loses
//! 0.16–0.19 dB of albedo; the PBR fit −0.3 to −0.9 dB (BENCHMARKS.md session 59).
//!
//! Surfels with opacity ≥ 0.3 are binned into cubic voxels `voxel` wide (scene units; the
//! inverse stage passes `--albedo-voxel` 0.024 × the camera extent: 8 cm on cornell); a
//! surfel's target is the mean albedo over its voxel and the 26 around it, and each channel's
//! difference beyond `cap` (`--albedo-voxel-cap` 0.1) goes free, so edges between materials
//! survive: uncapped, spheres' checkerboard lost 0.65 dB of albedo. The loss and its gradient
//! are the shared core in `binned_albedo.rs`.

use super::binned_albedo::{BinnedMean, MIN_OPACITY, Neighbourhoods, OUT, surfel_weight};
use crate::surfels::Surfels;
use rayon::prelude::*;
use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

/// Buffers of the prior, kept between iterations.
#[derive(Default)]
pub struct AlbedoVoxel {
    /// Per surfel: its voxel's key, then its voxel's index (or [`OUT`]).
    key: Vec<u64>,
    voxel: Vec<u32>,
    weight: Vec<f32>,
    grid: VoxelGrid,
    core: BinnedMean,
}

impl AlbedoVoxel {
    /// The loss (λ included) and its gradient added to `v_albedo` (per surfel, albedo units).
    pub fn loss(
        &mut self,
        surfels: &Surfels,
        albedo: &[[f32; 3]],
        lambda: f32,
        voxel: f32,
        cap: f32,
        v_albedo: &mut [[f32; 3]],
    ) -> f32 {
        (0..surfels.len())
            .into_par_iter()
            .map(|i| {
                if surfels.opacity(i) < MIN_OPACITY {
                    return (NO_KEY, 0.0);
                }
                (voxel_key(surfels.means[i].map(|x| (x / voxel).floor())), surfel_weight(surfels, i))
            })
            .unzip_into_vecs(&mut self.key, &mut self.weight);
        self.grid.build(&self.key, &mut self.voxel);
        self.core.loss(&self.voxel, &self.weight, &self.grid, albedo, lambda, cap, v_albedo)
    }
}

/// The key of a surfel that takes no part.
const NO_KEY: u64 = u64::MAX;
/// Bits per axis of a voxel key; coordinates are clamped to ±`KEY_HALF` − 2 (voxels that far
/// out are floaters, whose ties do not matter).
const KEY_BITS: u32 = 21;
const KEY_HALF: f32 = (1u32 << (KEY_BITS - 1)) as f32;

/// Three voxel coordinates packed 21 bits each, offset to be non-negative.
fn voxel_key(v: [f32; 3]) -> u64 {
    let axis = |x: f32| (x.clamp(-KEY_HALF + 2.0, KEY_HALF - 2.0) + KEY_HALF) as u64;
    (axis(v[0]) << (2 * KEY_BITS)) | (axis(v[1]) << KEY_BITS) | axis(v[2])
}

/// The keys of a voxel's 27 neighbours, itself included (offsets never leave the key's range:
/// coordinates are clamped 2 short of it).
fn neighbour_keys(key: u64) -> impl Iterator<Item = u64> {
    let one = [1u64 << (2 * KEY_BITS), 1u64 << KEY_BITS, 1];
    (0..27).map(move |k: u64| {
        let d = [k / 9, (k / 3) % 3, k % 3];
        (0..3).fold(key, |acc, a| acc + d[a] * one[a] - one[a])
    })
}

/// The occupied voxels, indexed, each with the indices of its occupied neighbours.
#[derive(Default)]
struct VoxelGrid {
    index: HashMap<u64, u32, BuildHasherDefault<KeyHasher>>,
    /// Per voxel: its occupied neighbours' indices, itself included ([`OUT`] where empty).
    around: Vec<[u32; 27]>,
}

impl VoxelGrid {
    /// Index the occupied voxels of `keys` and give each surfel its voxel's index.
    fn build(&mut self, keys: &[u64], voxel_of: &mut Vec<u32>) {
        self.index.clear();
        voxel_of.clear();
        for &key in keys {
            if key == NO_KEY {
                voxel_of.push(OUT);
                continue;
            }
            let next = self.index.len() as u32;
            voxel_of.push(*self.index.entry(key).or_insert(next));
        }
        let mut occupied = vec![0u64; self.index.len()];
        for (&key, &k) in &self.index {
            occupied[k as usize] = key;
        }
        let index = &self.index;
        occupied
            .par_iter()
            .map(|&key| {
                let mut around = [OUT; 27];
                for (slot, nb) in around.iter_mut().zip(neighbour_keys(key)) {
                    if let Some(&j) = index.get(&nb) {
                        *slot = j;
                    }
                }
                around
            })
            .collect_into_vec(&mut self.around);
    }
}

impl Neighbourhoods for VoxelGrid {
    fn bins(&self) -> usize {
        self.around.len()
    }

    fn gather<const N: usize>(&self, per_voxel: &[[f64; N]], out: &mut Vec<[f64; N]>) {
        out.clear();
        out.extend(self.around.iter().map(|around| {
            let mut acc = [0.0f64; N];
            for &j in around.iter().filter(|&&j| j != OUT) {
                for (a, v) in acc.iter_mut().zip(&per_voxel[j as usize]) {
                    *a += v;
                }
            }
            acc
        }));
    }
}

/// A multiplicative hash of the packed keys: the standard SipHash costs more than the whole
/// prior's arithmetic here, and the keys are not adversarial.
#[derive(Default)]
struct KeyHasher(u64);

impl Hasher for KeyHasher {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ b as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        }
    }

    fn write_u64(&mut self, x: u64) {
        let h = x.wrapping_mul(0x9e37_79b9_7f4a_7c15);
        self.0 = h ^ (h >> 29);
    }
}

#[cfg(test)]
mod tests {
    use super::super::binned_albedo::{check_gradient, random_surfels};
    use super::*;

    #[test]
    fn gradient_matches_finite_differences() {
        let (mut checked, mut kinks) = (0, 0);
        for (seed, cap) in [(0, f32::INFINITY), (1, f32::INFINITY), (2, 0.1), (3, 0.2)] {
            let (s, albedo) = random_surfels(30, seed);
            // 0.3: about 4 voxels a side, so neighbourhoods overlap without covering the box.
            let mut prior = AlbedoVoxel::default();
            let (c, k) = check_gradient(&albedo, |a, g| prior.loss(&s, a, 0.7, 0.3, cap, g));
            (checked, kinks) = (checked + c, kinks + k);
        }
        assert!(kinks * 10 < checked, "{kinks} kinks against {checked} checked");
    }

    /// The same loss by brute force: every pair of surfels compared by their voxel coordinates.
    fn brute_force(s: &Surfels, albedo: &[[f32; 3]], lambda: f32, voxel: f32, cap: f32) -> f64 {
        let cell = |i: usize| s.means[i].map(|x| (x / voxel).floor() as i64);
        let taking_part: Vec<usize> = (0..s.len()).filter(|&i| s.opacity(i) >= MIN_OPACITY).collect();
        let w = |i: usize| surfel_weight(s, i) as f64;
        let total: f64 = taking_part.iter().map(|&i| w(i)).sum();
        let mut loss = 0.0;
        for &i in &taking_part {
            let (ci, mut sum, mut sw) = (cell(i), [0.0f64; 3], 0.0);
            for &j in &taking_part {
                let cj = cell(j);
                // Neighbours: voxels within one step on every axis.
                if (0..3).all(|a| (ci[a] - cj[a]).abs() <= 1) {
                    for ch in 0..3 {
                        sum[ch] += w(j) * albedo[j][ch] as f64;
                    }
                    sw += w(j);
                }
            }
            for ch in 0..3 {
                loss += w(i) * (albedo[i][ch] as f64 - sum[ch] / sw).abs().min(cap as f64);
            }
        }
        lambda as f64 * loss / total
    }

    #[test]
    fn the_loss_matches_a_brute_force_over_pairs() {
        for (seed, voxel, cap) in [(1, 0.05, f32::INFINITY), (2, 0.2, f32::INFINITY), (3, 0.35, 0.1), (4, 2.0, 0.2)] {
            let (mut s, albedo) = random_surfels(60, seed);
            // Some surfels at negative coordinates: the floor of the voxel index matters there.
            for i in (0..s.len()).step_by(3) {
                s.means[i][1] -= 1.0;
            }
            let mut g = vec![[0.0f32; 3]; s.len()];
            let fast = AlbedoVoxel::default().loss(&s, &albedo, 0.5, voxel, cap, &mut g) as f64;
            let slow = brute_force(&s, &albedo, 0.5, voxel, cap);
            assert!((fast - slow).abs() < 1e-5 * slow.max(1e-3), "voxel {voxel}: {fast} vs {slow}");
        }
    }

    #[test]
    fn the_two_faces_of_a_thin_wall_are_tied_and_distant_surfels_are_not() {
        // A wall 5 cm thick: a surfel on each face (normals opposite), one far away.
        let mut s = Surfels::random_in_box(3, [0.0; 3], [1.0; 3], 1);
        s.means = vec![[1.0, 0.0, 0.5], [1.05, 0.0, 0.5], [-1.0, 0.0, 0.5]];
        s.opacity_logits = vec![3.0; 3];
        s.log_scales = vec![[-3.0, -3.0]; 3];
        let albedo = vec![[0.2, 0.6, 0.1], [0.4, 0.9, 0.3], [0.9, 0.1, 0.1]];
        let mut grad = vec![[0.0f32; 3]; 3];
        let loss = AlbedoVoxel::default().loss(&s, &albedo, 1.0, 0.04, f32::INFINITY, &mut grad);
        assert!(loss > 0.01, "{loss}");
        // The darker face is pulled up, the brighter one down; the far surfel is its own mean.
        assert!(grad[0].iter().all(|&g| g < 0.0) && grad[1].iter().all(|&g| g > 0.0), "{grad:?}");
        assert!(grad[2].iter().all(|g| g.abs() < 1e-7), "{grad:?}");
        // Capped at 0.05, the faces (0.1–0.15 from their mean in every channel) go free: an
        // edge between materials.
        let mut grad = vec![[0.0f32; 3]; 3];
        let capped = AlbedoVoxel::default().loss(&s, &albedo, 1.0, 0.04, 0.05, &mut grad);
        assert!(capped > 0.0 && capped < loss, "{capped} vs {loss}");
        assert!(grad.iter().flatten().all(|g| g.abs() < 1e-7), "{grad:?}");
    }

    #[test]
    fn transparent_surfels_take_no_part_and_one_albedo_costs_nothing() {
        let (mut s, albedo) = random_surfels(24, 7);
        s.opacity_logits[3] = -3.0; // opacity 0.05: out
        let mut grad = vec![[0.0f32; 3]; s.len()];
        assert!(AlbedoVoxel::default().loss(&s, &albedo, 1.0, 0.3, f32::INFINITY, &mut grad) > 0.0);
        assert_eq!(grad[3], [0.0; 3]);
        let same = vec![[0.4, 0.2, 0.6]; s.len()];
        let mut grad = vec![[0.0f32; 3]; s.len()];
        let loss = AlbedoVoxel::default().loss(&s, &same, 1.0, 0.3, 0.1, &mut grad);
        assert!(loss.abs() < 1e-6, "{loss}");
    }

    #[test]
    fn keys_and_neighbours_round_trip() {
        let k = voxel_key([-3.0, 0.0, 7.0]);
        let around: Vec<u64> = neighbour_keys(k).collect();
        assert_eq!(around.len(), 27);
        assert!(around.contains(&k));
        assert!(around.contains(&voxel_key([-4.0, -1.0, 8.0])));
        assert!(around.contains(&voxel_key([-2.0, 1.0, 6.0])));
        assert!(!around.contains(&voxel_key([-5.0, 0.0, 7.0])));
        // Far coordinates clamp inside the key's range.
        assert_ne!(voxel_key([1e12, 0.0, 0.0]), voxel_key([-1e12, 0.0, 0.0]));
    }
}
