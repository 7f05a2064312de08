//! One request in flight over a byte stream, for every line-framed stage
//! protocol: writes with a timeout, reads one framed reply before a deadline,
//! resynchronises after faults (input discarded until quiet, so that a late
//! reply cannot answer the next question), reports every exchange and every
//! stray reply to the [`StageObserver`].
//!
//! Cancel safety: when a future is dropped mid-exchange, the link stays marked
//! as possibly answering; the next send first waits out and discards that reply.

use std::fmt::Display;
use std::sync::Arc;
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;
use tracing::{debug, warn};

use super::error::{LinkRemedies, StageError};
use super::observer::{IoOutcome, StageIo, StageObserver, wall_ns};

/// A protocol's incremental reply framer, as the link drives it.
pub(crate) trait Framing: Send {
    /// One complete reply.
    type Reply: Send;
    /// Why bytes did not frame.
    type Error: Display + Send;
    /// Takes in bytes; complete replies queue up.
    fn feed(&mut self, bytes: &[u8]);
    /// The oldest complete reply (or framing error).
    fn next_reply(&mut self) -> Option<Result<Self::Reply, Self::Error>>;
    /// Forgets partial input and queued replies.
    fn reset(&mut self);
    /// The reply as printable text, for the record.
    fn text(reply: &Self::Reply) -> String;
}

impl Framing for sdsem_protocol::gcs::ReplyFramer {
    type Reply = sdsem_protocol::gcs::Reply;
    type Error = sdsem_protocol::gcs::FrameError;
    fn feed(&mut self, bytes: &[u8]) {
        Self::feed(self, bytes);
    }
    fn next_reply(&mut self) -> Option<Result<Self::Reply, Self::Error>> {
        Self::next_reply(self)
    }
    fn reset(&mut self) {
        Self::reset(self);
    }
    fn text(reply: &Self::Reply) -> String {
        reply.to_text()
    }
}

/// One framed input, or none in time.
pub(crate) enum Received<R, E> {
    Reply(R),
    Frame(E),
    Timeout,
}

/// A request on the wire.
pub(crate) struct Sent {
    pub seq: u64,
    pub at: Instant,
    pub wall_ns: u64,
    pub deadline: Instant,
}

/// Timing of the link, from the stage configuration.
#[derive(Clone, Copy, Debug)]
pub(crate) struct WireTiming {
    /// Time for one reply (and for one write).
    pub reply_timeout: Duration,
    /// After a fault, input is discarded until quiet this long.
    pub resync_quiet: Duration,
}

/// The byte stream, its framer, and the record of every exchange.
pub(crate) struct Wire<T, F> {
    io: T,
    framer: F,
    observer: Arc<dyn StageObserver>,
    timing: WireTiming,
    remedies: LinkRemedies,
    seq: u64,
    /// A reply may still be on its way (an exchange was cut short).
    dirty: bool,
}

