//! The functions sdsem calls, as typed requests: encoded by the client,
//! decoded by the simulator [TS-PDF; TS-CS; TS-PY `sem.py`].

use std::fmt;

use super::body::{BodyError, BodyReader, BodyWriter, format_float};
use super::header::{Flags, FnName, HEADER_LEN, Header};

/// Most stage axes `StgMoveTo` takes: x, y, z, rotation, tilt and (3.2.20+) tilt-Y.
pub const MAX_STAGE_AXES: usize = 6;

/// The arguments of `ScScanXY` [TS-PDF; TS-CS].
///
/// `width × height` is the whole scan window, tied to the view field; the
/// visible region `[left..=right] × [top..=bottom]` is what is scanned and sent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ScanXY {
    pub frame_id: u32,
    pub width: u32,
    pub height: u32,
    pub left: u32,
    pub top: u32,
    pub right: u32,
    pub bottom: u32,
    /// 1: one frame; 0: continuous.
    pub single: i32,
    /// Pixel dwell, ns (protocol 2.0.6+); none: the current speed index.
    pub dwell_ns: Option<u32>,
}

impl ScanXY {
    /// One frame of the whole `width × height` window.
    #[must_use]
    pub fn full_frame(frame_id: u32, width: u32, height: u32, dwell_ns: u32) -> Self {
        Self {
            frame_id,
            width,
            height,
            left: 0,
            top: 0,
            right: width.saturating_sub(1),
            bottom: height.saturating_sub(1),
            single: 1,
            dwell_ns: Some(dwell_ns),
        }
    }

    /// Pixels in the visible region, or none if the region is empty or outside the window.
    #[must_use]
    pub fn region_pixels(&self) -> Option<u64> {
        let ok = self.left <= self.right
            && self.top <= self.bottom
            && self.right < self.width
            && self.bottom < self.height;
        ok.then(|| u64::from(self.right - self.left + 1) * u64::from(self.bottom - self.top + 1))
    }
}

/// One request of the subset spoken here.
#[derive(Clone, Debug, PartialEq)]
pub enum Request {
    /// Protocol version, e.g. "2.0.22" (since 1.0.5).
    TcpGetVersion,
    /// SEM software version (since 2.0.9).
    TcpGetSwVersion,
    /// Serial number of the instrument (since 2.0.3).
    TcpGetDevice,
    /// Model name (since 3.2.20).
    TcpGetModel,
    /// Registers the client's local data port; replies 0.
    TcpRegDataPort { port: u32 },
    /// Stage position: x, y, z (mm), rotation, tilt (°), and tilt-Y on 3.x stages that have it.
    StgGetPosition,
    /// Absolute move, axes in the order x, y, z, rotation, tilt, tilt-Y; trailing axes may be left out.
    StgMoveTo(Vec<f64>),
    /// 1 while the stage moves.
    StgIsBusy,
    /// Stage limits: 0 = device, 1 = soft (since 2.0.22).
    StgGetLimits { kind: i32 },
    /// Stops the stage.
    StgStop,
    /// 1 when the stage is calibrated.
    StgIsCalibrated,
    /// Width of the whole scan window, mm.
    GetViewField,
    /// Sets the width of the whole scan window, mm (clamped by the SEM).
    SetViewField { mm: f64 },
    /// Scan speeds: map `speed.N.dwell=µs`.
    ScEnumSpeeds,
    /// Detectors: map `det.K.name=…`, `det.K.detector=<id>`.
    DtEnumDetectors,
    /// Connects detector `detector` to video channel `channel`.
    DtSelect { channel: i32, detector: i32 },
    /// Enables a channel, with 8 or 16 bits per pixel.
    DtEnable {
        channel: i32,
        enable: i32,
        bpp: Option<i32>,
    },
    /// The detector selected on a channel [TS-PY].
    DtGetSelected { channel: i32 },
    /// Whether a channel is enabled, and its bits per pixel [TS-PY].
    DtGetEnabled { channel: i32 },
    /// Starts a scan; replies 0, or < 0 for bad arguments.
    ScScanXY(ScanXY),
    /// Stops scanning; required after every scan.
    ScStopScan,
    /// 1 while any condition of `mask` (header bits 8–14) holds (since 2.0.9).
    IsBusy { mask: u32 },
    /// Device parameters as a map: 0 common, 1 SEM, 2 FIB (since 2.0.6).
    GetDeviceParams { set: u32 },
}

