//! `radiogs render`: pictures of a surfel scene from a camera file or a run's test views.
//!
//! PNG: 8-bit RGBA with straight alpha (colour = Σ w c / α, the SH colour as stored, no tone
//! mapping). EXR: 32-bit float RGBA, premultiplied (Σ w c, α), the EXR convention. `--aux`
//! adds float EXRs per view: `<name>_depth.exr` (expected camera depth Σ w z / α),
//! `<name>_median_depth.exr`, `<name>_surface_depth.exr` (GauS-SLAM's surface-aware depth:
//! hits behind the median pulled toward it, no hidden-surface bleed), `<name>_normal.exr`
//! (world normal Σ w n, premultiplied) and `<name>_distortion.exr`.

use crate::camera::Camera;
use crate::io::image::{Image, write_image};
use crate::raster::{self, Outputs, RasterSettings};
use crate::train::config::MAX_DOWNSCALE;
use anyhow::{Context, bail};
use std::path::PathBuf;

#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum ImageFormat {
    /// 8-bit RGBA, straight alpha.
    #[default]
    Png,
    /// 32-bit float RGBA, premultiplied alpha.
    Exr,
}

/// How pixels are computed.
#[derive(clap::ValueEnum, Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum RenderMode {
    /// The rasteriser (per-pixel sorted window of K hits).
    #[default]
    Surfel,
    /// The ray tracer: exact per-ray hit order (no screen-space fallback); colour and alpha only.
    Traced,
    /// Physically based: each surfel's rendering equation under the run's env (or --envmap),
    /// with its cached visibility and indirect light (needs a run after the inverse stage).
    Pbr,
    /// Recovered base colour (linear, shown sRGB-encoded in PNG).
    Albedo,
    /// Recovered roughness (grey).
    Roughness,
    /// World normal (n·0.5 + 0.5 in PNG), back faces culled.
    Normal,
    /// Cosine-weighted visibility of the sky per surfel (grey).
    Visibility,
    /// Outgoing radiance due to indirect light (the L_ind part of the rendering equation).
    Indirect,
}

impl RenderMode {
    fn needs_materials(self) -> bool {
        !matches!(self, RenderMode::Surfel | RenderMode::Traced)
    }
}

/// Render views of a surfel scene.
#[derive(clap::Args, Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct RenderArgs {
    /// A run folder (renders its test views).
    #[arg(long)]
    pub run: Option<PathBuf>,
    /// A surfel PLY file (2DGS/3DGS layout).
    #[arg(long)]
    pub ply: Option<PathBuf>,
    /// A Blender-format camera file (transforms_*.json).
    #[arg(long)]
    pub cameras: Option<PathBuf>,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Per-pixel sorting window K (1 = plain 2DGS order; 1..=32).
    #[arg(long, default_value_t = 8)]
    #[serde(default = "default_k")]
    pub k: usize,
    /// Draw back faces (normal flipped to the camera) instead of culling them.
    #[arg(long)]
    #[serde(default)]
    pub two_sided: bool,
    /// 1/σ² (px⁻²) of the screen-space fallback filter. Default: the run's training value with
    /// --run; with --ply the value radiogs recorded in its header, else 2 (2DGS/3DGS).
    #[arg(long)]
    #[serde(default)]
    pub filter_inv_square: Option<f32>,
    /// Colour image format.
    #[arg(long, value_enum, default_value_t = ImageFormat::Png)]
    #[serde(default)]
    pub format: ImageFormat,
    /// Also write float EXRs of expected depth, median depth, surface-aware depth, world normal
    /// and distortion.
    #[arg(long)]
    #[serde(default)]
    pub aux: bool,
    /// Image width (default: the camera file's `w`, else its first image's size).
    #[arg(long)]
    #[serde(default)]
    pub width: Option<u32>,
    /// Image height (with --width).
    #[arg(long)]
    #[serde(default)]
    pub height: Option<u32>,
    /// With --run and no --cameras: render its test views shrunk by this factor (default the
    /// run's `--resolution`; 1 = the dataset's full size).
    #[arg(short = 'r', long)]
    #[serde(default)]
    pub resolution: Option<u32>,
    /// Rasterised frames stop compositing a pixel once its transmittance falls below this
    /// (0 = exact, the default; e.g. 1/255 ≈ 0.0039 for 8-bit viewing: a pixel then misses
    /// at most that fraction of the colour behind it, and renders ~15 % faster on a trained
    /// scene). Only with --mode surfel.
    #[arg(long, default_value_t = 0.0)]
    #[serde(default)]
    pub display_stop: f32,
    /// Rasterised surfels or ray-traced surfels.
    #[arg(long, value_enum, default_value_t = RenderMode::Surfel)]
    #[serde(default)]
    pub mode: RenderMode,
    /// Light the PBR modes with this env map (.hdr/.exr, Blender's orientation) instead of the
    /// run's recovered one. (Indirect light stays the trained scene's; `radiogs relight` for more.)
    #[arg(long)]
    #[serde(default)]
    pub envmap: Option<PathBuf>,
    /// Instead of the views, render N frames once around the object (about the vertical, at the
    /// views' median distance and elevation, aimed where they look; the first view's
    /// intrinsics): orbit_000 … and, as PNG, the animation orbit.apng at 24 frames/s.
    #[arg(long, value_name = "N")]
    #[serde(default)]
    pub orbit: Option<usize>,
    /// The orbit's elevation in degrees above the object's centre (default: the views' median).
    #[arg(long, value_name = "DEG", requires = "orbit", allow_negative_numbers = true)]
    #[serde(default)]
    pub orbit_elevation: Option<f32>,
}

