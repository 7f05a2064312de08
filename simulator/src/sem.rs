//! The simulated SEM: requests of [`sdsem_protocol::sem`] in, replies out.
//! Frames are rendered from a synthetic [`Scene`] at the stage pose of the
//! moment; [`crate::sem_server`] only moves the bytes.
//!
//! - `GRAB` asks the [`PoseSource`] for the pose at the start of the scan,
//!   renders the frame (eucentric walk for that tilt, drift for the elapsed
//!   simulated time, shot noise for the dwell), then waits on the
//!   [`Clock`] until the scan time, width × height × dwell in simulated
//!   seconds, has passed since the start (rendering time counts), and replies.
//!   At `time_scale` 0.01 a 12 s scan takes 0.12 s of real time.
//! - The frame metadata carries the pose at the start of the scan and the
//!   wall-clock timestamps of its start and end ([`Clock::unix_ns`]).
//! - Ground truth: every frame's view is remembered (the last
//!   [`SemSimConfig::history`] frames). `GROUNDTRUTH <frame>` returns its true
//!   height map; `GROUNDTRUTH <frame> <path>` writes it as a Gwyddion Simple
//!   Field file (heights in metres, NaN off the specimen). In-process,
//!   [`SimSem::ground_truth`] and [`SimSem::frame`] give the same, and with
//!   [`SimSem::scene`] every function of [`crate::render`] (correspondences
//!   between two frames, visible points) applies.

use std::collections::BTreeMap;
use std::io;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use sdsem_protocol::sem::{
    Bits, ErrorCode, FrameMeta, FrameReply, GrabRequest, HeightMapReply, Reply, Request,
};

use crate::clock::Clock;
use crate::config::SemSimConfig;
use crate::pose::PoseSource;
use crate::render::{self, View};
use crate::scene::Scene;
use crate::scene::noise::mix64;

/// A frame the SEM has scanned: how it was taken.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameRecord {
    /// The imaging geometry (pose, walk, drift, pixel size): with the scene,
    /// everything the ground truth needs.
    pub view: View,
    /// The metadata sent with the frame.
    pub meta: FrameMeta,
}

#[derive(Debug)]
struct Frames {
    next: u64,
    records: BTreeMap<u64, FrameRecord>,
}

/// The simulated SEM, safe to share between threads.
pub struct SimSem {
    cfg: SemSimConfig,
    scene: Arc<Scene>,
    pose: Arc<dyn PoseSource>,
    clock: Arc<dyn Clock>,
    /// Simulated time when the SEM was switched on: drift counts from here.
    start_s: f64,
    noise_seed: u64,
    frames: Mutex<Frames>,
}

impl std::fmt::Debug for SimSem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SimSem")
            .field("scene", &self.scene)
            .field("clock", &self.clock)
            .field("frames", &self.frames().records.len())
            .finish_non_exhaustive()
    }
}

impl SimSem {
    /// The SEM of `cfg` (validated by the caller) imaging `scene`, looking at
    /// the stage `pose`, on `clock`. Unset seeds are derived as for simulator
    /// seed 0 ([`SemSimConfig::resolved`]); `cfg.scene` is replaced by the
    /// scene's own parameters.
    #[must_use]
    pub fn new(
        cfg: &SemSimConfig,
        scene: Arc<Scene>,
        pose: Arc<dyn PoseSource>,
        clock: Arc<dyn Clock>,
    ) -> Self {
        let mut cfg = cfg.resolved(0);
        cfg.scene = scene.params().clone();
        Self {
            noise_seed: cfg.noise_seed(),
            start_s: clock.now_s(),
            cfg,
            scene,
            pose,
            clock,
            frames: Mutex::new(Frames {
                next: 1,
                records: BTreeMap::new(),
            }),
        }
    }

    fn frames(&self) -> MutexGuard<'_, Frames> {
        self.frames.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The configuration in effect, seeds and scene filled in.
    #[must_use]
    pub fn config(&self) -> &SemSimConfig {
        &self.cfg
    }

    /// The specimen being imaged.
    #[must_use]
    pub fn scene(&self) -> &Arc<Scene> {
        &self.scene
    }

    /// How frame number `frame` was taken, if it is still remembered.
    #[must_use]
    pub fn frame(&self, frame: u64) -> Option<FrameRecord> {
        self.frames().records.get(&frame).cloned()
    }

    /// The number of the last frame scanned, if any.
    #[must_use]
    pub fn last_frame(&self) -> Option<u64> {
        self.frames().records.last_key_value().map(|(&k, _)| k)
    }

