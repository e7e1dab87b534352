//! Importance sampling of a known environment map, mixed with the Fibonacci directions by the
//! balance heuristic (Veach's multi-sample model).
//!
//! Why: under a map with a small bright source (a sun, a window) S uniform directions per
//! surfel hit the source a few times or not at all, and because each surfel's directions are
//! fixed the error is a blotchy pattern that a relit picture keeps. Relighting knows its map
//! before tracing, so part of each surfel's rays can go where the light is.
//!
//! Only the map's peaks are sampled: each texel's luminance above [`PEAK_THRESHOLD`] × the
//! map's mean. Elsewhere the map is smooth, and there the Fibonacci directions (a quadrature)
//! are far better than random ones: drawing from a smooth learned light cost cornell's PBR test
//! images 1.7 dB at S = 64 (BENCHMARKS.md, session 58). A map without peaks gets no sampler.
//!
//! The density follows the peaks as the shading reads them (bilinear between texel centres):
//! the map is cut into cells between four neighbouring texel centres (half cells at the poles,
//! where the lookup clamps), a cell is chosen with probability ∝ the mean of its corners' peak
//! luminance × its solid angle, and inside it the point is drawn with the bilinear density of
//! those four values in the map's (x, y) coordinates. So a one-texel sun is sampled as the tent
//! the lookup makes of it, and pdf(ω) = P(cell) · f(t)/(f̄·area) / J(θ),
//! J = dω/(dx dy) = sin θ · (π/H)(2π/W); pdf is 0 away from the peaks, which the Fibonacci
//! directions cover.
//!
//! A surfel's S samples: `n_u` Fibonacci directions (jittered within their bands: uniform over
//! the cap `n·ω ≥ sin 10°`, density n_u/Ω_cap together) and `n_e` drawn from the map. Each
//! sample in the cap weighs 1 / (n_u/Ω_cap + n_e·pdf_env(ω)); a map sample outside the cap
//! weighs 0 (the uniform estimator's domain). With `n_e = 0` this is the plain Fibonacci
//! quadrature, weight Ω_cap/S.

use super::sampling::{
    ElevationFloor, MIN_ELEVATION_DEG, cap_solid_angle, fibonacci_cap_jittered, fibonacci_hemisphere,
};
use crate::envmap::EnvMap;
use std::f64::consts::PI;

/// A texel is part of a peak by its luminance above this multiple of the map's mean (per
/// steradian). At 128 × 64 the relighting maps put 22 % (city's sun), 15 % (forest), 12 %
/// (courtyard) and 2 % (sunset) of their light above it; the learned lights of the shared
/// scenes (at most 5.7 × their mean) nothing.
pub const PEAK_THRESHOLD: f64 = 10.0;

/// Below this share of the map's light in its peaks, the map gets no sampler.
const MIN_PEAK_SHARE: f64 = 1e-3;

/// A sampler of directions ∝ an environment map's light.
#[derive(Clone, Debug)]
pub struct EnvSampler {
    width: usize,
    height: usize,
    /// Peak luminance (above the threshold) per texel, W × H.
    lum: Vec<f64>,
    /// Cumulative probabilities of the H + 1 cell rows, H + 2 entries from 0 to 1.
    row_cdf: Vec<f64>,
    /// Per cell row, cumulative column probabilities within it, W + 1 entries each.
    col_cdf: Vec<f64>,
    /// Per cell (row-major, (H + 1) × W): P(cell) / (mean corner luminance × (x, y) area).
    scale: Vec<f64>,
}

/// Cell row r spans map rows y ∈ [top, top + height) between texel rows `upper` and `lower`.
#[derive(Clone, Copy)]
struct CellRow {
    top: f64,
    height: f64,
    upper: usize,
    lower: usize,
}

fn cell_row(r: usize, h: usize) -> CellRow {
    if r == 0 {
        CellRow { top: 0.0, height: 0.5, upper: 0, lower: 0 }
    } else if r == h {
        CellRow { top: h as f64 - 0.5, height: 0.5, upper: h - 1, lower: h - 1 }
    } else {
        CellRow { top: r as f64 - 0.5, height: 1.0, upper: r - 1, lower: r }
    }
}

