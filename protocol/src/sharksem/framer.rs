//! Incremental framing: bytes in any chunks, whole messages (header + body) out.
//!
//! SharkSEM has no resynchronisation marker: a body size beyond the limit
//! leaves no way to find the next header, so the framer reports it once and
//! ignores everything after it (the connection must be closed). A bad name
//! with a sane size is reported and its body skipped: framing carries on.

use std::collections::VecDeque;

use super::header::{HEADER_LEN, Header, HeaderError, escape};

/// Largest body accepted by [`MessageFramer::new`]: 64 MiB, above any `ScData`
/// chunk of 50 ms (16-bit pixels at the shortest dwell) and any control reply.
pub const MAX_BODY: u32 = 64 << 20;

/// One framed message.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Message {
    pub header: Header,
    pub body: Vec<u8>,
}

/// Why bytes do not frame.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// A header whose name field is not a name; its body was skipped.
    #[error("message header refused: {0}")]
    BadHeader(HeaderError),
    /// A body size beyond the limit: the stream cannot be followed any further.
    #[error(
        "message {name:?} announces a body of {size} bytes, above the limit of {limit}: \
         the stream is not SharkSEM or is corrupt"
    )]
    BodyTooLarge { name: String, size: u32, limit: u32 },
}

#[derive(Debug)]
enum State {
    Head,
    Body {
        header: Header,
        body: Vec<u8>,
        need: usize,
    },
    Skip {
        left: usize,
        error: HeaderError,
    },
    Poisoned,
}

/// Cuts a byte stream into [`Message`] values.
#[derive(Debug)]
pub struct MessageFramer {
    head: [u8; HEADER_LEN],
    head_len: usize,
    state: State,
    max_body: u32,
    ready: VecDeque<Result<Message, FrameError>>,
}

impl Default for MessageFramer {
    fn default() -> Self {
        Self::new()
    }
}

impl MessageFramer {
    /// A framer accepting bodies up to [`MAX_BODY`].
    #[must_use]
    pub fn new() -> Self {
        Self::with_limit(MAX_BODY)
    }

    /// A framer accepting bodies up to `max_body` bytes.
    #[must_use]
    pub fn with_limit(max_body: u32) -> Self {
        Self {
            head: [0; HEADER_LEN],
            head_len: 0,
            state: State::Head,
            max_body,
            ready: VecDeque::new(),
        }
    }

    /// Feeds a chunk; complete messages and errors queue up for [`Self::next_message`].
    pub fn push(&mut self, mut bytes: &[u8]) {
        while !bytes.is_empty() {
            match &mut self.state {
                State::Poisoned => return,
                State::Head => {
                    let n = (HEADER_LEN - self.head_len).min(bytes.len());
                    self.head[self.head_len..self.head_len + n].copy_from_slice(&bytes[..n]);
                    self.head_len += n;
                    bytes = &bytes[n..];
                    if self.head_len == HEADER_LEN {
                        self.head_len = 0;
                        self.start_body();
                    }
                }
                State::Body { body, need, .. } => {
                    let n = (*need - body.len()).min(bytes.len());
                    body.extend_from_slice(&bytes[..n]);
                    bytes = &bytes[n..];
                    if body.len() == *need {
                        self.finish_body();
                    }
                }
                State::Skip { left, .. } => {
                    let n = (*left).min(bytes.len());
                    *left -= n;
                    bytes = &bytes[n..];
                    if *left == 0 {
                        self.finish_body();
                    }
                }
            }
        }
    }

    /// A header is complete: check the size, then expect its body.
    fn start_body(&mut self) {
        let size = u32::from_le_bytes([self.head[16], self.head[17], self.head[18], self.head[19]]);
        if size > self.max_body {
            let name_end = self.head[..16].iter().position(|&b| b == 0).unwrap_or(16);
            self.ready.push_back(Err(FrameError::BodyTooLarge {
                name: escape(&self.head[..name_end]),
                size,
                limit: self.max_body,
            }));
            self.state = State::Poisoned;
            return;
        }
        // Checked against the limit, which a usize holds.
        let need = size as usize;
        self.state = match Header::decode(&self.head) {
            Ok(header) => State::Body {
                header,
                body: Vec::with_capacity(need.min(1 << 20)),
                need,
            },
            Err(error) => State::Skip { left: need, error },
        };
        if need == 0 {
            self.finish_body();
        }
    }

    fn finish_body(&mut self) {
        match std::mem::replace(&mut self.state, State::Head) {
            State::Body { header, body, .. } => self.ready.push_back(Ok(Message { header, body })),
            State::Skip { error, .. } => self.ready.push_back(Err(FrameError::BadHeader(error))),
            other => self.state = other,
        }
    }

    /// The oldest complete message (or framing error) fed so far.
    pub fn next_message(&mut self) -> Option<Result<Message, FrameError>> {
        self.ready.pop_front()
    }

