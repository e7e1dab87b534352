//! The occlusion-aware differentiable surfel rasteriser (issue 4, DESIGN §2).
//!
//! Pipeline: [`project`] (per surfel: the 2DGS homogeneous ray–splat transform, culling, screen
//! bounding box, SH colour) → [`tiles`] (binning into 16 × 16 tiles, per-tile sort by centre
//! depth) → [`forward`] (per pixel: hits in the tile's order pass through a sorted window of K
//! entries and are blended nearest-first) → [`backward`] (re-runs each pixel's window to get the
//! exact blend order, then walks it back to front).
//!
//! Images are pixel-major, row 0 at the top, pixel (x, y) at index y·width + x, pixel centre at
//! (x + 0.5, y + 0.5) (as `Camera::ray`).

pub mod backward;
pub mod blend_weights;
pub mod forward;
mod lanes;
pub mod project;
#[cfg(test)]
pub mod reference;
#[cfg(test)]
mod tests;
pub mod tiles;

pub use backward::render_backward;
pub use forward::{HitRecorder, render, render_recorded};

/// Tile side in pixels.
pub const TILE: u32 = 16;
/// Largest per-pixel sorting window.
pub const MAX_WINDOW: usize = 32;
/// The display stop (`RasterSettings::display_stop`) of relit display frames: a pixel then
/// misses at most 1/255 of the colour behind it, one level of an 8-bit display.
pub const DISPLAY_STOP: f32 = 1.0 / 255.0;
/// Largest number of feature channels.
pub const MAX_FEATURES: usize = 16;

/// Which per-pixel outputs to compute (alpha is always computed). Default: all on.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Outputs {
    pub colour: bool,
    pub depth: bool,
    pub median_depth: bool,
    pub normal: bool,
    pub distortion: bool,
    /// The surface-aware depth of GauS-SLAM (see `RenderOutput::surface_depth`). Off in every
    /// preset: it is a forward-only output for users who need depth without hidden-surface
    /// bleed.
    #[serde(default)]
    pub surface_depth: bool,
}

impl Default for Outputs {
    /// Every output with a gradient on (not `surface_depth`).
    fn default() -> Self {
        Outputs { colour: true, depth: true, median_depth: true, normal: true, distortion: true, surface_depth: false }
    }
}

