//! The training iteration's shading, linearised: each entry's PBR colour L = L_direct +
//! L_indirect together with its Jacobian in the surfel's parameters, so that the backward for an
//! upstream gradient v on L is a small product per surfel plus the env's scatter, not a second
//! pass over the S samples' cache rows.
//!
//! Why: [`shade_subset_backward`](super::shade_subset_backward) re-gathers every sample
//! (direction, visibility, indirect light, env lookup) and re-runs the lobe: about 40 ms of a
//! 217 ms inverse iteration at 51k surfels (BENCHMARKS.md, session 85). Its result is linear in
//! v, so the forward can keep, per colour channel ch, with G_s = V_s·L_env(ω_s) + L_ind,s and
//! wc_s = w_s·n·ω_s (zero under the horizon):
//!
//!     E[ch]        = Σ_s wc_s G_s[ch]
//!     J_r[ch]      = Σ_s ∂spec_s/∂r · wc_s G_s[ch]
//!     J_n[c][ch]   = Σ_s (∂spec_s/∂n_c · wc_s + w_s ω_s,c (lam[ch] + spec_s)) G_s[ch]
//!     J_wo[c][ch]  = Σ_s ∂spec_s/∂ω_o,c · wc_s G_s[ch]
//!
//! and per sample wv_s = wc_s V_s and wvs_s = wv_s·spec_s for the env texels:
//! ∂L[ch]/∂L_env,s[ch] = lam[ch]·wv_s + wvs_s. The Lambert weight lam = a·kd(n·ω_o, r)/π is
//! chained in the backward as in `backward_one`. The upstream gradient of L_direct and
//! L_indirect must be the same v (the PBR image's path); the general backward stays for the rest.

use super::{EntryGrads, LaneEnv, PbrInputs, SubsetGrads, load_block};
use crate::envmap::EnvMap;
use crate::error::{Error, Result};
use crate::shade::brdf_lanes::{LANES, Lobe};
use crate::shade::float_lanes::FloatLanes;
use crate::shade::{V3, brdf, dot, scale, to32, to64};
use rayon::prelude::*;
use wide::{f32x4, f32x8};

/// Per entry: E (3), J_r (3), J_n (3 × 3, row c), J_wo (3 × 3, row c).
const JACOBIAN: usize = 24;
const J_E: usize = 0;
const J_R: usize = 3;
const J_N: usize = 6;
const J_WO: usize = 15;

/// What [`shade_subset_linearised`] keeps for [`shade_subset_linearised_backward`].
#[derive(Clone, Debug, Default)]
pub struct LinearisedShading {
    /// Per entry, the sums of the module note.
    jacobian: Vec<[f64; JACOBIAN]>,
    /// Per entry and sample: (wc·V, wc·V·spec) in f32 (what the env's gradient scatters).
    env_weights: Vec<[f32; 2]>,
    samples: usize,
}

impl LinearisedShading {
    /// Entries shaded.
    pub fn len(&self) -> usize {
        self.jacobian.len()
    }
    pub fn is_empty(&self) -> bool {
        self.jacobian.is_empty()
    }
}