/// The corner luminances of cell (r, c) of a W × H map: upper-left, upper-right, lower-left,
/// lower-right (columns wrap).
fn cell_corners(lum: &[f64], w: usize, h: usize, r: usize, c: usize) -> [f64; 4] {
    let cr = cell_row(r, h);
    let c1 = (c + 1) % w;
    [lum[cr.upper * w + c], lum[cr.upper * w + c1], lum[cr.lower * w + c], lum[cr.lower * w + c1]]
}

/// Draws t ∈ [0, 1) with density ∝ (1 − t)·a + t·b (a, b ≥ 0) from u ∈ [0, 1).
fn sample_linear(a: f64, b: f64, u: f64) -> f64 {
    // The root of ((b − a)/2)t² + a·t = u(a + b)/2, written without cancellation.
    if a + b <= 0.0 {
        return u;
    }
    let k = u * (a + b);
    (k / (a + (a * a + (b - a) * k).max(0.0).sqrt())).clamp(0.0, 1.0 - 1e-12)
}

impl EnvSampler {
    /// The sampler of `env`'s peaks; `None` if it has none (or no finite light).
    pub fn new(env: &EnvMap) -> Option<EnvSampler> {
        let (w, h) = (env.width, env.height);
        if w == 0 || h == 0 || env.texels.len() != w * h {
            return None;
        }
        let mut lum: Vec<f64> = env
            .texels
            .iter()
            .map(|t| {
                let l = 0.2126 * t[0] as f64 + 0.7152 * t[1] as f64 + 0.0722 * t[2] as f64;
                if l.is_finite() { l.max(0.0) } else { 0.0 }
            })
            .collect();
        let total: f64 = (0..w * h).map(|k| lum[k] * env.texel_solid_angle(k / w) as f64).sum();
        if !(total.is_finite() && total > 0.0) {
            return None;
        }
        let threshold = PEAK_THRESHOLD * total / (4.0 * PI);
        lum.iter_mut().for_each(|l| *l = (*l - threshold).max(0.0));
        let peaks: f64 = (0..w * h).map(|k| lum[k] * env.texel_solid_angle(k / w) as f64).sum();
        if !(peaks > MIN_PEAK_SHARE * total) {
            return None;
        }
        // Each cell's mean corner luminance, and its mass: that × its solid angle.
        let rows = h + 1;
        let mut mean = vec![0.0f64; rows * w];
        let mut mass = vec![0.0f64; rows * w];
        for r in 0..rows {
            let cr = cell_row(r, h);
            let (t0, t1) = (cr.top / h as f64 * PI, (cr.top + cr.height) / h as f64 * PI);
            let omega = 2.0 * PI / w as f64 * (t0.cos() - t1.cos());
            for c in 0..w {
                mean[r * w + c] = 0.25 * cell_corners(&lum, w, h, r, c).iter().sum::<f64>();
                mass[r * w + c] = mean[r * w + c] * omega;
            }
        }
        let sum: f64 = mass.iter().sum();
        let mut row_cdf = Vec::with_capacity(rows + 1);
        let mut col_cdf = Vec::with_capacity(rows * (w + 1));
        let mut scale = vec![0.0f64; rows * w];
        let mut acc = 0.0;
        row_cdf.push(0.0);
        for r in 0..rows {
            let cr = cell_row(r, h);
            let row = &mass[r * w..(r + 1) * w];
            let row_sum: f64 = row.iter().sum();
            let mut cum = 0.0;
            col_cdf.push(0.0);
            for (c, &m) in row.iter().enumerate() {
                cum += m;
                // (A row without peaks is never chosen.)
                col_cdf.push(if row_sum > 0.0 { cum / row_sum } else { (c + 1) as f64 / w as f64 });
                let f = mean[r * w + c];
                scale[r * w + c] = if f > 0.0 { m / sum / (f * cr.height) } else { 0.0 };
            }
            col_cdf[r * (w + 1) + w] = 1.0;
            acc += row_sum;
            row_cdf.push(acc / sum);
        }
        row_cdf[rows] = 1.0;
        Some(EnvSampler { width: w, height: h, lum, row_cdf, col_cdf, scale })
    }

