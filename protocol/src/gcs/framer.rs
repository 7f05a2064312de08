//! Incremental framing: bytes in, complete replies (client) or commands (server) out.
//!
//! Both framers accept input in any chunking, one byte at a time included, and
//! never panic: malformed input gives a [`FrameError`] once, after which the
//! framer skips to the end of the offending reply or line and carries on.

use std::collections::VecDeque;

use super::command::{BYTE_MOTION_STATUS, BYTE_READY, BYTE_STOP_ALL, MAX_COMMAND_LEN};
use super::reply::Reply;

/// Longest reply line accepted by [`ReplyFramer::new`], LF excluded.
pub const MAX_REPLY_LINE_LEN: usize = 256;
/// Most lines in one reply accepted by [`ReplyFramer::new`].
pub const MAX_REPLY_LINES: usize = 64;

/// Why bytes could not be framed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// A line grew past the limit without an LF (noise, wrong baud rate, or not a GCS device).
    #[error("line longer than {limit} bytes without a line feed")]
    LineTooLong {
        /// The limit, bytes.
        limit: usize,
    },
    /// A reply had more lines than the limit.
    #[error("reply of more than {limit} lines")]
    TooManyLines {
        /// The limit, lines.
        limit: usize,
    },
    /// A byte that no GCS reply contains (noise, wrong baud rate).
    #[error("byte 0x{byte:02X} is not valid in a GCS reply")]
    InvalidByte {
        /// The offending byte.
        byte: u8,
    },
}

/// Client side: cuts the controller's byte stream into complete [`Reply`] values.
///
/// A reply is one or more lines; a line ending in `" \n"` announces another line,
/// one ending in a bare `"\n"` ends the reply. Carriage returns are ignored.
/// Accepted bytes: printable ASCII, tab, and 0xB0/0xB1 (the answers to `#7`).
#[derive(Debug)]
pub struct ReplyFramer {
    line: Vec<u8>,
    lines: Vec<Vec<u8>>,
    /// Skipping the rest of a malformed reply, up to its final LF.
    discarding: bool,
    /// The last byte seen while discarding, to recognise `" \n"`.
    last_discarded: u8,
    max_line_len: usize,
    max_lines: usize,
    ready: VecDeque<Result<Reply, FrameError>>,
}

impl Default for ReplyFramer {
    fn default() -> Self {
        Self::new()
    }
}

impl ReplyFramer {
    /// A framer with the default limits ([`MAX_REPLY_LINE_LEN`], [`MAX_REPLY_LINES`]).
    pub fn new() -> Self {
        Self::with_limits(MAX_REPLY_LINE_LEN, MAX_REPLY_LINES)
    }

    /// A framer with explicit limits (both at least 1).
    pub fn with_limits(max_line_len: usize, max_lines: usize) -> Self {
        Self {
            line: Vec::new(),
            lines: Vec::new(),
            discarding: false,
            last_discarded: 0,
            max_line_len: max_line_len.max(1),
            max_lines: max_lines.max(1),
            ready: VecDeque::new(),
        }
    }

    /// Feeds one byte; returns a reply or an error when this byte completes one.
    pub fn push(&mut self, byte: u8) -> Option<Result<Reply, FrameError>> {
        if self.discarding {
            if byte == b'\n' && self.last_discarded != b' ' {
                self.discarding = false;
            }
            self.last_discarded = byte;
            return None;
        }
        match byte {
            b'\r' => None,
            b'\n' => {
                let continued = self.line.last() == Some(&b' ');
                if continued {
                    self.line.pop();
                }
                self.lines.push(std::mem::take(&mut self.line));
                if continued {
                    if self.lines.len() >= self.max_lines {
                        // The reply goes on: skip up to its final LF.
                        return Some(Err(self.fail(
                            0,
                            FrameError::TooManyLines {
                                limit: self.max_lines,
                            },
                        )));
                    }
                    None
                } else {
                    Some(Ok(Reply::from_lines(std::mem::take(&mut self.lines))))
                }
            }
            b'\t' | 0x20..=0x7E | 0xB0 | 0xB1 => {
                if self.line.len() >= self.max_line_len {
                    return Some(Err(self.fail(
                        byte,
                        FrameError::LineTooLong {
                            limit: self.max_line_len,
                        },
                    )));
                }
                self.line.push(byte);
                None
            }
            _ => Some(Err(self.fail(byte, FrameError::InvalidByte { byte }))),
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

    /// Whether no partial reply is buffered and nothing is queued.
    pub fn is_idle(&self) -> bool {
        self.line.is_empty() && self.lines.is_empty() && !self.discarding && self.ready.is_empty()
    }

    /// Forgets partial input and queued replies (after a resynchronisation).
    pub fn reset(&mut self) {
        self.line.clear();
        self.lines.clear();
        self.discarding = false;
        self.last_discarded = 0;
        self.ready.clear();
    }

    /// Drops the broken reply and skips input up to its final LF; `last` is the
    /// byte just consumed (a space there makes the next LF a continuation).
    fn fail(&mut self, last: u8, error: FrameError) -> FrameError {
        self.line.clear();
        self.lines.clear();
        self.discarding = true;
        self.last_discarded = last;
        error
    }
}

/// One framed input on the server side.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Incoming {
    /// A command line, LF removed.
    Line(Vec<u8>),
    /// A single-byte command (`#5`, `#7`, `#24`).
    Single(u8),
}

/// Server side: cuts the client's byte stream into command lines and single-byte commands.
///
/// Single-byte commands are recognised between lines (where the controllers
/// answer them immediately). Empty lines are skipped. An overlong line gives
/// [`FrameError::LineTooLong`] once and is skipped up to its LF.
#[derive(Debug)]
pub struct CommandFramer {
    line: Vec<u8>,
    discarding: bool,
    max_len: usize,
}

impl Default for CommandFramer {
    fn default() -> Self {
        Self::new()
    }
}

impl CommandFramer {
    /// A framer accepting lines up to [`MAX_COMMAND_LEN`] bytes.
    pub fn new() -> Self {
        Self {
            line: Vec::new(),
            discarding: false,
            max_len: MAX_COMMAND_LEN,
        }
    }

