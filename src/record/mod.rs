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
//! schemas are in [`messages`]; what a reconstruction adds for Foxglove (frames, preview,
//! mesh) is in `reconstruction` ([`RecorderHandle::reconstruction`]).
//!
//! ```no_run
//! use sdsem::record::{self, topics, FrameInfo, Recorder, RunOutcome, RunStatus};
//! use sdsem::vision::Image;
//!
//! fn record_one(
//!     t: u64,
//!     micrograph: &Image,
//!     info: &FrameInfo,
//! ) -> Result<(), Box<dyn std::error::Error>> {
//!     let recorder = Recorder::create("run.mcap", Default::default())?;
//!     let rec = recorder.handle(); // clone it into every producer
//!     rec.metadata(topics::METADATA_RUN, [("job".to_owned(), "j1".to_owned())].into())?;
//!     rec.frame(t, micrograph, info)?; // /sem/frame + /sem/frame_info, flushed
//!     rec.outcome(&RunOutcome { status: RunStatus::Succeeded, cause: None })?;
//!     let summary = recorder.finish()?; // must be called: writes the summary, returns errors
//!
//!     let inspection = record::read_summary("run.mcap")?; // also on a truncated file
//!     println!("{}", record::format_inspection(&inspection));
//!     let ends = record::read_end_micrographs("run.mcap")?; // for `sdsem replay`
//! #     let _ = (summary, ends);
//!     Ok(())
//! }
//! ```
//!
//! `tests/check_mcap.py RUN.mcap` validates a record with the reference Python reader
//! (package `mcap` only; protobuf decoded from the stored descriptors).

mod entry;
mod error;
mod inspect;
mod log_layer;
pub mod messages;
mod read;
mod reconstruction;
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
    RecordedJson, RecordedLog, RecordedMicrograph, RecordedPointCloud, ReplayInputs, ScanEnd,
    read_attachments, read_end_micrographs, read_images, read_json, read_logs, read_metadata,
    read_point_clouds, read_replay_inputs,
};
pub use reconstruction::{MESH_PREVIEW_MAX_VERTICES, ReconstructionView};
pub use recorder::{RecordSummary, Recorder, RecorderHandle, RecorderOptions, RecorderStatus};
pub use topics::FrameRole;

#[cfg(test)]
mod tests;
