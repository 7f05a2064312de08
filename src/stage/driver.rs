//! The safety layer: one [`StageDriver`] above every stage protocol
//! ([`StageBackend`]), holding every rule that keeps the specimen and the
//! column safe, once:
//!
//! - Targets outside the limits are refused before anything is sent. The
//!   limits are the configured ones, narrowed (never widened) by those the
//!   instrument reports.
//! - Every move is verified: the motion flags are polled until the axes settle,
//!   then the position is read back within the tolerance. A stale "settled" flag
//!   shows as a position still changing and is polled through. Within the
//!   backend's flag delay (RemCon32 sets its moving flag late) a "settled" flag
//!   proves nothing: arrival then needs two consecutive polls on target with the
//!   position unchanged between them. A position that stays off target without
//!   changing while the instrument reports it settled, past that delay, is a move
//!   that did not happen, re-issued once, then an error. Past the move timeout
//!   the stage is stopped.
//! - [`StageDriver::stop`] stops every axis at once (after an abort, on
//!   errors); [`StageDriver::move_to_safe_tilt`] returns to the safe tilt.
//! - Cancel safety: dropping a method's future mid-exchange (e.g. `select!`
//!   with Ctrl-C) leaves the driver usable; the backend discards the reply that
//!   may still come. Call [`StageDriver::stop`] after an abort.

use std::sync::Arc;
use std::time::Duration;

use sdsem_protocol::gcs::{MotionStatus, Query};
use serde::{Deserialize, Serialize};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::time::Instant;
use tracing::{debug, error, info, warn};

use super::backend::{Connected, StageBackend, StageIdentity};
use super::config::{StageAxis, StageConfig, StageProtocol, secs};
use super::error::StageError;
use super::gcs::GcsBackend;
use super::observer::{AxisState, StageEvent, StageObserver, StageState, wall_ns};
use super::wire::millis;

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
    /// Motion polls made (`ONT?` on PI GCS, `C95?` on RemCon32).
    pub polls: u32,
    /// From sending the move to verifying it.
    pub elapsed: Duration,
}

/// The stage, whatever its protocol. Methods take `&mut self`: one request in flight.
///
/// `B` is the backend: [`GcsBackend`] over a byte stream in tests, or the
/// backend chosen by `stage.protocol` ([`StageDriver::open`], the default type).
pub struct StageDriver<B: StageBackend = Box<dyn StageBackend>> {
    backend: B,
    config: StageConfig,
    limits: [(f64, f64); 3],
    /// The limits the instrument reported at connect, per axis.
    instrument_limits: [Option<(f64, f64)>; 3],
    observer: Arc<dyn StageObserver>,
    identity: StageIdentity,
}

fn slot(axis: StageAxis) -> usize {
    match axis {
        StageAxis::X => 0,
        StageAxis::Y => 1,
        StageAxis::Tilt => 2,
    }
}

impl StageDriver {
    /// Opens `config.endpoint` with the backend of `config.protocol`
    /// ([`super::open_backend`]) and connects.
    pub async fn open(
        config: StageConfig,
        observer: Arc<dyn StageObserver>,
    ) -> Result<Self, StageError> {
        config.validate()?;
        let backend = super::open_backend(&config, Arc::clone(&observer)).await?;
        Self::with_backend(backend, config, observer).await
    }
}

impl<T: AsyncRead + AsyncWrite + Unpin + Send> StageDriver<GcsBackend<T>> {
    /// Connects to a PI GCS controller over `io` and checks it: identity
    /// (`*IDN?`), servo states, reference states, soft limits. Fails saying
    /// exactly what is wrong (unless `auto_reference` may fix it).
    pub async fn connect(
        io: T,
        config: StageConfig,
        observer: Arc<dyn StageObserver>,
    ) -> Result<Self, StageError> {
        config.validate()?;
        let backend = GcsBackend::new(io, config.clone(), Arc::clone(&observer));
        Self::with_backend(backend, config, observer).await
    }

    /// Sends any typed GCS query (retried after timeouts and garbled replies).
    pub async fn query<Q: Query>(&mut self, query: &Q) -> Result<Q::Output, StageError> {
        self.backend.query(query).await
    }

