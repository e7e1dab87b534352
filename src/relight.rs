//! Relighting (RadioGS §relighting, DESIGN §1): put a trained scene under a new env map.
//!
//! - `finetune`: geometry and materials frozen, env = the new map; only the SH radiance is
//!   optimised, by the radiometric-consistency loss alone (λ 1), then the scene renders by plain
//!   rasterisation. The SH start from the ray-traced prediction (below) seen along each
//!   surfel's normal (DC only), so the finetune mostly adds view dependence and the
//!   inter-reflections of the new light. The right-hand side is detached (each step fits the
//!   SH to the rendering equation evaluated with the current SH as indirect light: a
//!   fixed-point iteration), which spares the tracer's backward pass. The residual is squared
//!   in linear radiance, not training's sRGB L1: each step's target is a 16-ray estimate, and an
//!   L1 fit settles on its median, which leaves out a sun the rays usually miss (BENCHMARKS.md,
//!   session 58).
//! - `traced`: no optimisation; per surfel, visibility and indirect light are traced under the
//!   new map and the light is iterated over a few bounces on the same rays ([`traced_cache`]):
//!   the hit surfels first radiate their split-sum colour seen along their normal (diffuse
//!   irradiance + prefiltered specular, no occlusion), then their own traced prediction of the
//!   bounce before; the PBR render shows the result.

use crate::camera::Camera;
use crate::envmap::EnvMap;
use crate::optim::{LearningRates, SurfelAdam};
use crate::shade::incident::{EnvImportance, IncidentCache, RayStart};
use crate::shade::pbr::{Detach, shade_surfels};
use crate::shade::splitsum::SplitSum;
use crate::surfels::Surfels;
use crate::trace::Tracer;
use crate::train::consistency::{RcScratch, RcSettings, encode, radiometric_consistency};
use crate::train::inverse::{BackFaces, trace_settings_with};
use crate::train::material::{MaterialGrads, MaterialView};
use anyhow::Context;
use rand::{RngExt, SeedableRng};
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;

#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RelightMode {
    /// Finetune the SH radiance with radiometric consistency; render by rasterisation.
    Finetune,
    /// Ray-traced PBR per surfel under the new light; no finetune.
    Traced,
}

/// Put a trained scene (after the inverse stage) under a new environment map.
#[derive(clap::Args, Debug, Clone)]
pub struct RelightArgs {
    /// Trained run folder (with envmap.exr, i.e. after `--stage inverse`).
    #[arg(long)]
    pub run: PathBuf,
    /// New environment map (.hdr or .exr, Blender's equirectangular orientation).
    #[arg(long)]
    pub envmap: PathBuf,
    /// New run folder.
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, value_enum, default_value_t = RelightMode::Finetune)]
    pub mode: RelightMode,
    /// Finetune iterations.
    #[arg(long, default_value_t = 400)]
    pub iters: u32,
    /// Rotate the map about the up axis (degrees, counter-clockwise seen from above).
    #[arg(long, default_value_t = 0.0)]
    pub rotate: f32,
    /// Consistency surfels per finetune iteration.
    #[arg(long, default_value_t = 2048)]
    pub rc_surfels: usize,
    /// Traced rays per consistency surfel.
    #[arg(long, default_value_t = RC_RAYS)]
    pub rc_rays: usize,
    /// Light bounces of the traced prediction (the traced mode's light and the finetune's
    /// start); 1 = the hit surfels lit by the unoccluded env only.
    #[arg(long, default_value_t = TRACED_BOUNCES)]
    pub bounces: usize,
    /// Incident directions per surfel of the traced prediction [default: the run's
    /// `pbr_samples`, 64].
    #[arg(long)]
    pub samples: Option<usize>,
    /// Share of those directions drawn from the new map's bright peaks (texels above 10 × its
    /// mean; a map without any is traced with Fibonacci directions only), the rest Fibonacci,
    /// mixed by the balance heuristic (0 = Fibonacci only, as published;
    /// src/shade/env_sampling.rs).
    #[arg(long, default_value_t = ENV_IMPORTANCE)]
    pub env_importance: f32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Traced rays per consistency surfel in each finetune iteration (`--rc-rays`).