/// Why a request from the wire is not one of [`Request`].
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// A function this subset does not know.
    #[error("unknown function {0}")]
    UnknownFunction(String),
    /// Wrong arguments for a known function.
    #[error("{name}: wrong arguments: {source}")]
    BadArguments { name: String, source: BodyError },
}

impl Request {
    /// The function name on the wire.
    #[must_use]
    pub fn name(&self) -> &'static str {
        match self {
            Self::TcpGetVersion => "TcpGetVersion",
            Self::TcpGetSwVersion => "TcpGetSWVersion",
            Self::TcpGetDevice => "TcpGetDevice",
            Self::TcpGetModel => "TcpGetModel",
            Self::TcpRegDataPort { .. } => "TcpRegDataPort",
            Self::StgGetPosition => "StgGetPosition",
            Self::StgMoveTo(_) => "StgMoveTo",
            Self::StgIsBusy => "StgIsBusy",
            Self::StgGetLimits { .. } => "StgGetLimits",
            Self::StgStop => "StgStop",
            Self::StgIsCalibrated => "StgIsCalibrated",
            Self::GetViewField => "GetViewField",
            Self::SetViewField { .. } => "SetViewField",
            Self::ScEnumSpeeds => "ScEnumSpeeds",
            Self::DtEnumDetectors => "DtEnumDetectors",
            Self::DtSelect { .. } => "DtSelect",
            Self::DtEnable { .. } => "DtEnable",
            Self::DtGetSelected { .. } => "DtGetSelected",
            Self::DtGetEnabled { .. } => "DtGetEnabled",
            Self::ScScanXY(_) => "ScScanXY",
            Self::ScStopScan => "ScStopScan",
            Self::IsBusy { .. } => "IsBusy",
            Self::GetDeviceParams { .. } => "GetDeviceParams",
        }
    }

    /// Whether the function returns a value: the server answers it even without
    /// [`Flags::SEND_RESPONSE`]. Void functions answer only with that flag.
    #[must_use]
    pub fn returns_value(&self) -> bool {
        !matches!(
            self,
            Self::StgMoveTo(_)
                | Self::StgStop
                | Self::SetViewField { .. }
                | Self::DtSelect { .. }
                | Self::DtEnable { .. }
                | Self::ScStopScan
        )
    }

    /// The arguments, encoded.
    #[must_use]
    pub fn body(&self) -> Vec<u8> {
        let mut w = BodyWriter::new();
        match self {
            Self::TcpRegDataPort { port } => {
                w.uint(*port);
            }
            Self::StgMoveTo(axes) => {
                for &v in axes {
                    w.float(v);
                }
            }
            Self::StgGetLimits { kind } => {
                w.int(*kind);
            }
            Self::SetViewField { mm } => {
                w.float(*mm);
            }
            Self::DtSelect { channel, detector } => {
                w.int(*channel).int(*detector);
            }
            Self::DtEnable {
                channel,
                enable,
                bpp,
            } => {
                w.int(*channel).int(*enable);
                if let Some(bpp) = bpp {
                    w.int(*bpp);
                }
            }
            Self::DtGetSelected { channel } | Self::DtGetEnabled { channel } => {
                w.int(*channel);
            }
            Self::ScScanXY(s) => {
                w.uint(s.frame_id)
                    .uint(s.width)
                    .uint(s.height)
                    .uint(s.left)
                    .uint(s.top)
                    .uint(s.right)
                    .uint(s.bottom)
                    .int(s.single);
                if let Some(d) = s.dwell_ns {
                    w.uint(d);
                }
            }
            Self::IsBusy { mask } => {
                w.uint(*mask);
            }
            Self::GetDeviceParams { set } => {
                w.uint(*set);
            }
            Self::TcpGetVersion
            | Self::TcpGetSwVersion
            | Self::TcpGetDevice
            | Self::TcpGetModel
            | Self::StgGetPosition
            | Self::StgIsBusy
            | Self::StgStop
            | Self::StgIsCalibrated
            | Self::GetViewField
            | Self::ScEnumSpeeds
            | Self::DtEnumDetectors
            | Self::ScStopScan => {}
        }
        w.finish()
    }

    /// The whole message: header (with `id`, `flags`, queue 0) and body.
    #[must_use]
    pub fn encode(&self, id: u32, flags: Flags) -> Vec<u8> {
        let body = self.body();
        let header = Header {
            name: FnName::new(self.name())
                .unwrap_or_else(|e| unreachable!("built-in function name: {e}")),
            body_size: u32::try_from(body.len()).unwrap_or(u32::MAX),
            id,
            flags,
            queue: 0,
        };
        let mut out = Vec::with_capacity(HEADER_LEN + body.len());
        out.extend_from_slice(&header.encode());
        out.extend_from_slice(&body);
        out
    }

    /// Server side: the request named `name` with arguments `body`. Only
    /// trailing optional arguments may be missing; extra bytes are wrong arguments.
    ///
    /// # Errors
    /// [`DecodeError`]: the server ignores such a request silently.
    pub fn decode(name: &str, body: &[u8]) -> Result<Self, DecodeError> {
        let mut r = BodyReader::new(body);
        let parsed = match name {
            "TcpGetVersion" => Ok(Self::TcpGetVersion),
            "TcpGetSWVersion" => Ok(Self::TcpGetSwVersion),
            "TcpGetDevice" => Ok(Self::TcpGetDevice),
            "TcpGetModel" => Ok(Self::TcpGetModel),
            "TcpRegDataPort" => r.uint().map(|port| Self::TcpRegDataPort { port }),
            "StgGetPosition" => Ok(Self::StgGetPosition),
            "StgMoveTo" => decode_axes(&mut r).map(Self::StgMoveTo),
            "StgIsBusy" => Ok(Self::StgIsBusy),
            "StgGetLimits" => r.int().map(|kind| Self::StgGetLimits { kind }),
            "StgStop" => Ok(Self::StgStop),
            "StgIsCalibrated" => Ok(Self::StgIsCalibrated),
            "GetViewField" => Ok(Self::GetViewField),
            "SetViewField" => r.float().map(|mm| Self::SetViewField { mm }),
            "ScEnumSpeeds" => Ok(Self::ScEnumSpeeds),
            "DtEnumDetectors" => Ok(Self::DtEnumDetectors),
            "DtSelect" => (|| {
                Ok(Self::DtSelect {
                    channel: r.int()?,
                    detector: r.int()?,
                })
            })(),
            "DtEnable" => (|| {
                let (channel, enable) = (r.int()?, r.int()?);
                let bpp = if r.is_empty() { None } else { Some(r.int()?) };
                Ok(Self::DtEnable {
                    channel,
                    enable,
                    bpp,
                })
            })(),
            "DtGetSelected" => r.int().map(|channel| Self::DtGetSelected { channel }),
            "DtGetEnabled" => r.int().map(|channel| Self::DtGetEnabled { channel }),
            "ScScanXY" => decode_scan(&mut r).map(Self::ScScanXY),
            "ScStopScan" => Ok(Self::ScStopScan),
            "IsBusy" => r.uint().map(|mask| Self::IsBusy { mask }),
            "GetDeviceParams" => r.uint().map(|set| Self::GetDeviceParams { set }),
            other => return Err(DecodeError::UnknownFunction(other.to_owned())),
        };
        let bad = |source| DecodeError::BadArguments {
            name: name.to_owned(),
            source,
        };
        let request = parsed.map_err(bad)?;
        r.end().map_err(bad)?;
        Ok(request)
    }
}