    /// `#7`: whether the controller is ready (false while it references).
    pub async fn controller_ready(&mut self) -> Result<bool, StageError> {
        self.backend.controller_ready().await
    }

    /// `#5`: the motion bitmap; bit *i* is the *i*-th axis of the controller's own
    /// axis list (which need not be the X, Y, tilt order).
    pub async fn motion_status(&mut self) -> Result<MotionStatus, StageError> {
        self.backend.motion_status().await
    }

    /// Gives the byte stream back.
    pub fn into_inner(self) -> T {
        self.backend.into_inner()
    }
}

impl<B: StageBackend> StageDriver<B> {
    /// Connects through `backend` (checks the instrument, narrows the limits
    /// to the instrument's, reads where the stage is).
    pub async fn with_backend(
        mut backend: B,
        config: StageConfig,
        observer: Arc<dyn StageObserver>,
    ) -> Result<Self, StageError> {
        config.validate()?;
        let Connected {
            identity,
            limits: instrument,
        } = backend.connect().await?;
        let mut limits = StageAxis::ALL.map(|a| config.limits(a));
        for (i, axis) in StageAxis::ALL.into_iter().enumerate() {
            let Some((lo, hi)) = instrument[i] else {
                continue;
            };
            let (min, max) = limits[i];
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
            limits[i] = narrowed;
        }
        let mut d = Self {
            backend,
            config,
            limits,
            instrument_limits: instrument,
            observer,
            identity,
        };
        d.read_position(StageEvent::Connected).await?;
        Ok(d)
    }

    /// The instrument's identification answer as received (`*IDN?`, `VER?`).
    pub fn identity(&self) -> &str {
        &self.identity.raw
    }

    /// The instrument's identity, field by field.
    pub fn instrument(&self) -> &StageIdentity {
        &self.identity
    }

    /// The protocol in use.
    pub fn protocol(&self) -> StageProtocol {
        self.backend.protocol()
    }

    /// The configuration in use.
    pub fn config(&self) -> &StageConfig {
        &self.config
    }

    /// The backend (protocol-specific queries).
    pub fn backend_mut(&mut self) -> &mut B {
        &mut self.backend
    }

    /// The limits enforced for an axis: the configured ones, narrowed to the
    /// controller's soft limits when read.
    pub fn limits(&self, axis: StageAxis) -> (f64, f64) {
        self.limits[slot(axis)]
    }

