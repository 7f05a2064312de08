//! The supervisor with a scripted runner on tokio's paused clock: ordering,
//! crash recovery, link loss and backoff, a full disk, stops, stalls, reloads,
//! and the watchdog.

#![allow(clippy::unwrap_used)]

mod daemon_support;

use std::path::Path;
use std::time::{Duration, SystemTime};

use daemon_support::{Behaviour, Event, FakeDisk, FakeRunner, Recorder, Script};
use sdsem::config::Config;
use sdsem::daemon::spool::CRASH_REASON;
use sdsem::daemon::supervisor::SupervisorError;
use sdsem::daemon::{Control, JobRecord, JobSpec, JobState, Notice, Spool, Stopped, Supervisor};
use tokio::sync::mpsc;
use tokio::time::{Instant, sleep};

struct Rig {
    _dir: tempfile::TempDir,
    spool: Spool,
    config: Config,
    runner: FakeRunner,
    notices: Recorder,
    disk: FakeDisk,
}

impl Rig {
    fn new(script: Script) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let mut config = Config::default();
        config.daemon.spool_dir = dir.path().join("spool");
        config.run.output_dir = dir.path().join("runs");
        config.daemon.min_free_gib = 2.0;
        config.daemon.backoff_initial_s = 1.0;
        config.daemon.backoff_max_s = 8.0;
        let spool = Spool::open(&config.daemon.spool_dir).unwrap();
        Self {
            _dir: dir,
            spool,
            config,
            runner: FakeRunner::new(script),
            notices: Recorder::default(),
            disk: FakeDisk::with_gib(100),
        }
    }

    fn submit(&self, name: &str) -> JobRecord {
        self.submit_text(&format!("name = {name:?}\nstart_tilt = 0\nend_tilt = 5\n"))
    }

    fn submit_text(&self, text: &str) -> JobRecord {
        self.spool
            .submit(JobSpec::parse(text).unwrap(), SystemTime::now())
            .unwrap()
    }

    fn supervisor(&self) -> (Supervisor<FakeRunner>, mpsc::Sender<Control>) {
        let (tx, rx) = mpsc::channel(8);
        let owned = self.spool.clone().lock().unwrap();
        let sup = Supervisor::new(owned, self.config.clone(), self.runner.clone(), rx)
            .with_notifier(self.notices.clone())
            .with_disk(self.disk.clone())
            .with_watchdog(Some(Duration::from_secs(5)));
        (sup, tx)
    }

    fn jobs(&self) -> Vec<JobRecord> {
        self.spool.list().unwrap().jobs
    }

    fn state_of(&self, name: &str) -> JobState {
        self.jobs()
            .into_iter()
            .find(|j| j.name == name)
            .unwrap()
            .state
    }

    /// Waits (in paused time) until `done` holds for the jobs, at most `limit`.
    async fn wait_until(&self, limit: Duration, done: impl Fn(&[JobRecord]) -> bool) {
        let end = Instant::now() + limit;
        while !done(&self.jobs()) {
            assert!(
                Instant::now() < end,
                "not reached within {limit:?}: {:#?}",
                self.jobs()
            );
            sleep(Duration::from_millis(100)).await;
        }
    }
}

fn stop() -> Control {
    Control::Stop {
        signal: "SIGTERM".into(),
    }
}

fn all_final(jobs: &[JobRecord]) -> bool {
    jobs.iter().all(|j| j.state.is_final())
}

