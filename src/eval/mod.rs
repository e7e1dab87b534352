//! `radiogs eval`: render every test view of a run and compare with the dataset (DESIGN §5,
//! TensoIR's protocol): PSNR over the full image per view, averaged; SSIM (11×11 Gaussian,
//! σ 1.5); normal MAE in degrees over all pixels with the background counting as 0 error.
//! Prediction and GT are both composited over the same background (white, as NeRF-synthetic
//! evaluations do). Writes `RUN/eval/*.png` and `RUN/eval/metrics.json`.

use crate::io::dataset::{Dataset, Pass, Split};
use crate::io::image::{Image, write_image};
use crate::loss::{psnr, ssim_eval};
use crate::raster::{self, Outputs, RasterSettings};
use crate::surfels::Surfels;
use crate::train::config::{MAX_DOWNSCALE, TrainConfig};
use anyhow::Context;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Evaluate a run against a dataset's test views.
#[derive(clap::Args, Debug, Clone)]
pub struct EvalArgs {
    /// Trained run folder.
    #[arg(long)]
    pub run: PathBuf,
    /// Dataset folder (defaults to the run's training data).
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Where else to write the metrics (RUN/eval/metrics.json is always written, beside the
    /// pictures; `-`: all of them to standard output instead of their means).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Evaluate only the first N test views (0 = all).
    #[arg(long, default_value_t = 0)]
    pub limit: usize,
    /// Skip relighting (otherwise every relit image set with a matching env map is evaluated,
    /// in both relighting modes).
    #[arg(long)]
    pub no_relight: bool,
    /// Finetune iterations per light for the relighting evaluation.
    #[arg(long, default_value_t = 300)]
    pub relight_iters: u32,
    /// Traced rays per consistency surfel in each finetune iteration (as `relight --rc-rays`).
    #[arg(long, default_value_t = crate::relight::RC_RAYS)]
    pub relight_rc_rays: usize,
    /// Incident directions per surfel for the ray-traced relighting.
    #[arg(long, default_value_t = 64)]
    pub relight_samples: usize,
    /// Share of those directions drawn from the new map's bright peaks (as `relight
    /// --env-importance`; 0 = Fibonacci only).
    #[arg(long, default_value_t = crate::relight::ENV_IMPORTANCE)]
    pub relight_env_importance: f32,
    /// Light bounces of the ray-traced relighting prediction (and of the finetune's start).
    #[arg(long, default_value_t = crate::relight::TRACED_BOUNCES)]
    pub relight_bounces: usize,
    /// Evaluate on the test images shrunk by this factor (default: the run's `--resolution`,
    /// as 3DGS evaluates at its training `-r`; 1 = the files' full size).
    #[arg(short = 'r', long)]
    pub resolution: Option<u32>,
}

/// The run's surfels: `point_cloud.ply`, else the newest checkpoint's parameters (nvs, init
/// or inverse), named in a warning.
pub fn load_run_surfels(run: &Path) -> anyhow::Result<Surfels> {
    let ply = run.join("point_cloud.ply");
    if ply.is_file() {
        let mut s = crate::io::ply::read_ply(&ply)?;
        s.sh_degree = s.sh_degree.max(0);
        return Ok(s);
    }
    // An interrupted run has no PLY yet (or it was removed): the newest stage's checkpoint, so
    // that an inverse stage's light is not paired with the geometry stage's surfels.
    if let Some(ckpt) = newest_checkpoint(run) {
        let c = crate::train::checkpoint::Checkpoint::load(&ckpt)?;
        let surfels = c.get_surfels(&ckpt, "params")?;
        warn_once(format!("{}: no point_cloud.ply; using the surfels of {}", run.display(), ckpt.display()));
        return Ok(surfels);
    }
    anyhow::bail!(
        "{}: no point_cloud.ply, checkpoint.bin, checkpoint_init.bin or checkpoint_inverse.bin (is this a run folder?)",
        run.display()
    )
}

/// The most recently written of the run's nvs, init and inverse checkpoints.
/// The unseen flags saved with the run's surfels ([`load_run_surfels`]'s source: the PLY's
/// property `unseen`, else the newest checkpoint's blob), or None; and that source's name.
pub fn load_run_unseen(run: &Path) -> anyhow::Result<(Option<Vec<bool>>, String)> {
    let ply = run.join("point_cloud.ply");
    if ply.is_file() {
        return Ok((crate::io::ply::read_ply_unseen(&ply)?, ply.display().to_string()));
    }
    match newest_checkpoint(run) {
        Some(ckpt) => {
            let c = crate::train::checkpoint::Checkpoint::load(&ckpt)?;
            Ok((crate::train::inverse::unseen_flags(&ckpt, &c)?, ckpt.display().to_string()))
        }
        None => Ok((None, run.display().to_string())),
    }
}

fn newest_checkpoint(run: &Path) -> Option<PathBuf> {
    let modified = |p: &PathBuf| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    crate::train::inverse::geometry_checkpoint(run)
        .into_iter()
        .chain(Some(crate::train::inverse::checkpoint_path(run)).filter(|p| p.is_file()))
        .max_by_key(modified)
}

/// Warn once per process (a run's surfels are read by several loaders in one command).
pub(crate) fn warn_once(message: String) {
    static SAID: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());
    let mut said = SAID.lock().unwrap_or_else(|e| e.into_inner());
    if !said.contains(&message) {
        tracing::warn!("{message}");
        said.push(message);
    }
}

/// The run's settings (`RUN/config.toml`), or defaults when absent.
pub fn load_run_config(run: &Path) -> anyhow::Result<TrainConfig> {
    let path = run.join("config.toml");
    if !path.is_file() {
        // Not trained by radiogs (e.g. a 2DGS output folder): its surfels were fitted with
        // 2DGS's screen-space filter unless a radiogs PLY header says otherwise.
        let ply = run.join("point_cloud.ply");
        let recorded = if ply.is_file() { crate::io::ply::read_ply_filter_inv_square(&ply)? } else { None };
        let filter_inv_square = recorded.unwrap_or_else(crate::raster::filter_inv_square_2dgs);
        // Nor were they oriented by radiogs: no unseen flags, back faces culled.
        return Ok(TrainConfig {
            filter_inv_square,
            trace_back_faces: crate::train::config::TraceBackFaces::Cull,
            ..TrainConfig::default()
        });
    }
    let text = std::fs::read_to_string(&path).with_context(|| format!("{}: cannot read", path.display()))?;
    let mut cfg: TrainConfig = toml::from_str(&text).map_err(|e| crate::train::config::toml_error(&path, &text, &e))?;
    // An edited file is checked as `train` checks its settings (a NaN filter renders nothing).
    cfg.validate().map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    // After the inverse stage the surfels are oriented (with flipped twins where a wall is
    // seen from both sides) and must be drawn with back faces culled.
    if run.join("envmap.exr").is_file() {
        cfg.two_sided = false;
    }
    cfg.data = dataset_of_run(run, &cfg.data, &cfg.out);
    Ok(cfg)
}

