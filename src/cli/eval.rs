//! `sdsem eval …`: the evaluation commands that print the figures our issues
//! and reports quote (ground truth from the simulator, real data from
//! `../shared/data`). Each lives in `crate::eval`; this only dispatches.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Subcommand};

use crate::eval::{self, EvalOptions};
use crate::vision::Preset;

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
    /// The 0→7° series on the simulator: tilts, frames, stage I/O, re-centring
    /// against ground truth, real-time overhead, the record in the Python reader.
    #[command(after_help = super::manual::EVAL_ACQUISITION)]
    Acquisition {
        /// Only the real-time figures, on the simulator of this configuration (its stage and
        /// imaging dialects, e.g. config/sim-zeiss.toml), at time scale 1.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
    },
    /// SIFT flow on Middlebury RubberWhale against its ground truth (paper Table 3).
    #[command(after_help = super::manual::EVAL_FLOW)]
    Flow {
        /// Override a dense parameter, KEY=VALUE as in [reconstruction.dense] (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// The daemon as a process through consecutive short jobs with seeded
    /// random stage faults: final states, reasons, records, RSS and fds.
    #[command(after_help = super::manual::EVAL_SOAK)]
    Soak(SoakArgs),
    /// `kill -9` of the daemon at random moments, each followed by a restart:
    /// no job lost or re-run, every record readable.
    #[command(after_help = super::manual::EVAL_KILL)]
    Kill(KillArgs),
    /// The dense stage on the simulator's ground-truth scenes: coverage, RMSE, disparity error, scale.
    #[command(after_help = super::manual::EVAL_DENSE)]
    Dense(DenseArgs),
    /// Agreement of the Potamogeton height maps from three tilt pairs (real Zeiss data).
    #[command(after_help = super::manual::EVAL_POTAMOGETON)]
    Potamogeton {
        /// Only this mode (default: improved and paper).
        #[arg(long, value_parser = parse_mode)]
        mode: Option<Preset>,
        /// Override a dense parameter, KEY=VALUE as in [reconstruction.dense] (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// The sparse stage (SIFT, ORSA, rectification): simulator pairs against their true
    /// correspondences, the grid over several seeds, the Potamogeton pairs beside the paper's
    /// Table 2, and the time per step at 1280×960.
    #[command(after_help = super::manual::EVAL_SPARSE)]
    Sparse,
}

#[derive(Debug, Args)]
pub struct SoakArgs {
    /// Jobs to run (default 50; 10 with --quick).
    #[arg(long)]
    pub jobs: Option<usize>,
    /// Seed of the faults and of when the simulator is switched off.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Keep the work directory (spool, runs, daemon log).
    #[arg(long)]
    pub keep: bool,
}

#[derive(Debug, Args)]
pub struct KillArgs {
    /// Kill-and-restart rounds (default 20; 5 with --quick).
    #[arg(long)]
    pub rounds: Option<usize>,
    /// Seed of the kill moments.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Keep the work directory (spool, runs, daemon logs).
    #[arg(long)]
    pub keep: bool,
}

#[derive(Debug, Args)]
pub struct DenseArgs {
    /// Rectify with the simulator's exact geometry instead of the sparse stage (dense errors alone).
    #[arg(long)]
    pub true_rectification: bool,
    /// Only this mode (default: improved and paper).
    #[arg(long, value_parser = parse_mode)]
    pub mode: Option<Preset>,
    /// Only the cases whose label ("dome 640x480") contains this text.
    #[arg(long, value_name = "TEXT")]
    pub only: Option<String>,
    /// Override a dense parameter, KEY=VALUE as in [reconstruction.dense] (repeatable).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Render the micrographs without scan noise (the noise floor apart).
    #[arg(long)]
    pub noiseless: bool,
    /// Pixel dwell time of the rendered micrographs, µs (default 10): the scan noise falls as its square root.
    #[arg(long, value_name = "US", value_parser = positive_dwell, allow_hyphen_values = true)]
    pub dwell_us: Option<f64>,
    /// Only write the selected cases' micrographs (16-bit TIFF with tilt and pixel size) into DIR.
    #[arg(long, value_name = "DIR")]
    pub write_pairs: Option<PathBuf>,
    /// Also write each case's maps into DIR as PNGs: left micrograph, true and estimated height, error (disparity px).
    #[arg(long, value_name = "DIR")]
    pub dump: Option<PathBuf>,
}

fn parse_mode(s: &str) -> Result<Preset, String> {
    match s {
        "paper" => Ok(Preset::Paper),
        "improved" => Ok(Preset::Improved),
        _ => Err(format!("unknown mode `{s}`: paper or improved")),
    }
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
    match &args.which {
        Which::Acquisition { config } => {
            let met = match config {
                Some(path) => eval::acquisition::run_config(&opts, path)?,
                None => eval::acquisition::run(&opts)?,
            };
            if !met {
                return Ok(ExitCode::FAILURE);
            }
        }
        Which::Flow { set } => eval::flow::run(&opts, set)?,
        Which::Soak(a) => {
            let report = eval::soak::run_soak(&eval::soak::SoakOptions {
                jobs: a.jobs.unwrap_or(if opts.quick { 10 } else { 50 }),
                seed: a.seed,
                keep: a.keep,
                json: opts.json,
            })?;
            if !eval::soak::soak_passed(&report) {
                eprintln!("soak: the daemon missed its targets (see the problems above)");
                return Ok(ExitCode::FAILURE);
            }
        }
        Which::Kill(a) => {
            let report = eval::soak::run_kill(&eval::soak::KillOptions {
                rounds: a.rounds.unwrap_or(if opts.quick { 5 } else { 20 }),
                seed: a.seed,
                keep: a.keep,
                json: opts.json,
            })?;
            if !eval::soak::kill_passed(&report) {
                eprintln!("kill: the daemon missed its targets (see the problems above)");
                return Ok(ExitCode::FAILURE);
            }
        }
        Which::Dense(d) => eval::dense::run(
            &opts,
            &eval::dense::DenseEvalArgs {
                true_rectification: d.true_rectification,
                mode: d.mode,
                only: d.only.clone(),
                set: d.set.clone(),
                noiseless: d.noiseless,
                dwell_us: d.dwell_us,
                write_pairs: d.write_pairs.clone(),
                dump: d.dump.clone(),
            },
        )?,
        Which::Potamogeton { mode, set } => eval::potamogeton::run(&opts, *mode, set)?,
        Which::Sparse => eval::sparse::run(&opts)?,
    }
    Ok(ExitCode::SUCCESS)
}

/// A dwell time: finite, positive and at most one second per pixel.
fn positive_dwell(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .parse()
        .map_err(|_| format!("`{s}` is not a number of microseconds"))?;
    if v.is_finite() && v > 0.0 && v <= 1e6 {
        Ok(v)
    } else {
        Err(format!("the dwell time must be in (0, 1e6] µs, not {s}"))
    }
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use crate::cli::Cli;

    /// The dwell time is checked where it is parsed, with its range named.
    #[test]
    fn dwell_time_must_be_positive() {
        let parse = |v: &str| Cli::try_parse_from(["sdsem", "eval", "dense", "--dwell-us", v]);
        assert!(parse("40").is_ok());
        for bad in ["0", "-5", "nan", "fast"] {
            let e = parse(bad).expect_err(bad).to_string();
            assert!(
                e.contains("dwell") || e.contains("microseconds"),
                "{bad}: {e}"
            );
        }
    }
}
