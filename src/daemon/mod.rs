//! The unattended service: job spool, supervisor, signals, systemd notification.
//!
//! ```text
//!  sdsem submit JOB.toml ──validate──▶ SPOOL/queued/<id>.json
//!                                            │ oldest first, one at a time
//!  SIGTERM/SIGINT/SIGHUP ──▶ Control ──▶ Supervisor ──▶ JobRunner (the acquisition run)
//!                                            │               └─ run dir: run.mcap, left/right.tif, height.*
//!                                            ├─ READY / STATUS / WATCHDOG ──▶ systemd
//!                                            └─ SPOOL/{running,done,failed,interrupted,rejected}/
//!  sdsem status ◀── reads SPOOL (records + daemon.json)
//! ```
//!
//! - [`job`]: the job file and the configuration a job runs with.
//! - [`spool`]: the crash-safe queue on disk, owned by one daemon at a time.
//! - [`runner`]: the [`JobRunner`] trait the acquisition implements, and its contract.
//! - [`supervisor`]: the main loop.
//! - [`notify`], [`disk`]: the service manager and the filesystem, behind traits for tests.

pub mod config;
pub mod disk;
pub mod job;
pub mod notify;
pub mod runner;
pub mod spool;
pub mod supervisor;
pub mod untrusted;
pub mod utc;

use std::path::PathBuf;
use std::time::Duration;

pub use config::{AfterCrash, DaemonConfig};
pub use job::{JobError, JobSpec};
pub use notify::{Notice, Notifier, SystemdNotifier};
pub use runner::{CancelSignal, JobContext, JobOutcome, JobRunner, Progress};
pub use spool::{JobId, JobRecord, JobState, OwnedSpool, Spool, SpoolError, Tamper};
pub use supervisor::{Control, Stopped, Supervisor, SupervisorError};

use crate::config::{Config, ConfigError};

/// What `sdsem daemon` was started with.
#[derive(Debug, Clone)]
pub struct DaemonOptions {
    /// The configuration file, read again on SIGHUP.
    pub config_file: PathBuf,
    /// `--set key=value` overrides, applied again on SIGHUP.
    pub overrides: Vec<String>,
    /// `--spool DIR`, beating `daemon.spool_dir`.
    pub spool: Option<PathBuf>,
}

/// Why the daemon could not start or had to stop abnormally.
#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    #[error(transparent)]
    Config(#[from] ConfigError),
    #[error("invalid configuration: {0}")]
    DaemonConfig(String),
    #[error("cannot {action}: {source}")]
    Os {
        action: &'static str,
        source: std::io::Error,
    },
    #[error(transparent)]
    Spool(#[from] SpoolError),
    #[error(transparent)]
    Supervisor(#[from] SupervisorError),
}

/// Loads and checks the daemon's configuration (every layer, `[daemon]` included).
///
/// # Errors
/// [`DaemonError::Config`] / [`DaemonError::DaemonConfig`] naming the key.
pub fn load_config(options: &DaemonOptions) -> Result<Config, DaemonError> {
    let config = Config::load(Some(&options.config_file), &options.overrides)?;
    config
        .daemon
        .validate()
        .map_err(DaemonError::DaemonConfig)?;
    Ok(config)
}

/// Runs the service until SIGTERM/SIGINT: takes the spool, recovers it,
/// notifies systemd, runs queued jobs with `runner`, reloads on SIGHUP.
/// `config` is what [`load_config`] gave for `options` (the caller may need
/// it to build the runner); reloads read `options` again.
///
/// # Errors
/// [`DaemonError`] when it cannot start (spool owned by another daemon,
/// signals) or had to give up (spool unwritable, a job that did not stop in time).
pub fn run_daemon<R: JobRunner>(
    options: &DaemonOptions,
    config: Config,
    runner: R,
) -> Result<Stopped, DaemonError> {
    let spool_dir = options
        .spool
        .clone()
        .unwrap_or_else(|| config.daemon.spool_dir.clone());
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("sdsem-daemon")
        .build()
        .map_err(|source| DaemonError::Os {
            action: "start the async runtime",
            source,
        })?;
    let result = runtime.block_on(async {
        let control = forward_signals()?;
        let spool = Spool::open(&spool_dir)?.lock()?;
        let reload_options = options.clone();
        let reloader: supervisor::Reloader =
            Box::new(move || load_config(&reload_options).map_err(|e| e.to_string()));
        let stopped = Supervisor::new(spool, config, runner, control)
            .with_notifier(SystemdNotifier::default())
            .with_watchdog(SystemdNotifier::watchdog_interval())
            .with_reloader(reloader)
            .run()
            .await?;
        Ok(stopped)
    });
    // Do not wait for blocking work a cancelled job may have left behind.
    runtime.shutdown_timeout(Duration::from_secs(1));
    result
}

/// Turns SIGTERM and SIGINT into [`Control::Stop`] and SIGHUP into [`Control::Reload`].
fn forward_signals() -> Result<tokio::sync::mpsc::Receiver<Control>, DaemonError> {
    use tokio::signal::unix::{SignalKind, signal};
    let os = |source| DaemonError::Os {
        action: "install the signal handlers",
        source,
    };
    let mut term = signal(SignalKind::terminate()).map_err(os)?;
    let mut int = signal(SignalKind::interrupt()).map_err(os)?;
    let mut hup = signal(SignalKind::hangup()).map_err(os)?;
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    tokio::spawn(async move {
        loop {
            let control = tokio::select! {
                _ = term.recv() => Control::Stop { signal: "SIGTERM".into() },
                _ = int.recv() => Control::Stop { signal: "SIGINT".into() },
                _ = hup.recv() => Control::Reload,
            };
            if tx.send(control).await.is_err() {
                break;
            }
        }
    });
    Ok(rx)
}