/// One entry: (L_direct, L_indirect, its sums); writes its samples' env weights.
fn shade_one_linearised<L: FloatLanes>(
    inp: &PbrInputs,
    env: &LaneEnv,
    i: usize,
    env_weights: &mut [[f32; 2]],
) -> (V3, V3, [f64; JACOBIAN]) {
    let s = inp.samples;
    let (a, r, n, wo) = (to64(inp.albedo[i]), inp.roughness[i] as f64, to64(inp.normal[i]), to64(inp.view[i]));
    let footprints = inp.footprints_for(env.env);
    let kd = if inp.lambert { brdf::diffuse_weight(dot(n, wo), r).0 } else { 0.0 };
    let lambert = scale(a, kd * std::f64::consts::FRAC_1_PI).map(L::splat);
    let lobe = inp.specular.then(|| Lobe::<L>::new(r, n, wo));
    let zero = L::ZERO;
    let (mut direct, mut indirect) = ([zero; 3], [zero; 3]);
    let (mut e, mut jr, mut jn, mut jwo) = ([zero; 3], [zero; 3], [[zero; 3]; 3], [[zero; 3]; 3]);
    for k0 in (i * s..(i + 1) * s).step_by(LANES) {
        let len = (i * s + s - k0).min(LANES);
        let b = load_block::<L>(inp, env, footprints, n, k0, len, None);
        // The lobe's derivatives for a unit upstream gradient (it is linear in it).
        let lg = lobe.as_ref().map(|l| l.eval_with_backward(b.dirs, L::splat(1.0)));
        let spec = lg.map_or(zero, |g| g.spec);
        for ch in 0..3 {
            let fw = b.wc * (lambert[ch] + spec);
            direct[ch] += fw * b.vis * b.le[ch];
            indirect[ch] += fw * b.li[ch];
            let g = b.vis * b.le[ch] + b.li[ch];
            let wcg = b.wc * g;
            e[ch] += wcg;
            let cos_part = b.w * (lambert[ch] + spec) * g;
            for c in 0..3 {
                jn[c][ch] += b.dirs[c] * cos_part;
            }
            if let Some(lg) = &lg {
                jr[ch] += lg.v_roughness * wcg;
                for c in 0..3 {
                    jn[c][ch] += lg.v_n[c] * wcg;
                    jwo[c][ch] += lg.v_wo[c] * wcg;
                }
            }
        }
        let wv = (b.wc * b.vis).to_f32s();
        let wvs = (b.wc * b.vis * spec).to_f32s();
        let base = k0 - i * s;
        for j in 0..len {
            env_weights[base + j] = [wv[j], wvs[j]];
        }
    }
    let mut jac = [0.0; JACOBIAN];
    for ch in 0..3 {
        jac[J_E + ch] = e[ch].sum();
        jac[J_R + ch] = jr[ch].sum();
        for c in 0..3 {
            jac[J_N + 3 * c + ch] = jn[c][ch].sum();
            jac[J_WO + 3 * c + ch] = jwo[c][ch].sum();
        }
    }
    (direct.map(L::sum), indirect.map(L::sum), jac)
}

/// [`shade_subset`](super::shade_subset) (the same outputs to f32 rounding: the samples run in
/// f32 lanes), keeping in `lin` what [`shade_subset_linearised_backward`] needs.
///
/// f32 lanes because this is the inverse iteration's largest shading pass and its inputs are
/// f32: f64 lanes (the tests' instantiation) took 1.6–1.8 × as long on the AVX2 VM (50k surfels ×
/// 64 samples: 82–92 ms against 45–57 ms, BENCHMARKS.md session 90). Sums over the samples run
/// per lane in f32 (eight samples a lane at S = 64) and across lanes in f64. Near the mirror
/// direction of smooth surfels the f32 lobe is coarser (see `f32_lanes_track_the_f64_lanes`).
pub fn shade_subset_linearised(
    inp: &PbrInputs,
    env: &EnvMap,
    ids: &[u32],
    direct: &mut [[f32; 3]],
    indirect: &mut [[f32; 3]],
    lin: &mut LinearisedShading,
) -> Result<()> {
    shade_subset_linearised_in::<f32x8>(inp, env, ids, direct, indirect, lin)
}

