//! The TESCAN SharkSEM backend (`stage.protocol = "sharksem"`): the SEM's own
//! stage over SharkSEM [TS-PDF; TS-CS; OD-T; SB-T], through a [`SharkLink`]
//! that the imaging source may share (one session, one control and one data
//! connection).
//!
//! - Connect: `StgIsCalibrated` must be 1 (an uncalibrated stage ignores every
//!   move); `StgGetLimits` 0 (device) and 1 (soft), since 2.0.22, intersected:
//!   the safety layer narrows the configured limits to them, never widens.
//! - Positions: `StgGetPosition` → x, y, z (mm), rotation, tilt (°) (and tilt-Y
//!   on 3.x stages that have it); x and y become µm.
//! - Moves: `StgMoveTo(x, y, z, rotation, tilt[, tilt-Y])` with every axis
//!   given: the ones not moved re-sent as just read, rotation *before* tilt
//!   (the reverse of Zeiss). Sent with wait B, so a stage still settling holds
//!   the move instead of ignoring it. The move answers nothing: the safety layer
//!   verifies it by reading back and re-issues it once.
//! - Motion: `StgIsBusy`. Stop: `StgStop` (never with wait B).

use std::time::Duration;

use sdsem_protocol::sharksem::{Flags, Request, Response, StageLimits, StagePosition, Version};
use tracing::{info, warn};

use super::backend::{BoxFuture, Connected, MotionPoll, StageBackend, StageIdentity};
use super::config::{StageAxis, StageConfig, StageProtocol, secs};
use super::error::StageError;
use crate::sharksem::{SessionConfig, SharkError, SharkLink, SharkSession};

/// The SEM's stage over SharkSEM.
#[derive(Debug)]
pub struct SharkSemBackend {
    link: SharkLink,
}

impl SharkSemBackend {
    /// The session settings of a stage-only SharkSEM link: `stage.endpoint` and its timeouts.
    #[must_use]
    pub fn session_config(config: &StageConfig) -> SessionConfig {
        SessionConfig {
            endpoint: config.endpoint.clone(),
            data_port: None,
            connect_timeout: secs(config.connect_timeout_s),
            reply_timeout: secs(config.reply_timeout_s),
            timeout_key: "stage.reply_timeout_s",
        }
    }

    /// A backend on `link` (nothing is sent before [`StageBackend::connect`]).
    #[must_use]
    pub fn new(link: SharkLink) -> Self {
        Self { link }
    }

    /// The session, to share it.
    #[must_use]
    pub fn link(&self) -> &SharkLink {
        &self.link
    }

    async fn connect_inner(&mut self) -> Result<Connected, StageError> {
        let mut s = self.link.lock().await;
        let wait = s.config().reply_timeout;
        if int(&mut s, &Request::StgIsCalibrated, wait).await? != 1 {
            return Err(SharkError::NotCalibrated.into());
        }
        let limits = if s.version() >= Version::STAGE_LIMITS {
            let device = limits(&mut s, 0, wait).await?;
            let soft = limits(&mut s, 1, wait).await?;
            let both = |(a, b): (f64, f64), (c, d): (f64, f64), scale: f64| {
                Some((a.max(c) * scale, b.min(d) * scale))
            };
            [
                both(device.x_mm, soft.x_mm, 1e3),
                both(device.y_mm, soft.y_mm, 1e3),
                both(device.tilt_deg, soft.tilt_deg, 1.0),
            ]
        } else {
            warn!(
                version = %s.version(),
                "SharkSEM before 2.0.22 reports no stage limits: only the configured ones apply"
            );
            [None; 3]
        };
        let info = s.info();
        let identity = StageIdentity {
            protocol: StageProtocol::Sharksem.as_str().to_owned(),
            vendor: "TESCAN".into(),
            model: info.model.clone().unwrap_or_default(),
            version: info
                .sw_version
                .clone()
                .unwrap_or_else(|| info.protocol.clone()),
            serial: info.device.clone().unwrap_or_default(),
            raw: info.to_string(),
        };
        info!(stage = %identity.raw, "SEM stage over SharkSEM connected");
        Ok(Connected { identity, limits })
    }

    async fn read_inner(&mut self, axes: &[StageAxis]) -> Result<Vec<f64>, StageError> {
        let mut s = self.link.lock().await;
        let p = position(&mut s).await?;
        Ok(axes.iter().map(|&a| get(&p, a)).collect())
    }

    async fn start_move_inner(
        &mut self,
        targets: &[(StageAxis, f64)],
    ) -> Result<String, StageError> {
        let mut s = self.link.lock().await;
        let mut p = position(&mut s).await?;
        for &(axis, v) in targets {
            match axis {
                StageAxis::X => p.x_mm = v * 1e-3,
                StageAxis::Y => p.y_mm = v * 1e-3,
                StageAxis::Tilt => p.tilt_deg = v,
            }
        }
        // x, y, z, rotation, tilt (, tilt-Y): rotation before tilt, the rest as read.
        let request = Request::StgMoveTo(p.values());
        let wait = s.config().reply_timeout;
        s.call(&request, Flags::WAIT_B, wait).await?;
        Ok(request.to_string())
    }

