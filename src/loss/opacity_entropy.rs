//! Binary-opacity regulariser on the surfels themselves (not on the rendered alpha).
//!
//! Why: after nvs the visible surface layer of an object is translucent and surfels inside the
//! object complete its opacity; the inverse stage then shades those interior surfels (dark,
//! self-occluded) into the picture and the albedo compensates. Pushing every surfel's opacity
//! to 0 or 1 makes the surface layer opaque (or prunable).
//!
//! With o_i = σ(x_i) (x the opacity logit) and H the binary entropy,
//!   L = 1/N Σ_i H(o_i),  H(o) = −o ln o − (1 − o) ln(1 − o),
//!   ∂H/∂o = ln((1 − o)/o) = −x, so ∂L/∂x_i = −x_i · o_i (1 − o_i) / N
//! (exact, no clamp needed: the product vanishes smoothly at both ends).

use crate::surfels::sigmoid;

/// Mean binary entropy of the surfel opacities; accumulates `weight · ∂L/∂logit` into
/// `v_logits`.
pub fn opacity_entropy(logits: &[f32], weight: f32, v_logits: &mut [f32]) -> f32 {
    let n = logits.len();
    assert_eq!(v_logits.len(), n);
    if n == 0 {
        return 0.0;
    }
    let scale = weight / n as f32;
    let mut acc = 0.0f64;
    for (&x, v) in logits.iter().zip(v_logits.iter_mut()) {
        let o = sigmoid(x);
        acc += entropy_of_logit(x as f64);
        *v += scale * (-x * o * (1.0 - o));
    }
    (acc / n as f64) as f32
}

/// H(σ(x)) in f64, stable for large |x|: H = ln(1 + e^{−|x|}) + |x| σ(−|x|).
fn entropy_of_logit(x: f64) -> f64 {
    let a = x.abs();
    let e = (-a).exp();
    (1.0 + e).ln() + a * e / (1.0 + e)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    fn entropy_direct(x: f64) -> f64 {
        let o = 1.0 / (1.0 + (-x).exp());
        -(o * o.ln() + (1.0 - o) * (1.0 - o).ln())
    }

    #[test]
    fn entropy_matches_the_definition_and_peaks_at_one_half() {
        for x in [-8.0, -2.0, -0.3, 0.0, 0.7, 3.0, 9.0] {
            assert!((entropy_of_logit(x) - entropy_direct(x)).abs() < 1e-9, "x = {x}");
        }
        assert!((entropy_of_logit(0.0) - std::f64::consts::LN_2).abs() < 1e-12);
        // Far from 0.5 it vanishes and stays finite (no ln 0).
        assert!(entropy_of_logit(80.0) < 1e-30 && entropy_of_logit(-80.0).is_finite());
    }

    #[test]
    fn gradient_matches_finite_differences_per_surfel() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        // Random logits plus the edge cases: o = 1/2 (zero gradient), saturated both ways.
        let mut x: Vec<f32> = (0..12).map(|_| rng.random_range(-6.0f32..6.0)).collect();
        x.extend([0.0, 15.0, -15.0, 1e-3]);
        let weight = 0.7f32;
        let mut v = vec![0.0f32; x.len()];
        let loss = opacity_entropy(&x, weight, &mut v);
        let n = x.len() as f64;
        let mean = x.iter().map(|&xi| entropy_of_logit(xi as f64)).sum::<f64>() / n;
        assert!((loss as f64 - mean).abs() < 1e-6);
        let h = 1e-5f64;
        for i in 0..x.len() {
            let xi = x[i] as f64;
            let fd = weight as f64 * (entropy_direct(xi + h) - entropy_direct(xi - h)) / (2.0 * h) / n;
            let tol = 1e-5 + 1e-3 * fd.abs();
            assert!((v[i] as f64 - fd).abs() < tol, "surfel {i}: x {xi}, analytic {} vs fd {fd}", v[i]);
        }
        // Accumulates rather than overwrites.
        let before = v.clone();
        opacity_entropy(&x, weight, &mut v);
        for i in 0..x.len() {
            assert!((v[i] - 2.0 * before[i]).abs() <= 1e-7 + 1e-6 * before[i].abs());
        }
    }

    #[test]
    fn a_gradient_step_pushes_opacities_away_from_one_half() {
        let x = [-1.0f32, -0.2, 0.2, 1.0];
        let mut v = [0.0f32; 4];
        opacity_entropy(&x, 1.0, &mut v);
        // Descent (x − lr·v) moves negative logits down and positive ones up.
        assert!(v[0] > 0.0 && v[1] > 0.0 && v[2] < 0.0 && v[3] < 0.0, "{v:?}");
    }
}