/// [`shade_subset_linearised`] in lanes of `L`.
fn shade_subset_linearised_in<L: FloatLanes>(
    inp: &PbrInputs,
    env: &EnvMap,
    ids: &[u32],
    direct: &mut [[f32; 3]],
    indirect: &mut [[f32; 3]],
    lin: &mut LinearisedShading,
) -> Result<()> {
    inp.validate()?;
    let (m, s) = (ids.len(), inp.samples);
    if direct.len() != m || indirect.len() != m {
        return Err(Error::invalid("PBR outputs", format!("need {m} entries")));
    }
    if ids.iter().any(|&i| i as usize >= inp.len()) {
        return Err(Error::invalid("PBR subset", format!("an id is not below {}", inp.len())));
    }
    lin.samples = s;
    lin.jacobian.resize(m, [0.0; JACOBIAN]);
    lin.env_weights.resize(m * s, [0.0; 2]);
    let env = &LaneEnv::new(env);
    direct
        .par_iter_mut()
        .zip(indirect.par_iter_mut())
        .zip(lin.jacobian.par_iter_mut())
        .zip(lin.env_weights.par_chunks_mut(s.max(1)))
        .zip(ids.par_iter())
        .with_min_len(64)
        .for_each(|((((d, ind), jac), weights), &i)| {
            let (a, b, j) = shade_one_linearised::<L>(inp, env, i as usize, weights);
            *d = to32(a);
            *ind = to32(b);
            *jac = j;
        });
    Ok(())
}

/// Backward of [`shade_subset_linearised`] for an upstream gradient `v_pbr` on each entry's
/// L = L_direct + L_indirect: the gradients of
/// [`shade_subset_backward`](super::shade_subset_backward) with v_direct = v_indirect = v_pbr
/// and nothing detached. `inp`, `env` and `ids` must be the forward's.
pub fn shade_subset_linearised_backward(
    inp: &PbrInputs,
    env: &EnvMap,
    ids: &[u32],
    lin: &LinearisedShading,
    v_pbr: &[[f32; 3]],
    grads: &mut SubsetGrads,
) -> Result<()> {
    inp.validate()?;
    let (m, s) = (ids.len(), inp.samples);
    if v_pbr.len() != m || lin.len() != m || lin.samples != s || lin.env_weights.len() != m * s {
        return Err(Error::invalid("PBR upstream gradients", format!("need {m} entries of the forward's shading")));
    }
    let footprints = inp.footprints_for(env);
    grads.fill(m, env.texels.len(), false, |k, acc| {
        let v = to64(v_pbr[k]);
        if v == [0.0; 3] {
            return ([0.0; 3], 0.0, [0.0; 3], [0.0; 3]);
        }
        let i = ids[k] as usize;
        let (grad, lam) = entry_gradients(inp, i, &lin.jacobian[k], v);
        // The env texels: v[ch]·(lam[ch]·wv + wvs) through each sample's bilinear taps.
        let vl = f32x4::from([(v[0] * lam[0]) as f32, (v[1] * lam[1]) as f32, (v[2] * lam[2]) as f32, 0.0]);
        let v4 = f32x4::from([v[0] as f32, v[1] as f32, v[2] as f32, 0.0]);
        for (q, &[wv, wvs]) in lin.env_weights[k * s..(k + 1) * s].iter().enumerate() {
            if wv == 0.0 {
                continue;
            }
            let at = i * s + q;
            let fp = match footprints {
                Some(f) => env.unpack(f[at]),
                None => env.footprint(inp.dirs[at]),
            };
            let g = vl * f32x4::splat(wv) + v4 * f32x4::splat(wvs);
            for t in 0..4 {
                acc[fp.index[t]] += g * f32x4::splat(fp.weight[t]);
            }
        }
        grad
    });
    Ok(())
}

/// One entry's albedo, roughness, normal and view gradients from its sums, and the Lambert
/// weight lam = a·kd/π (per channel) for the env's gradient.
fn entry_gradients(inp: &PbrInputs, i: usize, jac: &[f64; JACOBIAN], v: V3) -> (EntryGrads, V3) {
    let (a, r, n, wo) = (to64(inp.albedo[i]), inp.roughness[i] as f64, to64(inp.normal[i]), to64(inp.view[i]));
    let (kd, dkd_dnov, dkd_dr) = if inp.lambert { brdf::diffuse_weight(dot(n, wo), r) } else { (0.0, 0.0, 0.0) };
    let inv_pi = std::f64::consts::FRAC_1_PI;
    // Σ_s of the Lambert lobe's upstream gradient, per channel: v[ch]·E[ch].
    let v_lambert: V3 = std::array::from_fn(|ch| v[ch] * jac[J_E + ch]);
    let row = |at: usize| v[0] * jac[at] + v[1] * jac[at + 1] + v[2] * jac[at + 2];
    let v_kd = dot(v_lambert, a) * inv_pi;
    let va = to32(scale(v_lambert, kd * inv_pi));
    let vr = (row(J_R) + v_kd * dkd_dr) as f32;
    let vn = to32(std::array::from_fn(|c| row(J_N + 3 * c) + wo[c] * v_kd * dkd_dnov));
    let vv = to32(std::array::from_fn(|c| row(J_WO + 3 * c) + n[c] * v_kd * dkd_dnov));
    ((va, vr, vn, vv), scale(a, kd * inv_pi))
}

