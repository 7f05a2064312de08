//! TESCAN SharkSEM remote control (sans-IO): the subset sdsem needs for the
//! stage and for imaging, both sides of the link.
//!
//! Facts from TESCAN's "SharkSEM Remote Control" manual 2.0.25 [TS-PDF], the
//! C# library 3.2.20 docs [TS-CS] and TESCAN's Python client [TS-PY]
//! (`/work/shared/VENDORS.md` §2):
//!
//! - TCP; the SEM is the server. Control port 8300, data port 8301 (= control + 1).
//!   The client binds its data socket, registers that local port with
//!   `TcpRegDataPort`, then connects the data socket *from* it.
//! - Every message, both ways and on both channels, is a 32-byte little-endian
//!   [`Header`] (function name, body size, id, [`Flags`], queue) and a body
//!   ([`body`]): ints, arrays with a byte count padded to 4, NUL-terminated
//!   strings, floats as `strtod` strings, maps as `key=value` lines.
//! - A function answers only if it returns a value, or if the request sets
//!   [`Flags::SEND_RESPONSE`]. The response carries the request's name and id.
//! - Wait flags A–G (header bits 8–14) hold a request until the condition is clear
//!   (A scanning, B stage, C optics, D auto-procedure, E–G the same for the FIB).
//! - Bad input is ignored silently: an unknown function, wrong arguments or a
//!   malformed message get no reply; the client sees only its own timeout.
//! - Images arrive as [`SC_DATA`] chunks on the data channel about every 50 ms;
//!   [`FrameAssembler`] puts them together.
//!
//! Client side: [`Request::encode`], [`Request::decode_response`],
//! [`MessageFramer`], [`FrameAssembler`]. Server side (the simulator):
//! [`MessageFramer`], [`Request::decode`], [`Response::encode`], [`DataChunk::encode`].

pub mod body;
mod data;
mod framer;
mod header;
mod request;
mod response;

pub use body::{BodyError, BodyReader, BodyWriter};
pub use data::{AssembleError, AssemblyStats, DataChunk, FrameAssembler, Progress, SC_DATA, Skip};
pub use framer::{FrameError, MAX_BODY, Message, MessageFramer};
pub use header::{Flags, FnName, HEADER_LEN, Header, HeaderError, MAX_NAME_LEN};
pub use request::{DecodeError, MAX_STAGE_AXES, Request, ScanXY};
pub use response::{Detector, Response, ScanSpeed, StageLimits, StagePosition};

/// The control port of a SharkSEM server unless changed in the SEM software.
pub const DEFAULT_CONTROL_PORT: u16 = 8300;

/// A protocol version such as "2.0.22", compared numerically.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Version(pub u32, pub u32, pub u32);

impl Version {
    /// `ScScanXY` takes the dwell time; `GetDeviceParams` exists.
    pub const DWELL_ARGUMENT: Self = Self(2, 0, 6);
    /// `IsBusy` and `TcpGetSWVersion` exist.
    pub const IS_BUSY: Self = Self(2, 0, 9);
    /// `StgGetLimits` exists.
    pub const STAGE_LIMITS: Self = Self(2, 0, 22);
    /// `TcpGetModel` exists; 3.x stages may report tilt-Y.
    pub const MODEL: Self = Self(3, 2, 20);

    /// Parses the leading `major.minor.patch` of a version string (missing parts are 0,
    /// anything after a fourth dot or a non-digit is ignored). None without a major number.
    #[must_use]
    pub fn parse(s: &str) -> Option<Self> {
        let mut parts = s.trim().split('.').map(|p| {
            let digits: String = p.chars().take_while(char::is_ascii_digit).collect();
            digits.parse::<u32>().ok()
        });
        let major = parts.next().flatten()?;
        let minor = parts.next().flatten().unwrap_or(0);
        let patch = parts.next().flatten().unwrap_or(0);
        Some(Self(major, minor, patch))
    }
}

impl std::fmt::Display for Version {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}.{}.{}", self.0, self.1, self.2)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A whole conversation (requests, responses, data) fed to one framer one
    /// byte at a time decodes to what was sent; every truncation of each body
    /// fails or decodes without panicking.
    #[test]
    fn a_conversation_decodes_byte_by_byte_and_truncations_never_panic() {
        let exchanges = [
            (Request::TcpGetVersion, Response::Text("2.0.25".into())),
            (
                Request::StgGetPosition,
                Response::Position(StagePosition::default()),
            ),
            (Request::GetViewField, Response::ViewField(0.256)),
            (
                Request::DtEnumDetectors,
                Response::Detectors(vec![Detector {
                    index: 0,
                    name: "SE".into(),
                    id: 0,
                }]),
            ),
            (
                Request::ScScanXY(ScanXY::full_frame(1, 4, 2, 100)),
                Response::Int(0),
            ),
        ];
        let mut stream = Vec::new();
        for (i, (req, resp)) in exchanges.iter().enumerate() {
            let id = u32::try_from(i).unwrap();
            stream.extend(req.encode(id, Flags::NONE));
            stream.extend(resp.encode(&FnName::new(req.name()).unwrap(), id, 0));
        }
        let chunk = DataChunk {
            frame_id: 1,
            channel: 0,
            index: 0,
            bpp: 16,
            data: vec![0; 16],
        };
        stream.extend(chunk.encode());
        let mut framer = MessageFramer::new();
        let mut messages = Vec::new();
        for b in &stream {
            framer.push(std::slice::from_ref(b));
            while let Some(m) = framer.next_message() {
                messages.push(m.unwrap());
            }
        }
        assert_eq!(messages.len(), 2 * exchanges.len() + 1);
        for (i, (req, resp)) in exchanges.iter().enumerate() {
            let (q, a) = (&messages[2 * i], &messages[2 * i + 1]);
            assert_eq!(
                &Request::decode(q.header.name.as_str(), &q.body).unwrap(),
                req
            );
            assert_eq!(a.header.name.as_str(), req.name());
            assert_eq!(&req.decode_response(&a.body).unwrap(), resp);
            for cut in 0..a.body.len() {
                let _ = req.decode_response(&a.body[..cut]);
            }
        }
        let mut asm = FrameAssembler::new(1, 0, 16, 8);
        assert_eq!(
            asm.push(&messages[messages.len() - 1]),
            Ok(Progress::Complete)
        );
    }

    #[test]
    fn versions_compare_numerically() {
        assert_eq!(Version::parse("2.0.22"), Some(Version(2, 0, 22)));
        assert_eq!(Version::parse("3.2.20.1"), Some(Version(3, 2, 20)));
        assert_eq!(Version::parse("4"), Some(Version(4, 0, 0)));
        assert_eq!(Version::parse("x"), None);
        assert!(Version(2, 0, 22) > Version(2, 0, 9));
        assert!(Version::parse("2.0.9").unwrap() < Version::STAGE_LIMITS);
    }
}
