//! Replies: the value type for both sides, the wire form (server) and the
//! incremental framer (client).
//!
//! A reply is two lines, each ending in CR LF [SF, SF-old, ML, OD-Z]: an
//! acknowledge sent at once (`@` accepted, `#` invalid), then, once the command
//! has finished, a status line (`>` and optional data: success; `*` and an
//! error number, with or without a space: failure). After `#` no second line
//! is expected (⚠ uncertain whether one comes: the framer reports it as a
//! status without acknowledge, which a client discards).

use std::collections::VecDeque;

use super::error::RemconError;

/// Longest reply line accepted by [`ReplyFramer::new`], terminator excluded.
pub const MAX_REPLY_LINE_LEN: usize = 256;

/// One complete reply.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Reply {
    /// `@` then `>data`: done; the data is empty for setters.
    Done(String),
    /// `@` then `*NNN`: the command failed.
    Failed(RemconError),
    /// `#`: the command is invalid (e.g. the wrong number of values to `C95`).
    Invalid,
}

impl Reply {
    /// The wire form, lines ending in CR LF.
    pub fn to_bytes(&self) -> Vec<u8> {
        match self {
            Self::Done(data) => format!("@\r\n>{data}\r\n").into_bytes(),
            Self::Failed(e) => format!("@\r\n*{}\r\n", e.number()).into_bytes(),
            Self::Invalid => b"#\r\n".to_vec(),
        }
    }

    /// Printable, for the record: the lines joined by `\n` (`@\n>0.5`, `@\n*603`, `#`).
    pub fn to_text(&self) -> String {
        match self {
            Self::Done(data) => format!("@\n>{data}"),
            Self::Failed(e) => format!("@\n*{}", e.number()),
            Self::Invalid => "#".into(),
        }
    }
}

/// Why bytes do not frame as a reply.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// A line grew past the limit without a terminator (noise, wrong baud rate).
    #[error("line longer than {limit} bytes without a terminator")]
    LineTooLong {
        /// The limit, bytes.
        limit: usize,
    },
    /// A byte no RemCon32 reply contains (noise, wrong baud rate).
    #[error("byte 0x{byte:02X} is not valid in a RemCon32 reply")]
    InvalidByte {
        /// The offending byte.
        byte: u8,
    },
    /// A line that is none of `@`, `#`, `>…`, `*NNN`.
    #[error("line {line:?} is not a RemCon32 acknowledge or status line")]
    Unrecognised {
        /// The line.
        line: String,
    },
    /// A status line with no `@` before it (its acknowledge was lost, or it
    /// follows a `#`).
    #[error("status line {line:?} without an acknowledge before it")]
    StatusWithoutAck {
        /// The line.
        line: String,
    },
    /// Two `@` in a row.
    #[error("a second acknowledge before the status line")]
    DoubleAck,
}

/// Client side: cuts the instrument's byte stream into complete [`Reply`] values.
///
/// Accepts CR, LF or CR LF after each line; empty lines are skipped. Accepts
/// input in any chunking, one byte at a time included, and never panics:
/// malformed input gives a [`FrameError`] once and the framer carries on
/// with the next line.
#[derive(Debug)]
pub struct ReplyFramer {
    line: Vec<u8>,
    /// Skipping the rest of a malformed line, up to its terminator.
    discarding: bool,
    /// An `@` came; its status line has not.
    acknowledged: bool,
    max_line_len: usize,
    ready: VecDeque<Result<Reply, FrameError>>,
}

impl Default for ReplyFramer {
    fn default() -> Self {
        Self::new()
    }
}

impl ReplyFramer {
    /// A framer with the default line limit ([`MAX_REPLY_LINE_LEN`]).
    pub fn new() -> Self {
        Self::with_limit(MAX_REPLY_LINE_LEN)
    }

    /// A framer with an explicit line limit (at least 1).
    pub fn with_limit(max_line_len: usize) -> Self {
        Self {
            line: Vec::new(),
            discarding: false,
            acknowledged: false,
            max_line_len: max_line_len.max(1),
            ready: VecDeque::new(),
        }
    }

