//! `sdsem acquire` as a process against the real simulator (started inside
//! sdsem by the `[simulator]` section, faults set through its configuration),
//! its record read back: the happy path, bad input refused before anything is
//! sent, reply faults, a move that does not happen, a lost link, `kill -9`,
//! SIGTERM and SIGINT.
//!
//! Fast and deterministic: small frames, time scale 0.01, a fixed seed, and an
//! `ONT?` poll interval longer than any step's motion, so every run sends the
//! same commands in the same order. Faults are placed by command number (as
//! the simulator counts them) taken from a fault-free reference run, so they
//! hit the intended exchange whatever the driver's exact sequence is.

#![allow(clippy::unwrap_used)]

use std::io::ErrorKind;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use sdsem::record::{RecordInspection, RunStatus, read_images, read_json, read_summary, topics};
use sdsem::stage::{IoOutcome, StageAxis, StageEvent, StageIo, StageState};

/// The rig: a 100 µm specimen seen in 320×240 frames of 0.25 µm, tracking at
/// half that; everything 100× faster than real time.
fn config_text(dir: &Path) -> String {
    format!(
        r#"[run]
output_dir = "{}"
name = "t"
reconstruct = false

[series]
start_tilt_deg = 0.0
end_tilt_deg = 7.0
step_deg = 1.0

[stage]
axis_x = "X"
axis_y = "Y"
axis_tilt = "T"
poll_interval_s = 0.05
reply_timeout_s = 0.5
resync_quiet_s = 0.02
no_motion_timeout_s = 0.15
move_timeout_margin_s = 2.0

[imaging.micrograph]
width = 320
height = 240
dwell_us = 2.0

[imaging.tracking]
width = 160
height = 120
dwell_us = 1.0

[simulator]
seed = 3
time_scale = 0.01

[simulator.sem.scene]
kind = "particles"
field_um = 100.0
sample_um = 0.25

[simulator.sem.optics]
width = 320
height = 240
pixel_size_um = 0.25
"#,
        dir.join("runs").display()
    )
}

/// A temporary directory with the rig's configuration in it.
struct Rig {
    dir: tempfile::TempDir,
}

impl Rig {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("sim.toml"), config_text(dir.path())).unwrap();
        Self { dir }
    }

    fn config(&self) -> PathBuf {
        self.dir.path().join("sim.toml")
    }

    fn runs(&self) -> PathBuf {
        self.dir.path().join("runs")
    }

    /// Starts `sdsem acquire` with `--set` overrides; stdout and stderr go to files.
    fn spawn(&self, tag: &str, sets: &[String]) -> Running {
        let mut args = vec![
            "acquire".to_owned(),
            "--config".to_owned(),
            self.config().display().to_string(),
        ];
        for s in sets {
            args.push("--set".into());
            args.push(s.clone());
        }
        let out = self.dir.path().join(format!("{tag}.stdout"));
        let err = self.dir.path().join(format!("{tag}.stderr"));
        let child = Command::new(env!("CARGO_BIN_EXE_sdsem"))
            .args(&args)
            .env_remove("RUST_LOG")
            .stdout(std::fs::File::create(&out).unwrap())
            .stderr(std::fs::File::create(&err).unwrap())
            .spawn()
            .unwrap();
        Running {
            child,
            out,
            err,
            runs: self.runs(),
        }
    }

    /// Runs `sdsem acquire` to its end.
    fn acquire(&self, tag: &str, sets: &[String]) -> Finished {
        self.spawn(tag, sets).wait(Duration::from_secs(120))
    }
}

struct Running {
    child: Child,
    out: PathBuf,
    err: PathBuf,
    runs: PathBuf,
}

