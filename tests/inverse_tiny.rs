//! The inverse stage on a scene made here: a Lambert plane of surfels under a known constant
//! light, photographed with the PBR renderer. Starting from the right geometry with the wrong
//! albedo (0.3) and the light held fixed at the truth, the recovered albedo must converge to
//! the true one; then eval, render and relight must run on the result.

use radiogs::camera::Camera;
use radiogs::envmap::EnvMap;
use radiogs::io::dataset::Dataset;
use radiogs::io::image::{Image, write_image};
use radiogs::pbr_scene::PbrScene;
use radiogs::surfels::{Surfels, quat_with_normal};
use radiogs::train::checkpoint::Checkpoint;
use radiogs::train::config::{Background, TrainConfig};
use std::path::Path;

#[path = "../src/test_dir.rs"]
mod test_dir;
use test_dir::TempDir;

const TRUE_ALBEDO: [f32; 3] = [0.6, 0.35, 0.15];
const LIGHT: f32 = 1.2;

/// A fresh folder, removed at the end of the test (pass or fail).
fn temp_dir(name: &str) -> TempDir {
    TempDir::new(&format!("inv-{name}"))
}

/// The settings every inverse test here shares: its data and run folders, a black background,
/// no periodic checkpoints, sparse logs.
fn tiny_config(data: &Path, out: &Path) -> TrainConfig {
    TrainConfig {
        data: data.to_path_buf(),
        out: out.to_path_buf(),
        background: Background::Black,
        checkpoint_every: 0,
        log_every: 50,
        ..TrainConfig::default()
    }
}

fn plane() -> Surfels {
    let mut s = Surfels::default();
    for a in 0..8 {
        for b in 0..8 {
            let p = [-0.35 + 0.1 * a as f32, -0.35 + 0.1 * b as f32, 0.0];
            s.push(p, [0.08, 0.08], quat_with_normal([0.0, 0.0, 1.0]), 0.98, [0.5; 3], TRUE_ALBEDO, 0.9);
        }
    }
    s.sh_degree = 0;
    s
}

/// Render `cameras` of `scene` over black into `dir` as a Blender-layout dataset (the same frames
/// for train and test). The straight colour is chosen so that the loss's sRGB composite over
/// black (c·α) equals the PBR render's (linear composite, then encoded), also at partly covered
/// pixels.
fn write_views(dir: &Path, scene: &PbrScene, cameras: &[Camera], angle: f32) {
    let mut frames = Vec::new();
    for cam in cameras {
        let img = scene.render(cam, [0.0; 3]);
        let mut out = Image::new(cam.width, cam.height, 4);
        for (i, px) in out.data.chunks_exact_mut(4).enumerate() {
            let a = img.alpha[i];
            for c in 0..3 {
                px[c] = if a > 1e-4 { (img.pbr[i][c] / a).min(1.0) } else { 0.0 };
            }
            px[3] = a;
        }
        write_image(&dir.join(format!("train/{}.png", cam.name)), &out).unwrap();
        frames.push(serde_json::json!({
            "file_path": format!("./train/{}", cam.name), "transform_matrix": cam.to_blender_rows()
        }));
    }
    let json = serde_json::json!({"camera_angle_x": angle, "frames": frames});
    std::fs::write(dir.join("transforms_train.json"), json.to_string()).unwrap();
    std::fs::write(dir.join("transforms_test.json"), json.to_string()).unwrap();
}

/// Four views of the plane lit by the constant env, rendered by the PBR path.
fn make_dataset(dir: &Path) -> Surfels {
    let gt = plane();
    let env = EnvMap::constant(32, 16, [LIGHT; 3]);
    let scene = PbrScene::new(
        gt.clone(),
        env,
        64,
        radiogs::shade::incident::RayStart::offset_only(1e-3),
        8,
        1,
        1,
        radiogs::train::inverse::BackFaces::default(),
    );
    let angle = 0.9f32;
    let cameras: Vec<Camera> = (0..4)
        .map(|k| {
            let a = k as f32 * std::f32::consts::FRAC_PI_2 + 0.3;
            let eye = glam::Vec3::new(0.9 * a.cos(), 0.9 * a.sin(), 1.6);
            Camera::look_at(format!("r_{k}"), eye, glam::Vec3::ZERO, 32, 32, angle)
        })
        .collect();
    write_views(dir, &scene, &cameras, angle);
    gt
}

