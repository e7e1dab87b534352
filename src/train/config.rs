//! The training configuration: one struct that is both the `radiogs train` arguments and the
//! serde record written to `RUN/config.toml`, so every run can be reproduced.
//!
//! Precedence: built-in defaults < `--config F.toml` < flags given on the command line.
//! Iteration-based schedules are written for the 2DGS reference length (30k) and scaled by
//! `iters / 30000` (see [`TrainConfig::at`]).

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    /// Plain 2DGS: geometry and SH radiance (novel-view synthesis, the geometry check).
    Nvs,
    /// RadioGS stage 1: split-sum PBR + simplified consistency + 2DGS losses.
    Init,
    /// RadioGS stage 2: Monte Carlo PBR with traced light, full radiometric consistency.
    Inverse,
    /// Every stage in order.
    All,
}

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Background {
    /// A random colour per iteration (teaches alpha; the default for RGBA data).
    Random,
    White,
    Black,
}

/// How the PBR stages' traced rays (visibility, indirect light, consistency) treat back faces.
#[derive(clap::ValueEnum, Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TraceBackFaces {
    /// Culled: normals point outward (RadioGS). What runs saved before the setting traced.
    #[default]
    Cull,
    /// Composited with the normal flipped (plain 2DGS).
    TwoSided,
    /// As two-sided, but a back face adds no radiance: it only blocks the light behind it.
    Dark,
    /// Culled, except the surfels no training camera saw when the inverse stage oriented them
    /// (their orientation is a guess): their back faces block as `dark` ones do.
    DarkUnseen,
}

/// How the consistency step picks its B surfels each iteration.
#[derive(clap::ValueEnum, Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RcOrder {
    /// Drawn uniformly at random with replacement, as published. What runs saved before the
    /// setting used.
    #[default]
    Random,
    /// Every surfel once per pass, B at a time, in one random order (drawn without replacement).
    /// With `rc_rays` = `pbr_samples` the traced rows refresh the cache in that order, so the
    /// cache's own re-tracing only catches rows older than `cache_every`.
    Sweep,
}

/// How the inverse stage's PBR colour gets its specular lobe.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Specular {
    /// Monte Carlo over the cached S directions, like the diffuse lobe (the published method).
    Mc,
    /// Split-sum: the env prefiltered by roughness at the reflection direction × the GGX LUT,
    /// scaled by the surfel's cached visibility, plus its mean indirect light for the occluded
    /// part. The diffuse lobe stays Monte Carlo with traced visibility and indirect light.
    SplitSum,
    /// GGX importance sampling: `specular_rays` directions per shaded surfel drawn for the
    /// current view and traced every iteration (visibility and indirect light), the env read
    /// at full resolution. Not in the published method; for glossy objects, whose lobes the
    /// shared cached directions miss.
    Traced,
}

/// Largest `--resolution` factor (beyond it a value is more likely a width meant as 3DGS's
/// `-r 1600`, which radiogs does not take).
pub const MAX_DOWNSCALE: u32 = 16;

