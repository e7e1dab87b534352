//! Pinhole cameras in OpenCV axes (x right, y down, z forward), world-to-camera R|t, and the
//! conversion from Blender/NeRF camera-to-world matrices (OpenGL axes: looks along −z, +y up).
//! Pixel centres sit at (x + 0.5, y + 0.5): pixel (0, 0) covers [0, 1) × [0, 1).

use crate::error::{Error, Result};
use glam::{Mat3, Mat4, Vec3, Vec4};

#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// The view's name (file stem or folder name), used for output files.
    pub name: String,
    pub width: u32,
    pub height: u32,
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// World-to-camera rotation (rows are the camera axes in world coordinates).
    pub rotation: Mat3,
    /// World-to-camera translation: p_cam = rotation · p_world + translation.
    pub translation: Vec3,
}

impl Camera {
    /// Focal length in pixels from a horizontal field of view (NeRF-synthetic convention).
    pub fn focal_from_fov_x(width: u32, camera_angle_x: f32) -> f32 {
        width as f32 / (2.0 * (camera_angle_x * 0.5).tan())
    }

    /// Build a camera from a Blender `transform_matrix` (camera-to-world, OpenGL axes, rows as
    /// stored in JSON). Negating columns 1 and 2 turns OpenGL axes into OpenCV axes.
    pub fn from_blender(
        name: impl Into<String>,
        c2w_rows: [[f32; 4]; 4],
        width: u32,
        height: u32,
        camera_angle_x: f32,
    ) -> Result<Camera> {
        let name = name.into();
        if c2w_rows.iter().flatten().any(|v| !v.is_finite()) {
            return Err(Error::invalid(format!("camera {name}"), "transform_matrix has a non-finite entry"));
        }
        if !(camera_angle_x.is_finite() && camera_angle_x > 0.0 && camera_angle_x < std::f32::consts::PI) {
            return Err(Error::invalid(
                format!("camera {name}"),
                format!("camera_angle_x {camera_angle_x} is not in (0, pi)"),
            ));
        }
        if width == 0 || height == 0 {
            return Err(Error::invalid(format!("camera {name}"), "image size is zero"));
        }
        let c2w = Mat4::from_cols_array_2d(&c2w_rows).transpose();
        let x = c2w.x_axis.truncate();
        let y = -c2w.y_axis.truncate();
        let z = -c2w.z_axis.truncate();
        let rot_c2w = Mat3::from_cols(x, y, z);
        // Reject matrices whose rotation part is far from orthonormal (scaled or sheared cameras).
        let gram = rot_c2w.transpose() * rot_c2w;
        let err = (gram - Mat3::IDENTITY).to_cols_array().iter().map(|v| v.abs()).fold(0.0, f32::max);
        if err > 1e-3 {
            return Err(Error::invalid(
                format!("camera {name}"),
                format!("transform_matrix rotation is not orthonormal (|RᵀR − I| = {err:.2e})"),
            ));
        }
        let position = c2w.w_axis.truncate();
        let rotation = rot_c2w.transpose();
        let translation = -(rotation * position);
        let f = Self::focal_from_fov_x(width, camera_angle_x);
        Ok(Camera {
            name,
            width,
            height,
            fx: f,
            fy: f,
            cx: width as f32 * 0.5,
            cy: height as f32 * 0.5,
            rotation,
            translation,
        })
    }

    /// A camera at `eye` looking at `target` with world +z up (OpenCV axes inside).
    pub fn look_at(
        name: impl Into<String>,
        eye: Vec3,
        target: Vec3,
        width: u32,
        height: u32,
        camera_angle_x: f32,
    ) -> Camera {
        let forward = (target - eye).normalize();
        let mut right = forward.cross(Vec3::Z);
        if right.length_squared() < 1e-10 {
            right = Vec3::X;
        }
        let right = right.normalize();
        let down = forward.cross(right);
        let rot_c2w = Mat3::from_cols(right, down, forward);
        let rotation = rot_c2w.transpose();
        let f = Self::focal_from_fov_x(width, camera_angle_x);
        Camera {
            name: name.into(),
            width,
            height,
            fx: f,
            fy: f,
            cx: width as f32 * 0.5,
            cy: height as f32 * 0.5,
            rotation,
            translation: -(rotation * eye),
        }
    }

    /// Blender camera-to-world matrix (OpenGL axes), rows, for writing `transforms_*.json`.
    pub fn to_blender_rows(&self) -> [[f32; 4]; 4] {
        let rot_c2w = self.rotation.transpose();
        let pos = self.position();
        let c2w = Mat4::from_cols(
            rot_c2w.x_axis.extend(0.0),
            (-rot_c2w.y_axis).extend(0.0),
            (-rot_c2w.z_axis).extend(0.0),
            Vec4::new(pos.x, pos.y, pos.z, 1.0),
        );
        c2w.transpose().to_cols_array_2d()
    }

    /// Horizontal field of view in radians.
    pub fn fov_x(&self) -> f32 {
        2.0 * (self.width as f32 / (2.0 * self.fx)).atan()
    }

