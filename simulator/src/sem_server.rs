//! The simulated SEM's imaging link: the protocol of [`sdsem_protocol::sem`]
//! over TCP, answered by a [`SimSem`]. This module only moves bytes.
//!
//! - One client at a time; the next one is accepted when it disconnects. The
//!   server runs on its own thread and notices the stop flag within 100 ms
//!   (a scan in progress is cut short).
//! - [`crate::Simulator::spawn`] starts it beside the stage, looking at the
//!   simulated stage. [`spawn`] and [`spawn_with_scene`] start it alone, on a
//!   listener of the caller's, looking at any [`PoseSource`] (a
//!   [`crate::pose::FixedPose`] in tests).

use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use sdsem_protocol::sem::{Reply, RequestDecoder};

use crate::SimError;
use crate::clock::Clock;
use crate::config::SemSimConfig;
use crate::pose::PoseSource;
use crate::scene::Scene;
pub use crate::sem::FrameRecord;
use crate::sem::SimSem;
use crate::simulator::ServiceServer;

/// How often a blocked read looks at the stop flag.
const STOP_POLL: Duration = Duration::from_millis(100);

/// Listens on `addr` (port 0 picks one) and serves `sem` from a new thread.
pub(crate) fn serve_tcp(
    addr: SocketAddr,
    sem: Arc<SimSem>,
    stop: Arc<AtomicBool>,
) -> Result<ServiceServer, SimError> {
    let bind = |error| SimError::Bind {
        service: "SEM imaging",
        addr,
        error,
    };
    let listener = TcpListener::bind(addr).map_err(bind)?;
    let local = listener.local_addr().map_err(bind)?;
    serve_listener(listener, local, sem, stop)
}

/// Serves `sem` on `listener` (bound at `local`, blocking) from a new thread
/// until `stop` is set.
fn serve_listener(
    listener: TcpListener,
    local: SocketAddr,
    sem: Arc<SimSem>,
    stop: Arc<AtomicBool>,
) -> Result<ServiceServer, SimError> {
    let wake = if local.ip().is_unspecified() {
        SocketAddr::from(([127, 0, 0, 1], local.port()))
    } else {
        local
    };
    let thread = std::thread::Builder::new()
        .name("sem-server".to_owned())
        .spawn(move || accept_loop(&listener, &sem, &stop))
        .map_err(|error| SimError::Thread { error })?;
    tracing::info!(%local, "SEM imaging server listening on TCP");
    Ok(ServiceServer {
        endpoint: format!("tcp://{local}"),
        thread,
        wake: Some(wake),
    })
}

fn accept_loop(listener: &TcpListener, sem: &SimSem, stop: &AtomicBool) {
    for stream in listener.incoming() {
        if stop.load(Ordering::Relaxed) {
            return;
        }
        match stream {
            Ok(stream) => {
                let peer = stream.peer_addr().ok();
                tracing::debug!(?peer, "SEM link: client connected");
                if let Err(e) = session(stream, sem, stop) {
                    tracing::info!(?peer, error = %e, "SEM client connection ended");
                }
            }
            Err(e) => {
                tracing::warn!(error = %e, "SEM server accept failed");
                std::thread::sleep(Duration::from_millis(50));
            }
        }
        if stop.load(Ordering::Relaxed) {
            return;
        }
    }
}

