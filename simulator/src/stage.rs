//! The simulated stage shared between its links and the SEM renderer: the pure
//! model behind a mutex, driven by the simulator's clock.

use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use sdsem_protocol::gcs::{FrameError, Incoming};

use crate::clock::Clock;
use crate::config::StageSimConfig;
use crate::pose::{PoseSource, StagePose};
use crate::stage_model::{Response, StageModel, StageSnapshot};

/// The simulated stage controller, safe to share between threads.
#[derive(Debug)]
pub struct SimStage {
    model: Mutex<StageModel>,
    clock: Arc<dyn Clock>,
}

impl SimStage {
    /// A controller per `config` (validated by the caller) on `clock`, its
    /// fault draws seeded by `seed` ([`crate::Simulator`] passes the resolved
    /// `stage.seed`).
    pub fn new(config: &StageSimConfig, seed: u64, clock: Arc<dyn Clock>) -> Self {
        Self {
            model: Mutex::new(StageModel::new(config, seed)),
            clock,
        }
    }

    fn model(&self) -> MutexGuard<'_, StageModel> {
        // A panic elsewhere cannot leave the model half-updated in a way that
        // matters more than stopping the simulator would.
        self.model.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Handles one framed command now.
    pub fn handle(&self, incoming: Result<Incoming, FrameError>) -> Response {
        let mut model = self.model();
        // Read the clock under the lock so that time never runs backwards for the model.
        let now = self.clock.now_s();
        model.handle(now, incoming)
    }

    /// Runs `f` on the model at the time now (read under the lock, so that
    /// time never runs backwards for the model): how other dialects drive it.
    pub fn with_model<R>(&self, f: impl FnOnce(&mut StageModel, f64) -> R) -> R {
        let mut model = self.model();
        let now = self.clock.now_s();
        f(&mut model, now)
    }

    /// The whole controller state now (true positions, counters, faults fired).
    pub fn snapshot(&self) -> StageSnapshot {
        let model = self.model();
        model.snapshot(self.clock.now_s())
    }

    /// Commands received so far, all links together.
    pub fn command_count(&self) -> u64 {
        self.model().command_count()
    }

    /// The clock the stage runs on.
    pub fn clock(&self) -> &Arc<dyn Clock> {
        &self.clock
    }
}

impl PoseSource for SimStage {
    fn pose(&self) -> StagePose {
        let model = self.model();
        model.pose(self.clock.now_s())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::ManualClock;

    #[test]
    fn pose_follows_the_clock_mid_move() {
        let clock = Arc::new(ManualClock::new());
        let stage = SimStage::new(&StageSimConfig::default(), 0, clock.clone());
        stage.handle(Ok(Incoming::Line(b"MOV T 2 X 50".to_vec())));
        clock.advance(0.25);
        let pose = stage.pose();
        assert!((pose.tilt_deg - 0.25).abs() < 1e-9);
        assert!((pose.x_um - 25.0).abs() < 1e-9);
        assert_eq!(stage.command_count(), 1);
        clock.advance(10.0);
        let snap = stage.snapshot();
        assert_eq!(snap.pose.tilt_deg, 2.0);
        assert!(snap.axes.iter().all(|a| a.on_target));
    }
}
