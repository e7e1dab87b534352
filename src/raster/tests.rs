//! Tests of the fast rasteriser against the f64 reference (forward) and against finite
//! differences of the reference (backward).

use super::reference::{Order, RefOut, RefScene, render_ref};
use super::*;
use crate::camera::Camera;
use crate::surfels::{Surfels, logit, quat_with_normal};
use glam::Vec3;
use rand::{RngExt, SeedableRng};

fn camera(w: u32, h: u32) -> Camera {
    Camera::look_at("t", Vec3::new(0.3, -3.0, 0.4), Vec3::ZERO, w, h, 0.8)
}

/// Random surfels in a box in front of `camera(..)`.
fn random_scene(n: usize, seed: u64, scale: (f32, f32), opacity: (f32, f32)) -> Surfels {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut s = Surfels { sh_degree: 3, ..Default::default() };
    for _ in 0..n {
        let mean = [rng.random_range(-0.8..0.8), rng.random_range(-0.6..0.6), rng.random_range(-0.5..0.5f32)];
        let sc = [rng.random_range(scale.0..scale.1), rng.random_range(scale.0..scale.1)];
        let q: [f32; 4] = std::array::from_fn(|_| rng.random_range(-1.0..1.0f32));
        let o = rng.random_range(opacity.0..opacity.1);
        s.push(mean, sc, q, o, [rng.random(), rng.random(), rng.random()], [0.5; 3], 0.5);
        let last = s.sh.len() - 1;
        for k in 1..16 {
            for ch in 0..3 {
                s.sh[last][k][ch] = rng.random_range(-0.2..0.2);
            }
        }
    }
    s
}

fn random_features(n: usize, ch: usize, seed: u64) -> Vec<f32> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    (0..n * ch).map(|_| rng.random_range(-1.0..1.0)).collect()
}

fn max_diff(fast: &RenderOutput, r: &RefOut) -> f64 {
    let mut m = 0.0f64;
    let mut upd = |a: f32, b: f64| m = m.max((a as f64 - b).abs() / (1.0 + b.abs()));
    for i in 0..fast.alpha.len() {
        upd(fast.alpha[i], r.alpha[i]);
        if !fast.colour.is_empty() {
            for c in 0..3 {
                upd(fast.colour[i][c], r.colour[i][c]);
                upd(fast.normal[i][c], r.normal[i][c]);
            }
            upd(fast.depth[i], r.depth[i]);
            upd(fast.median_depth[i], r.median[i]);
            upd(fast.distortion[i] * 100.0, r.distortion[i] * 100.0);
        }
    }
    for i in 0..fast.features.len() {
        upd(fast.features[i], r.features[i]);
    }
    m
}

fn compare(s: &Surfels, cam: &Camera, set: &RasterSettings, feats: Option<(&[f32], usize)>, order: Order) -> f64 {
    let f = feats.map(|(d, c)| Features { data: d, channels: c });
    let (out, _) = render(s, cam, set, f);
    let r = render_ref(&RefScene::from_surfels(s, feats), cam, set, order);
    for v in out.colour.iter().flatten().chain(&out.alpha).chain(&out.depth).chain(&out.distortion) {
        assert!(v.is_finite());
    }
    max_diff(&out, &r)
}

#[test]
fn window_at_least_overlap_matches_full_sort_reference() {
    let cam = camera(40, 30);
    for (seed, two_sided) in [(1u64, false), (2, true), (3, true)] {
        let s = random_scene(24, seed, (0.05, 0.3), (0.05, 0.95));
        let f = random_features(24, 3, seed);
        let set = RasterSettings { window: 32, two_sided, background: [0.2, 0.5, 0.9], ..Default::default() };
        let r = render_ref(&RefScene::from_surfels(&s, Some((&f, 3))), &cam, &set, Order::Full);
        assert!(r.max_hits >= 4 && r.max_hits <= 32, "overlap {}", r.max_hits);
        let d = compare(&s, &cam, &set, Some((&f, 3)), Order::Full);
        assert!(d < 2e-4, "seed {seed}: max diff {d}");
    }
}

/// The distortion of hits whose depths nearly agree (a surface's stack of surfels): the forward
/// sums it in closed form A·M2 − M1², which cancels unless the m are taken relative to the
/// first hit's; the relative error against the reference's double sum stays small.
#[test]
fn distortion_of_nearly_coincident_hits_keeps_its_relative_precision() {
    let cam = Camera::look_at("t", Vec3::new(0.0, -5.0, 0.0), Vec3::ZERO, 9, 9, 0.4);
    let mut s = Surfels { sh_degree: 0, ..Default::default() };
    let q = quat_with_normal([0.0, -1.0, 0.0]);
    for i in 0..12 {
        // 0.5 mm apart at depth 5: m differs by ≈ 2·10⁻⁶ between neighbours (near 0.2, far 100).
        s.push([0.0, 5e-4 * i as f32 - 3e-3, 0.0], [1.0, 1.0], q, 0.3, [0.5; 3], [0.5; 3], 0.5);
    }
    for k in [1usize, 8] {
        let set = RasterSettings { window: k, two_sided: true, ..Default::default() };
        let (out, _) = render(&s, &cam, &set, None);
        let r = render_ref(&RefScene::from_surfels(&s, None), &cam, &set, Order::Full);
        let centre = 4 * 9 + 4;
        let (got, want) = (out.distortion[centre] as f64, r.distortion[centre]);
        assert!(want > 0.0 && want < 1e-9, "K = {k}: reference distortion {want}");
        assert!((got - want).abs() < 1e-2 * want, "K = {k}: distortion {got} against {want}");
    }
}

#[test]
fn k1_is_plain_centre_order_and_windows_match_the_window_reference() {
    let cam = camera(40, 30);
    let s = random_scene(30, 11, (0.05, 0.35), (0.1, 0.95));
    for k in [1usize, 2, 3, 8] {
        let set = RasterSettings { window: k, two_sided: true, ..Default::default() };
        let d = compare(&s, &cam, &set, None, Order::Window(k));
        assert!(d < 2e-4, "K = {k}: max diff {d}");
    }
    let set = RasterSettings { window: 1, two_sided: true, ..Default::default() };
    let d = compare(&s, &cam, &set, None, Order::Centre);
    assert!(d < 2e-4, "K = 1 vs centre order: {d}");
}

#[test]
fn error_against_full_sort_shrinks_as_window_grows() {
    let cam = camera(40, 30);
    let s = random_scene(40, 5, (0.1, 0.4), (0.3, 0.9));
    let set0 = RasterSettings { two_sided: true, ..Default::default() };
    let full = render_ref(&RefScene::from_surfels(&s, None), &cam, &set0, Order::Full);
    let mut errs = vec![];
    for k in [1usize, 2, 4, 8, 16, 32] {
        let set = RasterSettings { window: k, ..set0.clone() };
        let (out, _) = render(&s, &cam, &set, None);
        let e: f64 = (0..out.alpha.len())
            .map(|i| (0..3).map(|c| (out.colour[i][c] as f64 - full.colour[i][c]).abs()).sum::<f64>())
            .sum::<f64>()
            / out.alpha.len() as f64;
        errs.push((k, e));
    }
    assert!(full.max_hits <= 32);
    assert!(errs[0].1 > 1e-3, "K = 1 should differ from the full sort: {errs:?}");
    assert!(errs[3].1 < errs[0].1 * 0.5, "{errs:?}");
    assert!(errs[5].1 < 1e-5, "{errs:?}");
    for w in errs.windows(2) {
        assert!(w[1].1 <= w[0].1 * 1.05 + 1e-6, "{errs:?}");
    }
}

