//! Per-surfel blend-weighted sums of per-pixel values: Σ_p w_ip · v_p over the pixels p a surfel
//! i is composited into, from the raster backward with the values as the feature gradient.
//! Included by several example binaries.
#![allow(dead_code)]

use radiogs::raster::{Features, RasterSettings, RenderGrads};
use radiogs::surfels::Surfels;

/// Reusable scratch of [`add_view`].
pub struct BlendSums {
    zeros: Vec<f32>,
    v_surfels: Surfels,
    v_features: Vec<f32>,
    /// Per surfel, the 4 channels' sums so far.
    pub sums: Vec<[f64; 4]>,
}

impl BlendSums {
    pub fn new(s: &Surfels) -> BlendSums {
        BlendSums {
            zeros: vec![0.0; s.len() * 4],
            v_surfels: s.zeros_like(),
            v_features: vec![0.0; s.len() * 4],
            sums: vec![[0.0; 4]; s.len()],
        }
    }

    /// Render `cam` (the forward output, for computing the pixel values from it), then add each
    /// surfel's blend-weighted sum of the 4-channel values `pixel_values(&output)` returns.
    pub fn add_view(
        &mut self,
        s: &Surfels,
        cam: &radiogs::camera::Camera,
        settings: &RasterSettings,
        pixel_values: impl FnOnce(&radiogs::raster::RenderOutput) -> anyhow::Result<Vec<f32>>,
    ) -> anyhow::Result<()> {
        let feats = Features { data: &self.zeros, channels: 4 };
        let (out, state) = radiogs::raster::forward::render(s, cam, settings, Some(feats));
        let grads = RenderGrads { v_features: pixel_values(&out)?, ..Default::default() };
        self.v_surfels.fill_zero();
        self.v_features.iter_mut().for_each(|x| *x = 0.0);
        radiogs::raster::backward::render_backward(
            s,
            cam,
            settings,
            Some(feats),
            &state,
            &grads,
            &mut self.v_surfels,
            Some(&mut self.v_features),
        );
        for (acc, v) in self.sums.iter_mut().zip(self.v_features.chunks_exact(4)) {
            for c in 0..4 {
                acc[c] += v[c] as f64;
            }
        }
        Ok(())
    }
}