/// Where a run's dataset is. The run records `--data` and `--out` as they were typed, relative
/// to the folder training ran in, so from another folder a relative `data` misses. When `run`
/// ends with the recorded `out`, that folder is `run` without those last components, and the
/// dataset is `data` there (`--data demo/data --out demo/run` trained in X: X/demo/data). Any
/// other case keeps `data` as recorded.
fn dataset_of_run(run: &Path, data: &Path, out: &Path) -> PathBuf {
    if data.as_os_str().is_empty() || data.is_absolute() || data.exists() || out.is_absolute() {
        return data.to_path_buf();
    }
    let Ok(run) = std::path::absolute(run) else { return data.to_path_buf() };
    if out.as_os_str().is_empty() || !run.ends_with(out) {
        return data.to_path_buf();
    }
    let mut trained_in = run;
    for _ in out.components() {
        trained_in.pop();
    }
    let found = trained_in.join(data);
    if found.exists() { found } else { data.to_path_buf() }
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct ViewMetrics {
    pub view: String,
    pub psnr: f32,
    pub ssim: f32,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_mae_deg: Option<f32>,
    pub render_ms: f64,
}

/// Mean angular error (degrees) over all pixels; pixels outside the GT mask count as 0.
pub fn normal_mae_degrees(pred: &[[f32; 3]], gt: &Image) -> f32 {
    let mut sum = 0.0f64;
    for (i, p) in pred.iter().enumerate() {
        let g = &gt.data[i * gt.channels..i * gt.channels + 3];
        let mask = if gt.channels >= 4 { gt.data[i * gt.channels + 3] } else { 1.0 };
        if mask < 0.5 {
            continue;
        }
        // f64: squares of any finite f32 stay finite (a GT pass may hold huge values).
        let (p, g) = (p.map(f64::from), [g[0], g[1], g[2]].map(f64::from));
        let lp = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        let lg = (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt();
        let cos = if lp > 1e-8 && lg > 1e-8 { (p[0] * g[0] + p[1] * g[1] + p[2] * g[2]) / (lp * lg) } else { 0.0 };
        sum += cos.clamp(-1.0, 1.0).acos().to_degrees();
    }
    (sum / pred.len().max(1) as f64) as f32
}

fn rgb_over(img: &Image, bg: [f32; 3]) -> Vec<[f32; 3]> {
    img.data.chunks_exact(4).map(|p| [0, 1, 2].map(|k| p[k] * p[3] + bg[k] * (1.0 - p[3]))).collect()
}

fn to_image(rgb: &[[f32; 3]], alpha: Option<&[f32]>, w: u32, h: u32) -> Image {
    let mut img = Image::new(w, h, 4);
    for (i, px) in img.data.chunks_exact_mut(4).enumerate() {
        px[..3].copy_from_slice(&rgb[i]);
        px[3] = alpha.map_or(1.0, |a| a[i]);
    }
    img
}

fn straight_to_image(rgb: &[[f32; 3]], alpha: &[f32], w: u32, h: u32, f: impl Fn(f32) -> f32) -> Image {
    let rgb: Vec<[f32; 3]> = rgb.iter().map(|c| c.map(&f)).collect();
    to_image(&rgb, Some(alpha), w, h)
}

/// The recovered light against the true one, as white Lambertian surfaces facing the six axis
/// directions would see them (see [`compare_light`]).
#[derive(Clone, Debug, serde::Serialize)]
pub struct LightComparison {
    pub normals: Vec<LightAtNormal>,
    /// Mean over the normals and channels of |ln(ours / GT)|, both floored at 1e-3 × the
    /// truth's mean.
    pub log_error: f32,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct LightAtNormal {
    pub normal: String,
    pub ours: [f32; 3],
    pub gt: [f32; 3],
}

/// Compare a recovered env with the true one through [`EnvMap::lambert_radiance`] for the six
/// axis normals. `albedo_scale` is the eval's median albedo scale: an albedo × s renders the
/// same images as the env ÷ s, so ours is divided by it per channel first.
pub fn compare_light(
    ours: &crate::envmap::EnvMap,
    gt: &crate::envmap::EnvMap,
    albedo_scale: [f32; 3],
) -> LightComparison {
    let normals: Vec<LightAtNormal> = crate::envmap::AXIS_NORMALS
        .iter()
        .map(|&(name, n)| {
            let o = ours.lambert_radiance(n);
            LightAtNormal {
                normal: name.to_string(),
                ours: std::array::from_fn(|c| o[c] / albedo_scale[c].max(1e-6)),
                gt: gt.lambert_radiance(n),
            }
        })
        .collect();
    // Values below 1e-3 × the truth's mean count as that floor, so a black direction scores
    // a large but finite error.
    let mean_gt = normals.iter().flat_map(|l| l.gt).sum::<f32>() / 18.0;
    let floor = (1e-3 * mean_gt).max(1e-12);
    let sum: f64 = normals
        .iter()
        .flat_map(|l| (0..3).map(|c| ((l.ours[c].max(floor) / l.gt[c].max(floor)) as f64).ln().abs()))
        .sum();
    LightComparison { normals, log_error: (sum / 18.0) as f32 }
}

/// Per-channel median of gt/pred over the masked pixels of every view (the TensoIR albedo
/// scale; 1 where there is nothing to measure).
pub fn median_scale(pairs: &[(Vec<[f32; 3]>, Vec<[f32; 3]>, Vec<f32>)]) -> [f32; 3] {
    std::array::from_fn(|ch| {
        let mut r: Vec<f32> = pairs
            .iter()
            .flat_map(|(pred, gt, mask)| {
                pred.iter()
                    .zip(gt)
                    .zip(mask)
                    .filter(|((p, _), m)| **m > 0.5 && p[ch] > 1e-4)
                    .map(move |((p, g), _)| g[ch] / p[ch])
            })
            .collect();
        if r.is_empty() {
            return 1.0;
        }
        let mid = r.len() / 2;
        *r.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
    })
}

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct PbrViewMetrics {
    pub view: String,
    pub pbr_psnr: f32,
    pub pbr_ssim: f32,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub albedo_psnr: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub albedo_psnr_masked: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub albedo_ssim: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub roughness_mse: Option<f32>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub indirect_psnr: Option<f32>,
    /// What a noise-free prediction of the GT indirect pass could score: see
    /// [`noise_ceiling_psnr`].
    #[serde(skip_serializing_if = "Option::is_none")]
    pub indirect_noise_ceiling_psnr: Option<f32>,
}

/// The PSNR a noise-free prediction would score against a noisy (path-traced, not denoised)
/// GT pass: −10·log10 σ̂², σ̂² the mean over masked pixels of (g − m)²·k/(k − 1), m the mean of
/// the k ≥ 2 masked pixels of its 3×3 box (i.i.d. pixel noise leaves (k − 1)/k of its variance
/// in that residual). Texture and edges inside the box also count as noise, so this is a lower
/// estimate of the ceiling.
pub fn noise_ceiling_psnr(g: &[[f32; 3]], mask: &[f32], w: usize, h: usize) -> f32 {
    let (mut se, mut cnt) = (0.0f64, 0usize);
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            if mask[p] <= 0.5 {
                continue;
            }
            let (mut mean, mut k) = ([0.0f64; 3], 0usize);
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    if mask[yy * w + xx] > 0.5 {
                        k += 1;
                        for c in 0..3 {
                            mean[c] += g[yy * w + xx][c] as f64;
                        }
                    }
                }
            }
            if k < 2 {
                continue;
            }
            let kf = k as f64;
            for c in 0..3 {
                se += (g[p][c] as f64 - mean[c] / kf).powi(2) * kf / (kf - 1.0);
            }
            cnt += 3;
        }
    }
    if cnt == 0 {
        return f32::NAN;
    }
    (-10.0 * (se / cnt as f64).max(1e-12).log10()) as f32
}

