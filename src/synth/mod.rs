//! `radiogs synth`: built-in ground-truth scenes rendered by a reference path tracer that is
//! independent of the surfel code (it shares only cameras, env-map conventions and image IO).
//!
//! Layout written (both read by the same loader): per-view folders `train_XXX/`, `test_XXX/`
//! with TensoIR-style `metadata.json`; `transforms_{train,test}.json` (Blender convention);
//! `envmaps/<name>.hdr`; `README.json` with every parameter.

pub mod bench;
pub mod brdf;
pub mod bvh;
pub mod dataset;
pub mod envlight;
pub mod geometry;
pub mod integrator;
pub mod sampling;
pub mod scene;

use crate::envmap::EnvMap;
use anyhow::Context;
use envlight::{EnvLight, PROCEDURAL, procedural_description, procedural_map};
use integrator::RenderOptions;
use std::path::PathBuf;
use std::time::Instant;

/// Render a built-in scene into a dataset folder (TensoIR + Blender layouts, all GT passes).
#[derive(clap::Args, Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct SynthArgs {
    /// Scene name: spheres, box, torus or cornell.
    #[arg(long, default_value = "spheres")]
    pub scene: String,
    /// Output dataset folder.
    #[arg(long)]
    pub out: PathBuf,
    /// Image width and height in pixels.
    #[arg(long, default_value_t = 200)]
    pub res: u32,
    /// Number of training views.
    #[arg(long, default_value_t = 64)]
    pub train_views: usize,
    /// Number of test views (with every ground-truth pass).
    #[arg(long, default_value_t = 16)]
    pub test_views: usize,
    /// Samples per pixel (camera samples; alpha is their coverage). 256 (DESIGN §4): the
    /// test views' indirect pass is then quiet enough to measure issue 7's 28 dB, though its
    /// noise still costs ≈ 1 dB there (session 77: see `--test-spp`); the demo renders 128² at
    /// 32 spp.
    #[arg(long, default_value_t = 256)]
    pub spp: u32,
    /// Samples per pixel for the test views (their ground-truth passes and relit images)
    /// instead of `--spp`: a quieter reference to measure against (the indirect pass's noise
    /// falls as 1/spp in squared error) while the training images keep `--spp`'s noise. The
    /// training views are the same bytes whatever this is.
    #[arg(long)]
    #[serde(default)]
    pub test_spp: Option<u32>,
    /// Maximum surface vertices per path (≥ 4 recommended).
    #[arg(long, default_value_t = 8)]
    pub max_bounces: u32,
    /// Random seed (same seed, same bytes).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Training light: a built-in map name (sky, studio, sunset, overcast).
    #[arg(long, default_value = "sky")]
    pub train_env: String,
    /// A user's .hdr/.exr lat-long map (Blender convention) as the training light instead.
    #[arg(long)]
    pub envmap: Option<PathBuf>,
    /// Comma-separated built-in maps for the relit test renders (default: every other built-in).
    #[arg(long, value_delimiter = ',')]
    pub relight_envs: Option<Vec<String>>,
    /// Benchmark instead of writing a dataset: samples/s and the spp for noise < 1 % on one
    /// test view of `--scene` (or every scene with `--scene all`), printed as JSON lines.
    #[arg(long)]
    pub bench: bool,
    /// Resolution (width) of the procedural env maps; height is half.
    #[arg(long, default_value_t = 512)]
    pub env_width: usize,
    /// Render the test views from these cameras instead of the scene's band: a Blender
    /// `transforms_*.json`, or a dataset folder (its test views). Images are `--res` square;
    /// the cameras are scaled to it (they must be square too). `--test-views` is then ignored.
    #[arg(long)]
    #[serde(default)]
    pub test_cameras: Option<PathBuf>,
    /// The cameras' elevation band in degrees, `MIN,MAX` (default: the scene's, 14–79° for
    /// spheres); e.g. `45,80` for a capture from above only.
    #[arg(long, value_delimiter = ',', num_args = 1, allow_hyphen_values = true)]
    #[serde(default)]
    pub elevation: Option<Vec<f32>>,
    /// The cameras' azimuth range in degrees, `MIN,MAX` (default: the whole circle, −180,180);
    /// e.g. `-90,90` for a half orbit.
    #[arg(long, value_delimiter = ',', num_args = 1, allow_hyphen_values = true)]
    #[serde(default)]
    pub azimuth: Option<Vec<f32>>,
    /// Replace `--out` if it already holds files (without it such a folder is refused: a new
    /// dataset over an old one would keep the old one's extra views).
    #[arg(long)]
    #[serde(default)]
    pub overwrite: bool,
}

