//! The albedo–light gauge of the inverse stage: a 1-D search along the one direction in which
//! the PBR image hardly constrains the materials and the light.
//!
//! Under a → s·a, env → env/s the diffuse light from the env, a·E_env, does not change; only
//! the diffuse indirect part (∝ s: the traced indirect light comes from the surfels' SH, not
//! the env) and the specular env part (∝ 1/s) do. The image loss is therefore nearly flat
//! along s and Adam leaves the scale where the initialisation (albedo 0.3, env 1.5) and the
//! learning rates put it: on `../shared/data/spheres` the learned albedo came out 1.55–1.76×
//! too dark under an env as much too bright, which scales the indirect light (and the
//! indirect PSNR) down by the same factor. Every `gauge_every` iterations the stage evaluates
//! the PBR image loss (L1 + 0.2·D-SSIM, the training weights) on a few fixed training views
//! for scales s on a log grid, refines the best by golden-section search, and applies it to the
//! albedo (clamped to its range) and the env. s = 1 is always evaluated, so the step never
//! raises the evaluated loss. Not in the published method (0 = off).

use super::inverse::{InverseState, SpecularLobe, SurfelShading, TRAIN_CHANNELS, sample_factor};
use super::material::MaterialView;
use super::nvs::TrainImages;
use super::pbr_image::{PbrImage, PbrImageLoss};
use crate::camera::Camera;
use crate::envmap::EnvMap;
use crate::raster::blend_weights::BlendWeights;
use crate::raster::{Outputs, RasterSettings};
use crate::shade::incident::IncidentCache;
use crate::shade::splitsum::SplitSum;
use crate::shade::traced_specular::TracedSpecular;
use crate::surfels::Surfels;
use crate::surfels::{ALBEDO_HI, ALBEDO_LO, albedo_to_logit};
use crate::trace::Tracer;
use crate::train::config::{Specular, TrainConfig};

/// Scales searched: s in [1/4, 4].
const LOG_S_MAX: f64 = 1.386_294_4;
/// Grid points over [−LOG_S_MAX, LOG_S_MAX] (odd, so s = 1 is one of them) and golden-section
/// steps after it.
const GRID: usize = 9;
const GOLDEN_STEPS: usize = 6;
/// Half-width of the first, narrow bracket (ln s: ±10 %) and its golden-section steps (final
/// bracket 0.2 · 0.618³ ≈ 0.05 in ln s, as the whole-range search's 0.69 · 0.618⁶).
const LOCAL: f64 = 0.1;
const LOCAL_STEPS: usize = 3;
/// Training views the loss is evaluated on.
const VIEWS: usize = 3;

/// What one fit found.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct GaugeFit {
    pub scale: f32,
    pub loss_at_one: f32,
    pub loss: f32,
    pub evaluations: usize,
}

/// The albedo a surfel gets under scale s.
pub fn scaled_albedo(a: [f32; 3], s: f32) -> [f32; 3] {
    a.map(|x| (x * s).clamp(ALBEDO_LO, ALBEDO_HI))
}

/// One view's shading split by how it scales, per shaded surfel (`active`), under the unscaled
/// materials and light: the Lambert lobe per unit albedo from the env (`lambert_env`) and from
/// the indirect light (`lambert_indirect`), and the specular lobe's env and indirect parts.
///
/// The shading is linear in the albedo and in the env (the box filter, the split-sum prefilter
/// and the traced lobe's env lookups are linear too), so under a → a' = clamp(s·a), env → env/s
///   L_pbr(s) = (a' ⊙ lambert_env + specular_env) / s + a' ⊙ lambert_indirect + specular_indirect,
/// exactly what shading the scaled materials gives (up to rounding): two shading passes per
/// view and fit instead of one per evaluated scale.
#[derive(Default)]
pub struct ScaledShading {
    pub active: Vec<u32>,
    pub lambert_env: Vec<[f32; 3]>,
    pub lambert_indirect: Vec<[f32; 3]>,
    pub specular_env: Vec<[f32; 3]>,
    pub specular_indirect: Vec<[f32; 3]>,
}

