//! Diagnostic: per test view, masked means of our PBR radiance split into direct and indirect
//! parts beside the dataset's `indirect.exr` layers (direct.*, RGB = indirect); then the same
//! per material over all the views taken, with our specular part (the render with every albedo
//! 0) — pixels are given the material whose true base colour is nearest to `albedo.png`'s.
//!
//!     cargo run --release --example oracle_split -- RUN DATA [VIEWS]

#[path = "common/scene_readme.rs"]
mod scene_readme;

use anyhow::Context;
use radiogs::io::dataset::{Dataset, Split};
use radiogs::io::image::{read_exr_channels, srgb_to_linear};
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        anyhow::bail!("usage: oracle_split RUN DATA [VIEWS]");
    }
    let (run, data) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]));
    let nviews: usize = match args.get(3) {
        Some(v) => v.parse().with_context(|| format!("VIEWS: {v} is not a count"))?,
        None => 4,
    };
    let mut scene = radiogs::pbr_scene::PbrScene::from_run(&run)?
        .with_context(|| format!("{}: no envmap.exr (run the inverse stage first)", run.display()))?;
    if let Ok(v) = std::env::var("ENV_ROT") {
        scene.env = scene.env.rotated_about_up(v.parse()?);
    }
    let pure: Option<f32> = std::env::var("PURE")
        .ok()
        .map(|v| v.parse().with_context(|| format!("PURE={v}: not a tolerance")))
        .transpose()?;
    if std::env::var("ENV_MIRROR").is_ok() {
        // u → 1 − u: the azimuth mirrored (y → −y).
        let (w, h) = (scene.env.width, scene.env.height);
        let old = scene.env.texels.clone();
        for j in 0..h {
            for i in 0..w {
                scene.env.texels[j * w + i] = old[j * w + (w - 1 - i)];
            }
        }
    }
    if std::env::var("LINEAR_COMPOSITE").is_ok() {
        // Indirect light composited in linear radiance (each hit's colour decoded before
        // blending; view-independent: the SH DC colour) instead of decoding the sRGB composite.
        let s = &scene.surfels;
        let lin: Vec<f32> = (0..s.len())
            .flat_map(|i| {
                let dc = s.sh[i][0];
                (0..3).map(move |ch| radiogs::shade::incident::decode((0.5 + radiogs::sh::SH_C0 * dc[ch]).max(0.0)))
            })
            .collect();
        let srgb: Vec<f32> = (0..s.len())
            .flat_map(|i| {
                let dc = s.sh[i][0];
                (0..3).map(move |ch| (0.5 + radiogs::sh::SH_C0 * dc[ch]).max(0.0))
            })
            .collect();
        let tracer = radiogs::trace::Tracer::build(s, &radiogs::train::inverse::trace_settings());
        let mean = |c: &radiogs::shade::incident::IncidentCache| {
            c.indirect.iter().map(|c| c[1] as f64).sum::<f64>() / c.indirect.len() as f64
        };
        let before = mean(&scene.cache);
        let samples = scene.cache.samples;
        let extent = radiogs::pbr_scene::scene_extent(&run);
        let cfg = radiogs::eval::load_run_config(&run)?;
        let start = cfg.ray_start(extent);
        let mut dc_srgb = radiogs::shade::incident::IncidentCache::default();
        dc_srgb.refresh_with(&tracer, s, samples, start, cfg.seed, Some(&srgb));
        dc_srgb.indirect.iter_mut().for_each(|c| *c = c.map(radiogs::shade::incident::decode));
        scene.cache.refresh_with(&tracer, s, samples, start, cfg.seed, Some(&lin));
        println!(
            "mean indirect (G) per sample: SH sRGB composite decoded {before:.4}, DC sRGB composite decoded {:.4}, DC linear composite {:.4}",
            mean(&dc_srgb),
            mean(&scene.cache)
        );
    }
    if std::env::var("ANALYTIC_VIS").is_ok() {
        analytic_visibility(&mut scene, &data)?;
    }
    if let Ok(v) = std::env::var("VIS_SCALE") {
        let f: f32 = v.parse()?;
        scene.cache.visibility.iter_mut().for_each(|x| *x = (*x * f).min(1.0));
    }
    let ds = Dataset::open(&data)?;
    let mut tot = [[0.0f64; 3]; 7];
    // The per-material table needs the object list; without it only the per-view split is printed.
    let mats = match scene_readme::load(&data) {
        Ok(readme) => material_colours(&readme),
        Err(e) => {
            println!("no per-material table: {e:#}");
            Vec::new()
        }
    };
    let mut per_material = vec![[[0.0f64; 3]; 10]; mats.len()];
    let mut material_pixels = vec![0usize; mats.len()];
    // UNIFORM_ALBEDO=a: every surfel's albedo a (is the irradiance the same on both classes?).
    if let Ok(v) = std::env::var("UNIFORM_ALBEDO") {
        let a: f32 = v.parse().with_context(|| format!("UNIFORM_ALBEDO={v}: not an albedo"))?;
        scene.mats.albedo.iter_mut().for_each(|x| *x = [a; 3]);
    }
    let albedo = scene.mats.albedo.clone();
    for view in ds.views(Split::Test).iter().take(nviews) {
        scene.mats.albedo.iter_mut().for_each(|a| *a = [0.0; 3]);
        let specular = scene.render(&view.camera, [0.0; 3]);
        scene.mats.albedo.clone_from(&albedo);
        let img = scene.render(&view.camera, [0.0; 3]);
        let gt_albedo = view.load_pass(radiogs::io::dataset::Pass::Albedo)?;
        // Cycles' Diffuse Color pass (base × the diffuse layer's weight), where the data has it.
        let diffcol = {
            let path = view.folder.join("diffuse_color.png");
            if path.exists() { Some(radiogs::io::image::read_rgba(&path)?) } else { None }
        };
        let exr = view
            .pass_path(radiogs::io::dataset::Pass::Indirect)
            .with_context(|| format!("{}: no indirect.exr pass", view.camera.name))?;
        let gt_ind = read_exr_channels(&exr, &["R", "G", "B", "A"])?;
        let gt_dir = read_exr_channels(&exr, &["direct.R", "direct.G", "direct.B"])?;
        let gt = view.load_image()?;
        let mut acc = [[0.0f64; 3]; 7];
        let mut n = 0.0f64;
        let mut sq = 0.0f64;
        for p in 0..img.alpha.len() {
            if gt.data[p * 4 + 3] < 0.99 || img.alpha[p] < 0.99 {
                continue;
            }
            let material = gt_albedo.as_ref().filter(|_| !mats.is_empty()).map(|a| {
                let base: [f32; 3] = std::array::from_fn(|k| srgb_to_linear(a.data[p * 4 + k]));
                nearest(&mats, base)
            });
            // PURE=tol: only pixels whose 3×3 neighbourhood's albedo is within tol (linear, any
            // channel) of the material's base colour (colour edges, anti-aliased, left out).
            if let (Some(tol), Some(m), Some(a)) = (pure, material, gt_albedo.as_ref()) {
                let (w, h) = (a.width as isize, a.height as isize);
                let (x, y) = ((p as isize) % w, (p as isize) / w);
                let impure = (-1..=1).flat_map(|dy| (-1..=1).map(move |dx| (x + dx, y + dy))).any(|(u, v)| {
                    if u < 0 || v < 0 || u >= w || v >= h {
                        return true;
                    }
                    let q = (v * w + u) as usize;
                    (0..3).any(|k| (srgb_to_linear(a.data[q * 4 + k]) - mats[m].1[k]).abs() > tol)
                });
                if impure {
                    continue;
                }
            }
            n += 1.0;
            if let Some(m) = material {
                material_pixels[m] += 1;
            }
            for k in 0..3 {
                let ours = srgb_to_linear(img.pbr[p][k]) as f64;
                let ind = img.indirect[p][k] as f64;
                sq += (ours - ind - gt_dir.data[p * 3 + k] as f64).powi(2);
                let vals = [
                    srgb_to_linear(gt.data[p * 4 + k]) as f64,
                    ours,
                    gt_dir.data[p * 3 + k] as f64,
                    ours - ind,
                    gt_ind.data[p * 4 + k] as f64,
                    ind,
                    img.visibility[p] as f64,
                ];
                for (a, v) in acc.iter_mut().zip(vals) {
                    a[k] += v;
                }
                if let Some(m) = material {
                    let sums = &mut per_material[m];
                    for (a, v) in sums.iter_mut().zip(&vals[..6]) {
                        a[k] += v;
                    }
                    sums[6][k] += srgb_to_linear(specular.pbr[p][k]) as f64;
                    sums[8][k] += img.normal[p][k] as f64;
                    sums[9][k] += if k == 0 { img.visibility[p] as f64 } else { img.alpha[p] as f64 };
                    if let Some(d) = &diffcol {
                        sums[7][k] += srgb_to_linear(d.data[p * 4 + k]) as f64;
                    }
                }
            }
        }
        if let Ok(dir) = std::env::var("DUMP") {
            // direct GT | direct ours | ratio (grey = 1, ×2 contrast) side by side, sRGB.
            let (w, h) = (view.camera.width, view.camera.height);
            let mut out = radiogs::io::image::Image::new(3 * w, 2 * h, 3);
            for y in 0..h {
                for x in 0..w {
                    let p = (y * w + x) as usize;
                    let ok = gt.data[p * 4 + 3] > 0.99 && img.alpha[p] > 0.99;
                    for k in 0..3 {
                        let g = gt_dir.data[p * 3 + k];
                        let o = srgb_to_linear(img.pbr[p][k]) - img.indirect[p][k];
                        out.pixel_mut(x, y)[k] = radiogs::io::image::linear_to_srgb(g.clamp(0.0, 1.0));
                        out.pixel_mut(x + w, y)[k] = radiogs::io::image::linear_to_srgb(o.clamp(0.0, 1.0));
                        let r = if ok { (0.5 + 2.0 * (o / g.max(1e-3)).ln()).clamp(0.0, 1.0) } else { 0.0 };
                        out.pixel_mut(x + 2 * w, y)[k] = r;
                        // Second row: indirect GT | ours | ratio (×4 exposure on the pictures).
                        let gi = gt_ind.data[p * 4 + k];
                        let oi = img.indirect[p][k];
                        out.pixel_mut(x, y + h)[k] = radiogs::io::image::linear_to_srgb((4.0 * gi).clamp(0.0, 1.0));
                        out.pixel_mut(x + w, y + h)[k] = radiogs::io::image::linear_to_srgb((4.0 * oi).clamp(0.0, 1.0));
                        let ri =
                            if ok { (0.5 + 1.0 * (oi.max(1e-4) / gi.max(1e-3)).ln()).clamp(0.0, 1.0) } else { 0.0 };
                        out.pixel_mut(x + 2 * w, y + h)[k] = ri;
                    }
                }
            }
            radiogs::io::image::write_image(
                &std::path::Path::new(&dir).join(format!("{}_direct.png", view.camera.name)),
                &out,
            )?;
        }
        let f = |a: [f64; 3]| format!("[{:.4} {:.4} {:.4}]", a[0] / n, a[1] / n, a[2] / n);
        println!(
            "{} rmse_direct {:.4}: total gt {} ours {} | direct gt {} ours {} | indirect gt {} ours {} | vis {:.3}",
            view.camera.name,
            (sq / n / 3.0).sqrt(),
            f(acc[0]),
            f(acc[1]),
            f(acc[2]),
            f(acc[3]),
            f(acc[4]),
            f(acc[5]),
            acc[6][0] / n
        );
        for (t, a) in tot.iter_mut().zip(acc) {
            for k in 0..3 {
                t[k] += a[k] / n / nviews as f64;
            }
        }
    }
    let names = ["total gt", "total ours", "direct gt", "direct ours", "indirect gt", "indirect ours", "visibility"];
    for (nm, t) in names.iter().zip(tot) {
        println!("{nm:14} {:.4} {:.4} {:.4}", t[0], t[1], t[2]);
    }
    // Per material over every pixel of the views taken (no albedo.png: nothing to group by).
    let names = [
        "total gt",
        "total ours",
        "direct gt",
        "direct ours",
        "indirect gt",
        "indirect ours",
        "specular ours",
        "diffcol gt",
        "normal ours",
        "vis, alpha ours",
    ];
    for (m, (name, base)) in mats.iter().enumerate() {
        let count = material_pixels[m];
        if count == 0 {
            continue;
        }
        println!("{name}: base {base:.3?}, {count} pixels");
        for (nm, t) in names.iter().zip(per_material[m]) {
            let t = t.map(|x| x / count as f64);
            println!("  {nm:14} {:.4} {:.4} {:.4}", t[0], t[1], t[2]);
        }
    }
    Ok(())
}

