//! The `inverse` stage (RadioGS stage 2, DESIGN §1): recover albedo, roughness and the
//! environment light so that the surfels' radiance agrees with the rendering equation.
//!
//! Starts from the run's nvs checkpoint (geometry + SH): normals are oriented towards the
//! cameras (back faces are culled from here on), materials and light are fresh (albedo 0.3,
//! roughness 0.6, env 1.5). Per iteration, on one training view:
//! 1. per-surfel Monte Carlo PBR for the view direction, from the cached incident light
//!    (directions, visibility, indirect) and the current env (with gradients), for the surfels
//!    facing the camera; rasterised as feature channels [L_pbr, albedo, roughness] beside
//!    the SH colour;
//! 2. losses: PBR image (linear → sRGB, L1 + 0.2·D-SSIM), SH image (0.8·L1 + 0.2·D-SSIM),
//!    mask, normal consistency, edge-aware smoothness of albedo/roughness/normal, the
//!    non-local albedo prior on the SH colour's chromaticity (albedo_chroma.rs; not published)
//!    and a local one in space (albedo_voxel.rs; not published);
//! 3. radiometric consistency on B random surfels × R traced rays with gradients through the
//!    tracer (consistency.rs); the traced rows overwrite the cache when R = S;
//! 4. env priors (white light, TV), Adam on surfels (geometry lr × 0.01) and env (log radiance);
//! 5. the tracer is refitted every step; every `cache_every`/4 steps the cache rows that would
//!    otherwise grow older than `cache_every` are re-traced (no row is older than the
//!    published full refresh every `cache_every` allows; rows the consistency traced are kept).
//!
//! No densification. Writes `checkpoint_inverse.bin`, `point_cloud.ply` (with material
//! fields) and `envmap.exr`.

use super::albedo_chroma::AlbedoChroma;
use super::consistency::{RcLosses, RcScratch, RcSettings, radiometric_consistency};
use super::light::LearnedLight;
use super::material::{MaterialGrads, MaterialView, orient_surfels, view_dir, view_dir_backward};
use super::nvs::{
    self, StageSummary, TimeSplit, TrainImages, iteration_rng, open_metrics, progress_bar, view_for_iteration,
};
use super::pbr_image::{PbrImage, PbrImageLoss};
use crate::camera::Camera;
use crate::envmap::EnvMap;
use crate::error::Error;
use crate::io::dataset::{Dataset, Split};
use crate::io::ply::write_ply_flagged;
use crate::loss::{self, EdgeAwareSmoothness, NormalConsistency, Ssim};
use crate::optim::{LearningRates, SurfelAdam};
use crate::raster::{self, Features, Outputs, RasterSettings, RenderGrads};
use crate::shade::incident::{EnvImportance, IncidentCache};
use crate::shade::pbr::{
    Detach, LinearisedShading, SubsetGrads, shade_subset, shade_subset_linearised, shade_subset_linearised_backward,
};
use crate::shade::splitsum::{SplitSum, SplitSumGrads};
use crate::shade::traced_specular::{SpecularSamples, TracedSpecular};
use crate::surfels::{Surfels, albedo_to_logit, logit};
use crate::trace::{TraceSettings, Tracer};
use crate::train::checkpoint::Checkpoint;
use crate::train::config::{Background, RcOrder, Specular, TraceBackFaces, TrainConfig};
use crate::train::interrupt;
use anyhow::Context;
use rand::RngExt;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// Feature channels rasterised in training: linear L_pbr (3), albedo (3), roughness (1).
pub const TRAIN_CHANNELS: usize = 7;
/// Feature channels for pictures and evaluation: the training ones, then linear L_indirect
/// (3) and cosine-weighted visibility (1).
pub const VIEW_CHANNELS: usize = 11;

pub fn checkpoint_path(run: &Path) -> PathBuf {
    run.join("checkpoint_inverse.bin")
}

/// How much the env is box-filtered for the rendering equation's samples.
pub fn sample_factor(cfg: &TrainConfig) -> usize {
    if cfg.env_sample_height == 0 { 1 } else { (cfg.env_height / cfg.env_sample_height).max(1) }
}

/// The tracer settings of the PBR stages (RadioGS: stop at T < 0.03, cull back faces;
/// indirect light composited as linear radiance).
pub fn trace_settings() -> TraceSettings {
    trace_settings_with(&TraceBackFaces::Cull.into())
}

/// How the PBR stages' traced rays treat back faces: `--trace-back-faces` and, for
/// `dark-unseen`, which surfels no camera saw (one flag per surfel; without flags it culls);
/// and how the shading reads a ray's final transmittance (`--trace-opaque-below`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct BackFaces {
    pub mode: TraceBackFaces,
    pub unseen: Option<Arc<[bool]>>,
    /// One-sided modes: back faces within this many degrees past edge-on are still hit
    /// (`--trace-grazing`; [`TraceSettings::grazing_sin`]).
    pub grazing_deg: f32,
    /// The shading's visibility ramp ([`TraceSettings::opaque_below`]; 0 = off).
    pub opaque_below: f32,
}

impl From<TraceBackFaces> for BackFaces {
    fn from(mode: TraceBackFaces) -> Self {
        BackFaces { mode, unseen: None, grazing_deg: 0.0, opaque_below: 0.0 }
    }
}

impl BackFaces {
    /// A run's: its config's mode, and with `dark-unseen` the flags saved with its surfels
    /// (`point_cloud.ply`'s property `unseen`, else the newest checkpoint's), which must number
    /// `count`; without any, none is unseen (culled, with a warning).
    pub fn of_run(run: &Path, mode: TraceBackFaces, count: usize) -> anyhow::Result<BackFaces> {
        if mode != TraceBackFaces::DarkUnseen {
            return Ok(mode.into());
        }
        let (flags, source) = crate::eval::load_run_unseen(run)?;
        let Some(flags) = flags else {
            // Surfels written without flags (by hand, a probe, another tool): nothing is known
            // to be unseen, so the rays cull as they would for a run with none.
            crate::eval::warn_once(format!(
                "{source}: the run traces back faces as dark-unseen but holds no unseen flags; culling them all"
            ));
            return Ok(mode.into());
        };
        anyhow::ensure!(
            flags.len() == count,
            "{source}: {} unseen flags for {count} surfels (from another run?)",
            flags.len()
        );
        Ok(BackFaces { mode, unseen: Some(flags.into()), grazing_deg: 0.0, opaque_below: 0.0 })
    }

    /// The same with the grazing tolerance and the visibility ramp of a run's config.
    pub fn of_config(self, cfg: &TrainConfig) -> BackFaces {
        BackFaces { grazing_deg: cfg.trace_grazing, opaque_below: cfg.trace_opaque_below, ..self }
    }
}

/// [`trace_settings`] with back faces as `back_faces` says (`--trace-back-faces`).
pub fn trace_settings_with(back_faces: &BackFaces) -> TraceSettings {
    let (two_sided, dark_back_faces) = match back_faces.mode {
        TraceBackFaces::Cull | TraceBackFaces::DarkUnseen => (false, false),
        TraceBackFaces::TwoSided => (true, false),
        TraceBackFaces::Dark => (true, true),
    };
    let back_occluders = if back_faces.mode == TraceBackFaces::DarkUnseen { back_faces.unseen.clone() } else { None };
    let grazing_sin = back_faces.grazing_deg.to_radians().sin();
    TraceSettings {
        linear_radiance: true,
        two_sided,
        dark_back_faces,
        back_occluders,
        grazing_sin,
        opaque_below: back_faces.opaque_below,
        ..TraceSettings::default()
    }
}

/// Everything an inverse run holds.
pub struct InverseState {
    pub surfels: Surfels,
    pub adam: SurfelAdam,
    pub light: LearnedLight,
    pub cache: IncidentCache,
    /// The iteration each cache row was last traced (refresh or consistency).
    pub traced_at: Vec<u32>,
    pub iteration: u32,
    pub extent: f32,
    /// Per surfel: no training camera saw it when the stage oriented the surfels (all false
    /// when the geometry kept its own orientation, or the checkpoint predates the flags).
    /// `--trace-back-faces dark-unseen` uses it.
    pub unseen: Vec<bool>,
}

/// The nvs stage's initial position rate (scaled by the scene extent) × the geometry scale.
fn position_lr(cfg: &TrainConfig, extent: f32) -> f32 {
    cfg.lr_position_init * extent * cfg.geometry_lr_scale
}

fn learning_rates(cfg: &TrainConfig) -> LearningRates {
    let g = cfg.geometry_lr_scale;
    LearningRates {
        means: 0.0, // set from the extent by the caller (position_lr)
        log_scales: cfg.lr_scale * g,
        quats: cfg.lr_rotation * g,
        opacity_logits: cfg.lr_opacity * g,
        sh_dc: cfg.lr_sh,
        sh_rest: cfg.lr_sh_rest_inverse,
        albedo_logits: cfg.lr_albedo,
        roughness_logits: cfg.lr_roughness,
    }
}

impl InverseState {
    pub fn env(&self) -> EnvMap {
        self.light.env()
    }