#[cfg(test)]
mod tests {
    use super::super::tests::{
        Case, benchmark_case, check_env_gradient, check_material_gradients, random_case, random_env, richardson,
    };
    use super::super::{Detach, shade_one, shade_subset, shade_subset_backward};
    use super::*;
    use crate::envmap::PackedFootprint;
    use crate::shade::testutil::{close, rng};
    use crate::shade::{add, frame};
    use rand::RngExt;
    use wide::f64x8;

    /// A case of `n` surfels: grazing views on the first two (n·ω_o ≈ 2e-3 and below the
    /// clamp), roughness at both ends, optional importance-sampling weights.
    fn case_with(n: usize, s: usize, seed: u64, specular: bool, lambert: bool, weighted: bool) -> Case {
        let mut c = random_case(n, s, seed);
        for (i, z) in [(0usize, 2e-3f64), (1, -1e-3)] {
            let nn = to64(c.normal[i]);
            let (t, _) = frame(c.normal[i]);
            c.view[i] = to32(add(nn.map(|x| x * z), to64(t).map(|x| x * (1.0 - z * z).sqrt())));
        }
        let mut rg = rng(seed ^ 0x5eed);
        let sample_weights = weighted.then(|| (0..n * s).map(|_| rg.random_range(0.05..2.0f32)).collect());
        Case { specular, lambert, sample_weights, ..c }
    }

