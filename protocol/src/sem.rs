//! SEM imaging link protocol (sans-IO).
//!
//! A small vendor-style line protocol over TCP between `sdsem` (client) and the
//! microscope's imaging server (the simulator's `sem_server`, or an adapter
//! in front of a real SEM's remote-control interface). This module only turns
//! typed values into bytes and bytes into typed values; it does no I/O, so
//! both sides share it and are tested by feeding bytes one at a time.
//!
//! # Framing
//! - One client at a time; the client sends one request and reads its reply
//!   before sending the next.
//! - A request is one ASCII line ending in LF (a CR before it is ignored),
//!   tokens separated by spaces, at most [`MAX_LINE`] bytes.
//! - A reply is one ASCII header line ending in LF. The replies `FRAME` and
//!   `HEIGHTMAP` are followed by exactly `<nbytes>` bytes of binary payload.
//!
//! # Requests and replies
//! | request | reply |
//! | --- | --- |
//! | `*IDN?` | `IDN <vendor>,<model>,<serial>,<version>` |
//! | `PIXELSIZE? <width>` | `PIXELSIZE <width> <µm>`: the pixel size of a frame `width` pixels wide at the current magnification |
//! | `GRAB <width> <height> <dwell_us> <role> [<bits>]` | `FRAME <width> <height> <bits> <nbytes> <json>` + payload |
//! | `GROUNDTRUTH <frame>` | `HEIGHTMAP <width> <height> 32 <nbytes> <json>` + payload (simulator only) |
//! | `GROUNDTRUTH <frame> <path>` | `OK GROUNDTRUTH <frame> <path>` after writing the map as a Gwyddion GSF file at `path` on the server's machine (simulator only; the path is the rest of the line) |
//! | anything wrong | `ERR <code> <message>` |
//!
//! - `GRAB`: `role` is `tracking`, `left` or `right` (recorded in the metadata,
//!   it changes nothing in the scan); `dwell_us` is the pixel dwell time in µs
//!   (0 < dwell ≤ 10 000); `bits` is `16` (default) or `8`. The server scans
//!   the frame (taking width × height × dwell) at the stage pose of the start
//!   of the scan. The payload is row-major, x right, y down, unsigned
//!   little-endian samples of `bits` bits: `nbytes = width·height·bits/8`.
//! - `<json>` is one line of JSON, [`FrameMeta`]: frame number, role, pixel
//!   size (µm), dwell (µs), stage X/Y (µm) and tilt (°) at the start of the
//!   scan, tilt-axis direction and scan rotation (°), scan start and end (ns
//!   since the Unix epoch). Readers ignore keys they do not know, so the
//!   server may add some.
//! - `HEIGHTMAP`: the true height (µm, up towards the beam) of the surface
//!   seen at each pixel of frame `<frame>`, row-major little-endian `f32`,
//!   NaN where the beam missed the specimen; `<json>` is that frame's metadata.
//! - Error codes ([`ErrorCode`]): `1` unknown command, `2` bad or missing
//!   argument, `3` unknown frame number, `4` the server could not write a
//!   file, `5` internal error. The message is human-readable.
//!
//! Widths and heights are 1 ‥ [`MAX_SIDE`].

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

/// Longest request or reply header line, bytes (the LF included).
pub const MAX_LINE: usize = 8192;
/// Largest frame side, pixels.
pub const MAX_SIDE: u32 = 16384;
/// Longest pixel dwell, µs.
pub const MAX_DWELL_US: f64 = 10_000.0;

/// What a frame is for. Recorded with the frame; the scan is the same.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// A quick frame after a tilt step, to follow the specimen.
    Tracking,
    /// The full-quality micrograph at the lower tilt.
    Left,
    /// The full-quality micrograph at the higher tilt.
    Right,
}

impl Role {
    /// The wire spelling.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Tracking => "tracking",
            Self::Left => "left",
            Self::Right => "right",
        }
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Role {
    type Err = ();

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "tracking" => Ok(Self::Tracking),
            "left" => Ok(Self::Left),
            "right" => Ok(Self::Right),
            _ => Err(()),
        }
    }
}

/// Sample depth of a frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Bits {
    #[serde(rename = "8")]
    Eight,
    #[default]
    #[serde(rename = "16")]
    Sixteen,
}

