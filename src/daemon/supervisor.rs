//! The supervisor: the daemon's one main loop.
//!
//! On start it recovers the spool (a job left `running` by a crash becomes
//! `interrupted`, never re-run), checks the links and says READY. After an
//! unclean end (a job left running, or a previous daemon that never said
//! "stopped") it reads the stage before anything else and, off its safe tilt,
//! moves it there or waits for an operator (`daemon.after_crash`), saying so in
//! the journal, STATUS and `daemon.json`. Then, one job at a time, oldest
//! first: validate the job under the configuration in force (`rejected` if it
//! does not fit), wait while free disk space is under
//! `daemon.min_free_gib` (the job stays queued; STATUS says why), check the
//! links (on failure wait with capped exponential backoff, the job stays
//! queued), create the run directory, mark the job `running`, run it, record
//! its final state and reason. A final state that cannot be written (a full
//! disk) is kept and written again later; the daemon does not exit for it, nor
//! for anything found in the spool.
//!
//! Control arrives as [`Control`] messages (the binary turns SIGTERM/SIGINT and
//! SIGHUP into them): a stop cancels the running job, waits for it at most
//! `daemon.stop_timeout_s`, marks it `interrupted` and ends the loop; a reload
//! swaps the configuration only if the new one is valid, and applies to the
//! next job. WATCHDOG=1 is sent from this loop only, so a stuck loop stops the
//! pings and systemd restarts the service; so does a spool directory that was
//! moved away. A tampered `daemon.lock` is written again and reported, never a
//! reason to stop pinging. Time is tokio's (a paused clock in tests).

use std::future::Future;
use std::time::{Duration, SystemTime};

use tokio::sync::mpsc;
use tokio::time::{Instant, Interval, MissedTickBehavior};
use tracing::{error, info, warn};

use super::config::{AfterCrash, DaemonConfig, GIB};
use super::disk::{DiskSpace, Statvfs};
use super::notify::{Notice, Notifier};
use super::runner::{JobContext, JobOutcome, JobRunner, cancel_pair, progress_channel};
use super::spool::{
    DaemonStatus, JobId, JobRecord, JobState, OwnedSpool, SpoolError, StageCheck, Tamper,
    Unreadable,
};
use super::utc;
use crate::acquisition::RunDir;
use crate::acquisition::run_dir::printable;
use crate::config::Config;

/// A request to the supervisor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Control {
    /// Stop: cancel the running job safely, mark it interrupted, end the loop.
    /// `signal` names the cause for the records (`SIGTERM`).
    Stop { signal: String },
    /// Reload the configuration (SIGHUP).
    Reload,
}

/// Produces a fresh, validated configuration on reload, or says why not.
pub type Reloader = Box<dyn FnMut() -> Result<Config, String> + Send>;

/// How the loop ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Stopped {
    /// What asked for the stop.
    pub signal: String,
    /// The job that was running and is now `interrupted`, if any.
    pub interrupted: Option<JobId>,
}

/// Why the supervisor had to give up.
#[derive(Debug, thiserror::Error)]
pub enum SupervisorError {
    #[error(transparent)]
    Spool(#[from] SpoolError),
    #[error(
        "job {job} ({name}) did not stop within {timeout:?} after {cause}; it is marked \
         interrupted, but the stage may not be at its safe tilt: check it before the next run"
    )]
    RunnerOverran {
        job: JobId,
        name: String,
        timeout: Duration,
        cause: String,
    },
}

/// The daemon's main loop with everything it drives.
pub struct Supervisor<R> {
    runner: R,
    core: Core,
}

/// Everything but the runner, so the loop can use it while the runner's
/// future holds the runner.
struct Core {
    spool: OwnedSpool,
    config: Config,
    control: mpsc::Receiver<Control>,
    control_open: bool,
    notifier: Box<dyn Notifier + Send>,
    disk: Box<dyn DiskSpace + Send>,
    reloader: Option<Reloader>,
    watchdog: Option<Interval>,
    stop: Option<String>,
    status: String,
    state: &'static str,
    links: Option<Result<(), String>>,
    link_failures: u32,
    waiting_for_disk: bool,
    unhealthy_logged: bool,
    status_write_failed: bool,
    /// What the daemon wants a human to know (tampering), kept in `daemon.json`.
    warnings: Vec<String>,
    /// The stage check after the last unclean end.
    stage_check: Option<StageCheck>,
    /// The acknowledgement file was cleared when the wait for an operator began.
    hold_started: bool,
    /// An operator acknowledged the wait: the stage may be moved.
    acknowledged: bool,
    /// A job's final state that could not be written yet (a full disk).
    pending_finish: Option<PendingFinish>,
    /// `daemon.json` must be written again even if the STATUS line is unchanged.
    publish_due: bool,
}

