//! The SD-SEM reconstruction core: pure, synchronous, parallel with rayon.
//!
//! Nothing here does I/O, knows about tokio, MCAP or configuration files.

pub mod datum;
pub mod dense;
pub mod depth;
pub mod filter;
pub mod geometry;
pub mod image;
pub(crate) mod pages;
pub mod params;
pub mod pipeline;
pub mod precision;
pub mod rectify;
pub mod registration;
pub mod sparse;

pub use image::Image;
pub use params::{Preset, ReconstructionParams};
