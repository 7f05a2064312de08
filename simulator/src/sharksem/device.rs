//! The simulated TESCAN SEM behind SharkSEM: decoded requests in, responses
//! (or silence) out, on the shared stage model, SEM renderer and clock.
//! [`super::server`] moves the bytes and runs the scans.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use sdsem_protocol::sharksem::{
    Detector, Flags, Request, Response, ScanSpeed, ScanXY, StageLimits, StagePosition, Version,
};
use tracing::{debug, info, warn};

use super::config::SharkSemSimConfig;
use crate::clock::Clock;
use crate::sem::SimSem;
use crate::stage::SimStage;
use crate::stage_model::{AxisRole, MoveRefusal, fires};

/// Z travel of the simulated stage, mm (z does not exist in the stage model: moves are instant).
const Z_RANGE_MM: (f64, f64) = (0.0, 50.0);
/// Rotation travel, degrees (not in the stage model either: instant).
const ROTATION_RANGE_DEG: (f64, f64) = (-360.0, 360.0);
/// How long the optics settle after `SetViewField` (Wait C), simulated seconds [TS-PDF: about 5 ms].
const OPTICS_SETTLE_S: f64 = 0.005;
/// Largest scan window side accepted.
const MAX_SIDE: u32 = sdsem_protocol::sem::MAX_SIDE;
/// How often a held request looks at its condition, simulated seconds.
const WAIT_POLL_S: f64 = 0.01;

/// How many times each SharkSEM fault fired, and what was ignored.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SharkSemCounts {
    /// Requests received (all clients).
    pub requests: u64,
    /// Requests ignored silently: unknown, wrong arguments, or not allowed now.
    pub ignored: u64,
    /// `StgMoveTo` ignored because the stage was busy or uncalibrated.
    pub ignored_moves: u64,
    /// `SetViewField` ignored by the fault.
    pub ignored_view_fields: u64,
    /// `ScData` chunks generated, lost by the fault, sent twice by the fault.
    pub chunks: u64,
    pub lost_chunks: u64,
    pub resent_chunks: u64,
    /// Scans started.
    pub scans: u64,
    /// Clients dropped (fault, or data socket not read).
    pub disconnects: u64,
}

#[derive(Clone, Copy, Debug)]
struct Channel {
    detector: i32,
    enabled: bool,
    bpp: u8,
}

/// A scan accepted by `ScScanXY`, for the server to stream.
#[derive(Clone, Debug)]
pub(crate) struct ScanJob {
    pub scan: ScanXY,
    pub dwell_us: f64,
    /// Enabled channels and their bits per pixel.
    pub channels: Vec<(i32, u8)>,
    /// Pixel size of this scan window, µm.
    pub pixel_size_um: f64,
    /// Set by `ScStopScan` (or the end of the session).
    pub cancel: Arc<AtomicBool>,
}

/// What became of one chunk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum ChunkFate {
    Send,
    Lose,
    SendTwice,
}

/// What the server does with one request.
#[derive(Debug, Default)]
pub(crate) struct Handled {
    /// The response, if the function returns one (or send-response was asked).
    pub reply: Option<Response>,
    /// A scan to start streaming.
    pub scan: Option<ScanJob>,
    /// Register this local port of the client for its data connection.
    pub register_port: Option<u16>,
}

struct State {
    view_field_mm: f64,
    optics_stable_at: f64,
    channels: Vec<Channel>,
    z_mm: f64,
    rotation_deg: f64,
    /// `ScScanXY` accepted and not yet stopped by `ScStopScan`.
    armed: bool,
    /// Data still being scanned (Wait A).
    streaming: bool,
    scan_cancel: Option<Arc<AtomicBool>>,
    rng: ChaCha8Rng,
    view_field_sets: u64,
    disconnect_fired: bool,
    hung: bool,
    counts: SharkSemCounts,
}

/// The SEM as SharkSEM sees it, shared by every client.
pub struct SharkSemDevice {
    cfg: SharkSemSimConfig,
    version: Version,
    stage: Arc<SimStage>,
    sem: Arc<SimSem>,
    clock: Arc<dyn Clock>,
    state: Mutex<State>,
}

impl std::fmt::Debug for SharkSemDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SharkSemDevice")
            .field("version", &self.version)
            .field("counts", &self.counts())
            .finish_non_exhaustive()
    }
}