/// A job's end, waiting to be written into the spool.
struct PendingFinish {
    record: JobRecord,
    state: JobState,
    reason: Option<String>,
    at: SystemTime,
}

impl<R: JobRunner> Supervisor<R> {
    /// A supervisor for `spool`, configured by `config`, running jobs with
    /// `runner`, controlled through `control`. By default it notifies nobody,
    /// pings no watchdog, measures the real disk and cannot reload.
    pub fn new(
        spool: OwnedSpool,
        config: Config,
        runner: R,
        control: mpsc::Receiver<Control>,
    ) -> Self {
        struct Silent;
        impl Notifier for Silent {
            fn notify(&mut self, _: Notice) {}
        }
        Self {
            runner,
            core: Core {
                spool,
                config,
                control,
                control_open: true,
                notifier: Box::new(Silent),
                disk: Box::new(Statvfs),
                reloader: None,
                watchdog: None,
                stop: None,
                status: String::new(),
                state: "starting",
                links: None,
                link_failures: 0,
                waiting_for_disk: false,
                unhealthy_logged: false,
                status_write_failed: false,
                warnings: Vec::new(),
                stage_check: None,
                hold_started: false,
                acknowledged: false,
                pending_finish: None,
                publish_due: false,
            },
        }
    }

    /// Where READY, STATUS, WATCHDOG go.
    #[must_use]
    pub fn with_notifier(mut self, notifier: impl Notifier + Send + 'static) -> Self {
        self.core.notifier = Box::new(notifier);
        self
    }

    /// Send WATCHDOG=1 this often (half the unit's `WatchdogSec=`).
    #[must_use]
    pub fn with_watchdog(mut self, interval: Option<Duration>) -> Self {
        self.core.watchdog = interval.filter(|d| !d.is_zero()).map(|period| {
            let mut i = tokio::time::interval(period);
            i.set_missed_tick_behavior(MissedTickBehavior::Delay);
            i
        });
        self
    }

    /// How free disk space is measured.
    #[must_use]
    pub fn with_disk(mut self, disk: impl DiskSpace + Send + 'static) -> Self {
        self.core.disk = Box::new(disk);
        self
    }

    /// How a reload obtains the new configuration.
    #[must_use]
    pub fn with_reloader(mut self, reloader: Reloader) -> Self {
        self.core.reloader = Some(reloader);
        self
    }

    /// Runs until stopped.
    ///
    /// # Errors
    /// [`SupervisorError::Spool`] when the spool cannot be written (the job
    /// states would be lost); [`SupervisorError::RunnerOverran`] when a job
    /// did not stop in time after a stop or stall.
    pub async fn run(mut self) -> Result<Stopped, SupervisorError> {
        let now = SystemTime::now();
        let previous = self.core.spool.daemon_status();
        let recovery = self.core.spool.recover(now)?;
        for job in &recovery.interrupted {
            warn!(job = job.id.0, name = %printable(&job.name, 64), "{}", super::spool::CRASH_REASON);
        }
        log_quarantined(&recovery.quarantined);
        for problem in &recovery.problems {
            error!("spool recovery: {problem}");
        }
        self.core.stage_check = unclean_end(previous.as_ref(), &recovery, now);
        if let Some(check) = self.core.stage_check.as_ref().filter(|c| c.pending) {
            warn!(
                cause = %check.cause,
                "the previous daemon ended uncleanly: the stage is read, and brought to its safe \
                 tilt, before any job"
            );
        }
        if let Err(e) = self.core.spool.write_config_snapshot(&self.core.config) {
            warn!(error = %e, "cannot publish the configuration: `sdsem submit` checks against its own");
        }
        self.core
            .set_status("starting: checking the stage and imaging links");
        // READY once the links were checked, whatever the answer: a stage that
        // is off for the night is waited for (with backoff), not a start failure.
        self.core.state = "ready";
        let links_up = self.links_ready("starting").await;
        self.core.notifier.notify(Notice::Ready);
        info!(spool = %self.core.spool.root().display(), links_up, "daemon ready");
        if !links_up {
            self.core.pause_for_backoff().await;
        }

        let mut interrupted = None;
        while self.core.stop.is_none() {
            if let Some(id) = self.step().await? {
                interrupted = Some(id);
            }
        }
        let signal = self.core.stop.take().unwrap_or_default();
        self.core.state = "stopped";
        self.core.set_status(&format!("stopped ({signal})"));
        info!(%signal, "daemon stopped");
        Ok(Stopped {
            signal,
            interrupted,
        })
    }