impl Bits {
    /// Bits per sample.
    #[must_use]
    pub fn count(self) -> u32 {
        match self {
            Self::Eight => 8,
            Self::Sixteen => 16,
        }
    }

    /// Bytes per sample.
    #[must_use]
    pub fn bytes(self) -> usize {
        match self {
            Self::Eight => 1,
            Self::Sixteen => 2,
        }
    }

    fn parse(s: &str) -> Option<Self> {
        match s {
            "8" => Some(Self::Eight),
            "16" => Some(Self::Sixteen),
            _ => None,
        }
    }
}

/// `GRAB`: scan one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GrabRequest {
    pub width: u32,
    pub height: u32,
    /// Pixel dwell time, µs.
    pub dwell_us: f64,
    pub role: Role,
    pub bits: Bits,
}

impl GrabRequest {
    /// Time the scan takes at the microscope's own pace: width × height × dwell, seconds.
    #[must_use]
    pub fn scan_seconds(&self) -> f64 {
        f64::from(self.width) * f64::from(self.height) * self.dwell_us * 1e-6
    }
}

/// A request from the client.
#[derive(Clone, Debug, PartialEq)]
pub enum Request {
    /// `*IDN?`
    Identify,
    /// `PIXELSIZE? <width>`
    PixelSize { width: u32 },
    /// `GRAB …`
    Grab(GrabRequest),
    /// `GROUNDTRUTH <frame> [<path>]`
    GroundTruth { frame: u64, path: Option<String> },
}

/// A request line the server cannot accept; [`RequestError::code`] gives the
/// `ERR` code to answer with.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RequestError {
    #[error("unknown command {command:?}: expected *IDN?, PIXELSIZE?, GRAB or GROUNDTRUTH")]
    UnknownCommand { command: String },
    #[error("{command}: {reason}")]
    BadArgument {
        command: &'static str,
        reason: String,
    },
    #[error("request line longer than {limit} bytes")]
    LineTooLong { limit: usize },
    #[error("request line is not ASCII text")]
    NotText,
}

impl RequestError {
    /// The error code the server answers with.
    #[must_use]
    pub fn code(&self) -> ErrorCode {
        match self {
            Self::UnknownCommand { .. } => ErrorCode::UnknownCommand,
            Self::BadArgument { .. } | Self::LineTooLong { .. } | Self::NotText => {
                ErrorCode::BadArgument
            }
        }
    }
}

fn bad(command: &'static str, reason: impl Into<String>) -> RequestError {
    RequestError::BadArgument {
        command,
        reason: reason.into(),
    }
}

fn parse_side(command: &'static str, what: &str, token: Option<&str>) -> Result<u32, RequestError> {
    let token = token.ok_or_else(|| bad(command, format!("missing {what}")))?;
    match token.parse::<u32>() {
        Ok(v) if (1..=MAX_SIDE).contains(&v) => Ok(v),
        _ => Err(bad(
            command,
            format!("{what} {token:?} is not a whole number from 1 to {MAX_SIDE}"),
        )),
    }
}

