//! The simulated SEM's imaging server: the protocol of
//! [`sdsem_protocol::sem`] over TCP, frames rendered from a synthetic
//! [`Scene`] at the stage pose of the moment.
//!
//! - One client at a time on the listener given to [`spawn`]; the next one is
//!   accepted when it disconnects. The server runs on its own thread.
//! - `GRAB` asks the [`PoseSource`] for the pose at the start of the scan,
//!   renders the frame (eucentric walk for that tilt, drift for the elapsed
//!   simulated time, shot noise for the dwell), then waits until the scan
//!   time, width × height × dwell divided by the time scale, has passed since
//!   the start (rendering time counts), and replies.
//! - Ground truth: every frame's view is remembered (the last
//!   [`SemSimConfig::history`] frames). `GROUNDTRUTH <frame>` returns its true
//!   height map over the link; `GROUNDTRUTH <frame> <path>` writes it as a
//!   Gwyddion Simple Field file (heights in metres, NaN off the specimen);
//!   in-process, [`SemServerHandle::ground_truth`] and
//!   [`SemServerHandle::frame`] give the same, and with
//!   [`SemServerHandle::scene`] every function of [`crate::render`]
//!   (correspondences between two frames, visible points) applies.
//! - Time is an input: a [`Clock`] gives wall-clock time and sleeps, and
//!   `time_scale` is simulated seconds per real second.

use std::collections::BTreeMap;
use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use sdsem_protocol::sem::{
    Bits, ErrorCode, FrameMeta, FrameReply, GrabRequest, HeightMapReply, Reply, Request,
    RequestDecoder,
};
use serde::{Deserialize, Serialize};

use crate::pose::{PoseSource, StagePose};
use crate::render::{self, NoiseParams, OpticsParams, ShadingParams, View};
use crate::scene::noise::mix64;
use crate::scene::{Scene, SceneError, SceneParams};
use crate::walk::WalkParams;

/// Wall-clock time and sleeping, injected so tests need not wait.
pub trait Clock: Send + Sync {
    /// Now, ns since the Unix epoch.
    fn now_unix_ns(&self) -> u64;
    /// Blocks the calling thread for `d`.
    fn sleep(&self, d: Duration);
}

/// The real clock.
#[derive(Clone, Copy, Debug, Default)]
pub struct SystemClock;

impl Clock for SystemClock {
    fn now_unix_ns(&self) -> u64 {
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
    }

    fn sleep(&self, d: Duration) {
        std::thread::sleep(d);
    }
}

/// A stage that stays where it is put: for tests and for running the SEM
/// server without a stage model.
#[derive(Debug, Default)]
pub struct FixedPose(Mutex<StagePose>);

impl FixedPose {
    #[must_use]
    pub fn new(pose: StagePose) -> Self {
        Self(Mutex::new(pose))
    }

    /// Moves the stage (instantly).
    pub fn set(&self, pose: StagePose) {
        *self.0.lock().unwrap_or_else(PoisonError::into_inner) = pose;
    }
}