/// (name, linear base colour) of every material; a checker gives its two colours.
fn material_colours(readme: &scene_readme::SceneReadme) -> Vec<(String, [f32; 3])> {
    let mut names: Vec<&String> = readme.materials.keys().collect();
    names.sort();
    let f = |c: [f64; 3]| c.map(|x| x as f32);
    let mut out = Vec::new();
    for name in names {
        match &readme.materials[name].base_color_linear {
            scene_readme::BaseColor::Rgb(c) => out.push((name.clone(), f(*c))),
            scene_readme::BaseColor::Checker { checker_object_space: k } => {
                out.push((format!("{name}.1"), f(k.color1)));
                out.push((format!("{name}.2"), f(k.color2)));
            }
        }
    }
    out
}

/// The material whose base colour is nearest to `c` (linear rgb).
fn nearest(mats: &[(String, [f32; 3])], c: [f32; 3]) -> usize {
    let d = |a: [f32; 3]| (0..3).map(|k| (a[k] - c[k]).powi(2)).sum::<f32>();
    (0..mats.len()).min_by(|&a, &b| d(mats[a].1).total_cmp(&d(mats[b].1))).unwrap_or(0)
}

/// Replace the cache's traced visibility by exact ray casts against the dataset's objects.
fn analytic_visibility(scene: &mut radiogs::pbr_scene::PbrScene, data: &std::path::Path) -> anyhow::Result<()> {
    let readme = scene_readme::load(data)?;
    let s = scene.cache.samples;
    let offset = 0.01f64;
    let n = scene.surfels.len();
    let (mut before, mut after) = (0.0f64, 0.0f64);
    for i in 0..n {
        let m = scene.surfels.means[i];
        let nn = scene.surfels.normal(i);
        let o = [0, 1, 2].map(|k| m[k] as f64 + offset * nn[k] as f64);
        for k in i * s..(i + 1) * s {
            let d = scene.cache.dirs[k].map(|x| x as f64);
            let hit = readme.objects.iter().any(|obj| obj.ray_entry(o, d).is_some());
            before += scene.cache.visibility[k] as f64;
            let v = if hit { 0.0 } else { 1.0 };
            after += v;
            scene.cache.visibility[k] = v as f32;
        }
    }
    println!("mean sample visibility: traced {:.4}, analytic {:.4}", before / (n * s) as f64, after / (n * s) as f64);
    Ok(())
}
