//! The stage pose shared between the stage controller model and the SEM renderer.

/// Where the specimen stage is at one instant: what the SEM images.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StagePose {
    /// Stage X translation, micrometres.
    pub x_um: f64,
    /// Stage Y translation, micrometres.
    pub y_um: f64,
    /// Stage tilt, degrees.
    pub tilt_deg: f64,
}

/// Anything that can tell the current stage pose (the simulated stage controller).
pub trait PoseSource: Send + Sync {
    /// The pose at this instant, mid-move included.
    fn pose(&self) -> StagePose;
}

/// A stage that stays where it is put: for tests and for running the SEM
/// server without a stage model.
#[derive(Debug, Default)]
pub struct FixedPose(std::sync::Mutex<StagePose>);

impl FixedPose {
    /// A stage at `pose`.
    #[must_use]
    pub fn new(pose: StagePose) -> Self {
        Self(std::sync::Mutex::new(pose))
    }

    /// Moves the stage (instantly).
    pub fn set(&self, pose: StagePose) {
        *self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = pose;
    }
}

impl PoseSource for FixedPose {
    fn pose(&self) -> StagePose {
        *self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}