impl Running {
    fn wait(mut self, limit: Duration) -> Finished {
        let start = Instant::now();
        let status = loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                break status;
            }
            if start.elapsed() > limit {
                let _ = self.child.kill();
                let _ = self.child.wait();
                panic!(
                    "sdsem acquire still running after {limit:?}; stderr:\n{}",
                    std::fs::read_to_string(&self.err).unwrap_or_default()
                );
            }
            std::thread::sleep(Duration::from_millis(10));
        };
        Finished {
            status,
            stdout: std::fs::read_to_string(&self.out).unwrap(),
            stderr: std::fs::read_to_string(&self.err).unwrap(),
        }
    }

    /// The record of the run in progress, once its directory exists.
    fn record(&self) -> Option<PathBuf> {
        let dir = std::fs::read_dir(&self.runs).ok()?.next()?.ok()?.path();
        Some(dir.join("run.mcap"))
    }

    /// Waits until the record holds at least `n` frames; returns how many it holds.
    fn wait_for_frames(&mut self, n: usize, limit: Duration) -> usize {
        let start = Instant::now();
        loop {
            let frames = self
                .record()
                .and_then(|r| read_images(r, topics::SEM_FRAME, |_| true).ok())
                .map_or(0, |e| e.items.len());
            if frames >= n {
                return frames;
            }
            assert!(
                self.child.try_wait().unwrap().is_none(),
                "the run ended before {n} frames were recorded; stderr:\n{}",
                std::fs::read_to_string(&self.err).unwrap_or_default()
            );
            assert!(
                start.elapsed() < limit,
                "fewer than {n} frames after {limit:?}"
            );
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    fn signal(&self, signal: rustix::process::Signal) {
        rustix::process::kill_process(rustix::process::Pid::from_child(&self.child), signal)
            .unwrap();
    }
}

struct Finished {
    status: ExitStatus,
    stdout: String,
    stderr: String,
}

impl Finished {
    /// The run directory: the last line on stdout (DESIGN §4).
    fn run_dir(&self) -> PathBuf {
        let last = self.stdout.lines().last().unwrap_or_else(|| {
            panic!("nothing on stdout; stderr:\n{}", self.stderr);
        });
        let dir = PathBuf::from(last);
        assert!(dir.is_dir(), "last stdout line {last:?} is not a directory");
        dir
    }

    fn record(&self) -> PathBuf {
        self.run_dir().join("run.mcap")
    }

    /// The last line on stderr: the one-line cause of a failure.
    fn last_stderr_line(&self) -> &str {
        self.stderr.lines().last().unwrap_or("")
    }

    fn expect_success(&self) {
        assert!(
            self.status.success(),
            "sdsem acquire failed ({:?}):\n{}",
            self.status,
            self.stderr
        );
    }
}

fn stage_io(record: &Path) -> Vec<StageIo> {
    read_json(record, topics::STAGE_IO)
        .unwrap()
        .items
        .iter()
        .map(|m| m.parse().unwrap())
        .collect()
}

fn stage_states(record: &Path) -> Vec<StageState> {
    read_json(record, topics::STAGE_STATE)
        .unwrap()
        .items
        .iter()
        .map(|m| m.parse().unwrap())
        .collect()
}

/// The command lines sent, in order (strays left out): entry k − 1 is the
/// simulator's command number k.
fn commands(io: &[StageIo]) -> Vec<String> {
    io.iter()
        .filter(|e| e.outcome != IoOutcome::Stray)
        .filter_map(|e| e.command.clone())
        .collect()
}

/// Simulator command number (from 1) of the first command starting with
/// `want` after the command `anchor`.
fn command_number(commands: &[String], anchor: &str, want: &str) -> u64 {
    let a = commands
        .iter()
        .position(|c| c == anchor)
        .unwrap_or_else(|| panic!("no {anchor:?} in {commands:?}"));
    let k = a
        + 1
        + commands[a + 1..]
            .iter()
            .position(|c| c.starts_with(want))
            .unwrap_or_else(|| panic!("no {want:?} after {anchor:?}"));
    k as u64 + 1
}

/// The number of `MOV` commands up to and including `mov`: its number among
/// the moves the simulator accepts (every move of a fault-free run is accepted).
fn move_number(commands: &[String], mov: &str) -> u64 {
    let end = commands.iter().position(|c| c == mov).unwrap();
    commands[..=end]
        .iter()
        .filter(|c| c.starts_with("MOV "))
        .count() as u64
}

/// The commands of a fault-free run of the rig, computed once.
fn reference_commands() -> &'static [String] {
    static REFERENCE: OnceLock<Vec<String>> = OnceLock::new();
    REFERENCE.get_or_init(|| {
        let rig = Rig::new();
        let run = rig.acquire("reference", &[]);
        run.expect_success();
        let io = stage_io(&run.record());
        // A reply slower than the timeout on a starved machine would shift every
        // command number: say so rather than let the fault tests miss.
        let faults: Vec<&StageIo> = io
            .iter()
            .filter(|e| !matches!(e.outcome, IoOutcome::Replied | IoOutcome::Sent))
            .collect();
        assert!(
            faults.is_empty(),
            "the fault-free reference run saw faults: {faults:?}"
        );
        commands(&io)
    })
}

