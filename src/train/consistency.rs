//! Radiometric consistency (RadioGS; DESIGN §1), forward and backward side by side.
//!
//! Each call picks B surfels uniformly at random, traces R directions from each (Fibonacci on
//! the normal's hemisphere, a random rotation per surfel, from μ + offset·n) and evaluates the
//! rendering equation with the traced visibility V_s = T and indirect radiance L_ind,s:
//!
//!     L_rc = mean_i |SH_i(ω_cam) − enc(L_pbr(x_i, ω_cam))| + mean_i |SH_i(ω_rand) − enc(L_pbr(x_i, ω_rand))|
//!
//! ω_cam points to the current camera (entries with n·ω_cam ≤ 0 are masked out), ω_rand is
//! uniform on n's hemisphere. SH colours are sRGB-encoded (the images they are trained on),
//! so the rendering equation's linear radiance is encoded with the sRGB curve (extended above
//! 1, no clamp) before the comparison: both sides then live where the image losses live.
//!
//! Backward: ∂/∂SH_i (the left side; `detach_lhs` stops it), ∂/∂L_pbr (the right side;
//! `detach_rhs` stops it) → albedo, roughness, normal, env (each with its detach switch) and
//! the traced V_s, L_ind,s → through the tracer's backward to the hit surfels' position,
//! rotation, scale, opacity and SH. The ray origins and directions are treated as constants
//! (no gradient to the sampling surfel's own position/normal through its rays).
//!
//! The traced samples are handed back so the caller can overwrite those surfels' cache rows.

use super::material::{MaterialGrads, MaterialView, view_dir, view_dir_backward};
use crate::envmap::EnvMap;
use crate::sh;
use crate::shade::incident::{RayStart, decode, decode_derivative, rotation_for, surfel_rays};
use crate::shade::pbr::{Detach, PbrGrads, PbrInputs, shade_surfels, shade_surfels_backward};
use crate::shade::sampling::uniform_hemisphere;
use crate::surfels::{SurfelGrads, Surfels};
use crate::trace::{
    HitRecord, Ray, RayGrad, RayOutput, Tracer, trace, trace_backward_recorded, trace_recorded, visibility_ramp,
};
use rand::RngExt;

/// sRGB encoding extended above 1 (no clamp; 0 below 0).
#[inline]
pub fn encode(x: f32) -> f32 {
    if x <= 0.0 {
        0.0
    } else if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    }
}

/// d encode / dx (0 below 0).
#[inline]
pub fn encode_derivative(x: f32) -> f32 {
    if x <= 0.0 {
        0.0
    } else if x <= 0.003_130_8 {
        12.92
    } else {
        1.055 / 2.4 * x.powf(1.0 / 2.4 - 1.0)
    }
}

/// d encode / dx from x and y = encode(x): above the linear segment
/// 1.055/2.4 · x^(1/2.4 − 1) = (y + 0.055) / (2.4 x), so no second power.
#[inline]
pub fn encode_derivative_given(x: f32, y: f32) -> f32 {
    if x <= 0.0 {
        0.0
    } else if x <= 0.003_130_8 {
        12.92
    } else {
        (y + 0.055) / (2.4 * x)
    }
}

/// Settings of one consistency evaluation.
#[derive(Clone, Copy, Debug)]
pub struct RcSettings {
    /// B: surfels per call.
    pub surfels: usize,
    /// R: traced rays per surfel.
    pub rays: usize,
    /// Where the traced rays start and what they skip (scene units).
    pub start: RayStart,
    /// λ_rc.
    pub weight: f32,
    /// Switches on the right (PBR) side.
    pub detach: Detach,
    /// No gradient to the SH side.
    pub detach_lhs: bool,
    /// No gradient to the PBR side at all.
    pub detach_rhs: bool,
    /// Compare linear radiance by its square (decode(SH) − L)² instead of the sRGB L1
    /// |SH − encode(L)| of training: relighting's finetune, whose per-step target is a noisy
    /// estimate (16 rays) and whose L1 fit would settle on its median, dropping a sun that a
    /// step's rays usually miss.
    pub linear_l2: bool,
}

