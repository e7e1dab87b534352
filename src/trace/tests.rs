//! Tests of the tracer against the brute-force f64 reference, refit against rebuild, and the
//! backward pass against finite differences.

use super::reference::{all_hits, trace_ref};
use super::*;
use crate::surfels::{Surfels, quat_with_normal};
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

fn random_scene(n: usize, seed: u64, degree: u32) -> Surfels {
    let mut rng = Pcg64::seed_from_u64(seed);
    let mut s = Surfels::default();
    for _ in 0..n {
        let mean: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
        let q: [f32; 4] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
        let scales = [rng.random_range(0.05..0.4f32), rng.random_range(0.05..0.4f32)];
        let op = rng.random_range(0.0..1.0f32);
        s.push(mean, scales, q, op, [rng.random(), rng.random(), rng.random()], [0.3; 3], 0.5);
        let last = s.len() - 1;
        for k in 1..16 {
            s.sh[last][k] = std::array::from_fn(|_| rng.random_range(-0.3..0.3f32));
        }
    }
    s.sh_degree = degree;
    s
}

fn random_rays(n: usize, seed: u64, s: &Surfels) -> Vec<Ray> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..n)
        .map(|k| {
            let origin: [f32; 3] = if k % 3 == 0 && !s.is_empty() {
                s.means[rng.random_range(0..s.len())]
            } else {
                std::array::from_fn(|_| rng.random_range(-1.5..1.5f32))
            };
            let d: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
            Ray { origin, dir: d.map(|x| x / l), ..Default::default() }
        })
        .collect()
}

fn close(a: f32, b: f64, tol: f64) -> bool {
    (a as f64 - b).abs() <= tol * (1.0 + b.abs())
}

fn compare_with_reference(s: &Surfels, rays: &[Ray], settings: &TraceSettings, features: Option<(&[f32], usize)>) {
    let tracer = Tracer::build(s, settings);
    let mut out = vec![RayOutput::default(); rays.len()];
    let ch = features.map(|f| f.1).unwrap_or(0);
    let mut of = vec![0.0f32; rays.len() * ch];
    trace(
        &tracer,
        s,
        rays,
        features.map(|(data, channels)| Features { data, channels }),
        &mut out,
        features.map(|_| &mut of[..]),
    );
    let (mut compared, mut with_hits) = (0, 0);
    for (k, ray) in rays.iter().enumerate() {
        let r = trace_ref(s, ray, settings, features);
        if r.fragile {
            continue;
        }
        compared += 1;
        with_hits += (!r.hits.is_empty()) as usize;
        let o = &out[k];
        let tol = 2e-4;
        let ok = close(o.transmittance, r.transmittance, tol)
            && close(o.depth, r.depth, tol)
            && (0..3).all(|a| close(o.radiance[a], r.radiance[a], tol) && close(o.normal[a], r.normal[a], tol))
            && (0..ch).all(|c| close(of[k * ch + c], r.features[c], tol));
        assert!(ok, "ray {k} {ray:?}: traced {o:?} vs reference {r:?}");
    }
    assert!(compared * 10 >= rays.len() * 9, "too many fragile rays: {compared}/{}", rays.len());
    assert!(with_hits * 4 >= compared, "the scene is too empty to test: {with_hits}/{compared}");
}

#[test]
fn matches_brute_force_on_random_scenes() {
    for (seed, degree) in [(1u64, 3u32), (2, 0), (3, 1)] {
        let s = random_scene(400, seed, degree);
        let rays = random_rays(600, seed + 100, &s);
        compare_with_reference(&s, &rays, &TraceSettings::default(), None);
        let two = TraceSettings { two_sided: true, chunk: 4, ..Default::default() };
        compare_with_reference(&s, &rays, &two, None);
        let one = TraceSettings { chunk: 1, min_transmittance: 1e-4, ..Default::default() };
        compare_with_reference(&s, &rays, &one, None);
    }
}

#[test]
fn matches_brute_force_with_features_and_t_max() {
    let s = random_scene(300, 7, 3);
    let mut rng = Pcg64::seed_from_u64(8);
    let feats: Vec<f32> = (0..s.len() * 5).map(|_| rng.random_range(-1.0..1.0f32)).collect();
    let rays = random_rays(400, 9, &s);
    let settings = TraceSettings { t_max: 1.2, chunk: 3, ..Default::default() };
    compare_with_reference(&s, &rays, &settings, Some((&feats, 5)));
}

#[test]
fn equal_depths_are_composited_in_index_order() {
    // Three coincident surfels with different colours: same t, order by index.
    let mut s = Surfels::default();
    let q = quat_with_normal([0.0, 0.0, -1.0]);
    for (k, c) in [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].into_iter().enumerate() {
        s.push([0.0, 0.0, 2.0], [1.0, 1.0], q, 0.3 + 0.2 * k as f32, c, [0.3; 3], 0.5);
    }
    // Put the brightest last in index order and check the traced order is by index.
    let rays = vec![Ray { origin: [0.1, -0.05, 0.0], dir: [0.0, 0.0, 1.0], ..Default::default() }];
    for chunk in [1, 2, 16] {
        let settings = TraceSettings { chunk, min_transmittance: 0.0, ..Default::default() };
        let tracer = Tracer::build(&s, &settings);
        let mut out = [RayOutput::default()];
        trace(&tracer, &s, &rays, None, &mut out, None);
        let r = trace_ref(&s, &rays[0], &settings, None);
        assert_eq!(r.hits, vec![0, 1, 2]);
        for c in 0..3 {
            assert!(close(out[0].radiance[c], r.radiance[c], 1e-5), "chunk {chunk}: {:?} vs {:?}", out[0], r);
        }
    }
}

#[test]
fn empty_scene_and_missing_rays() {
    let s = Surfels::default();
    let settings = TraceSettings::default();
    let tracer = Tracer::build(&s, &settings);
    let rays = random_rays(10, 1, &s);
    let mut out = vec![RayOutput::default(); 10];
    trace(&tracer, &s, &rays, None, &mut out, None);
    assert!(out.iter().all(|o| o.transmittance == 1.0 && o.radiance == [0.0; 3] && o.depth == 0.0));
    let mut v = s.zeros_like();
    let mut vr = vec![Ray::default(); 10];
    let g = vec![RayGrad { v_radiance: [1.0; 3], v_transmittance: 1.0, v_depth: 1.0, v_normal: [1.0; 3] }; 10];
    trace_backward(&tracer, &s, &rays, None, &g, None, &mut v, None, Some(&mut vr));
    assert!(vr.iter().all(|r| r.origin == [0.0; 3] && r.dir == [0.0; 3]));

    // A ray pointing away from every surfel hits nothing and gets zero gradients.
    let s = random_scene(50, 3, 3);
    let tracer = Tracer::build(&s, &settings);
    let rays = vec![Ray { origin: [5.0, 5.0, 5.0], dir: [0.0, 0.0, 1.0], ..Default::default() }];
    let mut out = [RayOutput::default()];
    trace(&tracer, &s, &rays, None, &mut out, None);
    assert_eq!(out[0].transmittance, 1.0);
    let mut v = s.zeros_like();
    let mut vr = [Ray::default()];
    trace_backward(&tracer, &s, &rays, None, &g[..1], None, &mut v, None, Some(&mut vr));
    assert_eq!(v, s.zeros_like());
    assert_eq!(vr[0], Ray::default());
}

