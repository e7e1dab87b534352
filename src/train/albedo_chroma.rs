//! Non-local albedo prior: surfels whose observed colour has the same chromaticity are pulled
//! towards one albedo (the Retinex assumption that shading changes brightness, not hue).
//!
//! Why: the image losses alone cannot tell a brighter albedo from more light on one face
//! (cornell's recovered light sends sideways light to the zenith and the walls' albedo takes
//! the difference, BENCHMARKS.md sessions 27–28). Tying the same-coloured faces that look in
//! different directions (floor and back wall, the block's sides and top) leaves the light to
//! explain their brightness difference. It did not move cornell's light (its error 0.447 →
//! 0.438), but it ties each material's faces: albedo +1.1 dB and relighting +1.1–1.25 dB there
//! on two seeds, spheres unchanged (BENCHMARKS.md, session 33). Not in the published method
//! (`--lambda-albedo-chroma`, default 0.1; 0 = off).
//!
//! Each surfel's chromaticity is that of its SH colour's DC part, linearised: χ = c / Σc.
//! Surfels are binned on (χ_r, χ_g) with cells `bin` wide; a surfel's target is the mean
//! albedo over its cell and the 8 around it, weighted by opacity × disk area (so the visible
//! layer sets it). Loss = λ · Σ_i w_i |a_i − ā(i)|₁ / Σ_i w_i over surfels with opacity ≥ 0.3
//! and a colour bright enough to have a hue; ā is differentiated too. With `--albedo-chroma-cap` C
//! each channel's difference counts at most C and beyond it goes free (off by default: it frees
//! spheres' checkerboard but costs cornell, BENCHMARKS.md session 62). The loss scales with the
//! albedo, so it leans slightly towards a darker albedo under a brighter light; the same prior
//! on ln a (scale-free) measured worse on cornell (BENCHMARKS.md, session 33).

use super::binned_albedo::{BinnedMean, MIN_OPACITY, Neighbourhoods, OUT, surfel_weight};
use crate::io::image::srgb_to_linear;
use crate::sh::SH_C0;
use crate::surfels::{ALBEDO_HI, ALBEDO_LO, Surfels};
use rayon::prelude::*;

/// Below this linear brightness (sum of channels) the chromaticity is noise.
const MIN_BRIGHTNESS: f32 = 0.03;

/// Buffers of the prior, kept between iterations.
#[derive(Default)]
pub struct AlbedoChroma {
    /// Per surfel: its cell, or [`OUT`] when it does not take part.
    cell: Vec<u32>,
    weight: Vec<f32>,
    core: BinnedMean,
}

impl AlbedoChroma {
    /// The loss (λ included) and its gradient added to `v_albedo` (per surfel, albedo units).
    pub fn loss(
        &mut self,
        surfels: &Surfels,
        albedo: &[[f32; 3]],
        lambda: f32,
        bin: f32,
        cap: f32,
        v_albedo: &mut [[f32; 3]],
    ) -> f32 {
        let cells = (1.0 / bin).ceil() as usize + 1;
        // Each surfel's cell and weight (parallel: three sRGB decodes a surfel).
        (0..surfels.len())
            .into_par_iter()
            .map(|i| {
                let Some(chi) = observed_chromaticity(surfels, i) else { return (OUT, 0.0) };
                let (x, y) = ((chi[0] / bin) as usize, (chi[1] / bin) as usize);
                ((x.min(cells - 1) * cells + y.min(cells - 1)) as u32, surfel_weight(surfels, i))
            })
            .unzip_into_vecs(&mut self.cell, &mut self.weight);
        self.core.loss(&self.cell, &self.weight, &ChromaGrid { cells }, albedo, lambda, cap, v_albedo)
    }
}

/// A `cells` × `cells` grid on the (r, g) chromaticity plane; a cell's neighbourhood is itself
/// and the 8 around it (fewer at the border), so neighbours across a cell border share a target.
struct ChromaGrid {
    cells: usize,
}

impl Neighbourhoods for ChromaGrid {
    fn bins(&self) -> usize {
        self.cells * self.cells
    }