/// Train surfels from a dataset of posed RGBA images.
#[derive(clap::Args, Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Dataset folder (Blender/NeRF-synthetic or TensoIR layout).
    #[arg(long)]
    pub data: PathBuf,
    /// Run folder to write (config, checkpoints, metrics, PLY).
    #[arg(long)]
    pub out: PathBuf,
    /// Which stage(s) to run.
    #[arg(long, value_enum, default_value_t = Stage::Nvs)]
    pub stage: Stage,
    /// Train on the images shrunk by this factor (box filter; cameras scaled to match), as
    /// 3DGS/2DGS's `-r 2|4|8`: 800² NeRF-synthetic or TensoIR views train at 200² with `-r 4`.
    /// `eval`, `render` and `relight` use the run's factor unless told otherwise.
    #[arg(short = 'r', long, default_value_t = 1)]
    pub resolution: u32,
    /// Iterations of the stage (the 2DGS schedule is scaled to this length).
    #[arg(long, default_value_t = 7000)]
    pub iters: u32,
    /// A TOML file of settings (flags given on the command line win).
    #[arg(long)]
    #[serde(skip)]
    pub config: Option<PathBuf>,
    /// Continue from the run's latest checkpoint.
    #[arg(long)]
    #[serde(skip)]
    pub resume: bool,
    /// Train afresh into a run folder that already holds a trained run, replacing its files
    /// (without this such a folder is refused: continue it with --resume, or pick a new --out).
    #[arg(long)]
    #[serde(skip)]
    pub overwrite: bool,
    /// Random seed: same seed, data and settings give the same run.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Initial surfel count (random points inside the visual hull of the masks).
    #[arg(long, default_value_t = 20000)]
    pub init_points: usize,
    /// Optional PLY to start from instead of random points.
    #[arg(long)]
    pub init_ply: Option<PathBuf>,
    /// Per-pixel sorted window size K of the rasteriser (1 = plain 2DGS order).
    #[arg(long, default_value_t = 8)]
    pub window: usize,
    /// 1/σ² (px⁻²) of the rasteriser's screen-space fallback filter ρ₂ = f·|μ₂D − pixel|².
    /// 2DGS uses 2 (σ = 0.71 px); 8 (σ = 0.35 px) measured better normals and views on both
    /// shared scenes and the demo (BENCHMARKS.md, session 18). A run whose config predates the
    /// setting loads as 2, the value it was trained with (a `--config` file without it: 8).
    #[arg(long, default_value_t = 8.0)]
    #[serde(default = "crate::raster::filter_inv_square_2dgs")]
    pub filter_inv_square: f32,
    /// Two-sided surfels (2DGS) instead of back-face culling with outward normals.
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    pub two_sided: bool,
    /// Background behind the object in training.
    #[arg(long, value_enum, default_value_t = Background::Random)]
    pub background: Background,

    // Learning rates (2DGS defaults; positions scaled by the scene extent).
    #[arg(long, default_value_t = 1.6e-4)]
    pub lr_position_init: f32,
    #[arg(long, default_value_t = 1.6e-6)]
    pub lr_position_final: f32,
    /// Multiply both position rates by 30000 / iters (at most 10) in the nvs and init stages:
    /// 2DGS's rates are for 30k iterations, and a shorter run at them cannot move a surfel as
    /// far (on cornell the visual hull's surfels then settle as a cove 5–7 cm in front of the
    /// white floor–wall crease). 3000 iterations on cornell: normal MAE 8.04° at × 1, 7.66° at
    /// × 3, 7.16° at × 10, 8.00° at × 30 (BENCHMARKS.md, session 24). Runs saved before the
    /// setting load as false, the rates they were trained with (a `--config` file without it:
    /// true).
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    #[serde(default)]
    pub scale_position_lr: bool,
    /// SH learning rate: the DC term; the view-dependent terms in the nvs stage take 1/20 of it.
    #[arg(long, default_value_t = 2.5e-3)]
    pub lr_sh: f32,
    /// Learning rate of the SH's view-dependent terms in the inverse stage [lr_sh / 20]: the
    /// radiometric consistency reshapes a surfel's radiance in directions no camera saw
    /// through these terms alone.
    #[arg(long, default_value_t = 1.25e-4)]
    pub lr_sh_rest_inverse: f32,
    #[arg(long, default_value_t = 0.05)]
    pub lr_opacity: f32,
    #[arg(long, default_value_t = 5e-3)]
    pub lr_scale: f32,
    #[arg(long, default_value_t = 1e-3)]
    pub lr_rotation: f32,
    #[arg(long, default_value_t = 5e-3)]
    pub lr_albedo: f32,
    #[arg(long, default_value_t = 5e-3)]
    pub lr_roughness: f32,

    // Losses.
    /// Weight of D-SSIM in the image loss (1 − λ)·L1 + λ·D-SSIM.
    #[arg(long, default_value_t = 0.2)]
    pub lambda_dssim: f32,
    /// Depth distortion weight (normalised depth) and its start iteration (of 30k).
    #[arg(long, default_value_t = 1000.0)]
    pub lambda_dist: f32,
    #[arg(long, default_value_t = 3000)]
    pub dist_from: u32,
    /// Normal consistency weight of stages nvs and init (the inverse stage's is
    /// `lambda_normal_inverse`) and its start iteration (of 30k).
    #[arg(long, default_value_t = 0.05)]
    pub lambda_normal: f32,
    #[arg(long, default_value_t = 7000)]
    pub normal_from: u32,
    /// Weight of the spread of the normals blended into each pixel, α − |Σ w n|²/α (stages nvs
    /// and init, from `normal_from`; 0 = off): 2DGS's normal consistency only sees the blended
    /// normal, so surfels tilted both ways about a flat surface go unpunished, while the PBR
    /// shades each surfel with its own normal.
    #[arg(long, default_value_t = 0.0)]
    pub lambda_normal_dispersion: f32,
    /// Edge-aware smoothness (L1 of the Sobel gradient, weighted by exp(−|∇I|)) of the rendered
    /// normal in stage nvs, from `normal_from` (0 = off; stages init and inverse use
    /// `lambda_smooth_normal`): textureless planes are otherwise free to bend.
    #[arg(long, default_value_t = 0.0)]
    pub lambda_smooth_normal_nvs: f32,
    /// The depth the normal consistency of stages nvs and init differentiates, as 2DGS's
    /// `depth_ratio`: (1 − r) × expected depth + r × median depth (0: expected, 1: median).
    #[arg(long, default_value_t = 0.0)]
    pub depth_ratio: f32,
    /// Mask (alpha BCE) weight.
    #[arg(long, default_value_t = 0.1)]
    pub lambda_mask: f32,
    /// Binary-entropy regulariser on the surfel opacities (stages nvs and init; 0 = off) and
    /// its start iteration (of 30k; default: where densification and opacity resets end, so it
    /// does not fight a reset). Makes the surface layer opaque instead of translucent over
    /// interior surfels.
    #[arg(long, default_value_t = 0.0)]
    pub lambda_opacity_entropy: f32,
    #[arg(long, default_value_t = 15000)]
    pub opacity_entropy_from: u32,
    /// Weight of the view-dependence penalty in stage nvs: mean energy of the surfels' SH
    /// coefficients beyond the DC term (textureless surfaces; 0 = off).
    #[arg(long, default_value_t = 0.0)]
    pub lambda_sh_rest: f32,

    // Density control (2DGS defaults, iterations of 30k).
    #[arg(long, default_value_t = 500)]
    pub densify_from: u32,
    #[arg(long, default_value_t = 15000)]
    pub densify_until: u32,
    #[arg(long, default_value_t = 100)]
    pub densify_every: u32,
    #[arg(long, default_value_t = 3000)]
    pub opacity_reset_every: u32,
    /// An opacity reset lowers every opacity to at most this (1 = no reset, keeping the
    /// schedule that starts the huge-surfel prune after the first interval). 2DGS/3DGS use
    /// 0.01; after such a reset the faint surfels in front of a textureless wall regain
    /// opacity first and cornell's back wall ends 6 cm in front of the truth. 0.2: nvs normal
    /// MAE 7.72 → 6.84° on cornell, 3.28 → 3.27° on spheres, with `sh_up_every` 5000
    /// (BENCHMARKS.md, sessions 31–32).
    /// A run whose config predates the setting loads as 0.01 (a `--config` file without it: 0.2).
    #[arg(long, default_value_t = 0.2)]
    #[serde(default = "opacity_reset_cap_2dgs")]
    pub opacity_reset_cap: f32,
    #[arg(long, default_value_t = 2e-4)]
    pub densify_grad_threshold: f32,
    /// Split large surfels on AbsGS's homodirectional gradient (per-pixel |∂L/∂μ₂D| summed)
    /// at this threshold instead of on the plain gradient (AbsGS, PGSR: 8e-4); 0 = off (2DGS).
    #[arg(long, default_value_t = 0.0)]
    pub densify_abs_grad_threshold: f32,
    #[arg(long, default_value_t = 0.01)]
    pub percent_dense: f32,
    #[arg(long, default_value_t = 0.05)]
    pub prune_opacity: f32,
    /// Upper bound on the surfel count (densification stops adding above it).
    #[arg(long, default_value_t = 200_000)]
    pub max_surfels: usize,
    /// Raise the active SH degree every this many iterations (of 30k), up to 3. 2DGS's 1000,
    /// scaled into our short runs, reaches degree 3 at a tenth of the run, before the geometry
    /// settles; view-dependent colour then absorbs the shading parallax that tells a white
    /// corner's crease from a cove. 5000 (sessions 16–31: degree 3 at half the run) gave
    /// cornell 10.05 → 8.86°; 10000 (degree 1 at a third, 2 at two thirds, 3 only for the last
    /// iteration), with the 0.2 opacity-reset cap: cornell nvs normal MAE 6.84 → 5.91° (seed 1
    /// 5.88°) at −0.15 dB, glossy spheres 3.27 → 3.41° at −1.0 dB (BENCHMARKS.md, session 32).
    /// 5000 is the better choice for the views of glossy objects.
    #[arg(long, default_value_t = 10000)]
    pub sh_up_every: u32,

    // Stage `init` (RadioGS stage 1, DESIGN §1): the nvs losses and schedule plus these.
    /// Simplified radiometric consistency L1(SH_i, L_pbr,i) of stage 1 [0.1] and its start
    /// iteration (of 30k; the published 2000 of 40k).
    #[arg(long, default_value_t = 0.1)]
    pub lambda_simple_rc: f32,
    #[arg(long, default_value_t = 1500)]
    pub simple_rc_from: u32,

    // Inverse rendering (RadioGS stage 2, DESIGN §1). Published values in brackets; the CPU
    // defaults are chosen by measuring quality against time (BENCHMARKS.md).
    /// Iterations of the inverse stage [20000] (`--iters` sets the nvs stage). 3000 against
    /// 2000 (session 60): cornell relights 0.3–0.6 dB better and its albedo +0.6–0.7 dB, spheres
    /// relights the same with 0.9 dB less albedo, at 1.5 × the stage's time; 4000 gains cornell
    /// 0.15 dB more but costs spheres 0.3 dB of relighting (BENCHMARKS.md).
    #[arg(long, default_value_t = 3000)]
    pub inverse_iters: u32,
    /// Incident directions S per surfel in the cache and in the PBR render. With the env
    /// read at full resolution, 16 leaves each surfel's estimate blotchy; 64 gains albedo,
    /// PBR fit and relighting on both shared scenes (BENCHMARKS.md, session 54).
    #[arg(long, default_value_t = 64)]
    pub pbr_samples: usize,
    /// Incident-cache age limit [100: the published full refresh every 100 iterations]: every
    /// cache_every/4 iterations the rows that would otherwise grow older are re-traced; rows
    /// the consistency step traced meanwhile are fresh and kept. 200 measured as good as 100
    /// at S = 64 and halves the re-tracing (BENCHMARKS.md, session 54).
    #[arg(long, default_value_t = 200)]
    pub cache_every: u32,
    /// Radiometric consistency: surfels per iteration [2048]. 256 halves the consistency step's
    /// time (the inverse stage 8–12 % faster) but costs 0.1–0.2 dB of relighting on both shared
    /// scenes and of albedo on both cornells (BENCHMARKS.md, session 89).
    #[arg(long, default_value_t = 512)]
    pub rc_surfels: usize,
    /// Radiometric consistency: traced rays per surfel [64]; equal to `pbr_samples` lets the
    /// traced rows overwrite the cache. Under a learned sun, 16 rays usually miss it, and the L1
    /// residual fits that skewed target's median (5–8 % under its mean), which keeps lifting the
    /// indirect light as the stage runs; 32 rays do not, for 11 % more stage time
    /// (BENCHMARKS.md, sessions 74–75).
    #[arg(long, default_value_t = 32)]
    pub rc_rays: usize,
    /// How the consistency step picks its surfels: `random` (each iteration B uniform draws, as
    /// published) or `sweep` (each surfel once per pass of N/B iterations, in one random order; with
    /// `rc_rays` = `pbr_samples` its traced rows then refresh the cache, whose own re-tracing
    /// only catches rows older than `cache_every`). `--rc-order sweep --rc-surfels 256
    /// --rc-rays 64` traces as many rays as the default and leaves the cache almost nothing to
    /// re-trace: the inverse stage 11–13 % faster on shared spheres (51k surfels, 256 × 200 ≥ N),
    /// for −0.10 / −0.20 dB of relighting, −0.10 dB PBR, +0.11 dB albedo and +0.51 dB indirect
    /// light there (BENCHMARKS.md, session 92). Runs saved before the setting load as `random`.
    #[arg(long, value_enum, default_value_t = RcOrder::Random)]
    #[serde(default)]
    pub rc_order: RcOrder,
    /// λ_rc [0.2]; 0 gives the ablation "without radiometric consistency".
    #[arg(long, default_value_t = 0.2)]
    pub lambda_rc: f32,
    /// Weight of the PBR image loss (L1 + 0.2·D-SSIM).
    #[arg(long, default_value_t = 1.0)]
    pub lambda_pbr: f32,
    /// Weight of the SH image loss in the inverse stage (0.8·L1 + 0.2·D-SSIM).
    #[arg(long, default_value_t = 1.0)]
    pub lambda_sh_image: f32,
    /// Mask weight in the inverse stage [0.02].
    #[arg(long, default_value_t = 0.02)]
    pub lambda_mask_inverse: f32,
    /// Normal consistency weight in the inverse stage [0.2; published 0.05, the nvs stage's
    /// `lambda_normal`]. The inverse stage's shading turns the surfels of glossy objects away
    /// from their depth's normal (cornell's glossy sphere 7.7° → 11.1° mean error); at 0.2
    /// cornell's normal MAE improves 5.53 → 5.26° (BENCHMARKS.md, session 64). A run whose
    /// config predates the setting loads as 0.05.
    #[arg(long, default_value_t = 0.2)]
    #[serde(default = "lambda_normal_2dgs")]
    pub lambda_normal_inverse: f32,
    /// Edge-aware smoothness of albedo [0.2], roughness [0.1] and normal [0.5; published
    /// 0.01]. The inverse stage's shading bends the nvs normals (spheres' floor 5.2° → 7.1°);
    /// at 0.5 the normal MAE improves on both shared scenes, spheres' albedo by 0.9 dB, and
    /// relighting holds or rises (BENCHMARKS.md, session 63).
    #[arg(long, default_value_t = 0.2)]
    pub lambda_smooth_albedo: f32,
    #[arg(long, default_value_t = 0.1)]
    pub lambda_smooth_roughness: f32,
    #[arg(long, default_value_t = 0.5)]
    pub lambda_smooth_normal: f32,
    /// Non-local albedo prior [0.1; not in the published method, 0 = off]: surfels whose SH
    /// colour has the same chromaticity are pulled towards one albedo (src/train/albedo_chroma.rs;
    /// cornell: albedo +1.1 dB, relighting +1.1–1.25 dB on two seeds, spheres unchanged;
    /// BENCHMARKS.md session 33). A run whose config predates the setting loads as 0.
    #[arg(long, default_value_t = 0.1)]
    #[serde(default = "albedo_chroma_off")]
    pub lambda_albedo_chroma: f32,
    /// Cell width of that prior on the (r, g) chromaticity plane [0.015]; a surfel's target
    /// averages its cell and the 8 around it.
    #[arg(long, default_value_t = 0.015)]
    pub albedo_chroma_bin: f32,
    /// Per-channel cap on that prior's difference from its cell's mean [inf: none, plain L1]:
    /// larger differences go free, so materials of one hue but different brightness (a grey
    /// checkerboard's squares) are not pulled together. A scene-dependent trade, so off by
    /// default: at 0.1 spheres' albedo gains 0.8 dB and its relighting 0.1 dB, but cornell's
    /// loses 0.4 dB and 0.3 dB: there the uncapped tie flattens the shading that the white
    /// faces' albedo takes up in patches (BENCHMARKS.md, session 62).
    #[arg(long, default_value_t = f32::INFINITY)]
    #[serde(default = "albedo_chroma_cap_default")]
    pub albedo_chroma_cap: f32,
    /// Local albedo prior in space [0.1; not in the published method, 0 = off]: surfels within
    /// a voxel of each other are pulled towards one albedo, whichever way they face, so the two
    /// faces of a thin part share it (src/train/albedo_voxel.rs; three runs each: cornell
    /// relighting +0.7–0.9 dB, albedo +0.9–1.0 dB; spheres relighting +0.12–0.16 dB, albedo
    /// −0.16 to −0.19 dB; BENCHMARKS.md session 59). A run whose config predates the setting
    /// loads as 0.
    #[arg(long, default_value_t = 0.1)]
    #[serde(default = "albedo_voxel_off")]
    pub lambda_albedo_voxel: f32,
    /// Voxel size of that prior, as a fraction of the scene extent [0.024: 8 cm on cornell's
    /// 3.4 m]; a surfel's target averages its voxel and the 26 around it.
    #[arg(long, default_value_t = 0.024)]
    #[serde(default = "albedo_voxel_default")]
    pub albedo_voxel: f32,
    /// Per-channel cap on that prior's difference from the local mean [0.1]: larger
    /// differences (edges between materials, a checkerboard's squares) go free.
    #[arg(long, default_value_t = 0.1)]
    #[serde(default = "albedo_voxel_cap_default")]
    pub albedo_voxel_cap: f32,
    /// Treat the ground truth's saturated channels (stored 255: clipped at 1 by the dataset's
    /// view transform) as lower bounds in the PBR image loss [true]: a brighter rendering there
    /// is not an error (src/train/pbr_image.rs; BENCHMARKS.md session 36). A run whose config
    /// predates the setting loads as false.
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    #[serde(default = "clip_saturated_off")]
    pub clip_saturated: bool,
    /// White-light prior [0; published 0.01]: the L1 of each env texel's channels from their
    /// mean. It keeps the light grey where few surfels look (the ground far below the horizon,
    /// which only the objects' sides and undersides see). Off: albedo +0.07–0.36 dB and
    /// relighting +0.00–0.30 dB on all four measured scenes, indirect light within ±0.07 dB
    /// (BENCHMARKS.md, session 79). Old runs keep the value their config file holds.
    #[arg(long, default_value_t = 0.0)]
    pub lambda_white_light: f32,
    /// Env total variation [0.002; published 0.02]. Squared differences of linear radiance
    /// flatten a sun: at 0.02 the learned sun of the synthetic scenes peaks at 15 × the map's
    /// mean (the truth's: hundreds), shadows come out soft and the albedo takes them in. 0.002
    /// gains albedo (+0.1 to +0.8 dB) and normals on both shared and both synthetic scenes,
    /// relighting on three of them (cornell −0.1 / −0.2 dB; BENCHMARKS.md, session 65).
    #[arg(long, default_value_t = 0.002)]
    pub lambda_env_tv: f32,
    /// Consistency detach switches (the published method's): no gradient from the
    /// consistency term to the env [true in stage 2], the materials, the normals, the SH
    /// side (lhs) or the PBR side (rhs).
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    pub detach_env: bool,
    #[arg(long, default_value_t = false, action = clap::ArgAction::Set)]
    pub detach_material: bool,
    #[arg(long, default_value_t = false, action = clap::ArgAction::Set)]
    pub detach_normal: bool,
    #[arg(long, default_value_t = false, action = clap::ArgAction::Set)]
    pub detach_lhs: bool,
    #[arg(long, default_value_t = false, action = clap::ArgAction::Set)]
    pub detach_rhs: bool,
    /// Geometry learning rates in the inverse stage are multiplied by this [0.05]. The published
    /// 0.01 is for a 20k-iteration stage: over radiogs' 1.5–2k iterations it leaves the surfaces
    /// almost where nvs put them; 0.05 relights 0.3–0.6 dB better (BENCHMARKS.md, session 20).
    #[arg(long, default_value_t = 0.05)]
    pub geometry_lr_scale: f32,
    /// Learning rate of the env map's log radiance.
    #[arg(long, default_value_t = 0.01)]
    pub lr_env: f32,
    /// Start the inverse stage from fresh materials and light (albedo_init, roughness_init,
    /// env_init, as published); `false` keeps the albedo, roughness and light an init-stage
    /// checkpoint learned (nvs checkpoints have none: fresh either way).
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    pub fresh_materials: bool,
    /// Light first: for this many iterations at the start of the inverse stage albedo and
    /// roughness are frozen at their fresh values, so that the env (not per-surfel albedo)
    /// explains the shading that varies with the normal and the shadows (0 = off, as published).
    #[arg(long, default_value_t = 0)]
    pub light_warmup: u32,
    /// Albedo–light gauge: every this many iterations a 1-D search over s of the PBR image
    /// loss (3 training views) rescales albedo × s and env ÷ s, the direction the gradient
    /// hardly moves along (see `train::gauge`; not in the published method; measured in
    /// BENCHMARKS.md, session 13). 0 = off; off as well when the light or the albedo is held
    /// (`lr_env` or `lr_albedo` 0).
    #[arg(long, default_value_t = 100)]
    pub gauge_every: u32,
    /// Env map height H (width 2H) [64].
    #[arg(long, default_value_t = 64)]
    pub env_height: usize,
    /// Fresh materials and light at the start of the inverse stage [0.3, 0.6, 1.5].
    #[arg(long, default_value_t = 0.3)]
    pub albedo_init: f32,
    /// How much of each surfel's observed hue the fresh albedo starts with [1; the published
    /// method starts grey]: 0 = grey `albedo_init` everywhere (published); 1 = the chromaticity
    /// of its SH colour relative to the light's (read off the near-grey surfels), brightest
    /// channel at `albedo_init` (src/train/albedo_chroma.rs); near-grey surfels start grey.
    /// At 1 cornell relights 2.3–2.5 dB better and spheres 0.05–0.2 dB worse on three inverse
    /// seeds, the demo scene 0.3–0.5 dB better on two (BENCHMARKS.md sessions 56–57). Runs
    /// saved before the field existed load as 0, the start they had.
    #[arg(long, default_value_t = 1.0)]
    #[serde(default)]
    pub albedo_init_hue: f32,
    /// Fresh roughness [0.3; published 0.6]. The roughness learns little (4 % Fresnel against a
    /// light learned through the same lobes) and ends near its start; from 0.3 spheres' glossy
    /// balls end smoother than its diffuse ones (from 0.6 not), and albedo gains 0.3–0.7 dB and
    /// indirect light 0.4–0.8 dB on both shared scenes, but cornell's roughness MSE doubles
    /// (0.044 → 0.091) (BENCHMARKS.md, session 64).
    #[arg(long, default_value_t = 0.3)]
    pub roughness_init: f32,
    #[arg(long, default_value_t = 1.5)]
    pub env_init: f32,
    /// The rendering equation's S samples read the env box-filtered to this height (width 2×);
    /// 0 (default) = the full map, bilinear (the published lookup). A coarse box (8 was the
    /// default until session 54) quiets a small bright source at low S, but leaks it into the
    /// directions around it: shadows come out too light (BENCHMARKS.md, sessions 53–54).
    #[arg(long, default_value_t = 0)]
    pub env_sample_height: usize,
    /// Share of each surfel's S cached directions drawn from the learned light's peaks (its
    /// texels above 10 × its mean: a sun), the rest Fibonacci, mixed by the balance heuristic;
    /// the sampler follows the light at every cache check (`cache_every`/4). 0 = Fibonacci
    /// only (as published); a light without peaks (the start, a smooth sky) gets none.
    #[arg(long, default_value_t = 0.0)]
    #[serde(default)]
    pub env_importance_inverse: f32,
    /// Start the env from this map (.hdr/.exr) instead of a constant: "known light" runs, and
    /// with `--lr-env 0` a light held fixed (diagnostics, ablations).
    #[arg(long)]
    pub env_init_map: Option<PathBuf>,
    /// Specular lobe of the inverse stage's PBR colour: `mc` (S cached directions, as
    /// published) or `split-sum` (prefiltered env at the reflection direction; glossy
    /// reflections a few samples cannot resolve).
    #[arg(long, value_enum, default_value_t = Specular::Mc)]
    pub specular: Specular,
    /// Rays per shaded surfel and iteration of `--specular traced` [2].
    #[arg(long, default_value_t = DEFAULT_SPECULAR_RAYS)]
    #[serde(default = "default_specular_rays")]
    pub specular_rays: usize,
    /// Traced rays leave a surfel from μ + offset·n, offset = this × the scene extent.
    #[arg(long, default_value_t = 0.002)]
    pub ray_offset: f32,
    /// Traced rays leaving a surfel ignore surfels whose centre lies less than this × the
    /// scene extent above the surfel's tangent plane (0 = off): the fuzzy layers of the
    /// surface a ray starts from do not occlude it (measured on spheres: the self-hits made
    /// the indirect light 2–3 dB worse; see BENCHMARKS).
    #[arg(long, default_value_t = 0.013)]
    pub ray_skip_margin: f32,
    /// Back faces of the PBR stages' traced rays: `dark-unseen` (the default: culled but for
    /// the surfels no camera saw, whose orientation is a guess; their back faces block light
    /// and add none; the flags are kept in the checkpoint and as the PLY property `unseen`),
    /// `cull` (RadioGS), `two-sided` or `dark` (every back face blocks, none adds light).
    /// Culled, surfels no camera saw that face the wrong way leak light into shadows; two-sided
    /// and dark trade indirect light for albedo (BENCHMARKS.md, sessions 66–68). Training, eval
    /// and relighting of a run use its setting; runs saved before it load as `cull`.
    #[arg(long, value_enum, default_value_t = TraceBackFaces::DarkUnseen)]
    #[serde(default)]
    pub trace_back_faces: TraceBackFaces,
    /// One-sided back-face modes: traced rays still hit back faces seen at most this many
    /// degrees past edge-on, composited with their colour (0 = strict culling, as RadioGS). A
    /// trained surface is a fuzzy shell of tilted surfels: where a ray grazes an object many
    /// of them show their back, and culling them lets it leak through (BENCHMARKS.md, session
    /// 75). Runs saved before the setting load as 0.
    #[arg(long, default_value_t = 20.0)]
    #[serde(default = "grazing_off")]
    pub trace_grazing: f32,
    /// The shading reads a traced ray whose final transmittance is below this as fully blocked,
    /// its composited radiance scaled to the whole ray (`visibility_ramp` in src/trace/mod.rs;
    /// 0 = off, as RadioGS): a trained surface is a few translucent layers and lets a few per
    /// cent of the sky into the shadows behind it, a large share of a deep shadow's light.
    /// At 0.1 albedo +0.04 to +0.34 dB on four scenes, one seed each (BENCHMARKS.md sessions
    /// 81–82). Runs saved before the setting load as 0.
    #[arg(long, default_value_t = 0.1)]
    #[serde(default = "opaque_below_off")]
    pub trace_opaque_below: f32,
    /// The inverse stage drops the geometry's surfels whose largest blend weight (α T) over
    /// every training pixel is below this when it starts (0 = keep all, the default): hidden
    /// layers and faint fringes no view shows, which every later render and trace pays for
    /// (1/255 ≈ 0.0039: a faster stage and relit frame for 0.1–0.4 dB less on every metric).
    #[arg(long, default_value_t = DEFAULT_PRUNE_CONTRIBUTION)]
    #[serde(default = "default_prune_contribution")]
    pub prune_contribution: f32,

    /// Write a checkpoint every this many iterations (0 = only at the end).
    #[arg(long, default_value_t = 1000)]
    pub checkpoint_every: u32,
    /// Log metrics every this many iterations.
    #[arg(long, default_value_t = 50)]
    pub log_every: u32,
}

