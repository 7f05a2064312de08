//! The MCAP record of a run: writer thread, Foxglove schemas, reading back (DESIGN §5).
//!
//! ```text
//!  producers (sync or async) ──Entry──▶ bounded channel ──▶ writer thread ──▶ run.mcap
//!      RecorderHandle::image/json/...        (frames block,        (owns mcap::Writer,
//!      RecordLogLayer (tracing → /log)        logs may drop)        chunk cut per frame)
//!
//!  run.mcap ──linear read (truncation-tolerant)──▶ read_summary / read_images / read_json ...
//! ```
//!
//! Topics and schemas are the contract of DESIGN §5 ([`topics`]); the JSON messages and their
//! schemas are in [`messages`].

mod entry;
mod error;
mod inspect;
mod log_layer;
pub mod messages;
mod read;
mod recorder;
pub mod topics;

pub use entry::{Entry, LogLevel, Pixels};
pub use error::{ReadError, RecordError};
pub use inspect::{
    AttachmentInspection, RecordInspection, TopicInspection, format_inspection, read_summary,
    utc_time,
};
pub use log_layer::{RecordLogLayer, RecordLogSwitch, record_log_layer};
pub use messages::{FrameInfo, RunOutcome, RunStatus, StageIo, StageState};
pub use read::{
    ChannelInfo, EndMicrographs, Extract, MetadataRecord, RecordedAttachment, RecordedImage,
    RecordedJson, RecordedLog, RecordedMicrograph, RecordedPointCloud, ScanEnd, read_attachments,
    read_end_micrographs, read_images, read_json, read_logs, read_metadata, read_point_clouds,
};
pub use recorder::{RecordSummary, Recorder, RecorderHandle, RecorderOptions, RecorderStatus};
pub use topics::FrameRole;

#[cfg(test)]
mod tests;
