//! The `nvs` stage: plain 2DGS training of geometry and SH radiance from posed RGBA images.
//!
//! Per iteration: one training view (a seeded permutation per epoch), the GT composited over the
//! iteration's background, a rasterised render, the image loss (1 − λ)·L1 + λ·D-SSIM, the mask
//! BCE, depth distortion and normal consistency (both weighted by the GT alpha: unmasked, they
//! grow background floaters on object data), the rasteriser's backward pass, Adam with the
//! exponential position schedule, and 2DGS density control. Every random choice is derived
//! from (seed, iteration), so `--resume` continues bit-for-bit.
//!
//! Orientation: this stage is two-sided by default (as 2DGS): from a random start, culled
//! surfels facing away from a view get no gradient there and the geometry converges more
//! slowly. The PBR stages cull back faces and need outward normals; they orient the surfels
//! when they start.

use crate::camera::Camera;
use crate::error::Error;
use crate::io::dataset::{Dataset, Split};
use crate::io::ply::{read_ply, write_ply_trained};
use crate::loss::{self, NormalConsistency, Ssim};
use crate::optim::{ExponLr, LearningRates, SurfelAdam};
use crate::raster::{self, Features, Outputs, RasterSettings, RenderGrads};
use crate::surfels::{SurfelGrads, Surfels, sigmoid};
use crate::train::checkpoint::Checkpoint;
use crate::train::config::{Background, TrainConfig};
use crate::train::densify::{self, DensifyConfig, DensifyStats};
use crate::train::light::LearnedLight;
use crate::train::pbr_init::{self, InitLosses, InitPass};
use crate::train::{init, interrupt};
use anyhow::Context;
use rand::{RngExt, SeedableRng};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Training images held as straight sRGB colour and alpha, pixel-major.
pub struct TrainImages {
    pub cameras: Vec<Camera>,
    pub rgb: Vec<Vec<[f32; 3]>>,
    pub alpha: Vec<Vec<f32>>,
}

impl TrainImages {
    pub fn load(dataset: &Dataset, split: Split) -> crate::Result<TrainImages> {
        let images = dataset.load_images(split)?;
        let cameras = dataset.views(split).iter().map(|v| v.camera.clone()).collect();
        let rgb = images.iter().map(|img| img.data.chunks_exact(4).map(|p| [p[0], p[1], p[2]]).collect()).collect();
        let alpha = images.iter().map(|img| img.data.chunks_exact(4).map(|p| p[3]).collect()).collect();
        Ok(TrainImages { cameras, rgb, alpha })
    }
}

/// Time spent in each part of an iteration.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct TimeSplit {
    /// Stage init: per-surfel split-sum shading, its backward and the consistency.
    pub shading: f64,
    pub raster_forward: f64,
    pub raster_backward: f64,
    pub losses: f64,
    pub densify: f64,
    pub optimiser: f64,
    pub other: f64,
}

/// What a finished (or interrupted) stage reports.
#[derive(Clone, Debug, serde::Serialize)]
pub struct StageSummary {
    /// Last completed iteration.
    pub iterations: u32,
    /// Iterations run by this call (fewer than `iterations` after `--resume`); `seconds` is
    /// their time.
    pub iterations_run: u32,
    pub surfels: usize,
    pub seconds: f64,
    pub last_psnr: f32,
    pub time_split: TimeSplit,
    pub interrupted: bool,
}

/// The two stages that train geometry with densification: plain 2DGS (`nvs`) and RadioGS
/// stage 1 (`init`: the same plus split-sum PBR, materials and a learned light; pbr_init.rs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GeometryStage {
    Nvs,
    Init,
}

impl GeometryStage {
    pub fn name(self) -> &'static str {
        match self {
            GeometryStage::Nvs => "nvs",
            GeometryStage::Init => "init",
        }
    }

    pub fn checkpoint(self, run: &Path) -> PathBuf {
        match self {
            GeometryStage::Nvs => checkpoint_path(run),
            GeometryStage::Init => run.join("checkpoint_init.bin"),
        }
    }

    fn metrics(self, run: &Path) -> PathBuf {
        match self {
            GeometryStage::Nvs => run.join("metrics.jsonl"),
            GeometryStage::Init => run.join("metrics_init.jsonl"),
        }
    }
}