impl ScaledShading {
    /// Split the shading of `mats` (whose albedo is replaced) for `camera`: `first` is the lobe
    /// of the first pass (a traced lobe traces there), `again` that of the second (for a traced
    /// lobe `TracedAgain` under the same env, else the same lobe).
    #[allow(clippy::too_many_arguments)]
    pub fn compute(
        shading: &mut SurfelShading,
        surfels: &Surfels,
        mats: &MaterialView,
        cache: &IncidentCache,
        env: &EnvMap,
        first: SpecularLobe,
        again: SpecularLobe,
        camera: &Camera,
    ) -> ScaledShading {
        let mut unit = MaterialView { albedo: vec![[1.0; 3]; mats.albedo.len()], ..mats.clone() };
        shading.compute(surfels, &unit, cache, env, first, camera, TRAIN_CHANNELS);
        let (lambert_env, lambert_indirect) = (shading.direct.clone(), shading.indirect.clone());
        let active = shading.active.clone();
        unit.albedo.iter_mut().for_each(|a| *a = [0.0; 3]);
        shading.compute(surfels, &unit, cache, env, again, camera, TRAIN_CHANNELS);
        debug_assert_eq!(shading.active, active, "the albedo does not change which surfels are shaded");
        let minus = |a: Vec<[f32; 3]>, b: &[[f32; 3]]| -> Vec<[f32; 3]> {
            a.iter().zip(b).map(|(x, y)| [x[0] - y[0], x[1] - y[1], x[2] - y[2]]).collect()
        };
        ScaledShading {
            lambert_env: minus(lambert_env, &shading.direct),
            lambert_indirect: minus(lambert_indirect, &shading.indirect),
            specular_env: shading.direct.clone(),
            specular_indirect: shading.indirect.clone(),
            active,
        }
    }

    /// Per-surfel linear PBR colour (N × 3, zero where not shaded) under scale `s` for the
    /// unscaled albedo `albedo`.
    pub fn pbr(&self, albedo: &[[f32; 3]], s: f32, out: &mut Vec<f32>) {
        out.clear();
        out.resize(albedo.len() * 3, 0.0);
        for (k, &i) in self.active.iter().enumerate() {
            let i = i as usize;
            let a = scaled_albedo(albedo[i], s);
            for c in 0..3 {
                out[i * 3 + c] = (a[c] * self.lambert_env[k][c] + self.specular_env[k][c]) / s
                    + a[c] * self.lambert_indirect[k][c]
                    + self.specular_indirect[k][c];
            }
        }
    }
}

/// Evaluates the PBR image loss for a given scale (buffers reused between calls).
struct Evaluator<'a> {
    images: &'a TrainImages,
    views: Vec<usize>,
    albedo: Vec<[f32; 3]>,
    /// Per view: its shading split by scaling, and its blend weights (the geometry is fixed
    /// during a fit: every scale is blended with the same weights, no render per evaluation).
    shading: Vec<ScaledShading>,
    blend: Vec<BlendWeights>,
    /// Per view, the ground truth over black.
    gt: Vec<Vec<[f32; 3]>>,
    /// Scratch: per-surfel PBR colour, and one view's blended image.
    surfel_pbr: Vec<f32>,
    pbr: Vec<f32>,
    loss: PbrImageLoss,
    evaluations: usize,
}

impl Evaluator<'_> {
    fn loss(&mut self, s: f32) -> f32 {
        self.evaluations += 1;
        // A black background: the GT is composited over it too, so only the object counts.
        let bg = [0.0f32; 3];
        let mut total = 0.0f64;
        for (slot, &v) in self.views.iter().enumerate() {
            let cam = &self.images.cameras[v];
            self.shading[slot].pbr(&self.albedo, s, &mut self.surfel_pbr);
            let blend = &self.blend[slot];
            blend.blend(&self.surfel_pbr, 3, 0, 3, &mut self.pbr);
            let wh = (cam.width as usize, cam.height as usize);
            let img = PbrImage {
                features: &self.pbr,
                channels: 3,
                alpha: &blend.alpha,
                bg,
                gt: &self.gt[slot],
                gt_alpha: &self.images.alpha[v],
                size: wh,
            };
            let t = self.loss.value(&img);
            total += (t.l1 + 0.2 * t.dssim) as f64;
        }
        (total / self.views.len() as f64) as f32
    }
}

