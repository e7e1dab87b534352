//! Diagnostic: is the floor's indirect light short because of visibility or of radiance?
//! For a subset of the upward-facing floor surfels of a `radiogs synth` run (nearest object
//! the README's floor, within 15 mm of it), every cached direction is re-cast from the
//! surfel's foot point on the true floor into the synth scene. Where it truly hits an object,
//! the true radiance leaving that hit towards the floor is path-traced (the dataset's
//! integrator and training env) and set beside our cached indirect radiance (the composited
//! SH colour, decoded, already weighted by 1 − T). Prints Σ ours / Σ truth, and how much of
//! the gap the opacity (1 − T) explains, per hit object and per height of the true hit's
//! normal (undersides are what no camera sees).
//!
//!     cargo run --release --example probe_incident_truth -- RUN DATA [STRIDE] [PATHS] [objects]
//!
//! STRIDE (default 25): every STRIDE-th floor surfel; PATHS (default 64): paths per hit.
//! `objects`: probe the surfels of the other objects instead (see [`probe_objects`]).

#[path = "common/probe_run.rs"]
mod probe_run;
#[path = "common/scene_readme.rs"]
mod scene_readme;

use anyhow::Context;
use glam::Vec3;
use radiogs::pbr_scene::PbrScene;
use radiogs::synth::envlight::EnvLight;
use radiogs::synth::geometry::Ray as SynthRay;
use radiogs::synth::integrator::{RenderOptions, trace_path};
use radiogs::synth::sampling::pixel_rng;

#[derive(Default, Clone, Copy)]
struct Sums {
    rays: usize,
    ours: f64,
    truth: f64,
    opacity: f64,
}

impl Sums {
    fn add(&mut self, ours: f64, truth: f64, opacity: f64) {
        self.rays += 1;
        self.ours += ours;
        self.truth += truth;
        self.opacity += opacity;
    }
    fn line(&self, name: &str) {
        if self.rays == 0 {
            return;
        }
        let op = self.opacity / self.rays as f64;
        println!(
            "{name:28} {:7} rays | ours {:.4} truth {:.4} | ours / truth {:.3} | mean 1 − T {:.3} | radiance ratio (ours / (1 − T) / truth) {:.3}",
            self.rays,
            self.ours / self.rays as f64,
            self.truth / self.rays as f64,
            self.ours / self.truth,
            op,
            self.ours / op / self.truth
        );
    }
}