/// The state of an nvs or init run: everything a checkpoint holds.
pub struct NvsState {
    pub surfels: Surfels,
    pub adam: SurfelAdam,
    pub stats: DensifyStats,
    /// Last completed iteration (0 = none).
    pub iteration: u32,
    pub extent: f32,
    /// The learned light (stage `init` only).
    pub light: Option<LearnedLight>,
}

impl NvsState {
    pub fn stage(&self) -> GeometryStage {
        if self.light.is_some() { GeometryStage::Init } else { GeometryStage::Nvs }
    }
}

pub fn checkpoint_path(run: &Path) -> PathBuf {
    run.join("checkpoint.bin")
}

fn learning_rates(cfg: &TrainConfig, stage: GeometryStage) -> LearningRates {
    let materials = stage == GeometryStage::Init;
    LearningRates {
        means: cfg.lr_position_init * cfg.position_lr_factor(),
        log_scales: cfg.lr_scale,
        quats: cfg.lr_rotation,
        opacity_logits: cfg.lr_opacity,
        sh_dc: cfg.lr_sh,
        sh_rest: cfg.lr_sh / 20.0,
        albedo_logits: if materials { cfg.lr_albedo } else { 0.0 },
        roughness_logits: if materials { cfg.lr_roughness } else { 0.0 },
    }
}

impl NvsState {
    pub fn new(
        cfg: &TrainConfig,
        dataset: &Dataset,
        images: &TrainImages,
        stage: GeometryStage,
    ) -> anyhow::Result<NvsState> {
        let (_, extent) = dataset.camera_extent();
        let mut surfels = match &cfg.init_ply {
            Some(path) => read_ply(path)?,
            None => {
                let (points, colours) =
                    init::visual_hull_points(&images.cameras, &rgba_views(images), cfg.init_points, 0.5, cfg.seed);
                if points.is_empty() {
                    anyhow::bail!(
                        "{}: no point of the scene box lies inside every training mask; are the alpha channels empty, \
                         or do the cameras (transform_matrix, camera_angle_x) not look at the object?",
                        dataset.root.display()
                    );
                }
                Surfels::from_points(&points, &colours, cfg.seed)
            }
        };
        surfels.sh_degree = 0;
        let light = match stage {
            GeometryStage::Nvs => None,
            GeometryStage::Init => {
                let a = crate::surfels::albedo_to_logit(cfg.albedo_init);
                surfels.albedo_logits.iter_mut().for_each(|x| *x = [a; 3]);
                surfels.roughness_logits.iter_mut().for_each(|r| *r = crate::surfels::logit(cfg.roughness_init));
                Some(LearnedLight::fresh(cfg)?)
            }
        };
        let adam = SurfelAdam::new(&surfels, learning_rates(cfg, stage));
        let stats = DensifyStats::new(surfels.len());
        Ok(NvsState { surfels, adam, stats, iteration: 0, extent, light })
    }

    pub fn to_checkpoint(&self, cfg: &TrainConfig) -> Checkpoint {
        let mut c = Checkpoint {
            meta: serde_json::json!({
                "stage": self.stage().name(),
                "iteration": self.iteration,
                "extent": self.extent,
                "adam_step": self.adam.step,
                "seed": cfg.seed,
                "iters": cfg.iters,
                // The inverse stage re-orients a two-sided geometry's normals, not a culled one's.
                "two_sided": cfg.two_sided,
            }),
            ..Default::default()
        };
        c.put_surfels("params", &self.surfels);
        c.put_surfels("adam_m", &self.adam.m);
        c.put_surfels("adam_v", &self.adam.v);
        c.put("stats.grad_accum", self.stats.grad_accum.clone());
        c.put("stats.abs_accum", self.stats.abs_accum.clone());
        c.put("stats.denom", self.stats.denom.clone());
        c.put("stats.max_radii", self.stats.max_radii.clone());
        if let Some(light) = &self.light {
            light.put(&mut c);
        }
        c
    }