    /// The true height map (µm, row-major on the frame's grid, NaN off the
    /// specimen) of frame `frame`, if it is still remembered.
    #[must_use]
    pub fn ground_truth(&self, frame: u64) -> Option<Vec<f32>> {
        let record = self.frame(frame)?;
        Some(render::height_map(&self.scene, &record.view))
    }

    /// Answers one request. A scan in progress ends early when `cancel` is set
    /// (the simulator is stopping).
    pub fn handle(&self, request: &Request, cancel: &AtomicBool) -> Reply {
        match request {
            Request::Identify => Reply::Identity(self.cfg.identity.clone()),
            Request::PixelSize { width } => Reply::PixelSize {
                width: *width,
                pixel_size_um: self.cfg.optics.pixel_size_at(*width as usize),
            },
            Request::Grab(grab) => Reply::Frame(self.grab(grab, cancel)),
            Request::GroundTruth { frame, path } => {
                self.ground_truth_reply(*frame, path.as_deref())
            }
        }
    }

    /// Scans one frame (module docs), taking its scan time on the clock.
    pub fn grab(&self, grab: &GrabRequest, cancel: &AtomicBool) -> FrameReply {
        let start_s = self.clock.now_s();
        let (meta, pixels) = self.begin_scan(grab, None);
        // The scan takes its time; rendering is part of it.
        self.clock
            .sleep_until(start_s + grab.scan_seconds(), cancel);
        let meta = self.end_scan(meta.frame).unwrap_or(meta);
        match grab.bits {
            Bits::Sixteen => {
                FrameReply::from_u16(grab.width, grab.height, meta, &render::to_u16(&pixels))
            }
            Bits::Eight => {
                FrameReply::from_u8(grab.width, grab.height, meta, render::to_u8(&pixels))
            }
        }
    }

    /// Starts scanning one frame at the stage pose now: renders it (walk for
    /// the tilt, drift for the elapsed time, shot noise for the dwell),
    /// remembers it for ground truth and returns its metadata (scan end = start
    /// until [`Self::end_scan`]) and pixels in [0, 1], without waiting for the
    /// scan time. `pixel_size_um` replaces the optics' pixel size (a view field
    /// set over SharkSEM); none keeps [`crate::render::OpticsParams::pixel_size_at`].
    pub fn begin_scan(
        &self,
        grab: &GrabRequest,
        pixel_size_um: Option<f64>,
    ) -> (FrameMeta, Vec<f32>) {
        let cfg = &self.cfg;
        let start_s = self.clock.now_s();
        let start_ns = self.clock.unix_ns();
        let pose = self.pose.pose();
        let elapsed_s = start_s - self.start_s;
        let drift = [
            cfg.drift_um_per_s[0] * elapsed_s,
            cfg.drift_um_per_s[1] * elapsed_s,
        ];
        let (width, height) = (grab.width as usize, grab.height as usize);
        let walk = cfg.walk.offset_um(pose.tilt_deg, cfg.optics.pixel_size_um);
        let mut view = cfg.optics.view(&pose, width, height, walk, drift);
        if let Some(p) = pixel_size_um {
            view.pixel_size_um = p;
        }
        let frame = {
            let mut frames = self.frames();
            let n = frames.next;
            frames.next += 1;
            n
        };
        let pixels = render::render_noisy(
            &self.scene,
            &view,
            &cfg.shading,
            &cfg.noise,
            grab.dwell_us,
            mix64(self.noise_seed ^ mix64(frame)),
        );
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
            scan_start_unix_ns: start_ns,
            scan_end_unix_ns: start_ns,
        };
        let mut frames = self.frames();
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
        (meta, pixels)
    }

    /// Marks the scan of `frame` ended now; its metadata with the end time
    /// (none if the frame is no longer remembered).
    pub fn end_scan(&self, frame: u64) -> Option<FrameMeta> {
        let end_ns = self.clock.unix_ns();
        let mut frames = self.frames();
        let record = frames.records.get_mut(&frame)?;
        record.meta.scan_end_unix_ns = end_ns;
        Some(record.meta.clone())
    }

    fn ground_truth_reply(&self, frame: u64, path: Option<&str>) -> Reply {
        let record = {
            let frames = self.frames();
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
        let heights = render::height_map(&self.scene, &record.view);
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
            Some(path) => {
                match write_gsf(Path::new(path), w, h, record.view.pixel_size_um, &heights) {
                    Ok(()) => Reply::Ok(format!("GROUNDTRUTH {frame} {path}")),
                    Err(e) => Reply::Error {
                        code: ErrorCode::FileError,
                        message: format!("cannot write {path}: {e}"),
                    },
                }
            }
        }
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