/// One view's albedo errors, `scaled` being our linear albedo after the median scale and `gt`
/// the decoded GT albedo; only pixels inside the GT mask (alpha > 0.5) can err, as TensoIR's
/// protocol paints both images' background the same colour.
#[derive(Clone, Copy, Debug)]
pub struct AlbedoErrors {
    /// DESIGN §5: linear, over the full image (the background counts as 0 error).
    pub full_psnr: f32,
    /// The same squared errors averaged over the masked pixels only: eval's albedo PSNR up to
    /// session 60, kept so earlier figures stay comparable.
    pub masked_psnr: f32,
    /// Sum of squared errors as TensoIR's evaluation takes them (ours clipped to [0, 1], both
    /// raised to 1/2.2) and the number of values over the full image, to be pooled over views.
    pub gamma_se: f64,
    pub values: usize,
}

pub fn albedo_errors(scaled: &[[f32; 3]], gt: &[[f32; 3]], mask: &[f32]) -> AlbedoErrors {
    let (mut se, mut gamma_se, mut masked) = (0.0f64, 0.0f64, 0usize);
    for ((p, g), &a) in scaled.iter().zip(gt).zip(mask) {
        if a <= 0.5 {
            continue;
        }
        masked += 3;
        for c in 0..3 {
            se += (p[c] as f64 - g[c] as f64).powi(2);
            let enc = |x: f64| x.clamp(0.0, 1.0).powf(1.0 / 2.2);
            gamma_se += (enc(p[c] as f64) - enc(g[c] as f64)).powi(2);
        }
    }
    let psnr = |se: f64, n: usize| if n == 0 { f32::NAN } else { (-10.0 * (se / n as f64).max(1e-20).log10()) as f32 };
    AlbedoErrors {
        full_psnr: if masked == 0 { f32::NAN } else { psnr(se, 3 * gt.len()) },
        masked_psnr: psnr(se, masked),
        gamma_se,
        values: 3 * gt.len(),
    }
}

