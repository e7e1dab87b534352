//! Backward rasterisation, exact for the order the forward pass used.
//!
//! Per pixel the forward window is re-run (`composite_pixel`) to list the blended hits in blend
//! order with their T_before; the list is then walked back to front (2DGS bookkeeping). With
//! every output written as O = Σ_j w_j q_j + T_n b (w_j = α_j T_j), ∂O/∂α_j = T_j q_j −
//! (Σ_{k>j} w_k q_k + T_n b)/(1 − α_j). All outputs share that form with the combined
//! q_j = v_C·c_j + v_F·f_j + v_A' + v_D·z_j + v_N·n_j + v_dist·g_j, where
//! v_D = v_depth/A and v_A' = v_alpha − v_depth·D/A² (depth = D/A), and for the distortion
//! Σ_{i<j} w_i w_j (m_i − m_j)²: g_j = ∂/∂w_j = m_j² A − 2 m_j M1 + M2 (totals over the
//! pixel) and ∂/∂m_j = 2 w_j (m_j A − M1). Then α = o·G (no gradient when clamped at 0.99),
//! G = e^{−ρ/2}, and either ρ₃, z through (u, v) = h.xy/h.z, h = k × l, k = x·Tw − Tu,
//! l = y·Tw − Tv, or ρ₂ = 2|μ₂D − pixel|² with z = Tw.z.
//!
//! Parallel decomposition: rayon over rows of tiles. Each (tile, surfel) pair owns one
//! gradient row (tile-major, so a tile writes a contiguous slice, no atomics); rows are then
//! summed per surfel (rayon over surfels, via `sorted_of_gen`) and pushed through the
//! projection backward.

use super::forward::{Hit, TileData, composite_pixel, norm_depth};
use super::project::{ProjGrad, SurfelGradSlots, project_backward_one};
use super::tiles::split_by_offsets;
use super::{BackwardOutput, Features, ForwardState, MAX_FEATURES, RasterSettings, RenderGrads, TILE};
use crate::camera::Camera;
use crate::surfels::{SurfelGrads, Surfels};
use rayon::prelude::*;

const ROW_TU: usize = 0;
const ROW_TV: usize = 3;
const ROW_TW: usize = 6;
const ROW_MEAN2D: usize = 9;
const ROW_OPACITY: usize = 11;
const ROW_COLOUR: usize = 12;
const ROW_NORMAL: usize = 15;
const ROW_FEAT: usize = 18;

