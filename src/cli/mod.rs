//! The command line (DESIGN §4): argument definitions and dispatch to the
//! commands. Each command lives in its own module and returns a `Result`;
//! `main` turns it into the exit code.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};

use crate::config::{Config, LogFormat};

mod acquire;
mod check_config;
mod daemon;
mod inspect;
pub mod logging;
mod manual;
mod probe;
mod progress;
mod replay;
mod status;
mod submit;
mod vision;

pub use logging::journal_error_prefix;

/// Unattended 3D surface reconstruction on a scanning electron microscope.
#[derive(Debug, Parser)]
#[command(name = "sdsem", version, about, long_about = None, after_help = manual::ROOT)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
    /// Log format on stderr: auto (readable on a terminal, JSON lines otherwise), text or json.
    #[arg(long, global = true, value_enum)]
    pub log_format: Option<LogFormat>,
    /// Log filter (tracing syntax, e.g. `debug` or `sdsem=debug,info`); RUST_LOG overrides it.
    #[arg(long, global = true)]
    pub log: Option<String>,
}

/// The configuration file and overrides, shared by every command that reads one.
#[derive(Debug, Clone, Args)]
pub struct ConfigArgs {
    /// Configuration file (TOML); see config/sdsem.toml for every key.
    #[arg(long, short = 'c', value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Override one key, e.g. `--set reconstruction.mode=paper` (repeatable; beats file and
    /// environment).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
}