/// The dataset and an nvs checkpoint with the right geometry, in fresh folders named by `tag`
/// (removed when the returned guards drop, at the end of the caller).
fn dataset_and_nvs_run(tag: &str) -> (TempDir, Dataset, TempDir) {
    let data = temp_dir(&format!("{tag}-data"));
    let gt = make_dataset(&data);
    let dataset = Dataset::open(&data).unwrap();
    let run = temp_dir(&format!("{tag}-run"));
    // The nvs result: the right geometry (SH from the images do not matter here).
    // SH at the observed colour (as nvs would leave them): the Lambert part of the radiance.
    let mut gt = gt;
    let white_lambert = LIGHT * (1.0 - 10f32.to_radians().sin().powi(2));
    for sh in gt.sh.iter_mut() {
        sh[0] = TRUE_ALBEDO.map(|a| radiogs::sh::rgb_to_dc(radiogs::train::consistency::encode(a * white_lambert)));
    }
    let mut c = Checkpoint { meta: serde_json::json!({"stage": "nvs", "iteration": 1}), ..Default::default() };
    c.put_surfels("params", &gt);
    c.save(&radiogs::train::nvs::checkpoint_path(&run)).unwrap();
    (data, dataset, run)
}

/// `--light-warmup N`: albedo and roughness stay exactly at their fresh values for the first N
/// iterations while the light learns; after N they move. A resumed call reports only the
/// iterations it ran.
#[test]
fn light_warmup_freezes_materials_then_releases_them() {
    let (data, dataset, run) = dataset_and_nvs_run("warmup");
    let mut cfg = TrainConfig {
        inverse_iters: 12,
        light_warmup: 12,
        env_init: 0.5,
        // The grey start: every fresh albedo is the one value `albedo_init`.
        albedo_init_hue: 0.0,
        pbr_samples: 8,
        rc_rays: 8,
        rc_surfels: 16,
        ..tiny_config(&data, &run)
    };
    cfg.save(&run.join("config.toml")).unwrap();
    let summary = radiogs::train::inverse::run(&cfg, &dataset, false).unwrap();
    assert_eq!((summary.iterations, summary.iterations_run), (12, 12));
    let frozen = radiogs::io::ply::read_ply(&run.join("point_cloud.ply")).unwrap();
    for i in 0..frozen.len() {
        let a = frozen.albedo(i);
        assert!(a.iter().all(|&c| (c - cfg.albedo_init).abs() < 1e-5), "surfel {i}: albedo {a:?}");
        let r = radiogs::surfels::sigmoid(frozen.roughness_logits[i]);
        assert!((r - cfg.roughness_init).abs() < 1e-5, "surfel {i}: roughness {r}");
    }
    let env = EnvMap::load(&run.join("envmap.exr")).unwrap();
    assert!(env.texels.iter().flatten().any(|&v| (v - 0.5).abs() > 1e-3), "the light must learn meanwhile");
    // Past the warm-up the materials move; the resumed call ran 8 iterations.
    cfg.inverse_iters = 20;
    cfg.resume = true;
    let summary = radiogs::train::inverse::run(&cfg, &dataset, false).unwrap();
    assert_eq!((summary.iterations, summary.iterations_run), (20, 8));
    let moved = radiogs::io::ply::read_ply(&run.join("point_cloud.ply")).unwrap();
    let change = (0..moved.len()).map(|i| (moved.albedo(i)[0] - cfg.albedo_init).abs()).fold(0.0f32, f32::max);
    assert!(change > 1e-3, "albedo did not move after the warm-up: {change}");
}