impl Request {
    /// Parses one request line (without its LF).
    ///
    /// # Errors
    /// [`RequestError`] naming what is wrong.
    pub fn parse(line: &str) -> Result<Self, RequestError> {
        let line = line.trim_end_matches('\r').trim();
        let mut tokens = line.split_whitespace();
        let command = tokens.next().unwrap_or("");
        let request = match command {
            "*IDN?" => Self::Identify,
            "PIXELSIZE?" => Self::PixelSize {
                width: parse_side("PIXELSIZE?", "width", tokens.next())?,
            },
            "GRAB" => {
                let width = parse_side("GRAB", "width", tokens.next())?;
                let height = parse_side("GRAB", "height", tokens.next())?;
                let dwell = tokens
                    .next()
                    .ok_or_else(|| bad("GRAB", "missing dwell_us"))?;
                let dwell_us = match dwell.parse::<f64>() {
                    Ok(d) if d > 0.0 && d <= MAX_DWELL_US => d,
                    _ => {
                        return Err(bad(
                            "GRAB",
                            format!("dwell_us {dwell:?} is not a number in (0, {MAX_DWELL_US}]"),
                        ));
                    }
                };
                let role = tokens.next().ok_or_else(|| bad("GRAB", "missing role"))?;
                let role = role.parse::<Role>().map_err(|()| {
                    bad(
                        "GRAB",
                        format!("role {role:?} is not tracking, left or right"),
                    )
                })?;
                let bits = match tokens.next() {
                    None => Bits::Sixteen,
                    Some(b) => Bits::parse(b)
                        .ok_or_else(|| bad("GRAB", format!("bits {b:?} is not 8 or 16")))?,
                };
                Self::Grab(GrabRequest {
                    width,
                    height,
                    dwell_us,
                    role,
                    bits,
                })
            }
            "GROUNDTRUTH" => {
                let rest = line["GROUNDTRUTH".len()..].trim_start();
                let (frame, path) = rest.split_once(char::is_whitespace).unwrap_or((rest, ""));
                let frame = frame.parse::<u64>().map_err(|_| {
                    bad(
                        "GROUNDTRUTH",
                        format!("frame number {frame:?} is not a whole number"),
                    )
                })?;
                let path = path.trim();
                Self::GroundTruth {
                    frame,
                    path: (!path.is_empty()).then(|| path.to_owned()),
                }
            }
            other => {
                return Err(RequestError::UnknownCommand {
                    command: other.to_owned(),
                });
            }
        };
        if !matches!(request, Self::GroundTruth { .. })
            && let Some(extra) = tokens.next()
        {
            return Err(bad(
                command_name(&request),
                format!("unexpected argument {extra:?}"),
            ));
        }
        Ok(request)
    }

    /// The request line, LF included.
    #[must_use]
    pub fn encode(&self) -> Vec<u8> {
        let line = match self {
            Self::Identify => "*IDN?".to_owned(),
            Self::PixelSize { width } => format!("PIXELSIZE? {width}"),
            Self::Grab(g) => format!(
                "GRAB {} {} {} {} {}",
                g.width,
                g.height,
                g.dwell_us,
                g.role,
                g.bits.count()
            ),
            Self::GroundTruth { frame, path: None } => format!("GROUNDTRUTH {frame}"),
            Self::GroundTruth {
                frame,
                path: Some(path),
            } => format!("GROUNDTRUTH {frame} {path}"),
        };
        let mut out = line.into_bytes();
        out.push(b'\n');
        out
    }
}

fn command_name(r: &Request) -> &'static str {
    match r {
        Request::Identify => "*IDN?",
        Request::PixelSize { .. } => "PIXELSIZE?",
        Request::Grab(_) => "GRAB",
        Request::GroundTruth { .. } => "GROUNDTRUTH",
    }
}

/// Splits the server's input into request lines.
#[derive(Debug, Default)]
pub struct RequestDecoder {
    buf: Vec<u8>,
    /// Dropping the rest of an over-long line.
    discarding: bool,
}

impl RequestDecoder {
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// The next complete request, `None` until a whole line has arrived. A bad
    /// line yields an error once and decoding goes on with the next line.
    pub fn next_request(&mut self) -> Option<Result<Request, RequestError>> {
        loop {
            let Some(end) = self.buf.iter().position(|&b| b == b'\n') else {
                if self.buf.len() > MAX_LINE {
                    self.buf.clear();
                    if !self.discarding {
                        self.discarding = true;
                        return Some(Err(RequestError::LineTooLong { limit: MAX_LINE }));
                    }
                }
                return None;
            };
            let line: Vec<u8> = self.buf.drain(..=end).collect();
            if self.discarding {
                // The tail of a line already reported as too long.
                self.discarding = false;
                continue;
            }
            if line.len() > MAX_LINE {
                return Some(Err(RequestError::LineTooLong { limit: MAX_LINE }));
            }
            let Ok(text) = std::str::from_utf8(&line[..line.len() - 1]) else {
                return Some(Err(RequestError::NotText));
            };
            if text.trim().is_empty() {
                continue;
            }
            return Some(Request::parse(text));
        }
    }
}