    /// Fresh materials and light on the geometry stage's result, or with `kept_light` (log
    /// texels of `cfg.env_height`) the surfels' own materials and that light.
    pub fn from_nvs(
        cfg: &TrainConfig,
        mut surfels: Surfels,
        cameras: &[Camera],
        extent: f32,
        kept_light: Option<Vec<f32>>,
        geometry_two_sided: bool,
    ) -> crate::Result<InverseState> {
        let n0 = surfels.len();
        let mut unseen = vec![false; n0];
        if geometry_two_sided {
            let o;
            (o, unseen) = orient_surfels(&mut surfels, cameras, cfg.window, cfg.filter_inv_square, 0.01 * extent);
            tracing::info!(
                "inverse: oriented {n0} surfels towards the cameras that see them: {} flipped, {} seen from both \
                 sides doubled, {} unseen",
                o.flipped,
                o.doubled,
                o.unseen
            );
        } else {
            // A geometry trained with back-face culling already has the normals this stage
            // renders with: a two-sided vote would flip surfels no camera ever saw from the side
            // it now faces (their appearance was never trained) into view.
            tracing::info!("inverse: the geometry stage culled back faces; its {n0} surfels keep their orientation");
        }
        // Drop what no training pixel sees, as this stage renders (back faces culled).
        let settings = RasterSettings {
            window: cfg.window,
            filter_inv_square: cfg.filter_inv_square,
            two_sided: false,
            outputs: Outputs { colour: true, ..Outputs::none() },
            ..RasterSettings::default()
        };
        let n1 = surfels.len();
        let dropped =
            super::contribution::prune_unseen(&mut surfels, cameras, &settings, cfg.prune_contribution, &mut unseen);
        if dropped > 0 {
            tracing::info!(
                "inverse: dropped {dropped} of {n1} surfels that reach a blend weight of {} in no training pixel",
                cfg.prune_contribution
            );
        }
        if kept_light.is_none() {
            if cfg.albedo_init_hue > 0.0 {
                let fresh = super::albedo_chroma::hued_albedo(&surfels, cfg.albedo_init, cfg.albedo_init_hue);
                for (logit, a) in surfels.albedo_logits.iter_mut().zip(&fresh) {
                    *logit = a.map(albedo_to_logit);
                }
                // Say how much of the start is hued: a grey object starts as the published grey.
                let hued = fresh.iter().filter(|a| a[0] != a[1] || a[1] != a[2]).count();
                tracing::info!(
                    "inverse: {hued} of {} surfels start with the hue they were seen with (--albedo-init-hue {}), \
                     the rest grey at {}",
                    fresh.len(),
                    cfg.albedo_init_hue,
                    cfg.albedo_init
                );
            } else {
                surfels.albedo_logits.iter_mut().for_each(|a| *a = [albedo_to_logit(cfg.albedo_init); 3]);
            }
            surfels.roughness_logits.iter_mut().for_each(|r| *r = logit(cfg.roughness_init));
        }
        let mut adam = SurfelAdam::new(&surfels, learning_rates(cfg));
        adam.lr.means = position_lr(cfg, extent);
        Ok(InverseState {
            light: match kept_light {
                // A new stage: the light's optimiser starts afresh.
                Some(log) => {
                    LearnedLight { adam: crate::optim::Adam::new(log.len(), cfg.lr_env), log, height: cfg.env_height }
                }
                None => LearnedLight::fresh(cfg)?,
            },
            adam,
            surfels,
            cache: IncidentCache::default(),
            traced_at: Vec::new(),
            iteration: 0,
            extent,
            unseen,
        })
    }

    /// How this run's traced rays treat back faces.
    pub fn back_faces(&self, cfg: &TrainConfig) -> BackFaces {
        BackFaces {
            mode: cfg.trace_back_faces,
            unseen: Some(Arc::from(self.unseen.as_slice())),
            grazing_deg: cfg.trace_grazing,
            opaque_below: cfg.trace_opaque_below,
        }
    }

    pub fn to_checkpoint(&self, cfg: &TrainConfig) -> Checkpoint {
        let mut c = Checkpoint {
            meta: serde_json::json!({
                "stage": "inverse",
                "iteration": self.iteration,
                "extent": self.extent,
                "adam_step": self.adam.step,
                "cache_samples": self.cache.samples,
                "cache_weight": self.cache.weight,
                "seed": cfg.seed,
                "iters": cfg.inverse_iters,
            }),
            ..Default::default()
        };
        c.put_surfels("params", &self.surfels);
        c.put_surfels("adam_m", &self.adam.m);
        c.put_surfels("adam_v", &self.adam.v);
        self.light.put(&mut c);
        c.put("cache.dirs", self.cache.dirs.iter().flatten().copied().collect());
        c.put("cache.visibility", self.cache.visibility.clone());
        c.put("cache.indirect", self.cache.indirect.iter().flatten().copied().collect());
        // Iterations (< 2^24) are exact in f32.
        c.put("cache.traced_at", self.traced_at.iter().map(|&t| t as f32).collect());
        if !self.cache.sample_weights.is_empty() {
            c.put("cache.sample_weights", self.cache.sample_weights.clone());
        }
        c.put(UNSEEN_BLOB, self.unseen.iter().map(|&u| u as u8 as f32).collect());
        c
    }

    pub fn from_checkpoint(path: &Path, c: &Checkpoint, cfg: &TrainConfig) -> crate::Result<InverseState> {
        let meta_u64 = |key: &str| c.meta_u64(path, key);
        let surfels = c.get_surfels(path, "params")?;
        let extent = c.meta.get("extent").and_then(|v| v.as_f64()).unwrap_or(1.0) as f32;
        let mut adam = SurfelAdam::new(&surfels, learning_rates(cfg));
        adam.lr.means = position_lr(cfg, extent);
        adam.m = c.get_surfels(path, "adam_m")?;
        adam.v = c.get_surfels(path, "adam_v")?;
        adam.step = meta_u64("adam_step")?;
        let light = LearnedLight::get(path, c, cfg)?;
        let samples = meta_u64("cache_samples")? as usize;
        let triples = |name: &str| -> crate::Result<Vec<[f32; 3]>> {
            Ok(c.require(path, name)?.chunks_exact(3).map(|x| [x[0], x[1], x[2]]).collect())
        };
        let cache = IncidentCache {
            samples,
            weight: c.meta.get("cache_weight").and_then(|v| v.as_f64()).unwrap_or(0.0) as f32,
            dirs: triples("cache.dirs")?,
            visibility: c.require(path, "cache.visibility")?.to_vec(),
            indirect: triples("cache.indirect")?,
            // Rows drawn partly from the light's peaks (`env_importance_inverse`) weigh per sample.
            sample_weights: c.blob("cache.sample_weights").map(<[f32]>::to_vec).unwrap_or_default(),
            ..IncidentCache::default()
        };
        if cache.len() != surfels.len() && !cache.is_empty() {
            return Err(Error::format(path, "cache", "row count differs from the surfel count"));
        }
        // Every per-ray blob holds one entry per ray (shading indexes them together).
        let rays = cache.visibility.len();
        let weights = cache.sample_weights.len();
        for (name, len) in [("cache.dirs", cache.dirs.len()), ("cache.indirect", cache.indirect.len())]
            .into_iter()
            .chain((weights > 0).then_some(("cache.sample_weights", weights)))
        {
            if len != rays {
                return Err(Error::format(path, name, format!("{len} rays, but cache.visibility holds {rays}")));
            }
        }
        if samples.checked_mul(surfels.len()) != Some(rays) && rays != 0 {
            return Err(Error::format(
                path,
                "cache_samples",
                format!("{samples} per surfel × {} surfels is not the cache's {rays} rays", surfels.len()),
            ));
        }
        let iteration = meta_u64("iteration")? as u32;
        // Checkpoints from before the per-row refresh: every row as old as the checkpoint.
        let traced_at = match c.blob("cache.traced_at") {
            Some(t) if t.len() == cache.len() => t.iter().map(|&x| x as u32).collect(),
            _ => vec![iteration; cache.len()],
        };
        // Checkpoints from before the flags traced with back faces culled: none unseen.
        let unseen = unseen_flags(path, c)?.unwrap_or_else(|| vec![false; surfels.len()]);
        if unseen.len() != surfels.len() {
            return Err(Error::format(
                path,
                UNSEEN_BLOB,
                format!("{} flags for {} surfels", unseen.len(), surfels.len()),
            ));
        }
        Ok(InverseState { surfels, adam, light, cache, traced_at, iteration, extent, unseen })
    }
}

/// The checkpoint blob of [`InverseState::unseen`] (0 or 1 per surfel).
const UNSEEN_BLOB: &str = "unseen";

/// A checkpoint's unseen flags, or None when it has none (an nvs checkpoint, or an inverse one
/// from before session 68).
pub fn unseen_flags(path: &Path, c: &Checkpoint) -> crate::Result<Option<Vec<bool>>> {
    let Some(blob) = c.blob(UNSEEN_BLOB) else { return Ok(None) };
    blob.iter()
        .enumerate()
        .map(|(i, &v)| match v {
            0.0 => Ok(false),
            1.0 => Ok(true),
            _ => Err(Error::format(path, format!("{UNSEEN_BLOB}[{i}]"), format!("{v} is not 0 or 1"))),
        })
        .collect::<crate::Result<Vec<bool>>>()
        .map(Some)
}

