//! The CLI's commands as library functions: each takes its argument struct and does the work,
//! so `main.rs` only parses and prints.
pub mod demo;
pub mod export;
pub mod info;
pub mod render;