fn decode_axes(r: &mut BodyReader<'_>) -> Result<Vec<f64>, BodyError> {
    let mut axes = Vec::new();
    while !r.is_empty() {
        if axes.len() == MAX_STAGE_AXES {
            return Err(BodyError::Trailing(r.remaining()));
        }
        axes.push(r.float()?);
    }
    if axes.is_empty() {
        return Err(BodyError::Count {
            what: "StgMoveTo",
            expected: "1 to 6",
            got: 0,
        });
    }
    Ok(axes)
}

fn decode_scan(r: &mut BodyReader<'_>) -> Result<ScanXY, BodyError> {
    let mut s = ScanXY {
        frame_id: r.uint()?,
        width: r.uint()?,
        height: r.uint()?,
        left: r.uint()?,
        top: r.uint()?,
        right: r.uint()?,
        bottom: r.uint()?,
        single: r.int()?,
        dwell_ns: None,
    };
    if !r.is_empty() {
        s.dwell_ns = Some(r.uint()?);
    }
    Ok(s)
}

impl fmt::Display for Request {
    /// The function and its arguments in text, as `/stage/io` records them:
    /// `StgMoveTo(x=1, y=2, z=0, rotation=0, tilt=5)`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let name = self.name();
        match self {
            Self::TcpRegDataPort { port } => write!(f, "{name}(port={port})"),
            Self::StgMoveTo(axes) => {
                const AXES: [&str; MAX_STAGE_AXES] = ["x", "y", "z", "rotation", "tilt", "tilt_y"];
                let args: Vec<String> = AXES
                    .iter()
                    .zip(axes)
                    .map(|(n, v)| format!("{n}={}", format_float(*v)))
                    .collect();
                write!(f, "{name}({})", args.join(", "))
            }
            Self::StgGetLimits { kind } => write!(f, "{name}(type={kind})"),
            Self::SetViewField { mm } => write!(f, "{name}(mm={})", format_float(*mm)),
            Self::DtSelect { channel, detector } => {
                write!(f, "{name}(channel={channel}, detector={detector})")
            }
            Self::DtEnable {
                channel,
                enable,
                bpp,
            } => match bpp {
                Some(b) => write!(f, "{name}(channel={channel}, enable={enable}, bpp={b})"),
                None => write!(f, "{name}(channel={channel}, enable={enable})"),
            },
            Self::DtGetSelected { channel } | Self::DtGetEnabled { channel } => {
                write!(f, "{name}(channel={channel})")
            }
            Self::ScScanXY(s) => {
                write!(
                    f,
                    "{name}(frame={}, width={}, height={}, left={}, top={}, right={}, bottom={}, single={}",
                    s.frame_id, s.width, s.height, s.left, s.top, s.right, s.bottom, s.single
                )?;
                if let Some(d) = s.dwell_ns {
                    write!(f, ", dwell_ns={d}")?;
                }
                f.write_str(")")
            }
            Self::IsBusy { mask } => write!(f, "{name}(mask=0x{mask:04X})"),
            Self::GetDeviceParams { set } => write!(f, "{name}(set={set})"),
            _ => write!(f, "{name}()"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn all() -> Vec<Request> {
        vec![
            Request::TcpGetVersion,
            Request::TcpGetSwVersion,
            Request::TcpGetDevice,
            Request::TcpGetModel,
            Request::TcpRegDataPort { port: 50123 },
            Request::StgGetPosition,
            Request::StgMoveTo(vec![1.5, -2.0, 10.0, 0.0, 7.0]),
            Request::StgMoveTo(vec![0.25]),
            Request::StgIsBusy,
            Request::StgGetLimits { kind: 1 },
            Request::StgStop,
            Request::StgIsCalibrated,
            Request::GetViewField,
            Request::SetViewField { mm: 0.128 },
            Request::ScEnumSpeeds,
            Request::DtEnumDetectors,
            Request::DtSelect {
                channel: 0,
                detector: 3,
            },
            Request::DtEnable {
                channel: 0,
                enable: 1,
                bpp: Some(16),
            },
            Request::DtEnable {
                channel: 1,
                enable: 0,
                bpp: None,
            },
            Request::DtGetSelected { channel: 0 },
            Request::DtGetEnabled { channel: 0 },
            Request::ScScanXY(ScanXY::full_frame(9, 320, 240, 1000)),
            Request::ScScanXY(ScanXY {
                dwell_ns: None,
                ..ScanXY::full_frame(1, 8, 8, 1)
            }),
            Request::ScStopScan,
            Request::IsBusy { mask: 1 << 9 },
            Request::GetDeviceParams { set: 1 },
        ]
    }

    #[test]
    fn every_request_round_trips_through_its_bytes() {
        for req in all() {
            let bytes = req.encode(42, Flags::WAIT_B);
            let mut head = [0u8; HEADER_LEN];
            head.copy_from_slice(&bytes[..HEADER_LEN]);
            let h = Header::decode(&head).unwrap();
            assert_eq!(h.name.as_str(), req.name());
            assert_eq!(h.body_size as usize, bytes.len() - HEADER_LEN);
            assert_eq!((h.id, h.flags), (42, Flags::WAIT_B));
            assert_eq!(
                Request::decode(req.name(), &bytes[HEADER_LEN..]),
                Ok(req.clone())
            );
        }
    }

    #[test]
    fn scan_xy_body_is_eight_u32_and_the_dwell() {
        let b = Request::ScScanXY(ScanXY::full_frame(9, 320, 240, 1000)).body();
        let words: Vec<u32> = b
            .chunks(4)
            .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(words, [9, 320, 240, 0, 0, 319, 239, 1, 1000]);
    }

    #[test]
    fn stage_move_keeps_rotation_before_tilt_in_text_and_bytes() {
        let r = Request::StgMoveTo(vec![1.0, 2.0, 3.0, 45.0, -5.0]);
        assert_eq!(
            r.to_string(),
            "StgMoveTo(x=1, y=2, z=3, rotation=45, tilt=-5)"
        );
        let body = r.body();
        let mut rd = BodyReader::new(&body);
        let v: Vec<f64> = (0..5).map(|_| rd.float().unwrap()).collect();
        assert_eq!(v, [1.0, 2.0, 3.0, 45.0, -5.0]);
    }

    #[test]
    fn wrong_arguments_and_unknown_functions_are_told_apart() {
        assert_eq!(
            Request::decode("StgGoTo", &[]),
            Err(DecodeError::UnknownFunction("StgGoTo".into()))
        );
        let e = Request::decode("DtSelect", &[0, 0, 0, 0]).unwrap_err();
        assert!(
            matches!(&e, DecodeError::BadArguments { name, .. } if name == "DtSelect"),
            "{e}"
        );
        let e = Request::decode("StgIsBusy", &[0, 0, 0, 0]).unwrap_err();
        assert!(e.to_string().contains("unexpected bytes"), "{e}");
        assert!(
            Request::decode("StgMoveTo", &[]).is_err(),
            "at least one axis"
        );
        let seven: Vec<u8> = {
            let mut w = BodyWriter::new();
            for _ in 0..7 {
                w.float(1.0);
            }
            w.finish()
        };
        assert!(
            Request::decode("StgMoveTo", &seven).is_err(),
            "at most six axes"
        );
    }

    #[test]
    fn void_functions_are_known() {
        assert!(!Request::StgMoveTo(vec![0.0]).returns_value());
        assert!(!Request::ScStopScan.returns_value());
        assert!(Request::ScScanXY(ScanXY::full_frame(1, 2, 2, 1)).returns_value());
        assert!(Request::TcpRegDataPort { port: 1 }.returns_value());
    }

    #[test]
    fn regions_are_checked() {
        let s = ScanXY::full_frame(1, 320, 240, 100);
        assert_eq!(s.region_pixels(), Some(320 * 240));
        assert_eq!(ScanXY { right: 320, ..s }.region_pixels(), None);
        assert_eq!(
            ScanXY {
                left: 200,
                right: 100,
                ..s
            }
            .region_pixels(),
            None
        );
        assert_eq!(
            ScanXY {
                left: 10,
                right: 19,
                top: 5,
                bottom: 5,
                ..s
            }
            .region_pixels(),
            Some(10)
        );
    }
}