/// Where the PBR colour's specular lobe comes from (`--specular`).
#[derive(Clone, Copy)]
pub enum SpecularLobe<'a> {
    /// In the Monte Carlo sum over the cached directions (the published method).
    Cached,
    /// The prefiltered env ([`SplitSum::specular_lobe`]).
    SplitSum(&'a SplitSum),
    /// Traced for the view by GGX importance sampling (`shade::traced_specular`).
    Traced(TracedSpecular<'a>),
    /// The samples the previous `Traced` call of the same [`SurfelShading`] traced (same
    /// camera, surfels, normals and roughness), shaded again under this full-resolution env
    /// (the gauge's scaled lights).
    TracedAgain(&'a EnvMap),
}

impl<'a> SpecularLobe<'a> {
    fn split_sum(&self) -> Option<&'a SplitSum> {
        match self {
            SpecularLobe::SplitSum(ss) => Some(ss),
            _ => None,
        }
    }
}

/// Per-surfel features for one camera: which surfels are shaded (facing the camera, centre
/// in front of it), their view directions, and the feature rows (N × channels; surfels not
/// shaded get zero PBR but keep their material channels).
#[derive(Default)]
pub struct SurfelShading {
    pub active: Vec<u32>,
    pub view: Vec<[f32; 3]>,
    pub direct: Vec<[f32; 3]>,
    pub indirect: Vec<[f32; 3]>,
    pub features: Vec<f32>,
    /// Per active surfel, with a split-sum specular lobe: its occlusion (cached mean
    /// visibility) and fill radiance (cached mean indirect light).
    pub spec_occlusion: Vec<f32>,
    pub spec_fill: Vec<[f32; 3]>,
    /// With a traced specular lobe: its samples (kept for the backward) and its env and
    /// indirect parts per active surfel.
    pub traced: SpecularSamples,
    traced_direct: Vec<[f32; 3]>,
    traced_indirect: Vec<[f32; 3]>,
    /// Shade with the Jacobian kept for the training
    /// iteration's backward, `shade_subset_linearised_backward`) instead of the plain forward.
    pub linearise: bool,
    lin: LinearisedShading,
}

impl SurfelShading {
    /// Shade for `camera` with `channels` = [`TRAIN_CHANNELS`] or [`VIEW_CHANNELS`]. Unless
    /// `lobe` is [`SpecularLobe::Cached`], the Monte Carlo sum over the cache is Lambert only
    /// and the specular lobe comes from the prefiltered env ([`SplitSum::specular_lobe`]: its
    /// env part counts as direct light, its fill part as indirect) or from rays traced for
    /// this view (their env part direct, their hits indirect).
    #[allow(clippy::too_many_arguments)]
    pub fn compute(
        &mut self,
        surfels: &Surfels,
        mats: &MaterialView,
        cache: &IncidentCache,
        env: &EnvMap,
        lobe: SpecularLobe,
        camera: &Camera,
        channels: usize,
    ) {
        let split_sum = lobe.split_sum();
        let n = surfels.len();
        let eye = camera.position().to_array();
        self.view.resize(n, [0.0; 3]);
        self.active.clear();
        for i in 0..n {
            let w = view_dir(surfels.means[i], eye);
            self.view[i] = w;
            let nn = mats.normal[i];
            let facing = nn[0] * w[0] + nn[1] * w[1] + nn[2] * w[2] > 0.0;
            let z = camera.world_to_camera(glam::Vec3::from(surfels.means[i])).z;
            if facing && z > 0.0 {
                self.active.push(i as u32);
            }
        }
        let m = self.active.len();
        self.direct.resize(m, [0.0; 3]);
        self.indirect.resize(m, [0.0; 3]);
        let mut inp = cache.inputs(&mats.albedo, &mats.roughness, &mats.normal, &self.view);
        inp.specular = matches!(lobe, SpecularLobe::Cached);
        if self.linearise {
            shade_subset_linearised(&inp, env, &self.active, &mut self.direct, &mut self.indirect, &mut self.lin)
        } else {
            shade_subset(&inp, env, &self.active, &mut self.direct, &mut self.indirect)
        }
        .expect("sized above");
        let traced_env = match &lobe {
            SpecularLobe::Traced(spec) => {
                self.traced.trace(spec, &self.active, &mats.roughness, &mats.normal, &self.view);
                Some(spec.env)
            }
            SpecularLobe::TracedAgain(env) => {
                assert_eq!(self.traced.len(), m, "TracedAgain needs the samples of the same view");
                Some(*env)
            }
            _ => None,
        };
        if let Some(env_full) = traced_env {
            self.traced_direct.resize(m, [0.0; 3]);
            self.traced_indirect.resize(m, [0.0; 3]);
            self.traced.shade(env_full, &mut self.traced_direct, &mut self.traced_indirect).expect("sized above");
            for k in 0..m {
                for ch in 0..3 {
                    self.direct[k][ch] += self.traced_direct[k][ch];
                    self.indirect[k][ch] += self.traced_indirect[k][ch];
                }
            }
        }
        self.spec_occlusion.clear();
        self.spec_fill.clear();
        if let Some(ss) = split_sum {
            use crate::shade::to64;
            for (k, &i) in self.active.iter().enumerate() {
                let i = i as usize;
                let nn = mats.normal[i];
                let occ = cache.mean_visibility(i, nn);
                let fill = cache.mean_indirect(i, nn);
                let (r, n, wo) = (mats.roughness[i] as f64, to64(nn), to64(self.view[i]));
                let env_part = ss.specular_lobe(r, n, wo, occ as f64, [0.0; 3]);
                let fill_part = ss.specular_lobe(r, n, wo, 0.0, to64(fill));
                for ch in 0..3 {
                    self.direct[k][ch] += env_part[ch] as f32;
                    self.indirect[k][ch] += fill_part[ch] as f32;
                }
                self.spec_occlusion.push(occ);
                self.spec_fill.push(fill);
            }
        }
        self.features.clear();
        self.features.resize(n * channels, 0.0);
        for i in 0..n {
            let f = &mut self.features[i * channels..(i + 1) * channels];
            f[3..6].copy_from_slice(&mats.albedo[i]);
            f[6] = mats.roughness[i];
            if channels >= VIEW_CHANNELS {
                f[10] = cache.mean_visibility(i, mats.normal[i]);
            }
        }
        for (k, &i) in self.active.iter().enumerate() {
            let f = &mut self.features[i as usize * channels..(i as usize + 1) * channels];
            for ch in 0..3 {
                f[ch] = self.direct[k][ch] + self.indirect[k][ch];
                if channels >= VIEW_CHANNELS {
                    f[7 + ch] = self.indirect[k][ch];
                }
            }
        }
    }
}

impl SurfelShading {
    /// Backward of the split-sum specular lobe added by [`compute`](Self::compute): for the
    /// upstream gradient `v_pbr` on each active surfel's PBR colour, adds ∂/∂roughness,
    /// ∂/∂normal and ∂/∂view into `sub` (indexed like `active`) and writes the prefiltered-map
    /// gradients into `grads` (zeroed first; send them on with `SplitSum::backward_to_env`).
    pub fn split_sum_backward(
        &self,
        ss: &SplitSum,
        mats: &MaterialView,
        v_pbr: &[[f32; 3]],
        sub: &mut SubsetGrads,
        grads: &mut SplitSumGrads,
    ) {
        use crate::shade::to64;
        if grads.v_levels.len() != ss.levels.len()
            || grads.v_levels.iter().zip(&ss.levels).any(|(g, l)| g.len() != l.texels.len())
        {
            *grads = ss.zero_grads();
        }
        grads.v_levels.iter_mut().flatten().for_each(|t| *t = [0.0; 3]);
        grads.v_irradiance.iter_mut().for_each(|t| *t = [0.0; 3]);
        for (k, &i) in self.active.iter().enumerate() {
            let i = i as usize;
            let (r, n, wo) = (mats.roughness[i] as f64, to64(mats.normal[i]), to64(self.view[i]));
            let (occ, fill) = (self.spec_occlusion[k] as f64, to64(self.spec_fill[k]));
            let (v_r, v_n, v_wo) = ss.specular_lobe_backward(r, n, wo, occ, fill, to64(v_pbr[k]), grads);
            sub.v_roughness[k] += v_r as f32;
            for c in 0..3 {
                sub.v_normal[k][c] += v_n[c] as f32;
                sub.v_view[k][c] += v_wo[c] as f32;
            }
        }
    }
}

/// Losses of one iteration (unweighted).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct InverseLosses {
    pub total: f32,
    pub pbr_l1: f32,
    pub pbr_dssim: f32,
    pub sh_l1: f32,
    pub sh_dssim: f32,
    pub mask: f32,
    pub normal: f32,
    pub smooth: f32,
    pub albedo_chroma: f32,
    pub albedo_voxel: f32,
    pub env_prior: f32,
    pub rc: RcLosses,
    pub psnr_pbr: f32,
    pub psnr_sh: f32,
}

#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct InverseTimes {
    pub shading: f64,
    pub raster_forward: f64,
    pub losses: f64,
    pub raster_backward: f64,
    pub shading_backward: f64,
    pub consistency: f64,
    pub optimiser: f64,
    pub tracer_refit: f64,
    pub cache_refresh: f64,
    /// The albedo–light gauge fits (`gauge_every`).
    pub gauge: f64,
}

#[derive(Default)]
struct Scratch {
    gt: Vec<[f32; 3]>,
    /// `--rc-order sweep`: the pass's order and this iteration's consistency surfels.
    rc_sweep: super::rc_sweep::RcSweep,
    rc_batch: Vec<u32>,
    pbr_image: PbrImageLoss,
    grads: RenderGrads,
    ssim_sh: Ssim,
    normal: NormalConsistency,
    smooth: EdgeAwareSmoothness,
    map: Vec<f32>,
    v_map: Vec<f32>,
    v_feat: Vec<f32>,
    shading: SurfelShading,
    sub: SubsetGrads,
    v_sub_pbr: Vec<[f32; 3]>,
    mats: MaterialView,
    mgrads: MaterialGrads,
    v_env: Vec<[f32; 3]>,
    v_env_small: Vec<[f32; 3]>,
    v_env_log: Vec<f32>,
    rc: RcScratch,
    ss_grads: Option<SplitSumGrads>,
    /// The traced specular lobe's env gradient (full resolution; empty without it).
    v_env_traced: Vec<[f32; 3]>,
    albedo_chroma: AlbedoChroma,
    albedo_voxel: super::albedo_voxel::AlbedoVoxel,
    /// The forward's per-pixel hits, replayed by the backward (buffers reused).
    recorder: raster::HitRecorder,
}

fn rc_settings(cfg: &TrainConfig, extent: f32) -> RcSettings {
    RcSettings {
        surfels: cfg.rc_surfels,
        rays: cfg.rc_rays,
        start: cfg.ray_start(extent),
        weight: cfg.lambda_rc,
        detach: Detach { env: cfg.detach_env, material: cfg.detach_material, normal: cfg.detach_normal },
        detach_lhs: cfg.detach_lhs,
        detach_rhs: cfg.detach_rhs,
        linear_l2: false,
    }
}

