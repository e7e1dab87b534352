//! Diagnostic: where a run's PBR image differs from the dataset's, per material and channel,
//! split into the parts Cycles writes: direct and indirect light (`indirect.exr` layers), and
//! ours split the same way plus diffuse vs specular (the specular part is the render with
//! every albedo 0). Pixels are assigned to a material by the nearest true base colour
//! (`albedo.png`); only fully covered pixels count.
//!
//!     cargo run --release --example probe_components -- RUN DATA
//!
//! Meant for a run given the true materials and light by `oracle_materials`: what is left is
//! our shading model (and geometry, visibility, indirect light) against Cycles'.

#[path = "common/scene_readme.rs"]
mod scene_readme;

use anyhow::Context;
use radiogs::io::dataset::{Dataset, Pass, Split};
use radiogs::io::image::{read_exr_channels, read_rgba, srgb_to_linear};
use radiogs::pbr_scene::PbrScene;
use std::path::PathBuf;

/// Sums per material of 3-channel quantities.
const QUANTITIES: [&str; 9] = [
    "gt total",
    "gt direct",
    "gt indirect",
    "ours total",
    "ours direct",
    "ours indirect",
    "ours spec",
    "gt diffcol/base",
    "ours kd",
];

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(args.len() == 3, "usage: probe_components RUN DATA");
    let (run, data) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]));
    let readme = scene_readme::load(&data)?;
    let mats = material_colours(&readme);
    anyhow::ensure!(!mats.is_empty(), "{}: no materials", data.display());
    let mut scene = PbrScene::from_run(&run)?.context("run has no envmap.exr")?;
    let ds = Dataset::open(&data)?;
    let views = ds.views(Split::Test);
    let nq = QUANTITIES.len();
    let mut sums = vec![[0.0f64; 3]; mats.len() * nq];
    let mut counts = vec![0usize; mats.len()];
    let true_albedo = scene.mats.albedo.clone();
    for view in views {
        scene.mats.albedo.clone_from(&true_albedo);
        let full = scene.render(&view.camera, [0.0; 3]);
        scene.mats.albedo.iter_mut().for_each(|a| *a = [0.0; 3]);
        let spec = scene.render(&view.camera, [0.0; 3]);
        let rgba = view.load_image()?;
        let exr = view.pass_path(Pass::Indirect).context("no indirect.exr")?;
        let ind = read_exr_channels(&exr, &["R", "G", "B"])?;
        let dir = read_exr_channels(&exr, &["direct.R", "direct.G", "direct.B"])?;
        let albedo = view.load_pass(Pass::Albedo)?.context("no albedo.png")?;
        let diffcol_path = exr.with_file_name("diffuse_color.png");
        let diffcol = read_rgba(&diffcol_path)?;
        for p in 0..rgba.pixel_count() {
            if rgba.data[p * 4 + 3] < 0.999 || full.alpha[p] < 0.99 {
                continue;
            }
            let base: [f32; 3] = std::array::from_fn(|c| srgb_to_linear(albedo.data[p * 4 + c]));
            let m = nearest(&mats, base);
            counts[m] += 1;
            let pbr_lin = |img: &radiogs::pbr_scene::PbrImages| -> [f64; 3] {
                std::array::from_fn(|c| srgb_to_linear(img.pbr[p][c]) as f64)
            };
            let ours_total = pbr_lin(&full);
            let ours_ind: [f64; 3] = std::array::from_fn(|c| full.indirect[p][c] as f64 * full.alpha[p] as f64);
            let values: [[f64; 3]; 9] = [
                std::array::from_fn(|c| srgb_to_linear(rgba.data[p * 4 + c]) as f64),
                std::array::from_fn(|c| dir.data[p * 3 + c] as f64),
                std::array::from_fn(|c| ind.data[p * 3 + c] as f64),
                ours_total,
                std::array::from_fn(|c| ours_total[c] - ours_ind[c]),
                ours_ind,
                pbr_lin(&spec),
                std::array::from_fn(|c| {
                    srgb_to_linear(diffcol.data[p * 4 + c]) as f64 / (mats[m].1[c] as f64).max(1e-3)
                }),
                std::array::from_fn(|c| {
                    let a = full.albedo[p][c] as f64;
                    let d = ours_total[c] - pbr_lin(&spec)[c];
                    if a > 1e-3 { d / a } else { 0.0 }
                }),
            ];
            for (q, v) in values.iter().enumerate() {
                let s = &mut sums[m * nq + q];
                for c in 0..3 {
                    s[c] += v[c];
                }
            }
        }
    }
    println!("per material, mean over fully covered test pixels (linear rgb); 'ours kd' = ours diffuse / albedo");
    for (m, (name, base)) in mats.iter().enumerate() {
        if counts[m] == 0 {
            continue;
        }
        println!("{name}  base {:.3?}  pixels {}", base, counts[m]);
        for (q, label) in QUANTITIES.iter().enumerate() {
            let s = sums[m * nq + q].map(|x| x / counts[m] as f64);
            println!("  {label:<16} {:>7.4} {:>7.4} {:>7.4}", s[0], s[1], s[2]);
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

fn nearest(mats: &[(String, [f32; 3])], c: [f32; 3]) -> usize {
    let d = |a: [f32; 3]| (0..3).map(|k| (a[k] - c[k]).powi(2)).sum::<f32>();
    (0..mats.len()).min_by(|&a, &b| d(mats[a].1).total_cmp(&d(mats[b].1))).unwrap_or(0)
}
