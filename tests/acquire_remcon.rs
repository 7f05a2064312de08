//! `sdsem acquire` as a process with a Zeiss RemCon32 stage: the simulator's
//! RemCon32 dialect (started inside sdsem by `[simulator]`, served on a
//! pseudo-terminal as a serial port would be) and the sdsem imaging link, the
//! record read back. A move that starts late (its moving flag set late) is
//! waited out; a silently ignored move is re-issued once, then the run stops
//! with the stage aborted (`ABO`) and returned to the safe tilt.
//!
//! Faults are placed by move number (as the simulator counts `C95` moves),
//! taken from a fault-free reference run.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use sdsem::record::{RunStatus, read_json, read_summary, topics};
use sdsem::stage::{IoOutcome, StageAxis, StageEvent, StageIo, StageState};

/// The acquire rig of `tests/acquire.rs`, with a RemCon32 stage. The moving
/// flag is trusted 0.4 s after a move command; a late start lasts 0.3 s
/// (30 simulated seconds at time scale 0.01), longer than the 0.15 s after
/// which a standing stage counts as a move that did not happen.
fn config_text(dir: &Path) -> String {
    format!(
        r#"[run]
output_dir = "{}"
name = "zeiss"
reconstruct = false

[series]
start_tilt_deg = 0.0
end_tilt_deg = 4.0
step_deg = 1.0

[stage]
protocol = "remcon32"
poll_interval_s = 0.05
reply_timeout_s = 0.5
resync_quiet_s = 0.02
no_motion_timeout_s = 0.15
move_timeout_margin_s = 2.0
moving_flag_delay_s = 0.4

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

[simulator.stage]
protocol = "remcon32"
endpoint = "pty"

[simulator.stage.faults]
stale_on_target_s = 30.0

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

struct Run {
    success: bool,
    stdout: String,
    stderr: String,
    _dir: tempfile::TempDir,
}

impl Run {
    fn record(&self) -> PathBuf {
        let last = self.stdout.lines().last().unwrap_or_else(|| {
            panic!("nothing on stdout; stderr:\n{}", self.stderr);
        });
        PathBuf::from(last).join("run.mcap")
    }
}

fn acquire(sets: &[String]) -> Run {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("zeiss.toml");
    std::fs::write(&config, config_text(dir.path())).unwrap();
    let mut args = vec!["acquire".to_owned(), "--config".to_owned()];
    args.push(config.display().to_string());
    for s in sets {
        args.push("--set".into());
        args.push(s.clone());
    }
    let out = Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .args(&args)
        .env_remove("RUST_LOG")
        .output()
        .unwrap();
    Run {
        success: out.status.success(),
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        _dir: dir,
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

/// The commands sent, in order (strays left out).
fn commands(io: &[StageIo]) -> Vec<String> {
    io.iter()
        .filter(|e| e.outcome != IoOutcome::Stray)
        .filter_map(|e| e.command.clone())
        .collect()
}

/// The `C95` moves sent, in order.
fn moves(commands: &[String]) -> Vec<&String> {
    commands.iter().filter(|c| c.starts_with("C95 ")).collect()
}

/// The tilt of a `C95 x y z t r m` move.
fn tilt(mov: &str) -> f64 {
    mov.split(' ').nth(4).unwrap().parse().unwrap()
}

/// Number (from 1) of the first move to `deg` in a fault-free run.
fn move_to(deg: f64) -> u64 {
    static REFERENCE: OnceLock<Vec<String>> = OnceLock::new();
    let reference = REFERENCE.get_or_init(|| {
        let run = acquire(&[]);
        assert!(run.success, "reference run failed:\n{}", run.stderr);
        commands(&stage_io(&run.record()))
    });
    let m = moves(reference)
        .iter()
        .position(|m| tilt(m) == deg)
        .unwrap();
    m as u64 + 1
}

fn reached_tilts(states: &[StageState]) -> Vec<f64> {
    states
        .iter()
        .filter(|s| s.event == StageEvent::Reached)
        .filter_map(|s| {
            s.axes
                .iter()
                .find(|a| a.axis == StageAxis::Tilt)
                .and_then(|a| a.position)
        })
        .collect()
}

#[test]
fn a_remcon32_run_records_every_exchange_decoded_and_waits_out_a_late_moving_flag() {
    let m = move_to(3.0);
    let run = acquire(&[format!("simulator.stage.faults.stale_on_target.at=[{m}]")]);
    assert!(run.success, "{}", run.stderr);
    let record = run.record();
    let io = stage_io(&record);
    let cmds = commands(&io);

    // The handshake, then every move a read-modify-write of C95.
    assert_eq!(
        &cmds[..4],
        ["(null command)", "VER?", "IST?", "C95?"],
        "{cmds:?}"
    );
    for (i, c) in cmds
        .iter()
        .enumerate()
        .filter(|(_, c)| c.starts_with("C95 "))
    {
        assert_eq!(cmds[i - 1], "C95?", "{c} not preceded by a read");
        // z, rotation and m as the simulated stage has them, re-sent unchanged.
        assert!(c.ends_with(" 0.000000 0.000000"), "{c}");
        assert_eq!(c.split(' ').nth(3), Some("10.000000"), "{c}");
    }
    for e in &io {
        assert_ne!(e.outcome, IoOutcome::Timeout, "{e:?}");
        if e.outcome == IoOutcome::Replied {
            let reply = e.reply.as_deref().unwrap();
            assert!(reply.starts_with("@\n>"), "{e:?}");
            assert!(e.rtt_ns.is_some(), "{e:?}");
        }
    }
    // The late move was waited for, not re-issued (re-centring moves re-send
    // the tilt too: count the tilt moves the driver started).
    let states = stage_states(&record);
    assert!(!states.iter().any(|s| s.event == StageEvent::MoveReissued));
    let to_three = states
        .iter()
        .filter(|s| s.event == StageEvent::MoveStarted)
        .filter(|s| {
            s.axes
                .iter()
                .any(|a| a.axis == StageAxis::Tilt && a.target == Some(3.0))
        })
        .count();
    assert_eq!(to_three, 1);
    let reached = reached_tilts(&states);
    let expected: Vec<f64> = (0..=4).chain([0]).map(f64::from).collect();
    assert_eq!(reached.len(), expected.len(), "{reached:?}");
    for (r, t) in reached.iter().zip(&expected) {
        assert!((r - t).abs() <= 0.01, "reached {r}° for {t}°");
    }

    // The same fault with too short a wait: the standing stage is taken for a
    // move that did not happen and the move goes out twice (the run still ends well).
    let hasty = acquire(&[
        format!("simulator.stage.faults.stale_on_target.at=[{m}]"),
        "stage.moving_flag_delay_s=0.05".to_owned(),
    ]);
    assert!(hasty.success, "{}", hasty.stderr);
    let hasty_states = stage_states(&hasty.record());
    assert_eq!(
        hasty_states
            .iter()
            .filter(|s| s.event == StageEvent::MoveReissued)
            .count(),
        1
    );

    // The record names the stage's protocol and version.
    let s = read_summary(&record).unwrap();
    assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Succeeded);
    let ids = s.metadata_record("sdsem.instruments").unwrap();
    assert_eq!(
        ids.get("stage_protocol").map(String::as_str),
        Some("remcon32")
    );
    assert!(ids["stage_version"].contains("SmartSEM"), "{ids:?}");
}

#[test]
fn an_ignored_remcon32_move_is_reissued_once_then_the_run_stops_at_the_safe_tilt() {
    let m = move_to(3.0);
    let run = acquire(&[format!(
        "simulator.stage.faults.ignore_move.at=[{m}, {}]",
        m + 1
    )]);
    assert!(!run.success);
    let line = run.stderr.lines().last().unwrap_or("");
    assert!(
        line.contains("did not move the tilt axis") && line.contains("C95 "),
        "{line}"
    );
    let record = run.record();
    let cmds = commands(&stage_io(&record));
    let threes: Vec<usize> = cmds
        .iter()
        .enumerate()
        .filter(|(_, c)| c.starts_with("C95 ") && tilt(c) == 3.0)
        .map(|(i, _)| i)
        .collect();
    assert_eq!(threes.len(), 2, "re-issued exactly once: {cmds:?}");
    // Then the stage was aborted and sent back to the safe tilt.
    let after = &cmds[threes[1]..];
    let abo = after.iter().position(|c| c == "ABO").unwrap_or_else(|| {
        panic!("no ABO after the second move: {after:?}");
    });
    assert!(
        after[abo..]
            .iter()
            .any(|c| c.starts_with("C95 ") && tilt(c) == 0.0),
        "{after:?}"
    );
    let reached = reached_tilts(&stage_states(&record));
    assert!(reached.last().unwrap().abs() < 0.01, "{reached:?}");
    let s = read_summary(&record).unwrap();
    assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Failed);
    assert!(s.end.complete);
}