impl SharkSemDevice {
    /// The SEM of `cfg` (validated) on the simulator's stage, renderer and
    /// clock; `seed` seeds the fault draws.
    pub(crate) fn new(
        cfg: SharkSemSimConfig,
        stage: Arc<SimStage>,
        sem: Arc<SimSem>,
        seed: u64,
    ) -> Self {
        let optics = &sem.config().optics;
        #[allow(clippy::cast_precision_loss)]
        let default_field = optics.pixel_size_um * optics.width as f64 * 1e-3;
        let view_field_mm = cfg
            .view_field_mm
            .unwrap_or(default_field)
            .clamp(cfg.view_field_min_mm, cfg.view_field_max_mm);
        let channels = vec![
            Channel {
                detector: 10,
                enabled: false,
                bpp: 8,
            };
            cfg.channels as usize
        ];
        let clock = Arc::clone(stage.clock());
        Self {
            version: cfg.protocol_version(),
            state: Mutex::new(State {
                view_field_mm,
                optics_stable_at: 0.0,
                channels,
                z_mm: cfg.z_mm,
                rotation_deg: 0.0,
                armed: false,
                streaming: false,
                scan_cancel: None,
                rng: ChaCha8Rng::seed_from_u64(seed),
                view_field_sets: 0,
                disconnect_fired: false,
                hung: false,
                counts: SharkSemCounts::default(),
            }),
            cfg,
            stage,
            sem,
            clock,
        }
    }

