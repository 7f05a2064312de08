//! `sdsem daemon --config FILE [--spool DIR]`: the unattended service.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Args;

use crate::acquisition::{Instruments, RunHooks, run_job};
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

/// Builds the runner that performs jobs with the instruments.
fn acquisition_runner(_config: &Config) -> anyhow::Result<AcquisitionRunner> {
    Ok(AcquisitionRunner { instruments: None })
}

/// Runs each job as an acquisition, keeping the instruments connected between
/// jobs; a job that fails drops them, so the next link check reconnects.
struct AcquisitionRunner {
    instruments: Option<Instruments>,
}

impl JobRunner for AcquisitionRunner {
    async fn check_links(&mut self, config: &Config) -> Result<(), String> {
        if let Some(instruments) = &mut self.instruments {
            match instruments.stage.position().await {
                Ok(_) => return Ok(()),
                Err(e) => {
                    tracing::warn!("stage link lost between jobs ({e}); reconnecting");
                    self.instruments = None;
                }
            }
        }
        let instruments = Instruments::connect(config)
            .await
            .map_err(|e| e.to_string())?;
        self.instruments = Some(instruments);
        Ok(())
    }

    async fn run(
        &mut self,
        _job: &JobRecord,
        config: &Config,
        run_dir: &Path,
        ctx: JobContext,
    ) -> JobOutcome {
        let Some(instruments) = self.instruments.as_mut() else {
            return JobOutcome::Failed {
                reason: "the instruments are not connected".into(),
            };
        };
        let progress = ctx.progress.clone();
        let report = move |line: &str| progress.report(line);
        let hooks = RunHooks {
            cancel: ctx.cancel,
            logs: super::logging::record_logs(),
            progress: &report,
        };
        let outcome = match run_job(config, Some(instruments), run_dir, hooks).await {
            Ok(report) => report.outcome,
            Err(e) => JobOutcome::Failed {
                reason: e.to_string(),
            },
        };
        if !outcome.is_completed() {
            // Whatever went wrong may have been the link: start the next job afresh.
            self.instruments = None;
        }
        outcome
    }
}