#[test]
fn rays_leaving_a_surfel_skip_it() {
    let s = random_scene(200, 11, 2);
    let settings = TraceSettings::default();
    let tracer = Tracer::build(&s, &settings);
    // From each centre along the normal (and slightly tilted): the own surfel is at t ≈ 0.
    let rays: Vec<Ray> = (0..s.len())
        .map(|i| {
            let n = s.normal(i);
            Ray { origin: s.means[i], dir: n, ..Default::default() }
        })
        .collect();
    let mut out = vec![RayOutput::default(); rays.len()];
    trace(&tracer, &s, &rays, None, &mut out, None);
    for (i, ray) in rays.iter().enumerate() {
        let r = trace_ref(&s, ray, &settings, None);
        assert!(!r.hits.contains(&i));
        if !r.fragile {
            assert!(close(out[i].transmittance, r.transmittance, 2e-4), "{i}");
        }
    }
    // With t_min = 0 a two-sided surfel would be hit at t = 0 only through rounding; with the
    // offset the own surfel never contributes even when its opacity is high.
    let hit_self = rays.iter().enumerate().any(|(i, ray)| all_hits(&s, ray, &settings)[i].1);
    assert!(!hit_self);
}

#[test]
fn bounds_are_tight_and_contain_the_disk() {
    let s = random_scene(50, 5, 0);
    let tracer = Tracer::build(&s, &TraceSettings::default());
    // Rebuild the per-surfel boxes from leaves of one-primitive trees.
    for i in 0..s.len() {
        let one = Surfels {
            means: vec![s.means[i]],
            log_scales: vec![s.log_scales[i]],
            quats: vec![s.quats[i]],
            opacity_logits: vec![s.opacity_logits[i]],
            sh: vec![s.sh[i]],
            albedo_logits: vec![s.albedo_logits[i]],
            roughness_logits: vec![s.roughness_logits[i]],
            sh_degree: 0,
        };
        let t1 = Tracer::build(&one, &TraceSettings::default());
        let nd = t1.nodes[0];
        let o = s.opacity(i);
        if o < ALPHA_MIN {
            assert!(nd.min[0] > nd.max[0]);
            continue;
        }
        let r2 = 2.0 * (o as f64 * 255.0).ln();
        let rot = s.rotation(i);
        let sc = s.scale(i);
        // The extreme of the ellipse boundary along each axis, by dense sampling.
        for a in 0..3 {
            let mut hi = f64::NEG_INFINITY;
            for k in 0..20000 {
                let th = k as f64 / 20000.0 * std::f64::consts::TAU;
                let p = s.means[i][a] as f64
                    + r2.sqrt()
                        * (th.cos() * sc[0] as f64 * rot[0][a] as f64 + th.sin() * sc[1] as f64 * rot[1][a] as f64);
                hi = hi.max(p);
            }
            assert!(nd.max[a] as f64 >= hi - 1e-6, "surfel {i} axis {a}: box {} < disk {hi}", nd.max[a]);
            assert!((nd.max[a] as f64 - hi).abs() < 1e-4 * (1.0 + hi.abs()), "box not tight: {} vs {hi}", nd.max[a]);
        }
    }
    assert!(tracer.node_count() >= 1);
}

/// Surfels on the surfaces of three spheres with outward normals (a trained object's layout:
/// neighbouring surfels face the same way, so node normal cones are narrow and cull).
fn shell_scene(n: usize, seed: u64) -> Surfels {
    let mut rng = Pcg64::seed_from_u64(seed);
    let spheres = [([-0.5f32, 0.0, 0.0], 0.45f32), ([0.5, 0.1, 0.0], 0.4), ([0.0, 0.2, 0.7], 0.3)];
    let mut s = Surfels::default();
    for k in 0..n {
        let (c, r) = spheres[k % spheres.len()];
        let nrm = loop {
            let v: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
            let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            if l > 0.1 && l <= 1.0 {
                break v.map(|x| x / l);
            }
        };
        let mean = std::array::from_fn(|a| c[a] + r * nrm[a]);
        let scales = [rng.random_range(0.03..0.08f32), rng.random_range(0.03..0.08f32)];
        let op = rng.random_range(0.1..1.0f32);
        s.push(mean, scales, quat_with_normal(nrm), op, [rng.random(), rng.random(), rng.random()], [0.3; 3], 0.5);
    }
    s.sh_degree = 0;
    s
}

/// Rays from surfel centres into the hemisphere of their normal (the consistency and cache
/// rays), and from outside the shells.
fn leaving_rays(s: &Surfels, n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..n)
        .map(|k| {
            let d = loop {
                let v: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
                let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                if l > 0.1 && l <= 1.0 {
                    break v.map(|x| x / l);
                }
            };
            if k % 4 == 3 {
                // From outside, aimed at the middle.
                let o = d.map(|x| 2.5 * x);
                let aim: [f32; 3] = std::array::from_fn(|a| rng.random_range(-0.3..0.3f32) - o[a]);
                let l = (aim[0] * aim[0] + aim[1] * aim[1] + aim[2] * aim[2]).sqrt();
                return Ray { origin: o, dir: aim.map(|x| x / l), ..Default::default() };
            }
            let i = rng.random_range(0..s.len());
            let nrm = s.normal(i);
            let flip = if d[0] * nrm[0] + d[1] * nrm[1] + d[2] * nrm[2] < 0.0 { -1.0 } else { 1.0 };
            Ray { origin: s.means[i], dir: d.map(|x| flip * x), ..Default::default() }
        })
        .collect()
}

