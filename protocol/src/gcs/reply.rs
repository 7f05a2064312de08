//! Replies: one value type for both sides, formatting (server) and line parsing (client).

use std::fmt::Write as _;

use super::axis::AxisId;
use super::error_code::GcsErrorCode;

/// Byte answered by `#7` when the controller is ready.
pub(crate) const READY_BYTE: u8 = 0xB1;
/// Byte answered by `#7` while the controller is busy.
pub(crate) const BUSY_BYTE: u8 = 0xB0;

/// One complete reply: its lines, without the `" \n"` separators and final LF.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Reply {
    lines: Vec<Vec<u8>>,
}

/// Why a framed reply is not the answer to the query that was sent (a garbled
/// or misplaced reply).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ReplyError {
    /// The reply has the wrong number of lines.
    #[error("expected {expected} line(s), got {got}")]
    LineCount {
        /// Lines expected.
        expected: usize,
        /// Lines received.
        got: usize,
    },
    /// A line is not of the form `axis=value`.
    #[error("line {line:?} is not of the form axis=value")]
    NotAxisValue {
        /// The line, escaped.
        line: String,
    },
    /// A line names an axis that was not asked for, or names one twice.
    #[error("unexpected axis {axis:?} in reply (asked for {asked:?})")]
    UnexpectedAxis {
        /// The axis in the reply.
        axis: String,
        /// The axes asked for (empty = all).
        asked: Vec<String>,
    },
    /// A value does not parse as what the query answers.
    #[error("bad {what} {value:?} for axis {axis}")]
    BadValue {
        /// The axis.
        axis: String,
        /// The value text, escaped.
        value: String,
        /// What was expected ("number", "0 or 1").
        what: &'static str,
    },
    /// A single-line answer does not parse.
    #[error("expected {what}, got {line:?}")]
    BadAnswer {
        /// The line, escaped.
        line: String,
        /// What was expected.
        what: &'static str,
    },
}

impl Reply {
    /// A reply made of these lines (no separators, no LFs).
    pub fn from_lines(lines: Vec<Vec<u8>>) -> Self {
        Self { lines }
    }

    /// A one-line reply.
    pub fn line(line: impl Into<Vec<u8>>) -> Self {
        Self {
            lines: vec![line.into()],
        }
    }

    /// The lines, without separators.
    pub fn lines(&self) -> &[Vec<u8>] {
        &self.lines
    }

