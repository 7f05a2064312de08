//! Edge-preserving and smoothing filters shared by the stages.

pub mod bilateral_grid;
pub mod blur;
pub mod cross_grid;
pub mod detail;