    fn gather<const N: usize>(&self, grid: &[[f64; N]], out: &mut Vec<[f64; N]>) {
        let cells = self.cells;
        out.clear();
        for x in 0..cells {
            for y in 0..cells {
                let mut acc = [0.0f64; N];
                for nx in x.saturating_sub(1)..(x + 2).min(cells) {
                    for ny in y.saturating_sub(1)..(y + 2).min(cells) {
                        for (a, v) in acc.iter_mut().zip(&grid[nx * cells + ny]) {
                            *a += v;
                        }
                    }
                }
                out.push(acc);
            }
        }
    }
}

/// The chromaticity c / Σc of surfel i's linear SH colour (DC part), or None when the surfel
/// is too transparent or too dark to have a hue.
fn observed_chromaticity(surfels: &Surfels, i: usize) -> Option<[f32; 3]> {
    let c = surfels.sh[i][0].map(|x| srgb_to_linear((x * SH_C0 + 0.5).clamp(0.0, 1.0)));
    let sum = c[0] + c[1] + c[2];
    (surfels.opacity(i) >= MIN_OPACITY && sum >= MIN_BRIGHTNESS).then(|| c.map(|x| x / sum))
}

/// A fresh albedo per surfel that starts with the hue it was seen with (`albedo_init_hue`).
///
/// Why: from a grey start the light takes the scene's colours first (its learning rate is
/// the larger, and a saturated wall hardly constrains its own low channels), and the albedo
/// catches up only partly (cornell's red wall ends 3–5× too bright in green and blue,
/// BENCHMARKS.md session 36). Surfel i's linear SH colour c_i (DC part) has chromaticity
/// χ_i = c_i / Σc_i. The light's chromaticity χ_L is estimated from the near-grey surfels
/// ("grey pixels" colour constancy): starting from neutral, the weighted mean χ of the surfels
/// within `GREY_RADIUS` of the estimate, three times (a scene's mean colour would take a
/// saturated wall's hue for the light's: cornell's white floor then starts blue). Then
/// q_c = (χ_i,c / χ_L,c)^strength and the albedo is `level` · q_c / max(q), clamped to the
/// albedo range: the brightest channel starts at `level`, as a grey surfel's (a saturated red
/// starts at (level, low, low), not brighter in red than white is: with the mean level kept,
/// cornell's red wall started at 2.6 × 0.3 in red, ended at the range's 0.8 against the true
/// 0.63 and the light dimmed to match). Surfels too transparent or too dark to have a hue
/// start grey at `level`.
///
/// Only hues clearly off the light's take part: the strength ramps from 0 at `GREY_RADIUS`
/// (max channel distance from χ_L) to full at twice that. Why: a surfel's SH hue carries its
/// noise, and a start sticks; on spheres' mildly blue floor (0.07 off) the full-strength
/// start made the checker's albedo noisier (RMSE 0.097 vs 0.084) and relit 0.75 dB worse
/// (BENCHMARKS.md session 37), while cornell's walls (0.2 off) need the hue.
pub fn hued_albedo(surfels: &Surfels, level: f32, strength: f32) -> Vec<[f32; 3]> {
    let n = surfels.len();
    let chroma: Vec<Option<[f32; 3]>> = (0..n).into_par_iter().map(|i| observed_chromaticity(surfels, i)).collect();
    let light = light_chromaticity(surfels, &chroma);
    let grey = [level.clamp(ALBEDO_LO, ALBEDO_HI); 3];
    chroma
        .iter()
        .map(|chi| match chi {
            None => grey,
            Some(chi) => {
                // Near-grey surfels start grey, saturated ones with their hue (a ramp between).
                let off = (0..3).map(|c| (chi[c] - light[c]).abs()).fold(0.0f32, f32::max);
                let s = strength * ((off - GREY_RADIUS) / GREY_RADIUS).clamp(0.0, 1.0);
                // A channel that is 0 (a pure primary) keeps a small floor so q stays finite.
                let q = [0, 1, 2].map(|c| (chi[c].max(1e-3) / light[c]).powf(s));
                let q_max = q[0].max(q[1]).max(q[2]);
                q.map(|x| (level * x / q_max).clamp(ALBEDO_LO, ALBEDO_HI))
            }
        })
        .collect()
}

/// How far (max over channels) from the light's chromaticity a surfel's may lie to count as
/// grey: beyond a tinted light on a white surface (spheres' floor under the blue sky is 0.07
/// off neutral) and beyond the tints that shadows and reflections give the SH colours (the
/// floors' shadowed parts, the glossy spheres), which a start keeps. 0.2, not session 38's 0.1
/// (cornell's green wall, 0.2 off, now starts nearly grey): albedo and relighting better on
/// both shared scenes and both seeds tried (BENCHMARKS.md session 56).
const GREY_RADIUS: f32 = 0.2;

