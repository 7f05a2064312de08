//! `sdsem acquire` as a process against the simulator's TESCAN SharkSEM
//! dialect (started inside sdsem by `[simulator.sharksem]`): the SEM's own
//! stage and its scans over one session, faults placed through the
//! configuration, the record read back: every SharkSEM function in `/stage/io`
//! decoded, frames present, the micrographs' metadata.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::Command;

use sdsem::record::{RunStatus, read_json, read_summary, topics};
use sdsem::stage::{IoOutcome, StageEvent, StageIo, StageState};

/// 320×240 frames of 0.25 µm (tracking at half size), 100× faster than real time.
fn config_text(dir: &Path, stage_protocol: &str) -> String {
    let stage = if stage_protocol == "sharksem" {
        "protocol = \"sharksem\"\nendpoint = \"tcp://127.0.0.1:8300\"\n".to_owned()
    } else {
        "axis_x = \"X\"\naxis_y = \"Y\"\naxis_tilt = \"T\"\nreply_timeout_s = 0.5\n".to_owned()
    };
    format!(
        r#"[run]
output_dir = "{}"
name = "shark"
reconstruct = false

[series]
start_tilt_deg = 0.0
end_tilt_deg = 7.0
step_deg = 1.0

[stage]
{stage}poll_interval_s = 0.02
no_motion_timeout_s = 0.15
move_timeout_margin_s = 2.0

[imaging]
protocol = "sharksem"
endpoint = "tcp://127.0.0.1:8300"
timeout_ms = 1500

[imaging.micrograph]
width = 320
height = 240
dwell_us = 2.0

[imaging.tracking]
width = 160
height = 120
dwell_us = 1.0

[reconstruction]
tilt_axis_deg = 0.0

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

[simulator.sharksem]
version = "2.0.25"
"#,
        dir.join("runs").display()
    )
}

struct Run {
    ok: bool,
    stdout: String,
    stderr: String,
}

impl Run {
    fn record(&self) -> PathBuf {
        let last = self
            .stdout
            .lines()
            .last()
            .unwrap_or_else(|| panic!("nothing on stdout; stderr:\n{}", self.stderr));
        PathBuf::from(last).join("run.mcap")
    }
}