    async fn poll_inner(&mut self, axes: &[StageAxis]) -> Result<MotionPoll, StageError> {
        let mut s = self.link.lock().await;
        let wait = s.config().reply_timeout;
        let busy = int(&mut s, &Request::StgIsBusy, wait).await? != 0;
        Ok(MotionPoll {
            settled: vec![!busy; axes.len()],
            positions: None,
        })
    }

    /// `sdsem probe`'s lines: all axes as the SEM reports them, busy and calibrated.
    async fn probe_inner(&mut self) -> Result<Vec<(String, String)>, StageError> {
        let mut s = self.link.lock().await;
        let wait = s.config().reply_timeout;
        let p = position(&mut s).await?;
        let busy = int(&mut s, &Request::StgIsBusy, wait).await?;
        let calibrated = int(&mut s, &Request::StgIsCalibrated, wait).await?;
        let mut all = format!(
            "x {} mm, y {} mm, z {} mm, rotation {}°, tilt {}°",
            p.x_mm, p.y_mm, p.z_mm, p.rotation_deg, p.tilt_deg
        );
        if let Some(t) = p.tilt_y_deg {
            all.push_str(&format!(", tilt-Y {t}°"));
        }
        Ok(vec![
            ("StgGetPosition (all axes)".to_owned(), all),
            (
                "StgIsBusy".to_owned(),
                format!("{busy} ({})", if busy == 0 { "idle" } else { "moving" }),
            ),
            (
                "StgIsCalibrated".to_owned(),
                format!(
                    "{calibrated} ({})",
                    if calibrated == 1 {
                        "yes"
                    } else {
                        "NO: moves are ignored"
                    }
                ),
            ),
        ])
    }

    async fn stop_inner(&mut self) -> Result<(), StageError> {
        let mut s = self.link.lock().await;
        let wait = s.config().reply_timeout;
        s.call(&Request::StgStop, Flags::NONE, wait).await?;
        Ok(())
    }
}

fn get(p: &StagePosition, axis: StageAxis) -> f64 {
    match axis {
        StageAxis::X => p.x_mm * 1e3,
        StageAxis::Y => p.y_mm * 1e3,
        StageAxis::Tilt => p.tilt_deg,
    }
}

async fn int(s: &mut SharkSession, request: &Request, wait: Duration) -> Result<i32, SharkError> {
    match s.call(request, Flags::NONE, wait).await? {
        Response::Int(v) => Ok(v),
        other => Err(s.unexpected(request, &other)),
    }
}

async fn position(s: &mut SharkSession) -> Result<StagePosition, SharkError> {
    let wait = s.config().reply_timeout;
    match s.call(&Request::StgGetPosition, Flags::NONE, wait).await? {
        Response::Position(p) if p.values().iter().all(|v| v.is_finite()) => Ok(p),
        other => Err(s.unexpected(&Request::StgGetPosition, &other)),
    }
}

async fn limits(
    s: &mut SharkSession,
    kind: i32,
    wait: Duration,
) -> Result<StageLimits, SharkError> {
    let request = Request::StgGetLimits { kind };
    match s.call(&request, Flags::NONE, wait).await? {
        Response::Limits(l) => Ok(l),
        other => Err(s.unexpected(&request, &other)),
    }
}

impl StageBackend for SharkSemBackend {
    fn protocol(&self) -> StageProtocol {
        StageProtocol::Sharksem
    }

    fn connect(&mut self) -> BoxFuture<'_, Result<Connected, StageError>> {
        Box::pin(self.connect_inner())
    }

    fn axis_name(&self, axis: StageAxis) -> String {
        match axis {
            StageAxis::X => "x",
            StageAxis::Y => "y",
            StageAxis::Tilt => "tilt",
        }
        .to_owned()
    }

    fn read_position<'a>(
        &'a mut self,
        axes: &'a [StageAxis],
    ) -> BoxFuture<'a, Result<Vec<f64>, StageError>> {
        Box::pin(self.read_inner(axes))
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
        Box::pin(self.poll_inner(axes))
    }

    fn stop(&mut self) -> BoxFuture<'_, Result<(), StageError>> {
        Box::pin(self.stop_inner())
    }

    fn probe_facts(&mut self) -> BoxFuture<'_, Result<Vec<(String, String)>, StageError>> {
        Box::pin(self.probe_inner())
    }

    fn send_raw<'a>(
        &'a mut self,
        line: &'a str,
        _timeout: Duration,
    ) -> BoxFuture<'a, Result<String, StageError>> {
        Box::pin(async move {
            Err(StageError::Unsupported {
                protocol: StageProtocol::Sharksem,
                what: format!("the command line {line:?}"),
                remedy: "SharkSEM carries typed functions only: leave imaging.trigger empty, or \
                         use imaging.protocol = \"sharksem\" to scan over SharkSEM itself",
            })
        })
    }
}

#[cfg(test)]
mod tests;