    /// One turn of the loop: wait, reject, or run the oldest queued job.
    /// Returns the id of a job interrupted by a stop.
    async fn step(&mut self) -> Result<Option<JobId>, SupervisorError> {
        // Also without a watchdog: tampering is noticed at every turn.
        self.core.check_ownership();
        if !self.core.write_pending_finish() {
            let wait = self.core.daemon().disk_recheck();
            self.core.pause(wait).await;
            return Ok(None);
        }
        if !self.stage_safe().await {
            return Ok(None);
        }
        let (next, quarantined) = self.core.spool.next_queued()?;
        log_quarantined(&quarantined);
        let Some(job) = next else {
            // Idle with the links down (or unknown after a reload): keep
            // checking them so "idle, 0 queued" means ready to run.
            if !self.core.links_known_up() && !self.links_ready("idle, 0 queued").await {
                self.core.pause_for_backoff().await;
                return Ok(None);
            }
            self.core.set_status("idle, 0 queued");
            let wait = self.core.daemon().poll_interval();
            self.core.pause(wait).await;
            return Ok(None);
        };
        let queued = self.core.spool.queued_count()?;
        let label = format!("job {} {}", job.id, job.name);

        let config = match job.job.effective_config(&self.core.config) {
            Ok(c) => c,
            Err(e) => {
                let reason = if job.job.check_shape().is_err() {
                    format!("refused: {e}")
                } else {
                    format!("does not fit the configuration in force: {e}")
                };
                warn!(job = job.id.0, name = %printable(&job.name, 64), %reason, "job rejected");
                self.core
                    .end_job(&job, JobState::Rejected, Some(reason), SystemTime::now());
                return Ok(None);
            }
        };

        match self.core.check_disk(&config) {
            Ok(()) => self.core.waiting_for_disk = false,
            Err(DiskProblem::Unusable(reason)) => {
                error!(job = job.id.0, name = %job.name, %reason, "job failed before it started");
                self.core
                    .end_job(&job, JobState::Failed, Some(reason), SystemTime::now());
                return Ok(None);
            }
            Err(DiskProblem::Low(why)) => {
                if !self.core.waiting_for_disk {
                    warn!(job = job.id.0, "{why}; the job waits, queued");
                    self.core.waiting_for_disk = true;
                }
                self.core
                    .set_status(&format!("waiting for disk space: {why}; {queued} queued"));
                let wait = self.core.daemon().disk_recheck();
                self.core.pause(wait).await;
                return Ok(None);
            }
        }

        if !self
            .links_ready(&format!("{label} waits for the links ({queued} queued)"))
            .await
        {
            self.core.pause_for_backoff().await;
            return Ok(None);
        }
        self.run_job(job, config, queued.saturating_sub(1)).await
    }

    /// Checks the links and keeps count of consecutive failures; on failure
    /// says so in STATUS (prefixed by `doing`). True when they answer.
    async fn links_ready(&mut self, doing: &str) -> bool {
        let config = self.core.config.clone();
        match self.check_links(&config).await {
            Ok(()) => {
                if self.core.link_failures > 0 {
                    info!(
                        after_failures = self.core.link_failures,
                        "stage and imaging links are back"
                    );
                }
                self.core.link_failures = 0;
                self.core.links = Some(Ok(()));
                true
            }
            Err(_) if self.core.stop.is_some() => false,
            Err(reason) => {
                self.core.link_failures += 1;
                let failures = self.core.link_failures;
                let wait = self.core.daemon().backoff(failures);
                warn!(attempt = failures, %reason, retry_in_s = wait.as_secs_f64(), "link check failed");
                self.core.set_status(&format!(
                    "{doing}: link check {failures} failed: {reason}; retry in {}",
                    human(wait)
                ));
                self.core.links = Some(Err(reason));
                false
            }
        }
    }

    /// Checks the links, bounded in time, while answering control messages.
    async fn check_links(&mut self, config: &Config) -> Result<(), String> {
        let timeout = self.core.daemon().link_check_timeout();
        let deadline = Instant::now() + timeout;
        let check = self.runner.check_links(config);
        tokio::pin!(check);
        let core = &mut self.core;
        loop {
            tokio::select! {
                result = &mut check => return result,
                () = tokio::time::sleep_until(deadline) => {
                    return Err(format!("no answer within {} (daemon.link_check_timeout_s)", human(timeout)));
                }
                control = core.control.recv(), if core.control_open => {
                    if let Some(signal) = core.on_control(control) {
                        core.begin_stop(&signal);
                        return Err(format!("{signal} received"));
                    }
                }
                () = tick(&mut core.watchdog) => core.ping(),
            }
        }
    }