/// The metadata of a frame, sent as JSON in `FRAME` and `HEIGHTMAP` headers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameMeta {
    /// Frame number, counting from 1 since the server started.
    pub frame: u64,
    pub role: Role,
    /// Pixel size, µm.
    pub pixel_size_um: f64,
    /// Pixel dwell, µs.
    pub dwell_us: f64,
    /// Stage pose at the start of the scan.
    pub stage_x_um: f64,
    pub stage_y_um: f64,
    pub tilt_deg: f64,
    /// Direction of the tilt axis in the image (DESIGN §3), degrees.
    pub tilt_axis_deg: f64,
    /// Scan rotation, degrees.
    pub scan_rotation_deg: f64,
    /// Scan start and end, ns since the Unix epoch.
    pub scan_start_unix_ns: u64,
    pub scan_end_unix_ns: u64,
}

/// Error codes of `ERR` replies.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ErrorCode {
    UnknownCommand,
    BadArgument,
    UnknownFrame,
    FileError,
    Internal,
    /// A code this version does not know.
    Other(u16),
}

impl ErrorCode {
    /// The number on the wire.
    #[must_use]
    pub fn number(self) -> u16 {
        match self {
            Self::UnknownCommand => 1,
            Self::BadArgument => 2,
            Self::UnknownFrame => 3,
            Self::FileError => 4,
            Self::Internal => 5,
            Self::Other(n) => n,
        }
    }

    /// The code of a number.
    #[must_use]
    pub fn from_number(n: u16) -> Self {
        match n {
            1 => Self::UnknownCommand,
            2 => Self::BadArgument,
            3 => Self::UnknownFrame,
            4 => Self::FileError,
            5 => Self::Internal,
            n => Self::Other(n),
        }
    }
}

/// A scanned frame.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameReply {
    pub width: u32,
    pub height: u32,
    pub bits: Bits,
    pub meta: FrameMeta,
    /// Row-major little-endian samples.
    pub data: Vec<u8>,
}