/// The default start (`albedo_init_hue` 1): each surfel's fresh albedo is `hued_albedo` of the
/// geometry it starts from, not the grey level. Materials are held by the warm-up so the saved
/// albedo is the start itself.
#[test]
fn default_start_takes_each_surfels_observed_hue() {
    let (data, dataset, run) = dataset_and_nvs_run("hue-start");
    let cfg = TrainConfig {
        inverse_iters: 2,
        light_warmup: 2,
        pbr_samples: 8,
        rc_rays: 8,
        rc_surfels: 16,
        ..tiny_config(&data, &run)
    };
    assert_eq!(cfg.albedo_init_hue, TrainConfig::default().albedo_init_hue);
    assert!(cfg.albedo_init_hue > 0.0, "the default start is hued");
    let ckpt = radiogs::train::nvs::checkpoint_path(&run);
    let start = Checkpoint::load(&ckpt).unwrap().get_surfels(&ckpt, "params").unwrap();
    let want = radiogs::train::albedo_chroma::hued_albedo(&start, cfg.albedo_init, cfg.albedo_init_hue);
    radiogs::train::inverse::run(&cfg, &dataset, false).unwrap();
    let got = radiogs::io::ply::read_ply(&run.join("point_cloud.ply")).unwrap();
    assert_eq!(got.len(), start.len(), "the plane is seen from one side: no twins");
    let mut spread = 0.0f32;
    for i in 0..got.len() {
        let a = got.albedo(i);
        assert!((0..3).all(|c| (a[c] - want[i][c]).abs() < 1e-4), "surfel {i}: {a:?} vs {:?}", want[i]);
        spread = spread.max(a[0] - a[2]);
    }
    // The orange plane starts redder than blue (a grey start would give 0).
    assert!(spread > 5e-3, "fresh albedo is grey: red − blue = {spread}");
}

/// `--prune-contribution`: the stage starts without the surfels that no training pixel shows
/// at that weight (here a faint one on the plane and one outside every view); 0 keeps them.
#[test]
fn prune_contribution_drops_the_surfels_no_view_shows() {
    for tau in [0.0, 1.0 / 255.0] {
        let (data, dataset, run) = dataset_and_nvs_run(&format!("prune{}", tau > 0.0));
        let path = radiogs::train::nvs::checkpoint_path(&run);
        let mut c = Checkpoint::load(&path).unwrap();
        let mut s = c.get_surfels(&path, "params").unwrap();
        let up = quat_with_normal([0.0, 0.0, 1.0]);
        s.push([0.05, 0.05, 0.01], [0.05, 0.05], up, 0.002, [0.5; 3], TRUE_ALBEDO, 0.9);
        s.push([6.0, 6.0, 0.0], [0.05, 0.05], up, 0.9, [0.5; 3], TRUE_ALBEDO, 0.9);
        c.put_surfels("params", &s);
        c.save(&path).unwrap();
        let cfg = TrainConfig {
            inverse_iters: 1,
            // Geometry held, so that the surfels can be matched by their centres.
            geometry_lr_scale: 0.0,
            prune_contribution: tau,
            pbr_samples: 4,
            rc_rays: 4,
            rc_surfels: 4,
            ..tiny_config(&data, &run)
        };
        cfg.save(&run.join("config.toml")).unwrap();
        radiogs::train::inverse::run(&cfg, &dataset, false).unwrap();
        let out = radiogs::io::ply::read_ply(&run.join("point_cloud.ply")).unwrap();
        let kept = |m: &[f32; 3]| out.means.contains(m);
        if tau == 0.0 {
            assert!(out.len() == 66 && s.means.iter().all(kept), "{} surfels", out.len());
        } else {
            // Both extras go; the plane stays but for a few rim surfels that coplanar
            // neighbours blended before them cover in every view (weights below 1/255).
            assert!(!kept(&s.means[64]) && !kept(&s.means[65]));
            let plane = s.means[..64].iter().filter(|m| kept(m)).count();
            assert!(plane >= 58 && out.len() == plane, "{plane} plane surfels of 64 kept, {} in all", out.len());
        }
    }
}