/// What every run before `lambda_normal_inverse` used in the inverse stage: `lambda_normal`'s
/// default, 2DGS's and the published method's 0.05.
fn lambda_normal_2dgs() -> f32 {
    0.05
}

/// What every run before `lambda_albedo_voxel` used: no such prior.
fn albedo_voxel_off() -> f32 {
    0.0
}

/// What runs saved before `trace_grazing` traced with: strict culling.
fn grazing_off() -> f32 {
    0.0
}

/// What runs saved before `trace_opaque_below` shaded with: the transmittance as it is.
fn opaque_below_off() -> f32 {
    0.0
}

fn albedo_voxel_default() -> f32 {
    0.024
}

/// `albedo_chroma_cap`'s default (and every earlier run's): no cap, plain L1.
fn albedo_chroma_cap_default() -> f32 {
    f32::INFINITY
}

fn albedo_voxel_cap_default() -> f32 {
    0.1
}

/// What every run before `lambda_albedo_chroma` used: no such prior.
fn albedo_chroma_off() -> f32 {
    0.0
}

/// What every run before `clip_saturated` used: saturated pixels compared as exact values.
fn clip_saturated_off() -> bool {
    false
}

/// `specular_rays`' default (also what a run saved before the setting reads).
pub const DEFAULT_SPECULAR_RAYS: usize = 2;
/// `prune_contribution`'s default: off. At 1/255 (one 8-bit level) the inverse stage starts
/// with 21–26 % fewer surfels but ends 0.1–0.4 dB worse on every image metric of spheres and
/// cornell (BENCHMARKS.md, session 50).
pub const DEFAULT_PRUNE_CONTRIBUTION: f32 = 0.0;

