//! Every pixel's blend weights w_i = α_i T_i, kept so that new per-surfel features can be
//! blended again without re-running the per-pixel sorting windows.
//!
//! Why: the inverse stage's albedo–light gauge renders the same views under ~8–20 scaled
//! materials per fit. The geometry, hence every pixel's hits, their order and weights, is the
//! same for all of them; only the features change. Rasterising once and re-blending costs a
//! sparse product per evaluation instead of a render.

use super::forward::{TileData, composite_pixel};
use super::{RasterSettings, TILE, project, tiles};
use crate::camera::Camera;
use crate::surfels::Surfels;
use rayon::prelude::*;

/// Per pixel (row-major) the blended surfels and their weights, in blend order.
#[derive(Clone, Debug, Default)]
pub struct BlendWeights {
    pub width: u32,
    pub height: u32,
    /// Pixel p's hits are `ids[offsets[p]..offsets[p + 1]]` (and the same range of `weights`).
    pub offsets: Vec<u32>,
    pub ids: Vec<u32>,
    pub weights: Vec<f32>,
    /// Σ w per pixel: the rendered alpha.
    pub alpha: Vec<f32>,
}

impl BlendWeights {
    /// Rasterise `surfels` for `camera` with `settings` and keep the weights (what
    /// [`super::render`] blends, hit for hit).
    pub fn compute(surfels: &Surfels, camera: &Camera, settings: &RasterSettings) -> BlendWeights {
        let (w, h) = (camera.width, camera.height);
        let proj = project::project(surfels, camera, settings);
        let bins = tiles::bin(&proj, w, h, settings.alpha_min, settings.filter_inv_square);
        let k = settings.k();
        // One job per row of tiles: its pixels' (ids, weights) and per-pixel counts, row-major
        // within the tile row.
        let rows: Vec<(Vec<u32>, Vec<f32>, Vec<u32>)> = (0..bins.tiles_y)
            .into_par_iter()
            .map_init(TileData::default, |td, ty| {
                let (y0, y1) = (ty * TILE, ((ty + 1) * TILE).min(h));
                let px = ((y1 - y0) * w) as usize;
                // Per pixel of the row its hits; tiles visit pixels column block by block.
                let mut per_pixel: Vec<Vec<(u32, f32)>> = vec![Vec::new(); px];
                for tx in 0..bins.tiles_x {
                    let t = (ty * bins.tiles_x + tx) as usize;
                    let range = bins.offsets[t] as usize..bins.offsets[t + 1] as usize;
                    td.load(&proj, &bins.ids[range.clone()], &bins.quarter_masks[range], (tx * TILE, y0));
                    for y in y0..y1 {
                        for x in tx * TILE..((tx + 1) * TILE).min(w) {
                            let list = &mut per_pixel[((y - y0) * w + x) as usize];
                            let ids = &td.ids;
                            composite_pixel(td, x as f32 + 0.5, y as f32 + 0.5, settings, k, |li, _z, alpha, t| {
                                list.push((ids[li], alpha * t))
                            });
                        }
                    }
                }
                let mut ids = Vec::new();
                let mut weights = Vec::new();
                let mut counts = Vec::with_capacity(px);
                for list in per_pixel {
                    counts.push(list.len() as u32);
                    ids.extend(list.iter().map(|h| h.0));
                    weights.extend(list.iter().map(|h| h.1));
                }
                (ids, weights, counts)
            })
            .collect();
        let mut out = BlendWeights { width: w, height: h, offsets: vec![0], ..Default::default() };
        for (ids, weights, counts) in rows {
            for c in counts {
                let end = out.offsets.last().copied().unwrap_or(0) + c;
                out.offsets.push(end);
            }
            out.ids.extend(ids);
            out.weights.extend(weights);
        }
        out.alpha = (0..w as usize * h as usize)
            .into_par_iter()
            .with_min_len(1024)
            .map(|p| out.weights[out.offsets[p] as usize..out.offsets[p + 1] as usize].iter().sum())
            .collect();
        out
    }

    /// Blend channels `first..first + count` of the per-surfel `features` (N × `channels`) into
    /// `out` (pixels × `count`, resized): Σ_i w_i f_i per pixel, no background.
    pub fn blend(&self, features: &[f32], channels: usize, first: usize, count: usize, out: &mut Vec<f32>) {
        assert!(first + count <= channels, "channels {first}..{} of {channels}", first + count);
        let px = self.alpha.len();
        out.clear();
        out.resize(px * count, 0.0);
        if count == 0 {
            return;
        }
        out.par_chunks_mut(count).enumerate().with_min_len(1024).for_each(|(p, o)| {
            let range = self.offsets[p] as usize..self.offsets[p + 1] as usize;
            for (&id, &wgt) in self.ids[range.clone()].iter().zip(&self.weights[range]) {
                let f = &features[id as usize * channels + first..][..count];
                for c in 0..count {
                    o[c] += wgt * f[c];
                }
            }
        });
    }
}