    /// After an unclean end: reads the stage and, off its safe tilt, moves it there or
    /// waits for an operator (`daemon.after_crash`). True once the stage is known safe
    /// (or there was no unclean end); false when the caller should come back later.
    async fn stage_safe(&mut self) -> bool {
        if !self.core.stage_check.as_ref().is_some_and(|c| c.pending) {
            return true;
        }
        if !self.core.links_known_up()
            && !self
                .links_ready("after an unclean end, the stage is checked first")
                .await
        {
            self.core.pause_for_backoff().await;
            return false;
        }
        let config = self.core.config.clone();
        let (safe, tolerance) = (
            config.stage.safe_tilt_deg,
            config.stage.tilt_tolerance_deg.max(1e-6),
        );
        let limit = self.core.daemon().link_check_timeout();
        let tilt = match drive(&mut self.core, self.runner.stage_tilt(&config), limit).await {
            Some(Ok(tilt)) => tilt,
            result => {
                let why = match result {
                    Some(Err(e)) => e,
                    _ => format!("no answer within {}", human(limit)),
                };
                self.core
                    .stage_check_failed(&format!("cannot read the stage: {why}"));
                self.core.pause_for_backoff().await;
                return false;
            }
        };
        if (tilt - safe).abs() <= tolerance {
            self.core.stage_check_resolved(
                tilt,
                format!("the stage was found at its safe tilt ({tilt:.3}°)"),
            );
            return true;
        }
        let off = format!(
            "after an unclean end the stage is at {tilt:.3}°, not at its safe tilt {safe}° \
             (stage.safe_tilt_deg)"
        );
        if self.core.daemon().after_crash == AfterCrash::Wait && !self.core.acknowledged {
            if !self.core.hold_started {
                // Only an acknowledgement given from now on counts.
                self.core.spool.clear_ack();
                self.core.hold_started = true;
                error!(
                    tilt,
                    safe,
                    "{off}: no job runs until an operator checks it and runs `sdsem daemon --ack` (daemon.after_crash = \"wait\")"
                );
            }
            if let Some(who) = self.core.spool.take_ack() {
                warn!(%who, "an operator acknowledged the unclean end: the stage goes to its safe tilt");
                self.core.acknowledged = true;
            } else {
                let action = format!(
                    "waiting for an operator: {off}; check the specimen and the stage, then run \
                     `sdsem daemon --ack` (daemon.after_crash = \"wait\")"
                );
                self.core.update_stage_check(Some(tilt), &action);
                self.core.set_status(&format!("held: {action}"));
                let wait = self.core.daemon().poll_interval();
                self.core.pause(wait).await;
                return false;
            }
        }
        warn!(tilt, safe, "{off}: moving it there before anything else");
        let action = format!("{off}: moving it there before anything else");
        self.core.update_stage_check(Some(tilt), &action);
        self.core.set_status(&action);
        // The driver bounds the move itself; a stop leaves it daemon.stop_timeout_s.
        match drive(
            &mut self.core,
            self.runner.move_to_safe_tilt(&config),
            Duration::from_secs(24 * 3600),
        )
        .await
        {
            Some(Ok(reached)) => {
                let what = format!(
                    "after an unclean end the stage was at {tilt:.3}°; moved to its safe tilt \
                     ({reached:.3}°) before any job"
                );
                warn!("{what}");
                self.core.stage_check_resolved(tilt, what);
                true
            }
            Some(Err(e)) => {
                self.core
                    .stage_check_failed(&format!("the move to the safe tilt failed: {e}"));
                self.core.pause_for_backoff().await;
                false
            }
            None => {
                self.core.stage_check_failed(
                    "stopped before the stage reached its safe tilt: checked again at the next start",
                );
                false
            }
        }
    }