fn default_prune_contribution() -> f32 {
    DEFAULT_PRUNE_CONTRIBUTION
}

fn default_specular_rays() -> usize {
    DEFAULT_SPECULAR_RAYS
}

/// 2DGS's opacity reset value: what every run before `opacity_reset_cap` used.
fn opacity_reset_cap_2dgs() -> f32 {
    0.01
}

impl Default for TrainConfig {
    fn default() -> Self {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Wrapper {
            #[command(flatten)]
            config: TrainConfig,
        }
        let mut config = Wrapper::parse_from(["radiogs", "--data", ".", "--out", "."]).config;
        config.data = PathBuf::new();
        config.out = PathBuf::new();
        config
    }
}

impl TrainConfig {
    /// An iteration of the 30k reference schedule mapped onto this run's length.
    /// Where incident rays start and what they skip, for a scene of `extent`.
    pub fn ray_start(&self, extent: f32) -> crate::shade::incident::RayStart {
        crate::shade::incident::RayStart {
            offset: self.ray_offset * extent,
            skip_margin: (self.ray_skip_margin > 0.0).then_some(self.ray_skip_margin * extent),
        }
    }

    /// The factor on the position learning rates of the nvs and init stages
    /// (`scale_position_lr`).
    pub fn position_lr_factor(&self) -> f32 {
        if self.scale_position_lr { (30000.0 / self.iters.max(1) as f32).clamp(1.0, 10.0) } else { 1.0 }
    }

