//! Datasets of posed RGBA images in the two layouts users bring:
//! - Blender/NeRF-synthetic: `transforms_{train,test}.json` with `camera_angle_x` and frames of
//!   `file_path` (extension optional) + `transform_matrix` (camera-to-world, OpenGL axes);
//! - TensoIR: per-view folders `train_XXX/`, `test_XXX/` with `metadata.json`
//!   (`cam_transform_mat` row-major, `cam_angle_x`, `imh`, `imw`) and `rgba.png`, plus GT passes
//!   (`albedo.png`, `normal.png|exr`, `roughness.png`, `indirect.exr`, `rgba_<light>.png`) and env
//!   maps in `envmaps/`.
//! When both exist the transforms files give the cameras; GT passes are found in the folder of
//! each view's image. Images load lazily and in parallel.

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::io::image::{Image, check_image, image_dimensions, read_rgba};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    Blender,
    TensoIR,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Split {
    Train,
    Test,
}

impl Split {
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
        }
    }
}

/// One posed view: its camera, its image file and the folder holding its GT passes.
#[derive(Clone, Debug)]
pub struct View {
    /// The camera at the resolution images are loaded at (the files' size / `downscale`).
    pub camera: Camera,
    pub image_path: PathBuf,
    pub folder: PathBuf,
    /// Size of the image files, which every file of the view must have.
    pub file_size: (u32, u32),
    /// Images and passes load shrunk by this factor (`Image::downscale`; 1 = as stored).
    pub downscale: u32,
}

/// Ground-truth passes a view may have (each present only if its file exists).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pass {
    Albedo,
    Normal,
    Roughness,
    Indirect,
    Depth,
}

impl Pass {
    pub const ALL: [Pass; 5] = [Pass::Albedo, Pass::Normal, Pass::Roughness, Pass::Indirect, Pass::Depth];
    pub fn name(self) -> &'static str {
        match self {
            Pass::Albedo => "albedo",
            Pass::Normal => "normal",
            Pass::Roughness => "roughness",
            Pass::Indirect => "indirect",
            Pass::Depth => "depth",
        }
    }
    /// File names tried in order (float first where both exist).
    fn candidates(self) -> &'static [&'static str] {
        match self {
            Pass::Albedo => &["albedo.png"],
            Pass::Normal => &["normal.exr", "normal.png"],
            Pass::Roughness => &["roughness.png"],
            Pass::Indirect => &["indirect.exr"],
            Pass::Depth => &["depth.exr"],
        }
    }
}

impl View {
    pub fn pass_path(&self, pass: Pass) -> Option<PathBuf> {
        pass.candidates().iter().map(|f| self.folder.join(f)).find(|p| p.is_file())
    }

    /// Load a GT pass as RGBA float. Normals from PNG are decoded to [−1, 1]; albedo and
    /// roughness stay as stored (sRGB-encoded albedo, linear roughness).
    pub fn load_pass(&self, pass: Pass) -> Result<Option<Image>> {
        let Some(path) = self.pass_path(pass) else { return Ok(None) };
        let mut img = self.load_file(&path)?;
        if pass == Pass::Normal {
            if path.extension().is_some_and(|e| e == "png") {
                img.map_channels(3, |v| v * 2.0 - 1.0);
            }
            // A block's mean normal is shorter than 1: unit again.
            if self.downscale > 1 {
                let c = img.channels;
                for px in img.data.chunks_exact_mut(c) {
                    let n = &mut px[..3.min(c)];
                    let len = n.iter().map(|v| v * v).sum::<f32>().sqrt();
                    if len > 1e-12 {
                        n.iter_mut().for_each(|v| *v /= len);
                    }
                }
            }
        }
        Ok(Some(img))
    }

    /// Path of the image relit under env `name` (`rgba_<name>.png`), if present.
    pub fn relit_path(&self, name: &str) -> Option<PathBuf> {
        let p = self.folder.join(format!("rgba_{name}.png"));
        p.is_file().then_some(p)
    }

    /// The image relit under env `name`, if present (at the camera's resolution).
    pub fn load_relit(&self, name: &str) -> Result<Option<Image>> {
        self.relit_path(name).map(|p| self.load_file(&p)).transpose()
    }

    pub fn load_image(&self) -> Result<Image> {
        self.load_file(&self.image_path)
    }

    /// Decode the view's image in full and check its size, keeping nothing: a truncated or
    /// corrupt file is found before a run folder is written, not when the images load.
    pub fn check_image(&self) -> Result<()> {
        let size = check_image(&self.image_path)?;
        self.check_size(&self.image_path, size)
    }

    fn check_size(&self, path: &Path, (width, height): (u32, u32)) -> Result<()> {
        let (w, h) = self.file_size;
        if width != w || height != h {
            return Err(Error::format(path, "size", format!("{width}×{height} but the camera says {w}×{h}")));
        }
        Ok(())
    }

