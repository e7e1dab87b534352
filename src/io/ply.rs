//! Surfel PLY files in the 2DGS/3DGS binary little-endian layout:
//! x y z, nx ny nz (written as zeros), f_dc_0..2, f_rest_0..44, opacity (logit), scale_0 scale_1
//! (log), rot_0..3 (w x y z, unnormalised), then radiogs' material fields albedo_0..2 and
//! roughness (both as logits, so a file round-trips bit-exactly).
//!
//! f_rest is channel-major as 3DGS writes it: f_rest_0..14 are the 15 higher-order coefficients
//! of red, then green, then blue. Files with fewer f_rest fields (degree 0–2) load with a lower
//! SH degree. Viewers for 3DGS that need a third scale accept our files once a `scale_2`
//! (e.g. log(1e-6)) is added; SuperSplat loads them as they are with a zero third scale.

use crate::error::{Error, Result};
use crate::io::atomic::write_atomic_with;
use crate::sh::SH_COEFFS;
use crate::surfels::{self, Surfels};
use std::collections::HashMap;
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    /// The PLY type name (as in headers).
    fn name(self) -> &'static str {
        match self {
            Scalar::I8 => "char",
            Scalar::U8 => "uchar",
            Scalar::I16 => "short",
            Scalar::U16 => "ushort",
            Scalar::I32 => "int",
            Scalar::U32 => "uint",
            Scalar::F32 => "float",
            Scalar::F64 => "double",
        }
    }
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
    fn read(self, b: &[u8]) -> f32 {
        match self {
            Scalar::I8 => b[0] as i8 as f32,
            Scalar::U8 => b[0] as f32,
            Scalar::I16 => i16::from_le_bytes([b[0], b[1]]) as f32,
            Scalar::U16 => u16::from_le_bytes([b[0], b[1]]) as f32,
            Scalar::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
            Scalar::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
            Scalar::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
            Scalar::F64 => f64::from_le_bytes(b[..8].try_into().unwrap()) as f32,
        }
    }
}

struct Element {
    name: String,
    count: usize,
    properties: Vec<(String, Scalar)>,
}

/// Summary of a PLY without loading it all (for `radiogs info`).
pub struct PlyInfo {
    pub count: usize,
    pub sh_degree: u32,
    pub has_material: bool,
}

fn parse_header(path: &Path, bytes: &[u8]) -> Result<(Vec<Element>, usize)> {
    let bad = |field: &str, reason: &str| Error::format(path, field, reason);
    // The header's lines end in LF or CRLF (files written on Windows).
    let (end, body) = bytes
        .windows(10)
        .enumerate()
        .find_map(|(i, w)| match (w, &bytes[i + 10..]) {
            (b"end_header", [b'\n', ..]) => Some((i, i + 11)),
            (b"end_header", [b'\r', b'\n', ..]) => Some((i, i + 12)),
            _ => None,
        })
        .ok_or_else(|| bad("header", "no 'end_header' line (not a PLY file, or truncated)"))?;
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| bad("header", "not ASCII text"))?;
    let mut lines = header.lines().map(str::trim);
    if lines.next() != Some("ply") {
        return Err(bad("header", "first line is not 'ply'"));
    }
    let mut elements: Vec<Element> = Vec::new();
    for line in lines {
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["format", "binary_little_endian", _] => {}
            ["format", other, _] => {
                return Err(bad("format", &format!("'{other}' is not supported (only binary_little_endian)")));
            }
            ["comment", ..] | ["obj_info", ..] | [] => {}
            ["element", name, count] => {
                let count = count.parse().map_err(|_| bad("element", &format!("bad count '{count}' for '{name}'")))?;
                elements.push(Element { name: name.to_string(), count, properties: Vec::new() });
            }
            ["property", "list", ..] => {
                return Err(bad("property", "list properties are not supported in surfel files"));
            }
            ["property", ty, name] => {
                let scalar =
                    Scalar::parse(ty).ok_or_else(|| bad("property", &format!("unknown type '{ty}' of '{name}'")))?;
                let element = elements.last_mut().ok_or_else(|| bad("property", "property before any element"))?;
                element.properties.push((name.to_string(), scalar));
            }
            _ => return Err(bad("header", &format!("unexpected line '{line}'"))),
        }
    }
    Ok((elements, body))
}