    /// Runs one job to its end and records how it ended.
    async fn run_job(
        &mut self,
        job: JobRecord,
        config: Config,
        others_queued: usize,
    ) -> Result<Option<JobId>, SupervisorError> {
        let label = format!("job {} {}", job.id, job.name);
        let now = SystemTime::now();
        let run_dir = match job
            .job
            .run_name()
            .map_err(|e| e.to_string())
            .and_then(|name| {
                RunDir::create(&config.run.output_dir, &name, now).map_err(|e| e.to_string())
            }) {
            Ok(dir) => dir,
            Err(reason) => {
                error!(job = job.id.0, name = %job.name, %reason, "job failed before it started");
                self.core.end_job(&job, JobState::Failed, Some(reason), now);
                return Ok(None);
            }
        };
        let job = match self.core.spool.start(&job, run_dir.path(), now) {
            Ok(job) => job,
            Err(e) => {
                let reason = format!("cannot mark the job running: {e}");
                error!(job = job.id.0, name = %job.name, %reason, "job failed before it started");
                let _ = std::fs::remove_dir(run_dir.path());
                let record = JobRecord {
                    state: self.core.spool.state_of(job.id).unwrap_or(JobState::Queued),
                    ..job
                };
                self.core
                    .end_job(&record, JobState::Failed, Some(reason), now);
                return Ok(None);
            }
        };
        info!(job = job.id.0, name = %job.name, run_dir = %run_dir.path().display(), "job started");

        let daemon = self.core.daemon().clone();
        let stall_timeout = daemon.stall_timeout();
        let stop_timeout = daemon.stop_timeout();
        let (trigger, cancel) = cancel_pair();
        let (progress, mut progress_rx) = progress_channel();
        let mut progress_open = true;
        let mut last_progress = progress_rx.borrow().clone();
        let queued_note = if others_queued == 0 {
            String::new()
        } else {
            format!("; {others_queued} more queued")
        };
        self.core
            .set_status(&format!("running {label}: {last_progress}{queued_note}"));

        let ctx = JobContext { cancel, progress };
        // Boxed so it can be dropped (abandoned, if it overran) before the record is written.
        let mut run = Box::pin(self.runner.run(&job, &config, &run_dir, ctx));
        let core = &mut self.core;
        let mut stall_deadline = stall_timeout.map(|d| Instant::now() + d);
        let mut stop_deadline: Option<Instant> = None;
        let mut cancelled: Option<Cancelled> = None;
        let outcome = loop {
            tokio::select! {
                outcome = &mut run => break Some(outcome),
                () = sleep_until(stop_deadline) => break None,
                () = sleep_until(stall_deadline), if cancelled.is_none() => {
                    let after = human(stall_timeout.unwrap_or_default());
                    let why = format!(
                        "no progress for {after} (daemon.stall_timeout_s); last: {last_progress}"
                    );
                    error!(job = job.id.0, name = %job.name, "{why}: cancelling the job");
                    trigger.cancel(why.clone());
                    cancelled = Some(Cancelled::Stalled(why));
                    stop_deadline = Some(Instant::now() + stop_timeout);
                    core.set_status(&format!("cancelling stalled {label}: waiting for the stage to reach its safe tilt"));
                }
                changed = progress_rx.changed(), if progress_open => {
                    if changed.is_ok() {
                        last_progress = progress_rx.borrow_and_update().clone();
                        stall_deadline = stall_timeout.map(|d| Instant::now() + d);
                        if cancelled.is_none() {
                            core.set_status(&format!("running {label}: {last_progress}{queued_note}"));
                        }
                    } else {
                        progress_open = false;
                    }
                }
                control = core.control.recv(), if core.control_open => {
                    if let Some(signal) = core.on_control(control)
                        && !matches!(cancelled, Some(Cancelled::Stop(_)))
                    {
                        core.begin_stop(&signal);
                        trigger.cancel(format!("{signal} received: the daemon is stopping"));
                        if cancelled.is_none() {
                            stop_deadline = Some(Instant::now() + stop_timeout);
                        }
                        cancelled = Some(Cancelled::Stop(signal));
                        core.set_status(&format!(
                            "stopping: {label} is bringing the stage to its safe tilt and finishing its record"
                        ));
                    }
                }
                () = tick(&mut core.watchdog) => core.ping(),
            }
        };
        drop(run);

        let now = SystemTime::now();
        let (state, reason) = final_state(outcome.as_ref(), cancelled.as_ref(), stop_timeout);
        let finished = JobRecord {
            state,
            reason: reason.clone(),
            ..job.clone()
        };
        self.core.end_job(&job, state, reason.clone(), now);
        if state != JobState::Done {
            // The runner drops links after a job that did not complete: until
            // checked again, "idle" must not claim they are up.
            self.core.links = None;
        }
        let why = reason.as_deref().unwrap_or("");
        match state {
            JobState::Done => info!(job = job.id.0, name = %job.name, "job done"),
            // Error priority in the journal: `journalctl -u sdsem -p err` lists failed jobs.
            JobState::Failed => {
                error!(job = job.id.0, name = %job.name, reason = why, "job failed")
            }
            _ => warn!(job = job.id.0, name = %job.name, state = %state, reason = why, "job ended"),
        }
        if outcome.is_none() {
            let cause = match cancelled {
                Some(Cancelled::Stop(signal)) => signal,
                Some(Cancelled::Stalled(why)) => why,
                None => String::new(),
            };
            return Err(SupervisorError::RunnerOverran {
                job: finished.id,
                name: finished.name,
                timeout: stop_timeout,
                cause,
            });
        }
        Ok(matches!(cancelled, Some(Cancelled::Stop(_))).then_some(finished.id))
    }
}

/// Why a running job was asked to stop.
enum Cancelled {
    Stop(String),
    Stalled(String),
}