#[test]
fn lambert_plane_albedo_converges_under_known_light() {
    let (data, dataset, run) = dataset_and_nvs_run("plane");
    let cfg = TrainConfig {
        inverse_iters: 300,
        env_init: LIGHT,
        lr_env: 0.0,
        lr_albedo: 0.02,
        lambda_white_light: 0.0,
        pbr_samples: 32,
        rc_rays: 32,
        rc_surfels: 16,
        ..tiny_config(&data, &run)
    };
    cfg.save(&run.join("config.toml")).unwrap();
    let summary = radiogs::train::inverse::run(&cfg, &dataset, false).unwrap();
    assert!(!summary.interrupted && summary.iterations == 300);
    let out = radiogs::io::ply::read_ply(&run.join("point_cloud.ply")).unwrap();
    // Interior surfels (the edges are partly covered by one neighbour only).
    let mut mean = [0.0f32; 3];
    let mut count = 0.0;
    for i in 0..out.len() {
        let m = out.means[i];
        if m[0].abs() < 0.2 && m[1].abs() < 0.2 {
            let a = out.albedo(i);
            for c in 0..3 {
                mean[c] += a[c];
            }
            count += 1.0;
        }
    }
    let mean = mean.map(|v| v / count);
    for c in 0..3 {
        assert!((mean[c] - TRUE_ALBEDO[c]).abs() < 0.06, "albedo {mean:?} vs {TRUE_ALBEDO:?}");
    }
    assert!(run.join("envmap.exr").is_file());

    // Eval writes PBR / albedo metrics; relight (traced) and render run on the result.
    radiogs::eval::run(&radiogs::eval::EvalArgs {
        run: run.to_path_buf(),
        data: None,
        json: None,
        limit: 0,
        no_relight: true,
        relight_iters: 10,
        relight_rc_rays: radiogs::relight::RC_RAYS,
        relight_samples: 8,
        relight_env_importance: radiogs::relight::ENV_IMPORTANCE,
        relight_bounces: radiogs::relight::TRACED_BOUNCES,
        resolution: None,
    })
    .unwrap();
    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval/metrics.json")).unwrap()).unwrap();
    let pbr_psnr = metrics["mean"]["pbr_psnr"].as_f64().unwrap();
    assert!(pbr_psnr > 25.0, "PBR PSNR {pbr_psnr}");
    let env_file = data.join("warm.exr");
    // Warm light with a warm sun, for the traced mode's map samples to find.
    let mut warm = EnvMap::constant(32, 16, [1.5, 1.0, 0.5]);
    for k in [2 * 32 + 10, 2 * 32 + 11, 3 * 32 + 10, 3 * 32 + 11] {
        warm.texels[k] = [30.0, 20.0, 10.0];
    }
    warm.save(&env_file).unwrap();
    for (mode, name) in
        [(radiogs::relight::RelightMode::Traced, "traced"), (radiogs::relight::RelightMode::Finetune, "ft")]
    {
        let out = temp_dir(name);
        radiogs::relight::run(&radiogs::relight::RelightArgs {
            run: run.to_path_buf(),
            envmap: env_file.clone(),
            out: out.to_path_buf(),
            mode,
            iters: 20,
            rotate: 30.0,
            rc_surfels: 64,
            rc_rays: 8,
            bounces: 2,
            samples: Some(16),
            env_importance: 0.25,
            seed: 0,
        })
        .unwrap();
        let record: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("relight.json")).unwrap()).unwrap();
        assert_eq!((record["samples"].as_u64(), record["env_importance"].as_f64()), (Some(16), Some(0.25)));
        // Warm light on an orange plane: the relit plane is redder than before.
        let scene = PbrScene::from_run(&out).unwrap().unwrap();
        if mode == radiogs::relight::RelightMode::Traced {
            // Traced as recorded: 16 directions a surfel, 4 of them from the sun's texels.
            assert_eq!(scene.cache.samples, 16);
            assert_eq!(scene.cache.sample_weights.len(), scene.cache.dirs.len());
        }
        let cam = &dataset.test[0].camera;
        let img = scene.render(cam, [0.0; 3]);
        let centre = (16 * 32 + 16) as usize;
        let c = if mode == radiogs::relight::RelightMode::Traced { img.pbr[centre] } else { img.sh[centre] };
        assert!(c[0] > c[1] && c[1] > c[2], "{name}: relit centre {c:?}");
    }
    // The demo's report on this run: its turntables (both modes) play inline.
    let demo = temp_dir("report");
    radiogs::commands::demo::write_turntables(&demo.join("orbit"), &run).unwrap();
    let report = demo.join("report.html");
    radiogs::commands::demo::write_report(&report, &data, &run, &[("synthesis", 20.3), ("training", 361.0)]).unwrap();
    let html = std::fs::read_to_string(&report).unwrap();
    assert!(html.contains("6 min 21 s in all: synthesis 20.3 s, training 6 min 01 s"), "step times in the report");
    assert_eq!(html.matches("data:image/apng;base64,").count(), 2, "two turntables inline");
    for mode in ["surfel", "pbr"] {
        assert!(demo.join(format!("orbit/{mode}/orbit_035.png")).is_file(), "{mode}");
    }
}

