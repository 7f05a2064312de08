//! `sdsem acquire --config FILE`: one run now — tilt series, capture,
//! reconstruct, record. The last line on stdout is the run directory.

use std::process::ExitCode;

use anyhow::Context;
use tracing::warn;

use super::{ConfigArgs, logging};
use crate::acquisition::{CancelHandle, Outcome, RunDir, RunHooks, RunName, cancel_pair, run_job};

/// Exit code of a run stopped by the operator (as a shell reports SIGINT).
const EXIT_INTERRUPTED: u8 = 130;

pub fn run(args: &ConfigArgs) -> anyhow::Result<ExitCode> {
    // Everything is validated here, before any command reaches an instrument.
    let config = args.load()?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    runtime.block_on(async {
        let name = RunName::new(&config.run.name).context("run.name")?;
        let run_dir = RunDir::create(&config.run.output_dir, &name, std::time::SystemTime::now())?;
        let (handle, cancel) = cancel_pair();
        tokio::spawn(cancel_on_signals(handle));
        let display = super::progress::StageDisplay::on_stderr();
        let hooks = RunHooks {
            cancel,
            logs: logging::record_logs(),
            progress: &|stage| display.observe(stage),
        };
        let report = run_job(&config, None, &run_dir, hooks).await;
        display.finish(report.is_ok());
        let report = report?;
        if let Err(e) = &report.record {
            eprintln!("warning: the run record is incomplete: {e}");
        }
        let code = match &report.outcome {
            Outcome::Completed => ExitCode::SUCCESS,
            Outcome::Failed { reason } => {
                eprintln!("run failed: {reason}");
                ExitCode::FAILURE
            }
            Outcome::Interrupted { reason } => {
                eprintln!("run interrupted: {reason}");
                ExitCode::from(EXIT_INTERRUPTED)
            }
        };
        println!("{}", report.run_dir.display());
        Ok(code)
    })
}

/// Ctrl-C and SIGTERM stop the run safely (the stage returns to its safe tilt).
pub(crate) async fn cancel_on_signals(handle: CancelHandle) {
    use tokio::signal::unix::{SignalKind, signal};
    let mut term = match signal(SignalKind::terminate()) {
        Ok(s) => s,
        Err(e) => {
            warn!("cannot listen for SIGTERM: {e}");
            return;
        }
    };
    let reason = tokio::select! {
        _ = tokio::signal::ctrl_c() => "interrupted by Ctrl-C (SIGINT)",
        _ = term.recv() => "stopped by SIGTERM",
    };
    warn!("{reason}: stopping the stage and returning it to the safe tilt");
    handle.cancel(reason);
}
