//! The binary's behaviour on bad input: one clear line naming the file, a non-zero exit code,
//! never a panic; commands that are not built yet exit 2.

use std::process::Command;

#[path = "../src/test_dir.rs"]
mod test_dir;
use test_dir::TempDir;

fn radiogs(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_radiogs")).args(args).output().expect("run radiogs");
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).to_string(),
        String::from_utf8_lossy(&out.stderr).to_string(),
    )
}

/// A fresh folder, removed at the end of the test (pass or fail).
fn temp_dir(name: &str) -> TempDir {
    TempDir::new(&format!("cli-{name}"))
}

#[test]
fn help_lists_every_command() {
    let (code, out, _) = radiogs(&["--help"]);
    assert_eq!(code, 0);
    for cmd in ["synth", "train", "render", "relight", "eval", "bench", "demo", "info"] {
        assert!(out.contains(cmd), "--help lacks {cmd}: {out}");
    }
}

#[test]
fn missing_dataset_is_a_clear_error() {
    let (code, _, err) = radiogs(&["info", "--data", "/nonexistent/dataset"]);
    assert_eq!(code, 1);
    assert!(err.contains("/nonexistent/dataset") && !err.contains("panicked"), "{err}");
}

#[test]
fn a_width_given_as_resolution_is_refused_by_name() {
    let dir = temp_dir("res");
    let (code, _, err) =
        radiogs(&["train", "--data", dir.to_str().unwrap(), "--out", dir.join("run").to_str().unwrap(), "-r", "800"]);
    assert_eq!(code, 1);
    assert!(err.contains("resolution") && err.contains("not a width") && !err.contains("panicked"), "{err}");
}

#[test]
fn malformed_json_and_truncated_png_name_the_file() {
    let dir = temp_dir("json");
    std::fs::write(dir.join("transforms_train.json"), "{\"camera_angle_x\": 0.7, \"frames\": [").unwrap();
    let (code, _, err) = radiogs(&["info", "--data", dir.to_str().unwrap()]);
    assert_eq!(code, 1);
    assert!(err.contains("transforms_train.json") && err.contains("JSON"), "{err}");

    let view = dir.join("train_000");
    std::fs::create_dir_all(&view).unwrap();
    std::fs::remove_file(dir.join("transforms_train.json")).unwrap();
    std::fs::write(
        view.join("metadata.json"),
        r#"{"cam_transform_mat": "1,0,0,0,0,1,0,0,0,0,1,4,0,0,0,1", "cam_angle_x": 0.69, "imh": 4, "imw": 4}"#,
    )
    .unwrap();
    std::fs::write(view.join("rgba.png"), b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR\0\0").unwrap();
    let (code, _, err) = radiogs(&["info", "--data", dir.to_str().unwrap()]);
    assert_eq!(code, 1);
    assert!(err.contains("rgba.png") && !err.contains("panicked"), "{err}");
}

#[test]
fn empty_ply_is_refused() {
    let dir = temp_dir("ply");
    let ply = dir.join("empty.ply");
    std::fs::write(&ply, "ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nend_header\n")
        .unwrap();
    let (code, _, err) = radiogs(&["info", "--ply", ply.to_str().unwrap()]);
    assert_eq!(code, 1);
    assert!(err.contains("empty.ply") && err.contains("no surfels"), "{err}");
}

#[test]
fn relight_without_recovered_light_says_what_to_run() {
    let dir = temp_dir("relight");
    let run = dir.join("run");
    std::fs::create_dir_all(&run).unwrap();
    let (code, _, err) = radiogs(&[
        "relight",
        "--run",
        run.to_str().unwrap(),
        "--envmap",
        "/nonexistent/sky.hdr",
        "--out",
        dir.join("out").to_str().unwrap(),
    ]);
    assert_eq!(code, 1);
    assert!(err.contains("envmap.exr") && err.contains("--stage inverse") && !err.contains("panicked"), "{err}");
    assert!(!dir.join("out").exists(), "nothing is written on bad input");
}

/// Interval settings that divide the iteration number are refused by name before anything is
/// written (a 0 used to panic with a division by zero after `config.toml` was written).
#[test]
fn zero_intervals_are_refused_by_name() {
    for (flag, key) in [("--log-every", "log_every"), ("--densify-every", "densify_every")] {
        let dir = temp_dir(key);
        let out = dir.join("run");
        let (code, _, err) =
            radiogs(&["train", "--data", "/nonexistent/dataset", "--out", out.to_str().unwrap(), flag, "0"]);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains(key) && !err.contains("panicked"), "{err}");
        assert!(!out.exists(), "{flag} 0 left {}", out.display());
    }
}