#[test]
fn edge_cases_n0_n1_one_pixel_edge_on_camera_inside() {
    let set = RasterSettings::default();
    // N = 0.
    let cam = camera(17, 9);
    let (out, st) = render(&Surfels::default(), &cam, &set, None);
    assert_eq!(out.alpha.len(), 17 * 9);
    assert!(out.alpha.iter().all(|&a| a == 0.0));
    let mut g = Surfels::default();
    let grads = RenderGrads { v_colour: vec![[1.0; 3]; 17 * 9], ..Default::default() };
    let b = render_backward(&Surfels::default(), &cam, &set, None, &st, &grads, &mut g, None);
    assert!(b.v_mean2d.is_empty() && b.v_mean2d_abs.is_empty());
    // N = 1, facing the camera, at the centre of a 1 × 1 image.
    let mut s = Surfels { sh_degree: 0, ..Default::default() };
    let n = (cam.position() - Vec3::ZERO).normalize();
    s.push([0.0; 3], [0.3, 0.2], quat_with_normal(n.to_array()), 0.8, [0.9, 0.2, 0.1], [0.5; 3], 0.5);
    let cam1 = camera(1, 1);
    let (out, _) = render(&s, &cam1, &set, None);
    assert!((out.alpha[0] - 0.8).abs() < 1e-3, "alpha {}", out.alpha[0]);
    assert!((out.colour[0][0] - 0.72).abs() < 1e-3);
    let d = compare(&s, &cam1, &set, None, Order::Full);
    assert!(d < 1e-5);
    // Culled when seen from behind, drawn (normal flipped) when two-sided.
    let mut back = s.clone();
    back.quats[0] = quat_with_normal((-n).to_array());
    assert_eq!(render(&back, &cam1, &set, None).0.alpha[0], 0.0);
    let two = RasterSettings { two_sided: true, ..set.clone() };
    let (o2, _) = render(&back, &cam1, &two, None);
    assert!(o2.alpha[0] > 0.7);
    assert!(Vec3::from(o2.normal[0]).dot(n) > 0.0);

    // Exactly edge-on: the surfel plane z = 0 contains the camera centre (all values exact).
    let cam_e = Camera {
        name: "e".into(),
        width: 9,
        height: 9,
        fx: 10.0,
        fy: 10.0,
        cx: 4.5,
        cy: 4.5,
        // Camera x = world y, camera y (down) = world −z, forward = world x.
        rotation: glam::Mat3::from_cols(Vec3::new(0.0, 0.0, 1.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, -1.0, 0.0)),
        translation: Vec3::ZERO,
    };
    let mut e = Surfels { sh_degree: 0, ..Default::default() };
    e.push([2.0, 0.0, 0.0], [0.5, 0.5], [1.0, 0.0, 0.0, 0.0], 0.9, [0.5; 3], [0.5; 3], 0.5);
    assert_eq!(cam_e.world_to_camera(Vec3::new(2.0, 0.0, 0.0)), Vec3::new(0.0, 0.0, 2.0));
    for ts in [false, true] {
        let set_e = RasterSettings { two_sided: ts, ..Default::default() };
        let (oe, _) = render(&e, &cam_e, &set_e, None);
        assert!(oe.alpha.iter().all(|a| a.is_finite()));
        // Rays of the middle row lie in the plane (skipped, as 2DGS); the others meet it at the
        // camera centre (z = 0 < near), so only the screen-space filter draws a small blob.
        assert_eq!(oe.alpha[4 * 9 + 4], 0.0);
        let want = 0.9 * (-1.0f32).exp(); // ρ₂ = 2·1² one row off the centre.
        assert!((oe.alpha[3 * 9 + 4] - want).abs() < 1e-5, "{}", oe.alpha[3 * 9 + 4]);
        assert!((oe.alpha[5 * 9 + 4] - want).abs() < 1e-5);
        assert!(oe.alpha[0] == 0.0 && oe.alpha[3 * 9 + 8] == 0.0);
        assert!(compare(&e, &cam_e, &set_e, None, Order::Full) < 1e-5);
    }

    // Camera inside the scene: surfels all around it, some behind, some across the near plane.
    let mut inside = random_scene(40, 9, (0.2, 0.6), (0.3, 0.9));
    for m in inside.means.iter_mut() {
        *m = [m[0] * 4.0, m[1] * 6.0 - 3.0, m[2] * 3.0];
    }
    let set_i = RasterSettings { two_sided: true, ..Default::default() };
    let d = compare(&inside, &camera(24, 20), &set_i, None, Order::Window(8));
    assert!(d < 2e-4, "inside: {d}");
}

// ---------------------------------------------------------------------------------------------
// Finite-difference gradient checks: analytic f32 backward of the fast path against central
// differences of the f64 reference with the same window order (tiny steps, so the hard
// cut-offs are almost never crossed; most cases also use the smooth variant α_min → 1e-6,
// no T cut-off).

struct Weights {
    colour: Vec<[f32; 3]>,
    alpha: Vec<f32>,
    depth: Vec<f32>,
    median: Vec<f32>,
    normal: Vec<[f32; 3]>,
    distortion: Vec<f32>,
    features: Vec<f32>,
}

fn weights(px: usize, ch: usize, seed: u64) -> Weights {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut r = |s: f32| rng.random_range(-s..s);
    Weights {
        colour: (0..px).map(|_| [r(1.0), r(1.0), r(1.0)]).collect(),
        alpha: (0..px).map(|_| r(1.0)).collect(),
        depth: (0..px).map(|_| r(0.3)).collect(),
        median: (0..px).map(|_| r(0.3)).collect(),
        normal: (0..px).map(|_| [r(1.0), r(1.0), r(1.0)]).collect(),
        distortion: (0..px).map(|_| r(30.0)).collect(),
        features: (0..px * ch).map(|_| r(1.0)).collect(),
    }
}

fn ref_loss(r: &RefOut, w: &Weights) -> f64 {
    let mut l = 0.0;
    for i in 0..r.alpha.len() {
        for c in 0..3 {
            l += w.colour[i][c] as f64 * r.colour[i][c] + w.normal[i][c] as f64 * r.normal[i][c];
        }
        l += w.alpha[i] as f64 * r.alpha[i] + w.depth[i] as f64 * r.depth[i] + w.median[i] as f64 * r.median[i];
        l += w.distortion[i] as f64 * r.distortion[i];
    }
    for i in 0..r.features.len() {
        l += w.features[i] as f64 * r.features[i];
    }
    l
}

fn check_gradients(s: &Surfels, cam: &Camera, set: &RasterSettings, ch: usize, seed: u64) {
    check_gradients_with(s, cam, set, ch, seed, false);
}