fn vertex_layout<'a>(path: &Path, elements: &'a [Element]) -> Result<(&'a Element, usize)> {
    let mut offset = 0;
    for e in elements {
        if e.name == "vertex" {
            return Ok((e, offset));
        }
        let bytes = e.count.checked_mul(e.properties.iter().map(|p| p.1.size()).sum::<usize>());
        offset = bytes
            .and_then(|b| b.checked_add(offset))
            .ok_or_else(|| Error::format(path, format!("element {}", e.name), "its size overflows"))?;
    }
    Err(Error::format(path, "element vertex", "missing"))
}

fn sh_degree_from_rest(rest: usize) -> Option<u32> {
    match rest {
        0 => Some(0),
        9 => Some(1),
        24 => Some(2),
        45 => Some(3),
        _ => None,
    }
}

/// Read the header of a surfel PLY.
pub fn read_ply_info(path: &Path) -> Result<PlyInfo> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let (elements, _) = parse_header(path, &bytes)?;
    let (vertex, _) = vertex_layout(path, &elements)?;
    let names: Vec<&str> = vertex.properties.iter().map(|p| p.0.as_str()).collect();
    let rest = names.iter().filter(|n| n.starts_with("f_rest_")).count();
    Ok(PlyInfo {
        count: vertex.count,
        sh_degree: sh_degree_from_rest(rest).unwrap_or(0),
        has_material: names.contains(&"roughness") && names.contains(&"albedo_0"),
    })
}

