//! Activated material and normal per surfel, and the chain from their gradients back to the
//! surfel parameters (albedo a = 0.03 + 0.77·σ(θ_a), roughness r = σ(θ_r), normal = third
//! column of R(q), view direction ω = (c − μ)/|c − μ|).

use crate::surfels::{SurfelGrads, Surfels, rotation_from_quat_backward, sigmoid};
use rayon::prelude::*;

/// Per-surfel activated values the shading reads.
#[derive(Clone, Debug, Default)]
pub struct MaterialView {
    pub albedo: Vec<[f32; 3]>,
    pub roughness: Vec<f32>,
    pub normal: Vec<[f32; 3]>,
}

impl MaterialView {
    pub fn update(&mut self, s: &Surfels) {
        let n = s.len();
        self.albedo.resize(n, [0.0; 3]);
        self.roughness.resize(n, 0.0);
        self.normal.resize(n, [0.0; 3]);
        self.albedo
            .par_iter_mut()
            .zip(self.roughness.par_iter_mut())
            .zip(self.normal.par_iter_mut())
            .enumerate()
            .for_each(|(i, ((a, r), nn))| {
                *a = s.albedo(i);
                *r = s.roughness(i);
                *nn = s.normal(i);
            });
    }
}

/// Dense per-surfel gradients of the activated quantities.
#[derive(Clone, Debug, Default)]
pub struct MaterialGrads {
    pub v_albedo: Vec<[f32; 3]>,
    pub v_roughness: Vec<f32>,
    pub v_normal: Vec<[f32; 3]>,
    pub v_means: Vec<[f32; 3]>,
}

impl MaterialGrads {
    pub fn reset(&mut self, n: usize) {
        for v in [&mut self.v_albedo, &mut self.v_normal, &mut self.v_means] {
            v.clear();
            v.resize(n, [0.0; 3]);
        }
        self.v_roughness.clear();
        self.v_roughness.resize(n, 0.0);
    }

    /// Add the chained gradients into the parameter gradients.
    pub fn chain_into(&self, s: &Surfels, v: &mut SurfelGrads) {
        v.albedo_logits
            .par_iter_mut()
            .zip(v.roughness_logits.par_iter_mut())
            .zip(v.quats.par_iter_mut())
            .zip(v.means.par_iter_mut())
            .enumerate()
            .for_each(|(i, (((va, vr), vq), vm))| {
                for ch in 0..3 {
                    let sg = sigmoid(s.albedo_logits[i][ch]);
                    va[ch] += self.v_albedo[i][ch] * 0.77 * sg * (1.0 - sg);
                    vm[ch] += self.v_means[i][ch];
                }
                let sr = sigmoid(s.roughness_logits[i]);
                *vr += self.v_roughness[i] * sr * (1.0 - sr);
                let vn = self.v_normal[i];
                if vn != [0.0; 3] {
                    let g = rotation_from_quat_backward(s.quats[i], [[0.0; 3], [0.0; 3], vn]);
                    for k in 0..4 {
                        vq[k] += g[k];
                    }
                }
            });
    }
}

/// Unit direction from `p` towards `eye`.
#[inline]
pub fn view_dir(p: [f32; 3], eye: [f32; 3]) -> [f32; 3] {
    let d = [eye[0] - p[0], eye[1] - p[1], eye[2] - p[2]];
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-12);
    d.map(|x| x / l)
}

/// ∂L/∂p of [`view_dir`] for ∂L/∂ω = `v`: −(I − ωωᵀ) v / |eye − p|.
#[inline]
pub fn view_dir_backward(p: [f32; 3], eye: [f32; 3], v: [f32; 3]) -> [f32; 3] {
    let d = [eye[0] - p[0], eye[1] - p[1], eye[2] - p[2]];
    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-12);
    let w = d.map(|x| x / l);
    let dot = v[0] * w[0] + v[1] * w[1] + v[2] * w[2];
    [0, 1, 2].map(|k| -(v[k] - dot * w[k]) / l)
}

/// Flip surfel `i` so its normal points the other way: R' = R·Rx(π) = [t_u, −t_v, −n]
/// (q' = q ⊗ (0, 1, 0, 0)).
pub fn flip_surfel(s: &mut Surfels, i: usize) {
    let [w, x, y, z] = s.quats[i];
    s.quats[i] = [-x, w, z, -y];
}

/// What [`orient_surfels`] did.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct Orientation {
    pub flipped: usize,
    /// Surfels seen from both sides that got a flipped twin.
    pub doubled: usize,
    /// Surfels no camera sees (oriented away from the scene centre).
    pub unseen: usize,
}