/// Serves one client until it disconnects or the server stops.
fn session(mut stream: TcpStream, sem: &SimSem, stop: &AtomicBool) -> io::Result<()> {
    stream.set_read_timeout(Some(STOP_POLL))?;
    stream.set_nodelay(true)?;
    let mut decoder = RequestDecoder::new();
    let mut buf = vec![0u8; 4096];
    loop {
        while let Some(request) = decoder.next_request() {
            let reply = match request {
                Ok(request) => sem.handle(&request, stop),
                Err(e) => Reply::Error {
                    code: e.code(),
                    message: e.to_string(),
                },
            };
            let (head, payload) = reply.encode();
            stream.write_all(&head)?;
            stream.write_all(payload)?;
            stream.flush()?;
        }
        if stop.load(Ordering::Relaxed) {
            return Ok(());
        }
        match stream.read(&mut buf) {
            Ok(0) => return Ok(()),
            Ok(n) => decoder.push(&buf[..n]),
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) => {}
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
}

/// A SEM imaging server running alone. Dropping it stops the server and
/// waits for its thread.
pub struct SemServerHandle {
    addr: SocketAddr,
    sem: Arc<SimSem>,
    stop: Arc<AtomicBool>,
    server: Option<ServiceServer>,
}

impl std::fmt::Debug for SemServerHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SemServerHandle")
            .field("addr", &self.addr)
            .finish_non_exhaustive()
    }
}

/// Builds the scene of `cfg` (about a second for the default 200 µm field)
/// and serves on `listener` from a new thread, on `clock` (its time scale
/// sets how long scans take). `cfg.endpoint` is not used.
///
/// # Errors
/// [`SimError`] for an invalid configuration or listener.
pub fn spawn(
    listener: TcpListener,
    pose: Arc<dyn PoseSource>,
    cfg: &SemSimConfig,
    clock: Arc<dyn Clock>,
) -> Result<SemServerHandle, SimError> {
    cfg.validate()?;
    let cfg = cfg.resolved(0);
    let scene = Arc::new(Scene::generate(&cfg.scene)?);
    spawn_with_scene(listener, pose, &cfg, scene, clock)
}

/// [`spawn`] with a scene already built (`cfg.scene` is then not used).
///
/// # Errors
/// [`SimError`] for an invalid configuration or listener.
pub fn spawn_with_scene(
    listener: TcpListener,
    pose: Arc<dyn PoseSource>,
    cfg: &SemSimConfig,
    scene: Arc<Scene>,
    clock: Arc<dyn Clock>,
) -> Result<SemServerHandle, SimError> {
    cfg.validate()?;
    let listener_error = |error| SimError::Listener {
        service: "SEM imaging",
        error,
    };
    listener.set_nonblocking(false).map_err(listener_error)?;
    let addr = listener.local_addr().map_err(listener_error)?;
    let sem = Arc::new(SimSem::new(cfg, scene, pose, clock));
    let stop = Arc::new(AtomicBool::new(false));
    let server = serve_listener(listener, addr, Arc::clone(&sem), Arc::clone(&stop))?;
    Ok(SemServerHandle {
        addr,
        sem,
        stop,
        server: Some(server),
    })
}

impl SemServerHandle {
    /// Where the server listens.
    #[must_use]
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// The simulated SEM behind the link.
    #[must_use]
    pub fn sem(&self) -> &Arc<SimSem> {
        &self.sem
    }

    /// The specimen being imaged.
    #[must_use]
    pub fn scene(&self) -> &Arc<Scene> {
        self.sem.scene()
    }

    /// How frame number `frame` was taken, if it is still remembered.
    #[must_use]
    pub fn frame(&self, frame: u64) -> Option<FrameRecord> {
        self.sem.frame(frame)
    }

    /// The true height map (µm, row-major, NaN off the specimen) of frame `frame`.
    #[must_use]
    pub fn ground_truth(&self, frame: u64) -> Option<Vec<f32>> {
        self.sem.ground_truth(frame)
    }

    /// Stops serving and waits for the server thread.
    pub fn shutdown(mut self) {
        self.stop_server();
    }

    fn stop_server(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(server) = self.server.take() {
            server.join();
        }
    }
}

impl Drop for SemServerHandle {
    fn drop(&mut self) {
        self.stop_server();
    }
}

#[cfg(test)]
mod tests {
    use sdsem_protocol::sem::{
        Bits, ErrorCode, FrameReply, GrabRequest, ReplyDecoder, Request, Role,
    };

    use super::*;
    use crate::clock::ManualClock;
    use crate::pose::{FixedPose, StagePose};
    use crate::render::{self, OpticsParams, ShadingParams};
    use crate::scene::{SceneKind, SceneParams};
    use crate::walk::WalkParams;