/// `skip_kinks`: a parameter whose central difference changes with the step (h vs h/4) sits
/// on a discontinuity of the loss (two hits swapping blend order, a hit switching between the
/// ray–plane and filter branches): it is skipped, and at most 1 % may be. For dense scenes,
/// where some of the many hit pairs cross within the step.
fn check_gradients_with(s: &Surfels, cam: &Camera, set: &RasterSettings, ch: usize, seed: u64, skip_kinks: bool) {
    let n = s.len();
    let feats = random_features(n, ch, seed + 100);
    let px = (cam.width * cam.height) as usize;
    let w = weights(px, ch, seed + 200);
    let f = if ch > 0 { Some(Features { data: &feats, channels: ch }) } else { None };
    let (out, st) = render(s, cam, set, f);
    let grads = RenderGrads {
        v_colour: w.colour.clone(),
        v_alpha: w.alpha.clone(),
        v_depth: w.depth.clone(),
        v_median_depth: w.median.clone(),
        v_normal: w.normal.clone(),
        v_distortion: w.distortion.clone(),
        v_features: w.features.clone(),
    };
    let mut g = s.zeros_like();
    let mut gf = vec![0.0f32; n * ch];
    render_backward(s, cam, set, f, &st, &grads, &mut g, if ch > 0 { Some(&mut gf) } else { None });

    let base = RefScene::from_surfels(s, if ch > 0 { Some((&feats, ch)) } else { None });
    let order = Order::Window(set.k());
    let r0 = render_ref(&base, cam, set, order);
    let d = max_diff(&out, &r0);
    assert!(d < 5e-4, "forward differs from the reference by {d}");
    let central = |edit: &dyn Fn(&mut RefScene, f64), h: f64| {
        let mut p = base.clone();
        edit(&mut p, h);
        let lp = ref_loss(&render_ref(&p, cam, set, order), &w);
        let mut m = base.clone();
        edit(&mut m, -h);
        let lm = ref_loss(&render_ref(&m, cam, set, order), &w);
        (lp - lm) / (2.0 * h)
    };
    let kinks = std::cell::Cell::new(0usize);
    let fd = |edit: &dyn Fn(&mut RefScene, f64)| {
        let d = central(edit, 1e-5);
        if skip_kinks && (d - central(edit, 2.5e-6)).abs() > 1e-3 * (1.0 + d.abs()) {
            kinks.set(kinks.get() + 1);
            return f64::NAN;
        }
        d
    };
    let mut fails = vec![];
    let mut checked = 0;
    let mut nonzero = 0;
    let mut check = |name: String, a: f32, fdv: f64| {
        if fdv.is_nan() {
            return;
        }
        checked += 1;
        if fdv.abs() > 1e-3 {
            nonzero += 1;
        }
        if (a as f64 - fdv).abs() > 2e-3 * (1.0 + fdv.abs()) {
            fails.push(format!("{name}: analytic {a} vs fd {fdv}"));
        }
    };
    for i in 0..n {
        for k in 0..3 {
            check(format!("means[{i}][{k}]"), g.means[i][k], fd(&|p, e| p.means[i][k] += e));
        }
        for k in 0..2 {
            check(format!("log_scales[{i}][{k}]"), g.log_scales[i][k], fd(&|p, e| p.log_scales[i][k] += e));
        }
        for k in 0..4 {
            check(format!("quats[{i}][{k}]"), g.quats[i][k], fd(&|p, e| p.quats[i][k] += e));
        }
        check(format!("opacity[{i}]"), g.opacity_logits[i], fd(&|p, e| p.opacity_logits[i] += e));
        for k in [0usize, 2, 5, 13] {
            let c = (i + k) % 3;
            check(format!("sh[{i}][{k}][{c}]"), g.sh[i][k][c], fd(&|p, e| p.sh[i][k][c] += e));
        }
        for c in 0..ch {
            check(format!("feature[{i}][{c}]"), gf[i * ch + c], fd(&|p, e| p.features[i * ch + c] += e));
        }
    }
    assert!(fails.is_empty(), "{} of {checked} gradients wrong:\n{}", fails.len(), fails.join("\n"));
    assert!(kinks.get() * 100 <= checked, "{} of {checked} parameters on a discontinuity", kinks.get());
    assert!(nonzero * 3 > checked, "too few non-zero gradients ({nonzero} of {checked}): the scene is degenerate");
}

/// A sharper screen-space filter (`filter_inv_square` 8 instead of 2DGS's 2) on sub-pixel
/// surfels, where the fallback decides most hits: the fast path matches the brute-force
/// reference (which applies the filter independently), the setting changes the picture, and
/// the gradients match finite differences.
#[test]
fn sharper_screen_filter_matches_reference_and_gradients() {
    let cam = camera(40, 30);
    let s = random_scene(60, 5, (0.002, 0.02), (0.3, 0.95));
    let f = random_features(60, 3, 5);
    let sharp = RasterSettings { window: 32, two_sided: true, filter_inv_square: 8.0, ..Default::default() };
    let d = compare(&s, &cam, &sharp, Some((&f, 3)), Order::Full);
    assert!(d < 2e-4, "max diff {d}");
    let wide = RasterSettings { filter_inv_square: 2.0, ..sharp.clone() };
    let (a, _) = render(&s, &cam, &sharp, None);
    let (b, _) = render(&s, &cam, &wide, None);
    let alpha_sum = |o: &RenderOutput| o.alpha.iter().map(|&v| v as f64).sum::<f64>();
    // Coverage of a fallback blob scales as 1/f: 4× less at f = 8.
    assert!(alpha_sum(&a) < 0.5 * alpha_sum(&b), "{} vs {}", alpha_sum(&a), alpha_sum(&b));
    let small = random_scene(8, 31, (0.004, 0.03), (0.3, 0.9));
    check_gradients(&small, &camera(24, 18), &RasterSettings { filter_inv_square: 8.0, ..smooth(32, true) }, 2, 3);
}

fn smooth(window: usize, two_sided: bool) -> RasterSettings {
    RasterSettings {
        window,
        two_sided,
        background: [0.3, 0.6, 0.1],
        alpha_min: 1e-6,
        transmittance_min: 0.0,
        ..Default::default()
    }
}

#[test]
fn gradients_random_scene_full_order() {
    let s = random_scene(8, 21, (0.1, 0.35), (0.2, 0.9));
    check_gradients(&s, &camera(24, 18), &smooth(32, false), 2, 1);
}

#[test]
fn gradients_two_sided_window_reorders() {
    let s = random_scene(10, 22, (0.15, 0.4), (0.2, 0.9));
    let cam = camera(24, 18);
    // The window of 2 must actually reorder something in this scene.
    let set = smooth(2, true);
    let sc = RefScene::from_surfels(&s, None);
    let a = render_ref(&sc, &cam, &set, Order::Window(2));
    let b = render_ref(&sc, &cam, &set, Order::Full);
    let c = render_ref(&sc, &cam, &set, Order::Centre);
    let diff = |x: &RefOut, y: &RefOut| (0..x.alpha.len()).any(|i| (x.colour[i][0] - y.colour[i][0]).abs() > 1e-6);
    assert!(diff(&a, &b) && diff(&a, &c), "window 2 equals another order: scene does not exercise reordering");
    check_gradients(&s, &cam, &set, 1, 2);
}

/// Pixels with more than 16 blended hits (the backward works in groups of 16 and carries the
/// suffix sum from group to group) and 15 feature channels (the gradient row's tail spans two
/// transposed groups).
#[test]
fn gradients_dense_pixels_many_groups_and_channels() {
    use super::forward::{TileData, composite_pixel};
    let s = random_scene(40, 26, (0.35, 0.7), (0.1, 0.5));
    let cam = camera(16, 12);
    let set = smooth(8, true);
    let proj = super::project::project(&s, &cam, &set);
    let bins = super::tiles::bin(&proj, cam.width, cam.height, set.alpha_min, set.filter_inv_square);
    let mut td = TileData::default();
    let mut most = 0;
    for t in 0..(bins.tiles_x * bins.tiles_y) as usize {
        let (tx, ty) = (t as u32 % bins.tiles_x, t as u32 / bins.tiles_x);
        let range = bins.offsets[t] as usize..bins.offsets[t + 1] as usize;
        td.load(&proj, &bins.ids[range.clone()], &bins.quarter_masks[range], (tx * TILE, ty * TILE));
        for y in ty * TILE..((ty + 1) * TILE).min(cam.height) {
            for x in tx * TILE..((tx + 1) * TILE).min(cam.width) {
                let mut n = 0;
                composite_pixel(&td, x as f32 + 0.5, y as f32 + 0.5, &set, set.k(), |_, _, _, _| n += 1);
                most = most.max(n);
            }
        }
    }
    assert!(most > 32, "the scene must blend more than two groups of 16 at some pixel: {most}");
    check_gradients_with(&s, &cam, &set, 15, 6, true);
}