/// Orient surfel normals for the PBR stages, which cull back faces and need normals pointing
/// out of the surface. The nvs stage is two-sided, so its normals are arbitrary and a thin
/// wall may be one layer of surfels seen from both sides. For every training camera the
/// two-sided depth is rendered; a surfel votes for the side of each camera that sees it
/// (centre in the image, its depth within `tolerance` of the rendered depth). Surfels seen
/// from both sides (at least 2 cameras and 20% of the votes each) get a flipped twin at the
/// same place, so every view still sees one of the two; unseen surfels face away from the
/// centroid of the scene. Also returns which surfels (twins included) were unseen.
pub fn orient_surfels(
    s: &mut Surfels,
    cameras: &[crate::camera::Camera],
    window: usize,
    filter_inv_square: f32,
    tolerance: f32,
) -> (Orientation, Vec<bool>) {
    use crate::raster::{self, Outputs, RasterSettings};
    let n = s.len();
    let mut pos = vec![0u32; n];
    let mut neg = vec![0u32; n];
    let settings = RasterSettings {
        window,
        filter_inv_square,
        two_sided: true,
        outputs: Outputs { depth: true, ..Outputs::none() },
        ..RasterSettings::default()
    };
    for cam in cameras {
        let (out, _) = raster::render(s, cam, &settings, None);
        let c = cam.position();
        let votes: Vec<i8> = (0..n)
            .into_par_iter()
            .map(|i| {
                let m = s.means[i];
                let p = glam::Vec3::from(m);
                let z = cam.world_to_camera(p).z;
                let Some((x, y)) = cam.project(p) else { return 0 };
                if z <= 0.0 || x < 0.0 || y < 0.0 || x >= cam.width as f32 || y >= cam.height as f32 {
                    return 0;
                }
                let k = y as usize * cam.width as usize + x as usize;
                if out.alpha[k] < 0.5 || (out.depth[k] - z).abs() > tolerance {
                    return 0;
                }
                let nn = s.normal(i);
                let d = [c.x - m[0], c.y - m[1], c.z - m[2]];
                if d[0] * nn[0] + d[1] * nn[1] + d[2] * nn[2] >= 0.0 { 1 } else { -1 }
            })
            .collect();
        for (i, v) in votes.into_iter().enumerate() {
            match v {
                1 => pos[i] += 1,
                -1 => neg[i] += 1,
                _ => {}
            }
        }
    }
    let mut centroid = [0.0f64; 3];
    for m in &s.means {
        for k in 0..3 {
            centroid[k] += m[k] as f64 / n.max(1) as f64;
        }
    }
    let mut o = Orientation::default();
    let mut twins = Vec::new();
    let mut unseen = vec![false; n];
    for i in 0..n {
        let (p, q) = (pos[i], neg[i]);
        let total = p + q;
        if total == 0 {
            let nn = s.normal(i);
            let m = s.means[i];
            let out: f64 = (0..3).map(|k| (m[k] as f64 - centroid[k]) * nn[k] as f64).sum();
            if out < 0.0 {
                flip_surfel(s, i);
                o.flipped += 1;
            }
            o.unseen += 1;
            unseen[i] = true;
            continue;
        }
        if p.min(q) >= 2 && p.min(q) as f32 >= 0.2 * total as f32 {
            twins.push(i);
        } else if q > p {
            flip_surfel(s, i);
            o.flipped += 1;
        }
    }
    o.doubled = twins.len();
    s.append_copies(&twins);
    for k in 0..twins.len() {
        flip_surfel(s, n + k);
    }
    unseen.resize(s.len(), false);
    (o, unseen)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orientation_faces_the_cameras_and_doubles_two_sided_walls() {
        use crate::camera::Camera;
        use glam::Vec3;
        // A wall in the plane y = 0 made of a grid of surfels with random-sign normals, seen by
        // cameras on both sides; and a floor patch (z = −1) seen only from above.
        let mut s = Surfels::random_in_box(1, [0.0; 3], [0.0; 3], 1);
        s.means.clear();
        s.log_scales.clear();
        s.quats.clear();
        s.opacity_logits.clear();
        s.sh.clear();
        s.albedo_logits.clear();
        s.roughness_logits.clear();
        let wall_q = [std::f32::consts::FRAC_1_SQRT_2, -std::f32::consts::FRAC_1_SQRT_2, 0.0, 0.0]; // n = +y
        for a in 0..10 {
            for b in 0..10 {
                let q = if (a + b) % 2 == 0 { wall_q } else { [-wall_q[1], wall_q[0], 0.0, 0.0] };
                s.push(
                    [-0.45 + 0.1 * a as f32, 0.0, -0.45 + 0.1 * b as f32],
                    [0.08, 0.08],
                    q,
                    0.95,
                    [0.5; 3],
                    [0.5; 3],
                    0.5,
                );
            }
        }
        let floor_down = [0.0, 1.0, 0.0, 0.0]; // n = −z
        for a in 0..10 {
            for b in 0..10 {
                s.push(
                    [-0.45 + 0.1 * a as f32, 1.0 + 0.1 * b as f32, -1.0],
                    [0.08, 0.08],
                    floor_down,
                    0.95,
                    [0.5; 3],
                    [0.5; 3],
                    0.5,
                );
            }
        }
        // And one far off to the side that no camera sees.
        s.push([50.0, 0.0, 0.0], [0.08, 0.08], floor_down, 0.95, [0.5; 3], [0.5; 3], 0.5);
        assert!(s.normal(0)[1] > 0.99 && s.normal(1)[1] < -0.99 && s.normal(100)[2] < -0.99);
        let cams: Vec<Camera> = [
            Vec3::new(0.3, 3.0, 0.5),
            Vec3::new(-0.3, 3.0, 0.2),
            Vec3::new(0.2, -3.0, 0.4),
            Vec3::new(-0.2, -3.0, -0.3),
            Vec3::new(0.0, 1.5, 3.0),
            Vec3::new(0.5, 1.5, 3.0),
        ]
        .iter()
        .map(|&p| {
            let target = if p.z > 2.0 { Vec3::new(0.0, 1.5, -1.0) } else { Vec3::ZERO };
            Camera::look_at("c", p, target, 64, 64, 0.9)
        })
        .collect();
        let (o, unseen) = orient_surfels(&mut s, &cams, 8, 2.0, 0.05);
        assert_eq!(s.len(), 201 + o.doubled);
        assert_eq!(unseen.len(), s.len());
        assert!(unseen[200] && unseen[201..].iter().all(|u| !u), "the far surfel is unseen, the twins seen");
        assert_eq!(unseen.iter().filter(|u| **u).count(), o.unseen);
        assert!(o.doubled >= 50, "{o:?}");
        for i in 100..200 {
            assert!(s.normal(i)[2] > 0.99, "floor surfel {i} must face up: {:?}", s.normal(i));
        }
        // Every doubled wall surfel has a twin facing the other way.
        for k in 0..o.doubled {
            let t = 201 + k;
            assert!(s.normal(t)[1].abs() > 0.99);
        }
    }

    #[test]
    fn flip_negates_the_normal_and_keeps_the_plane() {
        let mut s = Surfels::random_in_box(5, [0.0; 3], [1.0; 3], 3);
        for i in 0..5 {
            let r = s.rotation(i);
            flip_surfel(&mut s, i);
            let r2 = s.rotation(i);
            for k in 0..3 {
                assert!((r2[0][k] - r[0][k]).abs() < 1e-5);
                assert!((r2[1][k] + r[1][k]).abs() < 1e-5);
                assert!((r2[2][k] + r[2][k]).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn view_dir_backward_matches_finite_differences() {
        let (p, eye, v) = ([0.1f32, -0.3, 0.2], [1.0f32, 2.0, -1.5], [0.3f32, -0.7, 0.4]);
        let g = view_dir_backward(p, eye, v);
        for k in 0..3 {
            let h = 1e-3;
            let (mut a, mut b) = (p, p);
            a[k] += h;
            b[k] -= h;
            let f = |q: [f32; 3]| {
                let w = view_dir(q, eye);
                (0..3).map(|j| w[j] * v[j]).sum::<f32>()
            };
            let fd = (f(a) - f(b)) / (2.0 * h);
            assert!((fd - g[k]).abs() < 1e-3, "{k}: {fd} vs {}", g[k]);
        }
    }

    #[test]
    fn chain_matches_finite_differences_for_albedo_roughness_and_normal() {
        let s = Surfels::random_in_box(3, [0.0; 3], [1.0; 3], 9);
        let mut g = MaterialGrads::default();
        g.reset(3);
        g.v_albedo[1] = [0.5, -0.2, 0.3];
        g.v_roughness[1] = -0.7;
        g.v_normal[1] = [0.2, 0.9, -0.4];
        let mut v = s.zeros_like();
        g.chain_into(&s, &mut v);
        let loss = |t: &Surfels| {
            let (a, r, n) = (t.albedo(1), t.roughness(1), t.normal(1));
            (0..3).map(|k| a[k] * g.v_albedo[1][k] + n[k] * g.v_normal[1][k]).sum::<f32>() + r * g.v_roughness[1]
        };
        let h = 1e-3;
        for k in 0..3 {
            let (mut a, mut b) = (s.clone(), s.clone());
            a.albedo_logits[1][k] += h;
            b.albedo_logits[1][k] -= h;
            let fd = (loss(&a) - loss(&b)) / (2.0 * h);
            assert!((fd - v.albedo_logits[1][k]).abs() < 1e-3);
        }
        let (mut a, mut b) = (s.clone(), s.clone());
        a.roughness_logits[1] += h;
        b.roughness_logits[1] -= h;
        assert!(((loss(&a) - loss(&b)) / (2.0 * h) - v.roughness_logits[1]).abs() < 1e-3);
        for k in 0..4 {
            let (mut a, mut b) = (s.clone(), s.clone());
            a.quats[1][k] += h;
            b.quats[1][k] -= h;
            let fd = (loss(&a) - loss(&b)) / (2.0 * h);
            assert!((fd - v.quats[1][k]).abs() < 2e-3, "q{k}: {fd} vs {}", v.quats[1][k]);
        }
        assert_eq!(v.albedo_logits[0], [0.0; 3]);
    }
}
