//! Frames from a TESCAN SEM over SharkSEM [TS-PDF `ScScanXY`/`ScData`; TS-PY
//! `FetchImageEx`; OD-T; SB-T].
//!
//! One frame, with the session locked throughout so nothing interleaves:
//! 1. `ScStopScan` (the operator's live view or an earlier scan stops first);
//! 2. once per session set-up: `DtEnumDetectors`, `DtSelect(channel, detector)`,
//!    `DtEnable(channel, 1, bpp)`, read back by `DtGetSelected`/`DtGetEnabled`;
//! 3. the view field: with `imaging.pixel_size_um`, `SetViewField(pixel × micrograph
//!    width)` when it differs, read back by `GetViewField` (wait C) and re-sent
//!    once if it did not take; without, the field is only read; pixel size =
//!    field / frame width (a tracking frame has the micrograph's field);
//! 4. `StgGetPosition` for the frame's metadata;
//! 5. the data channel drained, `ScScanXY(frame, w, h, 0, 0, w−1, h−1, single,
//!    dwell ns)` with wait B (stage idle), `ScData` reassembled;
//! 6. `ScStopScan`, whatever happened.
//!
//! A frame that fails for a transient cause (a lost chunk, data that stopped,
//! a lost connection, no answer) is taken again once, settings re-checked.
//! SharkSEM does not report the direction of the tilt axis in the image:
//! `reconstruction.tilt_axis_deg` gives it.

use sdsem_protocol::sem::Bits;
use sdsem_protocol::sharksem::{
    Detector, Flags, FrameAssembler, Request, Response, ScanXY, StagePosition, Version,
};
use tracing::warn;

use super::{
    Frame, FrameMeta, FrameSource, GrabFuture, GrabRequest, IdentifyFuture, ImagingConfig,
    ImagingError, Pixels, ProbeFuture, SourceIdentity,
};
use crate::sharksem::{SessionConfig, SharkError, SharkLink, SharkSession};
use crate::stage::StageObserver;
use crate::stage::observer::wall_ns;

/// The video channel used.
const CHANNEL: i32 = 0;
/// A view field read back within this relative difference counts as taken
/// (the SEM may round it).
const FIELD_TOLERANCE: f64 = 1e-3;

/// A [`FrameSource`] scanning on a TESCAN SEM (module docs).
#[derive(Debug)]
pub struct SharkSemSource {
    link: SharkLink,
    detector: String,
    pixel_size_um: Option<f64>,
    micrograph_width: u32,
    tilt_axis_deg: f64,
    /// Session generation and bit depth the detector was set up for.
    configured: Option<(u64, Bits)>,
    /// What the SEM said it is when the session was set up.
    identity: SourceIdentity,
}

impl SharkSemSource {
    /// The session settings of `cfg` (`imaging.endpoint`, `data_port`, `timeout_ms`).
    #[must_use]
    pub fn session_config(cfg: &ImagingConfig) -> SessionConfig {
        SessionConfig {
            endpoint: cfg.endpoint.clone(),
            data_port: cfg.data_port,
            connect_timeout: cfg.timeout(),
            reply_timeout: cfg.timeout(),
            timeout_key: "imaging.timeout_ms",
        }
    }

    /// Connects its own session to `cfg.endpoint`, reporting every exchange to
    /// `observer`; returns the source and the instrument's identification.
    ///
    /// # Errors
    /// [`ImagingError`] for a wrong setting, an unreachable or too old server.
    pub async fn connect(
        cfg: &ImagingConfig,
        tilt_axis_deg: Option<f64>,
        observer: std::sync::Arc<dyn StageObserver>,
    ) -> Result<(Self, String), ImagingError> {
        cfg.validate()?;
        check_tilt_axis(tilt_axis_deg)?;
        let link = SharkLink::connect(Self::session_config(cfg), observer).await?;
        Self::with_link(link, cfg, tilt_axis_deg).await
    }

    /// A source on a session that already exists (shared with the stage).
    ///
    /// # Errors
    /// [`ImagingError::InvalidConfig`], or [`SharkError::TooOld`] for a server
    /// without the dwell argument of `ScScanXY` (before 2.0.6).
    pub async fn with_link(
        link: SharkLink,
        cfg: &ImagingConfig,
        tilt_axis_deg: Option<f64>,
    ) -> Result<(Self, String), ImagingError> {
        cfg.validate()?;
        let tilt_axis_deg = check_tilt_axis(tilt_axis_deg)?;
        let (identification, identity) = {
            let s = link.lock().await;
            if s.version() < Version::DWELL_ARGUMENT {
                return Err(SharkError::TooOld {
                    version: s.version(),
                    needed: Version::DWELL_ARGUMENT,
                    what: "scanning with a given dwell time",
                }
                .into());
            }
            (s.info().to_string(), shark_identity(s.info()))
        };
        let source = Self {
            link,
            detector: cfg.detector.trim().to_owned(),
            pixel_size_um: cfg.pixel_size_um,
            micrograph_width: cfg.micrograph.width,
            tilt_axis_deg,
            configured: None,
            identity,
        };
        Ok((source, identification))
    }

