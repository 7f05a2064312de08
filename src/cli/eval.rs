//! `sdsem eval …`: the evaluation commands that print the figures our issues
//! and reports quote (ground truth from the simulator, real data from
//! `../shared/data`). Each lives in `crate::eval`; this only dispatches.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Subcommand};

use crate::eval::{self, EvalOptions};

#[derive(Debug, Args)]
pub struct EvalArgs {
    #[command(subcommand)]
    pub which: Which,
    /// The shared evaluation data (default: $SDSEM_DATA, else ../shared/data beside the repository).
    #[arg(long, global = true, value_name = "DIR")]
    pub data: Option<PathBuf>,
    /// A smaller, faster set of cases (a smoke run; the reported figures use the full set).
    #[arg(long, global = true)]
    pub quick: bool,
    /// Print the figures as JSON instead of a table.
    #[arg(long, global = true)]
    pub json: bool,
}

#[derive(Debug, Subcommand)]
pub enum Which {
    /// SIFT flow on Middlebury RubberWhale against its ground truth (paper Table 3).
    Flow,
    /// The sparse stage (SIFT, ORSA, rectification): simulator pairs against their true
    /// correspondences, the grid over several seeds, the Potamogeton pairs beside the paper's
    /// Table 2, and the time per step at 1280×960.
    Sparse,
}

/// Runs one evaluation.
///
/// # Errors
/// When its data are missing or a stage fails.
pub fn run(args: &EvalArgs) -> anyhow::Result<ExitCode> {
    let opts = EvalOptions {
        data_dir: args.data.clone().unwrap_or_else(eval::data_dir),
        quick: args.quick,
        json: args.json,
    };
    match args.which {
        Which::Flow => eval::flow::run(&opts)?,
        Which::Sparse => eval::sparse::run(&opts)?,
    }
    Ok(ExitCode::SUCCESS)
}
