//! radiogs: inverse rendering with radiometrically consistent 2D Gaussian surfels, on the CPU.
//! See DESIGN.md (shared) for the formulas and conventions every module follows.

pub mod bench;
pub mod camera;
pub mod commands;
pub mod envmap;
pub mod error;
pub mod eval;
pub mod io;
pub mod loss;
pub mod optim;
pub mod orbit;
pub mod pbr_scene;
pub mod raster;
pub mod relight;
pub mod sh;
pub mod shade;
pub mod surfels;
pub mod synth;
#[cfg(test)]
pub(crate) mod test_dir;
pub mod trace;
pub mod train;

pub use error::{Error, Result};

/// Returned by commands that are not built yet: the CLI prints it and exits with code 2.
#[derive(Debug)]
pub struct NotBuilt(pub &'static str);

impl std::fmt::Display for NotBuilt {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)
    }
}
impl std::error::Error for NotBuilt {}
