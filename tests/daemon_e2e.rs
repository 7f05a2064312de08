//! The real daemon (`sdsem daemon`, acquisition runner) as a process against
//! the simulator, end to end:
//!
//! - a valid job is done with its outputs; an invalid one is refused by
//!   `sdsem submit` and never queued; one that a SIGHUP-reloaded
//!   configuration no longer allows is `rejected` at its turn; one whose
//!   simulator disappears mid-job fails with its reason and a readable MCAP;
//!   the daemon reconnects (with backoff) once the simulator is back, and
//!   again when a reload moves the links to another simulator;
//! - SIGTERM mid-job: stage back at its safe tilt (from the record), MCAP
//!   finished, job `interrupted`, exit 0 within 15 s;
//! - `kill -9` mid-job, restart: that job `interrupted`, never re-run, the
//!   queue goes on;
//! - a job reconstructed by the daemon is reproduced bit for bit by
//!   `sdsem replay` with another thread count.
//!
//! Small frames (320×240, tracking 160×120) and a simulator 20× faster than
//! real time keep them at a few seconds each.

#![allow(clippy::unwrap_used)]

mod daemon_support;

use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use daemon_support::process::{Daemon, job, sdsem, state_of, submit, text, wait_final, write_job};
use rustix::process::Signal;
use sdsem::daemon::JobState;
use sdsem::daemon::spool::CRASH_REASON;
use sdsem::record::{self, RunStatus, StageState, topics};
use sdsem::stage::{StageAxis, StageEvent};
use sdsem_sim::{SimConfig, SimEndpoint, SimHandle, Simulator};

const TIME_SCALE: f64 = 0.05;