    pub fn from_checkpoint(path: &Path, c: &Checkpoint, cfg: &TrainConfig) -> crate::Result<NvsState> {
        let meta_u64 = |key: &str| c.meta_u64(path, key);
        let surfels = c.get_surfels(path, "params")?;
        let stage = match c.meta.get("stage").and_then(|s| s.as_str()) {
            Some("nvs") => GeometryStage::Nvs,
            Some("init") => GeometryStage::Init,
            other => {
                return Err(Error::format(path, "stage", format!("{other:?} is not an nvs or init checkpoint")));
            }
        };
        let light = match stage {
            GeometryStage::Nvs => None,
            GeometryStage::Init => Some(LearnedLight::get(path, c, cfg)?),
        };
        let mut adam = SurfelAdam::new(&surfels, learning_rates(cfg, stage));
        adam.m = c.get_surfels(path, "adam_m")?;
        adam.v = c.get_surfels(path, "adam_v")?;
        adam.step = meta_u64("adam_step")?;
        let stats = DensifyStats {
            grad_accum: c.require(path, "stats.grad_accum")?.to_vec(),
            // Checkpoints before the AbsGS statistic: start it at zero.
            abs_accum: c.blob("stats.abs_accum").map_or_else(|| vec![0.0; surfels.len()], <[f32]>::to_vec),
            denom: c.require(path, "stats.denom")?.to_vec(),
            max_radii: c.require(path, "stats.max_radii")?.to_vec(),
        };
        let stat_rows = [stats.grad_accum.len(), stats.abs_accum.len(), stats.max_radii.len(), stats.len()];
        if adam.m.len() != surfels.len() || stat_rows.iter().any(|&r| r != surfels.len()) {
            return Err(Error::format(path, "optimiser state", "row count differs from the surfel count"));
        }
        let extent = c.meta.get("extent").and_then(|v| v.as_f64()).unwrap_or(1.0) as f32;
        Ok(NvsState { surfels, adam, stats, iteration: meta_u64("iteration")? as u32, extent, light })
    }
}

fn rgba_views(images: &TrainImages) -> Vec<crate::io::image::Image> {
    images
        .rgb
        .iter()
        .zip(&images.alpha)
        .zip(&images.cameras)
        .map(|((rgb, alpha), cam)| {
            let mut img = crate::io::image::Image::new(cam.width, cam.height, 4);
            for (i, px) in img.data.chunks_exact_mut(4).enumerate() {
                px[..3].copy_from_slice(&rgb[i]);
                px[3] = alpha[i];
            }
            img
        })
        .collect()
}

/// The view trained at an iteration: a seeded permutation of the views per epoch.
pub(crate) fn view_for_iteration(seed: u64, iteration: u32, views: usize) -> usize {
    let epoch = (iteration as usize - 1) / views;
    let slot = (iteration as usize - 1) % views;
    let mut order: Vec<usize> = (0..views).collect();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed ^ 0x0b5e_55ed ^ ((epoch as u64) << 20));
    for i in (1..views).rev() {
        let j = rng.random_range(0..=i);
        order.swap(i, j);
    }
    order[slot]
}

pub(crate) fn iteration_rng(seed: u64, iteration: u32, stream: u64) -> rand_pcg::Pcg64 {
    rand_pcg::Pcg64::seed_from_u64(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ ((iteration as u64) << 8) ^ stream)
}

/// Scratch buffers reused across iterations (no allocation per iteration once sized).
#[derive(Default)]
struct Scratch {
    gt: Vec<[f32; 3]>,
    grads: RenderGrads,
    ssim: Ssim,
    normal: NormalConsistency,
    init: InitPass,
    v_features: Vec<f32>,
    /// Edge-aware normal smoothness of stage nvs and its gradient image.
    smooth: loss::EdgeAwareSmoothness,
    v_map: Vec<f32>,
    /// The forward's per-pixel hits, replayed by the backward (buffers reused).
    recorder: raster::HitRecorder,
}

