//! Brute-force reference rasteriser in f64, written separately from the fast path (test only).
//!
//! Per pixel: the ray through the pixel centre is intersected with every surfel's plane the
//! DESIGN way (t = n·(μ − o)/(n·d), p = o + t d − μ, u = t_u·p/s_u, v = t_v·p/s_v), the 2DGS
//! screen-space fallback ρ₂ = f|μ₂D − pixel|² (f = `filter_inv_square`) is applied, the hits are ordered (all by depth,
//! centre-depth order, or the K-window simulated with a plain Vec), then composited. The
//! distortion is the direct double sum. No tiles, no bounding boxes.

use super::RasterSettings;
use crate::camera::Camera;
use crate::surfels::Surfels;

/// A scene in f64 (so finite differences can use tiny steps).
#[derive(Clone, Debug)]
pub struct RefScene {
    pub means: Vec<[f64; 3]>,
    pub log_scales: Vec<[f64; 2]>,
    pub quats: Vec<[f64; 4]>,
    pub opacity_logits: Vec<f64>,
    pub sh: Vec<[[f64; 3]; 16]>,
    pub sh_degree: u32,
    pub features: Vec<f64>,
    pub channels: usize,
}

impl RefScene {
    pub fn from_surfels(s: &Surfels, features: Option<(&[f32], usize)>) -> RefScene {
        RefScene {
            means: s.means.iter().map(|m| m.map(|v| v as f64)).collect(),
            log_scales: s.log_scales.iter().map(|m| m.map(|v| v as f64)).collect(),
            quats: s.quats.iter().map(|m| m.map(|v| v as f64)).collect(),
            opacity_logits: s.opacity_logits.iter().map(|&v| v as f64).collect(),
            sh: s.sh.iter().map(|c| c.map(|r| r.map(|v| v as f64))).collect(),
            sh_degree: s.sh_degree,
            features: features.map_or(vec![], |(f, _)| f.iter().map(|&v| v as f64).collect()),
            channels: features.map_or(0, |(_, c)| c),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Order {
    /// Every hit sorted by its own depth.
    Full,
    /// Hits in centre-depth order (plain 2DGS).
    Centre,
    /// The K-entry sorted window.
    Window(usize),
}

#[derive(Clone, Debug, Default)]
pub struct RefOut {
    pub colour: Vec<[f64; 3]>,
    pub alpha: Vec<f64>,
    pub depth: Vec<f64>,
    pub median: Vec<f64>,
    pub normal: Vec<[f64; 3]>,
    pub distortion: Vec<f64>,
    pub features: Vec<f64>,
    pub surface_depth: Vec<f64>,
    /// Largest number of hits at one pixel.
    pub max_hits: usize,
}

fn sh_basis(d: [f64; 3]) -> [f64; 16] {
    let (x, y, z) = (d[0], d[1], d[2]);
    let c1 = 0.4886025119029199;
    [
        0.28209479177387814,
        -c1 * y,
        c1 * z,
        -c1 * x,
        1.0925484305920792 * x * y,
        -1.0925484305920792 * y * z,
        0.31539156525252005 * (2.0 * z * z - x * x - y * y),
        -1.0925484305920792 * x * z,
        0.5462742152960396 * (x * x - y * y),
        -0.5900435899266435 * y * (3.0 * x * x - y * y),
        2.890611442640554 * x * y * z,
        -0.4570457994644658 * y * (4.0 * z * z - x * x - y * y),
        0.3731763325901154 * z * (2.0 * z * z - 3.0 * x * x - 3.0 * y * y),
        -0.4570457994644658 * x * (4.0 * z * z - x * x - y * y),
        1.445305721320277 * z * (x * x - y * y),
        -0.5900435899266435 * x * (x * x - 3.0 * y * y),
    ]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

struct Surf {
    mu: [f64; 3],
    tu: [f64; 3],
    tv: [f64; 3],
    n: [f64; 3],
    su: f64,
    sv: f64,
    o: f64,
    cz: f64,
    m2d: [f64; 2],
    colour: [f64; 3],
    index: usize,
}

struct RHit {
    z: f64,
    alpha: f64,
    s: usize,
}

pub fn render_ref(scene: &RefScene, cam: &Camera, set: &RasterSettings, order: Order) -> RefOut {
    let rot: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| cam.rotation.col(c)[r] as f64));
    let tr = [cam.translation.x as f64, cam.translation.y as f64, cam.translation.z as f64];
    let (fx, fy, cx, cy) = (cam.fx as f64, cam.fy as f64, cam.cx as f64, cam.cy as f64);
    // Camera centre o = −Rᵀ t.
    let org: [f64; 3] = std::array::from_fn(|a| -(0..3).map(|r| rot[r][a] * tr[r]).sum::<f64>());
    let to_cam = |p: [f64; 3]| -> [f64; 3] { std::array::from_fn(|r| dot(rot[r], p) + tr[r]) };
    let near = set.near as f64;
    let amin = set.alpha_min as f64;
    let mut surfs = Vec::new();
    for i in 0..scene.means.len() {
        let mu = scene.means[i];
        let c = to_cam(mu);
        let o = 1.0 / (1.0 + (-scene.opacity_logits[i]).exp());
        if c[2] < near || o < amin {
            continue;
        }
        let q = scene.quats[i];
        let l = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
        let (w, x, y, z) = (q[0] / l, q[1] / l, q[2] / l, q[3] / l);
        let m = [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
            [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
            [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
        ];
        let col = |k: usize| [m[0][k], m[1][k], m[2][k]];
        let mut n = col(2);
        let view = [mu[0] - org[0], mu[1] - org[1], mu[2] - org[2]];
        if dot(n, view) > 0.0 {
            if !set.two_sided {
                continue;
            }
            n = n.map(|v| -v);
        }
        let vl = dot(view, view).sqrt();
        let b = sh_basis(view.map(|v| v / vl));
        let mut colour = [0.5; 3];
        let nc = ((scene.sh_degree.min(3) + 1) * (scene.sh_degree.min(3) + 1)) as usize;
        for k in 0..nc {
            for ch in 0..3 {
                colour[ch] += scene.sh[i][k][ch] * b[k];
            }
        }
        surfs.push(Surf {
            mu,
            tu: col(0),
            tv: col(1),
            n,
            su: scene.log_scales[i][0].exp(),
            sv: scene.log_scales[i][1].exp(),
            o,
            cz: c[2],
            m2d: [fx * c[0] / c[2] + cx, fy * c[1] / c[2] + cy],
            colour: colour.map(|v| v.max(0.0)),
            index: i,
        });
    }
    // Arrival order: centre depth, then index.
    surfs.sort_by(|a, b| a.cz.total_cmp(&b.cz).then(a.index.cmp(&b.index)));
    let (wd, ht) = (cam.width as usize, cam.height as usize);
    let nch = scene.channels;
    let mut out = RefOut {
        colour: vec![[0.0; 3]; wd * ht],
        alpha: vec![0.0; wd * ht],
        depth: vec![0.0; wd * ht],
        median: vec![0.0; wd * ht],
        normal: vec![[0.0; 3]; wd * ht],
        distortion: vec![0.0; wd * ht],
        features: vec![0.0; wd * ht * nch],
        surface_depth: vec![0.0; wd * ht],
        max_hits: 0,
    };
    let (near_f, far_f) = (set.near as f64, set.far as f64);
    let mnorm = |z: f64| far_f / (far_f - near_f) * (1.0 - near_f / z);
    for py in 0..ht {
        for px in 0..wd {
            let (pxf, pyf) = (px as f64 + 0.5, py as f64 + 0.5);
            let dc = [(pxf - cx) / fx, (pyf - cy) / fy, 1.0];
            let d: [f64; 3] = std::array::from_fn(|a| (0..3).map(|r| rot[r][a] * dc[r]).sum());
            let mut hits = Vec::new();
            for (si, s) in surfs.iter().enumerate() {
                let den = dot(s.n, d);
                if den == 0.0 {
                    continue;
                }
                let t = dot(s.n, [s.mu[0] - org[0], s.mu[1] - org[1], s.mu[2] - org[2]]) / den;
                let p = [org[0] + t * d[0] - s.mu[0], org[1] + t * d[1] - s.mu[1], org[2] + t * d[2] - s.mu[2]];
                let u = dot(s.tu, p) / s.su;
                let v = dot(s.tv, p) / s.sv;
                let rho3 = u * u + v * v;
                let rho2 = set.filter_inv_square as f64 * ((s.m2d[0] - pxf).powi(2) + (s.m2d[1] - pyf).powi(2));
                // d has camera z = 1, so the hit's camera depth is t.
                let (rho, z) = if rho3 <= rho2 { (rho3, t) } else { (rho2, s.cz) };
                if z < near {
                    continue;
                }
                let alpha = (s.o * (-0.5 * rho).exp()).min(0.99);
                if alpha < amin {
                    continue;
                }
                hits.push(RHit { z, alpha, s: si });
            }
            out.max_hits = out.max_hits.max(hits.len());
            let seq: Vec<RHit> = match order {
                Order::Full => {
                    hits.sort_by(|a, b| a.z.total_cmp(&b.z));
                    hits
                }
                Order::Centre => hits,
                Order::Window(k) => {
                    let mut win: Vec<RHit> = Vec::new();
                    let mut seq = Vec::new();
                    let take_nearest = |win: &mut Vec<RHit>| {
                        let mut best = 0;
                        for (j, h) in win.iter().enumerate() {
                            if h.z < win[best].z {
                                best = j;
                            }
                        }
                        win.remove(best)
                    };
                    for h in hits {
                        if win.len() == k.max(1) {
                            seq.push(take_nearest(&mut win));
                        }
                        win.push(h);
                    }
                    while !win.is_empty() {
                        seq.push(take_nearest(&mut win));
                    }
                    seq
                }
            };
            let pix = py * wd + px;
            let mut t = 1.0f64;
            let mut blended: Vec<(f64, f64)> = Vec::new(); // (weight, z)
            let mut median = None;
            for h in &seq {
                let next = t * (1.0 - h.alpha);
                if next < set.transmittance_min as f64 {
                    break;
                }
                let w = h.alpha * t;
                let s = &surfs[h.s];
                for ch in 0..3 {
                    out.colour[pix][ch] += w * s.colour[ch];
                    out.normal[pix][ch] += w * s.n[ch];
                }
                for ch in 0..nch {
                    out.features[pix * nch + ch] += w * scene.features[s.index * nch + ch];
                }
                blended.push((w, h.z));
                if median.is_none() && next <= 0.5 {
                    median = Some(h.z);
                }
                t = next;
                if next < set.display_stop as f64 {
                    break;
                }
            }
            if median.is_none() {
                median = blended.last().map(|b| b.1);
            }
            for ch in 0..3 {
                out.colour[pix][ch] += t * set.background[ch] as f64;
            }
            let a = 1.0 - t;
            out.alpha[pix] = a;
            let dsum: f64 = blended.iter().map(|(w, z)| w * z).sum();
            out.depth[pix] = if a > 0.0 { dsum / a } else { 0.0 };
            out.median[pix] = median.unwrap_or(0.0);
            let mut dist = 0.0;
            for i in 0..blended.len() {
                for j in 0..i {
                    dist += blended[i].0 * blended[j].0 * (mnorm(blended[i].1) - mnorm(blended[j].1)).powi(2);
                }
            }
            out.distortion[pix] = dist;
            out.surface_depth[pix] = surface_depth(&blended);
        }
    }
    out
}

/// GauS-SLAM's surface-aware depth from a pixel's blended (w, z) list, written from the
/// definition: the running median d_m(i) is the z of the last hit j ≤ i blended while
/// T_j > 0.5; σ²(i) the w-weighted mean of (ẑ_j − d_m(i))² over j < i (≥ 1e-7), summed
/// directly rather than by the fast path's Σ w ẑ / Σ w ẑ² recurrence.
fn surface_depth(blended: &[(f64, f64)]) -> f64 {
    let mut t = 1.0;
    let mut dm = 0.0;
    let mut zhat: Vec<f64> = Vec::with_capacity(blended.len());
    for (i, &(w, z)) in blended.iter().enumerate() {
        if t > 0.5 {
            dm = z;
        }
        let zh = if i == 0 {
            z
        } else {
            let wsum: f64 = blended[..i].iter().map(|b| b.0).sum();
            let spread: f64 = (0..i).map(|j| blended[j].0 * (zhat[j] - dm).powi(2)).sum();
            let var = (spread / wsum).max(1e-7);
            let conf = (-(z - dm).powi(2) / (4.0 * var)).exp();
            conf * z + (1.0 - conf) * dm
        };
        zhat.push(zh);
        // T before the next hit: w = α T.
        t -= w;
    }
    let a: f64 = blended.iter().map(|b| b.0).sum();
    if a > 0.0 { blended.iter().zip(&zhat).map(|(b, zh)| b.0 * zh).sum::<f64>() / a } else { 0.0 }
}