/// A `MIN,MAX` range of degrees within [lo, hi], MIN < MAX.
fn degree_range(flag: &str, range: &[f32], lo: f32, hi: f32) -> anyhow::Result<(f32, f32)> {
    match *range {
        [a, b] if a.is_finite() && b.is_finite() && lo <= a && a < b && b <= hi => Ok((a, b)),
        _ => anyhow::bail!("{flag} {range:?}: give MIN,MAX in degrees, MIN < MAX, both within {lo}..={hi}"),
    }
}

/// The test cameras of `--test-cameras`, scaled to `res` × `res` and named `test_XXX`.
fn load_test_cameras(path: &std::path::Path, res: u32) -> anyhow::Result<Vec<crate::camera::Camera>> {
    let what = || format!("--test-cameras {}", path.display());
    let views = if path.is_dir() {
        crate::io::dataset::Dataset::open(path).with_context(what)?.test
    } else {
        let root = path.parent().map(PathBuf::from).unwrap_or_default();
        crate::io::dataset::read_transforms_sized(&root, path, None).with_context(what)?
    };
    anyhow::ensure!(!views.is_empty(), "{}: no test views", what());
    views
        .into_iter()
        .enumerate()
        .map(|(i, v)| {
            let cam = v.camera;
            anyhow::ensure!(
                cam.width == cam.height,
                "{}: view {} is {}×{}; synth renders square images",
                what(),
                cam.name,
                cam.width,
                cam.height
            );
            let mut cam = cam.scaled(res, res);
            cam.name = format!("test_{i:03}");
            Ok(cam)
        })
        .collect()
}

impl SynthArgs {
    /// The demo configuration: 128², 48 train + 8 test views, 3 relit maps.
    pub fn demo(out: PathBuf) -> SynthArgs {
        SynthArgs {
            scene: "spheres".into(),
            out,
            res: 128,
            train_views: 48,
            test_views: 8,
            spp: 32,
            test_spp: None,
            max_bounces: 8,
            seed: 0,
            train_env: "sky".into(),
            envmap: None,
            relight_envs: None,
            bench: false,
            env_width: 512,
            test_cameras: None,
            elevation: None,
            azimuth: None,
            overwrite: false,
        }
    }
}

fn builtin_env(name: &str, width: usize, out: &std::path::Path) -> anyhow::Result<EnvLight> {
    let map = procedural_map(name, width, width / 2).with_context(|| {
        format!("--relight-envs/--train-env: unknown env '{name}' (built-ins: {})", PROCEDURAL.join(", "))
    })?;
    // Save as .hdr, then light the scene with exactly what the file holds (RGBE-quantised).
    let path = out.join("envmaps").join(format!("{name}.hdr"));
    map.save(&path)?;
    Ok(EnvLight::new(name, EnvMap::load(&path)?))
}

/// A user's lat-long map (`EnvMap::load` clamps the tiny negative values of half-float maps).
fn load_user_env(path: &std::path::Path) -> anyhow::Result<EnvMap> {
    Ok(EnvMap::load(path).with_context(|| format!("--envmap {}", path.display()))?)
}

fn run_bench(args: &SynthArgs) -> anyhow::Result<()> {
    let names: Vec<&str> = if args.scene == "all" { scene::SCENES.to_vec() } else { vec![args.scene.as_str()] };
    let map = procedural_map(&args.train_env, args.env_width, args.env_width / 2)
        .with_context(|| format!("--train-env: unknown env '{}'", args.train_env))?;
    let env = EnvLight::new(args.train_env.clone(), map);
    for name in names {
        let scene = scene::build(name).with_context(|| format!("--scene: unknown scene '{name}'"))?;
        let cam = dataset::cameras(&scene.rig, 1, args.res, true, args.seed).remove(0);
        let opts = RenderOptions { spp: args.spp, max_bounces: args.max_bounces, rr_start: 3 };
        let r = bench::measure(&scene, &env, &cam, &opts, args.seed);
        println!(
            "{}",
            serde_json::json!({"scene": name, "env": args.train_env, "res": args.res, "spp": args.spp,
                "threads": rayon::current_num_threads(), "seconds_4_renders": r.seconds,
                "samples_per_s": r.samples_per_s, "relative_noise": r.relative_noise, "spp_for_1pct_noise": r.spp_for_1pct})
        );
    }
    Ok(())
}

