//! Diagnostic: how much of a run's indirect-light error comes from rays hitting the surface
//! they start from. Scores the indirect pass (as `radiogs eval`) with the run's settings, then
//! with every cached ray blind to its own object (objects from the dataset's README.json) —
//! the ceiling of any self-hit rejection — and prints per object the mean cached visibility
//! and indirect radiance of the upward-facing surfels near the true surface.
//!
//!     cargo run --release --example probe_indirect -- RUN DATA
//!
//! `SKIP_MARGIN=m` overrides the run's `ray_skip_margin` (× extent; 0 = off).

#[path = "common/probe_run.rs"]
mod probe_run;
#[path = "common/scene_readme.rs"]
mod scene_readme;

use anyhow::Context;
use radiogs::io::dataset::{Dataset, Pass, Split};
use radiogs::pbr_scene::PbrScene;
use radiogs::trace::{Ray, RayOutput, Tracer, trace};

fn main() -> anyhow::Result<()> {
    let probe_run::ProbeRun { run, data, cfg, extent, surfels, back_faces } = probe_run::from_args("probe_indirect")?;
    let env = radiogs::envmap::EnvMap::load(&run.join("envmap.exr"))?;
    let factor = radiogs::train::inverse::sample_factor(&cfg);
    let start = cfg.ray_start(extent);
    let mut scene = PbrScene::new(surfels, env, cfg.pbr_samples, start, cfg.window, factor, cfg.seed, back_faces);
    scene.specular = cfg.specular;
    let readme = scene_readme::load(&data)?;
    let ds = Dataset::open(&data)?;
    let views = ds.views(Split::Test);
    let score = |scene: &PbrScene| -> anyhow::Result<f64> {
        let mut tot = 0.0;
        for view in views.iter() {
            let img = scene.render(&view.camera, [0.0; 3]);
            let exr =
                view.pass_path(Pass::Indirect).with_context(|| format!("{}: no indirect.exr", view.camera.name))?;
            let gt = radiogs::io::image::read_exr_channels(&exr, &["R", "G", "B"])?;
            let mask: Vec<f32> = view.load_image()?.data.chunks_exact(4).map(|p| p[3]).collect();
            let enc = |x: f32| radiogs::io::image::linear_to_srgb(x.clamp(0.0, 1.0));
            let g: Vec<[f32; 3]> = gt.data.chunks_exact(3).map(|p| [enc(p[0]), enc(p[1]), enc(p[2])]).collect();
            let ours: Vec<[f32; 3]> = img.indirect.iter().map(|c| c.map(enc)).collect();
            tot += radiogs::loss::ssim::psnr_masked(&ours, &g, &mask) as f64;
        }
        Ok(tot / views.len() as f64)
    };
    println!("ray offset {:.4}, skip margin {:?} (scene units)", start.offset, start.skip_margin);
    let owner: Vec<usize> =
        scene.surfels.means.iter().map(|m| scene_readme::nearest(&readme.objects, m.map(|x| x as f64))).collect();
    stats(&scene, &readme, &owner);
    println!("indirect PSNR with the run's settings: {:.2} dB", score(&scene)?);
    // Re-trace each object's rows against the other objects' surfels only.
    let ns = scene.cache.samples;
    let settings = radiogs::train::inverse::trace_settings();
    for k in 0..readme.objects.len() {
        let mut others = scene.surfels.clone();
        others.retain_mask(&owner.iter().map(|&o| o != k).collect::<Vec<_>>());
        let tracer = Tracer::build(&others, &settings);
        let rows: Vec<usize> = (0..owner.len()).filter(|&i| owner[i] == k).collect();
        let mut rays = Vec::with_capacity(rows.len() * ns);
        for &i in &rows {
            let (n, m) = (scene.surfels.normal(i), scene.surfels.means[i]);
            let origin = [0, 1, 2].map(|a| m[a] + start.offset * n[a]);
            rays.extend((0..ns).map(|q| Ray { origin, dir: scene.cache.dirs[i * ns + q], ..Default::default() }));
        }
        let mut out = vec![RayOutput::default(); rays.len()];
        trace(&tracer, &others, &rays, None, &mut out, None);
        for (j, &i) in rows.iter().enumerate() {
            for q in 0..ns {
                scene.cache.visibility[i * ns + q] = out[j * ns + q].transmittance;
                scene.cache.indirect[i * ns + q] = out[j * ns + q].radiance;
            }
        }
    }
    scene.cache.footprints.clear();
    println!("... with every ray blind to its own object: {:.2} dB", score(&scene)?);
    stats(&scene, &readme, &owner);
    Ok(())
}

/// Per object: upward-facing surfels (true normal z > 0.7) within 15 mm of the true surface,
/// their mean cached visibility and indirect radiance (G).
fn stats(scene: &PbrScene, readme: &scene_readme::SceneReadme, owner: &[usize]) {
    let ns = scene.cache.samples;
    for (k, o) in readme.objects.iter().enumerate() {
        let (mut n, mut vis, mut ind) = (0usize, 0.0f64, 0.0f64);
        for i in (0..owner.len()).filter(|&i| owner[i] == k) {
            let p = scene.surfels.means[i].map(|x| x as f64);
            let d = o.sdf(p);
            let e = 1e-4;
            let up = (o.sdf([p[0], p[1], p[2] + e]) - d) / e;
            if d.abs() > 0.015 || up < 0.7 {
                continue;
            }
            n += 1;
            vis += scene.cache.visibility[i * ns..(i + 1) * ns].iter().map(|&v| v as f64).sum::<f64>() / ns as f64;
            ind += scene.cache.indirect[i * ns..(i + 1) * ns].iter().map(|v| v[1] as f64).sum::<f64>() / ns as f64;
        }
        if n > 0 {
            println!(
                "  {:16} {n:6} surfels facing up: visibility {:.3}, indirect (G) {:.4}",
                o.object,
                vis / n as f64,
                ind / n as f64
            );
        }
    }
}
