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
use super::pbr_image::PbrImageLoss;
use crate::envmap::EnvMap;
use crate::raster::{self, Features, Outputs, RasterSettings};
use crate::shade::splitsum::SplitSum;
use crate::shade::traced_specular::TracedSpecular;
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

/// Evaluates the PBR image loss for a given scale (buffers reused between calls).
struct Evaluator<'a> {
    cfg: &'a TrainConfig,
    state: &'a InverseState,
    images: &'a TrainImages,
    views: Vec<usize>,
    base: MaterialView,
    mats: MaterialView,
    env: EnvMap,
    /// One per view: with a traced specular lobe, each view's samples are traced once per fit
    /// and shaded again under every scaled light.
    shading: Vec<SurfelShading>,
    /// The tracer of a traced specular lobe (none otherwise).
    tracer: Option<Tracer>,
    loss: PbrImageLoss,
    gt: Vec<[f32; 3]>,
    v_features: Vec<f32>,
    v_alpha: Vec<f32>,
    evaluations: usize,
}

impl Evaluator<'_> {
    fn loss(&mut self, s: f32) -> f32 {
        self.evaluations += 1;
        for (m, b) in self.mats.albedo.iter_mut().zip(&self.base.albedo) {
            *m = scaled_albedo(*b, s);
        }
        let mut env = self.env.clone();
        for t in &mut env.texels {
            *t = t.map(|v| v / s);
        }
        let env_s = env.box_downsample(sample_factor(self.cfg));
        let split_sum = match self.cfg.specular {
            Specular::SplitSum => Some(SplitSum::new(&env).expect("the learned env is a valid map")),
            Specular::Mc | Specular::Traced => None,
        };
        // A black background: the GT is composited over it too, so only the object counts.
        let bg = [0.0f32; 3];
        let mut total = 0.0f64;
        let first = self.evaluations == 1;
        for (slot, &v) in self.views.iter().enumerate() {
            let cam = &self.images.cameras[v];
            let lobe = match (&split_sum, &self.tracer) {
                (Some(ss), _) => SpecularLobe::SplitSum(ss),
                (None, Some(tracer)) if first => SpecularLobe::Traced(TracedSpecular {
                    tracer,
                    surfels: &self.state.surfels,
                    env: &env,
                    start: self.cfg.ray_start(self.state.extent),
                    rays: self.cfg.specular_rays,
                    // Fixed per fit (and per view): every scale sees the same samples.
                    seed: self.cfg.seed ^ 0x6a09_e667 ^ (self.state.iteration as u64) << 8 ^ v as u64,
                }),
                (None, Some(_)) => SpecularLobe::TracedAgain(&env),
                (None, None) => SpecularLobe::Cached,
            };
            let shading = &mut self.shading[slot];
            shading.compute(&self.state.surfels, &self.mats, &self.state.cache, &env_s, lobe, cam, TRAIN_CHANNELS);
            let settings = RasterSettings {
                window: self.cfg.window,
                filter_inv_square: self.cfg.filter_inv_square,
                two_sided: false,
                background: bg,
                outputs: Outputs { colour: false, ..Outputs::none() },
                ..RasterSettings::default()
            };
            let features = Features { data: &shading.features, channels: TRAIN_CHANNELS };
            let (out, _) = raster::render(&self.state.surfels, cam, &settings, Some(features));
            let (rgb, alpha) = (&self.images.rgb[v], &self.images.alpha[v]);
            self.gt.clear();
            self.gt.extend(rgb.iter().zip(alpha).map(|(c, &a)| c.map(|x| x * a)));
            let np = rgb.len();
            self.v_features.clear();
            self.v_features.resize(np * TRAIN_CHANNELS, 0.0);
            self.v_alpha.clear();
            self.v_alpha.resize(np, 0.0);
            let wh = (cam.width as usize, cam.height as usize);
            let t = self.loss.evaluate(
                &out.features,
                TRAIN_CHANNELS,
                &out.alpha,
                bg,
                &self.gt,
                alpha,
                wh,
                1.0,
                &mut self.v_features,
                &mut self.v_alpha,
            );
            total += (t.l1 + 0.2 * t.dssim) as f64;
        }
        (total / self.views.len() as f64) as f32
    }
}

/// Search the scale s minimising the PBR image loss on a few training views.
pub fn fit(cfg: &TrainConfig, state: &InverseState, images: &TrainImages) -> GaugeFit {
    let n = images.cameras.len();
    let count = VIEWS.min(n);
    let mut base = MaterialView::default();
    base.update(&state.surfels);
    let mut ev = Evaluator {
        cfg,
        state,
        images,
        // Fixed views spread over the set: the fit is deterministic.
        views: (0..count).map(|k| k * n / count).collect(),
        mats: base.clone(),
        base,
        env: state.env(),
        shading: (0..count).map(|_| SurfelShading::default()).collect(),
        tracer: (cfg.specular == Specular::Traced)
            .then(|| Tracer::build(&state.surfels, &super::inverse::trace_settings())),
        loss: PbrImageLoss::clipping(cfg.clip_saturated),
        gt: Vec::new(),
        v_features: Vec::new(),
        v_alpha: Vec::new(),
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
}