pub(crate) fn millis(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

impl<T: AsyncRead + AsyncWrite + Unpin + Send, F: Framing> Wire<T, F> {
    pub fn new(
        io: T,
        framer: F,
        observer: Arc<dyn StageObserver>,
        timing: WireTiming,
        remedies: LinkRemedies,
    ) -> Self {
        Self {
            io,
            framer,
            observer,
            timing,
            remedies,
            seq: 0,
            dirty: false,
        }
    }

    /// Gives the byte stream back.
    pub fn into_inner(self) -> T {
        self.io
    }

    pub fn timing(&self) -> WireTiming {
        self.timing
    }

    /// `command` got no reply in `attempts` attempts of `timeout` each.
    pub fn no_reply(&self, command: &str, attempts: u32, timeout: Duration) -> StageError {
        StageError::NoReply {
            command: command.to_owned(),
            attempts,
            timeout,
            remedy: self.remedies.silent.clone(),
        }
    }

    /// The awaited reply came: nothing more is on its way.
    pub fn answered(&mut self) {
        self.dirty = false;
    }

    /// A reply (or a second line of one) may still come: the next send waits it out.
    pub fn mark_dirty(&mut self) {
        self.dirty = true;
    }

    /// The framer (its partial state explains a timeout).
    pub fn framer(&self) -> &F {
        &self.framer
    }

    /// Writes one request. With `settle`, first waits out a reply that a
    /// cancelled exchange may still produce.
    pub async fn send(
        &mut self,
        bytes: &[u8],
        text: &str,
        settle: bool,
        expects_reply: bool,
    ) -> Result<Sent, StageError> {
        self.send_within(
            bytes,
            text,
            settle,
            expects_reply,
            self.timing.reply_timeout,
        )
        .await
    }

    /// [`Self::send`] whose reply deadline is `reply_timeout` after the write.
    pub async fn send_within(
        &mut self,
        bytes: &[u8],
        text: &str,
        settle: bool,
        expects_reply: bool,
        reply_timeout: Duration,
    ) -> Result<Sent, StageError> {
        let timeout = self.timing.reply_timeout;
        if self.dirty && settle {
            self.resync(timeout, text).await?;
        }
        self.discard_arrived(text).await?;
        self.seq += 1;
        let at = Instant::now();
        let wall = wall_ns();
        let written = tokio::time::timeout_at(at + timeout, async {
            self.io.write_all(bytes).await?;
            self.io.flush().await
        })
        .await;
        let cause = match written {
            Ok(Ok(())) => None,
            Ok(Err(e)) => Some(e.to_string()),
            Err(_) => Some(format!("could not write within {timeout:?}")),
        };
        if let Some(cause) = cause {
            return Err(StageError::Disconnected {
                command: text.to_owned(),
                cause,
            });
        }
        if expects_reply {
            self.dirty = true;
        }
        Ok(Sent {
            seq: self.seq,
            at,
            wall_ns: wall,
            deadline: at + reply_timeout,
        })
    }

    /// Reads until one reply (or framing error) is complete, or the deadline passes.
    pub async fn receive(
        &mut self,
        deadline: Instant,
        text: &str,
    ) -> Result<Received<F::Reply, F::Error>, StageError> {
        loop {
            if let Some(r) = self.framer.next_reply() {
                return Ok(match r {
                    Ok(reply) => Received::Reply(reply),
                    Err(e) => Received::Frame(e),
                });
            }
            let mut buf = [0u8; 256];
            match tokio::time::timeout_at(deadline, self.io.read(&mut buf)).await {
                Err(_) => return Ok(Received::Timeout),
                Ok(Ok(0)) => return Err(lost(text, "the controller closed the connection")),
                Ok(Ok(n)) => self.framer.feed(&buf[..n]),
                Ok(Err(e)) => return Err(lost(text, &e.to_string())),
            }
        }
    }

    /// Takes in what has already arrived, without waiting; replies nobody asked
    /// for are discarded (and reported).
    async fn discard_arrived(&mut self, text: &str) -> Result<(), StageError> {
        loop {
            let mut buf = [0u8; 256];
            match tokio::time::timeout(Duration::ZERO, self.io.read(&mut buf)).await {
                Err(_) => break,
                Ok(Ok(0)) => return Err(lost(text, "the controller closed the connection")),
                Ok(Ok(n)) => self.framer.feed(&buf[..n]),
                Ok(Err(e)) => return Err(lost(text, &e.to_string())),
            }
        }
        self.report_strays();
        Ok(())
    }

    /// Discards input until `window` has passed and the line has been quiet for
    /// `resync_quiet`, then forgets any partial reply. A device that never
    /// falls quiet (wrong baud rate, another protocol) is given up on one reply
    /// timeout after the window: the next exchange then fails as garbled.
    pub async fn resync(&mut self, window: Duration, text: &str) -> Result<(), StageError> {
        let quiet = self.timing.resync_quiet;
        let window_end = Instant::now() + window;
        let give_up = window_end + quiet + self.timing.reply_timeout;
        let mut deadline = window_end.max(Instant::now() + quiet);
        while deadline < give_up {
            let mut buf = [0u8; 256];
            match tokio::time::timeout_at(deadline, self.io.read(&mut buf)).await {
                Err(_) => break,
                Ok(Ok(0)) => return Err(lost(text, "the controller closed the connection")),
                Ok(Ok(n)) => {
                    self.framer.feed(&buf[..n]);
                    deadline = window_end.max(Instant::now() + quiet).min(give_up);
                }
                Ok(Err(e)) => return Err(lost(text, &e.to_string())),
            }
        }
        self.report_strays();
        self.framer.reset();
        self.dirty = false;
        Ok(())
    }

    fn report_strays(&mut self) {
        while let Some(r) = self.framer.next_reply() {
            let (reply, detail) = match r {
                Ok(reply) => (Some(F::text(&reply)), None),
                Err(e) => (None, Some(e.to_string())),
            };
            warn!(reply = ?reply, detail = ?detail, "discarded a stage reply nobody was waiting for");
            self.observer.io(&StageIo {
                seq: self.seq,
                command: None,
                attempt: 0,
                sent_wall_ns: None,
                reply,
                reply_wall_ns: Some(wall_ns()),
                rtt_ns: None,
                outcome: IoOutcome::Stray,
                detail,
            });
        }
    }

    /// A reply that framed but does not answer the request: recorded, input
    /// resynchronised; returns the error to report if no attempt succeeds.
    pub async fn garbled(
        &mut self,
        sent: &Sent,
        text: &str,
        attempt: u32,
        reply: String,
        cause: String,
    ) -> Result<StageError, StageError> {
        self.record(
            sent,
            text,
            attempt,
            Some(reply.clone()),
            IoOutcome::Garbled,
            Some(cause.clone()),
        );
        debug!(command = %text, %reply, %cause, "garbled stage reply");
        self.resync(Duration::ZERO, text).await?;
        Ok(StageError::Garbled {
            command: text.to_owned(),
            reply: Some(reply),
            cause,
            attempts: attempt,
            remedy: self.remedies.garbled.clone(),
        })
    }

    /// Bytes that did not frame as a reply: recorded, input resynchronised;
    /// returns the error to report if no attempt succeeds.
    pub async fn unframeable(
        &mut self,
        sent: &Sent,
        text: &str,
        attempt: u32,
        cause: String,
    ) -> Result<StageError, StageError> {
        self.record(
            sent,
            text,
            attempt,
            None,
            IoOutcome::Garbled,
            Some(cause.clone()),
        );
        debug!(command = %text, %cause, "unframeable stage reply");
        self.resync(Duration::ZERO, text).await?;
        Ok(StageError::Garbled {
            command: text.to_owned(),
            reply: None,
            cause,
            attempts: attempt,
            remedy: self.remedies.garbled.clone(),
        })
    }

    /// No reply by the deadline: recorded with `detail`, then the reply, which
    /// may only be late, is let arrive and discarded. Returns the error to
    /// report if no attempt succeeds (`timeout` is the time each attempt had).
    pub async fn timed_out(
        &mut self,
        sent: &Sent,
        text: &str,
        attempt: u32,
        timeout: Duration,
        detail: String,
    ) -> Result<StageError, StageError> {
        self.record(sent, text, attempt, None, IoOutcome::Timeout, Some(detail));
        debug!(command = %text, attempt, "stage reply timed out");
        self.resync(self.timing.reply_timeout, text).await?;
        Ok(self.no_reply(text, attempt, timeout))
    }

    /// Records a request that gets no reply of its own.
    pub fn record_sent(&self, sent: &Sent, text: &str) {
        debug!(command = %text, "stage command sent");
        self.observer.io(&StageIo {
            seq: sent.seq,
            command: Some(text.to_owned()),
            attempt: 1,
            sent_wall_ns: Some(sent.wall_ns),
            reply: None,
            reply_wall_ns: None,
            rtt_ns: None,
            outcome: IoOutcome::Sent,
            detail: None,
        });
    }

    /// Records an exchange: its reply (decoded text) when one came, how it ended and why.
    pub fn record(
        &self,
        sent: &Sent,
        text: &str,
        attempt: u32,
        reply: Option<String>,
        outcome: IoOutcome,
        detail: Option<String>,
    ) {
        let rtt = sent.at.elapsed();
        if outcome == IoOutcome::Replied {
            debug!(command = %text, reply = %reply.as_deref().unwrap_or_default(), ms = millis(rtt), "stage exchange");
        }
        let replied = reply.is_some();
        self.observer.io(&StageIo {
            seq: sent.seq,
            command: Some(text.to_owned()),
            attempt,
            sent_wall_ns: Some(sent.wall_ns),
            reply,
            reply_wall_ns: replied.then(wall_ns),
            rtt_ns: replied.then(|| u64::try_from(rtt.as_nanos()).unwrap_or(u64::MAX)),
            outcome,
            detail,
        });
    }
}

fn lost(text: &str, cause: &str) -> StageError {
    StageError::Disconnected {
        command: text.to_owned(),
        cause: cause.to_owned(),
    }
}