#[test]
fn normal_cones_bound_the_normals_below_them() {
    let s = shell_scene(900, 31);
    let tracer = Tracer::build(&s, &TraceSettings::default());
    let (mut narrow, mut interior) = (0, 0);
    for w in &tracer.wide {
        for j in 0..8 {
            if w.child[j] == u32::MAX {
                continue;
            }
            interior += 1;
            let threshold = w.cone[3][j];
            if threshold.is_finite() {
                narrow += 1;
                assert!(threshold > 0.0 && threshold < 1.0, "cull threshold {threshold}");
            }
        }
    }
    // Check the cone of every BVH2 node against its own surfels (via the leaf blocks).
    fn subtree_normals(t: &Tracer, k: usize, out: &mut Vec<[f32; 3]>) {
        let nd = t.nodes[k];
        if nd.count > 0 {
            let b = nd.right_or_first as usize;
            for lane in 0..8 {
                let i = t.blocks[b].index[lane];
                if i != u32::MAX && t.blocks[b].rho_max[lane] >= 0.0 {
                    out.push(t.slot_normal((b * 8 + lane) as u32));
                }
            }
        } else {
            subtree_normals(t, k + 1, out);
            subtree_normals(t, nd.right_or_first as usize, out);
        }
    }
    let cones = super::bvh::normal_cones_for_test(&tracer);
    for (k, cone) in cones.iter().enumerate() {
        let mut normals = Vec::new();
        subtree_normals(&tracer, k, &mut normals);
        if normals.is_empty() {
            assert!(cone.angle < 0.0);
            continue;
        }
        for n in normals {
            let c = (cone.axis[0] * n[0] + cone.axis[1] * n[1] + cone.axis[2] * n[2]) as f64;
            let angle = c.clamp(-1.0, 1.0).acos();
            assert!(angle <= cone.angle as f64, "node {k}: normal at {angle} outside the cone {}", cone.angle);
        }
    }
    assert!(narrow * 2 > interior, "too few cones narrow enough to cull: {narrow}/{interior}");
}

#[test]
fn rays_leaving_surfaces_match_brute_force() {
    // Rays leaving a shell are where the normal cones cull most; one-sided, two-sided (no
    // cone culling) and small chunks.
    let s = shell_scene(900, 41);
    let rays = leaving_rays(&s, 800, 42);
    compare_with_reference(&s, &rays, &TraceSettings::default(), None);
    compare_with_reference(&s, &rays, &TraceSettings { two_sided: true, ..Default::default() }, None);
    compare_with_reference(&s, &rays, &TraceSettings { chunk: 2, min_transmittance: 1e-4, ..Default::default() }, None);
}

#[test]
fn refit_after_flipping_surfels_matches_brute_force() {
    // Turn a third of the shell surfels inside out (normal −n, a 180° turn about t_u): the
    // refit must refresh the normal cones, or the culled subtrees would hide those surfels.
    let mut s = shell_scene(900, 51);
    let settings = TraceSettings::default();
    let mut tracer = Tracer::build(&s, &settings);
    for i in (0..s.len()).step_by(3) {
        let n = s.normal(i);
        s.quats[i] = quat_with_normal(n.map(|x| -x));
    }
    tracer.refit(&s);
    let rays = leaving_rays(&s, 800, 52);
    let mut a = vec![RayOutput::default(); rays.len()];
    let mut b = vec![RayOutput::default(); rays.len()];
    trace(&tracer, &s, &rays, None, &mut a, None);
    trace(&Tracer::build(&s, &settings), &s, &rays, None, &mut b, None);
    assert_eq!(a, b);
    compare_with_reference(&s, &rays, &settings, None);
}

#[test]
fn refit_matches_a_fresh_build() {
    let mut s = random_scene(500, 21, 3);
    let settings = TraceSettings::default();
    let mut tracer = Tracer::build(&s, &settings);
    assert!(!tracer.needs_rebuild());
    let mut rng = Pcg64::seed_from_u64(22);
    for i in 0..s.len() {
        for a in 0..3 {
            s.means[i][a] += rng.random_range(-0.3..0.3f32);
        }
        s.opacity_logits[i] += rng.random_range(-1.0..1.0f32);
        s.log_scales[i][0] += rng.random_range(-0.3..0.3f32);
        s.quats[i][1] += rng.random_range(-0.3..0.3f32);
    }
    tracer.refit(&s);
    let fresh = Tracer::build(&s, &settings);
    let rays = random_rays(500, 23, &s);
    let mut a = vec![RayOutput::default(); rays.len()];
    let mut b = vec![RayOutput::default(); rays.len()];
    trace(&tracer, &s, &rays, None, &mut a, None);
    trace(&fresh, &s, &rays, None, &mut b, None);
    assert_eq!(a, b);
    assert!(a.iter().filter(|o| o.transmittance < 1.0).count() > 100);

    // Scattering the surfels far apart degrades the refitted tree: a rebuild is wanted.
    let mut far = s.clone();
    for i in 0..far.len() {
        let k = (i * 7919) % far.len();
        far.means[i] = s.means[k].map(|x| x * 4.0);
    }
    tracer.refit(&far);
    assert!(tracer.quality_ratio() > 1.5 && tracer.needs_rebuild(), "ratio {}", tracer.quality_ratio());
    // A count change rebuilds on refit.
    far.append_copies(&[0, 1]);
    tracer.refit(&far);
    assert!(!tracer.count_mismatch(&far) && !tracer.needs_rebuild());
}

// ---------- finite differences ----------

/// A scene along +z whose hits are all away from the discontinuities (α = 1/255 edge, α clamp,
/// depth ties, grazing culls) for the given rays, so the outputs are smooth there.
/// `grazing_sin` > 0: surfel 3 is turned so that some rays hit it from behind within that
/// grazing tolerance (one-sided), and at least one ray must.
fn fd_scene(seed: u64, two_sided: bool, grazing: bool, grazing_sin: f32) -> (Surfels, Vec<Ray>, TraceSettings) {
    let settings = TraceSettings { chunk: 2, min_transmittance: 0.0, two_sided, grazing_sin, ..Default::default() };
    for attempt in 0..200u64 {
        let mut rng = Pcg64::seed_from_u64(seed * 1000 + attempt);
        let mut s = Surfels::default();
        let m = 6;
        for k in 0..m {
            let mut n = [rng.random_range(-0.5..0.5f32), rng.random_range(-0.5..0.5f32), -1.0];
            if grazing && k == 2 {
                n = [1.0, 0.0, -0.12];
            }
            if grazing_sin > 0.0 && k == 3 {
                n = [1.0, 0.0, 0.15];
            }
            if two_sided && k % 2 == 1 {
                n[2] = -n[2];
            }
            let qn = quat_with_normal(n);
            // Random spin about the normal.
            let th = rng.random_range(0.0..std::f32::consts::TAU);
            let spin = glam::Quat::from_axis_angle(glam::Vec3::from(n).normalize(), th)
                * glam::Quat::from_xyzw(qn[1], qn[2], qn[3], qn[0]);
            let mean = [rng.random_range(-0.2..0.2f32), rng.random_range(-0.2..0.2f32), 1.0 + 0.5 * k as f32];
            let sc = [rng.random_range(0.4..1.0f32), rng.random_range(0.4..1.0f32)];
            s.push(mean, sc, [spin.w, spin.x, spin.y, spin.z], rng.random_range(0.2..0.8), [0.5; 3], [0.3; 3], 0.5);
            for c in 0..16 {
                s.sh[k][c] = std::array::from_fn(|_| rng.random_range(-0.15..0.15f32));
            }
        }
        s.sh_degree = 3;
        let rays: Vec<Ray> = (0..4)
            .map(|_| {
                let origin = [rng.random_range(-0.1..0.1f32), rng.random_range(-0.1..0.1f32), 0.0];
                let d = [rng.random_range(-0.15..0.15f32), rng.random_range(-0.15..0.15f32), 1.0];
                let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                Ray { origin, dir: d.map(|x| x / l), ..Default::default() }
            })
            .collect();
        let back_hit = |ray: &Ray| all_hits(&s, ray, &settings).iter().any(|(h, valid)| *valid && h.cos > 0.0);
        let good = rays.iter().all(|ray| {
            let all = all_hits(&s, ray, &settings);
            let mut ts: Vec<f64> = Vec::new();
            for (h, valid) in &all {
                let o = crate::surfels::sigmoid(s.opacity_logits[h.index]) as f64;
                let r2 = 2.0 * (o * 255.0).ln();
                if h.cos.abs() < 0.05 || (h.rho - r2).abs() < 0.5 || h.t.abs() < 0.05 {
                    return false;
                }
                // Clear of the grazing tolerance's edge (unit ray directions).
                if grazing_sin > 0.0 && (h.cos - grazing_sin as f64).abs() < 0.05 {
                    return false;
                }
                if *valid {
                    ts.push(h.t);
                }
            }
            ts.sort_by(f64::total_cmp);
            ts.len() >= 2 && ts.windows(2).all(|w| w[1] - w[0] > 0.02)
        }) && (grazing_sin == 0.0 || rays.iter().any(back_hit));
        if good {
            return (s, rays, settings);
        }
    }
    panic!("no well-conditioned FD scene found");
}

