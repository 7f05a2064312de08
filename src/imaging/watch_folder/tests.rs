use std::sync::{Arc, Mutex};

use sdsem_protocol::sem::Bits;

use super::*;
use crate::imaging::file::{MicrographTags, SampleDepth, write_micrograph_tiff};
use crate::imaging::{Trigger, TriggerFuture};
use crate::stage::StagePosition;

/// Quick settings: 5 ms polls, stable over 3 polls and 40 ms, 2 s timeout.
fn config(dir: &Path) -> ImagingConfig {
    ImagingConfig {
        protocol: ImagingProtocol::WatchFolder,
        watch_dir: dir.to_owned(),
        watch_poll_ms: 5,
        watch_stable_ms: 40,
        watch_stable_polls: 3,
        watch_timeout_s: 2.0,
        ..ImagingConfig::default()
    }
}

fn request(role: Role, width: u32, height: u32) -> GrabRequest {
    GrabRequest {
        width,
        height,
        dwell_us: 1.0,
        role,
        bits: Bits::Sixteen,
    }
}

/// A 16-bit micrograph (ramp) with sdsem's Zeiss-style tags, as bytes.
fn micrograph_bytes(w: usize, h: usize, tilt: f64, pixel_um: f64) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.tif");
    let img = Image::from_fn(w, h, |x, y| ((x + y) % 256) as f32 / 255.0);
    let tags = MicrographTags {
        pixel_size_um: Some(pixel_um),
        tilt_deg: Some(tilt),
        ..MicrographTags::default()
    };
    write_micrograph_tiff(&path, &img, &tags, SampleDepth::Bits16).unwrap();
    std::fs::read(path).unwrap()
}

fn at_tilt(tilt_deg: f64) -> Option<StagePosition> {
    Some(StagePosition {
        x_um: 10.0,
        y_um: -5.0,
        tilt_deg,
    })
}

/// A trigger that records the commands and runs `on_trigger` (e.g. writes the file).
struct FakeTrigger {
    sent: Arc<Mutex<Vec<String>>>,
    on_trigger: Box<dyn FnMut() + Send>,
}

impl Trigger for FakeTrigger {
    fn trigger<'a>(&'a mut self, command: &'a str) -> TriggerFuture<'a> {
        self.sent.lock().unwrap().push(command.to_owned());
        (self.on_trigger)();
        Box::pin(async { Ok(()) })
    }
}

#[tokio::test]
async fn a_file_written_slowly_is_read_once_complete() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config(dir.path());
    cfg.trigger = "FREC".into();
    let (mut source, id) = WatchFolderSource::connect(cfg, Some(90.0)).await.unwrap();
    assert!(
        id.contains("watch folder") && id.contains("0 files"),
        "{id}"
    );
    let bytes = micrograph_bytes(64, 48, 3.0, 0.05);
    let path = dir.path().join("img_001.tif");
    let sent = Arc::new(Mutex::new(Vec::new()));
    // On the trigger the "SEM" writes the file in 8 chunks 15 ms apart: partial files
    // are visible for over 100 ms, longer than the stability window.
    let mut trigger = FakeTrigger {
        sent: Arc::clone(&sent),
        on_trigger: Box::new(move || {
            let (bytes, path) = (bytes.clone(), path.clone());
            std::thread::spawn(move || {
                use std::io::Write;
                let mut f = std::fs::File::create(&path).unwrap();
                for chunk in bytes.chunks(bytes.len().div_ceil(8)) {
                    f.write_all(chunk).unwrap();
                    f.flush().unwrap();
                    std::thread::sleep(Duration::from_millis(15));
                }
            });
        }),
    };
    let context = GrabContext {
        stage: at_tilt(3.2),
        trigger: Some(&mut trigger),
    };
    let frame = source
        .grab_with(request(Role::Left, 1280, 960), context)
        .await
        .unwrap();
    assert_eq!(*sent.lock().unwrap(), vec!["FREC".to_owned()]);
    assert_eq!((frame.width, frame.height), (64, 48));
    assert!((frame.meta.pixel_size_um - 0.05).abs() < 1e-12);
    assert_eq!(frame.meta.tilt_deg, 3.2, "the stage's verified tilt");
    assert_eq!(frame.meta.tilt_axis_deg, 90.0);
    assert_eq!((frame.meta.stage_x_um, frame.meta.stage_y_um), (10.0, -5.0));
    let Pixels::U16(px) = &frame.pixels else {
        panic!("16-bit file, 16-bit frame")
    };
    assert_eq!(px[1], 257, "the ramp's second pixel, exact");
    let origin = frame.origin.unwrap();
    assert_eq!(origin.name, "img_001.tif");
    assert_eq!(origin.recorded_tilt_deg, Some(3.0));
    assert_eq!(origin.downsampled, 1);

    // The same file is never delivered again: the next grab times out naming the folder.
    let mut cfg = config(dir.path());
    cfg.watch_timeout_s = 0.2;
    let mut source2 = WatchFolderSource::new(cfg, None).unwrap();
    let err = source2
        .grab(request(Role::Left, 64, 48))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains(&dir.path().display().to_string())
            && err.contains("no new micrograph")
            && err.contains("is the share mounted"),
        "{err}"
    );
}

