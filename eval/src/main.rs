//! `sdsem-eval …`: the evaluation commands that print the figures our issues and reports
//! quote (ground truth from the simulator, real data from `--data` / `$SDSEM_DATA`). A
//! workspace crate of its own, so the shipped `sdsem` binary carries none of it:
//! `cargo run --release -p sdsem-eval -- dense --quick`.

mod acquisition;
mod dense;
mod flow;
mod large;
mod potamogeton;
mod soak;
mod sparse;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};
use sdsem::config::LogFormat;
use sdsem::vision::Preset;

/// Print measured figures against ground truth (simulator scenes, shared real data).
#[derive(Debug, Parser)]
#[command(name = "sdsem-eval", version, about, long_about = None, after_help = EXAMPLES)]
pub struct EvalArgs {
    #[command(subcommand)]
    pub which: Which,
    /// The shared evaluation data, with middlebury/ and potamogeton/ (default: $SDSEM_DATA).
    #[arg(long, global = true, value_name = "DIR")]
    pub data: Option<PathBuf>,
    /// A smaller, faster set of cases (a smoke run; the reported figures use the full set).
    #[arg(long, global = true)]
    pub quick: bool,
    /// Print the figures as JSON instead of a table.
    #[arg(long, global = true)]
    pub json: bool,
    /// Log format on stderr: auto (readable on a terminal, JSON lines otherwise), text or json.
    #[arg(long, global = true, value_enum)]
    pub log_format: Option<LogFormat>,
    /// Log filter (tracing syntax, e.g. `debug` or `sdsem=debug,info`); RUST_LOG overrides it.
    #[arg(long, global = true)]
    pub log: Option<String>,
}

#[derive(Debug, Subcommand)]
pub enum Which {
    /// The 0→7° series on the simulator: tilts, frames, stage I/O, re-centring
    /// against ground truth, real-time overhead, the record in the Python reader.
    #[command(after_help = EVAL_ACQUISITION)]
    Acquisition {
        /// Only the real-time figures, on the simulator of this configuration (its stage and
        /// imaging dialects, e.g. config/sim-zeiss.toml), at time scale 1.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
    },
    /// SIFT flow on Middlebury RubberWhale against its ground truth (paper Table 3).
    #[command(after_help = EVAL_FLOW)]
    Flow {
        /// Override a dense parameter, KEY=VALUE as in [reconstruction.dense] (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
    },
    /// The daemon as a process through consecutive short jobs with seeded
    /// random stage faults: final states, reasons, records, RSS and fds.
    #[command(after_help = EVAL_SOAK)]
    Soak(SoakArgs),
    /// `kill -9` of the daemon at random moments, each followed by a restart:
    /// no job lost or re-run, every record readable.
    #[command(after_help = EVAL_KILL)]
    Kill(KillArgs),
    /// The dense stage on the simulator's ground-truth scenes: coverage, RMSE, disparity error, scale.
    #[command(after_help = EVAL_DENSE)]
    Dense(DenseArgs),
    /// Agreement of the Potamogeton height maps from three tilt pairs (real Zeiss data).
    #[command(after_help = EVAL_POTAMOGETON)]
    Potamogeton {
        /// Only this mode (default: improved and paper).
        #[arg(long, value_parser = parse_mode)]
        mode: Option<Preset>,
        /// Override a dense parameter, KEY=VALUE as in [reconstruction.dense] (repeatable).
        #[arg(long = "set", value_name = "KEY=VALUE")]
        set: Vec<String>,
        /// Write each pair's height map (`MODE_RIGHT_height.f32`, raw little-endian float32,
        /// µm, NaN unknown) and reasons (`MODE_RIGHT_unknown.u8`, confidence.tif's codes) on
        /// pot_03's grid (1536 × 2048, row-major) into this directory.
        #[arg(long, value_name = "DIR")]
        dump: Option<PathBuf>,
    },
    /// The sparse stage (SIFT, ORSA, rectification): simulator pairs against their true
    /// correspondences, the grid over several seeds, the Potamogeton pairs beside the paper's
    /// Table 2, and the time per step at 1280×960.
    #[command(after_help = EVAL_SPARSE)]
    Sparse,
    /// A height map (`sdsem reconstruct`'s height.tif) against a simulated pair's truth
    /// (`dense --write-pairs`' `_truth.tif`): coverage, RMSE without the best plane, scale.
    ScoreHeight {
        /// The truth: float32 µm, NaN where the pair does not see the pixel in both.
        truth: PathBuf,
        /// The estimated height map on the same (left) grid.
        height: PathBuf,
    },
}

