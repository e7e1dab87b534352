//! Diagnostic: how right is a run's traced visibility? For the surfels that lie on the floor
//! (nearest object = the first "floor" object of the dataset's README.json, within 15 mm of its
//! true surface, facing up) every cached direction is re-tested against the true objects
//! (analytic ray entry from the surfel's foot point on the true surface) and compared with the
//! cached transmittance. Prints, binned by the horizontal gap to the nearest sphere: mean cached
//! vs true visibility, leaks (truly blocked, cached T > 0.5), false blocks, ratios of direct
//! light under the true env restricted to the cached directions, the shader's own direct-light
//! estimate against the same estimator about the true normal (512 directions, true visibility)
//! and with our normal but the true visibility, and the normals' tilt and lean away from the
//! nearest sphere. Last, the shadow of the light's brightest texel (a sun): one ray per floor
//! surfel traced one-sided (as the PBR stages) and two-sided, its transmittance where the true
//! spheres block it (a leak) and where they do not. Reads the Cycles datasets of `../shared/data`
//! and `radiogs synth` scenes.
//!
//!     cargo run --release --example probe_visibility -- RUN DATA
//!
//! `SKIP_MARGIN=m` overrides the run's `ray_skip_margin` (× extent; 0 = off).

#[path = "common/probe_run.rs"]
mod probe_run;
#[path = "common/scene_readme.rs"]
mod scene_readme;

use anyhow::Context;
use radiogs::pbr_scene::PbrScene;
use radiogs::shade::sampling::{ElevationFloor, MIN_ELEVATION_DEG, fibonacci_hemisphere};

