//! The scene: 2D Gaussian surfels as a structure of arrays, their activations, and a gradient
//! buffer of the same shape (`SurfelGrads`, the `v_` arrays of every parameter).
//!
//! Parameters are stored raw (log-scales, unnormalised quaternions, logits) and activated on use:
//! scale = exp, rotation = normalise(q) with columns [t_u t_v n], opacity = sigmoid,
//! albedo = 0.03 + 0.77·sigmoid, roughness = sigmoid (DESIGN §1–2).

use crate::error::{Error, Result};
use crate::sh::{self, SH_COEFFS};
use rand::{RngExt, SeedableRng};

#[derive(Clone, Debug, Default, PartialEq)]
pub struct Surfels {
    pub means: Vec<[f32; 3]>,
    pub log_scales: Vec<[f32; 2]>,
    /// Quaternions (w, x, y, z), not necessarily unit.
    pub quats: Vec<[f32; 4]>,
    pub opacity_logits: Vec<f32>,
    /// SH coefficients, [coefficient][channel], degree 3 storage whatever the active degree.
    pub sh: Vec<[[f32; 3]; SH_COEFFS]>,
    pub albedo_logits: Vec<[f32; 3]>,
    pub roughness_logits: Vec<f32>,
    /// Active SH degree (0..=3): coefficients beyond it are ignored.
    pub sh_degree: u32,
}

/// Gradients have exactly the shape of the parameters.
pub type SurfelGrads = Surfels;

pub const DEFAULT_OPACITY: f32 = 0.1;
pub const DEFAULT_ALBEDO: f32 = 0.3;
pub const DEFAULT_ROUGHNESS: f32 = 0.6;

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}
pub fn logit(p: f32) -> f32 {
    let p = p.clamp(1e-6, 1.0 - 1e-6);
    (p / (1.0 - p)).ln()
}
/// The albedo activation's range, kept just inside so that the logit of a clamped value is
/// finite.
pub const ALBEDO_LO: f32 = 0.03 + 1e-4;
pub const ALBEDO_HI: f32 = 0.80 - 1e-4;

pub fn albedo_from_logit(x: f32) -> f32 {
    0.03 + 0.77 * sigmoid(x)
}
pub fn albedo_to_logit(a: f32) -> f32 {
    logit((a - 0.03) / 0.77)
}