pub fn run(args: &SynthArgs) -> anyhow::Result<()> {
    if args.bench {
        return run_bench(args);
    }
    let t0 = Instant::now();
    let mut scene = scene::build(&args.scene).with_context(|| {
        format!("--scene: unknown scene '{}' (built-ins: {})", args.scene, scene::SCENES.join(", "))
    })?;
    if let Some(range) = &args.elevation {
        (scene.rig.elev_min, scene.rig.elev_max) = degree_range("--elevation", range, -89.0, 89.0)?;
    }
    if let Some(range) = &args.azimuth {
        (scene.rig.az_min, scene.rig.az_max) = degree_range("--azimuth", range, -360.0, 360.0)?;
        anyhow::ensure!(
            scene.rig.az_max - scene.rig.az_min <= 360.0,
            "--azimuth {},{}: the range spans more than 360°",
            scene.rig.az_min,
            scene.rig.az_max
        );
    }
    anyhow::ensure!((8..=4096).contains(&args.res), "--res {} is out of range [8, 4096]", args.res);
    anyhow::ensure!(
        args.spp >= 1 && args.test_spp.is_none_or(|n| n >= 1) && args.max_bounces >= 1,
        "--spp, --test-spp and --max-bounces must be ≥ 1"
    );
    let test_spp = args.test_spp.unwrap_or(args.spp);
    anyhow::ensure!(
        (16..=16384).contains(&args.env_width),
        "--env-width {} is out of range [16, 16384]",
        args.env_width
    );
    anyhow::ensure!(
        (1..=10_000).contains(&args.train_views) && args.test_views <= 10_000,
        "--train-views must be in 1..=10000 and --test-views in 0..=10000 (got {} and {})",
        args.train_views,
        args.test_views
    );
    // ("sky" is --train-env's default: only another name is a conflict that can be seen.)
    if args.envmap.is_some() && args.train_env != "sky" {
        anyhow::bail!("--envmap and --train-env both name the training light: give one");
    }
    // Every built-in light named exists, before anything is written.
    let named =
        std::iter::once(&args.train_env).filter(|_| args.envmap.is_none()).chain(args.relight_envs.iter().flatten());
    for name in named.filter(|n| !n.is_empty()) {
        if !PROCEDURAL.contains(&name.as_str()) {
            anyhow::bail!("--relight-envs/--train-env: unknown env '{name}' (built-ins: {})", PROCEDURAL.join(", "));
        }
    }
    // The dataset is written beside `--out` and moved there whole at the end: a synthesis that
    // fails or is stopped half-way leaves no half-written dataset (nor a mix of two).
    if args.out.exists() && !args.out.is_dir() {
        anyhow::bail!("--out {}: exists and is not a folder", args.out.display());
    }
    let holds_files = std::fs::read_dir(&args.out).is_ok_and(|mut d| d.next().is_some());
    if holds_files && !args.overwrite {
        anyhow::bail!(
            "--out {}: exists and is not empty; pass --overwrite to replace it, or name a new folder",
            args.out.display()
        );
    }
    let partial = crate::io::atomic::PartialDir::beside(&args.out).context("--out")?;
    let out = partial.path();

    // Lights.
    let mut env_files = serde_json::Map::new();
    let mut env_desc = serde_json::Map::new();
    let train_env = match &args.envmap {
        Some(path) => {
            let map = load_user_env(path)?;
            let name = path.file_stem().and_then(|s| s.to_str()).unwrap_or("user").to_string();
            let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("hdr").to_ascii_lowercase();
            let dst = out.join("envmaps").join(format!("{name}.{ext}"));
            map.save(&dst)?;
            env_files.insert(name.clone(), format!("envmaps/{name}.{ext}").into());
            env_desc
                .insert(name.clone(), serde_json::json!({"kind": "user map", "source": path.display().to_string()}));
            EnvLight::new(name, EnvMap::load(&dst)?)
        }
        None => {
            let e = builtin_env(&args.train_env, args.env_width, out)?;
            env_files.insert(e.name.clone(), format!("envmaps/{}.hdr", e.name).into());
            env_desc.insert(e.name.clone(), procedural_description(&e.name));
            e
        }
    };
    let relight_names: Vec<String> = match &args.relight_envs {
        Some(v) => v.iter().filter(|s| !s.is_empty()).cloned().collect(),
        None => PROCEDURAL.iter().filter(|n| **n != train_env.name).map(|s| s.to_string()).collect(),
    };
    let mut relight = Vec::new();
    for name in &relight_names {
        let e = builtin_env(name, args.env_width, out)?;
        env_files.insert(name.clone(), format!("envmaps/{name}.hdr").into());
        env_desc.insert(name.clone(), procedural_description(name));
        relight.push(e);
    }

    let opts = RenderOptions { spp: args.spp, max_bounces: args.max_bounces, rr_start: 3 };
    let test_opts = RenderOptions { spp: test_spp, ..opts };
    let train_cams = dataset::cameras(&scene.rig, args.train_views, args.res, false, args.seed);
    let test_cams = match &args.test_cameras {
        Some(path) => load_test_cameras(path, args.res)?,
        None => dataset::cameras(&scene.rig, args.test_views, args.res, true, args.seed),
    };
    let px = (args.res as u64).pow(2);
    // Saturating: absurd sizes must not overflow a progress bar's total.
    let samples = |views: usize, spp: u32| px.saturating_mul(views as u64).saturating_mul(spp as u64);
    let total =
        samples(train_cams.len(), opts.spp).saturating_add(samples(test_cams.len() * (1 + relight.len()), test_spp));
    let bar = indicatif::ProgressBar::new(total);
    bar.set_style(
        indicatif::ProgressStyle::with_template("synth {msg} [{elapsed_precise}] {wide_bar} {percent}% ETA {eta}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_message(args.scene.clone());

    // Train views.
    let t_train = Instant::now();
    let mut frames_train = Vec::new();
    for (i, cam) in train_cams.iter().enumerate() {
        let img = dataset::render_view(&scene, &train_env, cam, &opts, args.seed, (1 << 32) | i as u64, &bar);
        let dir = out.join(&cam.name);
        crate::io::image::write_image(&dir.join("rgba.png"), &dataset::rgba_png(cam, &img))?;
        dataset::write_json(&dir.join("metadata.json"), &dataset::metadata(cam, &train_env.name, args.spp))?;
        frames_train.push(
            serde_json::json!({"file_path": format!("./{}/rgba", cam.name), "transform_matrix": cam.to_blender_rows()}),
        );
    }
    let train_s = t_train.elapsed().as_secs_f64();

    // Test views with every pass, then relit.
    let t_test = Instant::now();
    let mut frames_test = Vec::new();
    let mut stats = Vec::new();
    let mut relight_s = 0.0;
    for (i, cam) in test_cams.iter().enumerate() {
        let img = dataset::render_view(&scene, &train_env, cam, &test_opts, args.seed, (2 << 32) | i as u64, &bar);
        let dir = out.join(&cam.name);
        dataset::write_test_passes(&dir, cam, &img)?;
        dataset::write_json(&dir.join("metadata.json"), &dataset::metadata(cam, &train_env.name, test_spp))?;
        stats.push(dataset::pass_stats(&img));
        frames_test.push(
            serde_json::json!({"file_path": format!("./{}/rgba", cam.name), "transform_matrix": cam.to_blender_rows()}),
        );
        let tr = Instant::now();
        for (k, env) in relight.iter().enumerate() {
            let id = ((3 + k as u64) << 32) | i as u64;
            let img = dataset::render_view(&scene, env, cam, &test_opts, args.seed, id, &bar);
            crate::io::image::write_image(&dir.join(format!("rgba_{}.png", env.name)), &dataset::rgba_png(cam, &img))?;
        }
        relight_s += tr.elapsed().as_secs_f64();
    }
    let test_s = t_test.elapsed().as_secs_f64() - relight_s;
    bar.finish();

    let fov = scene.rig.camera_angle_x;
    // Given test cameras keep their own field of view (one per Blender file: the first's).
    let test_fov = test_cams.first().map_or(fov, |c| c.fov_x());
    for (name, frames, fov) in
        [("transforms_train.json", frames_train, fov), ("transforms_test.json", frames_test, test_fov)]
    {
        dataset::write_json(
            &out.join(name),
            &serde_json::json!({"camera_angle_x": fov, "w": args.res, "h": args.res, "env": train_env.name, "frames": frames}),
        )?;
    }
    let readme = serde_json::json!({
        "generator": "radiogs synth (the project's reference path tracer, src/synth/)",
        "renderer": "unidirectional path tracing, NEE to the env map + BSDF sampling with MIS (power heuristic), Russian roulette",
        "scene": args.scene,
        "resolution": [args.res, args.res],
        "camera_angle_x": fov,
        "n_train": args.train_views,
        "n_test": test_cams.len(),
        "seed": args.seed,
        "args": args,
        "sampling": {
            "spp": args.spp,
            "test_spp": test_spp,
            "pixel_filter": "box, stratified sub-pixel jitter (ceil(sqrt(spp))² grid)",
            "max_bounces": args.max_bounces,
            "russian_roulette_from_bounce": opts.rr_start,
            "mis": "power heuristic, one env sample + one BSDF sample per vertex",
            "env_sampling": "2D piecewise-constant marginal/conditional CDF over texels, weight = max luminance in 3×3 × sin θ",
            "clamp": "none",
            "denoiser": "none",
        },
        "brdf": "f = (1 − E(n·ω_o, r))·a/π + F·D·G/(4 NoL NoV), E the GGX lobe's directional albedo (split-sum LUT: the diffuse base under the specular layer, as Blender's Principled BSDF); GGX D with α = r²; height-correlated Smith G = 1/(1 + Λ(n·ω_i) + Λ(n·ω_o)); Schlick F, f0 = 0.04; cosines clamped to [1e-6, 1]",
        "color": "rgba/albedo PNGs: linear -> clip[0,1] -> sRGB OETF; straight (un-premultiplied) alpha; alpha = pixel coverage (fraction of camera samples hitting geometry); background transparent (0,0,0,0).",
        "cameras": {
            "radius": scene.rig.radius, "elev_min": scene.rig.elev_min, "elev_max": scene.rig.elev_max,
            "az_min": scene.rig.az_min, "az_max": scene.rig.az_max, "target": scene.rig.target,
            "distribution": match &args.test_cameras {
                Some(p) => format!("train: stratified uniform-solid-angle band with golden-angle azimuth; test: the cameras of {}", p.display()),
                None => "train: stratified uniform-solid-angle band with golden-angle azimuth; test: seeded uniform random in the same band".to_string(),
            },
            "convention": "transform_matrix = camera-to-world (Blender/OpenGL camera: looks along -Z, +Y up), world +Z up",
        },
        "environment": {
            "train_env": train_env.name,
            "relight_envs": relight_names,
            "strength": 1.0,
            "files": env_files,
            "maps": env_desc,
            "resolution": [train_env.map.width, train_env.map.height],
            "rotation": "none",
            "mapping": "Blender equirectangular; unit world dir d=(x,y,z), +Z up: u = 0.5 - atan2(d.y, d.x)/(2pi), v = 1 - acos(d.z)/pi, with u=0 the left column and v=1 the TOP row (so +X is the centre column, +Y is at u=0.25, the zenith is the top row); bilinear lookup (crate::envmap). Rendered with the map as stored in the .hdr file.",
        },
        "objects": scene.objects,
        "materials": scene.materials,
        "files": {
            "train_XXX/rgba.png": "RGBA 8-bit sRGB, lit by train env",
            "test_XXX/rgba.png": "RGBA 8-bit sRGB, lit by train env",
            "test_XXX/rgba_<env>.png": "RGBA 8-bit relit by <env> (same camera)",
            "test_XXX/albedo.png": "base colour (material albedo), sRGB-encoded, RGBA; decode sRGB to linear before comparing",
            "test_XXX/normal.png": "world-space shading normal of the first hit (facing the camera), (n*0.5+0.5)*255, no gamma, RGBA",
            "test_XXX/normal.exr": "float32 R,G,B = unit world-space normal, A = coverage",
            "test_XXX/roughness.png": "roughness r (α = r²), linear 8-bit, LA",
            "test_XXX/depth.exr": "float32 R=G=B = camera-space z (distance along the optical axis, NOT ray distance) of the first hit, averaged over covering samples; A = coverage; 0 on background",
            "test_XXX/indirect.exr": "float32 linear radiance, un-premultiplied: R,G,B = outgoing radiance at the first hit due to indirect incident light (all light received at path vertices ≥ 1), A = coverage",
            "test_XXX/direct.exr": "float32 linear radiance, un-premultiplied: light arriving at the first hit straight from the env (NEE + escaping BSDF rays, MIS); direct + indirect = rgba (linear, before clipping)",
            "XXX/metadata.json": "TensoIR-style per-view metadata (cam_transform_mat row-major Blender camera-to-world)",
        },
        "timings_s": {"train_s": train_s, "test_with_passes_s": test_s, "relight_s": relight_s, "total_s": t0.elapsed().as_secs_f64()},
        "n_renders": train_cams.len() + test_cams.len() * (1 + relight.len()),
        "machine": format!("{} rayon threads", rayon::current_num_threads()),
        "test_pass_stats": stats,
    });
    dataset::write_json(&out.join("README.json"), &readme)?;
    partial.publish(&args.out)?;
    eprintln!("synth: wrote {} in {:.1} s", args.out.display(), t0.elapsed().as_secs_f64());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_dir::TempDir;

    fn tiny(out: PathBuf) -> SynthArgs {
        SynthArgs {
            res: 16,
            train_views: 2,
            test_views: 1,
            spp: 2,
            env_width: 32,
            relight_envs: Some(vec!["studio".into()]),
            ..SynthArgs::demo(out)
        }
    }

    /// Settings that cannot make a dataset are refused by name, and nothing is written.
    #[test]
    fn bad_settings_write_nothing() {
        let base = TempDir::new("synth-bad-settings");
        let out = base.join("out");
        let cases = [
            (SynthArgs { train_views: 0, ..tiny(out.clone()) }, "--train-views"),
            (SynthArgs { test_spp: Some(0), ..tiny(out.clone()) }, "--test-spp"),
            (SynthArgs { relight_envs: Some(vec!["sky".into(), "nope".into()]), ..tiny(out.clone()) }, "'nope'"),
            (SynthArgs { train_env: "nope".into(), ..tiny(out.clone()) }, "'nope'"),
            (SynthArgs { env_width: 100_000, ..tiny(out.clone()) }, "--env-width"),
            (
                SynthArgs { envmap: Some(out.join("x.hdr")), train_env: "studio".into(), ..tiny(out.clone()) },
                "--envmap and --train-env",
            ),
        ];
        for (args, says) in cases {
            let err = run(&args).unwrap_err().to_string();
            assert!(err.contains(says), "{err}");
            assert!(!out.exists(), "{says}: wrote {}", out.display());
        }
    }

    #[test]
    fn test_cameras_come_from_a_dataset_folder_or_a_transforms_file() {
        let base = TempDir::new("synth-cams");
        let src = base.join("src");
        run(&SynthArgs { test_views: 2, ..tiny(src.clone()) }).unwrap();
        let matrices = |dir: &std::path::Path| -> Vec<serde_json::Value> {
            let tr: serde_json::Value =
                serde_json::from_slice(&std::fs::read(dir.join("transforms_test.json")).unwrap()).unwrap();
            tr["frames"].as_array().unwrap().iter().map(|f| f["transform_matrix"].clone()).collect()
        };
        let want = matrices(&src);
        for (k, given) in [src.clone(), src.join("transforms_test.json")].into_iter().enumerate() {
            let out = base.join(format!("out{k}"));
            // Another scene, resolution and test-view count: the cameras come from `given`.
            let args = SynthArgs {
                scene: "cornell".into(),
                res: 24,
                test_views: 5,
                test_cameras: Some(given),
                ..tiny(out.clone())
            };
            run(&args).unwrap();
            // The same poses, up to the f32 round trip of the camera centre through the file.
            let got = matrices(&out);
            assert_eq!(got.len(), want.len());
            for (g, w) in got.iter().zip(&want) {
                for r in 0..4 {
                    for c in 0..4 {
                        let (a, b) = (g[r][c].as_f64().unwrap(), w[r][c].as_f64().unwrap());
                        assert!((a - b).abs() < 1e-5, "pose entry ({r}, {c}): {a} vs {b}");
                    }
                }
            }
            let meta: serde_json::Value =
                serde_json::from_slice(&std::fs::read(out.join("test_001/metadata.json")).unwrap()).unwrap();
            assert_eq!(meta["imw"], 24);
            assert!(!out.join("test_002").exists());
        }
        let err = run(&SynthArgs { test_cameras: Some(base.join("missing")), ..tiny(base.join("bad")) }).unwrap_err();
        assert!(format!("{err:#}").contains("--test-cameras"), "{err:#}");
        // A synthesis that fails after it began writing leaves nothing behind.
        assert!(!base.join("bad").exists() && !base.join("bad.partial").exists());
    }

    #[test]
    fn dataset_layout_and_same_seed_same_bytes() {
        let base = TempDir::new("synth-layout");
        let (a, b) = (base.join("a"), base.join("b"));
        run(&tiny(a.clone())).unwrap();
        run(&tiny(b.clone())).unwrap();
        for f in [
            "README.json",
            "transforms_train.json",
            "transforms_test.json",
            "envmaps/sky.hdr",
            "envmaps/studio.hdr",
            "train_001/rgba.png",
            "train_001/metadata.json",
            "test_000/metadata.json",
            "test_000/rgba.png",
            "test_000/rgba_studio.png",
            "test_000/albedo.png",
            "test_000/normal.png",
            "test_000/normal.exr",
            "test_000/roughness.png",
            "test_000/depth.exr",
            "test_000/indirect.exr",
            "test_000/direct.exr",
        ] {
            let (x, y) = (std::fs::read(a.join(f)).unwrap(), std::fs::read(b.join(f)).unwrap());
            if f.ends_with(".png") || f.ends_with(".exr") {
                assert_eq!(x, y, "{f}: same seed, same bytes");
            }
        }
        // The Blender frame and the TensoIR metadata describe the same camera.
        let tr: serde_json::Value =
            serde_json::from_slice(&std::fs::read(a.join("transforms_test.json")).unwrap()).unwrap();
        assert_eq!(tr["frames"][0]["file_path"], "./test_000/rgba");
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(a.join("test_000/metadata.json")).unwrap()).unwrap();
        let flat: Vec<f32> =
            meta["cam_transform_mat"].as_str().unwrap().split(',').map(|s| s.parse().unwrap()).collect();
        for r in 0..4 {
            for c in 0..4 {
                let v = tr["frames"][0]["transform_matrix"][r][c].as_f64().unwrap() as f32;
                assert!((v - flat[r * 4 + c]).abs() < 1e-6);
            }
        }
        assert_eq!(meta["imw"], 16);
        assert_eq!(meta["envmap"], "sky");
    }

    /// `--test-spp` renders the test views (passes and relit images) with its own sample
    /// count and leaves the training views' bytes as `--spp` makes them.
    #[test]
    fn test_spp_changes_the_test_views_only() {
        let base = TempDir::new("synth-test-spp");
        let (plain, quiet) = (base.join("plain"), base.join("quiet"));
        run(&tiny(plain.clone())).unwrap();
        run(&SynthArgs { test_spp: Some(16), ..tiny(quiet.clone()) }).unwrap();
        let read = |dir: &std::path::Path, f: &str| std::fs::read(dir.join(f)).unwrap();
        for f in ["train_000/rgba.png", "train_001/rgba.png", "transforms_train.json", "transforms_test.json"] {
            assert_eq!(read(&plain, f), read(&quiet, f), "{f}");
        }
        for f in ["test_000/rgba.png", "test_000/indirect.exr", "test_000/rgba_studio.png"] {
            assert_ne!(read(&plain, f), read(&quiet, f), "{f}");
        }
        let json =
            |dir: &std::path::Path, f: &str| -> serde_json::Value { serde_json::from_slice(&read(dir, f)).unwrap() };
        assert_eq!(json(&quiet, "README.json")["sampling"]["spp"], 2);
        assert_eq!(json(&quiet, "README.json")["sampling"]["test_spp"], 16);
        assert_eq!(json(&plain, "README.json")["sampling"]["test_spp"], 2);
        assert_eq!(json(&quiet, "test_000/metadata.json")["spp"], 16);
        assert_eq!(json(&quiet, "train_000/metadata.json")["spp"], 2);
    }

    /// `--elevation` and `--azimuth` set the band every camera lies in; bad ranges are refused
    /// before anything is written.
    #[test]
    fn camera_band_flags_bound_every_camera() {
        let base = TempDir::new("synth-band");
        let out = base.join("band");
        let args = SynthArgs {
            train_views: 6,
            test_views: 3,
            elevation: Some(vec![45.0, 80.0]),
            azimuth: Some(vec![-90.0, 30.0]),
            ..tiny(out.clone())
        };
        run(&args).unwrap();
        for split in ["train", "test"] {
            let tr: serde_json::Value =
                serde_json::from_slice(&std::fs::read(out.join(format!("transforms_{split}.json"))).unwrap()).unwrap();
            for f in tr["frames"].as_array().unwrap() {
                let m = &f["transform_matrix"];
                let eye = [0, 1, 2].map(|r| m[r][3].as_f64().unwrap());
                // The spheres scene's band is centred on (0, 0, target_z) at radius 4.
                let elev = ((eye[2] - scene::build("spheres").unwrap().rig.target.z as f64) / 4.0).asin().to_degrees();
                let az = eye[1].atan2(eye[0]).to_degrees();
                assert!((45.0 - 1e-3..=80.0 + 1e-3).contains(&elev), "{split}: elevation {elev}");
                assert!((-90.0 - 1e-3..=30.0 + 1e-3).contains(&az), "{split}: azimuth {az}");
            }
        }
        for (elevation, azimuth, says) in [
            (Some(vec![80.0, 45.0]), None, "--elevation"),
            (Some(vec![0.0, 95.0]), None, "--elevation"),
            (Some(vec![10.0]), None, "--elevation"),
            (None, Some(vec![-180.0, 200.0]), "--azimuth"),
            (None, Some(vec![f32::NAN, 20.0]), "--azimuth"),
        ] {
            let bad = base.join("bad");
            let err = run(&SynthArgs { elevation, azimuth, ..tiny(bad.clone()) }).unwrap_err().to_string();
            assert!(err.contains(says), "{err}");
            assert!(!bad.exists() && !base.join("bad.partial").exists());
        }
    }

    /// A folder that holds files is refused without `--overwrite` (and left as it was); with it
    /// the new dataset replaces the old one whole, so no view of the old one survives.
    #[test]
    fn an_existing_dataset_is_replaced_only_with_overwrite() {
        let base = TempDir::new("synth-over");
        let out = base.join("out");
        run(&SynthArgs { test_views: 2, ..tiny(out.clone()) }).unwrap();
        let before = std::fs::read(out.join("transforms_test.json")).unwrap();
        let err = run(&SynthArgs { test_views: 1, ..tiny(out.clone()) }).unwrap_err().to_string();
        assert!(err.contains("--overwrite") && err.contains("not empty"), "{err}");
        assert_eq!(std::fs::read(out.join("transforms_test.json")).unwrap(), before);
        run(&SynthArgs { test_views: 1, overwrite: true, ..tiny(out.clone()) }).unwrap();
        assert!(out.join("test_000").is_dir() && !out.join("test_001").exists());
        assert!(!base.join("out.partial").exists());
        // An empty folder is fine without the flag (made beforehand, as scripts do).
        let empty = out.join("empty");
        std::fs::create_dir_all(&empty).unwrap();
        let err = run(&SynthArgs { train_views: 1, ..tiny(out.clone()) }).unwrap_err().to_string();
        assert!(err.contains("not empty"), "{err}");
        run(&SynthArgs { train_views: 1, ..tiny(empty.clone()) }).unwrap();
        assert!(empty.join("transforms_train.json").is_file());
    }

    #[test]
    fn bad_arguments_are_errors_not_panics() {
        let base = TempDir::new("synth-bad-args");
        let out = base.join("out");
        let err = run(&SynthArgs { scene: "nope".into(), ..tiny(out.clone()) }).unwrap_err().to_string();
        assert!(err.contains("nope"), "{err}");
        let err = run(&SynthArgs { relight_envs: Some(vec!["moon".into()]), ..tiny(out.clone()) }).unwrap_err();
        assert!(format!("{err:#}").contains("moon"));
    }
}
