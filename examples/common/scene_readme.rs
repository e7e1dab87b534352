//! The object list of a Blender-Cycles dataset's `README.json` (as in `../shared/data`) or of a
//! `radiogs synth` scene's: shapes, transforms and Principled materials, with signed distances
//! and ray hits for the diagnostics.
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
    /// The training map's file relative to the dataset (`radiogs synth` names it); None: the
    /// Cycles datasets' `envmaps/{train_env}.exr`.
    #[serde(default)]
    pub train_env_file: Option<String>,
}

impl SceneReadme {
    /// The training light's map file.
    pub fn train_env_path(&self, data: &Path) -> std::path::PathBuf {
        match &self.environment.train_env_file {
            Some(f) => data.join(f),
            None => data.join("envmaps").join(format!("{}.exr", self.environment.train_env)),
        }
    }
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
    let readme: SceneReadme = match serde_json::from_str(&text) {
        Ok(r) => r,
        Err(cycles_err) => from_synth(&text).map_err(|synth_err| {
            anyhow::anyhow!(
                "{}: not a scene README (Cycles layout: {cycles_err}; radiogs synth layout: {synth_err})",
                path.display()
            )
        })?,
    };
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

/// A `radiogs synth` README.json in this module's terms: spheres as they are, the disc floor as
/// a 20 mm cylinder whose top is the disc, boxes by centre, half extents and z rotation. Each
/// material's base colour is its constant or first checker/stripe colour (the probes that read
/// colours need Cycles' checker; the geometry is what the synthetic scenes are used for).
fn from_synth(text: &str) -> anyhow::Result<SceneReadme> {
    use serde_json::Value;
    let v: Value = serde_json::from_str(text)?;
    let f = |x: &Value| x.as_f64().context("not a number");
    let v3 = |x: &Value| -> anyhow::Result<[f64; 3]> {
        let a = x.as_array().filter(|a| a.len() == 3).context("not a 3-vector")?;
        Ok([f(&a[0])?, f(&a[1])?, f(&a[2])?])
    };
    let mats = v["materials"].as_array().context("materials: not a list")?;
    let mut materials = HashMap::new();
    let mut names = Vec::new();
    for m in mats {
        let name = m["name"].as_str().context("material without a name")?.to_string();
        let colour = if m["albedo"]["value"].is_array() { v3(&m["albedo"]["value"])? } else { v3(&m["albedo"]["a"])? };
        let rough = &m["roughness"];
        let roughness = if rough["value"].is_number() { f(&rough["value"])? } else { f(&rough["a"])? };
        materials.insert(name.clone(), Material { roughness, base_color_linear: BaseColor::Rgb(colour) });
        names.push(name);
    }
    let mut objects = Vec::new();
    for o in v["objects"].as_array().context("objects: not a list")? {
        let name = o["name"].as_str().context("object without a name")?.to_string();
        let material = names.get(o["material"].as_u64().context("material: not an index")? as usize).cloned();
        let material = material.with_context(|| format!("object {name}: material index out of range"))?;
        let sh = &o["shape"];
        let none = Params { radius: None, depth: None, half_extents: None };
        let (kind, location, rz, params) = match sh["type"].as_str() {
            Some("sphere") => {
                ("uv_sphere", v3(&sh["center"])?, 0.0, Params { radius: Some(f(&sh["radius"])?), ..none })
            }
            Some("disc") => {
                if v3(&sh["normal"])? != [0.0, 0.0, 1.0] {
                    bail!("object {name}: only discs facing +z are handled");
                }
                let c = v3(&sh["center"])?;
                (
                    "cylinder",
                    [c[0], c[1], c[2] - 0.01],
                    0.0,
                    Params { radius: Some(f(&sh["radius"])?), depth: Some(0.02), ..none },
                )
            }
            Some("box") if sh["min"].is_array() => {
                let (lo, hi) = (v3(&sh["min"])?, v3(&sh["max"])?);
                let c = [0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k]));
                ("box", c, 0.0, Params { half_extents: Some([0, 1, 2].map(|k| 0.5 * (hi[k] - lo[k]))), ..none })
            }
            Some("box") => {
                let rz = if sh["rotation_z"].is_number() { f(&sh["rotation_z"])? } else { 0.0 };
                ("box", v3(&sh["center"])?, rz, Params { half_extents: Some(v3(&sh["half_extents"])?), ..none })
            }
            other => bail!("object {name}: shape {other:?} is not handled (sphere, disc, box)"),
        };
        objects.push(Object {
            object: name,
            kind: kind.into(),
            location,
            rotation_euler: [0.0, 0.0, rz],
            params,
            material,
        });
    }
    let env = &v["environment"];
    let train_env = env["train_env"].as_str().context("environment.train_env missing")?.to_string();
    let file = env["files"][&train_env].as_str().with_context(|| format!("environment.files.{train_env} missing"))?;
    Ok(SceneReadme {
        objects,
        materials,
        environment: Environment { train_env_file: Some(file.to_string()), train_env },
    })
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

/// The foot point on object `k`'s true surface of a point `p` whose nearest object is `k`,
/// within 15 mm of it, where that surface faces up (its normal's z > 0.7); else None.
pub fn foot_on_upward_face(objects: &[Object], k: usize, p: [f64; 3]) -> Option<[f64; 3]> {
    if nearest(objects, p) != k {
        return None;
    }
    let o = &objects[k];
    let d = o.sdf(p);
    let e = 1e-4;
    let up = (o.sdf([p[0], p[1], p[2] + e]) - d) / e;
    (d.abs() <= 0.015 && up >= 0.7).then_some([p[0], p[1], p[2] - d])
}
