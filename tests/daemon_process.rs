//! The daemon and its commands as processes: `sdsem submit` and `sdsem status`
//! through the real binary; the daemon (with the scripted runner, since the
//! binary's acquisition runner is not in this branch) in a child process of
//! this test binary, driven by real signals and read through a real
//! `$NOTIFY_SOCKET`: READY, STATUS, WATCHDOG, SIGHUP, SIGTERM within 15 s,
//! a second daemon refused, and recovery after SIGKILL.

#![allow(clippy::unwrap_used)]

mod daemon_support;

use std::path::PathBuf;
use std::process::Command;
use std::time::Duration;

use daemon_support::process::{Daemon, sdsem, state_of, text, write_job};
use daemon_support::{Behaviour, FakeRunner, Script};
use sdsem::daemon::spool::CRASH_REASON;
use sdsem::daemon::{DaemonOptions, JobState, Spool, load_config, run_daemon};

const CHILD_ENV: &str = "SDSEM_TEST_DAEMON_CONFIG";

#[test]
fn submit_refuses_invalid_jobs_and_status_lists_the_queue() {
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join("spool");
    let spool_arg = spool.to_str().unwrap();

    let steep = write_job(
        dir.path(),
        "steep.toml",
        "name = \"steep\"\nstart_tilt = 0\nend_tilt = 80\n",
    );
    let out = sdsem(&["submit", &steep, "--spool", spool_arg]);
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(err.contains("refused, nothing queued"), "{err}");
    assert!(
        err.contains("end_tilt = 80°") && err.contains("[-5°, 70°]"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");

    let typo = write_job(
        dir.path(),
        "typo.toml",
        "name = \"t\"\nstart_tilt = 0\nend_tilt = 5\nstpe = 1\n",
    );
    let out = sdsem(&["submit", &typo, "--spool", spool_arg]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("stpe"), "{}", text(&out.stderr));

    let stage = write_job(
        dir.path(),
        "stage.toml",
        "name = \"s\"\nstart_tilt = 0\nend_tilt = 5\n[capture]\nstage.tilt_max_deg = 90\n",
    );
    let out = sdsem(&["submit", &stage, "--spool", spool_arg]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("a job may not set this key"));

    let good = write_job(
        dir.path(),
        "good.toml",
        "name = \"pollen-7\"\nstart_tilt = 0\nend_tilt = 7\n[capture]\ntracking.gain = 0.5\n",
    );
    let out = sdsem(&["submit", &good, "--spool", spool_arg]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(text(&out.stdout).starts_with("queued job 1 (pollen-7) in "));

    // Refused jobs never entered the queue.
    let listing = Spool::existing(&spool).unwrap().list().unwrap();
    assert_eq!(listing.jobs.len(), 1);

    let out = sdsem(&["status", "--spool", spool_arg, "--json"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json["spool"], spool_arg);
    assert!(json["daemon"].is_null());
    let job = &json["jobs"][0];
    assert_eq!(job["id"], 1);
    assert_eq!(job["name"], "pollen-7");
    assert_eq!(job["state"], "queued");
    assert!(job["reason"].is_null());
    assert!(job["submitted"].as_str().unwrap().ends_with('Z'));
    assert_eq!(job["job"]["step"], 1.0);
    assert_eq!(job["job"]["capture"]["tracking"]["gain"], 0.5);

    let out = sdsem(&["status", "--spool", spool_arg]);
    let table = text(&out.stdout);
    assert!(table.contains("ID  NAME      STATE   SUBMITTED"), "{table}");
    assert!(table.contains("pollen-7  queued"), "{table}");

    let out = sdsem(&[
        "status",
        "--spool",
        dir.path().join("nowhere").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("no spool at"));
}

/// Not a test on its own: the daemon process that the test below starts (this
/// same binary, with `SDSEM_TEST_DAEMON_CONFIG` set). Without it, it does nothing.
#[test]
#[ignore = "helper process of daemon_process_signals_exclusivity_and_crash_recovery"]
fn daemon_child() {
    let Ok(config) = std::env::var(CHILD_ENV) else {
        return;
    };
    let _ = tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_env_filter("info")
        .try_init();
    let mut script = Script::default();
    script.jobs.insert(
        "long".into(),
        Behaviour::Work {
            duration: Duration::from_secs(3600),
            stop_after: Duration::from_millis(500),
        },
    );
    script.jobs.insert(
        "quick".into(),
        Behaviour::Work {
            duration: Duration::from_millis(300),
            stop_after: Duration::from_millis(100),
        },
    );
    let options = DaemonOptions {
        config_file: PathBuf::from(config),
        overrides: Vec::new(),
        spool: None,
    };
    let code = match load_config(&options)
        .and_then(|config| run_daemon(&options, config, FakeRunner::new(script)))
    {
        Ok(_) => 0,
        Err(e) => {
            eprintln!("error: {e}");
            1
        }
    };
    std::process::exit(code);
}

/// This test binary as the daemon with the scripted runner.
fn fake_daemon(dir: &std::path::Path, config: &std::path::Path, tag: &str) -> Daemon {
    let mut command = Command::new(std::env::current_exe().unwrap());
    command
        .args([
            "daemon_child",
            "--exact",
            "--ignored",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD_ENV, config);
    Daemon::spawn(command, dir, tag)
}

#[test]
fn daemon_process_signals_exclusivity_and_crash_recovery() {
    use rustix::process::Signal;
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join("spool");
    let config = dir.path().join("sdsem.toml");
    let valid = format!(
        "[run]\noutput_dir = {:?}\n[daemon]\nspool_dir = {:?}\nmin_free_gib = 0\npoll_interval_s = 0.1\n",
        dir.path().join("runs"),
        spool
    );
    std::fs::write(&config, &valid).unwrap();
    let spool_arg = spool.to_str().unwrap();
    let long = write_job(
        dir.path(),
        "long.toml",
        "name = \"long\"\nstart_tilt = 0\nend_tilt = 7\n",
    );
    let quick = write_job(
        dir.path(),
        "quick.toml",
        "name = \"quick\"\nstart_tilt = 0\nend_tilt = 7\n",
    );

    // Start: READY once the links are checked, then STATUS idle, and watchdog pings.
    let mut daemon = fake_daemon(dir.path(), &config, "1");
    daemon.expect(Duration::from_secs(30), |l| l == "READY=1");
    daemon.expect(Duration::from_secs(5), |l| l == "STATUS=idle, 0 queued");
    daemon.expect(Duration::from_secs(5), |l| l == "WATCHDOG=1");

    // A job submitted while it runs is picked up.
    let out = sdsem(&["submit", &long, "--spool", spool_arg]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    daemon.expect(Duration::from_secs(10), |l| {
        l.starts_with("STATUS=running job 1 long")
    });

    // A second daemon on the same spool is refused, naming the first one's PID.
    let mut second = fake_daemon(dir.path(), &config, "2");
    let (status, _) = second.wait_exit(Duration::from_secs(30));
    assert!(!status.success());
    let msg = second.log();
    assert!(
        msg.contains(&format!(
            "in use by another sdsem daemon (PID {})",
            daemon.child.id()
        )),
        "{msg}"
    );

    // SIGHUP with a broken file: reload refused, the daemon goes on.
    std::fs::write(&config, "[daemon]\nspool_dirr = \"/x\"\n").unwrap();
    let before_hup = daemon.seen.len();
    daemon.signal(Signal::HUP);
    daemon.expect_after(before_hup, Duration::from_secs(5), |l| l == "RELOADING=1");
    daemon.expect_after(before_hup, Duration::from_secs(5), |l| l == "READY=1");
    std::fs::write(&config, &valid).unwrap();
    assert!(daemon.child.try_wait().unwrap().is_none());
    assert!(daemon.log().contains("configuration reload refused"));

    // SIGTERM: the job is interrupted, the daemon says STOPPING and exits 0 within 15 s.
    daemon.signal(Signal::TERM);
    let (status, took) = daemon.wait_exit(Duration::from_secs(15));
    assert!(status.success(), "exit {status:?}\n{}", daemon.log());
    println!("SIGTERM to exit during a job: {took:?}");
    daemon.expect(Duration::from_secs(1), |l| l == "STOPPING=1");
    let (state, reason) = state_of(&spool, 1).unwrap();
    assert_eq!(state, JobState::Interrupted);
    assert!(reason.unwrap().starts_with("stopped by SIGTERM"));

    // Crash: SIGKILL mid-job; the next start marks it interrupted and runs the rest.
    for job in [&long, &quick] {
        assert!(
            sdsem(&["submit", job, "--spool", spool_arg])
                .status
                .success()
        );
    }
    let mut daemon = fake_daemon(dir.path(), &config, "3");
    daemon.expect(Duration::from_secs(30), |l| {
        l.starts_with("STATUS=running job 2 long")
    });
    daemon.signal(Signal::KILL);
    daemon.wait_exit(Duration::from_secs(5));
    assert_eq!(
        state_of(&spool, 2).unwrap().0,
        JobState::Running,
        "as the crash left it"
    );

    let mut daemon = fake_daemon(dir.path(), &config, "4");
    daemon.expect(Duration::from_secs(30), |l| l == "STATUS=idle, 0 queued");
    let (state, reason) = state_of(&spool, 2).unwrap();
    assert_eq!(state, JobState::Interrupted);
    assert_eq!(reason.as_deref(), Some(CRASH_REASON));
    assert_eq!(state_of(&spool, 3).unwrap().0, JobState::Done);
    daemon.signal(Signal::TERM);
    let (status, took) = daemon.wait_exit(Duration::from_secs(15));
    assert!(status.success());
    assert!(took < Duration::from_secs(5), "idle stop took {took:?}");

    let out = sdsem(&["status", "--spool", spool_arg, "--json"]);
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let states: Vec<&str> = json["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["state"].as_str().unwrap())
        .collect();
    assert_eq!(states, ["interrupted", "interrupted", "done"]);
    assert_eq!(json["daemon"]["state"], "stopped");
    assert_eq!(json["daemon"]["alive"], false);
}

/// Every entry that once blocked, crashed or fooled the daemon, dropped into `queued/`
/// of a running daemon: it sets each aside with its reason, runs the valid job behind
/// them, keeps feeding the watchdog and answering SIGTERM; `status` prints the names
/// escaped and cut short.
#[test]
fn hostile_spool_entries_never_block_or_stop_the_daemon() {
    use rustix::process::Signal;
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join("spool");
    let config = dir.path().join("sdsem.toml");
    std::fs::write(
        &config,
        format!(
            "[run]\noutput_dir = {:?}\n[daemon]\nspool_dir = {:?}\nmin_free_gib = 0\npoll_interval_s = 0.1\n",
            dir.path().join("runs"),
            spool
        ),
    )
    .unwrap();
    let spool_arg = spool.to_str().unwrap();
    let mut daemon = fake_daemon(dir.path(), &config, "hostile");
    daemon.expect(Duration::from_secs(30), |l| l == "STATUS=idle, 0 queued");

    let q = spool.join("queued");
    std::fs::create_dir(q.join("00000201.json")).unwrap();
    rustix::fs::mknodat(
        rustix::fs::CWD,
        q.join("00000202.json"),
        rustix::fs::FileType::Fifo,
        rustix::fs::Mode::from_raw_mode(0o666),
        0,
    )
    .unwrap();
    std::os::unix::fs::symlink("/dev/zero", q.join("00000203.json")).unwrap();
    std::fs::write(q.join("00000204.json"), "x").unwrap();
    // Unreadable for the daemon's user (root reads it anyway: then it is garbage).
    std::fs::set_permissions(
        q.join("00000204.json"),
        std::fs::Permissions::from_mode(0o000),
    )
    .unwrap();
    std::fs::write(q.join("00000205.json"), "{\"id\": 205, \"garbage\": [").unwrap();
    std::fs::write(q.join("00000206.json"), vec![b'{'; 1 << 20]).unwrap();
    let evil = format!("\u{1b}[2J\u{1b}]0;pwned\u{7}{}\n.json", "A".repeat(200));
    std::fs::write(q.join(&evil), "{}").unwrap();
    let quick = write_job(
        dir.path(),
        "quick.toml",
        "name = \"quick\"\nstart_tilt = 0\nend_tilt = 7\n",
    );
    let out = sdsem(&["submit", &quick, "--spool", spool_arg]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(
        text(&out.stdout).starts_with("queued job 207 (quick)"),
        "{}",
        text(&out.stdout)
    );

    let done = daemon_support::process::wait_final(&spool, 207, Duration::from_secs(30));
    assert_eq!(done.state, JobState::Done, "{}", daemon.log());
    // Still alive, still pinging, still answering.
    let seen = daemon.seen.len();
    daemon.expect_after(seen, Duration::from_secs(5), |l| l == "WATCHDOG=1");
    assert!(daemon.child.try_wait().unwrap().is_none());

    let out = sdsem(&["status", "--spool", spool_arg]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let shown = text(&out.stdout);
    assert!(
        !shown.contains('\u{1b}') && !shown.contains('\u{7}'),
        "{shown:?}"
    );
    for (name, cause) in [
        ("00000201.json", "it is a directory, not a regular file"),
        ("00000202.json", "it is a FIFO, not a regular file"),
        (
            "00000203.json",
            "it is a symbolic link, which is never followed",
        ),
        ("00000206.json", "it is larger than 262144 bytes"),
        ("\\u{1b}[2J\\u{1b}]0;pwned\\u{7}AAAA", "not named <id>.json"),
    ] {
        assert!(
            shown.lines().any(|l| l.contains(name) && l.contains(cause)),
            "{name}: {shown}"
        );
    }
    assert!(
        shown.contains("set aside in") && shown.contains("(7 in all)"),
        "{shown}"
    );
    assert!(shown.contains("…(+"), "the long name is cut short: {shown}");
    let json = sdsem(&["status", "--spool", spool_arg, "--json"]);
    let json: serde_json::Value = serde_json::from_slice(&json.stdout).unwrap();
    assert_eq!(json["set_aside_total"], 7);

    daemon.signal(Signal::TERM);
    let (status, took) = daemon.wait_exit(Duration::from_secs(15));
    assert!(status.success(), "{}", daemon.log());
    assert!(took < Duration::from_secs(5), "{took:?}");
}

/// `mv daemon.lock` once let a second daemon in and both ran jobs: the lock is held on
/// the spool directory, the second daemon is refused, the first notices and says so.
#[test]
fn a_moved_lock_file_lets_no_second_daemon_in() {
    use rustix::process::Signal;
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join("spool");
    let config = dir.path().join("sdsem.toml");
    std::fs::write(
        &config,
        format!(
            "[run]\noutput_dir = {:?}\n[daemon]\nspool_dir = {:?}\nmin_free_gib = 0\npoll_interval_s = 0.1\n",
            dir.path().join("runs"),
            spool
        ),
    )
    .unwrap();
    let mut first = fake_daemon(dir.path(), &config, "first");
    first.expect(Duration::from_secs(30), |l| l == "READY=1");
    std::fs::rename(spool.join("daemon.lock"), dir.path().join("stolen.lock")).unwrap();
    let mut second = fake_daemon(dir.path(), &config, "second");
    let (status, _) = second.wait_exit(Duration::from_secs(30));
    assert!(!status.success());
    // Its PID is in daemon.lock, gone or written again by the first daemon by then.
    let refused = second.log();
    let first_pid = format!("(PID {})", first.child.id());
    assert!(
        refused.contains("in use by another sdsem daemon")
            && (refused.contains(&first_pid) || refused.contains("(PID unknown)")),
        "{refused}"
    );
    // Noticed within a watchdog period (1 s here), said in the log and in `status`.
    let end = std::time::Instant::now() + Duration::from_secs(10);
    let json = loop {
        let out = sdsem(&["status", "--spool", spool.to_str().unwrap(), "--json"]);
        let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        if json["daemon"]["warnings"]
            .as_array()
            .is_some_and(|w| !w.is_empty())
        {
            break json;
        }
        assert!(
            std::time::Instant::now() < end,
            "not noticed: {json}\n{}",
            first.log()
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    let warning = json["daemon"]["warnings"][0].as_str().unwrap();
    assert!(
        warning.contains("daemon.lock was moved away or removed"),
        "{warning}"
    );
    assert!(
        first.log().contains("still owns the spool"),
        "{}",
        first.log()
    );
    let pid = std::fs::read_to_string(spool.join("daemon.lock")).unwrap();
    assert_eq!(pid.trim(), first.child.id().to_string());
    first.signal(Signal::TERM);
    assert!(first.wait_exit(Duration::from_secs(15)).0.success());
}

/// `submit /dev/zero` read until out of memory; a 100 MB name was echoed whole.
#[test]
fn submit_refuses_special_files_and_huge_names_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let spool = dir.path().join("spool");
    let spool_arg = spool.to_str().unwrap();
    let t0 = std::time::Instant::now();
    let out = sdsem(&["submit", "/dev/zero", "--spool", spool_arg]);
    assert!(!out.status.success());
    assert_eq!(
        text(&out.stderr).trim(),
        "error: job /dev/zero refused, nothing queued: cannot read job file /dev/zero: it is a \
         character device, not a regular file"
    );
    let fifo = dir.path().join("job.fifo");
    rustix::fs::mknodat(
        rustix::fs::CWD,
        &fifo,
        rustix::fs::FileType::Fifo,
        rustix::fs::Mode::from_raw_mode(0o644),
        0,
    )
    .unwrap();
    let out = sdsem(&["submit", fifo.to_str().unwrap(), "--spool", spool_arg]);
    assert!(text(&out.stderr).contains("it is a FIFO, not a regular file"));
    assert!(t0.elapsed() < Duration::from_secs(10), "{:?}", t0.elapsed());
    let huge = write_job(
        dir.path(),
        "huge.toml",
        &format!(
            "name = \"{}\"\nstart_tilt = 0\nend_tilt = 5\n",
            "n".repeat(60_000)
        ),
    );
    let out = sdsem(&["submit", &huge, "--spool", spool_arg]);
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(
        err.len() < 600 && err.contains("is too long"),
        "{} bytes: {err:.300}",
        err.len()
    );
    // With the journal as stderr, the error line has error priority.
    let out = Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .args(["submit", "/dev/zero", "--spool", spool_arg])
        .stderr(std::fs::File::create(dir.path().join("err.log")).unwrap())
        .env(
            "JOURNAL_STREAM",
            journal_stream(&dir.path().join("err.log")),
        )
        .status()
        .unwrap();
    assert!(!out.success());
    let logged = std::fs::read_to_string(dir.path().join("err.log")).unwrap();
    assert!(
        logged.starts_with("<3>error: job /dev/zero refused"),
        "{logged}"
    );
}

fn journal_stream(path: &std::path::Path) -> String {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::metadata(path).unwrap();
    format!("{}:{}", m.dev(), m.ino())
}

/// The unit's promises that the daemon's code relies on.
#[test]
fn the_service_unit_keeps_the_daemons_promises() {
    let unit = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/systemd/sdsem.service"
    ))
    .unwrap();
    let values = |key: &str| -> Vec<String> {
        unit.lines()
            .filter_map(|l| l.strip_prefix(&format!("{key}=")))
            .map(str::to_owned)
            .collect()
    };
    let one = |key: &str| values(key).pop().unwrap_or_default();
    assert_eq!(one("Type"), "notify");
    assert_eq!(one("NotifyAccess"), "main");
    assert_eq!(one("Restart"), "on-failure");
    assert!(one("ExecReload").contains("-HUP"));
    // The 15 s safe stop must fit before systemd escalates to SIGKILL.
    let stop: u64 = one("TimeoutStopSec").parse().unwrap();
    assert!(stop >= 20, "TimeoutStopSec={stop}");
    let watchdog: u64 = one("WatchdogSec").parse().unwrap();
    assert!(
        watchdog >= 10,
        "WatchdogSec={watchdog}: the loop pings every half of it"
    );
    // The serial port stays reachable.
    assert!(values("PrivateDevices").iter().all(|v| v == "no"));
    assert_eq!(one("DevicePolicy"), "closed");
    assert!(values("DeviceAllow").contains(&"char-ttyUSB rw".to_owned()));
    assert!(values("SupplementaryGroups").contains(&"dialout".to_owned()));
    assert_eq!(one("ProtectSystem"), "strict");
    assert_eq!(one("StateDirectory"), "sdsem");
    // Bounded, and documented as the daemon sets its modes under this umask.
    assert!(!one("MemoryMax").is_empty() && !one("TasksMax").is_empty());
    let readme =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/systemd/README.md")).unwrap();
    assert_eq!(one("UMask"), "0007");
    assert!(
        readme.contains("(`UMask=0007`)"),
        "systemd/README.md names another umask"
    );
    for (path, mode) in [("`spool/`", "0750"), ("`spool/queued/`", "1770 (sticky)")] {
        assert!(
            readme.contains(&format!("| {path} | {mode} |")),
            "systemd/README.md: {path} {mode}"
        );
    }
}

/// `systemd/verify.sh`: `systemd-analyze verify` prints nothing for the units,
/// and the script does fail on a unit it complains about. Skipped (with a
/// note) where systemd-analyze is not installed.
#[test]
fn the_units_pass_systemd_analyze_verify() {
    if Command::new("systemd-analyze")
        .arg("--version")
        .output()
        .is_err()
    {
        eprintln!("systemd-analyze not installed: unit verification skipped");
        return;
    }
    let systemd = concat!(env!("CARGO_MANIFEST_DIR"), "/systemd");
    let out = Command::new(format!("{systemd}/verify.sh"))
        .output()
        .unwrap();
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{stdout}{}", text(&out.stderr));
    assert!(
        stdout.contains("systemd-analyze verify: no output for sdsem-sim.service sdsem.service"),
        "{stdout}"
    );
    assert!(stdout.contains("sdsem.service: 1."), "{stdout}");

    // The same script beside a unit with a misspelt key must fail.
    let dir = tempfile::tempdir().unwrap();
    std::fs::copy(format!("{systemd}/verify.sh"), dir.path().join("verify.sh")).unwrap();
    let unit = std::fs::read_to_string(format!("{systemd}/sdsem.service")).unwrap();
    std::fs::write(
        dir.path().join("sdsem.service"),
        unit.replace("ProtectHome=yes", "ProtectHom=yes"),
    )
    .unwrap();
    let out = Command::new(dir.path().join("verify.sh")).output().unwrap();
    assert!(!out.status.success(), "a broken unit passed verify.sh");
    assert!(
        text(&out.stderr).contains("ProtectHom"),
        "{}",
        text(&out.stderr)
    );
}
