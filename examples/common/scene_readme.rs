//! The object list of a Blender-Cycles dataset's `README.json` (as in `../shared/data`): shapes,
//! transforms and Principled materials, with signed distances and ray hits for the diagnostics.
//! Only rotations about z occur in these scenes; anything else is refused with a clear error.
//! Included by two example binaries, each using part of it.
#![allow(dead_code)]

use anyhow::{Context, bail};
use serde::Deserialize;
use std::collections::HashMap;
use std::path::Path;

#[derive(Deserialize)]
pub struct SceneReadme {
    pub objects: Vec<Object>,
    pub materials: HashMap<String, Material>,
    pub environment: Environment,
}

#[derive(Deserialize)]
pub struct Environment {
    pub train_env: String,
}

#[derive(Deserialize)]
pub struct Object {
    pub object: String,
    #[serde(rename = "type")]
    pub kind: String,
    pub location: [f64; 3],
    pub rotation_euler: [f64; 3],
    pub params: Params,
    pub material: String,
}

#[derive(Deserialize)]
pub struct Params {
    pub radius: Option<f64>,
    pub depth: Option<f64>,
    pub half_extents: Option<[f64; 3]>,
}

#[derive(Deserialize)]
pub struct Material {
    pub roughness: f64,
    pub base_color_linear: BaseColor,
}

#[derive(Deserialize)]
#[serde(untagged)]
pub enum BaseColor {
    Rgb([f64; 3]),
    Checker { checker_object_space: Checker },
}

#[derive(Deserialize)]
pub struct Checker {
    pub color1: [f64; 3],
    pub color2: [f64; 3],
    pub scale: f64,
}

#[derive(Clone, Copy)]
pub enum Shape {
    Sphere { radius: f64 },
    Cuboid { half: [f64; 3] },
    Cylinder { radius: f64, half_depth: f64 },
}

