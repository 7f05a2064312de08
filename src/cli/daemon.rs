//! `sdsem daemon --config FILE [--spool DIR]`: the unattended service.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;

use crate::config::Config;
use crate::daemon::{DaemonOptions, JobContext, JobOutcome, JobRecord, JobRunner, run_daemon};

#[derive(Debug, Args)]
pub struct DaemonArgs {
    /// Configuration file (TOML), read again on SIGHUP.
    #[arg(long, short = 'c', value_name = "FILE")]
    pub config: PathBuf,
    /// Override one key (repeatable), applied again on SIGHUP.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// The job spool (default: daemon.spool_dir, /var/lib/sdsem/spool).
    #[arg(long, value_name = "DIR")]
    pub spool: Option<PathBuf>,
}

pub fn run(args: &DaemonArgs) -> anyhow::Result<ExitCode> {
    let options = DaemonOptions {
        config_file: args.config.clone(),
        overrides: args.overrides.clone(),
        spool: args.spool.clone(),
    };
    let config = crate::daemon::load_config(&options)?;
    let runner = acquisition_runner(&config)?;
    let stopped = run_daemon(&options, config, runner)?;
    tracing::info!(signal = %stopped.signal, "sdsem daemon exits");
    Ok(ExitCode::SUCCESS)
}

// ───────────────────────── ACQUISITION RUNNER PLUG-IN POINT ─────────────────────────
// The lead replaces `acquisition_runner` with the real one (the acquisition run
// implementing `crate::daemon::JobRunner`, see its contract in daemon/runner.rs)
// and deletes `NoAcquisitionRunner`. Until then `sdsem daemon` refuses to start
// rather than pretend: `NoAcquisitionRunner` has no values, so no job can run.

/// Builds the runner that performs jobs with the instruments.
fn acquisition_runner(_config: &Config) -> anyhow::Result<NoAcquisitionRunner> {
    anyhow::bail!(
        "this build of sdsem has no acquisition runner yet, so `sdsem daemon` cannot run jobs \
         (it is plugged in at src/cli/daemon.rs when `sdsem acquire` lands)"
    )
}

/// The absence of a runner: an empty enum, so it can never be constructed.
enum NoAcquisitionRunner {}

impl JobRunner for NoAcquisitionRunner {
    async fn check_links(&mut self, _config: &Config) -> Result<(), String> {
        match *self {}
    }

    async fn run(
        &mut self,
        _job: &JobRecord,
        _config: &Config,
        _run_dir: &std::path::Path,
        _ctx: JobContext,
    ) -> JobOutcome {
        match *self {}
    }
}