#[tokio::test(start_paused = true)]
async fn jobs_run_one_at_a_time_oldest_first_each_in_its_own_directory() {
    let rig = Rig::new(Script::default());
    for name in ["a", "b", "c"] {
        rig.submit(name);
    }
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        rig.wait_until(Duration::from_secs(120), all_final).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    assert_eq!(
        result.unwrap(),
        Stopped {
            signal: "SIGTERM".into(),
            interrupted: None
        }
    );
    assert_eq!(rig.runner.started(), ["a", "b", "c"]);
    // One at a time: each job starts after the previous one ended.
    let mut last_end = None;
    for e in rig.runner.events() {
        match e {
            Event::Started { at, .. } => {
                assert!(last_end.is_none_or(|end| at >= end));
                last_end = None;
            }
            Event::Ended { at, .. } => last_end = Some(at),
            Event::LinkCheck { .. } | Event::StageRead { .. } | Event::SafeMove { .. } => {}
        }
    }
    let jobs = rig.jobs();
    let mut dirs: Vec<&Path> = jobs.iter().map(|j| j.run_dir.as_deref().unwrap()).collect();
    for (job, dir) in jobs.iter().zip(&dirs) {
        assert_eq!(job.state, JobState::Done);
        assert_eq!(
            std::fs::read(dir.join("run.mcap")).unwrap(),
            job.name.as_bytes()
        );
        assert!(dir.starts_with(&rig.config.run.output_dir));
    }
    dirs.dedup();
    assert_eq!(dirs.len(), 3);
    // READY after the start-up link check; STATUS says what happens.
    let notices = rig.notices.notices();
    let ready = notices.iter().position(|n| *n == Notice::Ready).unwrap();
    assert!(notices[..ready].contains(&Notice::Status(
        "starting: checking the stage and imaging links".into()
    )));
    let statuses = rig.notices.statuses();
    assert!(
        statuses
            .iter()
            .any(|s| s.starts_with("running job 1 a: working") && s.ends_with("2 more queued")),
        "{statuses:#?}"
    );
    assert!(
        statuses.contains(&"idle, 0 queued".to_owned()),
        "{statuses:#?}"
    );
    assert!(notices.contains(&Notice::Stopping));
    let published = rig.spool.daemon_status().unwrap();
    assert_eq!(published.state, "stopped");
    assert_eq!(published.pid, std::process::id());
}

#[tokio::test(start_paused = true)]
async fn after_a_crash_the_running_job_is_interrupted_not_rerun_and_the_queue_goes_on() {
    let rig = Rig::new(Script::default());
    rig.submit("a");
    rig.submit("b");
    {
        // The previous daemon started `a`, then the power went.
        let owned = rig.spool.clone().lock().unwrap();
        let a = owned.next_queued().unwrap().0.unwrap();
        owned
            .start(&a, Path::new("/runs/a-x"), SystemTime::now())
            .unwrap();
    }
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        rig.wait_until(Duration::from_secs(60), all_final).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    assert_eq!(rig.runner.started(), ["b"], "`a` must not be re-run");
    let jobs = rig.jobs();
    assert_eq!(jobs[0].state, JobState::Interrupted);
    assert_eq!(jobs[0].reason.as_deref(), Some(CRASH_REASON));
    assert_eq!(jobs[1].state, JobState::Done);
}

#[tokio::test(start_paused = true)]
async fn a_lost_link_fails_its_job_then_the_daemon_reconnects_with_backoff() {
    let mut script = Script::default();
    script.jobs.insert(
        "a".into(),
        Behaviour::Fail {
            after: Duration::from_secs(5),
            reason: "stage link lost during `MOV 3 4`: connection reset".into(),
        },
    );
    // Start-up and before `a`: fine. Then the controller is off for four checks.
    script.link_checks = [Ok(()), Ok(())]
        .into_iter()
        .chain((0..4).map(|_| Err("stage: connection refused".to_owned())))
        .collect();
    let rig = Rig::new(script);
    rig.submit("a");
    rig.submit("b");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        rig.wait_until(Duration::from_secs(120), all_final).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    let jobs = rig.jobs();
    assert_eq!(jobs[0].state, JobState::Failed);
    assert!(
        jobs[0]
            .reason
            .as_deref()
            .unwrap()
            .contains("stage link lost")
    );
    assert_eq!(jobs[1].state, JobState::Done, "{jobs:#?}");
    // After `a`: four failed checks spaced 1, 2, 4, 8 s, then success.
    let checks = rig.runner.link_check_times();
    let after_a: Vec<_> = checks[2..].to_vec();
    assert_eq!(
        after_a.iter().map(|(_, ok)| *ok).collect::<Vec<_>>(),
        [false, false, false, false, true]
    );
    let gaps: Vec<u64> = after_a
        .windows(2)
        .map(|w| (w[1].0 - w[0].0).as_secs())
        .collect();
    assert_eq!(gaps, [1, 2, 4, 8]);
    assert!(
        rig.notices.statuses().iter().any(|s| s
            == "job 2 b waits for the links (1 queued): link check 3 failed: \
                    stage: connection refused; retry in 4 s"),
        "{:#?}",
        rig.notices.statuses()
    );
}

