//! The `init` stage (RadioGS stage 1, DESIGN §1): 2DGS training with a split-sum PBR branch.
//!
//! It runs the nvs stage's loop (nvs.rs: view order, 2DGS losses, densification, checkpoints)
//! with albedo, roughness and a learned environment light added; per iteration this module
//! adds, for the iteration's camera:
//! 1. per-surfel split-sum PBR at each surfel centre for the view direction (no visibility,
//!    no indirect light: stage 1 ignores occlusion), rasterised as a 3-channel linear feature;
//! 2. the PBR image loss (linear → sRGB, λ_pbr·(L1 + 0.2·D-SSIM)) and edge-aware smoothness
//!    of the rendered normal;
//! 3. the simplified radiometric consistency λ·mean |SH_i(ω_cam) − enc(L_pbr,i(ω_cam))| over
//!    the shaded surfels (both sides get gradients), from `simple_rc_from`;
//! 4. the light priors (white light, TV); the light's Adam step is the caller's.
//!
//! Two-sided surfels (this stage's default, as nvs) are shaded with their normal turned
//! towards the camera; culled ones only when they face it.

use super::light::LearnedLight;
use super::material::{MaterialGrads, MaterialView, view_dir, view_dir_backward};
use super::pbr_image::{PbrImage, PbrImageLoss};
use crate::camera::Camera;
use crate::envmap::EnvMap;
use crate::loss::EdgeAwareSmoothness;
use crate::raster::{RenderGrads, RenderOutput};
use crate::sh;
use crate::shade::splitsum::SplitSum;
use crate::surfels::{SurfelGrads, Surfels};
use crate::train::config::TrainConfig;
use crate::train::consistency::{encode, encode_derivative};

/// Feature channels rasterised by this stage: linear L_pbr.
pub const CHANNELS: usize = 3;

/// Per-surfel split-sum shading for one camera, kept for the backward pass.
#[derive(Default)]
pub struct SplitSumShading {
    /// Shaded surfels: centre in front of the camera and (culled mode) facing it.
    pub active: Vec<u32>,
    /// Per active surfel: the shading normal (turned towards the camera), whether it was
    /// turned, the view direction ω_o (towards the camera), albedo, roughness, linear PBR.
    pub normal: Vec<[f32; 3]>,
    pub turned: Vec<bool>,
    pub view: Vec<[f32; 3]>,
    pub albedo: Vec<[f32; 3]>,
    pub roughness: Vec<f32>,
    pub pbr: Vec<[f32; 3]>,
    /// N × [`CHANNELS`] rows for the rasteriser (zero for surfels not shaded).
    pub features: Vec<f32>,
}

impl SplitSumShading {
    pub fn compute(&mut self, surfels: &Surfels, mats: &MaterialView, ss: &SplitSum, camera: &Camera, two_sided: bool) {
        let eye = camera.position().to_array();
        self.active.clear();
        self.normal.clear();
        self.turned.clear();
        self.view.clear();
        self.albedo.clear();
        self.roughness.clear();
        for i in 0..surfels.len() {
            if camera.world_to_camera(glam::Vec3::from(surfels.means[i])).z <= 0.0 {
                continue;
            }
            let w = view_dir(surfels.means[i], eye);
            let n = mats.normal[i];
            let facing = n[0] * w[0] + n[1] * w[1] + n[2] * w[2] > 0.0;
            if !facing && !two_sided {
                continue;
            }
            self.active.push(i as u32);
            self.normal.push(if facing { n } else { n.map(|x| -x) });
            self.turned.push(!facing);
            self.view.push(w);
            self.albedo.push(mats.albedo[i]);
            self.roughness.push(mats.roughness[i]);
        }
        self.pbr.clear();
        self.pbr.resize(self.active.len(), [0.0; 3]);
        ss.shade_batch(&self.albedo, &self.roughness, &self.normal, &self.view, &mut self.pbr);
        self.features.clear();
        self.features.resize(surfels.len() * CHANNELS, 0.0);
        for (k, &i) in self.active.iter().enumerate() {
            self.features[i as usize * CHANNELS..][..3].copy_from_slice(&self.pbr[k]);
        }
    }

