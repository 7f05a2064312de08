//! What differs per stage protocol: the [`StageBackend`] trait that each
//! driver (PI GCS, Zeiss RemCon32, …) implements. Everything that keeps the
//! specimen safe (limits, move timeouts, verification by read-back, one
//! re-issue, safe tilt, stop) is in [`super::StageDriver`], once, above all of them.
//!
//! A backend reports every exchange to the [`super::StageObserver`] as a
//! decoded [`super::StageIo`] (command word and arguments, reply, timings,
//! outcome). Units across this trait are sdsem's: µm for X/Y, degrees for tilt.

use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::config::{StageAxis, StageProtocol};
use super::error::StageError;

/// A boxed `Send` future: the trait's methods return these so that a backend
/// can be chosen at run time (`Box<dyn StageBackend>`).
pub type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// Who the instrument says it is (for the record and `sdsem probe`); fields
/// the protocol does not report are empty.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StageIdentity {
    /// `stage.protocol`: `pi-gcs`, `remcon32`, …
    pub protocol: String,
    /// Manufacturer.
    pub vendor: String,
    /// Controller or instrument model.
    pub model: String,
    /// Firmware or software version.
    pub version: String,
    /// Serial number.
    pub serial: String,
    /// The instrument's identification answer as received (`*IDN?`, `VER?`).
    pub raw: String,
}

/// What a backend learnt at connect.
#[derive(Clone, Debug, PartialEq)]
pub struct Connected {
    /// The instrument's identity.
    pub identity: StageIdentity,
    /// The instrument's own limits per axis ([`StageAxis::ALL`] order), when it
    /// reports them: they only ever narrow the configured ones.
    pub limits: [Option<(f64, f64)>; 3],
}

/// One poll of a move in progress.
#[derive(Clone, Debug, PartialEq)]
pub struct MotionPoll {
    /// Per axis asked for: whether the instrument reports it settled (on target, not moving).
    pub settled: Vec<bool>,
    /// The positions, when the same answer carried them (saves a query).
    pub positions: Option<Vec<f64>>,
}

/// One stage protocol. Methods take `&mut self`: one request in flight.
///
/// Cancel safety: dropping a returned future mid-exchange must leave the
/// backend usable (the next exchange discards the reply that may still come).
pub trait StageBackend: Send {
    /// Which protocol this is.
    fn protocol(&self) -> StageProtocol;

    /// Checks the instrument once, before anything else: identity, readiness,
    /// its own limits. Moves nothing unless the configuration allows it
    /// (`stage.auto_reference` on PI GCS).
    fn connect(&mut self) -> BoxFuture<'_, Result<Connected, StageError>>;

    /// The instrument's name of an axis, for the record (`T`, `3`, `t`).
    fn axis_name(&self, axis: StageAxis) -> String;

    /// The positions of `axes`, in that order (µm, degrees).
    fn read_position<'a>(
        &'a mut self,
        axes: &'a [StageAxis],
    ) -> BoxFuture<'a, Result<Vec<f64>, StageError>>;

    /// Starts an absolute move of the given axes together (vendor specifics such
    /// as read-modify-write and axis order included) and returns the command
    /// as recorded, for messages. Returns before the move ends; refusals by the
    /// instrument are errors.
    fn start_move<'a>(
        &'a mut self,
        targets: &'a [(StageAxis, f64)],
    ) -> BoxFuture<'a, Result<String, StageError>>;

    /// How long after a move command a "settled" flag may still be stale (RemCon32 sets
    /// its moving flag late, ~1 s [OD-Z]); zero when the flags hold at once. Until then
    /// the safety layer takes arrival only from positions (on target and holding still).
    fn flag_delay(&self) -> Duration;

    /// Whether each of `axes` has settled.
    fn poll_motion<'a>(
        &'a mut self,
        axes: &'a [StageAxis],
    ) -> BoxFuture<'a, Result<MotionPoll, StageError>>;

    /// Stops every axis at once, without delay.
    fn stop(&mut self) -> BoxFuture<'_, Result<(), StageError>>;

    /// Sends one raw command line of the vendor's language (a watch-folder
    /// trigger such as `FREC`) and returns the reply's data. A protocol that
    /// cannot carry one says so in [`StageError::Unsupported`].
    fn send_raw<'a>(
        &'a mut self,
        line: &'a str,
        timeout: Duration,
    ) -> BoxFuture<'a, Result<String, StageError>>;

    /// What `sdsem probe` shows besides identity, position and limits: the instrument's own
    /// state read by queries that move nothing (servo and reference states, pixel size,
    /// magnification, detector), as (name, value) lines; a query the instrument does not
    /// answer is a line saying so. Protocols with nothing more to say keep this default.
    fn probe_facts(&mut self) -> BoxFuture<'_, Result<Vec<(String, String)>, StageError>> {
        Box::pin(async { Ok(Vec::new()) })
    }
}

impl<B: StageBackend + ?Sized> StageBackend for Box<B> {
    fn protocol(&self) -> StageProtocol {
        (**self).protocol()
    }
    fn connect(&mut self) -> BoxFuture<'_, Result<Connected, StageError>> {
        (**self).connect()
    }
    fn axis_name(&self, axis: StageAxis) -> String {
        (**self).axis_name(axis)
    }
    fn read_position<'a>(
        &'a mut self,
        axes: &'a [StageAxis],
    ) -> BoxFuture<'a, Result<Vec<f64>, StageError>> {
        (**self).read_position(axes)
    }
    fn start_move<'a>(
        &'a mut self,
        targets: &'a [(StageAxis, f64)],
    ) -> BoxFuture<'a, Result<String, StageError>> {
        (**self).start_move(targets)
    }
    fn flag_delay(&self) -> Duration {
        (**self).flag_delay()
    }
    fn poll_motion<'a>(
        &'a mut self,
        axes: &'a [StageAxis],
    ) -> BoxFuture<'a, Result<MotionPoll, StageError>> {
        (**self).poll_motion(axes)
    }
    fn stop(&mut self) -> BoxFuture<'_, Result<(), StageError>> {
        (**self).stop()
    }
    fn send_raw<'a>(
        &'a mut self,
        line: &'a str,
        timeout: Duration,
    ) -> BoxFuture<'a, Result<String, StageError>> {
        (**self).send_raw(line, timeout)
    }
    fn probe_facts(&mut self) -> BoxFuture<'_, Result<Vec<(String, String)>, StageError>> {
        (**self).probe_facts()
    }
}