impl PoseSource for FixedPose {
    fn pose(&self) -> StagePose {
        *self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// Everything the simulated SEM needs besides its stage.
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `scene` | particles, seed 1, 200 µm | the specimen ([`SceneParams`]) |
/// | `optics` | 1280×960, 0.1 µm, φ = 0 | magnification, tilt axis, scan rotation, stage-to-image mapping ([`OpticsParams`]) |
/// | `walk` | 0.4 µm/° + random | eucentric walk ([`WalkParams`]) |
/// | `shading` | see [`ShadingParams`] | SE contrast |
/// | `noise` | 30 e⁻/µs | scan noise ([`NoiseParams`]) |
/// | `drift_um_per_s` | [0, 0] | slow drift of the specimen in the image plane, µm per simulated second |
/// | `history` | 100 000 | frames whose views are kept for ground truth (~100 bytes each) |
/// | `identity` | `sdsem,virtual-sem,0,<version>` | the `*IDN?` answer |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SemSimConfig {
    pub scene: SceneParams,
    pub optics: OpticsParams,
    pub walk: WalkParams,
    pub shading: ShadingParams,
    pub noise: NoiseParams,
    pub drift_um_per_s: [f64; 2],
    pub history: usize,
    pub identity: String,
}

impl Default for SemSimConfig {
    fn default() -> Self {
        Self {
            scene: SceneParams::default(),
            optics: OpticsParams::default(),
            walk: WalkParams::default(),
            shading: ShadingParams::default(),
            noise: NoiseParams::default(),
            drift_um_per_s: [0.0, 0.0],
            history: 100_000,
            identity: format!("sdsem,virtual-sem,0,{}", env!("CARGO_PKG_VERSION")),
        }
    }
}

/// The SEM server could not start.
#[derive(Debug, thiserror::Error)]
pub enum SemServerError {
    #[error("cannot build the simulated specimen: {0}")]
    Scene(#[from] SceneError),
    #[error("SEM simulator setting {name} = {value} is invalid: {expected}")]
    Invalid {
        name: &'static str,
        value: String,
        expected: &'static str,
    },
    #[error("SEM server listener: {0}")]
    Io(#[from] io::Error),
}

/// A frame the server has scanned: how it was taken.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameRecord {
    pub view: View,
    pub meta: FrameMeta,
}

struct Shared {
    cfg: SemSimConfig,
    scene: Arc<Scene>,
    pose: Arc<dyn PoseSource>,
    clock: Arc<dyn Clock>,
    time_scale: f64,
    start_ns: u64,
    stop: AtomicBool,
    frames: Mutex<Frames>,
}

#[derive(Default)]
struct Frames {
    next: u64,
    records: BTreeMap<u64, FrameRecord>,
}

/// The running server. Dropping it stops the server (and joins its thread).
pub struct SemServerHandle {
    addr: SocketAddr,
    shared: Arc<Shared>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for SemServerHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SemServerHandle")
            .field("addr", &self.addr)
            .finish_non_exhaustive()
    }
}

/// Builds the scene of `cfg` (about a second for the default 200 µm field)
/// and serves on `listener` from a new thread.
///
/// `time_scale` is the simulator's speed-up: simulated seconds per real
/// second (1 = real time, 10 = scans take a tenth of their time).
///
/// # Errors
/// [`SemServerError`] for an invalid configuration or listener.
pub fn spawn(
    listener: TcpListener,
    pose: Arc<dyn PoseSource>,
    cfg: SemSimConfig,
    time_scale: f64,
    clock: Arc<dyn Clock>,
) -> Result<SemServerHandle, SemServerError> {
    let scene = Arc::new(Scene::generate(&cfg.scene)?);
    spawn_with_scene(listener, pose, cfg, scene, time_scale, clock)
}

/// [`spawn`] with a scene already built (`cfg.scene` is then not used).
///
/// # Errors
/// [`SemServerError`] for an invalid configuration or listener.
pub fn spawn_with_scene(
    listener: TcpListener,
    pose: Arc<dyn PoseSource>,
    cfg: SemSimConfig,
    scene: Arc<Scene>,
    time_scale: f64,
    clock: Arc<dyn Clock>,
) -> Result<SemServerHandle, SemServerError> {
    if !(time_scale.is_finite() && time_scale > 0.0) {
        return Err(SemServerError::Invalid {
            name: "time_scale",
            value: time_scale.to_string(),
            expected: "a positive number (simulated seconds per real second)",
        });
    }
    let o = &cfg.optics;
    if !(o.pixel_size_um.is_finite() && o.pixel_size_um > 0.0) || o.width == 0 {
        return Err(SemServerError::Invalid {
            name: "optics.pixel_size_um",
            value: o.pixel_size_um.to_string(),
            expected: "a positive pixel size at a non-zero optics.width",
        });
    }
    listener.set_nonblocking(false)?;
    let addr = listener.local_addr()?;
    let start_ns = clock.now_unix_ns();
    let shared = Arc::new(Shared {
        cfg,
        scene,
        pose,
        clock,
        time_scale,
        start_ns,
        stop: AtomicBool::new(false),
        frames: Mutex::new(Frames {
            next: 1,
            records: BTreeMap::new(),
        }),
    });
    let worker = Arc::clone(&shared);
    let thread = std::thread::Builder::new()
        .name("sem-server".to_owned())
        .spawn(move || serve(&listener, &worker))?;
    Ok(SemServerHandle {
        addr,
        shared,
        thread: Some(thread),
    })
}

impl SemServerHandle {
    /// Where the server listens.
    #[must_use]
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// The specimen being imaged.
    #[must_use]
    pub fn scene(&self) -> &Arc<Scene> {
        &self.shared.scene
    }