pub const RC_RAYS: usize = 16;

/// Share of each surfel's traced directions drawn from the new map's peaks under relighting
/// (`--env-importance`). 0.25 and 0.5 relight alike (0.25: cornell +0.01 / +0.07 dB, spheres
/// +0.04 / +0.07 dB, finetune / traced; BENCHMARKS.md, session 58).
pub const ENV_IMPORTANCE: f32 = 0.25;

/// Checks `--env-importance` / `--relight-env-importance` (named `flag` in the error).
pub fn check_env_importance(flag: &str, share: f32) -> anyhow::Result<()> {
    if !(0.0..=0.9).contains(&share) {
        anyhow::bail!("{flag} {share}: must be a share in [0, 0.9] (0 = Fibonacci directions only)");
    }
    Ok(())
}

/// Settings of the finetune.
#[derive(Clone, Debug)]
pub struct FinetuneSettings {
    pub iters: u32,
    pub rc_surfels: usize,
    pub rc_rays: usize,
    pub samples: usize,
    pub start: RayStart,
    pub lr_sh: f32,
    /// Box filter of the env for the rendering equation's samples (as in training).
    pub sample_factor: usize,
    /// Light bounces of the traced start ([`traced_cache`]).
    pub bounces: usize,
    /// Share of the traced start's directions drawn from the map ([`traced_cache`]).
    pub env_importance: f32,
    /// The trained run's `trace_back_faces` (and unseen flags).
    pub back_faces: BackFaces,
    pub seed: u64,
}

/// Load a map, rotate it and resample it to H × 2H (the split-sum and training size).
pub fn prepare_env(path: &Path, rotate: f32, height: usize) -> crate::Result<EnvMap> {
    let env = EnvMap::load(path)?;
    let env = if rotate != 0.0 { env.rotated_about_up(rotate) } else { env };
    Ok(env.resample(2 * height, height))
}

/// Light bounces of the traced prediction: bounce 1 lights the hit surfels by the unoccluded
/// env (split-sum), each further bounce by their own traced prediction of the bounce before
/// (visibility and inter-reflection included), composited along the same recorded rays.
/// Four converge (eight add < 0.01 dB); with the true materials and light, one bounce cost
/// cornell's open box 1.8 dB of relighting (BENCHMARKS.md, session 35).
pub const TRACED_BOUNCES: usize = 4;

/// Visibility and indirect light under `env`, traced for every surfel: the rays are traced once
/// and the indirect light is iterated over `bounces` (≥ 1; see [`TRACED_BOUNCES`]). The hit
/// surfels' radiance is their outgoing radiance along their own normal (view-independent), and
/// the rendering equation of each bounce samples `env` box-filtered by `sample_factor` (as the
/// PBR render does). A share `env_importance` of each surfel's `samples` directions is drawn
/// from that map's peaks ([`EnvImportance`]; none if it has no peaks), the rest are Fibonacci.
/// Back faces as the run was trained (`back_faces`).
#[allow(clippy::too_many_arguments)]
pub fn traced_cache(
    surfels: &Surfels,
    mats: &MaterialView,
    env: &EnvMap,
    samples: usize,
    start: RayStart,
    seed: u64,
    sample_factor: usize,
    bounces: usize,
    env_importance: f32,
    back_faces: &BackFaces,
) -> crate::Result<IncidentCache> {
    let tracer = Tracer::build(surfels, &trace_settings_with(back_faces));
    let split = SplitSum::new(env)?;
    let env_s = env.box_downsample(sample_factor.max(1));
    let mut cache = IncidentCache::default();
    cache.set_importance(EnvImportance::of_map(&env_s, samples, env_importance));
    let n = surfels.len();
    // Bounce 1: each surfel's split-sum radiance along its normal (linear), as a traced feature.
    let mut radiance: Vec<f32> = (0..n)
        .into_par_iter()
        .flat_map_iter(|i| {
            let o = split.shade(mats.albedo[i], mats.roughness[i], mats.normal[i], mats.normal[i]);
            [0, 1, 2].map(|c| o.diffuse[c] + o.specular[c])
        })
        .collect();
    if bounces <= 1 {
        // One bounce needs no hit lists (they cost 8 bytes a hit).
        cache.refresh_with(&tracer, surfels, samples, start, seed, Some(&radiance));
        return Ok(cache);
    }
    let hits = cache.refresh_recorded(&tracer, surfels, samples, start, seed, &radiance);
    let (mut direct, mut indirect) = (vec![[0.0f32; 3]; n], vec![[0.0f32; 3]; n]);
    for _ in 1..bounces {
        let inp = cache.inputs(&mats.albedo, &mats.roughness, &mats.normal, &mats.normal);
        shade_surfels(&inp, &env_s, &mut direct, &mut indirect)?;
        radiance.par_chunks_mut(3).zip(direct.par_iter().zip(&indirect)).for_each(|(r, (d, ind))| {
            for c in 0..3 {
                r[c] = d[c] + ind[c];
            }
        });
        hits.composite(&radiance, &mut cache.indirect);
    }
    Ok(cache)
}