    fn state(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The settings in effect.
    #[must_use]
    pub fn config(&self) -> &SharkSemSimConfig {
        &self.cfg
    }

    /// The simulated SEM rendering the scans.
    #[must_use]
    pub fn sem(&self) -> &Arc<SimSem> {
        &self.sem
    }

    /// The clock of the simulator.
    pub(crate) fn clock(&self) -> &Arc<dyn Clock> {
        &self.clock
    }

    /// Counters so far.
    #[must_use]
    pub fn counts(&self) -> SharkSemCounts {
        self.state().counts
    }

    /// The field width now, mm.
    #[must_use]
    pub fn view_field_mm(&self) -> f64 {
        self.state().view_field_mm
    }

    /// Stage rotation now, degrees (instant axis, see the module docs).
    #[must_use]
    pub fn rotation_deg(&self) -> f64 {
        self.state().rotation_deg
    }

    /// Whether the server stopped answering (the `silent_after_requests` fault).
    #[must_use]
    pub fn is_hung(&self) -> bool {
        self.state().hung
    }

    pub(crate) fn count_disconnect(&self) {
        self.state().counts.disconnects += 1;
    }

    /// Counts one request and applies the request faults: `None` when the
    /// server has stopped answering, else whether to disconnect after it.
    pub(crate) fn admit(&self) -> Option<bool> {
        let mut s = self.state();
        s.counts.requests += 1;
        let k = s.counts.requests;
        let f = &self.cfg.faults;
        if s.hung || f.silent_after_requests.is_some_and(|n| k >= n) {
            if !s.hung {
                info!(request = k, "SharkSEM: the server stops answering (fault)");
            }
            s.hung = true;
            return None;
        }
        let disconnect = !s.disconnect_fired && f.disconnect_after_requests.is_some_and(|n| k >= n);
        if disconnect {
            s.disconnect_fired = true;
        }
        Some(disconnect)
    }

    /// Whether any condition of the wait flags (or `IsBusy` mask) holds now.
    fn busy(&self, flags: Flags) -> bool {
        let (streaming, stable_at) = {
            let s = self.state();
            (s.streaming, s.optics_stable_at)
        };
        (flags.contains(Flags::WAIT_A) && streaming)
            || (flags.contains(Flags::WAIT_B) && self.stage_busy())
            || (flags.contains(Flags::WAIT_C) && self.clock.now_s() < stable_at)
    }

    /// Holds the caller until every wait flag is clear; false if `stop` was set meanwhile.
    pub(crate) fn wait_clear(&self, flags: Flags, stop: &AtomicBool) -> bool {
        let waits = flags.waits();
        while self.busy(waits) {
            if stop.load(Ordering::Relaxed) {
                return false;
            }
            let until = self.clock.now_s() + WAIT_POLL_S;
            if !self.clock.sleep_until(until, stop) {
                return false;
            }
        }
        true
    }

    /// `StgIsBusy`: the model's moving flag (which the stale-flag fault makes lie).
    fn stage_busy(&self) -> bool {
        self.stage.with_model(|m, now| m.busy(now))
    }

    /// `StgIsCalibrated`: every axis referenced with its servo on.
    fn stage_calibrated(&self) -> bool {
        self.stage.with_model(|m, _| m.ready())
    }

    fn available(&self, request: &Request) -> bool {
        let v = self.version;
        match request {
            Request::TcpGetDevice => v >= Version(2, 0, 3),
            Request::TcpGetSwVersion | Request::IsBusy { .. } => v >= Version::IS_BUSY,
            Request::StgGetLimits { .. } => v >= Version::STAGE_LIMITS,
            Request::TcpGetModel => v >= Version::MODEL,
            Request::ScScanXY(s) => s.dwell_ns.is_none() || v >= Version::DWELL_ARGUMENT,
            // GetDeviceParams is not simulated: its keys are not documented publicly.
            Request::GetDeviceParams { .. } => false,
            _ => true,
        }
    }

    /// Answers one decoded request (wait flags already honoured). `None`
    /// reply: a void function, or a request ignored silently.
    pub(crate) fn handle(&self, request: &Request) -> Handled {
        if !self.available(request) {
            return self.ignore(request, "not in this protocol version");
        }
        let reply = |r| Handled {
            reply: Some(r),
            ..Handled::default()
        };
        match request {
            Request::TcpGetVersion => reply(Response::Text(self.cfg.version.clone())),
            Request::TcpGetSwVersion => reply(Response::Text(self.cfg.sw_version.clone())),
            Request::TcpGetDevice => reply(Response::Text(self.cfg.device.clone())),
            Request::TcpGetModel => reply(Response::Text(self.cfg.model.clone())),
            Request::TcpRegDataPort { port } => match u16::try_from(*port) {
                Ok(p) if p != 0 => Handled {
                    reply: Some(Response::Int(0)),
                    register_port: (!self.cfg.firewall_friendly).then_some(p),
                    ..Handled::default()
                },
                _ => self.ignore(request, "not a port number"),
            },
            Request::StgGetPosition => reply(Response::Position(self.position())),
            Request::StgMoveTo(axes) => {
                self.move_to(axes);
                Handled::default()
            }
            Request::StgIsBusy => reply(Response::Int(i32::from(self.stage_busy()))),
            Request::StgGetLimits { kind: 0 | 1 } => reply(Response::Limits(self.limits())),
            Request::StgStop => {
                self.stage.with_model(|m, now| m.halt_all(now));
                Handled::default()
            }
            Request::StgIsCalibrated => reply(Response::Int(i32::from(self.stage_calibrated()))),
            Request::GetViewField => reply(Response::ViewField(self.state().view_field_mm)),
            Request::SetViewField { mm } => {
                self.set_view_field(*mm);
                Handled::default()
            }
            Request::ScEnumSpeeds => reply(Response::Speeds(self.speeds())),
            Request::DtEnumDetectors => reply(Response::Detectors(self.detectors())),
            Request::DtSelect { channel, detector } => self.select(request, *channel, *detector),
            Request::DtEnable {
                channel,
                enable,
                bpp,
            } => self.enable(request, *channel, *enable, *bpp),
            Request::DtGetSelected { channel } => match self.channel(*channel) {
                Some(c) => reply(Response::Int(c.detector)),
                None => self.ignore(request, "no such channel"),
            },
            Request::DtGetEnabled { channel } => match self.channel(*channel) {
                Some(c) => reply(Response::Enabled {
                    enable: i32::from(c.enabled),
                    bpp: i32::from(c.bpp),
                }),
                None => self.ignore(request, "no such channel"),
            },
            Request::ScScanXY(scan) => self.start_scan(request, scan),
            Request::ScStopScan => {
                let mut s = self.state();
                s.armed = false;
                s.streaming = false;
                if let Some(c) = s.scan_cancel.take() {
                    c.store(true, Ordering::Relaxed);
                }
                Handled::default()
            }
            Request::IsBusy { mask } => {
                let mask = Flags(u16::try_from(*mask & 0x7F00).unwrap_or(0));
                reply(Response::Int(i32::from(self.busy(mask))))
            }
            Request::StgGetLimits { .. } | Request::GetDeviceParams { .. } => {
                self.ignore(request, "wrong arguments")
            }
        }
    }

    /// A request ignored silently, as the real server does [TS-PDF].
    pub(crate) fn ignore(&self, request: &impl std::fmt::Display, why: &str) -> Handled {
        self.state().counts.ignored += 1;
        debug!(%request, why, "SharkSEM: request ignored silently");
        Handled::default()
    }

    fn channel(&self, channel: i32) -> Option<Channel> {
        let s = self.state();
        usize::try_from(channel)
            .ok()
            .and_then(|i| s.channels.get(i).copied())
    }

    fn position(&self) -> StagePosition {
        let pose = self.stage.snapshot().pose;
        let s = self.state();
        StagePosition {
            x_mm: pose.x_um * 1e-3,
            y_mm: pose.y_um * 1e-3,
            z_mm: s.z_mm,
            rotation_deg: s.rotation_deg,
            tilt_deg: pose.tilt_deg,
            tilt_y_deg: self.cfg.tilt_y.then_some(0.0),
        }
    }

    /// The stage model's soft limits in mm and degrees; z and rotation are this dialect's.
    fn limits(&self) -> StageLimits {
        let (x, y, t) = self.stage.with_model(|m, _| {
            (
                m.limits(AxisRole::X),
                m.limits(AxisRole::Y),
                m.limits(AxisRole::Tilt),
            )
        });
        let mm = |l: Option<(f64, f64)>| l.map_or((0.0, 0.0), |(lo, hi)| (lo * 1e-3, hi * 1e-3));
        StageLimits {
            x_mm: mm(x),
            y_mm: mm(y),
            z_mm: Z_RANGE_MM,
            rotation_deg: ROTATION_RANGE_DEG,
            tilt_deg: t.unwrap_or((0.0, 0.0)),
        }
    }

    /// `StgMoveTo`: needs a calibrated, idle stage, else ignored silently;
    /// targets are limited silently [TS-PDF 2.0.25]; missing axes stay.
    fn move_to(&self, axes: &[f64]) {
        if !self.stage_calibrated() || self.stage_busy() {
            let mut s = self.state();
            s.counts.ignored_moves += 1;
            s.counts.ignored += 1;
            info!(
                ?axes,
                "SharkSEM: StgMoveTo ignored (stage busy or not calibrated)"
            );
            return;
        }
        let l = self.limits();
        let clamp = |v: f64, (lo, hi): (f64, f64)| v.clamp(lo, hi);
        let mut targets: Vec<(AxisRole, f64)> = Vec::new();
        if let Some(&x) = axes.first() {
            targets.push((AxisRole::X, clamp(x, l.x_mm) * 1e3));
        }
        if let Some(&y) = axes.get(1) {
            targets.push((AxisRole::Y, clamp(y, l.y_mm) * 1e3));
        }
        if let Some(&t) = axes.get(4) {
            targets.push((AxisRole::Tilt, clamp(t, l.tilt_deg)));
        }
        {
            let mut s = self.state();
            if let Some(&z) = axes.get(2) {
                s.z_mm = clamp(z, l.z_mm);
            }
            if let Some(&r) = axes.get(3) {
                s.rotation_deg = clamp(r, l.rotation_deg);
            }
        }
        if targets.is_empty() {
            return;
        }
        // Limited already; a refusal can only be the move_error fault: silent too.
        match self
            .stage
            .with_model(|m, now| m.move_roles(now, &targets, false))
        {
            Ok(true) => {}
            Ok(false)
            | Err(MoveRefusal::Fault | MoveRefusal::NotReady | MoveRefusal::OutOfLimits) => {
                info!(
                    ?targets,
                    "SharkSEM: StgMoveTo silently not executed (fault)"
                );
            }
        }
    }

    fn set_view_field(&self, mm: f64) {
        let now = self.clock.now_s();
        let mut s = self.state();
        s.view_field_sets += 1;
        let k = s.view_field_sets;
        if fires(&self.cfg.faults.ignore_view_field, k, &mut s.rng) {
            s.counts.ignored_view_fields += 1;
            info!(mm, "SharkSEM: SetViewField ignored (fault)");
            return;
        }
        s.view_field_mm = mm.clamp(self.cfg.view_field_min_mm, self.cfg.view_field_max_mm);
        s.optics_stable_at = now + OPTICS_SETTLE_S;
    }

    fn speeds(&self) -> Vec<ScanSpeed> {
        (1..)
            .zip(&self.cfg.speeds_us)
            .map(|(index, &dwell_us)| ScanSpeed { index, dwell_us })
            .collect()
    }

    fn detectors(&self) -> Vec<Detector> {
        (0..)
            .zip(&self.cfg.detectors)
            .map(|(index, name)| Detector {
                index,
                name: name.clone(),
                id: 10 + i32::try_from(index).unwrap_or(0),
            })
            .collect()
    }

    fn select(&self, request: &Request, channel: i32, detector: i32) -> Handled {
        let known = self.detectors().iter().any(|d| d.id == detector);
        let mut s = self.state();
        let slot = usize::try_from(channel)
            .ok()
            .filter(|&i| i < s.channels.len());
        match slot {
            Some(i) if known => {
                s.channels[i].detector = detector;
                Handled::default()
            }
            _ => {
                drop(s);
                self.ignore(request, "no such channel or detector")
            }
        }
    }

    /// `DtEnable`: only while scanning is stopped; bpp 8 by default, 3.x rounds
    /// 0–7 up to 8 and anything else to 16, 2.x takes 8 or 16 only.
    fn enable(&self, request: &Request, channel: i32, enable: i32, bpp: Option<i32>) -> Handled {
        let bpp = match (bpp, self.version >= Version(3, 0, 0)) {
            (None, _) => Some(8),
            (Some(b), true) => Some(if (0..=7).contains(&b) { 8 } else { 16 }),
            (Some(8), false) => Some(8),
            (Some(16), false) => Some(16),
            (Some(_), false) => None,
        };
        let mut s = self.state();
        let slot = usize::try_from(channel)
            .ok()
            .filter(|&i| i < s.channels.len());
        match (slot, bpp) {
            (Some(i), Some(bpp)) if !s.armed => {
                s.channels[i].enabled = enable != 0;
                s.channels[i].bpp = bpp;
                Handled::default()
            }
            _ => {
                drop(s);
                self.ignore(request, "no such channel, a wrong depth, or scanning")
            }
        }
    }

    fn start_scan(&self, request: &Request, scan: &ScanXY) -> Handled {
        let refuse = Handled {
            reply: Some(Response::Int(-1)),
            ..Handled::default()
        };
        if scan.width > MAX_SIDE || scan.height > MAX_SIDE || scan.region_pixels().is_none() {
            return refuse;
        }
        let dwell_us = match scan.dwell_ns {
            Some(0) => return refuse,
            Some(ns) => f64::from(ns) * 1e-3,
            None => self.cfg.speeds_us[self.cfg.speed_index as usize - 1],
        };
        let mut s = self.state();
        if s.armed {
            // The previous scan was never stopped: ScStopScan is required after every scan.
            drop(s);
            warn!("SharkSEM: ScScanXY ignored: the previous scan was not stopped with ScStopScan");
            return self.ignore(request, "previous scan not stopped");
        }
        let channels: Vec<(i32, u8)> = (0..)
            .zip(&s.channels)
            .filter(|(_, c)| c.enabled)
            .map(|(i, c)| (i, c.bpp))
            .collect();
        let cancel = Arc::new(AtomicBool::new(false));
        s.armed = true;
        s.streaming = true;
        s.scan_cancel = Some(Arc::clone(&cancel));
        s.counts.scans += 1;
        let pixel_size_um = s.view_field_mm * 1e3 / f64::from(scan.width);
        Handled {
            reply: Some(Response::Int(0)),
            scan: Some(ScanJob {
                scan: *scan,
                dwell_us,
                channels,
                pixel_size_um,
                cancel,
            }),
            ..Handled::default()
        }
    }

    /// A single scan has sent its last pixel (Wait A clears).
    pub(crate) fn scan_finished(&self, cancel: &Arc<AtomicBool>) {
        let mut s = self.state();
        if s.scan_cancel
            .as_ref()
            .is_some_and(|c| Arc::ptr_eq(c, cancel))
        {
            s.streaming = false;
        }
    }

    /// The fate of the next chunk (faults counted in chunks).
    pub(crate) fn next_chunk(&self) -> ChunkFate {
        let mut s = self.state();
        s.counts.chunks += 1;
        let k = s.counts.chunks;
        let f = &self.cfg.faults;
        if fires(&f.lose_chunk, k, &mut s.rng) {
            s.counts.lost_chunks += 1;
            return ChunkFate::Lose;
        }
        if fires(&f.resend_chunk, k, &mut s.rng) {
            s.counts.resent_chunks += 1;
            return ChunkFate::SendTwice;
        }
        ChunkFate::Send
    }
}