/// Losses of one iteration (unweighted values).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct Losses {
    pub total: f32,
    pub l1: f32,
    pub dssim: f32,
    pub mask: f32,
    pub distortion: f32,
    pub normal: f32,
    pub psnr: f32,
    /// Edge-aware smoothness of the rendered normal in stage nvs (0 while off).
    pub smooth_normal: f32,
    /// Spread of the blended normals (0 while off).
    pub normal_dispersion: f32,
    /// Mean binary entropy of the surfel opacities (0 while the regulariser is off).
    pub opacity_entropy: f32,
    /// Mean SH energy beyond the DC term (0 while the penalty is off).
    pub sh_rest: f32,
    /// Stage `init` only.
    pub init: InitLosses,
}

/// One nvs iteration on view `view` with background `bg`: forward, losses, backward. Returns
/// the losses; gradients are accumulated into `v_surfels` and densification statistics.
#[allow(clippy::too_many_arguments)]
fn iterate(
    cfg: &TrainConfig,
    state: &mut NvsState,
    images: &TrainImages,
    view: usize,
    bg: [f32; 3],
    scratch: &mut Scratch,
    v_surfels: &mut SurfelGrads,
    times: &mut TimeSplit,
) -> Losses {
    let iteration = state.iteration;
    let cam = &images.cameras[view];
    let (w, h) = (cam.width as usize, cam.height as usize);
    let n = w * h;
    let use_dist = cfg.lambda_dist > 0.0 && iteration >= cfg.at(cfg.dist_from);
    let use_normal = cfg.lambda_normal > 0.0 && iteration >= cfg.at(cfg.normal_from);
    let smooth_normal = state.light.is_some() && cfg.lambda_smooth_normal > 0.0;
    let smooth_normal_nvs =
        state.light.is_none() && cfg.lambda_smooth_normal_nvs > 0.0 && iteration >= cfg.at(cfg.normal_from);
    let use_dispersion = cfg.lambda_normal_dispersion > 0.0 && iteration >= cfg.at(cfg.normal_from);
    let settings = RasterSettings {
        window: cfg.window,
        filter_inv_square: cfg.filter_inv_square,
        two_sided: cfg.two_sided,
        background: bg,
        outputs: Outputs {
            colour: true,
            depth: use_normal && cfg.depth_ratio < 1.0,
            median_depth: use_normal && cfg.depth_ratio > 0.0,
            normal: use_normal || smooth_normal || use_dispersion || smooth_normal_nvs,
            distortion: use_dist,
            ..Outputs::none()
        },
        // AbsGS's statistic only while densification can use it.
        abs_centre_gradient: cfg.densify_abs_grad_threshold > 0.0 && iteration < cfg.at(cfg.densify_until),
        ..RasterSettings::default()
    };
    let t0 = Instant::now();
    // Stage init: the per-surfel split-sum PBR, rasterised as features (taken out of the
    // scratch for the iteration so the pass can be borrowed mutably meanwhile).
    if let Some(light) = &state.light {
        scratch.init.shade(cfg, &state.surfels, light, cam);
    }
    let feature_rows = std::mem::take(&mut scratch.init.shading.features);
    let features = state.light.as_ref().map(|_| Features { data: &feature_rows, channels: pbr_init::CHANNELS });
    let ts = Instant::now();
    times.shading += (ts - t0).as_secs_f64();
    let (out, mut fwd) = scratch.recorder.render(&state.surfels, cam, &settings, features);
    let t1 = Instant::now();
    times.raster_forward += (t1 - ts).as_secs_f64();

    let rgb = &images.rgb[view];
    let alpha = &images.alpha[view];
    scratch.gt.clear();
    scratch.gt.extend(rgb.iter().zip(alpha).map(|(c, &a)| [0, 1, 2].map(|k| c[k] * a + bg[k] * (1.0 - a))));
    let g = &mut scratch.grads;
    let reset = |v: &mut Vec<f32>, on: bool| {
        v.clear();
        if on {
            v.resize(n, 0.0);
        }
    };
    g.v_colour.clear();
    g.v_colour.resize(n, [0.0; 3]);
    reset(&mut g.v_alpha, cfg.lambda_mask > 0.0 || use_dispersion);
    reset(&mut g.v_depth, use_normal && cfg.depth_ratio < 1.0);
    reset(&mut g.v_median_depth, use_normal && cfg.depth_ratio > 0.0);
    reset(&mut g.v_distortion, use_dist);
    g.v_normal.clear();
    if use_normal || smooth_normal || use_dispersion || smooth_normal_nvs {
        g.v_normal.resize(n, [0.0; 3]);
    }
    g.v_features.clear();
    if features.is_some() {
        g.v_features.resize(n * pbr_init::CHANNELS, 0.0);
        if g.v_alpha.is_empty() {
            g.v_alpha.resize(n, 0.0);
        }
    }
    let mut losses = Losses::default();
    let lambda = cfg.lambda_dssim;
    losses.l1 = loss::l1_rgb(&out.colour, &scratch.gt, None, 1.0 - lambda, &mut g.v_colour);
    losses.dssim = if lambda > 0.0 {
        scratch.ssim.dssim_loss(&out.colour, &scratch.gt, w, h, lambda, &mut g.v_colour)
    } else {
        0.0
    };
    losses.total = (1.0 - lambda) * losses.l1 + lambda * losses.dssim;
    if cfg.lambda_mask > 0.0 {
        losses.mask = loss::mask_bce(&out.alpha, alpha, cfg.lambda_mask, &mut g.v_alpha);
        losses.total += cfg.lambda_mask * losses.mask;
    }
    if use_dist {
        // Mean over pixels of GT-alpha-weighted distortion.
        let inv = 1.0 / n as f32;
        let mut sum = 0.0f64;
        for i in 0..n {
            sum += (out.distortion[i] * alpha[i]) as f64;
            g.v_distortion[i] = cfg.lambda_dist * alpha[i] * inv;
        }
        losses.distortion = (sum / n as f64) as f32;
        losses.total += cfg.lambda_dist * losses.distortion;
    }
    if use_normal {
        // 2DGS's surface depth (1 − r)·expected + r·median.
        losses.normal = scratch.normal.loss_mixed_depth(
            cam,
            (&out.depth, &out.median_depth, cfg.depth_ratio),
            &out.normal,
            Some(&out.alpha),
            Some(alpha),
            cfg.lambda_normal,
            (&mut g.v_depth, &mut g.v_median_depth),
            &mut g.v_normal,
        );
        losses.total += cfg.lambda_normal * losses.normal;
    }
    if smooth_normal_nvs {
        scratch.v_map.clear();
        scratch.v_map.resize(n * 3, 0.0);
        let v = scratch.smooth.loss(
            out.normal.as_flattened(),
            3,
            &scratch.gt,
            w,
            h,
            Some(alpha),
            cfg.lambda_smooth_normal_nvs,
            &mut scratch.v_map,
        );
        losses.smooth_normal = v;
        losses.total += cfg.lambda_smooth_normal_nvs * v;
        for (d, s) in g.v_normal.as_flattened_mut().iter_mut().zip(&scratch.v_map) {
            *d += s;
        }
    }
    if use_dispersion {
        losses.normal_dispersion = loss::normal_dispersion(
            &out.normal,
            &out.alpha,
            cfg.lambda_normal_dispersion,
            &mut g.v_normal,
            &mut g.v_alpha,
        );
        losses.total += cfg.lambda_normal_dispersion * losses.normal_dispersion;
    }
    if state.light.is_some() {
        losses.total += scratch.init.image_losses(cfg, &out, &scratch.gt, alpha, bg, g, &mut losses.init);
    }
    losses.psnr = loss::psnr(&out.colour, &scratch.gt);
    let t2 = Instant::now();
    times.losses += (t2 - t1).as_secs_f64();

    let v_features = if features.is_some() {
        scratch.v_features.clear();
        scratch.v_features.resize(state.surfels.len() * pbr_init::CHANNELS, 0.0);
        Some(scratch.v_features.as_mut_slice())
    } else {
        None
    };
    let bwd =
        raster::render_backward(&state.surfels, cam, &settings, features, &fwd, &scratch.grads, v_surfels, v_features);
    if state.stats.len() == state.surfels.len() {
        state.stats.add_view(&bwd.v_mean2d, &bwd.v_mean2d_abs, &fwd.radii);
    }
    scratch.recorder.recycle(&mut fwd);
    let t3 = Instant::now();
    times.raster_backward += (t3 - t2).as_secs_f64();
    if let Some(light) = &state.light {
        let consistency = iteration >= cfg.at(cfg.simple_rc_from);
        losses.total += scratch.init.backward(
            cfg,
            &state.surfels,
            light,
            cam,
            &scratch.v_features,
            consistency,
            v_surfels,
            &mut losses.init,
        );
        times.shading += t3.elapsed().as_secs_f64();
    }
    scratch.init.shading.features = feature_rows;
    losses
}