/// What the finetune did.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct FinetuneReport {
    pub iterations: u32,
    pub seconds: f64,
    pub first_loss: f32,
    pub last_loss: f32,
}

/// Finetune the SH of `surfels` to the rendering equation under `env` (materials in `mats`).
pub fn finetune(
    surfels: &mut Surfels,
    mats: &MaterialView,
    env: &EnvMap,
    cameras: &[Camera],
    cfg: &FinetuneSettings,
    show_progress: bool,
    start_cache: Option<&IncidentCache>,
) -> crate::Result<FinetuneReport> {
    let started = Instant::now();
    let n = surfels.len();
    let split_env = env;
    let env_s = env.box_downsample(cfg.sample_factor);
    let env = &env_s;
    // Start: DC = the traced prediction along the normal (encoded like the SH images), from
    // `start_cache` when the caller traced it already (`traced_cache` with these settings).
    let traced;
    let cache = match start_cache {
        Some(c) => c,
        None => {
            traced = traced_cache(
                surfels,
                mats,
                split_env,
                cfg.samples,
                cfg.start,
                cfg.seed,
                cfg.sample_factor,
                cfg.bounces,
                cfg.env_importance,
                &cfg.back_faces,
            )?;
            &traced
        }
    };
    let inp = cache.inputs(&mats.albedo, &mats.roughness, &mats.normal, &mats.normal);
    let (mut direct, mut indirect) = (vec![[0.0f32; 3]; n], vec![[0.0f32; 3]; n]);
    shade_surfels(&inp, env, &mut direct, &mut indirect)?;
    for i in 0..n {
        let c = [0, 1, 2].map(|k| encode(direct[i][k] + indirect[i][k]));
        surfels.sh[i] = [[0.0; 3]; crate::sh::SH_COEFFS];
        surfels.sh[i][0] = c.map(crate::sh::rgb_to_dc);
    }
    let lr = LearningRates {
        means: 0.0,
        log_scales: 0.0,
        quats: 0.0,
        opacity_logits: 0.0,
        sh_dc: cfg.lr_sh,
        sh_rest: cfg.lr_sh / 5.0,
        albedo_logits: 0.0,
        roughness_logits: 0.0,
    };
    let mut adam = SurfelAdam::new(surfels, lr);
    let tracer = Tracer::build(surfels, &trace_settings_with(&cfg.back_faces));
    let rc = RcSettings {
        surfels: cfg.rc_surfels,
        rays: cfg.rc_rays,
        start: cfg.start,
        weight: 1.0,
        detach: Detach { env: true, material: true, normal: true },
        detach_lhs: false,
        detach_rhs: true,
        // The mean of the noisy targets, not their median (module note).
        linear_l2: true,
    };
    let mut scratch = RcScratch::default();
    let mut mgrads = MaterialGrads::default();
    mgrads.reset(n);
    let mut v_env = vec![[0.0f32; 3]; env.texels.len()];
    let mut v = surfels.zeros_like();
    let bar = indicatif::ProgressBar::new(cfg.iters as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("relight {bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    if !show_progress {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    let mut report = FinetuneReport::default();
    for it in 1..=cfg.iters {
        if crate::train::interrupt::requested() {
            break;
        }
        let mut rng = rand_pcg::Pcg64::seed_from_u64(cfg.seed ^ (it as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
        let eye = (!cameras.is_empty()).then(|| cameras[rng.random_range(0..cameras.len())].position().to_array());
        v.fill_zero();
        v.sh_degree = surfels.sh_degree;
        let l = radiometric_consistency(
            surfels,
            mats,
            &tracer,
            env,
            eye,
            None,
            &mut rng,
            &rc,
            &mut scratch,
            &mut v,
            &mut mgrads,
            &mut v_env,
        );
        adam.step(surfels, &v);
        if it == 1 {
            report.first_loss = l.total;
        }
        report.last_loss = l.total;
        report.iterations = it;
        if it % 20 == 0 {
            bar.set_message(format!("consistency {:.4}", l.total));
        }
        bar.set_position(it as u64);
    }
    bar.finish_and_clear();
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

/// `radiogs relight`.
pub fn run(args: &RelightArgs) -> anyhow::Result<()> {
    let run = &args.run;
    if !run.join("envmap.exr").is_file() {
        anyhow::bail!(
            "{}: no envmap.exr, so no recovered materials; run `radiogs train --stage inverse` (or all) first",
            run.display()
        );
    }
    if !(args.rotate.is_finite()) {
        anyhow::bail!("--rotate {}: must be a finite angle in degrees", args.rotate);
    }
    if args.bounces == 0 {
        anyhow::bail!("--bounces 0: must be at least 1 (1 = the unoccluded env lights the hit surfels)");
    }
    // The training config's ranges (256 rays; more surfels than a scene has is allowed).
    if !(1..=256).contains(&args.rc_rays) {
        anyhow::bail!("--rc-rays {}: must be 1..=256", args.rc_rays);
    }
    if !(1..=1 << 24).contains(&args.rc_surfels) {
        anyhow::bail!("--rc-surfels {}: must be 1..=16777216", args.rc_surfels);
    }
    if let Some(s) = args.samples
        && !(1..=1024).contains(&s)
    {
        anyhow::bail!("--samples {s}: must be 1..=1024");
    }
    check_env_importance("--env-importance", args.env_importance)?;
    // The relit run is a new folder (or a previous relit run): never the trained run it
    // comes from, nor another trained run, whose checkpoints would then describe other files.
    if crate::io::same_path(&args.out, run) {
        anyhow::bail!("--out {}: is the run being relit; write the relit run to another folder", args.out.display());
    }
    if let Some(f) = ["checkpoint.bin", "checkpoint_init.bin", "checkpoint_inverse.bin"]
        .into_iter()
        .find(|f| args.out.join(f).is_file())
    {
        anyhow::bail!("--out {}: holds a trained run ({f}); write the relit run to a new folder", args.out.display());
    }
    let cfg = crate::eval::load_run_config(run)?;
    let mut surfels = crate::eval::load_run_surfels(run)?;
    let back_faces = BackFaces::of_run(run, cfg.trace_back_faces, surfels.len())?.of_config(&cfg);
    let env = prepare_env(&args.envmap, args.rotate, cfg.env_height)?;
    let extent = crate::pbr_scene::scene_extent(run);
    let start = cfg.ray_start(extent);
    let cameras: Vec<Camera> = match crate::io::dataset::Dataset::open_downscaled(&cfg.data, cfg.resolution) {
        Ok(d) => d.train.iter().map(|v| v.camera.clone()).collect(),
        Err(_) => Vec::new(),
    };
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    crate::train::interrupt::install();
    let mut mats = MaterialView::default();
    mats.update(&surfels);
    let samples = args.samples.unwrap_or(cfg.pbr_samples);
    let mut record = serde_json::json!({
        "mode": args.mode, "envmap": args.envmap.display().to_string(), "rotate_deg": args.rotate,
        "source_run": run.display().to_string(), "bounces": args.bounces,
        "samples": samples, "env_importance": args.env_importance,
    });
    match args.mode {
        RelightMode::Finetune => {
            let settings = FinetuneSettings {
                iters: args.iters,
                rc_surfels: args.rc_surfels,
                rc_rays: args.rc_rays,
                samples,
                start,
                lr_sh: cfg.lr_sh,
                sample_factor: crate::train::inverse::sample_factor(&cfg),
                bounces: args.bounces,
                env_importance: args.env_importance,
                back_faces: back_faces.clone(),
                seed: args.seed,
            };
            let report = finetune(&mut surfels, &mats, &env, &cameras, &settings, true, None)?;
            eprintln!(
                "relight finetune: {} iterations in {:.1} s, consistency {:.4} → {:.4}",
                report.iterations, report.seconds, report.first_loss, report.last_loss
            );
            record["finetune"] = serde_json::to_value(&report)?;
        }
        RelightMode::Traced => {}
    }
    // The relit run keeps the unseen flags, so its traced renders block as the run's did.
    let unseen = back_faces.unseen.as_deref();
    crate::io::ply::write_ply_flagged(
        &args.out.join("point_cloud.ply"),
        &surfels,
        Some(cfg.filter_inv_square),
        unseen,
    )?;
    env.save(&args.out.join("envmap.exr"))?;
    cfg.save(&args.out.join("config.toml"))?;
    crate::io::atomic::write_atomic(&args.out.join("relight.json"), serde_json::to_string_pretty(&record)?.as_bytes())?;
    let how = match args.mode {
        RelightMode::Finetune => "radiogs render --run",
        RelightMode::Traced => "radiogs render --mode pbr --run",
    };
    eprintln!(
        "relit scene → {}; look at it with `{how} {} --out DIR` (add `--orbit 96` for a turntable)",
        args.out.display(),
        args.out.display()
    );
    Ok(())
}

/// The traced bounces recorded in a relit run folder ([`TRACED_BOUNCES`] when it has none:
/// runs relit before the setting existed are re-traced with today's default).
pub fn run_bounces(run: &Path) -> usize {
    let read = || -> Option<usize> {
        let text = std::fs::read_to_string(run.join("relight.json")).ok()?;
        let v: serde_json::Value = serde_json::from_str(&text).ok()?;
        v.get("bounces")?.as_u64().map(|b| b as usize)
    };
    read().filter(|&b| b >= 1).unwrap_or(TRACED_BOUNCES)
}

/// The traced prediction's directions per surfel and their share drawn from the map, as
/// recorded in a relit run folder; a run relit before these were recorded was traced with the
/// run's `pbr_samples`, all Fibonacci.
pub fn run_sampling(run: &Path, pbr_samples: usize) -> (usize, f32) {
    let v: Option<serde_json::Value> =
        std::fs::read_to_string(run.join("relight.json")).ok().and_then(|t| serde_json::from_str(&t).ok());
    let samples = v.as_ref().and_then(|v| v.get("samples")?.as_u64()).map(|s| s as usize);
    let share = v.as_ref().and_then(|v| v.get("env_importance")?.as_f64()).map(|s| s as f32);
    (
        samples.filter(|s| (1..=1024).contains(s)).unwrap_or(pbr_samples),
        share.filter(|s| (0.0..=0.9).contains(s)).unwrap_or(0.0),
    )
}

/// The relight mode recorded in a run folder, if it is a relit run.
pub fn run_mode(run: &Path) -> Option<RelightMode> {
    let text = std::fs::read_to_string(run.join("relight.json")).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    serde_json::from_value(v.get("mode")?.clone()).ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Furnace: a lone surfel under a constant env sees the whole sky (V = 1, no indirect
    /// light), and its white-Lambert radiance is the env times the 10° floor's coverage.
    #[test]
    fn furnace_lone_surfel_under_constant_light() {
        let mut s = Surfels::random_in_box(1, [0.0; 3], [0.0; 3], 2);
        s.quats[0] = crate::surfels::quat_with_normal([0.3, -0.2, 0.9]);
        let l = [1.3f32, 0.7, 2.0];
        let env = EnvMap::constant(32, 16, l);
        let mut mats = MaterialView::default();
        mats.update(&s);
        // A constant map has no peaks to sample: any share gives the Fibonacci directions.
        let traced = |share| {
            traced_cache(
                &s,
                &mats,
                &env,
                64,
                RayStart::offset_only(1e-3),
                5,
                1,
                TRACED_BOUNCES,
                share,
                &BackFaces::default(),
            )
        };
        let cache = traced(0.0).unwrap();
        let also = traced(ENV_IMPORTANCE).unwrap();
        assert!(also.sample_weights.is_empty() && also.dirs == cache.dirs);
        assert!(cache.visibility.iter().all(|&v| v == 1.0));
        assert!(cache.indirect.iter().all(|c| *c == [0.0; 3]));
        let shade = |a: f32| {
            let albedo = [[a; 3]];
            let inp = cache.inputs(&albedo, &mats.roughness, &mats.normal, &mats.normal);
            let (mut d, mut i) = (vec![[0.0f32; 3]], vec![[0.0f32; 3]]);
            shade_surfels(&inp, &env, &mut d, &mut i).unwrap();
            d[0]
        };
        let (white, black) = (shade(1.0), shade(0.0));
        let coverage = 1.0 - 10f32.to_radians().sin().powi(2);
        // Seen along its normal: the Lambert lobe is weighted by 1 − E(1, r) (shade/brdf.rs).
        let kd = crate::shade::brdf::diffuse_weight(1.0, mats.roughness[0] as f64).0 as f32;
        for c in 0..3 {
            let lambert = (white[c] - black[c]) / kd;
            assert!((lambert - l[c] * coverage).abs() < 2e-3 * l[c], "{c}: {lambert} vs {}", l[c] * coverage);
        }
    }

    /// Under a map with a sun, the traced light of surfels drawing half their directions from
    /// the map is much closer to a dense reference than with Fibonacci directions alone. The
    /// reference: the same shading over a quadrature of the map (2 × 2 cells a texel, each
    /// weighted by its solid angle, those under the 10° floor by 0).
    #[test]
    fn map_samples_find_the_sun() {
        use std::f32::consts::PI;
        // 16 lone surfels far apart (no occlusion), normals spread over the upper hemisphere.
        let n = 16;
        let mut s = Surfels::random_in_box(n, [0.0; 3], [0.0; 3], 2);
        for i in 0..n {
            s.means[i] = [10.0 * i as f32, 0.0, 0.0];
            let (a, z) = (i as f32 * 2.4, 0.2 + 0.8 * (i as f32 + 0.5) / n as f32);
            let r = (1.0 - z * z).sqrt();
            s.quats[i] = crate::surfels::quat_with_normal([r * a.cos(), r * a.sin(), z]);
        }
        let mut env = EnvMap::constant(128, 64, [0.05, 0.05, 0.06]);
        env.texels[10 * 128 + 40] = [3000.0, 2800.0, 2500.0];
        let mut mats = MaterialView::default();
        mats.update(&s);
        let direct = |samples: usize, share: f32| -> Vec<f32> {
            let cache = traced_cache(
                &s,
                &mats,
                &env,
                samples,
                RayStart::offset_only(1e-3),
                7,
                1,
                TRACED_BOUNCES,
                share,
                &BackFaces::default(),
            )
            .unwrap();
            let inp = cache.inputs(&mats.albedo, &mats.roughness, &mats.normal, &mats.normal);
            let (mut d, mut i) = (vec![[0.0f32; 3]; n], vec![[0.0f32; 3]; n]);
            shade_surfels(&inp, &env, &mut d, &mut i).unwrap();
            d.iter().map(|c| c[0]).collect()
        };
        let reference: Vec<f32> = {
            let sub = 2;
            let (w, h) = (env.width * sub, env.height * sub);
            let z_min = 10f32.to_radians().sin();
            let cells: Vec<([f32; 3], f32)> = (0..h)
                .flat_map(|y| (0..w).map(move |x| (x, y)))
                .map(|(x, y)| {
                    let d = env.pixel_to_dir((x as f32 + 0.5) / sub as f32, (y as f32 + 0.5) / sub as f32);
                    let (t0, t1) = (y as f32 / h as f32 * PI, (y + 1) as f32 / h as f32 * PI);
                    (d, 2.0 * PI / w as f32 * (t0.cos() - t1.cos()))
                })
                .collect();
            let s = cells.len();
            let mut dirs = Vec::with_capacity(n * s);
            let mut weights = Vec::with_capacity(n * s);
            for i in 0..n {
                let nn = mats.normal[i];
                for &(d, omega) in &cells {
                    dirs.push(d);
                    weights.push(if d[0] * nn[0] + d[1] * nn[1] + d[2] * nn[2] >= z_min { omega } else { 0.0 });
                }
            }
            let (visibility, indirect) = (vec![1.0f32; n * s], vec![[0.0f32; 3]; n * s]);
            let inp = crate::shade::pbr::PbrInputs {
                albedo: &mats.albedo,
                roughness: &mats.roughness,
                normal: &mats.normal,
                view: &mats.normal,
                dirs: &dirs,
                visibility: &visibility,
                indirect: &indirect,
                samples: s,
                weight: 0.0,
                sample_weights: Some(&weights),
                specular: true,
                lambert: true,
                footprints: None,
            };
            let (mut d, mut i) = (vec![[0.0f32; 3]; n], vec![[0.0f32; 3]; n]);
            shade_surfels(&inp, &env, &mut d, &mut i).unwrap();
            d.iter().map(|c| c[0]).collect()
        };
        let error = |v: &[f32]| -> f32 { v.iter().zip(&reference).map(|(a, b)| (a - b).powi(2)).sum::<f32>() };
        let (fib, mixed) = (error(&direct(64, 0.0)), error(&direct(64, 0.5)));
        let mean_square = reference.iter().map(|r| r * r).sum::<f32>();
        // Measured: squared error 0.84 with Fibonacci directions only, 1.4e-5 mixed, of 0.94.
        assert!(mixed < 0.1 * fib, "squared error: mixed {mixed}, Fibonacci {fib}");
        assert!(mixed < 0.01 * mean_square, "squared error: mixed {mixed} of {mean_square}");
    }

    /// A relit run records its traced sampling; one relit before it did reads as all Fibonacci
    /// at the run's `pbr_samples`, and a damaged record falls back the same way.
    #[test]
    fn relit_runs_record_their_sampling() {
        let dir = crate::test_dir::TempDir::new("relit-sampling");
        assert_eq!(run_sampling(&dir, 64), (64, 0.0));
        let write = |text: &str| std::fs::write(dir.join("relight.json"), text).unwrap();
        write(r#"{"mode": "traced", "bounces": 4}"#);
        assert_eq!(run_sampling(&dir, 64), (64, 0.0));
        write(r#"{"mode": "traced", "bounces": 4, "samples": 128, "env_importance": 0.25}"#);
        assert_eq!(run_sampling(&dir, 64), (128, 0.25));
        write(r#"{"mode": "traced", "samples": 0, "env_importance": 3.0}"#);
        assert_eq!(run_sampling(&dir, 32), (32, 0.0));
    }

    /// Multi-bounce traced light equals tracing each bounce again with the previous bounce's
    /// radiance as the payload (an independent path through the tracer's feature compositing).
    #[test]
    fn traced_bounces_match_tracing_every_bounce_again() {
        let mut s = Surfels::random_in_box(400, [-1.0; 3], [1.0; 3], 4);
        for (i, a) in s.albedo_logits.iter_mut().enumerate() {
            *a = [0.5, 1.5, -0.5].map(|x| x + 0.01 * i as f32);
        }
        let mut mats = MaterialView::default();
        mats.update(&s);
        let mut env = EnvMap::constant(32, 16, [1.2, 0.9, 0.6]);
        // A peak for half the directions to be drawn from.
        env.texels[4 * 32 + 9] = [900.0, 800.0, 700.0];
        let start = RayStart { offset: 1e-3, skip_margin: Some(0.02) };
        let (samples, seed, factor) = (8, 11, 2);
        let tracer = Tracer::build(&s, &crate::train::inverse::trace_settings());
        let split = SplitSum::new(&env).unwrap();
        let mut radiance: Vec<f32> = (0..s.len())
            .flat_map(|i| {
                let o = split.shade(mats.albedo[i], mats.roughness[i], mats.normal[i], mats.normal[i]);
                [0, 1, 2].map(|c| o.diffuse[c] + o.specular[c])
            })
            .collect();
        let env_s = env.box_downsample(factor);
        let mut reference = IncidentCache::default();
        // Half of each surfel's directions from the map: the recorded rays are the same ones.
        reference.importance = Some(EnvImportance::of_map(&env_s, samples, 0.5).expect("the map has a sun"));
        let mut previous: Option<Vec<[f32; 3]>> = None;
        for bounces in 1..=3 {
            reference.refresh_with(&tracer, &s, samples, start, seed, Some(&radiance));
            let fast = traced_cache(&s, &mats, &env, samples, start, seed, factor, bounces, 0.5, &BackFaces::default())
                .unwrap();
            assert_eq!(fast.sample_weights, reference.sample_weights);
            assert_eq!(fast.dirs, reference.dirs);
            assert_eq!(fast.visibility, reference.visibility);
            for (k, (a, b)) in fast.indirect.iter().zip(&reference.indirect).enumerate() {
                for c in 0..3 {
                    assert!((a[c] - b[c]).abs() <= 1e-5 * (1.0 + b[c].abs()), "bounces {bounces}, ray {k}");
                }
            }
            // Each bounce changes the light (the test would not see a missing bounce otherwise).
            if let Some(p) = &previous {
                let change: f32 = p.iter().zip(&fast.indirect).map(|(a, b)| (a[0] - b[0]).abs()).sum();
                assert!(change > 1e-3, "bounce {bounces} changed nothing");
            }
            previous = Some(fast.indirect.clone());
            let inp = reference.inputs(&mats.albedo, &mats.roughness, &mats.normal, &mats.normal);
            let (mut d, mut i) = (vec![[0.0f32; 3]; s.len()], vec![[0.0f32; 3]; s.len()]);
            shade_surfels(&inp, &env_s, &mut d, &mut i).unwrap();
            radiance = (0..s.len()).flat_map(|j| [0, 1, 2].map(|c| d[j][c] + i[j][c])).collect();
        }
    }

    #[test]
    fn prepare_env_resamples_and_rotates() {
        let dir = crate::test_dir::TempDir::new("relight");
        let mut env = EnvMap::constant(64, 32, [0.1; 3]);
        // A bright spot at +x (u = 0.5).
        env.texels[16 * 64 + 32] = [50.0; 3];
        let path = dir.join("spot.exr");
        env.save(&path).unwrap();
        let e0 = prepare_env(&path, 0.0, 8).unwrap();
        let e90 = prepare_env(&path, 90.0, 8).unwrap();
        assert_eq!((e0.width, e0.height), (16, 8));
        let bright = |e: &EnvMap, d: [f32; 3]| e.lookup(d)[0];
        assert!(bright(&e0, [1.0, 0.0, 0.0]) > 2.0 * bright(&e0, [0.0, 1.0, 0.0]));
        // Rotated by +90° (counter-clockwise seen from above): the spot moves from +x to +y.
        assert!(bright(&e90, [0.0, 1.0, 0.0]) > 2.0 * bright(&e90, [1.0, 0.0, 0.0]));
        assert!(EnvMap::load(&dir.join("missing.exr")).is_err());
    }
}
