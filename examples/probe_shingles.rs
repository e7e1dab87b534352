//! Diagnostic: are a run's surfels shingled? Renders every test view, and over the GT mask
//! compares with the GT normals: the rendered normals, and normals of the rendered depth taken
//! by central differences at strides 1, 2, 4, 8 px (pixels whose whole stencil is covered).
//!
//!     cargo run --release --example probe_shingles -- RUN DATA

#[path = "common/probe_run.rs"]
mod probe_run;

use glam::Vec3;
use radiogs::io::dataset::{Dataset, Pass, Split};
use radiogs::raster::{self, Outputs, RasterSettings};

const STRIDES: [usize; 4] = [1, 2, 4, 8];

fn angle(a: Vec3, b: Vec3) -> f64 {
    let (la, lb) = (a.length(), b.length());
    if la < 1e-8 || lb < 1e-8 {
        return 90.0;
    }
    ((a.dot(b) / (la * lb)).clamp(-1.0, 1.0) as f64).acos().to_degrees()
}

fn main() -> anyhow::Result<()> {
    let probe_run::ProbeRun { data, cfg, surfels, .. } = probe_run::from_args("probe_shingles")?;
    let ds = Dataset::open(&data)?;
    let settings = RasterSettings {
        window: cfg.window,
        filter_inv_square: cfg.filter_inv_square,
        two_sided: cfg.two_sided,
        background: [1.0; 3],
        outputs: Outputs { colour: true, normal: true, depth: true, ..Outputs::none() },
        ..RasterSettings::default()
    };
    // [rendered, stride…] sums over the pixels where the largest stride's stencil is valid.
    let mut sums = [0.0f64; 1 + STRIDES.len()];
    let mut pixels = 0usize;
    for view in ds.views(Split::Test) {
        let cam = &view.camera;
        let (out, _) = raster::render(&surfels, cam, &settings, None);
        let Some(gt) = view.load_pass(Pass::Normal)? else { anyhow::bail!("{}: no GT normal pass", cam.name) };
        let (w, h) = (cam.width as usize, cam.height as usize);
        let rt = cam.rotation.transpose();
        let o = cam.position();
        let point = |x: usize, y: usize| {
            let d = rt * Vec3::new((x as f32 + 0.5 - cam.cx) / cam.fx, (y as f32 + 0.5 - cam.cy) / cam.fy, 1.0);
            o + out.depth[y * w + x] * d
        };
        let gt_n = |x: usize, y: usize| {
            let i = (y * w + x) * 4;
            Vec3::new(gt.data[i], gt.data[i + 1], gt.data[i + 2])
        };
        // Covered, and on the same plane as the stencil's centre (GT normals within 1°).
        let covered = |x: usize, y: usize| gt.data[(y * w + x) * 4 + 3] >= 0.5 && out.alpha[y * w + x] > 0.5;
        let planar = |x: usize, y: usize, cx: usize, cy: usize| covered(x, y) && angle(gt_n(x, y), gt_n(cx, cy)) < 1.0;
        let smax = *STRIDES.last().unwrap();
        for y in smax..h.saturating_sub(smax) {
            for x in smax..w.saturating_sub(smax) {
                let i = y * w + x;
                if !(covered(x, y)
                    && planar(x - smax, y, x, y)
                    && planar(x + smax, y, x, y)
                    && planar(x, y - smax, x, y)
                    && planar(x, y + smax, x, y)
                    && planar(x - smax / 2, y, x, y)
                    && planar(x + smax / 2, y, x, y)
                    && planar(x, y - smax / 2, x, y)
                    && planar(x, y + smax / 2, x, y))
                {
                    continue;
                }
                let g = Vec3::new(gt.data[i * 4], gt.data[i * 4 + 1], gt.data[i * 4 + 2]);
                sums[0] += angle(Vec3::from(out.normal[i]), g);
                for (k, &s) in STRIDES.iter().enumerate() {
                    let dr = point(x, y + s) - point(x, y - s);
                    let dc = point(x + s, y) - point(x - s, y);
                    sums[1 + k] += angle(dr.cross(dc), g);
                }
                pixels += 1;
            }
        }
    }
    let n = pixels.max(1) as f64;
    println!("{pixels} pixels (GT mask, rendered alpha > 0.5, the 8 px stencil inside)");
    println!("rendered normals: {:.2}°", sums[0] / n);
    for (k, s) in STRIDES.iter().enumerate() {
        println!("depth normals, stride {s}: {:.2}°", sums[1 + k] / n);
    }
    Ok(())
}
