//! The supervisor: the daemon's one main loop.
//!
//! On start it recovers the spool (a job left `running` by a crash becomes
//! `interrupted`, never re-run), checks the links and says READY. Then, one job
//! at a time, oldest first: validate the job under the configuration in force
//! (`rejected` if it no longer fits), wait while free disk space is under
//! `daemon.min_free_gib` (the job stays queued; STATUS says why), check the
//! links (on failure wait with capped exponential backoff, the job stays
//! queued), create the run directory, mark the job `running`, run it, record
//! its final state and reason.
//!
//! Control arrives as [`Control`] messages (the binary turns SIGTERM/SIGINT and
//! SIGHUP into them): a stop cancels the running job, waits for it at most
//! `daemon.stop_timeout_s`, marks it `interrupted` and ends the loop; a reload
//! swaps the configuration only if the new one is valid, and applies to the
//! next job. WATCHDOG=1 is sent from this loop only, so a stuck loop stops the
//! pings and systemd restarts the service. Time is tokio's (a paused clock in tests).

use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime};

use tokio::sync::mpsc;
use tokio::time::{Instant, Interval, MissedTickBehavior};
use tracing::{error, info, warn};

use super::config::{DaemonConfig, GIB};
use super::disk::{DiskSpace, Statvfs};
use super::notify::{Notice, Notifier};
use super::runner::{JobContext, JobOutcome, JobRunner, cancel_pair, progress_channel};
use super::spool::{DaemonStatus, JobId, JobRecord, JobState, OwnedSpool, SpoolError, Unreadable};
use super::utc;
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
        let recovery = self.core.spool.recover(SystemTime::now())?;
        for job in &recovery.interrupted {
            warn!(job = job.id.0, name = %job.name, "{}", super::spool::CRASH_REASON);
        }
        log_quarantined(&recovery.quarantined);
        self.core.spool.write_config_snapshot(&self.core.config)?;
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
                let reason = format!("does not fit the configuration in force: {e}");
                warn!(job = job.id.0, name = %job.name, %reason, "job rejected");
                self.core.spool.finish(
                    &job,
                    JobState::Rejected,
                    Some(reason),
                    SystemTime::now(),
                )?;
                return Ok(None);
            }
        };

        match self.core.check_disk(&config) {
            Ok(()) => self.core.waiting_for_disk = false,
            Err(DiskProblem::Unusable(reason)) => {
                error!(job = job.id.0, name = %job.name, %reason, "job failed before it started");
                self.core
                    .spool
                    .finish(&job, JobState::Failed, Some(reason), SystemTime::now())?;
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

    /// Runs one job to its end and records how it ended.
    async fn run_job(
        &mut self,
        job: JobRecord,
        config: Config,
        others_queued: usize,
    ) -> Result<Option<JobId>, SupervisorError> {
        let label = format!("job {} {}", job.id, job.name);
        let now = SystemTime::now();
        let run_dir = match create_run_dir(&config.run.output_dir, &job, now) {
            Ok(dir) => dir,
            Err(reason) => {
                error!(job = job.id.0, name = %job.name, %reason, "job failed before it started");
                self.core
                    .spool
                    .finish(&job, JobState::Failed, Some(reason), now)?;
                return Ok(None);
            }
        };
        let job = self.core.spool.start(&job, &run_dir, now)?;
        info!(job = job.id.0, name = %job.name, run_dir = %run_dir.display(), "job started");

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
        // The reconstruction's buffers are free now: an idle daemon gives
        // their pages back rather than keep the peak of its last job.
        crate::memory::release_free_memory();

        let now = SystemTime::now();
        let (state, reason) = final_state(outcome.as_ref(), cancelled.as_ref(), stop_timeout);
        let finished = self.core.spool.finish(&job, state, reason.clone(), now)?;
        if state != JobState::Done {
            // The runner drops links after a job that did not complete: until
            // checked again, "idle" must not claim they are up.
            self.core.links = None;
        }
        match state {
            JobState::Done => info!(job = job.id.0, name = %job.name, "job done"),
            _ => {
                warn!(job = job.id.0, name = %job.name, state = %state, reason = reason.as_deref().unwrap_or(""), "job ended")
            }
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
        if self.status == status {
            return;
        }
        status.clone_into(&mut self.status);
        self.notifier.notify(Notice::Status(status.to_owned()));
        let record = DaemonStatus {
            pid: std::process::id(),
            state: self.state.to_owned(),
            status: status.to_owned(),
            updated: utc::rfc3339(SystemTime::now()),
        };
        match self.spool.write_daemon_status(&record) {
            Ok(()) => self.status_write_failed = false,
            Err(e) if !self.status_write_failed => {
                // Not fatal (a full disk is waited out); the journal has STATUS.
                warn!(error = %e, "cannot publish the daemon status in the spool");
                self.status_write_failed = true;
            }
            Err(_) => {}
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

    /// WATCHDOG=1, only while the loop can still do its work: the spool is there.
    fn ping(&mut self) {
        if self.spool.root().join("daemon.lock").is_file() {
            self.unhealthy_logged = false;
            self.notifier.notify(Notice::Watchdog);
        } else if !self.unhealthy_logged {
            error!(
                spool = %self.spool.root().display(),
                "the spool has vanished: no more watchdog pings, systemd will restart the daemon"
            );
            self.unhealthy_logged = true;
        }
    }

    fn check_disk(&self, config: &Config) -> Result<(), DiskProblem> {
        let dir = &config.run.output_dir;
        std::fs::create_dir_all(dir).map_err(|e| {
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

/// Creates `<output_dir>/<name>-<UTC time>` (with the job id appended if that
/// exists already) and returns its absolute path.
fn create_run_dir(output_dir: &Path, job: &JobRecord, now: SystemTime) -> Result<PathBuf, String> {
    let base = std::path::absolute(output_dir).map_err(|e| {
        format!(
            "cannot resolve run.output_dir {}: {e}",
            output_dir.display()
        )
    })?;
    let stem = format!("{}-{}", job.name, utc::compact(now));
    for name in [stem.clone(), format!("{stem}-job{}", job.id)] {
        let dir = base.join(name);
        match std::fs::create_dir(&dir) {
            Ok(()) => return Ok(dir),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => {
                return Err(format!(
                    "cannot create the run directory {}: {e}",
                    dir.display()
                ));
            }
        }
    }
    Err(format!(
        "cannot create a run directory in {}: {stem} and {stem}-job{} exist",
        base.display(),
        job.id
    ))
}

fn log_quarantined(quarantined: &[Unreadable]) {
    for q in quarantined {
        error!(path = %q.path.display(), cause = %q.cause, "unreadable job record set aside");
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

    #[test]
    fn run_directories_never_collide() {
        let dir = tempfile::tempdir().unwrap();
        let job = JobRecord {
            id: JobId(7),
            state: JobState::Queued,
            name: "pollen".into(),
            submitted: String::new(),
            started: None,
            finished: None,
            run_dir: None,
            reason: None,
            job: super::super::job::JobSpec::parse(
                "name = \"pollen\"\nstart_tilt = 0\nend_tilt = 5\n",
            )
            .unwrap(),
        };
        let t = SystemTime::UNIX_EPOCH + Duration::from_secs(1_740_837_909);
        let a = create_run_dir(dir.path(), &job, t).unwrap();
        let b = create_run_dir(dir.path(), &job, t).unwrap();
        assert!(a.ends_with("pollen-20250301T140509Z"));
        assert!(b.ends_with("pollen-20250301T140509Z-job7"));
        assert!(
            create_run_dir(dir.path(), &job, t)
                .unwrap_err()
                .contains("exist")
        );
    }
}