#[tokio::test(start_paused = true)]
async fn backoff_is_capped() {
    let script = Script {
        link_checks: [Ok(())]
            .into_iter()
            .chain((0..8).map(|_| Err("imaging: no answer".to_owned())))
            .collect(),
        ..Script::default()
    };
    let rig = Rig::new(script);
    rig.submit("a");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        rig.wait_until(Duration::from_secs(300), all_final).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    let checks = rig.runner.link_check_times();
    let gaps: Vec<u64> = checks[1..]
        .windows(2)
        .map(|w| (w[1].0 - w[0].0).as_secs())
        .collect();
    assert_eq!(gaps, [1, 2, 4, 8, 8, 8, 8, 8]);
}

#[tokio::test(start_paused = true)]
async fn a_job_waits_queued_while_the_disk_is_too_full() {
    let rig = Rig::new(Script::default());
    rig.disk.set_gib(1); // under min_free_gib = 2
    rig.submit("a");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        sleep(Duration::from_secs(600)).await;
        assert_eq!(rig.state_of("a"), JobState::Queued);
        assert!(rig.runner.started().is_empty());
        let status = rig.spool.daemon_status().unwrap().status;
        assert!(
            status.starts_with("waiting for disk space: 1.00 GiB free in")
                && status.contains("daemon.min_free_gib = 2"),
            "{status}"
        );
        rig.disk.set_gib(50);
        let freed = Instant::now();
        rig.wait_until(Duration::from_secs(120), all_final).await;
        ctl.send(stop()).await.unwrap();
        freed
    };
    let (result, freed) = tokio::join!(sup.run(), driver);
    result.unwrap();
    let Some(Event::Started { at, .. }) = rig
        .runner
        .events()
        .into_iter()
        .find(|e| matches!(e, Event::Started { .. }))
    else {
        panic!("never started")
    };
    assert!(
        at - freed <= Duration::from_secs(60),
        "started within daemon.disk_recheck_s"
    );
    assert_eq!(rig.state_of("a"), JobState::Done);
}

#[tokio::test(start_paused = true)]
async fn sigterm_interrupts_the_running_job_within_the_bound_and_leaves_the_queue() {
    let mut script = Script::default();
    script.jobs.insert(
        "long".into(),
        Behaviour::Work {
            duration: Duration::from_secs(3600),
            stop_after: Duration::from_secs(4),
        },
    );
    let rig = Rig::new(script);
    rig.submit("long");
    rig.submit("next");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        sleep(Duration::from_secs(30)).await;
        assert_eq!(rig.state_of("long"), JobState::Running);
        ctl.send(stop()).await.unwrap();
        Instant::now()
    };
    let (result, sent) = tokio::join!(sup.run(), driver);
    let stopped_after = Instant::now() - sent;
    assert_eq!(result.unwrap().interrupted.map(|id| id.0), Some(1));
    assert!(stopped_after <= Duration::from_secs(5), "{stopped_after:?}");
    let jobs = rig.jobs();
    assert_eq!(jobs[0].state, JobState::Interrupted);
    let reason = jobs[0].reason.as_deref().unwrap();
    assert!(
        reason.starts_with("stopped by SIGTERM: stage back at its safe tilt"),
        "{reason}"
    );
    assert_eq!(jobs[1].state, JobState::Queued, "nothing else starts");
    assert!(
        rig.notices
            .statuses()
            .iter()
            .any(|s| s.starts_with("stopping: job 1 long")),
        "{:#?}",
        rig.notices.statuses()
    );
}

#[tokio::test(start_paused = true)]
async fn a_runner_deaf_to_cancellation_is_abandoned_after_stop_timeout() {
    let mut script = Script::default();
    script.jobs.insert("deaf".into(), Behaviour::Deaf);
    let rig = Rig::new(script);
    rig.submit("deaf");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        sleep(Duration::from_secs(10)).await;
        ctl.send(stop()).await.unwrap();
        Instant::now()
    };
    let (result, sent) = tokio::join!(sup.run(), driver);
    let waited = Instant::now() - sent;
    assert_eq!(waited, Duration::from_secs(12), "daemon.stop_timeout_s");
    let err = result.unwrap_err();
    assert!(
        matches!(err, SupervisorError::RunnerOverran { .. }),
        "{err}"
    );
    assert!(
        err.to_string()
            .contains("stage may not be at its safe tilt"),
        "{err}"
    );
    let job = &rig.jobs()[0];
    assert_eq!(job.state, JobState::Interrupted);
    assert!(
        job.reason
            .as_deref()
            .unwrap()
            .contains("did not stop within 12 s")
    );
}

