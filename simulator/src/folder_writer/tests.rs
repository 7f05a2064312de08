use std::sync::atomic::AtomicBool;

use super::*;
use crate::clock::{ManualClock, ScaledClock};
use crate::config::SemSimConfig;
use crate::pose::{FixedPose, PoseSource, StagePose};
use crate::scene::{Scene, SceneKind, SceneParams};
use crate::store::StoreCommand;

fn sem(pose: Arc<FixedPose>, clock: Arc<dyn Clock>) -> Arc<SimSem> {
    let scene = Arc::new(
        Scene::generate(&SceneParams {
            kind: SceneKind::Grid,
            seed: Some(2),
            field_um: 40.0,
            sample_um: 0.2,
        })
        .unwrap(),
    );
    let mut cfg = SemSimConfig::default();
    cfg.optics.pixel_size_um = 0.25;
    cfg.optics.width = 64;
    cfg.optics.height = 48;
    Arc::new(SimSem::new(&cfg, scene, pose as Arc<dyn PoseSource>, clock))
}

fn config(dir: &Path) -> FolderSimConfig {
    FolderSimConfig {
        dir: dir.to_owned(),
        width: 64,
        height: 48,
        ..FolderSimConfig::default()
    }
}

/// The text of the Zeiss block of a stored file (tag 34118 of a file this module wrote).
fn zeiss_text(path: &Path) -> String {
    let bytes = std::fs::read(path).unwrap();
    let key = b"Stage at T =";
    let at = bytes.windows(key.len()).position(|w| w == key).unwrap();
    let end = bytes[at..].iter().position(|&b| b == b'\r').unwrap();
    String::from_utf8_lossy(&bytes[at..at + end]).into_owned()
}

#[test]
fn stores_numbered_files_at_the_stage_tilt_with_faults() {
    let dir = tempfile::tempdir().unwrap();
    let pose = Arc::new(FixedPose::new(StagePose {
        x_um: 0.0,
        y_um: 0.0,
        tilt_deg: 2.0,
    }));
    let clock = Arc::new(ManualClock::new());
    let mut cfg = config(dir.path());
    cfg.wrong_tilt = FaultTrigger::at([2]);
    cfg.temp_then_rename = true;
    let writer =
        FolderWriter::new(&cfg, 7, sem(pose.clone(), clock.clone()), clock.clone()).unwrap();
    let cancel = AtomicBool::new(false);
    let t0 = clock.now_s();
    let first = writer.store(&cancel).unwrap();
    // The scan took its time on the clock: 64 × 48 × 1 µs.
    assert!((clock.now_s() - t0 - 64.0 * 48.0 * 1e-6).abs() < 1e-9);
    assert_eq!(first.path, dir.path().join("image_0001.tif"));
    assert_eq!(zeiss_text(&first.path), "Stage at T =   2.0 \u{fffd}");
    pose.set(StagePose {
        tilt_deg: 3.0,
        ..StagePose::default()
    });
    let second = writer.store(&cancel).unwrap();
    assert_eq!(second.path, dir.path().join("image_0002.tif"));
    assert_eq!((second.tilt_deg, second.recorded_tilt_deg), (3.0, 8.0));
    assert_eq!(zeiss_text(&second.path), "Stage at T =   8.0 \u{fffd}");
    let mut names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    assert_eq!(
        names,
        ["image_0001.tif", "image_0002.tif"],
        "no temporary file left"
    );
    assert_eq!(writer.stored(), vec![first, second]);
}

#[test]
fn a_stale_file_waits_under_the_first_name() {
    let dir = tempfile::tempdir().unwrap();
    let clock = Arc::new(ManualClock::new());
    let mut cfg = config(dir.path());
    cfg.stale_file = true;
    cfg.first_number = 7;
    let writer = FolderWriter::new(&cfg, 1, sem(Arc::default(), clock.clone()), clock).unwrap();
    let stale = dir.path().join("image_0007.tif");
    assert_eq!(zeiss_text(&stale), "Stage at T =  45.0 \u{fffd}");
    // The first store overwrites it in place.
    writer.store(&AtomicBool::new(false)).unwrap();
    assert_eq!(zeiss_text(&stale), "Stage at T =   0.0 \u{fffd}");
}

