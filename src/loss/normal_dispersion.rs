//! Spread of the surfel normals blended into each pixel.
//!
//! Why: 2DGS's normal consistency compares the *blended* normal N = Σ w_i n_i with the depth
//! normal, and N is linear in the n_i, so surfels tilted ±10° about a flat floor cancel in it
//! and go unpunished. Our shading is per surfel (cos θ with each surfel's own normal, its own
//! hemisphere of traced rays), so those tilts bias the direct light (measured on spheres: floor
//! surfels 7–13° off on average, their direct light under the true env 7–27 % too bright).
//!
//! For unit normals and α = Σ w_i, Σ w_i |n_i − N/α|² = α − |N|²/α ≥ 0 (Cauchy–Schwarz), zero
//! exactly when the blended normals agree. Per pixel with α > `ALPHA_MIN`:
//!   L = 1/P Σ_p (α_p − |N_p|² / α_p),
//!   ∂L/∂N_p = −2 N_p / (α_p P),   ∂L/∂α_p = (1 + |N_p|² / α_p²) / P.
//! (When the normals agree, N = α n, the two terms cancel for every weight: no push on opacity.)

/// Pixels with less coverage are skipped (the ratio is ill-conditioned there).
pub const ALPHA_MIN: f32 = 1e-3;

/// Mean normal dispersion over pixels; accumulates `weight · ∂L/∂normal` into `v_normal` and
/// `weight · ∂L/∂alpha` into `v_alpha`.
pub fn normal_dispersion(
    normal: &[[f32; 3]],
    alpha: &[f32],
    weight: f32,
    v_normal: &mut [[f32; 3]],
    v_alpha: &mut [f32],
) -> f32 {
    let n = normal.len();
    assert_eq!(alpha.len(), n);
    assert_eq!(v_normal.len(), n);
    assert_eq!(v_alpha.len(), n);
    if n == 0 {
        return 0.0;
    }
    let scale = weight / n as f32;
    let mut acc = 0.0f64;
    for p in 0..n {
        let a = alpha[p];
        if a <= ALPHA_MIN {
            continue;
        }
        let nn = normal[p];
        let len2 = nn[0] * nn[0] + nn[1] * nn[1] + nn[2] * nn[2];
        acc += (a - len2 / a) as f64;
        let g = -2.0 * scale / a;
        for k in 0..3 {
            v_normal[p][k] += g * nn[k];
        }
        v_alpha[p] += scale * (1.0 + len2 / (a * a));
    }
    (acc / n as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    fn unit(rng: &mut rand_pcg::Pcg64) -> [f32; 3] {
        let v: [f32; 3] = [0, 1, 2].map(|_| rng.random_range(-1.0f32..1.0));
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-3);
        v.map(|x| x / l)
    }

    /// Blend of `normals` with weights `w`: (Σ w n, Σ w).
    fn blend(normals: &[[f32; 3]], w: &[f32]) -> ([f32; 3], f32) {
        let mut nn = [0.0; 3];
        for (n, &wi) in normals.iter().zip(w) {
            for k in 0..3 {
                nn[k] += wi * n[k];
            }
        }
        (nn, w.iter().sum())
    }

    #[test]
    fn zero_for_agreeing_normals_and_the_weighted_spread_otherwise() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let n0 = unit(&mut rng);
        let w = [0.3f32, 0.25, 0.2];
        let (nn, a) = blend(&[n0; 3], &w);
        let mut vn = [[0.0f32; 3]; 1];
        let mut va = [0.0f32; 1];
        let l = normal_dispersion(&[nn], &[a], 1.0, &mut vn, &mut va);
        assert!(l.abs() < 1e-6, "agreeing normals: {l}");
        // The gradient with respect to each surfel's weight, ∂L/∂α + ∂L/∂N · n_i, is zero.
        let dw = va[0] + vn[0][0] * n0[0] + vn[0][1] * n0[1] + vn[0][2] * n0[2];
        assert!(dw.abs() < 1e-5, "{dw}");
        // Tilted normals: the loss is Σ w |n_i − N/α|².
        let normals = [unit(&mut rng), unit(&mut rng), unit(&mut rng)];
        let (nn, a) = blend(&normals, &w);
        let mean = nn.map(|x| x / a);
        let want: f32 =
            normals.iter().zip(&w).map(|(n, &wi)| wi * (0..3).map(|k| (n[k] - mean[k]).powi(2)).sum::<f32>()).sum();
        let got = normal_dispersion(&[nn], &[a], 1.0, &mut vn, &mut va);
        assert!((got - want).abs() < 1e-5 && got > 0.01, "{got} vs {want}");
    }

    #[test]
    fn gradient_matches_finite_differences_per_pixel() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
        // Pixels from blends of 1–4 random unit normals, plus a pixel below ALPHA_MIN (skipped)
        // and a nearly transparent one just above it.
        let mut normal = Vec::new();
        let mut alpha = Vec::new();
        for _ in 0..8 {
            let k = rng.random_range(1..5usize);
            let ns: Vec<[f32; 3]> = (0..k).map(|_| unit(&mut rng)).collect();
            let w: Vec<f32> = (0..k).map(|_| rng.random_range(0.05f32..0.3)).collect();
            let (nn, a) = blend(&ns, &w);
            normal.push(nn);
            alpha.push(a);
        }
        normal.push([1e-4, 0.0, 0.0]);
        alpha.push(5e-4);
        normal.push([0.0, 0.0, 0.004]);
        alpha.push(0.005);
        let weight = 0.3f32;
        let mut vn = vec![[0.0f32; 3]; normal.len()];
        let mut va = vec![0.0f32; normal.len()];
        normal_dispersion(&normal, &alpha, weight, &mut vn, &mut va);
        let f = |normal: &[[f64; 3]], alpha: &[f64]| -> f64 {
            let mut s = 0.0;
            for p in 0..normal.len() {
                if alpha[p] > ALPHA_MIN as f64 {
                    let l2: f64 = normal[p].iter().map(|x| x * x).sum();
                    s += alpha[p] - l2 / alpha[p];
                }
            }
            weight as f64 * s / normal.len() as f64
        };
        let n64: Vec<[f64; 3]> = normal.iter().map(|n| n.map(|x| x as f64)).collect();
        let a64: Vec<f64> = alpha.iter().map(|&a| a as f64).collect();
        let h = 1e-7;
        for p in 0..normal.len() {
            let tol = |fd: f64| 1e-5 + 1e-3 * fd.abs();
            for k in 0..3 {
                let (mut up, mut dn) = (n64.clone(), n64.clone());
                up[p][k] += h;
                dn[p][k] -= h;
                let fd = (f(&up, &a64) - f(&dn, &a64)) / (2.0 * h);
                assert!((vn[p][k] as f64 - fd).abs() < tol(fd), "pixel {p} normal[{k}]: {} vs {fd}", vn[p][k]);
            }
            let (mut up, mut dn) = (a64.clone(), a64.clone());
            up[p] += h;
            dn[p] -= h;
            let fd = (f(&n64, &up) - f(&n64, &dn)) / (2.0 * h);
            assert!((va[p] as f64 - fd).abs() < tol(fd), "pixel {p} alpha: {} vs {fd}", va[p]);
        }
        assert_eq!(va[8], 0.0, "a pixel below ALPHA_MIN has no gradient");
    }
}
