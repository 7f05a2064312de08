//! The SharkSEM source against the in-process simulator's SharkSEM dialect.

use std::sync::Arc;

use sdsem_sim::config::FaultTrigger;
use sdsem_sim::scene::SceneKind;
use sdsem_sim::sharksem::SharkSemSimConfig;
use sdsem_sim::{SimConfig, SimHandle, Simulator};

use super::*;
use crate::imaging::{ImagingProtocol, Role, ScanSettings};
use crate::stage::{IoOutcome, MemoryObserver, StageIo};

/// A small, fast simulator (1000× real time) serving SharkSEM as `tweak` says.
fn sim(tweak: impl FnOnce(&mut SharkSemSimConfig, &mut SimConfig)) -> SimHandle {
    let mut c = SimConfig {
        seed: 3,
        time_scale: 0.001,
        ..SimConfig::default()
    };
    c.sem.scene.kind = SceneKind::Particles;
    c.sem.scene.field_um = 60.0;
    c.sem.optics.width = 128;
    c.sem.optics.height = 96;
    c.sem.optics.pixel_size_um = 0.25;
    c.stage.start_tilt_deg = 2.0;
    c.stage.start_x_um = 5.0;
    let mut shark = SharkSemSimConfig::default();
    tweak(&mut shark, &mut c);
    c.sharksem = Some(shark);
    Simulator::spawn(c).unwrap()
}

fn config(sim: &SimHandle) -> ImagingConfig {
    ImagingConfig {
        protocol: ImagingProtocol::Sharksem,
        endpoint: sim.sharksem_endpoint().to_owned(),
        timeout_ms: 2000,
        micrograph: ScanSettings {
            width: 128,
            height: 96,
            dwell_us: 2.0,
        },
        tracking: ScanSettings {
            width: 32,
            height: 24,
            dwell_us: 0.5,
        },
        ..ImagingConfig::default()
    }
}

async fn connect(cfg: &ImagingConfig) -> (SharkSemSource, String, Arc<MemoryObserver>) {
    let observer = Arc::new(MemoryObserver::default());
    let (source, id) = SharkSemSource::connect(cfg, Some(0.0), observer.clone())
        .await
        .unwrap();
    (source, id, observer)
}

fn commands(observer: &MemoryObserver) -> Vec<String> {
    observer
        .io_records()
        .into_iter()
        .filter_map(|r: StageIo| r.command)
        .collect()
}

