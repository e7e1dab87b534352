//! The specular lobe by GGX importance sampling, traced for each view (`--specular traced`).
//!
//! Why: the cached incident directions are uniform over the hemisphere and shared by every
//! view, so a glossy lobe (the shared scenes' spheres have r = 0.05–0.3: a lobe a few degrees
//! wide) gets almost none of the S samples (16 when this was written, 64 since session 54),
//! and neither the reflections of the env nor those of the neighbouring objects reach the PBR
//! colour; the albedo's dark channels take the missing light instead (BENCHMARKS.md sessions
//! 29, 40). Here, for each shaded surfel and the current view ω_o, K directions are drawn
//! from the GGX distribution of visible normals (Heitz 2018, [`ggx_vndf_sample`]) at the
//! surfel's roughness and traced like the cache's rays (same origin offset and skip plane, no
//! gradients), and the lobe is the estimate
//!
//!     L_spec = 1/K Σ_k f_s(ω_o, ω_k) · (V_k·L_env(ω_k) + L_ind,k) · max(0, n·ω_k) / pdf(ω_k)
//!
//! with the env at full resolution (a sharp lobe must not read a box-filtered map). The
//! Lambert lobe stays on the cache. The estimate is the rendering equation of pbr.rs with the
//! Lambert term off and per-sample weights 1/(K·pdf), so its forward and backward are
//! pbr.rs's. The backward holds the pdf and the directions fixed (they were drawn at the
//! current roughness and normal): that gradient is an unbiased estimate of the gradient of
//! the lobe's integral, whose integration domain does not move.
//!
//! Directions under the horizon (possible for a visible-normal sample at grazing views)
//! contribute nothing and are not traced. Samples are a hash of (seed, surfel, k), so a view
//! traced twice with one seed gets the same directions.

use super::pbr::{Detach, PbrGrads, PbrInputs, shade_surfels, shade_surfels_backward};
use super::sampling::{ggx_vndf_pdf, ggx_vndf_sample};
use super::{dot, to64};
use crate::envmap::EnvMap;
use crate::error::Result;
use crate::shade::incident::RayStart;
use crate::surfels::Surfels;
use crate::trace::{Ray, RayOutput, Tracer, skip_plane_above, trace};
use rayon::prelude::*;

/// What a traced specular lobe needs besides the surfels' materials: the tracer over the
/// surfels (built with linear radiance, as the PBR stages' tracer), the full-resolution env,
/// where rays start, K and the seed of the directions.
#[derive(Clone, Copy)]
pub struct TracedSpecular<'a> {
    pub tracer: &'a Tracer,
    pub surfels: &'a Surfels,
    pub env: &'a EnvMap,
    pub start: RayStart,
    pub rays: usize,
    pub seed: u64,
}

/// The traced samples of one view: per entry (a shaded surfel) its inputs, per entry × K the
/// directions, visibilities, indirect radiances and weights 1/(K·pdf).
#[derive(Default)]
pub struct SpecularSamples {
    pub rays: usize,
    /// Zero: the lobe alone does not read the albedo (kept for [`PbrInputs`]).
    albedo: Vec<[f32; 3]>,
    roughness: Vec<f32>,
    normal: Vec<[f32; 3]>,
    view: Vec<[f32; 3]>,
    dirs: Vec<[f32; 3]>,
    visibility: Vec<f32>,
    indirect: Vec<[f32; 3]>,
    weights: Vec<f32>,
    /// The traced rays (those above the horizon) and where their results go.
    live: Vec<u32>,
    rays_buf: Vec<Ray>,
    out_buf: Vec<RayOutput>,
    pub grads: PbrGrads,
}