#[test]
fn a_slow_write_shows_partial_files() {
    let dir = tempfile::tempdir().unwrap();
    // Real time: 0.3 s of writing in 6 chunks.
    let clock: Arc<dyn Clock> = Arc::new(ScaledClock::new(1.0));
    let mut cfg = config(dir.path());
    cfg.write_s = 0.3;
    cfg.write_chunks = 6;
    let writer =
        Arc::new(FolderWriter::new(&cfg, 1, sem(Arc::default(), clock.clone()), clock).unwrap());
    let stop = Arc::new(AtomicBool::new(false));
    let (requests, server) = serve(Arc::clone(&writer), Arc::clone(&stop)).unwrap();
    assert!(requests.store_now());
    let path = dir.path().join("image_0001.tif");
    let mut sizes = std::collections::BTreeSet::new();
    let start = std::time::Instant::now();
    while writer.stored().is_empty() && start.elapsed() < Duration::from_secs(10) {
        if let Ok(m) = std::fs::metadata(&path) {
            sizes.insert(m.len());
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let full = std::fs::metadata(&path).unwrap().len();
    assert!(
        sizes.iter().filter(|&&s| s > 0 && s < full).count() >= 3,
        "partial sizes seen: {sizes:?} of {full}"
    );
    stop.store(true, Ordering::Relaxed);
    server.join();
}

#[test]
fn the_timer_stores_on_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let clock: Arc<dyn Clock> = Arc::new(ScaledClock::new(0.01));
    let mut cfg = config(dir.path());
    cfg.every_s = 2.0;
    let writer =
        Arc::new(FolderWriter::new(&cfg, 1, sem(Arc::default(), clock.clone()), clock).unwrap());
    let stop = Arc::new(AtomicBool::new(false));
    let (_requests, server) = serve(Arc::clone(&writer), Arc::clone(&stop)).unwrap();
    let start = std::time::Instant::now();
    while writer.stored().len() < 2 && start.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(5));
    }
    stop.store(true, Ordering::Relaxed);
    server.join();
    assert!(
        writer.stored().len() >= 2,
        "two stores in 4 simulated seconds"
    );
}

#[test]
fn settings_are_checked() {
    let err = FolderSimConfig::default()
        .validate()
        .unwrap_err()
        .to_string();
    assert!(err.contains("folder.dir"), "{err}");
    let mut c = config(Path::new("/tmp/x"));
    c.bits = 12;
    assert!(
        c.validate()
            .unwrap_err()
            .to_string()
            .contains("folder.bits")
    );
    c.bits = 8;
    c.prefix = "../a".into();
    assert!(
        c.validate()
            .unwrap_err()
            .to_string()
            .contains("folder.prefix")
    );
}

