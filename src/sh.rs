//! Real spherical harmonics up to degree 3 in the 3DGS sign convention, with the backward pass.
//!
//! colour = max(Σ_k c_k · Y_k(d) + 0.5, 0) per channel, d the unit view direction (from the
//! ray origin towards the surfel). Only the first (degree + 1)² coefficients are used.

pub const SH_COEFFS: usize = 16;
pub const SH_C0: f32 = 0.282_094_8;
const C1: f32 = 0.488_602_52;
const C2: [f32; 5] = [1.092_548_4, -1.092_548_4, 0.315_391_57, -1.092_548_4, 0.546_274_2];
const C3: [f32; 7] = [-0.590_043_6, 2.890_611_4, -0.457_045_8, 0.373_176_33, -0.457_045_8, 1.445_305_7, -0.590_043_6];

/// Number of coefficients used at an SH degree (0..=3).
pub fn coeff_count(degree: u32) -> usize {
    ((degree.min(3) + 1) * (degree.min(3) + 1)) as usize
}

/// The basis Y_k(d) for a unit direction d.
pub fn basis(d: [f32; 3]) -> [f32; SH_COEFFS] {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    [
        SH_C0,
        -C1 * y,
        C1 * z,
        -C1 * x,
        C2[0] * x * y,
        C2[1] * y * z,
        C2[2] * (2.0 * zz - xx - yy),
        C2[3] * x * z,
        C2[4] * (xx - yy),
        C3[0] * y * (3.0 * xx - yy),
        C3[1] * x * y * z,
        C3[2] * y * (4.0 * zz - xx - yy),
        C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
        C3[4] * x * (4.0 * zz - xx - yy),
        C3[5] * z * (xx - yy),
        C3[6] * x * (xx - 3.0 * yy),
    ]
}

/// Partial derivatives ∂Y_k/∂(x, y, z) of the basis polynomials (d treated as free).
pub fn basis_jacobian(d: [f32; 3]) -> [[f32; 3]; SH_COEFFS] {
    let [x, y, z] = d;
    let (xx, yy, zz) = (x * x, y * y, z * z);
    [
        [0.0, 0.0, 0.0],
        [0.0, -C1, 0.0],
        [0.0, 0.0, C1],
        [-C1, 0.0, 0.0],
        [C2[0] * y, C2[0] * x, 0.0],
        [0.0, C2[1] * z, C2[1] * y],
        [-2.0 * C2[2] * x, -2.0 * C2[2] * y, 4.0 * C2[2] * z],
        [C2[3] * z, 0.0, C2[3] * x],
        [2.0 * C2[4] * x, -2.0 * C2[4] * y, 0.0],
        [6.0 * C3[0] * x * y, C3[0] * (3.0 * xx - 3.0 * yy), 0.0],
        [C3[1] * y * z, C3[1] * x * z, C3[1] * x * y],
        [-2.0 * C3[2] * x * y, C3[2] * (4.0 * zz - xx - 3.0 * yy), 8.0 * C3[2] * y * z],
        [-6.0 * C3[3] * x * z, -6.0 * C3[3] * y * z, C3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy)],
        [C3[4] * (4.0 * zz - 3.0 * xx - yy), -2.0 * C3[4] * x * y, 8.0 * C3[4] * x * z],
        [2.0 * C3[5] * x * z, -2.0 * C3[5] * y * z, C3[5] * (xx - yy)],
        [C3[6] * (3.0 * xx - 3.0 * yy), -6.0 * C3[6] * x * y, 0.0],
    ]
}

/// SH radiance for an unnormalised direction `dir` (normalised here), clamped at 0.
pub fn eval(coeffs: &[[f32; 3]; SH_COEFFS], degree: u32, dir: [f32; 3]) -> [f32; 3] {
    let d = normalize(dir);
    let b = basis(d);
    let mut c = [0.5f32; 3];
    // Degree 3 (every trained scene) as a loop of fixed length, which compiles unrolled and
    // without bounds checks; the same sums in the same order as the general loop.
    let n = if degree >= 3 { SH_COEFFS } else { coeff_count(degree) };
    let sum = |c: &mut [f32; 3], coeffs: &[[f32; 3]], b: &[f32]| {
        for (ck, bk) in coeffs.iter().zip(b) {
            for ch in 0..3 {
                c[ch] += ck[ch] * bk;
            }
        }
    };
    if n == SH_COEFFS {
        sum(&mut c, coeffs, &b)
    } else {
        sum(&mut c, &coeffs[..n], &b[..n])
    }
    [c[0].max(0.0), c[1].max(0.0), c[2].max(0.0)]
}

