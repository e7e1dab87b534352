//! Per-surfel projection (forward and backward), after 2DGS.
//!
//! Maths: in camera space a surfel point is X(u, v) = c + u·a_u + v·a_v with c = R_wc μ + t,
//! a_u = R_wc t_u s_u, a_v = R_wc t_v s_v. Its pixel in homogeneous form is K·X, i.e.
//! M·(u, v, 1)ᵀ with M = K [a_u a_v c]; the rows of M are Tu, Tv, Tw (Tw = the z row, so
//! Tw·(u, v, 1) is the camera depth). A pixel (x, y) hits the plane at (u, v, 1) ∝
//! (x·Tw − Tu) × (y·Tw − Tv).
//!
//! Bounding box: the disk u² + v² ≤ r² (r² = 2 ln(o / α_min), where α falls to α_min) maps to
//! a conic with dual C* = M diag(r², r², −1) Mᵀ (scaled); its tangents x = const give the box
//! x_c ± sqrt(x_c² − C*00/C*22), x_c = C*02/C*22. When C*22 ≥ 0 the disk reaches the camera
//! plane and the box is the whole image. The screen-space filter (ρ₂ = f|μ₂D − pixel|²)
//! adds a circle of radius sqrt(r²/f) about μ₂D (f = `filter_inv_square`, 2DGS: 2). Culled: centre closer than `near`, back
//! faces (unless two-sided), opacity < α_min, boxes outside the image.
//!
//! Parallel decomposition: rayon over surfels. Saved for backward: M rows, μ₂D, opacity,
//! colour, signed normal, the sign (two-sided flip).

use super::{RasterSettings, TILE};
use crate::camera::Camera;
use crate::sh;
use crate::surfels::{Surfels, rotation_from_quat, rotation_from_quat_backward, sigmoid};
use glam::{Mat3, Vec3};
use rayon::prelude::*;

/// Projected surfels, structure of arrays (index = surfel index).
#[derive(Clone, Debug, Default)]
pub struct Projected {
    /// SH colour at the direction camera → centre (empty if colour is off; zero for surfels
    /// that are not drawn).
    pub colour: Vec<[f32; 3]>,
    /// World normal, flipped to face the camera in two-sided mode.
    pub normal: Vec<[f32; 3]>,
    /// +1 or −1: the flip applied to the normal.
    pub sign: Vec<f32>,
    /// Tile rectangle [tx0, ty0, tx1, ty1] (inclusive); tx0 > tx1 when culled.
    pub rect: Vec<[u32; 4]>,
    /// Camera depth of the centre (the tile sort key).
    pub depth: Vec<f32>,
    /// Larger half-extent of the pixel bounding box (0 = culled).
    pub radius: Vec<f32>,
    /// Pixels [x0, y0, x1, y1] (inclusive) whose centre lies in the α ≥ α_min bounding box
    /// grown by half a pixel (and 10⁻³ of its size) against rounding; [1, 1, 0, 0] when culled.
    /// A tile quarter lists only the candidates whose box reaches it (`forward::TileData`).
    pub pixels: Vec<[u32; 4]>,
    /// What the compositor evaluates per candidate, one cache line per surfel (lanes `PK_*`
    /// of `forward`: T_u, T_v, T_w, μ₂D, opacity, ρ cut-off, the pixel box's x and y ranges).
    /// The only copy of those fields: read them through the accessors below.
    pub packed: Vec<[f32; 16]>,
}

impl Projected {
    fn lanes3(&self, i: usize, at: usize) -> [f32; 3] {
        let r = &self.packed[i];
        [r[at], r[at + 1], r[at + 2]]
    }
    /// Row T_u of M (zero when culled).
    pub fn tu(&self, i: usize) -> [f32; 3] {
        self.lanes3(i, 0)
    }
    /// Row T_v of M.
    pub fn tv(&self, i: usize) -> [f32; 3] {
        self.lanes3(i, 3)
    }
    /// Row T_w of M (T_w · (u, v, 1) is the camera depth).
    pub fn tw(&self, i: usize) -> [f32; 3] {
        self.lanes3(i, 6)
    }
    /// Projected centre μ₂D in pixels.
    pub fn mean2d(&self, i: usize) -> [f32; 2] {
        [self.packed[i][9], self.packed[i][10]]
    }
    /// Opacity (0 when culled).
    pub fn opacity(&self, i: usize) -> f32 {
        self.packed[i][11]
    }
    /// Conservative ρ cut-off: 2 ln(o/α_min) plus a margin for rounding (∞ when α_min ≤ 0,
    /// −∞ when culled). ρ above it cannot give α ≥ α_min (see `forward::Candidates`).
    pub fn rho_max(&self, i: usize) -> f32 {
        self.packed[i][12]
    }
}