#[derive(Debug, Args)]
pub struct SoakArgs {
    /// The `sdsem` binary whose daemon is measured (default: the one beside sdsem-eval;
    /// `cargo build --release -p sdsem` first, or it may be stale).
    #[arg(long, value_name = "FILE")]
    pub sdsem: Option<PathBuf>,
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
    /// The `sdsem` binary whose daemon is killed (default: the one beside sdsem-eval;
    /// `cargo build --release -p sdsem` first, or it may be stale).
    #[arg(long, value_name = "FILE")]
    pub sdsem: Option<PathBuf>,
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
    /// Rectify with the instrument's geometry (tilt axis, tiles' correlation) as if the sparse stage had failed, checked by the dense stage.
    #[arg(long, conflicts_with = "true_rectification")]
    pub instrument: bool,
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
    /// Only write the selected cases' micrographs (16-bit TIFF with tilt and pixel size) and their true heights (`_truth.tif`) into DIR.
    #[arg(long, value_name = "DIR")]
    pub write_pairs: Option<PathBuf>,
    /// Render the selected cases at WxH instead of their own size (same scene, field and seed; for the large-micrograph figures).
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    pub size: Option<(usize, usize)>,
    /// Also write each case's maps into DIR as PNGs: left micrograph, true and estimated height, error (disparity px).
    #[arg(long, value_name = "DIR")]
    pub dump: Option<PathBuf>,
}

/// A frame size `WxH`, each side 16 to 65536 pixels.
fn parse_size(s: &str) -> Result<(usize, usize), String> {
    let bad = || format!("the size must be WxH (e.g. 4096x3072), each side 16 to 65536, not {s}");
    let (w, h) = s.split_once(['x', 'X', '×']).ok_or_else(bad)?;
    let side = |v: &str| {
        v.trim()
            .parse::<usize>()
            .ok()
            .filter(|v| (16..=65536).contains(v))
    };
    Ok((side(w).ok_or_else(bad)?, side(h).ok_or_else(bad)?))
}

fn parse_mode(s: &str) -> Result<Preset, String> {
    match s {
        "paper" => Ok(Preset::Paper),
        "improved" => Ok(Preset::Improved),
        _ => Err(format!("unknown mode `{s}`: paper or improved")),
    }
}

/// What every evaluation takes.
#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// The shared evaluation data (`--data`, else `$SDSEM_DATA`), when given.
    pub data_dir: Option<PathBuf>,
    /// A smaller, faster set of cases (a smoke run, not the reported figures).
    pub quick: bool,
    /// Print the figures as JSON on stdout instead of a table.
    pub json: bool,
}

impl EvalOptions {
    /// The shared data folder, for the evaluations that read real data.
    ///
    /// # Errors
    /// When neither `--data` nor `$SDSEM_DATA` names a folder.
    pub fn data(&self) -> anyhow::Result<&Path> {
        match &self.data_dir {
            None => anyhow::bail!(
                "no evaluation data: pass --data DIR or set SDSEM_DATA to the shared folder with middlebury/ and potamogeton/"
            ),
            Some(dir) if !dir.is_dir() => anyhow::bail!(
                "the evaluation data folder {} does not exist: pass --data DIR or set SDSEM_DATA",
                dir.display()
            ),
            Some(dir) => Ok(dir),
        }
    }
}

/// `--data`, else `$SDSEM_DATA` (an empty value counts as unset).
fn data_dir(flag: Option<&Path>) -> Option<PathBuf> {
    flag.map(Path::to_path_buf).or_else(|| {
        std::env::var_os("SDSEM_DATA")
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    })
}

/// The `sdsem` binary the daemon evaluations start: `--sdsem`, else the one beside this binary
/// (cargo puts a workspace's binaries in one folder).
fn sdsem_binary(flag: Option<&Path>) -> anyhow::Result<PathBuf> {
    if let Some(path) = flag {
        anyhow::ensure!(
            path.is_file(),
            "{} is not a file: pass --sdsem FILE, the sdsem binary",
            path.display()
        );
        return Ok(path.to_path_buf());
    }
    let me = std::env::current_exe().map_err(|e| {
        anyhow::anyhow!("cannot find this binary's folder ({e}): pass --sdsem FILE")
    })?;
    let beside = me.with_file_name("sdsem");
    anyhow::ensure!(
        beside.is_file(),
        "no sdsem binary beside {}: build it (cargo build --release -p sdsem) or pass --sdsem FILE",
        me.display()
    );
    Ok(beside)
}

