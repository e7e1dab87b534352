//! A trained relightable scene — surfels with materials, an env map and the per-surfel
//! incident-light cache — and its pictures: SH radiance, PBR (linear → sRGB), albedo,
//! roughness, indirect radiance (the L_ind part of each surfel's rendering equation),
//! visibility (cosine-weighted, per surfel) and normals, all from one rasterisation with
//! feature channels and back faces culled (the PBR stages' convention).

use crate::camera::Camera;
use crate::envmap::EnvMap;
use crate::raster::{self, Features, Outputs, RasterSettings};
use crate::shade::incident::IncidentCache;
use crate::shade::incident::RayStart;
use crate::shade::splitsum::SplitSum;
use crate::shade::traced_specular::TracedSpecular;
use crate::surfels::Surfels;
use crate::trace::Tracer;
use crate::train::config::Specular;
use crate::train::consistency::encode;
use crate::train::inverse::{BackFaces, SpecularLobe, SurfelShading, VIEW_CHANNELS, trace_settings_with};
use crate::train::material::MaterialView;
use std::path::Path;

pub struct PbrScene {
    pub surfels: Surfels,
    pub env: EnvMap,
    pub cache: IncidentCache,
    pub mats: MaterialView,
    pub window: usize,
    /// The rasteriser's screen-space filter (the training config's `filter_inv_square`).
    pub filter_inv_square: f32,
    /// The env is box-filtered by this factor for the rendering equation's samples
    /// (`env_sample_height` of the training config).
    pub sample_factor: usize,
    /// How the PBR colour gets its specular lobe (the training config's `specular`).
    pub specular: Specular,
    /// Where incident rays start (the cache's, and a traced specular lobe's).
    pub ray_start: RayStart,
    /// Rays per surfel of a traced specular lobe, and their seed: a picture is one sample of
    /// the estimate where training averages many, so renders draw [`RENDER_RAYS_FACTOR`] × the
    /// training config's `specular_rays`.
    pub specular_rays: usize,
    pub seed: u64,
    /// How traced rays treat back faces (the training config's `trace_back_faces`, and the
    /// run's unseen flags).
    pub back_faces: BackFaces,
}

/// A render's traced specular rays per training ray (see [`PbrScene::specular_rays`]).
pub const RENDER_RAYS_FACTOR: usize = 4;

/// Straight-alpha pictures of one view (colours over `bg` where they are composited).
#[derive(Clone, Debug, Default)]
pub struct PbrImages {
    pub width: u32,
    pub height: u32,
    pub alpha: Vec<f32>,
    /// SH radiance (sRGB) over the background.
    pub sh: Vec<[f32; 3]>,
    /// PBR radiance, sRGB-encoded (clipped), over the background.
    pub pbr: Vec<[f32; 3]>,
    /// Linear albedo / roughness / indirect radiance / visibility, un-premultiplied (0 where α ≈ 0).
    pub albedo: Vec<[f32; 3]>,
    pub roughness: Vec<f32>,
    pub indirect: Vec<[f32; 3]>,
    pub visibility: Vec<f32>,
    /// World normal Σ w n (not normalised).
    pub normal: Vec<[f32; 3]>,
}

