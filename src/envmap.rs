//! Equirectangular (lat-long) environment maps in Blender's convention, world +z up:
//! for a unit direction d, u = 0.5 − atan2(d.y, d.x)/(2π), v = 1 − acos(d.z)/π, with u = 0 the
//! left column and v = 1 the top row. So +x is the centre column, +y is at u = 0.25 and the
//! zenith is the top row. Texel centres sit at (i + 0.5, j + 0.5) in pixel units.
//!
//! Lookup is bilinear (wrapping in u, clamped in v) with a backward pass to the texels.

use crate::error::{Error, Result};
use crate::io::image::{Image, read_rgba, write_image};
use std::f32::consts::PI;
use std::path::Path;

#[derive(Clone, Debug, PartialEq)]
pub struct EnvMap {
    pub width: usize,
    pub height: usize,
    /// Linear RGB radiance, row-major from the top row (zenith).
    pub texels: Vec<[f32; 3]>,
}

/// Bilinear footprint of a direction: four texel indices and weights.
#[derive(Clone, Copy, Debug)]
pub struct Footprint {
    pub index: [usize; 4],
    pub weight: [f32; 4],
}

/// A bilinear footprint stored compactly: top-left texel (x0, y0) and the fractions (tx, ty).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PackedFootprint {
    pub x0: u32,
    pub y0: u32,
    pub tx: f32,
    pub ty: f32,
}

/// The brightest texel a loaded map may hold (the sun in a real HDRI is ~1e5–1e9).
pub const MAX_RADIANCE: f32 = 1e15;

impl EnvMap {
    pub fn constant(width: usize, height: usize, rgb: [f32; 3]) -> EnvMap {
        EnvMap { width, height, texels: vec![rgb; width * height] }
    }

    /// Load a .hdr or .exr lat-long map (linear). Rejects non-finite values and values above
    /// [`MAX_RADIANCE`]; clamps
    /// negative ones to 0 with a warning.
    pub fn load(path: &Path) -> Result<EnvMap> {
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        if ext != "hdr" && ext != "exr" {
            return Err(Error::format(path, "extension", "environment maps must be .hdr or .exr (linear HDR)"));
        }
        let img = read_rgba(path)?;
        if img.width < 2 || img.height < 1 {
            return Err(Error::format(path, "size", format!("{}×{} is too small", img.width, img.height)));
        }
        // A lat-long map spans 360° by 180°: another shape is read over the whole sphere all
        // the same (stretched), which a cube-map cross or a cropped panorama is not.
        if img.width != 2 * img.height {
            tracing::warn!(
                "{}: size: {}×{} is not twice as wide as high; read as an equirectangular map over the whole \
                 sphere all the same (a cube map or a cropped panorama lights the scene wrongly)",
                path.display(),
                img.width,
                img.height
            );
        }
        let mut texels: Vec<[f32; 3]> = img.data.chunks_exact(4).map(|p| [p[0], p[1], p[2]]).collect();
        // Finite but absurd values (a float map's 3e38) overflow the shading's sums and priors.
        let brightest = texels.iter().flatten().fold(0.0f32, |m, v| m.max(*v));
        if brightest > MAX_RADIANCE {
            return Err(Error::format(
                path,
                "texels",
                format!(
                    "a value of {brightest:.3e} exceeds {MAX_RADIANCE:.0e} (no light is that bright; is the map scaled?)"
                ),
            ));
        }
        // Half-float maps filtered by their authors often carry tiny negative lobes: radiance
        // cannot be negative, so clamp them (and say so) rather than refuse the map.
        let negative = texels.iter().flatten().filter(|v| **v < 0.0).count();
        if negative > 0 {
            let worst = texels.iter().flatten().fold(0.0f32, |m, v| m.min(*v));
            tracing::warn!("{}: clamped {negative} negative values (min {worst:.3e}) to 0", path.display());
            texels.iter_mut().flatten().for_each(|v| *v = v.max(0.0));
        }
        Ok(EnvMap { width: img.width as usize, height: img.height as usize, texels })
    }