    /// The session, to share it.
    #[must_use]
    pub fn link(&self) -> &SharkLink {
        &self.link
    }

    /// Checks that the SEM answers (`TcpGetVersion`; the session is set up
    /// again if it was lost) and returns its identification.
    ///
    /// # Errors
    /// [`ImagingError::SharkSem`] naming the cause and the remedy.
    pub async fn identify(&mut self) -> Result<String, ImagingError> {
        let mut s = self.link.lock().await;
        let wait = s.config().reply_timeout;
        s.call(&Request::TcpGetVersion, Flags::NONE, wait).await?;
        Ok(s.info().to_string())
    }

    /// Scans one frame, once more if the first attempt failed for a transient cause.
    ///
    /// # Errors
    /// [`ImagingError::SharkSem`] naming the function, the cause and the remedy.
    pub async fn grab_frame(&mut self, request: GrabRequest) -> Result<Frame, ImagingError> {
        match self.try_grab(&request).await {
            Ok(frame) => Ok(frame),
            Err(e) if e.is_transient() => {
                warn!("{e}: taking the frame again");
                self.configured = None;
                Ok(self.try_grab(&request).await?)
            }
            Err(e) => Err(e.into()),
        }
    }

    async fn try_grab(&mut self, request: &GrabRequest) -> Result<Frame, SharkError> {
        let link = self.link.clone();
        let mut s = link.lock().await;
        let wait = s.config().reply_timeout;
        s.call(&Request::ScStopScan, Flags::NONE, wait).await?;
        if self.configured != Some((s.generation(), request.bits)) {
            self.select_detector(&mut s, request.bits).await?;
            self.configured = Some((s.generation(), request.bits));
        }
        let field_mm = self.view_field(&mut s).await?;
        let position = match s.call(&Request::StgGetPosition, Flags::NONE, wait).await? {
            Response::Position(p) => p,
            other => return Err(s.unexpected(&Request::StgGetPosition, &other)),
        };
        let frame_id = s.next_frame_id();
        s.drain_data();
        let start_ns = wall_ns();
        let scanned = scan(&mut s, request, frame_id).await;
        // Required after every scan, single ones included, whatever happened.
        let stopped = s.call(&Request::ScStopScan, Flags::NONE, wait).await;
        let end_ns = wall_ns();
        let assembler = scanned?;
        if let Err(e) = stopped {
            warn!("{e} (after frame {frame_id}, which is complete)");
        }
        let pixels = match request.bits {
            Bits::Sixteen => Pixels::U16(assembler.into_u16()),
            Bits::Eight => Pixels::U8(assembler.into_u8()),
        };
        Ok(Frame {
            width: request.width as usize,
            height: request.height as usize,
            pixels,
            meta: self.meta(request, frame_id, field_mm, &position, start_ns, end_ns),
            received_unix_ns: end_ns,
            origin: None,
        })
    }

    fn meta(
        &self,
        request: &GrabRequest,
        frame_id: u32,
        field_mm: f64,
        p: &StagePosition,
        start_ns: u64,
        end_ns: u64,
    ) -> FrameMeta {
        FrameMeta {
            frame: u64::from(frame_id),
            role: request.role,
            pixel_size_um: field_mm * 1e3 / f64::from(request.width),
            dwell_us: f64::from(dwell_ns(request.dwell_us)) * 1e-3,
            stage_x_um: p.x_mm * 1e3,
            stage_y_um: p.y_mm * 1e3,
            tilt_deg: p.tilt_deg,
            tilt_axis_deg: self.tilt_axis_deg,
            scan_rotation_deg: 0.0,
            scan_start_unix_ns: start_ns,
            scan_end_unix_ns: end_ns,
        }
    }

