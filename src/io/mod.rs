//! Files in and out: images, datasets, PLY, checkpoints. Every reader names the file and the
//! field in its errors; every writer is atomic.
pub mod atomic;
pub mod dataset;
pub mod image;
pub mod ply;
pub mod rgbe;