#[tokio::test]
async fn sets_up_the_data_channel_and_grabs_verified_frames() {
    let sim = sim(|_, _| {});
    let cfg = config(&sim);
    let (source, id, observer) = connect(&cfg).await;
    assert!(
        id.starts_with("TESCAN SharkSEM 2.0.25, software sdsem-sim"),
        "{id}"
    );
    // Chosen by configuration: the acquisition sees only the trait.
    let mut source: Box<dyn FrameSource> = Box::new(source);
    let left = source.grab(cfg.request(Role::Left)).await.unwrap();
    assert_eq!(
        (left.width, left.height, left.role()),
        (128, 96, Role::Left)
    );
    let Pixels::U16(px) = &left.pixels else {
        panic!("16-bit")
    };
    assert_eq!(px.len(), 128 * 96);
    let (lo, hi) = left.to_image().finite_range().unwrap();
    assert!(hi - lo > 0.2, "contrast {lo}..{hi}");
    // No pixel size configured: the SEM's field (0.25 µm × 128 = 0.032 mm) read back.
    assert!((left.pixel_size_um() - 0.25).abs() < 1e-12);
    assert_eq!((left.tilt_deg(), left.meta.stage_x_um), (2.0, 5.0));
    assert_eq!(left.meta.dwell_us, 2.0);
    let rendered = sim.frame(sim.last_frame().unwrap()).unwrap();
    assert_eq!(rendered.view.width, 128);
    assert!((rendered.view.pixel_size_um - 0.25).abs() < 1e-12);
    // A tracking frame has the micrograph's field: four times the pixel.
    let track = source.grab(cfg.request(Role::Tracking)).await.unwrap();
    assert!((track.pixel_size_um() - 1.0).abs() < 1e-12);
    assert_eq!(track.meta.frame, left.meta.frame + 1);

    let cmds = commands(&observer);
    let pos = |prefix: &str| {
        cmds.iter()
            .position(|c| c.starts_with(prefix))
            .unwrap_or(usize::MAX)
    };
    assert!(
        pos("TcpGetVersion()") < pos("TcpRegDataPort(port="),
        "{cmds:?}"
    );
    assert!(
        cmds.contains(&"DtSelect(channel=0, detector=10)".to_owned()),
        "{cmds:?}"
    );
    assert!(cmds.contains(&"DtEnable(channel=0, enable=1, bpp=16)".to_owned()));
    assert!(cmds.contains(
        &"ScScanXY(frame=1, width=128, height=96, left=0, top=0, right=127, bottom=95, single=1, dwell_ns=2000) [wait-B]"
            .to_owned()
    ));
    // Every scan is followed by its data and by ScStopScan.
    let scans: Vec<usize> = cmds
        .iter()
        .enumerate()
        .filter(|(_, c)| c.starts_with("ScScanXY"))
        .map(|(i, _)| i)
        .collect();
    assert_eq!(scans.len(), 2);
    for i in scans {
        assert!(cmds[i + 1].starts_with("ScData(frame="), "{cmds:?}");
        assert_eq!(cmds[i + 2], "ScStopScan()");
    }
    let records = observer.io_records();
    let data = records
        .iter()
        .find(|r| r.command.as_deref() == Some("ScData(frame=1, channel=0)"))
        .unwrap();
    assert_eq!(data.outcome, IoOutcome::Replied);
    assert!(
        data.reply
            .as_deref()
            .unwrap()
            .starts_with("12288 of 12288 pixels"),
        "{data:?}"
    );
    let field = records
        .iter()
        .find(|r| r.command.as_deref() == Some("GetViewField() [wait-C]"))
        .unwrap();
    assert_eq!(field.reply.as_deref(), Some("0.032 mm"));
    assert!(field.rtt_ns.is_some());
}

#[tokio::test]
async fn a_configured_pixel_size_is_set_and_an_ignored_setting_re_sent() {
    let sim = sim(|s, _| s.faults.ignore_view_field = FaultTrigger::at([1]));
    let mut cfg = config(&sim);
    cfg.pixel_size_um = Some(0.5);
    let (mut source, _, observer) = connect(&cfg).await;
    let f = source.grab_frame(cfg.request(Role::Left)).await.unwrap();
    assert!((f.pixel_size_um() - 0.5).abs() < 1e-12);
    assert!((sim.sharksem().unwrap().view_field_mm() - 0.064).abs() < 1e-15);
    assert_eq!(sim.sharksem().unwrap().counts().ignored_view_fields, 1);
    let sets = commands(&observer)
        .into_iter()
        .filter(|c| c == "SetViewField(mm=0.064)")
        .count();
    assert_eq!(sets, 2, "ignored once, re-sent once");
    // Taken now: the next frame reads it back and sets nothing.
    source
        .grab_frame(cfg.request(Role::Tracking))
        .await
        .unwrap();
    let sets = commands(&observer)
        .iter()
        .filter(|c| c.starts_with("SetViewField"))
        .count();
    assert_eq!(sets, 2);
}

#[tokio::test]
async fn a_setting_ignored_twice_stops_with_the_cause() {
    let sim = sim(|s, _| s.faults.ignore_view_field = FaultTrigger::at([1, 2]));
    let mut cfg = config(&sim);
    cfg.pixel_size_um = Some(0.5);
    let (mut source, _, _) = connect(&cfg).await;
    let e = source
        .grab_frame(cfg.request(Role::Left))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("did not take the view field = 0.064 mm") && e.contains("reads back 0.032 mm"),
        "{e}"
    );
    assert!(e.contains("imaging.pixel_size_um"), "{e}");
}