    /// Camera centre in world coordinates.
    pub fn position(&self) -> Vec3 {
        -(self.rotation.transpose() * self.translation)
    }

    pub fn world_to_camera(&self, p: Vec3) -> Vec3 {
        self.rotation * p + self.translation
    }

    pub fn camera_to_world(&self, p: Vec3) -> Vec3 {
        self.rotation.transpose() * (p - self.translation)
    }

    /// Continuous pixel coordinates of a world point, or None when it is not in front (z ≤ 0).
    pub fn project(&self, p: Vec3) -> Option<(f32, f32)> {
        let c = self.world_to_camera(p);
        if c.z <= 0.0 {
            return None;
        }
        Some((self.fx * c.x / c.z + self.cx, self.fy * c.y / c.z + self.cy))
    }

    /// World-space ray through continuous pixel coordinates (px, py): (origin, unit direction).
    /// The centre of pixel (i, j) is (i + 0.5, j + 0.5).
    pub fn ray(&self, px: f32, py: f32) -> (Vec3, Vec3) {
        let d_cam = Vec3::new((px - self.cx) / self.fx, (py - self.cy) / self.fy, 1.0);
        (self.position(), (self.rotation.transpose() * d_cam).normalize())
    }

    /// The camera of the image shrunk by an integer `factor` in blocks (`Image::downscale`):
    /// pixel j covers the old pixels [j·f, (j + 1)·f), so the intrinsics divide by f exactly,
    /// and the size rounds down (the rows and columns that fill no block are dropped).
    pub fn downscaled(&self, factor: u32) -> Camera {
        let f = factor.max(1);
        self.resized(self.width / f, self.height / f, 1.0 / f as f32, 1.0 / f as f32)
    }

    /// Same camera with the image scaled to `width` × `height` (intrinsics by the size ratio).
    pub fn scaled(&self, width: u32, height: u32) -> Camera {
        self.resized(width, height, width as f32 / self.width as f32, height as f32 / self.height as f32)
    }

    fn resized(&self, width: u32, height: u32, sx: f32, sy: f32) -> Camera {
        Camera { width, height, fx: self.fx * sx, fy: self.fy * sy, cx: self.cx * sx, cy: self.cy * sy, ..self.clone() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blender_camera_at_z(dist: f32) -> [[f32; 4]; 4] {
        // Camera above the origin looking straight down (−z), +y up in the image.
        [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, dist], [0.0, 0.0, 0.0, 1.0]]
    }

    #[test]
    fn point_in_front_of_blender_camera_projects_to_expected_pixel() {
        let cam = Camera::from_blender("c", blender_camera_at_z(4.0), 200, 100, 0.8).unwrap();
        // The origin is straight ahead: image centre.
        let (u, v) = cam.project(Vec3::ZERO).unwrap();
        assert!((u - 100.0).abs() < 1e-4 && (v - 50.0).abs() < 1e-4);
        // +x world is image right; +y world is image up (smaller row index).
        let (u, v) = cam.project(Vec3::new(0.5, 0.0, 0.0)).unwrap();
        let f = 200.0 / (2.0 * (0.4f32).tan());
        assert!((u - (100.0 + f * 0.5 / 4.0)).abs() < 1e-3, "u = {u}");
        assert!((v - 50.0).abs() < 1e-4);
        let (_, v) = cam.project(Vec3::new(0.0, 0.5, 0.0)).unwrap();
        assert!(v < 50.0);
        // Behind the camera: no projection.
        assert!(cam.project(Vec3::new(0.0, 0.0, 5.0)).is_none());
    }

    #[test]
    fn ray_through_projection_hits_point() {
        let cam = Camera::look_at("c", Vec3::new(3.0, -2.0, 1.5), Vec3::new(0.0, 0.0, 0.3), 64, 48, 0.7);
        let p = Vec3::new(0.2, 0.1, 0.5);
        let (u, v) = cam.project(p).unwrap();
        let (o, d) = cam.ray(u, v);
        let along = (p - o).normalize();
        assert!(along.dot(d) > 1.0 - 1e-6);
    }

    #[test]
    fn blender_round_trip() {
        let cam = Camera::look_at("c", Vec3::new(3.0, -2.0, 1.5), Vec3::ZERO, 64, 64, 0.7);
        let back = Camera::from_blender("c", cam.to_blender_rows(), 64, 64, cam.fov_x()).unwrap();
        assert!((back.position() - cam.position()).length() < 1e-5);
        assert!((back.rotation - cam.rotation).abs_diff_eq(Mat3::ZERO, 1e-5));
    }

    #[test]
    fn non_finite_matrix_is_rejected() {
        let mut m = blender_camera_at_z(4.0);
        m[1][2] = f32::NAN;
        let err = Camera::from_blender("view_7", m, 10, 10, 0.7).unwrap_err().to_string();
        assert!(err.contains("view_7") && err.contains("non-finite"), "{err}");
    }
}