    /// Backward for the upstream gradient `v_pbr` (per active surfel): albedo, roughness,
    /// normal (through the turn) and centre (through ω_o) into `mgrads`, env texels into
    /// `v_env` (added).
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &self,
        ss: &SplitSum,
        surfels: &Surfels,
        eye: [f32; 3],
        v_pbr: &[[f32; 3]],
        scratch: &mut ShadingGrads,
        mgrads: &mut MaterialGrads,
        v_env: &mut [[f32; 3]],
    ) {
        let m = self.active.len();
        let g = scratch;
        g.v_albedo.resize(m, [0.0; 3]);
        g.v_roughness.resize(m, 0.0);
        g.v_normal.resize(m, [0.0; 3]);
        g.v_view.resize(m, [0.0; 3]);
        ss.shade_batch_backward(
            &self.albedo,
            &self.roughness,
            &self.normal,
            &self.view,
            v_pbr,
            &mut g.v_albedo,
            &mut g.v_roughness,
            &mut g.v_normal,
            &mut g.v_view,
            v_env,
        );
        for (k, &i) in self.active.iter().enumerate() {
            let i = i as usize;
            let sign = if self.turned[k] { -1.0 } else { 1.0 };
            let vm = view_dir_backward(surfels.means[i], eye, g.v_view[k]);
            for c in 0..3 {
                mgrads.v_albedo[i][c] += g.v_albedo[k][c];
                mgrads.v_normal[i][c] += sign * g.v_normal[k][c];
                mgrads.v_means[i][c] += vm[c];
            }
            mgrads.v_roughness[i] += g.v_roughness[k];
        }
    }
}

/// Per-active-surfel gradient buffers of [`SplitSumShading::backward`].
#[derive(Default)]
pub struct ShadingGrads {
    v_albedo: Vec<[f32; 3]>,
    v_roughness: Vec<f32>,
    v_normal: Vec<[f32; 3]>,
    v_view: Vec<[f32; 3]>,
}

/// Simplified radiometric consistency, forward and backward: weight · mean over the shaded
/// surfels and channels of |SH_i(ω_cam) − enc(L_pbr,i)|, SH evaluated like the rasteriser
/// (direction camera → centre). Adds ∂/∂SH and ∂/∂μ (SH direction) into `v_surfels` and
/// ∂/∂L_pbr into `v_pbr`; returns the unweighted mean.
pub fn simple_consistency(
    surfels: &Surfels,
    shading: &SplitSumShading,
    eye: [f32; 3],
    weight: f32,
    v_surfels: &mut SurfelGrads,
    v_pbr: &mut [[f32; 3]],
) -> f32 {
    let m = shading.active.len();
    if m == 0 {
        return 0.0;
    }
    let norm = 1.0 / (3 * m) as f32;
    let mut sum = 0.0f64;
    for (k, &i) in shading.active.iter().enumerate() {
        let i = i as usize;
        let dir = [0, 1, 2].map(|c| surfels.means[i][c] - eye[c]);
        let lhs = sh::eval(&surfels.sh[i], surfels.sh_degree, dir);
        let mut v_lhs = [0.0f32; 3];
        for c in 0..3 {
            let res = lhs[c] - encode(shading.pbr[k][c]);
            sum += res.abs() as f64;
            let g = if res == 0.0 { 0.0 } else { weight * res.signum() * norm };
            v_lhs[c] = g;
            v_pbr[k][c] -= g * encode_derivative(shading.pbr[k][c]);
        }
        if weight > 0.0 {
            let v_dir = sh::eval_backward(&surfels.sh[i], surfels.sh_degree, dir, v_lhs, &mut v_surfels.sh[i]);
            for c in 0..3 {
                v_surfels.means[i][c] += v_dir[c];
            }
        }
    }
    (sum * norm as f64) as f32
}

/// Losses this stage adds (unweighted, except `smooth` and `env_prior`, which are weighted).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct InitLosses {
    pub pbr_l1: f32,
    pub pbr_dssim: f32,
    pub psnr_pbr: f32,
    pub simple_rc: f32,
    pub smooth: f32,
    pub env_prior: f32,
}

/// The stage's per-iteration work and buffers (one per run; no allocation once sized).
#[derive(Default)]
pub struct InitPass {
    mats: MaterialView,
    env: Option<EnvMap>,
    split_sum: Option<SplitSum>,
    pub shading: SplitSumShading,
    pbr_image: PbrImageLoss,
    smooth: EdgeAwareSmoothness,
    v_map: Vec<f32>,
    v_pbr: Vec<[f32; 3]>,
    grads: ShadingGrads,
    mgrads: MaterialGrads,
    v_env: Vec<[f32; 3]>,
    /// The light's gradient (log radiance) of the last iteration.
    pub v_env_log: Vec<f32>,
}