/// The commands before the return to the safe tilt (whose poll count varies
/// with the machine's load: it is the one long move).
fn before_return(commands: &[String]) -> &[String] {
    let last_seven = commands.iter().rposition(|c| c == "MOV T 7").unwrap();
    let ret = last_seven
        + commands[last_seven..]
            .iter()
            .position(|c| c == "MOV T 0")
            .unwrap();
    &commands[..ret]
}

fn tilt_of(state: &StageState) -> Option<f64> {
    state
        .axes
        .iter()
        .find(|a| a.axis == StageAxis::Tilt)
        .and_then(|a| a.position)
}

/// The run stopped the stage (`STP`) after `from` and brought it back to the
/// safe tilt 0° (a verified `MOV T 0` after the STP).
fn assert_stopped_and_safe(io: &[StageIo], states: &[StageState], from: usize) {
    let cmds = commands(io);
    let stp = from
        + cmds[from..]
            .iter()
            .position(|c| c == "STP")
            .unwrap_or_else(|| panic!("no STP after command {from}: {:?}", &cmds[from..]));
    assert!(
        cmds[stp..].iter().any(|c| c == "MOV T 0"),
        "no return to the safe tilt after STP: {:?}",
        &cmds[stp..]
    );
    let last = states
        .iter()
        .rev()
        .find(|s| s.event == StageEvent::Reached)
        .unwrap();
    let tilt = tilt_of(last).unwrap();
    assert!(tilt.abs() < 0.01, "the stage ended at tilt {tilt}°, not 0°");
}

fn summary(record: &Path) -> RecordInspection {
    read_summary(record).unwrap()
}

fn cause(inspection: &RecordInspection) -> String {
    inspection
        .outcome
        .as_ref()
        .and_then(|o| o.cause.clone())
        .unwrap_or_default()
}

fn set(key: &str, value: impl std::fmt::Display) -> String {
    format!("{key}={value}")
}

#[test]
fn a_zero_to_seven_run_records_everything_and_is_deterministic() {
    let rig = Rig::new();
    let run = rig.acquire("happy", &[]);
    run.expect_success();
    let dir = run.run_dir();
    let record = dir.join("run.mcap");

    // One line per step on stderr (the logs; readable text on a terminal).
    for k in 1..=7 {
        let line = format!("step {k}/7: tilt {k}.000° reached");
        assert!(
            run.stderr.contains(&line),
            "no {line:?} in:\n{}",
            run.stderr
        );
    }

    // The summary: complete, succeeded, 1 + 1 micrographs and 8 tracking
    // frames (the reference at 0° and one after each of the 7 steps).
    let s = summary(&record);
    assert!(s.end.complete, "{:?}", s.end);
    assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Succeeded);
    assert_eq!(s.frames_by_role.get("left"), Some(&1));
    assert_eq!(s.frames_by_role.get("right"), Some(&1));
    assert_eq!(s.frames_by_role.get("tracking"), Some(&8));
    for topic in [
        topics::SEM_FRAME_INFO,
        topics::STAGE_STATE,
        topics::STAGE_IO,
        topics::LOG,
    ] {
        assert!(s.message_count(topic) > 0, "no {topic}");
    }
    assert!(s.metadata_record(topics::METADATA_RUN).is_some());

    // Every command, from the handshake on, with its reply and round-trip time.
    let io = stage_io(&record);
    let cmds = commands(&io);
    assert_eq!(cmds.first().map(String::as_str), Some("*IDN?"), "{cmds:?}");
    for e in &io {
        assert_ne!(e.outcome, IoOutcome::Timeout, "{e:?}");
        if e.outcome == IoOutcome::Replied {
            assert!(e.reply.is_some() && e.rtt_ns.is_some(), "{e:?}");
        }
    }
    let tilt_moves: Vec<&String> = cmds.iter().filter(|c| c.starts_with("MOV T")).collect();
    let expected: Vec<String> = (0..=7).chain([0]).map(|t| format!("MOV T {t}")).collect();
    assert_eq!(tilt_moves, expected.iter().collect::<Vec<_>>());

    // Every tilt verified within 0.01°, the stage back at the safe tilt.
    let states = stage_states(&record);
    let reached: Vec<f64> = states
        .iter()
        .filter(|s| s.event == StageEvent::Reached)
        .filter_map(tilt_of)
        .collect();
    let expected_tilts: Vec<f64> = (0..=7).chain([0]).map(f64::from).collect();
    assert_eq!(reached.len(), expected_tilts.len(), "{reached:?}");
    for (r, t) in reached.iter().zip(&expected_tilts) {
        assert!((r - t).abs() <= 0.01, "reached {r}° for {t}°");
    }

    // The micrographs, with their tilt and pixel size in the TIFF metadata.
    for (name, tilt) in [("left.tif", 0.0), ("right.tif", 7.0)] {
        let m = sdsem::imaging::file::read_sem_metadata(dir.join(name)).unwrap();
        assert_eq!(m.tilt_deg, Some(tilt), "{name}: {m:?}");
        let p = m.pixel_size_um.unwrap();
        assert!((p - 0.25).abs() < 1e-9, "{name}: pixel size {p}");
    }

    // The same seed, the same run: the commands equal the reference run's.
    assert_eq!(before_return(&cmds), before_return(reference_commands()));
}

