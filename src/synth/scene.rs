//! Scenes of the reference path tracer: objects made of primitives, materials with spatially
//! varying albedo/roughness (constant, 3D checker, stripes, evaluated in object-local
//! coordinates), a BVH over all primitives, and the orbit camera rig. The built-in scenes:
//! `spheres`, `box` (open box, indirect light dominates inside), `torus` (non-convex mesh) and
//! `cornell` (the geometry, materials and camera band of `../shared/data/cornell`, so our
//! model's images of that scene can be compared with the Cycles ones).

use super::brdf::Bsdf;
use super::bvh::Bvh;
use super::geometry::{Ray, Shape};
use glam::{Mat3, Vec3};
use serde::Serialize;
use std::f32::consts::PI;

/// A spatially varying value, evaluated at an object-local point p.
#[derive(Clone, Debug, Serialize)]
#[serde(tag = "pattern", rename_all = "snake_case")]
pub enum Tex<T> {
    Constant {
        value: T,
    },
    /// Parity of Σ floor(p·scale + 0.25) (the 0.25 keeps planes at integer coordinates stable).
    Checker {
        a: T,
        b: T,
        scale: f32,
    },
    /// Parity of floor((p·axis)·frequency + 0.25).
    Stripes {
        a: T,
        b: T,
        frequency: f32,
        axis: Vec3,
    },
}