/// Read a surfel PLY (2DGS layout; material fields optional, defaulting as a fresh scene).
pub fn read_ply(path: &Path) -> Result<Surfels> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let (elements, body) = parse_header(path, &bytes)?;
    let (vertex, offset) = vertex_layout(path, &elements)?;
    if vertex.count == 0 {
        return Err(Error::format(path, "element vertex", "the file holds no surfels"));
    }
    let stride: usize = vertex.properties.iter().map(|p| p.1.size()).sum();
    let mut column: HashMap<&str, (usize, Scalar)> = HashMap::new();
    let mut at = 0;
    for (name, ty) in &vertex.properties {
        column.insert(name.as_str(), (at, *ty));
        at += ty.size();
    }
    let need = |name: &str| -> Result<(usize, Scalar)> {
        column.get(name).copied().ok_or_else(|| Error::format(path, format!("property {name}"), "missing"))
    };
    let rest_count = (0..45).take_while(|k| column.contains_key(format!("f_rest_{k}").as_str())).count();
    let sh_degree = sh_degree_from_rest(rest_count).ok_or_else(|| {
        Error::format(path, "f_rest_*", format!("{rest_count} fields; expected 0, 9, 24 or 45 (SH degree 0–3)"))
    })?;
    let per_channel = rest_count / 3;
    let mean_cols = [need("x")?, need("y")?, need("z")?];
    let dc_cols = [need("f_dc_0")?, need("f_dc_1")?, need("f_dc_2")?];
    let rest_cols: Vec<(usize, Scalar)> =
        (0..rest_count).map(|k| need(&format!("f_rest_{k}"))).collect::<Result<_>>()?;
    let opacity_col = need("opacity")?;
    let scale_cols = [need("scale_0")?, need("scale_1")?];
    let rot_cols = [need("rot_0")?, need("rot_1")?, need("rot_2")?, need("rot_3")?];
    let albedo_cols: Option<[(usize, Scalar); 3]> =
        match (column.get("albedo_0"), column.get("albedo_1"), column.get("albedo_2")) {
            (Some(a), Some(b), Some(c)) => Some([*a, *b, *c]),
            _ => None,
        };
    let roughness_col = column.get("roughness").copied();

    let start = body.checked_add(offset).filter(|&s| s <= bytes.len()).ok_or_else(|| {
        Error::format(path, "element vertex", "the elements before it need more bytes than the file holds")
    })?;
    let needed = vertex.count.checked_mul(stride).and_then(|n| n.checked_add(start));
    if needed.is_none_or(|n| n > bytes.len()) {
        // Too short for the header's layout: cut short, or the header's types (the bytes of a
        // surfel add up from them) are not those of the data.
        let present = bytes.len().saturating_sub(start);
        let not_float: Vec<String> = vertex
            .properties
            .iter()
            .filter(|p| p.1 != Scalar::F32)
            .map(|(name, ty)| format!("{name} is {}", ty.name()))
            .collect();
        let why = if not_float.is_empty() {
            "the file is truncated".to_string()
        } else {
            format!("truncated, or the header's types are not the data's ({}, not float)", not_float.join(", "))
        };
        return Err(Error::format(
            path,
            "vertex data",
            format!(
                "{} surfels of {stride} bytes need {} bytes, {present} present: {why}",
                vertex.count,
                vertex.count.saturating_mul(stride)
            ),
        ));
    }
    let get = |row: &[u8], (at, ty): (usize, Scalar)| ty.read(&row[at..]);
    let mut s = Surfels { sh_degree, ..Default::default() };
    for i in 0..vertex.count {
        let row = &bytes[start + i * stride..start + (i + 1) * stride];
        s.means.push(mean_cols.map(|c| get(row, c)));
        let mut coeffs = [[0.0f32; 3]; SH_COEFFS];
        coeffs[0] = dc_cols.map(|c| get(row, c));
        for ch in 0..3 {
            for k in 0..per_channel {
                coeffs[1 + k][ch] = get(row, rest_cols[ch * per_channel + k]);
            }
        }
        s.sh.push(coeffs);
        s.opacity_logits.push(get(row, opacity_col));
        s.log_scales.push(scale_cols.map(|c| get(row, c)));
        s.quats.push(rot_cols.map(|c| get(row, c)));
        s.albedo_logits.push(match albedo_cols {
            Some(cols) => cols.map(|c| get(row, c)),
            None => [surfels::albedo_to_logit(surfels::DEFAULT_ALBEDO); 3],
        });
        s.roughness_logits.push(match roughness_col {
            Some(c) => get(row, c),
            None => surfels::logit(surfels::DEFAULT_ROUGHNESS),
        });
    }
    // Every field must be finite: a NaN colour or material renders and trains as silently as
    // a NaN position would not. Named by the PLY's properties.
    if let Some((i, field)) = s.first_non_finite() {
        let name = match field {
            "means" => "x, y, z",
            "log_scales" => "scale_0..1",
            "quats" => "rot_0..3",
            "opacity_logits" => "opacity",
            "sh" => "f_dc_0..2 / f_rest_*",
            "albedo_logits" => "albedo_0..2",
            _ => "roughness",
        };
        return Err(Error::format(path, format!("surfel {i}: {name}"), "a value is NaN or infinite"));
    }
    if let Some(i) = (0..s.len()).find(|&i| s.quats[i].iter().all(|v| *v == 0.0)) {
        return Err(Error::format(path, format!("surfel {i}: rot_0..3"), "the quaternion is zero"));
    }
    Ok(s)
}