pub(crate) fn progress_bar(prefix: &'static str, total: u32, start: u32) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(total as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{prefix} {bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_prefix(prefix);
    bar.set_position(start as u64);
    bar
}

/// Keep the metrics lines up to `iteration` (after a resume) and return an appender.
pub(crate) fn open_metrics(path: &Path, keep_until: u32) -> anyhow::Result<std::fs::File> {
    let kept: Vec<String> = std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter(|l| {
            serde_json::from_str::<serde_json::Value>(l)
                .ok()
                .and_then(|v| v.get("iteration").and_then(|i| i.as_u64()))
                .is_some_and(|i| i <= keep_until as u64)
        })
        .map(|l| format!("{l}\n"))
        .collect();
    crate::io::atomic::write_atomic(path, kept.concat().as_bytes())?;
    std::fs::OpenOptions::new().append(true).open(path).with_context(|| format!("{}: cannot append", path.display()))
}

/// Run (or resume) the nvs stage into `cfg.out`.
pub fn run(cfg: &TrainConfig, dataset: &Dataset, show_progress: bool) -> anyhow::Result<StageSummary> {
    run_until(cfg, dataset, show_progress, None)
}

/// As [`run`], stopping as if interrupted after iteration `stop_after` (tests of `--resume`).
pub fn run_until(
    cfg: &TrainConfig,
    dataset: &Dataset,
    show_progress: bool,
    stop_after: Option<u32>,
) -> anyhow::Result<StageSummary> {
    run_stage(cfg, dataset, show_progress, stop_after, GeometryStage::Nvs)
}

