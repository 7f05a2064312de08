//! The watch-folder imaging source against the simulator's store folder, in process: the
//! simulated SEM scans where the (simulated) stage is and stores vendor TIFFs slowly, in
//! chunks, over a stale file; sdsem triggers, waits, reads each frame once it is whole,
//! checks its recorded tilt against the stage's and refuses the one that disagrees.

#![allow(clippy::unwrap_used)]

use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};

use sdsem::imaging::{
    FrameSource, GrabContext, GrabRequest, ImagingConfig, ImagingError, ImagingProtocol, Pixels,
    Role, Trigger, TriggerFuture, WatchFolderSource,
};
use sdsem::stage::StagePosition;
use sdsem_protocol::sem::Bits;
use sdsem_sim::clock::{Clock, ScaledClock};
use sdsem_sim::pose::{FixedPose, PoseSource, StagePose};
use sdsem_sim::scene::{Scene, SceneKind, SceneParams};
use sdsem_sim::vendor_tiff::Vendor;
use sdsem_sim::{FaultTrigger, FolderSimConfig, FolderWriter, SemSimConfig, SimSem};

/// The SEM's side of `imaging.trigger`: each command stores one micrograph, on the SEM's
/// own thread, as RemCon32's `FREC` does.
struct StoreOnTrigger {
    writer: Arc<FolderWriter>,
    sent: Arc<Mutex<Vec<String>>>,
}

impl Trigger for StoreOnTrigger {
    fn trigger<'a>(&'a mut self, command: &'a str) -> TriggerFuture<'a> {
        self.sent.lock().unwrap().push(command.to_owned());
        let writer = Arc::clone(&self.writer);
        std::thread::spawn(move || writer.store(&AtomicBool::new(false)).unwrap());
        Box::pin(async { Ok(()) })
    }
}

struct Rig {
    _dir: tempfile::TempDir,
    pose: Arc<FixedPose>,
    writer: Arc<FolderWriter>,
    source: WatchFolderSource,
    trigger: StoreOnTrigger,
}

const SIDE: (usize, usize) = (128, 96);

fn rig(vendor: Vendor) -> Rig {
    let dir = tempfile::tempdir().unwrap();
    let clock: Arc<dyn Clock> = Arc::new(ScaledClock::new(1.0));
    let pose = Arc::new(FixedPose::default());
    let scene = Arc::new(
        Scene::generate(&SceneParams {
            kind: SceneKind::Particles,
            seed: Some(5),
            field_um: 40.0,
            sample_um: 0.2,
        })
        .unwrap(),
    );
    let mut sem_cfg = SemSimConfig::default();
    sem_cfg.optics.width = 256;
    sem_cfg.optics.height = 192;
    sem_cfg.optics.pixel_size_um = 0.1;
    let sem = Arc::new(SimSem::new(
        &sem_cfg,
        scene,
        Arc::clone(&pose) as Arc<dyn PoseSource>,
        Arc::clone(&clock),
    ));
    // Written in 6 chunks over 0.15 s (partial files visible), over a stale file of the
    // first name; the third micrograph records a tilt 5° off.
    let folder = FolderSimConfig {
        dir: dir.path().to_owned(),
        vendor,
        width: SIDE.0,
        height: SIDE.1,
        bits: if vendor == Vendor::Tescan { 16 } else { 8 },
        write_s: 0.15,
        write_chunks: 6,
        stale_file: true,
        wrong_tilt: FaultTrigger::at([3]),
        wrong_tilt_deg: 5.0,
        ..FolderSimConfig::default()
    };
    let writer = Arc::new(FolderWriter::new(&folder, 11, sem, clock).unwrap());
    let cfg = ImagingConfig {
        protocol: ImagingProtocol::WatchFolder,
        watch_dir: dir.path().to_owned(),
        trigger: "FREC".into(),
        watch_poll_ms: 10,
        watch_stable_ms: 60,
        watch_stable_polls: 3,
        watch_timeout_s: 10.0,
        ..ImagingConfig::default()
    };
    let source = WatchFolderSource::new(cfg, Some(0.0)).unwrap();
    Rig {
        _dir: dir,
        pose,
        trigger: StoreOnTrigger {
            writer: Arc::clone(&writer),
            sent: Arc::default(),
        },
        writer,
        source,
    }
}

impl Rig {
    async fn grab_at(
        &mut self,
        tilt_deg: f64,
        role: Role,
    ) -> Result<sdsem::imaging::Frame, ImagingError> {
        self.pose.set(StagePose {
            x_um: 0.0,
            y_um: 0.0,
            tilt_deg,
        });
        let request = GrabRequest {
            width: 64,
            height: 48,
            dwell_us: 1.0,
            role,
            bits: Bits::Sixteen,
        };
        let context = GrabContext {
            stage: Some(StagePosition {
                x_um: 0.0,
                y_um: 0.0,
                tilt_deg,
            }),
            trigger: Some(&mut self.trigger),
        };
        self.source.grab_with(request, context).await
    }
}