/// Rotation matrix columns [t_u, t_v, n] of a (possibly unnormalised) quaternion (w, x, y, z).
pub fn rotation_from_quat(q: [f32; 4]) -> [[f32; 3]; 3] {
    let len = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt().max(1e-12);
    let (w, x, y, z) = (q[0] / len, q[1] / len, q[2] / len, q[3] / len);
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)],
        [2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)],
        [2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// Backward of [`rotation_from_quat`]: `v_cols[c][r]` = ∂L/∂R[r][c]; returns ∂L/∂q for the
/// unnormalised quaternion.
pub fn rotation_from_quat_backward(q: [f32; 4], v_cols: [[f32; 3]; 3]) -> [f32; 4] {
    let len = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt().max(1e-12);
    let (w, x, y, z) = (q[0] / len, q[1] / len, q[2] / len, q[3] / len);
    let g = |c: usize, r: usize| v_cols[c][r];
    // Σ over entries of v_R ⊙ ∂R/∂q_k, written per column (c) and row (r).
    let v_w = 2.0 * (z * (g(0, 1) - g(1, 0)) + y * (g(2, 0) - g(0, 2)) + x * (g(1, 2) - g(2, 1)));
    let v_x = 2.0 * (y * (g(0, 1) + g(1, 0)) + z * (g(0, 2) + g(2, 0)) + w * (g(1, 2) - g(2, 1)))
        - 4.0 * x * (g(1, 1) + g(2, 2));
    let v_y = 2.0 * (x * (g(0, 1) + g(1, 0)) + w * (g(2, 0) - g(0, 2)) + z * (g(1, 2) + g(2, 1)))
        - 4.0 * y * (g(0, 0) + g(2, 2));
    let v_z = 2.0 * (w * (g(0, 1) - g(1, 0)) + x * (g(0, 2) + g(2, 0)) + y * (g(1, 2) + g(2, 1)))
        - 4.0 * z * (g(0, 0) + g(1, 1));
    let vn = [v_w, v_x, v_y, v_z];
    let qn = [w, x, y, z];
    let dot: f32 = (0..4).map(|i| vn[i] * qn[i]).sum();
    [(vn[0] - dot * qn[0]) / len, (vn[1] - dot * qn[1]) / len, (vn[2] - dot * qn[2]) / len, (vn[3] - dot * qn[3]) / len]
}

/// Unit quaternion (w, x, y, z) whose rotation maps +z to the unit vector `n`.
pub fn quat_with_normal(n: [f32; 3]) -> [f32; 4] {
    let q = glam::Quat::from_rotation_arc(glam::Vec3::Z, glam::Vec3::from(n).normalize());
    [q.w, q.x, q.y, q.z]
}

impl Surfels {
    pub fn len(&self) -> usize {
        self.means.len()
    }
    pub fn is_empty(&self) -> bool {
        self.means.is_empty()
    }

    /// A zeroed buffer of the same shape (for gradients or optimiser moments).
    pub fn zeros_like(&self) -> Surfels {
        let n = self.len();
        Surfels {
            means: vec![[0.0; 3]; n],
            log_scales: vec![[0.0; 2]; n],
            quats: vec![[0.0; 4]; n],
            opacity_logits: vec![0.0; n],
            sh: vec![[[0.0; 3]; SH_COEFFS]; n],
            albedo_logits: vec![[0.0; 3]; n],
            roughness_logits: vec![0.0; n],
            sh_degree: self.sh_degree,
        }
    }

    /// Set every entry to zero, keeping the allocation.
    pub fn fill_zero(&mut self) {
        self.means.fill([0.0; 3]);
        self.log_scales.fill([0.0; 2]);
        self.quats.fill([0.0; 4]);
        self.opacity_logits.fill(0.0);
        self.sh.fill([[0.0; 3]; SH_COEFFS]);
        self.albedo_logits.fill([0.0; 3]);
        self.roughness_logits.fill(0.0);
    }

    /// Append one surfel given in activated form.
    #[allow(clippy::too_many_arguments)]
    pub fn push(
        &mut self,
        mean: [f32; 3],
        scales: [f32; 2],
        quat: [f32; 4],
        opacity: f32,
        rgb: [f32; 3],
        albedo: [f32; 3],
        roughness: f32,
    ) {
        self.means.push(mean);
        self.log_scales.push([scales[0].max(1e-12).ln(), scales[1].max(1e-12).ln()]);
        self.quats.push(quat);
        self.opacity_logits.push(logit(opacity));
        let mut coeffs = [[0.0; 3]; SH_COEFFS];
        coeffs[0] = rgb.map(sh::rgb_to_dc);
        self.sh.push(coeffs);
        self.albedo_logits.push(albedo.map(albedo_to_logit));
        self.roughness_logits.push(logit(roughness));
    }

    /// Keep only the surfels whose `keep` flag is set (order preserved).
    pub fn retain_mask(&mut self, keep: &[bool]) {
        fn filter<T: Copy>(v: &mut Vec<T>, keep: &[bool]) {
            let mut i = 0;
            v.retain(|_| {
                let k = keep[i];
                i += 1;
                k
            });
        }
        assert_eq!(keep.len(), self.len());
        filter(&mut self.means, keep);
        filter(&mut self.log_scales, keep);
        filter(&mut self.quats, keep);
        filter(&mut self.opacity_logits, keep);
        filter(&mut self.sh, keep);
        filter(&mut self.albedo_logits, keep);
        filter(&mut self.roughness_logits, keep);
    }

    /// Append copies of the surfels at `indices`.
    pub fn append_copies(&mut self, indices: &[usize]) {
        for &i in indices {
            self.means.push(self.means[i]);
            self.log_scales.push(self.log_scales[i]);
            self.quats.push(self.quats[i]);
            self.opacity_logits.push(self.opacity_logits[i]);
            self.sh.push(self.sh[i]);
            self.albedo_logits.push(self.albedo_logits[i]);
            self.roughness_logits.push(self.roughness_logits[i]);
        }
    }

    pub fn scale(&self, i: usize) -> [f32; 2] {
        [self.log_scales[i][0].exp(), self.log_scales[i][1].exp()]
    }
    pub fn opacity(&self, i: usize) -> f32 {
        sigmoid(self.opacity_logits[i])
    }
    pub fn rotation(&self, i: usize) -> [[f32; 3]; 3] {
        rotation_from_quat(self.quats[i])
    }
    pub fn normal(&self, i: usize) -> [f32; 3] {
        self.rotation(i)[2]
    }
    pub fn albedo(&self, i: usize) -> [f32; 3] {
        self.albedo_logits[i].map(albedo_from_logit)
    }
    pub fn roughness(&self, i: usize) -> f32 {
        sigmoid(self.roughness_logits[i])
    }

    /// Check every array has the same length and every value is finite.
    pub fn validate(&self) -> Result<()> {
        let n = self.len();
        let lens = [
            self.log_scales.len(),
            self.quats.len(),
            self.opacity_logits.len(),
            self.sh.len(),
            self.albedo_logits.len(),
            self.roughness_logits.len(),
        ];
        if lens.iter().any(|&l| l != n) {
            return Err(Error::invalid("surfels", format!("array lengths differ: {n} means vs {lens:?}")));
        }
        if let Some((i, name)) = self.first_non_finite() {
            return Err(Error::invalid("surfels", format!("surfel {i}: {name} is NaN or infinite")));
        }
        Ok(())
    }

    /// The first surfel holding a NaN or infinite value, and the parameter it is in (the
    /// field's name: `means`, `log_scales`, `quats`, `opacity_logits`, `sh`, `albedo_logits`,
    /// `roughness_logits`). Arrays must have equal lengths.
    pub fn first_non_finite(&self) -> Option<(usize, &'static str)> {
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        (0..self.len()).find_map(|i| {
            let params: [(&'static str, bool); 7] = [
                ("means", finite(&self.means[i])),
                ("log_scales", finite(&self.log_scales[i])),
                ("quats", finite(&self.quats[i])),
                ("opacity_logits", self.opacity_logits[i].is_finite()),
                ("sh", finite(self.sh[i].as_flattened())),
                ("albedo_logits", finite(&self.albedo_logits[i])),
                ("roughness_logits", self.roughness_logits[i].is_finite()),
            ];
            params.iter().find(|p| !p.1).map(|p| (i, p.0))
        })
    }

    /// Axis-aligned bounds of the centres (min, max); None when empty.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        let first = *self.means.first()?;
        let (mut lo, mut hi) = (first, first);
        for m in &self.means {
            for a in 0..3 {
                lo[a] = lo[a].min(m[a]);
                hi[a] = hi[a].max(m[a]);
            }
        }
        Some((lo, hi))
    }

    /// Surfels at uniformly random points in a box, random orientation, scales from the
    /// neighbour distances (2DGS initialisation for scenes without a point cloud).
    pub fn random_in_box(count: usize, lo: [f32; 3], hi: [f32; 3], seed: u64) -> Surfels {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let points: Vec<[f32; 3]> =
            (0..count).map(|_| std::array::from_fn(|a| lo[a] + (hi[a] - lo[a]) * rng.random::<f32>())).collect();
        let colours: Vec<[f32; 3]> = (0..count).map(|_| [rng.random(), rng.random(), rng.random()]).collect();
        Self::from_points(&points, &colours, seed)
    }

    /// Surfels at the given points with the given colours: scale = sqrt(mean squared distance
    /// to the 3 nearest neighbours), random rotation, opacity 0.1 (as 2DGS).
    pub fn from_points(points: &[[f32; 3]], colours: &[[f32; 3]], seed: u64) -> Surfels {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed ^ 0x5eed_5eed);
        let dist2 = mean_sq_dist_3nn(points);
        let mut s = Surfels::default();
        for (i, p) in points.iter().enumerate() {
            let scale = dist2[i].max(1e-7).sqrt();
            let q: [f32; 4] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
            let q = if q.iter().map(|v| v * v).sum::<f32>() < 1e-6 { [1.0, 0.0, 0.0, 0.0] } else { q };
            s.push(*p, [scale, scale], q, DEFAULT_OPACITY, colours[i], [DEFAULT_ALBEDO; 3], DEFAULT_ROUGHNESS);
        }
        s
    }
}