#[test]
fn remcon_frec_over_the_stage_link_stores_a_micrograph() {
    use std::io::{BufRead, BufReader};

    use crate::config::{SimConfig, SimStageProtocol};

    let dir = tempfile::tempdir().unwrap();
    let mut c = SimConfig {
        seed: 4,
        time_scale: 0.01,
        ..SimConfig::default()
    };
    c.stage.protocol = SimStageProtocol::Remcon32;
    c.sem.scene.kind = SceneKind::Grid;
    c.sem.scene.field_um = 40.0;
    c.sem.optics.width = 128;
    c.sem.optics.height = 96;
    c.folder = Some(FolderSimConfig {
        vendor: Vendor::Fei,
        macros: vec![FolderMacro {
            number: 1,
            width: 32,
            height: 24,
            dwell_us: 1.0,
        }],
        ..config(dir.path())
    });
    let sim = crate::Simulator::spawn(c).unwrap();
    assert!(
        sim.endpoint_lines()
            .contains(&format!("folder {}", dir.path().display()))
    );
    let addr = sim
        .stage_endpoint()
        .strip_prefix("tcp://")
        .unwrap()
        .to_owned();
    let stream = std::net::TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut reader = BufReader::new(stream.try_clone().unwrap());
    (&stream).write_all(b"FREC\r").unwrap();
    let mut lines = [String::new(), String::new()];
    for line in &mut lines {
        reader.read_line(line).unwrap();
    }
    assert_eq!(lines, ["@\r\n", ">\r\n"], "accepted, then done");
    let folder = sim.folder().unwrap();
    let start = std::time::Instant::now();
    while folder.stored().is_empty() && start.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(5));
    }
    let stored = folder.stored();
    assert_eq!(stored.len(), 1, "one FREC, one micrograph");
    assert_eq!(stored[0].path, dir.path().join("image_0001.tif"));
    assert!(
        sim.frame(stored[0].frame).is_some(),
        "the same SEM's frame: ground truth known"
    );
    assert_eq!(sim.frame(stored[0].frame).unwrap().view.width, 64);

    // MAC 1 stores at its macro's size; a macro that is not set up cannot execute.
    let mut ask = |line: &str| {
        (&stream).write_all(format!("{line}\r").as_bytes()).unwrap();
        let mut lines = [String::new(), String::new()];
        for line in &mut lines {
            reader.read_line(line).unwrap();
        }
        lines
    };
    assert_eq!(ask("MAC 1"), ["@\r\n", ">\r\n"]);
    assert_eq!(ask("MAC 2"), ["@\r\n", "*616\r\n"]);
    while folder.stored().len() < 2 && start.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(5));
    }
    let stored = folder.stored();
    assert_eq!(stored.len(), 2, "MAC 2 stored nothing");
    assert_eq!(sim.frame(stored[1].frame).unwrap().view.width, 32);
}

#[test]
fn frec_stores_at_the_folder_settings_and_a_macro_at_its_own() {
    let mut cfg = config(Path::new("/unused"));
    cfg.macros = vec![FolderMacro {
        number: 1,
        width: 32,
        height: 24,
        dwell_us: 0.5,
    }];
    cfg.validate().unwrap();
    assert_eq!(cfg.settings_for(StoreCommand::Record), Some(cfg.settings()));
    assert_eq!(
        cfg.settings_for(StoreCommand::Macro(1)),
        Some(StoreSettings {
            width: 32,
            height: 24,
            dwell_us: 0.5
        })
    );
    assert_eq!(cfg.settings_for(StoreCommand::Macro(2)), None);
    cfg.macros.push(cfg.macros[0]);
    assert!(cfg.validate().unwrap_err().to_string().contains("twice"));
    cfg.macros.pop();
    cfg.macros[0].dwell_us = 0.0;
    let e = cfg.validate().unwrap_err().to_string();
    assert!(e.contains("folder.macros.dwell_us"), "{e}");

    // A macro's store: its size, its scan time on the clock.
    let dir = tempfile::tempdir().unwrap();
    let clock = Arc::new(ManualClock::new());
    let writer = FolderWriter::new(
        &config(dir.path()),
        1,
        sem(Arc::default(), clock.clone()),
        clock.clone(),
    )
    .unwrap();
    let t0 = clock.now_s();
    let small = StoreSettings {
        width: 32,
        height: 24,
        dwell_us: 0.5,
    };
    let stored = writer.store_at(&small, &AtomicBool::new(false)).unwrap();
    assert!((clock.now_s() - t0 - 32.0 * 24.0 * 0.5e-6).abs() < 1e-9);
    let bytes = std::fs::read(&stored.path).unwrap();
    let key = b"Store resolution = 32 * 24";
    assert!(bytes.windows(key.len()).any(|w| w == key));
}
