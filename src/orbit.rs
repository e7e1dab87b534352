//! A camera path once around the captured object, for `radiogs render --orbit N`: the turntable
//! view users of 2DGS and nerfstudio render after training.
//!
//! The path is derived from the cameras the object was captured with: its centre is the point
//! nearest all their optical axes (where an inward-facing capture looks), its radius and
//! elevation are the cameras' medians about that point, and it turns about the world's vertical
//! (+z, Blender's up) starting at the first camera's azimuth, so frame 0 resembles the first view.
//! Every frame keeps the first camera's intrinsics (size, focal lengths, principal point).

use crate::camera::Camera;
use crate::error::{Error, Result};
use glam::{DMat3, DVec3, Vec3};

/// Most frames an orbit may have.
pub const MAX_FRAMES: usize = 10_000;
/// Elevation limit (degrees): at ±90° the camera would look along the vertical and its
/// image axes would be undefined.
pub const MAX_ELEVATION_DEG: f32 = 89.0;

/// The point nearest every camera's optical axis in the least-squares sense:
/// Σ (I − d dᵀ)(p − o) = 0 over the cameras' centres o and viewing directions d.
/// None when the axes are (nearly) parallel (no common point) or the point lies behind the
/// cameras (an outward-facing capture).
pub fn look_at_centre(cameras: &[Camera]) -> Option<Vec3> {
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for cam in cameras {
        // The camera's forward axis in world space is the third row of world-to-camera.
        let d = cam.rotation.row(2).as_dvec3().normalize();
        let o = cam.position().as_dvec3();
        let projector = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += projector;
        b += projector * o;
    }
    // A's eigenvalues lie in [0, n]; a near-zero one means the axes are nearly parallel. The
    // determinant against the cube of the mean eigenvalue is scale-free: ≈ 0.006 for two
    // cameras 5° apart, ≈ 6e-5 for 0.5°.
    let mean = (a.x_axis.x + a.y_axis.y + a.z_axis.z) / 3.0;
    if cameras.is_empty() || !(a.determinant() > 1e-4 * mean * mean * mean) {
        return None;
    }
    let p = a.inverse() * b;
    let in_front = cameras.iter().filter(|c| c.world_to_camera(p.as_vec3()).z > 0.0).count();
    (p.is_finite() && 2 * in_front > cameras.len()).then(|| p.as_vec3())
}

fn median(mut v: Vec<f32>) -> f32 {
    v.sort_by(f32::total_cmp);
    v[v.len() / 2]
}