/// Search the scale s minimising the PBR image loss on a few training views.
pub fn fit(cfg: &TrainConfig, state: &InverseState, images: &TrainImages) -> GaugeFit {
    let n = images.cameras.len();
    let count = VIEWS.min(n);
    // Fixed views spread over the set: the fit is deterministic.
    let views: Vec<usize> = (0..count).map(|k| k * n / count).collect();
    let mut mats = MaterialView::default();
    mats.update(&state.surfels);
    let env = state.env();
    let env_s = env.box_downsample(sample_factor(cfg));
    let split_sum = match cfg.specular {
        Specular::SplitSum => Some(SplitSum::new(&env).expect("the learned env is a valid map")),
        Specular::Mc | Specular::Traced => None,
    };
    let tracer = (cfg.specular == Specular::Traced)
        .then(|| Tracer::build(&state.surfels, &super::inverse::trace_settings_with(&state.back_faces(cfg))));
    let settings = RasterSettings {
        window: cfg.window,
        filter_inv_square: cfg.filter_inv_square,
        two_sided: false,
        outputs: Outputs::none(),
        ..RasterSettings::default()
    };
    let mut scratch = SurfelShading::default();
    let (mut shading, mut blend, mut gt) = (Vec::new(), Vec::new(), Vec::new());
    for &v in &views {
        let cam = &images.cameras[v];
        let lobes = || match (&split_sum, &tracer) {
            (Some(ss), _) => (SpecularLobe::SplitSum(ss), SpecularLobe::SplitSum(ss)),
            (None, Some(tracer)) => (
                SpecularLobe::Traced(TracedSpecular {
                    tracer,
                    surfels: &state.surfels,
                    env: &env,
                    start: cfg.ray_start(state.extent),
                    rays: cfg.specular_rays,
                    // Fixed per fit (and per view): every scale sees the same samples.
                    seed: cfg.seed ^ 0x6a09_e667 ^ (state.iteration as u64) << 8 ^ v as u64,
                }),
                SpecularLobe::TracedAgain(&env),
            ),
            (None, None) => (SpecularLobe::Cached, SpecularLobe::Cached),
        };
        let (first, again) = lobes();
        shading.push(ScaledShading::compute(
            &mut scratch,
            &state.surfels,
            &mats,
            &state.cache,
            &env_s,
            first,
            again,
            cam,
        ));
        blend.push(BlendWeights::compute(&state.surfels, cam, &settings));
        gt.push(images.rgb[v].iter().zip(&images.alpha[v]).map(|(c, &a)| c.map(|x| x * a)).collect());
    }
    let mut ev = Evaluator {
        images,
        views,
        albedo: mats.albedo,
        shading,
        blend,
        gt,
        surfel_pbr: Vec::new(),
        pbr: Vec::new(),
        loss: PbrImageLoss::clipping(cfg.clip_saturated),
        evaluations: 0,
    };
    let (best_x, best_loss, loss_at_one) = search(|x| ev.loss(x.exp() as f32));
    GaugeFit { scale: best_x.exp() as f32, loss_at_one, loss: best_loss, evaluations: ev.evaluations }
}

