//! What the daemon needs from whoever performs a job: the [`JobRunner`] trait.
//!
//! The acquisition run implements it; tests use fakes. The supervisor owns
//! the runner and drives it from its single main loop, one job at a time.
//!
//! # Contract
//!
//! [`JobRunner::check_links`]
//! - connects (or reconnects) the stage and imaging links if needed and proves
//!   they answer (e.g. a position query and a ping), then returns `Ok(())`;
//!   otherwise `Err(reason)` naming the link, the endpoint and the cause;
//! - moves nothing;
//! - may be dropped at any await point (the supervisor bounds it with
//!   `daemon.link_check_timeout_s` and abandons it on SIGTERM);
//! - picks up a changed configuration (the argument is the one in force, which
//!   SIGHUP may have replaced since the last call).
//!
//! [`JobRunner::stage_tilt`] and [`JobRunner::move_to_safe_tilt`] (after an unclean end)
//! - are called only after a successful `check_links`;
//! - read the stage's tilt, resp. bring it to `stage.safe_tilt_deg` verified, and
//!   return the tilt (degrees) or `Err(reason)`; the move may be dropped at an await
//!   point once the daemon must stop (after `daemon.stop_timeout_s`).
//!
//! [`JobRunner::run`]
//! - performs the whole job in `run_dir` (fresh and empty; its files are created
//!   through it, exclusively): `run.mcap`, the micrographs and the reconstruction outputs;
//! - reports what it is doing through [`JobContext::progress`] (it becomes the
//!   systemd STATUS line and `sdsem status`'s daemon line), at least every
//!   `daemon.stall_timeout_s` (default 30 min) or it is cancelled as stalled;
//! - keeps the async thread free: CPU-heavy work (reconstruction) goes to
//!   `spawn_blocking`/rayon and is awaited, so the main loop keeps feeding the
//!   systemd watchdog;
//! - once [`JobContext::cancel`] fires: stops motion, returns the stage to its
//!   safe tilt, finishes the MCAP (`finish()`), and returns
//!   [`JobOutcome::Interrupted`] within `daemon.stop_timeout_s` (default 12 s).
//!   A runner that overruns has its future dropped, the job is marked
//!   interrupted with "stage state unknown", and the daemon exits with failure;
//! - when a link is lost mid-job: brings the stage to safety if it still can,
//!   finishes the MCAP and returns [`JobOutcome::Failed`] with the cause; it
//!   drops the lost connection so the next `check_links` reconnects.
//!   Never retries a job by itself.

use std::future::Future;

use tokio::sync::watch;

use super::spool::JobRecord;
use crate::acquisition::RunDir;
use crate::config::Config;

/// How a job ended: the acquisition's own outcome.
pub use crate::acquisition::Outcome as JobOutcome;

/// Performs jobs for the daemon. See the [module documentation](self) for the contract.
pub trait JobRunner {
    /// Checks (and if needed re-establishes) the stage and imaging links.
    fn check_links(&mut self, config: &Config) -> impl Future<Output = Result<(), String>>;

    /// Reads the stage's tilt, degrees; moves nothing.
    fn stage_tilt(&mut self, config: &Config) -> impl Future<Output = Result<f64, String>>;

    /// Brings the stage to `stage.safe_tilt_deg`, verified; returns the tilt reached.
    fn move_to_safe_tilt(&mut self, config: &Config) -> impl Future<Output = Result<f64, String>>;

    /// Runs one job with its effective configuration, in `run_dir`.
    fn run(
        &mut self,
        job: &JobRecord,
        config: &Config,
        run_dir: &RunDir,
        ctx: JobContext,
    ) -> impl Future<Output = JobOutcome>;
}

/// What the supervisor hands a running job: a way to be told to stop and a
/// way to say what it is doing.
#[derive(Debug)]
pub struct JobContext {
    pub cancel: CancelSignal,
    pub progress: Progress,
}

// Cancellation is the acquisition's: the daemon asks, the run observes.
pub use crate::acquisition::{Cancel as CancelSignal, CancelHandle as CancelTrigger, cancel_pair};

/// Where a running job says what it is doing ("tilt 3° of 0…7°", "reconstructing").
#[derive(Debug, Clone)]
pub struct Progress {
    tx: watch::Sender<String>,
}

impl Progress {
    /// Reports what the job is doing now; also proves it is not stalled.
    pub fn report(&self, text: impl Into<String>) {
        self.tx.send_replace(text.into());
    }
}

/// A new progress channel: the job reports, the supervisor watches.
#[must_use]
pub fn progress_channel() -> (Progress, watch::Receiver<String>) {
    let (tx, rx) = watch::channel(String::from("starting"));
    (Progress { tx }, rx)
}
