//! The one error type of the exports.

use std::path::PathBuf;

/// Why an export could not be written or read back.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// Creating, writing, syncing or renaming the file failed.
    #[error(
        "cannot write {path}: {source} — check free space and permissions of the output directory"
    )]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Reading a file back failed.
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The data cannot be written in this format.
    #[error("cannot write {path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
    /// A file read back does not follow its format.
    #[error("{path} is not a valid {format} file: {reason}")]
    Format {
        path: PathBuf,
        format: &'static str,
        reason: String,
    },
}