impl InitPass {
    /// Before rasterising: prefilter the current light and shade the surfels for `camera`;
    /// the features are then in `self.shading.features`.
    pub fn shade(&mut self, cfg: &TrainConfig, surfels: &Surfels, light: &LearnedLight, camera: &Camera) {
        let env = light.env();
        let ss = SplitSum::new(&env).expect("the light is H × 2H with H a multiple of 8 (validated)");
        self.mats.update(surfels);
        self.shading.compute(surfels, &self.mats, &ss, camera, cfg.two_sided);
        self.env = Some(env);
        self.split_sum = Some(ss);
    }

    /// After the forward pass: the PBR image loss and the normal smoothness, gradients added
    /// into `g` (`g.v_features` sized N_pixels × [`CHANNELS`], `g.v_alpha`, `g.v_normal`
    /// sized when used). Returns the total weighted loss.
    #[allow(clippy::too_many_arguments)]
    pub fn image_losses(
        &mut self,
        cfg: &TrainConfig,
        out: &RenderOutput,
        gt: &[[f32; 3]],
        gt_alpha: &[f32],
        bg: [f32; 3],
        g: &mut RenderGrads,
        l: &mut InitLosses,
    ) -> f32 {
        let (w, h) = (out.width as usize, out.height as usize);
        let wp = cfg.lambda_pbr;
        self.pbr_image.clip_saturated = cfg.clip_saturated;
        let img =
            PbrImage { features: &out.features, channels: CHANNELS, alpha: &out.alpha, bg, gt, gt_alpha, size: (w, h) };
        let t = self.pbr_image.evaluate(&img, wp, &mut g.v_features, &mut g.v_alpha);
        (l.pbr_l1, l.pbr_dssim, l.psnr_pbr) = (t.l1, t.dssim, t.psnr);
        let mut total = wp * (t.l1 + 0.2 * t.dssim);
        if cfg.lambda_smooth_normal > 0.0 && !out.normal.is_empty() {
            self.smooth.prepare(gt, w, h);
            self.v_map.clear();
            self.v_map.resize(w * h * 3, 0.0);
            let v = self.smooth.loss_prepared(
                out.normal.as_flattened(),
                3,
                Some(gt_alpha),
                cfg.lambda_smooth_normal,
                &mut self.v_map,
            );
            l.smooth = cfg.lambda_smooth_normal * v;
            total += l.smooth;
            for (d, s) in g.v_normal.as_flattened_mut().iter_mut().zip(&self.v_map) {
                *d += s;
            }
        }
        total
    }

    /// After the rasteriser's backward (`v_features`: per-surfel feature gradients): the
    /// simplified consistency (when `consistency` is on), the shading backward, the light
    /// priors; gradients into `v_surfels` and `self.v_env_log`. Returns the weighted loss
    /// it adds.
    #[allow(clippy::too_many_arguments)]
    pub fn backward(
        &mut self,
        cfg: &TrainConfig,
        surfels: &Surfels,
        light: &LearnedLight,
        camera: &Camera,
        v_features: &[f32],
        consistency: bool,
        v_surfels: &mut SurfelGrads,
        l: &mut InitLosses,
    ) -> f32 {
        let (Some(ss), Some(env)) = (&self.split_sum, &self.env) else { return 0.0 };
        let sh = &self.shading;
        let eye = camera.position().to_array();
        self.v_pbr.clear();
        self.v_pbr.extend(sh.active.iter().map(|&i| {
            let f = &v_features[i as usize * CHANNELS..][..3];
            [f[0], f[1], f[2]]
        }));
        let weight = if consistency { cfg.lambda_simple_rc } else { 0.0 };
        l.simple_rc = simple_consistency(surfels, sh, eye, weight, v_surfels, &mut self.v_pbr);
        let mut total = weight * l.simple_rc;
        self.mgrads.reset(surfels.len());
        self.v_env.clear();
        self.v_env.resize(env.texels.len(), [0.0; 3]);
        sh.backward(ss, surfels, eye, &self.v_pbr, &mut self.grads, &mut self.mgrads, &mut self.v_env);
        self.mgrads.chain_into(surfels, v_surfels);
        l.env_prior = light.priors_and_chain(cfg, env, &mut self.v_env, &mut self.v_env_log);
        total += l.env_prior;
        total
    }
}