    /// The four corner luminances of cell (r, c): upper-left, upper-right, lower-left, lower-right.
    fn corners(&self, r: usize, c: usize) -> [f64; 4] {
        cell_corners(&self.lum, self.width, self.height, r, c)
    }

    /// Density (per steradian) of map point (x, y) (pixel units, as [`EnvMap::dir_to_pixel`]).
    fn pdf_xy(&self, x: f64, y: f64) -> f64 {
        let (w, h) = (self.width, self.height);
        let fx = (x - 0.5).rem_euclid(w as f64);
        let c = (fx.floor() as usize).min(w - 1);
        let tx = (fx - c as f64).clamp(0.0, 1.0);
        let r = ((y + 0.5).floor().max(0.0) as usize).min(h);
        let cr = cell_row(r, h);
        let ty = ((y - cr.top) / cr.height).clamp(0.0, 1.0);
        let [a, b, cc, d] = self.corners(r, c);
        let f = (1.0 - ty) * ((1.0 - tx) * a + tx * b) + ty * ((1.0 - tx) * cc + tx * d);
        let theta = y / h as f64 * PI;
        let jacobian = theta.sin() * (PI / h as f64) * (2.0 * PI / w as f64);
        if jacobian <= 0.0 { 0.0 } else { self.scale[r * w + c] * f / jacobian }
    }

    /// Density (per steradian) of direction `d` (unit).
    pub fn pdf(&self, d: [f32; 3]) -> f32 {
        let u = 0.5 - (d[1] as f64).atan2(d[0] as f64) / (2.0 * PI);
        // atan2, not acos: near the poles acos of an f32 z loses the angle.
        let (dx, dy, dz) = (d[0] as f64, d[1] as f64, d[2] as f64);
        let theta = (dx * dx + dy * dy).sqrt().atan2(dz);
        let x = (u - u.floor()) * self.width as f64;
        self.pdf_xy(x, theta / PI * self.height as f64) as f32
    }

    /// A direction for the uniform numbers `u` ∈ [0, 1)⁴ (cell row, cell column, within the
    /// cell), and its density.
    pub fn sample(&self, u: [f64; 4]) -> ([f32; 3], f32) {
        let (w, h) = (self.width, self.height);
        let r = upper_bin(&self.row_cdf, u[0]).min(h);
        let c = upper_bin(&self.col_cdf[r * (w + 1)..(r + 1) * (w + 1)], u[1]).min(w - 1);
        let [a, b, cc, d] = self.corners(r, c);
        let tx = sample_linear(a + cc, b + d, u[2]);
        let ty = sample_linear((1.0 - tx) * a + tx * b, (1.0 - tx) * cc + tx * d, u[3]);
        let cr = cell_row(r, h);
        let x = (c as f64 + 0.5 + tx).rem_euclid(w as f64);
        let y = cr.top + ty * cr.height;
        let theta = y / h as f64 * PI;
        let phi = (0.5 - x / w as f64) * 2.0 * PI;
        let dir = [(theta.sin() * phi.cos()) as f32, (theta.sin() * phi.sin()) as f32, theta.cos() as f32];
        (dir, self.pdf_xy(x, y) as f32)
    }
}

/// The bin k with cdf[k] ≤ u < cdf[k + 1] (cdf ascending from 0 to 1).
fn upper_bin(cdf: &[f64], u: f64) -> usize {
    let k = cdf.partition_point(|&c| c <= u);
    k.saturating_sub(1)
}

