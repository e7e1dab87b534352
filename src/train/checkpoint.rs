//! Versioned, atomic checkpoints: a magic tag, a format number, a JSON header (iteration, stage,
//! settings, blob table) and named little-endian f32 blobs (surfel parameters, optimiser
//! moments, density-control accumulators, env map). An old or foreign file is refused with a
//! message that says what it is.

use crate::error::{Error, Result};
use crate::io::atomic::write_atomic_with;
use crate::sh::SH_COEFFS;
use crate::surfels::Surfels;
use std::path::Path;

const MAGIC: &[u8; 8] = b"RADIOGS\x01";
pub const FORMAT_VERSION: u32 = 1;

#[derive(Clone, Debug, Default, PartialEq)]
pub struct Checkpoint {
    /// Free-form header: iteration, stage, anything a stage needs to resume.
    pub meta: serde_json::Value,
    pub blobs: Vec<(String, Vec<f32>)>,
}

impl Checkpoint {
    pub fn blob(&self, name: &str) -> Option<&[f32]> {
        self.blobs.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_slice())
    }

    /// A whole-number meta value, named with the file when missing or of another type.
    pub fn meta_u64(&self, path: &Path, key: &str) -> Result<u64> {
        self.meta
            .get(key)
            .and_then(|v| v.as_u64())
            .ok_or_else(|| Error::format(path, key, "missing from the checkpoint, or not a whole number"))
    }

    pub fn require(&self, path: &Path, name: &str) -> Result<&[f32]> {
        self.blob(name).ok_or_else(|| Error::format(path, format!("blob {name}"), "missing"))
    }

    pub fn put(&mut self, name: impl Into<String>, data: Vec<f32>) {
        let name = name.into();
        self.blobs.retain(|(n, _)| *n != name);
        self.blobs.push((name, data));
    }

    /// Store every array of `s` under `prefix.` names.
    pub fn put_surfels(&mut self, prefix: &str, s: &Surfels) {
        self.put(format!("{prefix}.means"), s.means.iter().flatten().copied().collect());
        self.put(format!("{prefix}.log_scales"), s.log_scales.iter().flatten().copied().collect());
        self.put(format!("{prefix}.quats"), s.quats.iter().flatten().copied().collect());
        self.put(format!("{prefix}.opacity_logits"), s.opacity_logits.clone());
        self.put(format!("{prefix}.sh"), s.sh.iter().flatten().flatten().copied().collect());
        self.put(format!("{prefix}.albedo_logits"), s.albedo_logits.iter().flatten().copied().collect());
        self.put(format!("{prefix}.roughness_logits"), s.roughness_logits.clone());
        self.put(format!("{prefix}.sh_degree"), vec![s.sh_degree as f32]);
    }

    pub fn get_surfels(&self, path: &Path, prefix: &str) -> Result<Surfels> {
        fn chunks<const K: usize>(path: &Path, name: &str, v: &[f32], n: usize) -> Result<Vec<[f32; K]>> {
            if v.len() != n * K {
                return Err(Error::format(
                    path,
                    format!("blob {name}"),
                    format!("{} values, expected {}", v.len(), n * K),
                ));
            }
            Ok(v.chunks_exact(K).map(|c| c.try_into().unwrap()).collect())
        }
        let name = |field: &str| format!("{prefix}.{field}");
        let means = self.require(path, &name("means"))?;
        let n = means.len() / 3;
        let sh_flat = self.require(path, &name("sh"))?;
        let sh_rows: Vec<[f32; 3 * SH_COEFFS]> = chunks(path, &name("sh"), sh_flat, n)?;
        let degree = self.require(path, &name("sh_degree"))?.first().copied().unwrap_or(0.0);
        let s = Surfels {
            means: chunks(path, &name("means"), means, n)?,
            log_scales: chunks(path, &name("log_scales"), self.require(path, &name("log_scales"))?, n)?,
            quats: chunks(path, &name("quats"), self.require(path, &name("quats"))?, n)?,
            opacity_logits: chunks::<1>(
                path,
                &name("opacity_logits"),
                self.require(path, &name("opacity_logits"))?,
                n,
            )?
            .into_iter()
            .map(|[v]| v)
            .collect(),
            sh: sh_rows.iter().map(|r| std::array::from_fn(|k| [r[3 * k], r[3 * k + 1], r[3 * k + 2]])).collect(),
            albedo_logits: chunks(path, &name("albedo_logits"), self.require(path, &name("albedo_logits"))?, n)?,
            roughness_logits: chunks::<1>(
                path,
                &name("roughness_logits"),
                self.require(path, &name("roughness_logits"))?,
                n,
            )?
            .into_iter()
            .map(|[v]| v)
            .collect(),
            sh_degree: degree as u32,
        };
        // Named here (file and blobs): a NaN would otherwise surface as a diverged loss.
        s.validate().map_err(|e| match e {
            Error::Invalid { reason, .. } => Error::format(path, format!("blobs {prefix}.*"), reason),
            other => other,
        })?;
        Ok(s)
    }

    /// Write atomically (temp file + rename).
    pub fn save(&self, path: &Path) -> Result<()> {
        let table: Vec<serde_json::Value> =
            self.blobs.iter().map(|(n, v)| serde_json::json!({"name": n, "len": v.len()})).collect();
        let header = serde_json::json!({"meta": self.meta, "blobs": table});
        let header = serde_json::to_vec(&header).map_err(|e| Error::invalid("checkpoint header", e.to_string()))?;
        write_atomic_with(path, |w| {
            w.write_all(MAGIC)?;
            w.write_all(&FORMAT_VERSION.to_le_bytes())?;
            w.write_all(&(header.len() as u64).to_le_bytes())?;
            w.write_all(&header)?;
            for (_, data) in &self.blobs {
                let mut bytes = Vec::with_capacity(data.len() * 4);
                for v in data {
                    bytes.extend_from_slice(&v.to_le_bytes());
                }
                w.write_all(&bytes)?;
            }
            Ok(())
        })
    }

    pub fn load(path: &Path) -> Result<Checkpoint> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        if bytes.len() < 20 || &bytes[..7] != &MAGIC[..7] {
            return Err(Error::format(path, "header", "not a radiogs checkpoint"));
        }
        let version = u32::from_le_bytes(bytes[8..12].try_into().unwrap());
        if version != FORMAT_VERSION || bytes[7] != MAGIC[7] {
            return Err(Error::format(
                path,
                "format version",
                format!(
                    "checkpoint format {version}; this radiogs reads format {FORMAT_VERSION} (retrain or use the matching radiogs)"
                ),
            ));
        }
        let header_len = u64::from_le_bytes(bytes[12..20].try_into().unwrap()) as usize;
        let header_end = 20usize.checked_add(header_len).filter(|&e| e <= bytes.len());
        let header_end = header_end.ok_or_else(|| Error::format(path, "header", "truncated"))?;
        let header: serde_json::Value =
            serde_json::from_slice(&bytes[20..header_end]).map_err(|e| Error::format(path, "header", e.to_string()))?;
        let table =
            header.get("blobs").and_then(|b| b.as_array()).ok_or_else(|| Error::format(path, "blobs", "missing"))?;
        let mut at = header_end;
        let mut blobs = Vec::with_capacity(table.len());
        for entry in table {
            let name = entry.get("name").and_then(|n| n.as_str()).unwrap_or("").to_string();
            let len =
                entry.get("len").and_then(|n| n.as_u64()).ok_or_else(|| Error::format(path, "blobs", "bad length"))?
                    as usize;
            let end = len.checked_mul(4).and_then(|b| at.checked_add(b)).filter(|&e| e <= bytes.len());
            let end = end.ok_or_else(|| Error::format(path, format!("blob {name}"), "truncated"))?;
            let data: Vec<f32> =
                bytes[at..end].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
            blobs.push((name, data));
            at = end;
        }
        Ok(Checkpoint { meta: header.get("meta").cloned().unwrap_or_default(), blobs })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_refusals() {
        let dir = crate::test_dir::TempDir::new("ckpt");
        let path = dir.join("a.ckpt");
        let s = Surfels::random_in_box(17, [0.0; 3], [1.0; 3], 2);
        let mut c = Checkpoint { meta: serde_json::json!({"iteration": 42}), ..Default::default() };
        c.put_surfels("params", &s);
        c.put("env", vec![1.0, 2.0, f32::MIN_POSITIVE]);
        c.save(&path).unwrap();
        let back = Checkpoint::load(&path).unwrap();
        assert_eq!(back, c);
        assert_eq!(back.get_surfels(&path, "params").unwrap(), s);
        // A NaN in any parameter is named with the file, the blobs, the surfel and the parameter.
        for (blob, at, named) in
            [("params.sh", 3 * 16 * 5 + 4, "surfel 5: sh"), ("params.quats", 4 * 16 + 1, "surfel 16: quats")]
        {
            let mut bad = c.clone();
            let mut v = bad.blob(blob).unwrap().to_vec();
            v[at] = f32::NAN;
            bad.put(blob, v);
            let err = bad.get_surfels(&path, "params").unwrap_err().to_string();
            assert!(err.contains("a.ckpt") && err.contains("params") && err.contains(named), "{err}");
        }

        let mut bytes = std::fs::read(&path).unwrap();
        bytes[8] = 99;
        std::fs::write(&path, &bytes).unwrap();
        let err = Checkpoint::load(&path).unwrap_err().to_string();
        assert!(err.contains("format 99"), "{err}");
        std::fs::write(&path, b"PK\x03\x04 some zip file with enough bytes").unwrap();
        assert!(Checkpoint::load(&path).unwrap_err().to_string().contains("not a radiogs checkpoint"));
        c.save(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() - 5]).unwrap();
        assert!(Checkpoint::load(&path).unwrap_err().to_string().contains("truncated"));
    }
}
