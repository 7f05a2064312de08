//! Errors of a SharkSEM session: each names the function, the cause and the remedy.

use std::time::Duration;

use sdsem_protocol::sharksem::{AssembleError, BodyError, FrameError, Version};

/// Everything that can go wrong between sdsem and a TESCAN SEM.
#[derive(Debug, thiserror::Error)]
pub enum SharkError {
    /// A setting is wrong.
    #[error("invalid SharkSEM setting {field}: {reason}")]
    Config { field: &'static str, reason: String },

    /// The control connection cannot be opened.
    #[error(
        "cannot connect to the SharkSEM server at {endpoint}: {cause}; check that the SEM \
         software runs with SharkSEM remote control enabled on that port (8300 by default) and \
         that no firewall blocks it"
    )]
    Connect { endpoint: String, cause: String },

    /// The data channel cannot be opened.
    #[error(
        "cannot open the SharkSEM data channel to {addr}: {cause}; the data port is the control \
         port + 1 unless imaging.data_port says otherwise: check it and that no firewall blocks it"
    )]
    DataChannel { addr: String, cause: String },

    /// A request with a value to return was not answered.
    #[error(
        "the SharkSEM server at {endpoint} did not answer {function} within {after:?}: SharkSEM \
         ignores requests it does not accept without a word (unknown to protocol {version}, \
         wrong arguments, or not allowed now), or the SEM is busy or hung; check the SEM \
         software, or raise {timeout_key}"
    )]
    NoReply {
        endpoint: String,
        function: String,
        after: Duration,
        version: String,
        timeout_key: &'static str,
    },

    /// The connection broke.
    #[error(
        "lost the SharkSEM connection to {endpoint} during {function}: {cause}; the next request \
         reconnects"
    )]
    Disconnected {
        endpoint: String,
        function: String,
        cause: String,
    },

    /// The server sent bytes that are not SharkSEM.
    #[error(
        "the SharkSEM server at {endpoint} sent a message sdsem cannot follow: {cause}; is it \
         really a TESCAN SharkSEM server?"
    )]
    Unframeable { endpoint: String, cause: FrameError },

    /// A response whose body does not hold what the function returns.
    #[error("the SharkSEM server answered {function} with a body sdsem cannot read: {cause}")]
    BadReply { function: String, cause: BodyError },

    /// The function answered a value that means failure.
    #[error("the SharkSEM server refused {function}: it returned {value}; {remedy}")]
    Refused {
        function: String,
        value: String,
        remedy: &'static str,
    },

    /// A setting did not take (SharkSEM ignores settings silently), even re-sent once.
    #[error(
        "the SEM did not take {setting} = {wanted}: it reads back {got}, the request re-sent \
         once; {remedy}"
    )]
    NotApplied {
        setting: String,
        wanted: String,
        got: String,
        remedy: &'static str,
    },

    /// A frame's image data broke the reassembly rules.
    #[error("frame {frame}: {cause}")]
    Frame { frame: u32, cause: AssembleError },

    /// A frame's image data stopped coming.
    #[error(
        "frame {frame}: only {received} of {total} pixels arrived within {after:?} (the scan time \
         and the reply timeout); check that the SEM scans (beam on, not in the operator's hands) \
         and that the data channel is open"
    )]
    DataTimeout {
        frame: u32,
        received: u64,
        total: u64,
        after: Duration,
    },

    /// The server is too old for something sdsem needs.
    #[error(
        "the SharkSEM server speaks protocol {version}; {what} needs {needed} or later: update \
         the SEM software"
    )]
    TooOld {
        version: Version,
        needed: Version,
        what: &'static str,
    },

    /// The stage is not calibrated: it would ignore every move.
    #[error(
        "the SEM stage is not calibrated (StgIsCalibrated = 0), so it would ignore every move: \
         calibrate it in the TESCAN software, then start again"
    )]
    NotCalibrated,

    /// The configured detector does not exist.
    #[error(
        "no detector {wanted:?} on this SEM (it has {available}); set imaging.detector to one of them"
    )]
    NoDetector { wanted: String, available: String },
}

impl SharkError {
    /// Whether trying the same frame once more may succeed: data lost or
    /// stalled, the connection gone, a request unanswered.
    #[must_use]
    pub fn is_transient(&self) -> bool {
        matches!(
            self,
            Self::Frame { .. }
                | Self::DataTimeout { .. }
                | Self::Disconnected { .. }
                | Self::NoReply { .. }
                | Self::Unframeable { .. }
        )
    }
}
