//! Evaluations against ground truth: figures the reports quote, printed by
//! ignored tests and evaluation functions (not run by `cargo test`); they read
//! `$SDSEM_DATA`, see [`data_dir`].

pub mod acquisition;
pub mod dense;
pub mod flow;
pub mod potamogeton;
pub mod soak;
pub mod sparse;
pub mod synthetic;

use std::path::PathBuf;

/// What every `sdsem eval …` command takes.
#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// The shared evaluation data (`--data`, else [`data_dir`]).
    pub data_dir: PathBuf,
    /// A smaller, faster set of cases (a smoke run, not the reported figures).
    pub quick: bool,
    /// Print the figures as JSON on stdout instead of a table.
    pub json: bool,
}

/// Where the shared evaluation data lives: `$SDSEM_DATA`, else
/// `<repository root>/../shared/data`.
#[must_use]
pub fn data_dir() -> PathBuf {
    std::env::var_os("SDSEM_DATA").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"),
        PathBuf::from,
    )
}