struct Loss {
    g: Vec<RayGrad>,
    gf: Vec<f32>,
}

fn eval_loss(s: &Surfels, rays: &[Ray], settings: &TraceSettings, feats: Option<(&[f32], usize)>, l: &Loss) -> f64 {
    let tracer = Tracer::build(s, settings);
    let mut out = vec![RayOutput::default(); rays.len()];
    let ch = feats.map(|f| f.1).unwrap_or(0);
    let mut of = vec![0.0f32; rays.len() * ch];
    trace(
        &tracer,
        s,
        rays,
        feats.map(|(data, channels)| Features { data, channels }),
        &mut out,
        feats.map(|_| &mut of[..]),
    );
    let mut total = 0.0f64;
    for (o, g) in out.iter().zip(&l.g) {
        for a in 0..3 {
            total += (o.radiance[a] * g.v_radiance[a]) as f64 + (o.normal[a] * g.v_normal[a]) as f64;
        }
        total += (o.transmittance * g.v_transmittance) as f64 + (o.depth * g.v_depth) as f64;
    }
    total + of.iter().zip(&l.gf).map(|(a, b)| (*a * *b) as f64).sum::<f64>()
}

fn check(name: &str, analytic: f32, fd: f64) {
    let tol = 2e-3 + 1e-2 * fd.abs();
    assert!((analytic as f64 - fd).abs() <= tol, "{name}: analytic {analytic} vs finite difference {fd}");
}

fn fd_check(seed: u64, two_sided: bool, grazing: bool, channels: usize) {
    fd_check_with(seed, two_sided, grazing, channels, |_| {}, None);
}

/// `skip_z`: every ray skips the surfels whose centre lies below that height.
/// `tweak` adjusts the settings (linear radiance, dark back faces).
fn fd_check_with(
    seed: u64,
    two_sided: bool,
    grazing: bool,
    channels: usize,
    tweak: fn(&mut TraceSettings),
    skip_z: Option<f32>,
) {
    let grazing_sin = {
        let mut t = TraceSettings::default();
        tweak(&mut t);
        t.grazing_sin
    };
    let (s, mut rays, mut settings) = fd_scene(seed, two_sided, grazing, grazing_sin);
    if let Some(z) = skip_z {
        rays.iter_mut().for_each(|r| r.skip_below = [0.0, 0.0, 1.0, z]);
    }
    tweak(&mut settings);
    let mut rng = Pcg64::seed_from_u64(seed + 77);
    let feats: Vec<f32> = (0..s.len() * channels).map(|_| rng.random_range(-1.0..1.0f32)).collect();
    let fopt = (channels > 0).then_some((&feats[..], channels));
    let l = Loss {
        g: (0..rays.len())
            .map(|_| RayGrad {
                v_radiance: std::array::from_fn(|_| rng.random_range(-1.0..1.0f32)),
                v_transmittance: rng.random_range(-1.0..1.0f32),
                v_depth: rng.random_range(-1.0..1.0f32),
                v_normal: std::array::from_fn(|_| rng.random_range(-1.0..1.0f32)),
            })
            .collect(),
        gf: (0..rays.len() * channels).map(|_| rng.random_range(-1.0..1.0f32)).collect(),
    };
    let tracer = Tracer::build(&s, &settings);
    let mut v = s.zeros_like();
    let mut vf = vec![0.0f32; s.len() * channels];
    let mut vr = vec![Ray::default(); rays.len()];
    trace_backward(
        &tracer,
        &s,
        &rays,
        fopt.map(|(data, channels)| Features { data, channels }),
        &l.g,
        (channels > 0).then_some(&l.gf[..]),
        &mut v,
        (channels > 0).then_some(&mut vf[..]),
        Some(&mut vr),
    );
    let h = 1e-3f32;
    let fd_of = |f: &dyn Fn(&mut Surfels, f32)| -> f64 {
        let (mut a, mut b) = (s.clone(), s.clone());
        f(&mut a, h);
        f(&mut b, -h);
        (eval_loss(&a, &rays, &settings, fopt, &l) - eval_loss(&b, &rays, &settings, fopt, &l)) / (2.0 * h as f64)
    };
    let mut nonzero = 0;
    for i in 0..s.len() {
        for a in 0..3 {
            check(&format!("means[{i}][{a}]"), v.means[i][a], fd_of(&|x, e| x.means[i][a] += e));
        }
        for a in 0..2 {
            check(&format!("log_scales[{i}][{a}]"), v.log_scales[i][a], fd_of(&|x, e| x.log_scales[i][a] += e));
        }
        for a in 0..4 {
            check(&format!("quats[{i}][{a}]"), v.quats[i][a], fd_of(&|x, e| x.quats[i][a] += e));
        }
        check(&format!("opacity[{i}]"), v.opacity_logits[i], fd_of(&|x, e| x.opacity_logits[i] += e));
        if channels == 0 {
            for k in 0..16 {
                for c in 0..3 {
                    check(&format!("sh[{i}][{k}][{c}]"), v.sh[i][k][c], fd_of(&|x, e| x.sh[i][k][c] += e));
                }
            }
        }
        nonzero += (v.opacity_logits[i] != 0.0) as usize;
    }
    assert!(nonzero >= 2, "too few surfels were hit");
    if let Some(z) = skip_z {
        for i in (0..s.len()).filter(|&i| s.means[i][2] < z) {
            assert_eq!(v.opacity_logits[i], 0.0, "surfel {i} below the skip plane got a gradient");
        }
    }
    for j in 0..feats.len() {
        let (mut a, mut b) = (feats.clone(), feats.clone());
        a[j] += h;
        b[j] -= h;
        let fd = (eval_loss(&s, &rays, &settings, Some((&a, channels)), &l)
            - eval_loss(&s, &rays, &settings, Some((&b, channels)), &l))
            / (2.0 * h as f64);
        check(&format!("features[{j}]"), vf[j], fd);
    }
    for r in 0..rays.len() {
        for a in 0..3 {
            for which in 0..2 {
                let (mut ra, mut rb) = (rays.clone(), rays.clone());
                if which == 0 {
                    ra[r].origin[a] += h;
                    rb[r].origin[a] -= h;
                } else {
                    ra[r].dir[a] += h;
                    rb[r].dir[a] -= h;
                }
                let fd = (eval_loss(&s, &ra, &settings, fopt, &l) - eval_loss(&s, &rb, &settings, fopt, &l))
                    / (2.0 * h as f64);
                let an = if which == 0 { vr[r].origin[a] } else { vr[r].dir[a] };
                check(&format!("ray[{r}].{}[{a}]", ["origin", "dir"][which]), an, fd);
            }
        }
    }
}