/// The specular lobe of the iteration's PBR colour: with `--specular traced`, rays drawn for
/// the view with the iteration's seed.
fn specular_lobe<'a>(
    cfg: &TrainConfig,
    state: &'a InverseState,
    env_full: &'a EnvMap,
    split_sum: Option<&'a SplitSum>,
    tracer: &'a Tracer,
) -> SpecularLobe<'a> {
    match (cfg.specular, split_sum) {
        (Specular::SplitSum, Some(ss)) => SpecularLobe::SplitSum(ss),
        (Specular::Traced, _) => SpecularLobe::Traced(TracedSpecular {
            tracer,
            surfels: &state.surfels,
            env: env_full,
            start: cfg.ray_start(state.extent),
            rays: cfg.specular_rays,
            seed: cfg.seed ^ (state.iteration as u64).wrapping_mul(0x2545_f491_4f6c_dd1d),
        }),
        _ => SpecularLobe::Cached,
    }
}

/// One iteration's forward and backward: gradients into `v_surfels` and `sc.v_env`.
#[allow(clippy::too_many_arguments)]
fn iterate(
    cfg: &TrainConfig,
    state: &InverseState,
    env_full: &EnvMap,
    env: &EnvMap,
    split_sum: Option<&SplitSum>,
    tracer: &Tracer,
    images: &TrainImages,
    view_index: usize,
    bg: [f32; 3],
    rng: &mut rand_pcg::Pcg64,
    sc: &mut Scratch,
    v_surfels: &mut Surfels,
    t: &mut InverseTimes,
) -> InverseLosses {
    let s = &state.surfels;
    let cam = &images.cameras[view_index];
    let (w, h) = (cam.width as usize, cam.height as usize);
    let np = w * h;
    let ch = TRAIN_CHANNELS;
    let t0 = Instant::now();
    sc.mats.update(s);
    let lobe = specular_lobe(cfg, state, env_full, split_sum, tracer);
    sc.shading.linearise = true;
    sc.shading.compute(s, &sc.mats, &state.cache, env, lobe, cam, ch);
    let t1 = Instant::now();
    t.shading += (t1 - t0).as_secs_f64();
    let settings = RasterSettings {
        window: cfg.window,
        filter_inv_square: cfg.filter_inv_square,
        two_sided: false,
        background: bg,
        outputs: Outputs { colour: true, depth: true, normal: true, ..Outputs::none() },
        ..RasterSettings::default()
    };
    let features = Features { data: &sc.shading.features, channels: ch };
    let (out, mut fwd) = sc.recorder.render(s, cam, &settings, Some(features));
    let t2 = Instant::now();
    t.raster_forward += (t2 - t1).as_secs_f64();

    // Ground truth over the iteration's background.
    let rgb = &images.rgb[view_index];
    let alpha = &images.alpha[view_index];
    sc.gt.clear();
    sc.gt.extend(rgb.iter().zip(alpha).map(|(c, &a)| [0, 1, 2].map(|k| c[k] * a + bg[k] * (1.0 - a))));
    let g = &mut sc.grads;
    g.v_colour.clear();
    g.v_colour.resize(np, [0.0; 3]);
    g.v_alpha.clear();
    g.v_alpha.resize(np, 0.0);
    g.v_depth.clear();
    g.v_depth.resize(np, 0.0);
    g.v_normal.clear();
    g.v_normal.resize(np, [0.0; 3]);
    g.v_features.clear();
    g.v_features.resize(np * ch, 0.0);
    g.v_distortion.clear();
    g.v_median_depth.clear();
    let mut l = InverseLosses::default();

    // SH image.
    let ws = cfg.lambda_sh_image;
    let lam = cfg.lambda_dssim;
    if ws > 0.0 {
        l.sh_l1 = loss::l1_rgb(&out.colour, &sc.gt, None, ws * (1.0 - lam), &mut g.v_colour);
        l.sh_dssim = sc.ssim_sh.dssim_loss(&out.colour, &sc.gt, w, h, ws * lam, &mut g.v_colour);
        l.total += ws * ((1.0 - lam) * l.sh_l1 + lam * l.sh_dssim);
    }
    l.psnr_sh = loss::psnr(&out.colour, &sc.gt);

    // PBR image: linear features over the linear background, then sRGB.
    let wp = cfg.lambda_pbr;
    let img = PbrImage {
        features: &out.features,
        channels: ch,
        alpha: &out.alpha,
        bg,
        gt: &sc.gt,
        gt_alpha: alpha,
        size: (w, h),
    };
    let pbr = sc.pbr_image.evaluate(&img, wp, &mut g.v_features, &mut g.v_alpha);
    (l.pbr_l1, l.pbr_dssim, l.psnr_pbr) = (pbr.l1, pbr.dssim, pbr.psnr);
    l.total += wp * (l.pbr_l1 + 0.2 * l.pbr_dssim);
    if cfg.lambda_mask_inverse > 0.0 {
        l.mask = loss::mask_bce(&out.alpha, alpha, cfg.lambda_mask_inverse, &mut g.v_alpha);
        l.total += cfg.lambda_mask_inverse * l.mask;
    }
    if cfg.lambda_normal_inverse > 0.0 {
        l.normal = sc.normal.loss(
            cam,
            &out.depth,
            &out.normal,
            Some(&out.alpha),
            Some(alpha),
            cfg.lambda_normal_inverse,
            &mut g.v_depth,
            &mut g.v_normal,
        );
        l.total += cfg.lambda_normal_inverse * l.normal;
    }
    // Edge-aware smoothness of the rendered albedo, roughness and normal maps.
    sc.smooth.prepare(&sc.gt, w, h);
    for (first, count, weight) in [(3usize, 3usize, cfg.lambda_smooth_albedo), (6, 1, cfg.lambda_smooth_roughness)] {
        if weight <= 0.0 {
            continue;
        }
        sc.map.clear();
        for p in 0..np {
            sc.map.extend_from_slice(&out.features[p * ch + first..p * ch + first + count]);
        }
        sc.v_map.clear();
        sc.v_map.resize(np * count, 0.0);
        let v = sc.smooth.loss_prepared(&sc.map, count, Some(alpha), weight, &mut sc.v_map);
        l.smooth += weight * v;
        for p in 0..np {
            for c in 0..count {
                g.v_features[p * ch + first + c] += sc.v_map[p * count + c];
            }
        }
    }
    if cfg.lambda_smooth_normal > 0.0 {
        sc.v_map.clear();
        sc.v_map.resize(np * 3, 0.0);
        let v =
            sc.smooth.loss_prepared(out.normal.as_flattened(), 3, Some(alpha), cfg.lambda_smooth_normal, &mut sc.v_map);
        l.smooth += cfg.lambda_smooth_normal * v;
        for (d, s) in g.v_normal.as_flattened_mut().iter_mut().zip(&sc.v_map) {
            *d += s;
        }
    }
    l.total += l.smooth;
    let t3 = Instant::now();
    t.losses += (t3 - t2).as_secs_f64();

    sc.v_feat.clear();
    sc.v_feat.resize(s.len() * ch, 0.0);
    raster::render_backward(s, cam, &settings, Some(features), &fwd, &sc.grads, v_surfels, Some(&mut sc.v_feat));
    sc.recorder.recycle(&mut fwd);
    let t4 = Instant::now();
    t.raster_backward += (t4 - t3).as_secs_f64();

    // Through the per-surfel shading (PBR image path: no detach).
    let n = s.len();
    sc.mgrads.reset(n);
    let sh = &sc.shading;
    sc.v_sub_pbr.clear();
    sc.v_sub_pbr.extend(sh.active.iter().map(|&i| {
        let f = &sc.v_feat[i as usize * ch..i as usize * ch + 3];
        [f[0], f[1], f[2]]
    }));
    let mut inp = state.cache.inputs(&sc.mats.albedo, &sc.mats.roughness, &sc.mats.normal, &sh.view);
    inp.specular = matches!(lobe, SpecularLobe::Cached);
    shade_subset_linearised_backward(&inp, env, &sh.active, &sh.lin, &sc.v_sub_pbr, &mut sc.sub).expect("sized above");
    if let Some(ss) = split_sum {
        let grads = sc.ss_grads.get_or_insert_with(|| ss.zero_grads());
        sh.split_sum_backward(ss, &sc.mats, &sc.v_sub_pbr, &mut sc.sub, grads);
    }
    // The traced lobe: per active surfel (no albedo in it), and its full-resolution env part.
    sc.v_env_traced.clear();
    if matches!(lobe, SpecularLobe::Traced(_)) {
        let g = sc.shading.traced.backward(env_full, &sc.v_sub_pbr).expect("sized above");
        for k in 0..g.v_roughness.len() {
            sc.sub.v_roughness[k] += g.v_roughness[k];
            for c in 0..3 {
                sc.sub.v_normal[k][c] += g.v_normal[k][c];
                sc.sub.v_view[k][c] += g.v_view[k][c];
            }
        }
        sc.v_env_traced.extend_from_slice(&g.v_env);
    }
    let sh = &sc.shading;
    let eye = cam.position().to_array();
    for (k, &i) in sh.active.iter().enumerate() {
        let i = i as usize;
        for c in 0..3 {
            sc.mgrads.v_albedo[i][c] += sc.sub.v_albedo[k][c];
            sc.mgrads.v_normal[i][c] += sc.sub.v_normal[k][c];
        }
        sc.mgrads.v_roughness[i] += sc.sub.v_roughness[k];
        let vm = view_dir_backward(s.means[i], eye, sc.sub.v_view[k]);
        for c in 0..3 {
            sc.mgrads.v_means[i][c] += vm[c];
        }
    }
    for i in 0..n {
        let f = &sc.v_feat[i * ch..(i + 1) * ch];
        for c in 0..3 {
            sc.mgrads.v_albedo[i][c] += f[3 + c];
        }
        sc.mgrads.v_roughness[i] += f[6];
    }
    if cfg.lambda_albedo_chroma > 0.0 {
        l.albedo_chroma = sc.albedo_chroma.loss(
            s,
            &sc.mats.albedo,
            cfg.lambda_albedo_chroma,
            cfg.albedo_chroma_bin,
            cfg.albedo_chroma_cap,
            &mut sc.mgrads.v_albedo,
        );
        l.total += l.albedo_chroma;
    }
    if cfg.lambda_albedo_voxel > 0.0 {
        let voxel = cfg.albedo_voxel * state.extent;
        l.albedo_voxel = sc.albedo_voxel.loss(
            s,
            &sc.mats.albedo,
            cfg.lambda_albedo_voxel,
            voxel,
            cfg.albedo_voxel_cap,
            &mut sc.mgrads.v_albedo,
        );
        l.total += l.albedo_voxel;
    }
    // The env gradient of the (box-filtered) sampled env, kept small until the end.
    sc.v_env_small.clear();
    sc.v_env_small.extend_from_slice(&sc.sub.v_env);
    let t5 = Instant::now();
    t.shading_backward += (t5 - t4).as_secs_f64();

    // Radiometric consistency.
    if cfg.lambda_rc > 0.0 {
        let rc = rc_settings(cfg, state.extent);
        let batch = match cfg.rc_order {
            RcOrder::Random => None,
            RcOrder::Sweep => {
                sc.rc_sweep.batch(cfg.seed, state.iteration, s.len(), cfg.rc_surfels, &mut sc.rc_batch);
                Some(&sc.rc_batch[..])
            }
        };
        l.rc = radiometric_consistency(
            s,
            &sc.mats,
            tracer,
            env,
            Some(eye),
            batch,
            rng,
            &rc,
            &mut sc.rc,
            v_surfels,
            &mut sc.mgrads,
            &mut sc.v_env_small,
        );
        l.total += l.rc.total;
    }
    t.consistency += t5.elapsed().as_secs_f64();
    sc.mgrads.chain_into(s, v_surfels);

    sc.v_env.clear();
    sc.v_env.resize(env_full.texels.len(), [0.0; 3]);
    env_full.box_downsample_backward(sample_factor(cfg), &sc.v_env_small, &mut sc.v_env);
    for (d, t) in sc.v_env.iter_mut().zip(&sc.v_env_traced) {
        for c in 0..3 {
            d[c] += t[c];
        }
    }
    if let (Some(ss), Some(grads)) = (split_sum, &sc.ss_grads) {
        ss.backward_to_env(grads, &mut sc.v_env);
    }
    // Env priors on the linear texels, then the exp activation.
    l.env_prior = state.light.priors_and_chain(cfg, env_full, &mut sc.v_env, &mut sc.v_env_log);
    l.total += l.env_prior;
    l
}

