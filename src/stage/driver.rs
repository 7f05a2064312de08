//! The stage driver: PI GCS over any byte stream, one request in flight, every
//! move verified.
//!
//! Rules it follows (DESIGN §7):
//! - Queries have a timeout each; a timed-out or garbled query is retried a
//!   bounded number of times after resynchronising (input discarded until
//!   quiet, so that a late reply cannot answer the next question). A query that
//!   times out is followed by `ERR?`: a controller that rejects a query does not
//!   answer it, it sets an error.
//! - Commands that do not answer (`MOV`, `SVO`, `FRF`, `STP`) are followed by
//!   `ERR?`. Commands that move are never re-sent blindly.
//! - Every move is verified: `ONT?` until on target, then `POS?` within the
//!   tolerance. A stale on-target flag shows as a position still changing and is
//!   polled through; a position that stays off target without changing while the
//!   controller reports on target is a move that did not happen, re-issued once,
//!   then an error. Past the move timeout the stage is stopped.
//! - Targets outside the limits are refused before anything is sent.
//!
//! Known limit: reading `ERR?` clears the code, so when the answer to an `ERR?`
//! is lost its retry answers 0. For a move this costs nothing but time: the
//! verification sees the stage not moving and re-issues the move once.

use std::sync::Arc;
use std::time::Duration;

use sdsem_protocol::gcs::{
    AxisId, Command, ErrorQuery, FrameError, GcsErrorCode, IdentityQuery, MaxLimitQuery,
    MinLimitQuery, MotionStatus, MotionStatusQuery, OnTargetQuery, PositionQuery, Query,
    ReadyQuery, ReferencedQuery, Reply, ReplyFramer, ServoQuery,
};
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::time::Instant;
use tracing::{debug, error, info, warn};

use super::config::{StageAxis, StageConfig, secs};
use super::error::{StageError, remedy};
use super::observer::{
    AxisState, IoOutcome, StageEvent, StageIo, StageObserver, StageState, wall_ns,
};
use super::transport::{self, StageLink};

/// Where the stage is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StagePosition {
    /// X, µm.
    pub x_um: f64,
    /// Y, µm.
    pub y_um: f64,
    /// Tilt, degrees.
    pub tilt_deg: f64,
}

impl StagePosition {
    /// The position of one axis.
    pub fn get(&self, axis: StageAxis) -> f64 {
        match axis {
            StageAxis::X => self.x_um,
            StageAxis::Y => self.y_um,
            StageAxis::Tilt => self.tilt_deg,
        }
    }
}

/// What a verified move did.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MoveReport {
    /// The targets commanded.
    pub targets: Vec<(StageAxis, f64)>,
    /// The positions read back once on target (same order).
    pub positions: Vec<(StageAxis, f64)>,
    /// Whether the move had to be re-issued (it did not happen the first time).
    pub reissued: bool,
    /// `ONT?` polls made.
    pub polls: u32,
    /// From sending the move to verifying it.
    pub elapsed: Duration,
}

/// One framed input, or none in time.
enum Received {
    Reply(Reply),
    Frame(FrameError),
    Timeout,
}

/// A request on the wire.
struct Sent {
    seq: u64,
    at: Instant,
    wall_ns: u64,
    deadline: Instant,
}

/// The driver. Methods take `&mut self`: one request in flight.
///
/// Cancel safety: dropping a method's future mid-exchange (e.g. `select!` with
/// Ctrl-C) leaves the driver usable; the next call first discards the reply
/// that may still come. Call [`StageDriver::stop`] after an abort.
pub struct StageDriver<T> {
    io: T,
    framer: ReplyFramer,
    config: StageConfig,
    limits: [(f64, f64); 3],
    observer: Arc<dyn StageObserver>,
    seq: u64,
    /// A reply may still be on its way (an exchange was cut short).
    dirty: bool,
    identity: String,
}

fn slot(axis: StageAxis) -> usize {
    match axis {
        StageAxis::X => 0,
        StageAxis::Y => 1,
        StageAxis::Tilt => 2,
    }
}

