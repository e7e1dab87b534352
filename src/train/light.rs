//! The learned environment light of the PBR stages: H × 2H lat-long texels stored as log
//! radiance (the exp activation keeps them positive), their Adam state, the light priors and
//! the chain from texel gradients to the log parameters. Shared by `init` and `inverse`.

use crate::envmap::EnvMap;
use crate::error::{Error, Result};
use crate::loss;
use crate::optim::Adam;
use crate::train::checkpoint::Checkpoint;
use crate::train::config::TrainConfig;
use std::path::Path;

#[derive(Clone)]
pub struct LearnedLight {
    /// Log radiance, H × 2H × 3.
    pub log: Vec<f32>,
    pub adam: Adam,
    pub height: usize,
}

impl LearnedLight {
    /// A fresh light: the `env_init_map` resampled, or the constant `env_init`.
    pub fn fresh(cfg: &TrainConfig) -> Result<LearnedLight> {
        let h = cfg.env_height;
        let log: Vec<f32> = match &cfg.env_init_map {
            Some(path) => {
                EnvMap::load(path)?.resample(2 * h, h).texels.iter().flat_map(|t| t.map(|v| v.max(1e-4).ln())).collect()
            }
            None => vec![cfg.env_init.ln(); h * 2 * h * 3],
        };
        Ok(LearnedLight { adam: Adam::new(log.len(), cfg.lr_env), log, height: h })
    }

    /// The activated map (linear radiance).
    pub fn env(&self) -> EnvMap {
        let h = self.height;
        EnvMap {
            width: 2 * h,
            height: h,
            texels: self.log.chunks_exact(3).map(|c| [c[0].exp(), c[1].exp(), c[2].exp()]).collect(),
        }
    }

    /// Store into a checkpoint (arrays `env.*`, meta `env_height`, `env_adam_step`).
    pub fn put(&self, c: &mut Checkpoint) {
        if let Some(meta) = c.meta.as_object_mut() {
            meta.insert("env_height".into(), self.height.into());
            meta.insert("env_adam_step".into(), self.adam.step.into());
        }
        c.put("env.log", self.log.clone());
        c.put("env.adam_m", self.adam.m.clone());
        c.put("env.adam_v", self.adam.v.clone());
    }

    /// Read what [`put`](Self::put) stored; the learning rate comes from `cfg`.
    pub fn get(path: &Path, c: &Checkpoint, cfg: &TrainConfig) -> Result<LearnedLight> {
        let meta_u64 = |key: &str| c.meta_u64(path, key);
        let h = meta_u64("env_height")? as usize;
        if h < 8 || h % 8 != 0 {
            return Err(Error::format(path, "env_height", format!("{h} is not a multiple of 8 (at least 8)")));
        }
        let log = c.require(path, "env.log")?.to_vec();
        if log.len() != h * 2 * h * 3 {
            return Err(Error::format(path, "env.log", "size does not match env_height"));
        }
        let mut adam = Adam::new(log.len(), cfg.lr_env);
        adam.m = c.require(path, "env.adam_m")?.to_vec();
        adam.v = c.require(path, "env.adam_v")?.to_vec();
        if adam.m.len() != log.len() || adam.v.len() != log.len() {
            return Err(Error::format(path, "env.adam_m", "size does not match env.log"));
        }
        adam.step = meta_u64("env_adam_step")?;
        Ok(LearnedLight { log, adam, height: h })
    }

    /// Add the light priors (white light, total variation; weights from `cfg`) to the linear
    /// texel gradients `v_env` of `env` (= `self.env()`), then chain through the exp
    /// activation into `v_log`. Returns the weighted prior loss.
    pub fn priors_and_chain(
        &self,
        cfg: &TrainConfig,
        env: &EnvMap,
        v_env: &mut [[f32; 3]],
        v_log: &mut Vec<f32>,
    ) -> f32 {
        let mut prior = 0.0;
        if cfg.lambda_white_light > 0.0 {
            prior += cfg.lambda_white_light * loss::white_light_prior(&env.texels, cfg.lambda_white_light, v_env);
        }
        if cfg.lambda_env_tv > 0.0 {
            prior +=
                cfg.lambda_env_tv * loss::env_tv(&env.texels, 2 * self.height, self.height, cfg.lambda_env_tv, v_env);
        }
        v_log.clear();
        v_log.extend(v_env.iter().zip(&env.texels).flat_map(|(v, t)| [v[0] * t[0], v[1] * t[1], v[2] * t[2]]));
        prior
    }

    pub fn step(&mut self, v_log: &[f32]) {
        self.adam.step(&mut self.log, v_log);
    }
}