fn data_records(observer: &MemoryObserver) -> Vec<StageIo> {
    observer
        .io_records()
        .into_iter()
        .filter(|r| {
            r.command
                .as_deref()
                .is_some_and(|c| c.starts_with("ScData"))
        })
        .collect()
}

#[tokio::test]
async fn a_lost_chunk_fails_the_frame_which_is_taken_again() {
    // 2 µs dwell, 2 ms chunks: 1000 pixels a chunk, 13 chunks a frame.
    let sim = sim(|s, _| {
        s.chunk_interval_s = 0.002;
        s.faults.lose_chunk = FaultTrigger::at([2]);
    });
    let cfg = config(&sim);
    let (mut source, _, observer) = connect(&cfg).await;
    let f = source.grab_frame(cfg.request(Role::Left)).await.unwrap();
    assert_eq!(f.width * f.height, 12288);
    let data = data_records(&observer);
    assert_eq!(data.len(), 2);
    assert_eq!(data[0].outcome, IoOutcome::Garbled);
    let detail = data[0].detail.as_deref().unwrap();
    assert!(
        detail
            .contains("chunk was lost: 1000 pixels received, the next chunk starts at pixel 2000"),
        "{detail}"
    );
    assert_eq!(data[1].outcome, IoOutcome::Replied);
    // ScStopScan after the failed scan too.
    let cmds = commands(&observer);
    let stops_after_scans = cmds
        .windows(2)
        .filter(|w| w[0].starts_with("ScData") && w[1] == "ScStopScan()")
        .count();
    assert_eq!(stops_after_scans, 2, "{cmds:?}");
    let counts = sim.sharksem().unwrap().counts();
    assert_eq!((counts.lost_chunks, counts.scans), (1, 2));
}

#[tokio::test]
async fn a_resent_chunk_is_truncated_and_appended() {
    let sim = sim(|s, _| {
        s.chunk_interval_s = 0.002;
        s.faults.resend_chunk = FaultTrigger::at([3]);
    });
    let cfg = config(&sim);
    let (mut source, _, observer) = connect(&cfg).await;
    let f = source.grab_frame(cfg.request(Role::Left)).await.unwrap();
    let data = data_records(&observer);
    assert_eq!(data.len(), 1, "no retry");
    assert!(
        data[0]
            .reply
            .as_deref()
            .unwrap()
            .contains("in 14 chunks, 1 re-sent"),
        "{:?}",
        data[0]
    );
    // The pixels are the simulator's render, re-send or not: compare with a clean second frame.
    let again = source.grab_frame(cfg.request(Role::Left)).await.unwrap();
    let (Pixels::U16(a), Pixels::U16(b)) = (&f.pixels, &again.pixels) else {
        panic!()
    };
    let differ = a
        .iter()
        .zip(b)
        .filter(|(x, y)| x.abs_diff(**y) > 20_000)
        .count();
    assert!(
        differ < a.len() / 50,
        "{differ} pixels far apart: the re-send garbled the frame"
    );
}

#[tokio::test]
async fn a_chunk_lost_twice_names_the_cause() {
    let sim = sim(|s, _| {
        s.chunk_interval_s = 0.002;
        // The 2nd chunk of frame 1, and whichever chunk the 2nd of frame 2 is (frame 1
        // streams 3 to 13 chunks before its ScStopScan arrives).
        s.faults.lose_chunk = FaultTrigger::at([2, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15]);
    });
    let cfg = config(&sim);
    let (mut source, _, _) = connect(&cfg).await;
    let e = source
        .grab_frame(cfg.request(Role::Left))
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("frame 2") && e.contains("chunk was lost"), "{e}");
}

