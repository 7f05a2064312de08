//! Typed queries: the command to send and the parser of its reply.

use serde::{Deserialize, Serialize};

use super::axis::AxisId;
use super::command::Command;
use super::error_code::GcsErrorCode;
use super::reply::{BUSY_BYTE, READY_BYTE, Reply, ReplyError, escape_bytes};

/// A GCS query: what to send and how to read its answer.
pub trait Query {
    /// The typed answer.
    type Output;
    /// The command that asks.
    fn command(&self) -> Command;
    /// Reads a framed reply; an error means the reply is garbled or answers something else.
    fn parse_reply(&self, reply: &Reply) -> Result<Self::Output, ReplyError>;
}

fn real(text: &str) -> Option<f64> {
    let numeric = !text.is_empty()
        && text
            .bytes()
            .all(|b| b.is_ascii_digit() || matches!(b, b'+' | b'-' | b'.' | b'e' | b'E'));
    text.parse::<f64>()
        .ok()
        .filter(|v| numeric && v.is_finite())
}

fn flag(text: &str) -> Option<bool> {
    match text {
        "0" => Some(false),
        "1" => Some(true),
        _ => None,
    }
}

macro_rules! axis_query {
    ($(#[$doc:meta])* $name:ident, $variant:ident, $out:ty, $what:literal, $parse:expr) => {
        $(#[$doc])*
        #[derive(Clone, Debug, Default, PartialEq, Eq)]
        pub struct $name(
            /// The axes asked for; empty asks for all.
            pub Vec<AxisId>,
        );

        impl Query for $name {
            type Output = Vec<(AxisId, $out)>;
            fn command(&self) -> Command {
                Command::$variant(self.0.clone())
            }
            fn parse_reply(&self, reply: &Reply) -> Result<Self::Output, ReplyError> {
                reply.axis_lines(&self.0, $what, $parse)
            }
        }
    };
}

axis_query!(
    /// `POS?`: current positions (`1=12.500000`), in the axis units (µm, degrees).
    PositionQuery, PosQ, f64, "number", real
);
axis_query!(
    /// `ONT?`: on-target flags (`1=1` once the axis has settled on its target).
    OnTargetQuery, OntQ, bool, "0 or 1", flag
);
axis_query!(
    /// `SVO?`: servo (closed-loop) states.
    ServoQuery, SvoQ, bool, "0 or 1", flag
);
axis_query!(
    /// `FRF?`: whether each axis has been referenced.
    ReferencedQuery, FrfQ, bool, "0 or 1", flag
);
axis_query!(
    /// `TMN?`: low soft limits.
    MinLimitQuery, TmnQ, f64, "number", real
);
axis_query!(
    /// `TMX?`: high soft limits.
    MaxLimitQuery, TmxQ, f64, "number", real
);

/// `ERR?`: the last error code (reading it resets it to 0).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ErrorQuery;

impl Query for ErrorQuery {
    type Output = GcsErrorCode;
    fn command(&self) -> Command {
        Command::ErrQ
    }
    fn parse_reply(&self, reply: &Reply) -> Result<GcsErrorCode, ReplyError> {
        let line = reply.single_ascii_line("an error code")?;
        let digits = line.strip_prefix('-').unwrap_or(line);
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
            return Err(ReplyError::BadAnswer {
                line: line.to_owned(),
                what: "an error code",
            });
        }
        line.parse::<i32>()
            .map(GcsErrorCode)
            .map_err(|_| ReplyError::BadAnswer {
                line: line.to_owned(),
                what: "an error code",
            })
    }
}

/// `*IDN?`: the identification string (maker, model, serial number, firmware).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct IdentityQuery;

impl Query for IdentityQuery {
    type Output = String;
    fn command(&self) -> Command {
        Command::IdnQ
    }
    fn parse_reply(&self, reply: &Reply) -> Result<String, ReplyError> {
        let line = reply.single_ascii_line("an identification string")?;
        if line.trim().is_empty() {
            return Err(ReplyError::BadAnswer {
                line: String::new(),
                what: "an identification string",
            });
        }
        Ok(line.trim().to_owned())
    }
}

/// The answer to `#5`: bit *i* set while the *i*-th axis of the controller moves.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct MotionStatus(pub u32);

impl MotionStatus {
    /// Whether the axis at this index (0-based, controller order) is moving.
    pub fn is_moving(self, index: usize) -> bool {
        index < 32 && self.0 & (1 << index) != 0
    }

    /// Whether any axis is moving.
    pub fn any(self) -> bool {
        self.0 != 0
    }
}

/// `#5` (single byte 0x05): which axes are in motion.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MotionStatusQuery;

impl Query for MotionStatusQuery {
    type Output = MotionStatus;
    fn command(&self) -> Command {
        Command::MotionStatus
    }
    fn parse_reply(&self, reply: &Reply) -> Result<MotionStatus, ReplyError> {
        let line = reply.single_ascii_line("a hexadecimal motion bitmap")?;
        let hex = line
            .strip_prefix("0x")
            .or_else(|| line.strip_prefix("0X"))
            .unwrap_or(line);
        if hex.is_empty() || !hex.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(ReplyError::BadAnswer {
                line: line.to_owned(),
                what: "a hexadecimal motion bitmap",
            });
        }
        u32::from_str_radix(hex, 16)
            .map(MotionStatus)
            .map_err(|_| ReplyError::BadAnswer {
                line: line.to_owned(),
                what: "a hexadecimal motion bitmap",
            })
    }
}

