//! Anything that delivers frames: the SEM link, a TESCAN SEM over SharkSEM, or a test double.

use std::future::Future;
use std::pin::Pin;

pub use sdsem_protocol::sem::GrabRequest;

use super::{Frame, ImagingError};

/// The future of one [`FrameSource::grab`].
pub type GrabFuture<'a> = Pin<Box<dyn Future<Output = Result<Frame, ImagingError>> + Send + 'a>>;

/// The future of one [`FrameSource::identify`].
pub type IdentifyFuture<'a> =
    Pin<Box<dyn Future<Output = Result<String, ImagingError>> + Send + 'a>>;

/// A source of SEM frames. Object-safe, so the acquisition can hold a
/// `Box<dyn FrameSource>` chosen by configuration.
pub trait FrameSource: Send {
    /// Scans one frame as requested (size, dwell, role, bit depth) and returns
    /// it with its metadata.
    fn grab(&mut self, request: GrabRequest) -> GrabFuture<'_>;

    /// Checks that the source answers and says what it is (an instrument's identity, a
    /// folder and its state); the daemon's link check between jobs.
    fn identify(&mut self) -> IdentifyFuture<'_>;
}
