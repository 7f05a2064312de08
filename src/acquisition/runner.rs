//! Performs the [`Series`] state machine's actions with the instruments and
//! feeds back what happened. Every frame goes to the record as soon as it is
//! grabbed (the recorder flushes a chunk per frame, so a run killed at any
//! moment keeps every completed frame).

use std::time::Instant;

use serde::Serialize;
use tracing::{error, info, warn};

use super::cancel::Cancel;
use super::machine::{Action, Event, FrameRole, Outcome, Series, Tracked};
use super::stage_trigger::StageTrigger;
use crate::imaging::{Frame, FrameSource, GrabContext, ImagingConfig, Pixels as FramePixels};
use crate::numbers;
use crate::progress::Stage;
use crate::record::{self, Entry, FrameInfo, Pixels, RecorderHandle, topics};
use crate::stage::{StageBackend, StageDriver, StagePosition};
use crate::vision::Image;
use crate::vision::registration::{PhaseCorrelationParams, phase_correlation};

/// A micrograph (or tracking frame) as grabbed, with its pixels as an image.
#[derive(Debug, Clone)]
pub struct Captured {
    pub frame: Frame,
    pub image: Image,
    /// The stage position verified before the frame was grabbed.
    pub stage: StagePosition,
}

/// What one tracking frame measured and what was done about it.
#[derive(Debug, Clone, Serialize)]
pub struct TrackingStep {
    pub step: usize,
    pub tilt_deg: f64,
    /// Shift against the previous reliable tracking frame, tracking pixels; none when lost.
    pub shift_px: Option<[f64; 2]>,
    /// Correlation peak ratio of the measurement (reliability).
    pub peak_ratio: Option<f64>,
    /// Re-centring move made, µm.
    pub correction_um: Option<[f64; 2]>,
}

/// Time spent in each kind of action: the figure the "wall time within 10 %
/// of motion + settle + frames" check compares against.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SeriesTimings {
    pub tilt_moves_s: f64,
    pub recentre_moves_s: f64,
    pub micrographs_s: f64,
    pub tracking_frames_s: f64,
    pub tracking_compute_s: f64,
    pub return_to_safe_s: f64,
    pub total_s: f64,
}

/// Everything a series produced.
#[derive(Debug, Clone)]
pub struct SeriesRecord {
    pub outcome: Outcome,
    pub left: Option<Captured>,
    pub right: Option<Captured>,
    /// Frames grabbed and recorded, tracking frames included.
    pub frames: u64,
    /// Tilts verified on the way, in order.
    pub tilts_reached: Vec<f64>,
    pub tracking: Vec<TrackingStep>,
    pub timings: SeriesTimings,
}

/// The instruments and the record a series works with.
pub struct SeriesContext<'a, T: StageBackend> {
    pub stage: &'a mut StageDriver<T>,
    pub imaging: &'a mut dyn FrameSource,
    pub imaging_config: &'a ImagingConfig,
    pub recorder: &'a RecorderHandle,
    pub phase: PhaseCorrelationParams,
    /// Told each stage of the series (tilt steps, frames) as it begins.
    pub progress: &'a (dyn Fn(Stage) + Send + Sync),
}