#[test]
fn gradients_match_finite_differences() {
    fd_check(1, false, false, 0);
    fd_check(2, false, false, 0);
}

/// Rays that skip the first surfel (centres at z = 1, 1.5, …; the plane at z = 1.25): the
/// others' gradients still match, the skipped one gets none.
#[test]
fn gradients_match_finite_differences_with_a_skip_plane() {
    fd_check_with(5, false, false, 0, |s| s.linear_radiance = true, Some(1.25));
    fd_check_with(6, true, false, 2, |_| {}, Some(1.25));
}

/// Skip planes of rays leaving a surfel (its tangent plane raised by a margin, some below it)
/// against brute force, and they do change what the rays hit.
#[test]
fn skip_planes_match_brute_force() {
    let s = shell_scene(900, 51);
    let mut rng = Pcg64::seed_from_u64(52);
    let mut rays = leaving_rays(&s, 800, 53);
    let plain = rays.clone();
    for r in rays.iter_mut() {
        if let Some(i) = s.means.iter().position(|m| *m == r.origin) {
            let n = s.normal(i);
            r.skip_below = skip_plane_above(n, r.origin, rng.random_range(-0.05..0.4f32));
        }
    }
    let settings = TraceSettings::default();
    let changed = rays
        .iter()
        .zip(&plain)
        .filter(|(a, b)| trace_ref(&s, a, &settings, None).hits != trace_ref(&s, b, &settings, None).hits)
        .count();
    assert!(changed * 20 > rays.len(), "the skip planes changed only {changed} of {} rays", rays.len());
    compare_with_reference(&s, &rays, &settings, None);
    compare_with_reference(&s, &rays, &TraceSettings { two_sided: true, ..Default::default() }, None);
    compare_with_reference(&s, &rays, &TraceSettings { chunk: 2, min_transmittance: 1e-4, ..Default::default() }, None);
    // A zero normal is no plane, whatever its offset: both tracers ignore it.
    let unplaned: Vec<Ray> = plain.iter().map(|r| Ray { skip_below: [0.0, 0.0, 0.0, 5.0], ..*r }).collect();
    for (a, b) in unplaned.iter().zip(&plain) {
        assert_eq!(trace_ref(&s, a, &settings, None).hits, trace_ref(&s, b, &settings, None).hits);
    }
    compare_with_reference(&s, &unplaned, &settings, None);
}

#[test]
fn gradients_match_finite_differences_two_sided_and_grazing() {
    fd_check(3, true, false, 0);
    fd_check(4, false, true, 0);
}

/// Back faces hit within the grazing tolerance (one-sided): composited with their colour and
/// the normal flipped, and differentiated like any hit (surfel 3 is hit from behind).
#[test]
fn gradients_match_finite_differences_with_grazing_back_faces() {
    fd_check_with(8, false, false, 0, |s| s.grazing_sin = 0.34, None);
    fd_check_with(9, false, true, 2, |s| (s.grazing_sin, s.linear_radiance) = (0.34, true), None);
}

/// The grazing tolerance against brute force, on shells whose leaving rays the normal cones
/// cull most (the cones must widen by the tolerance) and with back occluders beside it; and it
/// does change what the rays hit.
#[test]
fn grazing_back_faces_match_brute_force() {
    let s = shell_scene(900, 61);
    let rays = leaving_rays(&s, 800, 62);
    let strict = TraceSettings::default();
    for (deg, chunk) in [(10.0f32, 32), (25.0, 3)] {
        let graze = TraceSettings { grazing_sin: deg.to_radians().sin(), chunk, ..Default::default() };
        let changed =
            rays.iter().filter(|r| trace_ref(&s, r, &graze, None).hits != trace_ref(&s, r, &strict, None).hits).count();
        assert!(changed * 50 > rays.len(), "{deg}°: the tolerance changed only {changed} of {} rays", rays.len());
        compare_with_reference(&s, &rays, &graze, None);
        let flags: Vec<bool> = (0..s.len()).map(|i| i % 3 == 0).collect();
        let occluders = TraceSettings { back_occluders: Some(flags.into()), linear_radiance: true, ..graze.clone() };
        compare_with_reference(&s, &rays, &occluders, None);
    }
    let random = random_scene(400, 63, 3);
    let graze = TraceSettings { grazing_sin: 0.2, ..Default::default() };
    compare_with_reference(&random, &random_rays(600, 64, &random), &graze, None);
}

#[test]
fn gradients_match_finite_differences_with_linear_radiance() {
    fd_check_with(7, false, false, 0, |s| s.linear_radiance = true, None);
    fd_check_with(8, true, true, 0, |s| s.linear_radiance = true, None);
}

/// Dark back faces (the scene's odd surfels face away): their own payload terms vanish, their
/// occlusion of the hits behind them keeps its gradient; SH, linear radiance and features.
#[test]
fn gradients_match_finite_differences_with_dark_back_faces() {
    fd_check_with(9, true, false, 0, |s| s.dark_back_faces = true, None);
    fd_check_with(10, true, true, 0, |s| (s.dark_back_faces, s.linear_radiance) = (true, true), None);
    fd_check_with(11, true, false, 3, |s| s.dark_back_faces = true, None);
}