    /// Save as .exr or .hdr (by extension), atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut img = Image::new(self.width as u32, self.height as u32, 3);
        for (dst, src) in img.data.chunks_exact_mut(3).zip(&self.texels) {
            dst.copy_from_slice(src);
        }
        write_image(path, &img)
    }

    /// Continuous pixel coordinates (x right, y down from the top row) of a unit direction.
    pub fn dir_to_pixel(&self, d: [f32; 3]) -> (f32, f32) {
        let u = 0.5 - d[1].atan2(d[0]) / (2.0 * PI);
        let theta = d[2].clamp(-1.0, 1.0).acos();
        let u = u - u.floor();
        (u * self.width as f32, theta / PI * self.height as f32)
    }

    /// Unit direction through continuous pixel coordinates.
    pub fn pixel_to_dir(&self, x: f32, y: f32) -> [f32; 3] {
        let u = x / self.width as f32;
        let theta = y / self.height as f32 * PI;
        let phi = (0.5 - u) * 2.0 * PI;
        [theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()]
    }

    /// Direction of the centre of texel (i, j).
    pub fn texel_dir(&self, i: usize, j: usize) -> [f32; 3] {
        self.pixel_to_dir(i as f32 + 0.5, j as f32 + 0.5)
    }

    /// Solid angle of a texel in row j.
    pub fn texel_solid_angle(&self, j: usize) -> f32 {
        let t0 = j as f32 / self.height as f32 * PI;
        let t1 = (j + 1) as f32 / self.height as f32 * PI;
        2.0 * PI / self.width as f32 * (t0.cos() - t1.cos())
    }

    /// [`Self::dir_to_pixel`] through [`fast_atan2`] (≤ 2e-6 rad off, 0.001 texel on a
    /// 2048-wide map): the shading's lookups spent ~6 % of the inverse stage in libm's
    /// atan2f/acosf.
    pub fn dir_to_pixel_fast(&self, d: [f32; 3]) -> (f32, f32) {
        let u = 0.5 - fast_atan2(d[1], d[0]) / (2.0 * PI);
        let z = d[2].clamp(-1.0, 1.0);
        let theta = fast_atan2((1.0 - z * z).max(0.0).sqrt(), z);
        let u = u - u.floor();
        (u * self.width as f32, theta / PI * self.height as f32)
    }

    pub fn footprint(&self, d: [f32; 3]) -> Footprint {
        self.unpack(self.packed_footprint(d))
    }

    /// [`footprint`](Self::footprint) in 16 bytes (top-left texel, bilinear fractions): what a
    /// cache of fixed directions keeps so that every lookup of a changing map of this size
    /// skips the direction → pixel mapping (its atan2/acos).
    pub fn packed_footprint(&self, d: [f32; 3]) -> PackedFootprint {
        let (x, y) = self.dir_to_pixel_fast(d);
        let fx = x - 0.5;
        let fy = (y - 0.5).clamp(0.0, (self.height - 1) as f32);
        let x0 = fx.floor();
        let y0 = fy.floor().min((self.height - 1) as f32);
        PackedFootprint {
            x0: (x0 as i64).rem_euclid(self.width as i64) as u32,
            y0: y0 as u32,
            tx: fx - x0,
            ty: fy - y0,
        }
    }

    /// The full footprint of a packed one (made for a map of this size).
    #[inline]
    pub fn unpack(&self, p: PackedFootprint) -> Footprint {
        let (w, h) = (self.width, self.height);
        let (xi0, yi0) = (p.x0 as usize, p.y0 as usize);
        let xi1 = if xi0 + 1 == w { 0 } else { xi0 + 1 };
        let yi1 = (yi0 + 1).min(h - 1);
        let (tx, ty) = (p.tx, p.ty);
        Footprint {
            index: [yi0 * w + xi0, yi0 * w + xi1, yi1 * w + xi0, yi1 * w + xi1],
            weight: [(1.0 - tx) * (1.0 - ty), tx * (1.0 - ty), (1.0 - tx) * ty, tx * ty],
        }
    }

    /// Bilinear radiance of a packed footprint.
    #[inline]
    pub fn lookup_packed(&self, p: PackedFootprint) -> [f32; 3] {
        let fp = self.unpack(p);
        let mut c = [0.0f32; 3];
        for k in 0..4 {
            let t = self.texels[fp.index[k]];
            for ch in 0..3 {
                c[ch] += fp.weight[k] * t[ch];
            }
        }
        c
    }

    /// Bilinear radiance in direction d (unit).
    pub fn lookup(&self, d: [f32; 3]) -> [f32; 3] {
        self.lookup_packed(self.packed_footprint(d))
    }

    /// Backward of [`lookup`] with respect to the texels: adds into `v_texels`.
    pub fn lookup_backward(&self, d: [f32; 3], v_rgb: [f32; 3], v_texels: &mut [[f32; 3]]) {
        let fp = self.footprint(d);
        for k in 0..4 {
            for ch in 0..3 {
                v_texels[fp.index[k]][ch] += fp.weight[k] * v_rgb[ch];
            }
        }
    }

    /// Resample to width × height by area averaging (supersampled box filter).
    pub fn resample(&self, width: usize, height: usize) -> EnvMap {
        let sub = (self.width / width).clamp(1, 8) * 2;
        let mut out = EnvMap::constant(width, height, [0.0; 3]);
        for j in 0..height {
            for i in 0..width {
                let mut acc = [0.0f32; 3];
                let mut wsum = 0.0f32;
                for sj in 0..sub {
                    for si in 0..sub {
                        let x = (i as f32 + (si as f32 + 0.5) / sub as f32) / width as f32 * self.width as f32;
                        let y = (j as f32 + (sj as f32 + 0.5) / sub as f32) / height as f32 * self.height as f32;
                        let d = self.pixel_to_dir(x, y);
                        let w = (y / self.height as f32 * PI).sin().max(1e-6);
                        let c = self.lookup(d);
                        for ch in 0..3 {
                            acc[ch] += w * c[ch];
                        }
                        wsum += w;
                    }
                }
                out.texels[j * width + i] = acc.map(|v| v / wsum);
            }
        }
        out
    }

    /// The same light rotated by `degrees` about the world up axis (+z), counter-clockwise
    /// seen from above: a feature at azimuth φ moves to φ + degrees.
    pub fn rotated_about_up(&self, degrees: f32) -> EnvMap {
        let shift = degrees / 360.0 * self.width as f32;
        let mut out = self.clone();
        for j in 0..self.height {
            for i in 0..self.width {
                // u decreases as azimuth grows, so the new texel reads further right.
                let x = i as f32 + 0.5 + shift;
                let d = self.pixel_to_dir(x, j as f32 + 0.5);
                out.texels[j * self.width + i] = self.lookup(d);
            }
        }
        out
    }

    /// Solid-angle-weighted block average to (height / factor) × (width / factor): the light a
    /// sample direction stands for when S directions cover the hemisphere (prefiltering the
    /// env to the samples' footprint instead of point-sampling a sun). `factor` must divide
    /// both sizes; 1 returns a copy.
    pub fn box_downsample(&self, factor: usize) -> EnvMap {
        let f = factor.max(1);
        let (w, h) = (self.width / f, self.height / f);
        let mut out = EnvMap::constant(w, h, [0.0; 3]);
        for j in 0..h {
            let wsum: f32 = (0..f).map(|dj| self.texel_solid_angle(j * f + dj)).sum::<f32>() * f as f32;
            for i in 0..w {
                let mut acc = [0.0f32; 3];
                for dj in 0..f {
                    let sa = self.texel_solid_angle(j * f + dj);
                    for di in 0..f {
                        let t = self.texels[(j * f + dj) * self.width + i * f + di];
                        for c in 0..3 {
                            acc[c] += sa * t[c];
                        }
                    }
                }
                out.texels[j * w + i] = acc.map(|v| v / wsum.max(1e-20));
            }
        }
        out
    }

    /// Backward of [`box_downsample`](Self::box_downsample): adds ∂L/∂(full texels) for
    /// ∂L/∂(small texels) `v_small` into `v_full`.
    pub fn box_downsample_backward(&self, factor: usize, v_small: &[[f32; 3]], v_full: &mut [[f32; 3]]) {
        let f = factor.max(1);
        let (w, h) = (self.width / f, self.height / f);
        for j in 0..h {
            let wsum: f32 = (0..f).map(|dj| self.texel_solid_angle(j * f + dj)).sum::<f32>() * f as f32;
            for i in 0..w {
                let g = v_small[j * w + i];
                for dj in 0..f {
                    let k = self.texel_solid_angle(j * f + dj) / wsum.max(1e-20);
                    for di in 0..f {
                        let dst = &mut v_full[(j * f + dj) * self.width + i * f + di];
                        for c in 0..3 {
                            dst[c] += g[c] * k;
                        }
                    }
                }
            }
        }
    }

    /// A picture for people: each texel × `exposure`, sRGB-encoded and clipped (RGBA, α = 1).
    pub fn to_display_image(&self, exposure: f32) -> crate::io::image::Image {
        let mut img = crate::io::image::Image::new(self.width as u32, self.height as u32, 4);
        for (px, t) in img.data.chunks_exact_mut(4).zip(&self.texels) {
            for ch in 0..3 {
                px[ch] = crate::io::image::linear_to_srgb(t[ch] * exposure);
            }
            px[3] = 1.0;
        }
        img
    }

    /// Mean radiance weighted by solid angle (the irradiance-equivalent constant).
    pub fn mean_radiance(&self) -> [f32; 3] {
        let mut acc = [0.0f64; 3];
        let mut total = 0.0f64;
        for j in 0..self.height {
            let sa = self.texel_solid_angle(j) as f64;
            for i in 0..self.width {
                let t = self.texels[j * self.width + i];
                for ch in 0..3 {
                    acc[ch] += sa * t[ch] as f64;
                }
                total += sa;
            }
        }
        acc.map(|v| (v / total) as f32)
    }

    /// Unoccluded cosine-weighted irradiance over π for the unit normal `n`: the radiance a
    /// white Lambertian surface facing `n` reflects under this light alone,
    /// (1/π) ∫ L(ω) max(0, n·ω) dω, summed over the texels at their centre directions.
    pub fn lambert_radiance(&self, n: [f32; 3]) -> [f32; 3] {
        let mut acc = [0.0f64; 3];
        for j in 0..self.height {
            let sa = self.texel_solid_angle(j) as f64;
            for i in 0..self.width {
                let d = self.texel_dir(i, j);
                let cos = (d[0] * n[0] + d[1] * n[1] + d[2] * n[2]).max(0.0) as f64;
                if cos > 0.0 {
                    let t = self.texels[j * self.width + i];
                    for ch in 0..3 {
                        acc[ch] += sa * cos * t[ch] as f64;
                    }
                }
            }
        }
        acc.map(|v| (v / std::f64::consts::PI) as f32)
    }
}

