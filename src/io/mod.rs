//! Files in and out: images, datasets, PLY, checkpoints. Every reader names the file and the
//! field in its errors; every writer is atomic.
pub mod atomic;
pub mod dataset;
pub mod image;
pub mod ply;
pub mod rgbe;

/// Whether two paths name the same file or folder (both resolved; paths that cannot be resolved,
/// e.g. not yet made, are the same only when spelled the same).
pub fn same_path(a: &std::path::Path, b: &std::path::Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}
