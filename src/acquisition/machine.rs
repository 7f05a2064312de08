//! The tilt series as a pure state machine: the runner performs each
//! [`Action`] with the instruments and feeds back what happened as an
//! [`Event`]; [`Series::next`] decides what comes next. No I/O, no clock, so
//! every path — faults and cancellation included — is tested without hardware.
//!
//! A run climbs (or descends) the planned tilts one step at a time:
//!
//! ```text
//! MoveTilt(first) → Capture(first micrograph) → Capture(tracking reference)
//!   → [ MoveTilt(k) → Capture(tracking k) → Recentre? ]  for k = 1..=steps
//!   → Capture(last micrograph) → ReturnToSafe → Done(Completed)
//! any failure or cancellation → ReturnToSafe → Done(Failed | Interrupted)
//! ```

use serde::{Deserialize, Serialize};

use super::plan::SeriesPlan;

/// Which frame of the series a capture is (decides its size, dwell and
/// recorded role): the SEM link's own role type.
pub use sdsem_protocol::sem::Role as FrameRole;

/// How the specimen is kept centred.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackingConfig {
    /// Grab a tracking frame after every step and re-centre. Default true.
    pub enabled: bool,
    /// How a stage move shows in the image: content shift (pixels) =
    /// `stage_to_image` · stage move (µm) / pixel size (µm). Row-major 2×2.
    /// Default `[[-1, 0], [0, -1]]`: moving the stage +X moves the specimen
    /// towards −x in the image, as the simulator and most SEMs do.
    pub stage_to_image: [[f64; 2]; 2],
    /// Fraction of the measured offset corrected at each step, (0, 1]. Default 1.
    pub gain: f64,
    /// Offsets smaller than this, in pixels of the tracking frame, are left
    /// alone rather than chased with a stage move. Default 0.25.
    pub deadband_px: f64,
    /// Largest correction accepted in one step, µm; a larger one means the
    /// tracking lost the specimen, and the run stops rather than drive the
    /// stage far away. Default 50.
    pub max_correction_um: f64,
    /// Tracking frames in a row without a reliable shift before the run stops.
    /// Default 2.
    pub max_lost_frames: u32,
}

impl Default for TrackingConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            stage_to_image: [[-1.0, 0.0], [0.0, -1.0]],
            gain: 1.0,
            deadband_px: 0.25,
            max_correction_um: 50.0,
            max_lost_frames: 2,
        }
    }
}

/// How a run ended.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "state", rename_all = "lowercase")]
pub enum Outcome {
    /// Both micrographs captured.
    Completed,
    /// Stopped by a fault; `reason` says which.
    Failed { reason: String },
    /// Stopped by the operator (Ctrl-C, SIGTERM).
    Interrupted { reason: String },
}

impl Outcome {
    #[must_use]
    pub fn is_completed(&self) -> bool {
        matches!(self, Self::Completed)
    }
}

/// What the runner must do next.
#[derive(Debug, Clone, PartialEq)]
pub enum Action {
    /// Move the tilt axis to `tilt_deg` and verify it got there.
    MoveTilt { step: usize, tilt_deg: f64 },
    /// Grab and store a frame of `role` at the current pose.
    Capture {
        step: usize,
        tilt_deg: f64,
        role: FrameRole,
    },
    /// Move the stage X/Y by this much (relative, µm) to cancel the measured walk.
    Recentre {
        step: usize,
        dx_um: f64,
        dy_um: f64,
        offset_px: [f64; 2],
    },
    /// Stop motion first when `stop_first` (a fault or a cancellation), then
    /// move the tilt to the safe position.
    ReturnToSafe { tilt_deg: f64, stop_first: bool },
    /// The run is over.
    Done(Outcome),
}

/// The shift of the latest tracking frame against the previous one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Tracked {
    /// The first tracking frame: nothing to compare with yet.
    Reference,
    /// Content moved by (`dx_px`, `dy_px`) since the previous tracking frame,
    /// whose pixels measure `pixel_size_um`.
    Shift {
        dx_px: f64,
        dy_px: f64,
        pixel_size_um: f64,
    },
    /// No reliable shift could be measured.
    Lost,
}

