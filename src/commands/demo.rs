//! `radiogs demo`: the whole job on the built-in scene — synthesise the dataset, train, evaluate
//! — and write one self-contained HTML report (images inline, no network) with GT beside ours,
//! the metrics table and the training curves.

use crate::io::image::{Image, read_rgba, write_image};
use crate::train::config::TrainConfig;
use anyhow::Context;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Synthesise the built-in scene, train, evaluate and write an HTML report.
#[derive(clap::Args, Debug, Clone)]
pub struct DemoArgs {
    /// Output folder (dataset, run and report.html go inside).
    #[arg(long, default_value = "demo")]
    pub out: PathBuf,
    /// Built-in scene to synthesise.
    #[arg(long, default_value = "spheres")]
    pub scene: String,
    /// Image size of the synthesised views.
    #[arg(long, default_value_t = 128)]
    pub res: u32,
    /// Training iterations of the nvs (geometry) stage (2500: every metric within 0.06 dB and
    /// 0.05° of 3000's, and the inverse stage, starting with 8 % fewer surfels, 10 % faster:
    /// ≈ 50 s sooner in all; BENCHMARKS.md, session 51).
    #[arg(long, default_value_t = 2500)]
    pub iters: u32,
    /// Iterations of the inverse-rendering stage.
    #[arg(long, default_value_t = 1500)]
    pub inverse_iters: u32,
    /// Finetune iterations per light when relighting (100: within 0.02 dB of 150; the finetune
    /// starts from the traced relighting's incident light).
    #[arg(long, default_value_t = 100)]
    pub relight_iters: u32,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

#[derive(clap::Parser)]
struct SynthWrapper {
    #[command(flatten)]
    args: crate::synth::SynthArgs,
}

#[derive(clap::Parser)]
struct TrainWrapper {
    #[command(flatten)]
    args: TrainConfig,
}

/// `synth`'s arguments for the demo's dataset: 48 + 8 views at `--res` and 32 spp (`synth`'s
/// default 256 takes ~4 × longer here), relit under studio and sunset.
fn demo_synth_args(args: &DemoArgs, data: &Path) -> anyhow::Result<crate::synth::SynthArgs> {
    use clap::Parser;
    Ok(SynthWrapper::try_parse_from([
        "synth",
        "--scene",
        &args.scene,
        "--out",
        &data.to_string_lossy(),
        "--res",
        &args.res.to_string(),
        "--train-views",
        "48",
        "--test-views",
        "8",
        "--spp",
        "32",
        "--relight-envs",
        "studio,sunset",
        "--seed",
        &args.seed.to_string(),
    ])?
    .args)
}

/// A dataset an earlier demo left in `data` is used again only if it is the one asked for:
/// the scene, size and seed its README.json records (a `--scene cornell` after a spheres demo
/// used to train on the spheres). A dataset that radiogs did not synthesise is used as it is.
fn check_kept_dataset(data: &Path, args: &DemoArgs) -> anyhow::Result<()> {
    let path = data.join("README.json");
    let Ok(bytes) = std::fs::read(&path) else { return Ok(()) };
    let readme: serde_json::Value =
        serde_json::from_slice(&bytes).with_context(|| format!("{}: not valid JSON", path.display()))?;
    if !readme["generator"].as_str().is_some_and(|g| g.starts_with("radiogs synth")) {
        return Ok(());
    }
    let (scene, res, seed) = (readme["scene"].as_str(), readme["resolution"][0].as_u64(), readme["seed"].as_u64());
    if scene != Some(args.scene.as_str()) || res != Some(args.res as u64) || seed != Some(args.seed) {
        let show = |v: Option<String>| v.unwrap_or_else(|| "?".into());
        anyhow::bail!(
            "{}: holds the dataset of --scene {} --res {} --seed {}, not the --scene {} --res {} --seed {} asked for; \
             remove it, or give the demo another --out",
            data.display(),
            show(scene.map(String::from)),
            show(res.map(|r| r.to_string())),
            show(seed.map(|s| s.to_string())),
            args.scene,
            args.res,
            args.seed
        );
    }
    Ok(())
}

pub fn run(args: &DemoArgs) -> anyhow::Result<()> {
    let started = std::time::Instant::now();
    // Each step's wall time, for the closing line and the report.
    let mut steps: Vec<(&str, f64)> = Vec::new();
    let step = std::time::Instant::now();
    let data = args.out.join("data");
    let run = args.out.join("run");
    let cfg = {
        use clap::Parser;
        TrainWrapper::try_parse_from([
            "train",
            "--data",
            &data.to_string_lossy(),
            "--out",
            &run.to_string_lossy(),
            "--stage",
            "all",
            "--iters",
            &args.iters.to_string(),
            "--inverse-iters",
            &args.inverse_iters.to_string(),
            "--seed",
            &args.seed.to_string(),
            // A demo run again retrains its own run folder.
            "--overwrite",
        ])?
        .args
    };
    // Settings that cannot train are refused before minutes of synthesis.
    cfg.validate()?;
    if !data.join("transforms_train.json").is_file() {
        // synth refuses a folder that holds files; say it in the demo's terms.
        if std::fs::read_dir(&data).is_ok_and(|mut d| d.next().is_some()) {
            anyhow::bail!(
                "{}: holds files but no dataset (no transforms_train.json); remove it, or give the demo another --out",
                data.display()
            );
        }
        let synth = demo_synth_args(args, &data)?;
        eprintln!("[1/4] synthesising '{}' into {}", args.scene, data.display());
        crate::synth::run(&synth)?;
        steps.push(("synthesis", step.elapsed().as_secs_f64()));
    } else {
        check_kept_dataset(&data, args)?;
        eprintln!("[1/4] using the dataset already in {}", data.display());
    }
    eprintln!(
        "[2/4] training: nvs stage ({} iterations), then inverse rendering ({} iterations) into {}",
        args.iters,
        args.inverse_iters,
        run.display()
    );
    let step = std::time::Instant::now();
    crate::train::run(&cfg)?;
    steps.push(("training", step.elapsed().as_secs_f64()));
    let step = std::time::Instant::now();
    eprintln!("[3/4] evaluating, and relighting under the dataset's other lights (traced and finetuned)");
    crate::eval::run(&crate::eval::EvalArgs {
        run: run.clone(),
        data: Some(data.clone()),
        json: None,
        limit: 0,
        no_relight: false,
        relight_iters: args.relight_iters,
        relight_rc_rays: crate::relight::RC_RAYS,
        relight_samples: 64,
        relight_env_importance: crate::relight::ENV_IMPORTANCE,
        relight_bounces: crate::relight::TRACED_BOUNCES,
        resolution: None,
    })?;
    steps.push(("evaluation and relighting", step.elapsed().as_secs_f64()));
    let step = std::time::Instant::now();
    eprintln!("[4/4] turntables and the report");
    write_turntables(&args.out.join("orbit"), &run)?;
    steps.push(("turntables", step.elapsed().as_secs_f64()));
    let step = std::time::Instant::now();
    let report = args.out.join("report.html");
    write_report(&report, &data, &run, &steps)?;
    let overview = args.out.join("overview.png");
    write_overview(&overview, &data, &run, 2)?;
    steps.push(("report", step.elapsed().as_secs_f64()));
    eprintln!("demo: {} (the build before it not counted)", time_split(started.elapsed().as_secs_f64(), &steps));
    println!("report: {} (picture: {})", report.display(), overview.display());
    Ok(())
}

/// A duration as people read it: "45.3 s", "6 min 01 s".
fn minutes(seconds: f64) -> String {
    // Below 59.95 s the one decimal never rounds up to "60.0 s".
    if seconds < 59.95 {
        format!("{seconds:.1} s")
    } else {
        let s = seconds.round() as u64;
        format!("{} min {:02} s", s / 60, s % 60)
    }
}

/// "11 min 16 s in all: synthesis 20.3 s, training 6 min 01 s, …".
fn time_split(total: f64, steps: &[(&str, f64)]) -> String {
    let parts: Vec<String> = steps.iter().map(|(name, s)| format!("{name} {}", minutes(*s))).collect();
    format!("{} in all: {}", minutes(total), parts.join(", "))
}

/// Frames of each turntable in the report (24 frames/s: a turn in 1.5 s).
const TURNTABLE_FRAMES: usize = 36;
/// The report's turntables: `render --orbit` of the run in these modes, each into `orbit/<mode>`
/// (0.8 and 3.5 s on the demo's run; an albedo turntable would cost another 3.5 s).
const TURNTABLE_MODES: [(crate::commands::render::RenderMode, &str); 2] =
    [(crate::commands::render::RenderMode::Surfel, "surfel"), (crate::commands::render::RenderMode::Pbr, "pbr")];

/// The object once around, as the learned radiance and as the PBR render under the recovered
/// light (`radiogs render --run RUN --orbit 36 --mode surfel|pbr`).
pub fn write_turntables(dir: &Path, run: &Path) -> anyhow::Result<()> {
    use crate::commands::render::RenderArgs;
    for (mode, name) in TURNTABLE_MODES {
        crate::commands::render::run(&RenderArgs {
            run: Some(run.to_path_buf()),
            out: dir.join(name),
            mode,
            orbit: Some(TURNTABLE_FRAMES),
            ..RenderArgs::default()
        })?;
    }
    Ok(())
}

const B64: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

fn base64(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [chunk[0], *chunk.get(1).unwrap_or(&0), *chunk.get(2).unwrap_or(&0)];
        let v = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(B64[(v >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

fn img_tag(path: &Path) -> String {
    let mime = if path.extension().is_some_and(|e| e == "apng") { "image/apng" } else { "image/png" };
    match std::fs::read(path) {
        Ok(bytes) => format!("<img src=\"data:{mime};base64,{}\">", base64(&bytes)),
        Err(_) => "<span class=missing>missing</span>".to_string(),
    }
}

/// GT image composited over white as a PNG, for a fair side-by-side with our renders.
fn wide_img_tag(path: &Path) -> String {
    img_tag(path).replacen("<img ", "<img style=\"width:320px\" ", 1)
}

/// A GT indirect pass (linear EXR) as an sRGB PNG, as our indirect pictures are written.
fn indirect_to_png(src: &Path, dst: &Path) -> anyhow::Result<()> {
    let mut img = read_rgba(src)?;
    img.map_channels(3, |v| crate::io::image::linear_to_srgb(v.clamp(0.0, 1.0)));
    write_image(dst, &img)?;
    Ok(())
}

fn gt_over_white(src: &Path, dst: &Path) -> anyhow::Result<()> {
    let img = read_rgba(src)?;
    let mut out = Image::new(img.width, img.height, 3);
    for (o, p) in out.data.chunks_exact_mut(3).zip(img.data.chunks_exact(4)) {
        for c in 0..3 {
            o[c] = p[c] * p[3] + (1.0 - p[3]);
        }
    }
    write_image(dst, &out)?;
    Ok(())
}

/// A picture for a quick look: rows of GT | ours | GT normals | our normals for the first
/// `rows` test views evaluated, over white.
pub fn write_overview(path: &Path, data: &Path, run: &Path, rows: usize) -> anyhow::Result<()> {
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(run.join("eval/metrics.json"))?)?;
    let names: Vec<String> = metrics["per_view"]
        .as_array()
        .map(|v| v.iter().filter_map(|m| m["view"].as_str().map(String::from)).take(rows).collect())
        .unwrap_or_default();
    let mut tiles: Vec<Vec<Option<Image>>> = Vec::new();
    for name in &names {
        let load = |p: PathBuf| -> Option<Image> { read_rgba(&p).ok() };
        let light =
            metrics["relight"].as_array().and_then(|r| r.first()).and_then(|m| m["light"].as_str()).unwrap_or("");
        let row = [
            load(data.join(name).join("rgba.png")),
            load(run.join(format!("eval/{name}.png"))),
            load(run.join(format!("eval/{name}_pbr.png"))),
            load(data.join(name).join("normal.png")),
            load(run.join(format!("eval/{name}_normal.png"))),
            load(data.join(name).join("albedo.png")),
            load(run.join(format!("eval/{name}_albedo.png"))),
            load(data.join(name).join(format!("rgba_{light}.png"))),
            load(run.join(format!("eval/{name}_relit_{light}_finetune.png"))),
        ];
        tiles.push(row.into_iter().collect());
    }
    let Some(first) = tiles.iter().flatten().flatten().next() else { return Ok(()) };
    let (tw, th) = (first.width, first.height);
    let cols = tiles.iter().map(|r| r.len()).max().unwrap_or(0) as u32;
    let mut out = Image::new(tw * cols, th * tiles.len() as u32, 3);
    out.data.fill(1.0);
    for (r, row) in tiles.iter().enumerate() {
        for (c, img) in row.iter().enumerate() {
            let Some(img) = img else { continue };
            for y in 0..th.min(img.height) {
                for x in 0..tw.min(img.width) {
                    let p = img.pixel(x, y);
                    let a = p[3];
                    let dst = out.pixel_mut(c as u32 * tw + x, r as u32 * th + y);
                    for k in 0..3 {
                        dst[k] = p[k] * a + (1.0 - a);
                    }
                }
            }
        }
    }
    write_image(path, &out)?;
    Ok(())
}

/// An inline SVG line chart of one metric over iterations.
fn svg_curve(points: &[(f64, f64)], label: &str) -> String {
    if points.len() < 2 {
        return String::new();
    }
    let (w, h, pad) = (420.0, 180.0, 36.0);
    let (x0, x1) = (points[0].0, points[points.len() - 1].0.max(points[0].0 + 1.0));
    let (mut y0, mut y1) = points.iter().fold((f64::MAX, f64::MIN), |(a, b), p| (a.min(p.1), b.max(p.1)));
    if (y1 - y0).abs() < 1e-12 {
        y0 -= 1.0;
        y1 += 1.0;
    }
    let sx = |x: f64| pad + (x - x0) / (x1 - x0) * (w - 2.0 * pad);
    let sy = |y: f64| h - pad + (y0 - y) / (y1 - y0) * (h - 2.0 * pad);
    let path: Vec<String> = points.iter().map(|p| format!("{:.1},{:.1}", sx(p.0), sy(p.1))).collect();
    format!(
        "<svg width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\"><rect width=\"{w}\" height=\"{h}\" fill=\"#fafafa\"/>\
         <polyline fill=\"none\" stroke=\"#2962ff\" stroke-width=\"1.5\" points=\"{}\"/>\
         <text x=\"{pad}\" y=\"16\" font-size=\"12\">{label}</text>\
         <text x=\"2\" y=\"{:.0}\" font-size=\"10\">{y1:.3}</text><text x=\"2\" y=\"{:.0}\" font-size=\"10\">{y0:.3}</text>\
         <text x=\"{:.0}\" y=\"{:.0}\" font-size=\"10\">{x1:.0} it</text></svg>",
        path.join(" "),
        sy(y1) + 4.0,
        sy(y0),
        w - pad - 30.0,
        h - 8.0
    )
}

pub fn write_report(path: &Path, data: &Path, run: &Path, steps: &[(&str, f64)]) -> anyhow::Result<()> {
    let metrics_path = run.join("eval/metrics.json");
    let metrics: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&metrics_path).with_context(|| format!("{}: cannot read", metrics_path.display()))?,
    )?;
    let mut html = String::from(
        "<!doctype html><meta charset=utf-8><title>radiogs demo report</title><style>\
         body{font-family:system-ui,sans-serif;margin:24px;max-width:1100px}table{border-collapse:collapse}\
         td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}img{width:160px;image-rendering:pixelated}\
         .row{display:flex;gap:8px;align-items:center;margin:6px 0}.missing{color:#b00}</style>",
    );
    let _ = write!(
        html,
        "<h1>radiogs demo</h1><p>Dataset <code>{}</code>, run <code>{}</code>. {} (the build before it not counted).</p>",
        data.display(),
        run.display(),
        time_split(steps.iter().map(|s| s.1).sum(), steps)
    );
    html.push_str("<h2>Metrics (test views)</h2><table><tr><th>metric</th><th>value</th></tr>");
    if let Some(mean) = metrics.get("mean").and_then(|m| m.as_object()) {
        for (k, v) in mean {
            let _ = write!(
                html,
                "<tr><td style=text-align:left>{k}</td><td>{}</td></tr>",
                v.as_f64().map_or("–".into(), |x| format!("{x:.3}"))
            );
        }
    }
    let _ = write!(html, "<tr><td style=text-align:left>surfels</td><td>{}</td></tr></table>", metrics["surfels"]);
    let _ = write!(html, "<p><small>{}</small></p>", metrics["protocol"].as_str().unwrap_or(""));

    // Curves from metrics.jsonl.
    let lines = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap_or_default();
    let rows: Vec<serde_json::Value> = lines.lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
    let series = |key: &str| -> Vec<(f64, f64)> {
        rows.iter().filter_map(|r| Some((r["iteration"].as_f64()?, r[key].as_f64()?))).collect()
    };
    html.push_str("<h2>Training</h2><div class=row>");
    html.push_str(&svg_curve(&series("loss"), "loss"));
    html.push_str(&svg_curve(&series("psnr"), "train PSNR (dB)"));
    html.push_str(&svg_curve(&series("surfels"), "surfels"));
    html.push_str("</div>");

    let orbit = path.parent().unwrap_or(Path::new(".")).join("orbit");
    if orbit.join("surfel/orbit.apng").is_file() {
        html.push_str("<h2>Turntable: learned radiance | PBR under the recovered light</h2><div class=row>");
        for (_, name) in TURNTABLE_MODES {
            html.push_str(&img_tag(&orbit.join(name).join("orbit.apng")));
        }
        let _ = write!(
            html,
            "</div><p><small>{TURNTABLE_FRAMES} frames once around the object (<code>radiogs render --run {} --orbit {TURNTABLE_FRAMES} --mode surfel|pbr</code>; <code>--mode albedo</code> turns the recovered albedo); the frames are in <code>{}</code>.</small></p>",
            run.display(),
            orbit.display()
        );
    }
    html.push_str("<h2>Test views: ground truth | ours | GT normals | our normals</h2>");
    let tmp = run.join("eval/report_gt");
    if let Some(views) = metrics["per_view"].as_array() {
        for v in views {
            let name = v["view"].as_str().unwrap_or("");
            let gt_src = data.join(name).join("rgba.png");
            let gt_png = tmp.join(format!("{name}.png"));
            let gt = if gt_over_white(&gt_src, &gt_png).is_ok() { img_tag(&gt_png) } else { img_tag(&gt_src) };
            let _ = write!(
                html,
                "<div class=row>{gt}{}{}{}<span>{name}: PSNR {:.2} dB, SSIM {:.4}{}</span></div>",
                img_tag(&run.join(format!("eval/{name}.png"))),
                img_tag(&data.join(name).join("normal.png")),
                img_tag(&run.join(format!("eval/{name}_normal.png"))),
                v["psnr"].as_f64().unwrap_or(f64::NAN),
                v["ssim"].as_f64().unwrap_or(f64::NAN),
                v["normal_mae_deg"].as_f64().map_or(String::new(), |x| format!(", normal MAE {x:.2}°")),
            );
        }
    }
    // Inverse rendering: light, materials, PBR, indirect light, relighting.
    let inv_lines = std::fs::read_to_string(run.join("metrics_inverse.jsonl")).unwrap_or_default();
    let inv_rows: Vec<serde_json::Value> = inv_lines.lines().filter_map(|l| serde_json::from_str(l).ok()).collect();
    if !inv_rows.is_empty() {
        let inv_series = |key: &str| -> Vec<(f64, f64)> {
            inv_rows.iter().filter_map(|r| Some((r["iteration"].as_f64()?, r[key].as_f64()?))).collect()
        };
        html.push_str("<h2>Inverse rendering</h2><div class=row>");
        html.push_str(&svg_curve(&inv_series("psnr_pbr"), "train PBR PSNR (dB)"));
        html.push_str(&svg_curve(&inv_series("rc_camera"), "radiometric consistency (camera dir)"));
        html.push_str(&svg_curve(&inv_series("loss"), "inverse loss"));
        html.push_str("</div>");
    }
    let env_ours = run.join("eval/envmap.png");
    if env_ours.is_file() {
        let _ = write!(
            html,
            "<h3>Environment light: ground truth | recovered (same exposure)</h3><div class=row>{}{}</div>",
            wide_img_tag(&run.join("eval/envmap_gt.png")),
            wide_img_tag(&env_ours)
        );
        html.push_str(
            "<h3>Materials and light per view: GT | PBR render | GT albedo | our albedo (median-scaled) | \
             GT roughness | ours | GT indirect | ours</h3>",
        );
        if let Some(views) = metrics["per_view"].as_array() {
            for v in views.iter().take(4) {
                let name = v["view"].as_str().unwrap_or("");
                let e = |f: &str| img_tag(&run.join(format!("eval/{name}_{f}.png")));
                let gt_ind = tmp.join(format!("{name}_indirect_gt.png"));
                let gt_ind_tag = if indirect_to_png(&data.join(name).join("indirect.exr"), &gt_ind).is_ok() {
                    img_tag(&gt_ind)
                } else {
                    String::new()
                };
                let _ = write!(
                    html,
                    "<div class=row>{}{}{}{}{}{}{}{}</div>",
                    img_tag(&tmp.join(format!("{name}.png"))),
                    e("pbr"),
                    img_tag(&data.join(name).join("albedo.png")),
                    e("albedo"),
                    img_tag(&data.join(name).join("roughness.png")),
                    e("roughness"),
                    gt_ind_tag,
                    e("indirect"),
                );
            }
        }
    }
    if let Some(relit) = metrics.get("relight").and_then(|r| r.as_array()) {
        html.push_str("<h2>Relighting: GT | ray-traced PBR | finetuned surfels</h2><table><tr><th>light</th><th>mode</th><th>PSNR</th><th>SSIM</th><th>setup s</th><th>ms/frame</th></tr>");
        for m in relit {
            let _ = write!(
                html,
                "<tr><td>{}</td><td>{}</td><td>{:.2}</td><td>{:.4}</td><td>{:.1}</td><td>{:.1}</td></tr>",
                m["light"].as_str().unwrap_or(""),
                m["mode"].as_str().unwrap_or(""),
                m["psnr"].as_f64().unwrap_or(f64::NAN),
                m["ssim"].as_f64().unwrap_or(f64::NAN),
                m["seconds"].as_f64().unwrap_or(f64::NAN),
                m["frame_ms"].as_f64().unwrap_or(f64::NAN),
            );
        }
        html.push_str("</table>");
        let mut lights: Vec<&str> = relit.iter().filter_map(|m| m["light"].as_str()).collect();
        lights.dedup();
        if let Some(views) = metrics["per_view"].as_array() {
            for light in lights {
                for v in views.iter().take(2) {
                    let name = v["view"].as_str().unwrap_or("");
                    let gt_src = data.join(name).join(format!("rgba_{light}.png"));
                    let gt_png = tmp.join(format!("{name}_{light}.png"));
                    let gt = if gt_over_white(&gt_src, &gt_png).is_ok() { img_tag(&gt_png) } else { img_tag(&gt_src) };
                    let _ = write!(
                        html,
                        "<div class=row>{gt}{}{}<span>{name} under {light}</span></div>",
                        img_tag(&run.join(format!("eval/{name}_relit_{light}_traced.png"))),
                        img_tag(&run.join(format!("eval/{name}_relit_{light}_finetune.png"))),
                    );
                }
            }
        }
        if let Some(p) = metrics.get("relight_protocol").and_then(|p| p.as_str()) {
            let _ = write!(html, "<p><small>{p}</small></p>");
        }
    }
    if let Some(p) = metrics.get("pbr_protocol") {
        let _ = write!(html, "<p><small>PBR protocol: {}</small></p>", p);
    }
    crate::io::atomic::write_atomic(path, html.as_bytes())?;
    let _ = std::fs::remove_dir_all(&tmp);
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn durations_read_as_seconds_then_minutes() {
        assert_eq!(super::minutes(0.0), "0.0 s");
        assert_eq!(super::minutes(59.94), "59.9 s");
        assert_eq!(super::minutes(59.96), "1 min 00 s");
        assert_eq!(super::minutes(60.0), "1 min 00 s");
        assert_eq!(super::minutes(676.4), "11 min 16 s");
        assert_eq!(
            super::time_split(90.0, &[("training", 61.0), ("report", 2.5)]),
            "1 min 30 s in all: training 1 min 01 s, report 2.5 s"
        );
    }

    /// The demo's dataset keeps its size and 32 spp whatever `synth`'s defaults are (its 256
    /// made the demo's synthesis ~4 × longer in session 65).
    #[test]
    fn the_demo_synthesises_at_its_own_size_and_32_spp() {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Wrapper {
            #[command(flatten)]
            args: super::DemoArgs,
        }
        let demo = Wrapper::parse_from(["demo"]).args;
        let s = super::demo_synth_args(&demo, std::path::Path::new("demo/data")).unwrap();
        assert_eq!((s.spp, s.res, s.train_views, s.test_views), (32, 128, 48, 8));
        assert_eq!(s.relight_envs, Some(vec!["studio".to_string(), "sunset".to_string()]));
    }

    #[test]
    fn base64_matches_rfc4648_vectors() {
        for (input, want) in [("", ""), ("f", "Zg=="), ("fo", "Zm8="), ("foo", "Zm9v"), ("foobar", "Zm9vYmFy")] {
            assert_eq!(super::base64(input.as_bytes()), want);
        }
    }
}