/// Backward pass: adds ∂L/∂(parameters) into `v_surfels` (means, quats, log_scales,
/// opacity_logits, sh) and ∂L/∂features into `v_features` (N × channels).
#[allow(clippy::too_many_arguments)]
pub fn render_backward(
    surfels: &Surfels,
    camera: &Camera,
    settings: &RasterSettings,
    features: Option<Features>,
    state: &ForwardState,
    grads: &RenderGrads,
    v_surfels: &mut SurfelGrads,
    v_features: Option<&mut [f32]>,
) -> BackwardOutput {
    let n = surfels.len();
    assert_eq!(v_surfels.len(), n, "gradient buffer must have one entry per surfel");
    let nch = features.map_or(0, |f| f.channels);
    if let Some(f) = features {
        assert!(f.channels <= MAX_FEATURES);
        assert_eq!(f.data.len(), n * nch);
    }
    let bins = &state.tiles;
    let stride = ROW_FEAT + nch;
    let npairs = bins.ids.len();
    let mut rows = vec![0.0f32; npairs * stride];
    if state.width > 0 && state.height > 0 {
        let row_offsets: Vec<u32> =
            (0..=bins.tiles_y).map(|ty| bins.offsets[(ty * bins.tiles_x) as usize] * stride as u32).collect();
        split_by_offsets(&mut rows, &row_offsets).into_par_iter().enumerate().for_each_init(
            || (TileData::default(), Vec::<(Hit, f32)>::with_capacity(256)),
            |(td, list), (ty, chunk)| {
                backward_tile_row(state, camera, settings, features, grads, ty as u32, chunk, stride, td, list)
            },
        );
    }

    // Sum the pair rows per surfel, then the projection backward.
    let campos = camera.position();
    let proj = &state.proj;
    let mut v_mean2d = vec![[0.0f32; 2]; n];
    let row_sum = |i: usize, out: &mut [f32]| {
        for g in bins.pair_offsets[i]..bins.pair_offsets[i + 1] {
            let p = bins.sorted_of_gen[g as usize] as usize;
            for (o, r) in out.iter_mut().zip(&rows[p * stride..(p + 1) * stride]) {
                *o += *r;
            }
        }
    };
    (
        v_surfels.means.par_iter_mut(),
        v_surfels.log_scales.par_iter_mut(),
        v_surfels.quats.par_iter_mut(),
        v_surfels.opacity_logits.par_iter_mut(),
        v_surfels.sh.par_iter_mut(),
        v_mean2d.par_iter_mut(),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(i, (vm, vs, vq, vo, vsh, vm2))| {
            if bins.pair_offsets[i] == bins.pair_offsets[i + 1] {
                return;
            }
            let mut acc = [0.0f32; ROW_FEAT];
            row_sum_fixed(&rows, bins, i, stride, &mut acc);
            let g = ProjGrad {
                v_tu: [acc[ROW_TU], acc[ROW_TU + 1], acc[ROW_TU + 2]],
                v_tv: [acc[ROW_TV], acc[ROW_TV + 1], acc[ROW_TV + 2]],
                v_tw: [acc[ROW_TW], acc[ROW_TW + 1], acc[ROW_TW + 2]],
                v_mean2d: [acc[ROW_MEAN2D], acc[ROW_MEAN2D + 1]],
                v_opacity: acc[ROW_OPACITY],
                v_colour: [acc[ROW_COLOUR], acc[ROW_COLOUR + 1], acc[ROW_COLOUR + 2]],
                v_normal: [acc[ROW_NORMAL], acc[ROW_NORMAL + 1], acc[ROW_NORMAL + 2]],
            };
            let slots = SurfelGradSlots { means: vm, log_scales: vs, quats: vq, opacity_logit: vo, sh: vsh };
            *vm2 = project_backward_one(surfels, i, camera, campos, proj, &g, slots);
        });
    if let Some(vf) = v_features
        && nch > 0
    {
        assert_eq!(vf.len(), n * nch);
        vf.par_chunks_mut(nch).enumerate().for_each(|(i, out)| {
            let mut acc = [0.0f32; ROW_FEAT + MAX_FEATURES];
            row_sum(i, &mut acc[..stride]);
            for ch in 0..nch {
                out[ch] += acc[ROW_FEAT + ch];
            }
        });
    }
    let v_mean2d_norm = v_mean2d.iter().map(|g| (g[0] * g[0] + g[1] * g[1]).sqrt()).collect();
    BackwardOutput { v_mean2d_norm, v_mean2d }
}

fn row_sum_fixed(rows: &[f32], bins: &super::tiles::TileBins, i: usize, stride: usize, out: &mut [f32; ROW_FEAT]) {
    for g in bins.pair_offsets[i]..bins.pair_offsets[i + 1] {
        let p = bins.sorted_of_gen[g as usize] as usize;
        let r = &rows[p * stride..p * stride + ROW_FEAT];
        for k in 0..ROW_FEAT {
            out[k] += r[k];
        }
    }
}