/// The daemon's configuration; `stage` and `imaging` add keys to those sections.
fn daemon_config(dir: &Path, stage: &str, imaging: &str) -> String {
    format!(
        r#"[run]
output_dir = {runs:?}
reconstruct = false

[stage]
{stage}
axis_x = "X"
axis_y = "Y"
axis_tilt = "T"
poll_interval_s = 0.01
connect_timeout_s = 2.0

[imaging]
{imaging}

[imaging.micrograph]
width = 320
height = 240
dwell_us = 10.0

[imaging.tracking]
width = 160
height = 120
dwell_us = 1.0

[daemon]
spool_dir = {spool:?}
min_free_gib = 0
poll_interval_s = 0.1
backoff_initial_s = 0.2
backoff_max_s = 0.5
link_check_timeout_s = 5.0
"#,
        runs = dir.join("runs"),
        spool = dir.join("spool"),
    )
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// The simulator in this test process, on fixed ports so it can be stopped
/// (a lost link, as a switched-off controller gives) and started again.
fn start_simulator(stage_port: u16, sem_port: u16) -> SimHandle {
    let mut c = SimConfig {
        seed: 5,
        time_scale: TIME_SCALE,
        ..SimConfig::default()
    };
    c.stage.endpoint = SimEndpoint::Tcp(SocketAddr::from(([127, 0, 0, 1], stage_port)));
    c.sem.endpoint = SimEndpoint::Tcp(SocketAddr::from(([127, 0, 0, 1], sem_port)));
    let end = Instant::now() + Duration::from_secs(10);
    loop {
        match Simulator::spawn(c.clone()) {
            Ok(sim) => return sim,
            // The old listener's port may take a moment to be free again.
            Err(e) if Instant::now() < end => {
                eprintln!("simulator restart: {e}; retrying");
                std::thread::sleep(Duration::from_millis(100));
            }
            Err(e) => panic!("cannot start the simulator: {e}"),
        }
    }
}

fn run_dir(spool: &Path, id: u64) -> PathBuf {
    job(spool, id).unwrap().run_dir.unwrap()
}

/// Reads a record the way a user would and checks it is usable.
fn inspect(record: &Path) -> record::RecordInspection {
    let summary = record::read_summary(record)
        .unwrap_or_else(|e| panic!("{} unreadable: {e}", record.display()));
    // Every frame it holds decodes.
    let frames = record::read_images(record, topics::SEM_FRAME, |_| true).unwrap();
    for f in &frames.items {
        f.to_image().unwrap();
    }
    assert_eq!(
        frames.items.len() as u64,
        summary.message_count(topics::SEM_FRAME)
    );
    summary
}

fn wait_for_file(path: &Path, limit: Duration) {
    let end = Instant::now() + limit;
    while !path.exists() {
        assert!(Instant::now() < end, "{} never appeared", path.display());
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn three_jobs_done_rejected_failed_then_reconnect() {
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join("spool");
    let (stage_port, sem_port) = (free_port(), free_port());
    let config_path = dir.path().join("sdsem.toml");
    let config_for = |stage_port: u16, sem_port: u16, tilt_max: f64| {
        daemon_config(
            dir.path(),
            &format!("endpoint = \"tcp://127.0.0.1:{stage_port}\"\ntilt_max_deg = {tilt_max:.1}"),
            &format!("endpoint = \"tcp://127.0.0.1:{sem_port}\""),
        )
    };
    let endpoints = |tilt_max: f64| config_for(stage_port, sem_port, tilt_max);
    std::fs::write(&config_path, endpoints(70.0)).unwrap();
    // The daemon publishes its configuration in the spool; before it runs,
    // submit checks against the same file.
    let submit_checked = |job: &str| {
        let out = sdsem(&[
            "submit",
            job,
            "--spool",
            spool.to_str().unwrap(),
            "--config",
            config_path.to_str().unwrap(),
        ]);
        assert!(out.status.success(), "submit {job}: {}", text(&out.stderr));
    };
    let valid = write_job(
        dir.path(),
        "valid.toml",
        "name = \"valid\"\nstart_tilt = 0\nend_tilt = 3\n",
    );
    let long = write_job(
        dir.path(),
        "long.toml",
        "name = \"long\"\nstart_tilt = 0\nend_tilt = 60\n",
    );
    let wide = write_job(
        dir.path(),
        "wide.toml",
        "name = \"wide\"\nstart_tilt = 0\nend_tilt = 30\n",
    );
    submit_checked(&valid);
    submit_checked(&long);
    submit_checked(&wide);

    // Invalid: refused in one line, never queued.
    let steep = write_job(
        dir.path(),
        "steep.toml",
        "name = \"steep\"\nstart_tilt = 0\nend_tilt = 80\n",
    );
    let out = sdsem(&[
        "submit",
        &steep,
        "--spool",
        spool.to_str().unwrap(),
        "--config",
        config_path.to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(
        err.contains("refused, nothing queued") && err.contains("end_tilt = 80°"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(job(&spool, 4).is_none(), "the refused job was queued");

    let sim = start_simulator(stage_port, sem_port);
    let mut daemon = Daemon::sdsem(dir.path(), &config_path, "1");
    daemon.expect(Duration::from_secs(30), |l| l == "READY=1");

    // 1. Valid: done, with its outputs.
    let done = wait_final(&spool, 1, Duration::from_secs(60));
    assert_eq!(
        done.state,
        JobState::Done,
        "{:?}\n{}",
        done.reason,
        daemon.log()
    );
    let dir1 = done.run_dir.clone().unwrap();
    for file in ["run.mcap", "left.tif", "right.tif", "config.toml"] {
        assert!(
            dir1.join(file).is_file(),
            "{file} missing in {}",
            dir1.display()
        );
    }
    let summary = inspect(&dir1.join("run.mcap"));
    assert!(summary.end.complete);
    assert_eq!(summary.outcome.unwrap().status, RunStatus::Succeeded);
    assert_eq!(summary.frames_by_role.get("left"), Some(&1));
    assert_eq!(summary.frames_by_role.get("right"), Some(&1));

    // 2. Long: mid-job, reload a narrower configuration, then lose the simulator.
    daemon.expect(Duration::from_secs(30), |l| {
        l.starts_with("STATUS=running job 2 long: step 4/")
    });
    std::fs::write(&config_path, endpoints(25.0)).unwrap();
    let before = daemon.seen.len();
    daemon.signal(Signal::HUP);
    daemon.expect_after(before, Duration::from_secs(5), |l| l == "RELOADING=1");
    daemon.expect_after(before, Duration::from_secs(5), |l| l == "READY=1");
    assert_eq!(state_of(&spool, 2).unwrap().0, JobState::Running);
    drop(sim);

    let failed = wait_final(&spool, 2, Duration::from_secs(60));
    assert_eq!(failed.state, JobState::Failed, "{:?}", failed.reason);
    let reason = failed.reason.unwrap();
    println!("job 2 failed: {reason}");
    assert!(
        reason.contains("stage") || reason.contains("SEM"),
        "{reason}"
    );
    let summary = inspect(&failed.run_dir.unwrap().join("run.mcap"));
    assert!(
        summary.end.complete,
        "the record was finished: {:?}",
        summary.end
    );
    let outcome = summary.outcome.clone().unwrap();
    assert_eq!(outcome.status, RunStatus::Failed);
    assert!(outcome.cause.is_some());
    assert!(summary.message_count(topics::SEM_FRAME) >= 4);

    // 3. Wide: allowed when submitted, not under the reloaded configuration.
    let rejected = wait_final(&spool, 3, Duration::from_secs(30));
    assert_eq!(rejected.state, JobState::Rejected);
    let reason = rejected.reason.unwrap();
    assert!(
        reason.contains("does not fit the configuration in force")
            && reason.contains("end_tilt = 30°")
            && reason.contains("25°"),
        "{reason}"
    );
    assert!(rejected.run_dir.is_none(), "a rejected job never starts");

    // The links are down: checked again with backoff, said in STATUS.
    daemon.expect(Duration::from_secs(30), |l| {
        l.starts_with("STATUS=idle, 0 queued: link check 2 failed")
    });

    // The simulator is back: the next job runs.
    let sim = start_simulator(stage_port, sem_port);
    submit(&valid, &spool);
    let done = wait_final(&spool, 4, Duration::from_secs(60));
    assert_eq!(
        done.state,
        JobState::Done,
        "{:?}\n{}",
        done.reason,
        daemon.log()
    );
    assert!(daemon.log().contains("stage and imaging links are back"));

    // A reload that moves the links while they are up: the daemon
    // reconnects, and the next job runs on the new instruments.
    let (stage2, sem2) = (free_port(), free_port());
    let sim2 = start_simulator(stage2, sem2);
    let frames_on_first = sim.last_frame();
    std::fs::write(&config_path, config_for(stage2, sem2, 25.0)).unwrap();
    let before = daemon.seen.len();
    daemon.signal(Signal::HUP);
    daemon.expect_after(before, Duration::from_secs(5), |l| l == "READY=1");
    submit(&valid, &spool);
    let done = wait_final(&spool, 5, Duration::from_secs(60));
    assert_eq!(
        done.state,
        JobState::Done,
        "{:?}\n{}",
        done.reason,
        daemon.log()
    );
    assert!(
        sim2.last_frame().unwrap_or(0) >= 5,
        "job 5 ran on the new simulator"
    );
    assert_eq!(sim.last_frame(), frames_on_first, "not on the old one");

    let out = sdsem(&["status", "--spool", spool.to_str().unwrap(), "--json"]);
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let jobs = json["jobs"].as_array().unwrap();
    let states: Vec<&str> = jobs.iter().map(|j| j["state"].as_str().unwrap()).collect();
    assert_eq!(states, ["done", "failed", "rejected", "done", "done"]);
    assert!(jobs[1]["reason"].is_string() && jobs[2]["reason"].is_string());

    daemon.signal(Signal::TERM);
    let (status, _) = daemon.wait_exit(Duration::from_secs(15));
    assert!(status.success(), "{}", daemon.log());
    drop((sim, sim2));
}

/// The last verified tilt in a record's `/stage/state`.
fn last_reached_tilt(record: &Path) -> f64 {
    let states = record::read_json(record, topics::STAGE_STATE).unwrap();
    states
        .items
        .iter()
        .rev()
        .filter_map(|m| m.parse::<StageState>().ok())
        .filter(|s| s.event == StageEvent::Reached)
        .find_map(|s| {
            s.axes
                .iter()
                .find(|a| a.axis == StageAxis::Tilt)
                .and_then(|a| a.position)
        })
        .expect("a verified tilt in /stage/state")
}

#[test]
fn sigterm_and_kill_mid_job_then_replay_of_a_daemon_run() {
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join("spool");
    let config_path = dir.path().join("sdsem.toml");
    std::fs::write(
        &config_path,
        format!(
            "{}\n[simulator]\nseed = 3\ntime_scale = {TIME_SCALE}\n",
            daemon_config(dir.path(), "", "")
        ),
    )
    .unwrap();
    let job_file = |name: &str, end: u32, extra: &str| {
        write_job(
            dir.path(),
            &format!("{name}.toml"),
            &format!("name = \"{name}\"\nstart_tilt = 0\nend_tilt = {end}\n{extra}"),
        )
    };
    submit(&job_file("long", 60, ""), &spool);
    submit(
        &job_file("recon", 4, "[reconstruction]\nrun.reconstruct = true\n"),
        &spool,
    );

    // SIGTERM in mid-job.
    let mut daemon = Daemon::sdsem(dir.path(), &config_path, "term");
    daemon.expect(Duration::from_secs(30), |l| {
        l.starts_with("STATUS=running job 1 long: step 4/")
    });
    let sent = Instant::now();
    daemon.signal(Signal::TERM);
    let (status, _) = daemon.wait_exit(Duration::from_secs(15));
    let took = sent.elapsed();
    assert!(status.success(), "exit {status:?}\n{}", daemon.log());
    assert!(took < Duration::from_secs(15), "{took:?}");
    println!("SIGTERM to exit, mid-job, real runner: {took:?}");
    let (state, reason) = state_of(&spool, 1).unwrap();
    assert_eq!(state, JobState::Interrupted);
    assert!(reason.unwrap().starts_with("stopped by SIGTERM"));
    let record1 = run_dir(&spool, 1).join("run.mcap");
    let summary = inspect(&record1);
    assert!(summary.end.complete, "MCAP finished: {:?}", summary.end);
    assert_eq!(summary.outcome.unwrap().status, RunStatus::Aborted);
    let tilt = last_reached_tilt(&record1);
    assert!(tilt.abs() < 0.05, "stage left at {tilt}°, safe tilt is 0°");
    assert_eq!(state_of(&spool, 2).unwrap().0, JobState::Queued);

    // Restart: the reconstructing job runs; then kill -9 in the middle of the next.
    submit(&job_file("long2", 60, ""), &spool);
    submit(&job_file("quick", 2, ""), &spool);
    let mut daemon = Daemon::sdsem(dir.path(), &config_path, "kill");
    let recon = wait_final(&spool, 2, Duration::from_secs(120));
    assert_eq!(
        recon.state,
        JobState::Done,
        "{:?}\n{}",
        recon.reason,
        daemon.log()
    );
    // STATUS said which stage of the reconstruction ran.
    daemon.expect(Duration::from_secs(1), |l| {
        l.starts_with("STATUS=running job 2 recon: reconstructing: dense stage")
    });
    daemon.expect(Duration::from_secs(30), |l| {
        l.starts_with("STATUS=running job 3 long2: step 4/")
    });
    daemon.signal(Signal::KILL);
    daemon.wait_exit(Duration::from_secs(5));
    let crashed = job(&spool, 3).unwrap();
    assert_eq!(crashed.state, JobState::Running, "as the crash left it");
    let record3 = crashed.run_dir.clone().unwrap().join("run.mcap");
    let summary = inspect(&record3);
    assert!(
        !summary.end.complete,
        "a killed run leaves an unfinished file"
    );
    assert!(
        summary.message_count(topics::SEM_FRAME) >= 3,
        "frames up to the kill are readable: {:?}",
        summary.frames_by_role
    );

    // Next start: job 3 interrupted (not re-run), the queue goes on.
    let mut daemon = Daemon::sdsem(dir.path(), &config_path, "after");
    let quick = wait_final(&spool, 4, Duration::from_secs(60));
    assert_eq!(
        quick.state,
        JobState::Done,
        "{:?}\n{}",
        quick.reason,
        daemon.log()
    );
    let after = job(&spool, 3).unwrap();
    assert_eq!(after.state, JobState::Interrupted);
    assert_eq!(after.reason.as_deref(), Some(CRASH_REASON));
    assert_eq!(after.run_dir, crashed.run_dir);
    assert_eq!(after.started, crashed.started);
    let long2_runs = std::fs::read_dir(dir.path().join("runs"))
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .starts_with("long2-")
        })
        .count();
    assert_eq!(long2_runs, 1, "job 3 was run again");
    daemon.signal(Signal::TERM);
    let (status, _) = daemon.wait_exit(Duration::from_secs(15));
    assert!(status.success());

    // The daemon's reconstruction, replayed with one thread (the daemon had two).
    let record2 = recon.run_dir.unwrap().join("run.mcap");
    wait_for_file(&record2, Duration::from_secs(1));
    let out_dir = dir.path().join("replay");
    let out = Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .args(["replay", record2.to_str().unwrap(), "--out"])
        .arg(&out_dir)
        .env("RAYON_NUM_THREADS", "1")
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        text(&out.stdout).contains("bit-for-bit identical"),
        "{}",
        text(&out.stdout)
    );
}

/// A STATUS line's text, without the `STATUS=`.
fn status_of(line: &str) -> &str {
    line.strip_prefix("STATUS=").unwrap_or(line)
}

/// After kill -9 mid-move the restarted daemon said READY and "idle" with the stage left
/// at 14°: now it reads the stage first, says so, and moves it to its safe tilt before
/// any job (`after_crash = "move"`), or holds until `sdsem daemon --ack` (`"wait"`).
#[test]
fn after_kill_mid_move_the_stage_is_made_safe_before_the_next_job() {
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join("spool");
    let (stage_port, sem_port) = (free_port(), free_port());
    let sim = start_simulator(stage_port, sem_port);
    let config_path = dir.path().join("sdsem.toml");
    let write_config = |after_crash: &str| {
        let text = daemon_config(
            dir.path(),
            &format!("endpoint = \"tcp://127.0.0.1:{stage_port}\""),
            &format!("endpoint = \"tcp://127.0.0.1:{sem_port}\""),
        );
        std::fs::write(
            &config_path,
            format!("{text}after_crash = \"{after_crash}\"\n"),
        )
        .unwrap();
    };
    write_config("move");
    let job_file = |name: &str, end: u32| {
        write_job(
            dir.path(),
            &format!("{name}.toml"),
            &format!("name = \"{name}\"\nstart_tilt = 0\nend_tilt = {end}\n"),
        )
    };
    submit(&job_file("long", 60), &spool);
    submit(&job_file("quick", 2), &spool);

    let mut daemon = Daemon::sdsem(dir.path(), &config_path, "cut");
    daemon.expect(Duration::from_secs(60), |l| {
        l.starts_with("STATUS=running job 1 long: step 6/")
    });
    daemon.signal(Signal::KILL);
    daemon.wait_exit(Duration::from_secs(5));
    let left_at = sim.stage_snapshot().pose.tilt_deg;
    assert!(left_at > 3.0, "the kill left the stage at {left_at}°");

    let mut daemon = Daemon::sdsem(dir.path(), &config_path, "move");
    let said = daemon.expect(Duration::from_secs(60), |l| {
        status_of(l).starts_with("after an unclean end the stage is at")
    });
    println!("{said}");
    let quick = wait_final(&spool, 2, Duration::from_secs(60));
    assert_eq!(
        quick.state,
        JobState::Done,
        "{:?}\n{}",
        quick.reason,
        daemon.log()
    );
    let log = daemon.log();
    let moved = log
        .find("moved to its safe tilt")
        .unwrap_or_else(|| panic!("{log}"));
    let started = log.find("job started").unwrap();
    assert!(moved < started, "{log}");
    // Under the journal: a warning, with its priority.
    assert!(
        log.lines()
            .any(|l| l.starts_with("<4>") && l.contains("moved to its safe tilt")),
        "{log}"
    );
    let out = sdsem(&["status", "--spool", spool.to_str().unwrap(), "--json"]);
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let check = &json["daemon"]["stage_check"];
    assert_eq!(check["pending"], false, "{check}");
    assert!(check["found_tilt_deg"].as_f64().unwrap() > 3.0, "{check}");
    assert!(
        check["cause"]
            .as_str()
            .unwrap()
            .contains("job 1 was running")
    );
    let out = sdsem(&["status", "--spool", spool.to_str().unwrap()]);
    assert!(
        text(&out.stdout).contains("stage check after an unclean end"),
        "{}",
        text(&out.stdout)
    );
    daemon.signal(Signal::TERM);
    assert!(daemon.wait_exit(Duration::from_secs(15)).0.success());

    // "wait": nothing runs until an operator acknowledges.
    write_config("wait");
    submit(&job_file("long2", 60), &spool);
    submit(&job_file("quick2", 2), &spool);
    let mut daemon = Daemon::sdsem(dir.path(), &config_path, "cut2");
    daemon.expect(Duration::from_secs(60), |l| {
        l.starts_with("STATUS=running job 3 long2: step 6/")
    });
    daemon.signal(Signal::KILL);
    daemon.wait_exit(Duration::from_secs(5));
    let mut daemon = Daemon::sdsem(dir.path(), &config_path, "wait");
    daemon.expect(Duration::from_secs(60), |l| {
        status_of(l).starts_with("held: waiting for an operator")
    });
    std::thread::sleep(Duration::from_secs(1));
    assert_eq!(state_of(&spool, 4).unwrap().0, JobState::Queued);
    assert!(
        sim.stage_snapshot().pose.tilt_deg > 3.0,
        "moved without an operator"
    );
    let out = sdsem(&["daemon", "--ack", "--spool", spool.to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        text(&out.stdout).starts_with("acknowledged"),
        "{}",
        text(&out.stdout)
    );
    let quick2 = wait_final(&spool, 4, Duration::from_secs(60));
    assert_eq!(
        quick2.state,
        JobState::Done,
        "{:?}\n{}",
        quick2.reason,
        daemon.log()
    );
    assert!(
        daemon.log().contains("an operator acknowledged"),
        "{}",
        daemon.log()
    );
    daemon.signal(Signal::TERM);
    assert!(daemon.wait_exit(Duration::from_secs(15)).0.success());
    drop(sim);
}

/// A disk that filled while the record was written made the daemon exit 1 at every
/// restart, and the job was labelled "crash or power cut". On an 8 MiB tmpfs (in a user
/// and mount namespace of its own, `unshare -rm`): the job fails with the real reason,
/// its record is cut cleanly, the daemon goes on and runs the next job once space is back.
#[test]
fn a_full_disk_fails_the_job_with_the_real_reason_and_the_daemon_goes_on() {
    let probe = Command::new("unshare")
        .args(["-rm", "sh", "-c", "mount -t tmpfs -o size=1m tmpfs /mnt"])
        .output();
    if !probe.is_ok_and(|o| o.status.success()) {
        eprintln!("unshare -rm with a tmpfs mount is not available here: full-disk test skipped");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let disk = dir.path().join("disk");
    std::fs::create_dir(&disk).unwrap();
    let (stage_port, sem_port) = (free_port(), free_port());
    let sim = start_simulator(stage_port, sem_port);
    let config_path = dir.path().join("sdsem.toml");
    let text = daemon_config(
        &disk,
        &format!("endpoint = \"tcp://127.0.0.1:{stage_port}\""),
        &format!("endpoint = \"tcp://127.0.0.1:{sem_port}\""),
    );
    std::fs::write(&config_path, text).unwrap();
    let mut command = Command::new("unshare");
    command
        .args([
            "-rm",
            "sh",
            "-c",
            "mount -t tmpfs -o size=8m tmpfs \"$0\" && exec \"$@\"",
        ])
        .arg(&disk)
        .arg(env!("CARGO_BIN_EXE_sdsem"))
        .args(["--log-format", "text", "daemon", "--config"])
        .arg(&config_path)
        .env("RUST_LOG", "info");
    let mut daemon = Daemon::spawn(command, dir.path(), "disk");
    daemon.expect(Duration::from_secs(30), |l| l == "READY=1");
    // The tmpfs is the daemon's: seen through its root.
    let inside = PathBuf::from(format!("/proc/{}/root", daemon.child.id()))
        .join(disk.strip_prefix("/").unwrap());
    let spool = inside.join("spool");
    let job_file = |name: &str, end: u32| {
        write_job(
            dir.path(),
            &format!("{name}.toml"),
            &format!("name = \"{name}\"\nstart_tilt = 0\nend_tilt = {end}\n"),
        )
    };
    submit(&job_file("long", 60), &spool);
    daemon.expect(Duration::from_secs(60), |l| {
        l.starts_with("STATUS=running job 1 long: step 4/")
    });
    // Fill the disk.
    let filler = inside.join("filler");
    let mut f = std::fs::File::create(&filler).unwrap();
    let chunk = vec![0u8; 64 * 1024];
    while std::io::Write::write_all(&mut f, &chunk).is_ok() {}
    drop(f);

    let failed = wait_final(&spool, 1, Duration::from_secs(60));
    assert_eq!(
        failed.state,
        JobState::Failed,
        "{:?}\n{}",
        failed.reason,
        daemon.log()
    );
    let reason = failed.reason.unwrap();
    println!("job 1 failed: {reason}");
    assert!(reason.contains("No space left on device"), "{reason}");
    assert!(!reason.contains("crash or power cut"), "{reason}");
    assert!(
        daemon.child.try_wait().unwrap().is_none(),
        "{}",
        daemon.log()
    );
    let log = daemon.log();
    assert!(
        log.lines()
            .any(|l| l.starts_with("<3>") && l.contains("job failed")),
        "{log}"
    );
    let run_dir = PathBuf::from(format!("/proc/{}/root", daemon.child.id()))
        .join(failed.run_dir.unwrap().strip_prefix("/").unwrap());
    let record = run_dir.join("run.mcap");
    let summary = record::read_summary(&record).unwrap();
    assert!(summary.message_count(topics::SEM_FRAME) >= 3, "{summary:?}");

    // Space is back: the next job runs.
    std::fs::remove_file(&filler).unwrap();
    submit(&job_file("quick", 2), &spool);
    let done = wait_final(&spool, 2, Duration::from_secs(60));
    assert_eq!(
        done.state,
        JobState::Done,
        "{:?}\n{}",
        done.reason,
        daemon.log()
    );
    daemon.signal(Signal::TERM);
    let (status, _) = daemon.wait_exit(Duration::from_secs(15));
    assert!(status.success(), "{}", daemon.log());
    drop(sim);
}
