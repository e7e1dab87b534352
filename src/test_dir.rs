//! Scratch folders for tests that remove themselves: [`TempDir`] deletes its folder, and
//! everything in it, when dropped, also when the test panics (a failed assert unwinds through
//! the drop). Only `std`: the library's unit tests use it (`#[cfg(test)]` in `lib.rs`) and each
//! integration test in `tests/` includes this file by `#[path]`.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

/// `std::env::temp_dir()/radiogs-NAME-PID-N`, made empty by [`TempDir::new`] and removed when
/// dropped. The process id and a per-process count make it unique among tests running in
/// parallel and among test binaries, whatever the name; the name tells whose it is. It derefs to
/// its [`Path`], so `dir.join(..)`, `&dir` as a `&Path` and `dir.to_str()` work as on a path.
/// Bind it to a named variable (`let dir = ...`, never `let _ = ...`) so that it lives to the
/// end of the test.
#[derive(Debug)]
pub struct TempDir {
    path: PathBuf,
}

impl TempDir {
    pub fn new(name: &str) -> TempDir {
        static COUNT: AtomicUsize = AtomicUsize::new(0);
        let n = COUNT.fetch_add(1, Ordering::Relaxed);
        let path = std::env::temp_dir().join(format!("radiogs-{name}-{}-{n}", std::process::id()));
        // A folder kept from an earlier process with this id (see `keep`) does not leak in.
        let _ = std::fs::remove_dir_all(&path);
        std::fs::create_dir_all(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        TempDir { path }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

/// Set RADIOGS_KEEP_TEST_DIRS=1 (or the older RADIOGS_KEEP_TEST_OUTPUT) to keep test folders for debugging.
fn keep() -> bool {
    ["RADIOGS_KEEP_TEST_DIRS", "RADIOGS_KEEP_TEST_OUTPUT"]
        .iter()
        .any(|var| std::env::var_os(var).is_some_and(|v| !v.is_empty() && v != "0"))
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if keep() {
            eprintln!("kept {}", self.path.display());
        } else {
            let _ = std::fs::remove_dir_all(&self.path);
        }
    }
}

impl std::ops::Deref for TempDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        &self.path
    }
}

impl AsRef<Path> for TempDir {
    fn as_ref(&self) -> &Path {
        &self.path
    }
}