/// Dark back faces against brute force, from inside and outside a shell (the rays meet its far
/// side from behind): the same hits and occlusion as two-sided tracing, less radiance.
#[test]
fn dark_back_faces_match_brute_force() {
    let s = shell_scene(900, 61);
    let rays = leaving_rays(&s, 800, 62);
    let two = TraceSettings { two_sided: true, linear_radiance: true, min_transmittance: 1e-4, ..Default::default() };
    let dark = TraceSettings { dark_back_faces: true, ..two.clone() };
    compare_with_reference(&s, &rays, &dark, None);
    compare_with_reference(&s, &rays, &TraceSettings { min_transmittance: 0.03, ..dark.clone() }, None);
    let mut rng = Pcg64::seed_from_u64(63);
    let feats: Vec<f32> = (0..s.len() * 2).map(|_| rng.random_range(0.0..1.0f32)).collect();
    compare_with_reference(&s, &rays, &TraceSettings { chunk: 4, ..dark.clone() }, Some((&feats, 2)));
    // Without two-sided tracing the switch does nothing.
    let culled = TraceSettings { two_sided: false, ..dark.clone() };
    compare_with_reference(&s, &rays, &culled, None);
    let (mut darker, mut unchanged) = (0, 0);
    for ray in &rays {
        let (a, b) = (trace_ref(&s, ray, &two, None), trace_ref(&s, ray, &dark, None));
        assert_eq!(a.hits, b.hits, "dark back faces must occlude as two-sided ones do");
        assert!((a.transmittance - b.transmittance).abs() < 1e-12 && (a.depth - b.depth).abs() < 1e-12);
        let (ra, rb) = (a.radiance.iter().sum::<f64>(), b.radiance.iter().sum::<f64>());
        assert!(rb <= ra + 1e-12);
        if rb < ra - 1e-6 {
            darker += 1;
        } else if !a.hits.is_empty() {
            unchanged += 1;
        }
    }
    assert!(darker * 10 > rays.len() && unchanged > 0, "darker {darker}, unchanged {unchanged} of {}", rays.len());
}

/// Back occluders in one-sided tracing: the scene's odd surfels face away; surfels 1 and 3 are
/// flagged (hit from behind, dark), surfel 5 is not (culled). SH, linear radiance, features.
#[test]
fn gradients_match_finite_differences_with_back_occluders() {
    fn flag_1_and_3(s: &mut TraceSettings) {
        s.two_sided = false;
        s.back_occluders = Some(std::sync::Arc::from([false, true, false, true, false, false].as_slice()));
    }
    fd_check_with(12, true, false, 0, flag_1_and_3, None);
    fd_check_with(13, true, true, 0, |s| (flag_1_and_3(s), s.linear_radiance = true).1, None);
    fd_check_with(14, true, false, 3, flag_1_and_3, None);
}

/// Back occluders against brute force on shells where a third of the surfels face inwards, from
/// inside and outside: flagged surfels block from behind without colour, the rest cull; with
/// every surfel flagged, one-sided tracing equals two-sided tracing with dark back faces.
#[test]
fn back_occluders_match_brute_force() {
    let mut s = shell_scene(900, 71);
    let mut rng = Pcg64::seed_from_u64(72);
    let flags: Vec<bool> = (0..s.len()).map(|_| rng.random_range(0.0..1.0f32) < 0.4).collect();
    for i in 0..s.len() {
        if rng.random_range(0.0..1.0f32) < 0.33 {
            let n = s.normal(i);
            s.quats[i] = quat_with_normal(n.map(|x| -x));
        }
    }
    let rays = leaving_rays(&s, 800, 73);
    let culled = TraceSettings { linear_radiance: true, min_transmittance: 1e-4, ..Default::default() };
    let some = TraceSettings { back_occluders: Some(flags.into()), ..culled.clone() };
    compare_with_reference(&s, &rays, &some, None);
    compare_with_reference(&s, &rays, &TraceSettings { min_transmittance: 0.03, chunk: 4, ..some.clone() }, None);
    let feats: Vec<f32> = (0..s.len() * 2).map(|_| rng.random_range(0.0..1.0f32)).collect();
    compare_with_reference(&s, &rays, &TraceSettings { chunk: 4, ..some.clone() }, Some((&feats, 2)));
    // Flagged surfels add hits (never colour) to the culled trace; two-sided tracing ignores flags.
    let mut more = 0;
    for ray in &rays {
        let (a, b) = (trace_ref(&s, ray, &culled, None), trace_ref(&s, ray, &some, None));
        more += (b.hits.len() > a.hits.len()) as usize;
        assert!(b.transmittance <= a.transmittance + 1e-12);
    }
    assert!(more * 10 > rays.len(), "back occluders added hits to only {more} of {} rays", rays.len());
    let two = TraceSettings { two_sided: true, dark_back_faces: true, ..culled.clone() };
    compare_with_reference(
        &s,
        &rays,
        &TraceSettings { back_occluders: some.back_occluders.clone(), ..two.clone() },
        None,
    );
    let all = TraceSettings { back_occluders: Some(vec![true; s.len()].into()), ..culled.clone() };
    compare_with_reference(&s, &rays, &all, None);
    let (tracer_all, tracer_two) = (Tracer::build(&s, &all), Tracer::build(&s, &two));
    let (mut out_all, mut out_two) = (vec![RayOutput::default(); rays.len()], vec![RayOutput::default(); rays.len()]);
    trace(&tracer_all, &s, &rays, None, &mut out_all, None);
    trace(&tracer_two, &s, &rays, None, &mut out_two, None);
    for (a, b) in out_all.iter().zip(&out_two) {
        assert_eq!(a.transmittance, b.transmittance);
        assert_eq!(a.radiance, b.radiance);
        assert_eq!(a.normal, b.normal);
    }
}

#[test]
fn linear_radiance_matches_brute_force() {
    for seed in [21u64, 22] {
        let s = random_scene(300, seed, 2);
        let rays = random_rays(400, seed + 1, &s);
        let settings = TraceSettings { linear_radiance: true, chunk: 4, ..Default::default() };
        compare_with_reference(&s, &rays, &settings, None);
    }
}

#[test]
fn feature_gradients_match_finite_differences() {
    fd_check(5, false, false, 3);
}

#[test]
fn gradients_with_ray_origin_on_a_surfel() {
    // The ray starts on surfel 0 (skipped by t_min); perturbing the origin must not make it
    // appear, so the gradients stay those of the other surfels.
    let (mut s, mut rays, settings) = fd_scene(6, false, false, 0.0);
    rays.truncate(1);
    let o = rays[0].origin;
    s.means[0] = [o[0] + 0.01, o[1] - 0.01, o[2]];
    s.quats[0] = quat_with_normal([0.0, 0.0, -1.0]);
    let tracer = Tracer::build(&s, &settings);
    let l = RayGrad { v_radiance: [0.3, -0.5, 0.7], v_transmittance: 0.4, v_depth: -0.2, v_normal: [0.1, 0.2, -0.3] };
    let mut v = s.zeros_like();
    let mut vr = vec![Ray::default()];
    trace_backward(&tracer, &s, &rays, None, &[l], None, &mut v, None, Some(&mut vr));
    assert_eq!(v.opacity_logits[0], 0.0, "the origin's own surfel must not be hit");
    let loss = Loss { g: vec![l], gf: vec![] };
    let h = 1e-3;
    // In-plane moves keep the origin on the surfel (t = 0); a move along the normal would put
    // it genuinely in front of or behind the surfel, beyond the self-intersection offset.
    for a in 0..2 {
        let (mut ra, mut rb) = (rays.clone(), rays.clone());
        ra[0].origin[a] += h;
        rb[0].origin[a] -= h;
        let fd = (eval_loss(&s, &ra, &settings, None, &loss) - eval_loss(&s, &rb, &settings, None, &loss))
            / (2.0 * h as f64);
        check(&format!("origin[{a}]"), vr[0].origin[a], fd);
    }
}