    /// Read one of the view's files, check its size and shrink it to the camera's.
    fn load_file(&self, path: &Path) -> Result<Image> {
        let img = read_rgba(path)?;
        self.check_size(path, (img.width, img.height))?;
        Ok(img.downscale(self.downscale))
    }
}

#[derive(Clone, Debug)]
pub struct Dataset {
    pub root: PathBuf,
    pub layout: Layout,
    pub train: Vec<View>,
    pub test: Vec<View>,
    /// Env maps found in `envmaps/` as (name, path), sorted by name.
    pub envmaps: Vec<(String, PathBuf)>,
    /// Name of the env that lit the training images, when the dataset says.
    pub train_env: Option<String>,
}

fn read_json(path: &Path) -> Result<serde_json::Value> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| Error::format(path, "JSON", e.to_string()))
}

fn number(path: &Path, v: &serde_json::Value, field: &str) -> Result<f64> {
    let x = v.get(field).ok_or_else(|| Error::format(path, field, "missing"))?;
    let x = x.as_f64().ok_or_else(|| Error::format(path, field, "not a number"))?;
    if !x.is_finite() {
        return Err(Error::format(path, field, "not finite"));
    }
    Ok(x)
}

fn matrix_rows(path: &Path, field: &str, values: &[f64]) -> Result<[[f32; 4]; 4]> {
    if values.len() != 16 {
        return Err(Error::format(path, field, format!("{} values, expected 4 rows of 4 numbers", values.len())));
    }
    if values.iter().any(|v| !v.is_finite()) {
        return Err(Error::format(path, field, "a value is not finite"));
    }
    Ok(std::array::from_fn(|r| std::array::from_fn(|c| values[r * 4 + c] as f32)))
}

fn camera_error(path: &Path, field: &str, e: Error) -> Error {
    match e {
        Error::Invalid { reason, .. } => Error::format(path, field, reason),
        other => other,
    }
}

impl Dataset {
    /// Open a dataset folder (cameras only; images load later).
    pub fn open(root: &Path) -> Result<Dataset> {
        if root.is_file() {
            return Err(Error::invalid(
                root.display().to_string(),
                "is a file; --data takes the dataset folder (the one holding transforms_train.json or train_XXX/)",
            ));
        }
        if !root.is_dir() {
            return Err(Error::io(root, std::io::Error::new(std::io::ErrorKind::NotFound, "dataset folder not found")));
        }
        let has_transforms = root.join("transforms_train.json").is_file();
        let (layout, train, test) = if has_transforms {
            let train = read_transforms(root, &root.join("transforms_train.json"))?;
            let test_path = root.join("transforms_test.json");
            let test = if test_path.is_file() { read_transforms(root, &test_path)? } else { Vec::new() };
            (Layout::Blender, train, test)
        } else {
            let train = read_tensoir_split(root, Split::Train)?;
            let test = read_tensoir_split(root, Split::Test)?;
            if train.is_empty() {
                return Err(Error::format(
                    root,
                    "layout",
                    "neither transforms_train.json nor train_XXX/metadata.json folders found",
                ));
            }
            (Layout::TensoIR, train, test)
        };
        let mut envmaps = Vec::new();
        if let Ok(entries) = std::fs::read_dir(root.join("envmaps")) {
            for entry in entries.flatten() {
                let p = entry.path();
                let ext = p.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
                if ext == "exr" || ext == "hdr" {
                    let name = p.file_stem().unwrap_or_default().to_string_lossy().to_string();
                    envmaps.push((name, p));
                }
            }
        }
        envmaps.sort();
        // Every training image is there (only the first one's header was read): a missing file
        // stops here, before a run folder is written, not when the images load. (Test images
        // are needed by `eval` only, which says so when one is missing.)
        if let Some(v) = train.iter().find(|v| !v.image_path.is_file()) {
            return Err(Error::io(&v.image_path, std::io::Error::new(std::io::ErrorKind::NotFound, "image not found")));
        }
        let train_env = read_train_env(root);
        Ok(Dataset { root: root.to_path_buf(), layout, train, test, envmaps, train_env })
    }

    /// Below this many pixels on a side a downscaled view is warned about.
    pub const MIN_USEFUL_SIDE: u32 = 16;

