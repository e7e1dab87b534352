//! Diagnostic: give a run's surfels the dataset's ground-truth materials (from the object list
//! in `DATA/README.json`, nearest object surface per surfel) and copy the true env, so that
//! `radiogs eval` on the result measures the ceiling of our shading model with this geometry.
//!
//!     cargo run --release --example oracle_materials -- RUN DATA OUT

use radiogs::surfels::{albedo_to_logit, logit};
use std::path::PathBuf;

fn sdf(obj: &serde_json::Value, p: [f32; 3]) -> f32 {
    let loc: Vec<f32> = obj["location"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
    let rz = obj["rotation_euler"][2].as_f64().unwrap() as f32;
    let d = [p[0] - loc[0], p[1] - loc[1], p[2] - loc[2]];
    // Into the object's frame (rotation about z only in these scenes).
    let (s, c) = rz.sin_cos();
    let q = [c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]];
    match obj["type"].as_str().unwrap() {
        "uv_sphere" => {
            let r = obj["params"]["radius"].as_f64().unwrap() as f32;
            (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - r
        }
        "box" => {
            let h: Vec<f32> =
                obj["params"]["half_extents"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
            let e = [q[0].abs() - h[0], q[1].abs() - h[1], q[2].abs() - h[2]];
            let out = (e[0].max(0.0).powi(2) + e[1].max(0.0).powi(2) + e[2].max(0.0).powi(2)).sqrt();
            out + e[0].max(e[1]).max(e[2]).min(0.0)
        }
        "cylinder" => {
            let r = obj["params"]["radius"].as_f64().unwrap() as f32;
            let half = 0.5 * obj["params"]["depth"].as_f64().unwrap() as f32;
            let e = [(q[0] * q[0] + q[1] * q[1]).sqrt() - r, q[2].abs() - half];
            (e[0].max(0.0).powi(2) + e[1].max(0.0).powi(2)).sqrt() + e[0].max(e[1]).min(0.0)
        }
        t => panic!("object type {t} not handled"),
    }
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let (run, data, out) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]), PathBuf::from(&args[3]));
    let readme: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(data.join("README.json"))?)?;
    let objects = readme["objects"].as_array().unwrap();
    let materials = &readme["materials"];
    let mut s = radiogs::eval::load_run_surfels(&run)?;
    let mut counts = vec![0usize; objects.len()];
    for i in 0..s.len() {
        let p = s.means[i];
        let (k, _) =
            objects.iter().enumerate().map(|(k, o)| (k, sdf(o, p).abs())).min_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
        counts[k] += 1;
        let m = &materials[objects[k]["material"].as_str().unwrap()];
        let f3 = |v: &serde_json::Value| -> Vec<f32> {
            v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect()
        };
        let base: Vec<f32> = if let Some(ch) = m["base_color_linear"].get("checker_object_space") {
            // Blender's checker texture on object coordinates (scale, |floor| parity per axis).
            let loc = f3(&objects[k]["location"]);
            let sc = ch["scale"].as_f64().unwrap() as f32;
            let cell = |c: f32| (((c + 1e-6) * 0.999_999 * sc).floor() as i64).abs() % 2;
            let (xi, yi, zi) = (cell(p[0] - loc[0]), cell(p[1] - loc[1]), cell(p[2] - loc[2]));
            if (xi == yi) == (zi == 1) { f3(&ch["color1"]) } else { f3(&ch["color2"]) }
        } else {
            f3(&m["base_color_linear"])
        };
        s.albedo_logits[i] = [albedo_to_logit(base[0]), albedo_to_logit(base[1]), albedo_to_logit(base[2])];
        s.roughness_logits[i] = logit(m["roughness"].as_f64().unwrap() as f32);
    }
    for (o, c) in objects.iter().zip(&counts) {
        println!("{:20} {c}", o["object"].as_str().unwrap());
    }
    std::fs::create_dir_all(&out)?;
    radiogs::io::ply::write_ply(&out.join("point_cloud.ply"), &s)?;
    std::fs::copy(run.join("config.toml"), out.join("config.toml"))?;
    let env_name = readme["environment"]["train_env"].as_str().unwrap();
    let env = radiogs::envmap::EnvMap::load(&data.join("envmaps").join(format!("{env_name}.exr")))?;
    let cfg = radiogs::eval::load_run_config(&run)?;
    let h = cfg.env_height;
    let env = env.resample(2 * h, h);
    env.save(&out.join("envmap.exr"))?;
    // The inverse checkpoint with these materials and the true light, so that a resumed
    // inverse stage starts from the truth (how far do the losses pull it away?).
    let ckpt_path = run.join("checkpoint_inverse.bin");
    if ckpt_path.is_file() {
        let mut c = radiogs::train::checkpoint::Checkpoint::load(&ckpt_path)?;
        let mut params = c.get_surfels(&ckpt_path, "params")?;
        anyhow::ensure!(params.len() == s.len(), "checkpoint and PLY differ in surfel count");
        params.albedo_logits.clone_from(&s.albedo_logits);
        params.roughness_logits.clone_from(&s.roughness_logits);
        c.put_surfels("params", &params);
        c.put("env.log", env.texels.iter().flatten().map(|v| v.max(1e-6).ln()).collect());
        let zeros = vec![0.0f32; env.texels.len() * 3];
        c.put("env.adam_m", zeros.clone());
        c.put("env.adam_v", zeros);
        c.save(&out.join("checkpoint_inverse.bin"))?;
        std::fs::copy(run.join("checkpoint.bin"), out.join("checkpoint.bin"))?;
    }
    Ok(())
}