    struct Rig {
        handle: SemServerHandle,
        pose: Arc<FixedPose>,
        clock: Arc<ManualClock>,
        stream: TcpStream,
        decoder: ReplyDecoder,
    }

    fn rig(cfg: SemSimConfig, time_scale: f64) -> Rig {
        let scene = Arc::new(
            Scene::generate(&SceneParams {
                kind: SceneKind::Grid,
                seed: Some(2),
                field_um: 60.0,
                sample_um: 0.1,
            })
            .unwrap(),
        );
        let pose = Arc::new(FixedPose::default());
        let clock = Arc::new(ManualClock::with_time_scale(time_scale));
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let handle = spawn_with_scene(listener, pose.clone(), &cfg, scene, clock.clone()).unwrap();
        let stream = TcpStream::connect(handle.local_addr()).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(20)))
            .unwrap();
        Rig {
            handle,
            pose,
            clock,
            stream,
            decoder: ReplyDecoder::new(),
        }
    }

    impl Rig {
        fn ask(&mut self, request: &Request) -> Reply {
            self.stream.write_all(&request.encode()).unwrap();
            self.ask_raw(b"")
        }

        fn ask_raw(&mut self, bytes: &[u8]) -> Reply {
            self.stream.write_all(bytes).unwrap();
            let mut buf = vec![0u8; 65536];
            loop {
                if let Some(r) = self.decoder.next_reply().unwrap() {
                    return r;
                }
                let n = self.stream.read(&mut buf).unwrap();
                assert!(n > 0, "server closed the connection");
                self.decoder.push(&buf[..n]);
            }
        }

        fn grab(&mut self, width: u32, height: u32, dwell_us: f64, role: Role) -> FrameReply {
            match self.ask(&Request::Grab(GrabRequest {
                width,
                height,
                dwell_us,
                role,
                bits: Bits::Sixteen,
            })) {
                Reply::Frame(f) => f,
                other => panic!("{other:?}"),
            }
        }
    }

    fn cfg() -> SemSimConfig {
        SemSimConfig {
            optics: OpticsParams {
                width: 160,
                height: 120,
                pixel_size_um: 0.2,
                ..OpticsParams::default()
            },
            ..SemSimConfig::default()
        }
    }

    #[test]
    fn identifies_and_reports_pixel_size() {
        let mut rig = rig(cfg(), 1.0);
        let Reply::Identity(id) = rig.ask(&Request::Identify) else {
            panic!()
        };
        assert!(id.starts_with("sdsem,virtual-sem"));
        assert_eq!(
            rig.ask(&Request::PixelSize { width: 80 }),
            Reply::PixelSize {
                width: 80,
                pixel_size_um: 0.4
            }
        );
    }

    #[test]
    fn grab_renders_at_the_stage_pose_and_takes_the_scan_time() {
        // Four times faster than real time.
        let mut rig = rig(cfg(), 0.25);
        rig.pose.set(StagePose {
            x_um: 2.0,
            y_um: -1.0,
            tilt_deg: 7.0,
        });
        let f = rig.grab(160, 120, 2.0, Role::Left);
        assert_eq!((f.width, f.height, f.bits), (160, 120, Bits::Sixteen));
        assert_eq!(f.data.len(), 160 * 120 * 2);
        assert_eq!(f.meta.frame, 1);
        assert_eq!(f.meta.role, Role::Left);
        assert_eq!(
            (f.meta.stage_x_um, f.meta.stage_y_um, f.meta.tilt_deg),
            (2.0, -1.0, 7.0)
        );
        assert!((f.meta.pixel_size_um - 0.2).abs() < 1e-12);
        // 160 × 120 × 2 µs = 38.4 ms of simulated scan, at 4× speed: 9.6 ms
        // of wall clock between the timestamps.
        assert!((rig.clock.now_s() - 0.0384).abs() < 1e-12);
        assert_eq!(
            f.meta.scan_end_unix_ns - f.meta.scan_start_unix_ns,
            9_600_000
        );
        // The pixels are the renderer's for the same view.
        let record = rig.handle.frame(1).unwrap();
        assert_eq!(record.view.tilt_deg, 7.0);
        // 5 px/° of the full-resolution 0.2 µm pixels.
        let walk = WalkParams {
            seed: rig.handle.sem().config().walk.seed,
            ..WalkParams::default()
        }
        .offset_um(7.0, 0.2);
        assert!(walk[0].hypot(walk[1]) > 3.0, "{walk:?}");
        assert!((record.view.offset_um[0] - (-2.0 + walk[0])).abs() < 1e-12);
        assert!((record.view.offset_um[1] - (1.0 + walk[1])).abs() < 1e-12);
        let clean = render::render(rig.handle.scene(), &record.view, &ShadingParams::default());
        let samples: Vec<f64> = f
            .samples_u16()
            .iter()
            .map(|&v| f64::from(v) / 65535.0)
            .collect();
        let n = clean.len() as f64;
        let bias = samples
            .iter()
            .zip(&clean)
            .map(|(&a, &b)| a - f64::from(b))
            .sum::<f64>()
            / n;
        assert!(
            bias.abs() < 0.01,
            "frame is offset from its render by {bias}"
        );
        // Same content up to scan noise: strongly correlated.
        let (ma, mb) = (
            samples.iter().sum::<f64>() / n,
            clean.iter().map(|&v| f64::from(v)).sum::<f64>() / n,
        );
        let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
        for (&a, &b) in samples.iter().zip(&clean) {
            let (da, db) = (a - ma, f64::from(b) - mb);
            sab += da * db;
            saa += da * da;
            sbb += db * db;
        }
        let ncc = sab / (saa * sbb).sqrt();
        assert!(ncc > 0.6, "frame and render correlate only {ncc}");
        // Frame numbers count up; a tracking frame of quarter size has 4× the pixel size.
        let t = rig.grab(40, 30, 0.5, Role::Tracking);
        assert_eq!(t.meta.frame, 2);
        assert!((t.meta.pixel_size_um - 0.8).abs() < 1e-12);
    }

    #[test]
    fn eight_bit_frames_and_errors() {
        let mut rig = rig(cfg(), 0.01);
        let Reply::Frame(f) = rig.ask_raw(b"GRAB 16 8 1 right 8\n") else {
            panic!()
        };
        assert_eq!((f.bits, f.data.len()), (Bits::Eight, 128));
        let Reply::Error { code, message } = rig.ask_raw(b"ZOOM 3\n") else {
            panic!()
        };
        assert_eq!(code, ErrorCode::UnknownCommand);
        assert!(message.contains("ZOOM"));
        let Reply::Error { code, .. } = rig.ask_raw(b"GRAB 16 8 -1 right\n") else {
            panic!()
        };
        assert_eq!(code, ErrorCode::BadArgument);
        let Reply::Error { code, message } = rig.ask(&Request::GroundTruth {
            frame: 9,
            path: None,
        }) else {
            panic!()
        };
        assert_eq!(code, ErrorCode::UnknownFrame);
        assert!(message.contains("frames 1 to 1 are known"), "{message}");
    }

    #[test]
    fn ground_truth_over_the_link_and_to_a_file() {
        let mut rig = rig(cfg(), 0.01);
        rig.pose.set(StagePose {
            tilt_deg: -4.0,
            ..StagePose::default()
        });
        let f = rig.grab(64, 48, 1.0, Role::Left);
        let Reply::HeightMap(h) = rig.ask(&Request::GroundTruth {
            frame: f.meta.frame,
            path: None,
        }) else {
            panic!()
        };
        assert_eq!((h.width, h.height), (64, 48));
        assert_eq!(h.meta, f.meta);
        let heights = h.heights();
        let expect = rig.handle.ground_truth(f.meta.frame).unwrap();
        assert_eq!(heights.len(), expect.len());
        assert!(
            heights
                .iter()
                .zip(&expect)
                .all(|(a, b)| a.to_bits() == b.to_bits())
        );
        // The grid's bars stand ~15 µm above the floor.
        let (lo, hi) = heights
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        assert!(hi - lo > 10.0, "relief {lo}..{hi}");

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("truth map.gsf");
        let reply = rig.ask(&Request::GroundTruth {
            frame: f.meta.frame,
            path: Some(path.display().to_string()),
        });
        assert!(matches!(reply, Reply::Ok(_)), "{reply:?}");
        let bytes = std::fs::read(&path).unwrap();
        let header_end = bytes.iter().position(|&b| b == 0).unwrap();
        let header = std::str::from_utf8(&bytes[..header_end]).unwrap();
        assert!(header.starts_with("Gwyddion Simple Field 1.0\n"));
        assert!(header.lines().any(|l| l == "XRes = 64"));
        // 1–4 NUL bytes pad the header to a multiple of 4.
        let data_start = (header_end / 4 + 1) * 4;
        assert!(bytes[header_end..data_start].iter().all(|&b| b == 0));
        assert_eq!(bytes.len() - data_start, 64 * 48 * 4);
        let first = f32::from_le_bytes(bytes[data_start..data_start + 4].try_into().unwrap());
        assert!((first - expect[0] * 1e-6).abs() < 1e-12);
    }

    #[test]
    fn a_second_client_is_served_after_the_first_leaves() {
        let mut rig = rig(cfg(), 0.01);
        assert!(matches!(rig.ask(&Request::Identify), Reply::Identity(_)));
        let addr = rig.handle.local_addr();
        drop(std::mem::replace(
            &mut rig.stream,
            TcpStream::connect(addr).unwrap(),
        ));
        rig.stream
            .set_read_timeout(Some(Duration::from_secs(20)))
            .unwrap();
        assert!(matches!(rig.ask(&Request::Identify), Reply::Identity(_)));
    }

    #[test]
    fn rejects_a_bad_configuration() {
        let scene = Arc::new(
            Scene::generate(&SceneParams {
                field_um: 10.0,
                ..SceneParams::default()
            })
            .unwrap(),
        );
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let mut bad = cfg();
        bad.optics.pixel_size_um = -1.0;
        let err = spawn_with_scene(
            listener,
            Arc::new(FixedPose::default()),
            &bad,
            scene,
            Arc::new(ManualClock::new()),
        )
        .unwrap_err();
        assert!(err.to_string().contains("pixel_size_um"), "{err}");
    }

    #[test]
    fn stopping_cuts_a_long_scan_short() {
        let scene = Arc::new(
            Scene::generate(&SceneParams {
                field_um: 10.0,
                ..SceneParams::default()
            })
            .unwrap(),
        );
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        // Real time: a 16 × 16 frame at 10 ms dwell scans for 2.56 s.
        let handle = spawn_with_scene(
            listener,
            Arc::new(FixedPose::default()),
            &cfg(),
            scene,
            Arc::new(crate::clock::ScaledClock::new(1.0)),
        )
        .unwrap();
        let mut stream = TcpStream::connect(handle.local_addr()).unwrap();
        stream.write_all(b"GRAB 16 16 10000 tracking\n").unwrap();
        std::thread::sleep(Duration::from_millis(100));
        let t = std::time::Instant::now();
        handle.shutdown();
        assert!(t.elapsed() < Duration::from_secs(2), "{:?}", t.elapsed());
    }

    #[test]
    fn config_has_documented_defaults_and_denies_unknown_keys() {
        let c: SemSimConfig =
            serde_json::from_str(r#"{"scene":{"kind":"rough"},"optics":{"tilt_axis_deg":30}}"#)
                .unwrap();
        assert_eq!(c.scene.field_um, 200.0);
        assert_eq!(c.optics.tilt_axis_deg, 30.0);
        assert_eq!(c.optics.pixel_size_um, 0.1);
        assert!(serde_json::from_str::<SemSimConfig>(r#"{"optics":{"pixel":1}}"#).is_err());
    }
}
