//! `sdsem replay` against a real recorded run: a small acquisition on the
//! built-in simulator (2 reconstruction threads), replayed by the binary with
//! 1 and 3 threads, must reproduce the recorded height map bit for bit;
//! `--set` changes the result without failing; broken records give one-line
//! errors.

#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use sdsem::record::{self, Recorder, RecorderOptions, topics};

fn sdsem(args: &[&str], threads: usize) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .args(args)
        .env("RUST_LOG", "warn")
        .env("RAYON_NUM_THREADS", threads.to_string())
        .output()
        .unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// A 0→4° run at 320×240 on the simulator, reconstructed with 2 threads.
fn record_small_run(dir: &Path) -> PathBuf {
    let sim = concat!(env!("CARGO_MANIFEST_DIR"), "/config/sim.toml");
    let out = format!("run.output_dir={}", dir.join("runs").display());
    let out = sdsem(
        &[
            "acquire",
            "--config",
            sim,
            "--set",
            &out,
            "--set",
            "series.end_tilt_deg=4",
            "--set",
            "imaging.micrograph.width=320",
            "--set",
            "imaging.micrograph.height=240",
            "--set",
            "imaging.tracking.width=160",
            "--set",
            "imaging.tracking.height=120",
            "--set",
            "simulator.time_scale=0.02",
        ],
        2,
    );
    assert!(out.status.success(), "acquire: {}", text(&out.stderr));
    let run_dir = PathBuf::from(text(&out.stdout).lines().last().unwrap().trim());
    run_dir.join("run.mcap")
}

fn replay_json(out: &Output) -> serde_json::Value {
    assert!(out.status.success(), "replay: {}", text(&out.stderr));
    serde_json::from_slice(&out.stdout).unwrap()
}

/// Copies the first `len` bytes of `from` to `to`.
fn truncated_copy(from: &Path, to: &Path, len: usize) {
    let bytes = std::fs::read(from).unwrap();
    std::fs::write(to, &bytes[..len]).unwrap();
}

/// The longest prefix (in 1/200 steps) of `record` for which `keep` holds.
fn longest_prefix(
    record: &Path,
    scratch: &Path,
    keep: impl Fn(&record::EndMicrographs, bool) -> bool,
) -> usize {
    let len = std::fs::metadata(record).unwrap().len() as usize;
    for k in (1..200).rev() {
        let cut = len * k / 200;
        truncated_copy(record, scratch, cut);
        let ends = record::read_end_micrographs(scratch).unwrap();
        let has_height = !record::read_images(scratch, topics::RECON_HEIGHT, |_| true)
            .unwrap()
            .items
            .is_empty();
        if keep(&ends, has_height) {
            return cut;
        }
    }
    panic!("no prefix of {} fits", record.display());
}