fn main() -> anyhow::Result<()> {
    let probe_run::ProbeRun { run, data, cfg, extent, surfels, back_faces } =
        probe_run::from_args("probe_incident_truth")?;
    let args: Vec<String> = std::env::args().collect();
    let stride: usize = args.get(3).map(|s| s.parse()).transpose().context("STRIDE")?.unwrap_or(25).max(1);
    let paths: u32 = args.get(4).map(|s| s.parse()).transpose().context("PATHS")?.unwrap_or(64).max(1);
    let objects = match args.get(5).map(String::as_str) {
        None => false,
        Some("objects") => true,
        Some(other) => anyhow::bail!("mode {other:?}: the only mode is `objects` (leave it out for the floor)"),
    };
    let readme = scene_readme::load(&data)?;
    let info: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(data.join("README.json"))?)?;
    let scene_name = info["args"]["scene"].as_str().context("README.json: args.scene")?;
    let scene =
        radiogs::synth::scene::build(scene_name).with_context(|| format!("unknown synth scene {scene_name}"))?;
    let env_map = radiogs::envmap::EnvMap::load(&readme.train_env_path(&data))?;
    let env = EnvLight::new("train", env_map);
    let opts = RenderOptions { spp: 1, max_bounces: 8, rr_start: 3 };

    let learned = radiogs::envmap::EnvMap::load(&run.join("envmap.exr"))?;
    let factor = radiogs::train::inverse::sample_factor(&cfg);
    let start = cfg.ray_start(extent);
    let pbr = PbrScene::new(surfels, learned, cfg.pbr_samples, start, cfg.window, factor, cfg.seed, back_faces);
    let ns = pbr.cache.samples;
    let floor = readme.objects.iter().position(|o| o.object.contains("floor")).context("no floor object")?;
    if objects {
        return probe_objects(&readme, &scene, &env, &opts, &pbr, floor, stride, paths);
    }

    let mut rows = Vec::new();
    for i in 0..pbr.surfels.len() {
        let p = pbr.surfels.means[i].map(|x| x as f64);
        let Some(foot) = scene_readme::foot_on_upward_face(&readme.objects, floor, p) else { continue };
        if pbr.surfels.normal(i)[2] >= 0.7 {
            rows.push((i, Vec3::new(foot[0] as f32, foot[1] as f32, foot[2] as f32)));
        }
    }
    let picked: Vec<_> = rows.iter().step_by(stride).copied().collect();
    println!("{} floor surfels facing up, {} probed, {paths} paths per true hit", rows.len(), picked.len());

    use rayon::prelude::*;
    let names: Vec<String> = readme.objects.iter().map(|o| o.object.clone()).collect();
    let per_row: Vec<Vec<(usize, usize, f64, f64, f64)>> = picked
        .par_iter()
        .map(|&(i, foot)| {
            let mut out = Vec::new();
            for q in 0..ns {
                let d = Vec3::from(pbr.cache.dirs[i * ns + q]);
                if d.z <= 0.0 {
                    continue;
                }
                let ray = SynthRay { o: foot + 1e-4 * Vec3::Z, d };
                let Some(hit) = scene.intersect(&ray, f32::INFINITY) else {
                    continue;
                };
                let object = scene_readme::nearest(&readme.objects, hit.p.to_array().map(|x| x as f64));
                let mut rng = pixel_rng(7, i as u64, q as u64);
                let mut truth = Vec3::ZERO;
                for _ in 0..paths {
                    let (dl, il) = trace_path(&scene, &env, hit, d, &opts, &mut rng);
                    truth += dl + il;
                }
                let truth = truth / paths as f32;
                let ours = pbr.cache.indirect[i * ns + q];
                let opacity = 1.0 - pbr.cache.visibility[i * ns + q];
                // Where the true hit's normal points: below −0.3 is an underside.
                let band = ((hit.ng.z + 1.0) * 2.0).floor().clamp(0.0, 3.0) as usize;
                let g = |v: [f32; 3]| (v[0] + v[1] + v[2]) as f64 / 3.0;
                out.push((object, band, g(ours), g(truth.to_array()), opacity as f64));
            }
            out
        })
        .collect();
    let mut all = Sums::default();
    let mut by_object = vec![Sums::default(); names.len()];
    let mut by_band = [Sums::default(); 4];
    for &(object, band, ours, truth, opacity) in per_row.iter().flatten() {
        all.add(ours, truth, opacity);
        by_object[object].add(ours, truth, opacity);
        by_band[band].add(ours, truth, opacity);
    }
    println!("run {} (rays skip surfels < {:?} above the tangent plane)", run.display(), start.skip_margin);
    all.line("all truly blocked rays");
    for (name, s) in names.iter().zip(&by_object) {
        s.line(name);
    }
    for (b, s) in by_band.iter().enumerate() {
        s.line(&format!("hit normal z in [{:.1}, {:.1})", b as f32 * 0.5 - 1.0, b as f32 * 0.5 - 0.5));
    }
    // How much of the true indirect irradiance arrives below the cached directions' 10° floor.
    let z_min = (radiogs::shade::sampling::MIN_ELEVATION_DEG.to_radians().sin()) as f32;
    let band_paths = (paths / 4).max(1);
    let per_surfel: Vec<[f64; 5]> = picked
        .par_iter()
        .map(|&(i, foot)| {
            let mut rng = pixel_rng(11, i as u64, 0);
            // [indirect in the band, in the cap, env (unblocked) in the band, in the cap]
            let mut e = [0.0f64; 4];
            for (part, lo, hi, m) in [(0usize, 0.0f32, z_min, 64usize), (1, z_min, 1.0, 128)] {
                let weight = 2.0 * std::f64::consts::PI * (hi - lo) as f64 / m as f64;
                for k in 0..m {
                    use rand::RngExt;
                    let z = lo + (hi - lo) * (k as f32 + rng.random::<f32>()) / m as f32;
                    let phi = 2.0 * std::f32::consts::PI * rng.random::<f32>();
                    let r = (1.0 - z * z).max(0.0).sqrt();
                    let d = Vec3::new(r * phi.cos(), r * phi.sin(), z);
                    let ray = SynthRay { o: foot + 1e-4 * Vec3::Z, d };
                    match scene.intersect(&ray, f32::INFINITY) {
                        Some(hit) => {
                            let mut l = Vec3::ZERO;
                            for _ in 0..band_paths {
                                let (dl, il) = trace_path(&scene, &env, hit, d, &opts, &mut rng);
                                l += dl + il;
                            }
                            e[part] += weight * (l.element_sum() / 3.0 / band_paths as f32 * z) as f64;
                        }
                        None => e[2 + part] += weight * (env.eval(d).element_sum() / 3.0 * z) as f64,
                    }
                }
            }
            // Our estimate of the same indirect irradiance, as the shader weighs the cache.
            let n = pbr.surfels.normal(i);
            let mut ours = 0.0f64;
            for k in i * ns..(i + 1) * ns {
                let d = pbr.cache.dirs[k];
                let c = (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]).max(0.0) as f64;
                let w =
                    if pbr.cache.sample_weights.is_empty() { pbr.cache.weight } else { pbr.cache.sample_weights[k] };
                let l = pbr.cache.indirect[k];
                ours += w as f64 * c * (l[0] + l[1] + l[2]) as f64 / 3.0;
            }
            [e[0], e[1], e[2], e[3], ours]
        })
        .collect();
    let tot = per_surfel.iter().fold([0.0f64; 4], |a, e| [a[0] + e[0], a[1] + e[1], a[2] + e[2], a[3] + e[3]]);
    println!(
        "true irradiance below the {:.0}° floor, share of the total: indirect (from objects) {:.3}, env {:.3}",
        radiogs::shade::sampling::MIN_ELEVATION_DEG,
        tot[0] / (tot[0] + tot[1]),
        tot[2] / (tot[2] + tot[3])
    );
    // Our indirect irradiance against the truth's (whole hemisphere), by the truth's level.
    let truth_e: Vec<f64> = per_surfel.iter().map(|e| e[0] + e[1]).collect();
    let mut sorted = truth_e.clone();
    sorted.sort_by(f64::total_cmp);
    let q = |f: f64| sorted[((sorted.len() - 1) as f64 * f) as usize];
    let edges = [0.0, q(0.5), q(0.8), q(0.95), f64::INFINITY];
    println!("indirect irradiance ours / truth (whole hemisphere), surfels binned by the truth's:");
    for b in 0..4 {
        let (mut o, mut t, mut c) = (0.0, 0.0, 0);
        for (e, &te) in per_surfel.iter().zip(&truth_e) {
            if te >= edges[b] && te < edges[b + 1] {
                o += e[4];
                t += te;
                c += 1;
            }
        }
        println!(
            "  truth E in [{:.4}, {:.4}): {c:5} surfels, ours / truth {:.3}, share of the truth {:.2}",
            edges[b],
            edges[b + 1],
            o / t,
            t / truth_e.iter().sum::<f64>()
        );
    }
    let o: f64 = per_surfel.iter().map(|e| e[4]).sum();
    println!("  all: ours / truth {:.3}", o / truth_e.iter().sum::<f64>());
    Ok(())
}