#[tokio::test]
async fn a_wrong_tilt_is_refused_naming_both_tilts() {
    let dir = tempfile::tempdir().unwrap();
    let mut source = WatchFolderSource::new(config(dir.path()), None).unwrap();
    let bytes = micrograph_bytes(32, 24, 5.0, 0.1);
    let path = dir.path().join("late.tif");
    let mut trigger = FakeTrigger {
        sent: Arc::default(),
        on_trigger: Box::new(move || std::fs::write(&path, &bytes).unwrap()),
    };
    let mut cfg = config(dir.path());
    cfg.trigger = "MAC 1".into();
    source.cfg = cfg;
    let context = GrabContext {
        stage: at_tilt(4.0),
        trigger: Some(&mut trigger),
    };
    let err = source
        .grab_with(request(Role::Right, 32, 24), context)
        .await
        .unwrap_err();
    let text = err.to_string();
    assert!(matches!(err, ImagingError::WrongTilt { .. }), "{text}");
    assert!(
        text.contains("late.tif") && text.contains("5°") && text.contains("4°"),
        "{text}"
    );

    // An aftermarket tilt stage: the file records the SEM's own stage, not the series'
    // tilt; with the check off the frame is used and still says what the file recorded.
    let bytes = micrograph_bytes(32, 24, 0.0, 0.1);
    let path = dir.path().join("own_stage.tif");
    let mut trigger = FakeTrigger {
        sent: Arc::default(),
        on_trigger: Box::new(move || std::fs::write(&path, &bytes).unwrap()),
    };
    source.cfg.watch_check_tilt = false;
    let context = GrabContext {
        stage: at_tilt(6.0),
        trigger: Some(&mut trigger),
    };
    let frame = source
        .grab_with(request(Role::Right, 32, 24), context)
        .await
        .unwrap();
    assert_eq!(frame.meta.tilt_deg, 6.0);
    assert_eq!(frame.origin.unwrap().recorded_tilt_deg, Some(0.0));
}

#[tokio::test]
async fn a_trigger_without_a_link_to_carry_it_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = config(dir.path());
    cfg.trigger = "FREC".into();
    let mut source = WatchFolderSource::new(cfg, None).unwrap();
    let err = source
        .grab(request(Role::Left, 8, 8))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("\"FREC\"") && err.contains("remcon32"),
        "{err}"
    );
}

#[tokio::test]
async fn links_special_files_and_stale_files_are_never_read() {
    let dir = tempfile::tempdir().unwrap();
    let good = micrograph_bytes(16, 16, 0.0, 0.1);
    // Present before the wait: stale.
    std::fs::write(dir.path().join("stale.tif"), &good).unwrap();
    let mut cfg = config(dir.path());
    cfg.watch_timeout_s = 0.3;
    let mut source = WatchFolderSource::new(cfg, None).unwrap();
    let outside = tempfile::tempdir().unwrap();
    let target = outside.path().join("real.tif");
    std::fs::write(&target, &good).unwrap();
    let (link, socket, fifo) = (
        dir.path().join("link.tif"),
        dir.path().join("socket.tif"),
        dir.path().join("fifo.tif"),
    );
    let mut trigger = FakeTrigger {
        sent: Arc::default(),
        on_trigger: Box::new(move || {
            std::os::unix::fs::symlink(&target, &link).unwrap();
            std::mem::forget(std::os::unix::net::UnixListener::bind(&socket).unwrap());
            rustix::fs::mknodat(
                rustix::fs::CWD,
                &fifo,
                rustix::fs::FileType::Fifo,
                rustix::fs::Mode::from_raw_mode(0o644),
                0,
            )
            .unwrap();
        }),
    };
    source.cfg.trigger = "FREC".into();
    let context = GrabContext {
        stage: at_tilt(0.0),
        trigger: Some(&mut trigger),
    };
    let err = source
        .grab_with(request(Role::Left, 16, 16), context)
        .await
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("skipped: fifo.tif, link.tif, socket.tif")
            || (err.contains("link.tif") && err.contains("socket.tif") && err.contains("fifo.tif")),
        "{err}"
    );
    assert!(!err.contains("stale.tif"), "{err}");
}

#[tokio::test]
async fn a_large_tracking_frame_is_averaged_down_and_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let mut source = WatchFolderSource::new(config(dir.path()), Some(0.0)).unwrap();
    let bytes = micrograph_bytes(100, 60, 1.0, 0.05);
    let path = dir.path().join("t.tif");
    let mut trigger = FakeTrigger {
        sent: Arc::default(),
        on_trigger: Box::new(move || std::fs::write(&path, &bytes).unwrap()),
    };
    source.cfg.trigger = "FREC".into();
    let context = GrabContext {
        stage: at_tilt(1.0),
        trigger: Some(&mut trigger),
    };
    // 100×60 into at most 32×24: factor max(⌈100/32⌉, ⌈60/24⌉) = 4 → 25×15.
    let frame = source
        .grab_with(request(Role::Tracking, 32, 24), context)
        .await
        .unwrap();
    assert_eq!((frame.width, frame.height), (25, 15));
    assert!((frame.meta.pixel_size_um - 0.2).abs() < 1e-12);
    let origin = frame.origin.unwrap();
    assert_eq!(
        (
            origin.stored_width,
            origin.stored_height,
            origin.downsampled
        ),
        (100, 60, 4)
    );
}

#[test]
fn downsample_factors() {
    assert_eq!(downsample_factor((320, 240), (320, 240)), 1);
    assert_eq!(downsample_factor((1024, 768), (320, 240)), 4);
    assert_eq!(downsample_factor((200, 100), (320, 240)), 1);
    let img = Image::from_fn(4, 2, |x, _| x as f32);
    assert_eq!(box_average(&img, 2).data(), &[0.5, 2.5]);
}