/// Buffers reused across calls.
#[derive(Default)]
pub struct RcScratch {
    pub ids: Vec<u32>,
    dirs: Vec<[f32; 3]>,
    rays: Vec<Ray>,
    out: Vec<RayOutput>,
    albedo: Vec<[f32; 3]>,
    rough: Vec<f32>,
    normal: Vec<[f32; 3]>,
    view: Vec<[f32; 3]>,
    valid: Vec<bool>,
    dirs2: Vec<[f32; 3]>,
    vis2: Vec<f32>,
    ind2: Vec<[f32; 3]>,
    direct: Vec<[f32; 3]>,
    indirect: Vec<[f32; 3]>,
    grads: PbrGrads,
    ray_grads: Vec<RayGrad>,
    /// The forward's hits, replayed by the backward (no second cast).
    record: HitRecord,
    pub weight: f32,
    /// The tracer's radiance is already linear (`TraceSettings::linear_radiance`).
    linear: bool,
    /// The tracer's `opaque_below` (the shading's visibility ramp).
    opaque_below: f32,
}

impl RcScratch {
    /// The traced samples of the k-th selected surfel: (dirs, visibility, linear indirect).
    pub fn row(&self, k: usize, r: usize) -> (Vec<[f32; 3]>, Vec<f32>, Vec<[f32; 3]>) {
        let rng = k * r..(k + 1) * r;
        (
            self.dirs[rng.clone()].to_vec(),
            self.out[rng.clone()].iter().map(|o| visibility_ramp(o.transmittance, self.opaque_below).0).collect(),
            self.out[rng]
                .iter()
                .map(|o| {
                    let g = visibility_ramp(o.transmittance, self.opaque_below).1;
                    if self.linear { o.radiance } else { o.radiance.map(decode) }.map(|x| x * g)
                })
                .collect(),
        )
    }
}

/// What one call measured (unweighted means).
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct RcLosses {
    pub camera: f32,
    pub random: f32,
    /// λ_rc · (camera + random).
    pub total: f32,
}

