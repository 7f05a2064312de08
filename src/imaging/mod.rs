//! The SEM side: grabbing frames, and reading micrographs with their metadata.
//!
//! - [`Frame`]: pixels (8 or 16 bit) and [`FrameMeta`] (pixel size, dwell,
//!   stage pose and tilt, role, frame number, timestamps); [`Frame::to_image`]
//!   gives the vision core's [`crate::vision::Image`].
//! - [`FrameSource`]: anything that grabs frames; [`SemLinkClient`] speaks the
//!   SEM imaging link ([`sdsem_protocol::sem`]) over TCP to the simulator or a
//!   microscope adapter, configured by [`ImagingConfig`].
//! - [`WatchFolderSource`]: micrographs the SEM's own software stores in a folder
//!   (`imaging.protocol = "watch-folder"`), found by [`arrival`], sent for by a [`Trigger`]
//!   over the stage link.
//! - [`SharkSemSource`]: scans on a TESCAN SEM over SharkSEM ([`crate::sharksem`]).
//! - [`file`]: micrographs on disk (TIFF, PNG) with their SEM metadata ([`metadata`]).

pub mod arrival;
mod config;
mod error;
pub mod file;
mod file_raster;
mod file_tiff;
mod frame;
mod link_client;
pub mod metadata;
mod sharksem;
mod source;
mod watch_folder;

pub use config::{DEFAULT_PORT, ImagingConfig, ImagingProtocol, ScanSettings};
pub use error::ImagingError;
pub use frame::{Frame, FrameFile, FrameMeta, Pixels, Role};
pub use link_client::{GroundTruth, SemLinkClient};
pub use sharksem::SharkSemSource;
pub use source::{
    FrameSource, GrabContext, GrabFuture, GrabRequest, IdentifyFuture, ProbeFuture, SourceIdentity,
    Trigger, TriggerError, TriggerFuture,
};
pub use watch_folder::WatchFolderSource;