/// The state and reason to record for a job, from what the runner returned
/// (`None`: it did not return in time) and why it was cancelled.
fn final_state(
    outcome: Option<&JobOutcome>,
    cancelled: Option<&Cancelled>,
    stop_timeout: Duration,
) -> (JobState, Option<String>) {
    match (outcome, cancelled) {
        (Some(JobOutcome::Completed), _) => (JobState::Done, None),
        (Some(JobOutcome::Failed { reason }), Some(Cancelled::Stalled(why))) => {
            (JobState::Failed, Some(format!("{why}; then: {reason}")))
        }
        (Some(JobOutcome::Failed { reason }), _) => (JobState::Failed, Some(reason.clone())),
        (Some(JobOutcome::Interrupted { reason }), Some(Cancelled::Stalled(why))) => (
            JobState::Failed,
            Some(format!("{why}; cancelled: {reason}")),
        ),
        (Some(JobOutcome::Interrupted { reason }), Some(Cancelled::Stop(signal))) => (
            JobState::Interrupted,
            Some(format!("stopped by {signal}: {reason}")),
        ),
        (Some(JobOutcome::Interrupted { reason }), None) => {
            (JobState::Interrupted, Some(reason.clone()))
        }
        (None, cancelled) => {
            let cause = match cancelled {
                Some(Cancelled::Stop(signal)) => format!("stopped by {signal}"),
                Some(Cancelled::Stalled(why)) => why.clone(),
                None => "cancelled".into(),
            };
            (
                JobState::Interrupted,
                Some(format!(
                    "{cause}, but the job did not stop within {} (daemon.stop_timeout_s): \
                     stage state unknown, check it before the next run",
                    human(stop_timeout)
                )),
            )
        }
    }
}

/// Why a job cannot start for lack of disk.
enum DiskProblem {
    /// Too little space: wait.
    Low(String),
    /// The output directory cannot be created or measured: fail the job.
    Unusable(String),
}

impl Core {
    fn daemon(&self) -> &DaemonConfig {
        &self.config.daemon
    }

    /// Says what the daemon is doing: STATUS= and `daemon.json`, on change only.
    fn set_status(&mut self, status: &str) {
        if self.status == status && !self.publish_due {
            return;
        }
        if self.status != status {
            status.clone_into(&mut self.status);
            self.notifier.notify(Notice::Status(status.to_owned()));
        }
        self.publish_due = false;
        let record = DaemonStatus {
            pid: std::process::id(),
            state: self.state.to_owned(),
            status: status.to_owned(),
            updated: utc::rfc3339(SystemTime::now()),
            warnings: self.warnings.clone(),
            stage_check: self.stage_check.clone(),
        };
        match self.spool.write_daemon_status(&record) {
            Ok(()) => self.status_write_failed = false,
            Err(e) if !self.status_write_failed => {
                // Not fatal (a full disk is waited out); the journal has STATUS.
                warn!(error = %e, "cannot publish the daemon status in the spool");
                self.status_write_failed = true;
                self.publish_due = true;
            }
            Err(_) => self.publish_due = true,
        }
    }

    /// Writes `daemon.json` again (warnings or the stage check changed).
    fn publish(&mut self) {
        self.publish_due = true;
        let status = self.status.clone();
        self.set_status(&status);
    }

    fn update_stage_check(&mut self, tilt: Option<f64>, action: &str) {
        if let Some(check) = &mut self.stage_check
            && (check.action != action || (tilt.is_some() && check.found_tilt_deg != tilt))
        {
            action.clone_into(&mut check.action);
            if tilt.is_some() {
                check.found_tilt_deg = tilt;
            }
            self.publish_due = true;
        }
    }

    fn stage_check_resolved(&mut self, tilt: f64, action: String) {
        info!("{action}");
        if let Some(check) = &mut self.stage_check {
            check.found_tilt_deg = Some(tilt);
            check.action = action;
            check.pending = false;
            check.resolved = Some(utc::rfc3339(SystemTime::now()));
        }
        self.hold_started = false;
        self.acknowledged = false;
        self.publish();
    }

    /// The stage could not be checked or moved: the links are checked again, then it is retried.
    fn stage_check_failed(&mut self, why: &str) {
        error!("after an unclean end: {why}; no job runs until the stage is at its safe tilt");
        self.links = None;
        self.link_failures = self.link_failures.max(1);
        let action = format!("{why}; retrying");
        self.update_stage_check(None, &action);
        self.set_status(&format!("after an unclean end: {action}"));
    }

    /// Records a job's end; when the spool cannot take it (a full disk) it is kept and
    /// written again at the next turns, and the daemon goes on.
    fn end_job(
        &mut self,
        job: &JobRecord,
        state: JobState,
        reason: Option<String>,
        at: SystemTime,
    ) {
        self.pending_finish = Some(PendingFinish {
            record: job.clone(),
            state,
            reason,
            at,
        });
        self.write_pending_finish();
    }

    /// Writes the end of a job that is waiting for it; true when none is left waiting.
    fn write_pending_finish(&mut self) -> bool {
        let Some(p) = self.pending_finish.take() else {
            return true;
        };
        match self
            .spool
            .finish(&p.record, p.state, p.reason.clone(), p.at)
        {
            Ok(_) => true,
            Err(e) => {
                let what = format!(
                    "cannot record that job {} ended {}: {e}; retrying every {} \
                     (daemon.disk_recheck_s), no other job starts meanwhile",
                    p.record.id,
                    p.state,
                    human(self.daemon().disk_recheck())
                );
                error!("{what}");
                self.pending_finish = Some(p);
                self.set_status(&what);
                false
            }
        }
    }
    /// True when the last link check succeeded.
    fn links_known_up(&self) -> bool {
        matches!(self.links, Some(Ok(())))
    }