    /// Open a dataset whose images load shrunk by `factor` (3DGS/2DGS's `-r 2|4|8`): cameras
    /// scaled to match, files checked at their stored size.
    pub fn open_downscaled(root: &Path, factor: u32) -> Result<Dataset> {
        let mut ds = Dataset::open(root)?;
        if factor == 0 {
            return Err(Error::invalid("resolution", "the downscale factor must be at least 1"));
        }
        for view in ds.train.iter_mut().chain(ds.test.iter_mut()) {
            let (w, h) = view.file_size;
            if w < factor || h < factor {
                return Err(Error::invalid(
                    "resolution",
                    format!("downscale factor {factor} leaves no pixel of the {w}×{h} view {}", view.camera.name),
                ));
            }
            view.camera = view.camera.downscaled(factor);
            view.downscale = factor;
        }
        // Legal but almost surely a slip (e.g. `-r 16` on small images): say so once.
        if factor > 1 {
            let smallest = ds.train.iter().chain(&ds.test).map(|v| v.camera.width.min(v.camera.height)).min();
            if let Some(side) = smallest.filter(|&side| side < Self::MIN_USEFUL_SIDE) {
                tracing::warn!(
                    "{}: -r {factor} shrinks views to {side} px on a side (fewer than {}): little to train or evaluate on",
                    root.display(),
                    Self::MIN_USEFUL_SIDE
                );
            }
        }
        Ok(ds)
    }

    pub fn views(&self, split: Split) -> &[View] {
        match split {
            Split::Train => &self.train,
            Split::Test => &self.test,
        }
    }

    /// Load every image of a split in parallel (RGBA, values as stored).
    pub fn load_images(&self, split: Split) -> Result<Vec<Image>> {
        self.views(split).par_iter().map(|v| v.load_image()).collect()
    }

    /// Decode every image of a split in parallel and check its size, keeping none (see
    /// [`View::check_image`]); the first bad file is the error.
    pub fn check_images(&self, split: Split) -> Result<()> {
        self.views(split).par_iter().try_for_each(|v| v.check_image())
    }

    /// GT passes found in the first test view (or train view if no test split).
    pub fn passes_found(&self) -> Vec<Pass> {
        let Some(view) = self.test.first().or(self.train.first()) else { return Vec::new() };
        Pass::ALL.into_iter().filter(|p| view.pass_path(*p).is_some()).collect()
    }

    /// Names of relit images present in the first test view (rgba_<name>.png).
    pub fn relit_found(&self) -> Vec<String> {
        let Some(view) = self.test.first() else { return Vec::new() };
        self.envmaps.iter().filter(|(n, _)| view.relit_path(n).is_some()).map(|(n, _)| n.clone()).collect()
    }

    pub fn envmap_path(&self, name: &str) -> Option<&Path> {
        self.envmaps.iter().find(|(n, _)| n == name).map(|(_, p)| p.as_path())
    }

    /// A one-line summary: layout, views per split, resolution, GT passes and env maps.
    pub fn summary(&self) -> String {
        let res = self
            .train
            .first()
            .or(self.test.first())
            .map(|v| {
                let shrunk = if v.downscale > 1 {
                    format!(" (files {}×{} shrunk {}×)", v.file_size.0, v.file_size.1, v.downscale)
                } else {
                    String::new()
                };
                format!("{}×{}{shrunk}", v.camera.width, v.camera.height)
            })
            .unwrap_or_else(|| "no size (no views)".to_string());
        let passes: Vec<&str> = self.passes_found().iter().map(|p| p.name()).collect();
        let relit = self.relit_found();
        let envs: Vec<&str> = self.envmaps.iter().map(|(n, _)| n.as_str()).collect();
        format!(
            "{}: {} layout, {} train / {} test views at {}, GT passes [{}], relit [{}], env maps [{}]{}",
            self.root.display(),
            match self.layout {
                Layout::Blender => "Blender",
                Layout::TensoIR => "TensoIR",
            },
            self.train.len(),
            self.test.len(),
            res,
            passes.join(", "),
            relit.join(", "),
            envs.join(", "),
            self.train_env.as_ref().map(|e| format!(", trained under '{e}'")).unwrap_or_default()
        )
    }

    /// Centre and radius of the cameras' bounding sphere (as 3DGS's scene extent: 1.1 × the
    /// largest camera distance from their mean).
    pub fn camera_extent(&self) -> ([f32; 3], f32) {
        let positions: Vec<glam::Vec3> = self.train.iter().map(|v| v.camera.position()).collect();
        if positions.is_empty() {
            return ([0.0; 3], 1.0);
        }
        let centre = positions.iter().copied().sum::<glam::Vec3>() / positions.len() as f32;
        let radius = positions.iter().map(|p| (*p - centre).length()).fold(0.0, f32::max) * 1.1;
        (centre.to_array(), radius.max(1e-3))
    }
}

fn read_train_env(root: &Path) -> Option<String> {
    let readme = read_json(&root.join("README.json")).ok()?;
    readme.get("environment")?.get("train_env")?.as_str().map(String::from)
}

