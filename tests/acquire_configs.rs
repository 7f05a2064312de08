//! The shipped simulator configurations of each microscope dialect run `sdsem acquire` end to
//! end as `config/sim.toml` does, as a process, only the output folders moved: the record read
//! back holds the frames, every vendor command decoded with its round-trip time in
//! `/stage/io`, and metadata naming the protocols and the instrument's version and serial.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use sdsem::record::{FrameInfo, RunStatus, read_json, read_summary, topics};
use sdsem::stage::{IoOutcome, StageIo};

/// `sdsem acquire --config CONFIG` with the runs (and `extra` overrides) under `dir`; the record.
fn acquire(config: &str, dir: &Path, extra: &[String]) -> PathBuf {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_sdsem"));
    cmd.current_dir(env!("CARGO_MANIFEST_DIR"))
        .env_remove("RUST_LOG")
        .args(["--log", "warn", "acquire", "--config", config, "--set"])
        .arg(format!("run.output_dir={}", dir.join("runs").display()));
    for s in extra {
        cmd.args(["--set", s]);
    }
    let out = cmd.stdin(Stdio::null()).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{config}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let run_dir = PathBuf::from(stdout.lines().last().unwrap());
    assert!(
        run_dir.join("height.tif").is_file(),
        "{config}: no height map"
    );
    run_dir.join("run.mcap")
}

fn stage_io(record: &Path) -> Vec<StageIo> {
    read_json(record, topics::STAGE_IO)
        .unwrap()
        .items
        .iter()
        .map(|m| m.parse().unwrap())
        .collect()
}

fn frame_infos(record: &Path) -> Vec<FrameInfo> {
    read_json(record, topics::SEM_FRAME_INFO)
        .unwrap()
        .items
        .iter()
        .map(|m| m.parse().unwrap())
        .collect()
}

#[test]
fn sim_zeiss_runs_end_to_end_over_remcon32_and_the_store_folder() {
    let dir = tempfile::tempdir().unwrap();
    let store = format!(
        "simulator.folder.dir={}",
        dir.path().join("store").display()
    );
    let record = acquire("config/sim-zeiss.toml", dir.path(), &[store]);

    let summary = read_summary(&record).unwrap();
    assert_eq!(
        summary.outcome.as_ref().unwrap().status,
        RunStatus::Succeeded
    );
    assert_eq!(summary.frames_by_role.get("left"), Some(&1));
    assert_eq!(summary.frames_by_role.get("right"), Some(&1));
    assert!(summary.frames_by_role.get("tracking").copied().unwrap_or(0) >= 8);

    // Every RemCon32 exchange decoded, answered, and timed.
    let io = stage_io(&record);
    let commands: Vec<&str> = io.iter().filter_map(|e| e.command.as_deref()).collect();
    for word in ["VER?", "C95?", "FREC", "MAC 1"] {
        assert!(commands.contains(&word), "{word} not in {commands:?}");
    }
    assert!(
        commands.iter().any(|c| c.starts_with("C95 ")),
        "{commands:?}"
    );
    for e in io
        .iter()
        .filter(|e| e.command.as_deref() != Some("(null command)"))
    {
        assert_eq!(e.outcome, IoOutcome::Replied, "{e:?}");
        assert!(e.rtt_ns.is_some_and(|t| t > 0), "{e:?}");
    }

    // Each frame was read from a file SmartSEM stored, and says who stored it.
    let infos = frame_infos(&record);
    assert_eq!(infos.len() as u64, summary.message_count(topics::SEM_FRAME));
    for info in &infos {
        let file = info.file.as_ref().unwrap();
        assert_eq!(file.vendor.as_deref(), Some("Zeiss"));
        assert_eq!(file.instrument.serial, "sdsem-sim");
    }

    let ids = summary
        .metadata_record(topics::METADATA_INSTRUMENTS)
        .unwrap();
    assert_eq!(ids["stage_protocol"], "remcon32");
    assert_eq!(ids["sem_protocol"], "watch-folder");
    assert!(ids["stage_version"].contains("SmartSEM"), "{ids:?}");
    let stored = summary
        .metadata_record(topics::METADATA_INSTRUMENTS_FROM_FRAMES)
        .unwrap();
    assert_eq!(stored["sem_vendor"], "Zeiss");
    assert_eq!(stored["sem_serial"], "sdsem-sim");
    assert!(stored["sem_version"].starts_with("sdsem-sim"), "{stored:?}");
}

#[test]
fn sim_sharksem_runs_end_to_end_over_one_sharksem_session() {
    let dir = tempfile::tempdir().unwrap();
    let record = acquire("config/sim-sharksem.toml", dir.path(), &[]);

    let summary = read_summary(&record).unwrap();
    assert_eq!(
        summary.outcome.as_ref().unwrap().status,
        RunStatus::Succeeded
    );
    assert_eq!(summary.frames_by_role.get("left"), Some(&1));
    assert_eq!(summary.frames_by_role.get("right"), Some(&1));
    assert!(summary.frames_by_role.get("tracking").copied().unwrap_or(0) >= 8);

    // Every SharkSEM function decoded by name with its arguments, answered ones timed.
    let io = stage_io(&record);
    let commands: Vec<&str> = io.iter().filter_map(|e| e.command.as_deref()).collect();
    for name in [
        "TcpGetVersion",
        "StgGetPosition",
        "StgMoveTo(",
        "ScScanXY(",
        "ScStopScan",
    ] {
        assert!(
            commands.iter().any(|c| c.starts_with(name)),
            "{name} not in {commands:?}"
        );
    }
    let timed = io
        .iter()
        .filter(|e| e.outcome == IoOutcome::Replied)
        .inspect(|e| assert!(e.rtt_ns.is_some(), "{e:?}"))
        .count();
    assert!(timed > 20, "{timed} answered exchanges");
    assert!(
        !io.iter().any(|e| e.outcome == IoOutcome::Timeout),
        "a timeout"
    );

    let infos = frame_infos(&record);
    assert_eq!(infos.len() as u64, summary.message_count(topics::SEM_FRAME));
    let ids = summary
        .metadata_record(topics::METADATA_INSTRUMENTS)
        .unwrap();
    assert_eq!(ids["stage_protocol"], "sharksem");
    assert_eq!(ids["sem_protocol"], "sharksem");
    assert_eq!(ids["sem_vendor"], "TESCAN");
    assert!(
        !ids["sem_version"].is_empty() && !ids["sem_serial"].is_empty(),
        "{ids:?}"
    );
}
