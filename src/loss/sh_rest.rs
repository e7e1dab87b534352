//! View-dependence penalty: the energy of the surfels' higher-order SH coefficients.
//!
//! Why: on textureless surfaces (cornell's white floor and walls) many geometries reproduce the
//! images, and view-dependent SH lets a wrong one absorb the parallax of the soft shading that
//! would otherwise pin the surface down (with SH degree 0 throughout, cornell's normal error
//! falls from 10.05° to 8.04°). Penalising the coefficients beyond the DC term keeps view
//! dependence where the images need it (glossy objects) and removes it where they do not.
//!
//! L = 1/N Σ_i Σ_{k = 1..(d+1)²} Σ_c f_ikc² over the active degree d; ∂L/∂f_ikc = 2 f_ikc / N.

use crate::sh::SH_COEFFS;

/// Mean SH-rest energy per surfel over the active degree; accumulates `weight · ∂L/∂f` into
/// `v_sh` (same layout as `Surfels::sh`).
pub fn sh_rest_energy(
    sh: &[[[f32; 3]; SH_COEFFS]],
    degree: u32,
    weight: f32,
    v_sh: &mut [[[f32; 3]; SH_COEFFS]],
) -> f32 {
    let n = sh.len();
    assert_eq!(v_sh.len(), n);
    let active = ((degree as usize + 1) * (degree as usize + 1)).min(SH_COEFFS);
    if n == 0 || active <= 1 {
        return 0.0;
    }
    let scale = 2.0 * weight / n as f32;
    let mut acc = 0.0f64;
    for (coeffs, v) in sh.iter().zip(v_sh.iter_mut()) {
        for k in 1..active {
            for c in 0..3 {
                let f = coeffs[k][c];
                acc += (f as f64) * (f as f64);
                v[k][c] += scale * f;
            }
        }
    }
    (acc / n as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    fn random_sh(n: usize, seed: u64) -> Vec<[[f32; 3]; SH_COEFFS]> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        (0..n).map(|_| std::array::from_fn(|_| std::array::from_fn(|_| rng.random_range(-0.6..0.6f32)))).collect()
    }

    /// Central differences in f64 of the energy, per coefficient, for every degree; coefficients
    /// beyond the active degree and the DC term get no gradient.
    #[test]
    fn gradient_matches_finite_differences_per_coefficient() {
        let sh = random_sh(5, 3);
        let energy = |s: &[[[f32; 3]; SH_COEFFS]], d: usize| -> f64 {
            let active = (d + 1) * (d + 1);
            s.iter().map(|c| (1..active).flat_map(|k| c[k]).map(|f| (f as f64).powi(2)).sum::<f64>()).sum::<f64>()
                / s.len() as f64
        };
        for degree in 0..=3u32 {
            let weight = 0.7;
            let mut v = vec![[[0.0f32; 3]; SH_COEFFS]; sh.len()];
            let l = sh_rest_energy(&sh, degree, weight, &mut v);
            assert!((l as f64 - energy(&sh, degree as usize)).abs() < 1e-5);
            for i in 0..sh.len() {
                for k in 0..SH_COEFFS {
                    for c in 0..3 {
                        let h = 1e-3f32;
                        let (mut p, mut m) = (sh.clone(), sh.clone());
                        p[i][k][c] += h;
                        m[i][k][c] -= h;
                        let fd = weight as f64 * (energy(&p, degree as usize) - energy(&m, degree as usize))
                            / (2.0 * h as f64);
                        assert!(
                            (v[i][k][c] as f64 - fd).abs() < 1e-4,
                            "degree {degree} surfel {i} coeff {k} ch {c}: {} vs {fd}",
                            v[i][k][c]
                        );
                    }
                }
            }
        }
        // Empty input and degree 0: nothing to penalise.
        assert_eq!(sh_rest_energy(&[], 3, 1.0, &mut []), 0.0);
    }
}