/// The largest image side read or rendered (16k: beyond it one frame's buffers alone need
/// tens of GiB).
pub const MAX_IMAGE_SIDE: u32 = 16384;

/// Read a Blender `transforms_*.json`. Image size comes from `w`/`h` when present, else from
/// the first frame's image header; every frame must then have that size (checked on load).
pub fn read_transforms(root: &Path, path: &Path) -> Result<Vec<View>> {
    read_transforms_sized(root, path, None)
}

/// As [`read_transforms`], with the image size given (for camera files without images).
pub fn read_transforms_sized(root: &Path, path: &Path, size: Option<(u32, u32)>) -> Result<Vec<View>> {
    let json = read_json(path)?;
    let angle = number(path, &json, "camera_angle_x")? as f32;
    if !(angle > 0.0 && angle < std::f32::consts::PI) {
        return Err(Error::format(path, "camera_angle_x", format!("{angle} is not in (0, π) radians")));
    }
    let frames = json
        .get("frames")
        .and_then(|f| f.as_array())
        .ok_or_else(|| Error::format(path, "frames", "missing or not a list"))?;
    let mut size =
        size.or_else(|| match (json.get("w").and_then(|v| v.as_u64()), json.get("h").and_then(|v| v.as_u64())) {
            (Some(w), Some(h)) => Some((w.min(u32::MAX as u64) as u32, h.min(u32::MAX as u64) as u32)),
            _ => None,
        });
    for key in ["w", "h"] {
        if json.get(key).is_some_and(|v| v.as_u64().is_none()) {
            return Err(Error::format(path, key, "not a whole number of pixels"));
        }
    }
    if let Some((w, h)) = size
        && (w == 0 || h == 0 || w.max(h) > MAX_IMAGE_SIDE)
    {
        return Err(Error::format(path, "w, h", format!("{w}×{h}: each side must be 1..={MAX_IMAGE_SIDE}")));
    }
    let mut views = Vec::with_capacity(frames.len());
    for (i, frame) in frames.iter().enumerate() {
        let field = |name: &str| format!("frames[{i}].{name}");
        let file = frame
            .get("file_path")
            .and_then(|v| v.as_str())
            .ok_or_else(|| Error::format(path, field("file_path"), "missing or not a string"))?;
        let mut image_path = root.join(file.trim_start_matches("./"));
        if image_path.extension().is_none() {
            image_path.set_extension("png");
        }
        let rows = frame
            .get("transform_matrix")
            .and_then(|v| v.as_array())
            .ok_or_else(|| Error::format(path, field("transform_matrix"), "missing or not a list"))?;
        let values: Vec<f64> = rows
            .iter()
            .flat_map(|r| r.as_array().cloned().unwrap_or_default())
            .map(|v| v.as_f64().unwrap_or(f64::NAN))
            .collect();
        let c2w = matrix_rows(path, &field("transform_matrix"), &values)?;
        let (w, h) = match size {
            Some(s) => s,
            None => {
                let dims = image_dimensions(&image_path)?;
                size = Some(dims);
                dims
            }
        };
        let name = image_path
            .parent()
            .filter(|p| p.join("metadata.json").is_file())
            .and_then(|p| p.file_name())
            .or(image_path.file_stem())
            .unwrap_or_default()
            .to_string_lossy()
            .to_string();
        let camera = Camera::from_blender(name, c2w, w, h, angle)
            .map_err(|e| camera_error(path, &field("transform_matrix"), e))?;
        let folder = image_path.parent().unwrap_or(root).to_path_buf();
        views.push(View { camera, image_path, folder, file_size: (w, h), downscale: 1 });
    }
    unique_names(&mut views);
    Ok(views)
}

/// Views are written and reported by name: when two share one (a camera file whose frames
/// all point at `…/rgba.png` without a TensoIR `metadata.json` beside them), every view of a
/// shared name gets its image's folder in front (`test_000_rgba`), and the frame index when
/// that still collides (`007_rgba`).
fn unique_names(views: &mut [View]) {
    use std::collections::HashMap;
    let count = |views: &[View]| {
        let mut c: HashMap<String, usize> = HashMap::new();
        for v in views {
            *c.entry(v.camera.name.clone()).or_default() += 1;
        }
        c
    };
    let seen = count(views);
    for v in views.iter_mut().filter(|v| seen[&v.camera.name] > 1) {
        if let Some(folder) = v.image_path.parent().and_then(|p| p.file_name()) {
            v.camera.name = format!("{}_{}", folder.to_string_lossy(), v.camera.name);
        }
    }
    let seen = count(views);
    for (i, v) in views.iter_mut().enumerate() {
        if seen[&v.camera.name] > 1 {
            v.camera.name = format!("{i:03}_{}", v.camera.name);
        }
    }
}