#[test]
fn gradients_k1_centre_order() {
    let s = random_scene(8, 23, (0.15, 0.4), (0.2, 0.9));
    check_gradients(&s, &camera(24, 18), &smooth(1, true), 0, 3);
}

#[test]
fn gradients_with_hard_cutoffs_clamp_and_early_stop() {
    // High opacities: α at the 0.99 clamp near centres and T reaching the 1e-4 stop; low ones
    // near the 1/255 cut. Default cut-offs.
    let mut s = random_scene(10, 24, (0.15, 0.4), (0.01, 0.05));
    for i in 0..5 {
        s.opacity_logits[i] = logit(0.9995);
    }
    let set = RasterSettings { window: 8, two_sided: true, ..Default::default() };
    check_gradients(&s, &camera(24, 18), &set, 1, 4);
}

/// The display stop (compositing ends after the blend that takes T below it): the fast path
/// matches the reference with the same rule at every K, the stop changes the image (so the test
/// can fail), and each pixel differs from the exact render by at most the stop times the
/// largest colour or background (what the pixel then misses), its alpha by at most the stop.
#[test]
fn display_stop_matches_the_reference_and_bounds_the_difference() {
    let cam = camera(40, 30);
    let s = random_scene(40, 27, (0.1, 0.4), (0.3, 0.99));
    let bg = [0.2f32, 0.5, 0.9];
    for k in [1usize, 3, 8, 32] {
        for stop in [crate::raster::DISPLAY_STOP, 0.05] {
            let exact = RasterSettings { window: k, two_sided: true, background: bg, ..Default::default() };
            let display = RasterSettings { display_stop: stop, ..exact.clone() };
            let d = compare(&s, &cam, &display, None, Order::Window(k));
            assert!(d < 2e-4, "K = {k}, stop {stop}: max diff {d} against the reference");
            for outputs in [Outputs::default(), Outputs::colour_only()] {
                let (a, state) = render(&s, &cam, &RasterSettings { outputs, ..exact.clone() }, None);
                let (b, _) = render(&s, &cam, &RasterSettings { outputs, ..display.clone() }, None);
                // The largest colour a pixel can miss: a surfel's (SH, for this view) or the background.
                let bound_colour = state.proj.colour.iter().flatten().chain(&bg).fold(0.0f32, |m, &c| m.max(c));
                let mut changed = 0;
                for i in 0..a.alpha.len() {
                    let da = a.alpha[i] - b.alpha[i];
                    assert!(da > -1e-6 && da <= stop + 1e-6, "K = {k}, stop {stop}, pixel {i}: alpha {da}");
                    for c in 0..3 {
                        let dc = (a.colour[i][c] - b.colour[i][c]).abs();
                        assert!(dc <= stop * bound_colour + 1e-5, "K = {k}, stop {stop}, pixel {i}: colour {dc}");
                    }
                    changed += (a.colour[i] != b.colour[i]) as usize;
                }
                assert!(changed > 20, "K = {k}, stop {stop}: only {changed} pixels stopped early");
            }
        }
    }
}

/// The backward re-runs each pixel's compositing with the same settings, so a display stop
/// (never set by training) also gives the gradient of what the forward drew.
#[test]
fn gradients_with_a_display_stop() {
    let s = random_scene(10, 26, (0.15, 0.4), (0.4, 0.95));
    let set = RasterSettings { display_stop: 0.2, ..smooth(8, true) };
    let cam = camera(24, 18);
    let stopped = render(&s, &cam, &set, None).0;
    let exact = render(&s, &cam, &RasterSettings { display_stop: 0.0, ..set.clone() }, None).0;
    let changed = (0..stopped.alpha.len()).filter(|&i| stopped.alpha[i] != exact.alpha[i]).count();
    assert!(changed > 10, "the stop ends only {changed} pixels early");
    check_gradients_with(&s, &cam, &set, 1, 6, true);
}

#[test]
fn gradients_grazing_and_across_near_plane() {
    let cam = camera(24, 18);
    let fwd = (Vec3::ZERO - cam.position()).normalize();
    let mut s = random_scene(8, 25, (0.15, 0.4), (0.3, 0.9));
    let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
    // Normals almost perpendicular to the view direction (grazing).
    for i in 0..4 {
        let side = fwd.any_orthonormal_vector();
        let n = (side + fwd * rng.random_range(0.02..0.15f32)).normalize();
        s.quats[i] = quat_with_normal((-n).to_array());
    }
    // Large surfels just beyond the near plane, facing the camera: part of each disk is closer
    // than near.
    for i in 4..6 {
        let c = cam.position() + fwd * 0.3 + Vec3::new(0.05 * i as f32, 0.0, 0.02);
        s.means[i] = c.to_array();
        s.log_scales[i] = [0.6f32.ln(), 0.5f32.ln()];
        let tilt = (-fwd + fwd.any_orthonormal_vector() * 0.8).normalize();
        s.quats[i] = quat_with_normal(tilt.to_array());
    }
    check_gradients(&s, &cam, &smooth(8, true), 0, 5);
}

#[test]
fn densification_gradient_is_the_screen_space_centre_gradient() {
    // Moving a surfel by δ along the camera's x axis changes only Tu.z (by fx·δ), so
    // ∂L/∂μ · x_cam = ∂L/∂Tu.z · fx and v_mean2d.x = ∂L/∂Tu.z · z · W/2.
    let mut s = random_scene(12, 26, (0.1, 0.35), (0.3, 0.9));
    s.sh_degree = 0;
    let cam = camera(32, 24);
    let set = RasterSettings { two_sided: true, ..Default::default() };
    let (_, st) = render(&s, &cam, &set, None);
    let w = weights(32 * 24, 0, 9);
    let grads = RenderGrads { v_colour: w.colour, v_alpha: w.alpha, ..Default::default() };
    let mut g = s.zeros_like();
    let b = render_backward(&s, &cam, &set, None, &st, &grads, &mut g, None);
    let xcam = cam.rotation.row(0);
    let ycam = cam.rotation.row(1);
    let mut seen = 0;
    for i in 0..s.len() {
        if !st.visible[i] {
            assert_eq!((b.v_mean2d[i], b.v_mean2d_abs[i]), ([0.0; 2], [0.0; 2]));
            continue;
        }
        seen += 1;
        let z = cam.world_to_camera(Vec3::from(s.means[i])).z;
        let want_x = Vec3::from(g.means[i]).dot(xcam) / cam.fx * z * 0.5 * cam.width as f32;
        let want_y = Vec3::from(g.means[i]).dot(ycam) / cam.fy * z * 0.5 * cam.height as f32;
        let got = b.v_mean2d[i];
        assert!((got[0] - want_x).abs() < 1e-3 * (1.0 + want_x.abs()), "{i}: {got:?} vs {want_x} {want_y}");
        assert!((got[1] - want_y).abs() < 1e-3 * (1.0 + want_y.abs()), "{i}: {got:?} vs {want_x} {want_y}");
    }
    assert!(seen > 5);
}