/// The material / light metrics of a run with a recovered env (DESIGN §5).
fn eval_pbr(
    scene: &crate::pbr_scene::PbrScene,
    views: &[crate::io::dataset::View],
    out_dir: &Path,
    bg: [f32; 3],
) -> anyhow::Result<(Vec<PbrViewMetrics>, serde_json::Value)> {
    use crate::io::image::{linear_to_srgb, srgb_to_linear};
    use crate::loss::psnr_masked;
    let mut renders = Vec::new();
    for view in views {
        renders.push(scene.render(&view.camera, bg));
    }
    // Albedo scale from every test view.
    let mut pairs = Vec::new();
    for (view, img) in views.iter().zip(&renders) {
        if let Some(gt) = view.load_pass(Pass::Albedo)? {
            let g: Vec<[f32; 3]> = gt.data.chunks_exact(4).map(|p| [p[0], p[1], p[2]].map(srgb_to_linear)).collect();
            let m: Vec<f32> = gt.data.chunks_exact(4).map(|p| p[3]).collect();
            pairs.push((img.albedo.clone(), g, m));
        }
    }
    let scale = median_scale(&pairs);
    let mut metrics = Vec::new();
    let mut albedo_gamma = (0.0f64, 0usize);
    let mut pair_iter = pairs.iter();
    for (view, img) in views.iter().zip(&renders) {
        let cam = &view.camera;
        let (w, h) = (cam.width as usize, cam.height as usize);
        let gt = view.load_image()?;
        let gt_rgb = rgb_over(&gt, bg);
        let gt_mask: Vec<f32> = gt.data.chunks_exact(4).map(|p| p[3]).collect();
        let mut m = PbrViewMetrics {
            view: cam.name.clone(),
            pbr_psnr: psnr(&img.pbr, &gt_rgb),
            pbr_ssim: ssim_eval(&img.pbr, &gt_rgb, w, h)?,
            ..Default::default()
        };
        if view.load_pass(Pass::Albedo)?.is_some()
            && let Some((pred, g, mask)) = pair_iter.next()
        {
            let scaled: Vec<[f32; 3]> = pred.iter().map(|p| [0, 1, 2].map(|k| p[k] * scale[k])).collect();
            let e = albedo_errors(&scaled, g, mask);
            m.albedo_psnr = Some(e.full_psnr);
            m.albedo_psnr_masked = Some(e.masked_psnr);
            albedo_gamma.0 += e.gamma_se;
            albedo_gamma.1 += e.values;
            let on_black = |v: &[[f32; 3]]| -> Vec<[f32; 3]> {
                v.iter()
                    .zip(mask)
                    .map(|(c, &a)| if a > 0.5 { c.map(|x| x.clamp(0.0, 1.0)) } else { [0.0; 3] })
                    .collect()
            };
            m.albedo_ssim = Some(ssim_eval(&on_black(&scaled), &on_black(g), w, h)?);
            write_image(
                &out_dir.join(format!("{}_albedo.png", cam.name)),
                &straight_to_image(&scaled, &img.alpha, cam.width, cam.height, linear_to_srgb),
            )?;
        }
        if let Some(gt_r) = view.load_pass(Pass::Roughness)? {
            let (mut sum, mut cnt) = (0.0f64, 0usize);
            for (p, px) in gt_r.data.chunks_exact(4).enumerate() {
                if px[3] > 0.5 {
                    sum += ((img.roughness[p] - px[0]) as f64).powi(2);
                    cnt += 1;
                }
            }
            m.roughness_mse = Some((sum / cnt.max(1) as f64) as f32);
        }
        if let Some(gt_i) = view.load_pass(Pass::Indirect)? {
            let enc = |c: [f32; 3]| c.map(|x| linear_to_srgb(x.clamp(0.0, 1.0)));
            let g: Vec<[f32; 3]> = gt_i.data.chunks_exact(4).map(|p| enc([p[0], p[1], p[2]])).collect();
            let pred: Vec<[f32; 3]> = img.indirect.iter().map(|c| enc(*c)).collect();
            m.indirect_psnr = Some(psnr_masked(&pred, &g, &gt_mask));
            m.indirect_noise_ceiling_psnr = Some(noise_ceiling_psnr(&g, &gt_mask, w, h));
            write_image(
                &out_dir.join(format!("{}_indirect.png", cam.name)),
                &to_image(&pred, Some(&img.alpha), cam.width, cam.height),
            )?;
            // The GT pass beside ours, encoded the same way, so the two can be compared by eye.
            write_image(
                &out_dir.join(format!("{}_indirect_gt.png", cam.name)),
                &to_image(&g, Some(&gt_mask), cam.width, cam.height),
            )?;
        }
        let rough: Vec<[f32; 3]> = img.roughness.iter().map(|&r| [r; 3]).collect();
        write_image(
            &out_dir.join(format!("{}_roughness.png", cam.name)),
            &to_image(&rough, Some(&img.alpha), cam.width, cam.height),
        )?;
        write_image(&out_dir.join(format!("{}_pbr.png", cam.name)), &to_image(&img.pbr, None, cam.width, cam.height))?;
        metrics.push(m);
    }
    let protocol = serde_json::json!({
        "pbr": "per-surfel Monte Carlo PBR with the cached incident light, rasterised, linear -> sRGB, over white; PSNR/SSIM as NVS",
        "albedo": format!("linear albedo scaled per channel by the median of gt/pred over all masked test pixels \
                   (scale {:?}); GT albedo.png decoded from sRGB; albedo_psnr: PSNR per view over the full image \
                   (DESIGN 5), errors only inside the GT mask (alpha > 0.5), then averaged; albedo_psnr_masked: the \
                   same errors averaged over the GT-masked pixels only (eval's albedo_psnr up to session 60); \
                   albedo_psnr_tensoir: TensoIR's evaluation, ours clipped to [0,1], both raised to 1/2.2, squared \
                   errors pooled over every view's full image; SSIM on both images masked onto black", scale),
        "roughness": "MSE over GT-masked pixels against roughness.png (linear)",
        "indirect": "ours = L_ind part of each surfel's rendering equation, rasterised; GT = indirect.exr RGB; \
                     both clipped to [0,1] and sRGB-encoded; PSNR over GT-masked pixels; \
                     GT and ours side by side as test_*_indirect_gt.png / test_*_indirect.png",
        "indirect_noise_ceiling": "the PSNR a noise-free prediction could reach against the (noisy) GT pass: \
                     -10 log10 of 9/8 x the mean squared residual of the sRGB GT against its own 3x3 box mean over \
                     the GT mask (i.i.d. pixel-noise estimate; texture inside 3x3 counts as noise, so a lower estimate)",
        "albedo_scale": scale,
        "albedo_psnr_tensoir": (albedo_gamma.1 > 0)
            .then(|| -10.0 * (albedo_gamma.0 / albedo_gamma.1 as f64).max(1e-20).log10()),
    });
    Ok((metrics, protocol))
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct RelightMetrics {
    pub light: String,
    pub mode: &'static str,
    pub psnr: f32,
    pub ssim: f32,
    pub seconds: f64,
    /// Mean time of one relit frame (rasterised, or traced shading + rasterisation).
    pub frame_ms: f64,
    /// Test views with a relit image of this light (the means are over these).
    pub views: usize,
}

/// Relight under every dataset light with relit images, both modes (DESIGN §5: sRGB, the
/// prediction masked by the GT alpha over white, the albedo scale applied).
fn eval_relight(
    scene: &crate::pbr_scene::PbrScene,
    dataset: &Dataset,
    views: &[crate::io::dataset::View],
    scale: [f32; 3],
    args: &EvalArgs,
    cfg: &TrainConfig,
    extent: f32,
    out_dir: &Path,
) -> anyhow::Result<Vec<RelightMetrics>> {
    use crate::relight::{FinetuneSettings, finetune, prepare_env, traced_cache};
    let mut mats = scene.mats.clone();
    for a in mats.albedo.iter_mut() {
        *a = [0, 1, 2].map(|k| (a[k] * scale[k]).clamp(0.0, 1.0));
    }
    let cameras: Vec<crate::camera::Camera> = dataset.train.iter().map(|v| v.camera.clone()).collect();
    let start = cfg.ray_start(extent);
    let white = [1.0f32; 3];
    let mut results = Vec::new();
    for name in dataset.relit_found() {
        let Some(path) = dataset.envmap_path(&name) else { continue };
        let env = prepare_env(path, 0.0, cfg.env_height)?;
        // The traced mode's incident light is also the finetune's start (same settings).
        let mut light_cache = None;
        for mode in ["traced", "finetune"] {
            let t0 = Instant::now();
            let mut surfels = scene.surfels.clone();
            let traced_scene;
            let mut frame_ms = 0.0;
            let mut psnrs = Vec::new();
            let mut ssims = Vec::new();
            if mode == "traced" {
                let factor = crate::train::inverse::sample_factor(cfg);
                let bounces = args.relight_bounces;
                let cache = traced_cache(
                    &surfels,
                    &mats,
                    &env,
                    args.relight_samples,
                    start,
                    cfg.seed,
                    factor,
                    bounces,
                    args.relight_env_importance,
                    &scene.back_faces,
                )?;
                light_cache = Some(cache.clone());
                traced_scene = Some(crate::pbr_scene::PbrScene {
                    surfels: surfels.clone(),
                    env: env.clone(),
                    cache,
                    mats: mats.clone(),
                    window: cfg.window,
                    filter_inv_square: cfg.filter_inv_square,
                    sample_factor: crate::train::inverse::sample_factor(cfg),
                    specular: cfg.specular,
                    ray_start: start,
                    specular_rays: crate::pbr_scene::RENDER_RAYS_FACTOR * cfg.specular_rays,
                    seed: cfg.seed,
                    back_faces: scene.back_faces.clone(),
                });
            } else {
                let settings = FinetuneSettings {
                    iters: args.relight_iters,
                    rc_surfels: 2048,
                    rc_rays: args.relight_rc_rays,
                    samples: args.relight_samples,
                    start,
                    lr_sh: cfg.lr_sh,
                    sample_factor: crate::train::inverse::sample_factor(cfg),
                    bounces: args.relight_bounces,
                    env_importance: args.relight_env_importance,
                    back_faces: scene.back_faces.clone(),
                    seed: cfg.seed,
                };
                finetune(&mut surfels, &mats, &env, &cameras, &settings, true, light_cache.as_ref())?;
                traced_scene = None;
            }
            // The prefiltered map of a split-sum lobe, once per light (not per frame).
            let split_sum = traced_scene.as_ref().and_then(|sc| sc.split_sum());
            let setup = t0.elapsed().as_secs_f64();
            for (k, view) in views.iter().enumerate() {
                let Some(gt) = view.load_relit(&name)? else { continue };
                let cam = &view.camera;
                let tf = Instant::now();
                let pred = match &traced_scene {
                    Some(sc) => sc.render_with(cam, white, split_sum.as_ref()).pbr,
                    None => {
                        let settings = RasterSettings {
                            window: cfg.window,
                            filter_inv_square: cfg.filter_inv_square,
                            two_sided: false,
                            background: white,
                            outputs: Outputs::colour_only(),
                            ..RasterSettings::default()
                        };
                        raster::render(&surfels, cam, &settings, None).0.colour
                    }
                };
                frame_ms += tf.elapsed().as_secs_f64() * 1e3;
                let gt_rgb = rgb_over(&gt, white);
                let masked: Vec<[f32; 3]> = pred
                    .iter()
                    .zip(gt.data.chunks_exact(4))
                    .map(|(p, g)| [0, 1, 2].map(|c| p[c].clamp(0.0, 1.0) * g[3] + (1.0 - g[3])))
                    .collect();
                psnrs.push(psnr(&masked, &gt_rgb));
                ssims.push(ssim_eval(&masked, &gt_rgb, cam.width as usize, cam.height as usize)?);
                if k < 2 {
                    write_image(
                        &out_dir.join(format!("{}_relit_{name}_{mode}.png", cam.name)),
                        &to_image(&masked, None, cam.width, cam.height),
                    )?;
                }
            }
            if psnrs.len() < views.len() {
                eprintln!(
                    "warning: relight {name}: {} of {} test views have no rgba_{name}.png; the means are over the other {}",
                    views.len() - psnrs.len(),
                    views.len(),
                    psnrs.len()
                );
            }
            let nviews = psnrs.len().max(1);
            let m = RelightMetrics {
                views: psnrs.len(),
                light: name.clone(),
                mode: if mode == "traced" { "traced" } else { "finetune" },
                psnr: psnrs.iter().sum::<f32>() / nviews as f32,
                ssim: ssims.iter().sum::<f32>() / nviews as f32,
                seconds: setup,
                frame_ms: frame_ms / nviews as f64,
            };
            eprintln!("relight {name} ({}): PSNR {:.2} dB, SSIM {:.4}, {:.1} s", m.mode, m.psnr, m.ssim, m.seconds);
            results.push(m);
        }
    }
    Ok(results)
}

pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    if !(1..=1024).contains(&args.relight_samples) {
        anyhow::bail!("--relight-samples {}: must be 1..=1024", args.relight_samples);
    }
    if !(1..=256).contains(&args.relight_rc_rays) {
        anyhow::bail!("--relight-rc-rays {}: must be 1..=256", args.relight_rc_rays);
    }
    crate::relight::check_env_importance("--relight-env-importance", args.relight_env_importance)?;
    if let Some(r) = args.resolution
        && !(1..=MAX_DOWNSCALE).contains(&r)
    {
        anyhow::bail!(
            "-r/--resolution {r}: the downscale factor of the test images must be in 1..={MAX_DOWNSCALE} (1 = full size)"
        );
    }
    if args.relight_bounces == 0 {
        anyhow::bail!("--relight-bounces 0: must be at least 1 (1 = the unoccluded env lights the hit surfels)");
    }
    if let Some(json) = &args.json
        && json.is_dir()
    {
        anyhow::bail!("--json {}: is a folder; give a file path (or - for standard output)", json.display());
    }
    let surfels = load_run_surfels(&args.run)?;
    let pbr_scene = crate::pbr_scene::PbrScene::from_run(&args.run)?;
    let cfg = load_run_config(&args.run)?;
    let data = match &args.data {
        Some(d) => d.clone(),
        None if !cfg.data.as_os_str().is_empty() => cfg.data.clone(),
        None => anyhow::bail!("{}: the run has no config.toml naming its dataset; pass --data DIR", args.run.display()),
    };
    let factor = args.resolution.unwrap_or(cfg.resolution);
    let dataset = Dataset::open_downscaled(&data, factor)?;
    let mut views = dataset.views(Split::Test).to_vec();
    if views.is_empty() {
        anyhow::bail!("{}: the dataset has no test views", data.display());
    }
    if args.limit > 0 {
        views.truncate(args.limit);
    }
    // Pictures and metrics go to RUN/eval.partial and replace RUN/eval only when all of them
    // are written: an evaluation that fails half-way (a bad file among the test passes) leaves
    // the previous one whole.
    let final_dir = args.run.join("eval");
    let partial = crate::io::atomic::PartialDir::beside(&final_dir)?;
    let out_dir = partial.path().to_path_buf();
    let bg = [1.0f32; 3];
    let settings = RasterSettings {
        window: cfg.window,
        filter_inv_square: cfg.filter_inv_square,
        two_sided: cfg.two_sided,
        background: bg,
        outputs: Outputs { colour: true, normal: true, ..Outputs::none() },
        ..RasterSettings::default()
    };
    let bar = indicatif::ProgressBar::new(views.len() as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("eval {bar:30} {pos}/{len} [{elapsed_precise}<{eta_precise}] {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let mut per_view = Vec::new();
    for view in &views {
        let gt = view.load_image()?;
        let cam = &view.camera;
        let t0 = Instant::now();
        // A run with materials is rendered as the PBR stages see it (back faces culled).
        let settings = RasterSettings { two_sided: settings.two_sided && pbr_scene.is_none(), ..settings };
        let (out, _) = raster::render(&surfels, cam, &settings, None);
        let render_ms = t0.elapsed().as_secs_f64() * 1e3;
        let gt_rgb = rgb_over(&gt, bg);
        let (w, h) = (cam.width as usize, cam.height as usize);
        let normal_mae_deg = match view.load_pass(Pass::Normal)? {
            Some(gt_normal) => Some(normal_mae_degrees(&out.normal, &gt_normal)),
            None => None,
        };
        let m = ViewMetrics {
            view: cam.name.clone(),
            psnr: psnr(&out.colour, &gt_rgb),
            ssim: ssim_eval(&out.colour, &gt_rgb, w, h)?,
            normal_mae_deg,
            render_ms,
        };
        write_image(&out_dir.join(format!("{}.png", cam.name)), &to_image(&out.colour, None, cam.width, cam.height))?;
        let normal_rgb: Vec<[f32; 3]> = out
            .normal
            .iter()
            .map(|n| {
                let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-8);
                n.map(|v| v / l * 0.5 + 0.5)
            })
            .collect();
        write_image(
            &out_dir.join(format!("{}_normal.png", cam.name)),
            &to_image(&normal_rgb, Some(&out.alpha), cam.width, cam.height),
        )?;
        bar.set_message(format!("{} PSNR {:.2}", cam.name, m.psnr));
        bar.inc(1);
        per_view.push(m);
    }
    bar.finish_and_clear();
    let pbr = match &pbr_scene {
        Some(scene) => {
            eprintln!("eval: PBR, albedo, roughness and indirect light of {} test views", views.len());
            // The recovered light beside the dataset's (same exposure: 1 / the GT's mean).
            let gt_env = match dataset.train_env.as_deref().and_then(|n| dataset.envmap_path(n)) {
                Some(p) => Some(crate::envmap::EnvMap::load(p)?.resample(scene.env.width, scene.env.height)),
                None => None,
            };
            let mean = gt_env.as_ref().unwrap_or(&scene.env).mean_radiance();
            let exposure = 0.5 / ((mean[0] + mean[1] + mean[2]) / 3.0).max(1e-6);
            write_image(&out_dir.join("envmap.png"), &scene.env.to_display_image(exposure))?;
            if let Some(g) = &gt_env {
                write_image(&out_dir.join("envmap_gt.png"), &g.to_display_image(exposure))?;
            }
            let (pm, mut protocol) = eval_pbr(scene, &views, &out_dir, bg)?;
            let scale: [f32; 3] = serde_json::from_value(protocol["albedo_scale"].clone()).unwrap_or([1.0; 3]);
            let light = gt_env.as_ref().map(|g| compare_light(&scene.env, g, scale));
            if light.is_some() {
                protocol["light"] = serde_json::json!(
                    "per axis normal (world, z up): the radiance a white Lambertian surface facing it reflects under \
                     the env alone, (1/pi) x the unoccluded cosine integral, ours divided by the albedo scale per \
                     channel (albedo x s renders as env / s) against the dataset's training env; \
                     light_lambert_log_error = mean over the 6 normals and 3 channels of |ln(ours / GT)|, both floored \
                     at 1e-3 x the GT's mean"
                );
            }
            let relit = if args.no_relight || dataset.relit_found().is_empty() {
                Vec::new()
            } else {
                let extent = crate::pbr_scene::scene_extent(&args.run);
                eval_relight(scene, &dataset, &views, scale, args, &cfg, extent, &out_dir)?
            };
            Some((pm, protocol, relit, light))
        }
        None => None,
    };
    let mean = |f: &dyn Fn(&ViewMetrics) -> Option<f32>| -> Option<f32> {
        let v: Vec<f32> = per_view.iter().filter_map(f).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f32>() / v.len() as f32)
    };
    let summary = serde_json::json!({
        "dataset": data.display().to_string(),
        "run": args.run.display().to_string(),
        "views": per_view.len(),
        "downscale": factor,
        "resolution": [views[0].camera.width, views[0].camera.height],
        "surfels": surfels.len(),
        "protocol": "PSNR/SSIM per view on the full image, prediction and GT composited over white, then averaged; \
                     SSIM 11x11 Gaussian sigma 1.5; normal MAE in degrees over all pixels, background (GT alpha < 0.5) counting as 0",
        "mean": {
            "psnr": mean(&|m| Some(m.psnr)),
            "ssim": mean(&|m| Some(m.ssim)),
            "normal_mae_deg": mean(&|m| m.normal_mae_deg),
            "render_ms": mean(&|m| Some(m.render_ms as f32)),
        },
        "per_view": per_view,
    });
    let mut summary = summary;
    if let Some((pm, protocol, relit, light)) = &pbr {
        let pmean = |f: &dyn Fn(&PbrViewMetrics) -> Option<f32>| -> Option<f32> {
            let v: Vec<f32> = pm.iter().filter_map(f).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f32>() / v.len() as f32)
        };
        let mut mean = serde_json::Map::new();
        mean.insert("pbr_psnr".into(), serde_json::json!(pmean(&|m| Some(m.pbr_psnr))));
        mean.insert("pbr_ssim".into(), serde_json::json!(pmean(&|m| Some(m.pbr_ssim))));
        mean.insert("albedo_psnr".into(), serde_json::json!(pmean(&|m| m.albedo_psnr)));
        mean.insert("albedo_psnr_masked".into(), serde_json::json!(pmean(&|m| m.albedo_psnr_masked)));
        mean.insert("albedo_psnr_tensoir".into(), protocol["albedo_psnr_tensoir"].clone());
        mean.insert("albedo_ssim".into(), serde_json::json!(pmean(&|m| m.albedo_ssim)));
        mean.insert("roughness_mse".into(), serde_json::json!(pmean(&|m| m.roughness_mse)));
        mean.insert("indirect_psnr".into(), serde_json::json!(pmean(&|m| m.indirect_psnr)));
        mean.insert("indirect_noise_ceiling_psnr".into(), serde_json::json!(pmean(&|m| m.indirect_noise_ceiling_psnr)));
        let mut extra = serde_json::Map::new();
        if let Some(l) = light {
            mean.insert("light_lambert_log_error".into(), serde_json::json!(l.log_error));
            extra.insert("light".into(), serde_json::to_value(&l.normals)?);
        }
        extra.insert("pbr_protocol".into(), protocol.clone());
        extra.insert("pbr_per_view".into(), serde_json::to_value(pm)?);
        if !relit.is_empty() {
            for mode in ["traced", "finetune"] {
                let v: Vec<&RelightMetrics> = relit.iter().filter(|m| m.mode == mode).collect();
                let k = v.len().max(1) as f32;
                mean.insert(
                    format!("relight_{mode}_psnr"),
                    serde_json::json!(v.iter().map(|m| m.psnr).sum::<f32>() / k),
                );
                mean.insert(
                    format!("relight_{mode}_ssim"),
                    serde_json::json!(v.iter().map(|m| m.ssim).sum::<f32>() / k),
                );
            }
            extra.insert("relight".into(), serde_json::to_value(relit)?);
            extra.insert("relight_protocol".into(), serde_json::json!(format!(
                "per light with rgba_<light>.png and envmaps/<light>: albedo × the median scale; traced = per-surfel \
                 rendering equation with {} traced directions ({} of them drawn from the new map's peaks, texels \
                 above 10 × its mean, where it has any; the rest Fibonacci; balance heuristic; visibility + indirect light over {} bounces, the first \
                 from the hit surfels' split-sum colour) under the new map; finetune = SH started at that prediction \
                 and finetuned {} iterations by radiometric consistency (2048 surfels × {} traced rays a step), \
                 rasterised; prediction clipped to [0,1], masked by the GT alpha over white, PSNR/SSIM in sRGB, \
                 averaged over test views",
                args.relight_samples,
                (args.relight_env_importance * args.relight_samples as f32).round() as usize,
                args.relight_bounces,
                args.relight_iters,
                args.relight_rc_rays
            )));
        }
        if let Some(m) = summary["mean"].as_object_mut() {
            m.extend(mean);
        }
        if let Some(o) = summary.as_object_mut() {
            o.extend(extra);
        }
    }
    let text = serde_json::to_string_pretty(&summary)?;
    // Always beside the pictures, `--json` or not: publishing replaces the last evaluation's
    // folder whole, which would otherwise leave pictures without their figures.
    crate::io::atomic::write_atomic(&out_dir.join("metrics.json"), text.as_bytes())?;
    partial.publish(&final_dir)?;
    if args.json.as_deref() == Some(Path::new("-")) {
        println!("{text}");
        return Ok(());
    }
    let path = args.json.clone().unwrap_or_else(|| final_dir.join("metrics.json"));
    if args.json.is_some() {
        crate::io::atomic::write_atomic(&path, text.as_bytes())?;
    }
    println!("{}", serde_json::to_string_pretty(&summary["mean"])?);
    eprintln!("metrics → {}", path.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    /// DESIGN §5's full-image albedo PSNR, the masked one and TensoIR's gamma-space errors, each
    /// computed here by hand on a 4-pixel view with two pixels in the GT mask; whatever we
    /// predict outside the mask must not count.
    #[test]
    fn albedo_errors_follow_the_three_protocols() {
        let gt = [[0.5, 0.25, 1.0], [0.1, 0.2, 0.3], [0.0; 3], [0.0; 3]];
        let mask = [1.0, 0.9, 0.2, 0.0];
        // Inside: errors 0.1, 0, 0.5 (clipped to 1 for TensoIR) and 0.05 on every channel.
        let pred = [[0.6, 0.25, 1.5], [0.15, 0.25, 0.35], [7.0, -3.0, 0.4], [0.9; 3]];
        let e = super::albedo_errors(&pred, &gt, &mask);
        let se = 0.1f64 * 0.1 + 0.5 * 0.5 + 3.0 * 0.05 * 0.05;
        let db = |mse: f64| (-10.0 * mse.log10()) as f32;
        assert!((e.masked_psnr - db(se / 6.0)).abs() < 1e-4, "{e:?}");
        assert!((e.full_psnr - db(se / 12.0)).abs() < 1e-4, "{e:?}");
        let g = |x: f64| x.powf(1.0 / 2.2);
        let gamma_se = (g(0.6) - g(0.5)).powi(2)
            + (g(0.15) - g(0.1)).powi(2)
            + (g(0.25) - g(0.2)).powi(2)
            + (g(0.35) - g(0.3)).powi(2);
        assert!((e.gamma_se - gamma_se).abs() < 1e-9, "{e:?} vs {gamma_se}");
        assert_eq!(e.values, 12);
        // A perfect prediction is not a NaN, and an empty mask measures nothing.
        assert!(super::albedo_errors(&gt, &gt, &mask).full_psnr > 100.0);
        let empty = super::albedo_errors(&pred, &gt, &[0.0; 4]);
        assert!(empty.masked_psnr.is_nan() && empty.full_psnr.is_nan(), "{empty:?}");
    }

    /// A run trained as `--data DATA --out RUN` in one folder finds its dataset from any other;
    /// a path that exists as recorded, or a run moved elsewhere, keeps the recorded path.
    #[test]
    fn a_run_finds_its_relative_dataset_from_another_folder() {
        use std::path::{Path, PathBuf};
        let root = crate::test_dir::TempDir::new("where");
        let (data, out) = (PathBuf::from("scan-data"), PathBuf::from("runs/scan"));
        std::fs::create_dir_all(root.join(&data)).unwrap();
        std::fs::create_dir_all(root.join(&out)).unwrap();
        let found = super::dataset_of_run(&root.join(&out), &data, &out);
        assert_eq!(found, root.join(&data));
        // Moved: the run's path no longer ends with the recorded out.
        let moved = root.join("elsewhere");
        assert_eq!(super::dataset_of_run(&moved, &data, &out), data);
        // Found as recorded (relative to here), or absolute: unchanged.
        assert_eq!(super::dataset_of_run(&root.join(&out), Path::new("src"), &out), Path::new("src"));
        assert_eq!(super::dataset_of_run(&root.join(&out), &root, &out), root.path());
        // Through load_run_config, as render and eval read a run.
        let cfg = crate::train::config::TrainConfig { data: data.clone(), out: out.clone(), ..Default::default() };
        cfg.save(&root.join(&out).join("config.toml")).unwrap();
        assert_eq!(super::load_run_config(&root.join(&out)).unwrap().data, root.join(&data));
    }

    use super::*;
    use rand::{RngExt, SeedableRng};

    /// Huge but finite GT normals (a pass scaled wrong) still give an angle, not NaN.
    #[test]
    fn normal_error_of_huge_gt_vectors_is_finite() {
        let mut gt = Image::new(2, 1, 4);
        gt.data = vec![3e38, 0.0, 0.0, 1.0, 0.0, -3e38, 3e38, 1.0];
        let mae = normal_mae_degrees(&[[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], &gt);
        assert!((mae - (0.0 + 45.0) / 2.0).abs() < 1e-3, "{mae}");
    }

    /// Without a PLY the newest checkpoint of any stage gives the surfels: the inverse stage's
    /// over an older nvs one (it used to take the nvs one, beside the inverse stage's light),
    /// and the nvs one when it is the newer.
    #[test]
    fn a_run_without_its_ply_takes_the_newest_stages_checkpoint() {
        use crate::train::checkpoint::Checkpoint;
        let run = crate::test_dir::TempDir::new("eval-ckpt");
        assert!(load_run_surfels(&run).unwrap_err().to_string().contains("checkpoint_inverse.bin"));
        let write = |name: &str, count: usize, age_s: u64| {
            let mut c = Checkpoint::default();
            c.put_surfels("params", &Surfels::random_in_box(count, [0.0; 3], [1.0; 3], 1));
            c.save(&run.join(name)).unwrap();
            let when = std::time::SystemTime::now() - std::time::Duration::from_secs(age_s);
            std::fs::File::options().write(true).open(run.join(name)).unwrap().set_modified(when).unwrap();
        };
        write("checkpoint.bin", 5, 100);
        assert_eq!(load_run_surfels(&run).unwrap().len(), 5);
        write("checkpoint_inverse.bin", 7, 10);
        assert_eq!(load_run_surfels(&run).unwrap().len(), 7);
        write("checkpoint.bin", 5, 1);
        assert_eq!(load_run_surfels(&run).unwrap().len(), 5);
    }

    /// The same light scores 0; a light twice as bright scores ln 2 unless the albedo scale
    /// says the albedo was halved; a light that moved from the sides to the top is seen.
    #[test]
    fn compare_light_measures_the_light_in_albedo_units() {
        use crate::envmap::EnvMap;
        let gt = EnvMap::constant(64, 32, [1.0, 0.5, 0.25]);
        assert!(compare_light(&gt, &gt, [1.0; 3]).log_error < 1e-5);
        let bright = EnvMap::constant(64, 32, [2.0, 1.0, 0.5]);
        let c = compare_light(&bright, &gt, [1.0; 3]);
        assert!((c.log_error - 2f32.ln()).abs() < 1e-4, "{}", c.log_error);
        assert!(compare_light(&bright, &gt, [2.0; 3]).log_error < 1e-4);
        // All the light at the zenith rows: +z sees more than the truth, the sides less.
        let mut top = EnvMap::constant(64, 32, [0.0; 3]);
        for t in &mut top.texels[..64 * 8] {
            *t = [4.0, 2.0, 1.0];
        }
        let c = compare_light(&top, &gt, [1.0; 3]);
        let at = |name: &str| c.normals.iter().find(|l| l.normal == name).unwrap().clone();
        assert!(at("+z").ours[0] > at("+z").gt[0] && at("+x").ours[0] < at("+x").gt[0] && at("-z").ours[0] == 0.0);
        assert!(c.log_error > 0.5);
    }

    /// A flat grey pass plus i.i.d. Gaussian noise σ: the estimate is −10·log10 σ²; without
    /// noise it is far higher; unmasked pixels do not count.
    #[test]
    fn noise_ceiling_recovers_the_noise_level() {
        let (w, h) = (64, 48);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let sigma = 0.05f64;
        let mut gauss = || {
            // Box–Muller.
            let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-12), rng.random());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let noisy: Vec<[f32; 3]> = (0..w * h).map(|_| [0; 3].map(|_| (0.4 + sigma * gauss()) as f32)).collect();
        let mask: Vec<f32> = (0..w * h).map(|p| if p % w < w - 8 { 1.0 } else { 0.0 }).collect();
        let est = noise_ceiling_psnr(&noisy, &mask, w, h);
        let truth = (-10.0 * (sigma * sigma).log10()) as f32;
        assert!((est - truth).abs() < 0.3, "estimated {est} dB, noise {truth} dB");
        let mut flat = vec![[0.4f32; 3]; w * h];
        assert!(noise_ceiling_psnr(&flat, &mask, w, h) > 60.0);
        // Anything where the mask is 0 does not count, not even as a neighbour.
        for (p, c) in flat.iter_mut().enumerate() {
            if mask[p] == 0.0 {
                *c = [1.0, 0.0, 1.0];
            }
        }
        assert!(noise_ceiling_psnr(&flat, &mask, w, h) > 60.0);
        // A step edge inside the mask counts (the estimate is a lower bound of the ceiling).
        let step: Vec<[f32; 3]> = (0..w * h).map(|p| if p % w < w / 2 { [0.2; 3] } else { [0.6; 3] }).collect();
        let with_edge = noise_ceiling_psnr(&step, &mask, w, h);
        assert!(with_edge > 10.0 && with_edge < 60.0, "{with_edge}");
        assert!(noise_ceiling_psnr(&flat, &vec![0.0; w * h], w, h).is_nan());
    }
}