/// One radiometric-consistency evaluation with its backward. `eye` is the current camera
/// centre (None: a second random direction replaces ω_cam). `batch` names the surfels (its
/// length is B; `--rc-order sweep`); None draws `cfg.surfels` uniformly at random. Adds gradients into `v_surfels`
/// (SH of the sampled surfels and everything the tracer reaches), `mats` (albedo, roughness,
/// normal, means through ω_cam) and `v_env` (linear texels, unless detached).
#[allow(clippy::too_many_arguments)]
pub fn radiometric_consistency(
    surfels: &Surfels,
    view: &MaterialView,
    tracer: &Tracer,
    env: &EnvMap,
    eye: Option<[f32; 3]>,
    batch: Option<&[u32]>,
    rng: &mut rand_pcg::Pcg64,
    cfg: &RcSettings,
    scratch: &mut RcScratch,
    v_surfels: &mut SurfelGrads,
    mats: &mut MaterialGrads,
    v_env: &mut [[f32; 3]],
) -> RcLosses {
    let n = surfels.len();
    let (b, r) = (batch.map_or(cfg.surfels, |ids| ids.len()).min(n), cfg.rays);
    if b == 0 || r == 0 {
        return RcLosses::default();
    }
    let sc = scratch;
    sc.ids.clear();
    match batch {
        Some(ids) => sc.ids.extend(ids[..b].iter().map(|&i| {
            assert!((i as usize) < n, "consistency: batch names surfel {i} of {n}");
            i
        })),
        None => sc.ids.extend((0..b).map(|_| rng.random_range(0..n) as u32)),
    }
    let seed: u64 = rng.random();
    sc.dirs.resize(b * r, [0.0; 3]);
    sc.rays.resize(b * r, Ray::default());
    for (k, &i) in sc.ids.iter().enumerate() {
        sc.weight = surfel_rays(
            surfels,
            i as usize,
            cfg.start,
            rotation_for(seed, k),
            &mut sc.dirs[k * r..(k + 1) * r],
            &mut sc.rays[k * r..(k + 1) * r],
        );
    }
    sc.out.resize(b * r, RayOutput::default());
    if cfg.detach_rhs {
        // No gradient through the rays (relighting's finetune): nothing to record.
        trace(tracer, surfels, &sc.rays, None, &mut sc.out, None);
    } else {
        trace_recorded(tracer, surfels, &sc.rays, &mut sc.out, &mut sc.record);
    }
    sc.linear = tracer.settings.linear_radiance;
    sc.opaque_below = tracer.settings.opaque_below;

    // Two entries per surfel: 2k = ω_cam, 2k + 1 = ω_rand; both share the traced samples.
    let m = 2 * b;
    sc.albedo.resize(m, [0.0; 3]);
    sc.rough.resize(m, 0.0);
    sc.normal.resize(m, [0.0; 3]);
    sc.view.resize(m, [0.0; 3]);
    sc.valid.resize(m, false);
    sc.dirs2.resize(m * r, [0.0; 3]);
    sc.vis2.resize(m * r, 0.0);
    sc.ind2.resize(m * r, [0.0; 3]);
    for (k, &i) in sc.ids.iter().enumerate() {
        let i = i as usize;
        let nn = view.normal[i];
        let cam = match eye {
            Some(e) => view_dir(surfels.means[i], e),
            None => uniform_hemisphere(nn, rng.random::<f64>(), rng.random::<f64>()),
        };
        let rand_dir = uniform_hemisphere(nn, rng.random::<f64>(), rng.random::<f64>());
        for (e, w) in [(2 * k, cam), (2 * k + 1, rand_dir)] {
            sc.albedo[e] = view.albedo[i];
            sc.rough[e] = view.roughness[i];
            sc.normal[e] = nn;
            sc.view[e] = w;
            sc.valid[e] = nn[0] * w[0] + nn[1] * w[1] + nn[2] * w[2] > 1e-4;
            for j in 0..r {
                let o = &sc.out[k * r + j];
                let (v, g, _, _) = visibility_ramp(o.transmittance, sc.opaque_below);
                sc.dirs2[e * r + j] = sc.dirs[k * r + j];
                sc.vis2[e * r + j] = v;
                sc.ind2[e * r + j] = if sc.linear { o.radiance } else { o.radiance.map(decode) }.map(|x| x * g);
            }
        }
    }
    let inp = PbrInputs {
        albedo: &sc.albedo,
        roughness: &sc.rough,
        normal: &sc.normal,
        view: &sc.view,
        dirs: &sc.dirs2,
        visibility: &sc.vis2,
        indirect: &sc.ind2,
        samples: r,
        weight: sc.weight,
        sample_weights: None,
        specular: true,
        lambert: true,
        footprints: None,
    };
    sc.direct.resize(m, [0.0; 3]);
    sc.indirect.resize(m, [0.0; 3]);
    shade_surfels(&inp, env, &mut sc.direct, &mut sc.indirect).expect("consistency: buffers sized above");

    // Residuals and their gradients.
    let count = |parity: usize| (0..b).filter(|&k| sc.valid[2 * k + parity]).count().max(1) as f32;
    let (n_cam, n_rand) = (count(0), count(1));
    let mut v_pbr = vec![[0.0f32; 3]; m];
    let mut sums = [0.0f64; 2];
    for k in 0..b {
        let i = sc.ids[k] as usize;
        for parity in 0..2 {
            let e = 2 * k + parity;
            if !sc.valid[e] {
                continue;
            }
            let norm = 3.0 * if parity == 0 { n_cam } else { n_rand };
            let dir = sc.view[e].map(|x| -x);
            let lhs = sh::eval(&surfels.sh[i], surfels.sh_degree, dir);
            let mut v_lhs = [0.0f32; 3];
            for ch in 0..3 {
                let l = sc.direct[e][ch] + sc.indirect[e][ch];
                if cfg.linear_l2 {
                    let res = decode(lhs[ch]) - l;
                    sums[parity] += (res * res) as f64 / norm as f64;
                    let g = cfg.weight * 2.0 * res / norm;
                    v_lhs[ch] = g * decode_derivative(lhs[ch]);
                    v_pbr[e][ch] = -g;
                } else {
                    let res = lhs[ch] - encode(l);
                    sums[parity] += res.abs() as f64 / norm as f64;
                    let g = cfg.weight * res.signum() * (res != 0.0) as u8 as f32 / norm;
                    v_lhs[ch] = g;
                    v_pbr[e][ch] = -g * encode_derivative(l);
                }
            }
            if !cfg.detach_lhs {
                sh::eval_backward(&surfels.sh[i], surfels.sh_degree, dir, v_lhs, &mut v_surfels.sh[i]);
            }
        }
    }
    let losses =
        RcLosses { camera: sums[0] as f32, random: sums[1] as f32, total: cfg.weight * (sums[0] + sums[1]) as f32 };
    if cfg.detach_rhs {
        return losses;
    }
    if sc.grads.v_albedo.len() != m || sc.grads.v_visibility.len() != m * r || sc.grads.v_env.len() != env.texels.len()
    {
        sc.grads = PbrGrads::new(m, r, env.texels.len());
    }
    shade_surfels_backward(&inp, env, &v_pbr, &v_pbr, cfg.detach, &mut sc.grads).expect("consistency: sized above");
    let g = &sc.grads;
    for (k, &i) in sc.ids.iter().enumerate() {
        let i = i as usize;
        for e in [2 * k, 2 * k + 1] {
            for ch in 0..3 {
                mats.v_albedo[i][ch] += g.v_albedo[e][ch];
                mats.v_normal[i][ch] += g.v_normal[e][ch];
            }
            mats.v_roughness[i] += g.v_roughness[e];
        }
        if let Some(eye) = eye {
            let vm = view_dir_backward(surfels.means[i], eye, g.v_view[2 * k]);
            for ch in 0..3 {
                mats.v_means[i][ch] += vm[ch];
            }
        }
    }
    if !cfg.detach.env {
        for (d, s) in v_env.iter_mut().zip(&g.v_env) {
            for ch in 0..3 {
                d[ch] += s[ch];
            }
        }
    }
    // Per ray: the two entries' gradients to V and L_ind, then through the decode.
    sc.ray_grads.resize(b * r, RayGrad::default());
    for k in 0..b {
        for j in 0..r {
            let (e0, e1) = ((2 * k) * r + j, (2 * k + 1) * r + j);
            let o = &sc.out[k * r + j];
            let rad = o.radiance;
            // Through the ramp: V(T), and the indirect light g(T)·L(C).
            let (_, scale, dv_dt, dg_dt) = visibility_ramp(o.transmittance, sc.opaque_below);
            let mut v_t = (g.v_visibility[e0] + g.v_visibility[e1]) * dv_dt;
            let v_ind: [f32; 3] = std::array::from_fn(|ch| {
                let (l, d) = if sc.linear { (rad[ch], 1.0) } else { (decode(rad[ch]), decode_derivative(rad[ch])) };
                let v_l = g.v_indirect[e0][ch] + g.v_indirect[e1][ch];
                v_t += v_l * l * dg_dt;
                v_l * scale * d
            });
            sc.ray_grads[k * r + j] =
                RayGrad { v_radiance: v_ind, v_transmittance: v_t, v_depth: 0.0, v_normal: [0.0; 3] };
        }
    }
    trace_backward_recorded(tracer, surfels, &sc.rays, &sc.ray_grads, v_surfels, None, &sc.record);
    losses
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trace::TraceSettings;
    use rand::SeedableRng;

    /// The derivative from the encoded value is the power-law one, on both segments, at the
    /// kink and above 1 (unclamped encode); and both match f64 finite differences.
    #[test]
    fn encode_derivative_from_the_encoded_value() {
        for k in 0..2000 {
            let x = if k == 0 { 0.003_130_8 } else { 10f32.powf(-5.0 + 5.7 * k as f32 / 2000.0) };
            let (a, b) = (encode_derivative(x), encode_derivative_given(x, encode(x)));
            assert!((a - b).abs() <= 2e-6 * a.abs(), "x {x}: {a} vs {b}");
            let xd = x as f64;
            let e = |v: f64| if v <= 0.003_130_8 { 12.92 * v } else { 1.055 * v.powf(1.0 / 2.4) - 0.055 };
            let h = 1e-4 * xd;
            if (xd - 0.003_130_8).abs() > 2.0 * h {
                let fd = (e(xd + h) - e(xd - h)) / (2.0 * h);
                assert!((fd - b as f64).abs() < 1e-4 * fd, "x {x}: {b} vs FD {fd}");
            }
        }
        assert_eq!(encode_derivative_given(0.0, 0.0), 0.0);
        assert_eq!(encode_derivative_given(-1.0, 0.0), 0.0);
    }

    /// A small scene: a floor of surfels facing up and a few tilted occluders above it.
    fn scene() -> Surfels {
        let mut s = Surfels::random_in_box(12, [-0.5, -0.5, 0.0], [0.5, 0.5, 0.0], 5);
        for i in 0..12 {
            s.quats[i] = [1.0, 0.0, 0.0, 0.0];
            s.log_scales[i] = [(0.3f32).ln(), (0.25f32).ln()];
            s.opacity_logits[i] = 1.5;
        }
        let mut occ = Surfels::random_in_box(6, [-0.4, -0.4, 0.3], [0.4, 0.4, 0.6], 6);
        for i in 0..6 {
            occ.quats[i] = [0.2, 0.9 + 0.05 * i as f32, 0.1, -0.1];
            occ.log_scales[i] = [(0.3f32).ln(), (0.2f32).ln()];
            occ.opacity_logits[i] = 0.5;
        }
        for i in 0..6 {
            s.push(occ.means[i], [0.3, 0.2], occ.quats[i], 0.62, [0.5; 3], [0.5; 3], 0.5);
        }
        let mut rg = rand_pcg::Pcg64::seed_from_u64(3);
        for c in s.sh.iter_mut() {
            for k in 0..4 {
                *c.get_mut(k).unwrap() =
                    [rg.random_range(-0.3..0.3), rg.random_range(-0.3..0.3), rg.random_range(-0.3..0.3)];
            }
        }
        s.sh_degree = 1;
        s
    }

    type Grads = (f32, SurfelGrads, MaterialGrads, Vec<[f32; 3]>);

    fn loss_and_grads(s: &Surfels, env: &EnvMap, cfg: &RcSettings) -> Grads {
        loss_and_grads_with(s, env, cfg, false)
    }

    fn loss_and_grads_with(s: &Surfels, env: &EnvMap, cfg: &RcSettings, linear: bool) -> Grads {
        loss_and_grads_ramped(s, env, cfg, linear, 0.0)
    }

    fn loss_and_grads_ramped(s: &Surfels, env: &EnvMap, cfg: &RcSettings, linear: bool, opaque_below: f32) -> Grads {
        let settings =
            TraceSettings { min_transmittance: 0.0, linear_radiance: linear, opaque_below, ..TraceSettings::default() };
        evaluate(s, env, cfg, &settings, None).0
    }

    /// One call from a fixed camera and seed; also returns the surfels it picked.
    fn evaluate(
        s: &Surfels,
        env: &EnvMap,
        cfg: &RcSettings,
        settings: &TraceSettings,
        batch: Option<&[u32]>,
    ) -> (Grads, Vec<u32>) {
        let mut view = MaterialView::default();
        view.update(s);
        let tracer = Tracer::build(s, settings);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let mut v = s.zeros_like();
        v.sh_degree = s.sh_degree;
        let mut mats = MaterialGrads::default();
        mats.reset(s.len());
        let mut v_env = vec![[0.0f32; 3]; env.texels.len()];
        let mut sc = RcScratch::default();
        let l = radiometric_consistency(
            s,
            &view,
            &tracer,
            env,
            Some([0.3, -0.2, 2.0]),
            batch,
            &mut rng,
            cfg,
            &mut sc,
            &mut v,
            &mut mats,
            &mut v_env,
        );
        ((l.total, v, mats, v_env), sc.ids)
    }

    /// 8 surfels × 8 rays, no switch set.
    fn small_settings() -> RcSettings {
        RcSettings {
            surfels: 8,
            rays: 8,
            start: RayStart::offset_only(1e-3),
            weight: 1.0,
            detach: Detach::default(),
            detach_lhs: false,
            detach_rhs: false,
            linear_l2: false,
        }
    }

    #[test]
    fn gradients_match_finite_differences() {
        check_gradients(false);
    }

    #[test]
    fn gradients_match_finite_differences_with_linear_indirect() {
        check_gradients(true);
    }

    /// Relighting's finetune residual: squared, in linear radiance.
    #[test]
    fn gradients_match_finite_differences_linear_l2() {
        check_gradients_with(false, true);
    }

    /// Central difference (fa − fb)/2h against g; when an L1 kink lies inside the step (the
    /// one-sided slopes differ), g must match the slope of one side instead.
    fn fd_agrees(g: f32, fa: f64, fb: f64, f0: f64, h: f32, rel: f64, abs: f64) -> (bool, f64) {
        let h = h as f64;
        let fd = (fa - fb) / (2.0 * h);
        let (up, down) = ((fa - f0) / h, (f0 - fb) / h);
        let near = |x: f64| (x - g as f64).abs() < rel * g.abs() as f64 + abs;
        let kink = (up - down).abs() > 0.1 * up.abs().max(down.abs()) + 1e-3;
        (near(fd) || (kink && (near(up) || near(down))), fd)
    }

    /// The visibility ramp (`TraceSettings::opaque_below`) chains through V(T) and g(T)·L:
    /// high enough that part of the rays fall below it, part above.
    #[test]
    fn gradients_match_finite_differences_through_the_visibility_ramp() {
        check_gradients_ramped(true, false, 0.5);
        check_gradients_ramped(false, false, 0.3);
    }

    fn check_gradients(linear: bool) {
        check_gradients_with(linear, false);
    }

    fn check_gradients_with(linear: bool, linear_l2: bool) {
        check_gradients_ramped(linear, linear_l2, 0.0);
    }

    fn check_gradients_ramped(linear: bool, linear_l2: bool, opaque_below: f32) {
        let loss_and_grads =
            |s: &Surfels, e: &EnvMap, c: &RcSettings| loss_and_grads_ramped(s, e, c, linear, opaque_below);
        let s = scene();
        let mut env = EnvMap::constant(16, 8, [0.0; 3]);
        for (k, t) in env.texels.iter_mut().enumerate() {
            *t = [0.5 + (k % 7) as f32 * 0.2, 0.8, 1.0 + (k % 3) as f32 * 0.3];
        }
        let cfg = RcSettings {
            surfels: 8,
            rays: 12,
            start: RayStart::offset_only(1e-3),
            // (The squared linear residual is ~20× smaller: scaled so that as many gradients
            // clear the thresholds below.)
            weight: if linear_l2 { 14.0 } else { 0.7 },
            detach: Detach::default(),
            detach_lhs: false,
            detach_rhs: false,
            linear_l2,
        };
        let (_, v, mats, v_env) = loss_and_grads(&s, &env, &cfg);
        let f = |t: &Surfels, e: &EnvMap| loss_and_grads(t, e, &cfg).0 as f64;
        let f0 = f(&s, &env);
        // The loss is piecewise linear (L1), so the check uses a smooth-enough step and looks
        // at the parameters with the largest gradients.
        let h = 2e-3f32;
        let mut checked = 0;
        // SH of the sampled surfels and of the surfels their rays hit.
        for i in 0..s.len() {
            for k in 0..4 {
                for ch in 0..3 {
                    let g = v.sh[i][k][ch];
                    if g.abs() < 1e-3 {
                        continue;
                    }
                    let (mut a, mut b) = (s.clone(), s.clone());
                    a.sh[i][k][ch] += h;
                    b.sh[i][k][ch] -= h;
                    let (ok, fd) = fd_agrees(g, f(&a, &env), f(&b, &env), f0, h, 0.05, 2e-3);
                    assert!(ok, "sh[{i}][{k}][{ch}]: fd {fd} vs {g}");
                    checked += 1;
                }
            }
        }
        assert!(checked > 10, "only {checked} SH gradients checked");
        // Albedo (activated) through the material view.
        let mut view = MaterialView::default();
        view.update(&s);
        let mut na = 0;
        for i in 0..s.len() {
            for ch in 0..3 {
                let g = mats.v_albedo[i][ch];
                if g.abs() < 1e-3 {
                    continue;
                }
                // Perturb the albedo through its logit and compare with the chained gradient.
                let sgm = crate::surfels::sigmoid(s.albedo_logits[i][ch]);
                let dl = h / (0.77 * sgm * (1.0 - sgm));
                let (mut a, mut b) = (s.clone(), s.clone());
                a.albedo_logits[i][ch] += dl;
                b.albedo_logits[i][ch] -= dl;
                let (ok, fd) = fd_agrees(g, f(&a, &env), f(&b, &env), f0, h, 0.05, 3e-3);
                assert!(ok, "albedo[{i}][{ch}]: fd {fd} vs {g}");
                na += 1;
            }
        }
        assert!(na > 3);
        // Env texels.
        let mut ne = 0;
        for t in 0..env.texels.len() {
            let g = v_env[t][1];
            if g.abs() < 1e-3 {
                continue;
            }
            let (mut a, mut b) = (env.clone(), env.clone());
            a.texels[t][1] += h;
            b.texels[t][1] -= h;
            let (ok, fd) = fd_agrees(g, f(&s, &a), f(&s, &b), f0, h, 0.05, 2e-3);
            assert!(ok, "env[{t}]: fd {fd} vs {g}");
            ne += 1;
        }
        assert!(ne > 3);
        // Opacity of the occluders (through the traced visibility and indirect light).
        let mut no = 0;
        for i in 12..s.len() {
            let g = v.opacity_logits[i];
            if g.abs() < 5e-4 {
                continue;
            }
            let (mut a, mut b) = (s.clone(), s.clone());
            a.opacity_logits[i] += h;
            b.opacity_logits[i] -= h;
            // Absolute slack below the gradients checked (≥ 5e-4), so a wrong one fails.
            let (ok, fd) = fd_agrees(g, f(&a, &env), f(&b, &env), f0, h, 0.1, 3e-4);
            assert!(ok, "opacity[{i}]: fd {fd} vs {g}");
            no += 1;
        }
        let gmax = (12..s.len()).map(|i| v.opacity_logits[i].abs()).fold(0.0f32, f32::max);
        assert!(no > 0, "no occluder was hit (largest opacity gradient {gmax})");
    }

    /// A given batch (`--rc-order sweep`) replaces the random draw, its length is B, and only
    /// its surfels' left sides get SH gradients from their own residuals.
    #[test]
    fn a_given_batch_names_the_surfels() {
        let s = scene();
        let env = EnvMap::constant(16, 8, [1.0, 0.9, 0.8]);
        // No gradient through the rays: the SH gradients are the left sides' alone.
        let cfg = RcSettings { detach_rhs: true, ..small_settings() };
        let batch = [2u32, 0, 2];
        let settings = TraceSettings { min_transmittance: 0.0, ..TraceSettings::default() };
        let ((total, v, _, _), ids) = evaluate(&s, &env, &cfg, &settings, Some(&batch));
        assert!(total.is_finite() && total > 0.0, "{total}");
        assert_eq!(ids, batch);
        for i in 0..s.len() {
            let touched = v.sh[i].iter().any(|c| c.iter().any(|&x| x != 0.0));
            assert_eq!(touched, i == 0 || i == 2, "surfel {i}");
        }
    }

    #[test]
    fn detach_switches_stop_their_gradients() {
        let s = scene();
        let env = EnvMap::constant(16, 8, [1.0, 0.9, 0.8]);
        let base = small_settings();
        let (_, v, mats, v_env) = loss_and_grads(&s, &env, &base);
        assert!(mats.v_albedo.iter().any(|a| a[0] != 0.0) && v_env.iter().any(|t| t[0] != 0.0));
        let (_, _, m2, e2) = loss_and_grads(
            &s,
            &env,
            &RcSettings { detach: Detach { env: true, material: true, normal: true }, ..base },
        );
        assert!(m2.v_albedo.iter().all(|a| *a == [0.0; 3]) && m2.v_normal.iter().all(|a| *a == [0.0; 3]));
        assert!(e2.iter().all(|t| *t == [0.0; 3]));
        let (_, v3, m3, _) = loss_and_grads(&s, &env, &RcSettings { detach_rhs: true, ..base });
        assert!(m3.v_albedo.iter().all(|a| *a == [0.0; 3]) && v3.opacity_logits.iter().all(|&o| o == 0.0));
        let (_, v4, _, _) = loss_and_grads(&s, &env, &RcSettings { detach_lhs: true, ..base });
        // With the lhs detached, the sampled surfels' SH gradients come only through rays that hit them.
        assert_ne!(v4.sh, v.sh);
    }
}