    /// The limits the instrument itself reported for an axis at connect (PI GCS `TMN?`/`TMX?`
    /// when read), if any; [`Self::limits`] are the configured ones narrowed to them.
    pub fn instrument_limits(&self, axis: StageAxis) -> Option<(f64, f64)> {
        self.instrument_limits[slot(axis)]
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

    /// Stops every axis at once. Use on abort, on errors, on Ctrl-C.
    pub async fn stop(&mut self) -> Result<(), StageError> {
        self.backend.stop().await?;
        let positions = self.backend.read_position(&StageAxis::ALL).await.ok();
        let axes = StageAxis::ALL
            .iter()
            .enumerate()
            .map(|(i, &axis)| AxisState {
                axis,
                id: self.backend.axis_name(axis),
                position: positions.as_ref().map(|p| p[i]),
                target: None,
                on_target: None,
            })
            .collect();
        self.emit(StageEvent::Stopped, axes);
        Ok(())
    }

    /// Sends a watch-folder trigger (`imaging.trigger`, e.g. `FREC` or `MAC 1`
    /// on RemCon32) over the stage link and waits until the SEM reports it done
    /// (at most `stage.trigger_timeout_s`); returns the reply's data.
    /// Recorded in `/stage/io` like every exchange.
    pub async fn send_trigger(&mut self, line: &str) -> Result<String, StageError> {
        let printable = !line.is_empty() && line.bytes().all(|b| (0x20..=0x7E).contains(&b));
        if !printable || line.trim() != line {
            return Err(StageError::Config {
                field: "imaging.trigger",
                reason: format!(
                    "{line:?}: write one command of printable ASCII without leading or trailing \
                     spaces, e.g. \"FREC\" or \"MAC 1\""
                ),
            });
        }
        let timeout = secs(self.config.trigger_timeout_s);
        let reply = self.backend.send_raw(line, timeout).await?;
        info!(trigger = %line, reply = %reply, "SEM trigger done");
        Ok(reply)
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
                id: self.backend.axis_name(axis),
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
        let start = self.backend.read_position(&axes).await?;
        self.emit(
            StageEvent::MoveStarted,
            self.axis_states(targets, Some(&start), None),
        );
        let started = Instant::now();
        let text = self.backend.start_move(targets).await?;

        let poll = secs(self.config.poll_interval_s);
        let no_motion = secs(self.config.no_motion_timeout_s);
        let mut timeout = self.move_timeout(&start, targets);
        let mut deadline = started + timeout;
        let mut reissued = false;
        let mut last_pos = start;
        let mut last_progress = Instant::now();
        let mut polls = 0u32;
        // Until then a "settled" flag may be stale (set late after the command).
        let mut flags_trusted_at = started + self.backend.flag_delay();
        // The previous poll's positions when it read settled and on target.
        let mut on_target_before: Option<Vec<f64>> = None;
        loop {
            tokio::time::sleep(poll).await;
            polls += 1;
            let motion = self.backend.poll_motion(&axes).await?;
            let on = motion.settled;
            if on.iter().all(|&f| f) {
                let pos = match motion.positions {
                    Some(p) => p,
                    None => self.backend.read_position(&axes).await?,
                };
                self.emit(
                    StageEvent::Poll,
                    self.axis_states(targets, Some(&pos), Some(&on)),
                );
                let off = targets
                    .iter()
                    .zip(&pos)
                    .position(|(&(axis, t), &p)| (p - t).abs() > self.config.tolerance(axis));
                let trusted = Instant::now() >= flags_trusted_at;
                let held = on_target_before
                    .as_deref()
                    .is_some_and(|before| self.unchanged(targets, before, &pos));
                if off.is_none() && !trusted && !held {
                    // On target, but the flag may be stale: the next poll must find it still there.
                    on_target_before = Some(pos);
                } else if let Some(off) = off {
                    on_target_before = None;
                    // "Settled" yet not there: a stale flag (the position still changes) or,
                    // once the flag can be trusted, a move that did not happen (it does not).
                    if !self.unchanged(targets, &last_pos, &pos) {
                        last_pos = pos;
                        last_progress = Instant::now();
                    } else if trusted && last_progress.elapsed() >= no_motion {
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
                        self.backend.start_move(targets).await?;
                        self.emit(
                            StageEvent::MoveReissued,
                            self.axis_states(targets, Some(&pos), Some(&on)),
                        );
                        reissued = true;
                        last_progress = Instant::now();
                        flags_trusted_at = last_progress + self.backend.flag_delay();
                        timeout = self.move_timeout(&pos, targets);
                        deadline = last_progress + timeout;
                        last_pos = pos;
                    }
                } else {
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
                }
            } else {
                on_target_before = None;
            }
            if Instant::now() >= deadline {
                let now_at = self.backend.read_position(&axes).await.ok();
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

    /// Whether every axis of `targets` is where it was, within its tolerance.
    fn unchanged(&self, targets: &[(StageAxis, f64)], before: &[f64], now: &[f64]) -> bool {
        targets
            .iter()
            .zip(before.iter().zip(now))
            .all(|(&(axis, _), (&q, &p))| (p - q).abs() <= self.config.tolerance(axis))
    }

    async fn read_position(&mut self, event: StageEvent) -> Result<StagePosition, StageError> {
        let v = self.backend.read_position(&StageAxis::ALL).await?;
        let p = StagePosition {
            x_um: v[0],
            y_um: v[1],
            tilt_deg: v[2],
        };
        let axes = StageAxis::ALL
            .iter()
            .map(|&axis| AxisState {
                axis,
                id: self.backend.axis_name(axis),
                position: Some(p.get(axis)),
                target: None,
                on_target: None,
            })
            .collect();
        self.emit(event, axes);
        Ok(p)
    }

    fn emit(&self, event: StageEvent, axes: Vec<AxisState>) {
        self.observer.state(&StageState {
            wall_ns: wall_ns(),
            event,
            axes,
        });
    }
}