/// The `unseen` flags of a PLY written by [`write_ply_flagged`], or None when it has no such
/// property. A value other than 0 or 1 is an error naming the surfel.
pub fn read_ply_unseen(path: &Path) -> Result<Option<Vec<bool>>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let (elements, body) = parse_header(path, &bytes)?;
    let (vertex, offset) = vertex_layout(path, &elements)?;
    let stride: usize = vertex.properties.iter().map(|p| p.1.size()).sum();
    let mut at = 0;
    let mut column = None;
    for (name, ty) in &vertex.properties {
        if name == UNSEEN_PROPERTY {
            column = Some((at, *ty));
        }
        at += ty.size();
    }
    let Some((at, ty)) = column else { return Ok(None) };
    let start = body + offset;
    let needed = vertex.count.checked_mul(stride).and_then(|n| n.checked_add(start));
    if needed.is_none_or(|n| n > bytes.len()) {
        return Err(Error::format(path, "vertex data", "the file is shorter than its header says"));
    }
    (0..vertex.count)
        .map(|i| match ty.read(&bytes[start + i * stride + at..]) {
            0.0 => Ok(false),
            1.0 => Ok(true),
            v => Err(Error::format(path, format!("surfel {i}: {UNSEEN_PROPERTY}"), format!("{v} is not 0 or 1"))),
        })
        .collect::<Result<Vec<bool>>>()
        .map(Some)
}

/// The header comment that records the screen-space filter a radiogs PLY was trained with.
const FILTER_COMMENT: &str = "radiogs filter_inv_square";

/// The screen-space filter 1/σ² recorded in a PLY's header by [`write_ply_trained`], or None
/// (a PLY from 2DGS/3DGS or an older radiogs: trained with 2DGS's 2).
pub fn read_ply_filter_inv_square(path: &Path) -> Result<Option<f32>> {
    // The header only (surfel files run to hundreds of MB).
    let mut bytes = Vec::new();
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    std::io::Read::read_to_end(&mut std::io::Read::take(file, 1 << 20), &mut bytes).map_err(|e| Error::io(path, e))?;
    let (_, body) = parse_header(path, &bytes)?;
    let header = String::from_utf8_lossy(&bytes[..body]);
    for line in header.lines() {
        if let Some(value) = line.trim().strip_prefix("comment ").and_then(|c| c.strip_prefix(FILTER_COMMENT)) {
            let f: f32 = value.trim().parse().map_err(|_| {
                Error::format(path, "comment radiogs filter_inv_square", &format!("'{}' is not a number", value.trim()))
            })?;
            if !(f.is_finite() && f > 0.0) {
                return Err(Error::format(path, "comment radiogs filter_inv_square", "must be a positive number"));
            }
            return Ok(Some(f));
        }
    }
    Ok(None)
}

/// Write surfels as a 2DGS-layout binary PLY (all 45 f_rest fields) plus material fields. Atomic.
pub fn write_ply(path: &Path, s: &Surfels) -> Result<()> {
    write_ply_trained(path, s, None)
}

/// [`write_ply`] recording in a header comment the screen-space filter the surfels were trained
/// with, so that `radiogs render --ply` draws them as training did.
pub fn write_ply_trained(path: &Path, s: &Surfels, filter_inv_square: Option<f32>) -> Result<()> {
    write_ply_flagged(path, s, filter_inv_square, None)
}

/// The per-surfel property that flags surfels no training camera saw (1) as the inverse stage
/// oriented them; `--trace-back-faces dark-unseen` traces their back faces as occluders.
const UNSEEN_PROPERTY: &str = "unseen";

