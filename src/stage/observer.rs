//! What the driver reports as it works: every exchange on the wire and every
//! position that matters, as plain serialisable records (the recorder writes
//! them to `/stage/io` and `/stage/state`, DESIGN §5).

use std::sync::{Mutex, PoisonError};
use std::time::{SystemTime, UNIX_EPOCH};

use serde::{Deserialize, Serialize};

use super::config::StageAxis;

/// Receives the driver's records. Called inline from the driver: keep it quick
/// (hand the record to a channel).
pub trait StageObserver: Send + Sync {
    /// One exchange: a command sent and its reply, a timeout, a garbled or stray reply.
    fn io(&self, e: &StageIo);
    /// A stage state worth recording: connected, move started, poll results, target reached.
    fn state(&self, s: &StageState);
}

/// How an exchange ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum IoOutcome {
    /// A query and its reply.
    Replied,
    /// A command that does not answer (its `ERR?` follows as its own exchange).
    Sent,
    /// No reply within the timeout.
    Timeout,
    /// A reply that does not parse, or bytes that do not frame.
    Garbled,
    /// A reply nobody asked for (a late reply), discarded.
    Stray,
}

/// One exchange on the wire.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StageIo {
    /// Exchange number since connect (strays share the number of the exchange they disturbed).
    pub seq: u64,
    /// The command line sent, printable (`MOV 3 7`, `#5`); none for stray bytes.
    pub command: Option<String>,
    /// Which attempt of this command (1 = first).
    pub attempt: u32,
    /// Wall-clock time the command was written, ns since the Unix epoch.
    pub sent_wall_ns: Option<u64>,
    /// The reply, printable (lines joined by `\n`, other bytes as `\xNN`).
    pub reply: Option<String>,
    /// Wall-clock time the reply was complete, ns since the Unix epoch.
    pub reply_wall_ns: Option<u64>,
    /// Round-trip time, ns.
    pub rtt_ns: Option<u64>,
    /// How the exchange ended.
    pub outcome: IoOutcome,
    /// Why, for timeouts and garbled replies.
    pub detail: Option<String>,
}

/// What happened to the stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StageEvent {
    /// Connected and checked; positions as found.
    Connected,
    /// A move was sent; positions before it, targets set.
    MoveStarted,
    /// A poll during a move.
    Poll,
    /// A move was re-issued after it did not happen.
    MoveReissued,
    /// A move was verified: positions reached.
    Reached,
    /// The stage was stopped.
    Stopped,
    /// Positions read on request.
    Position,
}

/// One axis in a [`StageState`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AxisState {
    /// The axis role.
    pub axis: StageAxis,
    /// Its GCS identifier.
    pub id: String,
    /// Position, µm or degrees, when read.
    pub position: Option<f64>,
    /// Target, when a move is involved.
    pub target: Option<f64>,
    /// The controller's on-target flag, when read.
    pub on_target: Option<bool>,
}

/// A stage state worth recording.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StageState {
    /// Wall-clock time, ns since the Unix epoch.
    pub wall_ns: u64,
    /// What happened.
    pub event: StageEvent,
    /// The axes involved.
    pub axes: Vec<AxisState>,
}

/// An observer that drops everything.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoopObserver;

impl StageObserver for NoopObserver {
    fn io(&self, _: &StageIo) {}
    fn state(&self, _: &StageState) {}
}

/// An observer that keeps everything in memory (tests, diagnostics).
#[derive(Debug, Default)]
pub struct MemoryObserver {
    io: Mutex<Vec<StageIo>>,
    states: Mutex<Vec<StageState>>,
}

impl MemoryObserver {
    /// A copy of the exchanges recorded so far.
    pub fn io_records(&self) -> Vec<StageIo> {
        self.io
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// A copy of the states recorded so far.
    pub fn states(&self) -> Vec<StageState> {
        self.states
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }
}

impl StageObserver for MemoryObserver {
    fn io(&self, e: &StageIo) {
        self.io
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(e.clone());
    }
    fn state(&self, s: &StageState) {
        self.states
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(s.clone());
    }
}

/// Wall-clock now, ns since the Unix epoch (0 if the clock is before 1970).
pub(crate) fn wall_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}
