//! The PI GCS 2.0 backend (`stage.protocol = "pi-gcs"`), over any byte stream.
//!
//! Rules of the protocol it follows (DESIGN §7):
//! - Queries have a timeout each; a timed-out or garbled query is retried a
//!   bounded number of times after resynchronising. A query that times out is
//!   followed by `ERR?`: a controller that rejects a query does not answer it,
//!   it sets an error.
//! - Commands that do not answer (`MOV`, `SVO`, `FRF`, `STP`) are followed by
//!   `ERR?`. Commands that move are never re-sent blindly.
//!
//! Known limit: reading `ERR?` clears the code, so when the answer to an `ERR?`
//! is lost its retry answers 0. For a move this costs nothing but time: the
//! verification sees the stage not moving and re-issues the move once.

use std::sync::Arc;
use std::time::Duration;

use sdsem_protocol::gcs::{
    AxisId, Command, ErrorQuery, GcsErrorCode, IdentityQuery, MaxLimitQuery, MinLimitQuery,
    MotionStatus, MotionStatusQuery, OnTargetQuery, PositionQuery, Query, ReadyQuery,
    ReferencedQuery, ReplyFramer, ServoQuery,
};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::time::Instant;
use tracing::{info, warn};

use super::backend::{BoxFuture, Connected, MotionPoll, StageBackend, StageIdentity};
use super::config::{StageAxis, StageConfig, StageProtocol, secs};
use super::error::{LinkRemedies, StageError, remedy};
use super::observer::{AxisState, IoOutcome, StageEvent, StageObserver, StageState, wall_ns};
use super::wire::{Received, Wire, WireTiming};

/// A PI GCS 2.0 controller behind a byte stream.
pub struct GcsBackend<T> {
    wire: Wire<T, ReplyFramer>,
    config: StageConfig,
    observer: Arc<dyn StageObserver>,
}

impl<T: AsyncRead + AsyncWrite + Unpin + Send> GcsBackend<T> {
    /// A backend over `io` (nothing is sent before [`StageBackend::connect`]).
    pub fn new(io: T, config: StageConfig, observer: Arc<dyn StageObserver>) -> Self {
        let timing = WireTiming {
            reply_timeout: secs(config.reply_timeout_s),
            resync_quiet: secs(config.resync_quiet_s),
        };
        Self {
            wire: Wire::new(
                io,
                ReplyFramer::new(),
                Arc::clone(&observer),
                timing,
                LinkRemedies::new(&config),
            ),
            config,
            observer,
        }
    }

    /// Gives the byte stream back.
    pub fn into_inner(self) -> T {
        self.wire.into_inner()
    }