/// AbsGS's statistic is, per axis, the sum over pixels of |that pixel's centre gradient|:
/// checked against backward passes with the loss on one pixel at a time, on a scene with
/// surfels large enough to cover pixels on both sides of their centre (the opposite pulls that
/// cancel in `v_mean2d`) and tiny ones (the screen-space filter branch).
#[test]
fn abs_centre_gradient_sums_each_pixels_absolute_value() {
    let (w, h) = (20u32, 14u32);
    let mut s = random_scene(10, 31, (0.15, 0.5), (0.3, 0.9));
    s.sh_degree = 0;
    for i in 0..3 {
        s.log_scales[i] = [1e-3f32.ln(), 2e-3f32.ln()];
    }
    let cam = camera(w, h);
    let outputs = Outputs { colour: true, depth: true, normal: true, ..Outputs::none() };
    let set = RasterSettings { two_sided: true, outputs, abs_centre_gradient: true, ..Default::default() };
    let (_, st) = render(&s, &cam, &set, None);
    let px = (w * h) as usize;
    let wts = weights(px, 0, 4);
    let all = RenderGrads {
        v_colour: wts.colour.clone(),
        v_alpha: wts.alpha.clone(),
        v_depth: wts.depth.clone(),
        v_normal: wts.normal.clone(),
        ..Default::default()
    };
    let mut g = s.zeros_like();
    let full = render_backward(&s, &cam, &set, None, &st, &all, &mut g, None);
    let mut want = vec![[0.0f64; 2]; s.len()];
    let mut signed = vec![[0.0f64; 2]; s.len()];
    for p in 0..px {
        let only = |v: &[f32]| -> Vec<f32> { (0..px).map(|i| if i == p { v[i] } else { 0.0 }).collect() };
        let only3 =
            |v: &[[f32; 3]]| -> Vec<[f32; 3]> { (0..px).map(|i| if i == p { v[i] } else { [0.0; 3] }).collect() };
        let one = RenderGrads {
            v_colour: only3(&wts.colour),
            v_alpha: only(&wts.alpha),
            v_depth: only(&wts.depth),
            v_normal: only3(&wts.normal),
            ..Default::default()
        };
        let mut gp = s.zeros_like();
        let b = render_backward(&s, &cam, &set, None, &st, &one, &mut gp, None);
        for i in 0..s.len() {
            for a in 0..2 {
                want[i][a] += (b.v_mean2d[i][a] as f64).abs();
                signed[i][a] += b.v_mean2d[i][a] as f64;
            }
        }
    }
    let mut cancelled = 0;
    for i in 0..s.len() {
        for a in 0..2 {
            let got = full.v_mean2d_abs[i][a] as f64;
            assert!(
                (got - want[i][a]).abs() <= 1e-4 * (1.0 + want[i][a]),
                "surfel {i} axis {a}: {got} vs {}",
                want[i][a]
            );
            assert!((full.v_mean2d[i][a] as f64 - signed[i][a]).abs() <= 1e-4 * (1.0 + want[i][a]));
            if want[i][a] > 2.0 * signed[i][a].abs() + 1e-6 {
                cancelled += 1;
            }
        }
    }
    assert!(cancelled >= 3, "the scene must have surfels whose pixels pull opposite ways ({cancelled})");

    // Off (the default): zeros, and every other gradient bit for bit the same, features (whose
    // columns move) included.
    let ch = 3;
    let feats = random_features(s.len(), ch, 8);
    let f = Some(Features { data: &feats, channels: ch });
    let with_features = RenderGrads { v_features: weights(px, ch, 9).features, ..all };
    let mut grads_fv = Vec::new();
    for abs in [true, false] {
        let set = RasterSettings { abs_centre_gradient: abs, ..set };
        let (_, st) = render(&s, &cam, &set, f);
        let (mut g, mut fv) = (s.zeros_like(), vec![0.0; s.len() * ch]);
        let b = render_backward(&s, &cam, &set, f, &st, &with_features, &mut g, Some(&mut fv));
        assert_eq!(b.v_mean2d_abs.iter().any(|a| a != &[0.0; 2]), abs);
        grads_fv.push((g, fv, b.v_mean2d));
    }
    assert!(grads_fv[0] == grads_fv[1]);
}

/// The surface-aware depth (GauS-SLAM) against the f64 reference, which computes it from each
/// pixel's blended list by direct sums rather than the forward's running sums, for several
/// windows on layered scenes; and it must differ from the plain expected depth (the pull acts).
#[test]
fn surface_depth_matches_reference() {
    let cam = camera(40, 32);
    let mut pulled = 0usize;
    for (seed, k) in [(41u64, 1usize), (42, 4), (43, 8), (44, 16)] {
        let s = random_scene(60, seed, (0.1, 0.3), (0.2, 0.8));
        let set = RasterSettings {
            window: k,
            two_sided: true,
            outputs: Outputs { surface_depth: true, ..Outputs::default() },
            ..Default::default()
        };
        let (out, _) = render(&s, &cam, &set, None);
        let r = render_ref(&RefScene::from_surfels(&s, None), &cam, &set, Order::Window(k));
        let mut worst = 0.0f64;
        for i in 0..out.alpha.len() {
            let d = (out.surface_depth[i] as f64 - r.surface_depth[i]).abs();
            worst = worst.max(d / (1.0 + r.surface_depth[i].abs()));
            if (r.surface_depth[i] - r.depth[i]).abs() > 0.05 {
                pulled += 1;
            }
        }
        assert!(worst < 1e-3, "k = {k}: surface depth differs from the reference by {worst}");
    }
    assert!(pulled > 100, "the pull toward the median must change the depth somewhere ({pulled} pixels)");
}

/// α of surfel i at pixel (x, y) by a world-space ray–plane evaluation in f64 (independent of
/// the rasteriser's homogeneous algebra): the reference for what culling may drop.
fn alpha_f64(scene: &Surfels, camera: &Camera, filter: f32, i: usize, x: u32, y: u32) -> f64 {
    let rot: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| camera.rotation.col(c)[r] as f64));
    let tr = [camera.translation.x as f64, camera.translation.y as f64, camera.translation.z as f64];
    let org: [f64; 3] = std::array::from_fn(|a| -(0..3).map(|r| rot[r][a] * tr[r]).sum::<f64>());
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let r = crate::surfels::rotation_from_quat(scene.quats[i]);
    let (tu, tv, n) = (r[0].map(|v| v as f64), r[1].map(|v| v as f64), r[2].map(|v| v as f64));
    let mu = scene.means[i].map(|v| v as f64);
    let (su, sv) = (scene.log_scales[i][0].exp() as f64, scene.log_scales[i][1].exp() as f64);
    let o = 1.0 / (1.0 + (-scene.opacity_logits[i] as f64).exp());
    let c: [f64; 3] = std::array::from_fn(|k| dot(rot[k], mu) + tr[k]);
    let m2d = [camera.fx as f64 * c[0] / c[2] + camera.cx as f64, camera.fy as f64 * c[1] / c[2] + camera.cy as f64];
    let (pxf, pyf) = (x as f64 + 0.5, y as f64 + 0.5);
    let dc = [(pxf - camera.cx as f64) / camera.fx as f64, (pyf - camera.cy as f64) / camera.fy as f64, 1.0];
    let d: [f64; 3] = std::array::from_fn(|a| (0..3).map(|k| rot[k][a] * dc[k]).sum());
    let den = dot(n, d);
    let rho3 = if den == 0.0 {
        f64::INFINITY
    } else {
        let t = dot(n, [mu[0] - org[0], mu[1] - org[1], mu[2] - org[2]]) / den;
        let p = [org[0] + t * d[0] - mu[0], org[1] + t * d[1] - mu[1], org[2] + t * d[2] - mu[2]];
        (dot(tu, p) / su).powi(2) + (dot(tv, p) / sv).powi(2)
    };
    let rho2 = filter as f64 * ((m2d[0] - pxf).powi(2) + (m2d[1] - pyf).powi(2));
    o * (-0.5 * rho3.min(rho2)).exp()
}