/// The objects' surfels (nearest object not the floor, within 15 mm of its true surface, normal
/// within 45° of the true one): every cached direction in the true normal's hemisphere is
/// re-cast from the foot point on the true surface. Our indirect irradiance (the cache, weighed
/// with our normal) against the truth's over the same directions (path-traced radiance where the
/// true ray hits something, with the true normal), per height of the surfel's true normal and
/// per object; split into the directions that truly hit something and those that truly see the
/// sky. Beside it the direct light the same way (the learned light's scale is free: also shown
/// relative to all surfels'), and again under the true light with our normals and visibility and
/// with the true normal and our visibility (which of light, normals and visibility makes the
/// direct light's error; every sum runs over the cached directions, i.e. our normal's hemisphere); per face (the true normal's dominant axis) of each object the same
/// direct ratios, the albedo against the truth and the normals' lean (per surfel, not per pixel:
/// a crease's many small surfels weigh as much as a wall's few large ones); each object's albedo
/// against the truth and its mean roughness, and the truly blocked rays per hit object, the floor
/// also by the elevation it is seen at.
#[allow(clippy::too_many_arguments)]
fn probe_objects(
    readme: &scene_readme::SceneReadme,
    scene: &radiogs::synth::scene::Scene,
    env: &EnvLight,
    opts: &RenderOptions,
    pbr: &PbrScene,
    floor: usize,
    stride: usize,
    paths: u32,
) -> anyhow::Result<()> {
    use rayon::prelude::*;
    let ns = pbr.cache.samples;
    let mut rows = Vec::new();
    for i in 0..pbr.surfels.len() {
        let p = pbr.surfels.means[i].map(|x| x as f64);
        let k = scene_readme::nearest(&readme.objects, p);
        let o = &readme.objects[k];
        let d = o.sdf(p);
        if k == floor || d.abs() > 0.015 {
            continue;
        }
        let e = 1e-5;
        let g = [0, 1, 2].map(|a| {
            let mut q = p;
            q[a] += e;
            (o.sdf(q) - d) / e
        });
        let n_true = Vec3::new(g[0] as f32, g[1] as f32, g[2] as f32).normalize();
        if n_true.dot(Vec3::from(pbr.surfels.normal(i))) < 0.7 {
            continue;
        }
        let foot = Vec3::new((p[0] - d * g[0]) as f32, (p[1] - d * g[1]) as f32, (p[2] - d * g[2]) as f32);
        rows.push((i, foot, n_true));
    }
    let picked: Vec<_> = rows.iter().step_by(stride).copied().collect();
    println!("{} object surfels, {} probed, {paths} paths per true hit", rows.len(), picked.len());
    // Per surfel: the band of its true normal's z, its object, the sums `e` below, and per truly
    // blocked ray (hit object, ours, truth, our opacity 1 − T).
    let names: Vec<String> = readme.objects.iter().map(|o| o.object.clone()).collect();
    type Row = (usize, usize, [f64; 10], Vec<(usize, f64, f64, f64)>);
    let per_surfel: Vec<Row> = picked
        .par_iter()
        .map(|&(i, foot, n_true)| {
            let n_ours = Vec3::from(pbr.surfels.normal(i));
            // [ours indirect where truly blocked, ours indirect where truly open, truth indirect,
            //  ours direct (cached visibility × learned light), truth direct (the same directions
            //  where the true scene is open, the true light), and those two direct sums over the
            //  directions below the horizon only]
            // [7], [8]: our direct sums again with the true light in place of the learned one.
            let mut e = [0.0f64; 10];
            let mut hits = Vec::new();
            for q in 0..ns {
                let k = i * ns + q;
                let d = Vec3::from(pbr.cache.dirs[k]);
                let w =
                    if pbr.cache.sample_weights.is_empty() { pbr.cache.weight } else { pbr.cache.sample_weights[k] };
                let lum = |v: [f32; 3]| (v[0] + v[1] + v[2]) as f64 / 3.0;
                let ours = w as f64 * n_ours.dot(d).max(0.0) as f64 * lum(pbr.cache.indirect[k]);
                let cos_true = n_true.dot(d);
                let hit = if cos_true > 0.0 {
                    scene.intersect(&SynthRay { o: foot + 1e-4 * n_true, d }, f32::INFINITY)
                } else {
                    None
                };
                let ours_direct = w as f64
                    * n_ours.dot(d).max(0.0) as f64
                    * lum(pbr.env.lookup(d.to_array()))
                    * pbr.cache.visibility[k] as f64;
                let ours_direct_true_light = w as f64
                    * n_ours.dot(d).max(0.0) as f64
                    * (env.eval(d).element_sum() / 3.0) as f64
                    * pbr.cache.visibility[k] as f64;
                e[3] += ours_direct;
                e[7] += ours_direct_true_light;
                // [9]: the true normal's cosine with our visibility, under the true light.
                e[9] += w as f64
                    * cos_true.max(0.0) as f64
                    * (env.eval(d).element_sum() / 3.0) as f64
                    * pbr.cache.visibility[k] as f64;
                if d.z < 0.0 {
                    e[5] += ours_direct;
                    e[8] += ours_direct_true_light;
                }
                let Some(hit) = hit else {
                    e[1] += ours;
                    if cos_true > 0.0 {
                        let truth_direct = w as f64 * cos_true as f64 * (env.eval(d).element_sum() / 3.0) as f64;
                        e[4] += truth_direct;
                        if d.z < 0.0 {
                            e[6] += truth_direct;
                        }
                    }
                    continue;
                };
                let mut rng = pixel_rng(13, i as u64, q as u64);
                let mut l = Vec3::ZERO;
                for _ in 0..paths {
                    let (dl, il) = trace_path(scene, env, hit, d, opts, &mut rng);
                    l += dl + il;
                }
                let truth = w as f64 * cos_true as f64 * (l.element_sum() / 3.0 / paths as f32) as f64;
                e[0] += ours;
                e[2] += truth;
                let object = scene_readme::nearest(&readme.objects, hit.p.to_array().map(|x| x as f64));
                let opacity = 1.0 - pbr.cache.visibility[k] as f64;
                hits.push((object, ours, truth, opacity));
                if object == floor {
                    // The floor seen at this elevation (its SH read at −d): grazing is unseen.
                    let elevation = (-d.z).clamp(-1.0, 1.0).asin().to_degrees();
                    let bin = [15.0, 30.0, 60.0].iter().take_while(|&&e| elevation >= e).count();
                    hits.push((readme.objects.len() + bin, ours, truth, opacity));
                }
            }
            let band = ((n_true.z + 1.0) * 2.0).floor().clamp(0.0, 3.0) as usize;
            let own = scene_readme::nearest(&readme.objects, foot.to_array().map(|x| x as f64));
            (band, own, e, hits)
        })
        .collect();
    println!("indirect irradiance over the cached directions, by the surfel's true normal z, then by its object:");
    let groups = 5 + names.len();
    let all_direct = {
        let s = per_surfel.iter().fold([0.0; 2], |a, r| [a[0] + r.2[3], a[1] + r.2[4]]);
        s[0] / s[1]
    };
    for b in 0..groups {
        let rows: Vec<_> = per_surfel
            .iter()
            .filter(|r| {
                if b < 4 {
                    r.0 == b
                } else if b == 4 {
                    true
                } else {
                    r.1 == b - 5
                }
            })
            .collect();
        let s = rows.iter().fold([0.0; 10], |a, r| [0, 1, 2, 3, 4, 5, 6, 7, 8, 9].map(|c| a[c] + r.2[c]));
        let label = match b {
            0..4 => format!("[{:.1}, {:.1})", b as f32 * 0.5 - 1.0, b as f32 * 0.5 - 0.5),
            4 => "all".to_string(),
            _ => names[b - 5].clone(),
        };
        if s[2] > 0.0 {
            println!(
                "  {label:16} {:5} surfels | ours / truth {:.3} (truly blocked rays {:.3}, truly open rays add {:.3}) | mean truth E {:.4} | direct ours / truth {:.3} (÷ all's: {:.3}; from below the horizon: ours {:.3}, truth {:.3} of the truth's direct) | our normals and visibility under the true light: direct / truth {:.3} (below the horizon {:.3})",
                rows.len(),
                (s[0] + s[1]) / s[2],
                s[0] / s[2],
                s[1] / s[2],
                s[2] / rows.len() as f64,
                s[3] / s[4],
                s[3] / s[4] / all_direct,
                s[5] / s[4] / all_direct,
                s[6] / s[4],
                s[7] / s[4],
                s[8] / s[4]
            );
        }
    }
    // Per face: an object's surfels split by their true normal's dominant axis, since a wall's
    // two faces see opposite halves of the light. Albedo over every row of the face.
    let face_of = |n: Vec3| {
        let a = n.abs();
        let axis = if a.x >= a.y && a.x >= a.z {
            0
        } else if a.y >= a.z {
            1
        } else {
            2
        };
        2 * axis + usize::from(n[axis] < 0.0)
    };
    let face_names = ["+x", "-x", "+y", "-y", "+z", "-z"];
    println!("per face (true normal's dominant axis): direct ours / truth, under the true light, albedo ours / truth:");
    for (k, o) in readme.objects.iter().enumerate() {
        for (f, face_name) in face_names.iter().enumerate() {
            let mut s = [0.0f64; 10];
            let mut n = 0;
            for (r, p) in per_surfel.iter().zip(&picked) {
                if r.1 == k && face_of(p.2) == f {
                    n += 1;
                    for (sum, v) in s.iter_mut().zip(&r.2) {
                        *sum += v;
                    }
                }
            }
            let (mut ours, mut truth) = (0.0f64, 0.0f64);
            let (mut lean, mut angle, mut weight) = (Vec3::ZERO, 0.0f64, 0.0f64);
            for &(i, foot, n_true) in rows.iter() {
                let p = foot.to_array().map(|x| x as f64);
                if face_of(n_true) != f || scene_readme::nearest(&readme.objects, p) != k {
                    continue;
                }
                let w = pbr.surfels.opacity(i) as f64;
                let n_ours = Vec3::from(pbr.surfels.normal(i));
                lean += w as f32 * (n_ours - n_true);
                angle += w * n_ours.dot(n_true).clamp(-1.0, 1.0).acos().to_degrees() as f64;
                weight += w;
                ours += w * pbr.surfels.albedo(i).iter().map(|&a| a as f64).sum::<f64>();
                truth += w * o.base_colour(&readme.materials[&o.material], p).iter().sum::<f64>();
            }
            if n >= 3 && s[4] > 0.0 && truth > 0.0 {
                println!(
                    "  {:20} {} {:4} surfels | direct ours / truth {:.3} | true light {:.3} (with the true normal {:.3}) | albedo {:.3} | normal off {:.1}°, mean lean {:+.3} {:+.3} {:+.3}",
                    o.object,
                    face_name,
                    n,
                    s[3] / s[4],
                    s[7] / s[4],
                    s[9] / s[4],
                    ours / truth,
                    angle / weight,
                    lean.x / weight as f32,
                    lean.y / weight as f32,
                    lean.z / weight as f32
                );
            }
        }
    }
    // The albedo that multiplies this irradiance in the indirect pass: ours against the true base
    // colour, opacity-weighted over every row of each object (checkers: the cell's colour).
    println!("albedo ours / truth per object (opacity-weighted, channel sums), and our mean roughness:");
    for (k, o) in readme.objects.iter().enumerate() {
        let (mut ours, mut truth, mut rough, mut weight) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for &(i, foot, _) in rows.iter() {
            if scene_readme::nearest(&readme.objects, foot.to_array().map(|x| x as f64)) != k {
                continue;
            }
            let w = pbr.surfels.opacity(i) as f64;
            rough += w * pbr.surfels.roughness(i) as f64;
            weight += w;
            ours += w * pbr.surfels.albedo(i).iter().map(|&a| a as f64).sum::<f64>();
            let m = &readme.materials[&o.material];
            truth += w * o.base_colour(m, foot.to_array().map(|x| x as f64)).iter().sum::<f64>();
        }
        if truth > 0.0 {
            println!("  {:20} {:.3} | roughness {:.3}", o.object, ours / truth, rough / weight);
        }
    }
    println!("truly blocked rays by the object they truly hit (the floor also by the elevation it is seen at):");
    let labels: Vec<String> = names
        .iter()
        .cloned()
        .chain(
            ["floor seen at 0–15°", "floor seen at 15–30°", "floor seen at 30–60°", "floor seen at 60–90°"]
                .map(String::from),
        )
        .collect();
    for (k, name) in labels.iter().enumerate() {
        let (mut o, mut t, mut op, mut c) = (0.0, 0.0, 0.0, 0usize);
        for &(obj, ours, truth, opacity) in per_surfel.iter().flat_map(|r| &r.3) {
            if obj == k {
                o += ours;
                t += truth;
                op += opacity;
                c += 1;
            }
        }
        if c > 0 {
            println!("  {name:20} {c:7} rays | ours / truth {:.3} | mean 1 − T {:.3}", o / t, op / c as f64);
        }
    }
    Ok(())
}
