//! Diagnostic: can photo-consistency tell the visual hull's surface points from its air?
//! Samples the nvs stage's initial points (random points inside the visual hull of the training
//! masks), and scores each by how many training views agree with its median colour (views it
//! projects into, inside the mask; L∞ distance of the pixel's sRGB colour to the per-channel
//! median ≤ δ). Labels each point by its distance to the nearest true surface of the dataset's
//! README.json objects and prints, per distance band, the score's distribution.
//!
//!     cargo run --release --example probe_init -- DATA [POINTS] [DELTA]

#[path = "common/scene_readme.rs"]
mod scene_readme;

use radiogs::io::dataset::{Dataset, Split};
use radiogs::train::init::visual_hull_points;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let data = std::path::PathBuf::from(
        args.get(1).ok_or_else(|| anyhow::anyhow!("usage: probe_init DATA [POINTS] [DELTA]"))?,
    );
    let count: usize = match args.get(2) {
        Some(s) => s.parse().map_err(|e| anyhow::anyhow!("POINTS {s:?}: {e}"))?,
        None => 20000,
    };
    let delta: f32 = match args.get(3) {
        Some(s) => s.parse().map_err(|e| anyhow::anyhow!("DELTA {s:?}: {e}"))?,
        None => 0.05,
    };
    let readme = scene_readme::load(&data)?;
    anyhow::ensure!(!readme.objects.is_empty(), "{}: README.json lists no objects", data.display());
    let ds = Dataset::open(&data)?;
    let views = ds.views(Split::Train);
    let cams: Vec<_> = views.iter().map(|v| v.camera.clone()).collect();
    let images = ds.load_images(Split::Train)?;
    let (points, _) = visual_hull_points(&cams, &images, count, 0.5, 0);
    let bands = [0.01, 0.03, 0.06, 0.12, f64::INFINITY];
    let mut scores: Vec<Vec<f32>> = vec![Vec::new(); bands.len()];
    let mut corner: Vec<f32> = Vec::new();
    for p in &points {
        let mut cols: Vec<[f32; 3]> = Vec::new();
        for (cam, img) in cams.iter().zip(&images) {
            let Some((u, v)) = cam.project(glam::Vec3::from(*p)) else { continue };
            if u < 0.0 || v < 0.0 || u >= cam.width as f32 || v >= cam.height as f32 {
                continue;
            }
            let px = img.pixel(u as u32, v as u32);
            if img.channels >= 4 && px[3] <= 0.5 {
                continue;
            }
            cols.push([px[0], px[1], px[2]]);
        }
        if cols.len() < 4 {
            continue;
        }
        let median: [f32; 3] = std::array::from_fn(|c| {
            let mut v: Vec<f32> = cols.iter().map(|x| x[c]).collect();
            v.sort_by(f32::total_cmp);
            v[v.len() / 2]
        });
        let agree = cols.iter().filter(|x| (0..3).all(|c| (x[c] - median[c]).abs() <= delta)).count() as f32
            / cols.len() as f32;
        let q = p.map(|x| x as f64);
        let mut sdfs: Vec<f64> = readme.objects.iter().map(|o| o.sdf(q)).collect();
        let dist = sdfs.iter().fold(f64::INFINITY, |m, d| m.min(d.abs()));
        let band = bands.iter().position(|&b| dist < b).unwrap_or(bands.len() - 1);
        scores[band].push(agree);
        // In air, within 10 cm of two surfaces: a concave corner's fill.
        sdfs.sort_by(f64::total_cmp);
        if sdfs[0] > 0.03 && sdfs.get(1).is_some_and(|&d| d < 0.10) {
            corner.push(agree);
        }
    }
    let stats = |v: &mut Vec<f32>| -> String {
        if v.is_empty() {
            return "—".into();
        }
        v.sort_by(f32::total_cmp);
        let q = |f: f32| v[((v.len() - 1) as f32 * f) as usize];
        format!(
            "n {:6}  p10 {:.2}  p25 {:.2}  median {:.2}  p75 {:.2}  p90 {:.2}",
            v.len(),
            q(0.1),
            q(0.25),
            q(0.5),
            q(0.75),
            q(0.9)
        )
    };
    println!("{} hull points, δ = {delta}: fraction of views agreeing with the median colour", points.len());
    let names = ["< 1 cm", "1–3 cm", "3–6 cm", "6–12 cm", "> 12 cm"];
    for (name, s) in names.iter().zip(scores.iter_mut()) {
        println!("  {name:>8} from a true surface: {}", stats(s));
    }
    println!("  corner fill (air > 3 cm, two surfaces < 10 cm): {}", stats(&mut corner));
    Ok(())
}