/// Scenes for the culling tests: large tilted surfels (many pruned corners), tiny scales, a
/// sharper filter, and a few surfels seen nearly edge-on.
fn culling_scenes() -> Vec<(u64, Surfels, f32)> {
    [(11u64, (0.02f32, 0.4f32), 2.0f32), (12, (0.001, 0.01), 2.0), (13, (0.1, 0.6), 2.0), (14, (0.001, 0.01), 8.0)]
        .into_iter()
        .map(|(seed, scale, filter)| {
            let mut scene = random_scene(400, seed, scale, (0.05, 0.99));
            for i in 0..20 {
                let n = Vec3::new(1.0, 0.002 * i as f32, 0.0).normalize();
                scene.quats[i] = quat_with_normal(n.to_array());
            }
            (seed, scene, filter)
        })
        .collect()
}

/// Tile culling by the exact footprint (tiles.rs `Footprint`) drops only (tile, surfel) pairs
/// whose α is below α_min at every pixel centre of the tile: checked pair by pair against a
/// world-space ray–plane evaluation in f64 (not the conic algebra of the cull), on scenes with
/// large tilted surfels (many pruned corners), grazing surfels and tiny scales. It must also
/// drop something (a cull that never fires would pass the first check trivially).
#[test]
fn tile_culling_drops_only_pairs_without_hits() {
    let camera = camera(96, 80);
    let mut dropped_total = 0usize;
    for (seed, scene, filter) in culling_scenes() {
        let settings = RasterSettings { two_sided: true, filter_inv_square: filter, ..RasterSettings::default() };
        let proj = super::project::project(&scene, &camera, &settings);
        let culled = super::tiles::bin(&proj, camera.width, camera.height, settings.alpha_min, filter);
        let full = super::tiles::bin(&proj, camera.width, camera.height, 0.0, filter);
        let tiles = (full.tiles_x * full.tiles_y) as usize;
        for t in 0..tiles {
            // Every tile's list in (centre depth, index) order.
            let list = &culled.ids[culled.offsets[t] as usize..culled.offsets[t + 1] as usize];
            let key = |i: u32| (proj.depth[i as usize], i);
            assert!(list.windows(2).all(|w| key(w[0]) < key(w[1])), "seed {seed}: tile {t} out of depth order");
            let kept: std::collections::HashSet<u32> =
                culled.ids[culled.offsets[t] as usize..culled.offsets[t + 1] as usize].iter().copied().collect();
            let (tx, ty) = (t as u32 % full.tiles_x, t as u32 / full.tiles_x);
            for &i in &full.ids[full.offsets[t] as usize..full.offsets[t + 1] as usize] {
                if kept.contains(&i) {
                    continue;
                }
                dropped_total += 1;
                let i = i as usize;
                for y in ty * TILE..((ty + 1) * TILE).min(camera.height) {
                    for x in tx * TILE..((tx + 1) * TILE).min(camera.width) {
                        let alpha = alpha_f64(&scene, &camera, filter, i, x, y);
                        assert!(
                            alpha < settings.alpha_min as f64 * 0.999,
                            "seed {seed}: surfel {i} dropped from tile ({tx}, {ty}) but α = {alpha} at pixel ({x}, {y})"
                        );
                    }
                }
            }
        }
        // The backward sums a surfel's pair rows through pair_offsets / sorted_of_gen: with
        // pairs dropped, surfel i's generation numbers must map one-to-one onto exactly the
        // positions of `ids` that hold i, in ascending tile order.
        assert_eq!(culled.pair_offsets.len(), full.pair_offsets.len());
        assert_eq!(culled.ids.len(), *culled.pair_offsets.last().unwrap() as usize);
        let mut hit = vec![false; culled.ids.len()];
        for i in 0..scene.len() {
            let mut last = None;
            for g in culled.pair_offsets[i]..culled.pair_offsets[i + 1] {
                let pos = culled.sorted_of_gen[g as usize] as usize;
                assert_eq!(culled.ids[pos] as usize, i, "seed {seed}: generation {g} maps to another surfel");
                assert!(!hit[pos], "seed {seed}: position {pos} mapped twice");
                hit[pos] = true;
                let tile = culled.offsets.partition_point(|&o| o as usize <= pos) - 1;
                assert!(last.is_none_or(|l| l < tile), "seed {seed}: surfel {i}'s pairs out of tile order");
                last = Some(tile);
            }
        }
        assert!(hit.iter().all(|&h| h), "seed {seed}: a pair no surfel's generation range reaches");
    }
    assert!(dropped_total > 1000, "the cull dropped only {dropped_total} pairs");
}

/// The bin sorts every surfel with a tile rectangle by depth beside the footprint pass and then
/// drops those whose footprint missed every tile. Here surfel 0's rectangle is moved to tiles
/// its ellipse cannot reach: it must vanish from every list (no pair, no span), and every other
/// list must be exactly what it was. (Surfel 0 has the first generation range, so a span read
/// for it without pairs would index before the first pair.)
#[test]
fn a_rectangle_whose_footprint_misses_every_tile_leaves_no_pair() {
    let camera = camera(96, 80);
    let settings = RasterSettings { two_sided: true, ..RasterSettings::default() };
    // A scene whose surfel 0 is drawn, small and covers at least one tile.
    let (_, mut proj) = (31..200)
        .map(|seed| {
            let scene = random_scene(60, seed, (0.03, 0.12), (0.3, 0.99));
            let proj = super::project::project(&scene, &camera, &settings);
            (scene, proj)
        })
        .find(|(_, p)| p.radius[0] > 1.0 && p.radius[0] < 20.0)
        .expect("a scene with surfel 0 drawn");
    let bin = |p: &super::project::Projected| {
        super::tiles::bin(p, camera.width, camera.height, settings.alpha_min, settings.filter_inv_square)
    };
    let before = bin(&proj);
    let m = proj.mean2d(0);
    let (tiles_x, tiles_y) = (before.tiles_x, before.tiles_y);
    // A 2 × 2 block of tiles in the corner farthest from the centre (its box is ≥ 2 × 2, so
    // the footprint test runs; the ellipse is small against the image).
    let far_x = if m[0] < (camera.width / 2) as f32 { tiles_x - 2 } else { 0 };
    let far_y = if m[1] < (camera.height / 2) as f32 { tiles_y - 2 } else { 0 };
    proj.rect[0] = [far_x, far_y, far_x + 1, far_y + 1];
    let after = bin(&proj);
    assert_eq!(after.pair_offsets[1], 0, "the moved surfel kept a pair");
    let mut removed = 0;
    for t in 0..(tiles_x * tiles_y) as usize {
        let was: Vec<u32> = before.ids[before.offsets[t] as usize..before.offsets[t + 1] as usize].to_vec();
        removed += was.iter().filter(|&&i| i == 0).count();
        let expect: Vec<u32> = was.into_iter().filter(|&i| i != 0).collect();
        assert_eq!(&after.ids[after.offsets[t] as usize..after.offsets[t + 1] as usize], &expect[..], "tile {t}");
    }
    assert!(removed > 0, "surfel 0 had no pair before the move");
}