#[test]
fn replay_reproduces_a_recorded_run_bit_for_bit_whatever_the_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let record = record_small_run(dir.path());
    let run_dir = record.parent().unwrap();

    // The run's results are attached to its record, as written beside it.
    let summary = record::read_summary(&record).unwrap();
    for (name, media_type) in [
        (topics::ATTACHMENT_HEIGHT_GSF, "application/x-gwyddion-gsf"),
        (topics::ATTACHMENT_CONFIDENCE_TIFF, "image/tiff"),
    ] {
        let a = summary
            .attachments
            .iter()
            .find(|a| a.name == name)
            .unwrap_or_else(|| panic!("no {name} attachment: {:?}", summary.attachments));
        assert_eq!(a.media_type, media_type);
        assert_eq!(
            a.bytes,
            std::fs::metadata(run_dir.join(name)).unwrap().len()
        );
    }

    for threads in [1, 3] {
        let out_dir = dir.path().join(format!("replay-{threads}"));
        let out = sdsem(
            &[
                "replay",
                record.to_str().unwrap(),
                "--out",
                out_dir.to_str().unwrap(),
            ],
            threads,
        );
        assert!(out.status.success(), "{}", text(&out.stderr));
        let stdout = text(&out.stdout);
        assert!(
            stdout.contains("height map bit-for-bit identical to the recorded /recon/height"),
            "{threads} threads: {stdout}"
        );
        assert_eq!(stdout.lines().last().unwrap(), out_dir.to_str().unwrap());
        // The same bytes as the run's own outputs, and the full output set.
        assert_eq!(
            std::fs::read(out_dir.join("height.tif")).unwrap(),
            std::fs::read(run_dir.join("height.tif")).unwrap(),
            "height.tif with {threads} threads"
        );
        for file in [
            "height.gsf",
            "pointcloud.ply",
            "mesh.ply",
            "confidence.tif",
            "report.json",
        ] {
            assert!(out_dir.join(file).is_file(), "{file}");
        }
        let report: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out_dir.join("replay.json")).unwrap()).unwrap();
        assert_eq!(report["comparison"]["verdict"], "identical");
        assert_eq!(report["recorded_outcome"], "succeeded");
        assert_eq!(report["geometry"]["tilt_deg"], 4.0);
    }

    // The record alone suffices: without config.toml beside it.
    std::fs::remove_file(run_dir.join("config.toml")).unwrap();
    let out_dir = dir.path().join("replay-alone");
    let json = replay_json(&sdsem(
        &[
            "replay",
            record.to_str().unwrap(),
            "--out",
            out_dir.to_str().unwrap(),
            "--json",
        ],
        2,
    ));
    assert_eq!(json["comparison"]["verdict"], "identical");
    assert_eq!(json["config_source"], "its metadata sdsem.run");

    // --set re-runs with changed parameters: informative, not a failure.
    let out = sdsem(
        &[
            "replay",
            record.to_str().unwrap(),
            "--out",
            dir.path().join("replay-paper").to_str().unwrap(),
            "--set",
            "reconstruction.mode=paper",
            "--json",
        ],
        2,
    );
    let json = replay_json(&out);
    assert_eq!(json["comparison"]["verdict"], "differs");
    assert!(json["comparison"]["pixels_differing"].as_u64().unwrap() > 0);
    assert!(json["comparison"]["max_abs_diff_um"].as_f64().unwrap() > 0.0);
    assert_eq!(json["overrides"][0], "reconstruction.mode=paper");

    // An invalid override is named.
    let out = sdsem(
        &[
            "replay",
            record.to_str().unwrap(),
            "--out",
            dir.path().join("replay-bad").to_str().unwrap(),
            "--set",
            "reconstruction.mdoe=paper",
        ],
        2,
    );
    assert!(!out.status.success());
    let err = text(&out.stderr);
    assert!(err.contains("mdoe"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "{err}");

    // A record cut off after both micrographs but before the reconstruction:
    // replayed, with nothing to compare and a note saying so.
    let cut = dir.path().join("cut-after-right.mcap");
    let len = longest_prefix(&record, &cut, |ends, has_height| {
        ends.right.is_some() && !has_height
    });
    truncated_copy(&record, &cut, len);
    let json = replay_json(&sdsem(
        &[
            "replay",
            cut.to_str().unwrap(),
            "--out",
            dir.path().join("replay-cut").to_str().unwrap(),
            "--json",
        ],
        2,
    ));
    assert_eq!(json["comparison"]["verdict"], "not_recorded");
    assert_eq!(json["record_complete"], false);
    assert!(json["record_note"].as_str().unwrap().contains("truncated"));
}

#[test]
fn broken_records_give_one_line_errors() {
    let dir = tempfile::tempdir().unwrap();
    let replay = |record: &Path| {
        let out = sdsem(
            &[
                "replay",
                record.to_str().unwrap(),
                "--out",
                dir.path().join("out").to_str().unwrap(),
            ],
            1,
        );
        assert!(!out.status.success());
        assert!(!dir.path().join("out/height.tif").exists());
        let err = text(&out.stderr);
        assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
        err
    };

    let not_mcap = dir.path().join("notes.mcap");
    std::fs::write(&not_mcap, "this is not a record\n").unwrap();
    let err = replay(&not_mcap);
    assert!(err.contains("is not an MCAP file"), "{err}");

    let err = replay(&dir.path().join("missing.mcap"));
    assert!(err.contains("cannot open the run record"), "{err}");

    // A run that failed before its first micrograph.
    let empty = dir.path().join("failed.mcap");
    let recorder = Recorder::create(&empty, RecorderOptions::default()).unwrap();
    let rec = recorder.handle();
    rec.metadata(
        topics::METADATA_RUN,
        [("config".to_owned(), String::new())].into(),
    )
    .unwrap();
    rec.outcome(&record::RunOutcome {
        status: record::RunStatus::Failed,
        cause: Some("cannot reach the instruments: stage: connection refused".into()),
    })
    .unwrap();
    drop(rec);
    recorder.finish().unwrap();
    let err = replay(&empty);
    assert!(err.contains("holds no end micrographs"), "{err}");
    assert!(
        err.contains("the run failed: cannot reach the instruments"),
        "{err}"
    );

    // A record cut off between the left and the right micrograph.
    let full = record_small_run(dir.path());
    let cut = dir.path().join("cut-before-right.mcap");
    let len = longest_prefix(&full, &cut, |ends, _| {
        ends.left.is_some() && ends.right.is_none()
    });
    truncated_copy(&full, &cut, len);
    let err = replay(&cut);
    assert!(err.contains("holds no right micrograph"), "{err}");
    assert!(err.contains("the record is truncated"), "{err}");
}
