//! Split-sum image-based lighting (Karis 2013; as nvdiffrec / IRGS stage 1):
//!
//!     L(ω_o) ≈ a · Ē(n)  +  P(R, r) · (f0·A(NoV, r) + B(NoV, r)),      R = 2(n·ω_o)n − ω_o
//!
//! * Ē(n) = ∫ L_env(l)·max(0, n·l) dl / π — the cosine-weighted mean radiance ("irradiance
//!   over π"), so a white Lambert surface under a constant sky L returns exactly L. Stored as a
//!   16 × 32 lat-long map filtered from the 16 × 32 mip.
//! * P(R, r): the env prefiltered by the GGX lobe under the n = v = R assumption, weight
//!   D(R·h)·max(0, R·l)·Ω(l) with h = normalize(R + l), normalised to sum 1 (so a constant env
//!   stays constant). Levels at r = 0, 0.2, 0.4, 0.6, 0.8, 1.0 (r = 0 is the env itself; the
//!   others at 32×64, 16×32, 8×16, 8×16, 8×16 from the solid-angle box mips of the same size),
//!   linear in r between levels.
//! * (A, B): the GGX BRDF integration LUT of *our* BRDF (brdf.rs, height-correlated Smith,
//!   clamps included), 32 × 32 over (NoV, r) nodes i/31, 1024 Hammersley samples of D·NoH per
//!   node, computed once at start-up (`OnceLock`); bilinear with derivatives.
//!
//! All maps are linear in the env texels; every filter is a precomputed sparse matrix (CSR,
//! kernel averaged over 2×2 / 4×4 sub-points of each source texel), cached per env resolution,
//! and the backward to the texels applies the transposed matrices (and the transposed mip
//! chain). Parallel decomposition: filters rayon over output texels (forward) and sequential
//! scatter (backward; they are small); `shade_batch*` rayon over points with a per-thread
//! accumulation of the level gradients.

use super::{V3, add, dot, scale, to32, to64};
use crate::envmap::EnvMap;
use crate::error::{Error, Result};
use rayon::prelude::*;
use std::f64::consts::PI;
use std::sync::{Arc, Mutex, OnceLock};

/// Roughness of each prefiltered level.
pub const LEVEL_ROUGHNESS: [f64; 6] = [0.0, 0.2, 0.4, 0.6, 0.8, 1.0];
/// Mip index (halvings of the base resolution) of each level.
const LEVEL_MIP: [usize; 6] = [0, 1, 2, 3, 3, 3];
const IRRADIANCE_MIP: usize = 2;
const IRRADIANCE_SRC_MIP: usize = 2;
/// Kernel weights below this fraction of the output texel's largest weight are dropped.
const KERNEL_CUTOFF: f64 = 1e-3;

// ---------------------------------------------------------------------------------------------
// BRDF integration LUT
// ---------------------------------------------------------------------------------------------

/// Resolution of the (NoV, r) LUT.
pub const LUT_SIZE: usize = 32;
const LUT_SAMPLES: usize = 1024;

/// The GGX BRDF integration table: ∫ spec·NoL dω_i = f0·A + B.
pub struct BrdfLut {
    /// Row-major [r][nov], A and B interleaved.
    ab: Vec<[f64; 2]>,
}

/// (A, B) and their derivatives at one point.
#[derive(Clone, Copy, Debug)]
pub struct LutSample {
    pub a: f64,
    pub b: f64,
    pub da_dnov: f64,
    pub da_dr: f64,
    pub db_dnov: f64,
    pub db_dr: f64,
}

fn radical_inverse(mut bits: u32) -> f64 {
    bits = bits.reverse_bits();
    bits as f64 / 4294967296.0
}

impl BrdfLut {
    /// Compute the table (≈ 1M BRDF evaluations).
    pub fn compute() -> BrdfLut {
        let n = [0.0, 0.0, 1.0];
        let nodes: Vec<(usize, usize)> = (0..LUT_SIZE).flat_map(|j| (0..LUT_SIZE).map(move |i| (j, i))).collect();
        let ab = nodes
            .par_iter()
            .map(|&(j, i)| {
                let r = j as f64 / (LUT_SIZE - 1) as f64;
                let nov = (i as f64 / (LUT_SIZE - 1) as f64).max(1e-4);
                let wo = [(1.0 - nov * nov).sqrt(), 0.0, nov];
                let a2 = super::brdf::alpha2(r);
                let (mut sa, mut sb) = (0.0, 0.0);
                for s in 0..LUT_SAMPLES {
                    let u1 = (s as f64 + 0.5) / LUT_SAMPLES as f64;
                    let u2 = radical_inverse(s as u32);
                    // h ~ D(h)·NoH: cos²θ = (1 − u)/(1 + (α² − 1)u).
                    let c2 = (1.0 - u1) / (1.0 + (a2 - 1.0) * u1);
                    let ct = c2.sqrt();
                    let st = (1.0 - c2).max(0.0).sqrt();
                    let phi = 2.0 * PI * u2;
                    let h = [st * phi.cos(), st * phi.sin(), ct];
                    let voh = dot(wo, h);
                    if voh <= 0.0 {
                        continue;
                    }
                    let wi = add(scale(h, 2.0 * voh), scale(wo, -1.0));
                    let nol = wi[2];
                    if nol <= 0.0 {
                        continue;
                    }
                    let pdf = super::brdf::ggx_d(ct, a2) * ct / (4.0 * voh);
                    let base = super::brdf::specular_f0(r, n, wo, wi, 1.0) * nol / pdf;
                    let fc = (1.0 - voh.clamp(super::brdf::COS_EPS, 1.0)).powi(5);
                    sa += base * (1.0 - fc);
                    sb += base * fc;
                }
                [sa / LUT_SAMPLES as f64, sb / LUT_SAMPLES as f64]
            })
            .collect();
        BrdfLut { ab }
    }