struct One {
    tu: [f32; 3],
    tv: [f32; 3],
    tw: [f32; 3],
    mean2d: [f32; 2],
    opacity: f32,
    normal: [f32; 3],
    sign: f32,
    rect: [u32; 4],
    depth: f32,
    radius: f32,
    pixels: [u32; 4],
    rho_max: f32,
}

const CULLED: [u32; 4] = [1, 1, 0, 0];

fn project_one(s: &Surfels, i: usize, cam: &Camera, campos: Vec3, settings: &RasterSettings) -> One {
    let mut out = One {
        tu: [0.0; 3],
        tv: [0.0; 3],
        tw: [0.0; 3],
        mean2d: [0.0; 2],
        opacity: 0.0,
        normal: [0.0; 3],
        sign: 1.0,
        rect: CULLED,
        depth: 0.0,
        radius: 0.0,
        pixels: CULLED,
        rho_max: f32::NEG_INFINITY,
    };
    let mu = Vec3::from(s.means[i]);
    let c = cam.rotation * mu + cam.translation;
    let o = sigmoid(s.opacity_logits[i]);
    if !(c.z >= settings.near) || !(o >= settings.alpha_min) || !mu.is_finite() {
        return out;
    }
    let r = rotation_from_quat(s.quats[i]);
    let n = Vec3::from(r[2]);
    let dir = mu - campos;
    // The sign of n·(X − o) is the same for every point X of the plane, so this per-surfel
    // test equals the per-ray test.
    let back = n.dot(dir) > 0.0;
    if back && !settings.two_sided {
        return out;
    }
    let sign = if back { -1.0 } else { 1.0 };
    let su = s.log_scales[i][0].exp();
    let sv = s.log_scales[i][1].exp();
    let au = cam.rotation * Vec3::from(r[0]) * su;
    let av = cam.rotation * Vec3::from(r[1]) * sv;
    let (fx, fy, cx, cy) = (cam.fx, cam.fy, cam.cx, cam.cy);
    let tu = [fx * au.x + cx * au.z, fx * av.x + cx * av.z, fx * c.x + cx * c.z];
    let tv = [fy * au.y + cy * au.z, fy * av.y + cy * av.z, fy * c.y + cy * c.z];
    let tw = [au.z, av.z, c.z];
    let mean2d = [tu[2] / tw[2], tv[2] / tw[2]];

    // Bounding box of the region where α ≥ α_min.
    let r2 = 2.0 * (o / settings.alpha_min).ln();
    let (w, h) = (cam.width as f32, cam.height as f32);
    let dot = |a: [f32; 3], b: [f32; 3]| r2 * (a[0] * b[0] + a[1] * b[1]) - a[2] * b[2];
    let c22 = dot(tw, tw);
    let (mut x0, mut x1, mut y0, mut y1);
    if c22 < 0.0 {
        let xc = dot(tu, tw) / c22;
        let yc = dot(tv, tw) / c22;
        let ex = (xc * xc - dot(tu, tu) / c22).max(0.0).sqrt();
        let ey = (yc * yc - dot(tv, tv) / c22).max(0.0).sqrt();
        x0 = xc - ex;
        x1 = xc + ex;
        y0 = yc - ey;
        y1 = yc + ey;
    } else {
        x0 = f32::NEG_INFINITY;
        x1 = f32::INFINITY;
        y0 = f32::NEG_INFINITY;
        y1 = f32::INFINITY;
    }
    // The filter circle f·|μ₂D − p|² ≤ r².
    let rf = (r2 / settings.filter_inv_square).sqrt();
    x0 = x0.min(mean2d[0] - rf);
    x1 = x1.max(mean2d[0] + rf);
    y0 = y0.min(mean2d[1] - rf);
    y1 = y1.max(mean2d[1] + rf);
    if x0.is_nan() || x1.is_nan() || y0.is_nan() || y1.is_nan() {
        return out;
    }
    // Pixels whose centre (p + 0.5) lies in the box.
    let px0 = (x0 - 0.5).ceil().max(0.0);
    let px1 = (x1 - 0.5).floor().min(w - 1.0);
    let py0 = (y0 - 0.5).ceil().max(0.0);
    let py1 = (y1 - 0.5).floor().min(h - 1.0);
    if px0 > px1 || py0 > py1 {
        return out;
    }
    let t = TILE as f32;
    let (gx, gy) = (0.5 + 1e-3 * (x1 - x0), 0.5 + 1e-3 * (y1 - y0));
    out.pixels = [
        (x0 - gx - 0.5).ceil().max(0.0) as u32,
        (y0 - gy - 0.5).ceil().max(0.0) as u32,
        (x1 + gx - 0.5).floor().min(w - 1.0) as u32,
        (y1 + gy - 0.5).floor().min(h - 1.0) as u32,
    ];
    out.rect = [(px0 / t) as u32, (py0 / t) as u32, (px1 / t) as u32, (py1 / t) as u32];
    out.radius = (0.5 * (x1 - x0)).max(0.5 * (y1 - y0)).min(1e9).max(0.5);
    out.tu = tu;
    out.tv = tv;
    out.tw = tw;
    out.mean2d = mean2d;
    out.opacity = o;
    out.normal = (n * sign).to_array();
    out.sign = sign;
    out.depth = c.z;
    // Computed once per surfel here, not per tile candidate (the ln showed in profiles).
    out.rho_max = if settings.alpha_min > 0.0 { r2 + r2.abs() * 1e-3 + 1e-3 } else { f32::INFINITY };
    out
}