/// `#7` (single byte 0x07): whether the controller is ready (0xB1) or busy (0xB0).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ReadyQuery;

impl Query for ReadyQuery {
    type Output = bool;
    fn command(&self) -> Command {
        Command::Ready
    }
    fn parse_reply(&self, reply: &Reply) -> Result<bool, ReplyError> {
        match reply.lines() {
            [line] if line.as_slice() == [READY_BYTE] => Ok(true),
            [line] if line.as_slice() == [BUSY_BYTE] => Ok(false),
            [line] => Err(ReplyError::BadAnswer {
                line: escape_bytes(line),
                what: "0xB1 (ready) or 0xB0 (busy)",
            }),
            lines => Err(ReplyError::LineCount {
                expected: 1,
                got: lines.len(),
            }),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::framer::ReplyFramer;
    use super::*;

    fn ax(s: &str) -> AxisId {
        AxisId::new(s).unwrap()
    }

    /// Frames `bytes` one byte at a time and expects exactly one reply.
    fn frame(bytes: &[u8]) -> Reply {
        let mut framer = ReplyFramer::new();
        let mut out: Vec<_> = bytes.iter().filter_map(|&b| framer.push(b)).collect();
        assert_eq!(out.len(), 1, "{out:?}");
        out.remove(0).expect("framing")
    }

    #[test]
    fn position_reply_byte_by_byte() {
        let q = PositionQuery(vec![ax("1")]);
        assert_eq!(q.command().to_bytes(), b"POS? 1\n");
        assert_eq!(
            q.parse_reply(&frame(b"1=12.500000\n")),
            Ok(vec![(ax("1"), 12.5)])
        );
    }

    #[test]
    fn multi_axis_reply_follows_the_asked_order() {
        let q = PositionQuery(vec![ax("X"), ax("T")]);
        let r = frame(b"T=7.000000 \nX=-1.250000\n");
        assert_eq!(
            q.parse_reply(&r),
            Ok(vec![(ax("X"), -1.25), (ax("T"), 7.0)])
        );
    }

    #[test]
    fn all_axes_query_accepts_whatever_axes_answer() {
        let q = OnTargetQuery(vec![]);
        let r = frame(b"X=1 \nY=0 \nT=1\n");
        assert_eq!(
            q.parse_reply(&r),
            Ok(vec![(ax("X"), true), (ax("Y"), false), (ax("T"), true)])
        );
    }

    #[test]
    fn replies_to_another_query_are_rejected() {
        // An ONT? answer is not a position of another axis, nor the wrong line count.
        let q = PositionQuery(vec![ax("T")]);
        assert!(matches!(
            q.parse_reply(&frame(b"X=1\n")),
            Err(ReplyError::UnexpectedAxis { .. })
        ));
        assert!(matches!(
            q.parse_reply(&frame(b"0\n")),
            Err(ReplyError::NotAxisValue { .. })
        ));
        assert!(matches!(
            q.parse_reply(&frame(b"T=1 \nT=2\n")),
            Err(ReplyError::LineCount { .. })
        ));
        let q2 = PositionQuery(vec![ax("X"), ax("T")]);
        assert!(matches!(
            q2.parse_reply(&frame(b"T=1 \nT=2\n")),
            Err(ReplyError::UnexpectedAxis { .. })
        ));
        assert!(matches!(
            ErrorQuery.parse_reply(&frame(b"T=1.000000\n")),
            Err(ReplyError::BadAnswer { .. })
        ));
    }

    #[test]
    fn garbled_values_are_rejected() {
        let q = PositionQuery(vec![ax("T")]);
        for bad in [
            &b"T=1.0#0000\n"[..],
            b"T=\n",
            b"T=nan\n",
            b"T=inf\n",
            b"#=1.0\n",
            b"T1.0\n",
        ] {
            assert!(
                q.parse_reply(&frame(bad)).is_err(),
                "{:?} accepted",
                escape_bytes(bad)
            );
        }
        let q = OnTargetQuery(vec![ax("T")]);
        for bad in [&b"T=2\n"[..], b"T=#\n", b"T=true\n"] {
            assert!(q.parse_reply(&frame(bad)).is_err());
        }
    }

    #[test]
    fn error_code_replies() {
        assert_eq!(
            ErrorQuery.parse_reply(&frame(b"0\n")),
            Ok(GcsErrorCode::NO_ERROR)
        );
        assert_eq!(
            ErrorQuery.parse_reply(&frame(b"10\n")),
            Ok(GcsErrorCode::STOPPED)
        );
        assert_eq!(
            ErrorQuery.parse_reply(&frame(b"-1024\n")),
            Ok(GcsErrorCode(-1024))
        );
        for bad in [&b"#\n"[..], b"1 0\n", b"\n", b"99999999999\n", b"+5\n"] {
            assert!(ErrorQuery.parse_reply(&frame(bad)).is_err());
        }
    }

    #[test]
    fn single_byte_queries() {
        assert_eq!(MotionStatusQuery.command().to_bytes(), [0x05]);
        assert_eq!(
            MotionStatusQuery.parse_reply(&frame(b"5\n")),
            Ok(MotionStatus(5))
        );
        assert_eq!(
            MotionStatusQuery.parse_reply(&frame(b"0x1F\n")),
            Ok(MotionStatus(0x1F))
        );
        assert!(MotionStatusQuery.parse_reply(&frame(b"G\n")).is_err());
        let s = MotionStatus(0b100);
        assert!(s.is_moving(2) && !s.is_moving(0) && s.any() && !s.is_moving(40));

        assert_eq!(ReadyQuery.command().to_bytes(), [0x07]);
        assert_eq!(ReadyQuery.parse_reply(&frame(&[0xB1, b'\n'])), Ok(true));
        assert_eq!(ReadyQuery.parse_reply(&frame(&[0xB0, b'\n'])), Ok(false));
        assert!(ReadyQuery.parse_reply(&frame(b"#\n")).is_err());
    }

    #[test]
    fn identity_reply() {
        let idn = b"(c)2024 Physik Instrumente (PI) GmbH & Co. KG, C-884, 0, 1.0\n";
        assert!(
            IdentityQuery
                .parse_reply(&frame(idn))
                .unwrap()
                .contains("C-884")
        );
        assert!(IdentityQuery.parse_reply(&frame(b"\n")).is_err());
    }

    #[test]
    fn server_formatting_round_trips_through_client_parsing() {
        let values = vec![(ax("X"), 4999.999999), (ax("Y"), -0.5), (ax("T"), 70.0)];
        let r = frame(&Reply::axis_values(&values).to_bytes());
        assert_eq!(
            PositionQuery(vec![ax("X"), ax("Y"), ax("T")]).parse_reply(&r),
            Ok(values)
        );
        let flags = vec![(ax("X"), true), (ax("T"), false)];
        let r = frame(&Reply::axis_flags(&flags).to_bytes());
        assert_eq!(
            ServoQuery(vec![ax("X"), ax("T")]).parse_reply(&r),
            Ok(flags)
        );
        let r = frame(&Reply::error_code(GcsErrorCode::INVALID_AXIS_IDENTIFIER).to_bytes());
        assert_eq!(
            ErrorQuery.parse_reply(&r),
            Ok(GcsErrorCode::INVALID_AXIS_IDENTIFIER)
        );
        let r = frame(&Reply::motion_bitmap(6).to_bytes());
        assert_eq!(MotionStatusQuery.parse_reply(&r), Ok(MotionStatus(6)));
        let r = frame(&Reply::ready(false).to_bytes());
        assert_eq!(ReadyQuery.parse_reply(&r), Ok(false));
    }
}
