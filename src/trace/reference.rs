//! Brute-force reference tracer in f64, written apart from the fast path: intersect every
//! surfel, sort the valid hits by (t, index), composite front to back with the same stopping
//! rule. Also reports whether a ray sits near a discontinuity (α ≈ 1/255, T ≈ min_T, near
//! ties, grazing), where f32 and f64 may legitimately disagree.

use crate::surfels::Surfels;
use crate::trace::{ALPHA_MAX, ALPHA_MIN, Ray, TraceSettings};

#[derive(Clone, Copy, Debug)]
pub struct RefHit {
    pub t: f64,
    pub index: usize,
    pub alpha: f64,
    /// Unclamped o·G and the disk radius test value ρ = u² + v².
    pub raw: f64,
    pub rho: f64,
    pub cos: f64,
}

#[derive(Clone, Debug, Default)]
pub struct RefOutput {
    pub radiance: [f64; 3],
    pub transmittance: f64,
    pub depth: f64,
    pub normal: [f64; 3],
    pub features: Vec<f64>,
    pub hits: Vec<usize>,
    /// Near a threshold where f32 rounding can change the hit set or order.
    pub fragile: bool,
}

fn rot64(q: [f32; 4]) -> [[f64; 3]; 3] {
    let q = q.map(|x| x as f64);
    let l = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let (w, x, y, z) = (q[0] / l, q[1] / l, q[2] / l, q[3] / l);
    // Columns t_u, t_v, n of the rotation matrix R(q).
    let r = [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ];
    [[r[0][0], r[1][0], r[2][0]], [r[0][1], r[1][1], r[2][1]], [r[0][2], r[1][2], r[2][2]]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Every surfel's intersection with the ray (valid or not) in f64: (index, t, ρ, raw, cos).
pub fn all_hits(s: &Surfels, ray: &Ray, settings: &TraceSettings) -> Vec<(RefHit, bool)> {
    let o = ray.origin.map(|x| x as f64);
    let d = ray.dir.map(|x| x as f64);
    let mut v = Vec::new();
    for i in 0..s.len() {
        let r = rot64(s.quats[i]);
        let n = r[2];
        let b = dot(n, d);
        let mu = s.means[i].map(|x| x as f64);
        let t = dot(n, [mu[0] - o[0], mu[1] - o[1], mu[2] - o[2]]) / b;
        let p = [o[0] + t * d[0] - mu[0], o[1] + t * d[1] - mu[1], o[2] + t * d[2] - mu[2]];
        let u = dot(r[0], p) / (s.log_scales[i][0] as f64).exp();
        let vv = dot(r[1], p) / (s.log_scales[i][1] as f64).exp();
        let rho = u * u + vv * vv;
        let op = 1.0 / (1.0 + (-(s.opacity_logits[i] as f64)).exp());
        let raw = op * (-0.5 * rho).exp();
        let alpha = raw.min(ALPHA_MAX as f64);
        let occluder = !settings.two_sided && settings.back_occluders.as_ref().is_some_and(|f| f[i]);
        // One-sided: back faces within the grazing tolerance count too (b < |d| sin γ).
        let graze = settings.grazing_sin as f64 * dot(d, d).sqrt();
        let facing =
            (b < 0.0 || (!settings.two_sided && b > 0.0 && b < graze)) || ((settings.two_sided || occluder) && b > 0.0);
        let sk = ray.skip_below.map(|x| x as f64);
        // A zero normal is no plane (whatever its offset), as in the fast path.
        let plane = sk[0] != 0.0 || sk[1] != 0.0 || sk[2] != 0.0;
        let skipped = plane && dot([sk[0], sk[1], sk[2]], mu) < sk[3];
        let valid = facing
            && !skipped
            && t.is_finite()
            && t > settings.t_min as f64
            && t <= settings.t_max as f64
            && alpha >= ALPHA_MIN as f64;
        v.push((RefHit { t, index: i, alpha, raw, rho, cos: b }, valid));
    }
    v
}

/// Composite one ray by brute force. `features`: surfels × channels.
pub fn trace_ref(s: &Surfels, ray: &Ray, settings: &TraceSettings, features: Option<(&[f32], usize)>) -> RefOutput {
    let all = all_hits(s, ray, settings);
    let graze = settings.grazing_sin as f64 * ray.dir.map(|x| x as f64).iter().map(|x| x * x).sum::<f64>().sqrt();
    let mut fragile = false;
    for (h, _) in &all {
        let rel = |a: f64, b: f64| (a - b).abs() <= 1e-4 * b.abs().max(1e-6);
        if rel(h.alpha, ALPHA_MIN as f64)
            || rel(h.raw, ALPHA_MAX as f64)
            || (h.t - settings.t_min as f64).abs() < 1e-5
            || (h.cos.abs() < 1e-5)
            || (settings.grazing_sin > 0.0 && (h.cos - graze).abs() < 1e-5)
        {
            fragile = true;
        }
    }
    let mut hits: Vec<RefHit> = all.into_iter().filter(|(_, ok)| *ok).map(|(h, _)| h).collect();
    hits.sort_by(|a, b| a.t.total_cmp(&b.t).then(a.index.cmp(&b.index)));
    for w in hits.windows(2) {
        let dt = (w[1].t - w[0].t).abs();
        if dt > 0.0 && dt < 1e-5 * (1.0 + w[0].t.abs()) {
            fragile = true;
        }
    }
    let d = ray.dir.map(|x| x as f64);
    let dl = dot(d, d).sqrt();
    let dh = d.map(|x| x / dl);
    let mut out = RefOutput { transmittance: 1.0, ..Default::default() };
    if let Some((_, ch)) = features {
        out.features = vec![0.0; ch];
    }
    let min_t = settings.min_transmittance as f64;
    for h in hits {
        let i = h.index;
        let w = out.transmittance * h.alpha;
        let dark = h.cos > 0.0
            && if settings.two_sided {
                settings.dark_back_faces
            } else {
                settings.back_occluders.as_ref().is_some_and(|f| f[i])
            };
        match features {
            _ if dark => {}
            Some((f, ch)) => {
                for c in 0..ch {
                    out.features[c] += w * f[i * ch + c] as f64;
                }
            }
            None => {
                let col = sh_ref(&s.sh[i], s.sh_degree, dh);
                for c in 0..3 {
                    out.radiance[c] += w * if settings.linear_radiance { srgb_eotf(col[c]) } else { col[c] };
                }
            }
        }
        out.depth += w * h.t;
        let n = rot64(s.quats[i])[2];
        let sign = if h.cos > 0.0 { -1.0 } else { 1.0 };
        for a in 0..3 {
            out.normal[a] += w * sign * n[a];
        }
        out.hits.push(i);
        out.transmittance *= 1.0 - h.alpha;
        if (out.transmittance - min_t).abs() < 1e-4 * min_t.max(1e-6) {
            fragile = true;
        }
        if out.transmittance < min_t {
            break;
        }
    }
    out.fragile = fragile;
    out
}

/// SH colour max(Σ c_k Y_k(d) + 0.5, 0) in f64, basis written out independently.
/// The sRGB EOTF in f64, written here independently of the tracer's.
fn srgb_eotf(c: f64) -> f64 {
    if c <= 0.04045 { c / 12.92 } else { ((c + 0.055) / 1.055).powf(2.4) }
}

fn sh_ref(c: &[[f32; 3]; 16], degree: u32, d: [f64; 3]) -> [f64; 3] {
    let [x, y, z] = d;
    let y_k = [
        0.28209479177387814,
        -0.4886025119029199 * y,
        0.4886025119029199 * z,
        -0.4886025119029199 * x,
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
    ];
    let m = ((degree.min(3) + 1) * (degree.min(3) + 1)) as usize;
    let mut out = [0.5f64; 3];
    for k in 0..m {
        for ch in 0..3 {
            out[ch] += c[k][ch] as f64 * y_k[k];
        }
    }
    out.map(|v| v.max(0.0))
}