impl<T: Copy> Tex<T> {
    pub fn eval(&self, p: Vec3) -> T {
        match self {
            Tex::Constant { value } => *value,
            Tex::Checker { a, b, scale } => {
                let q = (p * *scale + 0.25).floor();
                if (q.x + q.y + q.z).rem_euclid(2.0) < 0.5 { *a } else { *b }
            }
            Tex::Stripes { a, b, frequency, axis } => {
                if (p.dot(*axis) * frequency + 0.25).floor().rem_euclid(2.0) < 0.5 { *a } else { *b }
            }
        }
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct Material {
    pub name: String,
    /// Linear base colour.
    pub albedo: Tex<Vec3>,
    pub roughness: Tex<f32>,
    /// 1: the radiogs model; 0: Lambert only (tests).
    pub specular: f32,
}

#[derive(Clone, Debug, Serialize)]
pub struct Object {
    pub name: String,
    /// Description for README.json (type and parameters).
    pub shape: serde_json::Value,
    pub material: usize,
    /// Object frame for texture coordinates: p_local = rotation_inv · (p − origin).
    pub origin: Vec3,
    #[serde(skip)]
    pub rotation_inv: Mat3,
}

#[derive(Clone, Debug, Serialize)]
pub struct CameraRig {
    pub radius: f32,
    pub elev_min: f32,
    pub elev_max: f32,
    pub az_min: f32,
    pub az_max: f32,
    pub target: Vec3,
    pub camera_angle_x: f32,
}

pub struct Scene {
    pub name: String,
    pub shapes: Vec<Shape>,
    /// Object of each primitive.
    pub prim_object: Vec<u32>,
    pub objects: Vec<Object>,
    pub materials: Vec<Material>,
    pub rig: CameraRig,
    pub bvh: Bvh,
}

/// Everything the integrator needs at a surface hit.
#[derive(Clone, Copy, Debug)]
pub struct SurfaceHit {
    pub t: f32,
    pub p: Vec3,
    /// Geometric normal, facing the incoming ray.
    pub ng: Vec3,
    /// Shading normal, on the same side as ng.
    pub ns: Vec3,
    pub bsdf: Bsdf,
}

/// Ray-origin offset along the geometric normal (scene scale ~1).
pub const EPS: f32 = 1e-4;

impl Scene {
    pub fn new(name: &str, rig: CameraRig) -> Scene {
        Scene {
            name: name.into(),
            shapes: vec![],
            prim_object: vec![],
            objects: vec![],
            materials: vec![],
            rig,
            bvh: Bvh::build(&[]),
        }
    }

    pub fn add_material(&mut self, m: Material) -> usize {
        self.materials.push(m);
        self.materials.len() - 1
    }

    pub fn add_object(&mut self, obj: Object, shapes: Vec<Shape>) {
        let id = self.objects.len() as u32;
        self.objects.push(obj);
        self.prim_object.extend(std::iter::repeat_n(id, shapes.len()));
        self.shapes.extend(shapes);
    }

    /// Build the BVH; call after adding every object.
    pub fn finish(mut self) -> Scene {
        self.bvh = Bvh::build(&self.shapes);
        self
    }

    pub fn intersect(&self, ray: &Ray, t_max: f32) -> Option<SurfaceHit> {
        let (pi, h) = self.bvh.intersect(&self.shapes, ray, EPS, t_max)?;
        let shape = &self.shapes[pi as usize];
        let (ng, mut ns) = shape.normals(ray, &h);
        let p = ray.o + h.t * ray.d;
        // A shading normal that puts the viewer below its horizon falls back to the geometric one.
        if ns.dot(-ray.d) <= 1e-4 {
            ns = ng;
        }
        let obj = &self.objects[self.prim_object[pi as usize] as usize];
        let m = &self.materials[obj.material];
        let local = obj.rotation_inv * (p - obj.origin);
        let bsdf = Bsdf { albedo: m.albedo.eval(local), roughness: m.roughness.eval(local), specular: m.specular };
        Some(SurfaceHit { t: h.t, p, ng, ns, bsdf })
    }

    pub fn occluded(&self, o: Vec3, d: Vec3, t_max: f32) -> bool {
        self.bvh.occluded(&self.shapes, &Ray { o, d }, EPS, t_max)
    }
}

fn obj(name: &str, shape: serde_json::Value, material: usize, origin: Vec3) -> Object {
    Object { name: name.into(), shape, material, origin, rotation_inv: Mat3::IDENTITY }
}

fn mat(name: &str, albedo: Tex<Vec3>, roughness: Tex<f32>) -> Material {
    Material { name: name.into(), albedo, roughness, specular: 1.0 }
}

fn c(v: f32) -> Tex<f32> {
    Tex::Constant { value: v }
}
fn rgb(r: f32, g: f32, b: f32) -> Tex<Vec3> {
    Tex::Constant { value: Vec3::new(r, g, b) }
}

fn sphere(s: &mut Scene, name: &str, material: usize, center: Vec3, radius: f32) {
    s.add_object(
        obj(name, serde_json::json!({"type": "sphere", "center": center, "radius": radius}), material, center),
        vec![Shape::Sphere { center, radius }],
    );
}

fn aabox(s: &mut Scene, name: &str, material: usize, min: Vec3, max: Vec3) {
    s.add_object(
        obj(name, serde_json::json!({"type": "box", "min": min, "max": max}), material, 0.5 * (min + max)),
        vec![Shape::Box { min, max }],
    );
}

fn disc(s: &mut Scene, name: &str, material: usize, center: Vec3, radius: f32) {
    s.add_object(
        obj(
            name,
            serde_json::json!({"type": "disc", "center": center, "normal": [0, 0, 1], "radius": radius}),
            material,
            center,
        ),
        vec![Shape::Disc { center, normal: Vec3::Z, radius }],
    );
}

/// A box of half-extents `half` turned by `yaw` radians about the vertical axis through
/// `center`, as 12 flat triangles wound counter-clockwise seen from outside.
fn turned_box(s: &mut Scene, name: &str, material: usize, center: Vec3, half: Vec3, yaw: f32) {
    let rot = Mat3::from_rotation_z(yaw);
    let mut tris = Vec::with_capacity(12);
    for axis in 0..3 {
        for sign in [1.0f32, -1.0] {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let corner = |du: f32, dv: f32| {
                let mut c = Vec3::ZERO;
                c[axis] = sign * half[axis];
                c[u] = du * half[u];
                c[v] = dv * half[v];
                rot * c + center
            };
            let mut face_normal = Vec3::ZERO;
            face_normal[axis] = sign;
            let n = rot * face_normal;
            let (a, mut b, c, mut d) = (corner(-1.0, -1.0), corner(1.0, -1.0), corner(1.0, 1.0), corner(-1.0, 1.0));
            if (b - a).cross(c - a).dot(n) < 0.0 {
                std::mem::swap(&mut b, &mut d);
            }
            tris.push(Shape::Triangle { v: [a, b, c], n: [n; 3] });
            tris.push(Shape::Triangle { v: [a, c, d], n: [n; 3] });
        }
    }
    let shape = serde_json::json!({"type": "box", "center": center, "half_extents": half, "rotation_z": yaw});
    let mut o = obj(name, shape, material, center);
    o.rotation_inv = rot.transpose();
    s.add_object(o, tris);
}

/// A torus (major radius big_r about the local z axis, tube radius r) as `nu × nv` quads split
/// into triangles with analytic vertex normals, rotated by `rot` and moved to `center`.
pub fn torus_mesh(big_r: f32, r: f32, nu: usize, nv: usize, rot: Mat3, center: Vec3) -> Vec<Shape> {
    let vert = |i: usize, j: usize| -> (Vec3, Vec3) {
        let u = (i % nu) as f32 / nu as f32 * 2.0 * PI;
        let v = (j % nv) as f32 / nv as f32 * 2.0 * PI;
        let n = Vec3::new(v.cos() * u.cos(), v.cos() * u.sin(), v.sin());
        let p = Vec3::new(big_r * u.cos(), big_r * u.sin(), 0.0) + r * n;
        (rot * p + center, (rot * n).normalize())
    };
    let mut tris = Vec::with_capacity(nu * nv * 2);
    for i in 0..nu {
        for j in 0..nv {
            let (p00, n00) = vert(i, j);
            let (p10, n10) = vert(i + 1, j);
            let (p01, n01) = vert(i, j + 1);
            let (p11, n11) = vert(i + 1, j + 1);
            // Counter-clockwise seen from outside: the winding normal points outward.
            tris.push(Shape::Triangle { v: [p00, p10, p11], n: [n00, n10, n11] });
            tris.push(Shape::Triangle { v: [p00, p11, p01], n: [n00, n11, n01] });
        }
    }
    tris
}

/// The camera band of `../shared/data` (radius 4, fov 0.6911503672599792 rad).
const FOV: f32 = 0.691_150_4;

/// The shared data's camera band: radius 4 about (0, 0, target_z), elevation and azimuth
/// ranges in degrees.
fn band(elevation: (f32, f32), azimuth: (f32, f32), target_z: f32) -> CameraRig {
    CameraRig {
        radius: 4.0,
        elev_min: elevation.0,
        elev_max: elevation.1,
        az_min: azimuth.0,
        az_max: azimuth.1,
        target: Vec3::new(0.0, 0.0, target_z),
        camera_angle_x: FOV,
    }
}

pub const SCENES: [&str; 4] = ["spheres", "box", "torus", "cornell"];

pub fn build(name: &str) -> Option<Scene> {
    Some(match name {
        "spheres" => spheres(),
        "box" => open_box(),
        "torus" => torus(),
        "cornell" => cornell(),
        _ => return None,
    })
}

fn checker_floor(s: &mut Scene) -> usize {
    s.add_material(mat(
        "floor_checker",
        Tex::Checker { a: Vec3::new(0.8, 0.8, 0.8), b: Vec3::new(0.4, 0.4, 0.46), scale: 4.0 },
        Tex::Stripes { a: 0.35, b: 0.75, frequency: 3.0, axis: Vec3::X },
    ))
}

fn spheres() -> Scene {
    let rig = band((10.0, 80.0), (-180.0, 180.0), 0.25);
    let mut s = Scene::new("spheres", rig);
    let floor = checker_floor(&mut s);
    disc(&mut s, "floor_disc", floor, Vec3::ZERO, 1.3);
    let m = s.add_material(mat("red_glossy", rgb(0.7, 0.08, 0.06), c(0.1)));
    sphere(&mut s, "red_glossy", m, Vec3::new(-0.36, -0.22, 0.38), 0.38);
    let m = s.add_material(mat("green_rough", rgb(0.1, 0.55, 0.12), c(0.6)));
    sphere(&mut s, "green_rough", m, Vec3::new(0.34, -0.24, 0.32), 0.32);
    let m = s.add_material(mat("blue_mid", rgb(0.08, 0.15, 0.65), c(0.3)));
    sphere(&mut s, "blue_mid", m, Vec3::new(0.02, 0.38, 0.42), 0.42);
    let m = s.add_material(mat("white_glossy", rgb(0.8, 0.8, 0.8), c(0.05)));
    sphere(&mut s, "white_glossy", m, Vec3::new(0.52, 0.40, 0.22), 0.22);
    let m = s.add_material(mat(
        "yellow_striped",
        Tex::Stripes { a: Vec3::new(0.8, 0.65, 0.1), b: Vec3::new(0.2, 0.3, 0.7), frequency: 8.0, axis: Vec3::Z },
        Tex::Stripes { a: 0.9, b: 0.4, frequency: 8.0, axis: Vec3::Z },
    ));
    sphere(&mut s, "yellow_striped", m, Vec3::new(-0.56, 0.42, 0.25), 0.25);
    s.finish()
}

fn open_box() -> Scene {
    let rig = band((35.0, 80.0), (-180.0, 180.0), 0.3);
    let mut s = Scene::new("box", rig);
    let (h, w, t) = (0.8f32, 0.7f32, 0.05f32);
    let floor = s.add_material(mat(
        "box_floor",
        Tex::Checker { a: Vec3::new(0.75, 0.75, 0.72), b: Vec3::new(0.3, 0.3, 0.35), scale: 3.0 },
        c(0.6),
    ));
    aabox(&mut s, "floor", floor, Vec3::new(-w - t, -w - t, -t), Vec3::new(w + t, w + t, 0.0));
    let red = s.add_material(mat("wall_red", rgb(0.7, 0.1, 0.08), c(0.5)));
    let green = s.add_material(mat("wall_green", rgb(0.1, 0.6, 0.12), c(0.5)));
    let white = s.add_material(mat(
        "wall_white_striped",
        Tex::Stripes { a: Vec3::new(0.75, 0.75, 0.75), b: Vec3::new(0.55, 0.5, 0.45), frequency: 6.0, axis: Vec3::Z },
        Tex::Stripes { a: 0.3, b: 0.8, frequency: 6.0, axis: Vec3::Z },
    ));
    aabox(&mut s, "wall_x_neg", red, Vec3::new(-w - t, -w - t, 0.0), Vec3::new(-w, w + t, h));
    aabox(&mut s, "wall_x_pos", green, Vec3::new(w, -w - t, 0.0), Vec3::new(w + t, w + t, h));
    aabox(&mut s, "wall_y_neg", white, Vec3::new(-w, -w - t, 0.0), Vec3::new(w, -w, h));
    aabox(&mut s, "wall_y_pos", white, Vec3::new(-w, w, 0.0), Vec3::new(w, w + t, h));
    let glossy = s.add_material(mat("glossy_blue", rgb(0.15, 0.25, 0.7), c(0.15)));
    sphere(&mut s, "glossy_sphere", glossy, Vec3::new(0.15, 0.15, 0.3), 0.3);
    let orange = s.add_material(mat("orange_block", rgb(0.8, 0.4, 0.1), c(0.4)));
    aabox(&mut s, "block", orange, Vec3::new(-0.45, -0.4, 0.0), Vec3::new(-0.15, -0.1, 0.35));
    s.finish()
}

/// `../shared/data/cornell` as its README.json describes it: a box open at the front (−y) and
/// the top, 50 mm walls, a glossy sphere, a turned tall block and a small blue sphere; cameras
/// in front of the opening. The materials are the radiogs model's (not Principled BSDF).
fn cornell() -> Scene {
    let rig = band((20.0, 75.0), (-140.0, -40.0), 0.35);
    let mut s = Scene::new("cornell", rig);
    let white = s.add_material(mat("white_wall", rgb(0.73, 0.73, 0.7), c(0.8)));
    let red = s.add_material(mat("red_wall", rgb(0.63, 0.06, 0.05), c(0.8)));
    let green = s.add_material(mat("green_wall", rgb(0.12, 0.45, 0.09), c(0.8)));
    let glossy = s.add_material(mat("glossy_sphere", rgb(0.85, 0.8, 0.7), c(0.08)));
    let block = s.add_material(mat("tall_block", rgb(0.6, 0.6, 0.62), c(0.45)));
    let blue = s.add_material(mat("blue_glossy_small", rgb(0.1, 0.2, 0.7), c(0.2)));
    let slab = |s: &mut Scene, name: &str, m: usize, centre: [f32; 3], half: [f32; 3]| {
        let (centre, half) = (Vec3::from(centre), Vec3::from(half));
        aabox(s, name, m, centre - half, centre + half);
    };
    slab(&mut s, "floor", white, [0.0, 0.0, -0.025], [1.05, 1.05, 0.025]);
    slab(&mut s, "back_wall", white, [0.0, 1.025, 0.5], [1.05, 0.025, 0.5]);
    slab(&mut s, "left_wall_red", red, [-1.025, 0.0, 0.5], [0.025, 1.0, 0.5]);
    slab(&mut s, "right_wall_green", green, [1.025, 0.0, 0.5], [0.025, 1.0, 0.5]);
    sphere(&mut s, "glossy_sphere", glossy, Vec3::new(0.38, -0.25, 0.33), 0.33);
    turned_box(
        &mut s,
        "tall_block",
        block,
        Vec3::new(-0.35, 0.3, 0.45),
        Vec3::new(0.25, 0.25, 0.45),
        20f32.to_radians(),
    );
    sphere(&mut s, "blue_glossy_small", blue, Vec3::new(-0.55, -0.5, 0.16), 0.16);
    s.finish()
}

fn torus() -> Scene {
    let rig = band((10.0, 80.0), (-180.0, 180.0), 0.35);
    let mut s = Scene::new("torus", rig);
    let floor = checker_floor(&mut s);
    disc(&mut s, "floor_disc", floor, Vec3::ZERO, 1.3);
    let m = s.add_material(mat(
        "torus_striped",
        Tex::Stripes { a: Vec3::new(0.8, 0.55, 0.15), b: Vec3::new(0.15, 0.35, 0.7), frequency: 5.0, axis: Vec3::X },
        Tex::Stripes { a: 0.2, b: 0.55, frequency: 5.0, axis: Vec3::X },
    ));
    let (big_r, r) = (0.45f32, 0.17f32);
    let rot = Mat3::from_rotation_x(55f32.to_radians());
    let center = Vec3::new(0.0, 0.0, 0.55);
    let (nu, nv) = (72, 32);
    let mut o = obj(
        "torus",
        serde_json::json!({"type": "triangle_mesh", "procedural": "torus", "major_radius": big_r, "minor_radius": r,
            "segments": [nu, nv], "triangles": 2 * nu * nv, "rotation_x_deg": 55.0, "center": center, "normals": "smooth (analytic vertex normals)"}),
        m,
        center,
    );
    o.rotation_inv = rot.transpose();
    s.add_object(o, torus_mesh(big_r, r, nu, nv, rot, center));
    let m = s.add_material(mat("white_glossy", rgb(0.8, 0.8, 0.8), c(0.08)));
    sphere(&mut s, "white_glossy", m, Vec3::new(0.6, -0.5, 0.2), 0.2);
    let m = s.add_material(mat("red_rough", rgb(0.7, 0.12, 0.1), c(0.7)));
    sphere(&mut s, "red_rough", m, Vec3::new(-0.6, 0.45, 0.22), 0.22);
    s.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cornell_block_is_a_closed_turned_box_wound_outward() {
        let s = build("cornell").unwrap();
        let k = s.objects.iter().position(|o| o.name == "tall_block").unwrap();
        let (centre, half, yaw) = (Vec3::new(-0.35, 0.3, 0.45), Vec3::new(0.25, 0.25, 0.45), 20f32.to_radians());
        let tris: Vec<&Shape> =
            s.shapes.iter().zip(&s.prim_object).filter(|(_, o)| **o == k as u32).map(|(t, _)| t).collect();
        assert_eq!(tris.len(), 12);
        for tri in &tris {
            let Shape::Triangle { v, n } = tri else { panic!("the block is a mesh") };
            let ng = (v[1] - v[0]).cross(v[2] - v[0]).normalize();
            let cen = (v[0] + v[1] + v[2]) / 3.0;
            assert!(ng.dot(cen - centre) > 0.0, "winding faces inward");
            assert!(n.iter().all(|m| m.dot(ng) > 0.999));
        }
        // Rays from just outside each side face (not the bottom: the floor is there) towards
        // the centre hit the face's centre, on the face turned by the yaw.
        let rot = Mat3::from_rotation_z(yaw);
        for local in [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z] {
            let face = centre + rot * (local * half);
            let out = rot * local;
            let o = face + 0.05 * out;
            let hit = s.intersect(&Ray { o, d: -out }, 10.0).expect("the block is hit");
            assert!((hit.p - face).length() < 1e-4, "{local}: hit at {} not {}", hit.p, face);
            assert!(hit.ng.dot(out) > 0.999);
        }
    }

    #[test]
    fn textures_and_torus_mesh() {
        let t = Tex::Checker { a: 1.0f32, b: 2.0, scale: 4.0 };
        assert_eq!(t.eval(Vec3::new(0.1, 0.1, 0.0)), 1.0);
        assert_eq!(t.eval(Vec3::new(0.3, 0.1, 0.0)), 2.0);
        assert_eq!(t.eval(Vec3::new(0.3, 0.1, -1e-7)), 2.0, "stable across a plane at z = 0");
        let st = Tex::Stripes { a: 0.0f32, b: 1.0, frequency: 2.0, axis: Vec3::Z };
        assert_eq!(st.eval(Vec3::new(0.0, 0.0, 0.1)), 0.0);
        assert_eq!(st.eval(Vec3::new(5.0, 0.0, 0.5)), 1.0);
        // Every torus triangle's winding normal points away from the tube's core circle.
        let tris = torus_mesh(1.0, 0.3, 24, 12, Mat3::IDENTITY, Vec3::ZERO);
        assert_eq!(tris.len(), 24 * 12 * 2);
        for tri in &tris {
            if let Shape::Triangle { v, n } = tri {
                let ng = (v[1] - v[0]).cross(v[2] - v[0]).normalize();
                let cen = (v[0] + v[1] + v[2]) / 3.0;
                let core = Vec3::new(cen.x, cen.y, 0.0).normalize();
                assert!(ng.dot(cen - core) > 0.0);
                assert!(n.iter().all(|k| k.dot(ng) > 0.5));
            }
        }
        for name in SCENES {
            let s = build(name).unwrap();
            assert!(s.bvh.node_count() > 0 && !s.objects.is_empty());
            assert!(s.materials.iter().all(|m| m.specular == 1.0));
        }
    }
}