/// A port nobody answers on, to see whether sdsem tried to reach an instrument.
struct Tripwire(TcpListener);

impl Tripwire {
    fn new() -> Self {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        l.set_nonblocking(true).unwrap();
        Self(l)
    }

    fn endpoint(&self) -> String {
        format!("tcp://{}", self.0.local_addr().unwrap())
    }

    fn untouched(&self) -> bool {
        matches!(self.0.accept(), Err(e) if e.kind() == ErrorKind::WouldBlock)
    }
}

#[test]
fn bad_input_is_refused_before_anything_is_sent() {
    let rig = Rig::new();
    // (what, added to [series], --set, what the one-line message must name)
    let cases: [(&str, &str, &[&str], &[&str]); 4] = [
        (
            "unknown key",
            "end_tilt = 5.0\n",
            &[],
            &["unknown key series.end_tilt"],
        ),
        (
            "zero step",
            "",
            &["series.step_deg=0"],
            &["series.step_deg = 0", "greater than 0"],
        ),
        (
            "negative step",
            "",
            &["series.step_deg=-1"],
            &["series.step_deg = -1", "greater than 0"],
        ),
        (
            "end beyond the limits",
            "",
            &["series.end_tilt_deg=75"],
            &["series.end_tilt_deg = 75", "[-5°, 70°]"],
        ),
    ];
    for (what, series_extra, sets, needles) in cases {
        // No simulator: the instruments are tripwires that notice any connection.
        let (stage, sem) = (Tripwire::new(), Tripwire::new());
        let text = config_text(rig.dir.path());
        let body = text[..text.find("[simulator]").unwrap()]
            .replacen("[series]\n", &format!("[series]\n{series_extra}"), 1)
            .replacen(
                "[stage]\n",
                &format!("[stage]\nendpoint = \"{}\"\n", stage.endpoint()),
                1,
            )
            .replacen(
                "[imaging.micrograph]\n",
                &format!(
                    "[imaging]\nendpoint = \"{}\"\n\n[imaging.micrograph]\n",
                    sem.endpoint()
                ),
                1,
            );
        let config = rig.dir.path().join("bad.toml");
        std::fs::write(&config, body).unwrap();
        let mut args = vec![
            "acquire".to_owned(),
            "--config".into(),
            config.display().to_string(),
        ];
        for s in sets {
            args.extend(["--set".to_owned(), (*s).to_owned()]);
        }
        let out = Command::new(env!("CARGO_BIN_EXE_sdsem"))
            .args(&args)
            .stdin(Stdio::null())
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{what}: accepted");
        assert_eq!(stderr.lines().count(), 1, "{what}: not one line:\n{stderr}");
        for needle in needles {
            assert_eq!(
                stderr.matches(needle).count(),
                1,
                "{what}: {needle:?} not once in {stderr:?}"
            );
        }
        assert!(
            stage.untouched() && sem.untouched(),
            "{what}: an instrument was contacted"
        );
        assert!(!rig.runs().exists(), "{what}: a run directory was created");
    }
}