/// Writes surfel normal `n`'s S = `dirs.len()` directions, the first `dirs.len() − n_env`
/// Fibonacci (rotated by `rotation`), the rest drawn from `sampler` with the uniform numbers
/// of `uniforms` (stratified in the row coordinate), and each sample's estimator weight
/// (module note). `n_env` = 0 (or no sampler) gives the plain Fibonacci directions and weight.
///
/// With map samples the Fibonacci points are jittered within their bands of equal solid angle
/// (z_i = 1 − (1 − z_min)(i + ξ_i)/n_u): the balance heuristic is unbiased only if the uniform
/// technique's samples together have density n_u/Ω_cap everywhere, and fixed rings never see
/// the poles' or the gaps' light (a sun on the normal: −38 % with fixed rings).
pub fn mixture_directions(
    n: [f32; 3],
    rotation: f64,
    sampler: Option<&EnvSampler>,
    n_env: usize,
    mut uniforms: impl FnMut() -> f64,
    dirs: &mut [[f32; 3]],
    weights: &mut [f32],
) {
    let s = dirs.len();
    let n_env = if sampler.is_some() { n_env.min(s.saturating_sub(1)) } else { 0 };
    let n_u = s - n_env;
    let Some(sampler) = sampler.filter(|_| n_env > 0) else {
        let w = fibonacci_hemisphere(n, rotation, MIN_ELEVATION_DEG, ElevationFloor::Spread, dirs);
        weights.fill(w as f32);
        return;
    };
    let z_min = MIN_ELEVATION_DEG.to_radians().sin();
    let omega_cap = cap_solid_angle(MIN_ELEVATION_DEG);
    fibonacci_cap_jittered(n, rotation, MIN_ELEVATION_DEG, &mut uniforms, &mut dirs[..n_u]);
    for k in 0..n_env {
        let u = [(k as f64 + uniforms()) / n_env as f64, uniforms(), uniforms(), uniforms()];
        dirs[n_u + k] = sampler.sample(u).0;
    }
    for (d, wt) in dirs.iter().zip(weights.iter_mut()) {
        let z = n[0] as f64 * d[0] as f64 + n[1] as f64 * d[1] as f64 + n[2] as f64 * d[2] as f64;
        *wt = if z >= z_min {
            (1.0 / (n_u as f64 / omega_cap + n_env as f64 * sampler.pdf(*d) as f64)) as f32
        } else {
            0.0
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// A dim sky with one bright texel cluster (a "sun") and coloured texels.
    fn sun_map(w: usize, h: usize) -> EnvMap {
        let mut env = EnvMap::constant(w, h, [0.05, 0.06, 0.08]);
        for (k, t) in env.texels.iter_mut().enumerate() {
            let f = 1.0 + 0.5 * ((k * 7919) % 13) as f32 / 13.0;
            *t = t.map(|c| c * f);
        }
        let (i, j) = (w / 3, h / 4);
        env.texels[j * w + i] = [400.0, 380.0, 300.0];
        env.texels[j * w + i + 1] = [100.0, 90.0, 80.0];
        env
    }

    /// ∫ g(ω) dω over the sphere by quadrature on `sub` × `sub` cells a texel.
    fn sphere_integral(env: &EnvMap, sub: usize, g: impl Fn([f32; 3]) -> f64) -> f64 {
        let (w, h) = (env.width * sub, env.height * sub);
        let mut acc = 0.0;
        for y in 0..h {
            let (t0, t1) = (y as f64 / h as f64 * PI, (y + 1) as f64 / h as f64 * PI);
            let omega = 2.0 * PI / w as f64 * (t0.cos() - t1.cos());
            for x in 0..w {
                let d = env.pixel_to_dir((x as f32 + 0.5) / sub as f32, (y as f32 + 0.5) / sub as f32);
                acc += g(d) * omega;
            }
        }
        acc
    }

    #[test]
    fn density_integrates_to_one_and_follows_the_light() {
        let env = sun_map(32, 16);
        let s = EnvSampler::new(&env).unwrap();
        let total = sphere_integral(&env, 16, |d| s.pdf(d) as f64);
        assert!((total - 1.0).abs() < 2e-3, "{total}");
        let sun = s.pdf(env.texel_dir(32 / 3, 4));
        let sky = s.pdf(env.texel_dir(0, 12));
        assert!(sun > 0.0 && sky == 0.0, "sun {sun} sky {sky}: only the peaks are sampled");
        // Within the sun's tent the density falls as the lookup's radiance does.
        let half = s.pdf(env.pixel_to_dir(32.0 / 3.0 - 0.5 + 0.5, 4.5 - 0.5));
        assert!(half < 0.7 * sun && half > 0.2 * sun, "sun {sun} half a texel up {half}");
    }

    #[test]
    fn samples_follow_the_density() {
        // Σ g(ω)/pdf(ω) / N → ∫ g dω over the density's support only if the samples' density
        // is pdf: for g = 1 (the support's solid angle), a cap round the sun, and the map's
        // own light (sampled nearly in proportion: small variance).
        let env = sun_map(16, 8);
        let s = EnvSampler::new(&env).unwrap();
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let n = 100_000;
        let sun = env.texel_dir(16 / 3, 2);
        let on = |d: [f32; 3]| if s.pdf(d) > 0.0 { 1.0 } else { 0.0 };
        let cap = |d: [f32; 3]| if d[0] * sun[0] + d[1] * sun[1] + d[2] * sun[2] > 0.995 { on(d) } else { 0.0 };
        // The peaks' luminance as the lookup reads it (texels above the threshold, less it).
        let lum = |t: [f32; 3]| 0.2126 * t[0] as f64 + 0.7152 * t[1] as f64 + 0.0722 * t[2] as f64;
        let total: f64 = (0..16 * 8).map(|k| lum(env.texels[k]) * env.texel_solid_angle(k / 16) as f64).sum();
        let mut peaks = env.clone();
        for t in peaks.texels.iter_mut() {
            *t = [(lum(*t) - PEAK_THRESHOLD * total / (4.0 * PI)).max(0.0) as f32; 3];
        }
        let light = |d: [f32; 3]| peaks.lookup(d)[0] as f64;
        let gs: [&dyn Fn([f32; 3]) -> f64; 3] = [&on, &cap, &light];
        let mut sums = [[0.0f64; 2]; 3];
        for _ in 0..n {
            let u = [rng.random::<f64>(), rng.random::<f64>(), rng.random::<f64>(), rng.random::<f64>()];
            let (d, p) = s.sample(u);
            assert!(((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) - 1.0).abs() < 1e-5);
            assert!(p > 0.0 && (p - s.pdf(d)).abs() <= 1e-3 * p, "{p} vs {}", s.pdf(d));
            for (k, g) in gs.iter().enumerate() {
                let x = g(d) / p as f64;
                sums[k][0] += x;
                sums[k][1] += x * x;
            }
        }
        for (k, g) in gs.iter().enumerate() {
            let truth = sphere_integral(&env, 32, g);
            assert!(truth > 0.0);
            let mean = sums[k][0] / n as f64;
            let se = ((sums[k][1] / n as f64 - mean * mean).max(0.0) / n as f64).sqrt();
            assert!((mean - truth).abs() < 4.0 * se + 3e-3 * truth, "g {k}: {mean} ± {se} vs {truth}");
            if k == 2 {
                // Sampled as the lookup spreads it: relative error of one sample below 10 %.
                assert!(se * (n as f64).sqrt() < 0.1 * truth, "light: {se} of {truth}");
            }
        }
    }

    /// Reference: the irradiance-like integral ∫_cap L(ω) (n·ω) dω by dense quadrature over
    /// the map's texels (16 × 16 sub-cells each).
    fn cap_integral(env: &EnvMap, n: [f32; 3]) -> [f64; 3] {
        let z_min = MIN_ELEVATION_DEG.to_radians().sin();
        let mut acc = [0.0f64; 3];
        let sub = 16;
        for y in 0..env.height * sub {
            for x in 0..env.width * sub {
                let (px, py) = ((x as f32 + 0.5) / sub as f32, (y as f32 + 0.5) / sub as f32);
                let d = env.pixel_to_dir(px, py);
                let z = (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) as f64;
                if z < z_min {
                    continue;
                }
                let t0 = y as f64 / (env.height * sub) as f64 * PI;
                let t1 = (y + 1) as f64 / (env.height * sub) as f64 * PI;
                let omega = 2.0 * PI / (env.width * sub) as f64 * (t0.cos() - t1.cos());
                let l = env.lookup(d);
                for c in 0..3 {
                    acc[c] += l[c] as f64 * z * omega;
                }
            }
        }
        acc
    }

    #[test]
    fn the_mixture_estimates_the_cap_integral_with_less_noise() {
        let env = sun_map(64, 32);
        let sampler = EnvSampler::new(&env).unwrap();
        let estimate = |n: [f32; 3], n_env: usize, trial: u64| -> [f64; 3] {
            let mut rng = rand_pcg::Pcg64::seed_from_u64(trial);
            let rotation = rng.random::<f64>() * std::f64::consts::TAU;
            let (mut dirs, mut w) = (vec![[0.0f32; 3]; 32], vec![0.0f32; 32]);
            mixture_directions(n, rotation, Some(&sampler), n_env, || rng.random::<f64>(), &mut dirs, &mut w);
            let mut acc = [0.0f64; 3];
            for (d, &wt) in dirs.iter().zip(&w) {
                let z = (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]).max(0.0) as f64;
                let l = env.lookup(*d);
                for c in 0..3 {
                    acc[c] += wt as f64 * l[c] as f64 * z;
                }
            }
            acc
        };
        // A normal that sees the sun, and a grazing one that has it near its 10° floor.
        let sun = env.texel_dir(64 / 3, 8);
        let grazing = {
            let t = [sun[1], -sun[0], 0.0];
            let l = (t[0] * t[0] + t[1] * t[1]).sqrt();
            let (a, b) = (80f32.to_radians().cos(), 80f32.to_radians().sin());
            let n = [sun[0] * a + t[0] / l * b, sun[1] * a + t[1] / l * b, sun[2] * a];
            let m = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            n.map(|x| x / m)
        };
        for n in [[0.0, 0.0, 1.0], sun, grazing] {
            let truth = cap_integral(&env, n);
            let trials = 2000;
            let (mut mean, mut var_mix, mut var_uni) = (0.0, 0.0, 0.0);
            for t in 0..trials {
                let m = estimate(n, 16, t)[1];
                let u = estimate(n, 0, t)[1];
                mean += m / trials as f64;
                var_mix += (m - truth[1]).powi(2) / trials as f64;
                var_uni += (u - truth[1]).powi(2) / trials as f64;
            }
            // Unbiased within 3 standard errors; and the mixture's error is smaller.
            let se = (var_mix / trials as f64).sqrt();
            assert!((mean - truth[1]).abs() < 3.0 * se + 1e-3 * truth[1], "n {n:?}: {mean} vs {}", truth[1]);
            // Measured: 0.017–0.11 of the uniform's squared error.
            assert!(var_mix < 0.25 * var_uni, "n {n:?}: mixture {var_mix} uniform {var_uni}");
        }
    }

    #[test]
    fn without_map_samples_every_weight_is_fibonaccis() {
        let env = sun_map(16, 8);
        let sampler = EnvSampler::new(&env).unwrap();
        let (mut d0, mut w0) = (vec![[0.0f32; 3]; 8], vec![0.0f32; 8]);
        let (mut d1, mut w1) = (vec![[0.0f32; 3]; 8], vec![0.0f32; 8]);
        mixture_directions([0.0, 1.0, 0.0], 0.3, Some(&sampler), 0, || 0.5, &mut d0, &mut w0);
        mixture_directions([0.0, 1.0, 0.0], 0.3, None, 4, || 0.5, &mut d1, &mut w1);
        let mut d2 = vec![[0.0f32; 3]; 8];
        let w = fibonacci_hemisphere([0.0, 1.0, 0.0], 0.3, MIN_ELEVATION_DEG, ElevationFloor::Spread, &mut d2) as f32;
        assert_eq!(d0, d2);
        assert_eq!(d1, d2);
        assert!(w0.iter().chain(&w1).all(|&x| x == w));
    }

    #[test]
    fn a_map_without_peaks_has_no_sampler() {
        assert!(EnvSampler::new(&EnvMap::constant(8, 4, [0.0; 3])).is_none());
        assert!(EnvSampler::new(&EnvMap::constant(8, 4, [f32::NAN; 3])).is_none());
        assert!(EnvSampler::new(&EnvMap::constant(8, 4, [1.0; 3])).is_none());
        let mut env = EnvMap::constant(32, 16, [1.0; 3]);
        env.texels[5 * 32 + 7] = [8.0; 3];
        assert!(EnvSampler::new(&env).is_none(), "8 × the mean is no peak");
        env.texels[5 * 32 + 7] = [200.0; 3];
        assert!(EnvSampler::new(&env).is_some());
    }
}
