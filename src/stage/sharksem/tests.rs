//! The SharkSEM stage backend under the safety layer, against the in-process simulator.

use std::sync::Arc;

use sdsem_protocol::sharksem::{Flags, Request};
use sdsem_sim::config::FaultTrigger;
use sdsem_sim::scene::SceneKind;
use sdsem_sim::sharksem::SharkSemSimConfig;
use sdsem_sim::{SimConfig, SimHandle, Simulator};

use super::*;
use crate::imaging::{
    FrameSource, ImagingConfig, ImagingProtocol, Role, ScanSettings, SharkSemSource,
};
use crate::stage::{IoOutcome, MemoryObserver, StageDriver};

fn sim(tweak: impl FnOnce(&mut SimConfig)) -> SimHandle {
    let mut c = SimConfig {
        seed: 9,
        time_scale: 0.001,
        sharksem: Some(SharkSemSimConfig::default()),
        ..SimConfig::default()
    };
    c.sem.scene.kind = SceneKind::Grid;
    c.sem.scene.field_um = 60.0;
    c.sem.optics.width = 64;
    c.sem.optics.height = 48;
    c.sem.optics.pixel_size_um = 0.5;
    tweak(&mut c);
    Simulator::spawn(c).unwrap()
}

fn config(sim: &SimHandle) -> StageConfig {
    StageConfig {
        protocol: StageProtocol::Sharksem,
        endpoint: sim.sharksem_endpoint().to_owned(),
        poll_interval_s: 0.005,
        no_motion_timeout_s: 0.2,
        tilt_min_deg: -10.0,
        tilt_max_deg: 80.0,
        ..StageConfig::default()
    }
}

async fn driver(
    sim: &SimHandle,
    config: StageConfig,
) -> (StageDriver<SharkSemBackend>, Arc<MemoryObserver>) {
    let observer = Arc::new(MemoryObserver::default());
    let link = SharkLink::connect(SharkSemBackend::session_config(&config), observer.clone())
        .await
        .unwrap();
    let backend = SharkSemBackend::new(link);
    let d = StageDriver::with_backend(backend, config, observer.clone())
        .await
        .unwrap();
    let _ = sim;
    (d, observer)
}

fn commands(observer: &MemoryObserver) -> Vec<String> {
    observer
        .io_records()
        .into_iter()
        .filter_map(|r| r.command)
        .collect()
}

#[tokio::test]
async fn moves_send_every_axis_rotation_before_tilt_and_are_verified() {
    let sim = sim(|_| {});
    let (mut stage, observer) = driver(&sim, config(&sim)).await;
    assert_eq!(
        stage.limits(StageAxis::Tilt),
        (-5.0, 70.0),
        "narrowed to the SEM's"
    );
    assert_eq!(stage.limits(StageAxis::X), (-5000.0, 5000.0));
    assert_eq!(stage.instrument().vendor, "TESCAN");
    assert_eq!(stage.instrument().serial, "SDSEMSIM0001");
    // Someone rotated the stage: the rotation is re-sent as it is, never zeroed.
    {
        let mut s = stage.backend_mut().link().lock().await;
        let wait = s.config().reply_timeout;
        s.call(
            &Request::StgMoveTo(vec![0.0, 0.0, 10.0, 30.0, 0.0]),
            Flags::NONE,
            wait,
        )
        .await
        .unwrap();
    }
    let report = stage.move_tilt(5.0).await.unwrap();
    assert!(!report.reissued);
    assert!((report.positions[0].1 - 5.0).abs() <= 0.01);
    assert_eq!(sim.stage_snapshot().pose.tilt_deg, 5.0);
    assert_eq!(sim.sharksem().unwrap().rotation_deg(), 30.0);
    stage.move_xy(12.5, -3.0).await.unwrap();
    let pose = sim.stage_snapshot().pose;
    assert_eq!((pose.x_um, pose.y_um, pose.tilt_deg), (12.5, -3.0, 5.0));
    let cmds = commands(&observer);
    assert!(
        cmds.contains(&"StgMoveTo(x=0, y=0, z=10, rotation=30, tilt=5) [wait-B]".to_owned()),
        "{cmds:?}"
    );
    assert!(
        cmds.contains(
            &"StgMoveTo(x=0.0125, y=-0.003, z=10, rotation=30, tilt=5) [wait-B]".to_owned()
        ),
        "{cmds:?}"
    );
    assert!(cmds.iter().any(|c| c == "StgIsBusy()"));
    assert!(cmds.contains(&"StgGetLimits(type=1)".to_owned()));
    let replied = observer
        .io_records()
        .into_iter()
        .find(|r| r.command.as_deref() == Some("StgIsCalibrated()"))
        .unwrap();
    assert_eq!(
        (replied.outcome, replied.reply.as_deref()),
        (IoOutcome::Replied, Some("1"))
    );
    // Outside the narrowed limits: refused before anything is sent.
    let before = observer.io_records().len();
    assert!(stage.move_tilt(75.0).await.is_err());
    assert_eq!(observer.io_records().len(), before);
}