/// A resumed inverse stage equals the uninterrupted one bit for bit: the checkpoint keeps the
/// light, the optimiser moments, the incident cache and each cache row's trace iteration
/// (rows are re-traced by age, here every 2 iterations with `cache_every` 8), and the
/// albedo–light gauge steps land on the same iterations.
#[test]
fn inverse_resume_is_exact_with_per_row_refresh() {
    let (data, dataset, straight) = dataset_and_nvs_run("resume-a");
    let cfg = |out: &Path| TrainConfig {
        inverse_iters: 20,
        cache_every: 8,
        // The albedo–light gauge at 5, 10 (after the resume) and 15.
        gauge_every: 5,
        pbr_samples: 8,
        rc_rays: 8,
        rc_surfels: 16,
        ..tiny_config(&data, out)
    };
    radiogs::train::inverse::run(&cfg(&straight), &dataset, false).unwrap();
    let split = temp_dir("resume-b-run");
    std::fs::copy(radiogs::train::nvs::checkpoint_path(&straight), radiogs::train::nvs::checkpoint_path(&split))
        .unwrap();
    let stopped = radiogs::train::inverse::run_until(&cfg(&split), &dataset, false, Some(9)).unwrap();
    assert!(stopped.interrupted && stopped.iterations == 9);
    let resumed = TrainConfig { resume: true, ..cfg(&split) };
    let summary = radiogs::train::inverse::run(&resumed, &dataset, false).unwrap();
    assert_eq!((summary.iterations, summary.iterations_run), (20, 11));
    for file in ["point_cloud.ply", "envmap.exr"] {
        let a = std::fs::read(straight.join(file)).unwrap();
        let b = std::fs::read(split.join(file)).unwrap();
        assert!(a == b, "{file}: the resumed inverse run differs from the uninterrupted one");
    }
}