/// Backward of [`eval`]: adds ∂L/∂coeffs into `v_coeffs` and returns ∂L/∂dir for the
/// unnormalised `dir`.
pub fn eval_backward(
    coeffs: &[[f32; 3]; SH_COEFFS],
    degree: u32,
    dir: [f32; 3],
    v_colour: [f32; 3],
    v_coeffs: &mut [[f32; 3]; SH_COEFFS],
) -> [f32; 3] {
    let len = (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt().max(1e-12);
    let d = [dir[0] / len, dir[1] / len, dir[2] / len];
    let b = basis(d);
    let n = coeff_count(degree);
    // The clamp at zero blocks gradients of channels that were clamped.
    let mut raw = [0.5f32; 3];
    for k in 0..n {
        for ch in 0..3 {
            raw[ch] += coeffs[k][ch] * b[k];
        }
    }
    let v = [
        if raw[0] > 0.0 { v_colour[0] } else { 0.0 },
        if raw[1] > 0.0 { v_colour[1] } else { 0.0 },
        if raw[2] > 0.0 { v_colour[2] } else { 0.0 },
    ];
    for k in 0..n {
        for ch in 0..3 {
            v_coeffs[k][ch] += v[ch] * b[k];
        }
    }
    if n <= 1 {
        return [0.0; 3];
    }
    let jac = basis_jacobian(d);
    let mut v_d = [0.0f32; 3];
    for k in 1..n {
        let g = coeffs[k][0] * v[0] + coeffs[k][1] * v[1] + coeffs[k][2] * v[2];
        for a in 0..3 {
            v_d[a] += g * jac[k][a];
        }
    }
    // Through the normalisation: ∂d/∂dir = (I − d dᵀ) / |dir|.
    let dot = v_d[0] * d[0] + v_d[1] * d[1] + v_d[2] * d[2];
    [(v_d[0] - dot * d[0]) / len, (v_d[1] - dot * d[1]) / len, (v_d[2] - dot * d[2]) / len]
}

fn normalize(v: [f32; 3]) -> [f32; 3] {
    let len = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
    [v[0] / len, v[1] / len, v[2] / len]
}

/// DC coefficient that makes SH radiance equal `rgb` in every direction.
pub fn rgb_to_dc(rgb: f32) -> f32 {
    (rgb - 0.5) / SH_C0
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    #[test]
    fn basis_is_orthonormal_by_monte_carlo() {
        // ∫ Y_i Y_j dω = δ_ij, estimated over a Fibonacci sphere.
        let n = 20000;
        let mut gram = [[0.0f64; SH_COEFFS]; SH_COEFFS];
        for s in 0..n {
            let z = 1.0 - 2.0 * (s as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = s as f64 * 2.399_963_229_728_653;
            let b = basis([(r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32]);
            for i in 0..SH_COEFFS {
                for j in 0..SH_COEFFS {
                    gram[i][j] += (b[i] as f64) * (b[j] as f64) * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for i in 0..SH_COEFFS {
            for j in 0..SH_COEFFS {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((gram[i][j] - want).abs() < 2e-3, "gram[{i}][{j}] = {}", gram[i][j]);
            }
        }
    }

    /// Coefficients uniform in ±`amp` and an unnormalised direction in the unit cube.
    fn random_case(rng: &mut rand_pcg::Pcg64, amp: f32) -> ([[f32; 3]; SH_COEFFS], [f32; 3]) {
        let mut coeffs = [[0.0f32; 3]; SH_COEFFS];
        for c in coeffs.iter_mut().flatten() {
            *c = rng.random_range(-amp..amp);
        }
        let dir = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0f32)];
        (coeffs, dir)
    }

    /// Each degree sums exactly its (degree + 1)² coefficients (the ones beyond are ignored)
    /// and matches an f64 sum; degrees above 3 act as 3.
    #[test]
    fn eval_uses_the_degree_s_coefficients_only() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        for _ in 0..50 {
            let (coeffs, dir) = random_case(&mut rng, 0.5);
            let b = basis(normalize(dir));
            for degree in 0..=4u32 {
                let n = coeff_count(degree);
                let got = eval(&coeffs, degree, dir);
                let mut junk = coeffs;
                for c in junk[n..].iter_mut().flatten() {
                    *c = 7.0;
                }
                assert_eq!(eval(&junk, degree, dir), got, "degree {degree}: reads beyond its coefficients");
                for ch in 0..3 {
                    let want = (0.5 + (0..n).map(|k| coeffs[k][ch] as f64 * b[k] as f64).sum::<f64>()).max(0.0);
                    assert!(
                        (got[ch] as f64 - want).abs() < 1e-5,
                        "degree {degree}, channel {ch}: {} vs {want}",
                        got[ch]
                    );
                }
            }
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        for _ in 0..20 {
            let (coeffs, dir) = random_case(&mut rng, 0.3);
            let v_col = [0.7, -0.4, 1.1];
            let loss = |c: &[[f32; 3]; SH_COEFFS], d: [f32; 3]| {
                let col = eval(c, 3, d);
                (col[0] * v_col[0] + col[1] * v_col[1] + col[2] * v_col[2]) as f64
            };
            let mut v_coeffs = [[0.0f32; 3]; SH_COEFFS];
            let v_dir = eval_backward(&coeffs, 3, dir, v_col, &mut v_coeffs);
            let h = 1e-3f32;
            for a in 0..3 {
                let (mut dp, mut dm) = (dir, dir);
                dp[a] += h;
                dm[a] -= h;
                let fd = (loss(&coeffs, dp) - loss(&coeffs, dm)) / (2.0 * h as f64);
                assert!((fd - v_dir[a] as f64).abs() < 2e-2 * (1.0 + fd.abs()), "dir[{a}]: fd {fd} vs {}", v_dir[a]);
            }
            for k in 0..SH_COEFFS {
                let (mut cp, mut cm) = (coeffs, coeffs);
                cp[k][1] += h;
                cm[k][1] -= h;
                let fd = (loss(&cp, dir) - loss(&cm, dir)) / (2.0 * h as f64);
                assert!((fd - v_coeffs[k][1] as f64).abs() < 1e-2, "coeff {k}: fd {fd} vs {}", v_coeffs[k][1]);
            }
        }
    }
}