    /// Sends any typed query (retried after timeouts and garbled replies).
    pub async fn query<Q: Query>(&mut self, query: &Q) -> Result<Q::Output, StageError> {
        self.query_inner(query, true).await
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

    fn ids(&self, axes: &[StageAxis]) -> Vec<AxisId> {
        axes.iter()
            .map(|&a| self.config.axis_id(a).clone())
            .collect()
    }

    /// `*IDN?`, the servo and reference states, the soft limits.
    async fn connect_inner(&mut self) -> Result<Connected, StageError> {
        // Whatever a previous session left in the controller's output is not ours.
        self.wire.resync(Duration::ZERO, "connect").await?;
        let idn = self.query(&IdentityQuery).await?;
        if !self.config.expect_idn.is_empty() && !idn.contains(&self.config.expect_idn) {
            return Err(StageError::UnexpectedIdentity {
                idn,
                expected: self.config.expect_idn.clone(),
            });
        }
        info!(idn = %idn, "stage controller identified");
        let pending = self.query(&ErrorQuery).await?;
        if pending.is_error() {
            info!(code = %pending, "cleared an error left pending in the stage controller");
        }
        let ids = self.ids(&StageAxis::ALL);
        let servo = self.query(&ServoQuery(ids.clone())).await?;
        let referenced = self.query(&ReferencedQuery(ids)).await?;
        let off = |flags: &[(AxisId, bool)]| -> Vec<AxisId> {
            flags
                .iter()
                .filter(|(_, on)| !on)
                .map(|(a, _)| a.clone())
                .collect()
        };
        let (servo_off, unreferenced) = (off(&servo), off(&referenced));
        if !servo_off.is_empty() || !unreferenced.is_empty() {
            if !self.config.auto_reference {
                let names = |v: &[AxisId]| v.iter().map(ToString::to_string).collect();
                return Err(StageError::NotReady {
                    unreferenced: names(&unreferenced),
                    servo_off: names(&servo_off),
                });
            }
            self.make_ready(servo_off, unreferenced).await?;
        }
        let limits = if self.config.read_controller_limits {
            self.read_controller_limits().await?
        } else {
            [None; 3]
        };
        Ok(Connected {
            identity: identity(&idn),
            limits,
        })
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
                if let Err(e) = self.stop_and_report().await {
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

    /// `STP`, then where the axes stopped, recorded (before the safety layer exists).
    async fn stop_and_report(&mut self) -> Result<(), StageError> {
        self.stop_inner().await?;
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
        self.observer.state(&StageState {
            wall_ns: wall_ns(),
            event: StageEvent::Stopped,
            axes,
        });
        Ok(())
    }

    /// The controller's soft limits (`TMN?`/`TMX?`), when it reports them.
    async fn read_controller_limits(&mut self) -> Result<[Option<(f64, f64)>; 3], StageError> {
        let ids = self.ids(&StageAxis::ALL);
        let lows = match self.query(&MinLimitQuery(ids.clone())).await {
            Ok(v) => v,
            Err(StageError::Controller { code, .. }) if code == GcsErrorCode::UNKNOWN_COMMAND => {
                info!(
                    "the stage controller does not report soft limits; using the configured ones"
                );
                return Ok([None; 3]);
            }
            Err(e) => return Err(e),
        };
        let highs = self.query(&MaxLimitQuery(ids)).await?;
        Ok([0, 1, 2].map(|i| Some((lows[i].1, highs[i].1))))
    }

    /// `STP` and its `ERR?`, at once (no resynchronisation wait first).
    async fn stop_inner(&mut self) -> Result<(), StageError> {
        let command = Command::Stp;
        let text = command.to_string();
        let sent = self
            .wire
            .send(&command.to_bytes(), &text, false, command.expects_reply())
            .await?;
        self.wire.record_sent(&sent, &text);
        let code = self.query_inner(&ErrorQuery, false).await?;
        if code != GcsErrorCode::STOPPED && code.is_error() {
            warn!(code = %code, "unexpected controller error after STP");
        }
        info!("stage stopped (STP)");
        Ok(())
    }

    async fn positions(&mut self, axes: &[StageAxis]) -> Result<Vec<f64>, StageError> {
        Ok(self
            .query(&PositionQuery(self.ids(axes)))
            .await?
            .into_iter()
            .map(|(_, p)| p)
            .collect())
    }

    async fn start_move_inner(
        &mut self,
        targets: &[(StageAxis, f64)],
    ) -> Result<String, StageError> {
        let mov = Command::Mov(
            targets
                .iter()
                .map(|&(axis, t)| (self.config.axis_id(axis).clone(), t))
                .collect(),
        );
        self.command(&mov).await?;
        Ok(mov.to_string())
    }

    async fn on_target(&mut self, axes: &[StageAxis]) -> Result<MotionPoll, StageError> {
        let settled = self
            .query(&OnTargetQuery(self.ids(axes)))
            .await?
            .into_iter()
            .map(|(_, f)| f)
            .collect();
        Ok(MotionPoll {
            settled,
            positions: None,
        })
    }

    /// Sends a command that does not answer, then asks `ERR?`.
    async fn command(&mut self, command: &Command) -> Result<(), StageError> {
        let text = command.to_string();
        let sent = self
            .wire
            .send(&command.to_bytes(), &text, true, command.expects_reply())
            .await?;
        self.wire.record_sent(&sent, &text);
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
        let bytes = command.to_bytes();
        let timeout = self.wire.timing().reply_timeout;
        let attempts = self.config.query_retries.saturating_add(1);
        let mut failure = self.wire.no_reply(&text, attempts, timeout);
        for attempt in 1..=attempts {
            let sent = self
                .wire
                .send(&bytes, &text, true, command.expects_reply())
                .await?;
            match self.wire.receive(sent.deadline, &text).await? {
                Received::Reply(reply) => match query.parse_reply(&reply) {
                    Ok(value) => {
                        self.wire.answered();
                        self.wire.record(
                            &sent,
                            &text,
                            attempt,
                            Some(reply.to_text()),
                            IoOutcome::Replied,
                            None,
                        );
                        if attempt > 1 {
                            warn!(command = %text, attempt, "stage query recovered by a retry");
                        }
                        return Ok(value);
                    }
                    Err(e) => {
                        failure = self
                            .wire
                            .garbled(&sent, &text, attempt, reply.to_text(), e.to_string())
                            .await?;
                    }
                },
                Received::Frame(e) => {
                    failure = self
                        .wire
                        .unframeable(&sent, &text, attempt, e.to_string())
                        .await?;
                }
                Received::Timeout => {
                    let detail = format!("no reply within {timeout:?}");
                    failure = self
                        .wire
                        .timed_out(&sent, &text, attempt, timeout, detail)
                        .await?;
                    // A controller does not answer a query it rejects: ask why.
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
}

/// `*IDN?` answers "vendor, model, serial, firmware" on PI controllers; other
/// answers are kept whole in `raw` only.
fn identity(idn: &str) -> StageIdentity {
    let parts: Vec<&str> = idn.split(',').map(str::trim).collect();
    let mut id = StageIdentity {
        protocol: StageProtocol::PiGcs.as_str().to_owned(),
        raw: idn.to_owned(),
        ..StageIdentity::default()
    };
    if let [vendor, model, serial, version, ..] = parts.as_slice() {
        id.vendor = (*vendor).to_owned();
        id.model = (*model).to_owned();
        id.serial = (*serial).to_owned();
        id.version = (*version).to_owned();
    }
    id
}

impl<T: AsyncRead + AsyncWrite + Unpin + Send> StageBackend for GcsBackend<T> {
    fn protocol(&self) -> StageProtocol {
        StageProtocol::PiGcs
    }

    fn connect(&mut self) -> BoxFuture<'_, Result<Connected, StageError>> {
        Box::pin(self.connect_inner())
    }

    fn axis_name(&self, axis: StageAxis) -> String {
        self.config.axis_id(axis).to_string()
    }

    fn read_position<'a>(
        &'a mut self,
        axes: &'a [StageAxis],
    ) -> BoxFuture<'a, Result<Vec<f64>, StageError>> {
        Box::pin(self.positions(axes))
    }

    fn start_move<'a>(
        &'a mut self,
        targets: &'a [(StageAxis, f64)],
    ) -> BoxFuture<'a, Result<String, StageError>> {
        Box::pin(self.start_move_inner(targets))
    }

    fn flag_delay(&self) -> Duration {
        Duration::ZERO
    }

    fn poll_motion<'a>(
        &'a mut self,
        axes: &'a [StageAxis],
    ) -> BoxFuture<'a, Result<MotionPoll, StageError>> {
        Box::pin(self.on_target(axes))
    }