#[tokio::test(start_paused = true)]
async fn a_job_without_progress_is_cancelled_as_stalled_and_fails() {
    let mut script = Script::default();
    script.jobs.insert("silent".into(), Behaviour::Silent);
    let mut rig = Rig::new(script);
    rig.config.daemon.stall_timeout_s = 90.0;
    rig.submit("silent");
    rig.submit("after");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        rig.wait_until(Duration::from_secs(300), all_final).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    let jobs = rig.jobs();
    assert_eq!(jobs[0].state, JobState::Failed);
    let reason = jobs[0].reason.as_deref().unwrap();
    assert!(
        reason.starts_with("no progress for 90 s (daemon.stall_timeout_s)"),
        "{reason}"
    );
    assert_eq!(jobs[1].state, JobState::Done);
}

#[tokio::test(start_paused = true)]
async fn a_job_that_no_longer_fits_is_rejected_at_its_turn_and_never_runs() {
    let rig = Rig::new(Script::default());
    // Queued directly (as a job valid under an earlier configuration would be).
    rig.submit_text("name = \"steep\"\nstart_tilt = 0\nend_tilt = 75\n");
    rig.submit("fine");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        rig.wait_until(Duration::from_secs(60), all_final).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    assert_eq!(rig.runner.started(), ["fine"]);
    let steep = &rig.jobs()[0];
    assert_eq!(steep.state, JobState::Rejected);
    let reason = steep.reason.as_deref().unwrap();
    assert!(
        reason.contains("end_tilt = 75°") && reason.contains("[-5°, 70°]"),
        "{reason}"
    );
}