    /// How frame number `frame` was taken, if it is still remembered.
    #[must_use]
    pub fn frame(&self, frame: u64) -> Option<FrameRecord> {
        self.shared.frames().records.get(&frame).cloned()
    }

    /// The true height map (µm, row-major, NaN off the specimen) of frame `frame`.
    #[must_use]
    pub fn ground_truth(&self, frame: u64) -> Option<Vec<f32>> {
        let record = self.frame(frame)?;
        Some(render::height_map(&self.shared.scene, &record.view))
    }

    /// Stops serving and waits for the server thread.
    pub fn shutdown(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        // Wake a blocking accept.
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_millis(200));
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for SemServerHandle {
    fn drop(&mut self) {
        self.stop();
    }
}

impl Shared {
    fn frames(&self) -> std::sync::MutexGuard<'_, Frames> {
        self.frames.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn stopped(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }
}

fn serve(listener: &TcpListener, shared: &Shared) {
    for stream in listener.incoming() {
        if shared.stopped() {
            return;
        }
        match stream {
            Ok(stream) => {
                let peer = stream.peer_addr().ok();
                if let Err(e) = session(stream, shared) {
                    tracing::info!(?peer, error = %e, "SEM client connection ended");
                }
            }
            Err(e) => {
                tracing::warn!(error = %e, "SEM server accept failed");
                shared.clock.sleep(Duration::from_millis(50));
            }
        }
        if shared.stopped() {
            return;
        }
    }
}

/// Serves one client until it disconnects or the server stops.
fn session(mut stream: TcpStream, shared: &Shared) -> io::Result<()> {
    stream.set_read_timeout(Some(Duration::from_millis(100)))?;
    stream.set_nodelay(true)?;
    let mut decoder = RequestDecoder::new();
    let mut buf = vec![0u8; 4096];
    loop {
        while let Some(request) = decoder.next_request() {
            let reply = match request {
                Ok(request) => handle(shared, &request),
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
        if shared.stopped() {
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

fn handle(shared: &Shared, request: &Request) -> Reply {
    match request {
        Request::Identify => Reply::Identity(shared.cfg.identity.clone()),
        Request::PixelSize { width } => Reply::PixelSize {
            width: *width,
            pixel_size_um: shared.cfg.optics.pixel_size_at(*width as usize),
        },
        Request::Grab(grab) => Reply::Frame(grab_frame(shared, grab)),
        Request::GroundTruth { frame, path } => ground_truth(shared, *frame, path.as_deref()),
    }
}

fn grab_frame(shared: &Shared, grab: &GrabRequest) -> FrameReply {
    let cfg = &shared.cfg;
    let start = shared.clock.now_unix_ns();
    let pose = shared.pose.pose();
    #[allow(clippy::cast_precision_loss)]
    let sim_seconds = start.saturating_sub(shared.start_ns) as f64 * 1e-9 * shared.time_scale;
    let drift = [
        cfg.drift_um_per_s[0] * sim_seconds,
        cfg.drift_um_per_s[1] * sim_seconds,
    ];
    let (width, height) = (grab.width as usize, grab.height as usize);
    let view = cfg.optics.view(
        &pose,
        width,
        height,
        cfg.walk.offset_um(pose.tilt_deg),
        drift,
    );
    let frame = {
        let mut frames = shared.frames();
        let n = frames.next;
        frames.next += 1;
        n
    };
    let seed = mix64(shared.scene.params().seed ^ mix64(frame));
    let pixels = render::render_noisy(
        &shared.scene,
        &view,
        &cfg.shading,
        &cfg.noise,
        grab.dwell_us,
        seed,
    );
    // The scan takes its time; rendering is part of it.
    let scan = Duration::from_secs_f64(grab.scan_seconds() / shared.time_scale);
    let spent = Duration::from_nanos(shared.clock.now_unix_ns().saturating_sub(start));
    if let Some(rest) = scan.checked_sub(spent) {
        shared.clock.sleep(rest);
    }
    let meta = FrameMeta {
        frame,
        role: grab.role,
        pixel_size_um: view.pixel_size_um,
        dwell_us: grab.dwell_us,
        stage_x_um: pose.x_um,
        stage_y_um: pose.y_um,
        tilt_deg: pose.tilt_deg,
        tilt_axis_deg: view.tilt_axis_deg,
        scan_rotation_deg: view.scan_rotation_deg,
        scan_start_unix_ns: start,
        scan_end_unix_ns: shared.clock.now_unix_ns(),
    };
    {
        let mut frames = shared.frames();
        frames.records.insert(
            frame,
            FrameRecord {
                view,
                meta: meta.clone(),
            },
        );
        while frames.records.len() > cfg.history.max(1) {
            frames.records.pop_first();
        }
    }
    match grab.bits {
        Bits::Sixteen => {
            FrameReply::from_u16(grab.width, grab.height, meta, &render::to_u16(&pixels))
        }
        Bits::Eight => FrameReply::from_u8(grab.width, grab.height, meta, render::to_u8(&pixels)),
    }
}

fn ground_truth(shared: &Shared, frame: u64, path: Option<&str>) -> Reply {
    let record = {
        let frames = shared.frames();
        match frames.records.get(&frame) {
            Some(r) => r.clone(),
            None => {
                let known = match (
                    frames.records.first_key_value(),
                    frames.records.last_key_value(),
                ) {
                    (Some((a, _)), Some((b, _))) => format!("frames {a} to {b} are known"),
                    _ => "no frame has been grabbed yet".to_owned(),
                };
                return Reply::Error {
                    code: ErrorCode::UnknownFrame,
                    message: format!("no frame {frame}: {known}"),
                };
            }
        }
    };
    let heights = render::height_map(&shared.scene, &record.view);
    let (w, h) = (record.view.width, record.view.height);
    match path {
        None => {
            // Frame sides came from a validated request (≤ MAX_SIDE).
            #[allow(clippy::cast_possible_truncation)]
            Reply::HeightMap(HeightMapReply::from_f32(
                w as u32,
                h as u32,
                record.meta,
                &heights,
            ))
        }
        Some(path) => match write_gsf(Path::new(path), w, h, record.view.pixel_size_um, &heights) {
            Ok(()) => Reply::Ok(format!("GROUNDTRUTH {frame} {path}")),
            Err(e) => Reply::Error {
                code: ErrorCode::FileError,
                message: format!("cannot write {path}: {e}"),
            },
        },
    }
}

/// Writes a height map (µm) as a Gwyddion Simple Field (DESIGN §7): text
/// header, 1–4 NUL bytes to a multiple of 4, then little-endian `f32` in metres.
///
/// # Errors
/// The file cannot be written.
pub fn write_gsf(
    path: &Path,
    width: usize,
    height: usize,
    pixel_size_um: f64,
    heights_um: &[f32],
) -> io::Result<()> {
    if heights_um.len() != width * height {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{} heights for a {width}×{height} map", heights_um.len()),
        ));
    }
    #[allow(clippy::cast_precision_loss)]
    let (xreal, yreal) = (
        width as f64 * pixel_size_um * 1e-6,
        height as f64 * pixel_size_um * 1e-6,
    );
    let mut out = format!(
        "Gwyddion Simple Field 1.0\nXRes = {width}\nYRes = {height}\nXReal = {xreal:e}\nYReal = {yreal:e}\nXYUnits = m\nZUnits = m\nTitle = sdsem-sim ground truth height\n"
    )
    .into_bytes();
    let pad = 4 - out.len() % 4;
    out.extend(std::iter::repeat_n(0u8, pad));
    out.reserve(heights_um.len() * 4);
    for &h in heights_um {
        out.extend_from_slice(&(h * 1e-6).to_le_bytes());
    }
    std::fs::write(path, out)
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicU64;

    use sdsem_protocol::sem::{ReplyDecoder, Role};

    use super::*;
    use crate::scene::SceneKind;

    /// A clock whose sleeps advance it instantly, recording them.
    #[derive(Default)]
    struct FakeClock {
        now: AtomicU64,
        slept: Mutex<Vec<Duration>>,
    }

    impl Clock for FakeClock {
        fn now_unix_ns(&self) -> u64 {
            self.now.load(Ordering::SeqCst)
        }

        fn sleep(&self, d: Duration) {
            self.slept.lock().unwrap().push(d);
            self.now
                .fetch_add(u64::try_from(d.as_nanos()).unwrap(), Ordering::SeqCst);
        }
    }

    struct Rig {
        handle: SemServerHandle,
        pose: Arc<FixedPose>,
        clock: Arc<FakeClock>,
        stream: TcpStream,
        decoder: ReplyDecoder,
    }

    fn rig(cfg: SemSimConfig, time_scale: f64) -> Rig {
        let scene = Arc::new(
            Scene::generate(&SceneParams {
                kind: SceneKind::Grid,
                seed: 2,
                field_um: 60.0,
                sample_um: 0.1,
            })
            .unwrap(),
        );
        let pose = Arc::new(FixedPose::default());
        let clock = Arc::new(FakeClock {
            now: AtomicU64::new(1_000_000_000),
            ..FakeClock::default()
        });
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let handle = spawn_with_scene(
            listener,
            pose.clone(),
            cfg,
            scene,
            time_scale,
            clock.clone(),
        )
        .unwrap();
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
        let mut rig = rig(cfg(), 4.0);
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
        // 160 × 120 × 2 µs = 38.4 ms of scan, at 4× speed: 9.6 ms.
        let slept: Duration = rig.clock.slept.lock().unwrap().iter().sum();
        assert_eq!(slept, Duration::from_secs_f64(0.0096));
        assert_eq!(
            f.meta.scan_end_unix_ns - f.meta.scan_start_unix_ns,
            9_600_000
        );
        // The pixels are the renderer's for the same view.
        let record = rig.handle.frame(1).unwrap();
        assert_eq!(record.view.tilt_deg, 7.0);
        let walk = WalkParams::default().offset_um(7.0);
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
        let mut rig = rig(cfg(), 100.0);
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
        let mut rig = rig(cfg(), 100.0);
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
        let mut rig = rig(cfg(), 100.0);
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
    fn rejects_a_bad_time_scale() {
        let scene = Arc::new(
            Scene::generate(&SceneParams {
                field_um: 10.0,
                ..SceneParams::default()
            })
            .unwrap(),
        );
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let err = spawn_with_scene(
            listener,
            Arc::new(FixedPose::default()),
            cfg(),
            scene,
            0.0,
            Arc::new(SystemClock),
        )
        .unwrap_err();
        assert!(err.to_string().contains("time_scale"));
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