    fn stop(&mut self) -> BoxFuture<'_, Result<(), StageError>> {
        Box::pin(self.stop_inner())
    }

    fn send_raw<'a>(
        &'a mut self,
        line: &'a str,
        _timeout: Duration,
    ) -> BoxFuture<'a, Result<String, StageError>> {
        Box::pin(async move {
            Err(StageError::Unsupported {
                protocol: StageProtocol::PiGcs,
                what: format!("the SEM command {line:?}"),
                remedy: "a PI GCS controller drives only the stage, not the SEM: set \
                         imaging.trigger = \"\" and store micrographs from the SEM's own \
                         software, or use stage.protocol = \"remcon32\" on a Zeiss SEM",
            })
        })
    }

    fn probe_facts(&mut self) -> BoxFuture<'_, Result<Vec<(String, String)>, StageError>> {
        Box::pin(async move {
            let ids = self.ids(&StageAxis::ALL);
            let on = |flags: Vec<(AxisId, bool)>| {
                flags
                    .iter()
                    .map(|(a, f)| format!("{a}={}", u8::from(*f)))
                    .collect::<Vec<_>>()
                    .join(" ")
            };
            let servo = on(self.query(&ServoQuery(ids.clone())).await?);
            let referenced = on(self.query(&ReferencedQuery(ids.clone())).await?);
            let on_target = on(self.query(&OnTargetQuery(ids)).await?);
            let ready = self.query(&ReadyQuery).await?;
            Ok(vec![
                ("SVO? servo on".to_owned(), servo),
                ("FRF? referenced".to_owned(), referenced),
                ("ONT? on target".to_owned(), on_target),
                (
                    "#7 controller ready".to_owned(),
                    if ready { "yes" } else { "no (referencing?)" }.to_owned(),
                ),
            ])
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn idn_fields_are_split_when_there_are_four() {
        let id = identity("(c)2015 Physik Instrumente (PI), C-884.4DC, 0115500234, 1.2.3.0");
        assert_eq!(id.vendor, "(c)2015 Physik Instrumente (PI)");
        assert_eq!(id.model, "C-884.4DC");
        assert_eq!(id.serial, "0115500234");
        assert_eq!(id.version, "1.2.3.0");
        let id = identity("some stage");
        assert_eq!((id.raw.as_str(), id.model.as_str()), ("some stage", ""));
        assert_eq!(id.protocol, "pi-gcs");
    }
}