#[test]
fn traced_camera_rays_match_the_rasteriser_with_a_large_window() {
    use crate::camera::Camera;
    use crate::raster::{RasterSettings, render};
    use glam::Vec3;
    // Surfels of several pixels, roughly facing the camera (the 2DGS screen-space fallback only
    // matters for sub-pixel or edge-on splats), view-independent colour (the rasteriser shades
    // at the direction to the centre, the tracer at the ray direction).
    let camera = Camera::look_at("t", Vec3::new(0.3, -3.0, 0.4), Vec3::ZERO, 48, 40, 0.8);
    let eye = camera.position();
    let mut rng = Pcg64::seed_from_u64(31);
    let mut s = Surfels::default();
    for _ in 0..60 {
        let mean: [f32; 3] = std::array::from_fn(|_| rng.random_range(-0.8..0.8f32));
        let to_eye = (eye - Vec3::from(mean)).normalize();
        let tilt = Vec3::new(rng.random_range(-0.4..0.4), rng.random_range(-0.4..0.4), rng.random_range(-0.4..0.4));
        let q = quat_with_normal((to_eye + tilt).normalize().to_array());
        let sc = [rng.random_range(0.08..0.3f32), rng.random_range(0.08..0.3f32)];
        s.push(mean, sc, q, rng.random_range(0.3..0.9), [rng.random(), rng.random(), rng.random()], [0.3; 3], 0.5);
    }
    s.sh_degree = 0;
    for two_sided in [false, true] {
        let rs = RasterSettings { window: 32, two_sided, transmittance_min: 1e-4, ..Default::default() };
        let (img, _) = render(&s, &camera, &rs, None);
        let ts = TraceSettings { min_transmittance: 1e-4, two_sided, ..Default::default() };
        let (colour, alpha) = render_camera_traced(&s, &camera, &ts);
        let mut worst = 0.0f32;
        let mut covered = 0;
        for k in 0..colour.len() {
            covered += (alpha[k] > 0.1) as usize;
            worst = worst.max((alpha[k] - img.alpha[k]).abs());
            for c in 0..3 {
                worst = worst.max((colour[k][c] - img.colour[k][c]).abs());
            }
        }
        assert!(covered * 3 > colour.len(), "too little of the image is covered: {covered}");
        assert!(worst < 2e-3, "two_sided {two_sided}: traced vs rasterised differ by {worst}");
    }
}

#[test]
fn backward_is_deterministic_across_thread_counts() {
    // Many blocks of rays through a dense scene: the summed gradients must be bitwise equal
    // whatever the thread count (the reduction order may not depend on scheduling).
    let s = random_scene(400, 21, 3);
    let settings = TraceSettings::default();
    let tracer = Tracer::build(&s, &settings);
    let rays = random_rays(3000, 22, &s);
    let g: Vec<RayGrad> = (0..rays.len())
        .map(|k| {
            let x = (k % 7) as f32 * 0.1 - 0.3;
            RayGrad { v_radiance: [1.0, x, 0.5], v_transmittance: x, v_depth: 0.2, v_normal: [x, 0.3, -0.1] }
        })
        .collect();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            let mut v = s.zeros_like();
            let mut vr = vec![Ray::default(); rays.len()];
            trace_backward(&tracer, &s, &rays, None, &g, None, &mut v, None, Some(&mut vr));
            (v, vr)
        })
    };
    let (v1, r1) = run(1);
    assert!(v1.means.iter().any(|m| m[0] != 0.0), "no gradients reached the surfels");
    for threads in [2, 3, 4] {
        let (v, r) = run(threads);
        assert!(v == v1, "surfel gradients differ with {threads} threads");
        assert!(r == r1, "ray gradients differ with {threads} threads");
    }
}

#[test]
fn coherent_order_keeps_each_origins_rays_together_in_the_callers_order() {
    // 40 origins × 8 directions, the origins' batches interleaved in pairs and then some rays
    // with origins of their own: each origin's rays must come out as one contiguous run in
    // the caller's order, runs ordered by the Morton code of their origin.
    let mut rng = Pcg64::seed_from_u64(63);
    let origins: Vec<[f32; 3]> = (0..40).map(|_| std::array::from_fn(|_| rng.random_range(-1.0..1.0f32))).collect();
    let mut rays = Vec::new();
    for (o, &origin) in origins.iter().enumerate() {
        for j in 0..8 {
            rays.push(Ray { origin, dir: [j as f32, 1.0, o as f32], ..Default::default() });
        }
    }
    for _ in 0..30 {
        rays.push(Ray {
            origin: std::array::from_fn(|_| rng.random_range(-1.0..1.0f32)),
            dir: [0.0, 0.0, 1.0],
            ..Default::default()
        });
    }
    let order = super::forward::coherent_order(&rays);
    let mut seen = order.clone();
    seen.sort_unstable();
    assert!(seen.iter().enumerate().all(|(j, &k)| j == k as usize), "not a permutation");
    // Runs of equal origin in the output, each increasing in the caller's index.
    let origin_of = |j: usize| rays[order[j] as usize].origin;
    let mut runs = 0;
    let mut j = 0;
    while j < order.len() {
        let mut e = j + 1;
        while e < order.len() && origin_of(e) == origin_of(j) {
            assert!(order[e] == order[e - 1] + 1, "a run is not in the caller's order");
            e += 1;
        }
        let count = rays.iter().filter(|r| r.origin == origin_of(j)).count();
        assert_eq!(e - j, count, "an origin's rays are split into several runs");
        runs += 1;
        j = e;
    }
    assert_eq!(runs, 70);
    assert!(order.windows(2).any(|w| w[1] < w[0]), "the runs were not reordered");
    assert_eq!(order, super::forward::coherent_order(&rays), "not deterministic");
}