/// Minimise `loss` over x = ln s in [−LOG_S_MAX, LOG_S_MAX]: (best x, its loss, the loss at
/// x = 0). x = 0 is always evaluated, so the result is never worse than s = 1.
fn search(mut loss: impl FnMut(f64) -> f32) -> (f64, f32, f32) {
    // After the first fits the scale stays within a few per cent of 1 (session 39: every fit
    // after the fifth within ±2 % on cornell): try a narrow bracket around 1 first and search
    // the whole range only when its best point is not inside it.
    let loss_at_one = loss(0.0);
    let (below, above) = (loss(-LOCAL), loss(LOCAL));
    let (lo, hi, mut best_x, mut best_loss, steps) = if loss_at_one <= below && loss_at_one <= above {
        (-LOCAL, LOCAL, 0.0, loss_at_one, LOCAL_STEPS)
    } else {
        let step = 2.0 * LOG_S_MAX / (GRID - 1) as f64;
        let grid: Vec<(f64, f32)> = (0..GRID)
            .map(|k| {
                // The middle point is s = 1, evaluated above.
                if k == GRID / 2 {
                    return (0.0, loss_at_one);
                }
                let x = -LOG_S_MAX + k as f64 * step;
                (x, loss(x))
            })
            .collect();
        let best = (0..GRID).min_by(|&a, &b| grid[a].1.total_cmp(&grid[b].1)).unwrap_or(GRID / 2);
        let (lo, hi) = (grid[best.saturating_sub(1)].0, grid[(best + 1).min(GRID - 1)].0);
        let mut fit = (lo, hi, grid[best].0, grid[best].1, GOLDEN_STEPS);
        for (x, f) in [(-LOCAL, below), (LOCAL, above)] {
            if f < fit.3 {
                (fit.2, fit.3) = (x, f);
            }
        }
        fit
    };
    let (mut lo, mut hi) = (lo, hi);
    // Golden-section search in the bracket.
    let r = (5f64.sqrt() - 1.0) / 2.0;
    let mut c = hi - r * (hi - lo);
    let mut d = lo + r * (hi - lo);
    let (mut fc, mut fd) = (loss(c), loss(d));
    for _ in 0..steps {
        if fc < fd {
            hi = d;
            (d, fd) = (c, fc);
            c = hi - r * (hi - lo);
            fc = loss(c);
        } else {
            lo = c;
            (c, fc) = (d, fd);
            d = lo + r * (hi - lo);
            fd = loss(d);
        }
    }
    for (x, f) in [(c, fc), (d, fd)] {
        if f < best_loss {
            (best_x, best_loss) = (x, f);
        }
    }
    (best_x, best_loss, loss_at_one)
}