/// Frame sizes beyond what the renderer may allocate are refused before any work (a
/// 100000² frame used to panic in the compositor after a minute).
#[test]
fn bench_frame_sizes_out_of_range_are_refused_by_flag() {
    for size in ["0", "100000"] {
        let (code, _, err) = radiogs(&["bench", "relight", "--run", "/nonexistent/run", "--sizes", size]);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains("--sizes") && err.contains(size) && !err.contains("panicked"), "{err}");
    }
    // The raster bench takes the windows `render --k` takes.
    for k in ["0", "1000"] {
        let (code, _, err) = radiogs(&["bench", "raster", "--quick", "--k", k]);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains("--k") && err.contains(k) && !err.contains("panicked"), "{err}");
    }
}

/// `demo --iters 0` is refused before the dataset is synthesised.
#[test]
fn demo_settings_are_checked_before_synthesis() {
    let dir = temp_dir("demo0");
    let out = dir.join("demo");
    let (code, _, err) = radiogs(&["demo", "--out", out.to_str().unwrap(), "--iters", "0"]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("iters") && !err.contains("panicked"), "{err}");
    assert!(!out.join("data").exists(), "the dataset was synthesised first");
}

/// `radiogs synth` of a tiny dataset into `data` (res², `train_views` training views, 1 test
/// view, 1 spp, then `extra` arguments); returns its standard error.
fn synth_tiny(data: &std::path::Path, res: &str, train_views: &str, extra: &[&str]) -> String {
    let mut args =
        vec!["synth", "--out", data.to_str().unwrap(), "--res", res, "--train-views", train_views, "--test-views", "1"];
    args.extend_from_slice(&["--spp", "1"]);
    args.extend_from_slice(extra);
    let (code, _, err) = radiogs(&args);
    assert_eq!(code, 0, "{err}");
    err
}

/// A tiny synthetic dataset (16², 2 training views, 1 test view) in `dir/data`.
fn tiny_dataset(dir: &std::path::Path) -> std::path::PathBuf {
    let data = dir.join("data");
    synth_tiny(&data, "16", "2", &[]);
    data
}