/// The six axis normals ±x, ±y, ±z (world, z up) and their names, for comparing a recovered
/// light with the true one by [`EnvMap::lambert_radiance`].
pub const AXIS_NORMALS: [(&str, [f32; 3]); 6] = [
    ("+x", [1.0, 0.0, 0.0]),
    ("-x", [-1.0, 0.0, 0.0]),
    ("+y", [0.0, 1.0, 0.0]),
    ("-y", [0.0, -1.0, 0.0]),
    ("+z", [0.0, 0.0, 1.0]),
    ("-z", [0.0, 0.0, -1.0]),
];

/// atan2(y, x) in (−π, π] by a degree-11 odd minimax polynomial of atan on [0, 1] (max error
/// 1.9e-6 rad, checked against f64 in the tests); atan2(0, 0) = 0 like the libm.
#[inline]
pub fn fast_atan2(y: f32, x: f32) -> f32 {
    let (ax, ay) = (x.abs(), y.abs());
    let (lo, hi) = (ax.min(ay), ax.max(ay));
    if !(hi > 0.0) {
        // Both zero (or NaN): fall back to the libm's conventions.
        return y.atan2(x);
    }
    let a = lo / hi;
    let s = a * a;
    let mut r = a
        * (0.999_977_26
            + s * (-0.332_623_47 + s * (0.193_543_46 + s * (-0.116_432_87 + s * (0.052_653_32 - s * 0.011_721_20)))));
    if ay > ax {
        r = std::f32::consts::FRAC_PI_2 - r;
    }
    if x < 0.0 {
        r = PI - r;
    }
    if y < 0.0 || (y == 0.0 && y.is_sign_negative() && x < 0.0) { -r } else { r }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A finite but absurd texel is refused naming the file; the brightest plausible one loads.
    #[test]
    fn absurdly_bright_maps_are_refused() {
        let dir = crate::test_dir::TempDir::new("env-bright");
        let path = dir.join("bright.exr");
        let mut env = EnvMap::constant(8, 4, [1.0; 3]);
        env.texels[5] = [3e38, 1.0, 1.0];
        env.save(&path).unwrap();
        let err = EnvMap::load(&path).unwrap_err().to_string();
        assert!(err.contains("bright.exr") && err.contains("texels") && err.contains("exceeds"), "{err}");
        env.texels[5] = [1e9, 1.0, 1.0];
        env.save(&path).unwrap();
        assert_eq!(EnvMap::load(&path).unwrap().texels[5][0], 1e9);
        // An empty or cut-off file says so (it said "failed to fill whole buffer").
        std::fs::write(dir.join("empty.hdr"), b"").unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(dir.join("cut.exr"), &bytes[..bytes.len() / 2]).unwrap();
        let err = EnvMap::load(&dir.join("empty.hdr")).unwrap_err().to_string();
        assert!(err.contains("empty.hdr") && err.contains("ends early"), "{err}");
        let err = EnvMap::load(&dir.join("cut.exr")).unwrap_err().to_string();
        assert!(err.contains("cut.exr") && !err.contains("fill whole buffer"), "{err}");
    }

    #[test]
    fn box_downsample_keeps_the_mean_and_its_backward_is_the_transpose() {
        let mut env = EnvMap::constant(16, 8, [0.0; 3]);
        for (k, t) in env.texels.iter_mut().enumerate() {
            *t = [(k % 7) as f32, (k % 3) as f32 + 0.5, 1.0];
        }
        let small = env.box_downsample(4);
        assert_eq!((small.width, small.height), (4, 2));
        let (a, b) = (env.mean_radiance(), small.mean_radiance());
        for c in 0..3 {
            assert!((a[c] - b[c]).abs() < 1e-4, "{a:?} vs {b:?}");
        }
        // <v_small, D x> = <Dᵀ v_small, x> for the linear map D.
        let v_small: Vec<[f32; 3]> = (0..8).map(|k| [k as f32 * 0.3 - 1.0, 0.2, (k % 2) as f32]).collect();
        let mut v_full = vec![[0.0f32; 3]; env.texels.len()];
        env.box_downsample_backward(4, &v_small, &mut v_full);
        let lhs: f32 = small.texels.iter().zip(&v_small).map(|(x, v)| x[0] * v[0] + x[1] * v[1] + x[2] * v[2]).sum();
        let rhs: f32 = env.texels.iter().zip(&v_full).map(|(x, v)| x[0] * v[0] + x[1] * v[1] + x[2] * v[2]).sum();
        assert!((lhs - rhs).abs() < 1e-3 * lhs.abs().max(1.0), "{lhs} vs {rhs}");
    }

    #[test]
    fn lambert_radiance_matches_the_analytic_cases() {
        // A constant sky of radiance c: a white Lambertian surface reflects c whatever it faces.
        let c = [0.5f32, 1.0, 2.0];
        let env = EnvMap::constant(128, 64, c);
        for (name, n) in AXIS_NORMALS {
            let r = env.lambert_radiance(n);
            for ch in 0..3 {
                assert!((r[ch] - c[ch]).abs() < 2e-3 * c[ch], "{name}: {r:?} vs {c:?}");
            }
        }
        // The upper hemisphere alone (z > 0; the equator falls between texel rows): facing up
        // the full c, facing down nothing, facing sideways c/2, and c·(1 + sin 45°)/2 at 45°.
        let mut env = EnvMap::constant(128, 64, [0.0; 3]);
        for j in 0..32 {
            for i in 0..128 {
                env.texels[j * 128 + i] = [1.0; 3];
            }
        }
        let s = std::f32::consts::FRAC_1_SQRT_2;
        for (n, want) in [
            ([0.0, 0.0, 1.0], 1.0),
            ([0.0, 0.0, -1.0], 0.0),
            ([1.0, 0.0, 0.0], 0.5),
            ([0.0, -1.0, 0.0], 0.5),
            ([s, 0.0, s], (1.0 + s) / 2.0),
        ] {
            let r = env.lambert_radiance(n)[0];
            assert!((r - want).abs() < 3e-3, "n {n:?}: {r} vs {want}");
        }
        // A single bright texel: its solid angle × cos / π, nothing from behind.
        let mut env = EnvMap::constant(128, 64, [0.0; 3]);
        let (i, j) = (40, 20);
        env.texels[j * 128 + i] = [100.0; 3];
        let d = env.texel_dir(i, j);
        let want = 100.0 * env.texel_solid_angle(j) / std::f32::consts::PI;
        assert!((env.lambert_radiance(d)[1] - want).abs() < 1e-4 * want);
        assert_eq!(env.lambert_radiance(d.map(|x| -x))[1], 0.0);
    }

    #[test]
    fn fast_atan2_and_fast_pixels_match_the_libm() {
        let mut worst = 0.0f64;
        let n = 2000;
        for i in 0..n {
            for j in 0..n / 4 {
                let phi = i as f64 / n as f64 * std::f64::consts::TAU - std::f64::consts::PI;
                let r = 10f64.powf(j as f64 / (n / 4) as f64 * 6.0 - 3.0);
                let (y, x) = ((r * phi.sin()) as f32, (r * phi.cos()) as f32);
                let err = (fast_atan2(y, x) as f64 - (y as f64).atan2(x as f64)).abs();
                worst = worst.max(err);
            }
        }
        assert!(worst < 2e-5, "fast_atan2 off by {worst} rad");
        for (y, x) in [(0.0f32, 1.0f32), (0.0, -1.0), (1.0, 0.0), (-1.0, 0.0), (0.0, 0.0)] {
            assert!((fast_atan2(y, x) - y.atan2(x)).abs() < 1e-6, "atan2({y}, {x})");
        }
        let env = EnvMap::constant(2048, 1024, [1.0; 3]);
        for k in 0..5000 {
            let d = env.pixel_to_dir((k * 7919 % 2048) as f32 + 0.37, (k * 104729 % 1024) as f32 + 0.61);
            let (a, b) = (env.dir_to_pixel(d), env.dir_to_pixel_fast(d));
            let dx = (a.0 - b.0).abs().min(2048.0 - (a.0 - b.0).abs());
            assert!(dx < 0.01 && (a.1 - b.1).abs() < 0.01, "{d:?}: {a:?} vs {b:?}");
        }
    }

    #[test]
    fn blender_convention_axes() {
        let env = EnvMap::constant(128, 64, [1.0; 3]);
        let (x, _) = env.dir_to_pixel([1.0, 0.0, 0.0]);
        assert!((x - 64.0).abs() < 1e-3, "+x at the centre column");
        let (x, _) = env.dir_to_pixel([0.0, 1.0, 0.0]);
        assert!((x - 32.0).abs() < 1e-3, "+y at u = 0.25");
        let (_, y) = env.dir_to_pixel([0.0, 0.0, 1.0]);
        assert!(y.abs() < 1e-3, "zenith on the top row");
        for &(x, y) in &[(10.3f32, 5.5f32), (100.0, 40.2), (64.0, 32.0)] {
            let d = env.pixel_to_dir(x, y);
            let (x2, y2) = env.dir_to_pixel(d);
            assert!((x - x2).abs() < 1e-3 && (y - y2).abs() < 1e-3);
        }
    }

    #[test]
    fn lookup_backward_matches_fd_and_solid_angles_sum_to_sphere() {
        let mut env = EnvMap::constant(16, 8, [0.0; 3]);
        for (i, t) in env.texels.iter_mut().enumerate() {
            *t = [(i as f32 * 0.37).sin().abs(), 0.5, (i % 7) as f32];
        }
        let d = [0.3f32, -0.8, 0.52];
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        let d = d.map(|v| v / len);
        let mut v = vec![[0.0f32; 3]; env.texels.len()];
        env.lookup_backward(d, [1.0, 0.0, 0.0], &mut v);
        for k in 0..env.texels.len() {
            let mut e2 = env.clone();
            e2.texels[k][0] += 1.0;
            let fd = e2.lookup(d)[0] - env.lookup(d)[0];
            assert!((fd - v[k][0]).abs() < 1e-5);
        }
        let total: f32 = (0..8).map(|j| env.texel_solid_angle(j) * 16.0).sum();
        assert!((total - 4.0 * PI).abs() < 1e-4);
    }

    #[test]
    fn rotation_moves_azimuth() {
        let mut env = EnvMap::constant(64, 32, [0.0; 3]);
        // A bright texel at +x (centre column) near the horizon.
        env.texels[16 * 64 + 32] = [10.0; 3];
        let r = env.rotated_about_up(90.0);
        let at_y = r.lookup(r.pixel_to_dir(16.5, 16.5));
        assert!(at_y[0] > 5.0, "after 90°, the feature is at +y: {at_y:?}");
    }
}
