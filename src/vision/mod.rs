//! The SD-SEM reconstruction core: pure, synchronous, parallel with rayon.
//!
//! Nothing here does I/O, knows about tokio, MCAP or configuration files.

pub mod fundamental;
pub mod image;
pub mod matching;
pub mod orsa;
pub mod pipeline;
pub mod precision;
pub mod rectify;
pub mod registration;
pub mod sift;
pub mod sparse;
pub mod warp;

pub use image::Image;
pub mod bilateral_grid;
pub mod consistency;
pub mod dense;
pub mod dense_sift;
pub mod depth;
pub mod fill;
pub mod reassign;
pub mod sift_flow;
pub mod subpixel;