    /// Selects and enables the detector on [`CHANNEL`] with `bits`, verified by reading back.
    async fn select_detector(&self, s: &mut SharkSession, bits: Bits) -> Result<(), SharkError> {
        let wait = s.config().reply_timeout;
        let detectors = match s.call(&Request::DtEnumDetectors, Flags::NONE, wait).await? {
            Response::Detectors(d) => d,
            other => return Err(s.unexpected(&Request::DtEnumDetectors, &other)),
        };
        let detector = pick_detector(&detectors, &self.detector)?;
        let bpp = i32::try_from(bits.count()).unwrap_or(16);
        let select = Request::DtSelect {
            channel: CHANNEL,
            detector: detector.id,
        };
        let enable = Request::DtEnable {
            channel: CHANNEL,
            enable: 1,
            bpp: Some(bpp),
        };
        let mut readback = String::new();
        for _ in 0..2 {
            s.call(&select, Flags::NONE, wait).await?;
            s.call(&enable, Flags::NONE, wait).await?;
            let selected = s
                .call(
                    &Request::DtGetSelected { channel: CHANNEL },
                    Flags::NONE,
                    wait,
                )
                .await?;
            let enabled = s
                .call(
                    &Request::DtGetEnabled { channel: CHANNEL },
                    Flags::NONE,
                    wait,
                )
                .await?;
            if selected == Response::Int(detector.id)
                && enabled == (Response::Enabled { enable: 1, bpp })
            {
                return Ok(());
            }
            readback = format!("detector {selected}, {enabled}");
        }
        Err(SharkError::NotApplied {
            setting: format!("channel {CHANNEL}"),
            wanted: format!(
                "detector {} ({:?}) enabled at {bpp} bits",
                detector.id, detector.name
            ),
            got: readback,
            remedy: "the SEM may be scanning under the operator's control, or the detector is not \
                     available now: check the SEM software",
        })
    }

    /// The field width in effect, mm: set to the configured pixel size first,
    /// verified by reading it back (re-sent once).
    async fn view_field(&self, s: &mut SharkSession) -> Result<f64, SharkError> {
        let read = read_view_field(s).await?;
        let Some(pixel_um) = self.pixel_size_um else {
            return Ok(read);
        };
        let target = pixel_um * f64::from(self.micrograph_width) * 1e-3;
        let close = |v: f64| (v - target).abs() <= FIELD_TOLERANCE * target;
        if close(read) {
            return Ok(read);
        }
        let wait = s.config().reply_timeout;
        let mut got = read;
        for _ in 0..2 {
            s.call(&Request::SetViewField { mm: target }, Flags::NONE, wait)
                .await?;
            got = read_view_field(s).await?;
            if close(got) {
                return Ok(got);
            }
        }
        Err(SharkError::NotApplied {
            setting: "the view field".into(),
            wanted: format!(
                "{target} mm (imaging.pixel_size_um {pixel_um} × {} px)",
                self.micrograph_width
            ),
            got: format!("{got} mm"),
            remedy: "the field may be outside what this SEM allows at its working distance and \
                     voltage: choose another imaging.pixel_size_um, or leave it out to keep the SEM's field",
        })
    }
}

impl SharkSemSource {
    /// `sdsem probe`'s lines: the view field and the pixel size it gives, the detectors and
    /// the one `imaging.detector` picks; nothing is set or scanned.
    async fn probe_lines(&mut self) -> Result<Vec<(String, String)>, ImagingError> {
        let mut s = self.link.lock().await;
        let wait = s.config().reply_timeout;
        let field_mm = read_view_field(&mut s).await?;
        let width = self.micrograph_width;
        let mut lines = vec![(
            "GetViewField".to_owned(),
            format!(
                "{field_mm} mm: pixel {} µm at the micrograph's {width} px",
                field_mm * 1e3 / f64::from(width)
            ),
        )];
        lines.push((
            "imaging.pixel_size_um".to_owned(),
            self.pixel_size_um.map_or_else(
                || "unset: the SEM's field is kept".to_owned(),
                |p| {
                    format!(
                        "{p} µm: a run sets the field to {} mm",
                        p * f64::from(width) * 1e-3
                    )
                },
            ),
        ));
        let detectors = match s.call(&Request::DtEnumDetectors, Flags::NONE, wait).await? {
            Response::Detectors(d) => d,
            other => return Err(s.unexpected(&Request::DtEnumDetectors, &other).into()),
        };
        lines.push((
            "DtEnumDetectors".to_owned(),
            detectors
                .iter()
                .map(|d| format!("{} (id {})", d.name, d.id))
                .collect::<Vec<_>>()
                .join(", "),
        ));
        let selected = s
            .call(
                &Request::DtGetSelected { channel: CHANNEL },
                Flags::NONE,
                wait,
            )
            .await?;
        lines.push((format!("DtGetSelected({CHANNEL})"), selected.to_string()));
        lines.push((
            "imaging.detector".to_owned(),
            match pick_detector(&detectors, &self.detector) {
                Ok(d) => format!("a run selects {} (id {})", d.name, d.id),
                Err(e) => e.to_string(),
            },
        ));
        Ok(lines)
    }
}