#[test]
fn a_series_beyond_the_controllers_soft_limits_never_moves_the_stage() {
    let rig = Rig::new();
    let run = rig.acquire(
        "soft-limits",
        &[
            set("simulator.stage.tilt_max_deg", 60),
            set("series.end_tilt_deg", 65),
        ],
    );
    assert!(!run.status.success());
    let line = run.last_stderr_line();
    assert!(
        line.starts_with("run failed: series.end_tilt_deg = 65°") && line.contains("[-5°, 60°]"),
        "{line}"
    );
    let record = run.record();
    let cmds = commands(&stage_io(&record));
    assert!(cmds.iter().any(|c| c.starts_with("TMX?")), "{cmds:?}");
    assert!(!cmds.iter().any(|c| c.starts_with("MOV")), "{cmds:?}");
    let s = summary(&record);
    assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Failed);
    assert!(cause(&s).contains("series.end_tilt_deg"), "{}", cause(&s));
}

#[test]
fn a_late_or_garbled_query_is_retried_and_the_run_completes() {
    let reference = reference_commands();
    // The first ONT? of the move to 3°.
    let k = command_number(reference, "MOV T 3", "ONT?");
    let rig = Rig::new();
    for (fault, extra) in [
        (
            "late_reply",
            vec![set("simulator.stage.faults.late_reply_delay_s", 0.8)],
        ),
        ("garble_reply", vec![]),
    ] {
        let mut sets = vec![set(
            &format!("simulator.stage.faults.{fault}.at"),
            format!("[{k}]"),
        )];
        sets.extend(extra);
        let run = rig.acquire(fault, &sets);
        run.expect_success();
        let io = stage_io(&run.record());
        let hit = io
            .iter()
            .filter(|e| e.outcome != IoOutcome::Stray && e.command.is_some())
            .nth(usize::try_from(k - 1).unwrap())
            .unwrap();
        let want = if fault == "late_reply" {
            IoOutcome::Timeout
        } else {
            IoOutcome::Garbled
        };
        assert_eq!(hit.command.as_deref(), Some("ONT? T"), "{hit:?}");
        assert_eq!(hit.outcome, want, "{fault}: {hit:?}");
        assert!(
            io.iter().any(|e| e.command.as_deref() == Some("ONT? T")
                && e.attempt == 2
                && e.outcome == IoOutcome::Replied),
            "{fault}: no successful retry"
        );
        if fault == "late_reply" {
            assert!(
                io.iter().any(|e| e.outcome == IoOutcome::Stray),
                "the late reply was not discarded as a stray"
            );
        }
        assert!(
            !commands(&io).iter().any(|c| c == "STP"),
            "{fault}: stopped"
        );
        let s = summary(&run.record());
        assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Succeeded);
        assert_eq!(s.message_count(topics::SEM_FRAME), 10);
        // Rerun in a fresh output directory.
        std::fs::remove_dir_all(rig.runs()).unwrap();
    }
}

#[test]
fn a_query_that_keeps_failing_stops_the_run_and_the_stage() {
    let reference = reference_commands();
    let k = command_number(reference, "MOV T 3", "ONT?");
    let rig = Rig::new();
    // Three attempts (stage.query_retries = 2): garbled ones follow each other;
    // a timed-out one is followed by ERR? before the next attempt.
    for (fault, at, cause_text) in [
        (
            "garble_reply",
            [k, k + 1, k + 2],
            "garbled reply to `ONT? T` (3 attempt(s))",
        ),
        ("late_reply", [k, k + 2, k + 4], "no reply to `ONT? T`"),
    ] {
        let run = rig.acquire(
            fault,
            &[
                set(
                    &format!("simulator.stage.faults.{fault}.at"),
                    format!("[{}, {}, {}]", at[0], at[1], at[2]),
                ),
                set("simulator.stage.faults.late_reply_delay_s", 0.8),
            ],
        );
        assert!(!run.status.success(), "{fault}: the run completed");
        let line = run.last_stderr_line();
        assert!(
            line.starts_with("run failed: tilt move to 3° failed"),
            "{fault}: {line}"
        );
        assert!(line.contains(cause_text), "{fault}: {line}");
        let record = run.record();
        let io = stage_io(&record);
        assert_stopped_and_safe(&io, &stage_states(&record), usize::try_from(k).unwrap());
        let s = summary(&record);
        assert!(s.end.complete);
        assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Failed);
        assert!(cause(&s).contains(cause_text), "{fault}: {}", cause(&s));
        // Left, the reference and the tracking frames of steps 1 and 2.
        assert_eq!(s.message_count(topics::SEM_FRAME), 4, "{fault}");
        std::fs::remove_dir_all(rig.runs()).unwrap();
    }
}