/// The iteration's background colour (drawn from `rng` when random).
fn draw_background(cfg: &TrainConfig, rng: &mut rand_pcg::Pcg64) -> [f32; 3] {
    match cfg.background {
        Background::Random => [rng.random::<f32>(), rng.random::<f32>(), rng.random::<f32>()],
        Background::White => [1.0; 3],
        Background::Black => [0.0; 3],
    }
}

/// Draw the cache's next rows partly from the learned light's peaks (`env_importance_inverse`),
/// with the light as the shading reads it now; rows traced before keep their directions and
/// weights, so every row stays an unbiased estimate of its surfel's incident light.
fn follow_light_peaks(cfg: &TrainConfig, state: &mut InverseState) {
    if cfg.env_importance_inverse > 0.0 {
        let env_s = state.env().box_downsample(sample_factor(cfg));
        state.cache.set_importance(EnvImportance::of_map(&env_s, cfg.pbr_samples, cfg.env_importance_inverse));
    }
}

/// The prefiltered env of the split-sum specular path, when the config uses it.
fn split_sum_for(cfg: &TrainConfig, env: &EnvMap) -> crate::Result<Option<SplitSum>> {
    Ok(match cfg.specular {
        Specular::SplitSum => Some(SplitSum::new(env)?),
        Specular::Mc | Specular::Traced => None,
    })
}

/// The stage's objective at the run's inverse checkpoint, view by view, without a step: which
/// state do the losses prefer, over every training view rather than one iteration's view?
/// (A diagnostic, `examples/probe_objective.rs`.) The cache is re-traced once with `seed`;
/// each view gets a background and a consistency sample fixed by (`seed`, view), so two runs
/// of the same scene are scored on the same draws.
pub fn objective_per_view(cfg: &TrainConfig, dataset: &Dataset, seed: u64) -> anyhow::Result<Vec<InverseLosses>> {
    let images = TrainImages::load(dataset, Split::Train)?;
    if images.cameras.is_empty() {
        anyhow::bail!("{}: the dataset has no training views", dataset.root.display());
    }
    let ckpt_path = checkpoint_path(&cfg.out);
    let c = Checkpoint::load(&ckpt_path)?;
    let mut state = InverseState::from_checkpoint(&ckpt_path, &c, cfg)?;
    let tracer = Tracer::build(&state.surfels, &trace_settings_with(&state.back_faces(cfg)));
    state.cache.refresh(&tracer, &state.surfels, cfg.pbr_samples, cfg.ray_start(state.extent), seed);
    let env = state.env();
    let env_s = env.box_downsample(sample_factor(cfg));
    state.cache.prepare_footprints(&env_s);
    let split_sum = split_sum_for(cfg, &env)?;
    let mut sc = Scratch::default();
    sc.pbr_image.clip_saturated = cfg.clip_saturated;
    let mut v_surfels = state.surfels.zeros_like();
    let mut times = InverseTimes::default();
    let mut out = Vec::with_capacity(images.cameras.len());
    for view in 0..images.cameras.len() {
        let mut rng = iteration_rng(seed, view as u32, 0x0b_1ec7);
        let bg = draw_background(cfg, &mut rng);
        v_surfels.fill_zero();
        v_surfels.sh_degree = state.surfels.sh_degree;
        out.push(iterate(
            cfg,
            &state,
            &env,
            &env_s,
            split_sum.as_ref(),
            &tracer,
            &images,
            view,
            bg,
            &mut rng,
            &mut sc,
            &mut v_surfels,
            &mut times,
        ));
    }
    Ok(out)
}

/// The geometry the inverse stage starts from: the newer of the run's `init` and `nvs`
/// checkpoints.
pub fn geometry_checkpoint(run: &Path) -> Option<PathBuf> {
    let modified = |p: &PathBuf| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    [nvs::GeometryStage::Init, nvs::GeometryStage::Nvs]
        .map(|s| s.checkpoint(run))
        .into_iter()
        .filter(|p| p.is_file())
        .max_by_key(modified)
}

/// Run (or resume) the inverse stage into `cfg.out`, starting from the run's newest geometry
/// checkpoint ([`geometry_checkpoint`]).
pub fn run(cfg: &TrainConfig, dataset: &Dataset, show_progress: bool) -> anyhow::Result<StageSummary> {
    run_until(cfg, dataset, show_progress, None)
}