    pub fn at(&self, reference_iter: u32) -> u32 {
        ((reference_iter as f64) * self.iters as f64 / 30000.0).round() as u32
    }

    /// Merge: defaults < file < the flags the user typed (named in `explicit`).
    ///
    /// A key the file leaves out takes the built-in default, including the settings whose
    /// serde default is the older value (`filter_inv_square`, `scale_position_lr`,
    /// `opacity_reset_cap`, `lambda_albedo_chroma`, `lambda_albedo_voxel`, `clip_saturated`,
    /// `albedo_init_hue`, `lambda_normal_inverse`): those older values are for reading a run
    /// folder saved before the setting existed (`eval::load_run_config`), not for a
    /// hand-written settings file.
    ///
    /// `--resume` without `--config` reads the run's own `RUN/config.toml` in the file's place,
    /// as a run folder (keys it predates take the values it was trained with), so a resumed run
    /// keeps its settings when a built-in default has changed since (session 54 changed S and
    /// the env lookup); flags typed now still win.
    pub fn resolve(cli: &TrainConfig, explicit: &[String]) -> Result<TrainConfig> {
        let saved = cli.out.join("config.toml");
        let (path, run_folder) = match &cli.config {
            Some(path) => (path.clone(), false),
            None if cli.resume && saved.is_file() => (saved, true),
            None => return Ok(cli.clone()),
        };
        let path = &path;
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        // Parsed whole first, so unknown keys and bad values are reported with their line.
        let parsed: TrainConfig = toml::from_str(&text).map_err(|e| toml_error(path, &text, &e))?;
        let from_file: toml::Table = if run_folder {
            match toml::Value::try_from(&parsed) {
                // `--data` and `--out` are always typed; the file's may be relative to elsewhere.
                Ok(toml::Value::Table(mut table)) => {
                    table.remove("data");
                    table.remove("out");
                    table
                }
                _ => return Err(Error::format(path, "TOML", "cannot be written back as a table")),
            }
        } else {
            toml::from_str(&text).map_err(|e| toml_error(path, &text, &e))?
        };
        if run_folder {
            // An edited run file is named with its bad setting (the merged settings are
            // checked again by `train`).
            parsed.validate().map_err(|e| Error::invalid(path.display().to_string(), e.to_string()))?;
            eprintln!("resuming with the settings saved in {} (flags typed now override them)", path.display());
        }
        // The command line's values (flags typed or their defaults), then the file's keys,
        // then the typed flags again.
        let mut merged = toml::Value::try_from(cli).map_err(|e| Error::invalid("config", e.to_string()))?;
        let cli_value = merged.clone();
        if let (Some(table), Some(cli_table)) = (merged.as_table_mut(), cli_value.as_table()) {
            table.extend(from_file);
            for key in explicit {
                if let Some(v) = cli_table.get(key) {
                    table.insert(key.clone(), v.clone());
                }
            }
        }
        let mut out: TrainConfig =
            merged.try_into().map_err(|e: toml::de::Error| Error::format(path, "TOML", e.message().to_string()))?;
        out.config = cli.config.clone();
        out.resume = cli.resume;
        out.overwrite = cli.overwrite;
        Ok(out)
    }