    /// The process-wide table, computed on first use.
    ///
    /// Not `get_or_init`: the computation runs on the rayon pool, and a pool worker that
    /// blocked on the lock while the initialising thread waits for that worker's jobs would
    /// deadlock (seen in the test suite). Threads that race here each compute the same table
    /// and the first one stored wins.
    pub fn get() -> &'static BrdfLut {
        static LUT: OnceLock<BrdfLut> = OnceLock::new();
        if let Some(lut) = LUT.get() {
            return lut;
        }
        let _ = LUT.set(BrdfLut::compute());
        LUT.get().expect("set above")
    }

    /// Value at node (i = NoV index, j = roughness index).
    pub fn node(&self, i: usize, j: usize) -> [f64; 2] {
        self.ab[j * LUT_SIZE + i]
    }

    /// Bilinear lookup with derivatives (zero outside [0, 1]).
    pub fn lookup(&self, nov: f64, r: f64) -> LutSample {
        let m = (LUT_SIZE - 1) as f64;
        let (x, dx) = if (0.0..=1.0).contains(&nov) { (nov * m, m) } else { (nov.clamp(0.0, 1.0) * m, 0.0) };
        let (y, dy) = if (0.0..=1.0).contains(&r) { (r * m, m) } else { (r.clamp(0.0, 1.0) * m, 0.0) };
        let i0 = (x.floor() as usize).min(LUT_SIZE - 2);
        let j0 = (y.floor() as usize).min(LUT_SIZE - 2);
        let tx = x - i0 as f64;
        let ty = y - j0 as f64;
        let v00 = self.node(i0, j0);
        let v10 = self.node(i0 + 1, j0);
        let v01 = self.node(i0, j0 + 1);
        let v11 = self.node(i0 + 1, j0 + 1);
        let f = |k: usize| {
            let val = (1.0 - ty) * ((1.0 - tx) * v00[k] + tx * v10[k]) + ty * ((1.0 - tx) * v01[k] + tx * v11[k]);
            let dtx = (1.0 - ty) * (v10[k] - v00[k]) + ty * (v11[k] - v01[k]);
            let dty = (1.0 - tx) * (v01[k] - v00[k]) + tx * (v11[k] - v10[k]);
            (val, dtx * dx, dty * dy)
        };
        let (a, da_dnov, da_dr) = f(0);
        let (b, db_dnov, db_dr) = f(1);
        LutSample { a, b, da_dnov, da_dr, db_dnov, db_dr }
    }
}

// ---------------------------------------------------------------------------------------------
// Bilinear env lookup differentiable in the direction
// ---------------------------------------------------------------------------------------------

struct DirFootprint {
    index: [usize; 4],
    tx: f64,
    ty: f64,
    ylive: f64,
    dx_dd: V3,
    dy_dd: V3,
}

impl DirFootprint {
    fn weights(&self) -> [f64; 4] {
        let (tx, ty) = (self.tx, self.ty);
        [(1.0 - tx) * (1.0 - ty), tx * (1.0 - ty), (1.0 - tx) * ty, tx * ty]
    }
}

/// The bilinear footprint of [`EnvMap::footprint`], computed with θ = atan2(|d_xy|, d_z) so it
/// is defined (and scale invariant) for any non-zero d, plus ∂(x, y)/∂d.
fn dir_footprint(env: &EnvMap, d: V3) -> DirFootprint {
    let (w, h) = (env.width as f64, env.height as f64);
    let rho2 = d[0] * d[0] + d[1] * d[1];
    let rho = rho2.sqrt();
    let phi = d[1].atan2(d[0]);
    let theta = rho.atan2(d[2]);
    let u = 0.5 - phi / (2.0 * PI);
    let x = (u - u.floor()) * w;
    let y = theta / PI * h;
    let (dx_dd, dy_dd) = if rho > 1e-12 {
        let dphi = [-d[1] / rho2, d[0] / rho2, 0.0];
        let r2 = rho2 + d[2] * d[2];
        let dtheta = [d[0] * d[2] / (rho * r2), d[1] * d[2] / (rho * r2), -rho / r2];
        (scale(dphi, -w / (2.0 * PI)), scale(dtheta, h / PI))
    } else {
        ([0.0; 3], [0.0; 3])
    };
    let fx = x - 0.5;
    let ymax = h - 1.0;
    let (fy, ylive) = if y - 0.5 < 0.0 {
        (0.0, 0.0)
    } else if y - 0.5 > ymax {
        (ymax, 0.0)
    } else {
        (y - 0.5, 1.0)
    };
    let x0 = fx.floor();
    let y0 = fy.floor().min(ymax);
    let wi = env.width as i64;
    let xi0 = (x0 as i64).rem_euclid(wi) as usize;
    let xi1 = (x0 as i64 + 1).rem_euclid(wi) as usize;
    let yi0 = y0 as usize;
    let yi1 = (yi0 + 1).min(env.height - 1);
    let ew = env.width;
    DirFootprint {
        index: [yi0 * ew + xi0, yi0 * ew + xi1, yi1 * ew + xi0, yi1 * ew + xi1],
        tx: fx - x0,
        ty: fy - y0,
        ylive,
        dx_dd,
        dy_dd,
    }
}

/// Bilinear lookup of `env` in direction `d` (any non-zero length), with the Jacobian ∂rgb/∂d
/// (rows = channels). Same texels and weights as [`EnvMap::lookup`] for unit d.
pub fn env_lookup_grad(env: &EnvMap, d: V3) -> (V3, [V3; 3]) {
    let fp = dir_footprint(env, d);
    let t = |k: usize| to64(env.texels[fp.index[k]]);
    let (t0, t1, t2, t3) = (t(0), t(1), t(2), t(3));
    let (tx, ty) = (fp.tx, fp.ty);
    let mut c = [0.0; 3];
    let mut jac = [[0.0; 3]; 3];
    for ch in 0..3 {
        c[ch] = (1.0 - ty) * ((1.0 - tx) * t0[ch] + tx * t1[ch]) + ty * ((1.0 - tx) * t2[ch] + tx * t3[ch]);
        let dtx = (1.0 - ty) * (t1[ch] - t0[ch]) + ty * (t3[ch] - t2[ch]);
        let dty = ((1.0 - tx) * (t2[ch] - t0[ch]) + tx * (t3[ch] - t1[ch])) * fp.ylive;
        jac[ch] = add(scale(fp.dx_dd, dtx), scale(fp.dy_dd, dty));
    }
    (c, jac)
}