/// Read and check `DATA/README.json`: every object has a known shape with its parameters, a
/// rotation about z only, and a material in the list.
pub fn load(data: &Path) -> anyhow::Result<SceneReadme> {
    let path = data.join("README.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("{}: cannot read", path.display()))?;
    let readme: SceneReadme = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a scene README (objects, materials)", path.display()))?;
    for o in &readme.objects {
        o.shape().with_context(|| format!("{}: object {}", path.display(), o.object))?;
        if o.rotation_euler[0] != 0.0 || o.rotation_euler[1] != 0.0 {
            bail!("{}: object {}: only rotations about z are handled", path.display(), o.object);
        }
        if !readme.materials.contains_key(&o.material) {
            bail!("{}: object {}: material {} is not in `materials`", path.display(), o.object, o.material);
        }
    }
    Ok(readme)
}

impl Object {
    pub fn shape(&self) -> anyhow::Result<Shape> {
        let p = &self.params;
        Ok(match self.kind.as_str() {
            "uv_sphere" => Shape::Sphere { radius: p.radius.context("params.radius missing")? },
            "box" => Shape::Cuboid { half: p.half_extents.context("params.half_extents missing")? },
            "cylinder" => Shape::Cylinder {
                radius: p.radius.context("params.radius missing")?,
                half_depth: 0.5 * p.depth.context("params.depth missing")?,
            },
            other => bail!("type {other} is not handled (uv_sphere, box, cylinder)"),
        })
    }

    /// A world point or direction in the object's frame (translation only for points).
    fn local(&self, v: [f64; 3], point: bool) -> [f64; 3] {
        let d = if point { [v[0] - self.location[0], v[1] - self.location[1], v[2] - self.location[2]] } else { v };
        let (s, c) = self.rotation_euler[2].sin_cos();
        [c * d[0] + s * d[1], -s * d[0] + c * d[1], d[2]]
    }

    /// Signed distance of world point p to the surface (checked by `load`).
    pub fn sdf(&self, p: [f64; 3]) -> f64 {
        let q = self.local(p, true);
        let len2 = |a: f64, b: f64| (a.max(0.0).powi(2) + b.max(0.0).powi(2)).sqrt();
        match self.shape().expect("checked by load") {
            Shape::Sphere { radius } => (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt() - radius,
            Shape::Cuboid { half } => {
                let e = [q[0].abs() - half[0], q[1].abs() - half[1], q[2].abs() - half[2]];
                (len2(e[0], e[1]).powi(2) + e[2].max(0.0).powi(2)).sqrt() + e[0].max(e[1]).max(e[2]).min(0.0)
            }
            Shape::Cylinder { radius, half_depth } => {
                let e = [(q[0] * q[0] + q[1] * q[1]).sqrt() - radius, q[2].abs() - half_depth];
                len2(e[0], e[1]) + e[0].max(e[1]).min(0.0)
            }
        }
    }

    /// Distance t > 0 along the ray o + t·d where it enters the solid; None if it misses or
    /// starts inside.
    pub fn ray_entry(&self, o: [f64; 3], d: [f64; 3]) -> Option<f64> {
        let (ro, rd) = (self.local(o, true), self.local(d, false));
        // Slab entry/exit over the axes the shape bounds by planes.
        let slabs = |axes: &[(usize, f64)], mut t0: f64, mut t1: f64| {
            for &(a, h) in axes {
                let inv = 1.0 / rd[a];
                let (ta, tb) = ((-h - ro[a]) * inv, (h - ro[a]) * inv);
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
            (t0, t1)
        };
        let (t0, t1) = match self.shape().expect("checked by load") {
            Shape::Sphere { radius } => {
                let b = ro[0] * rd[0] + ro[1] * rd[1] + ro[2] * rd[2];
                let a = rd[0] * rd[0] + rd[1] * rd[1] + rd[2] * rd[2];
                let c = ro[0] * ro[0] + ro[1] * ro[1] + ro[2] * ro[2] - radius * radius;
                let disc = b * b - a * c;
                if disc < 0.0 {
                    return None;
                }
                ((-b - disc.sqrt()) / a, (-b + disc.sqrt()) / a)
            }
            Shape::Cuboid { half } => {
                slabs(&[(0, half[0]), (1, half[1]), (2, half[2])], f64::NEG_INFINITY, f64::INFINITY)
            }
            Shape::Cylinder { radius, half_depth } => {
                let a = rd[0] * rd[0] + rd[1] * rd[1];
                let b = ro[0] * rd[0] + ro[1] * rd[1];
                let c = ro[0] * ro[0] + ro[1] * ro[1] - radius * radius;
                let (c0, c1) = if a == 0.0 {
                    if c > 0.0 {
                        return None;
                    }
                    (f64::NEG_INFINITY, f64::INFINITY)
                } else {
                    let disc = b * b - a * c;
                    if disc < 0.0 {
                        return None;
                    }
                    ((-b - disc.sqrt()) / a, (-b + disc.sqrt()) / a)
                };
                slabs(&[(2, half_depth)], c0, c1)
            }
        };
        (t0 <= t1 && t0 > 0.0).then_some(t0)
    }

    /// Base colour (linear) of this object's material at world point p: the Blender checker
    /// texture on object coordinates evaluated like Cycles (|floor| parity per axis).
    /// Whether the material's base colour varies over the surface (a checker).
    pub fn textured(&self, material: &Material) -> bool {
        matches!(material.base_color_linear, BaseColor::Checker { .. })
    }

    pub fn base_colour(&self, material: &Material, p: [f64; 3]) -> [f64; 3] {
        match &material.base_color_linear {
            BaseColor::Rgb(c) => *c,
            BaseColor::Checker { checker_object_space: ch } => {
                let q = [p[0] - self.location[0], p[1] - self.location[1], p[2] - self.location[2]];
                let cell = |c: f64| (((c + 1e-6) * 0.999_999 * ch.scale).floor() as i64).abs() % 2;
                let (xi, yi, zi) = (cell(q[0]), cell(q[1]), cell(q[2]));
                if (xi == yi) == (zi == 1) { ch.color1 } else { ch.color2 }
            }
        }
    }
}

/// The object whose surface is nearest to p (the list is non-empty: checked by the caller).
pub fn nearest(objects: &[Object], p: [f64; 3]) -> usize {
    (0..objects.len()).min_by(|&a, &b| objects[a].sdf(p).abs().total_cmp(&objects[b].sdf(p).abs())).unwrap_or(0)
}