    /// The wire form: lines joined by `" \n"`, the last ended by `"\n"`.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::new();
        for (i, line) in self.lines.iter().enumerate() {
            if i > 0 {
                out.extend_from_slice(b" \n");
            }
            out.extend_from_slice(line);
        }
        out.push(b'\n');
        out
    }

    /// A printable form for logs: lines joined by `\n`, other bytes escaped as `\xNN`.
    pub fn to_text(&self) -> String {
        let mut out = String::new();
        for (i, line) in self.lines.iter().enumerate() {
            if i > 0 {
                out.push('\n');
            }
            out.push_str(&escape_bytes(line));
        }
        out
    }

    /// Server: `axis=value` lines, six decimals (`POS?`, `TMN?`, `TMX?`).
    pub fn axis_values(values: &[(AxisId, f64)]) -> Self {
        Self::from_lines(
            values
                .iter()
                .map(|(axis, v)| format!("{axis}={v:.6}").into_bytes())
                .collect(),
        )
    }

    /// Server: `axis=0|1` lines (`ONT?`, `SVO?`, `FRF?`).
    pub fn axis_flags(values: &[(AxisId, bool)]) -> Self {
        Self::from_lines(
            values
                .iter()
                .map(|(axis, v)| format!("{axis}={}", u8::from(*v)).into_bytes())
                .collect(),
        )
    }

    /// Server: the answer to `ERR?`.
    pub fn error_code(code: GcsErrorCode) -> Self {
        Self::line(code.0.to_string())
    }

    /// Server: the answer to `#5`, the motion bitmap in hexadecimal.
    pub fn motion_bitmap(bits: u32) -> Self {
        Self::line(format!("{bits:X}"))
    }

    /// Server: the answer to `#7`.
    pub fn ready(ready: bool) -> Self {
        Self::line(vec![if ready { READY_BYTE } else { BUSY_BYTE }])
    }

    /// The only line of a one-line reply, as ASCII text.
    pub(crate) fn single_ascii_line(&self, what: &'static str) -> Result<&str, ReplyError> {
        if self.lines.len() != 1 {
            return Err(ReplyError::LineCount {
                expected: 1,
                got: self.lines.len(),
            });
        }
        let line = &self.lines[0];
        ascii(line).ok_or_else(|| ReplyError::BadAnswer {
            line: escape_bytes(line),
            what,
        })
    }

    /// Parses `axis=value` lines. With a non-empty `asked`, exactly those axes
    /// must answer, each once (in any order); the result follows `asked`.
    pub(crate) fn axis_lines<T>(
        &self,
        asked: &[AxisId],
        what: &'static str,
        value: fn(&str) -> Option<T>,
    ) -> Result<Vec<(AxisId, T)>, ReplyError> {
        if !asked.is_empty() && self.lines.len() != asked.len() {
            return Err(ReplyError::LineCount {
                expected: asked.len(),
                got: self.lines.len(),
            });
        }
        let asked_names = || asked.iter().map(|a| a.as_str().to_owned()).collect();
        let mut answered: Vec<(AxisId, T)> = Vec::with_capacity(self.lines.len());
        for line in &self.lines {
            let text = ascii(line).ok_or_else(|| ReplyError::NotAxisValue {
                line: escape_bytes(line),
            })?;
            let (axis, v) = text
                .split_once('=')
                .ok_or_else(|| ReplyError::NotAxisValue {
                    line: text.to_owned(),
                })?;
            let axis = AxisId::new(axis.trim()).map_err(|_| ReplyError::NotAxisValue {
                line: text.to_owned(),
            })?;
            let known = asked.is_empty() || asked.contains(&axis);
            if !known || answered.iter().any(|(a, _)| *a == axis) {
                return Err(ReplyError::UnexpectedAxis {
                    axis: axis.to_string(),
                    asked: asked_names(),
                });
            }
            let parsed = value(v.trim()).ok_or_else(|| ReplyError::BadValue {
                axis: axis.to_string(),
                value: v.to_owned(),
                what,
            })?;
            answered.push((axis, parsed));
        }
        if asked.is_empty() {
            return Ok(answered);
        }
        // Same set (counts are equal and no axis is repeated): reorder as asked.
        let mut ordered = Vec::with_capacity(asked.len());
        for axis in asked {
            let i = answered
                .iter()
                .position(|(a, _)| a == axis)
                .ok_or_else(|| ReplyError::UnexpectedAxis {
                    axis: axis.to_string(),
                    asked: asked_names(),
                })?;
            ordered.push(answered.swap_remove(i));
        }
        Ok(ordered)
    }
}

fn ascii(line: &[u8]) -> Option<&str> {
    if line
        .iter()
        .all(|b| (b.is_ascii() && !b.is_ascii_control()) || *b == b'\t')
    {
        std::str::from_utf8(line).ok()
    } else {
        None
    }
}

/// Printable form of wire bytes: printable ASCII as is, LF as `\n`, others as `\xNN`.
pub fn escape_bytes(bytes: &[u8]) -> String {
    let mut out = String::with_capacity(bytes.len());
    for &b in bytes {
        match b {
            b'\n' => out.push_str("\\n"),
            b'\\' => out.push_str("\\\\"),
            0x20..=0x7E => out.push(char::from(b)),
            _ => {
                let _ = write!(out, "\\x{b:02X}");
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wire_form_uses_space_lf_between_lines() {
        let r = Reply::axis_values(&[
            (AxisId::new("1").unwrap(), 12.5),
            (AxisId::new("2").unwrap(), -3.0),
        ]);
        assert_eq!(r.to_bytes(), b"1=12.500000 \n2=-3.000000\n");
        assert_eq!(Reply::error_code(GcsErrorCode::STOPPED).to_bytes(), b"10\n");
        assert_eq!(Reply::motion_bitmap(0b101).to_bytes(), b"5\n");
        assert_eq!(Reply::motion_bitmap(0xAB).to_bytes(), b"AB\n");
        assert_eq!(Reply::ready(true).to_bytes(), [0xB1, b'\n']);
        assert_eq!(Reply::ready(false).to_bytes(), [0xB0, b'\n']);
    }

    #[test]
    fn escapes_non_printable_bytes_for_logs() {
        assert_eq!(escape_bytes(b"MOV X 1\n"), "MOV X 1\\n");
        assert_eq!(escape_bytes(&[0x05]), "\\x05");
        assert_eq!(escape_bytes(&[0xB1]), "\\xB1");
        assert_eq!(
            Reply::from_lines(vec![b"X=1".to_vec(), b"Y=0".to_vec()]).to_text(),
            "X=1\nY=0"
        );
    }
}