#[tokio::test]
async fn a_silently_ignored_move_is_reissued_once() {
    let sim = sim(|c| c.stage.faults.ignore_move = FaultTrigger::at([1]));
    let (mut stage, observer) = driver(&sim, config(&sim)).await;
    let report = stage.move_tilt(3.0).await.unwrap();
    assert!(report.reissued);
    assert_eq!(sim.stage_snapshot().pose.tilt_deg, 3.0);
    let moves = commands(&observer)
        .iter()
        .filter(|c| c.starts_with("StgMoveTo"))
        .count();
    assert_eq!(moves, 2);
    assert_eq!(sim.stage_snapshot().faults.ignored_moves, 1);
}

#[tokio::test]
async fn a_move_ignored_twice_stops_the_run_with_the_cause() {
    let sim = sim(|c| c.stage.faults.ignore_move = FaultTrigger::at([1, 2]));
    let (mut stage, _) = driver(&sim, config(&sim)).await;
    let e = stage.move_tilt(3.0).await.unwrap_err().to_string();
    assert!(e.contains("StgMoveTo"), "{e}");
    assert_eq!(sim.stage_snapshot().pose.tilt_deg, 0.0);
}

#[tokio::test]
async fn an_uncalibrated_stage_is_refused_at_connect() {
    let sim = sim(|c| c.stage.referenced = false);
    let config = config(&sim);
    let observer = Arc::new(MemoryObserver::default());
    let link = SharkLink::connect(SharkSemBackend::session_config(&config), observer.clone())
        .await
        .unwrap();
    let e = StageDriver::with_backend(SharkSemBackend::new(link), config, observer)
        .await
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("not calibrated") && e.contains("TESCAN software"),
        "{e}"
    );
}

#[tokio::test]
async fn stop_halts_a_move_and_raw_commands_are_refused() {
    let sim = sim(|c| c.time_scale = 0.01);
    let (mut stage, _) = driver(&sim, config(&sim)).await;
    {
        let mut s = stage.backend_mut().link().lock().await;
        let wait = s.config().reply_timeout;
        s.call(
            &Request::StgMoveTo(vec![0.0, 0.0, 10.0, 0.0, 60.0]),
            Flags::NONE,
            wait,
        )
        .await
        .unwrap();
    }
    tokio::time::sleep(std::time::Duration::from_millis(30)).await;
    stage.stop().await.unwrap();
    let t = sim.stage_snapshot().pose.tilt_deg;
    assert!(t > 0.5 && t < 60.0, "{t}");
    tokio::time::sleep(std::time::Duration::from_millis(30)).await;
    assert_eq!(
        sim.stage_snapshot().pose.tilt_deg,
        t,
        "stopped where it was"
    );
    let e = stage.send_trigger("FREC").await.unwrap_err().to_string();
    assert!(
        e.contains("sharksem") && e.contains("imaging.trigger"),
        "{e}"
    );
}

#[tokio::test]
async fn stage_and_imaging_share_one_session() {
    let sim = sim(|_| {});
    let config = config(&sim);
    let observer = Arc::new(MemoryObserver::default());
    let link = SharkLink::connect(SharkSemBackend::session_config(&config), observer.clone())
        .await
        .unwrap();
    let imaging = ImagingConfig {
        protocol: ImagingProtocol::Sharksem,
        endpoint: sim.sharksem_endpoint().to_owned(),
        micrograph: ScanSettings {
            width: 64,
            height: 48,
            dwell_us: 1.0,
        },
        ..ImagingConfig::default()
    };
    let (mut source, _) = SharkSemSource::with_link(link.clone(), &imaging, Some(0.0))
        .await
        .unwrap();
    let mut stage = StageDriver::with_backend(SharkSemBackend::new(link), config, observer.clone())
        .await
        .unwrap();
    stage.move_tilt(4.0).await.unwrap();
    let frame = source.grab(imaging.request(Role::Left)).await.unwrap();
    assert_eq!(frame.tilt_deg(), 4.0);
    stage.move_tilt(0.0).await.unwrap();
    let cmds = commands(&observer);
    let sessions = cmds
        .iter()
        .filter(|c| c.starts_with("TcpRegDataPort"))
        .count();
    assert_eq!(sessions, 1, "one control and one data connection: {cmds:?}");
    assert_eq!(sim.sharksem().unwrap().counts().disconnects, 0);
}