impl PbrScene {
    /// A scene from its parts; traces the incident cache (S samples, where rays start in scene
    /// units; back faces as `back_faces` says, RadioGS: cull).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        surfels: Surfels,
        env: EnvMap,
        samples: usize,
        start: crate::shade::incident::RayStart,
        window: usize,
        sample_factor: usize,
        seed: u64,
        back_faces: BackFaces,
    ) -> PbrScene {
        let tracer = Tracer::build(&surfels, &trace_settings_with(&back_faces));
        let mut cache = IncidentCache::default();
        cache.refresh(&tracer, &surfels, samples, start, seed);
        let mut mats = MaterialView::default();
        mats.update(&surfels);
        PbrScene {
            surfels,
            env,
            cache,
            mats,
            window,
            filter_inv_square: crate::raster::filter_inv_square_2dgs(),
            sample_factor,
            specular: Specular::Mc,
            ray_start: start,
            specular_rays: RENDER_RAYS_FACTOR * crate::train::config::DEFAULT_SPECULAR_RAYS,
            seed,
            back_faces,
        }
    }

    /// Re-trace the incident cache with the share `env_importance` of each surfel's directions
    /// drawn from the map's peaks (the training setting `env_importance_inverse`); nothing
    /// happens at 0 or for a map without peaks.
    pub fn draw_from_light_peaks(&mut self, env_importance: f32) {
        let env_s = self.env.box_downsample(self.sample_factor.max(1));
        let samples = self.cache.samples;
        let Some(importance) = crate::shade::incident::EnvImportance::of_map(&env_s, samples, env_importance) else {
            return;
        };
        self.cache.set_importance(Some(importance));
        let tracer = Tracer::build(&self.surfels, &trace_settings_with(&self.back_faces));
        self.cache.refresh(&tracer, &self.surfels, samples, self.ray_start, self.seed);
    }

    /// The scene of a run after the inverse stage (`point_cloud.ply` + `envmap.exr`), or None
    /// when the run has no recovered light yet.
    pub fn from_run(run: &Path) -> anyhow::Result<Option<PbrScene>> {
        let env_path = run.join("envmap.exr");
        if !env_path.is_file() {
            return Ok(None);
        }
        let cfg = crate::eval::load_run_config(run)?;
        let surfels = crate::eval::load_run_surfels(run)?;
        let back_faces = BackFaces::of_run(run, cfg.trace_back_faces, surfels.len())?.of_config(&cfg);
        let env = EnvMap::load(&env_path)?;
        let extent = scene_extent(run);
        let start = cfg.ray_start(extent);
        if crate::relight::run_mode(run) == Some(crate::relight::RelightMode::Traced) {
            let mut mats = MaterialView::default();
            mats.update(&surfels);
            let sample_factor = crate::train::inverse::sample_factor(&cfg);
            let bounces = crate::relight::run_bounces(run);
            let (samples, env_importance) = crate::relight::run_sampling(run, cfg.pbr_samples);
            let cache = crate::relight::traced_cache(
                &surfels,
                &mats,
                &env,
                samples,
                start,
                cfg.seed,
                sample_factor,
                bounces,
                env_importance,
                &back_faces,
            )?;
            let specular = cfg.specular;
            let filter_inv_square = cfg.filter_inv_square;
            return Ok(Some(PbrScene {
                surfels,
                env,
                cache,
                mats,
                window: cfg.window,
                filter_inv_square,
                sample_factor,
                specular,
                ray_start: start,
                specular_rays: RENDER_RAYS_FACTOR * cfg.specular_rays,
                seed: cfg.seed,
                back_faces,
            }));
        }
        let factor = crate::train::inverse::sample_factor(&cfg);
        let mut scene = PbrScene::new(surfels, env, cfg.pbr_samples, start, cfg.window, factor, cfg.seed, back_faces);
        scene.draw_from_light_peaks(cfg.env_importance_inverse);
        scene.specular = cfg.specular;
        scene.specular_rays = RENDER_RAYS_FACTOR * cfg.specular_rays;
        scene.filter_inv_square = cfg.filter_inv_square;
        Ok(Some(scene))
    }

    /// The prefiltered env when the specular lobe is split-sum (build once, render many).
    pub fn split_sum(&self) -> Option<SplitSum> {
        match self.specular {
            Specular::SplitSum => {
                let env = if self.env.height.is_multiple_of(8) && self.env.width == 2 * self.env.height {
                    self.env.clone()
                } else {
                    self.env.resample(128, 64)
                };
                Some(SplitSum::new(&env).expect("H × 2H, H a multiple of 8"))
            }
            Specular::Mc | Specular::Traced => None,
        }
    }

    /// Render one view over the background `bg` (sRGB).
    pub fn render(&self, cam: &Camera, bg: [f32; 3]) -> PbrImages {
        self.render_with(cam, bg, self.split_sum().as_ref())
    }

    /// As [`render`](Self::render) with the prefiltered env of [`split_sum`](Self::split_sum).
    pub fn render_with(&self, cam: &Camera, bg: [f32; 3], split_sum: Option<&SplitSum>) -> PbrImages {
        let mut shading = SurfelShading::default();
        let env = self.env.box_downsample(self.sample_factor);
        let tracer = (self.specular == Specular::Traced)
            .then(|| Tracer::build(&self.surfels, &trace_settings_with(&self.back_faces)));
        let lobe = match (split_sum, &tracer) {
            (Some(ss), _) => SpecularLobe::SplitSum(ss),
            (None, Some(tracer)) => SpecularLobe::Traced(TracedSpecular {
                tracer,
                surfels: &self.surfels,
                env: &self.env,
                start: self.ray_start,
                rays: self.specular_rays,
                seed: self.seed,
            }),
            (None, None) => SpecularLobe::Cached,
        };
        shading.compute(&self.surfels, &self.mats, &self.cache, &env, lobe, cam, VIEW_CHANNELS);
        self.render_features(cam, bg, &shading.features)
    }

    /// Rasterise per-surfel features laid out as [`VIEW_CHANNELS`].
    pub fn render_features(&self, cam: &Camera, bg: [f32; 3], features: &[f32]) -> PbrImages {
        let ch = VIEW_CHANNELS;
        let settings = RasterSettings {
            window: self.window,
            filter_inv_square: self.filter_inv_square,
            two_sided: false,
            background: bg,
            outputs: Outputs { colour: true, normal: true, ..Outputs::none() },
            ..RasterSettings::default()
        };
        let (out, _) = raster::render(&self.surfels, cam, &settings, Some(Features { data: features, channels: ch }));
        let np = out.alpha.len();
        let bg_lin = bg.map(crate::io::image::srgb_to_linear);
        let mut img = PbrImages {
            width: cam.width,
            height: cam.height,
            alpha: out.alpha.clone(),
            sh: out.colour,
            normal: out.normal,
            ..Default::default()
        };
        for p in 0..np {
            let f = &out.features[p * ch..(p + 1) * ch];
            let a = out.alpha[p];
            let inv = if a > 1e-3 { 1.0 / a } else { 0.0 };
            img.pbr.push([0, 1, 2].map(|k| encode(f[k] + (1.0 - a) * bg_lin[k]).min(1.0)));
            img.albedo.push([f[3] * inv, f[4] * inv, f[5] * inv]);
            img.roughness.push(f[6] * inv);
            img.indirect.push([f[7] * inv, f[8] * inv, f[9] * inv]);
            img.visibility.push(f[10] * inv);
        }
        img
    }
}

/// The scene extent the run trained with (from its inverse checkpoint), else the radius of
/// the surfels' bounding box.
pub fn scene_extent(run: &Path) -> f32 {
    let ckpt = crate::train::inverse::checkpoint_path(run);
    if let Ok(c) = crate::train::checkpoint::Checkpoint::load(&ckpt)
        && let Some(e) = c.meta.get("extent").and_then(|v| v.as_f64())
    {
        return e as f32;
    }
    crate::eval::load_run_surfels(run)
        .ok()
        .and_then(|s| s.bounds())
        .map(|(lo, hi)| 0.5 * ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt())
        .unwrap_or(1.0)
}