/// What happened when the runner performed the last action.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// The tilt move was verified.
    TiltReached,
    /// The frame was grabbed (and stored); for tracking frames, its shift.
    Captured { tracked: Option<Tracked> },
    /// The re-centring move was verified.
    Recentred,
    /// The safe tilt was reached (or could not be: `error`).
    SafeReached { error: Option<String> },
    /// The action failed; the run cannot go on.
    Failed { reason: String },
    /// The operator asked to stop.
    Cancelled { reason: String },
}

#[derive(Debug, Clone, PartialEq)]
enum Phase {
    Idle,
    MovingTilt { step: usize },
    CapturingFirst,
    Tracking { step: usize },
    Recentring { step: usize },
    CapturingLast,
    ReturningSafe { outcome: Outcome },
    Done,
}

/// The state of one tilt series.
#[derive(Debug, Clone)]
pub struct Series {
    plan: SeriesPlan,
    tracking: TrackingConfig,
    safe_tilt_deg: f64,
    phase: Phase,
    /// Where the specimen content sat in the latest tracking frame relative to
    /// the first one, tracking-frame pixels: the sum of the measured shifts.
    /// (Each shift compares two frames taken before their corrections, so the
    /// sum is the content's position in the latest frame.)
    seen_px: [f64; 2],
    /// Where the content sits now, after the latest correction.
    offset_px: [f64; 2],
    lost_in_row: u32,
}

impl Series {
    #[must_use]
    pub fn new(plan: SeriesPlan, tracking: TrackingConfig, safe_tilt_deg: f64) -> Self {
        Self {
            plan,
            tracking,
            safe_tilt_deg,
            phase: Phase::Idle,
            seen_px: [0.0, 0.0],
            offset_px: [0.0, 0.0],
            lost_in_row: 0,
        }
    }

    #[must_use]
    pub fn plan(&self) -> &SeriesPlan {
        &self.plan
    }

    /// The specimen's remaining offset from its first position, tracking-frame pixels.
    #[must_use]
    pub fn offset_px(&self) -> [f64; 2] {
        self.offset_px
    }

    /// The first action of the run.
    pub fn start(&mut self) -> Action {
        self.move_to(0)
    }

    /// Role of the micrograph at the first (`first = true`) or last tilt.
    fn micrograph_role(&self, first: bool) -> FrameRole {
        if first == self.plan.ascending() {
            FrameRole::Left
        } else {
            FrameRole::Right
        }
    }

    fn move_to(&mut self, step: usize) -> Action {
        self.phase = Phase::MovingTilt { step };
        Action::MoveTilt {
            step,
            tilt_deg: self.plan.tilts()[step],
        }
    }

    fn capture(&mut self, step: usize, role: FrameRole) -> Action {
        Action::Capture {
            step,
            tilt_deg: self.plan.tilts()[step],
            role,
        }
    }

    fn finish_step(&mut self, step: usize) -> Action {
        if step == self.plan.steps() {
            self.phase = Phase::CapturingLast;
            let role = self.micrograph_role(false);
            self.capture(step, role)
        } else {
            self.move_to(step + 1)
        }
    }

    fn return_to_safe(&mut self, outcome: Outcome) -> Action {
        let stop_first = !outcome.is_completed();
        self.phase = Phase::ReturningSafe { outcome };
        Action::ReturnToSafe {
            tilt_deg: self.safe_tilt_deg,
            stop_first,
        }
    }

    fn fail(&mut self, reason: String) -> Action {
        self.return_to_safe(Outcome::Failed { reason })
    }