impl FrameReply {
    /// Builds a 16-bit frame from samples.
    #[must_use]
    pub fn from_u16(width: u32, height: u32, meta: FrameMeta, samples: &[u16]) -> Self {
        Self {
            width,
            height,
            bits: Bits::Sixteen,
            meta,
            data: samples.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }

    /// Builds an 8-bit frame from samples.
    #[must_use]
    pub fn from_u8(width: u32, height: u32, meta: FrameMeta, samples: Vec<u8>) -> Self {
        Self {
            width,
            height,
            bits: Bits::Eight,
            meta,
            data: samples,
        }
    }

    /// The samples widened to 16 bits (8-bit samples are not rescaled).
    #[must_use]
    pub fn samples_u16(&self) -> Vec<u16> {
        match self.bits {
            Bits::Eight => self.data.iter().map(|&b| u16::from(b)).collect(),
            Bits::Sixteen => self
                .data
                .chunks_exact(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .collect(),
        }
    }
}

/// The true height map of a frame (simulator only).
#[derive(Clone, Debug, PartialEq)]
pub struct HeightMapReply {
    pub width: u32,
    pub height: u32,
    pub meta: FrameMeta,
    /// Row-major little-endian `f32`, µm, NaN where unknown.
    pub data: Vec<u8>,
}

impl HeightMapReply {
    /// Builds the reply from heights.
    #[must_use]
    pub fn from_f32(width: u32, height: u32, meta: FrameMeta, heights: &[f32]) -> Self {
        Self {
            width,
            height,
            meta,
            data: heights.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }

    /// The heights, µm.
    #[must_use]
    pub fn heights(&self) -> Vec<f32> {
        self.data
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    }
}

/// A reply from the server.
#[derive(Clone, Debug, PartialEq)]
pub enum Reply {
    /// `IDN <text>`
    Identity(String),
    /// `PIXELSIZE <width> <µm>`
    PixelSize { width: u32, pixel_size_um: f64 },
    /// `FRAME …` + payload
    Frame(FrameReply),
    /// `HEIGHTMAP …` + payload
    HeightMap(HeightMapReply),
    /// `OK <text>`
    Ok(String),
    /// `ERR <code> <message>`
    Error { code: ErrorCode, message: String },
}

impl Reply {
    /// The header line (LF included) and the payload to send after it.
    #[must_use]
    pub fn encode(&self) -> (Vec<u8>, &[u8]) {
        let one_line = |s: &str| s.replace(['\n', '\r'], " ");
        let meta_json =
            |m: &FrameMeta| serde_json::to_string(m).unwrap_or_else(|_| "{}".to_owned());
        let (line, payload): (String, &[u8]) = match self {
            Self::Identity(text) => (format!("IDN {}", one_line(text)), &[]),
            Self::PixelSize {
                width,
                pixel_size_um,
            } => (format!("PIXELSIZE {width} {pixel_size_um}"), &[]),
            Self::Frame(f) => (
                format!(
                    "FRAME {} {} {} {} {}",
                    f.width,
                    f.height,
                    f.bits.count(),
                    f.data.len(),
                    meta_json(&f.meta)
                ),
                &f.data,
            ),
            Self::HeightMap(h) => (
                format!(
                    "HEIGHTMAP {} {} 32 {} {}",
                    h.width,
                    h.height,
                    h.data.len(),
                    meta_json(&h.meta)
                ),
                &h.data,
            ),
            Self::Ok(text) => (format!("OK {}", one_line(text)), &[]),
            Self::Error { code, message } => {
                (format!("ERR {} {}", code.number(), one_line(message)), &[])
            }
        };
        let mut head = line.into_bytes();
        head.push(b'\n');
        (head, payload)
    }

    /// Header and payload in one buffer.
    #[must_use]
    pub fn to_bytes(&self) -> Vec<u8> {
        let (mut head, payload) = self.encode();
        head.extend_from_slice(payload);
        head
    }
}

/// A reply the client cannot make sense of: the link is out of step or the
/// server speaks another protocol.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReplyError {
    #[error("malformed reply {line:?}: {reason}")]
    Malformed { line: String, reason: String },
    #[error("reply header longer than {limit} bytes: not an SEM imaging server?")]
    LineTooLong { limit: usize },
}

fn malformed(line: &str, reason: impl Into<String>) -> ReplyError {
    let mut shown = line.to_owned();
    if shown.len() > 200 {
        let mut cut = 200;
        while !shown.is_char_boundary(cut) {
            cut -= 1;
        }
        shown.truncate(cut);
        shown.push('…');
    }
    ReplyError::Malformed {
        line: shown,
        reason: reason.into(),
    }
}

/// A payload-carrying header waiting for its bytes.
#[derive(Debug)]
enum Pending {
    Frame {
        width: u32,
        height: u32,
        bits: Bits,
        meta: FrameMeta,
        nbytes: usize,
    },
    HeightMap {
        width: u32,
        height: u32,
        meta: FrameMeta,
        nbytes: usize,
    },
}

/// Decodes the client's input into replies, incrementally.
#[derive(Debug, Default)]
pub struct ReplyDecoder {
    buf: Vec<u8>,
    pending: Option<Pending>,
}

impl ReplyDecoder {
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// Appends received bytes.
    pub fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// Bytes still needed to finish the reply in progress, when known (a
    /// payload); lets the caller read large payloads in big chunks.
    #[must_use]
    pub fn payload_remaining(&self) -> Option<usize> {
        self.pending.as_ref().map(|p| {
            let n = match p {
                Pending::Frame { nbytes, .. } | Pending::HeightMap { nbytes, .. } => *nbytes,
            };
            n.saturating_sub(self.buf.len())
        })
    }

    /// The next complete reply, `Ok(None)` until enough bytes have arrived.
    ///
    /// # Errors
    /// [`ReplyError`] when the bytes are not a reply of this protocol; the
    /// decoder should then be dropped with the connection.
    pub fn next_reply(&mut self) -> Result<Option<Reply>, ReplyError> {
        if self.pending.is_none() {
            let Some(end) = self.buf.iter().position(|&b| b == b'\n') else {
                if self.buf.len() > MAX_LINE {
                    return Err(ReplyError::LineTooLong { limit: MAX_LINE });
                }
                return Ok(None);
            };
            let line: Vec<u8> = self.buf.drain(..=end).collect();
            let text = String::from_utf8_lossy(&line[..line.len() - 1]);
            let text = text.trim_end_matches('\r');
            match parse_header(text)? {
                Header::Done(reply) => return Ok(Some(reply)),
                Header::Payload(p) => self.pending = Some(p),
            }
        }
        let need = match &self.pending {
            Some(Pending::Frame { nbytes, .. } | Pending::HeightMap { nbytes, .. }) => *nbytes,
            None => return Ok(None),
        };
        if self.buf.len() < need {
            return Ok(None);
        }
        let data: Vec<u8> = self.buf.drain(..need).collect();
        let reply = match self.pending.take() {
            Some(Pending::Frame {
                width,
                height,
                bits,
                meta,
                ..
            }) => Reply::Frame(FrameReply {
                width,
                height,
                bits,
                meta,
                data,
            }),
            Some(Pending::HeightMap {
                width,
                height,
                meta,
                ..
            }) => Reply::HeightMap(HeightMapReply {
                width,
                height,
                meta,
                data,
            }),
            None => return Ok(None),
        };
        Ok(Some(reply))
    }
}

enum Header {
    Done(Reply),
    Payload(Pending),
}

fn parse_header(line: &str) -> Result<Header, ReplyError> {
    let (keyword, rest) = line.split_once(' ').unwrap_or((line, ""));
    let reply = match keyword {
        "IDN" => Reply::Identity(rest.to_owned()),
        "OK" => Reply::Ok(rest.to_owned()),
        "ERR" => {
            let (code, message) = rest.split_once(' ').unwrap_or((rest, ""));
            let code = code
                .parse::<u16>()
                .map_err(|_| malformed(line, "error code is not a number"))?;
            Reply::Error {
                code: ErrorCode::from_number(code),
                message: message.to_owned(),
            }
        }
        "PIXELSIZE" => {
            let mut t = rest.split_whitespace();
            let width = t.next().and_then(|w| w.parse::<u32>().ok());
            let size = t.next().and_then(|p| p.parse::<f64>().ok());
            match (width, size, t.next()) {
                (Some(width), Some(pixel_size_um), None)
                    if pixel_size_um.is_finite() && pixel_size_um > 0.0 =>
                {
                    Reply::PixelSize {
                        width,
                        pixel_size_um,
                    }
                }
                _ => return Err(malformed(line, "expected PIXELSIZE <width> <µm>")),
            }
        }
        "FRAME" | "HEIGHTMAP" => return payload_header(line, keyword, rest).map(Header::Payload),
        _ => return Err(malformed(line, "unknown reply keyword")),
    };
    Ok(Header::Done(reply))
}

fn payload_header(line: &str, keyword: &str, rest: &str) -> Result<Pending, ReplyError> {
    let mut parts = rest.splitn(5, ' ');
    let mut number = |what: &str| -> Result<u64, ReplyError> {
        parts
            .next()
            .and_then(|t| t.parse::<u64>().ok())
            .ok_or_else(|| malformed(line, format!("{what} is missing or not a number")))
    };
    let (width, height, bits, nbytes) = (
        number("width")?,
        number("height")?,
        number("bits")?,
        number("nbytes")?,
    );
    let json = parts
        .next()
        .ok_or_else(|| malformed(line, "metadata JSON is missing"))?;
    let meta: FrameMeta =
        serde_json::from_str(json).map_err(|e| malformed(line, format!("metadata JSON: {e}")))?;
    let side = |v: u64, what: &str| -> Result<u32, ReplyError> {
        u32::try_from(v)
            .ok()
            .filter(|v| (1..=MAX_SIDE).contains(v))
            .ok_or_else(|| malformed(line, format!("{what} {v} is outside 1..={MAX_SIDE}")))
    };
    let (width, height) = (side(width, "width")?, side(height, "height")?);
    let bytes_per_sample: u64 = match (keyword, bits) {
        ("FRAME", 8) => 1,
        ("FRAME", 16) => 2,
        ("HEIGHTMAP", 32) => 4,
        _ => {
            return Err(malformed(
                line,
                format!("{bits} bits is not valid for {keyword}"),
            ));
        }
    };
    let expected = u64::from(width) * u64::from(height) * bytes_per_sample;
    if nbytes != expected {
        return Err(malformed(
            line,
            format!("nbytes {nbytes} does not match {width}×{height}×{bits} bits = {expected}"),
        ));
    }
    // At most 16384² × 4 bytes: fits usize on any 64-bit host; checked anyway.
    let nbytes =
        usize::try_from(nbytes).map_err(|_| malformed(line, "payload too large for this host"))?;
    Ok(if keyword == "FRAME" {
        let bits = if bits == 8 {
            Bits::Eight
        } else {
            Bits::Sixteen
        };
        Pending::Frame {
            width,
            height,
            bits,
            meta,
            nbytes,
        }
    } else {
        Pending::HeightMap {
            width,
            height,
            meta,
            nbytes,
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn meta() -> FrameMeta {
        FrameMeta {
            frame: 7,
            role: Role::Left,
            pixel_size_um: 0.1,
            dwell_us: 2.5,
            stage_x_um: -3.25,
            stage_y_um: 1.0,
            tilt_deg: -5.0,
            tilt_axis_deg: 0.0,
            scan_rotation_deg: 0.0,
            scan_start_unix_ns: 1_700_000_000_000_000_000,
            scan_end_unix_ns: 1_700_000_000_100_000_000,
        }
    }

    fn decode_bytewise_requests(bytes: &[u8]) -> Vec<Result<Request, RequestError>> {
        let mut d = RequestDecoder::new();
        let mut out = Vec::new();
        for b in bytes {
            d.push(std::slice::from_ref(b));
            while let Some(r) = d.next_request() {
                out.push(r);
            }
        }
        out
    }

    #[test]
    fn requests_round_trip_byte_by_byte() {
        let requests = vec![
            Request::Identify,
            Request::PixelSize { width: 320 },
            Request::Grab(GrabRequest {
                width: 1280,
                height: 960,
                dwell_us: 12.5,
                role: Role::Right,
                bits: Bits::Sixteen,
            }),
            Request::Grab(GrabRequest {
                width: 320,
                height: 240,
                dwell_us: 0.3,
                role: Role::Tracking,
                bits: Bits::Eight,
            }),
            Request::GroundTruth {
                frame: 3,
                path: None,
            },
            Request::GroundTruth {
                frame: 4,
                path: Some("/tmp/a dir/h.gsf".to_owned()),
            },
        ];
        let bytes: Vec<u8> = requests.iter().flat_map(Request::encode).collect();
        let decoded: Vec<Request> = decode_bytewise_requests(&bytes)
            .into_iter()
            .map(Result::unwrap)
            .collect();
        assert_eq!(decoded, requests);
    }

    #[test]
    fn request_errors_name_the_problem_and_decoding_goes_on() {
        let out = decode_bytewise_requests(
            b"FOO 1\r\nGRAB 0 10 1 left\nGRAB 10 10 1 middle\nGRAB 8 8 1 left 12\n\n*IDN?\r\n",
        );
        assert_eq!(out.len(), 5);
        let e0 = out[0].clone().unwrap_err();
        assert_eq!(e0.code(), ErrorCode::UnknownCommand);
        assert!(e0.to_string().contains("\"FOO\""));
        assert!(
            out[1]
                .clone()
                .unwrap_err()
                .to_string()
                .contains("width \"0\"")
        );
        assert!(
            out[2]
                .clone()
                .unwrap_err()
                .to_string()
                .contains("role \"middle\"")
        );
        assert!(
            out[3]
                .clone()
                .unwrap_err()
                .to_string()
                .contains("bits \"12\"")
        );
        assert_eq!(out[4], Ok(Request::Identify));
        assert!(Request::parse("GRAB 8 8 0 left").is_err(), "zero dwell");
        assert!(Request::parse("GRAB 8 8 nan left").is_err());
        assert!(Request::parse("PIXELSIZE? 10 11").is_err());
        assert!(Request::parse("GROUNDTRUTH x").is_err());
    }

    #[test]
    fn over_long_lines_are_reported_once() {
        let mut bytes = vec![b'A'; MAX_LINE + 10];
        bytes.extend_from_slice(b"AAAA\n*IDN?\n");
        let out = decode_bytewise_requests(&bytes);
        assert_eq!(out.len(), 2, "{out:?}");
        assert_eq!(out[0], Err(RequestError::LineTooLong { limit: MAX_LINE }));
        assert_eq!(out[1], Ok(Request::Identify));
    }

    #[test]
    fn replies_round_trip_byte_by_byte() {
        let replies = vec![
            Reply::Identity("sdsem,virtual-sem,0,0.1.0".to_owned()),
            Reply::PixelSize {
                width: 320,
                pixel_size_um: 0.4,
            },
            Reply::Frame(FrameReply::from_u16(
                3,
                2,
                meta(),
                &[0, 1, 2, 65535, 256, 10],
            )),
            Reply::Frame(FrameReply::from_u8(2, 1, meta(), vec![b'\n', 255])),
            Reply::HeightMap(HeightMapReply::from_f32(2, 1, meta(), &[1.5, f32::NAN])),
            Reply::Ok("GROUNDTRUTH 3 /tmp/x.gsf".to_owned()),
            Reply::Error {
                code: ErrorCode::UnknownFrame,
                message: "no frame 99: frames 1 to 5 are known".to_owned(),
            },
        ];
        let bytes: Vec<u8> = replies.iter().flat_map(Reply::to_bytes).collect();
        let mut d = ReplyDecoder::new();
        let mut out = Vec::new();
        for b in &bytes {
            d.push(std::slice::from_ref(b));
            while let Some(r) = d.next_reply().unwrap() {
                out.push(r);
            }
        }
        assert_eq!(out.len(), replies.len());
        // NaN != NaN: compare the height map through its bytes.
        for (a, b) in out.iter().zip(&replies) {
            assert_eq!(format!("{a:?}"), format!("{b:?}"));
        }
        let Reply::Frame(f) = &out[2] else { panic!() };
        assert_eq!(f.samples_u16(), vec![0, 1, 2, 65535, 256, 10]);
        let Reply::HeightMap(h) = &out[4] else {
            panic!()
        };
        assert_eq!(h.heights()[0], 1.5);
        assert!(h.heights()[1].is_nan());
    }

    #[test]
    fn payload_remaining_tells_how_much_to_read() {
        let bytes = Reply::Frame(FrameReply::from_u16(4, 4, meta(), &[7; 16])).to_bytes();
        let split = bytes.iter().position(|&b| b == b'\n').unwrap() + 1;
        let mut d = ReplyDecoder::new();
        d.push(&bytes[..split + 5]);
        assert_eq!(d.next_reply(), Ok(None));
        assert_eq!(d.payload_remaining(), Some(32 - 5));
        d.push(&bytes[split + 5..]);
        assert!(matches!(d.next_reply(), Ok(Some(Reply::Frame(_)))));
        assert_eq!(d.payload_remaining(), None);
    }

    #[test]
    fn inconsistent_headers_are_rejected() {
        let json = serde_json::to_string(&meta()).unwrap();
        for bad in [
            format!("FRAME 4 4 16 31 {json}\n"),
            format!("FRAME 4 4 12 16 {json}\n"),
            format!("HEIGHTMAP 4 4 16 32 {json}\n"),
            "FRAME 4 4 16 32 {not json\n".to_owned(),
            "PIXELSIZE 10 -1\n".to_owned(),
            "HELLO\n".to_owned(),
            "ERR x boom\n".to_owned(),
        ] {
            let mut d = ReplyDecoder::new();
            d.push(bad.as_bytes());
            assert!(d.next_reply().is_err(), "accepted {bad:?}");
        }
        let mut d = ReplyDecoder::new();
        d.push(&vec![b'x'; MAX_LINE + 1]);
        assert_eq!(
            d.next_reply(),
            Err(ReplyError::LineTooLong { limit: MAX_LINE })
        );
    }

    #[test]
    fn metadata_tolerates_unknown_keys() {
        let mut v = serde_json::to_value(meta()).unwrap();
        v["detector"] = serde_json::json!("SE2");
        let line = format!("FRAME 1 1 8 1 {v}\n");
        let mut d = ReplyDecoder::new();
        d.push(line.as_bytes());
        d.push(&[9]);
        let Some(Reply::Frame(f)) = d.next_reply().unwrap() else {
            panic!()
        };
        assert_eq!(f.meta, meta());
    }

    #[test]
    fn scan_time_is_pixels_times_dwell() {
        let g = GrabRequest {
            width: 1000,
            height: 500,
            dwell_us: 2.0,
            role: Role::Left,
            bits: Bits::Sixteen,
        };
        assert!((g.scan_seconds() - 1.0).abs() < 1e-12);
    }
}