/// The CLI's defaults (window 8, PNG, exact, surfel mode) with no scene and an empty `out`, for
/// callers that set a few fields.
impl Default for RenderArgs {
    fn default() -> Self {
        RenderArgs {
            run: None,
            ply: None,
            cameras: None,
            out: PathBuf::new(),
            k: default_k(),
            two_sided: false,
            filter_inv_square: None,
            format: ImageFormat::Png,
            aux: false,
            width: None,
            height: None,
            resolution: None,
            display_stop: 0.0,
            mode: RenderMode::Surfel,
            envmap: None,
            orbit: None,
            orbit_elevation: None,
        }
    }
}

/// Frames per second of `render --orbit`'s animation.
pub const ORBIT_FPS: u16 = 24;

fn default_k() -> usize {
    8
}

pub fn run(args: &RenderArgs) -> anyhow::Result<()> {
    if let Some(f) = args.filter_inv_square {
        if !(f.is_finite() && f > 0.0) {
            bail!("--filter-inv-square {f}: must be a positive number (2 = 2DGS, 8 = radiogs's default)");
        }
    }
    if let Some(r) = args.resolution
        && !(1..=MAX_DOWNSCALE).contains(&r)
    {
        bail!(
            "-r/--resolution {r}: the downscale factor of the run's test images must be in 1..={MAX_DOWNSCALE} (1 = full size)"
        );
    }
    if !(1..=raster::MAX_WINDOW).contains(&args.k) {
        bail!("--k {}: the sorting window must be in 1..={}", args.k, raster::MAX_WINDOW);
    }
    let size = match (args.width, args.height) {
        (Some(w), Some(h)) if w > 0 && h > 0 && w.max(h) <= crate::io::dataset::MAX_IMAGE_SIDE => Some((w, h)),
        (None, None) => None,
        _ => bail!("--width and --height must be given together, each in 1..={}", crate::io::dataset::MAX_IMAGE_SIDE),
    };
    // The scene and cameras: a PLY + camera file, or a run (its surfels, its dataset's test views).
    // A run renders with its own screen-space filter; a PLY with 2DGS's.
    let (surfels, views, two_sided, filter_inv_square) = match (&args.run, &args.ply, &args.cameras) {
        (Some(run), None, cameras) => {
            let cfg = crate::eval::load_run_config(run)?;
            let surfels = crate::eval::load_run_surfels(run)?;
            let views = match cameras {
                Some(cameras) => {
                    let root = cameras.parent().map(PathBuf::from).unwrap_or_default();
                    crate::io::dataset::read_transforms_sized(&root, cameras, size)?
                }
                None if cfg.data.as_os_str().is_empty() => bail!(
                    "{}: the run has no config.toml naming its dataset; give --cameras transforms.json",
                    run.display()
                ),
                None => {
                    crate::io::dataset::Dataset::open_downscaled(&cfg.data, args.resolution.unwrap_or(cfg.resolution))
                        .with_context(|| {
                            format!("the dataset of run {} (give --cameras to render other views)", run.display())
                        })?
                        .test
                }
            };
            (surfels, views, args.two_sided || cfg.two_sided, args.filter_inv_square.unwrap_or(cfg.filter_inv_square))
        }
        (None, Some(ply), Some(cameras)) => {
            let surfels = crate::io::ply::read_ply(ply)?;
            let root = cameras.parent().map(PathBuf::from).unwrap_or_default();
            let views = crate::io::dataset::read_transforms_sized(&root, cameras, size)?;
            // The filter recorded by radiogs in the PLY's header, else 2DGS's.
            let recorded = crate::io::ply::read_ply_filter_inv_square(ply)?;
            let filter = args.filter_inv_square.or(recorded).unwrap_or_else(crate::raster::filter_inv_square_2dgs);
            (surfels, views, args.two_sided, filter)
        }
        _ => bail!("radiogs render needs --run RUN, or --ply F.ply with --cameras transforms.json"),
    };
    if views.is_empty() {
        bail!("no views to render (the camera file's frames are empty)");
    }
    // --width/--height size a run's test views too (a camera file's are sized as read).
    let cameras: Vec<Camera> = views
        .into_iter()
        .map(|v| match size {
            Some((w, h)) if args.cameras.is_none() => v.camera.scaled(w, h),
            _ => v.camera,
        })
        .collect();
    let cameras = match args.orbit {
        Some(frames) => crate::orbit::orbit(&cameras, frames, args.orbit_elevation)?,
        None => cameras,
    };
    let outputs = Outputs {
        colour: true,
        depth: args.aux,
        median_depth: args.aux,
        normal: args.aux,
        distortion: args.aux,
        surface_depth: args.aux,
    };
    if !(0.0..1.0).contains(&args.display_stop) {
        bail!("--display-stop {}: must be in [0, 1) (a transmittance)", args.display_stop);
    }
    if args.display_stop > 0.0 && args.mode != RenderMode::Surfel {
        bail!("--display-stop is only available with --mode surfel");
    }
    let settings = RasterSettings {
        window: args.k,
        two_sided,
        outputs,
        filter_inv_square,
        display_stop: args.display_stop,
        ..Default::default()
    };
    let trace_settings = crate::trace::TraceSettings { two_sided, ..Default::default() };
    if args.mode == RenderMode::Traced && args.aux {
        bail!("--aux is only available with --mode surfel");
    }
    if args.mode.needs_materials() {
        return render_pbr_modes(args, &cameras);
    }
    if args.mode == RenderMode::Surfel
        && let Some(run) = &args.run
        && crate::relight::run_mode(run) == Some(crate::relight::RelightMode::Traced)
    {
        if args.display_stop > 0.0 {
            bail!("--display-stop: {} was relit in traced mode and renders with --mode pbr", run.display());
        }
        eprintln!("{}: a ray-traced relit run renders with --mode pbr", run.display());
        return render_pbr_modes(&RenderArgs { mode: RenderMode::Pbr, ..args.clone() }, &cameras);
    }
    create_out(&args.out)?;
    let bar = indicatif::ProgressBar::new(cameras.len() as u64);
    for cam in &cameras {
        let img = match args.mode {
            RenderMode::Surfel => raster::render(&surfels, cam, &settings, None).0,
            RenderMode::Traced => {
                let (colour, alpha) = crate::trace::render_camera_traced(&surfels, cam, &trace_settings);
                raster::RenderOutput { width: cam.width, height: cam.height, colour, alpha, ..Default::default() }
            }
            mode => bail!("--mode {mode:?} is rendered by the material path"),
        };
        let (w, h) = (img.width, img.height);
        let mut rgba = Image::new(w, h, 4);
        let straight = args.format == ImageFormat::Png;
        for (i, px) in rgba.data.chunks_exact_mut(4).enumerate() {
            let a = img.alpha[i];
            let c = img.colour[i];
            let s = if straight && a > 0.0 { 1.0 / a } else { 1.0 };
            px.copy_from_slice(&[c[0] * s, c[1] * s, c[2] * s, a]);
        }
        let ext = if straight { "png" } else { "exr" };
        write_image(&args.out.join(format!("{}.{ext}", cam.name)), &rgba)?;
        if args.aux {
            let grey = |v: &[f32]| Image { width: w, height: h, channels: 1, data: v.to_vec() };
            write_image(&args.out.join(format!("{}_depth.exr", cam.name)), &grey(&img.depth))?;
            write_image(&args.out.join(format!("{}_median_depth.exr", cam.name)), &grey(&img.median_depth))?;
            write_image(&args.out.join(format!("{}_surface_depth.exr", cam.name)), &grey(&img.surface_depth))?;
            write_image(&args.out.join(format!("{}_distortion.exr", cam.name)), &grey(&img.distortion))?;
            let normal =
                Image { width: w, height: h, channels: 3, data: img.normal.iter().flatten().copied().collect() };
            write_image(&args.out.join(format!("{}_normal.exr", cam.name)), &normal)?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    println!("rendered {} views of {} surfels to {}", cameras.len(), surfels.len(), args.out.display());
    write_orbit_animation(args, &cameras)
}

/// With `--orbit` and PNG frames: the frames as one looping animated PNG, `orbit.apng`.
fn write_orbit_animation(args: &RenderArgs, cameras: &[Camera]) -> anyhow::Result<()> {
    if args.orbit.is_none() || args.format != ImageFormat::Png {
        return Ok(());
    }
    let frames: Vec<PathBuf> = cameras.iter().map(|c| args.out.join(format!("{}.png", c.name))).collect();
    let path = args.out.join("orbit.apng");
    crate::io::image::write_apng(&path, &frames, ORBIT_FPS)?;
    println!("animation: {} ({} frames at {ORBIT_FPS} frames/s)", path.display(), frames.len());
    Ok(())
}

/// The PBR / material modes: one rasterisation with feature channels per view.
/// The output folder, made only once the inputs have loaded (no empty folder after an error).
fn create_out(out: &std::path::Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating output folder {}", out.display()))
}

fn render_pbr_modes(args: &RenderArgs, cameras: &[Camera]) -> anyhow::Result<()> {
    use crate::io::image::linear_to_srgb;
    let Some(run) = &args.run else { bail!("--mode {:?} needs --run RUN (a run after the inverse stage)", args.mode) };
    let Some(mut scene) = crate::pbr_scene::PbrScene::from_run(run)? else {
        bail!(
            "{}: no envmap.exr, so no recovered materials and light; run `radiogs train --stage inverse` first",
            run.display()
        )
    };
    if let Some(path) = &args.envmap {
        let env = crate::envmap::EnvMap::load(path)?;
        scene.env = env;
    }
    scene.window = args.k;
    create_out(&args.out)?;
    let bar = indicatif::ProgressBar::new(cameras.len() as u64);
    let png = args.format == ImageFormat::Png;
    let split_sum = scene.split_sum();
    for cam in cameras {
        let img = scene.render_with(cam, [0.0; 3], split_sum.as_ref());
        let mut rgba = Image::new(cam.width, cam.height, 4);
        for (i, px) in rgba.data.chunks_exact_mut(4).enumerate() {
            let a = img.alpha[i];
            // Straight linear values (PBR: linear radiance recovered from the sRGB render over black).
            let lin: [f32; 3] = match args.mode {
                RenderMode::Pbr => img.pbr[i].map(|v| crate::io::image::srgb_to_linear(v) / a.max(1e-3)),
                RenderMode::Albedo => img.albedo[i],
                RenderMode::Roughness => [img.roughness[i]; 3],
                RenderMode::Visibility => [img.visibility[i]; 3],
                RenderMode::Indirect => img.indirect[i],
                _ => {
                    let n = img.normal[i];
                    let l = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-8);
                    n.map(|v| v / l)
                }
            };
            let out: [f32; 3] = match (png, args.mode) {
                (true, RenderMode::Normal) => lin.map(|v| v * 0.5 + 0.5),
                (true, RenderMode::Roughness | RenderMode::Visibility) => lin,
                (true, _) => lin.map(linear_to_srgb),
                (false, _) => lin.map(|v| v * a),
            };
            px.copy_from_slice(&[out[0], out[1], out[2], a]);
        }
        let ext = if png { "png" } else { "exr" };
        write_image(&args.out.join(format!("{}.{ext}", cam.name)), &rgba)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    println!(
        "rendered {} views ({:?}) of {} surfels to {}",
        cameras.len(),
        args.mode,
        scene.surfels.len(),
        args.out.display()
    );
    write_orbit_animation(args, cameras)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surfels::{Surfels, quat_with_normal};
    use crate::test_dir::TempDir;
    use glam::Vec3;

    /// A unit sphere of outward-facing surfels coloured by their normal, and a camera file.
    fn sphere_scene(dir: &std::path::Path) -> (PathBuf, PathBuf) {
        let n = 3000;
        let mut s = Surfels { sh_degree: 0, ..Default::default() };
        for i in 0..n {
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / n as f32;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f32 * 2.399_963;
            let p = Vec3::new(r * phi.cos(), r * phi.sin(), z);
            let c = (p * 0.5 + Vec3::splat(0.5)).to_array();
            s.push(p.to_array(), [0.06, 0.06], quat_with_normal(p.to_array()), 0.95, c, [0.5; 3], 0.5);
        }
        let ply = dir.join("sphere.ply");
        crate::io::ply::write_ply(&ply, &s).unwrap();
        let frames: Vec<serde_json::Value> = [("front", Vec3::new(0.0, -3.0, 0.5)), ("side", Vec3::new(3.0, 0.5, 1.0))]
            .iter()
            .map(|(name, eye)| {
                let cam = Camera::look_at(*name, *eye, Vec3::ZERO, 64, 48, 0.8);
                serde_json::json!({"file_path": format!("./test/{name}"), "transform_matrix": cam.to_blender_rows()})
            })
            .collect();
        let json = serde_json::json!({"camera_angle_x": 0.8, "w": 64, "h": 48, "frames": frames});
        let cams = dir.join("transforms_test.json");
        std::fs::write(&cams, serde_json::to_string(&json).unwrap()).unwrap();
        (ply, cams)
    }

    /// `render --ply PLY --cameras CAMS --out OUT` with every other option at its default.
    fn ply_args(ply: PathBuf, cams: PathBuf, out: &std::path::Path) -> RenderArgs {
        RenderArgs { ply: Some(ply), cameras: Some(cams), out: out.to_path_buf(), ..RenderArgs::default() }
    }

    #[test]
    fn renders_png_exr_and_aux_of_a_ply_sphere() {
        let dir = TempDir::new("render");
        let (ply, cams) = sphere_scene(&dir);
        let out = dir.join("out");
        let mut args = RenderArgs { aux: true, ..ply_args(ply, cams, &out) };
        run(&args).unwrap();
        let png = crate::io::image::read_rgba(&out.join("front.png")).unwrap();
        assert_eq!((png.width, png.height), (64, 48));
        // Centre: opaque sphere; corner: empty.
        let centre = png.pixel(32, 24);
        assert!(centre[3] > 0.97, "centre alpha {}", centre[3]);
        assert_eq!(png.pixel(0, 0)[3], 0.0);
        // Front camera at −y sees normals ≈ −y: colour ≈ (0.5, 0, 0.5) ± the small elevation.
        assert!(centre[1] < 0.2 && (centre[0] - 0.5).abs() < 0.15, "{centre:?}");
        let depth = crate::io::image::read_channels(&out.join("front_depth.exr"), 1).unwrap();
        let d = depth.pixel(32, 24)[0];
        assert!((d - 2.05).abs() < 0.15, "depth {d}");
        assert!(out.join("front_normal.exr").is_file() && out.join("side_distortion.exr").is_file());
        args.format = ImageFormat::Exr;
        args.aux = false;
        args.width = Some(32);
        args.height = Some(24);
        run(&args).unwrap();
        let exr = crate::io::image::read_rgba(&out.join("side.exr")).unwrap();
        assert_eq!((exr.width, exr.height), (32, 24));
        // The tracer sees the same opaque sphere (it has no screen-space fallback, so compare
        // the interior, not the silhouette).
        args.mode = RenderMode::Traced;
        args.out = dir.join("traced");
        run(&args).unwrap();
        let traced = crate::io::image::read_rgba(&dir.join("traced/side.exr")).unwrap();
        let (cx, cy) = (16, 12);
        for c in 0..4 {
            let (a, b) = (exr.pixel(cx, cy)[c], traced.pixel(cx, cy)[c]);
            assert!((a - b).abs() < 0.05, "channel {c}: rasterised {a} vs traced {b}");
        }
        args.aux = true;
        assert!(run(&args).unwrap_err().to_string().contains("--aux"));
        args.aux = false;
        args.display_stop = 0.01;
        assert!(run(&args).unwrap_err().to_string().contains("--display-stop"));
        // A display frame: the opaque sphere's interior as the exact frame's, to 8-bit display.
        args.mode = RenderMode::Surfel;
        args.out = dir.join("display");
        run(&args).unwrap();
        let shown = crate::io::image::read_rgba(&dir.join("display/side.exr")).unwrap();
        for c in 0..4 {
            let (a, b) = (exr.pixel(cx, cy)[c], shown.pixel(cx, cy)[c]);
            assert!((a - b).abs() <= 0.01, "channel {c}: exact {a} vs display {b}");
        }
        for bad in [-0.1, 1.0, f32::NAN] {
            args.display_stop = bad;
            assert!(run(&args).unwrap_err().to_string().contains("--display-stop"), "{bad}");
        }
        args.display_stop = 0.0;
        args.mode = RenderMode::Surfel;
        args.k = 0;
        assert!(run(&args).unwrap_err().to_string().contains("--k"));
        args.k = 8;
        args.filter_inv_square = Some(f32::NAN);
        assert!(run(&args).unwrap_err().to_string().contains("--filter-inv-square"));
    }

    /// The frames of an APNG, decoded independently of `write_apng`, and its play count.
    fn apng_frames(path: &std::path::Path) -> (Vec<Vec<u8>>, u32, (u16, u16)) {
        let mut reader =
            png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap())).read_info().unwrap();
        let control = reader.info().animation_control.expect("an animation control chunk");
        let mut frames = Vec::new();
        let mut delay = (0, 0);
        for _ in 0..control.num_frames {
            let mut buf = vec![0; reader.output_buffer_size().unwrap()];
            let out = reader.next_frame(&mut buf).unwrap();
            let fc = reader.info().frame_control.unwrap();
            delay = (fc.delay_num, fc.delay_den);
            buf.truncate(out.buffer_size());
            frames.push(buf);
        }
        (frames, control.num_plays, delay)
    }

    #[test]
    fn an_orbit_renders_frames_around_the_object_and_their_animation() {
        let dir = TempDir::new("orbit");
        let (ply, cams) = sphere_scene(&dir);
        let out = dir.join("orbit");
        let mut args = RenderArgs { orbit: Some(6), orbit_elevation: Some(30.0), ..ply_args(ply, cams, &out) };
        run(&args).unwrap();
        let (frames, plays, delay) = apng_frames(&out.join("orbit.apng"));
        assert_eq!((frames.len(), plays, delay), (6, 0, (1, ORBIT_FPS)));
        for (i, frame) in frames.iter().enumerate() {
            // Each animation frame is its PNG file, pixel for pixel.
            let png = crate::io::image::read_rgba(&out.join(format!("orbit_{i:03}.png"))).unwrap();
            assert_eq!((png.width, png.height), (64, 48));
            let bytes: Vec<u8> = png.data.iter().map(|&v| (v * 255.0).round() as u8).collect();
            assert!(bytes == *frame, "frame {i} differs from its file");
            // The unit sphere at the centre the two cameras aim at fills the middle of every
            // frame and leaves the corners empty; frames differ as the sphere's colours turn.
            assert!(png.pixel(32, 24)[3] > 0.97, "frame {i}: centre alpha {}", png.pixel(32, 24)[3]);
            assert_eq!(png.pixel(0, 0)[3], 0.0);
        }
        assert!(frames[0] != frames[3]);
        // The sphere is coloured by its normal: frame 0 looks from the first camera's azimuth
        // (−y), so the centre pixel is ≈ (0.5, 0, 0.5 + elevation); half a turn later (+y) green.
        let (f0, f3) = (
            crate::io::image::read_rgba(&out.join("orbit_000.png")).unwrap(),
            crate::io::image::read_rgba(&out.join("orbit_003.png")).unwrap(),
        );
        assert!(
            f0.pixel(32, 24)[1] < 0.2 && f3.pixel(32, 24)[1] > 0.8,
            "{:?} {:?}",
            f0.pixel(32, 24),
            f3.pixel(32, 24)
        );
        // EXR frames have no animation; bad orbits are refused by flag.
        args.format = ImageFormat::Exr;
        args.out = dir.join("orbit_exr");
        run(&args).unwrap();
        assert!(dir.join("orbit_exr/orbit_005.exr").is_file() && !dir.join("orbit_exr/orbit.apng").exists());
        args.orbit = Some(0);
        assert!(run(&args).unwrap_err().to_string().contains("--orbit"));
        args.orbit = Some(4);
        args.orbit_elevation = Some(91.0);
        assert!(run(&args).unwrap_err().to_string().contains("--orbit-elevation"));
    }
}