/// [`write_ply_trained`] plus, with `unseen` (one flag per surfel), the float property
/// `unseen` (0 or 1), which 3DGS/2DGS readers ignore.
pub fn write_ply_flagged(
    path: &Path,
    s: &Surfels,
    filter_inv_square: Option<f32>,
    unseen: Option<&[bool]>,
) -> Result<()> {
    s.validate()?;
    if let Some(u) = unseen {
        assert_eq!(u.len(), s.len(), "write_ply: one unseen flag per surfel");
    }
    let mut header = String::from(
        "ply\nformat binary_little_endian 1.0\ncomment radiogs surfels (2DGS layout + albedo/roughness logits)\n",
    );
    if let Some(f) = filter_inv_square {
        header.push_str(&format!("comment {FILTER_COMMENT} {f}\n"));
    }
    header.push_str(&format!("element vertex {}\n", s.len()));
    let mut names: Vec<String> =
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"].map(String::from).to_vec();
    names.extend((0..45).map(|k| format!("f_rest_{k}")));
    names.extend(
        [
            "opacity",
            "scale_0",
            "scale_1",
            "rot_0",
            "rot_1",
            "rot_2",
            "rot_3",
            "albedo_0",
            "albedo_1",
            "albedo_2",
            "roughness",
        ]
        .map(String::from),
    );
    if unseen.is_some() {
        names.push(UNSEEN_PROPERTY.to_string());
    }
    for n in &names {
        header.push_str(&format!("property float {n}\n"));
    }
    header.push_str("end_header\n");
    write_atomic_with(path, |w| {
        w.write_all(header.as_bytes())?;
        let mut row: Vec<f32> = Vec::with_capacity(names.len());
        for i in 0..s.len() {
            row.clear();
            row.extend_from_slice(&s.means[i]);
            // 2DGS writes zero normals; the surfel normal is the third rotation column.
            row.extend_from_slice(&[0.0; 3]);
            row.extend_from_slice(&s.sh[i][0]);
            for ch in 0..3 {
                row.extend((1..SH_COEFFS).map(|k| s.sh[i][k][ch]));
            }
            row.push(s.opacity_logits[i]);
            row.extend_from_slice(&s.log_scales[i]);
            row.extend_from_slice(&s.quats[i]);
            row.extend_from_slice(&s.albedo_logits[i]);
            row.push(s.roughness_logits[i]);
            if let Some(u) = unseen {
                row.push(if u[i] { 1.0 } else { 0.0 });
            }
            for v in &row {
                w.write_all(&v.to_le_bytes())?;
            }
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    /// A fresh folder (removed when the guard drops, pass or fail) and `s.ply` in it.
    fn temp(name: &str) -> (crate::test_dir::TempDir, std::path::PathBuf) {
        let dir = crate::test_dir::TempDir::new(&format!("ply-{name}"));
        let path = dir.join("s.ply");
        (dir, path)
    }

    fn random_surfels(n: usize) -> Surfels {
        let mut s = Surfels::random_in_box(n, [-1.0; 3], [1.0; 3], 9);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(4);
        for c in s.sh.iter_mut().flatten().flatten() {
            *c = rng.random_range(-1.0..1.0);
        }
        s.sh_degree = 3;
        s
    }

    #[test]
    fn the_training_filter_is_recorded_in_the_header() {
        let s = random_surfels(5);
        let (_dir, path) = temp("filter");
        write_ply_trained(&path, &s, Some(8.0)).unwrap();
        assert_eq!(read_ply_filter_inv_square(&path).unwrap(), Some(8.0));
        // The comment does not disturb the reader.
        assert_eq!(read_ply(&path).unwrap().means, s.means);
        write_ply(&path, &s).unwrap();
        assert_eq!(read_ply_filter_inv_square(&path).unwrap(), None);
        // A damaged value names the field.
        let bytes = std::fs::read(&path).unwrap();
        let text = String::from_utf8_lossy(&bytes[..200])
            .replace("comment radiogs surfels", "comment radiogs filter_inv_square x");
        let mut damaged = text.into_bytes();
        damaged.extend_from_slice(&bytes[200..]);
        std::fs::write(&path, &damaged).unwrap();
        let err = read_ply_filter_inv_square(&path).unwrap_err().to_string();
        assert!(err.contains("filter_inv_square") && err.contains("not a number"), "{err}");
    }

    #[test]
    fn unseen_flags_round_trip_and_bad_values_are_named() {
        let s = random_surfels(6);
        let (_dir, path) = temp("unseen");
        write_ply_trained(&path, &s, Some(2.0)).unwrap();
        assert_eq!(read_ply_unseen(&path).unwrap(), None);
        let flags = [true, false, false, true, true, false];
        write_ply_flagged(&path, &s, Some(2.0), Some(&flags)).unwrap();
        assert_eq!(read_ply_unseen(&path).unwrap().as_deref(), Some(&flags[..]));
        // The extra property leaves the surfels as they were.
        let back = read_ply(&path).unwrap();
        assert_eq!((back.means, back.sh, back.quats), (s.means.clone(), s.sh.clone(), s.quats.clone()));
        // A value other than 0 or 1 (the last float of surfel 2's row) is named.
        let mut bytes = std::fs::read(&path).unwrap();
        let row = 4 * (9 + 45 + 11 + 1);
        let end = bytes.len() - 3 * row;
        bytes[end - 4..end].copy_from_slice(&0.5f32.to_le_bytes());
        std::fs::write(&path, &bytes).unwrap();
        let err = read_ply_unseen(&path).unwrap_err().to_string();
        assert!(err.contains("surfel 2: unseen") && err.contains("0.5"), "{err}");
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let s = random_surfels(57);
        let (_dir, path) = temp("rt");
        write_ply(&path, &s).unwrap();
        let back = read_ply(&path).unwrap();
        assert_eq!(back, s);
        let info = read_ply_info(&path).unwrap();
        assert_eq!((info.count, info.sh_degree, info.has_material), (57, 3, true));
    }

    /// Double properties are read (as f32), and a header with CRLF line ends is read as one
    /// with LF (it was refused as having no 'end_header').
    #[test]
    fn double_properties_and_crlf_headers_load() {
        let s = random_surfels(3);
        let (_dir, path) = temp("double");
        write_ply(&path, &s).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let body = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let header = String::from_utf8_lossy(&bytes[..body]).to_string();
        let names: Vec<&str> = header.lines().filter_map(|l| l.strip_prefix("property float ")).collect();
        let k = names.iter().position(|n| *n == "opacity").unwrap();
        let mut doubled = header.replace("property float opacity", "property double opacity").into_bytes();
        for row in bytes[body..].chunks_exact(4 * names.len()) {
            doubled.extend_from_slice(&row[..4 * k]);
            let v = f32::from_le_bytes(row[4 * k..4 * k + 4].try_into().unwrap());
            doubled.extend((v as f64).to_le_bytes());
            doubled.extend_from_slice(&row[4 * k + 4..]);
        }
        std::fs::write(&path, &doubled).unwrap();
        assert_eq!(read_ply(&path).unwrap(), s);
        let mut crlf = header.replace('\n', "\r\n").into_bytes();
        crlf.extend_from_slice(&bytes[body..]);
        std::fs::write(&path, &crlf).unwrap();
        assert_eq!(read_ply(&path).unwrap(), s);
        assert_eq!(read_ply_info(&path).unwrap().count, 3);
    }

    /// A file in the exact layout of the official 2DGS `save_ply` (no material fields).
    #[test]
    fn reads_official_2dgs_layout() {
        let s = random_surfels(3);
        let mut header = String::from("ply\nformat binary_little_endian 1.0\nelement vertex 3\n");
        let mut names: Vec<String> =
            ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"].map(String::from).to_vec();
        names.extend((0..45).map(|k| format!("f_rest_{k}")));
        names.extend(["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"].map(String::from));
        for n in &names {
            header.push_str(&format!("property float {n}\n"));
        }
        header.push_str("end_header\n");
        let mut bytes = header.into_bytes();
        for i in 0..3 {
            let mut row = s.means[i].to_vec();
            row.extend([0.0; 3]);
            row.extend(s.sh[i][0]);
            // features_rest is (N, 15, 3) transposed to (N, 3, 15) before flattening.
            for ch in 0..3 {
                row.extend((1..16).map(|k| s.sh[i][k][ch]));
            }
            row.push(s.opacity_logits[i]);
            row.extend(s.log_scales[i]);
            row.extend(s.quats[i]);
            for v in row {
                bytes.extend(v.to_le_bytes());
            }
        }
        let (_dir, path) = temp("official");
        std::fs::write(&path, bytes).unwrap();
        let back = read_ply(&path).unwrap();
        assert_eq!(back.means, s.means);
        assert_eq!(back.sh, s.sh);
        assert_eq!(back.quats, s.quats);
        assert_eq!(back.roughness(0), surfels::DEFAULT_ROUGHNESS.clamp(0.0, 1.0));
    }

    #[test]
    fn bad_files_give_clear_errors() {
        let (_dir, path) = temp("bad");
        std::fs::write(
            &path,
            b"ply\nformat binary_little_endian 1.0\nelement vertex 0\nproperty float x\nend_header\n",
        )
        .unwrap();
        let err = read_ply(&path).unwrap_err().to_string();
        assert!(err.contains("s.ply") && err.contains("no surfels"), "{err}");

        std::fs::write(&path, b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n\0\0\0\0\0\0\0\0").unwrap();
        let err = read_ply(&path).unwrap_err().to_string();
        assert!(err.contains("property z") && err.contains("missing"), "{err}");

        write_ply(&path, &random_surfels(4)).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 10]).unwrap();
        let err = read_ply(&path).unwrap_err().to_string();
        assert!(err.contains("truncated"), "{err}");

        // A header that says double where the data holds float names the property.
        let body = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let text = String::from_utf8_lossy(&bytes[..body]).replace("property float opacity", "property double opacity");
        let mut lying = text.into_bytes();
        lying.extend_from_slice(&bytes[body..]);
        std::fs::write(&path, &lying).unwrap();
        let err = read_ply(&path).unwrap_err().to_string();
        assert!(err.contains("vertex data") && err.contains("opacity is double, not float"), "{err}");

        // A NaN or infinity in any field of surfel 2 is refused naming the surfel and the field.
        let names: Vec<String> = String::from_utf8_lossy(&bytes[..body])
            .lines()
            .filter_map(|l| l.strip_prefix("property float ").map(String::from))
            .collect();
        let stride = 4 * names.len();
        for (field, named) in [
            ("f_dc_1", "f_dc_0..2"),
            ("f_rest_44", "f_rest"),
            ("albedo_2", "albedo_0..2"),
            ("roughness", "roughness"),
            ("opacity", "opacity"),
            ("z", "x, y, z"),
        ] {
            let k = names.iter().position(|n| n == field).unwrap();
            for bad in [f32::NAN, f32::INFINITY] {
                let mut b = bytes.clone();
                let at = body + 2 * stride + 4 * k;
                b[at..at + 4].copy_from_slice(&bad.to_le_bytes());
                std::fs::write(&path, &b).unwrap();
                let err = read_ply(&path).unwrap_err().to_string();
                assert!(err.contains("surfel 2") && err.contains(named) && err.contains("NaN"), "{field}: {err}");
            }
        }

        // Elements before the vertices whose byte size overflows, or that the file cannot
        // hold, are refused (they used to wrap and move the vertex data).
        for (props, expect) in [(4, "overflows"), (1, "more bytes than the file holds")] {
            let face =
                format!("element face 4611686018427387903\n{}element vertex", "property float a\n".repeat(props));
            let text = String::from_utf8_lossy(&bytes[..body]).replace("element vertex", &face);
            let mut huge = text.into_bytes();
            huge.extend_from_slice(&bytes[body..]);
            std::fs::write(&path, &huge).unwrap();
            let err = read_ply(&path).unwrap_err().to_string();
            assert!(err.contains("s.ply") && err.contains("element") && err.contains(expect), "{err}");
        }

        std::fs::write(&path, b"not a ply").unwrap();
        assert!(read_ply(&path).unwrap_err().to_string().contains("end_header"));
        std::fs::write(&path, b"ply\nformat ascii 1.0\nelement vertex 1\nend_header\n").unwrap();
        assert!(read_ply(&path).unwrap_err().to_string().contains("ascii"));
    }
}