impl ConfigArgs {
    /// Loads the layered configuration.
    ///
    /// # Errors
    /// When the file cannot be read or a key is unknown or invalid.
    pub fn load(&self) -> anyhow::Result<Config> {
        Ok(Config::load(self.config.as_deref(), &self.overrides)?)
    }
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// One run now: tilt series, end micrographs, reconstruction, record.
    /// The last line on stdout is the run directory.
    #[command(after_help = manual::ACQUIRE)]
    Acquire {
        #[command(flatten)]
        config: ConfigArgs,
    },
    /// Connect to the stage and the SEM, say what they are and where the stage is; moves nothing.
    #[command(after_help = manual::PROBE)]
    Probe {
        #[command(flatten)]
        config: ConfigArgs,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Height map, point cloud and mesh from a stereo pair (SD-SEM).
    #[command(after_help = manual::RECONSTRUCT)]
    Reconstruct(vision::ReconstructArgs),
    /// The sparse stage alone: matches and the rectified pair.
    #[command(after_help = manual::RECTIFY)]
    Rectify(vision::RectifyArgs),
    /// Dense SIFT-flow correspondence of two images, as Middlebury .flo.
    #[command(after_help = manual::FLOW)]
    Flow(vision::FlowArgs),
    /// Summarise a run record: topics, message counts, frames, outcome (works on truncated files).
    #[command(after_help = manual::INSPECT)]
    Inspect {
        /// The record, e.g. runs/sim-…/run.mcap.
        record: PathBuf,
        /// Print the summary as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Validate a configuration file (all layers) and print the effective configuration.
    #[command(after_help = manual::CHECK_CONFIG)]
    CheckConfig {
        /// The configuration file.
        file: PathBuf,
        /// Overrides, as for the other commands.
        #[arg(long = "set", value_name = "KEY=VALUE")]
        overrides: Vec<String>,
        /// Print nothing on success.
        #[arg(long, short)]
        quiet: bool,
    },
    /// The unattended service: run queued jobs one at a time (SIGTERM stops safely, SIGHUP reloads).
    #[command(after_help = manual::DAEMON)]
    Daemon(daemon::DaemonArgs),
    /// Validate a job file and queue it for the daemon (an invalid job is refused, never queued).
    #[command(after_help = manual::SUBMIT)]
    Submit(submit::SubmitArgs),
    /// List the spool's jobs (name, state, reason) and what the daemon is doing.
    #[command(after_help = manual::STATUS)]
    Status(status::StatusArgs),
    /// Reconstruct a run again from its record; says whether the height map is bit-identical.
    #[command(after_help = manual::REPLAY)]
    Replay(replay::ReplayArgs),
    /// Print the completion script of a shell (bash, zsh, fish, elvish, powershell).
    #[command(after_help = manual::COMPLETIONS)]
    Completions(manual::CompletionsArgs),
    /// Print the manual page of sdsem or of one command, as roff.
    #[command(after_help = manual::MAN)]
    Man(manual::ManArgs),
}

impl Command {
    /// The `[log]` section of the configuration this command reads, if it
    /// reads one and it loads.
    fn log_config(&self) -> Option<crate::config::LogConfig> {
        let config = match self {
            Self::Acquire { config } | Self::Probe { config, .. } => config.load().ok()?,
            Self::Reconstruct(args) => args.config.load().ok()?,
            Self::Rectify(args) => args.config.load().ok()?,
            Self::Flow(args) => args.config.load().ok()?,
            Self::Daemon(args) => {
                Config::load(Some(args.config.as_deref()?), &args.overrides).ok()?
            }
            _ => return None,
        };
        Some(config.log)
    }
}

impl Command {
    /// Whether the command must outlive the reader of its output: `acquire` and `daemon` drive
    /// the instruments (a run stopped half-way leaves the stage tilted). Every other command
    /// ends quietly by SIGPIPE when its reader goes away (`sdsem check-config … | head -1`).
    #[must_use]
    pub fn outlives_its_reader(&self) -> bool {
        matches!(self, Self::Acquire { .. } | Self::Daemon(_))
    }
}

/// The one line `main` prints for a failure: the causes joined by ": ", each once — a
/// cause whose text an outer message already holds ("cannot read x.tif: No such file or
/// directory") is not repeated.
#[must_use]
pub fn error_line(err: &anyhow::Error) -> String {
    let mut line = String::new();
    for cause in err.chain() {
        let text = cause.to_string();
        if line.contains(&text) {
            continue;
        }
        if !line.is_empty() {
            line.push_str(": ");
        }
        line.push_str(&text);
    }
    line
}

/// Runs one command.
///
/// # Errors
/// Whatever the command fails with; `main` prints it on one line.
pub fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    // The configuration's [log] section applies to the commands that read a
    // configuration; the command-line flags (and RUST_LOG) beat it. A file
    // that does not load is reported by the command itself, after this.
    let from_config = cli.command.log_config();
    logging::init(
        cli.log_format
            .or(from_config.as_ref().map(|l| l.format))
            .unwrap_or(LogFormat::Auto),
        cli.log
            .as_deref()
            .or(from_config.as_ref().map(|l| l.filter.as_str())),
    );
    match cli.command {
        Command::Acquire { config } => acquire::run(&config),
        Command::Probe { config, json } => probe::run(&config, json),
        Command::Inspect { record, json } => inspect::run(&record, json),
        Command::Reconstruct(args) => vision::run_reconstruct(&args),
        Command::Rectify(args) => vision::run_rectify(&args),
        Command::Flow(args) => vision::run_flow(&args),
        Command::CheckConfig {
            file,
            overrides,
            quiet,
        } => check_config::run(&file, &overrides, quiet),
        Command::Daemon(args) => daemon::run(&args),
        Command::Submit(args) => submit::run(&args),
        Command::Status(args) => status::run(&args),
        Command::Replay(args) => replay::run(&args),
        Command::Completions(args) => manual::completions(&args),
        Command::Man(args) => manual::man(&args),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, thiserror::Error)]
    #[error("cannot read {path}: {source}")]
    struct ReadFailed {
        path: String,
        source: std::io::Error,
    }

    /// An error that shows its source and also names it as `source()` reads once.
    #[test]
    fn a_cause_the_message_already_shows_is_printed_once() {
        let io = std::io::Error::from(std::io::ErrorKind::NotFound);
        let io_text = io.to_string();
        let err = anyhow::Error::new(ReadFailed {
            path: "nope.tif".into(),
            source: io,
        })
        .context("reconstruct refused");
        let line = error_line(&err);
        assert_eq!(line.matches(&io_text).count(), 1, "{line}");
        assert_eq!(
            line,
            format!("reconstruct refused: cannot read nope.tif: {io_text}")
        );
        // Distinct causes are all kept.
        let err = anyhow::anyhow!("inner").context("middle").context("outer");
        assert_eq!(error_line(&err), "outer: middle: inner");
    }
}