fn read_tensoir_split(root: &Path, split: Split) -> Result<Vec<View>> {
    let prefix = format!("{}_", split.name());
    let mut folders: Vec<PathBuf> = std::fs::read_dir(root)
        .map_err(|e| Error::io(root, e))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_dir() && p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with(&prefix)))
        .collect();
    folders.sort();
    let mut views = Vec::with_capacity(folders.len());
    let mut unknown: Vec<(PathBuf, String)> = Vec::new();
    for folder in &folders {
        let (view, convention) = read_tensoir_view(folder)?;
        views.push(view);
        unknown.extend(convention.map(|c| (folder.join("metadata.json"), c)));
    }
    // Nothing says what another convention would mean (TensoIR's files have none; radiogs
    // synth writes CONVENTION): the matrix is read as Blender's all the same, and said so.
    if let Some((path, value)) = unknown.first() {
        tracing::warn!(
            "{}: convention: {value} is not understood and is ignored ({} of {} {} views): cam_transform_mat is read \
             as '{CONVENTION}' (camera-to-world, OpenGL camera axes: looking along -z, +y up)",
            path.display(),
            unknown.len(),
            views.len(),
            split.name()
        );
    }
    Ok(views)
}

/// The camera convention of a TensoIR `metadata.json` that radiogs reads (and writes).
const CONVENTION: &str = "blender_camera_to_world";

