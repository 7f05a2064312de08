use std::io::{Read, Write};
use std::net::TcpListener;
use std::sync::Arc;

use sdsem_sim::pose::StagePose;
use sdsem_sim::render::OpticsParams;
use sdsem_sim::scene::{Scene, SceneKind, SceneParams};
use sdsem_sim::sem_server::{self, FixedPose, SemServerHandle, SemSimConfig, SystemClock};

use super::*;
use crate::imaging::{Pixels, Role};

fn server() -> (SemServerHandle, Arc<FixedPose>) {
    let scene = Scene::generate(&SceneParams {
        kind: SceneKind::Particles,
        seed: 4,
        field_um: 50.0,
        sample_um: 0.1,
    })
    .unwrap();
    let cfg = SemSimConfig {
        optics: OpticsParams {
            width: 128,
            height: 96,
            pixel_size_um: 0.25,
            ..OpticsParams::default()
        },
        ..SemSimConfig::default()
    };
    let pose = Arc::new(FixedPose::new(StagePose {
        x_um: 1.0,
        y_um: 2.0,
        tilt_deg: -3.0,
    }));
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let handle = sem_server::spawn_with_scene(
        listener,
        pose.clone(),
        cfg,
        Arc::new(scene),
        1000.0,
        Arc::new(SystemClock),
    )
    .unwrap();
    (handle, pose)
}

fn config(endpoint: String) -> ImagingConfig {
    let mut cfg = ImagingConfig {
        endpoint,
        timeout_ms: 3000,
        ..ImagingConfig::default()
    };
    cfg.micrograph = crate::imaging::ScanSettings {
        width: 128,
        height: 96,
        dwell_us: 4.0,
    };
    cfg.tracking = crate::imaging::ScanSettings {
        width: 32,
        height: 24,
        dwell_us: 0.5,
    };
    cfg
}

#[tokio::test]
async fn grabs_frames_and_ground_truth_from_the_simulator() {
    let (handle, pose) = server();
    let cfg = config(handle.local_addr().to_string());
    let (client, id) = SemLinkClient::connect(cfg.clone()).await.unwrap();
    assert!(id.starts_with("sdsem,virtual-sem"), "{id}");
    // Chosen by configuration: the acquisition sees only the trait.
    let mut source: Box<dyn FrameSource> = Box::new(client);
    let left = source.grab(cfg.request(Role::Left)).await.unwrap();
    assert_eq!((left.width, left.height), (128, 96));
    assert!(matches!(left.pixels, Pixels::U16(_)));
    assert_eq!(left.role(), Role::Left);
    assert_eq!(left.tilt_deg(), -3.0);
    assert_eq!((left.meta.stage_x_um, left.meta.stage_y_um), (1.0, 2.0));
    assert!((left.pixel_size_um() - 0.25).abs() < 1e-12);
    assert!(left.received_unix_ns >= left.meta.scan_end_unix_ns);
    let img = left.to_image();
    let (lo, hi) = img.finite_range().unwrap();
    assert!(
        lo >= 0.0 && hi <= 1.0 && hi - lo > 0.2,
        "contrast {lo}..{hi}"
    );

    pose.set(StagePose {
        tilt_deg: 0.0,
        ..StagePose::default()
    });
    let track = source.grab(cfg.request(Role::Tracking)).await.unwrap();
    assert_eq!(
        (track.width, track.height, track.meta.frame),
        (32, 24, left.meta.frame + 1)
    );
    assert!(
        (track.pixel_size_um() - 1.0).abs() < 1e-12,
        "quarter width, four times the pixel"
    );

    // One client at a time: the next one is served once this one has gone.
    drop(source);
    let mut client = SemLinkClient::new(cfg).unwrap();
    assert!((client.pixel_size_um(64).await.unwrap() - 0.5).abs() < 1e-12);
    let truth = client.ground_truth(left.meta.frame).await.unwrap();
    assert_eq!((truth.width, truth.height), (128, 96));
    assert_eq!(truth.meta, left.meta);
    let expect = handle.ground_truth(left.meta.frame).unwrap();
    assert!(
        truth
            .heights_um
            .iter()
            .zip(&expect)
            .all(|(a, b)| a.to_bits() == b.to_bits())
    );
}

#[tokio::test]
async fn refusals_name_the_request_and_the_link_goes_on() {
    let (handle, _) = server();
    let mut client = SemLinkClient::new(config(handle.local_addr().to_string())).unwrap();
    let err = client.ground_truth(42).await.unwrap_err();
    let ImagingError::Refused { code, .. } = &err else {
        panic!("{err}")
    };
    assert_eq!(*code, 3);
    let text = err.to_string();
    assert!(
        text.contains("GROUNDTRUTH 42") && text.contains("no frame 42"),
        "{text}"
    );
    assert!(client.identify().await.is_ok());
}

#[tokio::test]
async fn unreachable_server_names_endpoint_and_remedy() {
    let port = {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        l.local_addr().unwrap().port()
    };
    let endpoint = format!("127.0.0.1:{port}");
    let err = SemLinkClient::connect(config(endpoint.clone()))
        .await
        .unwrap_err();
    assert!(matches!(err, ImagingError::Connect { .. }), "{err}");
    let text = err.to_string();
    assert!(
        text.contains(&endpoint) && text.contains("sdsem-sim") && text.contains("imaging.endpoint"),
        "{text}"
    );
}

/// A server that accepts, reads one request and then does `then`.
fn fake_server(then: impl Fn(&mut std::net::TcpStream) + Send + 'static) -> String {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap().to_string();
    std::thread::spawn(move || {
        for stream in listener.incoming() {
            let Ok(mut stream) = stream else { return };
            let mut buf = [0u8; 256];
            let _ = stream.read(&mut buf);
            then(&mut stream);
        }
    });
    addr
}

#[tokio::test]
async fn a_silent_server_times_out_with_advice() {
    let addr = fake_server(|_| std::thread::sleep(std::time::Duration::from_secs(2)));
    let mut cfg = config(addr.clone());
    cfg.timeout_ms = 150;
    let mut client = SemLinkClient::new(cfg).unwrap();
    let err = client.identify().await.unwrap_err();
    assert!(matches!(err, ImagingError::Timeout { .. }), "{err}");
    let text = err.to_string();
    assert!(
        text.contains(&addr) && text.contains("*IDN?") && text.contains("imaging.timeout_ms"),
        "{text}"
    );
}

#[tokio::test]
async fn a_hang_up_and_a_foreign_protocol_are_reported() {
    let addr = fake_server(|s| {
        let _ = s.shutdown(std::net::Shutdown::Both);
    });
    let mut client = SemLinkClient::new(config(addr)).unwrap();
    let err = client.pixel_size_um(10).await.unwrap_err();
    assert!(
        matches!(err, ImagingError::Closed { .. } | ImagingError::Io { .. }),
        "{err}"
    );

    let addr = fake_server(|s| {
        let _ = s.write_all(b"HELLO WORLD\n");
    });
    let mut client = SemLinkClient::new(config(addr)).unwrap();
    let err = client.identify().await.unwrap_err();
    assert!(matches!(err, ImagingError::Protocol { .. }), "{err}");
    assert!(err.to_string().contains("really an SEM imaging server"));
}