    /// Feeds one byte; returns a reply or an error when this byte completes one.
    pub fn push(&mut self, byte: u8) -> Option<Result<Reply, FrameError>> {
        match byte {
            b'\r' | b'\n' => {
                if std::mem::take(&mut self.discarding) {
                    return None;
                }
                let line = std::mem::take(&mut self.line);
                self.line_done(&line)
            }
            _ if self.discarding => None,
            b'\t' | 0x20..=0x7E => {
                if self.line.len() >= self.max_line_len {
                    return Some(Err(self.fail(FrameError::LineTooLong {
                        limit: self.max_line_len,
                    })));
                }
                self.line.push(byte);
                None
            }
            _ => Some(Err(self.fail(FrameError::InvalidByte { byte }))),
        }
    }

    /// Feeds a chunk; complete replies and errors queue up for [`Self::next_reply`].
    pub fn feed(&mut self, bytes: &[u8]) {
        for &b in bytes {
            if let Some(r) = self.push(b) {
                self.ready.push_back(r);
            }
        }
    }

    /// The oldest complete reply (or framing error) fed so far.
    pub fn next_reply(&mut self) -> Option<Result<Reply, FrameError>> {
        self.ready.pop_front()
    }

    /// Whether an acknowledge came whose status line has not.
    pub fn is_acknowledged(&self) -> bool {
        self.acknowledged
    }

    /// Forgets partial input and queued replies (after a resynchronisation).
    pub fn reset(&mut self) {
        self.line.clear();
        self.discarding = false;
        self.acknowledged = false;
        self.ready.clear();
    }

    fn fail(&mut self, error: FrameError) -> FrameError {
        self.line.clear();
        self.discarding = true;
        self.acknowledged = false;
        error
    }