/// Runs `series` to its end: completed, failed (with the stage stopped and
/// returned to its safe tilt) or interrupted by `cancel`.
pub async fn run_series<T>(
    series: &mut Series,
    ctx: &mut SeriesContext<'_, T>,
    cancel: &mut Cancel,
) -> SeriesRecord
where
    T: StageBackend,
{
    let started = Instant::now();
    let mut run = RunState {
        record: SeriesRecord {
            outcome: Outcome::Completed,
            left: None,
            right: None,
            frames: 0,
            tilts_reached: Vec::new(),
            tracking: Vec::new(),
            timings: SeriesTimings::default(),
        },
        reference: None,
        position: None,
        pending_drift: None,
    };
    let steps = series.plan().steps();
    let mut action = series.start();
    loop {
        let event = match action {
            Action::Done(outcome) => {
                run.record.outcome = outcome;
                break;
            }
            Action::MoveTilt { step, tilt_deg } => {
                (ctx.progress)(Stage::Tilt {
                    step,
                    steps,
                    tilt_deg,
                });
                let t0 = Instant::now();
                let result = cancellable(cancel, ctx.stage.move_tilt(tilt_deg)).await;
                run.record.timings.tilt_moves_s += t0.elapsed().as_secs_f64();
                match result {
                    Err(reason) => Event::Cancelled { reason },
                    Ok(Err(e)) => Event::Failed {
                        reason: format!("tilt move to {tilt_deg}° failed: {e}"),
                    },
                    Ok(Ok(report)) => {
                        run.update_position(&report.positions);
                        let reached = run.position.map_or(tilt_deg, |p| p.tilt_deg);
                        run.record.tilts_reached.push(reached);
                        info!(
                            step,
                            steps,
                            tilt_deg = numbers::deg(reached),
                            move_s = numbers::secs(report.elapsed.as_secs_f64()),
                            "step {step}/{steps}: tilt {reached:.3}° reached{}",
                            if report.reissued {
                                " (move re-issued)"
                            } else {
                                ""
                            }
                        );
                        Event::TiltReached
                    }
                }
            }
            Action::Capture {
                step,
                tilt_deg,
                role,
            } => run.capture(ctx, cancel, step, tilt_deg, role).await,
            Action::Recentre {
                step,
                dx_um,
                dy_um,
                offset_px,
            } => {
                let t0 = Instant::now();
                let event = run.recentre(ctx, cancel, dx_um, dy_um).await;
                run.record.timings.recentre_moves_s += t0.elapsed().as_secs_f64();
                if let Some(last) = run.record.tracking.last_mut() {
                    last.correction_um = Some([dx_um, dy_um]);
                }
                if matches!(event, Event::Recentred) {
                    info!(
                        step,
                        dx_um = numbers::um(dx_um),
                        dy_um = numbers::um(dy_um),
                        "step {step}/{steps}: specimen {:.1} px off, re-centred by ({dx_um:+.3}, {dy_um:+.3}) µm",
                        offset_px[0].hypot(offset_px[1])
                    );
                }
                event
            }
            Action::ReturnToSafe {
                tilt_deg,
                stop_first,
            } => {
                let t0 = Instant::now();
                let event = return_to_safe(ctx.stage, tilt_deg, stop_first).await;
                run.record.timings.return_to_safe_s += t0.elapsed().as_secs_f64();
                event
            }
        };
        action = series.next(event);
    }
    run.record.timings.total_s = started.elapsed().as_secs_f64();
    match &run.record.outcome {
        Outcome::Completed => info!("series completed: {} frames", run.record.frames),
        Outcome::Failed { reason } => error!("series failed: {reason}"),
        Outcome::Interrupted { reason } => warn!("series interrupted: {reason}"),
    }
    run.record
}

/// Runs `fut` unless the run is cancelled first; `Err(reason)` when cancelled.
async fn cancellable<F: std::future::Future>(
    cancel: &mut Cancel,
    fut: F,
) -> Result<F::Output, String> {
    if let Some(reason) = cancel.reason() {
        return Err(reason);
    }
    tokio::select! {
        biased;
        reason = cancel.cancelled() => Err(reason),
        out = fut => Ok(out),
    }
}

/// Stops motion when asked (a fault or a cancellation), then drives the tilt
/// to the safe position. Never cancelled itself: leaving the stage tilted is
/// what this step exists to prevent; the driver's timeouts bound it.
async fn return_to_safe<T>(stage: &mut StageDriver<T>, tilt_deg: f64, stop_first: bool) -> Event
where
    T: StageBackend,
{
    if stop_first && let Err(e) = stage.stop().await {
        warn!("STP before returning to the safe tilt failed: {e}");
    }
    match stage.move_tilt(tilt_deg).await {
        Ok(_) => {
            info!("stage back at the safe tilt {}°", numbers::deg(tilt_deg));
            Event::SafeReached { error: None }
        }
        Err(e) => {
            error!("stage could not return to the safe tilt {tilt_deg}°: {e}");
            Event::SafeReached {
                error: Some(e.to_string()),
            }
        }
    }
}