    /// Waits the backoff due after the current run of link-check failures.
    async fn pause_for_backoff(&mut self) {
        if self.stop.is_none() && self.link_failures > 0 {
            let wait = self.daemon().backoff(self.link_failures);
            self.pause(wait).await;
        }
    }

    /// Waits `duration` while answering control messages and feeding the watchdog.
    async fn pause(&mut self, duration: Duration) {
        let deadline = Instant::now() + duration;
        loop {
            tokio::select! {
                () = tokio::time::sleep_until(deadline) => return,
                control = self.control.recv(), if self.control_open => {
                    if let Some(signal) = self.on_control(control) {
                        self.begin_stop(&signal);
                        return;
                    }
                }
                () = tick(&mut self.watchdog) => self.ping(),
            }
        }
    }

    /// Handles a reload at once; returns the signal of a stop request.
    fn on_control(&mut self, control: Option<Control>) -> Option<String> {
        match control {
            Some(Control::Reload) => {
                self.reload();
                None
            }
            Some(Control::Stop { signal }) => Some(signal),
            None => {
                self.control_open = false;
                Some("end of control channel".into())
            }
        }
    }

    fn begin_stop(&mut self, signal: &str) {
        if self.stop.is_none() {
            info!(%signal, "stopping");
            self.notifier.notify(Notice::Stopping);
            self.stop = Some(signal.to_owned());
        }
    }

    /// Replaces the configuration if the new one is valid; keeps the old one otherwise.
    fn reload(&mut self) {
        self.notifier.notify(Notice::Reloading);
        let result = match &mut self.reloader {
            Some(reload) => reload().and_then(|c| c.daemon.validate().map(|()| c)),
            None => Err("this daemon has no configuration file to reload".into()),
        };
        match result {
            Ok(new) => {
                if new.daemon.spool_dir != self.config.daemon.spool_dir {
                    warn!(
                        "daemon.spool_dir changed: it takes effect at the next start; this \
                         daemon keeps {}",
                        self.spool.root().display()
                    );
                }
                self.config = new;
                self.links = None;
                match self.spool.write_config_snapshot(&self.config) {
                    Ok(()) => info!("configuration reloaded; it applies from the next job"),
                    Err(e) => {
                        warn!(error = %e, "configuration reloaded, but `sdsem submit` cannot see it")
                    }
                }
            }
            Err(reason) => {
                error!(%reason, "configuration reload refused; keeping the current configuration");
            }
        }
        self.notifier.notify(Notice::Ready);
    }

    /// WATCHDOG=1, only while the loop can still do its work: the spool is the one it
    /// locked. A tampered `daemon.lock` is written again and reported, and pings go on.
    fn ping(&mut self) {
        if self.check_ownership() {
            self.notifier.notify(Notice::Watchdog);
        }
    }

    /// Checks the spool is still the one locked and `daemon.lock` still ours (writing it
    /// again and reporting it if not); false when the spool directory itself is gone.
    fn check_ownership(&mut self) -> bool {
        match self.spool.check_ownership() {
            Ok(()) => {}
            Err(Tamper::LockFile(what)) => {
                error!(spool = %self.spool.root().display(), "{what}");
                let note = format!("{}: {what}", utc::rfc3339(SystemTime::now()));
                self.warnings.push(note);
                let excess = self.warnings.len().saturating_sub(10);
                self.warnings.drain(..excess);
                self.publish();
            }
            Err(Tamper::SpoolGone(what)) => {
                if !self.unhealthy_logged {
                    error!("{what}: no more watchdog pings, systemd will restart the daemon");
                    self.unhealthy_logged = true;
                }
                return false;
            }
        }
        self.unhealthy_logged = false;
        true
    }

    fn check_disk(&self, config: &Config) -> Result<(), DiskProblem> {
        use std::os::unix::fs::DirBuilderExt;
        let dir = &config.run.output_dir;
        std::fs::DirBuilder::new()
            .recursive(true)
            .mode(0o750)
            .create(dir)
            .map_err(|e| {
                DiskProblem::Unusable(format!(
                    "cannot create run.output_dir {}: {e}",
                    dir.display()
                ))
            })?;
        let free = self.disk.free_bytes(dir).map_err(|e| {
            DiskProblem::Unusable(format!(
                "cannot measure free space in {}: {e}",
                dir.display()
            ))
        })?;
        let need = self.daemon().min_free_bytes();
        if free < need {
            #[allow(clippy::cast_precision_loss)]
            let free_gib = free as f64 / GIB;
            return Err(DiskProblem::Low(format!(
                "{free_gib:.2} GiB free in {}, daemon.min_free_gib = {}",
                dir.display(),
                self.daemon().min_free_gib
            )));
        }
        Ok(())
    }
}