fn acquire(dir: &Path, stage_protocol: &str, sets: &[&str]) -> Run {
    let config = dir.join(format!("{stage_protocol}.toml"));
    std::fs::write(&config, config_text(dir, stage_protocol)).unwrap();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_sdsem"));
    cmd.args(["acquire", "--config"])
        .arg(&config)
        .env_remove("RUST_LOG");
    for s in sets {
        cmd.args(["--set", s]);
    }
    let out = cmd.output().unwrap();
    Run {
        ok: out.status.success(),
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
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

fn commands(io: &[StageIo]) -> Vec<String> {
    io.iter().filter_map(|e| e.command.clone()).collect()
}

fn reissued(record: &Path) -> usize {
    read_json(record, topics::STAGE_STATE)
        .unwrap()
        .items
        .iter()
        .map(|m| m.parse::<StageState>().unwrap())
        .filter(|s| s.event == StageEvent::MoveReissued)
        .count()
}

/// Every scan is followed by its image data, then by `ScStopScan`.
fn assert_every_scan_stopped(cmds: &[String]) {
    let scans: Vec<usize> = cmds
        .iter()
        .enumerate()
        .filter(|(_, c)| c.starts_with("ScScanXY("))
        .map(|(i, _)| i)
        .collect();
    assert!(!scans.is_empty());
    for i in scans {
        assert!(cmds[i + 1].starts_with("ScData(frame="), "{:?}", &cmds[i..]);
        assert_eq!(cmds[i + 2], "ScStopScan()", "{:?}", &cmds[i..]);
    }
}

#[test]
fn a_tescan_run_shares_one_session_and_records_every_function_decoded() {
    let dir = tempfile::tempdir().unwrap();
    let run = acquire(dir.path(), "sharksem", &[]);
    assert!(run.ok, "sdsem acquire failed:\n{}", run.stderr);
    let record = run.record();
    let s = read_summary(&record).unwrap();
    assert!(s.end.complete);
    assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Succeeded);
    assert_eq!(s.frames_by_role.get("left"), Some(&1));
    assert_eq!(s.frames_by_role.get("right"), Some(&1));
    assert_eq!(s.frames_by_role.get("tracking"), Some(&8));
    let ids = s.metadata_record("sdsem.instruments").unwrap();
    for side in ["stage", "sem"] {
        assert!(
            ids[side].starts_with("TESCAN SharkSEM 2.0.25, software sdsem-sim"),
            "{side}: {}",
            ids[side]
        );
    }

    let io = stage_io(&record);
    let cmds = commands(&io);
    assert_eq!(cmds.first().map(String::as_str), Some("TcpGetVersion()"));
    assert_eq!(
        cmds.iter()
            .filter(|c| c.starts_with("TcpRegDataPort(port="))
            .count(),
        1,
        "one session for stage and imaging"
    );
    // Tilt moves: every axis sent, rotation before tilt, in series order and back to 0°.
    let tilts: Vec<String> = cmds
        .iter()
        .filter(|c| c.starts_with("StgMoveTo("))
        .map(|c| {
            assert!(c.contains(", z=10, rotation=0, tilt="), "{c}");
            c.split("tilt=")
                .nth(1)
                .unwrap()
                .split(')')
                .next()
                .unwrap()
                .to_owned()
        })
        .collect();
    let mut distinct = tilts.clone();
    distinct.dedup();
    let expected: Vec<String> = (0..=7).chain([0]).map(|t| t.to_string()).collect();
    assert_eq!(distinct, expected, "{tilts:?}");
    assert_every_scan_stopped(&cmds);
    assert_eq!(
        cmds.iter().filter(|c| c.starts_with("ScScanXY(")).count(),
        10
    );
    assert!(cmds.iter().any(|c| {
        c == "ScScanXY(frame=1, width=320, height=240, left=0, top=0, right=319, bottom=239, \
              single=1, dwell_ns=2000) [wait-B]"
    }));
    // Replies decoded, with round-trip times.
    let pos = io
        .iter()
        .find(|e| e.command.as_deref() == Some("StgGetPosition()"))
        .unwrap();
    assert!(
        pos.reply
            .as_deref()
            .unwrap()
            .starts_with("x=0 y=0 z=10 rotation=0 tilt=0"),
        "{pos:?}"
    );
    for e in &io {
        assert!(
            matches!(e.outcome, IoOutcome::Replied | IoOutcome::Sent),
            "{e:?}"
        );
        if e.outcome == IoOutcome::Replied {
            assert!(e.reply.is_some() && e.rtt_ns.is_some(), "{e:?}");
        }
    }

    let run_dir = record.parent().unwrap();
    for (name, tilt) in [("left.tif", 0.0), ("right.tif", 7.0)] {
        let m = sdsem::imaging::file::read_sem_metadata(run_dir.join(name)).unwrap();
        assert_eq!(m.tilt_deg, Some(tilt), "{name}: {m:?}");
        assert!(
            (m.pixel_size_um.unwrap() - 0.25).abs() < 1e-9,
            "{name}: {m:?}"
        );
    }
}

#[test]
fn lost_chunks_an_ignored_move_and_an_ignored_setting_are_recovered() {
    let dir = tempfile::tempdir().unwrap();
    let run = acquire(
        dir.path(),
        "sharksem",
        &[
            // The first micrograph's second chunk (four 50 ms chunks a micrograph).
            "simulator.sharksem.faults.lose_chunk.at=[2]",
            "simulator.sharksem.faults.ignore_view_field.at=[1]",
            "simulator.stage.faults.ignore_move.at=[3]",
            "imaging.pixel_size_um=0.2",
        ],
    );
    assert!(run.ok, "sdsem acquire failed:\n{}", run.stderr);
    let record = run.record();
    let io = stage_io(&record);
    let cmds = commands(&io);
    let data: Vec<&StageIo> = io
        .iter()
        .filter(|e| {
            e.command
                .as_deref()
                .is_some_and(|c| c.starts_with("ScData("))
        })
        .collect();
    assert_eq!(data[0].outcome, IoOutcome::Garbled, "{:?}", data[0]);
    assert!(
        data[0]
            .detail
            .as_deref()
            .unwrap()
            .contains("chunk was lost")
    );
    assert!(data[1..].iter().all(|e| e.outcome == IoOutcome::Replied));
    assert_eq!(
        cmds.iter().filter(|c| c.starts_with("ScScanXY(")).count(),
        11,
        "one frame retaken"
    );
    assert_every_scan_stopped(&cmds);
    assert_eq!(
        cmds.iter()
            .filter(|c| *c == "SetViewField(mm=0.064)")
            .count(),
        2,
        "ignored, verified by reading back, re-sent once"
    );
    assert_eq!(reissued(&record), 1, "the ignored move was re-issued");
    let s = read_summary(&record).unwrap();
    assert_eq!(s.message_count(topics::SEM_FRAME), 10);
    let m =
        sdsem::imaging::file::read_sem_metadata(record.parent().unwrap().join("left.tif")).unwrap();
    assert!((m.pixel_size_um.unwrap() - 0.2).abs() < 1e-9, "{m:?}");
}

#[test]
fn a_pi_stage_pairs_with_sharksem_imaging_and_a_silent_sem_fails_in_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let run = acquire(dir.path(), "pi-gcs", &[]);
    assert!(run.ok, "sdsem acquire failed:\n{}", run.stderr);
    let cmds = commands(&stage_io(&run.record()));
    assert!(cmds.iter().any(|c| c == "MOV T 7"));
    assert_every_scan_stopped(&cmds);
    std::fs::remove_dir_all(dir.path().join("runs")).unwrap();

    // The SEM stops answering mid-run: one line naming the function and the
    // remedy, the stage back at its safe tilt, the record finished.
    let run = acquire(
        dir.path(),
        "pi-gcs",
        &["simulator.sharksem.faults.silent_after_requests=40"],
    );
    assert!(!run.ok);
    let line = run.stderr.lines().last().unwrap_or("");
    assert!(
        line.contains("did not answer") && line.contains("raise imaging.timeout_ms"),
        "{line}"
    );
    let record = run.record();
    let s = read_summary(&record).unwrap();
    assert!(s.end.complete);
    assert_eq!(s.outcome.as_ref().unwrap().status, RunStatus::Failed);
    let cmds = commands(&stage_io(&record));
    assert_eq!(
        cmds.iter()
            .rev()
            .find(|c| c.starts_with("MOV T"))
            .map(String::as_str),
        Some("MOV T 0")
    );
}