/// Who the SEM says it is (`TcpGetModel`, `TcpGetSWVersion`, `TcpGetDevice`).
fn shark_identity(info: &crate::sharksem::InstrumentInfo) -> SourceIdentity {
    SourceIdentity {
        vendor: "TESCAN".into(),
        model: info.model.clone().unwrap_or_default(),
        version: info
            .sw_version
            .clone()
            .unwrap_or_else(|| info.protocol.clone()),
        serial: info.device.clone().unwrap_or_default(),
    }
}

fn check_tilt_axis(tilt_axis_deg: Option<f64>) -> Result<f64, ImagingError> {
    match tilt_axis_deg {
        Some(t) if t.is_finite() => Ok(t),
        _ => Err(ImagingError::InvalidConfig {
            name: "reconstruction.tilt_axis_deg",
            value: "(unset)".into(),
            expected: "the direction of the stage tilt axis in the image, degrees: SharkSEM does not report it",
        }),
    }
}

/// `GetViewField` once the optics are stable (wait C).
async fn read_view_field(s: &mut SharkSession) -> Result<f64, SharkError> {
    let wait = s.config().reply_timeout;
    match s.call(&Request::GetViewField, Flags::WAIT_C, wait).await? {
        Response::ViewField(mm) if mm.is_finite() && mm > 0.0 => Ok(mm),
        other => Err(s.unexpected(&Request::GetViewField, &other)),
    }
}

/// Pixel dwell in ns, as `ScScanXY` takes it (at least 1).
fn dwell_ns(dwell_us: f64) -> u32 {
    // Validated dwell times are ≤ 10 000 µs = 10⁷ ns.
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let ns = (dwell_us * 1e3).round().clamp(1.0, f64::from(u32::MAX)) as u32;
    ns
}

/// `ScScanXY` of the whole window (wait B: the stage idle) and its data.
async fn scan(
    s: &mut SharkSession,
    request: &GrabRequest,
    frame_id: u32,
) -> Result<FrameAssembler, SharkError> {
    let wait = s.config().reply_timeout;
    let scan = ScanXY::full_frame(
        frame_id,
        request.width,
        request.height,
        dwell_ns(request.dwell_us),
    );
    let call = Request::ScScanXY(scan);
    match s.call(&call, Flags::WAIT_B, wait).await? {
        Response::Int(0) => {}
        other => {
            return Err(SharkError::Refused {
                function: call.to_string(),
                value: other.to_string(),
                remedy: "the SEM refused the scan window or dwell: check imaging.micrograph and imaging.tracking",
            });
        }
    }
    let total = u64::from(request.width) * u64::from(request.height);
    let bits = u8::try_from(request.bits.count()).unwrap_or(16);
    let assembler = FrameAssembler::new(frame_id, CHANNEL, bits, total);
    let within = wait + std::time::Duration::from_secs_f64(request.scan_seconds());
    s.receive_frame(assembler, frame_id, CHANNEL, total, within)
        .await
}

/// The detector named (case-insensitive) or numbered (its id) by `wanted`; the first when empty.
fn pick_detector<'a>(detectors: &'a [Detector], wanted: &str) -> Result<&'a Detector, SharkError> {
    let found = if wanted.is_empty() {
        detectors.first()
    } else if let Ok(id) = wanted.parse::<i32>() {
        detectors.iter().find(|d| d.id == id)
    } else {
        detectors
            .iter()
            .find(|d| d.name.eq_ignore_ascii_case(wanted))
    };
    found.ok_or_else(|| SharkError::NoDetector {
        wanted: wanted.to_owned(),
        available: detectors
            .iter()
            .map(|d| format!("{} (id {})", d.name, d.id))
            .collect::<Vec<_>>()
            .join(", "),
    })
}

impl FrameSource for SharkSemSource {
    fn grab(&mut self, request: GrabRequest) -> GrabFuture<'_> {
        Box::pin(self.grab_frame(request))
    }

    fn identify(&mut self) -> IdentifyFuture<'_> {
        // The inherent `identify` (`TcpGetVersion`).
        Box::pin(Self::identify(self))
    }

    fn identity(&self) -> SourceIdentity {
        self.identity.clone()
    }

    fn probe(&mut self) -> ProbeFuture<'_> {
        Box::pin(self.probe_lines())
    }
}

#[cfg(test)]
mod tests;