impl Outputs {
    /// Only colour (and alpha).
    pub fn colour_only() -> Self {
        Outputs { colour: true, ..Outputs::none() }
    }
    /// Nothing but alpha (e.g. feature-only renders).
    pub fn none() -> Self {
        Outputs {
            colour: false,
            depth: false,
            median_depth: false,
            normal: false,
            distortion: false,
            surface_depth: false,
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RasterSettings {
    /// Per-pixel sorting window K (1 = plain 2DGS centre-depth order; clamped to 1..=32).
    pub window: usize,
    /// true: back faces are drawn with their normal flipped to face the camera (2DGS);
    /// false: surfels whose normal faces away from the camera are culled (RadioGS).
    pub two_sided: bool,
    /// Added to colour as T_final · background.
    pub background: [f32; 3],
    /// Near plane (camera z): surfel centres and hits closer than this are skipped.
    pub near: f32,
    /// Far value of the normalised depth used by the distortion loss.
    pub far: f32,
    pub outputs: Outputs,
    /// Hits with α below this are skipped (1/255). Tests lower it for finite differences.
    pub alpha_min: f32,
    /// Compositing stops before a blend would take T below this (1e-4).
    pub transmittance_min: f32,
    /// Compositing also stops right after a blend that took T below this (0 = never; off
    /// for training and evaluation). For display frames: what the pixel then misses is at
    /// most T times the colour behind it.
    #[serde(default)]
    pub display_stop: f32,
    /// The backward also sums AbsGS's statistic (`BackwardOutput::v_mean2d_abs`, else zeros):
    /// two more gradient columns per (tile, surfel) pair, so only when densification uses it.
    pub abs_centre_gradient: bool,
    /// 1/σ² (px⁻²) of the screen-space low-pass fallback ρ₂ = f·|μ₂D − pixel|² (2DGS's
    /// FilterInvSquare: 2, σ = 0.71 px). Larger is a sharper fallback.
    #[serde(default = "filter_inv_square_2dgs")]
    pub filter_inv_square: f32,
}

/// 2DGS's screen-space filter, 1/σ² = 2 px⁻²: what every run before the setting used.
pub fn filter_inv_square_2dgs() -> f32 {
    2.0
}

impl Default for RasterSettings {
    fn default() -> Self {
        RasterSettings {
            window: 8,
            two_sided: false,
            background: [0.0; 3],
            near: 0.2,
            far: 100.0,
            outputs: Outputs::default(),
            alpha_min: 1.0 / 255.0,
            transmittance_min: 1e-4,
            display_stop: 0.0,
            abs_centre_gradient: false,
            filter_inv_square: filter_inv_square_2dgs(),
        }
    }
}

impl RasterSettings {
    pub(crate) fn k(&self) -> usize {
        self.window.clamp(1, MAX_WINDOW)
    }
}

/// Per-surfel feature vectors rendered like colour (no background): N × channels, surfel-major.
#[derive(Clone, Copy, Debug)]
pub struct Features<'a> {
    pub data: &'a [f32],
    pub channels: usize,
}

/// Rendered images. Outputs that were not requested are empty vectors.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RenderOutput {
    pub width: u32,
    pub height: u32,
    /// Σ w c + T_final · background.
    pub colour: Vec<[f32; 3]>,
    /// Σ w = 1 − T_final (always computed).
    pub alpha: Vec<f32>,
    /// Expected depth Σ w z / α (camera z; 0 where α < 1e-6).
    pub depth: Vec<f32>,
    /// Camera z of the hit at which T first drops to ≤ 0.5 (the last hit if it never does; 0 if none).
    pub median_depth: Vec<f32>,
    /// World normal Σ w n (not normalised).
    pub normal: Vec<[f32; 3]>,
    /// Σ_{i<j} w_i w_j (m_i − m_j)², m = far/(far − near) · (1 − near/z) (2DGS; summed in closed form,
    /// A·M2 − M1² over m relative to the first blended hit).
    pub distortion: Vec<f32>,
    /// Σ w f, pixel-major, `channels` values per pixel.
    pub features: Vec<f32>,
    /// Surface-aware depth (GauS-SLAM): Σ w ẑ / Σ w, where a hit behind the running median
    /// depth d_m (z of the last blend made while T > 0.5) is pulled toward it,
    /// ẑ = c z + (1 − c) d_m, c = exp(−(z − d_m)² / (4 σ²)), σ² = Σ_{earlier} w (ẑ − d_m)² /
    /// Σ_{earlier} w (≥ 1e-7); the first hit and hits up to the median keep ẑ = z. 0 where
    /// nothing is blended. Forward only: no gradient.
    pub surface_depth: Vec<f32>,
}

/// Gradients of the loss with respect to each output; an empty vector means zero.
#[derive(Clone, Debug, Default)]
pub struct RenderGrads {
    pub v_colour: Vec<[f32; 3]>,
    pub v_alpha: Vec<f32>,
    pub v_depth: Vec<f32>,
    pub v_median_depth: Vec<f32>,
    pub v_normal: Vec<[f32; 3]>,
    pub v_distortion: Vec<f32>,
    pub v_features: Vec<f32>,
}

/// Per-surfel by-products of the backward pass (for densification).
#[derive(Clone, Debug, Default)]
pub struct BackwardOutput {
    /// ∂L/∂(projected centre) in NDC-like units, as 2DGS reports it:
    /// (∂L/∂T[0][2] · z · W/2, ∂L/∂T[1][2] · z · H/2), T the splat-to-pixel transform
    /// (rows Tu, Tv, Tw), z the centre's camera depth. Since x_pix = Tu.z / z, this is
    /// ∂L/∂x_pix · W/2 ≈ ∂L/∂x_ndc with the 3D (ray–splat) path included.
    pub v_mean2d: Vec<[f32; 2]>,
    /// AbsGS's homodirectional statistic, same units: per axis the sum over pixels of the
    /// absolute value of each pixel's contribution to `v_mean2d` (no cancellation between the
    /// pixels of a large surfel that pull its centre opposite ways).
    pub v_mean2d_abs: Vec<[f32; 2]>,
}

/// Everything the backward pass needs from the forward pass, plus per-surfel visibility.
#[derive(Clone, Debug, Default)]
pub struct ForwardState {
    pub width: u32,
    pub height: u32,
    pub proj: project::Projected,
    pub tiles: tiles::TileBins,
    /// Screen radius in pixels (the larger half-extent of the bounding box); 0 = not drawn.
    pub radii: Vec<f32>,
    /// Surfel drawn in this view (radius > 0).
    pub visible: Vec<bool>,
    /// Surfel-pixel evaluations of the tile lists: per pixel the entries of its tile's list up
    /// to early stop (what a per-tile compositor evaluates; the figure benchmarks report).
    pub evaluations: u64,
    /// The evaluations made: each pixel goes through its tile quarter's list only.
    pub evaluations_performed: u64,
    /// Every pixel's blended hits, when rendered by [`render_recorded`]: the backward then
    /// replays them instead of re-running each pixel's sorting window. Take it back
    /// (`state.record.take()`) to reuse its buffers in the next frame.
    pub record: Option<PixelHitRecord>,
}

/// One blended hit as the forward saw it: the candidate's index in its tile's list, its depth,
/// α and the transmittance in front of it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct RecordedHit {
    pub li: u32,
    pub z: f32,
    pub alpha: f32,
    pub t: f32,
}

/// The blended hits of one row of tiles, pixels in row-major order within the row.
#[derive(Clone, Debug, Default)]
pub(crate) struct RowHits {
    pub hits: Vec<RecordedHit>,
    /// Per pixel of the row (index (y − y0)·width + x): its range in `hits`, or
    /// [`NOT_RECORDED`] (the row had used up its share of the budget: the backward re-runs
    /// that pixel's window).
    pub spans: Vec<(u32, u32)>,
    /// Per pixel: the final transmittance.
    pub t_final: Vec<f32>,
}

pub(crate) const NOT_RECORDED: (u32, u32) = (u32::MAX, u32::MAX);

/// Every pixel's blended hits of one forward pass (16 bytes a hit, at most about
/// [`forward::RECORD_BUDGET_BYTES`]: pixels beyond a row's share are not recorded), kept for
/// the backward. Buffers are reused when a record
/// is handed back to [`render_recorded`].
#[derive(Clone, Debug, Default)]
pub struct PixelHitRecord {
    pub(crate) rows: Vec<RowHits>,
}

impl PixelHitRecord {
    /// Blended hits held.
    pub fn hits(&self) -> usize {
        self.rows.iter().map(|r| r.hits.len()).sum()
    }
    /// Pixels whose hits did not fit the budget (the backward re-runs their windows).
    pub fn pixels_not_recorded(&self) -> usize {
        self.rows.iter().map(|r| r.spans.iter().filter(|&&s| s == NOT_RECORDED).count()).sum()
    }
    /// Bytes in use (hits, spans, final transmittances).
    pub fn bytes(&self) -> usize {
        self.rows
            .iter()
            .map(|r| r.hits.len() * std::mem::size_of::<RecordedHit>() + r.spans.len() * 8 + r.t_final.len() * 4)
            .sum()
    }
}