/// A training image cut short (its header whole) is refused by name before the run folder is
/// written (it used to fail when the images loaded, after `config.toml` was written).
#[test]
fn truncated_training_image_is_refused_before_anything_is_written() {
    let dir = temp_dir("truncated");
    let data = tiny_dataset(&dir);
    let image = data.join("train_001/rgba.png");
    let bytes = std::fs::read(&image).unwrap();
    std::fs::write(&image, &bytes[..bytes.len() / 2]).unwrap();
    let out = dir.join("run");
    let (code, _, err) =
        radiogs(&["train", "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap(), "--iters", "2"]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("train_001/rgba.png") && err.contains("truncated") && !err.contains("panicked"), "{err}");
    assert!(!out.exists(), "a bad image left {}", out.display());
}

/// Training afresh into a folder that holds a trained run is refused before anything in it
/// changes (a failed re-train used to leave a mix of both runs); `--resume` continues it and
/// `--overwrite` replaces it. The dataset folder is never a run folder.
#[test]
fn a_trained_run_is_not_replaced_without_overwrite() {
    let dir = temp_dir("rerun");
    let data = tiny_dataset(&dir);
    let (data_s, out) = (data.to_str().unwrap(), dir.join("run"));
    let out_s = out.to_str().unwrap();
    let train = |extra: &[&str]| {
        let mut args = vec!["train", "--data", data_s, "--out", out_s];
        args.extend_from_slice(extra);
        radiogs(&args)
    };
    let (code, _, err) = train(&["--iters", "2"]);
    assert_eq!(code, 0, "{err}");
    let listing = |p: &std::path::Path| {
        let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(p)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .map(|p| (p.file_name().unwrap().to_string_lossy().to_string(), std::fs::read(&p).unwrap()))
            .collect();
        v.sort();
        v
    };
    let before = listing(&out);
    for stage in ["nvs", "all"] {
        let (code, _, err) = train(&["--stage", stage, "--iters", "3"]);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains(out_s) && err.contains("--overwrite") && err.contains("--resume"), "{err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    assert!(listing(&out) == before, "a refused run changed the folder");
    // The inverse stage starts from the folder's nvs checkpoint: allowed.
    let (code, _, err) = train(&["--stage", "inverse", "--iters", "2", "--inverse-iters", "2"]);
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = train(&["--stage", "inverse", "--iters", "2", "--inverse-iters", "2"]);
    assert_eq!(code, 1, "a second fresh inverse stage: {err}");
    assert!(err.contains("checkpoint_inverse.bin") || err.contains("envmap.exr"), "{err}");
    // Relighting never writes into a trained run (its own, or another).
    let other = dir.join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::copy(out.join("checkpoint.bin"), other.join("checkpoint.bin")).unwrap();
    for (to, expect) in [(out_s, "is the run being relit"), (other.to_str().unwrap(), "holds a trained run")] {
        let (code, _, err) = radiogs(&["relight", "--run", out_s, "--envmap", "/nonexistent/sky.hdr", "--out", to]);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains(expect) && !err.contains("panicked"), "{err}");
    }
    let (code, _, err) = train(&["--overwrite", "--iters", "3"]);
    assert_eq!(code, 0, "{err}");
    assert!(!out.join("envmap.exr").exists(), "--overwrite leaves no stale inverse outputs");
    for extra in [None, Some("--overwrite")] {
        let mut args = vec!["train", "--data", data_s, "--out", data_s, "--iters", "2"];
        args.extend(extra);
        let (code, _, err) = radiogs(&args);
        assert_eq!(code, 1, "{extra:?}: {err}");
        assert!(err.contains("dataset folder"), "{err}");
    }
}

/// A bad initial light or initial surfel file stops training before the run folder is made
/// (the light used to be read only after the whole nvs stage).
#[test]
fn bad_initialisation_files_are_refused_before_anything_is_written() {
    let dir = temp_dir("badinit");
    let data = tiny_dataset(&dir);
    let bad = dir.join("bad.exr");
    std::fs::write(&bad, b"not an OpenEXR file").unwrap();
    let out = dir.join("run");
    for (flag, file) in [
        ("--env-init-map", bad.to_str().unwrap()),
        ("--env-init-map", "/nonexistent/sky.exr"),
        ("--init-ply", "/nonexistent/p.ply"),
    ] {
        let args =
            ["train", "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap(), "--iters", "2", flag, file];
        let (code, _, err) = radiogs(&args);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains(file) && !err.contains("panicked"), "{flag} {file}: {err}");
        assert!(!out.exists(), "{flag} {file} left {}", out.display());
    }
}

/// An evaluation that fails half-way (a bad test pass read after the first pictures are made)
/// leaves the previous `RUN/eval` untouched and no partial folder.
#[test]
fn a_failed_eval_leaves_the_previous_one_whole() {
    let dir = temp_dir("evalfail");
    let data = tiny_dataset(&dir);
    let run = dir.join("run");
    let (data_s, run_s) = (data.to_str().unwrap(), run.to_str().unwrap());
    let args = ["train", "--data", data_s, "--out", run_s, "--stage", "all", "--iters", "2", "--inverse-iters", "2"];
    let (code, _, err) = radiogs(&args);
    assert_eq!(code, 0, "{err}");
    let (code, _, err) = radiogs(&["eval", "--run", run_s, "--no-relight"]);
    assert_eq!(code, 0, "{err}");
    let eval = run.join("eval");
    let snapshot = || {
        let mut v: Vec<(std::path::PathBuf, std::time::SystemTime)> = std::fs::read_dir(&eval)
            .unwrap()
            .map(|e| e.unwrap().path())
            .map(|p| (p.clone(), std::fs::metadata(&p).unwrap().modified().unwrap()))
            .collect();
        v.sort();
        v
    };
    let before = snapshot();
    assert!(before.iter().any(|(p, _)| p.ends_with("metrics.json")));
    // The albedo pass is read by the PBR part, after the views' pictures are written.
    let albedo = data.join("test_000/albedo.png");
    let bytes = std::fs::read(&albedo).unwrap();
    std::fs::write(&albedo, &bytes[..bytes.len() / 2]).unwrap();
    let (code, _, err) = radiogs(&["eval", "--run", run_s, "--no-relight"]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("albedo.png") && !err.contains("panicked"), "{err}");
    assert!(snapshot() == before, "the failed eval changed RUN/eval");
    assert!(!run.join("eval.partial").exists());
    let (code, _, err) = radiogs(&["eval", "--run", run_s, "--no-relight", "--json", dir.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("--json") && err.contains("folder"), "{err}");
}

/// A run folder without `config.toml` (a 2DGS output) names the missing dataset instead of an
/// empty path, and `-r 0` on eval and render names the flag; nothing is written.
#[test]
fn run_without_a_dataset_and_zero_resolution_are_named() {
    let dir = temp_dir("nocfg");
    let run = dir.join("run");
    std::fs::create_dir_all(&run).unwrap();
    let surfels = radiogs::surfels::Surfels::random_in_box(4, [-1.0; 3], [1.0; 3], 1);
    radiogs::io::ply::write_ply(&run.join("point_cloud.ply"), &surfels).unwrap();
    let (run_s, out) = (run.to_str().unwrap(), dir.join("out"));
    let (code, _, err) = radiogs(&["render", "--run", run_s, "--out", out.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains(run_s) && err.contains("config.toml") && err.contains("--cameras"), "{err}");
    assert!(!err.contains(": :") && !err.contains("panicked"), "{err}");
    for args in [
        vec!["eval", "--run", run_s, "-r", "0"],
        vec!["render", "--run", run_s, "-r", "0", "--out", out.to_str().unwrap()],
    ] {
        let (code, _, err) = radiogs(&args);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains("--resolution 0") && err.contains("1..=16"), "{args:?}: {err}");
    }
    assert!(!out.exists() && !run.join("eval").exists(), "nothing is written on bad input");
}

/// `--json -` writes the metrics to standard output (it wrote a file named `-`), and the run's
/// eval folder still gets the same metrics beside its pictures.
#[test]
fn eval_json_dash_is_standard_output() {
    let dir = temp_dir("json-dash");
    let data = tiny_dataset(&dir);
    let run = dir.join("run");
    std::fs::create_dir_all(&run).unwrap();
    let surfels = radiogs::surfels::Surfels::random_in_box(50, [-1.0; 3], [1.0; 3], 1);
    radiogs::io::ply::write_ply(&run.join("point_cloud.ply"), &surfels).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_radiogs"))
        .args(["eval", "--run", run.to_str().unwrap(), "--data", data.to_str().unwrap(), "--json", "-"])
        .current_dir(&dir)
        .output()
        .expect("run radiogs");
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert_eq!(out.status.code(), Some(0), "{stderr}");
    let json: serde_json::Value = serde_json::from_str(&stdout).expect("stdout is one JSON document");
    assert_eq!(json["views"], 1, "{stdout}");
    assert!(json["mean"]["psnr"].is_number(), "{stdout}");
    assert!(!dir.join("-").exists());
    let kept: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("eval/metrics.json")).unwrap()).unwrap();
    assert_eq!(kept, json);
}

/// Input that is read but may not mean what it says is accepted with a warning naming the file
/// and field: an env map that is not twice as wide as high, a TensoIR camera convention that is
/// not Blender's (both were accepted silently).
#[test]
fn doubtful_env_maps_and_camera_conventions_are_warned_about() {
    let dir = temp_dir("warn");
    let env = dir.join("wide.exr");
    radiogs::envmap::EnvMap::constant(48, 16, [0.5; 3]).save(&env).unwrap();
    let data = dir.join("data");
    let err = synth_tiny(&data, "8", "1", &["--relight-envs", "studio", "--envmap", env.to_str().unwrap()]);
    assert!(err.contains("wide.exr: size: 48×16 is not twice as wide as high"), "{err}");

    // The same data as TensoIR folders only, one view's convention changed.
    std::fs::remove_file(data.join("transforms_train.json")).unwrap();
    std::fs::remove_file(data.join("transforms_test.json")).unwrap();
    let (code, _, err) = radiogs(&["info", "--data", data.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(!err.contains("convention"), "{err}");
    let meta = data.join("train_000/metadata.json");
    let text = std::fs::read_to_string(&meta).unwrap().replace("blender_camera_to_world", "opencv");
    std::fs::write(&meta, text).unwrap();
    let (code, _, err) = radiogs(&["info", "--data", data.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("train_000/metadata.json: convention: \"opencv\" is not understood and is ignored"), "{err}");
}

/// Legal inputs that are almost surely slips are warned about when training starts: views
/// shrunk below 16 px by `-r`, and training images without transparency (the whole frame would
/// count as the object).
#[test]
fn slips_in_training_data_are_warned_about() {
    let dir = temp_dir("slips");
    let data = tiny_dataset(&dir);
    let train = |out: &str, extra: &[&str]| {
        let out = dir.join(out);
        let mut args = vec!["train", "--data", data.to_str().unwrap(), "--out", out.to_str().unwrap()];
        args.extend_from_slice(&["--stage", "nvs", "--iters", "1"]);
        args.extend_from_slice(extra);
        let (code, _, err) = radiogs(&args);
        assert_eq!(code, 0, "{err}");
        err
    };
    let err = train("plain", &[]);
    assert!(!err.contains("shrinks views") && !err.contains("opaque"), "{err}");
    let err = train("shrunk", &["-r", "2"]);
    assert!(err.contains("-r 2 shrinks views to 8 px"), "{err}");
    // The first training image as RGB without alpha.
    let first = data.join("train_000/rgba.png");
    let rgba = radiogs::io::image::read_rgba(&first).unwrap();
    radiogs::io::image::write_image(&first, &rgba.take_channels(3)).unwrap();
    let err = train("opaque", &[]);
    assert!(err.contains("train_000/rgba.png: every pixel is opaque"), "{err}");
}

/// Benchmarks take at least one repetition (`--repeats 0` used to be read as 1).
#[test]
fn zero_repeats_are_refused() {
    for bench in [&["raster", "--quick"][..], &["relight", "--run", "/nonexistent/run"], &["trace"]] {
        let mut args = vec!["bench"];
        args.extend_from_slice(bench);
        args.extend_from_slice(&["--repeats", "0"]);
        let (code, _, err) = radiogs(&args);
        assert_ne!(code, 0, "{err}");
        assert!(err.contains("--repeats") && err.contains("1..="), "{args:?}: {err}");
    }
}

/// A dataset kept from an earlier demo is not reused for another scene, size or seed: the demo
/// refuses before training, naming both (it used to train on the old scene).
#[test]
fn the_demo_does_not_reuse_another_scenes_dataset() {
    let dir = temp_dir("demo-kept");
    let out = dir.join("demo");
    synth_tiny(&out.join("data"), "16", "2", &["--scene", "spheres"]);
    for (scene, res, seed) in [("cornell", "16", "0"), ("spheres", "32", "0"), ("spheres", "16", "3")] {
        let args = ["demo", "--out", out.to_str().unwrap(), "--scene", scene, "--res", res, "--seed", seed];
        let (code, _, err) = radiogs(&args);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains("holds the dataset of --scene spheres --res 16 --seed 0"), "{err}");
        assert!(!out.join("run").exists(), "{args:?}: trained");
    }
}