/// Apply scale s: albedo × s (clamped to its range), env ÷ s (a shift of the log texels).
pub fn apply(state: &mut InverseState, s: f32) {
    if s == 1.0 {
        return;
    }
    let surfels = &mut state.surfels;
    for i in 0..surfels.len() {
        surfels.albedo_logits[i] = scaled_albedo(surfels.albedo(i), s).map(albedo_to_logit);
    }
    let shift = s.ln();
    for l in &mut state.light.log {
        *l -= shift;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The narrow bracket finds a minimum near s = 1 in few evaluations; a minimum outside it
    /// falls back to the whole range; the result is never worse than s = 1.
    #[test]
    fn search_finds_near_and_far_minima() {
        for (x0, max_evals) in [(0.03, 8), (-0.04, 8), (0.0, 8), (-0.07, 19), (0.4, 19), (-1.1, 19), (1.38, 19)] {
            let mut evals = 0;
            let (x, f, f1) = search(|x| {
                evals += 1;
                ((x - x0) * (x - x0)) as f32 + 0.5
            });
            assert!(evals <= max_evals, "minimum at {x0}: {evals} evaluations");
            assert!((x - x0).abs() < 0.03, "minimum at {x0}: found {x}");
            assert!(f <= f1 && f1 == (x0 * x0) as f32 + 0.5);
        }
        // A loss with its minimum at the edge of the narrow bracket's neighbour grid point and a
        // flat region: still never above the loss at s = 1.
        let (_, f, f1) = search(|x| if x.abs() < 0.5 { 1.0 } else { 2.0 });
        assert!(f <= f1);
    }
    use crate::shade::pbr::{PbrInputs, shade_surfels};

    /// The transform is the claimed symmetry: under a → s·a, env → env/s the Lambert light from
    /// the env is unchanged and the Lambert indirect light scales by s (the specular env part by
    /// 1/s), per surfel of the real shading code.
    #[test]
    fn scaling_albedo_and_light_keeps_the_diffuse_env_light() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let (n, samples) = (40usize, 16usize);
        let env = EnvMap {
            width: 16,
            height: 8,
            texels: (0..128).map(|_| [rng.random_range(0.2..3.0), rng.random_range(0.2..3.0), 1.0]).collect(),
        };
        let albedo: Vec<[f32; 3]> = (0..n).map(|_| [0, 1, 2].map(|_| rng.random_range(0.05..0.3))).collect();
        let roughness: Vec<f32> = (0..n).map(|_| rng.random_range(0.2..0.9)).collect();
        let normal = vec![[0.0, 0.0, 1.0]; n];
        let view: Vec<[f32; 3]> = (0..n).map(|_| [0.3, 0.1, 0.95]).collect();
        let dirs: Vec<[f32; 3]> = (0..n * samples)
            .map(|_| {
                let (a, z) = (rng.random_range(0.0..6.28f32), rng.random_range(0.2..1.0f32));
                let r = (1.0 - z * z).sqrt();
                [r * a.cos(), r * a.sin(), z]
            })
            .collect();
        let vis: Vec<f32> = (0..n * samples).map(|_| rng.random_range(0.0..1.0)).collect();
        let ind: Vec<[f32; 3]> = (0..n * samples).map(|_| [rng.random_range(0.0..0.5); 3]).collect();
        let shade = |albedo: &[[f32; 3]], env: &EnvMap, specular: bool| {
            let inp = PbrInputs {
                albedo,
                roughness: &roughness,
                normal: &normal,
                view: &view,
                dirs: &dirs,
                visibility: &vis,
                indirect: &ind,
                samples,
                weight: 2.0 * std::f32::consts::PI / samples as f32,
                sample_weights: None,
                specular,
                lambert: true,
                footprints: None,
            };
            let (mut d, mut i) = (vec![[0.0f32; 3]; n], vec![[0.0f32; 3]; n]);
            shade_surfels(&inp, env, &mut d, &mut i).unwrap();
            (d, i)
        };
        let s = 2.5f32;
        let scaled: Vec<[f32; 3]> = albedo.iter().map(|&a| scaled_albedo(a, s)).collect();
        let mut dim = env.clone();
        dim.texels.iter_mut().for_each(|t| *t = t.map(|v| v / s));
        let (d0, i0) = shade(&albedo, &env, false);
        let (d1, i1) = shade(&scaled, &dim, false);
        let (ds0, is0) = shade(&albedo, &env, true);
        let (ds1, is1) = shade(&scaled, &dim, true);
        for k in 0..n {
            for c in 0..3 {
                let close = |a: f32, b: f32| (a - b).abs() <= 1e-5 + 1e-4 * b.abs();
                assert!(close(d1[k][c], d0[k][c]), "diffuse env light changed: {} vs {}", d1[k][c], d0[k][c]);
                assert!(close(i1[k][c], s * i0[k][c]), "diffuse indirect not × s: {} vs {}", i1[k][c], s * i0[k][c]);
                // Specular parts: env part ÷ s, indirect part unchanged.
                let (spec_env0, spec_env1) = (ds0[k][c] - d0[k][c], ds1[k][c] - d1[k][c]);
                let (spec_ind0, spec_ind1) = (is0[k][c] - i0[k][c], is1[k][c] - i1[k][c]);
                assert!(close(spec_env1, spec_env0 / s), "specular env part not ÷ s");
                assert!(close(spec_ind1, spec_ind0), "specular indirect part changed");
            }
        }
        // Clamping: an albedo near the top of the range cannot follow s.
        assert_eq!(scaled_albedo([0.7, 0.01, 0.3], 2.0), [ALBEDO_HI, ALBEDO_LO, 0.6]);
    }

    /// The split shading re-scaled equals shading the scaled albedo under the scaled light
    /// (`SurfelShading::compute`, the path the gauge used per evaluation), for every specular
    /// lobe, at scales whose albedo clamps at either end of its range.
    #[test]
    fn scaled_shading_is_shading_the_scaled_materials() {
        use super::super::inverse::trace_settings;
        use crate::shade::incident::RayStart;
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let mut surfels = Surfels::random_in_box(60, [-0.6, -0.6, -0.3], [0.6, 0.6, 0.3], 7);
        for i in 0..surfels.len() {
            // Albedo over the whole range: some clamp at s = 4 (high) and at s = 1/4 (low).
            surfels.albedo_logits[i] = [0; 3].map(|_| albedo_to_logit(rng.random_range(0.05..0.9)));
            surfels.roughness_logits[i] = crate::surfels::logit(rng.random_range(0.1..0.9));
        }
        let tracer = Tracer::build(&surfels, &trace_settings());
        let mut cache = IncidentCache::default();
        let start = RayStart::offset_only(1e-3);
        cache.refresh(&tracer, &surfels, 16, start, 3);
        let env = EnvMap {
            width: 32,
            height: 16,
            texels: (0..512).map(|_| [0; 3].map(|_| rng.random_range(0.1..3.0))).collect(),
        };
        let env_s = env.box_downsample(2);
        let split = SplitSum::new(&env).unwrap();
        let cam = Camera::look_at("g", glam::Vec3::new(0.4, -2.5, 1.2), glam::Vec3::ZERO, 24, 24, 0.9);
        let mut mats = MaterialView::default();
        mats.update(&surfels);
        fn traced<'a>(
            tracer: &'a Tracer,
            surfels: &'a Surfels,
            env: &'a EnvMap,
            start: RayStart,
        ) -> TracedSpecular<'a> {
            TracedSpecular { tracer, surfels, env, start, rays: 4, seed: 11 }
        }
        for lobe in ["cached", "split-sum", "traced"] {
            let pick = || match lobe {
                "cached" => (SpecularLobe::Cached, SpecularLobe::Cached),
                "split-sum" => (SpecularLobe::SplitSum(&split), SpecularLobe::SplitSum(&split)),
                _ => (SpecularLobe::Traced(traced(&tracer, &surfels, &env, start)), SpecularLobe::TracedAgain(&env)),
            };
            let (first, again) = pick();
            let mut scratch = SurfelShading::default();
            let split_shading =
                ScaledShading::compute(&mut scratch, &surfels, &mats, &cache, &env_s, first, again, &cam);
            assert!(split_shading.active.len() > 10, "{lobe}: too few shaded surfels");
            let mut fast = Vec::new();
            for s in [0.25f32, 0.8, 1.0, 2.3, 4.0] {
                split_shading.pbr(&mats.albedo, s, &mut fast);
                // The direct way: scaled albedo, env ÷ s (and for split-sum its prefilter of it).
                let mut scaled = mats.clone();
                scaled.albedo.iter_mut().for_each(|a| *a = scaled_albedo(*a, s));
                let mut dim = env.clone();
                dim.texels.iter_mut().for_each(|t| *t = t.map(|v| v / s));
                let dim_split = SplitSum::new(&dim).unwrap();
                let direct_lobe = match lobe {
                    "cached" => SpecularLobe::Cached,
                    "split-sum" => SpecularLobe::SplitSum(&dim_split),
                    _ => SpecularLobe::Traced(traced(&tracer, &surfels, &dim, start)),
                };
                let mut direct = SurfelShading::default();
                direct.compute(&surfels, &scaled, &cache, &dim.box_downsample(2), direct_lobe, &cam, TRAIN_CHANNELS);
                assert_eq!(direct.active, split_shading.active);
                let mut clamped = 0;
                for &i in &direct.active {
                    let i = i as usize;
                    clamped += (scaled.albedo[i] != mats.albedo[i].map(|a| a * s)) as usize;
                    for c in 0..3 {
                        let (got, want) = (fast[i * 3 + c], direct.features[i * TRAIN_CHANNELS + c]);
                        assert!(
                            (got - want).abs() <= 1e-5 + 2e-5 * want.abs(),
                            "{lobe}, s {s}, surfel {i}: {got} vs {want}"
                        );
                    }
                }
                if s == 4.0 || s == 0.25 {
                    assert!(clamped > 0, "{lobe}, s {s}: no albedo clamps");
                }
            }
        }
    }
}