    /// Bytes still missing from the message being received (for sizing reads).
    #[must_use]
    pub fn pending(&self) -> usize {
        match &self.state {
            State::Head => HEADER_LEN - self.head_len,
            State::Body { body, need, .. } => need - body.len(),
            State::Skip { left, .. } => *left,
            State::Poisoned => 0,
        }
    }

    /// Whether nothing is buffered: no partial message, nothing queued.
    #[must_use]
    pub fn is_idle(&self) -> bool {
        matches!(self.state, State::Head) && self.head_len == 0 && self.ready.is_empty()
    }

    /// Whether an oversized body stopped the framing for good.
    #[must_use]
    pub fn is_poisoned(&self) -> bool {
        matches!(self.state, State::Poisoned)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sharksem::{Flags, Request, Response, ScanXY};

    fn feed_bytewise(f: &mut MessageFramer, bytes: &[u8]) -> Vec<Result<Message, FrameError>> {
        let mut out = Vec::new();
        for b in bytes {
            f.push(std::slice::from_ref(b));
            while let Some(m) = f.next_message() {
                out.push(m);
            }
        }
        out
    }

    #[test]
    fn messages_frame_one_byte_at_a_time_and_in_any_chunks() {
        let reqs = [
            Request::StgMoveTo(vec![1.0, 2.0, 0.0, 0.0, 7.5]),
            Request::ScStopScan,
            Request::ScScanXY(ScanXY::full_frame(3, 64, 48, 500)),
        ];
        let stream: Vec<u8> = reqs
            .iter()
            .enumerate()
            .flat_map(|(i, r)| r.encode(i as u32, Flags::WAIT_B))
            .collect();
        let mut f = MessageFramer::new();
        let got = feed_bytewise(&mut f, &stream);
        assert!(f.is_idle());
        assert_eq!(got.len(), 3);
        for (i, (m, r)) in got.into_iter().zip(&reqs).enumerate() {
            let m = m.unwrap();
            assert_eq!(m.header.id as usize, i);
            assert_eq!(
                &Request::decode(m.header.name.as_str(), &m.body).unwrap(),
                r
            );
        }
        for chunk in [2, 5, 31, 32, 33, 1000] {
            let mut f = MessageFramer::new();
            let mut n = 0;
            for c in stream.chunks(chunk) {
                f.push(c);
                while let Some(m) = f.next_message() {
                    m.unwrap();
                    n += 1;
                }
            }
            assert_eq!(n, 3, "chunks of {chunk}");
        }
    }

    #[test]
    fn a_bad_name_skips_its_body_and_framing_goes_on() {
        let mut garbage = Request::TcpGetVersion.encode(0, Flags::NONE);
        garbage[..16].copy_from_slice(&[0xAB; 16]);
        garbage[16..20].copy_from_slice(&4u32.to_le_bytes());
        garbage.extend_from_slice(&[9, 9, 9, 9]);
        let good =
            Response::Int(0).encode(&crate::sharksem::FnName::new("StgIsBusy").unwrap(), 5, 0);
        let mut f = MessageFramer::new();
        let got = feed_bytewise(&mut f, &[garbage, good].concat());
        assert!(matches!(got[0], Err(FrameError::BadHeader(_))), "{got:?}");
        assert_eq!(got[1].as_ref().unwrap().header.id, 5);
        assert!(!f.is_poisoned());
    }

    #[test]
    fn a_huge_body_size_poisons_the_stream() {
        let mut msg = Request::GetViewField.encode(0, Flags::NONE);
        msg[16..20].copy_from_slice(&u32::MAX.to_le_bytes());
        msg.extend_from_slice(&Request::GetViewField.encode(1, Flags::NONE));
        let mut f = MessageFramer::with_limit(1024);
        let got = feed_bytewise(&mut f, &msg);
        assert_eq!(got.len(), 1);
        let e = got[0].as_ref().unwrap_err().to_string();
        assert!(
            e.contains("GetViewField") && e.contains("4294967295"),
            "{e}"
        );
        assert!(f.is_poisoned());
        f.push(&Request::GetViewField.encode(2, Flags::NONE));
        assert!(f.next_message().is_none(), "nothing after the poison");
    }

    #[test]
    fn truncation_leaves_the_message_pending() {
        let bytes = Request::SetViewField { mm: 0.5 }.encode(0, Flags::NONE);
        let mut f = MessageFramer::new();
        f.push(&bytes[..bytes.len() - 1]);
        assert!(f.next_message().is_none());
        assert_eq!(f.pending(), 1);
        assert!(!f.is_idle());
        f.push(&bytes[bytes.len() - 1..]);
        assert!(f.next_message().unwrap().is_ok());
    }

    #[test]
    fn random_garbage_never_panics() {
        // A xorshift stream of bytes: whatever comes out, the framer stays sane.
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut bytes = Vec::new();
        for _ in 0..20_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            bytes.push((x >> 24) as u8);
        }
        let mut f = MessageFramer::with_limit(4096);
        for c in bytes.chunks(7) {
            f.push(c);
            while f.next_message().is_some() {}
        }
        assert!(f.is_poisoned() || f.pending() <= 4096 + HEADER_LEN);
    }
}