    /// Feeds one byte; returns a command (or an error) when this byte completes one.
    pub fn push(&mut self, byte: u8) -> Option<Result<Incoming, FrameError>> {
        if self.discarding {
            if byte == b'\n' {
                self.discarding = false;
            }
            return None;
        }
        match byte {
            BYTE_MOTION_STATUS | BYTE_READY | BYTE_STOP_ALL if self.line.is_empty() => {
                Some(Ok(Incoming::Single(byte)))
            }
            b'\n' => {
                let mut line = std::mem::take(&mut self.line);
                if line.last() == Some(&b'\r') {
                    line.pop();
                }
                if line.iter().all(u8::is_ascii_whitespace) {
                    None
                } else {
                    Some(Ok(Incoming::Line(line)))
                }
            }
            _ if self.line.len() >= self.max_len => {
                self.line.clear();
                self.discarding = true;
                Some(Err(FrameError::LineTooLong {
                    limit: self.max_len,
                }))
            }
            _ => {
                self.line.push(byte);
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn feed_bytewise(framer: &mut ReplyFramer, bytes: &[u8]) -> Vec<Result<Reply, FrameError>> {
        bytes.iter().filter_map(|&b| framer.push(b)).collect()
    }

    fn lines(r: &Reply) -> Vec<&[u8]> {
        r.lines().iter().map(Vec::as_slice).collect()
    }

    #[test]
    fn single_line_reply_byte_by_byte() {
        let mut f = ReplyFramer::new();
        let out = feed_bytewise(&mut f, b"1=12.500000\n");
        assert_eq!(out.len(), 1);
        assert_eq!(
            lines(out[0].as_ref().unwrap()),
            vec![b"1=12.500000".as_slice()]
        );
        assert!(f.is_idle());
    }

    #[test]
    fn multi_line_reply_is_one_reply() {
        let mut f = ReplyFramer::new();
        let bytes = b"X=1.000000 \nY=2.000000 \nT=3.000000\n";
        // Nothing is emitted until the final bare LF.
        let out = feed_bytewise(&mut f, &bytes[..bytes.len() - 1]);
        assert!(out.is_empty());
        let out = feed_bytewise(&mut f, b"\n");
        assert_eq!(
            lines(out[0].as_ref().unwrap()),
            vec![b"X=1.000000".as_slice(), b"Y=2.000000", b"T=3.000000"]
        );
    }

    #[test]
    fn back_to_back_replies_in_one_chunk() {
        let mut f = ReplyFramer::new();
        f.feed(b"0\nX=1 \nY=0\n\xb1\n");
        let a = f.next_reply().unwrap().unwrap();
        let b = f.next_reply().unwrap().unwrap();
        let c = f.next_reply().unwrap().unwrap();
        assert!(f.next_reply().is_none());
        assert_eq!(lines(&a), vec![b"0".as_slice()]);
        assert_eq!(lines(&b), vec![b"X=1".as_slice(), b"Y=0"]);
        assert_eq!(lines(&c), vec![[0xB1].as_slice()]);
    }

    #[test]
    fn carriage_returns_are_ignored() {
        let mut f = ReplyFramer::new();
        let out = feed_bytewise(&mut f, b"0\r\n");
        assert_eq!(lines(out[0].as_ref().unwrap()), vec![b"0".as_slice()]);
    }

    #[test]
    fn garbage_byte_gives_one_error_then_resyncs_on_the_next_reply() {
        let mut f = ReplyFramer::new();
        let out = feed_bytewise(&mut f, b"X=1\xff2 \nY=3\n0\n");
        assert_eq!(out.len(), 2, "{out:?}");
        assert_eq!(out[0], Err(FrameError::InvalidByte { byte: 0xFF }));
        // The rest of the broken reply (its continuation line included) is skipped.
        assert_eq!(lines(out[1].as_ref().unwrap()), vec![b"0".as_slice()]);
    }

    #[test]
    fn control_bytes_are_garbage() {
        for byte in [0x00u8, 0x05, 0x1B, 0x7F, 0x80, 0xFF] {
            let mut f = ReplyFramer::new();
            let out = feed_bytewise(&mut f, &[b'1', byte, b'\n', b'0', b'\n']);
            assert_eq!(out[0], Err(FrameError::InvalidByte { byte }));
            assert_eq!(lines(out[1].as_ref().unwrap()), vec![b"0".as_slice()]);
        }
    }

    #[test]
    fn overlong_line_gives_one_error_and_recovers() {
        let mut f = ReplyFramer::with_limits(8, 4);
        let mut bytes = vec![b'7'; 100];
        bytes.extend_from_slice(b"\n0\n");
        let out = feed_bytewise(&mut f, &bytes);
        assert_eq!(out.len(), 2);
        assert_eq!(out[0], Err(FrameError::LineTooLong { limit: 8 }));
        assert_eq!(lines(out[1].as_ref().unwrap()), vec![b"0".as_slice()]);
    }

    #[test]
    fn endless_continuation_lines_are_bounded() {
        let mut f = ReplyFramer::with_limits(16, 3);
        let out = feed_bytewise(&mut f, b"a \nb \nc \nd \ne\n0\n");
        assert_eq!(out[0], Err(FrameError::TooManyLines { limit: 3 }));
        assert_eq!(lines(out[1].as_ref().unwrap()), vec![b"0".as_slice()]);
        assert_eq!(out.len(), 2);
    }

    #[test]
    fn random_noise_never_panics_and_clean_input_recovers() {
        // A small deterministic xorshift stream of arbitrary bytes.
        let mut state = 0x9E37_79B9_7F4A_7C15_u64;
        let mut f = ReplyFramer::with_limits(32, 4);
        for _ in 0..20_000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let _ = f.push(state.to_le_bytes()[3]);
        }
        // Whatever state noise left, a bare LF ends it and the next reply is clean.
        let _ = feed_bytewise(&mut f, b"\n\n");
        let out = feed_bytewise(&mut f, b"T=1\n");
        assert_eq!(
            lines(out.last().unwrap().as_ref().unwrap()),
            vec![b"T=1".as_slice()]
        );
    }

    #[test]
    fn reset_forgets_partial_input() {
        let mut f = ReplyFramer::new();
        f.feed(b"X=1 \nY=");
        assert!(!f.is_idle());
        f.reset();
        assert!(f.is_idle());
        f.feed(b"0\n");
        assert_eq!(
            lines(&f.next_reply().unwrap().unwrap()),
            vec![b"0".as_slice()]
        );
    }

    #[test]
    fn command_framer_splits_lines_and_single_bytes() {
        let mut f = CommandFramer::new();
        let out: Vec<_> = b"\x05MOV X 1\r\n\n\x07ERR?\n\x18"
            .iter()
            .filter_map(|&b| f.push(b))
            .collect();
        assert_eq!(
            out,
            vec![
                Ok(Incoming::Single(0x05)),
                Ok(Incoming::Line(b"MOV X 1".to_vec())),
                Ok(Incoming::Single(0x07)),
                Ok(Incoming::Line(b"ERR?".to_vec())),
                Ok(Incoming::Single(0x18)),
            ]
        );
    }

    #[test]
    fn command_framer_rejects_overlong_lines_once() {
        let mut f = CommandFramer::new();
        let mut bytes = vec![b'A'; MAX_COMMAND_LEN + 50];
        bytes.extend_from_slice(b"\nERR?\n");
        let out: Vec<_> = bytes.iter().filter_map(|&b| f.push(b)).collect();
        assert_eq!(
            out,
            vec![
                Err(FrameError::LineTooLong {
                    limit: MAX_COMMAND_LEN
                }),
                Ok(Incoming::Line(b"ERR?".to_vec())),
            ]
        );
    }
}
