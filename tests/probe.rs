//! `sdsem probe` as a process against the simulator, one test per dialect: what it reports
//! (identity, position, limits, the vendor's own state, the newest stored micrograph), that
//! it moves and triggers nothing, and one line with cause and remedy when the stage is at a
//! wrong port or answers nothing.

#![allow(clippy::unwrap_used)]

use std::io::Read;
use std::net::TcpListener;
use std::path::Path;
use std::process::{Command, Output, Stdio};

use sdsem_sim::vendor_tiff::{Samples, StoredMeta, Vendor, encode};
use serde_json::Value;

fn probe(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env_remove("RUST_LOG")
        .args(["--log", "off", "probe"])
        .args(args)
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

fn ok_json(out: &Output) -> Value {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    serde_json::from_slice(&out.stdout).unwrap()
}

fn fact<'a>(facts: &'a Value, name: &str) -> &'a str {
    facts
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["name"] == name)
        .unwrap_or_else(|| panic!("no fact {name:?} in {facts}"))["value"]
        .as_str()
        .unwrap()
}

/// The one line a failed probe prints, asserted to be the only one.
fn one_error_line(out: &Output) -> String {
    assert!(!out.status.success());
    assert!(
        out.stdout.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    let lines: Vec<&str> = stderr.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "{stderr}");
    lines[0].to_owned()
}

#[test]
fn a_pi_stage_and_the_sdsem_link_are_identified() {
    let report = ok_json(&probe(&["--config", "config/sim.toml", "--json"]));
    assert_eq!(report["simulator"], true);
    let stage = &report["stage"];
    assert_eq!(stage["protocol"], "pi-gcs");
    assert_eq!(stage["identity"]["vendor"], "sdsem-sim");
    assert_eq!(stage["identity"]["version"], env!("CARGO_PKG_VERSION"));
    let limits = stage["limits"].as_array().unwrap();
    assert_eq!(limits.len(), 3);
    let tilt = &limits[2];
    assert_eq!(tilt["axis"], "tilt");
    // The controller's TMN?/TMX? were read, and the stage stands inside them.
    assert_eq!(tilt["instrument"], serde_json::json!([-5.0, 70.0]));
    assert_eq!(tilt["inside"], true);
    assert_eq!(fact(&stage["facts"], "FRF? referenced"), "X=1 Y=1 T=1");
    assert_eq!(fact(&stage["facts"], "ONT? on target"), "X=1 Y=1 T=1");
    let imaging = &report["imaging"];
    assert_eq!(imaging["protocol"], "sdsem-link");
    assert_eq!(imaging["identity"]["model"], "virtual-sem");
    assert!(
        fact(&imaging["facts"], "pixel size, micrograph").contains("at 1280 px wide"),
        "{imaging}"
    );
}

#[test]
fn a_tescan_sem_is_identified_over_one_sharksem_session() {
    let report = ok_json(&probe(&["--config", "config/sim-sharksem.toml", "--json"]));
    let stage = &report["stage"];
    assert_eq!(stage["protocol"], "sharksem");
    assert_eq!(stage["identity"]["vendor"], "TESCAN");
    assert!(
        stage["identity"]["raw"]
            .as_str()
            .unwrap()
            .contains("SharkSEM 2.0.25"),
        "{stage}"
    );
    // 2.0.22+ reports its limits (StgGetLimits): they are shown and narrow ours.
    let tilt = &stage["limits"][2];
    assert!(tilt["instrument"].is_array(), "{tilt}");
    assert_eq!(fact(&stage["facts"], "StgIsCalibrated"), "1 (yes)");
    assert_eq!(fact(&stage["facts"], "StgIsBusy"), "0 (idle)");
    let imaging = &report["imaging"];
    assert_eq!(imaging["protocol"], "sharksem");
    assert_eq!(imaging["identity"]["vendor"], "TESCAN");
    assert!(!fact(&imaging["facts"], "DtEnumDetectors").is_empty());
    assert!(
        fact(&imaging["facts"], "imaging.detector").starts_with("a run selects "),
        "{imaging}"
    );
    assert!(fact(&imaging["facts"], "GetViewField").contains(" mm: pixel "));
}

/// A Zeiss micrograph as SmartSEM stores it (tag 34118), at 12° tilt.
fn stored_zeiss(dir: &Path, name: &str) {
    let (w, h) = (64, 48);
    let samples = Samples::U8((0..w * h).map(|i| (i % 251) as u8).collect());
    let meta = StoredMeta {
        pixel_size_um: 0.125,
        dwell_us: 10.0,
        stage_x_um: 0.0,
        stage_y_um: 0.0,
        tilt_deg: 12.0,
        unix_s: 1_780_000_000,
    };
    std::fs::write(dir.join(name), encode(Vendor::Zeiss, w, h, &samples, &meta)).unwrap();
}

