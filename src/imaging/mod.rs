//! The SEM side: grabbing frames, and reading micrographs with their metadata.
//!
//! - [`Frame`]: pixels (8 or 16 bit) and [`FrameMeta`] (pixel size, dwell,
//!   stage pose and tilt, role, frame number, timestamps); [`Frame::to_image`]
//!   gives the vision core's [`crate::vision::Image`].
//! - [`FrameSource`]: anything that grabs frames; [`SemLinkClient`] speaks the
//!   SEM imaging link ([`sdsem_protocol::sem`]) over TCP to the simulator or a
//!   microscope adapter, configured by [`ImagingConfig`].

mod config;
mod error;
mod frame;
mod link_client;
mod source;

pub use config::{DEFAULT_PORT, ImagingConfig, ScanSettings};
pub use error::ImagingError;
pub use frame::{Frame, FrameMeta, Pixels, Role};
pub use link_client::{GroundTruth, SemLinkClient};
pub use source::{FrameSource, GrabFuture, GrabRequest};