/// The packed candidate record (`Projected::packed`).
fn pack(o: &One) -> [f32; 16] {
    let mut r = [0.0f32; 16];
    r[0..3].copy_from_slice(&o.tu);
    r[3..6].copy_from_slice(&o.tv);
    r[6..9].copy_from_slice(&o.tw);
    r[9..11].copy_from_slice(&o.mean2d);
    r[11] = o.opacity;
    r[12] = o.rho_max;
    // The pixel box as two u16 pairs (bit patterns, never used as numbers).
    let [x0, y0, x1, y1] = o.pixels.map(|v| v.min(u16::MAX as u32));
    r[13] = f32::from_bits(x0 | (x1 << 16));
    r[14] = f32::from_bits(y0 | (y1 << 16));
    r
}

/// Project every surfel (rayon over surfels).
pub fn project(surfels: &Surfels, camera: &Camera, settings: &RasterSettings) -> Projected {
    let campos = camera.position();
    let colour_on = settings.outputs.colour;
    let n = surfels.len();
    // Every slot is written below (each surfel's own), so the arrays start uninitialised: a
    // relit frame at 51k surfels zeroed ~8 MB per frame only to overwrite it.
    let mut colour = uninit_vec(if colour_on { n } else { 0 });
    let mut normal = uninit_vec(n);
    let mut sign = uninit_vec(n);
    let mut rect = uninit_vec(n);
    let mut depth = uninit_vec(n);
    let mut radius = uninit_vec(n);
    let mut pixels = uninit_vec(n);
    let mut packed = uninit_vec(n);
    let outputs = (normal.par_iter_mut(), sign.par_iter_mut(), rect.par_iter_mut(), depth.par_iter_mut());
    let more = (radius.par_iter_mut(), pixels.par_iter_mut(), packed.par_iter_mut());
    outputs.into_par_iter().zip(more.into_par_iter()).enumerate().for_each(
        |(i, ((normal, sign, rect, depth), (radius, pixels, packed)))| {
            let o = project_one(surfels, i, camera, campos, settings);
            normal.write(o.normal);
            sign.write(o.sign);
            rect.write(o.rect);
            depth.write(o.depth);
            radius.write(o.radius);
            pixels.write(o.pixels);
            packed.write(pack(&o));
        },
    );
    // SAFETY: the loop above wrote every slot of these (one per surfel index).
    let (normal, sign, rect, depth) =
        unsafe { (assume_init(normal), assume_init(sign), assume_init(rect), assume_init(depth)) };
    // SAFETY: as above.
    let (radius, pixels, packed) = unsafe { (assume_init(radius), assume_init(pixels), assume_init(packed)) };
    // SH colour (at the direction camera → centre) only for surfels that are drawn.
    colour.par_iter_mut().enumerate().for_each(|(i, c)| {
        c.write(if radius[i] > 0.0 {
            let dir = Vec3::from(surfels.means[i]) - campos;
            sh::eval(&surfels.sh[i], surfels.sh_degree, dir.to_array())
        } else {
            [0.0; 3]
        });
    });
    // SAFETY: every slot written just above.
    let colour = unsafe { assume_init(colour) };
    Projected { colour, normal, sign, rect, depth, radius, pixels, packed }
}

/// `n` slots to be written before [`assume_init`] (no zeroing pass).
fn uninit_vec<T>(n: usize) -> Vec<std::mem::MaybeUninit<T>> {
    let mut v = Vec::with_capacity(n);
    v.resize_with(n, std::mem::MaybeUninit::uninit);
    v
}