#[test]
fn coherent_order_leaves_results_in_the_callers_places() {
    // Batches of ≥ 64 rays are traced in a sorted order; each ray's outputs, feature channels
    // and ray gradients must land at its own index: compare with tracing each ray alone.
    let s = random_scene(300, 61, 2);
    let tracer = Tracer::build(&s, &TraceSettings::default());
    let rays = random_rays(500, 62, &s);
    let order = super::forward::coherent_order(&rays);
    assert!(order.iter().enumerate().any(|(j, &k)| j != k as usize), "the order is the identity");
    let mut sorted = order.clone();
    sorted.sort_unstable();
    assert!(sorted.iter().enumerate().all(|(j, &k)| j == k as usize), "not a permutation");

    let ch = 2;
    let feats: Vec<f32> = (0..s.len() * ch).map(|i| (i % 11) as f32 * 0.1).collect();
    let f = || Some(Features { data: &feats, channels: ch });
    let mut out = vec![RayOutput::default(); rays.len()];
    let mut of = vec![0.0f32; rays.len() * ch];
    trace(&tracer, &s, &rays, f(), &mut out, Some(&mut of));
    let g: Vec<RayGrad> = (0..rays.len())
        .map(|k| RayGrad { v_transmittance: 1.0 + k as f32 * 0.01, v_depth: 0.1, ..Default::default() })
        .collect();
    let mut v = s.zeros_like();
    let mut vr = vec![Ray::default(); rays.len()];
    trace_backward(&tracer, &s, &rays, None, &g, None, &mut v, None, Some(&mut vr));
    for k in 0..rays.len() {
        let mut o1 = [RayOutput::default()];
        let mut of1 = vec![0.0f32; ch];
        trace(&tracer, &s, &rays[k..k + 1], f(), &mut o1, Some(&mut of1));
        assert_eq!(out[k], o1[0], "ray {k}");
        assert_eq!(&of[k * ch..(k + 1) * ch], &of1[..], "ray {k} features");
        let mut v1 = s.zeros_like();
        let mut vr1 = [Ray::default()];
        trace_backward(&tracer, &s, &rays[k..k + 1], None, &g[k..k + 1], None, &mut v1, None, Some(&mut vr1));
        assert_eq!(vr[k], vr1[0], "ray {k} gradient");
    }
    assert!(out.iter().filter(|o| o.transmittance < 1.0).count() > 100);
}

/// The recorded forward gives `trace`'s outputs, and the backward replaying its hits gives
/// bitwise the gradients of the backward that casts the rays again (more than 64 rays, so the
/// coherent order is in play; a tiny chunk and early termination on).
#[test]
fn recorded_hits_replay_the_backward_exactly() {
    let s = random_scene(300, 17, 3);
    for settings in [TraceSettings::default(), TraceSettings { chunk: 2, min_transmittance: 0.2, ..Default::default() }]
    {
        let tracer = Tracer::build(&s, &settings);
        let rays = random_rays(150, 23, &s);
        let mut plain = vec![RayOutput::default(); rays.len()];
        trace(&tracer, &s, &rays, None, &mut plain, None);
        let mut record = crate::trace::HitRecord::default();
        let mut recorded = vec![RayOutput::default(); rays.len()];
        crate::trace::trace_recorded(&tracer, &s, &rays, &mut recorded, &mut record);
        assert_eq!(plain, recorded);
        assert!(record.hits.len() > rays.len(), "the test needs hits: {}", record.hits.len());
        let g: Vec<RayGrad> = (0..rays.len())
            .map(|k| {
                let x = (k % 7) as f32 * 0.1 - 0.3;
                RayGrad { v_radiance: [x, 0.5, -x], v_transmittance: 0.7 - x, v_depth: x, v_normal: [0.2, x, 0.1] }
            })
            .collect();
        let (mut va, mut vb) = (s.zeros_like(), s.zeros_like());
        let (mut ra, mut rb) = (vec![Ray::default(); rays.len()], vec![Ray::default(); rays.len()]);
        trace_backward(&tracer, &s, &rays, None, &g, None, &mut va, None, Some(&mut ra));
        crate::trace::trace_backward_recorded(&tracer, &s, &rays, &g, &mut vb, Some(&mut rb), &record);
        assert!(va == vb && ra == rb, "chunk {}: replayed gradients differ", settings.chunk);
        assert!(va != s.zeros_like());
    }
}

/// The gradient lists of the blocks are merged by surfel ranges in parallel: the sums must be
/// bitwise those of one range walked by one task (each surfel's sum in block order), on a scene
/// of several ranges and more rays than one wave of blocks.
#[test]
fn merging_by_surfel_ranges_changes_no_bit() {
    let s = random_scene(2500, 31, 2);
    let tracer = Tracer::build(&s, &TraceSettings::default());
    let rays = random_rays(20_000, 32, &s);
    let g: Vec<RayGrad> = (0..rays.len())
        .map(|k| {
            let x = (k % 5) as f32 * 0.1 - 0.2;
            RayGrad { v_radiance: [0.5, x, 1.0], v_transmittance: x, v_depth: 0.1, v_normal: [x, 0.2, 0.3] }
        })
        .collect();
    let run = |range: usize| {
        let mut v = s.zeros_like();
        crate::trace::backward::backward(&tracer, &s, &rays, None, &g, None, &mut v, None, None, None, range);
        v
    };
    let one_range = run(usize::MAX);
    let last = s.len() - 1;
    assert!(one_range.means[last] != [0.0; 3] && one_range.means[0] != [0.0; 3], "the test needs gradients");
    for range in [1, 7, 1000, 2048] {
        assert!(run(range) == one_range, "merge range {range} changed the sums");
    }
}

/// The visibility ramp keeps V + g·(1 − T) = 1, is the identity when off, and its derivatives
/// match central differences away from the kink at t₀.
#[test]
fn visibility_ramp_conserves_the_coverage_and_its_derivatives_match() {
    assert_eq!(visibility_ramp(0.37, 0.0), (0.37, 1.0, 1.0, 0.0));
    for &t0 in &[0.05f32, 0.1, 0.3] {
        assert_eq!(visibility_ramp(0.0, t0).0, 0.0);
        assert!((visibility_ramp(1.0, t0).0 - 1.0).abs() < 1e-6);
        for k in 0..=40 {
            let t = k as f32 / 41.0 + 0.01;
            let (v, g, dv, dg) = visibility_ramp(t, t0);
            assert!((v + g * (1.0 - t) - 1.0).abs() < 1e-5, "t0 {t0} T {t}: V {v} g {g}");
            if (t - t0).abs() < 2e-3 {
                continue;
            }
            let h = 1e-3f64;
            let at = |x: f64| {
                let (v, g, _, _) = visibility_ramp(x as f32, t0);
                (v as f64, g as f64)
            };
            let ((va, ga), (vb, gb)) = (at(t as f64 + h), at(t as f64 - h));
            assert!(((va - vb) / (2.0 * h) - dv as f64).abs() < 1e-2, "t0 {t0} T {t}: dV");
            assert!(((ga - gb) / (2.0 * h) - dg as f64).abs() < 1e-2 * (1.0 + dg.abs() as f64), "t0 {t0} T {t}: dg");
        }
    }
}