/// `frames` cameras once around the object the `reference` cameras look at (see the module
/// note), at `elevation_deg` above the centre's horizontal plane if given, else at the
/// cameras' median elevation. Named `orbit_000`, `orbit_001`, …
pub fn orbit(reference: &[Camera], frames: usize, elevation_deg: Option<f32>) -> Result<Vec<Camera>> {
    if !(1..=MAX_FRAMES).contains(&frames) {
        return Err(Error::invalid("--orbit", format!("{frames} frames: must be in 1..={MAX_FRAMES}")));
    }
    if let Some(e) = elevation_deg
        && !(e.abs() <= MAX_ELEVATION_DEG)
    {
        return Err(Error::invalid(
            "--orbit-elevation",
            format!("{e}°: must be in [-{MAX_ELEVATION_DEG}, {MAX_ELEVATION_DEG}] degrees"),
        ));
    }
    let Some(first) = reference.first() else {
        return Err(Error::invalid("--orbit", "no cameras to derive the orbit from"));
    };
    let Some(centre) = look_at_centre(reference) else {
        return Err(Error::invalid(
            "--orbit",
            "the cameras do not look at a common point (parallel or outward-facing views), so there is no object to orbit",
        ));
    };
    let offsets: Vec<Vec3> = reference.iter().map(|c| c.position() - centre).collect();
    let radius = median(offsets.iter().map(|v| v.length()).collect());
    if !(radius > 0.0) {
        return Err(Error::invalid("--orbit", "the cameras sit at the point they look at"));
    }
    let elevation = match elevation_deg {
        Some(e) => e.to_radians(),
        None => {
            median(offsets.iter().map(|v| (v.z / v.length().max(f32::MIN_POSITIVE)).clamp(-1.0, 1.0).asin()).collect())
                .clamp(-MAX_ELEVATION_DEG.to_radians(), MAX_ELEVATION_DEG.to_radians())
        }
    };
    let start = offsets[0].y.atan2(offsets[0].x);
    let digits = (frames.saturating_sub(1).max(1).ilog10() as usize + 1).max(3);
    Ok((0..frames)
        .map(|i| {
            let azimuth = start + std::f32::consts::TAU * i as f32 / frames as f32;
            let dir = Vec3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin());
            let cam = Camera::look_at(
                format!("orbit_{i:0digits$}"),
                centre + radius * dir,
                centre,
                first.width,
                first.height,
                first.fov_x(),
            );
            Camera { fx: first.fx, fy: first.fy, cx: first.cx, cy: first.cy, ..cam }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// Cameras at random places around `centre`, each aimed at it with a random small error.
    fn capture(centre: Vec3, n: usize, seed: u64) -> Vec<Camera> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        (0..n)
            .map(|i| {
                let az: f32 = rng.random_range(0.0..std::f32::consts::TAU);
                let el: f32 = rng.random_range(0.1..1.2);
                let r: f32 = rng.random_range(3.0..5.0);
                let eye = centre + r * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
                let mut cam = Camera::look_at(format!("c{i}"), eye, centre, 80, 60, 0.7);
                cam.cx = 41.5; // an off-centre principal point the orbit must keep
                cam
            })
            .collect()
    }

    #[test]
    fn the_centre_is_where_the_cameras_look() {
        let centre = Vec3::new(0.3, -0.2, 0.5);
        let found = look_at_centre(&capture(centre, 12, 1)).unwrap();
        assert!((found - centre).length() < 1e-4, "{found}");
        // Two cameras 90° apart suffice; one camera, parallel axes and an outward-facing ring do not.
        let two = [
            Camera::look_at("a", Vec3::new(4.0, 0.0, 1.0), centre, 8, 8, 0.7),
            Camera::look_at("b", Vec3::new(0.0, 4.0, 1.0), centre, 8, 8, 0.7),
        ];
        assert!((look_at_centre(&two).unwrap() - centre).length() < 1e-4);
        assert!(look_at_centre(&two[..1]).is_none());
        let parallel: Vec<Camera> = (0..5)
            .map(|i| Camera::look_at("p", Vec3::new(i as f32, -4.0, 1.0), Vec3::new(i as f32, 0.0, 1.0), 8, 8, 0.7))
            .collect();
        assert!(look_at_centre(&parallel).is_none());
        let outward: Vec<Camera> = (0..6)
            .map(|i| {
                let a = i as f32;
                let eye = Vec3::new(a.cos(), a.sin(), 0.0);
                Camera::look_at("o", eye, eye * 3.0, 8, 8, 0.7)
            })
            .collect();
        assert!(look_at_centre(&outward).is_none());
    }

    #[test]
    fn orbit_frames_circle_the_centre_and_look_at_it() {
        let centre = Vec3::new(0.3, -0.2, 0.5);
        let reference = capture(centre, 9, 2);
        let offsets: Vec<Vec3> = reference.iter().map(|c| c.position() - centre).collect();
        let radius = median(offsets.iter().map(|v| v.length()).collect());
        let elevation = median(offsets.iter().map(|v| (v.z / v.length()).asin()).collect());
        let frames = orbit(&reference, 8, None).unwrap();
        assert_eq!(frames.len(), 8);
        assert_eq!(frames[0].name, "orbit_000");
        assert_eq!(frames[7].name, "orbit_007");
        let start = offsets[0].y.atan2(offsets[0].x);
        for (i, cam) in frames.iter().enumerate() {
            let v = cam.position() - centre;
            assert!((v.length() - radius).abs() < 1e-4, "radius {}", v.length());
            assert!(((v.z / v.length()).asin() - elevation).abs() < 1e-4);
            let azimuth = start + std::f32::consts::TAU * i as f32 / 8.0;
            let turned = (v.y.atan2(v.x) - azimuth).rem_euclid(std::f32::consts::TAU);
            assert!(turned < 1e-4 || turned > std::f32::consts::TAU - 1e-4, "frame {i}: {turned}");
            // The centre sits at the principal point; the intrinsics are the first camera's.
            let (u, w) = cam.project(centre).unwrap();
            assert!((u - reference[0].cx).abs() < 1e-3 && (w - reference[0].cy).abs() < 1e-3, "({u}, {w})");
            assert_eq!((cam.width, cam.height, cam.fx, cam.fy), (80, 60, reference[0].fx, reference[0].fy));
            // Upright: world +z points up the image (towards smaller rows).
            let (_, above) = cam.project(centre + Vec3::Z * 0.1).unwrap();
            assert!(above < w);
        }
        // A given elevation; the names widen past 1000 frames.
        let high = orbit(&reference, 1001, Some(60.0)).unwrap();
        let v = high[500].position() - centre;
        assert!(((v.z / v.length()).asin().to_degrees() - 60.0).abs() < 1e-3);
        assert_eq!(high[1000].name, "orbit_1000");
    }

    #[test]
    fn bad_orbits_are_refused_by_name() {
        let reference = capture(Vec3::ZERO, 5, 3);
        for (frames, elevation, flag) in [
            (0, None, "--orbit"),
            (MAX_FRAMES + 1, None, "--orbit"),
            (10, Some(90.0), "--orbit-elevation"),
            (10, Some(f32::NAN), "--orbit-elevation"),
        ] {
            let err = orbit(&reference, frames, elevation).unwrap_err().to_string();
            assert!(err.contains(flag), "{err}");
        }
        assert!(orbit(&[], 10, None).unwrap_err().to_string().contains("no cameras"));
    }
}