    /// Reject settings that cannot work, naming the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, reason: String| Err(Error::invalid(format!("setting '{key}'"), reason));
        if self.iters == 0 {
            return bad("iters", "must be at least 1".into());
        }
        if !(1..=32).contains(&self.window) {
            return bad("window", format!("{} is not in 1..=32", self.window));
        }
        if !(self.filter_inv_square.is_finite() && self.filter_inv_square > 0.0) {
            return bad("filter_inv_square", format!("{} is not a positive number", self.filter_inv_square));
        }
        if !(0.0..=1.0).contains(&self.lambda_dssim) {
            return bad("lambda_dssim", format!("{} is not in [0, 1]", self.lambda_dssim));
        }
        if !(self.opacity_reset_cap > 0.0 && self.opacity_reset_cap <= 1.0) {
            return bad("opacity_reset_cap", format!("{} is not in (0, 1]", self.opacity_reset_cap));
        }
        if !(0.0..=1.0).contains(&self.depth_ratio) {
            return bad("depth_ratio", format!("{} is not in [0, 1]", self.depth_ratio));
        }
        for (key, v) in [
            ("lambda_dist", self.lambda_dist),
            ("lambda_normal", self.lambda_normal),
            ("lambda_normal_dispersion", self.lambda_normal_dispersion),
            ("lambda_smooth_normal_nvs", self.lambda_smooth_normal_nvs),
            ("lambda_mask", self.lambda_mask),
            ("lambda_opacity_entropy", self.lambda_opacity_entropy),
            ("lambda_sh_rest", self.lambda_sh_rest),
            ("densify_grad_threshold", self.densify_grad_threshold),
            ("densify_abs_grad_threshold", self.densify_abs_grad_threshold),
            ("percent_dense", self.percent_dense),
            ("prune_opacity", self.prune_opacity),
            ("lr_sh", self.lr_sh),
            ("lr_sh_rest_inverse", self.lr_sh_rest_inverse),
            ("lr_opacity", self.lr_opacity),
            ("lr_scale", self.lr_scale),
            ("lr_rotation", self.lr_rotation),
            ("lr_position_init", self.lr_position_init),
            ("lr_position_final", self.lr_position_final),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(key, format!("{v} must be finite and ≥ 0"));
            }
        }
        for (key, v) in [
            ("lambda_rc", self.lambda_rc),
            ("lambda_simple_rc", self.lambda_simple_rc),
            ("lambda_pbr", self.lambda_pbr),
            ("lambda_sh_image", self.lambda_sh_image),
            ("lambda_mask_inverse", self.lambda_mask_inverse),
            ("lambda_normal_inverse", self.lambda_normal_inverse),
            ("lambda_smooth_albedo", self.lambda_smooth_albedo),
            ("lambda_smooth_roughness", self.lambda_smooth_roughness),
            ("lambda_smooth_normal", self.lambda_smooth_normal),
            ("lambda_albedo_chroma", self.lambda_albedo_chroma),
            ("lambda_albedo_voxel", self.lambda_albedo_voxel),
            ("lambda_white_light", self.lambda_white_light),
            ("lambda_env_tv", self.lambda_env_tv),
            ("geometry_lr_scale", self.geometry_lr_scale),
            ("lr_env", self.lr_env),
            ("lr_albedo", self.lr_albedo),
            ("lr_roughness", self.lr_roughness),
            ("ray_offset", self.ray_offset),
            ("ray_skip_margin", self.ray_skip_margin),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(key, format!("{v} must be finite and ≥ 0"));
            }
        }
        if !(self.albedo_voxel.is_finite() && self.albedo_voxel >= 1e-4 && self.albedo_voxel <= 0.5) {
            return bad(
                "albedo_voxel",
                format!("{} is not in [0.0001, 0.5] (a fraction of the scene extent)", self.albedo_voxel),
            );
        }
        if !(self.albedo_chroma_cap > 0.0) {
            return bad("albedo_chroma_cap", format!("{} must be > 0 (inf: no cap)", self.albedo_chroma_cap));
        }
        if !(self.albedo_voxel_cap.is_finite() && self.albedo_voxel_cap > 0.0) {
            return bad("albedo_voxel_cap", format!("{} must be finite and > 0", self.albedo_voxel_cap));
        }
        if !(0.0..1.0).contains(&self.prune_contribution) {
            return bad("prune_contribution", format!("{} is not in [0, 1)", self.prune_contribution));
        }
        if !(0.0..=1.0).contains(&self.albedo_init_hue) {
            return bad("albedo_init_hue", format!("{} is not in [0, 1]", self.albedo_init_hue));
        }
        if !(self.albedo_chroma_bin.is_finite() && self.albedo_chroma_bin >= 0.002 && self.albedo_chroma_bin <= 0.5) {
            return bad("albedo_chroma_bin", format!("{} is not in [0.002, 0.5]", self.albedo_chroma_bin));
        }
        if !(1..=256).contains(&self.pbr_samples) {
            return bad("pbr_samples", format!("{} is not in 1..=256", self.pbr_samples));
        }
        if self.rc_surfels == 0 {
            return bad("rc_surfels", "must be at least 1".into());
        }
        if !(0.0..=45.0).contains(&self.trace_grazing) {
            return bad("trace_grazing", format!("{} is not in [0, 45] degrees", self.trace_grazing));
        }
        if !(0.0..=0.9).contains(&self.trace_opaque_below) {
            return bad("trace_opaque_below", format!("{} is not in [0, 0.9]", self.trace_opaque_below));
        }
        if !(1..=256).contains(&self.rc_rays) {
            return bad("rc_rays", format!("{} is not in 1..=256", self.rc_rays));
        }
        if self.env_height < 8 || self.env_height % 8 != 0 || self.env_height > 1024 {
            return bad("env_height", format!("{} must be a multiple of 8 in 8..=1024", self.env_height));
        }
        if !(0.03..0.8).contains(&self.albedo_init) {
            return bad("albedo_init", format!("{} is not in (0.03, 0.8)", self.albedo_init));
        }
        if !(0.0..1.0).contains(&self.roughness_init) || self.roughness_init <= 0.0 {
            return bad("roughness_init", format!("{} is not in (0, 1)", self.roughness_init));
        }
        if !(self.env_init.is_finite() && self.env_init > 0.0) {
            return bad("env_init", format!("{} must be > 0", self.env_init));
        }
        if !(0.0..=0.9).contains(&self.env_importance_inverse) {
            return bad(
                "env_importance_inverse",
                format!("{} is not a share in [0, 0.9] (0 = Fibonacci directions only)", self.env_importance_inverse),
            );
        }
        if self.env_sample_height != 0
            && (self.env_sample_height > self.env_height || self.env_height % self.env_sample_height != 0)
        {
            return bad(
                "env_sample_height",
                format!("{} must divide env_height {} (or be 0)", self.env_sample_height, self.env_height),
            );
        }
        if self.cache_every == 0 {
            return bad("cache_every", "must be at least 1".into());
        }
        if self.densify_every == 0 {
            return bad("densify_every", "must be at least 1 (densify_until 0 turns densification off)".into());
        }
        if self.log_every == 0 {
            return bad("log_every", "must be at least 1".into());
        }
        if self.specular_rays == 0 || self.specular_rays > 256 {
            return bad("specular_rays", format!("{} must be 1..=256", self.specular_rays));
        }
        if !(1..=MAX_DOWNSCALE).contains(&self.resolution) {
            return bad(
                "resolution",
                format!(
                    "{} is not a downscale factor in 1..={MAX_DOWNSCALE} (it divides the image size, as 3DGS's -r 2|4|8; it is not a width)",
                    self.resolution
                ),
            );
        }
        if self.init_points == 0 && self.init_ply.is_none() {
            return bad("init_points", "must be at least 1".into());
        }
        Ok(())
    }

    /// Write `RUN/config.toml` atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        let text = toml::to_string_pretty(self).map_err(|e| Error::invalid("config", e.to_string()))?;
        crate::io::atomic::write_atomic(path, text.as_bytes())
    }
}

