//! Writing a dataset: orbit cameras, the per-view folders (TensoIR layout, `metadata.json`),
//! `transforms_{train,test}.json` (Blender/NeRF layout), every GT pass of the test views, the
//! relit renders, the env maps and README.json.

use super::envlight::EnvLight;
use super::integrator::{PixelOut, RenderOptions, render};
use super::scene::{CameraRig, Scene};
use crate::camera::Camera;
use crate::io::atomic::write_atomic;
use crate::io::image::{Image, linear_to_srgb, write_image};
use glam::Vec3;
use std::path::Path;

/// Train cameras: stratified uniform-solid-angle band (uniform in sin(elevation)) with
/// golden-angle azimuth; test cameras: seeded uniform random in the same band.
pub fn cameras(rig: &CameraRig, n: usize, res: u32, test: bool, seed: u64) -> Vec<Camera> {
    let (s0, s1) = (rig.elev_min.to_radians().sin(), rig.elev_max.to_radians().sin());
    let golden = 180.0 * (3.0 - 5f32.sqrt());
    let mut rng = super::sampling::pixel_rng(seed, 0xCA3E_0000 + test as u64, 0);
    (0..n)
        .map(|i| {
            let (z, az) = if test {
                let a = super::sampling::uniform(&mut rng);
                let b = super::sampling::uniform(&mut rng);
                (s0 + a * (s1 - s0), rig.az_min + b * (rig.az_max - rig.az_min))
            } else {
                let z = s0 + (i as f32 + 0.5) / n as f32 * (s1 - s0);
                (z, rig.az_min + (i as f32 * golden).rem_euclid(rig.az_max - rig.az_min))
            };
            let el = z.clamp(-1.0, 1.0).asin();
            let az = az.to_radians();
            let eye = rig.target + rig.radius * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
            let name = format!("{}_{i:03}", if test { "test" } else { "train" });
            Camera::look_at(name, eye, rig.target, res, res, rig.camera_angle_x)
        })
        .collect()
}

fn pretty(v: &serde_json::Value) -> Vec<u8> {
    let mut buf = Vec::new();
    let fmt = serde_json::ser::PrettyFormatter::with_indent(b" ");
    let mut ser = serde_json::Serializer::with_formatter(&mut buf, fmt);
    serde::Serialize::serialize(v, &mut ser).expect("JSON values always serialise");
    buf
}

pub fn write_json(path: &Path, v: &serde_json::Value) -> crate::Result<()> {
    write_atomic(path, &pretty(v))
}

pub fn metadata(cam: &Camera, env: &str, spp: u32) -> serde_json::Value {
    let m = cam.to_blender_rows();
    let s: Vec<String> = m.iter().flatten().map(|v| format!("{v:.8}")).collect();
    serde_json::json!({
        "cam_transform_mat": s.join(","),
        "cam_angle_x": cam.fov_x(),
        "imh": cam.height,
        "imw": cam.width,
        "envmap": env,
        "spp": spp,
        "convention": "blender_camera_to_world",
    })
}

fn img(w: u32, h: u32, c: usize, px: &[PixelOut], f: impl Fn(&PixelOut, &mut [f32])) -> Image {
    let mut im = Image::new(w, h, c);
    for (dst, p) in im.data.chunks_exact_mut(c).zip(px) {
        f(p, dst);
    }
    im
}

/// rgba.png: sRGB 8-bit, straight alpha, transparent background.
pub fn rgba_png(cam: &Camera, px: &[PixelOut]) -> Image {
    img(cam.width, cam.height, 4, px, |p, d| {
        if p.alpha > 0.0 {
            for k in 0..3 {
                d[k] = linear_to_srgb(p.rgb[k]);
            }
        }
        d[3] = p.alpha;
    })
}

/// Write every GT pass of a test view.
pub fn write_test_passes(dir: &Path, cam: &Camera, px: &[PixelOut]) -> crate::Result<()> {
    let (w, h) = (cam.width, cam.height);
    write_image(&dir.join("rgba.png"), &rgba_png(cam, px))?;
    write_image(
        &dir.join("albedo.png"),
        &img(w, h, 4, px, |p, d| {
            for k in 0..3 {
                d[k] = if p.alpha > 0.0 { linear_to_srgb(p.albedo[k]) } else { 0.0 };
            }
            d[3] = p.alpha;
        }),
    )?;
    write_image(
        &dir.join("normal.png"),
        &img(w, h, 4, px, |p, d| {
            for k in 0..3 {
                d[k] = if p.alpha > 0.0 { p.normal[k] * 0.5 + 0.5 } else { 0.0 };
            }
            d[3] = p.alpha;
        }),
    )?;
    write_image(
        &dir.join("normal.exr"),
        &img(w, h, 4, px, |p, d| {
            d[..3].copy_from_slice(&p.normal.to_array());
            d[3] = p.alpha;
        }),
    )?;
    write_image(
        &dir.join("roughness.png"),
        &img(w, h, 2, px, |p, d| {
            d[0] = p.roughness;
            d[1] = p.alpha;
        }),
    )?;
    write_image(
        &dir.join("depth.exr"),
        &img(w, h, 4, px, |p, d| {
            d[..3].fill(p.depth);
            d[3] = p.alpha;
        }),
    )?;
    for (name, get) in [("indirect.exr", 0), ("direct.exr", 1)] {
        write_image(
            &dir.join(name),
            &img(w, h, 4, px, |p, d| {
                let v = if get == 0 { p.indirect } else { p.direct };
                d[..3].copy_from_slice(&v.to_array());
                d[3] = p.alpha;
            }),
        )?;
    }
    Ok(())
}

/// Mean direct and indirect radiance over the mask (README statistics).
pub fn pass_stats(px: &[PixelOut]) -> serde_json::Value {
    let (mut d, mut i, mut n) = (0.0f64, 0.0f64, 0.0f64);
    for p in px.iter().filter(|p| p.alpha > 0.0) {
        d += (p.direct.x + p.direct.y + p.direct.z) as f64 / 3.0;
        i += (p.indirect.x + p.indirect.y + p.indirect.z) as f64 / 3.0;
        n += 1.0;
    }
    let n = n.max(1.0);
    serde_json::json!({"mean_indirect_over_mask": i / n, "mean_direct_over_mask": d / n})
}

/// Render one view; `id` makes the RNG stream distinct per (split, view, env).
pub fn render_view(
    scene: &Scene,
    env: &EnvLight,
    cam: &Camera,
    opts: &RenderOptions,
    seed: u64,
    id: u64,
    bar: &indicatif::ProgressBar,
) -> Vec<PixelOut> {
    // The bar counts camera samples, so that views of different spp weigh what they cost.
    render(scene, env, cam, opts, seed, id, &|n| bar.inc(n.saturating_mul(opts.spp.max(1) as u64)))
}
