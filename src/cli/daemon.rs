//! `sdsem daemon --config FILE [--spool DIR]`: the unattended service.
//! `sdsem daemon --ack [--spool DIR | --config FILE]`: an operator's acknowledgement
//! for a daemon that waits after an unclean end (`daemon.after_crash = "wait"`).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::SystemTime;

use clap::Args;

use crate::acquisition::{Instruments, RunDir, RunHooks, run_job};
use crate::config::Config;
use crate::daemon::{
    DaemonOptions, JobContext, JobOutcome, JobRecord, JobRunner, Spool, run_daemon,
};

#[derive(Debug, Args)]
pub struct DaemonArgs {
    /// Configuration file (TOML), read again on SIGHUP.
    #[arg(
        long,
        short = 'c',
        value_name = "FILE",
        required_unless_present = "ack"
    )]
    pub config: Option<PathBuf>,
    /// Override one key (repeatable), applied again on SIGHUP.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// The job spool (default: daemon.spool_dir, /var/lib/sdsem/spool).
    #[arg(long, value_name = "DIR")]
    pub spool: Option<PathBuf>,
    /// Do not run: tell the daemon on this spool that an operator has checked the stage
    /// after an unclean end, so that it moves the stage to its safe tilt and runs jobs again.
    #[arg(long)]
    pub ack: bool,
}

pub fn run(args: &DaemonArgs) -> anyhow::Result<ExitCode> {
    if args.ack {
        return acknowledge(args);
    }
    let Some(config_file) = args.config.clone() else {
        anyhow::bail!("--config FILE is required to run the daemon");
    };
    let options = DaemonOptions {
        config_file,
        overrides: args.overrides.clone(),
        spool: args.spool.clone(),
    };
    let config = crate::daemon::load_config(&options)?;
    let runner = acquisition_runner(&config)?;
    let stopped = run_daemon(&options, config, runner)?;
    tracing::info!(signal = %stopped.signal, "sdsem daemon exits");
    Ok(ExitCode::SUCCESS)
}

/// `--ack`: the acknowledgement file in the spool, seen by the daemon at its next turn.
fn acknowledge(args: &DaemonArgs) -> anyhow::Result<ExitCode> {
    let config = match &args.config {
        Some(path) => Some(Config::load(Some(path), &args.overrides)?),
        None => None,
    };
    let dir = super::submit::spool_dir(args.spool.as_deref(), config.as_ref())?;
    let spool = Spool::existing(&dir)?;
    let path = spool.acknowledge(SystemTime::now())?;
    match spool.daemon_status().and_then(|d| d.stage_check) {
        Some(check) if check.pending => println!(
            "acknowledged ({}): the daemon moves the stage to its safe tilt, then runs jobs",
            path.display()
        ),
        _ => println!(
            "acknowledged ({}), although the daemon is not waiting for it: it counts only for \
             a wait that begins later if it is still there then",
            path.display()
        ),
    }
    Ok(ExitCode::SUCCESS)
}

/// Builds the runner that performs jobs with the instruments.
fn acquisition_runner(_config: &Config) -> anyhow::Result<AcquisitionRunner> {
    Ok(AcquisitionRunner { instruments: None })
}

/// Runs each job as an acquisition, keeping the instruments connected between
/// jobs; a job that fails drops them, so the next link check reconnects, and
/// so does a reload that changes how they are reached.
struct AcquisitionRunner {
    instruments: Option<(Instruments, LinkSettings)>,
}

/// What the connection to the instruments depends on: the stage section
/// (endpoint, axes, timeouts, limits), the imaging source and how it is
/// reached (protocol, endpoint, watch folder, SharkSEM field and detector…),
/// the tilt axis a watch folder or SharkSEM source puts in its frames, and the
/// in-process simulator. Scan sizes and the rest apply per job.
#[derive(Debug, Clone, PartialEq)]
struct LinkSettings {
    stage: crate::stage::StageConfig,
    imaging: crate::imaging::ImagingConfig,
    tilt_axis_deg: Option<f64>,
    simulator: Option<sdsem_sim::SimConfig>,
}

impl LinkSettings {
    fn of(config: &Config) -> Self {
        Self {
            stage: config.stage.clone(),
            imaging: config.imaging.link_settings(),
            tilt_axis_deg: config.reconstruction.tilt_axis_deg,
            simulator: config.simulator.clone(),
        }
    }
}

impl JobRunner for AcquisitionRunner {
    async fn check_links(&mut self, config: &Config) -> Result<(), String> {
        let wanted = LinkSettings::of(config);
        if let Some((instruments, settings)) = &mut self.instruments {
            if *settings != wanted {
                tracing::info!("the reloaded configuration changes the links; reconnecting");
                self.instruments = None;
            } else {
                match instruments.stage.position().await {
                    // The SEM link reconnects by itself on its next request.
                    Ok(_) => {
                        return instruments
                            .imaging
                            .identify()
                            .await
                            .map(drop)
                            .map_err(|e| format!("SEM imaging link: {e}"));
                    }
                    Err(e) => {
                        tracing::warn!("stage link lost between jobs ({e}); reconnecting");
                        self.instruments = None;
                    }
                }
            }
        }
        let instruments = Instruments::connect(config)
            .await
            .map_err(|e| e.to_string())?;
        self.instruments = Some((instruments, wanted));
        Ok(())
    }

    async fn stage_tilt(&mut self, _config: &Config) -> Result<f64, String> {
        let (instruments, _) = self
            .instruments
            .as_mut()
            .ok_or("the instruments are not connected")?;
        match instruments.stage.position().await {
            Ok(p) => Ok(p.tilt_deg),
            Err(e) => {
                self.instruments = None;
                Err(format!("stage: {e}"))
            }
        }
    }

    async fn move_to_safe_tilt(&mut self, _config: &Config) -> Result<f64, String> {
        let (instruments, _) = self
            .instruments
            .as_mut()
            .ok_or("the instruments are not connected")?;
        let moved = instruments.stage.move_to_safe_tilt().await;
        match moved {
            Ok(_) => match instruments.stage.position().await {
                Ok(p) => Ok(p.tilt_deg),
                Err(e) => Err(format!("stage: {e}")),
            },
            Err(e) => {
                if let Err(stop) = instruments.stage.stop().await {
                    tracing::warn!("STP after the failed move failed too: {stop}");
                }
                self.instruments = None;
                Err(format!("stage: {e}"))
            }
        }
    }

    async fn run(
        &mut self,
        _job: &JobRecord,
        config: &Config,
        run_dir: &RunDir,
        ctx: JobContext,
    ) -> JobOutcome {
        let Some((instruments, _)) = self.instruments.as_mut() else {
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
