//! Diagnostic: where a run's normal error comes from. Renders every test view as `radiogs eval`
//! does, finds each pixel's true surface by casting the pixel's ray against the dataset's
//! README.json objects, and prints per object: its share of the image's normal MAE (DESIGN §5:
//! mean over all pixels), the mean angle error on its pixels, the angle of the *mean* rendered
//! normal against the mean true normal (a systematic tilt; small when the errors cancel) and
//! the rendered depth's error against the true depth (mean, mean |·|, and the median depth's
//! mean; z-depth, scene units). A run folder with only a checkpoint (a copy taken mid-run) works.
//! Writes `RUN/probe_normals/<view>_error.png` (angle error, 0–30° as black–white) and
//! `<view>_depth.png` (rendered − true depth: red in front of the truth, blue behind, full
//! at 0.1 scene units).
//!
//!     cargo run --release --example probe_normals -- RUN DATA

#[path = "common/probe_run.rs"]
mod probe_run;
#[path = "common/scene_readme.rs"]
mod scene_readme;

use radiogs::io::dataset::{Dataset, Pass, Split};
use radiogs::io::image::{Image, write_image};
use radiogs::raster::{self, Outputs, RasterSettings};

#[derive(Default, Clone)]
struct ObjectSums {
    pixels: usize,
    angle: f64,
    mean_ours: [f64; 3],
    mean_true: [f64; 3],
    depth_err: f64,
    depth_abs: f64,
    median_err: f64,
    /// Pixels more than 10° off.
    over10: usize,
}

fn main() -> anyhow::Result<()> {
    let probe_run::ProbeRun { run, data, cfg, surfels, .. } = probe_run::from_args("probe_normals")?;
    let readme = scene_readme::load(&data)?;
    let ds = Dataset::open(&data)?;
    let views = ds.views(Split::Test);
    let settings = RasterSettings {
        window: cfg.window,
        filter_inv_square: cfg.filter_inv_square,
        two_sided: cfg.two_sided,
        background: [1.0; 3],
        outputs: Outputs { colour: true, normal: true, depth: true, median_depth: true, ..Outputs::none() },
        ..RasterSettings::default()
    };
    let out_dir = run.join("probe_normals");
    std::fs::create_dir_all(&out_dir)?;
    let mut sums = vec![ObjectSums::default(); readme.objects.len()];
    let (mut all_pixels, mut all_angle, mut off_object) = (0usize, 0.0f64, 0.0f64);
    for view in views.iter() {
        let cam = &view.camera;
        let (out, _) = raster::render(&surfels, cam, &settings, None);
        let Some(gt_normal) = view.load_pass(Pass::Normal)? else {
            anyhow::bail!("{}: no GT normal pass", cam.name);
        };
        let mut err_img = Image::new(cam.width, cam.height, 4);
        let mut depth_img = Image::new(cam.width, cam.height, 4);
        for py in 0..cam.height {
            for px in 0..cam.width {
                let i = (py * cam.width + px) as usize;
                all_pixels += 1;
                let g = &gt_normal.data[i * gt_normal.channels..][..gt_normal.channels];
                let mask = if gt_normal.channels >= 4 { g[3] } else { 1.0 };
                if mask < 0.5 {
                    continue;
                }
                let n = out.normal[i];
                let (ln, lg) = (
                    (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt(),
                    (g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).sqrt(),
                );
                let cos =
                    if ln > 1e-8 && lg > 1e-8 { (n[0] * g[0] + n[1] * g[1] + n[2] * g[2]) / (ln * lg) } else { 0.0 };
                let angle = (cos.clamp(-1.0, 1.0) as f64).acos().to_degrees();
                all_angle += angle;
                let px_rgba = &mut err_img.data[i * 4..i * 4 + 4];
                let shade = (angle / 30.0).min(1.0) as f32;
                px_rgba.copy_from_slice(&[shade, shade, shade, 1.0]);
                // The true surface under this pixel: the nearest entry of its ray.
                let (o, d) = cam.ray(px as f32 + 0.5, py as f32 + 0.5);
                let (o, d) = ([o.x as f64, o.y as f64, o.z as f64], [d.x as f64, d.y as f64, d.z as f64]);
                let hit = readme
                    .objects
                    .iter()
                    .enumerate()
                    .filter_map(|(k, obj)| obj.ray_entry(o, d).map(|t| (k, t)))
                    .min_by(|a, b| a.1.total_cmp(&b.1));
                let Some((k, t)) = hit else {
                    off_object += angle;
                    continue;
                };
                let p = [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
                let true_z = cam.world_to_camera(glam_vec(p)).z as f64;
                let s = &mut sums[k];
                s.pixels += 1;
                s.angle += angle;
                if angle > 10.0 {
                    s.over10 += 1;
                }
                for c in 0..3 {
                    s.mean_ours[c] += (n[c] / ln.max(1e-8)) as f64;
                    s.mean_true[c] += (g[c] / lg.max(1e-8)) as f64;
                }
                let dz = out.depth[i] as f64 - true_z;
                let f = (dz.abs() / 0.1).min(1.0) as f32;
                let rgba = if dz < 0.0 { [1.0, 1.0 - f, 1.0 - f, 1.0] } else { [1.0 - f, 1.0 - f, 1.0, 1.0] };
                depth_img.data[i * 4..i * 4 + 4].copy_from_slice(&rgba);
                s.depth_err += dz;
                s.depth_abs += dz.abs();
                s.median_err += out.median_depth[i] as f64 - true_z;
            }
        }
        write_image(&out_dir.join(format!("{}_error.png", cam.name)), &err_img)?;
        write_image(&out_dir.join(format!("{}_depth.png", cam.name)), &depth_img)?;
    }
    let mae = all_angle / all_pixels as f64;
    println!("normal MAE over all pixels {mae:.2}° ({} views)", views.len());
    println!(
        "{:<20} {:>8} {:>8} {:>10} {:>9} {:>10} {:>10} {:>10} {:>7}",
        "object", "pixels", "share°", "mean err°", "tilt°", "dz mean", "|dz| mean", "dz median", ">10°"
    );
    for (obj, s) in readme.objects.iter().zip(&sums) {
        if s.pixels == 0 {
            continue;
        }
        let np = s.pixels as f64;
        let angle_between = |a: [f64; 3], b: [f64; 3]| {
            let (la, lb) = (a.iter().map(|x| x * x).sum::<f64>().sqrt(), b.iter().map(|x| x * x).sum::<f64>().sqrt());
            ((a[0] * b[0] + a[1] * b[1] + a[2] * b[2]) / (la * lb).max(1e-12)).clamp(-1.0, 1.0).acos().to_degrees()
        };
        println!(
            "{:<20} {:>8} {:>8.2} {:>10.2} {:>9.2} {:>10.4} {:>10.4} {:>10.4} {:>6.1}%",
            obj.object,
            s.pixels,
            s.angle / all_pixels as f64,
            s.angle / np,
            angle_between(s.mean_ours, s.mean_true),
            s.depth_err / np,
            s.depth_abs / np,
            s.median_err / np,
            100.0 * s.over10 as f64 / np
        );
    }
    println!("{:<20} {:>8} {:>8.2}", "(no true hit)", "", off_object / all_pixels as f64);
    Ok(())
}

fn glam_vec(p: [f64; 3]) -> glam::Vec3 {
    glam::Vec3::new(p[0] as f32, p[1] as f32, p[2] as f32)
}