/// A pixel evaluates only its tile quarter's candidates (`TileData::quarters`): every candidate
/// left out of a quarter has α < α_min at every pixel centre of it (by the f64 world-space
/// evaluation), the quarters keep the tile's order, and on small surfels they drop most of the
/// list (else the split would be pointless). The bin's footprint masks must leave out pairs
/// that the pixel boxes alone keep (else the masks would be pointless).
#[test]
fn tile_quarters_leave_out_only_candidates_without_hits() {
    use super::forward::{QUARTER, TileData};
    let camera = camera(96, 80);
    let mut by_mask = 0usize;
    for (seed, scene, filter) in culling_scenes() {
        let (mut left_out, mut listed) = (0usize, 0usize);
        let settings = RasterSettings { two_sided: true, filter_inv_square: filter, ..RasterSettings::default() };
        let proj = super::project::project(&scene, &camera, &settings);
        let bins = super::tiles::bin(&proj, camera.width, camera.height, settings.alpha_min, filter);
        let mut td = TileData::default();
        for t in 0..(bins.tiles_x * bins.tiles_y) as usize {
            let (tx, ty) = (t as u32 % bins.tiles_x, t as u32 / bins.tiles_x);
            let ids = &bins.ids[bins.offsets[t] as usize..bins.offsets[t + 1] as usize];
            let masks = &bins.quarter_masks[bins.offsets[t] as usize..bins.offsets[t + 1] as usize];
            td.load(&proj, ids, &vec![0b1111; ids.len()], (tx * TILE, ty * TILE));
            let box_only: usize = td.quarters.iter().map(|q| q.n).sum();
            td.load(&proj, ids, masks, (tx * TILE, ty * TILE));
            by_mask += box_only - td.quarters.iter().map(|q| q.n).sum::<usize>();
            for (q, quarter) in td.quarters.iter().enumerate() {
                assert_eq!(quarter.n, quarter.slot.len());
                assert!(quarter.slot.windows(2).all(|w| w[0] < w[1]), "seed {seed}: quarter {q} out of tile order");
                let x0 = tx * TILE + QUARTER * (q as u32 % 2);
                let y0 = ty * TILE + QUARTER * (q as u32 / 2);
                for (j, &i) in ids.iter().enumerate() {
                    if quarter.slot.binary_search(&(j as u32)).is_ok() {
                        listed += 1;
                        continue;
                    }
                    left_out += 1;
                    for y in y0..(y0 + QUARTER).min(camera.height) {
                        for x in x0..(x0 + QUARTER).min(camera.width) {
                            let alpha = alpha_f64(&scene, &camera, filter, i as usize, x, y);
                            assert!(
                                alpha < settings.alpha_min as f64 * 0.999,
                                "seed {seed}: surfel {i} left out of quarter {q} of tile ({tx}, {ty}) but α = {alpha} at ({x}, {y})"
                            );
                        }
                    }
                }
            }
        }
        // Seeds 12 and 14 have tiny surfels (a few pixels): most of a tile's list misses a
        // given quarter.
        let tiny = seed == 12 || seed == 14;
        assert!(
            left_out > 0 && (!tiny || left_out > listed),
            "seed {seed}: the quarters left out only {left_out} of {} entries",
            left_out + listed
        );
    }
    assert!(by_mask > 1000, "the footprint masks left out only {by_mask} pairs the boxes keep");
}

/// The recorded forward (`render_recorded`) gives `render`'s outputs, and the backward that
/// replays its hits gives bitwise the gradients of the backward that re-runs the windows: per
/// window size, one- and two-sided, with features, an odd width (a lone last pixel of a pair),
/// several tiles, and a record reused from a frame of another size.
#[test]
fn recorded_hits_replay_the_backward_exactly() {
    let s = random_scene(300, 41, (0.03, 0.2), (0.1, 0.95));
    let ch = 3;
    let feats = random_features(s.len(), ch, 42);
    let f = Some(Features { data: &feats, channels: ch });
    let mut reuse = PixelHitRecord::default();
    let cases = [
        (1, false, (37, 29), usize::MAX),
        (8, true, (37, 29), usize::MAX),
        (32, false, (20, 45), usize::MAX),
        (8, false, (37, 70), 0),
    ];
    for (window, two_sided, (w, h), budget) in cases {
        let set = RasterSettings { window, two_sided, background: [0.2, 0.1, 0.4], ..Default::default() };
        let cam = camera(w, h);
        let px = (w * h) as usize;
        let wts = weights(px, ch, 43);
        // Some pixels without any gradient (the backward skips them).
        let zero_some = |v: &mut Vec<f32>| v.iter_mut().step_by(5).for_each(|x| *x = 0.0);
        let mut alpha = wts.alpha.clone();
        zero_some(&mut alpha);
        let grads = RenderGrads {
            v_colour: wts.colour.clone(),
            v_alpha: alpha,
            v_depth: wts.depth.clone(),
            v_median_depth: wts.median.clone(),
            v_normal: wts.normal.clone(),
            v_distortion: wts.distortion.clone(),
            v_features: wts.features.clone(),
        };
        let (out_a, st_a) = render(&s, &cam, &set, f);
        // Budget 0 here: one that the fuller half of the rows of tiles do not fit entirely.
        let budget = if budget > 0 {
            budget
        } else {
            let (_, full) = render_recorded(&s, &cam, &set, f, PixelHitRecord::default());
            let rows = &full.record.as_ref().unwrap().rows;
            let mut per_row: Vec<usize> = rows.iter().map(|r| r.hits.len()).collect();
            per_row.sort();
            per_row[per_row.len() / 2] * std::mem::size_of::<super::RecordedHit>() * rows.len()
        };
        let (out_b, mut st_b) =
            super::forward::render_recorded_with_budget(&s, &cam, &set, f, std::mem::take(&mut reuse), budget);
        assert!(out_a == out_b, "window {window}: recorded forward differs");
        assert!(st_a.record.is_none());
        let rec = st_b.record.as_ref().unwrap();
        let over = rec.pixels_not_recorded();
        if budget == usize::MAX {
            assert!(rec.hits() > px * 2 && over == 0, "window {window}: the test needs hits ({})", rec.hits());
        } else {
            assert!(over > 0 && over < px / 2, "budget {budget}: {over} of {px} pixels not recorded");
        }
        let (mut ga, mut gb) = (s.zeros_like(), s.zeros_like());
        let (mut fa, mut fb) = (vec![0.0; s.len() * ch], vec![0.0; s.len() * ch]);
        let ba = render_backward(&s, &cam, &set, f, &st_a, &grads, &mut ga, Some(&mut fa));
        let bb = render_backward(&s, &cam, &set, f, &st_b, &grads, &mut gb, Some(&mut fb));
        assert!(ga == gb && fa == fb, "window {window}: replayed gradients differ");
        assert!(ba.v_mean2d == bb.v_mean2d && ba.v_mean2d_abs == bb.v_mean2d_abs);
        assert!(ga != s.zeros_like());
        reuse = st_b.record.take().unwrap();
    }
}

