//! The per-surfel rendering equation of DESIGN §1 (RadioGS), for surfel i with albedo a,
//! roughness r, normal n, view direction ω_o (towards the camera) and S incident directions ω_s:
//!
//!     L_pbr = Σ_s w_s · f(ω_o, ω_s) · (V_s·L_env(ω_s) + L_ind,s) · max(0, n·ω_s)
//!           = L_direct (the V·L_env part) + L_indirect (the L_ind part)
//!
//! with f the BRDF of brdf.rs and w_s the solid angle each direction stands for: the weight
//! returned by `sampling::fibonacci_hemisphere` (2π(1 − sin 10°)/S for the default spread
//! placement, 2π/S for IRGS's clamp — DESIGN's 2π/S), or per-sample weights 1/(S·pdf) for
//! importance sampling. The directions, visibilities and indirect radiances are inputs (the
//! per-surfel cache or the tracer's output): the gradient to n does not move the directions.
//!
//! Parallel decomposition: rayon over chunks of surfels; each surfel's S samples run in blocks
//! of eight lanes (no allocation): the per-sample inputs and env lookups are gathered per
//! lane (`load_block`), the specular lobe (`brdf_lanes::Lobe`, the scalar lobe to rounding), the
//! products and the sums run in SIMD, and the lane sums are added in lane order at the end. The
//! lanes here are f64; the blocks and the lobe are generic over the lane type
//! ([`FloatLanes`]) because the inverse iteration's linearised shading runs them in f32. The
//! backward recomputes the forward terms (nothing saved) and accumulates the env-texel gradient
//! in one buffer per rayon job, summed at the end. The inverse iteration's PBR image uses the
//! linearised pair instead ([`linearised`]: the forward keeps each entry's Jacobian, so its
//! backward does not pass over the samples again but for the env's scatter); the general
//! backward stays for the consistency (gradients to the traced samples) and as its reference.

use super::brdf_lanes::{LANES, Lobe};
use super::float_lanes::FloatLanes;
use super::{V3, add, brdf, dot, scale, to32, to64};
use crate::envmap::{EnvMap, Footprint, PackedFootprint};
use crate::error::{Error, Result};
use rayon::prelude::*;
use wide::{f32x4, f64x8};

mod linearised;
pub use linearised::{LinearisedShading, shade_subset_linearised, shade_subset_linearised_backward};

/// SoA inputs: N surfels, S samples each (per-sample arrays are N·S, surfel-major).
#[derive(Clone, Copy)]
pub struct PbrInputs<'a> {
    pub albedo: &'a [[f32; 3]],
    pub roughness: &'a [f32],
    /// Unit normals.
    pub normal: &'a [[f32; 3]],
    /// Unit directions from the surfel towards the camera.
    pub view: &'a [[f32; 3]],
    /// Unit incident directions ω_s (pointing away from the surface), N·S.
    pub dirs: &'a [[f32; 3]],
    /// V_s ∈ [0, 1], N·S.
    pub visibility: &'a [f32],
    /// L_ind,s (linear rgb), N·S.
    pub indirect: &'a [[f32; 3]],
    /// S.
    pub samples: usize,
    /// Solid angle per sample (used when `sample_weights` is None).
    pub weight: f32,
    /// Optional per-sample weights (N·S), e.g. 1/(S·pdf) for importance sampling.
    pub sample_weights: Option<&'a [f32]>,
    /// Include the GGX specular lobe in f (true), or only the Lambert term (false: the caller
    /// adds the specular part another way, e.g. split-sum).
    pub specular: bool,
    /// Include the Lambert lobe in f (true), or only the specular lobe (false: samples drawn
    /// for the specular lobe alone, `traced_specular`).
    pub lambert: bool,
    /// Optional env footprints of `dirs` (N·S), used when the env has their size: the same
    /// lookups without the per-sample direction → pixel mapping.
    pub footprints: Option<CachedFootprints<'a>>,
}

/// Env footprints of fixed directions for maps of `width` × `height`.
#[derive(Clone, Copy)]
pub struct CachedFootprints<'a> {
    pub data: &'a [PackedFootprint],
    pub width: usize,
    pub height: usize,
}

impl PbrInputs<'_> {
    /// The footprints when they were made for `env`'s size.
    #[inline]
    fn footprints_for(&self, env: &EnvMap) -> Option<&[PackedFootprint]> {
        self.footprints.filter(|f| f.width == env.width && f.height == env.height).map(|f| f.data)
    }
}

/// What the backward does not differentiate (the published method's detach switches).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Detach {
    /// No gradient to the env texels.
    pub env: bool,
    /// No gradient to albedo and roughness.
    pub material: bool,
    /// No gradient to the normal.
    pub normal: bool,
}

/// Gradients of [`shade_surfels`]; every buffer is overwritten by the backward.
#[derive(Clone, Debug, Default)]
pub struct PbrGrads {
    pub v_albedo: Vec<[f32; 3]>,
    pub v_roughness: Vec<f32>,
    pub v_normal: Vec<[f32; 3]>,
    pub v_view: Vec<[f32; 3]>,
    /// N·S.
    pub v_visibility: Vec<f32>,
    /// N·S.
    pub v_indirect: Vec<[f32; 3]>,
    /// Env texels (∂/∂ linear radiance; the caller chains the exp activation).
    pub v_env: Vec<[f32; 3]>,
}

impl PbrGrads {
    /// Buffers sized for `n` surfels with `s` samples and an env of `texels` texels.
    pub fn new(n: usize, s: usize, texels: usize) -> PbrGrads {
        PbrGrads {
            v_albedo: vec![[0.0; 3]; n],
            v_roughness: vec![0.0; n],
            v_normal: vec![[0.0; 3]; n],
            v_view: vec![[0.0; 3]; n],
            v_visibility: vec![0.0; n * s],
            v_indirect: vec![[0.0; 3]; n * s],
            v_env: vec![[0.0; 3]; texels],
        }
    }
}

impl PbrInputs<'_> {
    /// Number of surfels.
    pub fn len(&self) -> usize {
        self.albedo.len()
    }
    pub fn is_empty(&self) -> bool {
        self.albedo.is_empty()
    }

    fn validate(&self) -> Result<()> {
        let n = self.albedo.len();
        let ns = n * self.samples;
        let check = |what: &str, got: usize, want: usize| {
            if got != want {
                Err(Error::invalid(format!("PBR inputs: {what}"), format!("length {got}, expected {want}")))
            } else {
                Ok(())
            }
        };
        check("roughness", self.roughness.len(), n)?;
        check("normal", self.normal.len(), n)?;
        check("view", self.view.len(), n)?;
        check("dirs", self.dirs.len(), ns)?;
        check("visibility", self.visibility.len(), ns)?;
        check("indirect", self.indirect.len(), ns)?;
        if let Some(w) = self.sample_weights {
            check("sample_weights", w.len(), ns)?;
        }
        Ok(())
    }

    #[inline]
    fn w(&self, k: usize) -> f64 {
        match self.sample_weights {
            Some(w) => w[k] as f64,
            None => self.weight as f64,
        }
    }
}

/// Chunks per parallel accumulator of the env gradient (a fixed partition, so the sum's order
/// is fixed). Each group zeroes and sums a whole env-sized accumulator, so groups of 1024
/// surfels: ~36 per 36k-surfel view instead of 142 at 4 chunks (whose zeroing and summing took
/// a few ms an iteration).
const REDUCE_GROUP: usize = 16;
/// Surfels per parallel chunk of the backward passes.
const CHUNK_SURFELS: usize = 64;

#[inline]
fn splat(x: f64) -> f64x8 {
    f64x8::splat(x)
}

/// The env as the lane kernel reads it: the map (for footprints) and its texels padded to four
/// floats, so that a bilinear lookup is four SIMD loads and products, not twelve scalar ones.
pub struct LaneEnv<'a> {
    pub env: &'a EnvMap,
    texels: Vec<f32x4>,
}