/// Two uniforms in [0, 1) for sample k of surfel i (a splitmix64 chain of the three).
fn uniforms(seed: u64, i: usize, k: usize) -> (f64, f64) {
    let mix = |mut x: u64| {
        x = x.wrapping_add(0x9e37_79b9_7f4a_7c15);
        x = (x ^ (x >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        x = (x ^ (x >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        x ^ (x >> 31)
    };
    let a = mix(seed ^ mix(i as u64 ^ mix(k as u64)));
    let b = mix(a);
    let unit = |x: u64| (x >> 11) as f64 / (1u64 << 53) as f64;
    (unit(a), unit(b))
}

impl SpecularSamples {
    /// Number of entries.
    pub fn len(&self) -> usize {
        self.roughness.len()
    }
    pub fn is_empty(&self) -> bool {
        self.roughness.is_empty()
    }

    /// Draw and trace the K directions of every entry: entry k is surfel `ids[k]`, with the
    /// per-surfel `roughness`, unit shading `normal` and unit `view` direction (towards the
    /// camera) given for all surfels.
    pub fn trace(
        &mut self,
        spec: &TracedSpecular,
        ids: &[u32],
        roughness: &[f32],
        normal: &[[f32; 3]],
        view: &[[f32; 3]],
    ) {
        let (m, kk) = (ids.len(), spec.rays.max(1));
        self.rays = kk;
        self.albedo.clear();
        self.albedo.resize(m, [0.0; 3]);
        self.roughness.clear();
        self.roughness.extend(ids.iter().map(|&i| roughness[i as usize]));
        self.normal.clear();
        self.normal.extend(ids.iter().map(|&i| normal[i as usize]));
        self.view.clear();
        self.view.extend(ids.iter().map(|&i| view[i as usize]));
        self.dirs.resize(m * kk, [0.0; 3]);
        self.weights.resize(m * kk, 0.0);
        self.visibility.clear();
        self.visibility.resize(m * kk, 0.0);
        self.indirect.clear();
        self.indirect.resize(m * kk, [0.0; 3]);
        let (seed, inv_k) = (spec.seed, 1.0 / kk as f64);
        self.dirs.par_chunks_mut(kk).zip(self.weights.par_chunks_mut(kk)).zip(ids.par_iter()).for_each(
            |((dirs, weights), &i)| {
                let i = i as usize;
                let (n, wo, r) = (normal[i], view[i], roughness[i] as f64);
                for k in 0..kk {
                    let (u1, u2) = uniforms(seed, i, k);
                    let d = ggx_vndf_sample(n, wo, r, u1, u2);
                    let pdf = ggx_vndf_pdf(n, wo, d, r);
                    let above = dot(to64(n), to64(d)) > 0.0;
                    dirs[k] = d;
                    // A zero weight marks a sample that contributes nothing (and is not traced).
                    weights[k] = if above && pdf > 1e-12 { (inv_k / pdf) as f32 } else { 0.0 };
                }
            },
        );
        self.live.clear();
        self.live.extend((0..m * kk).filter(|&q| self.weights[q] > 0.0).map(|q| q as u32));
        let (start, surfels) = (spec.start, spec.surfels);
        self.rays_buf.clear();
        self.rays_buf.extend(self.live.iter().map(|&q| {
            let q = q as usize;
            let i = ids[q / kk] as usize;
            let (n, mu) = (normal[i], surfels.means[i]);
            let o = start.offset;
            let skip_below = match start.skip_margin {
                Some(margin) => skip_plane_above(n, mu, margin),
                None => [0.0; 4],
            };
            Ray { origin: [mu[0] + o * n[0], mu[1] + o * n[1], mu[2] + o * n[2]], dir: self.dirs[q], skip_below }
        }));
        self.out_buf.clear();
        self.out_buf.resize(self.rays_buf.len(), RayOutput::default());
        trace(spec.tracer, surfels, &self.rays_buf, None, &mut self.out_buf, None);
        let linear = spec.tracer.settings.linear_radiance;
        for (&q, o) in self.live.iter().zip(&self.out_buf) {
            let q = q as usize;
            // The shading's visibility ramp, as the incident cache reads its rays.
            let (v, g, _, _) = crate::trace::visibility_ramp(o.transmittance, spec.tracer.settings.opaque_below);
            self.visibility[q] = v;
            let radiance = if linear { o.radiance } else { o.radiance.map(crate::shade::incident::decode) };
            self.indirect[q] = radiance.map(|x| x * g);
        }
    }

    /// The samples as rendering-equation inputs: the specular lobe alone, weights 1/(K·pdf).
    pub fn inputs(&self) -> PbrInputs<'_> {
        PbrInputs {
            albedo: &self.albedo,
            roughness: &self.roughness,
            normal: &self.normal,
            view: &self.view,
            dirs: &self.dirs,
            visibility: &self.visibility,
            indirect: &self.indirect,
            samples: self.rays,
            weight: 0.0,
            sample_weights: Some(&self.weights),
            specular: true,
            lambert: false,
            footprints: None,
        }
    }

    /// The lobe's env part and indirect part per entry (`env` at full resolution).
    pub fn shade(&self, env: &EnvMap, direct: &mut [[f32; 3]], indirect: &mut [[f32; 3]]) -> Result<()> {
        shade_surfels(&self.inputs(), env, direct, indirect)
    }

    /// Backward for the upstream gradient `v_pbr` on each entry's colour (the env and the
    /// indirect part alike): per-entry ∂/∂roughness, ∂/∂normal, ∂/∂view and the env-texel
    /// gradient, in [`grads`](Self::grads).
    pub fn backward(&mut self, env: &EnvMap, v_pbr: &[[f32; 3]]) -> Result<&PbrGrads> {
        let (m, kk) = (self.len(), self.rays);
        let mut grads = std::mem::take(&mut self.grads);
        if grads.v_roughness.len() != m || grads.v_visibility.len() != m * kk || grads.v_env.len() != env.texels.len() {
            grads = PbrGrads::new(m, kk, env.texels.len());
        }
        let result = shade_surfels_backward(&self.inputs(), env, v_pbr, v_pbr, Detach::default(), &mut grads);
        self.grads = grads;
        result.map(|()| &self.grads)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shade::brdf;
    use crate::shade::testutil::{rng, unit_in};
    use crate::shade::{add, scale, to32};
    use crate::trace::TraceSettings;
    use rand::RngExt;

    /// Rays leaving 1 mm above the surfel, no skip plane.
    fn lobe<'a>(
        tracer: &'a Tracer,
        surfels: &'a Surfels,
        env: &'a EnvMap,
        rays: usize,
        seed: u64,
    ) -> TracedSpecular<'a> {
        TracedSpecular { tracer, surfels, env, start: RayStart::offset_only(1e-3), rays, seed }
    }

    /// One surfel with a given normal (`quats` rotating +z onto it), far from everything.
    fn lone_surfel(n: [f32; 3]) -> Surfels {
        let mut s = Surfels::random_in_box(1, [0.0; 3], [0.0; 3], 1);
        s.means = vec![[0.0; 3]];
        // The rotation taking +z to n (half-angle quaternion).
        let h = crate::shade::normalize(add([0.0, 0.0, 1.0], to64(n)));
        let axis = [-h[1], h[0], 0.0]; // z × h
        s.quats = vec![[h[2] as f32, axis[0] as f32, axis[1] as f32, axis[2] as f32]];
        s.log_scales = vec![[-6.0, -6.0]];
        s.opacity_logits = vec![10.0];
        s
    }

    /// Furnace: a lone surfel under a constant sky. The importance-sampled lobe, averaged over
    /// seeds, is the specular directional albedo × the sky, from smooth to rough and at a
    /// grazing view; its indirect part is zero and every ray sees the sky.
    #[test]
    fn furnace_matches_the_quadrature_of_the_lobe() {
        let sky = [1.5f32, 0.8, 0.3];
        let env = EnvMap::constant(64, 32, sky);
        let mut rg = rng(11);
        for (r, nov) in [(0.05, 0.8), (0.1, 0.5), (0.3, 0.9), (0.6, 0.4), (0.9, 0.7), (0.3, 0.05)] {
            let n = to32(unit_in(&mut rg, [0.0, 0.0, 1.0], 0.9));
            let (t, _) = crate::shade::frame(n);
            let wo = to32(add(scale(to64(n), nov), scale(to64(t), (1.0f64 - nov * nov).sqrt())));
            let surfels = lone_surfel(n);
            assert!(dot(to64(surfels.normal(0)), to64(n)) > 0.9999);
            let tracer = Tracer::build(&surfels, &TraceSettings { linear_radiance: true, ..Default::default() });
            // The reference: brdf.rs's quadrature over the half vector (no sampling code).
            let want = brdf::directional_albedo_reference(nov, r, 0.04, 600);
            let mut samples = SpecularSamples::default();
            let (mut mean, trials) = (0.0, 400);
            for seed in 0..trials {
                let spec = lobe(&tracer, &surfels, &env, 8, seed);
                samples.trace(&spec, &[0], &[r as f32], &[n], &[wo]);
                assert!(samples.visibility.iter().zip(&samples.weights).all(|(&v, &w)| w == 0.0 || v == 1.0));
                let (mut d, mut ind) = ([[0.0f32; 3]; 1], [[0.0f32; 3]; 1]);
                samples.shade(&env, &mut d, &mut ind).unwrap();
                assert_eq!(ind[0], [0.0; 3]);
                for c in 0..3 {
                    assert!((d[0][c] / sky[c] - d[0][0] / sky[0]).abs() < 1e-5);
                }
                mean += d[0][0] as f64 / sky[0] as f64 / trials as f64;
            }
            assert!((mean - want).abs() < 0.02 * want + 1e-4, "r {r}, NoV {nov}: IS {mean} vs quadrature {want}");
        }
    }

    /// An opaque lid over a floor surfel: the glossy lobe's rays hit it and bring its
    /// radiance as indirect light, none as env light; the same seed gives the same samples.
    #[test]
    fn a_lid_turns_the_reflection_into_indirect_light() {
        let mut s = Surfels::random_in_box(2, [0.0; 3], [0.0; 3], 1);
        s.means = vec![[0.0, 0.0, 0.0], [0.0, 0.0, 0.5]];
        s.quats = vec![[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]];
        s.log_scales = vec![[-6.0, -6.0], [3.0, 3.0]];
        s.opacity_logits = vec![10.0, 10.0];
        s.sh.iter_mut().for_each(|c| *c = [[0.0; 3]; crate::sh::SH_COEFFS]);
        s.sh_degree = 0;
        let tracer = Tracer::build(&s, &TraceSettings { linear_radiance: true, ..Default::default() });
        let env = EnvMap::constant(32, 16, [2.0; 3]);
        let n = [0.0f32, 0.0, 1.0];
        let wo = to32(crate::shade::normalize([0.3, 0.0, 1.0]));
        let spec = lobe(&tracer, &s, &env, 16, 5);
        let mut a = SpecularSamples::default();
        a.trace(&spec, &[0], &[0.1, 0.5], &[n, [0.0, 0.0, -1.0]], &[wo, wo]);
        let (mut d, mut ind) = ([[0.0f32; 3]; 1], [[0.0f32; 3]; 1]);
        a.shade(&env, &mut d, &mut ind).unwrap();
        // The lid's SH colour 0.5 (linear radiance 0.5 with linear tracing) times its α ≈ 1.
        assert!(a.visibility.iter().all(|&v| v < 0.05), "{:?}", a.visibility);
        assert!(d[0].iter().all(|&x| x < 0.15 * ind[0][0]) && ind[0][0] > 0.0, "{d:?} {ind:?}");
        let mut b = SpecularSamples::default();
        b.trace(&spec, &[0], &[0.1, 0.5], &[n, [0.0, 0.0, -1.0]], &[wo, wo]);
        assert_eq!((a.dirs.clone(), a.weights.clone()), (b.dirs, b.weights));

        // A translucent lid (α 0.8): with the visibility ramp at 0.5 its rays count as blocked and
        // their radiance as the whole ray's, each sample the unramped one mapped by the ramp.
        s.opacity_logits[1] = (0.8f32 / 0.2).ln();
        let traced_with = |t0: f32| {
            let settings = TraceSettings { linear_radiance: true, opaque_below: t0, ..Default::default() };
            let tracer = Tracer::build(&s, &settings);
            let mut c = SpecularSamples::default();
            c.trace(&lobe(&tracer, &s, &env, 16, 5), &[0], &[0.1, 0.5], &[n, [0.0, 0.0, -1.0]], &[wo, wo]);
            (c.visibility.clone(), c.indirect.clone())
        };
        let ((v0, i0), (v1, i1)) = (traced_with(0.0), traced_with(0.5));
        assert!(v0.iter().any(|&v| v > 0.1 && v < 0.5), "{v0:?}");
        for q in 0..v0.len() {
            let (v, g, _, _) = crate::trace::visibility_ramp(v0[q], 0.5);
            assert!((v1[q] - v).abs() < 1e-6 && (0..3).all(|c| (i1[q][c] - g * i0[q][c]).abs() < 1e-5), "sample {q}");
        }
    }

    /// The backward through the traced samples is pbr.rs's: compare with finite differences of
    /// the estimate with the samples held fixed, per parameter, at a grazing view and small r.
    #[test]
    fn backward_matches_finite_differences_with_samples_fixed() {
        let mut rg = rng(21);
        let m = 6;
        let mut surfels = Surfels::random_in_box(m, [-1.0; 3], [1.0; 3], 3);
        for i in 0..m {
            surfels.opacity_logits[i] = 2.0;
            surfels.log_scales[i] = [-1.5, -1.5];
        }
        let tracer = Tracer::build(&surfels, &TraceSettings { linear_radiance: true, ..Default::default() });
        let mut env = EnvMap::constant(32, 16, [0.0; 3]);
        env.texels.iter_mut().for_each(|t| *t = [0, 1, 2].map(|_| rg.random_range(0.1..3.0)));
        let normal: Vec<[f32; 3]> = (0..m).map(|i| surfels.normal(i)).collect();
        // Surfel 0 seen at a grazing angle (NoV 0.03), the others from random directions.
        let view: Vec<[f32; 3]> = normal
            .iter()
            .enumerate()
            .map(|(i, &n)| {
                if i == 0 {
                    let (t, _) = crate::shade::frame(n);
                    to32(add(scale(to64(n), 0.03), scale(to64(t), (1.0f64 - 0.03 * 0.03).sqrt())))
                } else {
                    to32(unit_in(&mut rg, to64(n), 0.1))
                }
            })
            .collect();
        // The samples sit in the lobe's peak, where f32 steps of the (unnormalised) normal
        // resolve the lobe only for r ≳ 0.2; smaller r are brdf.rs's f64 checks (exact at the
        // mirror direction to 1e-4 at r = 0.08).
        let rough = vec![0.2f32, 0.25, 0.3, 0.4, 0.7, 0.95];
        let spec = lobe(&tracer, &surfels, &env, 4, 9);
        let ids: Vec<u32> = (0..m as u32).collect();
        let mut smp = SpecularSamples::default();
        smp.trace(&spec, &ids, &rough, &normal, &view);
        let v: Vec<[f32; 3]> = (0..m).map(|_| [rg.random_range(-1.0..1.0), rg.random(), rg.random()]).collect();
        let g = smp.backward(&env, &v).unwrap().clone();
        let obj = |s: &SpecularSamples| {
            let (mut d, mut ind) = (vec![[0.0f32; 3]; m], vec![[0.0f32; 3]; m]);
            s.shade(&env, &mut d, &mut ind).unwrap();
            (0..m).map(|k| (0..3).map(|c| ((d[k][c] + ind[k][c]) * v[k][c]) as f64).sum::<f64>()).sum::<f64>()
        };
        let fd = |mutate: &dyn Fn(&mut SpecularSamples, f32)| {
            let central = |e: f32| {
                let (mut p, mut q) = (SpecularSamples::default(), SpecularSamples::default());
                for x in [&mut p, &mut q] {
                    x.trace(&spec, &ids, &rough, &normal, &view);
                }
                mutate(&mut p, e);
                mutate(&mut q, -e);
                (obj(&p) - obj(&q)) / (2.0 * e as f64)
            };
            (4.0 * central(2.5e-4) - central(5e-4)) / 3.0
        };
        let close = |a: f32, b: f64, tol: f64| (a as f64 - b).abs() <= tol * (1.0 + b.abs());
        let mut nonzero = 0;
        for k in 0..m {
            let f = fd(&|s, e| s.roughness[k] += e);
            assert!(close(g.v_roughness[k], f, 5e-3), "v_r[{k}] {} vs {f}", g.v_roughness[k]);
            nonzero += (f.abs() > 1e-4) as usize;
            for c in 0..3 {
                let f = fd(&|s, e| s.normal[k][c] += e);
                assert!(close(g.v_normal[k][c], f, 1e-2), "v_n[{k}][{c}] {} vs {f}", g.v_normal[k][c]);
                let f = fd(&|s, e| s.view[k][c] += e);
                assert!(close(g.v_view[k][c], f, 1e-2), "v_wo[{k}][{c}] {} vs {f}", g.v_view[k][c]);
            }
        }
        assert!(nonzero >= 3, "too few surfels with a roughness gradient");
        // Env texels enter linearly: a unit step is exact.
        let base = obj(&smp);
        for t in (0..env.texels.len()).step_by(7) {
            let mut e2 = env.clone();
            e2.texels[t][1] += 1.0;
            let mut p = SpecularSamples::default();
            p.trace(&spec, &ids, &rough, &normal, &view);
            let (mut d, mut ind) = (vec![[0.0f32; 3]; m], vec![[0.0f32; 3]; m]);
            p.shade(&e2, &mut d, &mut ind).unwrap();
            let f = (0..m).map(|k| (0..3).map(|c| ((d[k][c] + ind[k][c]) * v[k][c]) as f64).sum::<f64>()).sum::<f64>()
                - base;
            assert!(close(g.v_env[t][1], f, 1e-3), "v_env[{t}] {} vs {f}", g.v_env[t][1]);
        }
    }
}
