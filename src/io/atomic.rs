//! Atomic output: write to a temporary sibling, then rename, so a crash or Ctrl-C never leaves
//! a half-written file where a user (or `--resume`) would read it.

use crate::error::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};

fn temp_sibling(path: &Path) -> PathBuf {
    let mut name = path.file_name().map(|n| n.to_os_string()).unwrap_or_default();
    name.push(format!(".{}.tmp", std::process::id()));
    path.with_file_name(name)
}

/// Create the parent directory of `path` if needed.
pub fn ensure_parent(path: &Path) -> Result<()> {
    if let Some(parent) = path.parent() {
        if !parent.as_os_str().is_empty() {
            std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
        }
    }
    Ok(())
}

/// Where an atomic write of `path` must go: a symlink is followed (the rename replaces its
/// target, not the link), and an existing path that is not a regular file (a device, a FIFO, a
/// folder) is refused, since the rename would replace it with a file.
fn write_target(path: &Path) -> Result<PathBuf> {
    let mut target = path.to_path_buf();
    // A chain of links, bounded (a loop is an error).
    for _ in 0..40 {
        match std::fs::symlink_metadata(&target) {
            Ok(m) if m.file_type().is_symlink() => {
                let link = std::fs::read_link(&target).map_err(|e| Error::io(&target, e))?;
                target = match target.parent() {
                    Some(parent) if link.is_relative() => parent.join(link),
                    _ => link,
                };
            }
            Ok(m) if !m.is_file() => {
                return Err(Error::invalid(
                    target.display().to_string(),
                    "exists and is not a regular file; outputs are written to a temporary file and renamed over it",
                ));
            }
            _ => return Ok(target),
        }
    }
    Err(Error::invalid(path.display().to_string(), "too many levels of symbolic links"))
}

/// Write `path` atomically with the bytes produced by `fill`.
pub fn write_atomic_with(path: &Path, fill: impl FnOnce(&mut dyn Write) -> std::io::Result<()>) -> Result<()> {
    let resolved = write_target(path)?;
    let path = resolved.as_path();
    ensure_parent(path)?;
    let tmp = temp_sibling(path);
    let result = (|| {
        let file = std::fs::File::create(&tmp)?;
        let mut writer = std::io::BufWriter::new(file);
        fill(&mut writer)?;
        let file = writer.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::io(path, e));
    }
    Ok(())
}

/// Write `bytes` to `path` atomically.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// An output folder filled beside the one it will replace (`<target>.partial`), so a command
/// that fails half-way leaves the previous folder whole: removed when dropped, unless
/// [`publish`](Self::publish)ed in place of its target.
pub struct PartialDir(Option<PathBuf>);

impl PartialDir {
    /// A fresh, empty `<target>.partial` (what a failed run left there is removed first).
    pub fn beside(target: &Path) -> Result<Self> {
        let Some(name) = target.file_name() else {
            return Err(Error::invalid(target.display().to_string(), "must name a folder (not `.`, `..` or `/`)"));
        };
        let mut partial_name = name.to_os_string();
        partial_name.push(".partial");
        let dir = target.with_file_name(partial_name);
        if dir.exists() {
            std::fs::remove_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        }
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        Ok(PartialDir(Some(dir)))
    }

    /// The folder being filled.
    pub fn path(&self) -> &Path {
        self.0.as_deref().expect("a PartialDir is used only until published")
    }

    /// Replace `to` (if it exists) with the filled folder.
    pub fn publish(mut self, to: &Path) -> Result<()> {
        let Some(from) = self.0.take() else { return Ok(()) };
        if to.exists() {
            std::fs::remove_dir_all(to).map_err(|e| Error::io(to, e))?;
        }
        std::fs::rename(&from, to).map_err(|e| Error::io(to, e))
    }
}

impl Drop for PartialDir {
    fn drop(&mut self) {
        if let Some(dir) = self.0.take() {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_dir::TempDir;

    /// A write through a symlink (and a chain of two) replaces the target's content and keeps
    /// the links; a path that is a folder or a device is refused before anything is written.
    #[test]
    fn links_are_followed_and_non_files_refused() {
        let dir = TempDir::new("atomic");
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        let target = dir.join("sub/target.json");
        std::fs::write(&target, "old").unwrap();
        std::os::unix::fs::symlink("sub/target.json", dir.join("link.json")).unwrap();
        std::os::unix::fs::symlink(dir.join("link.json"), dir.join("link2.json")).unwrap();
        write_atomic(&dir.join("link2.json"), b"new").unwrap();
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "new");
        for link in ["link.json", "link2.json"] {
            assert!(std::fs::symlink_metadata(dir.join(link)).unwrap().file_type().is_symlink(), "{link}");
        }
        // A dangling link: the file is created where it points.
        std::os::unix::fs::symlink("sub/fresh.json", dir.join("dangling.json")).unwrap();
        write_atomic(&dir.join("dangling.json"), b"x").unwrap();
        assert_eq!(std::fs::read_to_string(dir.join("sub/fresh.json")).unwrap(), "x");
        let err = write_atomic(&dir.join("sub"), b"x").unwrap_err().to_string();
        assert!(err.contains("sub") && err.contains("not a regular file"), "{err}");
        assert!(dir.join("sub").is_dir());
        let err = write_atomic(Path::new("/dev/null"), b"x").unwrap_err().to_string();
        assert!(err.contains("/dev/null") && err.contains("not a regular file"), "{err}");
    }

    /// A partial folder is removed when dropped and replaces its target (and only then) when
    /// published.
    #[test]
    fn a_partial_folder_replaces_its_target_only_when_published() {
        let dir = TempDir::new("partial");
        let target = dir.join("out");
        std::fs::create_dir_all(&target).unwrap();
        std::fs::write(target.join("old.txt"), "old").unwrap();
        {
            let p = PartialDir::beside(&target).unwrap();
            assert_eq!(p.path(), dir.join("out.partial"));
            std::fs::write(p.path().join("new.txt"), "new").unwrap();
        }
        assert!(!dir.join("out.partial").exists());
        assert_eq!(std::fs::read_to_string(target.join("old.txt")).unwrap(), "old");
        let p = PartialDir::beside(&target).unwrap();
        std::fs::write(p.path().join("new.txt"), "new").unwrap();
        p.publish(&target).unwrap();
        assert!(!target.join("old.txt").exists() && target.join("new.txt").is_file());
        assert!(!dir.join("out.partial").exists());
        assert!(PartialDir::beside(Path::new("/")).is_err());
    }
}
