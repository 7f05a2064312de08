//! What a long command is doing now: the stages of a tilt series and of a reconstruction,
//! told by the code that does them to an observer its caller passes in (`&dyn Fn(Stage)`):
//! no global state, no I/O here. The command line shows them (a progress display on a
//! terminal, a log line per stage otherwise), the daemon puts them in its `STATUS=` line,
//! tests collect them.

use std::fmt;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// A stage of `acquire`, `reconstruct` or `replay`, told when it begins.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Stage {
    /// Connecting to the stage and the SEM.
    Connect,
    /// Tilt step `step` of `steps` (0 is the move to the first tilt).
    Tilt {
        step: usize,
        steps: usize,
        tilt_deg: f64,
    },
    /// A frame at step `step`: `"tracking"`, `"left"` or `"right"`.
    Capture {
        step: usize,
        role: &'static str,
        tilt_deg: f64,
    },
    /// The sparse stage: SIFT, matching, ORSA, rectification.
    Sparse,
    /// The dense stage: dense SIFT, SIFT flow, refinement, left–right check, bilateral grid.
    Dense,
    /// Heights h = d·p / (2 sin(θ/2)) on the left micrograph's grid.
    Depth,
    /// Writing the output files.
    Export,
    /// Publishing the results in the run record.
    Record,
}

/// Observer of stages, as the code doing them receives it.
pub type Observer<'a> = &'a (dyn Fn(Stage) + Sync);

/// The observer that ignores every stage.
pub fn unobserved(_: Stage) {}

impl Stage {
    /// A short name, the same for every instance of the stage (`tilt` for any step).
    #[must_use]
    pub fn name(&self) -> &'static str {
        match self {
            Self::Connect => "connect",
            Self::Tilt { .. } => "tilt",
            Self::Capture { .. } => "capture",
            Self::Sparse => "sparse",
            Self::Dense => "dense",
            Self::Depth => "depth",
            Self::Export => "export",
            Self::Record => "record",
        }
    }

    /// True for the stages of the tilt series (the acquisition logs them itself).
    #[must_use]
    pub fn is_acquisition(&self) -> bool {
        matches!(
            self,
            Self::Connect | Self::Tilt { .. } | Self::Capture { .. }
        )
    }

    /// `(done, of)` where the stage is one of a counted sequence: the tilt steps.
    #[must_use]
    pub fn count(&self) -> Option<(usize, usize)> {
        match *self {
            Self::Tilt { step, steps, .. } => Some((step, steps)),
            _ => None,
        }
    }
}

impl fmt::Display for Stage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Connect => f.write_str("connecting to the instruments"),
            Self::Tilt {
                step,
                steps,
                tilt_deg,
            } => write!(f, "step {step}/{steps}: tilting to {tilt_deg:.3}°"),
            Self::Capture {
                step,
                role,
                tilt_deg,
            } => write!(
                f,
                "step {step}: capturing the {role} frame at {tilt_deg:.3}°"
            ),
            Self::Sparse => f.write_str("sparse stage (SIFT, matching, ORSA, rectification)"),
            Self::Dense => f.write_str("dense stage (SIFT flow, left–right check, bilateral grid)"),
            Self::Depth => f.write_str("heights on the left micrograph's grid"),
            Self::Export => f.write_str("writing the outputs"),
            Self::Record => f.write_str("recording the results"),
        }
    }
}

/// Times each stage from its start to the start of the next one, or to
/// [`StageClock::finish`]. Time is an input: the caller says when.
#[derive(Debug, Default)]
pub struct StageClock {
    current: Mutex<Option<(Stage, Instant)>>,
}

impl StageClock {
    /// `stage` begins at `now`; returns the stage it ends and how long that one took.
    pub fn start(&self, stage: Stage, now: Instant) -> Option<(Stage, Duration)> {
        let mut current = self.current.lock().unwrap_or_else(|e| e.into_inner());
        let ended = current.map(|(s, t)| (s, now.saturating_duration_since(t)));
        *current = Some((stage, now));
        ended
    }

    /// The stage running at `now` ends; returns it and how long it took.
    pub fn finish(&self, now: Instant) -> Option<(Stage, Duration)> {
        let mut current = self.current.lock().unwrap_or_else(|e| e.into_inner());
        current
            .take()
            .map(|(s, t)| (s, now.saturating_duration_since(t)))
    }

    /// The stage running now, if any.
    #[must_use]
    pub fn current(&self) -> Option<Stage> {
        self.current
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .map(|(s, _)| s)
    }
}

/// Collects the stages it is told, in order: for tests.
#[derive(Debug, Default)]
pub struct StageLog(Mutex<Vec<Stage>>);

impl StageLog {
    /// Records `stage`.
    pub fn push(&self, stage: Stage) {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).push(stage);
    }

    /// The stages told so far.
    #[must_use]
    pub fn stages(&self) -> Vec<Stage> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_clock_times_each_stage_until_the_next_begins() {
        let clock = StageClock::default();
        let t0 = Instant::now();
        assert_eq!(clock.start(Stage::Sparse, t0), None);
        let t1 = t0 + Duration::from_millis(1500);
        assert_eq!(
            clock.start(Stage::Dense, t1),
            Some((Stage::Sparse, Duration::from_millis(1500)))
        );
        assert_eq!(clock.current(), Some(Stage::Dense));
        let t2 = t1 + Duration::from_millis(20);
        assert_eq!(
            clock.finish(t2),
            Some((Stage::Dense, Duration::from_millis(20)))
        );
        assert_eq!(clock.finish(t2), None);
    }

    #[test]
    fn stages_read_as_what_they_do() {
        assert_eq!(Stage::Dense.count(), None);
        let tilt = Stage::Tilt {
            step: 3,
            steps: 7,
            tilt_deg: 3.0,
        };
        assert_eq!(tilt.to_string(), "step 3/7: tilting to 3.000°");
        assert!(tilt.is_acquisition() && !Stage::Sparse.is_acquisition());
    }
}