#[inline(always)]
fn get3(v: &[[f32; 3]], i: usize) -> [f32; 3] {
    if v.is_empty() { [0.0; 3] } else { v[i] }
}
#[inline(always)]
fn get1(v: &[f32], i: usize) -> f32 {
    if v.is_empty() { 0.0 } else { v[i] }
}
#[inline(always)]
fn dot3(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
#[inline(always)]
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

#[allow(clippy::too_many_arguments)]
fn backward_tile_row(
    state: &ForwardState,
    camera: &Camera,
    s: &RasterSettings,
    features: Option<Features>,
    grads: &RenderGrads,
    ty: u32,
    chunk: &mut [f32],
    stride: usize,
    td: &mut TileData,
    list: &mut Vec<(Hit, f32)>,
) {
    let bins = &state.tiles;
    let proj = &state.proj;
    let (w, h) = (camera.width, camera.height);
    let k = s.k();
    let nch = features.map_or(0, |f| f.channels);
    let o = s.outputs;
    let mut win = [Hit::default(); super::forward::RING];
    let row_start = bins.offsets[(ty * bins.tiles_x) as usize];
    let y0 = ty * TILE;
    let y1 = (y0 + TILE).min(h);
    let has_f = nch > 0 && !grads.v_features.is_empty();
    for tx in 0..bins.tiles_x {
        let t = (ty * bins.tiles_x + tx) as usize;
        let (p0, p1) = (bins.offsets[t], bins.offsets[t + 1]);
        if p0 == p1 {
            continue;
        }
        let ids = &bins.ids[p0 as usize..p1 as usize];
        let tile_rows = &mut chunk[(p0 - row_start) as usize * stride..(p1 - row_start) as usize * stride];
        td.load(proj, ids, s.alpha_min);
        let x0 = tx * TILE;
        let x1 = (x0 + TILE).min(w);
        for y in y0..y1 {
            for x in x0..x1 {
                let pix = (y * w + x) as usize;
                let v_c = if o.colour { get3(&grads.v_colour, pix) } else { [0.0; 3] };
                let v_alpha = get1(&grads.v_alpha, pix);
                let v_depth = if o.depth { get1(&grads.v_depth, pix) } else { 0.0 };
                let v_median = if o.median_depth { get1(&grads.v_median_depth, pix) } else { 0.0 };
                let v_n = if o.normal { get3(&grads.v_normal, pix) } else { [0.0; 3] };
                let v_dist = if o.distortion { get1(&grads.v_distortion, pix) } else { 0.0 };
                let mut v_f = [0.0f32; MAX_FEATURES];
                let mut any_f = false;
                if has_f {
                    v_f[..nch].copy_from_slice(&grads.v_features[pix * nch..(pix + 1) * nch]);
                    any_f = v_f[..nch].iter().any(|&g| g != 0.0);
                }
                if v_c == [0.0; 3]
                    && v_alpha == 0.0
                    && v_depth == 0.0
                    && v_median == 0.0
                    && v_n == [0.0; 3]
                    && v_dist == 0.0
                    && !any_f
                {
                    continue;
                }
                let (pxf, pyf) = (x as f32 + 0.5, y as f32 + 0.5);
                list.clear();
                let (tf, _) = composite_pixel(
                    td,
                    pxf,
                    pyf,
                    s,
                    k,
                    &mut win,
                    #[inline(always)]
                    |hit, t| list.push((*hit, t)),
                );
                if list.is_empty() {
                    continue;
                }
                // Totals over the pixel.
                let (mut a_tot, mut d_tot, mut m1, mut m2) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
                let mut median_j = usize::MAX;
                for (j, (hit, t)) in list.iter().enumerate() {
                    let wgt = hit.alpha * t;
                    d_tot += wgt * hit.z;
                    a_tot += wgt;
                    if v_dist != 0.0 {
                        let m = norm_depth(hit.z, s.near, s.far);
                        m1 += wgt * m;
                        m2 += wgt * m * m;
                    }
                    if *t > 0.5 {
                        median_j = j;
                    }
                }
                let (v_dd, v_a) = if a_tot > 0.0 {
                    (v_depth / a_tot, v_alpha - v_depth * d_tot / (a_tot * a_tot))
                } else {
                    (0.0, v_alpha)
                };
                let dm_scale = s.far / (s.far - s.near) * s.near;
                let mut acc = tf * dot3(v_c, s.background);
                for j in (0..list.len()).rev() {
                    let (hit, t) = list[j];
                    let li = hit.li as usize;
                    let id = td.ids[li] as usize;
                    let wgt = hit.alpha * t;
                    let row = &mut tile_rows[li * stride..(li + 1) * stride];
                    let mut q = v_a + v_dd * hit.z;
                    let mut v_z = wgt * v_dd;
                    if o.colour {
                        let col = td.colour[li];
                        q += dot3(v_c, col);
                        for ch in 0..3 {
                            row[ROW_COLOUR + ch] += wgt * v_c[ch];
                        }
                    }
                    if o.normal {
                        q += dot3(v_n, td.normal[li]);
                        for ch in 0..3 {
                            row[ROW_NORMAL + ch] += wgt * v_n[ch];
                        }
                    }
                    if v_dist != 0.0 {
                        let m = norm_depth(hit.z, s.near, s.far);
                        q += v_dist * (m * m * a_tot - 2.0 * m * m1 + m2);
                        let dm_dz = dm_scale / (hit.z * hit.z);
                        v_z += v_dist * 2.0 * wgt * (m * a_tot - m1) * dm_dz;
                    }
                    if any_f {
                        let fe = features.unwrap();
                        let src = &fe.data[id * nch..(id + 1) * nch];
                        for ch in 0..nch {
                            q += v_f[ch] * src[ch];
                            row[ROW_FEAT + ch] += wgt * v_f[ch];
                        }
                    }
                    if j == median_j {
                        v_z += v_median;
                    }
                    let v_alpha_j = t * q - acc / (1.0 - hit.alpha);
                    acc += wgt * q;

                    // α = o·G → ρ → (u, v) or μ₂D, and z.
                    let mut v_rho = 0.0;
                    if !hit.clamped {
                        let op = td.op[li];
                        row[ROW_OPACITY] += hit.g * v_alpha_j;
                        v_rho = -0.5 * hit.g * op * v_alpha_j;
                    }
                    let twv = [td.twx[li], td.twy[li], td.twz[li]];
                    if hit.is3d {
                        let (u, v) = (hit.u, hit.v);
                        let v_u = 2.0 * u * v_rho + twv[0] * v_z;
                        let v_v = 2.0 * v * v_rho + twv[1] * v_z;
                        let kk = [pxf * twv[0] - td.tux[li], pxf * twv[1] - td.tuy[li], pxf * twv[2] - td.tuz[li]];
                        let ll = [pyf * twv[0] - td.tvx[li], pyf * twv[1] - td.tvy[li], pyf * twv[2] - td.tvz[li]];
                        let inv_hz = 1.0 / (kk[0] * ll[1] - kk[1] * ll[0]);
                        let v_h = [v_u * inv_hz, v_v * inv_hz, -(v_u * u + v_v * v) * inv_hz];
                        let v_k = cross(ll, v_h);
                        let v_l = cross(v_h, kk);
                        for a in 0..3 {
                            row[ROW_TU + a] -= v_k[a];
                            row[ROW_TV + a] -= v_l[a];
                            row[ROW_TW + a] += pxf * v_k[a] + pyf * v_l[a];
                        }
                        row[ROW_TW] += u * v_z;
                        row[ROW_TW + 1] += v * v_z;
                        row[ROW_TW + 2] += v_z;
                    } else {
                        let dx = td.mx[li] - pxf;
                        let dy = td.my[li] - pyf;
                        row[ROW_MEAN2D] += 4.0 * dx * v_rho;
                        row[ROW_MEAN2D + 1] += 4.0 * dy * v_rho;
                        row[ROW_TW + 2] += v_z;
                    }
                }
            }
        }
    }
}
