//! Errors of the imaging layer.

use std::path::PathBuf;
use std::time::Duration;

use sdsem_protocol::sem::ReplyError;

/// Something went wrong getting a frame. Messages name the endpoint, the
/// request and what to do about it.
#[derive(Debug, thiserror::Error)]
pub enum ImagingError {
    #[error(
        "cannot connect to the SEM imaging server at {endpoint}: {source}; check that the microscope's imaging server (or sdsem-sim) is running and that imaging.endpoint is right"
    )]
    Connect {
        endpoint: String,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "the SEM imaging server at {endpoint} did not answer {request} within {after:?}; the microscope may be busy or hung: check it, or raise imaging.timeout_ms"
    )]
    Timeout {
        endpoint: String,
        request: String,
        after: Duration,
    },
    #[error(
        "lost the link to the SEM imaging server at {endpoint} during {request}: {source}; the next request reconnects"
    )]
    Io {
        endpoint: String,
        request: String,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "the SEM imaging server at {endpoint} closed the connection during {request}; the next request reconnects"
    )]
    Closed { endpoint: String, request: String },
    #[error(
        "the SEM imaging server at {endpoint} sent a reply to {request} that sdsem cannot read: {source}; is {endpoint} really an SEM imaging server of this protocol version?"
    )]
    Protocol {
        endpoint: String,
        request: String,
        #[source]
        source: ReplyError,
    },
    #[error("the SEM imaging server at {endpoint} refused {request}: error {code}: {message}")]
    Refused {
        endpoint: String,
        request: String,
        code: u16,
        message: String,
    },
    #[error("the SEM imaging server at {endpoint} answered {request} with {got}")]
    UnexpectedReply {
        endpoint: String,
        request: String,
        got: String,
    },
    /// A TESCAN SEM over SharkSEM (the message names the function and the remedy).
    #[error("{0}")]
    SharkSem(crate::sharksem::SharkError),
    #[error("imaging setting {name} = {value} is invalid: expected {expected}")]
    InvalidConfig {
        name: &'static str,
        value: String,
        expected: &'static str,
    },
    #[error(
        "cannot read the watch folder {dir}: {error}; is the share mounted and readable, and is imaging.watch_dir right?"
    )]
    WatchFolder {
        dir: PathBuf,
        /// Not a `source`: the message already shows it.
        error: std::io::Error,
    },
    #[error(
        "no new micrograph in {dir} within {after:?}{}{}; is the SEM storing to that folder? is the share mounted? (raise imaging.watch_timeout_s for slow scans)",
        if trigger.is_empty() { String::new() } else { format!(" after sending {trigger:?}") },
        if seen.is_empty() { String::new() } else { format!(" ({seen})") }
    )]
    NoNewFile {
        dir: PathBuf,
        after: Duration,
        trigger: String,
        /// What was seen and not used, or "".
        seen: String,
    },
    #[error(
        "{file} records a stage tilt of {recorded_deg}° but the stage is at {stage_deg}° (more than imaging.tilt_tolerance_deg = {tolerance_deg}° apart): refused, not used; is it a late file of another step? (with a tilt stage the SEM does not know, set imaging.watch_check_tilt = false)"
    )]
    WrongTilt {
        file: PathBuf,
        recorded_deg: f64,
        stage_deg: f64,
        tolerance_deg: f64,
    },
    #[error(
        "{file} records no pixel size (no vendor tags or sidecar that give one); have the SEM store its metadata with each image (TIFF tags, or the .txt sidecar with imaging.watch_sidecar = \"txt\")"
    )]
    NoPixelSize { file: PathBuf },
    #[error("cannot use {file}: {cause}")]
    BadFile { file: PathBuf, cause: String },
    #[error("the SEM did not take the trigger {command:?}: {error}")]
    Trigger {
        command: String,
        /// Not a `source`: the message already shows it.
        error: super::source::TriggerError,
    },
    #[error(
        "the trigger {command:?} (imaging.trigger, imaging.tracking_trigger) must go over the stage link, and this stage link cannot carry it; use a stage protocol that speaks to the SEM (stage.protocol = \"remcon32\"), or set both to \"\" and have the SEM store each micrograph on its own"
    )]
    NoTriggerLink { command: String },
}

error_from!(ImagingError {
    SharkSem(crate::sharksem::SharkError)
});