    /// The linearised forward gives `shade_subset`'s colours, and its backward the general
    /// backward's gradients with v_direct = v_indirect (an independent path: it re-gathers every
    /// sample), for every lobe setting, partial blocks, cached footprints or not, repeated ids
    /// and entries without upstream gradient.
    #[test]
    fn matches_the_general_backward() {
        let env = random_env(16, 32, 7);
        let mut checked = 0;
        for (specular, lambert, weighted) in [(true, true, false), (false, true, false), (true, false, true)] {
            for s in [5, 13, 64] {
                let case = case_with(12, s, 40 + s as u64, specular, lambert, weighted);
                let packed: Vec<PackedFootprint> = case.dirs.iter().map(|d| env.packed_footprint(*d)).collect();
                let ids = [3u32, 0, 11, 1, 3, 7, 5];
                let mut rg = rng(s as u64);
                let mut v: Vec<[f32; 3]> =
                    ids.iter().map(|_| [rg.random_range(-1.0..1.0), rg.random_range(-1.0..1.0), rg.random()]).collect();
                v[5] = [0.0; 3];
                for cached in [false, true] {
                    let inp = case.inputs_cached(&packed, &env, cached);
                    let m = ids.len();
                    let (mut d, mut ind) = (vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
                    let (mut d2, mut ind2) = (vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
                    shade_subset(&inp, &env, &ids, &mut d, &mut ind).unwrap();
                    let mut lin = LinearisedShading::default();
                    shade_subset_linearised_in::<f64x8>(&inp, &env, &ids, &mut d2, &mut ind2, &mut lin).unwrap();
                    for k in 0..m {
                        for ch in 0..3 {
                            assert!(close(d2[k][ch] as f64, d[k][ch] as f64, 1e-6, 1e-9), "direct {k}");
                            assert!(close(ind2[k][ch] as f64, ind[k][ch] as f64, 1e-6, 1e-9), "indirect {k}");
                        }
                    }
                    let mut want = SubsetGrads::default();
                    shade_subset_backward(&inp, &env, &ids, &v, &v, Detach::default(), &mut want).unwrap();
                    let mut got = SubsetGrads::default();
                    shade_subset_linearised_backward(&inp, &env, &ids, &lin, &v, &mut got).unwrap();
                    let scale_of = |x: &[[f32; 3]]| x.iter().flatten().fold(0f64, |a, &b| a.max(b.abs() as f64));
                    let near = |a: f32, b: f32, scale: f64| close(a as f64, b as f64, 1e-5, 1e-6 * scale);
                    let (sn, sv) = (scale_of(&want.v_normal), scale_of(&want.v_view));
                    for k in 0..m {
                        for ch in 0..3 {
                            assert!(near(got.v_albedo[k][ch], want.v_albedo[k][ch], 1.0), "v_a {k}");
                            assert!(near(got.v_normal[k][ch], want.v_normal[k][ch], sn), "v_n {k}");
                            assert!(near(got.v_view[k][ch], want.v_view[k][ch], sv), "v_wo {k}");
                        }
                        assert!(near(got.v_roughness[k], want.v_roughness[k], 1.0), "v_r {k}");
                    }
                    assert_eq!((got.v_albedo[5], got.v_roughness[5]), ([0.0; 3], 0.0));
                    let se = scale_of(&want.v_env);
                    assert!(se > 0.0);
                    for (a, b) in got.v_env.iter().zip(&want.v_env) {
                        for ch in 0..3 {
                            assert!(near(a[ch], b[ch], se), "v_env {a:?} vs {b:?}");
                        }
                    }
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, 18);
    }

    /// The f32 lanes (training) against the f64 lanes (checked above against the general path
    /// and finite differences): colours, and the gradients of one backward fed by either
    /// forward, relative to each quantity's largest magnitude over the entries. Everything
    /// finite.
    ///
    /// The bound depends on the lobe's width: tt = 1 − NoH²(1 − α²) carries an absolute
    /// rounding of ≈ 1e-7 in f32 against tt ≈ α² near the mirror direction, so smooth surfels
    /// (three of twelve at each roughness, with samples 3e-3 and 3e-2 rad off their mirror
    /// direction) are checked at bounds that grow as α² shrinks; at r = 1e-3, 1 − α² rounds to 1
    /// in f32 and only finiteness is asked. (The f64 lanes are no exact truth there either:
    /// normals stored in f32 are unit to ≈ 1e-7, the same absolute error in tt.)
    #[test]
    fn f32_lanes_track_the_f64_lanes() {
        let env = random_env(16, 32, 8);
        // (roughness of surfels 2–4, bound on colours, on the gradients)
        let settings =
            [(None, 1e-5, 1e-4), (Some(0.3f32), 1e-4, 3e-4), (Some(0.1), 1e-2, 2e-2), (Some(0.05), 0.1, 0.5)];
        let finite_only = [(Some(0.02f32), f64::INFINITY, f64::INFINITY), (Some(1e-3), f64::INFINITY, f64::INFINITY)];
        let mut checked = 0;
        for (specular, lambert, weighted) in [(true, true, false), (true, false, true)] {
            for s in [13, 64] {
                for &(smooth, colour_bound, grad_bound) in settings.iter().chain(&finite_only) {
                    let mut case = case_with(12, s, 70 + s as u64, specular, lambert, weighted);
                    for i in smooth.map_or(0..0, |_| 2..5) {
                        case.rough[i] = smooth.unwrap();
                        // Two samples just off the mirror direction of the view.
                        let (nn, wo) = (to64(case.normal[i]), to64(case.view[i]));
                        let m = crate::shade::sub(scale(nn, 2.0 * dot(nn, wo)), wo);
                        let (t, _) = frame(to32(m));
                        for (q, off) in [(0, 3e-3), (1, 3e-2)] {
                            case.dirs[i * s + q] = to32(crate::shade::normalize(add(m, scale(to64(t), off))));
                        }
                    }
                    let inp = case.inputs();
                    let ids: Vec<u32> = (0..12).collect();
                    let mut rg = rng(s as u64 + 1);
                    let v: Vec<[f32; 3]> = ids
                        .iter()
                        .map(|_| [rg.random_range(-1.0..1.0), rg.random_range(-1.0..1.0), rg.random()])
                        .collect();
                    let run = |f32_lanes: bool| {
                        let (mut d, mut ind) = (vec![[0.0; 3]; 12], vec![[0.0; 3]; 12]);
                        let mut lin = LinearisedShading::default();
                        if f32_lanes {
                            shade_subset_linearised(&inp, &env, &ids, &mut d, &mut ind, &mut lin).unwrap();
                        } else {
                            shade_subset_linearised_in::<f64x8>(&inp, &env, &ids, &mut d, &mut ind, &mut lin).unwrap();
                        }
                        let mut g = SubsetGrads::default();
                        shade_subset_linearised_backward(&inp, &env, &ids, &lin, &v, &mut g).unwrap();
                        (d, ind, g)
                    };
                    let (d32, i32_, g32) = run(true);
                    let (d64, i64_, g64) = run(false);
                    let flat = |x: &[[f32; 3]]| x.iter().flatten().map(|&y| y as f64).collect::<Vec<f64>>();
                    let rel = |a: &[f64], b: &[f64]| {
                        assert!(a.iter().all(|x| x.is_finite()), "not finite at {smooth:?}");
                        let scale = b.iter().fold(0f64, |m, x| m.max(x.abs())).max(f64::MIN_POSITIVE);
                        a.iter().zip(b).fold(0f64, |m, (x, y)| m.max((x - y).abs())) / scale
                    };
                    let rough: [Vec<f64>; 2] = [&g32, &g64].map(|g| g.v_roughness.iter().map(|&x| x as f64).collect());
                    let colour = rel(&flat(&d32), &flat(&d64)).max(rel(&flat(&i32_), &flat(&i64_)));
                    let grads = [
                        rel(&flat(&g32.v_albedo), &flat(&g64.v_albedo)),
                        rel(&rough[0], &rough[1]),
                        rel(&flat(&g32.v_normal), &flat(&g64.v_normal)),
                        rel(&flat(&g32.v_view), &flat(&g64.v_view)),
                        rel(&flat(&g32.v_env), &flat(&g64.v_env)),
                    ];
                    assert!(colour <= colour_bound, "colours at {smooth:?}, S {s}: {colour:e}");
                    for (what, err) in ["albedo", "roughness", "normal", "view", "env"].iter().zip(grads) {
                        assert!(err <= grad_bound, "{what} gradient at {smooth:?}, S {s}: {err:e}");
                    }
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, 24);
    }

    /// The linearised backward against central differences of the linearised forward (f64
    /// outputs), per parameter: albedo, roughness, normal, view and env texels.
    #[test]
    fn backward_matches_finite_differences() {
        for (specular, lambert, weighted, s) in
            [(true, true, false, 16), (true, false, true, 13), (false, true, false, 8)]
        {
            let make = || case_with(5, s, 9, specular, lambert, weighted);
            let env = random_env(16, 32, 2);
            let case = make();
            let n = case.albedo.len();
            let ids: Vec<u32> = (0..n as u32).collect();
            let mut rg = rng(4);
            let v: Vec<[f32; 3]> =
                (0..n).map(|_| [rg.random_range(-1.0..1.0), rg.random(), rg.random_range(-1.0..1.0)]).collect();
            let (mut d, mut ind) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
            let mut lin = LinearisedShading::default();
            shade_subset_linearised_in::<f64x8>(&case.inputs(), &env, &ids, &mut d, &mut ind, &mut lin).unwrap();
            let mut g = SubsetGrads::default();
            shade_subset_linearised_backward(&case.inputs(), &env, &ids, &lin, &v, &mut g).unwrap();
            let obj = |c: &Case, e: &EnvMap, i: usize| {
                let mut weights = vec![[0.0f32; 2]; s];
                let (dd, ii, _) = shade_one_linearised::<f64x8>(&c.inputs(), &LaneEnv::new(e), i, &mut weights);
                // The general forward's value, as a check of the linearised one's.
                let (d0, i0) = shade_one(&c.inputs(), &LaneEnv::new(e), i);
                for ch in 0..3 {
                    assert!(close(dd[ch] + ii[ch], d0[ch] + i0[ch], 1e-12, 1e-15));
                }
                dot(add(dd, ii), to64(v[i]))
            };
            // Richardson-extrapolated central differences of f32 inputs.
            let fd = |mutate: &dyn Fn(&mut Case, f32), i: usize| richardson(&make, &|c| obj(c, &env, i), mutate, 1e-4);
            // Surfels 0 and 1 view at grazing angles: steps must not cross n·ω_o = 0 (a kink).
            let grads = (&g.v_albedo[..], &g.v_roughness[..], &g.v_normal[..], &g.v_view[..]);
            for i in 0..n {
                check_material_gradients(i, grads, &fd, (1e-2, 2e-3));
            }
            check_env_gradient(&env, &g.v_env, |e| (0..n).map(|i| obj(&case, e, i)).sum::<f64>());
        }
    }

    /// The linearised forward alone, repeated, for a profiler (`perf record` on `cargo test
    /// --release --lib linearised::tests::forward_for_profiling -- --ignored --nocapture`): 50k
    /// surfels × 64 samples with cached footprints, the training iteration's shape.
    #[test]
    #[ignore]
    fn forward_for_profiling() {
        profile(false);
    }

    /// The linearised backward alone, repeated, the same way (fixed upstream gradients on
    /// every entry).
    #[test]
    #[ignore]
    fn backward_for_profiling() {
        profile(true);
    }

    fn profile(backward: bool) {
        let (env, case, packed) = benchmark_case();
        let n = case.albedo.len();
        let inputs = case.inputs_cached(&packed, &env, true);
        let ids: Vec<u32> = (0..n as u32).collect();
        let (mut d, mut ind) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
        let mut lin = LinearisedShading::default();
        let v = vec![[0.5f32, -0.25, 1.0]; n];
        let mut g = SubsetGrads::default();
        if backward {
            shade_subset_linearised(&inputs, &env, &ids, &mut d, &mut ind, &mut lin).unwrap();
        }
        let reps = 40;
        let t0 = std::time::Instant::now();
        for _ in 0..reps {
            if backward {
                shade_subset_linearised_backward(&inputs, &env, &ids, &lin, &v, &mut g).unwrap();
            } else {
                shade_subset_linearised(&inputs, &env, &ids, &mut d, &mut ind, &mut lin).unwrap();
            }
        }
        let ms = t0.elapsed().as_secs_f64() / reps as f64 * 1e3;
        if backward {
            let sum: f64 = g.v_env.iter().flatten().map(|&x| x as f64).sum();
            println!("linearised backward: {ms:.1} ms (env gradient sum {sum:.6e})");
        } else {
            println!("linearised forward: {ms:.1} ms");
        }
    }

    #[test]
    fn rejects_a_backward_of_another_shading() {
        let env = random_env(8, 16, 1);
        let case = random_case(4, 8, 2);
        let ids = [0u32, 2];
        let (mut d, mut ind) = (vec![[0.0; 3]; 2], vec![[0.0; 3]; 2]);
        let mut lin = LinearisedShading::default();
        shade_subset_linearised(&case.inputs(), &env, &ids, &mut d, &mut ind, &mut lin).unwrap();
        let mut g = SubsetGrads::default();
        let err = shade_subset_linearised_backward(&case.inputs(), &env, &[0], &lin, &[[1.0; 3]], &mut g);
        assert!(err.is_err());
        let bad = shade_subset_linearised(&case.inputs(), &env, &[0, 4], &mut d, &mut ind, &mut lin);
        assert!(bad.is_err());
    }
}