async fn series(vendor: Vendor) {
    let mut rig = rig(vendor);
    let pixel = 0.1 * 256.0 / SIDE.0 as f64;

    // 1: overwrites the stale file (tilt 45°) in place, slowly: read once whole.
    let f = rig.grab_at(0.0, Role::Left).await.unwrap();
    let origin = f.origin.clone().unwrap();
    assert_eq!(origin.name, "image_0001.tif", "{vendor:?}");
    assert_eq!(
        origin.recorded_tilt_deg,
        Some(0.0),
        "{vendor:?}: not the stale file's 45°"
    );
    assert!(
        rig.source.last_wait().changing.contains(&origin.name),
        "{vendor:?}: the partial file was seen and waited for: {:?}",
        rig.source.last_wait()
    );
    assert_eq!((f.width, f.height), SIDE, "{vendor:?}: info bar cut off");
    assert_eq!(
        origin.stored_height as usize,
        SIDE.1 + vendor.bar_rows(SIDE.1)
    );
    assert!(
        (f.meta.pixel_size_um - pixel).abs() < 1e-3 * pixel,
        "{vendor:?} {}",
        f.meta.pixel_size_um
    );
    let last_row_is_bar_edge = match &f.pixels {
        Pixels::U8(v) => v[(SIDE.1 - 1) * SIDE.0..].iter().all(|&p| p == 255),
        Pixels::U16(v) => v[(SIDE.1 - 1) * SIDE.0..].iter().all(|&p| p == u16::MAX),
    };
    assert!(
        !last_row_is_bar_edge,
        "{vendor:?}: the bar leaked into the frame"
    );

    // 2: a tracking frame, averaged down to the 64×48 asked.
    let f = rig.grab_at(1.0, Role::Tracking).await.unwrap();
    assert_eq!((f.width, f.height), (64, 48), "{vendor:?}");
    assert_eq!(f.origin.unwrap().downsampled, 2);
    assert!((f.meta.pixel_size_um - 2.0 * pixel).abs() < 2e-3 * pixel);

    // 3: records 2° + 5°: refused, naming both tilts.
    let err = rig.grab_at(2.0, Role::Left).await.unwrap_err();
    let text = err.to_string();
    assert!(
        matches!(err, ImagingError::WrongTilt { .. }),
        "{vendor:?}: {text}"
    );
    assert!(
        text.contains("image_0003.tif") && text.contains("7°") && text.contains("2°"),
        "{text}"
    );

    // 4: the refused file is never taken again; the next one is.
    let f = rig.grab_at(2.0, Role::Right).await.unwrap();
    assert_eq!(f.origin.unwrap().name, "image_0004.tif");
    assert_eq!(f.meta.tilt_deg, 2.0);

    assert_eq!(*rig.trigger.sent.lock().unwrap(), vec!["FREC"; 4]);
    let stored = rig.writer.stored();
    assert_eq!(stored.len(), 4);
    assert_eq!(stored[2].recorded_tilt_deg, 7.0);
}

#[tokio::test]
async fn zeiss_files_arrive_whole_and_a_wrong_tilt_is_refused() {
    series(Vendor::Zeiss).await;
}

#[tokio::test]
async fn fei_files_lose_their_data_bar() {
    series(Vendor::Fei).await;
}

#[tokio::test]
async fn tescan_files_lose_their_info_strip() {
    series(Vendor::Tescan).await;
}

/// `sdsem acquire` refuses a watch-folder configuration it cannot run, in one line naming
/// the key and the remedy, before any stage command.
#[test]
fn unusable_watch_folder_configurations_are_refused_in_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let config = dir.path().join("watch.toml");
    std::fs::write(
        &config,
        format!(
            r#"[run]
output_dir = "{runs}"
reconstruct = false

[stage]
axis_x = "X"
axis_y = "Y"
axis_tilt = "T"

[imaging]
protocol = "watch-folder"

[simulator]
time_scale = 0.01

[simulator.sem.scene]
field_um = 40.0

[simulator.folder]
dir = "{store}"
"#,
            runs = dir.path().join("runs").display(),
            store = store.display()
        ),
    )
    .unwrap();
    let cases: [(&str, &[&str], &[&str]); 3] = [
        (
            "a trigger a PI stage cannot carry",
            &["imaging.trigger=FREC"],
            &["\"FREC\"", "stage.protocol = \"remcon32\""],
        ),
        (
            "no tilt axis to reconstruct with",
            &["run.reconstruct=true"],
            &["reconstruction.tilt_axis_deg"],
        ),
        (
            "a one-shot stability",
            &["imaging.watch_stable_polls=1"],
            &["imaging.watch_stable_polls"],
        ),
    ];
    for (what, sets, needles) in cases {
        let mut args = vec![
            "acquire".to_owned(),
            "--config".to_owned(),
            config.display().to_string(),
        ];
        for s in sets {
            args.extend(["--set".to_owned(), (*s).to_owned()]);
        }
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_sdsem"))
            .args(&args)
            .stdin(std::process::Stdio::null())
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{what}: accepted");
        let last = stderr.lines().last().unwrap_or_default();
        for needle in needles {
            assert!(
                last.contains(needle),
                "{what}: {needle:?} not in {stderr:?}"
            );
        }
    }
}