/// Re-blending features with the kept weights gives the reference's (independent, f64) feature
/// images and alpha, for every window order, culling mode and a tile-straddling image; and the
/// fast render's features to float rounding.
#[test]
fn blend_weights_reblend_features_as_the_reference() {
    let cam = camera(37, 29);
    for (seed, k, two_sided) in [(21u64, 32usize, false), (22, 4, true), (23, 1, true)] {
        let s = random_scene(40, seed, (0.05, 0.35), (0.1, 0.95));
        let ch = 5;
        let f = random_features(40, ch, seed + 100);
        let set = RasterSettings { window: k, two_sided, background: [0.3, 0.6, 0.9], ..Default::default() };
        let order = if k == 32 { Order::Full } else { Order::Window(k) };
        let r = render_ref(&RefScene::from_surfels(&s, Some((&f, ch))), &cam, &set, order);
        let bw = blend_weights::BlendWeights::compute(&s, &cam, &set);
        assert_eq!(bw.offsets.len(), (37 * 29) + 1);
        assert!(bw.ids.len() > 37 * 29, "seed {seed}: too few hits ({}) to test anything", bw.ids.len());
        let (fast, _) = render(&s, &cam, &set, Some(Features { data: &f, channels: ch }));
        // Channels 1..4 only: the offset into each surfel's row counts.
        let mut out = Vec::new();
        bw.blend(&f, ch, 1, 3, &mut out);
        for p in 0..37 * 29 {
            let a = bw.alpha[p] as f64;
            assert!((a - r.alpha[p]).abs() < 2e-4, "seed {seed} pixel {p}: alpha {a} vs {}", r.alpha[p]);
            for c in 0..3 {
                let (got, want) = (out[p * 3 + c] as f64, r.features[p * ch + 1 + c]);
                assert!((got - want).abs() < 2e-4 * (1.0 + want.abs()), "seed {seed} pixel {p}: {got} vs {want}");
                let fast_v = fast.features[p * ch + 1 + c] as f64;
                assert!((got - fast_v).abs() < 1e-5 * (1.0 + fast_v.abs()), "seed {seed} pixel {p}: {got} vs {fast_v}");
            }
        }
    }
}

/// Renders that ask only for colour / alpha / features take the lean paths of the forward
/// (only the blend row per hit; 8 lanes when at most one feature channel): their values must
/// be bit for bit those of the full render, and match the reference.
#[test]
fn lean_and_narrow_renders_match_the_full_render_and_the_reference() {
    let cam = camera(40, 30);
    let s = random_scene(30, 21, (0.05, 0.35), (0.1, 0.95));
    for k in [1usize, 3, 8, 32] {
        for (nch, outputs) in [
            (0usize, Outputs::colour_only()),
            (1, Outputs::colour_only()),
            (1, Outputs::none()),
            (5, Outputs::colour_only()),
            (12, Outputs::colour_only()),
            (0, Outputs { normal: true, ..Outputs::colour_only() }),
        ] {
            let f = random_features(s.len(), nch.max(1), 7 + nch as u64);
            let feats = (nch > 0).then(|| Features { data: &f, channels: nch });
            let full = RasterSettings { window: k, two_sided: true, ..Default::default() };
            let lean = RasterSettings { outputs, ..full.clone() };
            let (a, _) = render(&s, &cam, &full, feats);
            let (b, _) = render(&s, &cam, &lean, feats);
            let what = format!("K = {k}, {nch} features, {outputs:?}");
            assert_eq!(a.alpha, b.alpha, "{what}: alpha");
            assert_eq!(a.features, b.features, "{what}: features");
            if outputs.colour {
                assert_eq!(a.colour, b.colour, "{what}: colour");
            } else {
                assert!(b.colour.is_empty(), "{what}");
            }
            if outputs.normal {
                assert_eq!(a.normal, b.normal, "{what}: normal");
            }
            assert!(b.depth.is_empty() && b.distortion.is_empty(), "{what}");
            let r =
                render_ref(&RefScene::from_surfels(&s, feats.map(|f| (f.data, nch))), &cam, &lean, Order::Window(k));
            let mut m = 0.0f64;
            for i in 0..b.alpha.len() {
                m = m.max((b.alpha[i] as f64 - r.alpha[i]).abs());
                if !b.colour.is_empty() {
                    for c in 0..3 {
                        m = m.max((b.colour[i][c] as f64 - r.colour[i][c]).abs() / (1.0 + r.colour[i][c].abs()));
                    }
                }
            }
            for i in 0..b.features.len() {
                m = m.max((b.features[i] as f64 - r.features[i]).abs() / (1.0 + r.features[i].abs()));
            }
            assert!(m < 2e-4, "{what}: max diff {m} against the reference");
        }
    }
}

/// Narrow frames composited sixteen pixels at a time (`forward::block`) against the same frames
/// one pixel at a time: bit for bit, with the evaluation counts, on image sizes that cut blocks
/// (odd widths and heights), windows that fill (hundreds of surfels), hits at the α clamp and T
/// cut-off, display stops, equal depths (duplicated surfels with other colours: their blend
/// order shows), culled back faces, a background, normals and one feature channel.
#[test]
fn pixel_blocks_render_narrow_frames_bit_for_bit_as_pixel_by_pixel() {
    use super::forward::{Compositor, render_with};
    let mut s = random_scene(300, 31, (0.04, 0.3), (0.05, 0.99));
    for i in 0..20 {
        s.opacity_logits[i] = logit(0.9995);
    }
    // Ten duplicates of surfels 30..40 with other colours: the same hits at the same z.
    for i in 30..40 {
        let (m, q) = (s.means[i], s.quats[i]);
        s.push(m, [1.0; 2], q, 0.5, [0.9, 0.1, 0.4], [0.5; 3], 0.5);
        let last = s.len() - 1;
        s.opacity_logits[last] = s.opacity_logits[i];
        s.log_scales[last] = s.log_scales[i];
    }
    let f = random_features(s.len(), 1, 5);
    let mut blocks_seen = 0;
    for (w, h) in [(37u32, 23u32), (48, 32), (9, 3)] {
        let cam = camera(w, h);
        for two_sided in [true, false] {
            for display_stop in [0.0, crate::raster::DISPLAY_STOP, 0.05] {
                for (feats, outputs) in [
                    (None, Outputs::colour_only()),
                    (Some(Features { data: &f, channels: 1 }), Outputs { normal: true, ..Outputs::colour_only() }),
                    (None, Outputs::none()),
                ] {
                    let set = RasterSettings {
                        window: 8,
                        two_sided,
                        display_stop,
                        background: [0.2, 0.5, 0.9],
                        outputs,
                        ..Default::default()
                    };
                    let what = format!("{w}×{h}, two-sided {two_sided}, stop {display_stop}, {outputs:?}");
                    let (a, sa) = render_with(&s, &cam, &set, feats, Compositor::Blocks);
                    let (b, sb) = render_with(&s, &cam, &set, feats, Compositor::Pixels);
                    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&a.alpha), bits(&b.alpha), "{what}: alpha");
                    assert_eq!(bits(a.colour.as_flattened()), bits(b.colour.as_flattened()), "{what}: colour");
                    assert_eq!(bits(a.normal.as_flattened()), bits(b.normal.as_flattened()), "{what}: normal");
                    assert_eq!(bits(&a.features), bits(&b.features), "{what}: features");
                    assert_eq!(sa.evaluations_performed, sb.evaluations_performed, "{what}: evaluations");
                    assert_eq!(sa.evaluations, sb.evaluations, "{what}: tile-list evaluations");
                    blocks_seen += a.alpha.iter().filter(|&&x| x > 0.999).count();
                }
            }
        }
    }
    // The scenes are deep enough to reach the cut-offs.
    assert!(blocks_seen > 1000, "only {blocks_seen} opaque pixels");
}