    fn line_done(&mut self, raw: &[u8]) -> Option<Result<Reply, FrameError>> {
        // Only printable ASCII and tabs reach here.
        let text = String::from_utf8_lossy(raw);
        let line = text.trim();
        if line.is_empty() {
            return None;
        }
        let acknowledged = std::mem::take(&mut self.acknowledged);
        let status = match line.as_bytes()[0] {
            b'@' if line.len() == 1 => {
                self.acknowledged = true;
                return acknowledged.then_some(Err(FrameError::DoubleAck));
            }
            b'#' if line.len() == 1 => return Some(Ok(Reply::Invalid)),
            b'>' => Reply::Done(line[1..].trim().to_owned()),
            b'*' => match line[1..].trim().parse::<u16>() {
                Ok(n) => Reply::Failed(RemconError::from_number(n)),
                Err(_) => {
                    return Some(Err(FrameError::Unrecognised { line: line.into() }));
                }
            },
            _ => return Some(Err(FrameError::Unrecognised { line: line.into() })),
        };
        Some(if acknowledged {
            Ok(status)
        } else {
            Err(FrameError::StatusWithoutAck { line: line.into() })
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bytewise(f: &mut ReplyFramer, bytes: &[u8]) -> Vec<Result<Reply, FrameError>> {
        bytes.iter().filter_map(|&b| f.push(b)).collect()
    }

    fn done(s: &str) -> Result<Reply, FrameError> {
        Ok(Reply::Done(s.into()))
    }

    #[test]
    fn two_line_replies_byte_by_byte_in_every_line_ending() {
        for eol in ["\r\n", "\r", "\n", "\n\r"] {
            let mut f = ReplyFramer::new();
            let wire = format!("@{eol}>1.5 2.5{eol}@{eol}>{eol}");
            let out = bytewise(&mut f, wire.as_bytes());
            assert_eq!(out, [done("1.5 2.5"), done("")], "{eol:?}");
            assert!(!f.is_acknowledged());
        }
    }

    #[test]
    fn acknowledge_alone_is_not_a_reply_yet() {
        let mut f = ReplyFramer::new();
        assert!(bytewise(&mut f, b"@\r\n").is_empty());
        assert!(f.is_acknowledged());
        assert_eq!(
            bytewise(&mut f, b">SmartSEM V06.01\r"),
            [done("SmartSEM V06.01")]
        );
    }

    #[test]
    fn error_numbers_with_and_without_a_space() {
        let mut f = ReplyFramer::new();
        let out = bytewise(&mut f, b"@\r\n*600\r\n@\r\n* 603\r\n@\r\n*999\r\n");
        assert_eq!(
            out,
            [
                Ok(Reply::Failed(RemconError::UnknownCommand)),
                Ok(Reply::Failed(RemconError::ParameterOutOfRange)),
                Ok(Reply::Failed(RemconError::Other(999))),
            ]
        );
    }

    #[test]
    fn invalid_needs_no_second_line_and_a_second_one_is_flagged_not_taken() {
        let mut f = ReplyFramer::new();
        assert_eq!(bytewise(&mut f, b"#\r\n"), [Ok(Reply::Invalid)]);
        let out = bytewise(&mut f, b"*601\r\n@\r\n>ok\r\n");
        assert_eq!(
            out,
            [
                Err(FrameError::StatusWithoutAck {
                    line: "*601".into()
                }),
                done("ok")
            ]
        );
    }

    #[test]
    fn garbage_overlong_lines_and_bad_bytes_are_errors_once_then_framing_resumes() {
        let mut f = ReplyFramer::with_limit(16);
        let mut wire = Vec::new();
        wire.extend_from_slice(b"hello\r\n");
        wire.extend_from_slice(&[b'7'; 40]);
        wire.extend_from_slice(b"\r\n@\r\n>1\xff23\r\n@\r\n*abc\r\n@\r\n@\r\n>2\r\n");
        let out = bytewise(&mut f, &wire);
        assert_eq!(
            out,
            [
                Err(FrameError::Unrecognised {
                    line: "hello".into()
                }),
                Err(FrameError::LineTooLong { limit: 16 }),
                Err(FrameError::InvalidByte { byte: 0xFF }),
                Err(FrameError::Unrecognised {
                    line: "*abc".into()
                }),
                Err(FrameError::DoubleAck),
                done("2"),
            ]
        );
        // A line cut by a bad byte does not leave a half acknowledge behind.
        assert!(!f.is_acknowledged());
    }

    #[test]
    fn status_whose_acknowledge_was_lost_is_flagged() {
        let mut f = ReplyFramer::new();
        assert_eq!(
            bytewise(&mut f, b">0.5\r\n"),
            [Err(FrameError::StatusWithoutAck {
                line: ">0.5".into()
            })]
        );
    }

    #[test]
    fn chunks_and_reset() {
        let mut f = ReplyFramer::new();
        f.feed(b"@\r\n>1 2");
        assert!(f.next_reply().is_none());
        f.reset();
        // The rest of the forgotten reply is not taken for the start of one.
        f.feed(b" 3\r\n@\r\n>4\r\n");
        assert_eq!(
            f.next_reply(),
            Some(Err(FrameError::Unrecognised { line: "3".into() }))
        );
        assert_eq!(f.next_reply(), Some(done("4")));
        assert_eq!(f.next_reply(), None);
    }

    #[test]
    fn wire_and_text_forms() {
        assert_eq!(Reply::Done("1.0".into()).to_bytes(), b"@\r\n>1.0\r\n");
        assert_eq!(
            Reply::Failed(RemconError::ParameterUnattainable).to_bytes(),
            b"@\r\n*613\r\n"
        );
        assert_eq!(Reply::Invalid.to_bytes(), b"#\r\n");
        assert_eq!(Reply::Done("1.0".into()).to_text(), "@\n>1.0");
        assert_eq!(
            Reply::Failed(RemconError::ParameterOutOfRange).to_text(),
            "@\n*603"
        );
        // Every reply frames back to itself.
        for r in [
            Reply::Done(String::new()),
            Reply::Done("0.1 0.2 10 3 0 0 1.0".into()),
            Reply::Failed(RemconError::CommandTooLong),
            Reply::Invalid,
        ] {
            let mut f = ReplyFramer::new();
            assert_eq!(bytewise(&mut f, &r.to_bytes()), [Ok(r.clone())]);
        }
    }
}