fn main() -> anyhow::Result<()> {
    let probe_run::ProbeRun { data, cfg, extent, surfels, back_faces, .. } = probe_run::from_args("probe_visibility")?;
    let readme = scene_readme::load(&data)?;
    let env_path = readme.train_env_path(&data);
    let true_env = radiogs::envmap::EnvMap::load(&env_path)?;
    let start = cfg.ray_start(extent);
    let scene = PbrScene::new(surfels, true_env.clone(), cfg.pbr_samples, start, cfg.window, 1, cfg.seed, back_faces);
    probe_run::print_cache(scene.surfels.len(), scene.cache.samples, start);
    let floor = readme.objects.iter().position(|o| o.object.contains("floor")).context("no floor object")?;
    let spheres: Vec<usize> =
        (0..readme.objects.len()).filter(|&k| k != floor && readme.objects[k].kind == "uv_sphere").collect();
    let ns = scene.cache.samples;
    // Bins by horizontal gap from the surfel to the nearest sphere's footprint edge (scene units).
    let edges = [0.0, 0.05, 0.1, 0.2, 0.4, f64::INFINITY];
    #[derive(Default, Clone, Copy)]
    struct Bin {
        surfels: usize,
        dirs: usize,
        vis_ours: f64,
        vis_true: f64,
        leaks: usize,
        false_blocks: usize,
        blocked: usize,
        direct_ours: f64,
        direct_true: f64,
        direct_true_cos: f64,
        direct_true_vis: f64,
        shader_ours: f64,
        shader_true: f64,
        shader_our_normal: f64,
        radial_lean: f64,
        tilt: f64,
        mean_normal: [f64; 3],
    }
    let mut bins = vec![Bin::default(); edges.len() - 1];
    // Floor surfels (index, foot point, gap bin) for the sun-ray section at the end.
    let mut floor_surfels: Vec<(usize, [f64; 3], usize)> = Vec::new();
    let mut dense = vec![[0.0f32; 3]; 512];
    // Luminance-weighted mean direction of the true light over the upper hemisphere.
    let mut light_dir = [0.0f64; 3];
    for k in 0..4096 {
        let z = 1.0 - (k as f64 + 0.5) / 4096.0;
        let phi = k as f64 * 2.399_963_229_728_653;
        let r = (1.0 - z * z).sqrt();
        let d = [r * phi.cos(), r * phi.sin(), z];
        let l = true_env.lookup(d.map(|x| x as f32));
        let lum = (0.2126 * l[0] + 0.7152 * l[1] + 0.0722 * l[2]) as f64;
        for a in 0..3 {
            light_dir[a] += lum * d[a];
        }
    }
    println!(
        "true light's mean direction (upper hemisphere): elevation {:.1}°, azimuth {:.1}°",
        90.0 - mean_tilt(light_dir),
        light_dir[1].atan2(light_dir[0]).to_degrees()
    );
    for i in 0..scene.surfels.len() {
        let p = scene.surfels.means[i].map(|x| x as f64);
        let Some(f) = scene_readme::foot_on_upward_face(&readme.objects, floor, p) else { continue };
        let foot = [f[0], f[1], f[2] + 1e-6];
        let gap = spheres
            .iter()
            .map(|&k| {
                let s = &readme.objects[k];
                let h = ((foot[0] - s.location[0]).powi(2) + (foot[1] - s.location[1]).powi(2)).sqrt();
                h - s.params.radius.unwrap_or(0.0)
            })
            .fold(f64::INFINITY, f64::min);
        let Some(b) = edges.windows(2).position(|w| gap >= w[0] && gap < w[1]) else { continue };
        // Unit horizontal direction from the nearest sphere's centre to the foot point.
        let nearest_sphere = spheres
            .iter()
            .copied()
            .min_by(|&a, &c| {
                let g = |k: usize| {
                    let s = &readme.objects[k];
                    ((foot[0] - s.location[0]).powi(2) + (foot[1] - s.location[1]).powi(2)).sqrt()
                        - s.params.radius.unwrap_or(0.0)
                };
                g(a).total_cmp(&g(c))
            })
            .context("no sphere")?;
        let c = readme.objects[nearest_sphere].location;
        let (rx, ry) = (foot[0] - c[0], foot[1] - c[1]);
        let rl = (rx * rx + ry * ry).sqrt().max(1e-12);
        floor_surfels.push((i, foot, b));
        let bin = &mut bins[b];
        bin.surfels += 1;
        let n = scene.surfels.normal(i);
        bin.tilt += (n[2] as f64).clamp(-1.0, 1.0).acos().to_degrees();
        // Lean of the normal away from the sphere (degrees; negative: towards it).
        bin.radial_lean += ((n[0] as f64 * rx + n[1] as f64 * ry) / rl).clamp(-1.0, 1.0).asin().to_degrees();
        for a in 0..3 {
            bin.mean_normal[a] += n[a] as f64;
        }
        // The shader's own estimate (its directions about our normal, below the true horizon
        // included, per-sample solid angle of the 10°-floor spiral) against the same estimator
        // about the true normal with 512 directions and the true visibility.
        let lum_of = |d: [f32; 3]| {
            let l = true_env.lookup(d);
            (0.2126 * l[0] + 0.7152 * l[1] + 0.0722 * l[2]) as f64
        };
        let cap = 2.0 * std::f64::consts::PI * (1.0 - MIN_ELEVATION_DEG.to_radians().sin());
        for q in 0..ns {
            let dir = scene.cache.dirs[i * ns + q];
            let cos = (n[0] * dir[0] + n[1] * dir[1] + n[2] * dir[2]).max(0.0) as f64;
            bin.shader_ours += lum_of(dir) * cos * scene.cache.visibility[i * ns + q] as f64 * cap / ns as f64;
        }
        fibonacci_hemisphere([0.0, 0.0, 1.0], 0.0, MIN_ELEVATION_DEG, ElevationFloor::Spread, &mut dense);
        for d in &dense {
            let dd = d.map(|x| x as f64);
            if !spheres.iter().any(|&k| readme.objects[k].ray_entry(foot, dd).is_some()) {
                bin.shader_true += lum_of(*d) * dd[2] * cap / dense.len() as f64;
            }
        }
        // The same dense estimator about our normal with the true visibility (the true floor
        // blocks what lies below its plane): the share of the error due to the normal alone.
        fibonacci_hemisphere(n, 0.0, MIN_ELEVATION_DEG, ElevationFloor::Spread, &mut dense);
        for d in &dense {
            let dd = d.map(|x| x as f64);
            if dd[2] > 0.0 && !spheres.iter().any(|&k| readme.objects[k].ray_entry(foot, dd).is_some()) {
                let cos = (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]).max(0.0) as f64;
                bin.shader_our_normal += lum_of(*d) * cos * cap / dense.len() as f64;
            }
        }
        for q in 0..ns {
            let dir = scene.cache.dirs[i * ns + q];
            let dd = dir.map(|x| x as f64);
            // True hemisphere of the floor (normal +z).
            if dd[2] <= 0.0 {
                continue;
            }
            let blocked = spheres.iter().any(|&k| readme.objects[k].ray_entry(foot, dd).is_some());
            let t = scene.cache.visibility[i * ns + q] as f64;
            let cos_ours = (n[0] * dir[0] + n[1] * dir[1] + n[2] * dir[2]).max(0.0) as f64;
            let l = true_env.lookup(dir);
            let lum = (0.2126 * l[0] + 0.7152 * l[1] + 0.0722 * l[2]) as f64;
            bin.dirs += 1;
            bin.vis_ours += t;
            bin.vis_true += if blocked { 0.0 } else { 1.0 };
            bin.blocked += blocked as usize;
            bin.leaks += (blocked && t > 0.5) as usize;
            bin.false_blocks += (!blocked && t < 0.5) as usize;
            bin.direct_ours += lum * cos_ours * t;
            bin.direct_true += lum * dd[2] * if blocked { 0.0 } else { 1.0 };
            bin.direct_true_cos += lum * dd[2] * t;
            bin.direct_true_vis += lum * cos_ours * if blocked { 0.0 } else { 1.0 };
        }
    }
    println!(
        "gap to sphere | surfels | dirs | vis ours | vis true | truly blocked | leaks (of blocked) | false blocks (of free) | direct ours/true | (true cos) | (true vis) | mean normal tilt °"
    );
    for (k, b) in bins.iter().enumerate() {
        if b.dirs == 0 {
            continue;
        }
        let nd = b.dirs as f64;
        println!(
            "[{:.2}, {:.2}) | {} | {} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.3} | {:.1} | {:.3} | {:.3} | {:+.1} | {:.1} ({:+.2})",
            edges[k],
            edges[k + 1],
            b.surfels,
            b.dirs,
            b.vis_ours / nd,
            b.vis_true / nd,
            b.blocked as f64 / nd,
            b.leaks as f64 / (b.blocked.max(1)) as f64,
            b.false_blocks as f64 / ((b.dirs - b.blocked).max(1)) as f64,
            b.direct_ours / b.direct_true.max(1e-12),
            b.direct_true_cos / b.direct_true.max(1e-12),
            b.direct_true_vis / b.direct_true.max(1e-12),
            b.tilt / b.surfels as f64,
            b.shader_ours / b.shader_true.max(1e-12),
            b.shader_our_normal / b.shader_true.max(1e-12),
            b.radial_lean / b.surfels as f64,
            mean_tilt(b.mean_normal),
            towards(b.mean_normal, light_dir)
        );
    }
    sun_rays(&scene, &true_env, start, &readme, &spheres, &floor_surfels, &edges);
    Ok(())
}

