//! Diagnostic: give a run's surfels the dataset's ground-truth materials (from the object list
//! in `DATA/README.json`, nearest object surface per surfel) and copy the true env, so that
//! `radiogs eval` on the result measures the ceiling of our shading model with this geometry.
//!
//!     cargo run --release --example oracle_materials -- RUN DATA OUT
//!
//! `ORACLE_ALBEDO=a` or `ORACLE_ROUGHNESS=r` replace the true albedo (grey a) or roughness by a
//! constant: a resumed stage with the other material's learning rate at 0 then shows whether
//! one material can be learned when the light and the other material are right.
//! `ORACLE_ENV_CONSTANT=v` starts the checkpoint's light at the constant v instead of the true
//! env (the true materials kept; `envmap.exr` stays the true env until the resumed stage
//! writes its own): where does the light go when only it is learned?

#[path = "common/scene_readme.rs"]
mod scene_readme;

use anyhow::Context;
use radiogs::surfels::{albedo_to_logit, logit};
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 4 {
        anyhow::bail!("usage: oracle_materials RUN DATA OUT");
    }
    let (run, data, out) = (PathBuf::from(&args[1]), PathBuf::from(&args[2]), PathBuf::from(&args[3]));
    let readme = scene_readme::load(&data)?;
    let objects = &readme.objects;
    anyhow::ensure!(!objects.is_empty(), "{}: README.json lists no objects", data.display());
    let constant = |name: &str| -> anyhow::Result<Option<f32>> {
        match std::env::var(name) {
            Ok(v) => {
                let x: f32 = v.parse().with_context(|| format!("{name}={v}: not a number"))?;
                anyhow::ensure!(x > 0.0 && x < 1.0, "{name}={v}: must be inside (0, 1)");
                Ok(Some(x))
            }
            Err(_) => Ok(None),
        }
    };
    let (albedo_override, roughness_override) = (constant("ORACLE_ALBEDO")?, constant("ORACLE_ROUGHNESS")?);
    let env_constant: Option<f32> = match std::env::var("ORACLE_ENV_CONSTANT") {
        Ok(v) => {
            let x: f32 = v.parse().with_context(|| format!("ORACLE_ENV_CONSTANT={v}: not a number"))?;
            anyhow::ensure!(x.is_finite() && x > 0.0, "ORACLE_ENV_CONSTANT={v}: must be a positive radiance");
            Some(x)
        }
        Err(_) => None,
    };
    let mut s = radiogs::eval::load_run_surfels(&run)?;
    let mut counts = vec![0usize; objects.len()];
    for i in 0..s.len() {
        let p = s.means[i].map(|x| x as f64);
        let k = scene_readme::nearest(objects, p);
        counts[k] += 1;
        let m = &readme.materials[&objects[k].material];
        let base = objects[k].base_colour(m, p);
        s.albedo_logits[i] = base.map(|c| albedo_to_logit(albedo_override.unwrap_or(c as f32)));
        s.roughness_logits[i] = logit(roughness_override.unwrap_or(m.roughness as f32));
    }
    for (o, c) in objects.iter().zip(&counts) {
        println!("{:20} {c}", o.object);
    }
    std::fs::create_dir_all(&out)?;
    radiogs::io::ply::write_ply(&out.join("point_cloud.ply"), &s)?;
    std::fs::copy(run.join("config.toml"), out.join("config.toml"))?;
    let env_name = &readme.environment.train_env;
    let env = radiogs::envmap::EnvMap::load(&data.join("envmaps").join(format!("{env_name}.exr")))
        .with_context(|| format!("the training env {env_name} of {}", data.display()))?;
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
        c.put("env.log", env.texels.iter().flatten().map(|v| env_constant.unwrap_or(*v).max(1e-6).ln()).collect());
        let zeros = vec![0.0f32; env.texels.len() * 3];
        c.put("env.adam_m", zeros.clone());
        c.put("env.adam_v", zeros);
        c.save(&out.join("checkpoint_inverse.bin"))?;
        std::fs::copy(run.join("checkpoint.bin"), out.join("checkpoint.bin"))?;
    }
    Ok(())
}