/// The albedo–light gauge (`gauge_every`) recovers the scale the image gradient cannot: a
/// grey corner (floor + wall, albedo 0.6 under a constant light 1.2, so each plane lights the
/// other) photographed with the PBR renderer, its SH at the radiance the rendering equation
/// gives (a few fixed-point passes, so the traced indirect light is consistent). The inverse
/// stage starts from the same pictures explained at half the albedo under twice the light —
/// equal Lambert light from the env, half the inter-reflected light — with every learning
/// rate 0 or negligible, so only the gauge step moves anything; it must land near ×2.
#[test]
fn gauge_recovers_the_albedo_scale_from_inter_reflections() {
    use radiogs::shade::incident::RayStart;
    const ALBEDO: f32 = 0.6;
    let mut gt = Surfels::default();
    for a in 0..10 {
        for b in 0..10 {
            let (p, q) = (-0.45 + 0.1 * a as f32, -0.45 + 0.1 * b as f32);
            // Floor z = 0 and a wall x = −0.5 facing +x, meeting along y.
            gt.push([p, q, 0.0], [0.07, 0.07], quat_with_normal([0.0, 0.0, 1.0]), 0.98, [0.5; 3], [ALBEDO; 3], 0.9);
            gt.push(
                [-0.5, q, p + 0.5],
                [0.07, 0.07],
                quat_with_normal([1.0, 0.0, 0.0]),
                0.98,
                [0.5; 3],
                [ALBEDO; 3],
                0.9,
            );
        }
    }
    gt.sh_degree = 0;
    let env = EnvMap::constant(32, 16, [LIGHT; 3]);
    let start = RayStart::offset_only(1e-3);
    // Fixed point: SH = the Lambert-dominated radiance along the normal, the indirect light
    // traced from the previous SH.
    for _ in 0..4 {
        let scene =
            PbrScene::new(gt.clone(), env.clone(), 64, start, 8, 1, 1, radiogs::train::inverse::BackFaces::default());
        let n = gt.len();
        let normal: Vec<[f32; 3]> = (0..n).map(|i| gt.normal(i)).collect();
        let rough = vec![0.9f32; n];
        let inp = scene.cache.inputs(&scene.mats.albedo, &rough, &normal, &normal);
        let (mut d, mut ind) = (vec![[0.0f32; 3]; n], vec![[0.0f32; 3]; n]);
        radiogs::shade::pbr::shade_surfels(&inp, &env, &mut d, &mut ind).unwrap();
        for i in 0..n {
            let c = [0, 1, 2].map(|k| radiogs::train::consistency::encode(d[i][k] + ind[i][k]));
            gt.sh[i][0] = c.map(radiogs::sh::rgb_to_dc);
        }
    }
    let data = temp_dir("gauge-data");
    let scene = PbrScene::new(gt.clone(), env, 64, start, 8, 1, 1, radiogs::train::inverse::BackFaces::default());
    let angle = 0.9f32;
    let cameras: Vec<Camera> = (0..4)
        .map(|k| {
            let a = -0.8 + 0.55 * k as f32;
            let eye = glam::Vec3::new(2.2 * a.cos(), 2.2 * a.sin(), 1.5);
            Camera::look_at(format!("r_{k}"), eye, glam::Vec3::new(-0.2, 0.0, 0.2), 64, 64, angle)
        })
        .collect();
    write_views(&data, &scene, &cameras, angle);
    let dataset = Dataset::open(&data).unwrap();
    let run = temp_dir("gauge-run");
    let mut c = Checkpoint { meta: serde_json::json!({"stage": "nvs", "iteration": 1}), ..Default::default() };
    c.put_surfels("params", &gt);
    c.save(&radiogs::train::nvs::checkpoint_path(&run)).unwrap();
    let cfg = TrainConfig {
        inverse_iters: 2,
        gauge_every: 1,
        albedo_init: 0.5 * ALBEDO,
        env_init: 2.0 * LIGHT,
        roughness_init: 0.9,
        // As good as frozen (the gauge runs only while albedo and light learn).
        lr_albedo: 1e-12,
        lr_roughness: 0.0,
        lr_env: 1e-12,
        lr_sh: 0.0,
        lr_sh_rest_inverse: 0.0,
        geometry_lr_scale: 0.0,
        pbr_samples: 32,
        rc_rays: 32,
        rc_surfels: 16,
        ray_skip_margin: 0.0,
        ..tiny_config(&data, &run)
    };
    cfg.save(&run.join("config.toml")).unwrap();
    radiogs::train::inverse::run(&cfg, &dataset, false).unwrap();
    let out = radiogs::io::ply::read_ply(&run.join("point_cloud.ply")).unwrap();
    let mean = (0..out.len()).map(|i| out.albedo(i)[1]).sum::<f32>() / out.len() as f32;
    let light = EnvMap::load(&run.join("envmap.exr")).unwrap();
    let mean_light = light.texels.iter().map(|t| t[1]).sum::<f32>() / light.texels.len() as f32;
    assert!((mean - ALBEDO).abs() < 0.08, "albedo after the gauge {mean} (truth {ALBEDO}, start {})", 0.5 * ALBEDO);
    assert!((mean_light - LIGHT).abs() < 0.2 * LIGHT, "light after the gauge {mean_light} (truth {LIGHT})");
}