#[tokio::test]
async fn a_dropped_connection_is_set_up_again_and_the_frame_retaken() {
    // Set-up: 4 requests; the first frame's 8th (StgGetPosition) is the 12th.
    let sim = sim(|s, _| s.faults.disconnect_after_requests = Some(12));
    let cfg = config(&sim);
    let (mut source, _, observer) = connect(&cfg).await;
    for _ in 0..3 {
        source
            .grab_frame(cfg.request(Role::Tracking))
            .await
            .unwrap();
    }
    assert_eq!(sim.sharksem().unwrap().counts().disconnects, 1);
    let regs = commands(&observer)
        .iter()
        .filter(|c| c.starts_with("TcpRegDataPort"))
        .count();
    assert_eq!(regs, 2, "the session was set up again");
}

#[tokio::test]
async fn a_silent_server_times_out_naming_the_function() {
    let sim = sim(|s, _| s.faults.silent_after_requests = Some(6));
    let mut cfg = config(&sim);
    cfg.timeout_ms = 200;
    let (mut source, _, _) = connect(&cfg).await;
    let e = source
        .grab_frame(cfg.request(Role::Left))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("did not answer") && e.contains("within 200ms"),
        "{e}"
    );
    assert!(e.contains("ignores requests it does not accept"), "{e}");
    assert!(e.contains("raise imaging.timeout_ms"), "{e}");
}

#[tokio::test]
async fn detectors_are_chosen_by_name_or_id_and_a_wrong_one_is_named() {
    let sim = sim(|_, _| {});
    let mut cfg = config(&sim);
    cfg.detector = "bse".into();
    let (mut source, _, observer) = connect(&cfg).await;
    source
        .grab_frame(cfg.request(Role::Tracking))
        .await
        .unwrap();
    assert!(commands(&observer).contains(&"DtSelect(channel=0, detector=11)".to_owned()));
    cfg.detector = "LVSTD".into();
    let (mut source, _, _) = connect(&cfg).await;
    let e = source
        .grab_frame(cfg.request(Role::Tracking))
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("no detector \"LVSTD\"") && e.contains("SE (id 10), BSE (id 11)"),
        "{e}"
    );
}

#[tokio::test]
async fn eight_bit_frames_are_enabled_and_checked() {
    let sim = sim(|_, _| {});
    let mut cfg = config(&sim);
    cfg.bits = 8;
    let (mut source, _, observer) = connect(&cfg).await;
    let f = source
        .grab_frame(cfg.request(Role::Tracking))
        .await
        .unwrap();
    assert!(matches!(f.pixels, Pixels::U8(ref v) if v.len() == 32 * 24));
    assert!(commands(&observer).contains(&"DtEnable(channel=0, enable=1, bpp=8)".to_owned()));
}

#[tokio::test]
async fn set_up_problems_are_named() {
    let sim = sim(|s, _| s.version = "2.0.5".into());
    let cfg = config(&sim);
    let observer = Arc::new(MemoryObserver::default());
    let e = SharkSemSource::connect(&cfg, Some(0.0), observer.clone())
        .await
        .unwrap_err();
    assert!(
        e.to_string().contains("protocol 2.0.5") && e.to_string().contains("2.0.6"),
        "{e}"
    );
    let e = SharkSemSource::connect(&cfg, None, observer.clone())
        .await
        .unwrap_err();
    assert!(
        e.to_string().contains("reconstruction.tilt_axis_deg"),
        "{e}"
    );
    let mut wrong = cfg.clone();
    wrong.data_port = Some(1);
    let e = SharkSemSource::connect(&wrong, Some(0.0), observer.clone())
        .await
        .unwrap_err();
    assert!(
        e.to_string().contains("data channel") && e.to_string().contains("imaging.data_port"),
        "{e}"
    );
    let closed = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap()
    };
    wrong.endpoint = format!("tcp://{closed}");
    let e = SharkSemSource::connect(&wrong, Some(0.0), observer)
        .await
        .unwrap_err();
    assert!(e.to_string().contains("remote control enabled"), "{e}");
}