/// The stage check due at this start, if the previous daemon ended uncleanly (a job found
/// running, a status other than "stopped", a check it left pending); else the last one, kept
/// for `sdsem status`.
fn unclean_end(
    previous: Option<&DaemonStatus>,
    recovery: &super::spool::Recovery,
    now: SystemTime,
) -> Option<StageCheck> {
    let cause = if let Some(job) = recovery.interrupted.first() {
        Some(format!(
            "job {} was running when the previous daemon ended",
            job.id
        ))
    } else {
        match previous {
            Some(p) if p.stage_check.as_ref().is_some_and(|c| c.pending) => {
                Some("the previous daemon stopped before the stage was checked".to_owned())
            }
            Some(p) if p.state != "stopped" => Some(format!(
                "the previous daemon (PID {}) ended without stopping cleanly (last seen {}: {})",
                p.pid,
                printable(&p.updated, 40),
                printable(&p.status, 200)
            )),
            _ => None,
        }
    };
    match cause {
        Some(cause) => Some(StageCheck {
            noticed: utc::rfc3339(now),
            cause,
            found_tilt_deg: None,
            action: "the stage is read before any job".into(),
            pending: true,
            resolved: None,
        }),
        None => previous.and_then(|p| p.stage_check.clone()),
    }
}

/// Runs `work` to its end while answering control messages and feeding the watchdog;
/// `None` when it took longer than `limit` (or, after a stop, than `daemon.stop_timeout_s`).
async fn drive<T>(core: &mut Core, work: impl Future<Output = T>, limit: Duration) -> Option<T> {
    tokio::pin!(work);
    let mut deadline = Instant::now() + limit;
    let mut stopping = core.stop.is_some();
    if stopping {
        deadline = deadline.min(Instant::now() + core.daemon().stop_timeout());
    }
    loop {
        tokio::select! {
            out = &mut work => return Some(out),
            () = tokio::time::sleep_until(deadline) => return None,
            control = core.control.recv(), if core.control_open => {
                if let Some(signal) = core.on_control(control) {
                    core.begin_stop(&signal);
                    if !stopping {
                        stopping = true;
                        deadline = deadline.min(Instant::now() + core.daemon().stop_timeout());
                    }
                }
            }
            () = tick(&mut core.watchdog) => core.ping(),
        }
    }
}

fn log_quarantined(quarantined: &[Unreadable]) {
    for q in quarantined {
        error!(entry = %q.name, moved_to = %q.path.display(), cause = %q.cause, "spool entry set aside: not a job record");
    }
}

async fn tick(watchdog: &mut Option<Interval>) {
    match watchdog {
        Some(interval) => {
            interval.tick().await;
        }
        None => std::future::pending().await,
    }
}

async fn sleep_until(deadline: Option<Instant>) {
    match deadline {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}

/// `4 s`, `1.5 s`, `2 min`.
fn human(d: Duration) -> String {
    let s = d.as_secs_f64();
    if s >= 120.0 {
        format!("{} min", (s / 60.0).round())
    } else if (s - s.round()).abs() < 1e-9 {
        format!("{s:.0} s")
    } else {
        format!("{s:.1} s")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn final_states_follow_outcome_and_cause() {
        let t = Duration::from_secs(12);
        let stop = Cancelled::Stop("SIGTERM".into());
        let stall = Cancelled::Stalled("no progress for 30 min".into());
        let interrupted = JobOutcome::Interrupted {
            reason: "at tilt 3°".into(),
        };
        assert_eq!(
            final_state(Some(&JobOutcome::Completed), Some(&stop), t),
            (JobState::Done, None)
        );
        let (s, r) = final_state(Some(&interrupted), Some(&stop), t);
        assert_eq!(s, JobState::Interrupted);
        assert_eq!(r.as_deref(), Some("stopped by SIGTERM: at tilt 3°"));
        let (s, r) = final_state(Some(&interrupted), Some(&stall), t);
        assert_eq!(s, JobState::Failed);
        assert!(r.unwrap().starts_with("no progress for 30 min"));
        let (s, r) = final_state(None, Some(&stop), t);
        assert_eq!(s, JobState::Interrupted);
        assert!(r.unwrap().contains("did not stop within 12 s"));
    }

    #[test]
    fn durations_read_well() {
        assert_eq!(human(Duration::from_secs(4)), "4 s");
        assert_eq!(human(Duration::from_millis(1500)), "1.5 s");
        assert_eq!(human(Duration::from_secs(1800)), "30 min");
    }
}