fn millis(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

impl StageDriver<StageLink> {
    /// Opens `config.endpoint` through [`transport::open`] and connects.
    pub async fn open(
        config: StageConfig,
        observer: Arc<dyn StageObserver>,
    ) -> Result<Self, StageError> {
        config.validate()?;
        let link = transport::open(
            &config.endpoint,
            config.baud,
            secs(config.connect_timeout_s),
        )
        .await?;
        Self::connect(link, config, observer).await
    }
}

impl<T: AsyncRead + AsyncWrite + Unpin> StageDriver<T> {
    /// Connects over `io` and checks the controller: identity (`*IDN?`), servo
    /// states, reference states, soft limits. Fails saying exactly what is wrong
    /// (unless `auto_reference` may fix it).
    pub async fn connect(
        io: T,
        config: StageConfig,
        observer: Arc<dyn StageObserver>,
    ) -> Result<Self, StageError> {
        config.validate()?;
        let limits = StageAxis::ALL.map(|a| config.limits(a));
        let mut d = Self {
            io,
            framer: ReplyFramer::new(),
            config,
            limits,
            observer,
            seq: 0,
            dirty: false,
            identity: String::new(),
        };
        // Whatever a previous session left in the controller's output is not ours.
        d.resync(Duration::ZERO, "connect").await?;
        let idn = d.query(&IdentityQuery).await?;
        if !d.config.expect_idn.is_empty() && !idn.contains(&d.config.expect_idn) {
            return Err(StageError::UnexpectedIdentity {
                idn,
                expected: d.config.expect_idn.clone(),
            });
        }
        info!(idn = %idn, "stage controller identified");
        d.identity = idn;
        let pending = d.query(&ErrorQuery).await?;
        if pending.is_error() {
            info!(code = %pending, "cleared an error left pending in the stage controller");
        }
        let ids = d.ids(&StageAxis::ALL);
        let servo = d.query(&ServoQuery(ids.clone())).await?;
        let referenced = d.query(&ReferencedQuery(ids)).await?;
        let off = |flags: &[(AxisId, bool)]| -> Vec<AxisId> {
            flags
                .iter()
                .filter(|(_, on)| !on)
                .map(|(a, _)| a.clone())
                .collect()
        };
        let (servo_off, unreferenced) = (off(&servo), off(&referenced));
        if !servo_off.is_empty() || !unreferenced.is_empty() {
            if !d.config.auto_reference {
                let names = |v: &[AxisId]| v.iter().map(ToString::to_string).collect();
                return Err(StageError::NotReady {
                    unreferenced: names(&unreferenced),
                    servo_off: names(&servo_off),
                });
            }
            d.make_ready(servo_off, unreferenced).await?;
        }
        if d.config.read_controller_limits {
            d.read_controller_limits().await?;
        }
        d.read_position(StageEvent::Connected).await?;
        Ok(d)
    }

    /// The controller's answer to `*IDN?`.
    pub fn identity(&self) -> &str {
        &self.identity
    }

    /// The configuration in use.
    pub fn config(&self) -> &StageConfig {
        &self.config
    }

    /// The limits enforced for an axis: the configured ones, narrowed to the
    /// controller's soft limits when read.
    pub fn limits(&self, axis: StageAxis) -> (f64, f64) {
        self.limits[slot(axis)]
    }

    /// Gives the byte stream back.
    pub fn into_inner(self) -> T {
        self.io
    }

    /// Reads the three positions.
    pub async fn position(&mut self) -> Result<StagePosition, StageError> {
        self.read_position(StageEvent::Position).await
    }

    /// Tilts to `deg`, verified.
    pub async fn move_tilt(&mut self, deg: f64) -> Result<MoveReport, StageError> {
        self.move_to(&[(StageAxis::Tilt, deg)]).await
    }

    /// Moves X and Y together, verified.
    pub async fn move_xy(&mut self, x_um: f64, y_um: f64) -> Result<MoveReport, StageError> {
        self.move_to(&[(StageAxis::X, x_um), (StageAxis::Y, y_um)])
            .await
    }

    /// Returns to the configured safe tilt.
    pub async fn move_to_safe_tilt(&mut self) -> Result<MoveReport, StageError> {
        self.move_tilt(self.config.safe_tilt_deg).await
    }

    /// `#7`: whether the controller is ready (false while it references).
    pub async fn controller_ready(&mut self) -> Result<bool, StageError> {
        self.query(&ReadyQuery).await
    }

    /// `#5`: the motion bitmap; bit *i* is the *i*-th axis of the controller's own
    /// axis list (which need not be the X, Y, tilt order).
    pub async fn motion_status(&mut self) -> Result<MotionStatus, StageError> {
        self.query(&MotionStatusQuery).await
    }

    /// Moves the given axes together and verifies that they arrive.
    pub async fn move_to(
        &mut self,
        targets: &[(StageAxis, f64)],
    ) -> Result<MoveReport, StageError> {
        self.check_targets(targets)?;
        if targets.is_empty() {
            return Ok(MoveReport {
                targets: Vec::new(),
                positions: Vec::new(),
                reissued: false,
                polls: 0,
                elapsed: Duration::ZERO,
            });
        }
        let result = self.move_verified(targets).await;
        if let Err(e) = &result {
            error!(error = %e, "stage move lost");
        }
        result
    }

    /// Stops every axis at once (`STP`). Use on abort, on errors, on Ctrl-C.
    pub async fn stop(&mut self) -> Result<(), StageError> {
        let command = Command::Stp;
        let text = command.to_string();
        // No resynchronisation wait first: stopping must not be delayed.
        let sent = self.send(&command, &text, false).await?;
        self.record_sent(&sent, &text);
        let code = self.query_inner(&ErrorQuery, false).await?;
        if code != GcsErrorCode::STOPPED && code.is_error() {
            warn!(code = %code, "unexpected controller error after STP");
        }
        info!("stage stopped (STP)");
        let positions = self
            .query(&PositionQuery(self.ids(&StageAxis::ALL)))
            .await
            .ok();
        let axes = StageAxis::ALL
            .iter()
            .enumerate()
            .map(|(i, &axis)| AxisState {
                axis,
                id: self.config.axis_id(axis).to_string(),
                position: positions.as_ref().map(|p| p[i].1),
                target: None,
                on_target: None,
            })
            .collect();
        self.emit(StageEvent::Stopped, axes);
        Ok(())
    }

    /// Sends any typed query (retried after timeouts and garbled replies).
    pub async fn query<Q: Query>(&mut self, query: &Q) -> Result<Q::Output, StageError> {
        self.query_inner(query, true).await
    }

    fn ids(&self, axes: &[StageAxis]) -> Vec<AxisId> {
        axes.iter()
            .map(|&a| self.config.axis_id(a).clone())
            .collect()
    }

    fn check_targets(&self, targets: &[(StageAxis, f64)]) -> Result<(), StageError> {
        for (i, &(axis, target)) in targets.iter().enumerate() {
            if targets[..i].iter().any(|(a, _)| *a == axis) {
                return Err(StageError::Config {
                    field: "move targets",
                    reason: format!("the {axis} axis is given twice"),
                });
            }
            let (min, max) = self.limits(axis);
            if !(target.is_finite() && (min..=max).contains(&target)) {
                return Err(StageError::OutOfLimits {
                    axis,
                    target,
                    min,
                    max,
                    unit: axis.unit(),
                });
            }
        }
        Ok(())
    }

    fn move_timeout(&self, from: &[f64], targets: &[(StageAxis, f64)]) -> Duration {
        let travel_s = targets
            .iter()
            .zip(from)
            .map(|(&(axis, target), &p)| (target - p).abs() / self.config.speed(axis))
            .fold(0.0, f64::max);
        secs(travel_s * self.config.move_timeout_factor + self.config.move_timeout_margin_s)
    }

    fn axis_states(
        &self,
        targets: &[(StageAxis, f64)],
        positions: Option<&[f64]>,
        on: Option<&[bool]>,
    ) -> Vec<AxisState> {
        targets
            .iter()
            .enumerate()
            .map(|(i, &(axis, target))| AxisState {
                axis,
                id: self.config.axis_id(axis).to_string(),
                position: positions.map(|p| p[i]),
                target: Some(target),
                on_target: on.map(|o| o[i]),
            })
            .collect()
    }

    async fn move_verified(
        &mut self,
        targets: &[(StageAxis, f64)],
    ) -> Result<MoveReport, StageError> {
        let axes: Vec<StageAxis> = targets.iter().map(|&(a, _)| a).collect();
        let ids = self.ids(&axes);
        let start: Vec<f64> = self
            .query(&PositionQuery(ids.clone()))
            .await?
            .into_iter()
            .map(|(_, p)| p)
            .collect();
        let mov = Command::Mov(
            ids.iter()
                .cloned()
                .zip(targets.iter().map(|&(_, t)| t))
                .collect(),
        );
        let text = mov.to_string();
        self.emit(
            StageEvent::MoveStarted,
            self.axis_states(targets, Some(&start), None),
        );
        let started = Instant::now();
        self.command(&mov).await?;

        let poll = secs(self.config.poll_interval_s);
        let no_motion = secs(self.config.no_motion_timeout_s);
        let mut timeout = self.move_timeout(&start, targets);
        let mut deadline = started + timeout;
        let mut reissued = false;
        let mut last_pos = start;
        let mut last_progress = Instant::now();
        let mut polls = 0u32;
        loop {
            tokio::time::sleep(poll).await;
            polls += 1;
            let on: Vec<bool> = self
                .query(&OnTargetQuery(ids.clone()))
                .await?
                .into_iter()
                .map(|(_, f)| f)
                .collect();
            if on.iter().all(|&f| f) {
                let pos: Vec<f64> = self
                    .query(&PositionQuery(ids.clone()))
                    .await?
                    .into_iter()
                    .map(|(_, p)| p)
                    .collect();
                self.emit(
                    StageEvent::Poll,
                    self.axis_states(targets, Some(&pos), Some(&on)),
                );
                let off = targets
                    .iter()
                    .zip(&pos)
                    .position(|(&(axis, t), &p)| (p - t).abs() > self.config.tolerance(axis));
                let Some(off) = off else {
                    let elapsed = started.elapsed();
                    self.emit(
                        StageEvent::Reached,
                        self.axis_states(targets, Some(&pos), Some(&on)),
                    );
                    debug!(command = %text, ms = millis(elapsed), polls, "stage move verified");
                    return Ok(MoveReport {
                        targets: targets.to_vec(),
                        positions: axes.iter().copied().zip(pos).collect(),
                        reissued,
                        polls,
                        elapsed,
                    });
                };
                // "On target" yet not there: a stale flag (the position still
                // changes) or a move that did not happen (it does not).
                let moved = targets
                    .iter()
                    .zip(pos.iter().zip(&last_pos))
                    .any(|(&(axis, _), (&p, &q))| (p - q).abs() > self.config.tolerance(axis));
                if moved {
                    last_pos = pos;
                    last_progress = Instant::now();
                } else if last_progress.elapsed() >= no_motion {
                    let (axis, target) = targets[off];
                    if reissued {
                        return Err(StageError::MoveNotExecuted {
                            command: text,
                            axis,
                            target,
                            position: pos[off],
                            tolerance: self.config.tolerance(axis),
                            unit: axis.unit(),
                        });
                    }
                    warn!(
                        command = %text, %axis, position = pos[off], target,
                        "stage reports on target but did not move; re-issuing the move once"
                    );
                    self.command(&mov).await?;
                    self.emit(
                        StageEvent::MoveReissued,
                        self.axis_states(targets, Some(&pos), Some(&on)),
                    );
                    reissued = true;
                    last_progress = Instant::now();
                    timeout = self.move_timeout(&pos, targets);
                    deadline = last_progress + timeout;
                    last_pos = pos;
                }
            }
            if Instant::now() >= deadline {
                let now_at: Option<Vec<f64>> = self
                    .query(&PositionQuery(ids.clone()))
                    .await
                    .ok()
                    .map(|v| v.into_iter().map(|(_, p)| p).collect());
                let i = on.iter().position(|&f| !f).unwrap_or(0);
                let (axis, target) = targets[i];
                if let Err(e) = self.stop().await {
                    warn!(error = %e, "could not stop the stage after a move timeout");
                }
                return Err(StageError::MoveTimeout {
                    command: text,
                    axis,
                    target,
                    position: now_at.map(|p| p[i]),
                    timeout,
                });
            }
        }
    }

    async fn read_position(&mut self, event: StageEvent) -> Result<StagePosition, StageError> {
        let v = self
            .query(&PositionQuery(self.ids(&StageAxis::ALL)))
            .await?;
        let p = StagePosition {
            x_um: v[0].1,
            y_um: v[1].1,
            tilt_deg: v[2].1,
        };
        let axes = StageAxis::ALL
            .iter()
            .map(|&axis| AxisState {
                axis,
                id: self.config.axis_id(axis).to_string(),
                position: Some(p.get(axis)),
                target: None,
                on_target: None,
            })
            .collect();
        self.emit(event, axes);
        Ok(p)
    }

    /// `auto_reference`: servo on, then `FRF` and wait for `FRF?` = 1.
    async fn make_ready(
        &mut self,
        servo_off: Vec<AxisId>,
        unreferenced: Vec<AxisId>,
    ) -> Result<(), StageError> {
        if !servo_off.is_empty() {
            info!(axes = ?servo_off, "switching the stage servos on (auto_reference)");
            self.command(&Command::Svo(
                servo_off.into_iter().map(|a| (a, true)).collect(),
            ))
            .await?;
        }
        if unreferenced.is_empty() {
            return Ok(());
        }
        info!(axes = ?unreferenced, "referencing the stage axes (auto_reference)");
        self.command(&Command::Frf(unreferenced.clone())).await?;
        let timeout = secs(self.config.reference_timeout_s);
        let deadline = Instant::now() + timeout;
        loop {
            tokio::time::sleep(secs(self.config.poll_interval_s)).await;
            let done = self.query(&ReferencedQuery(unreferenced.clone())).await?;
            if done.iter().all(|(_, f)| *f) {
                return Ok(());
            }
            if Instant::now() >= deadline {
                if let Err(e) = self.stop().await {
                    warn!(error = %e, "could not stop the stage after a referencing timeout");
                }
                return Err(StageError::ReferenceTimeout {
                    axes: done
                        .iter()
                        .filter(|(_, f)| !f)
                        .map(|(a, _)| a.to_string())
                        .collect(),
                    timeout,
                });
            }
        }
    }

    /// Narrows the configured limits to the controller's soft limits.
    async fn read_controller_limits(&mut self) -> Result<(), StageError> {
        let ids = self.ids(&StageAxis::ALL);
        let lows = match self.query(&MinLimitQuery(ids.clone())).await {
            Ok(v) => v,
            Err(StageError::Controller { code, .. }) if code == GcsErrorCode::UNKNOWN_COMMAND => {
                info!(
                    "the stage controller does not report soft limits; using the configured ones"
                );
                return Ok(());
            }
            Err(e) => return Err(e),
        };
        let highs = self.query(&MaxLimitQuery(ids)).await?;
        for (i, axis) in StageAxis::ALL.into_iter().enumerate() {
            let (min, max) = self.limits[i];
            let (lo, hi) = (lows[i].1, highs[i].1);
            let narrowed = (min.max(lo), max.min(hi));
            if narrowed.0 >= narrowed.1 {
                return Err(StageError::Config {
                    field: axis.limit_fields(),
                    reason: format!(
                        "[{min}, {max}] does not overlap the controller's soft limits [{lo}, {hi}]"
                    ),
                });
            }
            if narrowed != (min, max) {
                info!(%axis, configured = ?(min, max), controller = ?(lo, hi), "limits narrowed to the controller's");
            }
            self.limits[i] = narrowed;
        }
        Ok(())
    }

    /// Sends a command that does not answer, then asks `ERR?`.
    async fn command(&mut self, command: &Command) -> Result<(), StageError> {
        let text = command.to_string();
        let sent = self.send(command, &text, true).await?;
        self.record_sent(&sent, &text);
        let code = self.query_inner(&ErrorQuery, false).await?;
        if code.is_error() {
            return Err(StageError::Controller {
                command: text,
                code,
                remedy: remedy(code),
            });
        }
        Ok(())
    }

    /// A query with bounded retries. With `explain_timeouts`, a timeout is
    /// followed by `ERR?`, since a controller does not answer a query it rejects.
    async fn query_inner<Q: Query>(
        &mut self,
        query: &Q,
        explain_timeouts: bool,
    ) -> Result<Q::Output, StageError> {
        let command = query.command();
        let text = command.to_string();
        let timeout = secs(self.config.reply_timeout_s);
        let attempts = self.config.query_retries.saturating_add(1);
        let mut failure = StageError::NoReply {
            command: text.clone(),
            attempts,
            timeout,
        };
        for attempt in 1..=attempts {
            let sent = self.send(&command, &text, true).await?;
            match self.receive(sent.deadline, &text).await? {
                Received::Reply(reply) => match query.parse_reply(&reply) {
                    Ok(value) => {
                        self.dirty = false;
                        self.record(
                            &sent,
                            &text,
                            attempt,
                            Some(&reply),
                            IoOutcome::Replied,
                            None,
                        );
                        if attempt > 1 {
                            warn!(command = %text, attempt, "stage query recovered by a retry");
                        }
                        return Ok(value);
                    }
                    Err(e) => {
                        let cause = e.to_string();
                        self.record(
                            &sent,
                            &text,
                            attempt,
                            Some(&reply),
                            IoOutcome::Garbled,
                            Some(cause.clone()),
                        );
                        debug!(command = %text, reply = %reply.to_text(), %cause, "garbled stage reply");
                        failure = StageError::Garbled {
                            command: text.clone(),
                            reply: Some(reply.to_text()),
                            cause,
                            attempts: attempt,
                        };
                        self.resync(Duration::ZERO, &text).await?;
                    }
                },
                Received::Frame(e) => {
                    let cause = e.to_string();
                    self.record(
                        &sent,
                        &text,
                        attempt,
                        None,
                        IoOutcome::Garbled,
                        Some(cause.clone()),
                    );
                    debug!(command = %text, %cause, "unframeable stage reply");
                    failure = StageError::Garbled {
                        command: text.clone(),
                        reply: None,
                        cause,
                        attempts: attempt,
                    };
                    self.resync(Duration::ZERO, &text).await?;
                }
                Received::Timeout => {
                    self.record(
                        &sent,
                        &text,
                        attempt,
                        None,
                        IoOutcome::Timeout,
                        Some(format!("no reply within {timeout:?}")),
                    );
                    debug!(command = %text, attempt, "stage reply timed out");
                    failure = StageError::NoReply {
                        command: text.clone(),
                        attempts: attempt,
                        timeout,
                    };
                    // The reply may only be late: let it arrive and discard it.
                    self.resync(timeout, &text).await?;
                    if explain_timeouts {
                        let code = Box::pin(self.query_inner(&ErrorQuery, false)).await?;
                        if code.is_error() {
                            return Err(StageError::Controller {
                                command: text,
                                code,
                                remedy: remedy(code),
                            });
                        }
                    }
                }
            }
        }
        Err(failure)
    }

    /// Writes one command. With `settle`, first waits out a reply that a
    /// cancelled exchange may still produce.
    async fn send(
        &mut self,
        command: &Command,
        text: &str,
        settle: bool,
    ) -> Result<Sent, StageError> {
        let timeout = secs(self.config.reply_timeout_s);
        if self.dirty && settle {
            self.resync(timeout, text).await?;
        }
        self.discard_arrived(text).await?;
        self.seq += 1;
        let bytes = command.to_bytes();
        let at = Instant::now();
        let wall = wall_ns();
        let deadline = at + timeout;
        let written = tokio::time::timeout_at(deadline, async {
            self.io.write_all(&bytes).await?;
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
        if command.expects_reply() {
            self.dirty = true;
        }
        Ok(Sent {
            seq: self.seq,
            at,
            wall_ns: wall,
            deadline,
        })
    }

    /// Reads until one reply (or framing error) is complete, or the deadline passes.
    async fn receive(&mut self, deadline: Instant, text: &str) -> Result<Received, StageError> {
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
                Ok(Ok(0)) => return Err(self.lost(text, "the controller closed the connection")),
                Ok(Ok(n)) => self.framer.feed(&buf[..n]),
                Ok(Err(e)) => return Err(self.lost(text, &e.to_string())),
            }
        }
    }

    fn lost(&self, text: &str, cause: &str) -> StageError {
        StageError::Disconnected {
            command: text.to_owned(),
            cause: cause.to_owned(),
        }
    }

    /// Takes in what has already arrived, without waiting; replies nobody asked
    /// for are discarded (and reported).
    async fn discard_arrived(&mut self, text: &str) -> Result<(), StageError> {
        loop {
            let mut buf = [0u8; 256];
            match tokio::time::timeout(Duration::ZERO, self.io.read(&mut buf)).await {
                Err(_) => break,
                Ok(Ok(0)) => return Err(self.lost(text, "the controller closed the connection")),
                Ok(Ok(n)) => self.framer.feed(&buf[..n]),
                Ok(Err(e)) => return Err(self.lost(text, &e.to_string())),
            }
        }
        self.report_strays();
        Ok(())
    }

    /// Discards input until `window` has passed and the line has been quiet for
    /// `resync_quiet_s`, then forgets any partial reply. A device that never
    /// falls quiet (wrong baud rate, not a GCS controller) is given up on one
    /// reply timeout after the window: the next exchange then fails as garbled.
    async fn resync(&mut self, window: Duration, text: &str) -> Result<(), StageError> {
        let quiet = secs(self.config.resync_quiet_s);
        let window_end = Instant::now() + window;
        let give_up = window_end + quiet + secs(self.config.reply_timeout_s);
        let mut deadline = window_end.max(Instant::now() + quiet);
        while deadline < give_up {
            let mut buf = [0u8; 256];
            match tokio::time::timeout_at(deadline, self.io.read(&mut buf)).await {
                Err(_) => break,
                Ok(Ok(0)) => return Err(self.lost(text, "the controller closed the connection")),
                Ok(Ok(n)) => {
                    self.framer.feed(&buf[..n]);
                    deadline = window_end.max(Instant::now() + quiet).min(give_up);
                }
                Ok(Err(e)) => return Err(self.lost(text, &e.to_string())),
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
                Ok(reply) => (Some(reply.to_text()), None),
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

    fn record_sent(&self, sent: &Sent, text: &str) {
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

    fn record(
        &self,
        sent: &Sent,
        text: &str,
        attempt: u32,
        reply: Option<&Reply>,
        outcome: IoOutcome,
        detail: Option<String>,
    ) {
        let rtt = sent.at.elapsed();
        if outcome == IoOutcome::Replied {
            debug!(command = %text, reply = %reply.map(Reply::to_text).unwrap_or_default(), ms = millis(rtt), "stage exchange");
        }
        self.observer.io(&StageIo {
            seq: sent.seq,
            command: Some(text.to_owned()),
            attempt,
            sent_wall_ns: Some(sent.wall_ns),
            reply: reply.map(Reply::to_text),
            reply_wall_ns: reply.map(|_| wall_ns()),
            rtt_ns: reply.map(|_| u64::try_from(rtt.as_nanos()).unwrap_or(u64::MAX)),
            outcome,
            detail,
        });
    }

    fn emit(&self, event: StageEvent, axes: Vec<AxisState>) {
        self.observer.state(&StageState {
            wall_ns: wall_ns(),
            event,
            axes,
        });
    }
}