    /// Decides the next action from what happened.
    pub fn next(&mut self, event: Event) -> Action {
        let phase = std::mem::replace(&mut self.phase, Phase::Done);
        match (phase, event) {
            (Phase::Done, _) => {
                self.phase = Phase::Done;
                Action::Done(Outcome::Failed {
                    reason: "internal error: event after the run ended".into(),
                })
            }
            (Phase::ReturningSafe { outcome }, event) => {
                self.phase = Phase::Done;
                Action::Done(match event {
                    Event::SafeReached { error: None } => outcome,
                    Event::SafeReached { error: Some(e) } | Event::Failed { reason: e } => {
                        with_note(
                            outcome,
                            &format!("the stage could not return to the safe tilt: {e}"),
                        )
                    }
                    Event::Cancelled { reason } => with_note(
                        outcome,
                        &format!("return to the safe tilt cancelled: {reason}"),
                    ),
                    other => with_note(
                        outcome,
                        &format!("internal error: unexpected {other:?} while returning to safe"),
                    ),
                })
            }
            (_, Event::Failed { reason }) => self.fail(reason),
            (_, Event::Cancelled { reason }) => {
                self.return_to_safe(Outcome::Interrupted { reason })
            }
            (Phase::MovingTilt { step: 0 }, Event::TiltReached) => {
                self.phase = Phase::CapturingFirst;
                let role = self.micrograph_role(true);
                self.capture(0, role)
            }
            (Phase::MovingTilt { step }, Event::TiltReached) => {
                if self.tracking.enabled {
                    self.phase = Phase::Tracking { step };
                    self.capture(step, FrameRole::Tracking)
                } else {
                    self.finish_step(step)
                }
            }
            (Phase::CapturingFirst, Event::Captured { .. }) => {
                if self.tracking.enabled {
                    self.phase = Phase::Tracking { step: 0 };
                    self.capture(0, FrameRole::Tracking)
                } else {
                    self.finish_step(0)
                }
            }
            (Phase::Tracking { step }, Event::Captured { tracked }) => {
                self.on_tracked(step, tracked)
            }
            (Phase::Recentring { step }, Event::Recentred) => self.finish_step(step),
            (Phase::CapturingLast, Event::Captured { .. }) => {
                self.return_to_safe(Outcome::Completed)
            }
            (phase, event) => self.fail(format!(
                "internal error: unexpected {event:?} in phase {phase:?}"
            )),
        }
    }

    fn on_tracked(&mut self, step: usize, tracked: Option<Tracked>) -> Action {
        match tracked {
            Some(Tracked::Reference) if step == 0 => self.finish_step(step),
            Some(Tracked::Lost) => {
                self.lost_in_row += 1;
                if self.lost_in_row > self.tracking.max_lost_frames {
                    self.fail(format!(
                        "specimen lost: {} tracking frames in a row without a reliable shift \
                         (check focus and brightness; tracking.max_lost_frames = {})",
                        self.lost_in_row, self.tracking.max_lost_frames
                    ))
                } else {
                    self.finish_step(step)
                }
            }
            Some(Tracked::Shift {
                dx_px,
                dy_px,
                pixel_size_um,
            }) => {
                self.lost_in_row = 0;
                self.seen_px[0] += dx_px;
                self.seen_px[1] += dy_px;
                self.offset_px = self.seen_px;
                self.recentre(step, pixel_size_um)
            }
            other => self.fail(format!(
                "internal error: tracking frame at step {step} reported {other:?}"
            )),
        }
    }

    fn recentre(&mut self, step: usize, pixel_size_um: f64) -> Action {
        let [ox, oy] = self.offset_px;
        if ox.hypot(oy) < self.tracking.deadband_px {
            return self.finish_step(step);
        }
        let g = self.tracking.gain;
        // Wanted content shift (px) → stage move (µm): solve M·s = p·shift.
        let [[a, b], [c, d]] = self.tracking.stage_to_image;
        let det = a * d - b * c;
        if det.abs() < 1e-9 {
            return self.fail(
                "tracking.stage_to_image is singular: stage moves cannot re-centre the image"
                    .into(),
            );
        }
        let (wx, wy) = (-g * ox * pixel_size_um, -g * oy * pixel_size_um);
        let dx_um = (d * wx - b * wy) / det;
        let dy_um = (-c * wx + a * wy) / det;
        let size = dx_um.hypot(dy_um);
        if size > self.tracking.max_correction_um {
            return self.fail(format!(
                "tracking asks for a {size:.1} µm re-centring move at step {step}, more than \
                 tracking.max_correction_um = {} µm: the specimen was probably lost",
                self.tracking.max_correction_um
            ));
        }
        let offset_px = self.offset_px;
        self.offset_px = [(1.0 - g) * ox, (1.0 - g) * oy];
        self.phase = Phase::Recentring { step };
        Action::Recentre {
            step,
            dx_um,
            dy_um,
            offset_px,
        }
    }
}