/// Run (or resume) a geometry stage (`nvs` or `init`) into `cfg.out`, stopping as if
/// interrupted after iteration `stop_after` when given.
pub fn run_stage(
    cfg: &TrainConfig,
    dataset: &Dataset,
    show_progress: bool,
    stop_after: Option<u32>,
    stage: GeometryStage,
) -> anyhow::Result<StageSummary> {
    let images = TrainImages::load(dataset, Split::Train)?;
    if images.cameras.is_empty() {
        anyhow::bail!("{}: the dataset has no training views", dataset.root.display());
    }
    let ckpt_path = stage.checkpoint(&cfg.out);
    let mut state = if cfg.resume && ckpt_path.is_file() {
        let c = Checkpoint::load(&ckpt_path)?;
        let state = NvsState::from_checkpoint(&ckpt_path, &c, cfg)?;
        if state.stage() != stage {
            anyhow::bail!("{}: not an {}-stage checkpoint", ckpt_path.display(), stage.name());
        }
        state
    } else {
        if cfg.resume {
            tracing::warn!("--resume: no checkpoint in {}, starting fresh", cfg.out.display());
        }
        NvsState::new(cfg, dataset, &images, stage)?
    };
    interrupt::install();
    let metrics_path = stage.metrics(&cfg.out);
    let mut metrics = open_metrics(&metrics_path, state.iteration)?;
    let schedule = ExponLr::position(state.extent, cfg.iters as u64);
    let schedule = ExponLr {
        lr_init: cfg.lr_position_init * cfg.position_lr_factor() * state.extent,
        lr_final: cfg.lr_position_final * cfg.position_lr_factor() * state.extent,
        ..schedule
    };
    let densify_cfg = DensifyConfig {
        grad_threshold: cfg.densify_grad_threshold,
        abs_grad_threshold: cfg.densify_abs_grad_threshold,
        min_opacity: cfg.prune_opacity,
        percent_dense: cfg.percent_dense,
        ..DensifyConfig::default()
    };
    let bar = progress_bar(stage.name(), cfg.iters, state.iteration);
    if !show_progress {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let mut scratch = Scratch::default();
    let mut v_surfels = state.surfels.zeros_like();
    let mut times = TimeSplit::default();
    let started = Instant::now();
    let first_iteration = state.iteration;
    let mut last = Losses::default();
    let mut interrupted = false;
    // Surfels need a few densification rounds after a reset to regain opacity before the
    // prune, so short schedules keep the reset at least 5 densification intervals apart.
    let reset_every = cfg.at(cfg.opacity_reset_every).max(5 * cfg.densify_every).max(1);
    let sh_every = cfg.at(cfg.sh_up_every).max(1);
    while state.iteration < cfg.iters {
        if interrupt::requested() || stop_after.is_some_and(|s| state.iteration >= s) {
            interrupted = true;
            break;
        }
        state.iteration += 1;
        let it = state.iteration;
        let t_iter = Instant::now();
        state.surfels.sh_degree = (it / sh_every).min(3);
        let mut rng = iteration_rng(cfg.seed, it, 1);
        let bg = match cfg.background {
            Background::Random => [rng.random::<f32>(), rng.random::<f32>(), rng.random::<f32>()],
            Background::White => [1.0; 3],
            Background::Black => [0.0; 3],
        };
        let view = view_for_iteration(cfg.seed, it, images.cameras.len());
        if v_surfels.len() != state.surfels.len() {
            v_surfels = state.surfels.zeros_like();
        } else {
            v_surfels.fill_zero();
        }
        v_surfels.sh_degree = state.surfels.sh_degree;
        let mut split = TimeSplit::default();
        last = iterate(cfg, &mut state, &images, view, bg, &mut scratch, &mut v_surfels, &mut split);
        if !last.total.is_finite() {
            anyhow::bail!(
                "iteration {it}: the loss is {} (diverged); lower the learning rates or check the data",
                last.total
            );
        }

        if cfg.lambda_opacity_entropy > 0.0 && it >= cfg.at(cfg.opacity_entropy_from) {
            let e = loss::opacity_entropy(
                &state.surfels.opacity_logits,
                cfg.lambda_opacity_entropy,
                &mut v_surfels.opacity_logits,
            );
            last.opacity_entropy = e;
            last.total += cfg.lambda_opacity_entropy * e;
        }
        if cfg.lambda_sh_rest > 0.0 {
            let e =
                loss::sh_rest_energy(&state.surfels.sh, state.surfels.sh_degree, cfg.lambda_sh_rest, &mut v_surfels.sh);
            last.sh_rest = e;
            last.total += cfg.lambda_sh_rest * e;
        }

        let t_opt = Instant::now();
        state.adam.lr.means = schedule.at(it as u64);
        state.adam.step(&mut state.surfels, &v_surfels);
        if let Some(light) = &mut state.light {
            light.step(&scratch.init.v_env_log);
        }
        split.optimiser += t_opt.elapsed().as_secs_f64();

        let t_dens = Instant::now();
        if it < cfg.at(cfg.densify_until) {
            if it > cfg.at(cfg.densify_from) && it % cfg.densify_every == 0 {
                let max_screen = (it > reset_every).then_some(20.0);
                let mut drng = iteration_rng(cfg.seed, it, 2);
                if state.surfels.len() < cfg.max_surfels {
                    densify::densify_and_prune(
                        &mut state.surfels,
                        &mut state.adam,
                        &mut state.stats,
                        &densify_cfg,
                        state.extent,
                        max_screen,
                        &mut drng,
                    );
                } else {
                    // At the budget: only prune (no clone/split) so the count stays bounded.
                    let cfg_prune = DensifyConfig { grad_threshold: f32::INFINITY, ..densify_cfg };
                    densify::densify_and_prune(
                        &mut state.surfels,
                        &mut state.adam,
                        &mut state.stats,
                        &cfg_prune,
                        state.extent,
                        max_screen,
                        &mut drng,
                    );
                }
            }
            if it % reset_every == 0 && cfg.opacity_reset_cap < 1.0 {
                densify::reset_opacity(&mut state.surfels, &mut state.adam, cfg.opacity_reset_cap);
            }
        }
        // The entropy regulariser drives most interior surfels to opacity ≈ 0 after the last
        // densification; prune those as densification would, so later stages do not carry them.
        if cfg.lambda_opacity_entropy > 0.0
            && it >= cfg.at(cfg.opacity_entropy_from)
            && (it % cfg.densify_every == 0 || it == cfg.iters)
        {
            let remove: Vec<bool> =
                state.surfels.opacity_logits.iter().map(|&x| sigmoid(x) < cfg.prune_opacity).collect();
            if remove.iter().any(|&r| r) {
                densify::prune_points(&mut state.surfels, &mut state.adam, &mut state.stats, &remove);
            }
        }
        split.densify += t_dens.elapsed().as_secs_f64();
        split.other = t_iter.elapsed().as_secs_f64()
            - (split.shading
                + split.raster_forward
                + split.raster_backward
                + split.losses
                + split.optimiser
                + split.densify);
        times.shading += split.shading;
        times.raster_forward += split.raster_forward;
        times.raster_backward += split.raster_backward;
        times.losses += split.losses;
        times.optimiser += split.optimiser;
        times.densify += split.densify;
        times.other += split.other.max(0.0);

        if it % cfg.log_every == 0 || it == cfg.iters {
            let mut line = serde_json::json!({
                "stage": stage.name(), "iteration": it, "loss": last.total, "l1": last.l1, "dssim": last.dssim,
                "mask": last.mask, "distortion": last.distortion, "normal": last.normal, "psnr": last.psnr,
                "opacity_entropy": last.opacity_entropy, "normal_dispersion": last.normal_dispersion,
                "sh_rest": last.sh_rest,
                "smooth_normal": last.smooth_normal,
                "surfels": state.surfels.len(), "seconds": started.elapsed().as_secs_f64(),
            });
            if let (Some(obj), GeometryStage::Init) = (line.as_object_mut(), stage) {
                let i = &last.init;
                for (key, v) in [
                    ("psnr_pbr", i.psnr_pbr),
                    ("pbr_l1", i.pbr_l1),
                    ("pbr_dssim", i.pbr_dssim),
                    ("simple_rc", i.simple_rc),
                    ("smooth", i.smooth),
                    ("env_prior", i.env_prior),
                ] {
                    obj.insert(key.into(), v.into());
                }
            }
            writeln!(metrics, "{line}").with_context(|| format!("writing {}", metrics_path.display()))?;
            let pbr =
                if stage == GeometryStage::Init { format!(" pbr {:.2}", last.init.psnr_pbr) } else { String::new() };
            bar.set_message(format!(
                "loss {:.4} psnr {:.2}{pbr} surfels {}",
                last.total,
                last.psnr,
                state.surfels.len()
            ));
        }
        bar.set_position(it as u64);
        if cfg.checkpoint_every > 0 && it % cfg.checkpoint_every == 0 && it < cfg.iters {
            state.to_checkpoint(cfg).save(&ckpt_path)?;
        }
    }
    bar.finish_and_clear();
    state.to_checkpoint(cfg).save(&ckpt_path)?;
    if !interrupted {
        write_ply_trained(&cfg.out.join("point_cloud.ply"), &state.surfels, Some(cfg.filter_inv_square))?;
        if let Some(light) = &state.light {
            light.env().save(&cfg.out.join("envmap.exr"))?;
        }
    }
    Ok(StageSummary {
        iterations: state.iteration,
        iterations_run: state.iteration - first_iteration,
        surfels: state.surfels.len(),
        seconds: started.elapsed().as_secs_f64(),
        last_psnr: last.psnr,
        time_split: times,
        interrupted,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn view_order_is_a_permutation_per_epoch() {
        let mut seen = vec![0; 7];
        for it in 1..=7 {
            seen[view_for_iteration(3, it, 7)] += 1;
        }
        assert!(seen.iter().all(|&c| c == 1));
        assert_ne!(
            (1..=7).map(|it| view_for_iteration(3, it, 7)).collect::<Vec<_>>(),
            (8..=14).map(|it| view_for_iteration(3, it, 7)).collect::<Vec<_>>()
        );
    }
}