#[test]
fn a_zeiss_sem_is_read_through_remcon32_and_its_store_folder_without_a_trigger() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    std::fs::create_dir(&store).unwrap();
    stored_zeiss(&store, "earlier0001.tif");
    let folder = format!("simulator.folder.dir={}", store.display());
    let args = ["--config", "config/sim-zeiss.toml", "--set", &folder];

    let table = probe(&args);
    let text = String::from_utf8_lossy(&table.stdout);
    assert!(
        table.status.success(),
        "{}",
        String::from_utf8_lossy(&table.stderr)
    );
    for line in [
        "remcon32",
        "C95? (all axes)",
        "DET? detector",
        "\"FREC\" over the stage link",
    ] {
        assert!(text.contains(line), "{line:?} missing from\n{text}");
    }

    let report = ok_json(&probe(&[&args[..], &["--json"]].concat()));
    let stage = &report["stage"];
    assert_eq!(stage["protocol"], "remcon32");
    assert!(
        stage["identity"]["raw"]
            .as_str()
            .unwrap()
            .contains("SmartSEM"),
        "{stage}"
    );
    // No FREC was sent (the photo count stands at 0) and the stage was not moved.
    assert_eq!(fact(&stage["facts"], "PHN? photo number"), "0");
    assert_eq!(stage["position"]["tilt_deg"], 0.0);
    assert!(fact(&stage["facts"], "PIX? pixel size").ends_with(" nm (field width / 1024)"));
    let imaging = &report["imaging"];
    assert_eq!(imaging["protocol"], "watch-folder");
    // Who stores the files, from the newest one's tag 34118 (Serial No., Version).
    assert_eq!(imaging["identity"]["vendor"], "Zeiss");
    assert_eq!(imaging["identity"]["serial"], "sdsem-sim");
    let its = fact(&imaging["facts"], "its metadata");
    assert!(
        its.contains("stage tilt 12°") && its.contains("pixel 0.125 µm"),
        "{its}"
    );
    assert_eq!(
        std::fs::read_dir(&store).unwrap().count(),
        1,
        "the probe stored a micrograph"
    );
}

/// A configuration without a simulator: the stage of `protocol` at `endpoint`, a short timeout.
fn rig(dir: &Path, protocol: &str, endpoint: &str) -> String {
    let path = dir.join(format!("{protocol}.toml"));
    std::fs::write(
        &path,
        format!(
            "[stage]\nprotocol = \"{protocol}\"\nendpoint = \"{endpoint}\"\n\
             connect_timeout_s = 1.0\nreply_timeout_s = 0.2\nquery_retries = 1\n"
        ),
    )
    .unwrap();
    path.display().to_string()
}

#[test]
fn a_wrong_port_is_one_line_with_cause_and_remedy() {
    let dir = tempfile::tempdir().unwrap();
    // A port that was free a moment ago: nothing listens there.
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let endpoint = format!("tcp://127.0.0.1:{port}");
    for (protocol, remedy) in [
        ("pi-gcs", "is the port right?"),
        ("remcon32", "is the port right?"),
        ("sharksem", "SharkSEM remote control enabled on that port"),
    ] {
        let line = one_error_line(&probe(&["--config", &rig(dir.path(), protocol, &endpoint)]));
        assert!(
            line.contains(&endpoint) && line.contains("refused") && line.contains(remedy),
            "{protocol}: {line}"
        );
    }
}

#[test]
fn a_silent_server_is_one_line_with_cause_and_remedy() {
    let dir = tempfile::tempdir().unwrap();
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let endpoint = format!("tcp://{}", listener.local_addr().unwrap());
    // Accepts and reads, answers nothing.
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut s) = stream else { return };
            std::thread::spawn(move || {
                let mut buf = [0u8; 256];
                while s.read(&mut buf).is_ok_and(|n| n > 0) {}
            });
        }
    });
    // PI GCS clears the error state first (`ERR?`); RemCon32 asks for the version. Over TCP
    // the remedy names the address and the language to speak there, never a baud rate.
    let addr = endpoint.trim_start_matches("tcp://");
    for (protocol, query, server) in [
        (
            "pi-gcs",
            "`ERR?`",
            "the stage controller's TCP port, that it speaks PI GCS",
        ),
        (
            "remcon32",
            "`VER?`",
            "a serial-to-Ethernet server on the SEM PC's RemCon32 line, that it speaks Zeiss \
             RemCon32",
        ),
    ] {
        let line = one_error_line(&probe(&["--config", &rig(dir.path(), protocol, &endpoint)]));
        let remedy = format!(
            "check that {addr} (stage.endpoint) is {server} (stage.protocol = \"{protocol}\")"
        );
        assert!(
            line.contains(&format!("no reply to {query}"))
                && line.contains(&remedy)
                && !line.contains("baud"),
            "{protocol}: {line}"
        );
    }
    // SharkSEM answers nothing it does not accept, so silence is named as such.
    let line = one_error_line(&probe(&[
        "--config",
        &rig(dir.path(), "sharksem", &endpoint),
    ]));
    assert!(
        line.contains(&endpoint) && line.contains("did not answer") && line.contains("check"),
        "sharksem: {line}"
    );
}