/// A view's camera and files, and its `convention` when one is given that is not
/// [`CONVENTION`] (as written in the file).
fn read_tensoir_view(folder: &Path) -> Result<(View, Option<String>)> {
    let meta_path = folder.join("metadata.json");
    let meta = read_json(&meta_path)?;
    let convention = meta.get("convention").filter(|c| c.as_str() != Some(CONVENTION)).map(|c| c.to_string());
    let matrix =
        meta.get("cam_transform_mat").ok_or_else(|| Error::format(&meta_path, "cam_transform_mat", "missing"))?;
    let values: Vec<f64> = match matrix {
        serde_json::Value::String(s) => s.split(',').map(|v| v.trim().parse::<f64>().unwrap_or(f64::NAN)).collect(),
        serde_json::Value::Array(a) => a
            .iter()
            .flat_map(|r| match r {
                serde_json::Value::Array(row) => row.iter().map(|v| v.as_f64().unwrap_or(f64::NAN)).collect(),
                v => vec![v.as_f64().unwrap_or(f64::NAN)],
            })
            .collect(),
        _ => return Err(Error::format(&meta_path, "cam_transform_mat", "not a string or list")),
    };
    let c2w = matrix_rows(&meta_path, "cam_transform_mat", &values)?;
    let angle = number(&meta_path, &meta, "cam_angle_x")? as f32;
    if !(angle > 0.0 && angle < std::f32::consts::PI) {
        return Err(Error::format(&meta_path, "cam_angle_x", format!("{angle} is not in (0, π) radians")));
    }
    let w = number(&meta_path, &meta, "imw")?;
    let h = number(&meta_path, &meta, "imh")?;
    if w < 1.0 || h < 1.0 || w.fract() != 0.0 || h.fract() != 0.0 {
        return Err(Error::format(&meta_path, "imw/imh", format!("{w}×{h} is not a positive integer size")));
    }
    if w.max(h) > MAX_IMAGE_SIDE as f64 {
        return Err(Error::format(&meta_path, "imw/imh", format!("{w}×{h}: each side must be 1..={MAX_IMAGE_SIDE}")));
    }
    let name = folder.file_name().unwrap_or_default().to_string_lossy().to_string();
    let camera = Camera::from_blender(name, c2w, w as u32, h as u32, angle)
        .map_err(|e| camera_error(&meta_path, "cam_transform_mat", e))?;
    let view = View {
        camera,
        image_path: folder.join("rgba.png"),
        folder: folder.to_path_buf(),
        file_size: (w as u32, h as u32),
        downscale: 1,
    };
    Ok((view, convention))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::image::write_image;

    /// A fresh folder, removed at the end of the test (pass or fail).
    fn temp_dir(name: &str) -> crate::test_dir::TempDir {
        crate::test_dir::TempDir::new(&format!("ds-{name}"))
    }

    const C2W: &str = "[[1,0,0,0],[0,1,0,0],[0,0,1,4],[0,0,0,1]]";

    fn write_blender(dir: &Path, frames: usize, size: u32) {
        let mut list = Vec::new();
        for i in 0..frames {
            list.push(format!(r#"{{"file_path": "./train/r_{i}", "transform_matrix": {C2W}}}"#));
            write_image(&dir.join(format!("train/r_{i}.png")), &Image::new(size, size, 4)).unwrap();
        }
        std::fs::write(
            dir.join("transforms_train.json"),
            format!(r#"{{"camera_angle_x": 0.69, "frames": [{}]}}"#, list.join(",")),
        )
        .unwrap();
    }

    #[test]
    fn blender_layout_loads() {
        let dir = temp_dir("blender");
        write_blender(&dir, 3, 8);
        let ds = Dataset::open(&dir).unwrap();
        assert_eq!(ds.layout, Layout::Blender);
        assert_eq!(ds.train.len(), 3);
        assert_eq!(ds.load_images(Split::Train).unwrap().len(), 3);
        assert!(ds.summary().contains("3 train / 0 test views at 8×8"));
    }

    /// Grey and grey-alpha training images beside RGBA ones load as RGBA (grey in every
    /// colour channel, alpha 1 when the file has none).
    #[test]
    fn grey_images_load_beside_rgba_ones() {
        let dir = temp_dir("grey");
        write_blender(&dir, 3, 4);
        let mut grey = Image::new(4, 4, 1);
        grey.data.iter_mut().enumerate().for_each(|(i, v)| *v = i as f32 / 15.0);
        write_image(&dir.join("train/r_1.png"), &grey).unwrap();
        let mut grey_alpha = Image::new(4, 4, 2);
        grey_alpha.data.chunks_exact_mut(2).for_each(|p| p.copy_from_slice(&[0.6, 0.2]));
        write_image(&dir.join("train/r_2.png"), &grey_alpha).unwrap();
        let ds = Dataset::open(&dir).unwrap();
        ds.check_images(Split::Train).unwrap();
        let images = ds.load_images(Split::Train).unwrap();
        assert!(images.iter().all(|img| img.channels == 4 && img.data.len() == 64));
        let (g, ga) = (images[1].pixel(3, 3), images[2].pixel(0, 0));
        assert!(g[0] == 1.0 && g[1] == 1.0 && g[2] == 1.0 && g[3] == 1.0, "{g:?}");
        assert!((ga[0] - 0.6).abs() < 3e-3 && ga[0] == ga[2] && (ga[3] - 0.2).abs() < 3e-3, "{ga:?}");
    }

    /// Frames whose images share a file name get distinct view names (outputs are written by
    /// name): the folder first, then the frame index; distinct names stay as they are.
    #[test]
    fn views_sharing_a_file_name_get_distinct_names() {
        let dir = temp_dir("names");
        let files = ["a/rgba", "b/rgba", "c/x/rgba", "d/x/rgba", "r_7"];
        let frames: Vec<String> = files
            .iter()
            .map(|f| {
                write_image(&dir.join(format!("{f}.png")), &Image::new(4, 4, 4)).unwrap();
                format!(r#"{{"file_path": "./{f}", "transform_matrix": {C2W}}}"#)
            })
            .collect();
        let json = dir.join("cams.json");
        std::fs::write(&json, format!(r#"{{"camera_angle_x": 0.69, "frames": [{}]}}"#, frames.join(","))).unwrap();
        let views = read_transforms(&dir, &json).unwrap();
        let names: Vec<&str> = views.iter().map(|v| v.camera.name.as_str()).collect();
        assert_eq!(names, ["a_rgba", "b_rgba", "002_x_rgba", "003_x_rgba", "r_7"]);
    }

    /// A dataset without views says so in its summary (the size used to be left blank).
    #[test]
    fn summary_of_a_dataset_without_views() {
        let dir = temp_dir("noviews");
        std::fs::write(dir.join("transforms_train.json"), r#"{"camera_angle_x": 0.5, "frames": []}"#).unwrap();
        let summary = Dataset::open(&dir).unwrap().summary();
        assert!(summary.contains("0 train / 0 test views at no size (no views)"), "{summary}");
    }

    #[test]
    fn downscaled_dataset_shrinks_images_passes_and_cameras_together() {
        let dir = temp_dir("downscale");
        // 9 × 6 files: by 2, 4 × 3 (the last column fills no block).
        let mut list = Vec::new();
        for i in 0..2 {
            list.push(format!(r#"{{"file_path": "./train/r_{i}", "transform_matrix": {C2W}}}"#));
            let mut img = Image::new(9, 6, 4);
            for y in 0..6 {
                for x in 0..9 {
                    img.pixel_mut(x, y).copy_from_slice(&[x as f32 / 8.0, y as f32 / 5.0, 0.5, 1.0]);
                }
            }
            write_image(&dir.join(format!("train/r_{i}.png")), &img).unwrap();
        }
        // A normal pass (PNG, encoded (n + 1)/2) whose 2 × 2 blocks mix two directions.
        let mut normal = Image::new(9, 6, 4);
        for y in 0..6 {
            for x in 0..9 {
                let n = if x % 2 == 0 { [1.0, 0.0, 0.0] } else { [0.0, 1.0, 0.0] };
                normal.pixel_mut(x, y).copy_from_slice(&[(n[0] + 1.0) / 2.0, (n[1] + 1.0) / 2.0, 0.5, 1.0]);
            }
        }
        write_image(&dir.join("train/normal.png"), &normal).unwrap();
        std::fs::write(
            dir.join("transforms_train.json"),
            format!(r#"{{"camera_angle_x": 0.69, "frames": [{}]}}"#, list.join(",")),
        )
        .unwrap();
        let full = Dataset::open(&dir).unwrap();
        let half = Dataset::open_downscaled(&dir, 2).unwrap();
        let (c1, c2) = (&full.train[0].camera, &half.train[0].camera);
        assert_eq!((c2.width, c2.height), (4, 3));
        assert_eq!((c2.fx, c2.fy, c2.cx, c2.cy), (c1.fx / 2.0, c1.fy / 2.0, c1.cx / 2.0, c1.cy / 2.0));
        // A point projects to half the pixel coordinates (pixel j covers old pixels 2j, 2j + 1).
        let p = glam::Vec3::new(0.03, -0.02, 0.1);
        let (u1, v1) = c1.project(p).unwrap();
        let (u2, v2) = c2.project(p).unwrap();
        assert!((u2 - u1 / 2.0).abs() < 1e-5 && (v2 - v1 / 2.0).abs() < 1e-5);
        // The image is the block mean of the file (8-bit PNG values).
        let img = half.train[1].load_image().unwrap();
        let file = full.train[1].load_image().unwrap();
        assert_eq!((img.width, img.height), (4, 3));
        assert_eq!(img, file.downscale(2));
        assert!((img.pixel(1, 2)[0] - (2.5 / 8.0)).abs() < 3e-3, "{:?}", img.pixel(1, 2));
        // Passes too; normals come back unit length ((1,0,0) + (0,1,0) → (1,1,0)/√2).
        let n = half.train[0].load_pass(Pass::Normal).unwrap().unwrap();
        assert_eq!((n.width, n.height), (4, 3));
        let px = n.pixel(0, 0);
        let len = (px[0] * px[0] + px[1] * px[1] + px[2] * px[2]).sqrt();
        assert!((len - 1.0).abs() < 1e-5 && (px[0] - px[1]).abs() < 1e-2, "{px:?}");
        assert!(half.summary().contains("4×3 (files 9×6 shrunk 2×)"), "{}", half.summary());
        // Factors that leave nothing, or none at all, are refused by name.
        let err = Dataset::open_downscaled(&dir, 7).unwrap_err().to_string();
        assert!(err.contains("resolution") && err.contains("9×6"), "{err}");
        let err = Dataset::open_downscaled(&dir, 0).unwrap_err().to_string();
        assert!(err.contains("resolution"), "{err}");
    }

    #[test]
    fn tensoir_layout_loads() {
        let dir = temp_dir("tensoir");
        for split in ["train", "test"] {
            let v = dir.join(format!("{split}_000"));
            std::fs::create_dir_all(&v).unwrap();
            std::fs::write(
                v.join("metadata.json"),
                r#"{"cam_transform_mat": "1,0,0,0,0,1,0,0,0,0,1,4,0,0,0,1", "cam_angle_x": 0.69, "imh": 6, "imw": 8}"#,
            )
            .unwrap();
            write_image(&v.join("rgba.png"), &Image::new(8, 6, 4)).unwrap();
        }
        write_image(&dir.join("test_000/albedo.png"), &Image::new(8, 6, 4)).unwrap();
        let ds = Dataset::open(&dir).unwrap();
        assert_eq!(ds.layout, Layout::TensoIR);
        assert_eq!((ds.train.len(), ds.test.len()), (1, 1));
        assert_eq!(ds.passes_found(), vec![Pass::Albedo]);
        assert!(ds.test[0].load_pass(Pass::Albedo).unwrap().is_some());
        assert!(ds.test[0].load_pass(Pass::Indirect).unwrap().is_none());
        // Sizes beyond the cap (a renderer would try to allocate them) are refused by name.
        for size in ["100000", "1e12"] {
            let meta = dir.join("test_000/metadata.json");
            std::fs::write(
                &meta,
                format!(r#"{{"cam_transform_mat": "1,0,0,0,0,1,0,0,0,0,1,4,0,0,0,1", "cam_angle_x": 0.69, "imh": 6, "imw": {size}}}"#),
            )
            .unwrap();
            let err = Dataset::open(&dir).unwrap_err().to_string();
            assert!(err.contains("metadata.json") && err.contains("imw/imh") && err.contains("16384"), "{err}");
        }
    }

    #[test]
    fn bad_inputs_name_file_and_field() {
        let dir = temp_dir("bad");
        // Missing folder.
        let err = Dataset::open(&dir.join("nope")).unwrap_err().to_string();
        assert!(err.contains("nope"), "{err}");
        // Empty folder: no layout.
        let err = Dataset::open(&dir).unwrap_err().to_string();
        assert!(err.contains("layout"), "{err}");
        // Malformed JSON.
        std::fs::write(dir.join("transforms_train.json"), "{ not json").unwrap();
        let err = Dataset::open(&dir).unwrap_err().to_string();
        assert!(err.contains("transforms_train.json") && err.contains("JSON"), "{err}");
        // Missing field.
        std::fs::write(dir.join("transforms_train.json"), r#"{"frames": []}"#).unwrap();
        let err = Dataset::open(&dir).unwrap_err().to_string();
        assert!(err.contains("camera_angle_x") && err.contains("missing"), "{err}");
        // Non-finite matrix (JSON has no NaN literal; a string value stands in for one).
        std::fs::write(
            dir.join("transforms_train.json"),
            r#"{"camera_angle_x": 0.7, "w": 4, "h": 4, "frames": [{"file_path": "a", "transform_matrix": [[1,0,0,0],[0,"x",0,0],[0,0,1,4],[0,0,0,1]]}]}"#,
        )
        .unwrap();
        let err = Dataset::open(&dir).unwrap_err().to_string();
        assert!(err.contains("frames[0].transform_matrix") && err.contains("not finite"), "{err}");
        // A frame whose image size differs from the others.
        let dir2 = temp_dir("size");
        write_blender(&dir2, 2, 8);
        write_image(&dir2.join("train/r_1.png"), &Image::new(9, 8, 4)).unwrap();
        let ds = Dataset::open(&dir2).unwrap();
        let err = ds.load_images(Split::Train).unwrap_err().to_string();
        assert!(err.contains("r_1.png") && err.contains("9×8"), "{err}");
        // Missing image file: the first (whose header gives the size) and a later one.
        std::fs::remove_file(dir2.join("train/r_1.png")).unwrap();
        let err = Dataset::open(&dir2).unwrap_err().to_string();
        assert!(err.contains("r_1.png") && err.contains("not found"), "{err}");
        std::fs::remove_file(dir2.join("train/r_0.png")).unwrap();
        let err = Dataset::open(&dir2).unwrap_err().to_string();
        assert!(err.contains("r_0.png"), "{err}");
        // A training image cut short is found by the check that reads every image in full
        // (the header alone, which gives the size, is still whole).
        write_blender(&dir2, 2, 8);
        let bytes = std::fs::read(dir2.join("train/r_1.png")).unwrap();
        std::fs::write(dir2.join("train/r_1.png"), &bytes[..bytes.len() - 20]).unwrap();
        let ds = Dataset::open(&dir2).unwrap();
        let err = ds.check_images(Split::Train).unwrap_err().to_string();
        assert!(err.contains("r_1.png") && err.contains("truncated"), "{err}");
        write_image(&dir2.join("train/r_1.png"), &Image::new(9, 8, 4)).unwrap();
        let err = ds.check_images(Split::Train).unwrap_err().to_string();
        assert!(err.contains("r_1.png") && err.contains("9×8"), "{err}");
        write_image(&dir2.join("train/r_1.png"), &Image::new(8, 8, 4)).unwrap();
        ds.check_images(Split::Train).unwrap();
        // An image size out of range or not a whole number.
        for (bad, key) in
            [(r#""w": 0, "h": 4"#, "w, h"), (r#""w": 100000, "h": 4"#, "w, h"), (r#""w": 16.5, "h": 4"#, "w")]
        {
            std::fs::write(
                dir.join("transforms_train.json"),
                format!(
                    r#"{{"camera_angle_x": 0.7, {bad}, "frames": [{{"file_path": "a", "transform_matrix": {C2W}}}]}}"#
                ),
            )
            .unwrap();
            let err = Dataset::open(&dir).unwrap_err().to_string();
            assert!(err.contains(&format!("transforms_train.json: {key}")), "{bad}: {err}");
        }
        // The transforms file given instead of its folder; a field of view out of range.
        let err = Dataset::open(&dir2.join("transforms_train.json")).unwrap_err().to_string();
        assert!(err.contains("is a file") && err.contains("folder"), "{err}");
        write_blender(&dir2, 1, 8);
        let text = std::fs::read_to_string(dir2.join("transforms_train.json")).unwrap();
        std::fs::write(dir2.join("transforms_train.json"), text.replace("0.69", "0")).unwrap();
        let err = Dataset::open(&dir2).unwrap_err().to_string();
        assert!(err.contains("transforms_train.json: camera_angle_x"), "{err}");
    }
}