/// The light's chromaticity from the near-grey surfels (see [`hued_albedo`]); neutral when
/// none is near grey.
fn light_chromaticity(surfels: &Surfels, chroma: &[Option<[f32; 3]>]) -> [f32; 3] {
    let mut light = [1.0f32 / 3.0; 3];
    for _ in 0..3 {
        let (mut sum, mut total) = ([0.0f64; 3], 0.0f64);
        for (i, chi) in chroma.iter().enumerate() {
            let Some(chi) = chi else { continue };
            if (0..3).any(|c| (chi[c] - light[c]).abs() > GREY_RADIUS) {
                continue;
            }
            let w = surfel_weight(surfels, i) as f64;
            total += w;
            for c in 0..3 {
                sum[c] += w * chi[c] as f64;
            }
        }
        if total <= 0.0 {
            break;
        }
        light = sum.map(|x| (x / total) as f32);
    }
    light
}

#[cfg(test)]
mod tests {
    use super::super::binned_albedo::{check_gradient, random_surfels};
    use super::*;
    use crate::sh::rgb_to_dc;
    use rand::{RngExt, SeedableRng};

    /// Surfels in two colour families (a reddish one spread over several cells, a white one)
    /// with random opacities, scales and albedos.
    fn scene(seed: u64) -> (Surfels, Vec<[f32; 3]>) {
        let (mut s, albedo) = random_surfels(24, seed);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed + 100);
        for i in 0..s.len() {
            let base = if i % 2 == 0 { [0.8, 0.3, 0.3] } else { [0.7, 0.7, 0.7] };
            let c = base.map(|x: f32| x + rng.random_range(-0.05..0.05));
            s.sh[i][0] = c.map(rgb_to_dc);
        }
        (s, albedo)
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let (mut checked, mut kinks) = (0, 0);
        for seed in 0..4 {
            let (s, albedo) = scene(seed);
            let mut prior = AlbedoChroma::default();
            let (c, k) = check_gradient(&albedo, |a, g| prior.loss(&s, a, 0.7, 0.02, f32::INFINITY, g));
            (checked, kinks) = (checked + c, kinks + k);
        }
        assert!(kinks * 10 < checked, "{kinks} kinks against {checked} checked");
    }

    #[test]
    fn excluded_surfels_get_no_gradient_and_equal_albedos_cost_nothing() {
        let (mut s, albedo) = scene(7);
        s.opacity_logits[3] = -3.0; // opacity 0.05: out
        s.sh[5][0] = [0.0; 3].map(rgb_to_dc); // black: no hue
        let mut grad = vec![[0.0f32; 3]; s.len()];
        let loss = AlbedoChroma::default().loss(&s, &albedo, 1.0, 0.02, f32::INFINITY, &mut grad);
        assert!(loss > 0.0);
        assert_eq!(grad[3], [0.0; 3]);
        assert_eq!(grad[5], [0.0; 3]);
        // One albedo for every surfel: every target equals it.
        let same = vec![[0.4, 0.2, 0.6]; s.len()];
        let mut grad = vec![[0.0f32; 3]; s.len()];
        let loss = AlbedoChroma::default().loss(&s, &same, 1.0, 0.02, f32::INFINITY, &mut grad);
        assert!(loss.abs() < 1e-6, "{loss}");
    }

    #[test]
    fn the_loss_scales_with_the_albedo() {
        let (s, albedo) = scene(3);
        let half: Vec<[f32; 3]> = albedo.iter().map(|a| a.map(|x| 0.5 * x)).collect();
        let mut g = vec![[0.0f32; 3]; s.len()];
        let full = AlbedoChroma::default().loss(&s, &albedo, 1.0, 0.02, f32::INFINITY, &mut g);
        let halved = AlbedoChroma::default().loss(&s, &half, 1.0, 0.02, f32::INFINITY, &mut g);
        assert!(full > 0.01 && (0.5 * full - halved).abs() < 1e-5 * full, "{full} vs {halved}");
    }

    #[test]
    fn different_hues_are_not_tied() {
        // Two red surfels of different albedo pull on each other; the blue one is untouched.
        let mut s = Surfels::random_in_box(3, [0.0; 3], [1.0; 3], 1);
        s.sh[0][0] = [0.9, 0.1, 0.1].map(rgb_to_dc);
        s.sh[1][0] = [0.1, 0.1, 0.9].map(rgb_to_dc);
        s.sh[2][0] = [0.5, 0.06, 0.06].map(rgb_to_dc);
        s.opacity_logits = vec![3.0; 3];
        let albedo = vec![[0.8, 0.1, 0.1], [0.1, 0.1, 0.7], [0.4, 0.05, 0.05]];
        let mut grad = vec![[0.0f32; 3]; 3];
        let loss = AlbedoChroma::default().loss(&s, &albedo, 1.0, 0.02, f32::INFINITY, &mut grad);
        assert!(loss > 0.01, "{loss}");
        assert!(grad[0][0] > 0.0 && grad[2][0] < 0.0, "{grad:?}");
        assert!(grad[1].iter().all(|g| g.abs() < 1e-7), "{grad:?}");
    }

    /// With a cap, two grey materials of different brightness (a checkerboard's squares) go
    /// free of each other, while close albedos are still pulled together; the gradient of the
    /// capped loss matches finite differences.
    #[test]
    fn a_cap_frees_materials_of_one_hue_and_different_brightness() {
        let mut s = Surfels::random_in_box(4, [0.0; 3], [1.0; 3], 2);
        for i in 0..4 {
            s.sh[i][0] = [0.6, 0.6, 0.6].map(rgb_to_dc);
        }
        s.opacity_logits = vec![3.0; 4];
        s.log_scales = vec![[-2.0, -2.0]; 4];
        // Light squares 0.8 and 0.78, dark squares 0.4 and 0.42: every surfel is ~0.2 from the
        // common mean 0.6, past a cap of 0.1; uncapped, all four are pulled towards it.
        let albedo = vec![[0.8; 3], [0.78; 3], [0.4; 3], [0.42; 3]];
        let mut free = vec![[0.0f32; 3]; 4];
        let capped = AlbedoChroma::default().loss(&s, &albedo, 1.0, 0.02, 0.1, &mut free);
        assert!((capped - 3.0 * 0.1).abs() < 1e-5, "{capped}");
        assert!(free.iter().flatten().all(|g| g.abs() < 1e-7), "{free:?}");
        let mut pulled = vec![[0.0f32; 3]; 4];
        AlbedoChroma::default().loss(&s, &albedo, 1.0, 0.02, f32::INFINITY, &mut pulled);
        assert!(pulled[0][0] > 0.0 && pulled[2][0] < 0.0, "{pulled:?}");
        // Within the cap the pull stays.
        let close = vec![[0.62; 3], [0.6; 3], [0.58; 3], [0.6; 3]];
        let mut g = vec![[0.0f32; 3]; 4];
        AlbedoChroma::default().loss(&s, &close, 1.0, 0.02, 0.1, &mut g);
        assert!(g[0][0] > 0.0 && g[2][0] < 0.0, "{g:?}");
        let (mut checked, mut kinks) = (0, 0);
        for seed in 0..4 {
            let (s, albedo) = scene(seed);
            let mut prior = AlbedoChroma::default();
            let (c, k) = check_gradient(&albedo, |a, g| prior.loss(&s, a, 0.7, 0.02, 0.08, g));
            (checked, kinks) = (checked + c, kinks + k);
        }
        assert!(kinks * 10 < checked, "{kinks} kinks against {checked} checked");
    }

    #[test]
    fn hued_albedo_keeps_the_hue_and_not_the_light() {
        // Grey and red surfels: under a white and under a blue-tinted light the start is the
        // same (the light's tint is read off the grey surfels), grey surfels start grey, red
        // ones red, all with the brightest channel at the level.
        let lit_with = |tint: [f32; 3], red: fn(usize) -> bool| {
            let mut s = Surfels::random_in_box(40, [0.0; 3], [1.0; 3], 3);
            for i in 0..s.len() {
                let albedo = if red(i) { [0.7, 0.1, 0.1] } else { [0.5, 0.5, 0.5] };
                let linear = [0, 1, 2].map(|c| albedo[c] * tint[c]);
                s.sh[i][0] = linear.map(|x| rgb_to_dc(crate::io::image::linear_to_srgb(x)));
                s.opacity_logits[i] = 3.0;
                s.log_scales[i] = [-2.0, -2.0];
            }
            // One transparent and one black surfel: no hue to take.
            s.opacity_logits[1] = -4.0;
            s.sh[2][0] = [0.0; 3].map(rgb_to_dc);
            s
        };
        let lit = |tint: [f32; 3]| lit_with(tint, |i| i % 4 == 0);
        let (white, tinted) = (lit([1.0; 3]), lit([0.8, 0.9, 1.2]));
        let a = hued_albedo(&tinted, 0.3, 1.0);
        let a_white = hued_albedo(&white, 0.3, 1.0);
        assert_eq!(a[1], [0.3; 3]);
        assert_eq!(a[2], [0.3; 3]);
        for i in 3..a.len() {
            let (a, b) = (a[i], a_white[i]);
            assert!(a.iter().all(|&x| (ALBEDO_LO..=ALBEDO_HI).contains(&x)), "{i}: {a:?}");
            assert!((0..3).all(|c| (a[c] - b[c]).abs() < 0.02), "{i}: tinted {a:?}, white {b:?}");
            assert!((a[0].max(a[1]).max(a[2]) - 0.3).abs() < 1e-4, "{i}: {a:?}");
            if i % 4 == 0 {
                assert!(a[0] > 2.5 * a[1] && a[0] > 2.5 * a[2], "red surfel {i}: {a:?}");
            } else {
                assert!(a.iter().all(|&x| (x - 0.3).abs() < 1e-3), "grey surfel {i}: {a:?}");
            }
        }
        // Red surfels in the majority (3 in 4): the grey ones still start grey (a mean over the
        // scene would take the red for the light's colour).
        let mostly_red = hued_albedo(&lit_with([0.8, 0.9, 1.2], |i| i % 4 != 3), 0.3, 1.0);
        assert!(mostly_red[3].iter().all(|&x| (x - 0.3).abs() < 1e-3), "{:?}", mostly_red[3]);
        // Strength 0 is the published grey start; a half strength lies between.
        assert!(hued_albedo(&tinted, 0.3, 0.0).iter().all(|a| a.iter().all(|&x| (x - 0.3).abs() < 1e-6)));
        let (full, half) = (a[4], hued_albedo(&tinted, 0.3, 0.5)[4]);
        assert!(half[0] == full[0] && half[1] > full[1] && half[1] < 0.3, "{half:?} {full:?}");
    }

    #[test]
    fn only_clearly_tinted_surfels_take_their_hue() {
        // Grey, faintly blue (0.04 off neutral), half-saturated orange (0.27 off) and red
        // (0.44 off) surfels under a white light: the faint tint starts grey, the orange one
        // with part of its hue, the red one with all of it.
        let colours = [[0.5, 0.5, 0.5], [0.5, 0.5, 0.6], [0.85, 0.35, 0.2], [0.7, 0.1, 0.1]];
        let mut s = Surfels::random_in_box(40, [0.0; 3], [1.0; 3], 5);
        for i in 0..s.len() {
            let c = colours[if i % 2 == 0 { 0 } else { 1 + (i / 2) % 3 }];
            s.sh[i][0] = c.map(|x| rgb_to_dc(crate::io::image::linear_to_srgb(x)));
            s.opacity_logits[i] = 3.0;
            s.log_scales[i] = [-2.0, -2.0];
        }
        let full = |c: [f32; 3]| {
            let sum = c[0] + c[1] + c[2];
            let q = c.map(|x| x / sum * 3.0);
            let m = q[0].max(q[1]).max(q[2]);
            q.map(|x| 0.3 * x / m)
        };
        let a = hued_albedo(&s, 0.3, 1.0);
        for i in 0..s.len() {
            let kind = if i % 2 == 0 { 0 } else { 1 + (i / 2) % 3 };
            match kind {
                0 | 1 => assert!(a[i].iter().all(|&x| (x - 0.3).abs() < 1e-3), "{i} kind {kind}: {:?}", a[i]),
                2 => {
                    let f = full(colours[2]);
                    assert!(a[i][2] < 0.3 - 0.01 && a[i][2] > f[2] + 0.01, "{i}: {:?} vs full {f:?}", a[i]);
                }
                _ => {
                    let f = full(colours[3]);
                    assert!((0..3).all(|c| (a[i][c] - f[c]).abs() < 0.02), "{i}: {:?} vs {f:?}", a[i]);
                }
            }
        }
    }
}