/// Mean squared distance from each point to its 3 nearest neighbours, by a uniform grid.
pub fn mean_sq_dist_3nn(points: &[[f32; 3]]) -> Vec<f32> {
    let n = points.len();
    if n < 2 {
        return vec![1e-2; n];
    }
    let mut lo = points[0];
    let mut hi = points[0];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let extent: [f32; 3] = std::array::from_fn(|a| (hi[a] - lo[a]).max(1e-6));
    let volume = extent[0] * extent[1] * extent[2];
    let cell = (volume / n as f32 * 2.0).cbrt().max(1e-6);
    let dims: [i64; 3] = std::array::from_fn(|a| ((extent[a] / cell).ceil() as i64).clamp(1, 1024));
    let key = |c: [i64; 3]| ((c[2] * dims[1] + c[1]) * dims[0] + c[0]) as usize;
    let cell_of =
        |p: &[f32; 3]| -> [i64; 3] { std::array::from_fn(|a| (((p[a] - lo[a]) / cell) as i64).clamp(0, dims[a] - 1)) };
    let total = (dims[0] * dims[1] * dims[2]) as usize;
    let mut starts = vec![0usize; total + 1];
    for p in points {
        starts[key(cell_of(p)) + 1] += 1;
    }
    for i in 0..total {
        starts[i + 1] += starts[i];
    }
    let mut fill = starts.clone();
    let mut order = vec![0usize; n];
    for (i, p) in points.iter().enumerate() {
        let k = key(cell_of(p));
        order[fill[k]] = i;
        fill[k] += 1;
    }
    use rayon::prelude::*;
    (0..n)
        .into_par_iter()
        .map(|i| {
            let p = points[i];
            let c = cell_of(&p);
            let mut best = [f32::INFINITY; 3];
            let mut ring = 1i64;
            loop {
                for dz in -ring..=ring {
                    for dy in -ring..=ring {
                        for dx in -ring..=ring {
                            // Only the shell of this ring; inner cells were visited before.
                            if dx.abs().max(dy.abs()).max(dz.abs()) != ring && ring > 1 {
                                continue;
                            }
                            let cc = [c[0] + dx, c[1] + dy, c[2] + dz];
                            if (0..3).any(|a| cc[a] < 0 || cc[a] >= dims[a]) {
                                continue;
                            }
                            let k = key(cc);
                            for &j in &order[starts[k]..starts[k + 1]] {
                                if j == i {
                                    continue;
                                }
                                let q = points[j];
                                let d = (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
                                if d < best[2] {
                                    best[2] = d;
                                    if best[2] < best[1] {
                                        best.swap(1, 2);
                                    }
                                    if best[1] < best[0] {
                                        best.swap(0, 1);
                                    }
                                }
                            }
                        }
                    }
                }
                // Points beyond this ring are at least ring·cell away.
                let covered = (ring as f32 * cell).powi(2);
                if (best[2] <= covered) || ring > dims.iter().copied().max().unwrap() {
                    break;
                }
                ring += 1;
            }
            let found: Vec<f32> = best.iter().copied().filter(|d| d.is_finite()).collect();
            if found.is_empty() { 1e-2 } else { found.iter().sum::<f32>() / found.len() as f32 }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_is_orthonormal_and_backward_matches_fd() {
        let q = [0.3f32, -0.5, 0.8, 0.2];
        let r = rotation_from_quat(q);
        for i in 0..3 {
            for j in 0..3 {
                let d: f32 = (0..3).map(|a| r[i][a] * r[j][a]).sum();
                assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-5);
            }
        }
        let weights = [[0.3f32, -1.0, 0.5], [0.2, 0.7, -0.4], [1.1, -0.6, 0.9]];
        let loss = |q: [f32; 4]| -> f64 {
            let r = rotation_from_quat(q);
            (0..3).flat_map(|c| (0..3).map(move |k| (c, k))).map(|(c, k)| (r[c][k] * weights[c][k]) as f64).sum()
        };
        let v_q = rotation_from_quat_backward(q, weights);
        for k in 0..4 {
            let (mut qp, mut qm) = (q, q);
            qp[k] += 1e-3;
            qm[k] -= 1e-3;
            let fd = (loss(qp) - loss(qm)) / 2e-3;
            assert!((fd - v_q[k] as f64).abs() < 5e-3, "q[{k}]: fd {fd} vs {}", v_q[k]);
        }
    }

    #[test]
    fn quat_with_normal_points_the_normal() {
        let n = [0.2f32, -0.6, 0.77];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let r = rotation_from_quat(quat_with_normal(n));
        for a in 0..3 {
            assert!((r[2][a] - n[a] / len).abs() < 1e-5);
        }
    }

    #[test]
    fn knn_matches_brute_force() {
        let s = Surfels::random_in_box(500, [-1.0; 3], [1.0, 2.0, 0.5], 3);
        let d = mean_sq_dist_3nn(&s.means);
        for i in (0..500).step_by(37) {
            let mut all: Vec<f32> = (0..500)
                .filter(|&j| j != i)
                .map(|j| (0..3).map(|a| (s.means[i][a] - s.means[j][a]).powi(2)).sum())
                .collect();
            all.sort_by(f32::total_cmp);
            let want = (all[0] + all[1] + all[2]) / 3.0;
            assert!((d[i] - want).abs() < 1e-6 * (1.0 + want), "{i}: {} vs {want}", d[i]);
        }
    }

    #[test]
    fn retain_and_copy_keep_arrays_aligned() {
        let mut s = Surfels::random_in_box(10, [0.0; 3], [1.0; 3], 1);
        let keep: Vec<bool> = (0..10).map(|i| i % 3 != 0).collect();
        let before = s.clone();
        s.retain_mask(&keep);
        assert_eq!(s.len(), 6);
        assert_eq!(s.means[0], before.means[1]);
        s.append_copies(&[0]);
        assert_eq!(s.len(), 7);
        assert_eq!(s.sh[6], before.sh[1]);
        s.validate().unwrap();
    }
}
