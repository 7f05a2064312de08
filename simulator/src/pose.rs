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