/// The inverse stage re-orients (and twins) the surfels of a two-sided geometry stage, whose
/// normals are arbitrary, but keeps a back-face-culled geometry's orientation as trained: its
/// hidden sides were never rendered, so a flip would bring untrained surfels into view.
#[test]
fn inverse_keeps_the_orientation_of_a_culled_geometry_stage() {
    let count_up = |s: &Surfels| (0..s.len()).filter(|&i| s.normal(i)[2] > 0.0).count();
    for geometry_two_sided in [true, false] {
        let tag = if geometry_two_sided { "orient2" } else { "orient1" };
        let data = temp_dir(&format!("{tag}-data"));
        let mut gt = make_dataset(&data);
        let dataset = Dataset::open(&data).unwrap();
        let run = temp_dir(&format!("{tag}-run"));
        // Every other surfel of the plane faces down, away from all four cameras above it.
        for i in (0..gt.len()).step_by(2) {
            gt.quats[i] = quat_with_normal([0.0, 0.0, -1.0]);
        }
        let up_before = count_up(&gt);
        assert_eq!(up_before, gt.len() / 2);
        let mut c = Checkpoint {
            meta: serde_json::json!({"stage": "nvs", "iteration": 1, "two_sided": geometry_two_sided}),
            ..Default::default()
        };
        c.put_surfels("params", &gt);
        c.save(&radiogs::train::nvs::checkpoint_path(&run)).unwrap();
        let cfg = TrainConfig {
            inverse_iters: 1,
            pbr_samples: 8,
            rc_rays: 8,
            rc_surfels: 16,
            two_sided: geometry_two_sided,
            ..tiny_config(&data, &run)
        };
        cfg.save(&run.join("config.toml")).unwrap();
        radiogs::train::inverse::run(&cfg, &dataset, false).unwrap();
        let after = radiogs::io::ply::read_ply(&run.join("point_cloud.ply")).unwrap();
        assert_eq!(after.len(), gt.len(), "no twins on a plane seen from one side");
        if geometry_two_sided {
            assert_eq!(count_up(&after), gt.len(), "two-sided geometry: every surfel turned to the cameras");
        } else {
            assert_eq!(count_up(&after), up_before, "culled geometry: orientation kept");
        }
    }
}

/// `objective_per_view` (the diagnostic behind `examples/probe_objective`): one finite entry per
/// training view, the same on a second call, no step taken (the checkpoint is unchanged), and
/// the PBR image term lower at the true albedo than at a wrong one (the light at the truth).
#[test]
fn objective_scores_every_view_without_a_step() {
    use radiogs::train::inverse::{checkpoint_path, objective_per_view};
    let (data, dataset, run) = dataset_and_nvs_run("objective");
    let cfg = TrainConfig {
        inverse_iters: 4,
        env_init: LIGHT,
        lr_env: 0.0,
        pbr_samples: 8,
        rc_rays: 8,
        rc_surfels: 16,
        ..tiny_config(&data, &run)
    };
    cfg.save(&run.join("config.toml")).unwrap();
    radiogs::train::inverse::run(&cfg, &dataset, false).unwrap();
    let path = checkpoint_path(&run);
    let saved = std::fs::read(&path).unwrap();
    let first = objective_per_view(&cfg, &dataset, 3).unwrap();
    let second = objective_per_view(&cfg, &dataset, 3).unwrap();
    assert_eq!(first.len(), 4);
    for (a, b) in first.iter().zip(&second) {
        assert!(a.total.is_finite() && a.total > 0.0, "{a:?}");
        assert_eq!((a.total, a.pbr_l1, a.rc.total), (b.total, b.pbr_l1, b.rc.total));
    }
    assert!(std::fs::read(&path).unwrap() == saved, "the objective must not write the checkpoint");
    let mean_pbr_l1_at = |albedo: [f32; 3]| {
        let mut c = Checkpoint::load(&path).unwrap();
        let mut s = c.get_surfels(&path, "params").unwrap();
        s.albedo_logits.iter_mut().for_each(|l| *l = albedo.map(radiogs::surfels::albedo_to_logit));
        c.put_surfels("params", &s);
        c.save(&path).unwrap();
        let v = objective_per_view(&cfg, &dataset, 3).unwrap();
        v.iter().map(|l| l.pbr_l1).sum::<f32>() / v.len() as f32
    };
    let (truth, wrong) = (mean_pbr_l1_at(TRUE_ALBEDO), mean_pbr_l1_at([0.3, 0.6, 0.8]));
    assert!(truth < 0.5 * wrong, "PBR L1 at the true albedo {truth}, at a wrong one {wrong}");
}
