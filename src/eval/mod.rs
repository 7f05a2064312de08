//! Evaluation functions that print figures on real and simulated data (not run by `cargo test`).

pub mod sparse;