impl<'a> LaneEnv<'a> {
    pub fn new(env: &'a EnvMap) -> LaneEnv<'a> {
        LaneEnv { env, texels: env.texels.iter().map(|t| f32x4::from([t[0], t[1], t[2], 0.0])).collect() }
    }
}

/// Samples k0..k0 + len of one surfel in lanes. Lanes that do not contribute (past `len`, or
/// under the horizon: n·ω ≤ 0) have zero weight and radiance and the direction n (harmless in
/// the lobe), so every sum over lanes is the sum over the live samples.
struct Block<L: FloatLanes> {
    dirs: [L; 3],
    /// Sample weight (0 on dead lanes).
    w: L,
    /// w · n·ω (0 on dead lanes).
    wc: L,
    /// Visibility, env radiance (bilinear in f32) and cached indirect radiance of each sample.
    vis: L,
    le: [L; 3],
    li: [L; 3],
    live: [bool; LANES],
}

/// Gathers a block: the directions, their cosines, and for the live lanes the env lookup
/// (its footprint written to `fps` when given, for the backward's scatter).
#[inline]
fn load_block<L: FloatLanes>(
    inp: &PbrInputs,
    env: &LaneEnv,
    footprints: Option<&[PackedFootprint]>,
    n: V3,
    k0: usize,
    len: usize,
    mut fps: Option<&mut [Footprint; LANES]>,
) -> Block<L> {
    if len == LANES {
        return load_full_block(inp, env, footprints, n, k0, fps);
    }
    // A partial block, lane by lane.
    let mut d = [[0.0f64; LANES]; 3];
    let mut w = [0.0f64; LANES];
    let mut vis = [0.0f64; LANES];
    let mut le = [[0.0f64; LANES]; 3];
    let mut li = [[0.0f64; LANES]; 3];
    let mut live = [false; LANES];
    for j in 0..LANES {
        let dk = if j < len { inp.dirs[k0 + j] } else { [0.0; 3] };
        let c = n[0] * dk[0] as f64 + n[1] * dk[1] as f64 + n[2] * dk[2] as f64;
        if j >= len || c <= 0.0 {
            for a in 0..3 {
                d[a][j] = n[a];
            }
            continue;
        }
        let k = k0 + j;
        live[j] = true;
        for a in 0..3 {
            d[a][j] = dk[a] as f64;
        }
        w[j] = inp.w(k);
        vis[j] = inp.visibility[k] as f64;
        let ind = inp.indirect[k];
        for ch in 0..3 {
            li[ch][j] = ind[ch] as f64;
        }
        // One footprint for the lookup and its backward (the atan2/acos are the costly part,
        // skipped when the directions' footprints are cached).
        let fp = match footprints {
            Some(f) => env.env.unpack(f[k]),
            None => env.env.footprint(dk),
        };
        // Bilinear in f32, the same sums in the same order as `EnvMap::lookup`.
        let mut e4 = env.texels[fp.index[0]] * f32x4::splat(fp.weight[0]);
        for q in 1..4 {
            e4 += env.texels[fp.index[q]] * f32x4::splat(fp.weight[q]);
        }
        let e = e4.to_array();
        for ch in 0..3 {
            le[ch][j] = e[ch] as f64;
        }
        if let Some(f) = fps.as_deref_mut() {
            f[j] = fp;
        }
    }
    let dirs = d.map(L::from_f64s);
    let w = L::from_f64s(w);
    let cos = dirs[0] * L::splat(n[0]) + dirs[1] * L::splat(n[1]) + dirs[2] * L::splat(n[2]);
    Block { dirs, w, wc: w * cos, vis: L::from_f64s(vis), le: le.map(L::from_f64s), li: li.map(L::from_f64s), live }
}

/// [`load_block`] for a whole block (the training's S = 64 has only these), without a branch
/// per lane: every lane is gathered and looked up in the env, then the lanes under the horizon
/// are zeroed by mask, the same values as the lane-by-lane path (which took ≈ 40 % of the
/// linearised forward; this path: −14 % of it, −23 % of the general forward, −13 % of the general
/// backward on the AVX2 VM, BENCHMARKS.md session 88). Footprints are written only when asked:
/// copying each lane's footprint to a local array stalled on store forwarding and ate the gain.
#[inline]
fn load_full_block<L: FloatLanes>(
    inp: &PbrInputs,
    env: &LaneEnv,
    footprints: Option<&[PackedFootprint]>,
    n: V3,
    k0: usize,
    mut fps: Option<&mut [Footprint; LANES]>,
) -> Block<L> {
    let range = k0..k0 + LANES;
    let dk: &[[f32; 3]; LANES] = inp.dirs[range.clone()].try_into().expect("a whole block");
    let d: [L; 3] = std::array::from_fn(|a| L::from_f32s(dk.map(|x| x[a])));
    let nl = n.map(L::splat);
    let cos = d[0] * nl[0] + d[1] * nl[1] + d[2] * nl[2];
    let live = cos.gt(L::ZERO);
    let w = match inp.sample_weights {
        Some(sw) => L::from_f32s(std::array::from_fn(|j| sw[k0 + j])),
        None => L::splat(inp.weight as f64),
    };
    let vis: &[f32; LANES] = inp.visibility[range.clone()].try_into().expect("a whole block");
    let ind: &[[f32; 3]; LANES] = inp.indirect[range].try_into().expect("a whole block");
    let li: [L; 3] = std::array::from_fn(|ch| L::from_f32s(ind.map(|x| x[ch])));
    let mut le = [[0.0f32; LANES]; 3];
    // The lookup is written out here, not shared with the partial path: a shared inline helper
    // returning (footprint, colour) measured slower in the linearised forward (BENCHMARKS.md).
    for j in 0..LANES {
        let fp = match footprints {
            Some(f) => env.env.unpack(f[k0 + j]),
            None => env.env.footprint(dk[j]),
        };
        // Bilinear in f32, the same sums in the same order as `EnvMap::lookup`.
        let mut e4 = env.texels[fp.index[0]] * f32x4::splat(fp.weight[0]);
        for q in 1..4 {
            e4 += env.texels[fp.index[q]] * f32x4::splat(fp.weight[q]);
        }
        let e = e4.to_array();
        for ch in 0..3 {
            le[ch][j] = e[ch];
        }
        if let Some(f) = fps.as_deref_mut() {
            f[j] = fp;
        }
    }
    let zero = L::ZERO;
    let dirs: [L; 3] = std::array::from_fn(|a| live.select(d[a], nl[a]));
    let w = live.select(w, zero);
    // n·ω of the dead lanes' direction n, as the lane-by-lane path computes it (times w = 0).
    let cos = dirs[0] * nl[0] + dirs[1] * nl[1] + dirs[2] * nl[2];
    let mask = live.bitmask();
    Block {
        dirs,
        w,
        wc: w * cos,
        vis: live.select(L::from_f32s(*vis), zero),
        le: le.map(|c| live.select(L::from_f32s(c), zero)),
        li: li.map(|c| live.select(c, zero)),
        live: std::array::from_fn(|j| mask >> j & 1 == 1),
    }
}

/// One surfel, f64: (direct, indirect). Samples run in blocks of eight lanes (f64x8): the
/// gathers per lane, the lobe and the sums in SIMD.
pub fn shade_one(inp: &PbrInputs, env: &LaneEnv, i: usize) -> (V3, V3) {
    let s = inp.samples;
    let (a, r, n, wo) = (to64(inp.albedo[i]), inp.roughness[i] as f64, to64(inp.normal[i]), to64(inp.view[i]));
    let footprints = inp.footprints_for(env.env);
    // The Lambert lobe under the specular layer (brdf.rs): one weight per surfel and view.
    let kd = if inp.lambert { brdf::diffuse_weight(dot(n, wo), r).0 } else { 0.0 };
    let lambert = scale(a, kd * std::f64::consts::FRAC_1_PI).map(splat);
    let lobe = inp.specular.then(|| Lobe::new(r, n, wo));
    let (mut direct, mut indirect) = ([f64x8::ZERO; 3], [f64x8::ZERO; 3]);
    for k0 in (i * s..(i + 1) * s).step_by(LANES) {
        let len = (i * s + s - k0).min(LANES);
        let b = load_block(inp, env, footprints, n, k0, len, None);
        let spec = match &lobe {
            Some(l) => l.eval(b.dirs),
            None => f64x8::ZERO,
        };
        for ch in 0..3 {
            let fw = b.wc * (lambert[ch] + spec);
            direct[ch] += fw * b.vis * b.le[ch];
            indirect[ch] += fw * b.li[ch];
        }
    }
    (direct.map(FloatLanes::sum), indirect.map(FloatLanes::sum))
}

/// Forward: writes L_direct and L_indirect per surfel (L_pbr = their sum).
pub fn shade_surfels(inp: &PbrInputs, env: &EnvMap, direct: &mut [[f32; 3]], indirect: &mut [[f32; 3]]) -> Result<()> {
    inp.validate()?;
    if direct.len() != inp.len() || indirect.len() != inp.len() {
        return Err(Error::invalid("PBR outputs", format!("need {} surfels", inp.len())));
    }
    let env = &LaneEnv::new(env);
    direct.par_iter_mut().zip(indirect.par_iter_mut()).enumerate().with_min_len(64).for_each(|(i, (d, ind))| {
        let (a, b) = shade_one(inp, env, i);
        *d = to32(a);
        *ind = to32(b);
    });
    Ok(())
}

/// Per-surfel gradients of one surfel; writes the per-sample ones into `v_vis` and `v_lind`
/// (unless they are empty) and adds the env gradient into `v_env` (unless it is empty).
#[allow(clippy::too_many_arguments)]
fn backward_one(
    inp: &PbrInputs,
    env: &LaneEnv,
    i: usize,
    v_dir: V3,
    v_ind: V3,
    detach: Detach,
    v_vis: &mut [f32],
    v_lind: &mut [[f32; 3]],
    v_env: &mut [f32x4],
) -> (V3, f64, V3, V3) {
    let s = inp.samples;
    let (a, r, n, wo) = (to64(inp.albedo[i]), inp.roughness[i] as f64, to64(inp.normal[i]), to64(inp.view[i]));
    let footprints = inp.footprints_for(env.env);
    let (kd, dkd_dnov, dkd_dr) = if inp.lambert { brdf::diffuse_weight(dot(n, wo), r) } else { (0.0, 0.0, 0.0) };
    let lambert = scale(a, kd * std::f64::consts::FRAC_1_PI).map(splat);
    let lobe = inp.specular.then(|| Lobe::new(r, n, wo));
    let (v_dir8, v_ind8) = (v_dir.map(splat), v_ind.map(splat));
    let (incident, env_grad) = (!v_vis.is_empty(), !detach.env && !v_env.is_empty());
    // Lane accumulators; Σ_s v_f (the Lambert lobe's gradient) is chained once per surfel below.
    let (mut vr, mut vn, mut vwo, mut v_lambert) = (f64x8::ZERO, [f64x8::ZERO; 3], [f64x8::ZERO; 3], [f64x8::ZERO; 3]);
    let mut fps = [Footprint { index: [0; 4], weight: [0.0; 4] }; LANES];
    for k0 in (i * s..(i + 1) * s).step_by(LANES) {
        let len = (i * s + s - k0).min(LANES);
        let b = load_block(inp, env, footprints, n, k0, len, Some(&mut fps));
        // g = V·Le ⊙ v_dir + L_ind ⊙ v_ind per channel (the incident side seen by v); the
        // lobe's upstream gradient v_f = wc·g does not depend on f.
        let g: [f64x8; 3] = std::array::from_fn(|ch| v_dir8[ch] * b.vis * b.le[ch] + v_ind8[ch] * b.li[ch]);
        let v_f: [f64x8; 3] = std::array::from_fn(|ch| g[ch] * b.wc);
        let spec = match &lobe {
            Some(l) => {
                let lg = l.eval_with_backward(b.dirs, v_f[0] + v_f[1] + v_f[2]);
                vr += lg.v_roughness;
                for c in 0..3 {
                    vn[c] += lg.v_n[c];
                    vwo[c] += lg.v_wo[c];
                }
                lg.spec
            }
            None => f64x8::ZERO,
        };
        let f: [f64x8; 3] = std::array::from_fn(|ch| lambert[ch] + spec);
        for ch in 0..3 {
            v_lambert[ch] += v_f[ch];
        }
        let v_c = b.w * (f[0] * g[0] + f[1] * g[1] + f[2] * g[2]);
        for c in 0..3 {
            vn[c] += b.dirs[c] * v_c;
        }
        // The incident side (dead lanes have wc = 0, hence zero gradients).
        let wf: [f64x8; 3] = std::array::from_fn(|ch| b.wc * f[ch]);
        if incident {
            let vv =
                (wf[0] * b.le[0] * v_dir8[0] + wf[1] * b.le[1] * v_dir8[1] + wf[2] * b.le[2] * v_dir8[2]).to_array();
            let vl: [[f64; LANES]; 3] = std::array::from_fn(|ch| (wf[ch] * v_ind8[ch]).to_array());
            let base = k0 - i * s;
            for j in 0..len {
                v_vis[base + j] = vv[j] as f32;
                v_lind[base + j] = [vl[0][j] as f32, vl[1][j] as f32, vl[2][j] as f32];
            }
        }
        if env_grad {
            let v_le: [[f64; LANES]; 3] = std::array::from_fn(|ch| (wf[ch] * b.vis * v_dir8[ch]).to_array());
            for j in 0..len {
                if !b.live[j] {
                    continue;
                }
                let fp = &fps[j];
                let v = f32x4::from([v_le[0][j] as f32, v_le[1][j] as f32, v_le[2][j] as f32, 0.0]);
                for q in 0..4 {
                    v_env[fp.index[q]] += v * f32x4::splat(fp.weight[q]);
                }
            }
        }
    }
    let v_lambert = v_lambert.map(FloatLanes::sum);
    let (mut vr, mut vn, mut vwo) = (vr.sum(), vn.map(FloatLanes::sum), vwo.map(FloatLanes::sum));
    // lambert = a·kd(NoV, r)/π.
    let mut va = scale(v_lambert, kd * std::f64::consts::FRAC_1_PI);
    let v_kd = dot(v_lambert, a) * std::f64::consts::FRAC_1_PI;
    vr += v_kd * dkd_dr;
    vn = add(vn, scale(wo, v_kd * dkd_dnov));
    vwo = add(vwo, scale(n, v_kd * dkd_dnov));
    if detach.material {
        va = [0.0; 3];
        vr = 0.0;
    }
    if detach.normal {
        vn = [0.0; 3];
    }
    (va, vr, vn, vwo)
}

/// Sums the env-gradient accumulators of the rayon groups in group order (a fixed order: the
/// result does not depend on scheduling) into `out`; all zero when there are none (detached).
fn store_env_gradient(groups: Vec<Vec<f32x4>>, out: &mut [[f32; 3]]) {
    let mut groups = groups.into_iter().filter(|g| !g.is_empty());
    let Some(first) = groups.next() else {
        out.iter_mut().for_each(|x| *x = [0.0; 3]);
        return;
    };
    let rest: Vec<Vec<f32x4>> = groups.collect();
    // Rayon over texel ranges; per texel the groups are still added in group order.
    const TEXELS: usize = 512;
    out.par_chunks_mut(TEXELS).zip(first.par_chunks(TEXELS)).enumerate().for_each(|(c, (dst, sum))| {
        for (j, (d, &t0)) in dst.iter_mut().zip(sum).enumerate() {
            let mut t = t0;
            for g in &rest {
                t += g[c * TEXELS + j];
            }
            let t = t.to_array();
            *d = [t[0], t[1], t[2]];
        }
    });
}

/// Backward of [`shade_surfels`] for upstream gradients on L_direct and L_indirect. Overwrites
/// every buffer of `grads` (sized with [`PbrGrads::new`]).
pub fn shade_surfels_backward(
    inp: &PbrInputs,
    env: &EnvMap,
    v_direct: &[[f32; 3]],
    v_indirect: &[[f32; 3]],
    detach: Detach,
    grads: &mut PbrGrads,
) -> Result<()> {
    inp.validate()?;
    let n = inp.len();
    let s = inp.samples;
    if v_direct.len() != n || v_indirect.len() != n {
        return Err(Error::invalid("PBR upstream gradients", format!("need {n} surfels")));
    }
    if grads.v_albedo.len() != n
        || grads.v_roughness.len() != n
        || grads.v_normal.len() != n
        || grads.v_view.len() != n
        || grads.v_visibility.len() != n * s
        || grads.v_indirect.len() != n * s
        || grads.v_env.len() != env.texels.len()
    {
        return Err(Error::invalid("PBR gradient buffers", "sizes do not match the inputs; use PbrGrads::new"));
    }
    if s == 0 {
        *grads = PbrGrads::new(n, 0, env.texels.len());
        return Ok(());
    }
    let texels = env.texels.len();
    let lane_env = &LaneEnv::new(env);
    let v_env = grads
        .v_albedo
        .par_chunks_mut(CHUNK_SURFELS)
        .zip(grads.v_roughness.par_chunks_mut(CHUNK_SURFELS))
        .zip(grads.v_normal.par_chunks_mut(CHUNK_SURFELS))
        .zip(grads.v_view.par_chunks_mut(CHUNK_SURFELS))
        .zip(grads.v_visibility.par_chunks_mut(CHUNK_SURFELS * s))
        .zip(grads.v_indirect.par_chunks_mut(CHUNK_SURFELS * s))
        .enumerate()
        // Fixed groups of chunks, summed in order: the env gradient does not depend on how
        // rayon schedules the work (a plain fold + reduce made resumed runs differ).
        .fold_chunks(
            REDUCE_GROUP,
            || if detach.env { Vec::new() } else { vec![f32x4::ZERO; texels] },
            |mut acc, (c, (((((va, vr), vn), vv), vvis), vind))| {
                for j in 0..va.len() {
                    let i = c * CHUNK_SURFELS + j;
                    let (ga, gr, gn, gv) = backward_one(
                        inp,
                        lane_env,
                        i,
                        to64(v_direct[i]),
                        to64(v_indirect[i]),
                        detach,
                        &mut vvis[j * s..(j + 1) * s],
                        &mut vind[j * s..(j + 1) * s],
                        &mut acc,
                    );
                    va[j] = to32(ga);
                    vr[j] = gr as f32;
                    vn[j] = to32(gn);
                    vv[j] = to32(gv);
                }
                acc
            },
        )
        .collect::<Vec<_>>();
    store_env_gradient(v_env, &mut grads.v_env);
    Ok(())
}

/// [`shade_surfels`] for the surfels listed in `ids` only (e.g. those a camera sees): output k
/// belongs to surfel `ids[k]`.
pub fn shade_subset(
    inp: &PbrInputs,
    env: &EnvMap,
    ids: &[u32],
    direct: &mut [[f32; 3]],
    indirect: &mut [[f32; 3]],
) -> Result<()> {
    inp.validate()?;
    if direct.len() != ids.len() || indirect.len() != ids.len() {
        return Err(Error::invalid("PBR outputs", format!("need {} entries", ids.len())));
    }
    let env = &LaneEnv::new(env);
    direct.par_iter_mut().zip(indirect.par_iter_mut()).zip(ids.par_iter()).with_min_len(64).for_each(
        |((d, ind), &i)| {
            let (a, b) = shade_one(inp, env, i as usize);
            *d = to32(a);
            *ind = to32(b);
        },
    );
    Ok(())
}

/// Per-surfel gradients of [`shade_subset`] (entry k belongs to `ids[k]`); no gradients to the
/// cached visibility and indirect light (the cache is refreshed without gradients).
#[derive(Clone, Debug, Default)]
pub struct SubsetGrads {
    pub v_albedo: Vec<[f32; 3]>,
    pub v_roughness: Vec<f32>,
    pub v_normal: Vec<[f32; 3]>,
    pub v_view: Vec<[f32; 3]>,
    /// Env texels (∂/∂ linear radiance); all zero when `detach.env`.
    pub v_env: Vec<[f32; 3]>,
}

/// One entry's (albedo, roughness, normal, view) gradients.
type EntryGrads = ([f32; 3], f32, [f32; 3], [f32; 3]);

impl SubsetGrads {
    /// Fill the `m` entries' gradients with `entry(k, env accumulator)` → (albedo, roughness,
    /// normal, view) in parallel chunks, and the env's from the accumulators (none when
    /// `detach_env`: zeros). The chunks' accumulators are summed in fixed groups, in order: the
    /// env gradient does not depend on how rayon schedules the work (a plain fold + reduce made
    /// resumed runs differ).
    fn fill(
        &mut self,
        m: usize,
        texels: usize,
        detach_env: bool,
        entry: impl Fn(usize, &mut [f32x4]) -> EntryGrads + Sync,
    ) {
        self.v_albedo.resize(m, [0.0; 3]);
        self.v_roughness.resize(m, 0.0);
        self.v_normal.resize(m, [0.0; 3]);
        self.v_view.resize(m, [0.0; 3]);
        let v_env = self
            .v_albedo
            .par_chunks_mut(CHUNK_SURFELS)
            .zip(self.v_roughness.par_chunks_mut(CHUNK_SURFELS))
            .zip(self.v_normal.par_chunks_mut(CHUNK_SURFELS))
            .zip(self.v_view.par_chunks_mut(CHUNK_SURFELS))
            .enumerate()
            .fold_chunks(
                REDUCE_GROUP,
                || if detach_env { Vec::new() } else { vec![f32x4::ZERO; texels] },
                |mut acc, (c, (((va, vr), vn), vv))| {
                    for j in 0..va.len() {
                        (va[j], vr[j], vn[j], vv[j]) = entry(c * CHUNK_SURFELS + j, &mut acc);
                    }
                    acc
                },
            )
            .collect::<Vec<_>>();
        self.v_env.resize(texels, [0.0; 3]);
        store_env_gradient(v_env, &mut self.v_env);
    }
}

/// Backward of [`shade_subset`] for upstream gradients on L_direct and L_indirect (per entry).
pub fn shade_subset_backward(
    inp: &PbrInputs,
    env: &EnvMap,
    ids: &[u32],
    v_direct: &[[f32; 3]],
    v_indirect: &[[f32; 3]],
    detach: Detach,
    grads: &mut SubsetGrads,
) -> Result<()> {
    inp.validate()?;
    let m = ids.len();
    if v_direct.len() != m || v_indirect.len() != m {
        return Err(Error::invalid("PBR upstream gradients", format!("need {m} entries")));
    }
    let lane_env = &LaneEnv::new(env);
    grads.fill(m, env.texels.len(), detach.env, |k, acc| {
        // No upstream gradient (e.g. a surfel the rasteriser did not reach): every gradient of
        // the entry is zero.
        if v_direct[k] == [0.0; 3] && v_indirect[k] == [0.0; 3] {
            return ([0.0; 3], 0.0, [0.0; 3], [0.0; 3]);
        }
        let (ga, gr, gn, gv) = backward_one(
            inp,
            lane_env,
            ids[k] as usize,
            to64(v_direct[k]),
            to64(v_indirect[k]),
            detach,
            // No gradients to the cache: the per-sample ones are not written.
            &mut [],
            &mut [],
            acc,
        );
        (to32(ga), gr as f32, to32(gn), to32(gv))
    });
    Ok(())
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;
    use crate::shade::sampling::{ElevationFloor, MIN_ELEVATION_DEG, fibonacci_hemisphere};
    use crate::shade::testutil::{close, rng, unit, unit_in};
    use rand::RngExt;
    use std::f64::consts::PI;

    pub(in crate::shade::pbr) struct Case {
        pub albedo: Vec<[f32; 3]>,
        pub rough: Vec<f32>,
        pub normal: Vec<[f32; 3]>,
        pub view: Vec<[f32; 3]>,
        pub dirs: Vec<[f32; 3]>,
        pub vis: Vec<f32>,
        pub ind: Vec<[f32; 3]>,
        pub s: usize,
        pub weight: f32,
        pub specular: bool,
        pub lambert: bool,
        /// Per-sample weights instead of `weight` (importance sampling).
        pub sample_weights: Option<Vec<f32>>,
    }

    impl Case {
        /// [`inputs`](Self::inputs) with `packed` (the footprints of `dirs` for maps of
        /// `env`'s size) as cached footprints when `cached`.
        pub(in crate::shade::pbr) fn inputs_cached<'a>(
            &'a self,
            packed: &'a [PackedFootprint],
            env: &EnvMap,
            cached: bool,
        ) -> PbrInputs<'a> {
            let footprints = cached.then_some(CachedFootprints { data: packed, width: env.width, height: env.height });
            PbrInputs { footprints, ..self.inputs() }
        }

