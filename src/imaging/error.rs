//! Errors of the imaging layer.

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
}

error_from!(ImagingError {
    SharkSem(crate::sharksem::SharkError)
});