/// Run (or resume) the `init` stage into `cfg.out` (`cfg.iters` iterations).
pub fn run(
    cfg: &TrainConfig,
    dataset: &crate::io::dataset::Dataset,
    show_progress: bool,
) -> anyhow::Result<super::nvs::StageSummary> {
    super::nvs::run_stage(cfg, dataset, show_progress, None, super::nvs::GeometryStage::Init)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surfels::{albedo_to_logit, logit, quat_with_normal};
    use rand::{RngExt, SeedableRng};

    fn scene(rg: &mut rand_pcg::Pcg64) -> Surfels {
        let mut s = Surfels::default();
        // Normals towards the camera (+z side), one grazing, one facing away (turned when
        // two-sided, skipped when culled).
        let normals = [[0.2, -0.1, 1.0], [-0.3, 0.4, 1.0], [1.0, 0.0, 0.12], [0.1, 0.2, -1.0], [0.0, -0.5, 1.0]];
        for n in normals {
            let m = [rg.random_range(-0.5..0.5), rg.random_range(-0.5..0.5), rg.random_range(-0.2..0.2)];
            s.push(m, [0.2, 0.1], quat_with_normal(n), 0.8, [0.5; 3], [0.5; 3], 0.5);
        }
        s.sh_degree = 3;
        for i in 0..s.len() {
            for k in 0..16 {
                s.sh[i][k] = [0, 1, 2].map(|_| rg.random_range(-0.08..0.08));
            }
            s.albedo_logits[i] = [0, 1, 2].map(|_| albedo_to_logit(rg.random_range(0.1..0.7)));
            // Away from the prefiltered levels (steps of 0.2) and the LUT nodes (i/31).
            s.roughness_logits[i] = logit([0.07, 0.33, 0.55, 0.93, 0.47][i]);
        }
        s
    }

    fn light(rg: &mut rand_pcg::Pcg64, cfg: &TrainConfig) -> LearnedLight {
        let mut l = LearnedLight::fresh(cfg).unwrap();
        l.log.iter_mut().for_each(|x| *x = rg.random_range(-0.7..0.7));
        l
    }

    /// Σ features·v_features + the weighted losses of `InitPass::backward` (consistency, light
    /// priors): the objective whose gradient the pass computes.
    fn objective(cfg: &TrainConfig, s: &Surfels, l: &LearnedLight, cam: &Camera, v_feat: &[f32]) -> f64 {
        let mut pass = InitPass::default();
        pass.shade(cfg, s, l, cam);
        let linear: f64 = pass.shading.features.iter().zip(v_feat).map(|(&f, &v)| f as f64 * v as f64).sum();
        let mut scratch = s.zeros_like();
        let mut losses = InitLosses::default();
        linear + pass.backward(cfg, s, l, cam, v_feat, true, &mut scratch, &mut losses) as f64
    }

    /// The stage's per-surfel chain (split-sum shading with the turned normals, simplified
    /// consistency, light priors, exp activation) against central differences, per parameter
    /// kind: albedo and roughness logits, quaternions, centres, SH coefficients, env log texels.
    #[test]
    fn init_pass_gradients_match_finite_differences() {
        for two_sided in [true, false] {
            // Seeds whose consistency residuals stay clear of the L1 kink by more than the FD steps.
            let mut rg = rand_pcg::Pcg64::seed_from_u64(if two_sided { 11 } else { 13 });
            let cfg = TrainConfig { env_height: 16, lambda_simple_rc: 0.3, two_sided, ..TrainConfig::default() };
            let s = scene(&mut rg);
            let l = light(&mut rg, &cfg);
            let cam = Camera::look_at("fd", glam::Vec3::new(0.4, -0.3, 3.0), glam::Vec3::ZERO, 16, 16, 1.0);
            let v_feat: Vec<f32> = (0..s.len() * CHANNELS).map(|_| rg.random_range(-1.0..1.0)).collect();

            let mut pass = InitPass::default();
            pass.shade(&cfg, &s, &l, &cam);
            let want_active = if two_sided { 5 } else { 4 };
            assert_eq!(pass.shading.active.len(), want_active, "two-sided {two_sided}");
            assert_eq!(pass.shading.turned.iter().filter(|&&t| t).count(), if two_sided { 1 } else { 0 });
            let mut v = s.zeros_like();
            let mut losses = InitLosses::default();
            pass.backward(&cfg, &s, &l, &cam, &v_feat, true, &mut v, &mut losses);
            assert!(losses.simple_rc > 0.0 && losses.env_prior > 0.0);

            let check = |analytic: f32, plus: &dyn Fn(f32) -> f64, h: f32, what: &str| {
                let fd = (plus(h) - plus(-h)) / (2.0 * h as f64);
                assert!(
                    (analytic as f64 - fd).abs() < 3e-2 * fd.abs() + 2e-3,
                    "two-sided {two_sided}, {what}: analytic {analytic} vs fd {fd}"
                );
            };
            for i in 0..s.len() {
                for c in 0..3 {
                    let f = |d: f32| {
                        let mut t = s.clone();
                        t.albedo_logits[i][c] += d;
                        objective(&cfg, &t, &l, &cam, &v_feat)
                    };
                    check(v.albedo_logits[i][c], &f, 1e-2, &format!("albedo logit [{i}][{c}]"));
                    let f = |d: f32| {
                        let mut t = s.clone();
                        t.means[i][c] += d;
                        objective(&cfg, &t, &l, &cam, &v_feat)
                    };
                    check(v.means[i][c], &f, 1e-3, &format!("mean [{i}][{c}]"));
                    for k in [0, 3, 9] {
                        let f = |d: f32| {
                            let mut t = s.clone();
                            t.sh[i][k][c] += d;
                            objective(&cfg, &t, &l, &cam, &v_feat)
                        };
                        check(v.sh[i][k][c], &f, 1e-3, &format!("sh [{i}][{k}][{c}]"));
                    }
                }
                for c in 0..4 {
                    let f = |d: f32| {
                        let mut t = s.clone();
                        t.quats[i][c] += d;
                        objective(&cfg, &t, &l, &cam, &v_feat)
                    };
                    // 2e-4: the LUT is bilinear in NoV, and a 1e-3 step took surfel 1's NoV across
                    // a node (a kink) once the LUT held the height-correlated Smith lobe.
                    check(v.quats[i][c], &f, 2e-4, &format!("quat [{i}][{c}]"));
                }
                let f = |d: f32| {
                    let mut t = s.clone();
                    t.roughness_logits[i] += d;
                    objective(&cfg, &t, &l, &cam, &v_feat)
                };
                check(v.roughness_logits[i], &f, 1e-3, &format!("roughness logit [{i}]"));
            }
            let mut order: Vec<usize> = (0..pass.v_env_log.len()).collect();
            order.sort_by(|&a, &b| pass.v_env_log[b].abs().total_cmp(&pass.v_env_log[a].abs()));
            for &t in order.iter().take(10) {
                let f = |d: f32| {
                    let mut e = l.clone();
                    e.log[t] += d;
                    objective(&cfg, &s, &e, &cam, &v_feat)
                };
                check(pass.v_env_log[t], &f, 1e-2, &format!("env log texel {t}"));
            }
        }
    }

    /// Furnace: under a constant light L, a surfel's split-sum colour is a·(1 − E)·L + E·L, E = F0·A + B
    /// (Ē = L, P = L); a back-facing surfel in two-sided mode shades exactly like its twin
    /// flipped to face the camera.
    #[test]
    fn constant_light_furnace_and_turned_twins() {
        let mut s = Surfels::default();
        let n = [0.3f32, -0.2, 0.9];
        s.push([0.1, 0.0, 0.0], [0.2, 0.2], quat_with_normal(n), 0.9, [0.5; 3], [0.6, 0.2, 0.4], 0.35);
        s.push([0.1, 0.0, 0.0], [0.2, 0.2], quat_with_normal(n.map(|x| -x)), 0.9, [0.5; 3], [0.6, 0.2, 0.4], 0.35);
        let cfg = TrainConfig { env_height: 16, two_sided: true, ..TrainConfig::default() };
        let l_rgb = [1.3f32, 0.7, 2.0];
        let mut light = LearnedLight::fresh(&cfg).unwrap();
        for (k, x) in light.log.iter_mut().enumerate() {
            *x = l_rgb[k % 3].ln();
        }
        let cam = Camera::look_at("furnace", glam::Vec3::new(1.0, -1.5, 3.0), glam::Vec3::ZERO, 16, 16, 0.8);
        let mut pass = InitPass::default();
        pass.shade(&cfg, &s, &light, &cam);
        let sh = &pass.shading;
        assert_eq!(sh.active, vec![0, 1]);
        assert_eq!(sh.turned, vec![false, true]);
        let (nn, wo) = (sh.normal[0], sh.view[0]);
        let nov = (nn[0] * wo[0] + nn[1] * wo[1] + nn[2] * wo[2]) as f64;
        let lut = crate::shade::splitsum::BrdfLut::get().lookup(nov, sh.roughness[0] as f64);
        let spec = crate::shade::brdf::F0 * lut.a + lut.b;
        for c in 0..3 {
            // The base layer gets what the specular layer leaves: a·(1 − E) + E.
            let want = (sh.albedo[0][c] as f64 * (1.0 - spec) + spec) * l_rgb[c] as f64;
            assert!((sh.pbr[0][c] as f64 - want).abs() < 2e-3 * want, "channel {c}: {} vs {want}", sh.pbr[0][c]);
            // (Equal up to rounding: the twin's quaternion is built from −n.)
            assert!((sh.pbr[0][c] - sh.pbr[1][c]).abs() < 1e-6, "the turned twin shades the same");
        }
    }
}
