//! The SD-SEM reconstruction core: pure, synchronous, parallel with rayon.
//!
//! Nothing here does I/O, knows about tokio, MCAP or configuration files.

pub mod image;

pub use image::Image;
pub mod dense_sift;
pub mod sift_flow;