/// Runs one evaluation.
///
/// # Errors
/// When its data are missing or a stage fails.
pub fn run(args: &EvalArgs) -> anyhow::Result<ExitCode> {
    let opts = EvalOptions {
        data_dir: data_dir(args.data.as_deref()),
        quick: args.quick,
        json: args.json,
    };
    match &args.which {
        Which::Acquisition { config } => {
            let met = match config {
                Some(path) => acquisition::run_config(&opts, path)?,
                None => acquisition::run(&opts)?,
            };
            if !met {
                return Ok(ExitCode::FAILURE);
            }
        }
        Which::Flow { set } => flow::run(&opts, set)?,
        Which::Soak(a) => {
            let report = soak::run_soak(&soak::SoakOptions {
                sdsem: sdsem_binary(a.sdsem.as_deref())?,
                jobs: a.jobs.unwrap_or(if opts.quick { 10 } else { 50 }),
                seed: a.seed,
                keep: a.keep,
                json: opts.json,
            })?;
            if !soak::soak_passed(&report) {
                eprintln!("soak: the daemon missed its targets (see the problems above)");
                return Ok(ExitCode::FAILURE);
            }
        }
        Which::Kill(a) => {
            let report = soak::run_kill(&soak::KillOptions {
                sdsem: sdsem_binary(a.sdsem.as_deref())?,
                rounds: a.rounds.unwrap_or(if opts.quick { 5 } else { 20 }),
                seed: a.seed,
                keep: a.keep,
                json: opts.json,
            })?;
            if !soak::kill_passed(&report) {
                eprintln!("kill: the daemon missed its targets (see the problems above)");
                return Ok(ExitCode::FAILURE);
            }
        }
        Which::Dense(d) => dense::run(
            &opts,
            &dense::DenseEvalArgs {
                true_rectification: d.true_rectification,
                instrument: d.instrument,
                mode: d.mode,
                only: d.only.clone(),
                set: d.set.clone(),
                noiseless: d.noiseless,
                dwell_us: d.dwell_us,
                write_pairs: d.write_pairs.clone(),
                size: d.size,
                dump: d.dump.clone(),
            },
        )?,
        Which::Potamogeton { mode, set, dump } => {
            potamogeton::run(&opts, *mode, set, dump.as_deref())?;
        }
        Which::Sparse => sparse::run(&opts)?,
        Which::ScoreHeight { truth, height } => large::run_score(truth, height, opts.json)?,
    }
    Ok(ExitCode::SUCCESS)
}

fn main() -> ExitCode {
    let args = EvalArgs::parse();
    // `soak` and `kill` own daemon processes and must outlive the reader of their output;
    // the others end quietly by SIGPIPE when it goes away, as `sdsem` does.
    if !matches!(args.which, Which::Soak(_) | Which::Kill(_)) {
        // SAFETY: `signal` with SIG_DFL installs no handler; called before any other thread.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    sdsem::cli::logging::init(
        args.log_format.unwrap_or(LogFormat::Auto),
        args.log.as_deref(),
    );
    match run(&args) {
        Ok(code) => code,
        Err(err) => {
            eprintln!(
                "{}error: {}",
                sdsem::cli::journal_error_prefix(),
                sdsem::cli::error_line(&err)
            );
            ExitCode::FAILURE
        }
    }
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

const EXAMPLES: &str = "\
Examples:
  cargo run --release -p sdsem-eval -- dense --quick
  sdsem-eval dense --mode paper --only \"dome 640x480\" --set refine.window_sigma=4
  SDSEM_DATA=/srv/sdsem-data sdsem-eval flow --json";

const EVAL_ACQUISITION: &str = "\
Examples:
  sdsem-eval acquisition
  sdsem-eval acquisition --quick --json
  sdsem-eval acquisition --config config/sim-zeiss.toml
      real-time overhead of another dialect (here RemCon32 + watch folder)";

const EVAL_SPARSE: &str = "\
Examples:
  sdsem-eval sparse --quick --data /srv/sdsem-data
  SDSEM_DATA=/srv/sdsem-data sdsem-eval sparse --json";

const EVAL_DENSE: &str = "\
Examples:
  sdsem-eval dense --quick
  sdsem-eval dense --true-rectification --only dome
  sdsem-eval dense --dwell-us 40 --write-pairs pairs/
  sdsem-eval dense --only \"dome 1280x960\" --size 4096x3072 --write-pairs large/
      a large pair and its truth; then sdsem reconstruct …, and
  sdsem-eval score-height large/dome_4096x3072_truth.tif out/height.tif";

const EVAL_FLOW: &str = "\
Examples:
  sdsem-eval flow --data /srv/sdsem-data
  sdsem-eval flow --set alpha=300";

const EVAL_POTAMOGETON: &str = "\
Examples:
  sdsem-eval potamogeton --mode improved
  sdsem-eval potamogeton --set fill_max_gap=96";

const EVAL_SOAK: &str = "\
Examples:
  sdsem-eval soak --quick
  sdsem-eval soak --jobs 200 --seed 7 --keep --sdsem target/release/sdsem";

const EVAL_KILL: &str = "\
Examples:
  sdsem-eval kill --quick
  sdsem-eval kill --rounds 40 --seed 2";

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    /// The dwell time is checked where it is parsed, with its range named.
    #[test]
    fn dwell_time_must_be_positive() {
        let parse = |v: &str| EvalArgs::try_parse_from(["sdsem-eval", "dense", "--dwell-us", v]);
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