fn with_note(outcome: Outcome, note: &str) -> Outcome {
    match outcome {
        Outcome::Completed => Outcome::Failed {
            reason: note.to_owned(),
        },
        Outcome::Failed { reason } => Outcome::Failed {
            reason: format!("{reason}; {note}"),
        },
        Outcome::Interrupted { reason } => Outcome::Interrupted {
            reason: format!("{reason}; {note}"),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::super::plan::SeriesConfig;
    use super::*;

    fn series(start: f64, end: f64, tracking: bool) -> Series {
        let plan = SeriesPlan::new(
            &SeriesConfig {
                start_tilt_deg: start,
                end_tilt_deg: end,
                step_deg: 1.0,
            },
            -5.0,
            70.0,
        )
        .unwrap();
        Series::new(
            plan,
            TrackingConfig {
                enabled: tracking,
                ..TrackingConfig::default()
            },
            0.0,
        )
    }

    /// Drives a run where the specimen walks `walk` px per step and every
    /// action succeeds; returns the actions in order.
    fn drive(s: &mut Series, walk: [f64; 2]) -> Vec<Action> {
        let mut actions = vec![s.start()];
        // The true offset of the specimen in the image, moved by walk and corrections.
        let mut true_offset = [0.0, 0.0];
        let mut last_seen = [0.0, 0.0];
        let pixel = 0.4;
        loop {
            let action = actions.last().cloned().unwrap();
            let event = match action {
                Action::MoveTilt { step, .. } => {
                    if step > 0 {
                        true_offset[0] += walk[0];
                        true_offset[1] += walk[1];
                    }
                    Event::TiltReached
                }
                Action::Capture {
                    role: FrameRole::Tracking,
                    step,
                    ..
                } => {
                    let tracked = if step == 0 {
                        Tracked::Reference
                    } else {
                        Tracked::Shift {
                            dx_px: true_offset[0] - last_seen[0],
                            dy_px: true_offset[1] - last_seen[1],
                            pixel_size_um: pixel,
                        }
                    };
                    last_seen = true_offset;
                    Event::Captured {
                        tracked: Some(tracked),
                    }
                }
                Action::Capture { .. } => Event::Captured { tracked: None },
                Action::Recentre { dx_um, dy_um, .. } => {
                    // Default mapping: content moves by −stage/p.
                    true_offset[0] -= dx_um / pixel;
                    true_offset[1] -= dy_um / pixel;
                    Event::Recentred
                }
                Action::ReturnToSafe { .. } => Event::SafeReached { error: None },
                Action::Done(_) => return actions,
            };
            actions.push(s.next(event));
        }
    }

    fn captures(actions: &[Action]) -> Vec<(usize, FrameRole)> {
        actions
            .iter()
            .filter_map(|a| match a {
                Action::Capture { step, role, .. } => Some((*step, *role)),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn ascending_run_visits_every_tilt_and_tracks_after_each_step() {
        let mut s = series(0.0, 7.0, true);
        let actions = drive(&mut s, [2.0, -1.0]);
        let tilts: Vec<f64> = actions
            .iter()
            .filter_map(|a| match a {
                Action::MoveTilt { tilt_deg, .. } => Some(*tilt_deg),
                _ => None,
            })
            .collect();
        assert_eq!(tilts, vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]);
        let caps = captures(&actions);
        assert_eq!(caps.first(), Some(&(0, FrameRole::Left)));
        assert_eq!(caps.last(), Some(&(7, FrameRole::Right)));
        let tracking = caps.iter().filter(|c| c.1 == FrameRole::Tracking).count();
        assert_eq!(tracking, 8, "a reference frame plus one per step");
        assert_eq!(actions.last(), Some(&Action::Done(Outcome::Completed)));
        assert!(matches!(
            actions[actions.len() - 2],
            Action::ReturnToSafe {
                stop_first: false,
                ..
            }
        ));
    }

    #[test]
    fn recentring_cancels_the_walk_in_stage_units() {
        let mut s = series(0.0, 3.0, true);
        let actions = drive(&mut s, [5.0, 0.0]);
        let moves: Vec<(f64, f64)> = actions
            .iter()
            .filter_map(|a| match a {
                Action::Recentre { dx_um, dy_um, .. } => Some((*dx_um, *dy_um)),
                _ => None,
            })
            .collect();
        // Content walked +5 px = +2 µm towards +x; stage +X moves content −x: move +2 µm.
        assert_eq!(moves.len(), 3);
        for (dx, dy) in moves {
            assert!((dx - 2.0).abs() < 1e-9 && dy.abs() < 1e-9, "{dx} {dy}");
        }
        assert!(s.offset_px()[0].abs() < 1e-9);
    }

    #[test]
    fn descending_run_swaps_roles() {
        let mut s = series(5.0, 2.0, true);
        let caps = captures(&drive(&mut s, [0.0, 0.0]));
        assert_eq!(caps.first(), Some(&(0, FrameRole::Right)));
        assert_eq!(caps.last(), Some(&(3, FrameRole::Left)));
    }

    #[test]
    fn without_tracking_no_tracking_frames_or_moves() {
        let mut s = series(0.0, 7.0, false);
        let actions = drive(&mut s, [5.0, 0.0]);
        assert_eq!(captures(&actions).len(), 2);
        assert!(!actions.iter().any(|a| matches!(a, Action::Recentre { .. })));
    }

    #[test]
    fn failure_stops_then_returns_to_safe_and_reports_reason() {
        let mut s = series(0.0, 7.0, true);
        let _ = s.start();
        let a = s.next(Event::Failed {
            reason: "stage did not answer POS?".into(),
        });
        assert_eq!(
            a,
            Action::ReturnToSafe {
                tilt_deg: 0.0,
                stop_first: true
            }
        );
        let done = s.next(Event::SafeReached { error: None });
        assert_eq!(
            done,
            Action::Done(Outcome::Failed {
                reason: "stage did not answer POS?".into()
            })
        );
    }

    #[test]
    fn cancellation_is_an_interruption_and_safe_failure_is_noted() {
        let mut s = series(0.0, 7.0, true);
        let _ = s.start();
        let _ = s.next(Event::TiltReached);
        let _ = s.next(Event::Cancelled {
            reason: "SIGTERM".into(),
        });
        let done = s.next(Event::SafeReached {
            error: Some("connection lost".into()),
        });
        match done {
            Action::Done(Outcome::Interrupted { reason }) => {
                assert!(reason.contains("SIGTERM") && reason.contains("connection lost"));
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn lost_specimen_fails_after_the_allowed_frames() {
        let mut s = series(0.0, 7.0, true);
        let mut a = s.start();
        let mut lost_reported = 0;
        loop {
            let event = match a {
                Action::MoveTilt { .. } => Event::TiltReached,
                Action::Capture {
                    role: FrameRole::Tracking,
                    step,
                    ..
                } => Event::Captured {
                    tracked: Some(if step == 0 {
                        Tracked::Reference
                    } else {
                        lost_reported += 1;
                        Tracked::Lost
                    }),
                },
                Action::Capture { .. } => Event::Captured { tracked: None },
                Action::ReturnToSafe { stop_first, .. } => {
                    assert!(stop_first);
                    Event::SafeReached { error: None }
                }
                Action::Done(outcome) => {
                    assert_eq!(lost_reported, 3);
                    assert!(
                        matches!(outcome, Outcome::Failed { ref reason } if reason.contains("specimen lost"))
                    );
                    break;
                }
                Action::Recentre { .. } => panic!("no shift was measured"),
            };
            a = s.next(event);
        }
    }

    #[test]
    fn a_huge_correction_stops_the_run() {
        let mut s = series(0.0, 2.0, true);
        let actions = drive(&mut s, [500.0, 0.0]);
        match actions.last() {
            Some(Action::Done(Outcome::Failed { reason })) => {
                assert!(reason.contains("max_correction_um"), "{reason}");
            }
            other => panic!("{other:?}"),
        }
    }
}