struct RunState {
    record: SeriesRecord,
    /// Last reliable tracking frame: the next shift is measured against it.
    reference: Option<Image>,
    /// Last verified stage position.
    position: Option<StagePosition>,
    /// Drift measured on the frame being recorded.
    pending_drift: Option<[f64; 2]>,
}

impl RunState {
    fn update_position(&mut self, positions: &[(crate::stage::StageAxis, f64)]) {
        let mut p = self.position.unwrap_or_default();
        for &(axis, value) in positions {
            match axis {
                crate::stage::StageAxis::X => p.x_um = value,
                crate::stage::StageAxis::Y => p.y_um = value,
                crate::stage::StageAxis::Tilt => p.tilt_deg = value,
            }
        }
        self.position = Some(p);
    }

    async fn capture<T>(
        &mut self,
        ctx: &mut SeriesContext<'_, T>,
        cancel: &mut Cancel,
        step: usize,
        tilt_deg: f64,
        role: FrameRole,
    ) -> Event
    where
        T: StageBackend,
    {
        (ctx.progress)(Stage::Capture {
            step,
            role: role.as_str(),
            tilt_deg,
        });
        let request = ctx.imaging_config.request(role);
        let t0 = Instant::now();
        // The verified position lets a file-based source check the tilt its file records;
        // the stage link carries its trigger (`imaging.trigger`).
        let mut trigger = StageTrigger(&mut *ctx.stage);
        let context = GrabContext {
            stage: self.position,
            trigger: Some(&mut trigger),
        };
        let grabbed = cancellable(cancel, ctx.imaging.grab_with(request, context)).await;
        let grab_s = t0.elapsed().as_secs_f64();
        let frame = match grabbed {
            Err(reason) => return Event::Cancelled { reason },
            Ok(Err(e)) => {
                return Event::Failed {
                    reason: format!("{role} frame at {tilt_deg}° failed: {e}"),
                };
            }
            Ok(Ok(frame)) => frame,
        };
        if role == FrameRole::Tracking {
            self.record.timings.tracking_frames_s += grab_s;
        } else {
            self.record.timings.micrographs_s += grab_s;
        }
        let image = frame.to_image();

        let tracked = if role == FrameRole::Tracking {
            let t1 = Instant::now();
            let tracked = self.track(step, tilt_deg, &image, frame.meta.pixel_size_um, &ctx.phase);
            self.record.timings.tracking_compute_s += t1.elapsed().as_secs_f64();
            Some(tracked)
        } else {
            None
        };

        if let Err(e) = self.record_frame(ctx.recorder, &frame).await {
            return Event::Failed {
                reason: format!("cannot record the {role} frame: {e}"),
            };
        }
        self.record.frames += 1;
        match role {
            FrameRole::Left => {
                let tilt_deg = numbers::deg(tilt_deg);
                info!(tilt_deg, "left micrograph captured at {tilt_deg}°");
                self.record.left = Some(Captured {
                    frame,
                    image,
                    stage: self.position.unwrap_or_default(),
                });
            }
            FrameRole::Right => {
                let tilt_deg = numbers::deg(tilt_deg);
                info!(tilt_deg, "right micrograph captured at {tilt_deg}°");
                self.record.right = Some(Captured {
                    frame,
                    image,
                    stage: self.position.unwrap_or_default(),
                });
            }
            FrameRole::Tracking => {}
        }
        Event::Captured { tracked }
    }