/// A TOML error of `path` naming the line (and so the setting) it is about.
pub(crate) fn toml_error(path: &std::path::Path, text: &str, e: &toml::de::Error) -> Error {
    let at = e.span().map(|span| {
        let line_no = text[..span.start.min(text.len())].matches('\n').count() + 1;
        let line = text.lines().nth(line_no - 1).unwrap_or("").trim();
        format!("line {line_no} (`{line}`): ")
    });
    Error::format(path, "TOML", format!("{}{}", at.unwrap_or_default(), e.message()))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bad value in a settings file names the file and its line, so the setting.
    #[test]
    fn toml_errors_name_the_line_of_the_setting() {
        let text = "iters = 10\ngauge_every = \"often\"\n";
        let e = toml::from_str::<TrainConfig>(text).unwrap_err();
        let msg = toml_error(std::path::Path::new("run/config.toml"), text, &e).to_string();
        assert!(msg.contains("run/config.toml"), "{msg}");
        assert!(msg.contains("line 2 (`gauge_every = \"often\"`)"), "{msg}");
    }

    #[test]
    fn defaults_round_trip_through_toml_and_file_overrides_apply() {
        let d = TrainConfig::default();
        assert_eq!(d.window, 8);
        let text = toml::to_string(&d).unwrap();
        let back: TrainConfig = toml::from_str(&text).unwrap();
        assert_eq!(toml::to_string(&back).unwrap(), text);

        let dir = crate::test_dir::TempDir::new("cfg");
        let file = dir.join("c.toml");
        std::fs::write(&file, "iters = 123\nwindow = 4\n").unwrap();
        let mut cli = TrainConfig { config: Some(file.clone()), ..TrainConfig::default() };
        cli.window = 16;
        let merged = TrainConfig::resolve(&cli, &["window".to_string()]).unwrap();
        assert_eq!((merged.iters, merged.window), (123, 16), "file sets iters, the typed flag wins for window");

        std::fs::write(&file, "iters = 5\nwindoww = 4\n").unwrap();
        let err = TrainConfig::resolve(&cli, &[]).unwrap_err().to_string();
        assert!(err.contains("c.toml") && err.contains("windoww"), "{err}");
        assert!(
            TrainConfig { window: 0, ..TrainConfig::default() }.validate().unwrap_err().to_string().contains("window")
        );
        let err = TrainConfig { depth_ratio: 1.5, ..TrainConfig::default() }.validate().unwrap_err().to_string();
        assert!(err.contains("depth_ratio"), "{err}");
        // No consistency batch is λ_rc = 0, not 0 surfels (relight refuses 0 too).
        let err = TrainConfig { rc_surfels: 0, ..TrainConfig::default() }.validate().unwrap_err().to_string();
        assert!(err.contains("rc_surfels"), "{err}");
        // A cap of 0 would reset opacity logits to −∞.
        for bad in [0.0, -0.1, 1.5, f32::NAN] {
            let err =
                TrainConfig { opacity_reset_cap: bad, ..TrainConfig::default() }.validate().unwrap_err().to_string();
            assert!(err.contains("opacity_reset_cap"), "{err}");
        }
        assert!(TrainConfig { opacity_reset_cap: 1.0, ..TrainConfig::default() }.validate().is_ok());
        // A bin of 0 would make the prior's grid infinite.
        for bad in [0.0, 0.001, 0.6, f32::NAN] {
            let err =
                TrainConfig { albedo_chroma_bin: bad, ..TrainConfig::default() }.validate().unwrap_err().to_string();
            assert!(err.contains("albedo_chroma_bin"), "{err}");
        }
        let err =
            TrainConfig { lambda_albedo_chroma: -0.1, ..TrainConfig::default() }.validate().unwrap_err().to_string();
        assert!(err.contains("lambda_albedo_chroma"), "{err}");
        // The chroma prior's cap: positive, `inf` (the default) for none; a settings file
        // without it (every run before session 62) reads as none, the prior those runs had.
        for bad in [0.0, -0.1, f32::NAN] {
            let err =
                TrainConfig { albedo_chroma_cap: bad, ..TrainConfig::default() }.validate().unwrap_err().to_string();
            assert!(err.contains("albedo_chroma_cap"), "{err}");
        }
        assert_eq!(TrainConfig::default().albedo_chroma_cap, f32::INFINITY);
        let old: TrainConfig = toml::from_str("iters = 3000\n").unwrap();
        assert_eq!(old.albedo_chroma_cap, f32::INFINITY);
        let saved = toml::to_string(&TrainConfig { albedo_chroma_cap: 0.1, ..TrainConfig::default() }).unwrap();
        assert_eq!(toml::from_str::<TrainConfig>(&saved).unwrap().albedo_chroma_cap, 0.1);
        let saved = toml::to_string(&TrainConfig::default()).unwrap();
        assert_eq!(toml::from_str::<TrainConfig>(&saved).unwrap().albedo_chroma_cap, f32::INFINITY);
        for bad in [-0.1, 1.5, f32::NAN] {
            let err =
                TrainConfig { albedo_init_hue: bad, ..TrainConfig::default() }.validate().unwrap_err().to_string();
            assert!(err.contains("albedo_init_hue"), "{err}");
        }
        assert!(TrainConfig { albedo_init_hue: 0.0, ..TrainConfig::default() }.validate().is_ok());
        for bad in [-0.01, 1.0, f32::NAN] {
            let err =
                TrainConfig { prune_contribution: bad, ..TrainConfig::default() }.validate().unwrap_err().to_string();
            assert!(err.contains("prune_contribution"), "{err}");
        }
        for bad in [0, MAX_DOWNSCALE + 1, 800] {
            let err = TrainConfig { resolution: bad, ..TrainConfig::default() }.validate().unwrap_err().to_string();
            assert!(err.contains("resolution") && err.contains("not a width"), "{err}");
        }
        assert!(TrainConfig { resolution: 4, ..TrainConfig::default() }.validate().is_ok());
        // Both are divisors of the iteration number (a 0 panicked before it was checked).
        let err = TrainConfig { densify_every: 0, ..TrainConfig::default() }.validate().unwrap_err().to_string();
        assert!(err.contains("densify_every") && err.contains("densify_until"), "{err}");
        let err = TrainConfig { log_every: 0, ..TrainConfig::default() }.validate().unwrap_err().to_string();
        assert!(err.contains("log_every"), "{err}");
        // A 100000-texel-high env aborted on allocation.
        for bad in [0, 12, 100_000] {
            let err = TrainConfig { env_height: bad, ..TrainConfig::default() }.validate().unwrap_err().to_string();
            assert!(err.contains("env_height"), "{err}");
        }
    }

    /// Position rates scale as 30000 / iters within [1, 10]; a settings file or a run saved
    /// without the setting keeps the unscaled rates it was written with.
    #[test]
    fn position_rates_scale_for_short_runs_and_old_runs_keep_theirs() {
        let factor = |iters| TrainConfig { iters, ..TrainConfig::default() }.position_lr_factor();
        assert_eq!(factor(3000), 10.0);
        assert!((factor(7000) - 30000.0 / 7000.0).abs() < 1e-6);
        assert_eq!((factor(30000), factor(60000), factor(100)), (1.0, 1.0, 10.0));
        assert!(TrainConfig::default().scale_position_lr);
        let old: TrainConfig = toml::from_str("iters = 3000\n").unwrap();
        assert!(!old.scale_position_lr);
        assert_eq!(old.position_lr_factor(), 1.0);
    }

    /// `specular_rays` is checked (the error names it), and a settings file without it (every
    /// run saved before `--specular traced`) reads as 2.
    #[test]
    fn specular_rays_are_validated_and_default_to_two() {
        for bad in [0usize, 257] {
            let err = TrainConfig { specular_rays: bad, ..TrainConfig::default() }.validate().unwrap_err();
            assert!(err.to_string().contains("specular_rays"), "{err}");
        }
        assert!(TrainConfig { specular_rays: 1, ..TrainConfig::default() }.validate().is_ok());
        let old: TrainConfig = toml::from_str("iters = 3000\nspecular = \"traced\"\n").unwrap();
        assert_eq!((old.specular, old.specular_rays), (Specular::Traced, 2));
    }

    /// `env_importance_inverse` is a share in [0, 0.9] (the error names it); a run saved before
    /// the setting reads as 0, the Fibonacci directions it was trained with.
    #[test]
    fn env_importance_inverse_is_validated_and_old_runs_read_zero() {
        for bad in [-0.1f32, 0.95, f32::NAN] {
            let err = TrainConfig { env_importance_inverse: bad, ..TrainConfig::default() }.validate().unwrap_err();
            assert!(err.to_string().contains("env_importance_inverse"), "{err}");
        }
        assert!(TrainConfig { env_importance_inverse: 0.25, ..TrainConfig::default() }.validate().is_ok());
        let old: TrainConfig = toml::from_str("iters = 3000\n").unwrap();
        assert_eq!(old.env_importance_inverse, 0.0);
    }

    /// A hand-written `--config` file that leaves out the settings whose serde default is the
    /// older value gets the built-in defaults for them; the run-folder reader keeps the older
    /// values (what a run saved before the setting was trained with); a file that names them wins.
    #[test]
    fn a_settings_file_without_a_key_gets_the_built_in_default() {
        let dir = crate::test_dir::TempDir::new("cfg-defaults");
        let file = dir.join("partial.toml");
        std::fs::write(&file, "iters = 3000\n").unwrap();
        let cli = TrainConfig { config: Some(file.clone()), ..TrainConfig::default() };
        let merged = TrainConfig::resolve(&cli, &[]).unwrap();
        let d = TrainConfig::default();
        assert_eq!(merged.iters, 3000);
        assert!(merged.scale_position_lr && d.scale_position_lr);
        assert_eq!(merged.filter_inv_square, d.filter_inv_square);
        assert_ne!(d.filter_inv_square, crate::raster::filter_inv_square_2dgs());
        assert_eq!(merged.opacity_reset_cap, d.opacity_reset_cap);
        assert_ne!(d.opacity_reset_cap, opacity_reset_cap_2dgs());
        assert_eq!(merged.lambda_albedo_chroma, d.lambda_albedo_chroma);
        assert_ne!(d.lambda_albedo_chroma, albedo_chroma_off());
        assert_eq!(merged.lambda_albedo_voxel, d.lambda_albedo_voxel);
        assert_ne!(d.lambda_albedo_voxel, albedo_voxel_off());
        assert_eq!((merged.albedo_init_hue, d.albedo_init_hue), (1.0, 1.0));
        assert_eq!(
            (merged.trace_back_faces, d.trace_back_faces),
            (TraceBackFaces::DarkUnseen, TraceBackFaces::DarkUnseen)
        );
        assert_eq!((merged.trace_grazing, d.trace_grazing), (20.0, 20.0));
        assert_ne!(d.trace_grazing, grazing_off());
        assert_eq!(merged.trace_opaque_below, d.trace_opaque_below);
        assert_ne!(d.trace_opaque_below, opaque_below_off());
        assert_eq!(
            toml::to_string(&TrainConfig { iters: 3000, config: Some(file.clone()), ..d.clone() }).unwrap(),
            toml::to_string(&merged).unwrap()
        );

        let run = dir.join("run");
        std::fs::create_dir_all(&run).unwrap();
        std::fs::write(run.join("config.toml"), "iters = 3000\n").unwrap();
        let saved = crate::eval::load_run_config(&run).unwrap();
        // A run's file is validated as `train`'s settings are, naming the file and the setting.
        for bad in [
            "window = 0\n",
            "filter_inv_square = nan\n",
            "trace_grazing = 90.0\n",
            "trace_grazing = nan\n",
            "trace_opaque_below = 1.0\n",
        ] {
            std::fs::write(run.join("config.toml"), format!("iters = 3000\n{bad}")).unwrap();
            let err = crate::eval::load_run_config(&run).unwrap_err().to_string();
            let key = bad.split(' ').next().unwrap();
            assert!(err.contains("config.toml") && err.contains(key), "{err}");
        }
        std::fs::write(run.join("config.toml"), "iters = 3000\n").unwrap();
        assert!(!saved.scale_position_lr);
        assert_eq!(saved.filter_inv_square, crate::raster::filter_inv_square_2dgs());
        assert_eq!(saved.opacity_reset_cap, opacity_reset_cap_2dgs());
        assert_eq!(saved.lambda_albedo_chroma, albedo_chroma_off());
        assert_eq!(saved.lambda_albedo_voxel, albedo_voxel_off());
        assert_eq!(saved.albedo_init_hue, 0.0, "the grey start runs before the setting had");
        assert_eq!(saved.trace_back_faces, TraceBackFaces::Cull, "the culled tracing runs before the setting had");
        assert_eq!(saved.trace_grazing, 0.0, "the strict culling runs before the setting had");
        assert_eq!(saved.trace_opaque_below, 0.0, "the unramped visibility runs before the setting had");
        assert_eq!(saved.rc_order, RcOrder::Random, "the random consistency batches runs before the setting had");

        std::fs::write(&file, "scale_position_lr = false\nfilter_inv_square = 2.0\nopacity_reset_cap = 0.01\n")
            .unwrap();
        let named = TrainConfig::resolve(&cli, &[]).unwrap();
        assert!(!named.scale_position_lr);
        assert_eq!(named.filter_inv_square, 2.0);
        assert_eq!(named.opacity_reset_cap, 0.01);
    }

    /// `--resume` continues with the run's saved settings (keys the file predates at their
    /// older values), flags typed now win, and a fresh run or a run without a saved file gets
    /// the built-in defaults.
    #[test]
    fn resume_keeps_the_runs_saved_settings() {
        let dir = crate::test_dir::TempDir::new("cfg-resume");
        let run = dir.join("run");
        std::fs::create_dir_all(&run).unwrap();
        let saved = "out = \"elsewhere\"\npbr_samples = 16\nenv_sample_height = 8\ncache_every = 100\niters = 3000\n";
        std::fs::write(run.join("config.toml"), saved).unwrap();
        let d = TrainConfig::default();
        assert_ne!((d.pbr_samples, d.env_sample_height, d.cache_every), (16, 8, 100));
        let cli = TrainConfig { out: run.clone(), resume: true, ..d.clone() };
        let r = TrainConfig::resolve(&cli, &[]).unwrap();
        assert_eq!((r.pbr_samples, r.env_sample_height, r.cache_every, r.iters), (16, 8, 100, 3000));
        assert_eq!(r.out, run, "the run folder typed, not the file's");
        assert!(r.resume && r.config.is_none());
        assert_eq!(r.filter_inv_square, crate::raster::filter_inv_square_2dgs(), "a key the file predates");
        assert_eq!((r.lambda_normal_inverse, d.lambda_normal_inverse), (0.05, 0.2), "the inverse stage's as it was");
        let typed = TrainConfig { pbr_samples: 32, ..cli.clone() };
        let r = TrainConfig::resolve(&typed, &["pbr_samples".to_string()]).unwrap();
        assert_eq!((r.pbr_samples, r.cache_every), (32, 100));
        let fresh = TrainConfig { resume: false, ..cli.clone() };
        assert_eq!(TrainConfig::resolve(&fresh, &[]).unwrap().pbr_samples, d.pbr_samples);

        std::fs::write(run.join("config.toml"), "window = 0\n").unwrap();
        let err = TrainConfig::resolve(&cli, &[]).unwrap_err().to_string();
        assert!(err.contains("config.toml") && err.contains("window"), "{err}");
        std::fs::write(run.join("config.toml"), "pbr_samplez = 16\n").unwrap();
        let err = TrainConfig::resolve(&cli, &[]).unwrap_err().to_string();
        assert!(err.contains("config.toml") && err.contains("pbr_samplez"), "{err}");
        std::fs::remove_file(run.join("config.toml")).unwrap();
        assert_eq!(TrainConfig::resolve(&cli, &[]).unwrap().pbr_samples, d.pbr_samples);
    }
}