#[tokio::test(start_paused = true)]
async fn reload_swaps_only_a_valid_configuration_and_applies_it_to_the_next_job() {
    let mut script = Script::default();
    script.jobs.insert(
        "first".into(),
        Behaviour::Work {
            duration: Duration::from_secs(20),
            stop_after: Duration::from_secs(1),
        },
    );
    let rig = Rig::new(script);
    let new_output = rig
        .config
        .run
        .output_dir
        .with_file_name("runs-after-reload");
    let mut valid = rig.config.clone();
    valid.run.output_dir.clone_from(&new_output);
    let replies = std::sync::Arc::new(std::sync::Mutex::new(vec![
        Ok(valid),
        Err("invalid configuration: unknown field `stpe`".to_owned()),
    ]));
    let (sup, ctl) = rig.supervisor();
    let sup = sup.with_reloader(Box::new(move || replies.lock().unwrap().pop().unwrap()));
    rig.submit("first");
    rig.submit("second");
    let driver = async {
        sleep(Duration::from_secs(5)).await;
        assert_eq!(rig.state_of("first"), JobState::Running);
        ctl.send(Control::Reload).await.unwrap(); // refused
        sleep(Duration::from_secs(1)).await;
        ctl.send(Control::Reload).await.unwrap(); // accepted
        rig.wait_until(Duration::from_secs(120), all_final).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    let jobs = rig.jobs();
    assert!(
        jobs[0]
            .run_dir
            .as_ref()
            .unwrap()
            .starts_with(&rig.config.run.output_dir)
    );
    assert!(jobs[1].run_dir.as_ref().unwrap().starts_with(&new_output));
    let notices = rig.notices.notices();
    let reloads = notices.iter().filter(|n| **n == Notice::Reloading).count();
    assert_eq!(reloads, 2);
    // Each RELOADING is followed by READY.
    for (i, n) in notices.iter().enumerate() {
        if *n == Notice::Reloading {
            assert_eq!(notices[i + 1], Notice::Ready);
        }
    }
    // `sdsem submit` now validates against the reloaded configuration.
    let published = Config::load_with_env(
        Some(&rig.spool.config_snapshot_path()),
        &[],
        std::iter::empty(),
    )
    .unwrap();
    assert_eq!(published.run.output_dir, new_output);
}

#[tokio::test(start_paused = true)]
async fn the_watchdog_is_fed_during_long_jobs_and_stops_when_the_spool_is_gone() {
    let mut script = Script::default();
    script.jobs.insert(
        "long".into(),
        Behaviour::Work {
            duration: Duration::from_secs(600),
            stop_after: Duration::from_secs(1),
        },
    );
    let rig = Rig::new(script);
    rig.submit("long");
    let (sup, ctl) = rig.supervisor();
    let root = rig.spool.root().to_owned();
    let driver = async {
        rig.wait_until(Duration::from_secs(700), all_final).await;
        let t0 = Instant::now();
        // `mv daemon.lock` once stopped the pings (and let a second daemon in): now it
        // is noticed, said, and the lock file written again; the pings go on.
        std::fs::rename(root.join("daemon.lock"), root.join("elsewhere")).unwrap();
        sleep(Duration::from_secs(60)).await;
        let t1 = Instant::now();
        let status = rig.spool.daemon_status().unwrap();
        // The spool directory itself moved away: nothing can work, systemd must restart.
        std::fs::rename(&root, root.with_extension("gone")).unwrap();
        sleep(Duration::from_secs(60)).await;
        let t2 = Instant::now();
        std::fs::rename(root.with_extension("gone"), &root).unwrap();
        ctl.send(stop()).await.unwrap();
        (t0, t1, t2, status)
    };
    let start = Instant::now();
    let (result, (t0, t1, t2, status)) = tokio::join!(sup.run(), driver);
    result.unwrap();
    // Every 5 s through the 600 s job, idle too, with the lock file tampered with.
    assert!(rig.notices.watchdogs_between(start, t0) >= 120);
    assert_eq!(rig.notices.watchdogs_between(t0, t1), 12);
    assert_eq!(
        rig.notices
            .watchdogs_between(t1 + Duration::from_secs(5), t2),
        0
    );
    assert_eq!(status.warnings.len(), 1, "{:?}", status.warnings);
    assert!(
        status.warnings[0].contains("daemon.lock was moved away or removed"),
        "{:?}",
        status.warnings
    );
    let pid = std::fs::read_to_string(root.join("daemon.lock")).unwrap();
    assert_eq!(pid.trim(), std::process::id().to_string());
}

/// Starts a job and leaves it `running` with the stage at `tilt`, as a kill -9 would.
fn crash_mid_job(rig: &Rig, name: &str) {
    rig.submit(name);
    let owned = rig.spool.clone().lock().unwrap();
    let job = owned.next_queued().unwrap().0.unwrap();
    owned
        .start(&job, Path::new("/runs/x"), SystemTime::now())
        .unwrap();
}

/// After kill -9 mid-job with the stage left at 14°, the next start said READY and "idle"
/// without a word: now the stage is read and moved to its safe tilt before any job, and
/// the event is kept in `daemon.json`.
#[tokio::test(start_paused = true)]
async fn after_an_unclean_end_the_stage_is_brought_to_its_safe_tilt_before_any_job() {
    let script = Script {
        tilt: 14.0,
        safe_move: Duration::from_secs(14),
        ..Script::default()
    };
    let rig = Rig::new(script);
    crash_mid_job(&rig, "cut");
    rig.submit("next");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        rig.wait_until(Duration::from_secs(120), all_final).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    let events = rig.runner.events();
    let moved = events
        .iter()
        .position(|e| matches!(e, Event::SafeMove { from, .. } if *from == 14.0))
        .expect("moved to the safe tilt");
    let started = events
        .iter()
        .position(|e| matches!(e, Event::Started { .. }))
        .unwrap();
    assert!(moved < started, "{events:#?}");
    assert!(
        rig.notices.statuses().iter().any(|s| s
            .starts_with("after an unclean end the stage is at 14.000°, not at its safe tilt 0°")),
        "{:#?}",
        rig.notices.statuses()
    );
    let check = rig.spool.daemon_status().unwrap().stage_check.unwrap();
    assert!(!check.pending);
    assert_eq!(check.found_tilt_deg, Some(14.0));
    assert!(check.cause.contains("job 1 was running"), "{}", check.cause);
    assert!(
        check.action.contains("moved to its safe tilt"),
        "{}",
        check.action
    );

    // A clean stop: the next start reads nothing, moves nothing, keeps the last check.
    let runner = FakeRunner::new(Script {
        tilt: 3.0,
        ..Script::default()
    });
    let (tx, rx) = mpsc::channel(8);
    let sup = Supervisor::new(
        rig.spool.clone().lock().unwrap(),
        rig.config.clone(),
        runner.clone(),
        rx,
    )
    .with_disk(rig.disk.clone());
    let driver = async {
        sleep(Duration::from_secs(10)).await;
        tx.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    assert!(
        !runner
            .events()
            .iter()
            .any(|e| matches!(e, Event::StageRead { .. })),
        "{:?}",
        runner.events()
    );
    assert_eq!(rig.spool.daemon_status().unwrap().stage_check, Some(check));
}

/// `daemon.after_crash = "wait"`: no job runs until an operator acknowledges; then the
/// stage goes to its safe tilt and the queue runs. A wait cut short by a stop is still
/// pending at the next start.
#[tokio::test(start_paused = true)]
async fn with_after_crash_wait_no_job_runs_until_an_operator_acknowledges() {
    let script = Script {
        tilt: 9.0,
        ..Script::default()
    };
    let mut rig = Rig::new(script);
    rig.config.daemon.after_crash = sdsem::daemon::AfterCrash::Wait;
    crash_mid_job(&rig, "cut");
    rig.submit("next");
    // An old acknowledgement does not count for a new unclean end.
    rig.spool.acknowledge(SystemTime::now()).unwrap();
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        sleep(Duration::from_secs(60)).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    assert!(rig.runner.started().is_empty());
    let check = rig.spool.daemon_status().unwrap().stage_check.unwrap();
    assert!(
        check.pending && check.action.starts_with("waiting for an operator"),
        "{check:?}"
    );
    assert!(
        rig.notices
            .statuses()
            .iter()
            .any(|s| s.starts_with("held: waiting for an operator"))
    );

    // Restarted cleanly while waiting: still held; acknowledged: moved, then the job runs.
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        sleep(Duration::from_secs(30)).await;
        assert!(rig.runner.started().is_empty());
        rig.spool.acknowledge(SystemTime::now()).unwrap();
        rig.wait_until(Duration::from_secs(60), all_final).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    assert_eq!(rig.runner.started(), ["next"]);
    let check = rig.spool.daemon_status().unwrap().stage_check.unwrap();
    assert!(
        !check.pending && check.action.contains("moved to its safe tilt"),
        "{check:?}"
    );
}

/// A record written straight into `queued/` with `"name": "../../pub/evil"` made the daemon
/// create its run directory outside the output directory and run it: such a record gets the
/// same check as `submit` and is rejected; nothing is created, nothing runs.
#[tokio::test(start_paused = true)]
async fn a_record_written_around_submit_gets_the_same_check_and_is_rejected() {
    let rig = Rig::new(Script::default());
    let good = rig.submit("good");
    let queued = rig.spool.root().join("queued");
    let forged = |id: u64, edit: &dyn Fn(&mut serde_json::Value)| {
        let mut v = serde_json::to_value(&good).unwrap();
        v["id"] = id.into();
        edit(&mut v);
        std::fs::write(queued.join(format!("{id:08}.json")), v.to_string()).unwrap();
    };
    forged(2, &|v| {
        v["name"] = "../../pub/evil".into();
        v["job"]["name"] = "../../pub/evil".into();
    });
    forged(3, &|v| v["job"]["step"] = 1e-4.into());
    forged(4, &|v| {
        v["job"]["capture"] = serde_json::json!({"tracking": {"max_correction_um": 500.0}});
    });
    forged(5, &|v| v["job"]["end_tilt"] = serde_json::Value::Null);
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        rig.wait_until(Duration::from_secs(60), |jobs| {
            jobs.iter().filter(|j| j.state.is_final()).count() == 4
        })
        .await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    assert_eq!(rig.runner.started(), ["good"]);
    let jobs = rig.jobs();
    let reason = |id: u64| {
        let j = jobs.iter().find(|j| j.id.0 == id).unwrap();
        assert_eq!(j.state, JobState::Rejected, "{j:?}");
        assert!(j.run_dir.is_none());
        j.reason.clone().unwrap()
    };
    assert!(
        reason(2).starts_with("refused: name = \"../../pub/evil\" starts with"),
        "{}",
        reason(2)
    );
    assert!(
        reason(3).contains("below the step floor daemon.min_step_deg"),
        "{}",
        reason(3)
    );
    assert!(
        reason(4).contains("tracking.max_correction_um: a job may not set this key"),
        "{}",
        reason(4)
    );
    let listing = rig.spool.list().unwrap();
    // JSON has no inf: `end_tilt = inf` reaches a record as null, which is no number.
    assert_eq!(listing.set_aside_total, 1, "the record with end_tilt null");
    assert!(
        listing.set_aside[0]
            .cause
            .starts_with("not a job record: invalid type: null, expected f64"),
        "{:?}",
        listing.set_aside
    );
    // Only the good job's directory exists, inside the output directory.
    let runs: Vec<_> = std::fs::read_dir(&rig.config.run.output_dir)
        .unwrap()
        .collect();
    assert_eq!(runs.len(), 1);
    assert!(!rig.config.run.output_dir.join("../../pub").exists());
}

#[tokio::test(start_paused = true)]
async fn a_stop_while_waiting_for_the_links_ends_at_once() {
    let script = Script {
        link_checks: (0..100).map(|_| Err("stage: refused".to_owned())).collect(),
        ..Script::default()
    };
    let rig = Rig::new(script);
    rig.submit("a");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        sleep(Duration::from_secs(20)).await;
        ctl.send(stop()).await.unwrap();
        Instant::now()
    };
    let (result, sent) = tokio::join!(sup.run(), driver);
    assert_eq!(result.unwrap().interrupted, None);
    assert!(Instant::now() - sent < Duration::from_millis(10));
    assert_eq!(rig.state_of("a"), JobState::Queued);
    // READY came even though the first check failed, and STATUS says so.
    assert!(rig.notices.notices().contains(&Notice::Ready));
}

#[tokio::test(start_paused = true)]
async fn links_down_at_start_still_give_ready_and_are_rechecked_while_idle() {
    let script = Script {
        link_checks: (0..3).map(|_| Err("stage: refused".to_owned())).collect(),
        ..Script::default()
    };
    let rig = Rig::new(script);
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        sleep(Duration::from_secs(30)).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    let notices = rig.notices.notices();
    let ready = notices.iter().position(|n| *n == Notice::Ready).unwrap();
    assert_eq!(
        notices[ready - 1],
        Notice::Status("starting: link check 1 failed: stage: refused; retry in 1 s".into())
    );
    let checks = rig.runner.link_check_times();
    let gaps: Vec<u64> = checks
        .windows(2)
        .map(|w| (w[1].0 - w[0].0).as_secs())
        .collect();
    assert_eq!(gaps, [1, 2, 4], "then up: no more checks while idle");
    let statuses = rig.notices.statuses();
    assert!(
        statuses.contains(
            &"idle, 0 queued: link check 3 failed: stage: refused; retry in 4 s".to_owned()
        )
    );
    assert_eq!(statuses[statuses.len() - 2], "idle, 0 queued");
}

#[tokio::test(start_paused = true)]
async fn after_a_failed_job_the_idle_daemon_checks_the_links_again() {
    let mut script = Script::default();
    script.jobs.insert(
        "a".into(),
        Behaviour::Fail {
            after: Duration::from_secs(2),
            reason: "stage link lost: connection reset".into(),
        },
    );
    // Start-up and before `a`: fine; after it the controller is off twice.
    script.link_checks = [Ok(()), Ok(())]
        .into_iter()
        .chain((0..2).map(|_| Err("stage: connection refused".to_owned())))
        .collect();
    let rig = Rig::new(script);
    rig.submit("a");
    let (sup, ctl) = rig.supervisor();
    let driver = async {
        sleep(Duration::from_secs(30)).await;
        ctl.send(stop()).await.unwrap();
    };
    let (result, ()) = tokio::join!(sup.run(), driver);
    result.unwrap();
    assert_eq!(rig.state_of("a"), JobState::Failed);
    let oks: Vec<bool> = rig
        .runner
        .link_check_times()
        .iter()
        .map(|(_, ok)| *ok)
        .collect();
    assert_eq!(oks, [true, true, false, false, true], "checked while idle");
    let statuses = rig.notices.statuses();
    let failed_at = statuses
        .iter()
        .position(|s| s.starts_with("idle, 0 queued: link check 1 failed"))
        .unwrap_or_else(|| panic!("{statuses:#?}"));
    // Not "idle, 0 queued" (ready) between the failed job and that check.
    assert!(
        !statuses[..failed_at]
            .iter()
            .rev()
            .take_while(|s| !s.starts_with("running job"))
            .any(|s| s == "idle, 0 queued"),
        "{statuses:#?}"
    );
    assert_eq!(statuses.last().unwrap(), "stopped (SIGTERM)");
}