        pub(in crate::shade::pbr) fn inputs(&self) -> PbrInputs<'_> {
            PbrInputs {
                albedo: &self.albedo,
                roughness: &self.rough,
                normal: &self.normal,
                view: &self.view,
                dirs: &self.dirs,
                visibility: &self.vis,
                indirect: &self.ind,
                samples: self.s,
                weight: self.weight,
                sample_weights: self.sample_weights.as_deref(),
                specular: self.specular,
                lambert: self.lambert,
                footprints: None,
            }
        }
    }

    pub(in crate::shade::pbr) fn random_case(n: usize, s: usize, seed: u64) -> Case {
        let mut rg = rng(seed);
        let normal: Vec<[f32; 3]> = (0..n).map(|_| to32(unit(&mut rg))).collect();
        let view = normal.iter().map(|nn| to32(unit_in(&mut rg, to64(*nn), 0.02))).collect();
        let mut dirs = vec![[0.0f32; 3]; n * s];
        let mut weight = 0.0;
        for i in 0..n {
            weight = fibonacci_hemisphere(
                normal[i],
                rg.random::<f64>() * 6.3,
                MIN_ELEVATION_DEG,
                ElevationFloor::Spread,
                &mut dirs[i * s..(i + 1) * s],
            );
        }
        // A few directions under the horizon (they must contribute nothing).
        dirs[1] = to32(scale(to64(normal[0]), -1.0));
        Case {
            albedo: (0..n).map(|_| [rg.random(), rg.random(), rg.random()]).collect(),
            rough: (0..n)
                .map(|i| {
                    if i == 0 {
                        0.08
                    } else if i == 1 {
                        0.99
                    } else {
                        rg.random_range(0.1..0.9)
                    }
                })
                .collect(),
            normal,
            view,
            dirs,
            vis: (0..n * s).map(|_| rg.random()).collect(),
            ind: (0..n * s).map(|_| [rg.random(), rg.random(), rg.random()]).collect(),
            s,
            weight: weight as f32,
            specular: true,
            lambert: true,
            sample_weights: None,
        }
    }

    pub(in crate::shade::pbr) fn random_env(h: usize, w: usize, seed: u64) -> EnvMap {
        let mut rg = rng(seed);
        let mut env = EnvMap::constant(w, h, [0.0; 3]);
        for t in env.texels.iter_mut() {
            *t = [rg.random_range(0.1..3.0), rg.random_range(0.1..3.0), rg.random_range(0.1..3.0)];
        }
        env
    }

    #[test]
    fn subset_matches_the_full_pass() {
        let case = random_case(9, 8, 4);
        let env = random_env(8, 16, 5);
        let inp = case.inputs();
        let ids = [7u32, 2, 5];
        let (mut d, mut ind) = (vec![[0.0; 3]; 9], vec![[0.0; 3]; 9]);
        shade_surfels(&inp, &env, &mut d, &mut ind).unwrap();
        let (mut ds, mut is) = (vec![[0.0; 3]; 3], vec![[0.0; 3]; 3]);
        shade_subset(&inp, &env, &ids, &mut ds, &mut is).unwrap();
        let mut v_dir = vec![[0.0f32; 3]; 9];
        let mut v_ind = vec![[0.0f32; 3]; 9];
        let (vs_dir, vs_ind) = (vec![[0.3f32, -0.2, 0.5]; 3], vec![[-0.1f32, 0.4, 0.2]; 3]);
        for (k, &i) in ids.iter().enumerate() {
            assert_eq!(ds[k], d[i as usize]);
            assert_eq!(is[k], ind[i as usize]);
            v_dir[i as usize] = vs_dir[k];
            v_ind[i as usize] = vs_ind[k];
        }
        let mut full = PbrGrads::new(9, 8, env.texels.len());
        shade_surfels_backward(&inp, &env, &v_dir, &v_ind, Detach::default(), &mut full).unwrap();
        let mut sub = SubsetGrads::default();
        shade_subset_backward(&inp, &env, &ids, &vs_dir, &vs_ind, Detach::default(), &mut sub).unwrap();
        for (k, &i) in ids.iter().enumerate() {
            assert_eq!(sub.v_albedo[k], full.v_albedo[i as usize]);
            assert_eq!(sub.v_roughness[k], full.v_roughness[i as usize]);
            assert_eq!(sub.v_normal[k], full.v_normal[i as usize]);
            assert_eq!(sub.v_view[k], full.v_view[i as usize]);
        }
        for (a, b) in sub.v_env.iter().zip(&full.v_env) {
            for ch in 0..3 {
                assert!((a[ch] - b[ch]).abs() <= 1e-5 * (1.0 + b[ch].abs()), "{a:?} {b:?}");
            }
        }
        assert!(sub.v_env.iter().any(|t| t[0] != 0.0));
    }

    /// The lane kernel against a plain per-sample loop over `brdf::eval` and `EnvMap::lookup`,
    /// for sample counts with full and partial blocks, with and without cached footprints.
    #[test]
    fn lanes_match_a_per_sample_loop() {
        let env = random_env(16, 32, 21);
        for s in [1, 7, 8, 13, 64] {
            let case = random_case(6, s, 30 + s as u64);
            let packed: Vec<PackedFootprint> = case.dirs.iter().map(|d| env.packed_footprint(*d)).collect();
            for cached in [false, true] {
                let inp = case.inputs_cached(&packed, &env, cached);
                for i in 0..6 {
                    let (direct, indirect) = shade_one(&inp, &LaneEnv::new(&env), i);
                    let (a, r, n, wo) =
                        (to64(case.albedo[i]), case.rough[i] as f64, to64(case.normal[i]), to64(case.view[i]));
                    let (mut want_d, mut want_i) = ([0.0f64; 3], [0.0f64; 3]);
                    for k in i * s..(i + 1) * s {
                        let wi = to64(case.dirs[k]);
                        let c = dot(n, wi);
                        if c <= 0.0 {
                            continue;
                        }
                        let f = brdf::eval(a, r, n, wo, wi);
                        let le = to64(env.lookup(case.dirs[k]));
                        let w = case.weight as f64 * c;
                        for ch in 0..3 {
                            want_d[ch] += w * f[ch] * case.vis[k] as f64 * le[ch];
                            want_i[ch] += w * f[ch] * case.ind[k][ch] as f64;
                        }
                    }
                    for ch in 0..3 {
                        assert!(
                            close(direct[ch], want_d[ch], 1e-12, 1e-15),
                            "S {s} surfel {i}: {direct:?} vs {want_d:?}"
                        );
                        assert!(close(indirect[ch], want_i[ch], 1e-12, 1e-15), "S {s} surfel {i}: {indirect:?}");
                    }
                    assert!(want_d.iter().all(|x| *x > 0.0) || s == 1);
                }
            }
        }
    }

    #[test]
    fn furnace_lambert_part() {
        // L_pbr is affine in the albedo: L(a = 1) − L(a = 0) is the white-Lambert term.
        let l = [1.3f32, 0.7, 2.0];
        let env = EnvMap::constant(32, 16, l);
        for (floor, expect) in [(ElevationFloor::Spread, None), (ElevationFloor::Clamp, None::<f64>)] {
            let mut case = random_case(20, 64, 1);
            for i in 0..20 {
                case.weight = fibonacci_hemisphere(
                    case.normal[i],
                    i as f64,
                    MIN_ELEVATION_DEG,
                    floor,
                    &mut case.dirs[i * 64..(i + 1) * 64],
                ) as f32;
            }
            case.vis.iter_mut().for_each(|v| *v = 1.0);
            case.ind.iter_mut().for_each(|v| *v = [0.0; 3]);
            let z_min = MIN_ELEVATION_DEG.to_radians().sin();
            // The bias of each placement at the 10° floor (module note of sampling.rs).
            let want = match floor {
                ElevationFloor::Spread => 1.0 - z_min * z_min,
                ElevationFloor::Clamp => {
                    (0..64).map(|i| (1.0 - 2.0 * i as f64 / 127.0).max(z_min)).sum::<f64>() * 2.0 / 64.0
                }
            };
            let _ = expect;
            let (mut d1, mut d0, mut ind) = (vec![[0.0; 3]; 20], vec![[0.0; 3]; 20], vec![[0.0; 3]; 20]);
            case.albedo.iter_mut().for_each(|a| *a = [1.0; 3]);
            shade_surfels(&case.inputs(), &env, &mut d1, &mut ind).unwrap();
            case.albedo.iter_mut().for_each(|a| *a = [0.0; 3]);
            shade_surfels(&case.inputs(), &env, &mut d0, &mut ind).unwrap();
            for i in 0..20 {
                // The Lambert lobe sits under the specular layer: weighted by 1 − E(NoV, r).
                let kd = brdf::diffuse_weight(dot(to64(case.normal[i]), to64(case.view[i])), case.rough[i] as f64).0;
                // (Low at grazing views of smooth surfels: the specular layer reflects most there.)
                assert!(kd < 1.0 && kd > 0.2, "{kd}");
                for ch in 0..3 {
                    let lam = (d1[i][ch] - d0[i][ch]) as f64 / l[ch] as f64 / kd;
                    assert!((lam - want).abs() < 2e-3, "{floor:?}: {lam} vs {want}");
                    assert_eq!(ind[i][ch], 0.0);
                }
            }
            match floor {
                ElevationFloor::Spread => assert!((want - 0.9698).abs() < 1e-3),
                ElevationFloor::Clamp => assert!((want - 1.038).abs() < 1e-3, "{want}"),
            }
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        check_backward(true);
    }

    #[test]
    fn backward_without_specular_matches_finite_differences() {
        check_backward(false);
    }

    /// The specular lobe alone with importance-sampling weights (`traced_specular`'s inputs):
    /// no Lambert term, so no albedo gradient.
    #[test]
    fn backward_of_the_weighted_specular_lobe_alone_matches_finite_differences() {
        check_backward_with(true, false, true, 16);
    }

    fn check_backward(specular: bool) {
        check_backward_with(specular, true, false, 16)
    }

    /// A sample count that leaves a partial block of lanes (13 = 8 + 5).
    #[test]
    fn backward_with_a_partial_block_matches_finite_differences() {
        check_backward_with(true, true, false, 13)
    }

    fn check_backward_with(specular: bool, lambert: bool, weighted: bool, samples: usize) {
        let random_case = |n, s, seed| {
            let c = random_case(n, s, seed);
            let mut rg = rng(seed ^ 0x5eed);
            let sample_weights = weighted.then(|| (0..n * s).map(|_| rg.random_range(0.05..2.0f32)).collect());
            Case { specular, lambert, sample_weights, ..c }
        };
        let env = random_env(16, 32, 2);
        let case = random_case(5, samples, 3);
        let n = case.albedo.len();
        let mut rg = rng(4);
        let v_dir: Vec<[f32; 3]> = (0..n).map(|_| [rg.random_range(-1.0..1.0), rg.random(), rg.random()]).collect();
        let v_ind: Vec<[f32; 3]> = (0..n).map(|_| [rg.random(), rg.random_range(-1.0..1.0), rg.random()]).collect();
        let mut g = PbrGrads::new(n, case.s, env.texels.len());
        shade_surfels_backward(&case.inputs(), &env, &v_dir, &v_ind, Detach::default(), &mut g).unwrap();
        let obj = |c: &Case, e: &EnvMap, i: usize| {
            let (d, ind) = shade_one(&c.inputs(), &LaneEnv::new(e), i);
            dot(d, to64(v_dir[i])) + dot(ind, to64(v_ind[i]))
        };
        // Inputs are f32 (steps can't be tiny); Richardson-extrapolated central differences.
        // (Steps of 1e-3 left 1.3 % of truncation error in the specular lobe's normal
        // gradient, which the Lambert term's larger gradient had hidden.)
        let make = || random_case(5, samples, 3);
        let fd = |mutate: &dyn Fn(&mut Case, f32), i: usize| richardson(&make, &|c| obj(c, &env, i), mutate, 2.5e-4);
        let grads = (&g.v_albedo[..], &g.v_roughness[..], &g.v_normal[..], &g.v_view[..]);
        for i in 0..n {
            check_material_gradients(i, grads, &fd, (5e-3, 1e-3));
            if !lambert {
                assert_eq!(g.v_albedo[i], [0.0; 3]);
            }
            for j in 0..case.s {
                let k = i * case.s + j;
                let f = fd(&|c, e| c.vis[k] += e, i);
                assert!(close(g.v_visibility[k] as f64, f, 1e-3, 1e-5), "v_V[{k}] {} vs {f}", g.v_visibility[k]);
                for ch in 0..3 {
                    let f = fd(&|c, e| c.ind[k][ch] += e, i);
                    assert!(close(g.v_indirect[k][ch] as f64, f, 1e-3, 1e-5), "v_Lind");
                }
            }
        }
        // The objective sums over all surfels.
        check_env_gradient(&env, &g.v_env, |e| (0..n).map(|i| obj(&case, e, i)).sum::<f64>());
    }

    /// Surfel i's albedo, roughness, normal and view gradients against `fd(mutate, i)`; the
    /// normal's and view's (rel, abs) tolerance given.
    #[allow(clippy::type_complexity)]
    pub(in crate::shade::pbr) fn check_material_gradients(
        i: usize,
        (v_albedo, v_roughness, v_normal, v_view): (&[[f32; 3]], &[f32], &[[f32; 3]], &[[f32; 3]]),
        fd: &dyn Fn(&dyn Fn(&mut Case, f32), usize) -> f64,
        (rel, abs): (f64, f64),
    ) {
        let f = fd(&|c, e| c.rough[i] += e, i);
        assert!(close(v_roughness[i] as f64, f, 2e-3, 1e-4), "v_r[{i}] {} vs {f}", v_roughness[i]);
        for ch in 0..3 {
            let f = fd(&|c, e| c.albedo[i][ch] += e, i);
            assert!(close(v_albedo[i][ch] as f64, f, 1e-3, 1e-5), "v_a[{i}][{ch}] {} vs {f}", v_albedo[i][ch]);
            let f = fd(&|c, e| c.normal[i][ch] += e, i);
            assert!(close(v_normal[i][ch] as f64, f, rel, abs), "v_n[{i}][{ch}] {} vs {f}", v_normal[i][ch]);
            let f = fd(&|c, e| c.view[i][ch] += e, i);
            assert!(close(v_view[i][ch] as f64, f, rel, abs), "v_wo[{i}][{ch}] {} vs {f}", v_view[i][ch]);
        }
    }

    /// Richardson-extrapolated central difference of `obj` at the case `make` gives, under
    /// `mutate(case, ±step)` and `±2·step`.
    pub(in crate::shade::pbr) fn richardson(
        make: &dyn Fn() -> Case,
        obj: &dyn Fn(&Case) -> f64,
        mutate: &dyn Fn(&mut Case, f32),
        step: f32,
    ) -> f64 {
        let central = |eps: f32| {
            let (mut p, mut m) = (make(), make());
            mutate(&mut p, eps);
            mutate(&mut m, -eps);
            (obj(&p) - obj(&m)) / (2.0 * eps as f64)
        };
        (4.0 * central(step) - central(2.0 * step)) / 3.0
    }

    /// `v_env` against unit steps of each texel of `total` (exact: L is linear in the texels),
    /// and that more than 30 texel channels matter.
    pub(in crate::shade::pbr) fn check_env_gradient(env: &EnvMap, v_env: &[[f32; 3]], total: impl Fn(&EnvMap) -> f64) {
        let base = total(env);
        let mut nonzero = 0;
        for t in 0..env.texels.len() {
            for ch in 0..3 {
                let mut e2 = env.clone();
                e2.texels[t][ch] += 1.0;
                let f = total(&e2) - base;
                assert!(close(v_env[t][ch] as f64, f, 1e-3, 1e-5), "v_env[{t}][{ch}] {} vs {f}", v_env[t][ch]);
                nonzero += (f.abs() > 1e-6) as usize;
            }
        }
        assert!(nonzero > 30);
    }

    #[test]
    fn backward_grazing_and_detach() {
        let env = random_env(16, 32, 5);
        let mut case = random_case(4, 8, 6);
        // Grazing view (NoV ≈ 2e-3 and below the clamp) and roughness near 0 and 1. (The f32
        // FD step, 2e-4, must not cross NoV = 0: the Lambert weight 1 − E(NoV) has a kink there.)
        for i in 0..4 {
            let n = to64(case.normal[i]);
            let (t, _) = crate::shade::frame(case.normal[i]);
            let z = [2e-3, -1e-3, 0.3, 0.9][i];
            case.view[i] = to32(add(scale(n, z), scale(to64(t), (1.0f64 - z * z).sqrt())));
        }
        case.rough = vec![0.02, 0.999, 0.5, 0.05];
        let v = vec![[1.0f32, 0.5, -0.3]; 4];
        let mut g = PbrGrads::new(4, 8, env.texels.len());
        shade_surfels_backward(&case.inputs(), &env, &v, &v, Detach::default(), &mut g).unwrap();
        let obj = |c: &Case, i: usize| {
            let (d, ind) = shade_one(&c.inputs(), &LaneEnv::new(&env), i);
            dot(add(d, ind), to64(v[i]))
        };
        for i in 0..4 {
            for ch in 0..3 {
                let e = 2e-4f32;
                let (mut p, mut m) = (
                    Case { view: case.view.clone(), ..random_case(4, 8, 6) },
                    Case { view: case.view.clone(), ..random_case(4, 8, 6) },
                );
                p.rough = case.rough.clone();
                m.rough = case.rough.clone();
                p.normal[i][ch] += e;
                m.normal[i][ch] -= e;
                let f = (obj(&p, i) - obj(&m, i)) / (2.0 * e as f64);
                assert!(
                    close(g.v_normal[i][ch] as f64, f, 1e-2, 2e-3),
                    "grazing v_n[{i}][{ch}] {} vs {f}",
                    g.v_normal[i][ch]
                );
            }
            assert!(g.v_roughness[i].is_finite() && g.v_view[i].iter().all(|x| x.is_finite()));
        }
        for (flag, which) in [
            (Detach { env: true, ..Default::default() }, 0),
            (Detach { material: true, ..Default::default() }, 1),
            (Detach { normal: true, ..Default::default() }, 2),
        ] {
            let mut g2 = PbrGrads::new(4, 8, env.texels.len());
            shade_surfels_backward(&case.inputs(), &env, &v, &v, flag, &mut g2).unwrap();
            match which {
                0 => assert!(g2.v_env.iter().all(|t| *t == [0.0; 3]) && g2.v_albedo == g.v_albedo),
                1 => assert!(
                    g2.v_albedo.iter().all(|t| *t == [0.0; 3])
                        && g2.v_roughness.iter().all(|t| *t == 0.0)
                        && g2.v_env == g.v_env
                ),
                _ => assert!(g2.v_normal.iter().all(|t| *t == [0.0; 3]) && g2.v_roughness == g.v_roughness),
            }
        }
        assert!(g.v_env.iter().any(|t| *t != [0.0; 3]));
    }

    /// The Fibonacci estimator against a brute-force quadrature of the same integral over the
    /// cap above 10°, written independently (polar grid, no sampling code).
    #[test]
    fn estimator_matches_quadrature() {
        let mut env = EnvMap::constant(64, 32, [0.0; 3]);
        for j in 0..32 {
            for i in 0..64 {
                let d = env.texel_dir(i, j);
                env.texels[j * 64 + i] = [1.0 + 0.8 * d[2], 0.5 + 0.4 * d[0], 0.7 + 0.3 * d[1] * d[2]];
            }
        }
        let lind = |d: [f32; 3]| [0.2 + 0.1 * d[0], 0.3, 0.1 + 0.2 * d[2].abs()];
        let vis = |d: [f32; 3]| 0.5 + 0.5 * d[1] * d[1];
        let mut rg = rng(8);
        let z_min = MIN_ELEVATION_DEG.to_radians().sin();
        for trial in 0..4 {
            let n = unit(&mut rg);
            let wo = unit_in(&mut rg, n, 0.3);
            let a = [0.6, 0.3, 0.8];
            let r = [0.5, 0.7, 0.9, 0.6][trial];
            // Reference: midpoint rule on (z, φ) about n over z ∈ [z_min, 1].
            let (t, b) = crate::shade::frame(to32(n));
            let (t, b) = (to64(t), to64(b));
            let (nz, np) = (300, 600);
            let (mut rd, mut ri) = ([0.0f64; 3], [0.0f64; 3]);
            for iz in 0..nz {
                let z = z_min + (1.0 - z_min) * (iz as f64 + 0.5) / nz as f64;
                let rad = (1.0 - z * z).sqrt();
                for ip in 0..np {
                    let phi = 2.0 * PI * (ip as f64 + 0.5) / np as f64;
                    let d = add(add(scale(t, rad * phi.cos()), scale(b, rad * phi.sin())), scale(n, z));
                    let d32 = to32(d);
                    let f = brdf::eval(a, r, n, wo, d);
                    let le = to64(env.lookup(d32));
                    let li = to64(lind(d32));
                    let v = vis(d32) as f64;
                    let dw = (1.0 - z_min) / nz as f64 * 2.0 * PI / np as f64;
                    for ch in 0..3 {
                        rd[ch] += f[ch] * v * le[ch] * z * dw;
                        ri[ch] += f[ch] * li[ch] * z * dw;
                    }
                }
            }
            // Estimator: S = 256, averaged over 8 random rotations.
            let s = 256;
            let reps = 8;
            let mut dirs = vec![[0.0f32; 3]; reps * s];
            let mut weight = 0.0;
            for k in 0..reps {
                weight = fibonacci_hemisphere(
                    to32(n),
                    rg.random::<f64>() * 6.3,
                    MIN_ELEVATION_DEG,
                    ElevationFloor::Spread,
                    &mut dirs[k * s..(k + 1) * s],
                );
            }
            let c = Case {
                albedo: vec![to32(a); reps],
                rough: vec![r as f32; reps],
                normal: vec![to32(n); reps],
                view: vec![to32(wo); reps],
                vis: dirs.iter().map(|d| vis(*d)).collect(),
                ind: dirs.iter().map(|d| lind(*d)).collect(),
                dirs,
                s,
                weight: weight as f32,
                specular: true,
                lambert: true,
                sample_weights: None,
            };
            let (mut od, mut oi) = (vec![[0.0; 3]; reps], vec![[0.0; 3]; reps]);
            shade_surfels(&c.inputs(), &env, &mut od, &mut oi).unwrap();
            for ch in 0..3 {
                let ed = od.iter().map(|x| x[ch] as f64).sum::<f64>() / reps as f64;
                let ei = oi.iter().map(|x| x[ch] as f64).sum::<f64>() / reps as f64;
                assert!((ed - rd[ch]).abs() < 0.02 * rd[ch], "trial {trial} direct {ed} vs {}", rd[ch]);
                assert!((ei - ri[ch]).abs() < 0.02 * ri[ch], "trial {trial} indirect {ei} vs {}", ri[ch]);
            }
        }
    }

    #[test]
    fn rejects_bad_lengths() {
        let env = random_env(16, 32, 9);
        let mut case = random_case(3, 4, 10);
        case.vis.pop();
        let (mut d, mut i) = (vec![[0.0; 3]; 3], vec![[0.0; 3]; 3]);
        assert!(shade_surfels(&case.inputs(), &env, &mut d, &mut i).is_err());
    }

    /// Process CPU time (user + system, all threads) from /proc/self/stat, in seconds.
    fn cpu_seconds() -> f64 {
        let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
        let rest = stat.rsplit(')').next().unwrap_or("");
        let f: Vec<f64> = rest.split_whitespace().map(|x| x.parse().unwrap_or(0.0)).collect();
        // Fields 14 and 15 of the full line (utime, stime) are 11 and 12 after the ')'.
        (f.get(11).copied().unwrap_or(0.0) + f.get(12).copied().unwrap_or(0.0)) / 100.0
    }

    /// The env-gradient sum over several groups (a view's backward over more than
    /// REDUCE_GROUP × 64 surfels; the finite-difference tests have one group): per texel the
    /// groups' sum in group order, over texel counts that do and do not fill the parallel
    /// ranges; detached (empty) groups are skipped; no group at all gives zeros.
    #[test]
    fn env_gradient_groups_sum_per_texel_in_group_order() {
        let mut r = rng(77);
        for (groups, texels) in [(1usize, 100usize), (3, 512), (5, 1500), (9, 8192)] {
            let g: Vec<Vec<f32x4>> = (0..groups)
                .map(|_| (0..texels).map(|_| f32x4::from([r.random(), r.random(), r.random(), 0.0])).collect())
                .collect();
            let mut with_empty = g.clone();
            with_empty.insert(1.min(groups), Vec::new());
            let mut out = vec![[9.0f32; 3]; texels];
            store_env_gradient(with_empty, &mut out);
            for t in 0..texels {
                let mut want = g[0][t];
                for gg in &g[1..] {
                    want += gg[t];
                }
                let w = want.to_array();
                assert_eq!(out[t], [w[0], w[1], w[2]], "{groups} groups, texel {t}");
            }
        }
        let mut out = vec![[9.0f32; 3]; 7];
        store_env_gradient(vec![Vec::new(), Vec::new()], &mut out);
        assert!(out.iter().all(|x| *x == [0.0; 3]));
    }

    /// Blocks, whole and partial, against a lane-by-lane reference written here from the
    /// definitions (`EnvMap::lookup`, the horizon test, zero on dead lanes), bit for bit:
    /// directions, weights, cosines, visibility, env and indirect radiance, live lanes and
    /// footprints, with lanes under the horizon, per-sample weights, cached footprints or not.
    #[test]
    fn blocks_load_as_the_lane_by_lane_definition() {
        let env = random_env(16, 32, 3);
        let lane_env = LaneEnv::new(&env);
        let s = 16;
        let mut case = random_case(6, s, 21);
        // Dead lanes: a few directions of surfels 2 and 3 under their horizon, one exactly on it.
        for k in [2 * s + 3, 2 * s + 7, 3 * s] {
            case.dirs[k] = case.dirs[k].map(|x| -x);
        }
        let (t, _) = crate::shade::frame(case.normal[4]);
        case.dirs[4 * s + 9] = t;
        let mut rg = rng(5);
        let weights: Vec<f32> = (0..6 * s).map(|_| rg.random_range(0.1..2.0)).collect();
        let packed: Vec<PackedFootprint> = case.dirs.iter().map(|d| env.packed_footprint(*d)).collect();
        let (mut dead, mut blocks) = (0, 0);
        for weighted in [false, true] {
            case.sample_weights = weighted.then(|| weights.clone());
            for cached in [false, true] {
                let inp = case.inputs_cached(&packed, &env, cached);
                for i in 0..6 {
                    let n = to64(inp.normal[i]);
                    // Whole blocks (the SIMD path) and partial ones (lane by lane).
                    for (k0, len) in [(i * s, LANES), (i * s + LANES, LANES), (i * s + 2, 5), (i * s + 9, 3)] {
                        let empty = Footprint { index: [0; 4], weight: [0.0; 4] };
                        let mut fps = [empty; LANES];
                        let b = load_block(&inp, &lane_env, inp.footprints_for(&env), n, k0, len, Some(&mut fps));
                        let lane = |x: f64x8, j: usize| x.to_array()[j].to_bits();
                        for j in 0..LANES {
                            let k = k0 + j;
                            let dk = if j < len { to64(inp.dirs[k]) } else { [0.0; 3] };
                            let live = j < len && n[0] * dk[0] + n[1] * dk[1] + n[2] * dk[2] > 0.0;
                            let dir = if live { dk } else { n };
                            let w = match (live, weighted) {
                                (false, _) => 0.0,
                                (true, true) => weights[k] as f64,
                                (true, false) => inp.weight as f64,
                            };
                            let le = if live { env.lookup(inp.dirs[k]) } else { [0.0; 3] };
                            let li = if live { inp.indirect[k] } else { [0.0; 3] };
                            let vis = if live { inp.visibility[k] as f64 } else { 0.0 };
                            assert_eq!(b.live[j], live, "live {i} {k0} {j}");
                            for c in 0..3 {
                                assert_eq!(lane(b.dirs[c], j), dir[c].to_bits(), "dir {i} {k0} {j}");
                                assert_eq!(lane(b.le[c], j), (le[c] as f64).to_bits(), "le {i} {k0} {j}");
                                assert_eq!(lane(b.li[c], j), (li[c] as f64).to_bits(), "li {i} {k0} {j}");
                            }
                            let cos = n[0] * dir[0] + n[1] * dir[1] + n[2] * dir[2];
                            assert_eq!(lane(b.w, j), w.to_bits(), "w {i} {k0} {j}");
                            assert_eq!(lane(b.wc, j), (w * cos).to_bits(), "wc {i} {k0} {j}");
                            assert_eq!(lane(b.vis, j), vis.to_bits(), "vis {i} {k0} {j}");
                            if live {
                                let want = env.footprint(inp.dirs[k]);
                                assert_eq!((fps[j].index, fps[j].weight), (want.index, want.weight));
                            }
                            dead += usize::from(j < len && !live);
                        }
                        blocks += 1;
                    }
                }
            }
        }
        assert_eq!(blocks, 4 * 6 * 4);
        // dirs[1] (under surfel 0's horizon) and the three flipped ones, in each of 4 passes, in
        // whole blocks and again in the partial ones that cover them; the tangent may round
        // either way.
        assert!(dead >= 16, "{dead}");
    }

    /// The shading benchmarks' case: 50k surfels × 64 samples under a 64 × 128 map, and the
    /// footprints of the cached directions (the training path makes them once per cache refresh).
    pub(in crate::shade::pbr) fn benchmark_case() -> (EnvMap, Case, Vec<PackedFootprint>) {
        let env = random_env(64, 128, 11);
        let case = random_case(50_000, 64, 12);
        let packed = case.dirs.iter().map(|d| env.packed_footprint(*d)).collect();
        (env, case, packed)
    }

    /// Throughput for BENCHMARKS-shade.md: `cargo test --release --lib
    /// shade::pbr::tests::throughput -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn throughput() {
        let (env, case, packed) = benchmark_case();
        let (n, s) = (case.albedo.len(), case.s);
        for cached in [false, true] {
            let inputs = case.inputs_cached(&packed, &env, cached);
            let (mut d, mut ind) = (vec![[0.0; 3]; n], vec![[0.0; 3]; n]);
            let mut g = PbrGrads::new(n, s, env.texels.len());
            let v = vec![[1.0f32; 3]; n];
            shade_surfels(&inputs, &env, &mut d, &mut ind).unwrap();
            let reps = 5;
            let t0 = std::time::Instant::now();
            for _ in 0..reps {
                shade_surfels(&inputs, &env, &mut d, &mut ind).unwrap();
            }
            let tf = t0.elapsed().as_secs_f64() / reps as f64;
            let t0 = std::time::Instant::now();
            for _ in 0..reps {
                shade_surfels_backward(&inputs, &env, &v, &v, Detach::default(), &mut g).unwrap();
            }
            let tb = t0.elapsed().as_secs_f64() / reps as f64;
            let ns = (n * s) as f64;
            let cpu1 = cpu_seconds();
            shade_surfels(&inputs, &env, &mut d, &mut ind).unwrap();
            shade_surfels_backward(&inputs, &env, &v, &v, Detach::default(), &mut g).unwrap();
            let cpu = cpu_seconds() - cpu1;
            let what = if cached { "cached footprints" } else { "directions mapped per lookup" };
            // The training iteration's path: the linearised forward and its backward.
            let ids: Vec<u32> = (0..n as u32).collect();
            let mut lin = LinearisedShading::default();
            let mut sub = SubsetGrads::default();
            shade_subset_linearised(&inputs, &env, &ids, &mut d, &mut ind, &mut lin).unwrap();
            let t0 = std::time::Instant::now();
            for _ in 0..reps {
                shade_subset_linearised(&inputs, &env, &ids, &mut d, &mut ind, &mut lin).unwrap();
            }
            let tlf = t0.elapsed().as_secs_f64() / reps as f64;
            let t0 = std::time::Instant::now();
            for _ in 0..reps {
                shade_subset_linearised_backward(&inputs, &env, &ids, &lin, &v, &mut sub).unwrap();
            }
            let tlb = t0.elapsed().as_secs_f64() / reps as f64;
            println!(
                "pbr linearised ({what}): forward {:.1} ms, backward {:.1} ms, forward+backward {:.1} ms",
                tlf * 1e3,
                tlb * 1e3,
                (tlf + tlb) * 1e3
            );
            println!(
                "pbr ({what}) CPU time (all threads) for one forward+backward: {:.1} ms = {:.3} µs per surfel-sample",
                cpu * 1e3,
                cpu / ns * 1e6
            );
            println!(
                "pbr ({what}) {n} surfels x {s} samples, {} threads: forward {:.1} ms, backward {:.1} ms, forward+backward {:.1} ms = {:.2} M surfel-samples/s",
                rayon::current_num_threads(),
                tf * 1e3,
                tb * 1e3,
                (tf + tb) * 1e3,
                ns / (tf + tb) / 1e6
            );
        }
    }
}