#[test]
fn a_move_that_does_not_happen_is_reissued_once_then_stops_the_run() {
    let reference = reference_commands();
    let m = move_number(reference, "MOV T 3");
    let rig = Rig::new();

    // Ignored once: verification sees the stage standing still, re-issues the move.
    let run = rig.acquire(
        "ignored-once",
        &[set(
            "simulator.stage.faults.ignore_move.at",
            format!("[{m}]"),
        )],
    );
    run.expect_success();
    let record = run.record();
    let cmds = commands(&stage_io(&record));
    assert_eq!(
        cmds.iter().filter(|c| *c == "MOV T 3").count(),
        2,
        "{cmds:?}"
    );
    let states = stage_states(&record);
    assert_eq!(
        states
            .iter()
            .filter(|s| s.event == StageEvent::MoveReissued)
            .count(),
        1
    );
    assert_eq!(summary(&record).message_count(topics::SEM_FRAME), 10);
    std::fs::remove_dir_all(rig.runs()).unwrap();

    // Ignored twice: the run stops, naming the axis, and the stage is stopped.
    let run = rig.acquire(
        "ignored-twice",
        &[set(
            "simulator.stage.faults.ignore_move.at",
            format!("[{m}, {}]", m + 1),
        )],
    );
    assert!(!run.status.success());
    let line = run.last_stderr_line();
    assert!(
        line.starts_with(
            "run failed: tilt move to 3° failed: `MOV T 3` did not move the tilt axis"
        ),
        "{line}"
    );
    let record = run.record();
    let io = stage_io(&record);
    let cmds = commands(&io);
    let second = cmds.iter().rposition(|c| c == "MOV T 3").unwrap();
    assert_eq!(
        cmds.iter().filter(|c| *c == "MOV T 3").count(),
        2,
        "{cmds:?}"
    );
    assert_stopped_and_safe(&io, &stage_states(&record), second);
    let s = summary(&record);
    assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Failed);
    assert!(
        cause(&s).contains("did not move the tilt axis"),
        "{}",
        cause(&s)
    );
    assert_eq!(s.message_count(topics::SEM_FRAME), 4);
}

#[test]
fn a_lost_link_fails_the_run_and_keeps_the_record_readable() {
    let reference = reference_commands();
    // The controller hangs up after answering the first ONT? of the move to 4°.
    let k = command_number(reference, "MOV T 4", "ONT?");
    let rig = Rig::new();
    let run = rig.acquire(
        "disconnect",
        &[set("simulator.stage.faults.disconnect_after_commands", k)],
    );
    assert!(!run.status.success());
    assert_eq!(run.status.code(), Some(1));
    let line = run.last_stderr_line();
    assert!(
        line.starts_with("run failed: tilt move to 4° failed: stage link lost during"),
        "{line}"
    );
    let record = run.record();
    let s = summary(&record);
    assert!(s.end.complete, "the record was not finished: {:?}", s.end);
    assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Failed);
    assert!(cause(&s).contains("stage link lost"), "{}", cause(&s));
    // Everything up to the fault: left, reference, and the frames of steps 1–3.
    let tilts: Vec<f64> = read_json(&record, topics::SEM_FRAME_INFO)
        .unwrap()
        .items
        .iter()
        .map(|m| m.value["tilt_deg"].as_f64().unwrap())
        .collect();
    assert_eq!(tilts, [0.0, 0.0, 1.0, 2.0, 3.0]);
    let frames = read_images(&record, topics::SEM_FRAME, |_| true).unwrap();
    assert_eq!(frames.items.len(), 5);
    assert_eq!(frames.items[0].frame_id, "left");
}