    /// Measures the shift of a tracking frame against the last reliable one.
    fn track(
        &mut self,
        step: usize,
        tilt_deg: f64,
        image: &Image,
        pixel_size_um: f64,
        params: &PhaseCorrelationParams,
    ) -> Tracked {
        self.pending_drift = None;
        let Some(reference) = &self.reference else {
            self.reference = Some(image.clone());
            return Tracked::Reference;
        };
        match phase_correlation(reference, image, params) {
            Ok(shift) => {
                self.record.tracking.push(TrackingStep {
                    step,
                    tilt_deg,
                    shift_px: Some([shift.dx, shift.dy]),
                    peak_ratio: Some(shift.peak_ratio),
                    correction_um: None,
                });
                self.pending_drift = Some([shift.dx, shift.dy]);
                self.reference = Some(image.clone());
                Tracked::Shift {
                    dx_px: shift.dx,
                    dy_px: shift.dy,
                    pixel_size_um,
                }
            }
            Err(e) => {
                warn!(step, "tracking frame at {tilt_deg}°: {e}");
                self.record.tracking.push(TrackingStep {
                    step,
                    tilt_deg,
                    shift_px: None,
                    peak_ratio: None,
                    correction_um: None,
                });
                Tracked::Lost
            }
        }
    }

    async fn recentre<T>(
        &mut self,
        ctx: &mut SeriesContext<'_, T>,
        cancel: &mut Cancel,
        dx_um: f64,
        dy_um: f64,
    ) -> Event
    where
        T: StageBackend,
    {
        let here = match self.position {
            Some(p) => p,
            None => match cancellable(cancel, ctx.stage.position()).await {
                Err(reason) => return Event::Cancelled { reason },
                Ok(Err(e)) => {
                    return Event::Failed {
                        reason: format!("cannot read the stage position to re-centre: {e}"),
                    };
                }
                Ok(Ok(p)) => p,
            },
        };
        let (x, y) = (here.x_um + dx_um, here.y_um + dy_um);
        match cancellable(cancel, ctx.stage.move_xy(x, y)).await {
            Err(reason) => Event::Cancelled { reason },
            Ok(Err(e)) => Event::Failed {
                reason: format!("re-centring move to X {x:.3} µm, Y {y:.3} µm failed: {e}"),
            },
            Ok(Ok(report)) => {
                self.update_position(&report.positions);
                Event::Recentred
            }
        }
    }

    async fn record_frame(
        &mut self,
        recorder: &RecorderHandle,
        frame: &Frame,
    ) -> Result<(), record::RecordError> {
        let pixels = match &frame.pixels {
            FramePixels::U8(v) => Pixels::Mono8(v.clone()),
            FramePixels::U16(v) => Pixels::Mono16(v.clone()),
        };
        let (w, h) = (
            u32::try_from(frame.width).unwrap_or(u32::MAX),
            u32::try_from(frame.height).unwrap_or(u32::MAX),
        );
        let t = frame.received_unix_ns;
        let position = self.position.unwrap_or_default();
        let info = FrameInfo {
            role: frame.meta.role,
            index: self.record.frames,
            tilt_deg: position.tilt_deg,
            stage_x_um: position.x_um,
            stage_y_um: position.y_um,
            pixel_size_um: frame.meta.pixel_size_um,
            dwell_us: frame.meta.dwell_us,
            width: w,
            height: h,
            tilt_axis_deg: Some(frame.meta.tilt_axis_deg),
            drift_px: self.pending_drift.take(),
            file: frame.origin.clone(),
        };
        let image = Entry::image(
            topics::SEM_FRAME,
            t,
            frame.meta.role.as_str(),
            &pixels,
            w,
            h,
        )?;
        // One chunk for the frame and its info, cut after the info.
        let info = Entry::json(topics::SEM_FRAME_INFO, t, &info)?.cutting_chunk(true);
        recorder.send_async(image.cutting_chunk(false)).await?;
        recorder.send_async(info).await
    }
}