/// The shadow of the light's brightest direction (a sun): one ray per floor surfel, traced as
/// the cache traces (the run's ray start) one-sided (the PBR stages' back-face culling) and
/// two-sided, against the true spheres. A truly shadowed surfel's transmittance is a leak of
/// the sun into its shadow; a lit one's missing transmittance a false shadow.
fn sun_rays(
    scene: &PbrScene,
    true_env: &radiogs::envmap::EnvMap,
    start: radiogs::shade::incident::RayStart,
    readme: &scene_readme::SceneReadme,
    spheres: &[usize],
    floor_surfels: &[(usize, [f64; 3], usize)],
    edges: &[f64],
) {
    use radiogs::trace::{Ray, RayOutput, Tracer, skip_plane_above, trace};
    let (mut sun, mut best) = ([0.0f32, 0.0, 1.0], f32::NEG_INFINITY);
    for j in 0..true_env.height {
        for i in 0..true_env.width {
            let t = true_env.texels[j * true_env.width + i];
            let l = 0.2126 * t[0] + 0.7152 * t[1] + 0.0722 * t[2];
            if l > best {
                (best, sun) = (l, true_env.texel_dir(i, j));
            }
        }
    }
    println!(
        "sun rays: brightest texel at elevation {:.1}°, azimuth {:.1}°",
        (sun[2] as f64).clamp(-1.0, 1.0).asin().to_degrees(),
        (sun[1] as f64).atan2(sun[0] as f64).to_degrees()
    );
    let surfels = &scene.surfels;
    let rays: Vec<Ray> = floor_surfels
        .iter()
        .map(|&(i, _, _)| {
            let (n, m) = (surfels.normal(i), surfels.means[i]);
            let origin = [0, 1, 2].map(|k| m[k] + start.offset * n[k]);
            let skip_below = start.skip_margin.map_or([0.0; 4], |margin| skip_plane_above(n, m, margin));
            Ray { origin, dir: sun, skip_below }
        })
        .collect();
    let one = radiogs::train::inverse::trace_settings();
    let two = radiogs::trace::TraceSettings { two_sided: true, ..one.clone() };
    let mut t = [vec![RayOutput::default(); rays.len()], vec![RayOutput::default(); rays.len()]];
    for (settings, out) in [one, two].iter().zip(t.iter_mut()) {
        trace(&Tracer::build(surfels, settings), surfels, &rays, None, out, None);
    }
    println!(
        "gap to sphere | lit surfels | T one-sided / two-sided (lit) | shadowed surfels | T one-sided / two-sided (shadowed: the leak)"
    );
    let sun64 = sun.map(|x| x as f64);
    for b in 0..edges.len() - 1 {
        let (mut lit, mut shadowed) = ((0usize, 0.0f64, 0.0f64), (0usize, 0.0f64, 0.0f64));
        for (k, &(_, foot, bin)) in floor_surfels.iter().enumerate() {
            if bin != b {
                continue;
            }
            let blocked = spheres.iter().any(|&o| readme.objects[o].ray_entry(foot, sun64).is_some());
            let acc = if blocked { &mut shadowed } else { &mut lit };
            acc.0 += 1;
            acc.1 += t[0][k].transmittance as f64;
            acc.2 += t[1][k].transmittance as f64;
        }
        let mean = |a: (usize, f64, f64)| (a.1 / a.0.max(1) as f64, a.2 / a.0.max(1) as f64);
        let (l, s) = (mean(lit), mean(shadowed));
        println!(
            "[{:.2}, {:.2}) | {} | {:.3} / {:.3} | {} | {:.3} / {:.3}",
            edges[b],
            edges[b + 1],
            lit.0,
            l.0,
            l.1,
            shadowed.0,
            s.0,
            s.1
        );
    }
}

/// Angle of vector v from +z, degrees.
fn mean_tilt(v: [f64; 3]) -> f64 {
    let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
    (v[2] / l).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Cosine between the horizontal parts of v and the light direction.
fn towards(v: [f64; 3], light: [f64; 3]) -> f64 {
    let a = (v[0] * v[0] + v[1] * v[1]).sqrt() * (light[0] * light[0] + light[1] * light[1]).sqrt();
    if a > 0.0 { (v[0] * light[0] + v[1] * light[1]) / a } else { 0.0 }
}