/// The vector of written slots.
///
/// # Safety
/// Every slot of `v` must have been written.
unsafe fn assume_init<T>(v: Vec<std::mem::MaybeUninit<T>>) -> Vec<T> {
    let mut v = std::mem::ManuallyDrop::new(v);
    // SAFETY: MaybeUninit<T> has T's layout; the caller guarantees every slot is initialised;
    // pointer, length and capacity come from a live Vec that is not dropped.
    unsafe { Vec::from_raw_parts(v.as_mut_ptr() as *mut T, v.len(), v.capacity()) }
}

/// Per-surfel gradients of the projected quantities (summed over pixels).
#[derive(Clone, Copy, Debug, Default)]
pub struct ProjGrad {
    pub v_tu: [f32; 3],
    pub v_tv: [f32; 3],
    pub v_tw: [f32; 3],
    pub v_mean2d: [f32; 2],
    pub v_opacity: f32,
    pub v_colour: [f32; 3],
    pub v_normal: [f32; 3],
}

/// Backward of [`project_one`] for a drawn surfel: adds into `v` (one surfel's slots of the
/// gradient buffer) and returns the 2DGS densification gradient (see `BackwardOutput`).
pub fn project_backward_one(
    s: &Surfels,
    i: usize,
    cam: &Camera,
    campos: Vec3,
    p: &Projected,
    g: &ProjGrad,
    v: SurfelGradSlots<'_>,
) -> [f32; 2] {
    let mut v_tu = Vec3::from(g.v_tu);
    let mut v_tv = Vec3::from(g.v_tv);
    let mut v_tw = Vec3::from(g.v_tw);
    let (tu, tv, tw) = (p.tu(i), p.tv(i), p.tw(i));
    // μ₂D = (Tu.z / Tw.z, Tv.z / Tw.z).
    let iz = 1.0 / tw[2];
    v_tu.z += g.v_mean2d[0] * iz;
    v_tv.z += g.v_mean2d[1] * iz;
    v_tw.z -= (g.v_mean2d[0] * tu[2] + g.v_mean2d[1] * tv[2]) * iz * iz;
    let v_mean2d_ndc = [v_tu.z * tw[2] * 0.5 * cam.width as f32, v_tv.z * tw[2] * 0.5 * cam.height as f32];

    // M = K [a_u a_v c]: column j of [a_u a_v c] gets (fx v_Tu_j, fy v_Tv_j, cx v_Tu_j + cy v_Tv_j + v_Tw_j).
    let (fx, fy, cx, cy) = (cam.fx, cam.fy, cam.cx, cam.cy);
    let col = |j: usize| Vec3::new(fx * v_tu[j], fy * v_tv[j], cx * v_tu[j] + cy * v_tv[j] + v_tw[j]);
    let (v_au, v_av, v_c) = (col(0), col(1), col(2));
    let r = rotation_from_quat(s.quats[i]);
    let su = s.log_scales[i][0].exp();
    let sv = s.log_scales[i][1].exp();
    let rt: Mat3 = cam.rotation.transpose();
    let v_tu_world = rt * v_au * su;
    let v_tv_world = rt * v_av * sv;
    let tu_cam = cam.rotation * Vec3::from(r[0]);
    let tv_cam = cam.rotation * Vec3::from(r[1]);
    v.log_scales[0] += su * tu_cam.dot(v_au);
    v.log_scales[1] += sv * tv_cam.dot(v_av);
    let mut v_mu = rt * v_c;
    let v_n = Vec3::from(g.v_normal) * p.sign[i];
    let v_q = rotation_from_quat_backward(s.quats[i], [v_tu_world.to_array(), v_tv_world.to_array(), v_n.to_array()]);
    for k in 0..4 {
        v.quats[k] += v_q[k];
    }
    let o = p.opacity(i);
    *v.opacity_logit += o * (1.0 - o) * g.v_opacity;
    if !p.colour.is_empty() && g.v_colour != [0.0; 3] {
        let dir = Vec3::from(s.means[i]) - campos;
        let v_dir = sh::eval_backward(&s.sh[i], s.sh_degree, dir.to_array(), g.v_colour, v.sh);
        v_mu += Vec3::from(v_dir);
    }
    for k in 0..3 {
        v.means[k] += v_mu[k];
    }
    v_mean2d_ndc
}

/// Mutable views of one surfel's gradient entries.
pub struct SurfelGradSlots<'a> {
    pub means: &'a mut [f32; 3],
    pub log_scales: &'a mut [f32; 2],
    pub quats: &'a mut [f32; 4],
    pub opacity_logit: &'a mut f32,
    pub sh: &'a mut [[f32; 3]; sh::SH_COEFFS],
}