/// Backward of [`env_lookup_grad`] to the texels: adds w·v_rgb into `v_texels`.
pub fn env_lookup_scatter(env: &EnvMap, d: V3, v_rgb: V3, v_texels: &mut [[f32; 3]]) {
    let fp = dir_footprint(env, d);
    let w = fp.weights();
    for k in 0..4 {
        let dst = &mut v_texels[fp.index[k]];
        for ch in 0..3 {
            dst[ch] += (w[k] * v_rgb[ch]) as f32;
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Sparse filters, mips
// ---------------------------------------------------------------------------------------------

/// A sparse linear map from a source lat-long grid to an output grid (CSR rows per output).
struct SparseFilter {
    src_mip: usize,
    out_mip: usize,
    offsets: Vec<u32>,
    index: Vec<u32>,
    weight: Vec<f32>,
}

/// Resolution (height, width) of each mip.
fn mip_sizes(h: usize, w: usize, count: usize) -> Vec<(usize, usize)> {
    (0..count).map(|m| (h >> m, w >> m)).collect()
}

fn texel_dir_sub(h: usize, w: usize, i: usize, j: usize, si: f64, sj: f64) -> V3 {
    let x = (i as f64 + si) / w as f64;
    let y = (j as f64 + sj) / h as f64;
    let theta = y * PI;
    let phi = (0.5 - x) * 2.0 * PI;
    [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()]
}

fn solid_angle(h: usize, w: usize, j: usize) -> f64 {
    let t0 = j as f64 / h as f64 * PI;
    let t1 = (j + 1) as f64 / h as f64 * PI;
    2.0 * PI / w as f64 * (t0.cos() - t1.cos())
}

/// Builds a normalised filter: out(o) = Σ_s k(o, s)·src(s) / Σ_s k(o, s), with k averaged over
/// sub × sub points of each source texel and multiplied by its solid angle.
fn build_filter(
    sizes: &[(usize, usize)],
    src_mip: usize,
    out_mip: usize,
    sub: usize,
    kernel: &(dyn Fn(V3, V3) -> f64 + Sync),
) -> SparseFilter {
    let (sh, sw) = sizes[src_mip];
    let (oh, ow) = sizes[out_mip];
    let rows: Vec<Vec<(u32, f32)>> = (0..oh * ow)
        .into_par_iter()
        .map(|o| {
            let dir_o = texel_dir_sub(oh, ow, o % ow, o / ow, 0.5, 0.5);
            let mut ks: Vec<(u32, f64)> = Vec::new();
            let mut kmax = 0.0f64;
            for j in 0..sh {
                let sa = solid_angle(sh, sw, j);
                for i in 0..sw {
                    let mut k = 0.0;
                    for a in 0..sub {
                        for b in 0..sub {
                            let l = texel_dir_sub(
                                sh,
                                sw,
                                i,
                                j,
                                (a as f64 + 0.5) / sub as f64,
                                (b as f64 + 0.5) / sub as f64,
                            );
                            k += kernel(dir_o, l);
                        }
                    }
                    let k = k * sa / (sub * sub) as f64;
                    if k > 0.0 {
                        kmax = kmax.max(k);
                        ks.push(((j * sw + i) as u32, k));
                    }
                }
            }
            ks.retain(|&(_, k)| k >= KERNEL_CUTOFF * kmax);
            let total: f64 = ks.iter().map(|&(_, k)| k).sum();
            ks.into_iter().map(|(s, k)| (s, (k / total) as f32)).collect()
        })
        .collect();
    let mut offsets = vec![0u32];
    let (mut index, mut weight) = (Vec::new(), Vec::new());
    for row in rows {
        for (s, k) in row {
            index.push(s);
            weight.push(k);
        }
        offsets.push(index.len() as u32);
    }
    SparseFilter { src_mip, out_mip, offsets, index, weight }
}

impl SparseFilter {
    fn apply(&self, src: &[[f32; 3]], out: &mut [[f32; 3]]) {
        out.par_iter_mut().enumerate().for_each(|(o, dst)| {
            let (b, e) = (self.offsets[o] as usize, self.offsets[o + 1] as usize);
            let mut acc = [0.0f32; 3];
            for k in b..e {
                let s = src[self.index[k] as usize];
                let w = self.weight[k];
                acc[0] += w * s[0];
                acc[1] += w * s[1];
                acc[2] += w * s[2];
            }
            *dst = acc;
        });
    }

    /// Transposed: v_src += Wᵀ v_out.
    fn apply_transposed(&self, v_out: &[[f32; 3]], v_src: &mut [[f32; 3]]) {
        for (o, g) in v_out.iter().enumerate() {
            if g[0] == 0.0 && g[1] == 0.0 && g[2] == 0.0 {
                continue;
            }
            for k in self.offsets[o] as usize..self.offsets[o + 1] as usize {
                let w = self.weight[k];
                let d = &mut v_src[self.index[k] as usize];
                d[0] += w * g[0];
                d[1] += w * g[1];
                d[2] += w * g[2];
            }
        }
    }
}

/// 2×2 box by solid angle: (h, w) → (h/2, w/2).
fn downsample(src: &[[f32; 3]], h: usize, w: usize, out: &mut [[f32; 3]]) {
    let (oh, ow) = (h / 2, w / 2);
    for j in 0..oh {
        let (s0, s1) = (solid_angle(h, w, 2 * j) as f32, solid_angle(h, w, 2 * j + 1) as f32);
        let (w0, w1) = (s0 / (2.0 * (s0 + s1)), s1 / (2.0 * (s0 + s1)));
        for i in 0..ow {
            let a = src[2 * j * w + 2 * i];
            let b = src[2 * j * w + 2 * i + 1];
            let c = src[(2 * j + 1) * w + 2 * i];
            let d = src[(2 * j + 1) * w + 2 * i + 1];
            out[j * ow + i] = std::array::from_fn(|ch| w0 * (a[ch] + b[ch]) + w1 * (c[ch] + d[ch]));
        }
    }
}

fn downsample_transposed(v_out: &[[f32; 3]], h: usize, w: usize, v_src: &mut [[f32; 3]]) {
    let (oh, ow) = (h / 2, w / 2);
    for j in 0..oh {
        let (s0, s1) = (solid_angle(h, w, 2 * j) as f32, solid_angle(h, w, 2 * j + 1) as f32);
        let (w0, w1) = (s0 / (2.0 * (s0 + s1)), s1 / (2.0 * (s0 + s1)));
        for i in 0..ow {
            let g = v_out[j * ow + i];
            for ch in 0..3 {
                v_src[2 * j * w + 2 * i][ch] += w0 * g[ch];
                v_src[2 * j * w + 2 * i + 1][ch] += w0 * g[ch];
                v_src[(2 * j + 1) * w + 2 * i][ch] += w1 * g[ch];
                v_src[(2 * j + 1) * w + 2 * i + 1][ch] += w1 * g[ch];
            }
        }
    }
}

/// The precomputed filters of one base resolution.
struct Filters {
    sizes: Vec<(usize, usize)>,
    /// Levels 1.. (level 0 is the env itself).
    levels: Vec<SparseFilter>,
    irradiance: SparseFilter,
}

fn filters_for(h: usize, w: usize) -> Arc<Filters> {
    static CACHE: OnceLock<Mutex<Vec<Arc<Filters>>>> = OnceLock::new();
    let cache = CACHE.get_or_init(|| Mutex::new(Vec::new()));
    // The lock is not held while the filters are built on the rayon pool (a worker waiting for
    // it could hold a job the builder waits for): racing threads may build the same filters once
    // each, and the first stored is kept.
    if let Some(f) = cache.lock().unwrap_or_else(|e| e.into_inner()).iter().find(|f| f.sizes[0] == (h, w)) {
        return f.clone();
    }
    let sizes = mip_sizes(h, w, 4);
    let levels = (1..LEVEL_ROUGHNESS.len())
        .map(|k| {
            let a2 = super::brdf::alpha2(LEVEL_ROUGHNESS[k]);
            let m = LEVEL_MIP[k];
            let kernel = move |r: V3, l: V3| {
                let nol = dot(r, l);
                if nol <= 0.0 {
                    return 0.0;
                }
                let hv = super::normalize(add(r, l));
                super::brdf::ggx_d(dot(r, hv).max(0.0), a2) * nol
            };
            build_filter(&sizes, m, m, 2, &kernel)
        })
        .collect();
    let irradiance = build_filter(&sizes, IRRADIANCE_SRC_MIP, IRRADIANCE_MIP, 2, &|n: V3, l: V3| dot(n, l).max(0.0));
    let f = Arc::new(Filters { sizes, levels, irradiance });
    let mut guard = cache.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(first) = guard.iter().find(|g| g.sizes[0] == (h, w)) {
        return first.clone();
    }
    guard.push(f.clone());
    f
}

// ---------------------------------------------------------------------------------------------
// The split-sum shader
// ---------------------------------------------------------------------------------------------

/// Prefiltered maps of one env (rebuilt every iteration from the current texels).
pub struct SplitSum {
    /// Prefiltered radiance per level of [`LEVEL_ROUGHNESS`] (level 0 = the env).
    pub levels: Vec<EnvMap>,
    /// Cosine-weighted mean radiance Ē(n) = E(n)/π.
    pub irradiance: EnvMap,
    filters: Arc<Filters>,
    mips: Vec<EnvMap>,
}

/// Gradients of the split-sum maps, accumulated by [`SplitSum::shade_backward`] and sent to the
/// env texels by [`SplitSum::backward_to_env`].
pub struct SplitSumGrads {
    pub v_levels: Vec<Vec<[f32; 3]>>,
    pub v_irradiance: Vec<[f32; 3]>,
}

/// Split-sum colour of one point.
#[derive(Clone, Copy, Debug, Default)]
pub struct SplitSumOut {
    pub diffuse: [f32; 3],
    pub specular: [f32; 3],
}

/// Per-point gradients.
#[derive(Clone, Copy, Debug, Default)]
pub struct PointGrads {
    pub v_albedo: [f32; 3],
    pub v_roughness: f32,
    pub v_n: [f32; 3],
    pub v_wo: [f32; 3],
}

#[inline]
fn level_coords(r: f64) -> (usize, f64, f64) {
    // Returns (lower level, blend t, dt/dr).
    let step = LEVEL_ROUGHNESS[1] - LEVEL_ROUGHNESS[0];
    let last = LEVEL_ROUGHNESS.len() - 1;
    if r <= 0.0 {
        return (0, 0.0, 0.0);
    }
    if r >= 1.0 {
        return (last - 1, 1.0, 0.0);
    }
    let f = r / step;
    let k = (f.floor() as usize).min(last - 1);
    (k, f - k as f64, 1.0 / step)
}

impl SplitSum {
    /// Prefilter `env`. Its size must be H × 2H with H divisible by 8 and ≥ 8 (training uses
    /// 64 × 128); other maps should be resampled first (`EnvMap::resample`).
    pub fn new(env: &EnvMap) -> Result<SplitSum> {
        let (h, w) = (env.height, env.width);
        if h < 8 || h % 8 != 0 || w != 2 * h || env.texels.len() != h * w {
            return Err(Error::invalid(
                "split-sum environment map",
                format!("needs H × 2H texels with H a multiple of 8, got {h} × {w}; resample it first"),
            ));
        }
        let filters = filters_for(h, w);
        let sizes = &filters.sizes;
        let mut mips = vec![env.clone()];
        for m in 1..sizes.len() {
            let (ph, pw) = sizes[m - 1];
            let mut out = EnvMap::constant(sizes[m].1, sizes[m].0, [0.0; 3]);
            downsample(&mips[m - 1].texels, ph, pw, &mut out.texels);
            mips.push(out);
        }
        let mut levels = vec![env.clone()];
        for f in &filters.levels {
            let (oh, ow) = sizes[f.out_mip];
            let mut out = EnvMap::constant(ow, oh, [0.0; 3]);
            f.apply(&mips[f.src_mip].texels, &mut out.texels);
            levels.push(out);
        }
        let (ih, iw) = sizes[IRRADIANCE_MIP];
        let mut irradiance = EnvMap::constant(iw, ih, [0.0; 3]);
        filters.irradiance.apply(&mips[IRRADIANCE_SRC_MIP].texels, &mut irradiance.texels);
        Ok(SplitSum { levels, irradiance, filters, mips })
    }

    /// Zeroed gradient buffers shaped like the maps.
    pub fn zero_grads(&self) -> SplitSumGrads {
        SplitSumGrads {
            v_levels: self.levels.iter().map(|l| vec![[0.0; 3]; l.texels.len()]).collect(),
            v_irradiance: vec![[0.0; 3]; self.irradiance.texels.len()],
        }
    }

    /// Prefiltered radiance P(d, r) with ∂/∂d (Jacobian rows = channels) and ∂/∂r.
    pub fn prefiltered(&self, d: V3, r: f64) -> (V3, [V3; 3], V3) {
        let (k, t, dt) = level_coords(r);
        let (c0, j0) = env_lookup_grad(&self.levels[k], d);
        let (c1, j1) = env_lookup_grad(&self.levels[k + 1], d);
        let c = add(scale(c0, 1.0 - t), scale(c1, t));
        let jac = std::array::from_fn(|ch| add(scale(j0[ch], 1.0 - t), scale(j1[ch], t)));
        let dr = scale(super::sub(c1, c0), dt);
        (c, jac, dr)
    }

    /// Split-sum colour for albedo a, roughness r, normal n (unit), view ω_o (unit, towards the
    /// camera).
    pub fn shade(&self, a: [f32; 3], r: f32, n: [f32; 3], wo: [f32; 3]) -> SplitSumOut {
        let (d, s) = self.shade64(to64(a), r as f64, to64(n), to64(wo));
        SplitSumOut { diffuse: to32(d), specular: to32(s) }
    }

    /// [`shade`] in f64: (diffuse, specular).
    pub fn shade64(&self, a: V3, r: f64, n: V3, wo: V3) -> (V3, V3) {
        let (irr, _) = env_lookup_grad(&self.irradiance, n);
        let ndv = dot(n, wo);
        let refl = add(scale(n, 2.0 * ndv), scale(wo, -1.0));
        let (p, _, _) = self.prefiltered(refl, r);
        let lut = BrdfLut::get().lookup(ndv.clamp(super::brdf::COS_EPS, 1.0), r);
        let spec = super::brdf::F0 * lut.a + lut.b;
        // The Lambert base under the specular layer (brdf.rs): weighted by 1 − E(NoV, r).
        let kd = super::brdf::diffuse_weight(ndv, r).0;
        ([a[0] * irr[0] * kd, a[1] * irr[1] * kd, a[2] * irr[2] * kd], scale(p, spec))
    }

    /// The specular lobe alone with occlusion: (F0·A(NoV, r) + B(NoV, r)) · (o·P(R, r) + fill),
    /// where o ∈ [0, 1] scales the env part (specular occlusion) and `fill` is the radiance
    /// standing in for the occluded part (both constants: no gradient). o = 1, fill = 0 is the
    /// specular term of [`shade64`](Self::shade64).
    pub fn specular_lobe(&self, r: f64, n: V3, wo: V3, occlusion: f64, fill: V3) -> V3 {
        let ndv = dot(n, wo);
        let refl = add(scale(n, 2.0 * ndv), scale(wo, -1.0));
        let (p, _, _) = self.prefiltered(refl, r);
        let lut = BrdfLut::get().lookup(ndv.clamp(super::brdf::COS_EPS, 1.0), r);
        let k = super::brdf::F0 * lut.a + lut.b;
        std::array::from_fn(|ch| k * (occlusion * p[ch] + fill[ch]))
    }

    /// Backward of [`specular_lobe`](Self::specular_lobe) for the upstream gradient `v`:
    /// returns (∂/∂r, ∂/∂n, ∂/∂ω_o) and adds the prefiltered-map gradients into `grads`.
    #[allow(clippy::too_many_arguments)]
    pub fn specular_lobe_backward(
        &self,
        r: f64,
        n: V3,
        wo: V3,
        occlusion: f64,
        fill: V3,
        v: V3,
        grads: &mut SplitSumGrads,
    ) -> (f64, V3, V3) {
        let ndv = dot(n, wo);
        let refl = add(scale(n, 2.0 * ndv), scale(wo, -1.0));
        let (p, jp, dp_dr) = self.prefiltered(refl, r);
        let (nov, live) = if ndv < super::brdf::COS_EPS {
            (super::brdf::COS_EPS, 0.0)
        } else if ndv > 1.0 {
            (1.0, 0.0)
        } else {
            (ndv, 1.0)
        };
        let lut = BrdfLut::get().lookup(nov, r);
        let spec = super::brdf::F0 * lut.a + lut.b;
        let incident: V3 = std::array::from_fn(|ch| occlusion * p[ch] + fill[ch]);
        let v_spec = dot(v, incident);
        let v_p = scale(v, spec * occlusion);
        let mut v_r = dot(v_p, dp_dr) + v_spec * (super::brdf::F0 * lut.da_dr + lut.db_dr);
        let v_nov = v_spec * (super::brdf::F0 * lut.da_dnov + lut.db_dnov) * live;
        // Prefiltered maps: bilinear scatter into the two levels.
        let (k, t, _) = level_coords(r);
        env_lookup_scatter(&self.levels[k], refl, scale(v_p, 1.0 - t), &mut grads.v_levels[k]);
        env_lookup_scatter(&self.levels[k + 1], refl, scale(v_p, t), &mut grads.v_levels[k + 1]);
        // R = 2(n·ω_o)n − ω_o.
        let mut v_refl = [0.0; 3];
        for ch in 0..3 {
            v_refl = add(v_refl, scale(jp[ch], v_p[ch]));
        }
        let rdn = dot(v_refl, n);
        let mut v_n = add(scale(v_refl, 2.0 * ndv), scale(wo, 2.0 * rdn));
        let mut v_wo = add(scale(n, 2.0 * rdn), scale(v_refl, -1.0));
        // NoV into the LUT.
        v_n = add(v_n, scale(wo, v_nov));
        v_wo = add(v_wo, scale(n, v_nov));
        if !(0.0..=1.0).contains(&r) {
            v_r = 0.0;
        }
        (v_r, v_n, v_wo)
    }

    /// Backward of [`shade`] for the upstream gradient `v_rgb` on diffuse + specular. Returns
    /// the point's gradients and adds the map gradients into `grads`.
    pub fn shade_backward(
        &self,
        a: [f32; 3],
        r: f32,
        n: [f32; 3],
        wo: [f32; 3],
        v_rgb: [f32; 3],
        grads: &mut SplitSumGrads,
    ) -> PointGrads {
        let (a, r, n, wo, v) = (to64(a), r as f64, to64(n), to64(wo), to64(v_rgb));
        // Diffuse: a ⊙ irr(n) · kd(NoV, r).
        let (irr, jirr) = env_lookup_grad(&self.irradiance, n);
        let (kd, dkd_dnov, dkd_dr) = super::brdf::diffuse_weight(dot(n, wo), r);
        let v_albedo = [v[0] * irr[0] * kd, v[1] * irr[1] * kd, v[2] * irr[2] * kd];
        let v_irr = [v[0] * a[0] * kd, v[1] * a[1] * kd, v[2] * a[2] * kd];
        let v_kd = v[0] * a[0] * irr[0] + v[1] * a[1] * irr[1] + v[2] * a[2] * irr[2];
        env_lookup_scatter(&self.irradiance, n, v_irr, &mut grads.v_irradiance);
        let mut v_n = scale(wo, v_kd * dkd_dnov);
        for ch in 0..3 {
            v_n = add(v_n, scale(jirr[ch], v_irr[ch]));
        }
        // Specular.
        let (v_r, v_ns, v_wo) = self.specular_lobe_backward(r, n, wo, 1.0, [0.0; 3], v, grads);
        let v_n = add(v_n, v_ns);
        let v_wo = add(v_wo, scale(n, v_kd * dkd_dnov));
        let v_r = v_r + v_kd * dkd_dr;
        PointGrads { v_albedo: to32(v_albedo), v_roughness: v_r as f32, v_n: to32(v_n), v_wo: to32(v_wo) }
    }

    /// Sends the map gradients to the env texels (transposed filters and mip chain); adds into
    /// `v_texels` (length H·W of the env this was built from).
    pub fn backward_to_env(&self, grads: &SplitSumGrads, v_texels: &mut [[f32; 3]]) {
        let f = &self.filters;
        let mut v_mips: Vec<Vec<[f32; 3]>> = self.mips.iter().map(|m| vec![[0.0; 3]; m.texels.len()]).collect();
        for (k, lf) in f.levels.iter().enumerate() {
            lf.apply_transposed(&grads.v_levels[k + 1], &mut v_mips[lf.src_mip]);
        }
        f.irradiance.apply_transposed(&grads.v_irradiance, &mut v_mips[f.irradiance.src_mip]);
        for (dst, g) in v_mips[0].iter_mut().zip(&grads.v_levels[0]) {
            for ch in 0..3 {
                dst[ch] += g[ch];
            }
        }
        for m in (1..f.sizes.len()).rev() {
            let (ph, pw) = f.sizes[m - 1];
            let (lo, hi) = v_mips.split_at_mut(m);
            downsample_transposed(&hi[0], ph, pw, &mut lo[m - 1]);
        }
        for (dst, g) in v_texels.iter_mut().zip(&v_mips[0]) {
            for ch in 0..3 {
                dst[ch] += g[ch];
            }
        }
    }

    /// [`shade`] over SoA slices (rayon over points); writes diffuse + specular into `out`.
    pub fn shade_batch(
        &self,
        albedo: &[[f32; 3]],
        rough: &[f32],
        normal: &[[f32; 3]],
        view: &[[f32; 3]],
        out: &mut [[f32; 3]],
    ) {
        out.par_iter_mut().enumerate().for_each(|(i, o)| {
            let s = self.shade(albedo[i], rough[i], normal[i], view[i]);
            *o = std::array::from_fn(|c| s.diffuse[c] + s.specular[c]);
        });
    }

    /// Backward of [`shade_batch`]: per-point gradients written into the `v_*` slices (same
    /// length as the inputs), env texel gradients added into `v_texels`.
    #[allow(clippy::too_many_arguments)]
    pub fn shade_batch_backward(
        &self,
        albedo: &[[f32; 3]],
        rough: &[f32],
        normal: &[[f32; 3]],
        view: &[[f32; 3]],
        v_out: &[[f32; 3]],
        v_albedo: &mut [[f32; 3]],
        v_rough: &mut [f32],
        v_normal: &mut [[f32; 3]],
        v_view: &mut [[f32; 3]],
        v_texels: &mut [[f32; 3]],
    ) {
        const CHUNK: usize = 1024;
        let grads = v_albedo
            .par_chunks_mut(CHUNK)
            .zip(v_rough.par_chunks_mut(CHUNK))
            .zip(v_normal.par_chunks_mut(CHUNK))
            .zip(v_view.par_chunks_mut(CHUNK))
            .enumerate()
            // Fixed groups of chunks, summed in order: the result does not depend on how rayon
            // schedules the work (a plain fold + reduce made resumed runs differ).
            .fold_chunks(
                4,
                || self.zero_grads(),
                |mut g, (c, (((va, vr), vn), vv))| {
                    for k in 0..va.len() {
                        let i = c * CHUNK + k;
                        let p = self.shade_backward(albedo[i], rough[i], normal[i], view[i], v_out[i], &mut g);
                        va[k] = p.v_albedo;
                        vr[k] = p.v_roughness;
                        vn[k] = p.v_n;
                        vv[k] = p.v_wo;
                    }
                    g
                },
            )
            .collect::<Vec<_>>()
            .into_iter()
            .fold(self.zero_grads(), |mut a, b| {
                for (la, lb) in a.v_levels.iter_mut().zip(&b.v_levels) {
                    for (x, y) in la.iter_mut().zip(lb) {
                        for ch in 0..3 {
                            x[ch] += y[ch];
                        }
                    }
                }
                for (x, y) in a.v_irradiance.iter_mut().zip(&b.v_irradiance) {
                    for ch in 0..3 {
                        x[ch] += y[ch];
                    }
                }
                a
            });
        self.backward_to_env(&grads, v_texels);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shade::testutil::{close, rng, unit, unit_in};
    use rand::RngExt;

    fn smooth_env(h: usize, w: usize) -> EnvMap {
        let mut env = EnvMap::constant(w, h, [0.0; 3]);
        for j in 0..h {
            for i in 0..w {
                let d = env.texel_dir(i, j);
                env.texels[j * w + i] = [
                    1.0 + 0.6 * d[2] + 0.3 * d[0],
                    0.8 + 0.5 * (3.0 * d[1]).sin() * d[2].abs(),
                    (0.5 + 0.4 * d[0] * d[1] + 0.3 * d[2] * d[2]).max(0.0),
                ];
            }
        }
        env
    }

    fn random_env(h: usize, w: usize, seed: u64) -> EnvMap {
        let mut rg = rng(seed);
        let mut env = EnvMap::constant(w, h, [0.0; 3]);
        for t in env.texels.iter_mut() {
            *t = [rg.random_range(0.1..3.0), rg.random_range(0.1..3.0), rg.random_range(0.1..3.0)];
        }
        env
    }

    #[test]
    fn lut_matches_brute_force_quadrature() {
        let lut = BrdfLut::get();
        for &(i, j) in &[(31, 31), (31, 3), (16, 10), (4, 20), (2, 31), (8, 6), (24, 16), (1, 1)] {
            let nov = (i as f64 / 31.0).max(1e-4);
            let r = j as f64 / 31.0;
            let [a, b] = lut.node(i, j);
            let e1 = crate::shade::brdf::directional_albedo_reference(nov, r, 1.0, 240);
            let e0 = crate::shade::brdf::directional_albedo_reference(nov, r, 0.0, 240);
            assert!((a + b - e1).abs() < 0.01 + 0.01 * e1, "({i},{j}) A+B {} vs {e1}", a + b);
            assert!((b - e0).abs() < 0.005 + 0.01 * e0, "({i},{j}) B {b} vs {e0}");
        }
    }

    #[test]
    fn lut_lookup_derivatives() {
        let lut = BrdfLut::get();
        let mut rg = rng(3);
        for _ in 0..50 {
            let (nov, r): (f64, f64) = (rg.random_range(0.01..0.99), rg.random_range(0.01..0.99));
            let s = lut.lookup(nov, r);
            let e = 1e-7;
            let (p, m) = (lut.lookup(nov + e, r), lut.lookup(nov - e, r));
            assert!(close(s.da_dnov, (p.a - m.a) / (2.0 * e), 1e-4, 1e-6));
            assert!(close(s.db_dnov, (p.b - m.b) / (2.0 * e), 1e-4, 1e-6));
            let (p, m) = (lut.lookup(nov, r + e), lut.lookup(nov, r - e));
            assert!(close(s.da_dr, (p.a - m.a) / (2.0 * e), 1e-4, 1e-6));
            assert!(close(s.db_dr, (p.b - m.b) / (2.0 * e), 1e-4, 1e-6));
        }
    }

    #[test]
    fn direction_lookup_matches_envmap_and_its_jacobian() {
        let env = random_env(16, 32, 4);
        let mut rg = rng(5);
        for _ in 0..300 {
            let d = unit(&mut rg);
            let (c, jac) = env_lookup_grad(&env, d);
            let c2 = env.lookup(to32(d));
            for ch in 0..3 {
                assert!((c[ch] - c2[ch] as f64).abs() < 1e-4, "{c:?} vs {c2:?}");
            }
            let e = 1e-7;
            for a in 0..3 {
                let (mut p, mut m) = (d, d);
                p[a] += e;
                m[a] -= e;
                let (cp, _) = env_lookup_grad(&env, p);
                let (cm, _) = env_lookup_grad(&env, m);
                for ch in 0..3 {
                    let fd = (cp[ch] - cm[ch]) / (2.0 * e);
                    assert!(close(jac[ch][a], fd, 1e-4, 1e-4), "d{a} ch{ch}: {} vs {fd}", jac[ch][a]);
                }
            }
        }
    }

    #[test]
    fn furnace_diffuse_exact_and_specular_is_lut() {
        let env = EnvMap::constant(128, 64, [1.7, 0.4, 2.5]);
        let ss = SplitSum::new(&env).unwrap();
        let mut rg = rng(6);
        for _ in 0..100 {
            let n = unit(&mut rg);
            let wo = unit_in(&mut rg, n, 0.01);
            let r: f64 = rg.random_range(0.0..1.0);
            let (d, s) = ss.shade64([1.0; 3], r, n, wo);
            let lut = BrdfLut::get().lookup(dot(n, wo).min(1.0), r);
            let k = super::super::brdf::F0 * lut.a + lut.b;
            // A white base under the specular layer reflects 1 − E: with the lobe, all of it.
            for (ch, l) in [1.7, 0.4, 2.5].iter().enumerate() {
                assert!((d[ch] - l * (1.0 - k)).abs() < 1e-5 * l, "diffuse {d:?}");
                assert!((s[ch] - l * k).abs() < 1e-5 * l, "specular {s:?} vs {}", l * k);
            }
        }
    }

    #[test]
    fn filters_match_brute_force_integrals() {
        let env = smooth_env(64, 128);
        let ss = SplitSum::new(&env).unwrap();
        let mut rg = rng(7);
        let mut worst_irr = 0.0f64;
        let mut worst_spec = 0.0f64;
        for _ in 0..20 {
            let n = unit(&mut rg);
            // Brute force over every base texel with 2×2 sub-points.
            let (mut e, mut wsum) = ([0.0f64; 3], 0.0);
            let k = 1 + (rg.random::<f64>() * 4.99) as usize;
            let a2 = super::super::brdf::alpha2(LEVEL_ROUGHNESS[k]);
            let (mut p, mut psum) = ([0.0f64; 3], 0.0);
            for j in 0..64 {
                let sa = solid_angle(64, 128, j);
                for i in 0..128 {
                    let t = to64(env.texels[j * 128 + i]);
                    for (sa_, sb) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
                        let l = texel_dir_sub(64, 128, i, j, sa_, sb);
                        let c = dot(n, l).max(0.0) * sa;
                        e = add(e, scale(t, c));
                        wsum += c;
                        if dot(n, l) > 0.0 {
                            let hv = crate::shade::normalize(add(n, l));
                            let w = super::super::brdf::ggx_d(dot(n, hv), a2) * dot(n, l) * sa;
                            p = add(p, scale(t, w));
                            psum += w;
                        }
                    }
                }
            }
            let (irr, _) = env_lookup_grad(&ss.irradiance, n);
            let (pre, _) = env_lookup_grad(&ss.levels[k], n);
            for ch in 0..3 {
                let want = e[ch] / wsum;
                worst_irr = worst_irr.max((irr[ch] - want).abs() / want);
                let want = p[ch] / psum;
                worst_spec = worst_spec.max((pre[ch] - want).abs() / want.max(0.1));
            }
        }
        assert!(worst_irr < 0.02, "irradiance rel. error {worst_irr}");
        assert!(worst_spec < 0.05, "prefiltered rel. error {worst_spec}");
    }

    /// A random normal, view and roughness; every 5th view grazing, every 4th roughness near 0
    /// and near 1.
    fn shading_point(rg: &mut rand_pcg::Pcg64, case: usize) -> (V3, V3, f64) {
        let n = unit(rg);
        let wo = unit_in(rg, n, if case % 5 == 0 { 0.0 } else { 0.05 });
        let r: f64 = match case % 4 {
            0 => rg.random_range(0.001..0.05),
            1 => rg.random_range(0.95..0.999),
            _ => rg.random_range(0.05..0.95),
        };
        (n, wo, r)
    }

    #[test]
    fn shade_backward_matches_finite_differences() {
        let env = random_env(64, 128, 8);
        let ss = SplitSum::new(&env).unwrap();
        let mut rg = rng(9);
        let wch = [0.9, -0.4, 1.3];
        let obj = |a: V3, r: f64, n: V3, wo: V3| {
            let (d, s) = ss.shade64(a, r, n, wo);
            dot(wch, add(d, s))
        };
        for case in 0..60 {
            let (n, wo, r) = shading_point(&mut rg, case);
            let a: V3 = [rg.random(), rg.random(), rg.random()];
            let mut g = ss.zero_grads();
            let pg = ss.shade_backward(to32(a), r as f32, to32(n), to32(wo), to32(wch), &mut g);
            // The backward ran on f32-rounded inputs: evaluate the FD there too.
            let (a, r, n, wo) = (to64(to32(a)), r as f32 as f64, to64(to32(n)), to64(to32(wo)));
            let e = 1e-6;
            let fd_r = (obj(a, r + e, n, wo) - obj(a, r - e, n, wo)) / (2.0 * e);
            assert!(close(pg.v_roughness as f64, fd_r, 2e-3, 1e-3), "case {case} v_r {} vs {fd_r}", pg.v_roughness);
            for c in 0..3 {
                let bump = |v: V3, s: f64| {
                    let mut p = v;
                    p[c] += s;
                    p
                };
                let fd = (obj(bump(a, e), r, n, wo) - obj(bump(a, -e), r, n, wo)) / (2.0 * e);
                assert!(close(pg.v_albedo[c] as f64, fd, 1e-4, 1e-5), "case {case} v_a");
                let fd = (obj(a, r, bump(n, e), wo) - obj(a, r, bump(n, -e), wo)) / (2.0 * e);
                assert!(close(pg.v_n[c] as f64, fd, 2e-3, 2e-3), "case {case} v_n[{c}] {} vs {fd}", pg.v_n[c]);
                let fd = (obj(a, r, n, bump(wo, e)) - obj(a, r, n, bump(wo, -e))) / (2.0 * e);
                assert!(close(pg.v_wo[c] as f64, fd, 2e-3, 2e-3), "case {case} v_wo[{c}] {} vs {fd}", pg.v_wo[c]);
            }
        }
    }

    #[test]
    fn occluded_specular_lobe_matches_finite_differences() {
        let env = random_env(64, 128, 12);
        let ss = SplitSum::new(&env).unwrap();
        let mut rg = rng(13);
        let wch = [0.7, 1.1, -0.5];
        for case in 0..40 {
            let (n, wo, r) = shading_point(&mut rg, case);
            let occ: f64 = if case % 3 == 0 { 0.0 } else { rg.random() };
            let fill: V3 = [rg.random(), rg.random(), rg.random()];
            let obj = |r: f64, n: V3, wo: V3| dot(wch, ss.specular_lobe(r, n, wo, occ, fill));
            let mut g = ss.zero_grads();
            let (v_r, v_n, v_wo) = ss.specular_lobe_backward(r, n, wo, occ, fill, wch, &mut g);
            let e = 1e-6;
            let fd = (obj(r + e, n, wo) - obj(r - e, n, wo)) / (2.0 * e);
            assert!(close(v_r, fd, 2e-3, 1e-3), "case {case} v_r {v_r} vs {fd}");
            for c in 0..3 {
                let bump = |v: V3, s: f64| {
                    let mut p = v;
                    p[c] += s;
                    p
                };
                let fd = (obj(r, bump(n, e), wo) - obj(r, bump(n, -e), wo)) / (2.0 * e);
                assert!(close(v_n[c], fd, 2e-3, 2e-3), "case {case} v_n[{c}] {} vs {fd}", v_n[c]);
                let fd = (obj(r, n, bump(wo, e)) - obj(r, n, bump(wo, -e))) / (2.0 * e);
                assert!(close(v_wo[c], fd, 2e-3, 2e-3), "case {case} v_wo[{c}] {} vs {fd}", v_wo[c]);
            }
            // Env texels (linear): a unit step on the texels with the largest gradients.
            if case % 10 == 1 {
                let mut vt = vec![[0.0f32; 3]; env.texels.len()];
                ss.backward_to_env(&g, &mut vt);
                let mut order: Vec<usize> = (0..vt.len()).collect();
                order.sort_by(|&a, &b| vt[b][1].abs().total_cmp(&vt[a][1].abs()));
                assert!(occ == 0.0 || vt[order[0]][1] != 0.0);
                for &t in &order[..6] {
                    let mut e2 = env.clone();
                    e2.texels[t][1] += 1.0;
                    let s2 = SplitSum::new(&e2).unwrap();
                    let fd = dot(wch, s2.specular_lobe(r, n, wo, occ, fill)) - obj(r, n, wo);
                    assert!(close(vt[t][1] as f64, fd, 1e-3, 1e-6), "case {case} texel {t}: {} vs {fd}", vt[t][1]);
                }
            }
        }
    }

    #[test]
    fn env_texel_gradients_match_finite_differences() {
        let env = random_env(64, 128, 10);
        let ss = SplitSum::new(&env).unwrap();
        let mut rg = rng(11);
        let m = 24;
        let normal: Vec<[f32; 3]> = (0..m).map(|_| to32(unit(&mut rg))).collect();
        let view: Vec<[f32; 3]> = normal.iter().map(|n| to32(unit_in(&mut rg, to64(*n), 0.1))).collect();
        let albedo: Vec<[f32; 3]> = (0..m).map(|_| [rg.random(), rg.random(), rg.random()]).collect();
        let rough: Vec<f32> = (0..m).map(|i| if i < 4 { 0.03 * i as f32 } else { rg.random() }).collect();
        let v_out: Vec<[f32; 3]> = (0..m).map(|_| [rg.random_range(-1.0..1.0), rg.random(), rg.random()]).collect();
        let (mut va, mut vr, mut vn, mut vv) = (vec![[0.0; 3]; m], vec![0.0; m], vec![[0.0; 3]; m], vec![[0.0; 3]; m]);
        let mut vt = vec![[0.0f32; 3]; env.texels.len()];
        ss.shade_batch_backward(&albedo, &rough, &normal, &view, &v_out, &mut va, &mut vr, &mut vn, &mut vv, &mut vt);
        let obj = |e: &EnvMap| {
            let s = SplitSum::new(e).unwrap();
            (0..m)
                .map(|i| {
                    let (d, sp) = s.shade64(to64(albedo[i]), rough[i] as f64, to64(normal[i]), to64(view[i]));
                    dot(to64(v_out[i]), add(d, sp))
                })
                .sum::<f64>()
        };
        let base = obj(&env);
        // The texels with the largest gradients, plus random ones (most are zero or tiny).
        let mut order: Vec<usize> = (0..vt.len()).collect();
        order.sort_by(|&a, &b| vt[b][0].abs().partial_cmp(&vt[a][0].abs()).unwrap());
        let mut picks: Vec<usize> = order[..12].to_vec();
        picks.extend((0..12).map(|_| rg.random_range(0..vt.len())));
        for &t in &picks {
            for ch in 0..3 {
                let mut e2 = env.clone();
                e2.texels[t][ch] += 1.0;
                let fd = obj(&e2) - base; // linear in the texels
                assert!(close(vt[t][ch] as f64, fd, 1e-3, 1e-5), "texel {t} ch {ch}: {} vs {fd}", vt[t][ch]);
            }
        }
        // The per-point outputs of the batch equal the single-point backward.
        let mut g = ss.zero_grads();
        let p = ss.shade_backward(albedo[5], rough[5], normal[5], view[5], v_out[5], &mut g);
        assert_eq!(p.v_n, vn[5]);
        assert_eq!(p.v_roughness, vr[5]);
    }

    #[test]
    fn rejects_bad_sizes() {
        assert!(SplitSum::new(&EnvMap::constant(100, 50, [1.0; 3])).is_err());
        assert!(SplitSum::new(&EnvMap::constant(16, 4, [1.0; 3])).is_err());
    }

    /// Timing of the per-iteration prefilter forward + backward (run in release with
    /// `cargo test --release --lib shade::splitsum::tests::prefilter_timing -- --ignored --nocapture`).
    #[test]
    #[ignore]
    fn prefilter_timing() {
        let env = random_env(64, 128, 12);
        let _ = SplitSum::new(&env).unwrap(); // builds the cached filters
        let iters = 200;
        let t0 = std::time::Instant::now();
        let mut vt = vec![[0.0f32; 3]; env.texels.len()];
        for _ in 0..iters {
            let ss = SplitSum::new(&env).unwrap();
            let mut g = ss.zero_grads();
            for l in g.v_levels.iter_mut() {
                l.iter_mut().for_each(|x| *x = [1.0; 3]);
            }
            g.v_irradiance.iter_mut().for_each(|x| *x = [1.0; 3]);
            ss.backward_to_env(&g, &mut vt);
        }
        let ms = t0.elapsed().as_secs_f64() * 1e3 / iters as f64;
        println!("split-sum prefilter forward+backward (64x128): {ms:.3} ms per iteration");
    }
}