#[test]
fn kill_9_leaves_every_recorded_frame_readable() {
    let rig = Rig::new();
    let mut running = rig.spawn("kill", &[set("simulator.time_scale", 0.05)]);
    let seen = running.wait_for_frames(4, Duration::from_secs(60));
    running.signal(rustix::process::Signal::KILL);
    let record = running.record().unwrap();
    let finished = running.wait(Duration::from_secs(10));
    assert!(!finished.status.success());

    let frames = read_images(&record, topics::SEM_FRAME, |_| true).unwrap();
    assert!(!frames.end.complete, "the killed run finished its record");
    assert!(
        frames.items.len() >= seen,
        "{} < {seen}",
        frames.items.len()
    );
    assert!(frames.items.len() < 10, "the run was not cut short");
    assert_eq!(frames.items[0].frame_id, "left");
    for f in &frames.items {
        let image = f.to_image().unwrap();
        let want = if f.frame_id == "tracking" {
            (160, 120)
        } else {
            (320, 240)
        };
        assert_eq!((image.width(), image.height()), want);
    }

    // `sdsem inspect` reads the truncated record.
    let out = Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .args(["inspect", "--json", record.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(json["end"]["complete"], false);
    assert!(json["outcome"].is_null());
    let counted: u64 = json["frames_by_role"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert_eq!(counted, frames.items.len() as u64);
    let text = Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .args(["inspect", record.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(text.status.success());
    assert!(String::from_utf8_lossy(&text.stdout).contains("INCOMPLETE"));
}

#[test]
fn sigterm_and_sigint_stop_the_stage_and_return_it_to_the_safe_tilt() {
    use rustix::process::Signal;
    for (signal, why) in [(Signal::TERM, "SIGTERM"), (Signal::INT, "Ctrl-C (SIGINT)")] {
        let rig = Rig::new();
        let mut running = rig.spawn(why, &[set("simulator.time_scale", 0.05)]);
        running.wait_for_frames(3, Duration::from_secs(60));
        running.signal(signal);
        let run = running.wait(Duration::from_secs(30));
        assert_eq!(
            run.status.code(),
            Some(130),
            "{why}: {:?}\n{}",
            run.status,
            run.stderr
        );
        assert!(
            run.last_stderr_line().starts_with("run interrupted:"),
            "{why}: {}",
            run.last_stderr_line()
        );
        let record = run.record();
        let s = summary(&record);
        assert!(s.end.complete, "{why}");
        assert_eq!(
            s.outcome.as_ref().unwrap().status,
            RunStatus::Aborted,
            "{why}"
        );
        assert!(cause(&s).contains(why), "{why}: {}", cause(&s));
        assert!(
            s.message_count(topics::SEM_FRAME) < 10,
            "{why}: not interrupted"
        );
        let io = stage_io(&record);
        assert_stopped_and_safe(&io, &stage_states(&record), 0);
    }
}

/// The Python reference reader accepts a record with all eight topics (the
/// reconstruction included). Needs python3 and the `mcap` package; CI sets
/// `SDSEM_REQUIRE_PYTHON_MCAP=1` (after `pip install mcap`) so that a missing
/// package fails instead of skipping.
#[test]
fn the_record_opens_in_the_python_mcap_reader() {
    let required = std::env::var_os("SDSEM_REQUIRE_PYTHON_MCAP").is_some_and(|v| v == "1");
    let available = Command::new("python3")
        .args(["-c", "import mcap"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !available {
        assert!(
            !required,
            "SDSEM_REQUIRE_PYTHON_MCAP=1 but python3 cannot import mcap (pip install mcap)"
        );
        eprintln!("skipped: python3 with the mcap package is not available (pip install mcap)");
        return;
    }
    let rig = Rig::new();
    // The reconstruction needs more than the rig's 320×240 micrographs.
    let run = rig.acquire(
        "python",
        &[
            set("run.reconstruct", true),
            set("simulator.sem.optics.width", 640),
            set("simulator.sem.optics.height", 480),
            set("simulator.sem.optics.pixel_size_um", 0.125),
            set("imaging.micrograph.width", 640),
            set("imaging.micrograph.height", 480),
        ],
    );
    run.expect_success();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/check_mcap.py");
    let out = Command::new("python3")
        .arg(&script)
        .arg(run.record())
        .arg("--require-all-topics")
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{text}");
    assert!(text.lines().any(|l| l == "OK"), "{text}");
    for topic in topics::ALL_TOPICS {
        assert!(text.contains(topic), "{topic} missing:\n{text}");
    }
}
