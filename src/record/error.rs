//! Errors of the run record: writing ([`RecordError`]) and reading back ([`ReadError`]).

use std::path::PathBuf;

/// Why recording failed or a message was refused.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The record file could not be created.
    #[error(
        "cannot create the run record {path}: {source} — check that the directory exists and is writable"
    )]
    Create {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The writer thread could not be started.
    #[error("cannot start the recorder thread for {path}: {source}")]
    Spawn {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Writing to the record failed (disk full, I/O error); the recorder stopped writing.
    /// Everything up to the last completed chunk stays readable.
    #[error(
        "writing the run record {path} failed while {doing}: {cause} — is the disk full or gone?"
    )]
    Write {
        path: PathBuf,
        doing: &'static str,
        /// The error and its sources, joined by ": ".
        cause: String,
    },
    /// A message was refused because the writer had already failed; the cause is
    /// reported once, by [`super::Recorder::finish`] and [`super::RecorderHandle::status`].
    #[error("the recorder of {path} stopped after an earlier write error (see its status)")]
    Stopped { path: PathBuf },
    /// The recorder was already finished (or its thread is gone).
    #[error("the recorder is closed: the run record was already finished")]
    Closed,
    /// A message did not make sense (e.g. pixel buffer of the wrong length).
    #[error("refused a message on {topic}: {reason}")]
    InvalidMessage { topic: String, reason: String },
    /// A JSON message could not be serialised.
    #[error("cannot serialise the JSON message on {topic}: {source}")]
    Json {
        topic: String,
        #[source]
        source: serde_json::Error,
    },
    /// The writer thread panicked; the file holds what was flushed before.
    #[error("the recorder thread of {path} panicked; the record is incomplete")]
    WriterPanicked { path: PathBuf },
}

/// Why a run record could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("cannot open the run record {path}: {source}")]
    Open {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot read the run record {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The file does not start like an MCAP file.
    #[error("{path} is not an MCAP file: {cause}")]
    NotMcap { path: PathBuf, cause: String },
    /// A message of a known schema could not be decoded.
    #[error("{path}: cannot decode a {schema} message on {topic}: {cause}")]
    Decode {
        path: PathBuf,
        topic: String,
        schema: String,
        cause: String,
    },
}

/// `error` and its chain of sources, joined by ": " (mcap's I/O error hides its source
/// from `Display`, and "No space left on device" is what the user needs to read).
pub(crate) fn error_chain(error: &dyn std::error::Error) -> String {
    let mut text = error.to_string();
    let mut source = error.source();
    while let Some(e) = source {
        let part = e.to_string();
        if !text.contains(&part) {
            text.push_str(": ");
            text.push_str(&part);
        }
        source = e.source();
    }
    text
}