/// As [`run`], stopping as if interrupted after iteration `stop_after`.
pub fn run_until(
    cfg: &TrainConfig,
    dataset: &Dataset,
    show_progress: bool,
    stop_after: Option<u32>,
) -> anyhow::Result<StageSummary> {
    let images = TrainImages::load(dataset, Split::Train)?;
    if images.cameras.is_empty() {
        anyhow::bail!("{}: the dataset has no training views", dataset.root.display());
    }
    let ckpt_path = checkpoint_path(&cfg.out);
    let mut state = if cfg.resume && ckpt_path.is_file() {
        let c = Checkpoint::load(&ckpt_path)?;
        InverseState::from_checkpoint(&ckpt_path, &c, cfg)?
    } else {
        let Some(geometry) = geometry_checkpoint(&cfg.out) else {
            anyhow::bail!(
                "{}: no nvs or init checkpoint; the inverse stage starts from the geometry of `radiogs train \
                 --stage nvs` or `--stage init` (or run --stage all)",
                cfg.out.display()
            );
        };
        let c = Checkpoint::load(&geometry)?;
        if !matches!(c.meta.get("stage").and_then(|s| s.as_str()), Some("nvs" | "init")) {
            anyhow::bail!("{}: not an nvs- or init-stage checkpoint", geometry.display());
        }
        tracing::info!("inverse: starting from the geometry of {}", geometry.display());
        let mut surfels = c.get_surfels(&geometry, "params")?;
        surfels.sh_degree = 3;
        let (_, extent) = dataset.camera_extent();
        let kept = if !cfg.fresh_materials && c.meta.get("stage").and_then(|s| s.as_str()) == Some("init") {
            let light = LearnedLight::get(&geometry, &c, cfg)?;
            if light.height != cfg.env_height {
                anyhow::bail!(
                    "{}: the init stage's light is {} texels high, env_height is {}; use the same env_height or \
                     --fresh-materials true",
                    geometry.display(),
                    light.height,
                    cfg.env_height
                );
            }
            tracing::info!("inverse: keeping the init stage's albedo, roughness and light");
            Some(light.log)
        } else {
            None
        };
        // Checkpoints from before the field were all two-sided.
        let two_sided = c.meta.get("two_sided").and_then(|v| v.as_bool()).unwrap_or(true);
        InverseState::from_nvs(cfg, surfels, &images.cameras, extent, kept, two_sided)?
    };
    interrupt::install();
    let mut metrics = open_metrics(&cfg.out.join("metrics_inverse.jsonl"), state.iteration)?;
    if cfg.trace_back_faces == TraceBackFaces::DarkUnseen {
        let k = state.unseen.iter().filter(|u| **u).count();
        tracing::info!("inverse: the back faces of the {k} unseen surfels block traced rays (dark-unseen)");
    }
    let mut tracer = Tracer::build(&state.surfels, &trace_settings_with(&state.back_faces(cfg)));
    let start = cfg.ray_start(state.extent);
    let mut times = InverseTimes::default();
    follow_light_peaks(cfg, &mut state);
    if state.cache.len() != state.surfels.len() || state.cache.samples != cfg.pbr_samples {
        let t = Instant::now();
        state.cache.refresh(&tracer, &state.surfels, cfg.pbr_samples, start, cfg.seed ^ state.iteration as u64);
        state.traced_at = vec![state.iteration; state.surfels.len()];
        times.cache_refresh += t.elapsed().as_secs_f64();
    }
    // Rows are re-traced when they would otherwise grow older than `cache_every` iterations
    // (the published full refresh every 100 iterations bounds the age the same way); rows the
    // consistency step traced meanwhile are fresh already, so each check traces fewer rows.
    let check_every = (cfg.cache_every / 4).max(1);
    // Under the sweep with R = S the consistency's rows refresh the cache (each row once per
    // pass of N/B iterations); the checks then only re-trace rows older than `cache_every`,
    // which a pass no longer than `cache_every` leaves none of.
    let swept = cfg.lambda_rc > 0.0 && cfg.rc_rays == cfg.pbr_samples && cfg.rc_order == RcOrder::Sweep;
    let limit = if swept { cfg.cache_every } else { cfg.cache_every.saturating_sub(check_every) };
    let mut stale: Vec<u32> = Vec::new();
    let bar = progress_bar("inverse", cfg.inverse_iters, state.iteration);
    if !show_progress {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let mut sc = Scratch::default();
    sc.pbr_image.clip_saturated = cfg.clip_saturated;
    let mut v_surfels = state.surfels.zeros_like();
    let started = Instant::now();
    let first_iteration = state.iteration;
    let mut last = InverseLosses::default();
    let mut interrupted = false;
    while state.iteration < cfg.inverse_iters {
        if interrupt::requested() || stop_after.is_some_and(|s| state.iteration >= s) {
            interrupted = true;
            break;
        }
        state.iteration += 1;
        let it = state.iteration;
        let mut rng = iteration_rng(cfg.seed, it, 0x1_0000_0011);
        let bg = draw_background(cfg, &mut rng);
        let view = view_for_iteration(cfg.seed ^ 0x1a7e, it, images.cameras.len());
        v_surfels.fill_zero();
        v_surfels.sh_degree = state.surfels.sh_degree;
        let env = state.env();
        let env_s = env.box_downsample(sample_factor(cfg));
        state.cache.prepare_footprints(&env_s);
        let split_sum = split_sum_for(cfg, &env)?;
        last = iterate(
            cfg,
            &state,
            &env,
            &env_s,
            split_sum.as_ref(),
            &tracer,
            &images,
            view,
            bg,
            &mut rng,
            &mut sc,
            &mut v_surfels,
            &mut times,
        );
        if !last.total.is_finite() {
            anyhow::bail!("inverse iteration {it}: the loss is {} (diverged); lower the learning rates", last.total);
        }
        let t_opt = Instant::now();
        if it <= cfg.light_warmup {
            // Light first: a zero gradient leaves Adam's moments (and so the parameter) at rest.
            v_surfels.albedo_logits.fill([0.0; 3]);
            v_surfels.roughness_logits.fill(0.0);
        }
        state.adam.step(&mut state.surfels, &v_surfels);
        state.light.step(&sc.v_env_log);
        times.optimiser += t_opt.elapsed().as_secs_f64();

        // The consistency rows are fresh traces: keep them (when they match the cache layout).
        if cfg.lambda_rc > 0.0 && cfg.rc_rays == cfg.pbr_samples {
            for k in 0..sc.rc.ids.len() {
                let (d, v, ind) = sc.rc.row(k, cfg.rc_rays);
                let i = sc.rc.ids[k] as usize;
                state.cache.overwrite_row(i, &d, &v, &ind);
                state.traced_at[i] = it;
            }
        }
        let gauge = cfg.gauge_every > 0 && cfg.lr_env > 0.0 && cfg.lr_albedo > 0.0;
        if gauge && it % cfg.gauge_every == 0 && it < cfg.inverse_iters {
            let t = Instant::now();
            let g = super::gauge::fit(cfg, &state, &images);
            super::gauge::apply(&mut state, g.scale);
            times.gauge += t.elapsed().as_secs_f64();
            let line = serde_json::json!({ "stage": "inverse", "iteration": it, "gauge": g });
            writeln!(metrics, "{line}").context("writing metrics_inverse.jsonl")?;
            tracing::debug!("inverse {it}: gauge {g:?}");
        }
        let t_fit = Instant::now();
        tracer.refit(&state.surfels);
        if tracer.needs_rebuild() {
            tracer = Tracer::build(&state.surfels, &trace_settings_with(&state.back_faces(cfg)));
        }
        times.tracer_refit += t_fit.elapsed().as_secs_f64();
        if it % check_every == 0 && it < cfg.inverse_iters {
            let t = Instant::now();
            stale.clear();
            stale.extend((0..state.traced_at.len() as u32).filter(|&i| it - state.traced_at[i as usize] > limit));
            follow_light_peaks(cfg, &mut state);
            state.cache.refresh_rows(&tracer, &state.surfels, &stale, start, cfg.seed ^ it as u64);
            for &i in &stale {
                state.traced_at[i as usize] = it;
            }
            times.cache_refresh += t.elapsed().as_secs_f64();
        }
        if it % cfg.log_every == 0 || it == cfg.inverse_iters {
            let line = serde_json::json!({
                "stage": "inverse", "iteration": it, "loss": last.total, "psnr_pbr": last.psnr_pbr,
                "psnr_sh": last.psnr_sh, "pbr_l1": last.pbr_l1, "sh_l1": last.sh_l1, "rc_camera": last.rc.camera,
                "rc_random": last.rc.random, "mask": last.mask, "normal": last.normal, "smooth": last.smooth, "albedo_chroma": last.albedo_chroma, "albedo_voxel": last.albedo_voxel,
                "env_prior": last.env_prior, "seconds": started.elapsed().as_secs_f64(),
            });
            writeln!(metrics, "{line}").context("writing metrics_inverse.jsonl")?;
            bar.set_message(format!(
                "loss {:.4} pbr {:.2} dB sh {:.2} dB rc {:.4}",
                last.total,
                last.psnr_pbr,
                last.psnr_sh,
                last.rc.camera + last.rc.random
            ));
        }
        bar.set_position(it as u64);
        if cfg.checkpoint_every > 0 && it % cfg.checkpoint_every == 0 && it < cfg.inverse_iters {
            state.to_checkpoint(cfg).save(&ckpt_path)?;
        }
    }
    bar.finish_and_clear();
    state.to_checkpoint(cfg).save(&ckpt_path)?;
    if !interrupted {
        let unseen = Some(&state.unseen[..]);
        write_ply_flagged(&cfg.out.join("point_cloud.ply"), &state.surfels, Some(cfg.filter_inv_square), unseen)?;
        state.env().save(&cfg.out.join("envmap.exr"))?;
    }
    let seconds = started.elapsed().as_secs_f64();
    let split = serde_json::to_value(times)?;
    crate::io::atomic::write_atomic(
        &cfg.out.join("inverse_times.json"),
        serde_json::to_string_pretty(&serde_json::json!({
            "iterations": state.iteration, "seconds": seconds, "split_seconds": split,
            "surfels": state.surfels.len(), "pbr_samples": cfg.pbr_samples, "rc_surfels": cfg.rc_surfels,
            "rc_rays": cfg.rc_rays, "rc_order": cfg.rc_order, "lambda_rc": cfg.lambda_rc,
        }))?
        .as_bytes(),
    )?;
    Ok(StageSummary {
        iterations: state.iteration,
        iterations_run: state.iteration - first_iteration,
        surfels: state.surfels.len(),
        seconds,
        last_psnr: last.psnr_pbr,
        time_split: TimeSplit {
            raster_forward: times.raster_forward,
            raster_backward: times.raster_backward,
            losses: times.losses,
            densify: 0.0,
            optimiser: times.optimiser,
            shading: times.shading + times.shading_backward + times.consistency,
            other: times.tracer_refit + times.cache_refresh + times.gauge,
        },
        interrupted,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shade::splitsum::BrdfLut;

    /// A checkpoint whose cache blobs disagree in length (cut, or from another run) is refused
    /// by name when it is loaded, not left to panic in the first shading step.
    #[test]
    fn checkpoint_cache_blobs_of_the_wrong_length_are_refused_by_name() {
        let cfg = TrainConfig::default();
        let s = Surfels::random_in_box(5, [-1.0; 3], [1.0; 3], 3);
        let Ok(mut state) = InverseState::from_nvs(&cfg, s.clone(), &[], 1.0, None, false) else { panic!("state") };
        let tracer = Tracer::build(&s, &trace_settings());
        state.cache.refresh(&tracer, &s, 4, crate::shade::incident::RayStart::offset_only(1e-3), 1);
        state.traced_at = vec![0; s.len()];
        let path = Path::new("run/checkpoint_inverse.bin");
        let good = state.to_checkpoint(&cfg);
        assert!(InverseState::from_checkpoint(path, &good, &cfg).is_ok());
        for (blob, keep) in [("cache.dirs", 9), ("cache.indirect", 30), ("cache.dirs", 0)] {
            let mut c = good.clone();
            let cut = c.blob(blob).unwrap()[..keep].to_vec();
            c.put(blob, cut);
            let err = InverseState::from_checkpoint(path, &c, &cfg).err().expect("refused").to_string();
            assert!(err.contains("checkpoint_inverse.bin") && err.contains(blob), "{err}");
        }
        // Rows drawn partly from a map keep their per-sample weights through a checkpoint.
        state.cache.sample_weights = (0..state.cache.dirs.len()).map(|k| 0.1 + k as f32).collect();
        let c = state.to_checkpoint(&cfg);
        let back = InverseState::from_checkpoint(path, &c, &cfg).expect("weights load");
        assert_eq!(back.cache.sample_weights, state.cache.sample_weights);
        let mut cut = c.clone();
        cut.put("cache.sample_weights", vec![1.0; 5]);
        let err = InverseState::from_checkpoint(path, &cut, &cfg).err().expect("refused").to_string();
        assert!(err.contains("cache.sample_weights"), "{err}");
        // Unseen flags round-trip; a blob of another length or with another value is refused.
        state.unseen = vec![true, false, false, true, false];
        let c = state.to_checkpoint(&cfg);
        assert_eq!(InverseState::from_checkpoint(path, &c, &cfg).expect("flags load").unseen, state.unseen);
        for bad in [vec![1.0; 4], vec![0.0, 0.5, 0.0, 0.0, 0.0]] {
            let mut cut = c.clone();
            cut.put("unseen", bad);
            let err = InverseState::from_checkpoint(path, &cut, &cfg).err().expect("refused").to_string();
            assert!(err.contains("unseen"), "{err}");
        }
        // A wrong sample count, and one whose product with the surfel count overflows.
        for samples in [3u64, 1 << 62] {
            let mut c = good.clone();
            c.meta["cache_samples"] = serde_json::json!(samples);
            let err = InverseState::from_checkpoint(path, &c, &cfg).err().expect("refused").to_string();
            assert!(err.contains("cache"), "{err}");
        }
    }

    /// A run's back faces: a mode other than dark-unseen needs nothing; dark-unseen takes the
    /// PLY's flags, else the checkpoint's, names the file when they are miscounted and culls
    /// when there are none.
    #[test]
    fn a_runs_back_faces_take_its_saved_unseen_flags() {
        let run = crate::test_dir::TempDir::new("back-faces");
        let s = Surfels::random_in_box(4, [-1.0; 3], [1.0; 3], 3);
        assert_eq!(BackFaces::of_run(&run, TraceBackFaces::Dark, 4).unwrap(), TraceBackFaces::Dark.into());
        let mut c = Checkpoint::default();
        c.put_surfels("params", &s);
        c.put(UNSEEN_BLOB, vec![0.0, 1.0, 1.0, 0.0]);
        c.save(&checkpoint_path(&run)).unwrap();
        let b = BackFaces::of_run(&run, TraceBackFaces::DarkUnseen, 4).unwrap();
        assert_eq!(b.unseen.as_deref(), Some(&[false, true, true, false][..]));
        let ply = run.join("point_cloud.ply");
        write_ply_flagged(&ply, &s, None, Some(&[true, false, false, false])).unwrap();
        let b = BackFaces::of_run(&run, TraceBackFaces::DarkUnseen, 4).unwrap();
        assert_eq!(b.unseen.as_deref(), Some(&[true, false, false, false][..]));
        let err = BackFaces::of_run(&run, TraceBackFaces::DarkUnseen, 5).unwrap_err().to_string();
        assert!(err.contains("point_cloud.ply") && err.contains("4 unseen flags for 5 surfels"), "{err}");
        // Surfels written without flags: traced as culled (with a warning).
        write_ply_flagged(&ply, &s, None, None).unwrap();
        let b = BackFaces::of_run(&run, TraceBackFaces::DarkUnseen, 4).unwrap();
        assert_eq!(trace_settings_with(&b), trace_settings_with(&TraceBackFaces::Cull.into()));
        // A folder radiogs did not train (no config.toml) traces culled.
        assert_eq!(crate::eval::load_run_config(&run).unwrap().trace_back_faces, TraceBackFaces::Cull);
    }

    /// The split-sum PBR colour of `SurfelShading` (Lambert Monte Carlo + occluded split-sum
    /// lobe) against finite differences of its backward (`shade_subset_linearised_backward`
    /// with the Lambert-only inputs + `split_sum_backward`), per roughness, normal and env texel. The
    /// normal check runs on lone surfels (V = 1, no fill), where the lobe's occlusion does not
    /// depend on the normal (the backward holds occlusion and fill constant).
    #[test]
    fn split_sum_shading_matches_finite_differences() {
        use rand::SeedableRng;
        for occluded in [false, true] {
            let mut rg = rand_pcg::Pcg64::seed_from_u64(if occluded { 7 } else { 8 });
            let mut s = Surfels::default();
            for k in 0..4 {
                let spread = if occluded { 0.15 } else { 3.0 };
                let m = [rg.random_range(-spread..spread), rg.random_range(-spread..spread), 0.1 * k as f32];
                let n = [rg.random_range(-0.4..0.4f32), rg.random_range(-0.4..0.4f32), 1.0];
                s.push(m, [0.3, 0.2], crate::surfels::quat_with_normal(n), 0.7, [0.5; 3], [0.5; 3], 0.5);
            }
            for i in 0..s.len() {
                s.albedo_logits[i] = [rg.random_range(-1.0..1.0); 3];
                // Away from the prefiltered levels (0.2 steps) and the LUT nodes (i/31): kinks.
                s.roughness_logits[i] = logit([0.07, 0.33, 0.55, 0.93][i]);
            }
            let mut env = EnvMap::constant(32, 16, [0.0; 3]);
            for t in env.texels.iter_mut() {
                *t = [rg.random_range(0.2..2.0), rg.random_range(0.2..2.0), rg.random_range(0.2..2.0)];
            }
            let tracer = Tracer::build(&s, &trace_settings());
            let mut cache = IncidentCache::default();
            cache.refresh(&tracer, &s, 16, crate::shade::incident::RayStart::offset_only(1e-3), 3);
            if occluded {
                assert!(cache.visibility.iter().any(|&v| v < 0.9), "the test needs occlusion");
            } else {
                assert!(cache.visibility.iter().all(|&v| v == 1.0));
            }
            let mut mats = MaterialView::default();
            mats.update(&s);
            let cam = Camera::look_at("fd", glam::Vec3::new(0.5, -1.0, 6.0), glam::Vec3::ZERO, 16, 16, 1.2);
            let v_pbr: Vec<[f32; 3]> =
                (0..s.len()).map(|_| [rg.random_range(-1.0..1.0), rg.random(), rg.random_range(-1.0..1.0)]).collect();
            let objective = |m: &MaterialView, e: &EnvMap| -> f64 {
                let ss = SplitSum::new(e).unwrap();
                let mut sh = SurfelShading::default();
                sh.compute(&s, m, &cache, e, SpecularLobe::SplitSum(&ss), &cam, TRAIN_CHANNELS);
                sh.active
                    .iter()
                    .enumerate()
                    .map(|(k, &i)| {
                        (0..3)
                            .map(|c| sh.features[i as usize * TRAIN_CHANNELS + c] as f64 * v_pbr[k][c] as f64)
                            .sum::<f64>()
                    })
                    .sum()
            };
            // Analytic gradients.
            let ss = SplitSum::new(&env).unwrap();
            // The training iteration's pair: the linearised shading and its backward.
            let mut sh = SurfelShading { linearise: true, ..Default::default() };
            sh.compute(&s, &mats, &cache, &env, SpecularLobe::SplitSum(&ss), &cam, TRAIN_CHANNELS);
            assert!(sh.active.len() >= 3, "{} active", sh.active.len());
            let v_sub: Vec<[f32; 3]> = (0..sh.active.len()).map(|k| v_pbr[k]).collect();
            let mut inp = cache.inputs(&mats.albedo, &mats.roughness, &mats.normal, &sh.view);
            inp.specular = false;
            let mut sub = SubsetGrads::default();
            shade_subset_linearised_backward(&inp, &env, &sh.active, &sh.lin, &v_sub, &mut sub).unwrap();
            let mut grads = ss.zero_grads();
            sh.split_sum_backward(&ss, &mats, &v_sub, &mut sub, &mut grads);
            let mut v_env = sub.v_env.clone();
            ss.backward_to_env(&grads, &mut v_env);
            let h = 1e-3f32;
            let close = |a: f32, fd: f64, what: &str| {
                assert!((a as f64 - fd).abs() < 2e-2 * fd.abs() + 2e-3, "{what}: analytic {a} vs fd {fd}");
            };
            for (k, &i) in sh.active.iter().enumerate() {
                let i = i as usize;
                let (mut a, mut b) = (mats.clone(), mats.clone());
                a.roughness[i] += h;
                b.roughness[i] -= h;
                let fd = (objective(&a, &env) - objective(&b, &env)) / (2.0 * h as f64);
                close(sub.v_roughness[k], fd, &format!("occluded {occluded}: roughness[{i}]"));
                if !occluded {
                    for c in 0..3 {
                        let (mut a, mut b) = (mats.clone(), mats.clone());
                        a.normal[i][c] += h;
                        b.normal[i][c] -= h;
                        let fd = (objective(&a, &env) - objective(&b, &env)) / (2.0 * h as f64);
                        close(sub.v_normal[k][c], fd, &format!("normal[{i}][{c}]"));
                    }
                }
            }
            // Env texels (linear): unit steps on the texels with the largest gradients.
            let base = objective(&mats, &env);
            let mut order: Vec<usize> = (0..v_env.len()).collect();
            order.sort_by(|&a, &b| v_env[b][0].abs().total_cmp(&v_env[a][0].abs()));
            for &t in &order[..8] {
                let mut e2 = env.clone();
                e2.texels[t][0] += 1.0;
                let fd = objective(&mats, &e2) - base;
                close(v_env[t][0], fd, &format!("occluded {occluded}: env texel {t}"));
            }
        }
    }

    /// Furnace for the split-sum specular path: a lone surfel under a constant env L has
    /// V = 1 and no indirect light, so its PBR colour is a·L·(10° floor coverage) from the
    /// Lambert Monte Carlo sum plus L·(F0·A + B) from the split-sum lobe — and with
    /// `split_sum = None` the lobe comes from the Monte Carlo sum instead.
    #[test]
    fn split_sum_furnace_on_a_lone_surfel() {
        let mut s = Surfels::random_in_box(1, [0.0; 3], [0.0; 3], 2);
        let n = [0.3f32, -0.2, 0.9];
        s.quats[0] = crate::surfels::quat_with_normal(n);
        s.albedo_logits[0] = [albedo_to_logit(0.6), albedo_to_logit(0.2), albedo_to_logit(0.4)];
        s.roughness_logits[0] = logit(0.35);
        let l = [1.3f32, 0.7, 2.0];
        let env = EnvMap::constant(128, 64, l);
        let ss = SplitSum::new(&env).unwrap();
        let tracer = Tracer::build(&s, &trace_settings());
        let mut cache = IncidentCache::default();
        cache.refresh(&tracer, &s, 64, crate::shade::incident::RayStart::offset_only(1e-3), 5);
        assert!(cache.visibility.iter().all(|&v| v == 1.0));
        let mut mats = MaterialView::default();
        mats.update(&s);
        let eye = glam::Vec3::new(1.0, -1.5, 3.0);
        let cam = Camera::look_at("furnace", eye, glam::Vec3::ZERO, 32, 32, 0.8);
        let mut sh = SurfelShading::default();
        sh.compute(&s, &mats, &cache, &env, SpecularLobe::SplitSum(&ss), &cam, VIEW_CHANNELS);
        assert_eq!(sh.active, vec![0]);
        let nn = mats.normal[0];
        let wo = view_dir(s.means[0], eye.to_array());
        let nov = (nn[0] * wo[0] + nn[1] * wo[1] + nn[2] * wo[2]) as f64;
        let lut = BrdfLut::get().lookup(nov, mats.roughness[0] as f64);
        let spec = crate::shade::brdf::F0 * lut.a + lut.b;
        let coverage = 1.0 - 10f64.to_radians().sin().powi(2);
        for c in 0..3 {
            let want = mats.albedo[0][c] as f64 * (1.0 - spec) * l[c] as f64 * coverage + l[c] as f64 * spec;
            let got = sh.features[c] as f64;
            assert!((got - want).abs() < 3e-3 * l[c] as f64, "channel {c}: {got} vs {want}");
            assert_eq!(sh.features[7 + c], 0.0, "no indirect light");
        }
        // Monte Carlo lobe instead: same Lambert part, a different (noisier) specular estimate.
        let mut mc = SurfelShading::default();
        mc.compute(&s, &mats, &cache, &env, SpecularLobe::Cached, &cam, VIEW_CHANNELS);
        for c in 0..3 {
            let lambert = mats.albedo[0][c] as f64 * (1.0 - spec) * l[c] as f64 * coverage;
            let mc_spec = mc.features[c] as f64 - lambert;
            assert!(mc_spec > 0.0 && (mc_spec - l[c] as f64 * spec).abs() < 0.5 * l[c] as f64 * spec + 1e-3);
        }
    }

    /// The same furnace with the specular lobe traced for the view (`--specular traced`):
    /// averaged over seeds it is L·(F0·A + B) too, the Lambert part is the cache's, every ray
    /// sees the sky (no indirect light), and a seed's samples re-shaded under a dimmer sky
    /// (`TracedAgain`, the gauge's path) scale with it.
    #[test]
    fn traced_lobe_furnace_on_a_lone_surfel() {
        let mut s = Surfels::random_in_box(1, [0.0; 3], [0.0; 3], 2);
        s.quats[0] = crate::surfels::quat_with_normal([0.3, -0.2, 0.9]);
        s.albedo_logits[0] = [albedo_to_logit(0.6), albedo_to_logit(0.2), albedo_to_logit(0.4)];
        s.roughness_logits[0] = logit(0.35);
        let l = [1.3f32, 0.7, 2.0];
        let env = EnvMap::constant(128, 64, l);
        let tracer = Tracer::build(&s, &trace_settings());
        let mut cache = IncidentCache::default();
        cache.refresh(&tracer, &s, 64, crate::shade::incident::RayStart::offset_only(1e-3), 5);
        let mut mats = MaterialView::default();
        mats.update(&s);
        let eye = glam::Vec3::new(1.0, -1.5, 3.0);
        let cam = Camera::look_at("furnace", eye, glam::Vec3::ZERO, 32, 32, 0.8);
        let wo = view_dir(s.means[0], eye.to_array());
        let nn = mats.normal[0];
        let nov = (nn[0] * wo[0] + nn[1] * wo[1] + nn[2] * wo[2]) as f64;
        let lut = BrdfLut::get().lookup(nov, mats.roughness[0] as f64);
        let spec = crate::shade::brdf::F0 * lut.a + lut.b;
        let coverage = 1.0 - 10f64.to_radians().sin().powi(2);
        let (trials, mut mean) = (200, [0.0f64; 3]);
        let mut sh = SurfelShading::default();
        for seed in 0..trials {
            let lobe = SpecularLobe::Traced(TracedSpecular {
                tracer: &tracer,
                surfels: &s,
                env: &env,
                start: crate::shade::incident::RayStart::offset_only(1e-3),
                rays: 4,
                seed,
            });
            sh.compute(&s, &mats, &cache, &env, lobe, &cam, VIEW_CHANNELS);
            assert_eq!(sh.active, vec![0]);
            for c in 0..3 {
                assert_eq!(sh.features[7 + c], 0.0, "no indirect light");
                mean[c] += sh.features[c] as f64 / trials as f64;
            }
        }
        for c in 0..3 {
            let lambert = mats.albedo[0][c] as f64 * (1.0 - spec) * l[c] as f64 * coverage;
            let traced = mean[c] - lambert;
            assert!(
                (traced - l[c] as f64 * spec).abs() < 0.03 * l[c] as f64 * spec,
                "{c}: {traced} vs {}",
                l[c] as f64 * spec
            );
        }
        let before = sh.features[..3].to_vec();
        let dim = EnvMap::constant(128, 64, l.map(|x| 0.5 * x));
        sh.compute(&s, &mats, &cache, &env, SpecularLobe::TracedAgain(&dim), &cam, VIEW_CHANNELS);
        for c in 0..3 {
            let lambert = (mats.albedo[0][c] as f64 * (1.0 - spec) * l[c] as f64 * coverage) as f32;
            let want = lambert + 0.5 * (before[c] - lambert);
            assert!((sh.features[c] - want).abs() < 1e-5, "{} vs {want}", sh.features[c]);
        }
    }

    /// `--trace-back-faces` end to end through the incident cache: a floor surfel under a
    /// large opaque surfel that faces up (away from it). Culled, the floor sees the whole sky;
    /// two-sided, the upper surfel blocks it and adds its colour; dark, it blocks it and adds
    /// nothing.
    #[test]
    fn traced_back_faces_cull_composite_or_only_block() {
        let mut s = Surfels::default();
        let up = crate::surfels::quat_with_normal([0.0, 0.0, 1.0]);
        s.push([0.0; 3], [0.05, 0.05], up, 0.9, [0.5; 3], [0.5; 3], 0.5);
        s.push([0.0, 0.0, 0.3], [2.0, 2.0], up, 0.95, [0.9, 0.6, 0.3], [0.5; 3], 0.5);
        let samples = 64;
        let cache_of = |mode: BackFaces| {
            let tracer = Tracer::build(&s, &trace_settings_with(&mode));
            let mut cache = IncidentCache::default();
            cache.refresh(&tracer, &s, samples, crate::shade::incident::RayStart::offset_only(1e-3), 5);
            let vis: f32 = cache.visibility[..samples].iter().sum::<f32>() / samples as f32;
            let ind: f32 = cache.indirect[..samples].iter().map(|c| c[0]).sum::<f32>() / samples as f32;
            (vis, ind)
        };
        let (cull, two, dark) = (
            cache_of(TraceBackFaces::Cull.into()),
            cache_of(TraceBackFaces::TwoSided.into()),
            cache_of(TraceBackFaces::Dark.into()),
        );
        assert!(cull.0 > 0.999 && cull.1 == 0.0, "culled: {cull:?}");
        assert!(two.0 < 0.5 && two.1 > 0.1, "two-sided: {two:?}");
        assert_eq!(dark.0, two.0, "dark back faces block as two-sided ones do");
        assert_eq!(dark.1, 0.0, "dark back faces add no light");
        // dark-unseen: the upper surfel blocks as dark when flagged unseen, else it is culled.
        let unseen = |flags: [bool; 2]| BackFaces {
            mode: TraceBackFaces::DarkUnseen,
            unseen: Some(flags.into()),
            grazing_deg: 0.0,
            opaque_below: 0.0,
        };
        assert_eq!(cache_of(unseen([false, true])), dark);
        assert_eq!(cache_of(unseen([true, false])), cull);
        assert_eq!(cache_of(TraceBackFaces::DarkUnseen.into()), cull, "without flags it culls");
    }

    /// `--trace-opaque-below` through the incident cache: a floor surfel under a translucent
    /// surfel facing it. Every cached sample is the unramped one mapped by `visibility_ramp`,
    /// and the rays through the surfel's core count as blocked.
    #[test]
    fn the_visibility_ramp_reaches_the_incident_cache() {
        let mut s = Surfels::default();
        let up = crate::surfels::quat_with_normal([0.0, 0.0, 1.0]);
        let down = crate::surfels::quat_with_normal([0.0, 0.0, -1.0]);
        s.push([0.0; 3], [0.05, 0.05], up, 0.9, [0.5; 3], [0.5; 3], 0.5);
        s.push([0.0, 0.0, 0.3], [0.4, 0.4], down, 0.8, [0.9, 0.6, 0.3], [0.5; 3], 0.5);
        let samples = 64;
        let cache_of = |t0: f32| {
            let mode = BackFaces { opaque_below: t0, ..TraceBackFaces::Cull.into() };
            let tracer = Tracer::build(&s, &trace_settings_with(&mode));
            let mut cache = IncidentCache::default();
            cache.refresh(&tracer, &s, samples, crate::shade::incident::RayStart::offset_only(1e-3), 5);
            cache
        };
        let (plain, ramped) = (cache_of(0.0), cache_of(0.5));
        let mut blocked = 0;
        for k in 0..samples {
            let (v, g, _, _) = crate::trace::visibility_ramp(plain.visibility[k], 0.5);
            assert!((ramped.visibility[k] - v).abs() < 1e-6, "sample {k}");
            for c in 0..3 {
                assert!((ramped.indirect[k][c] - g * plain.indirect[k][c]).abs() < 1e-5, "sample {k} ch {c}");
            }
            blocked += (plain.visibility[k] > 0.0 && plain.visibility[k] < 0.5) as usize;
            assert!(ramped.visibility[k] <= plain.visibility[k]);
        }
        assert!(blocked > 3, "only {blocked} samples under the ramp");
    }
}
