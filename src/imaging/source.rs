//! Anything that delivers frames: the SEM link, a watched folder, a TESCAN SEM over SharkSEM,
//! or a test double.

use std::future::Future;
use std::pin::Pin;

pub use sdsem_protocol::sem::GrabRequest;
use serde::{Deserialize, Serialize};

use super::{Frame, ImagingError};
use crate::stage::StagePosition;

/// The future of one [`FrameSource::grab`].
pub type GrabFuture<'a> = Pin<Box<dyn Future<Output = Result<Frame, ImagingError>> + Send + 'a>>;

/// The future of one [`FrameSource::identify`].
pub type IdentifyFuture<'a> =
    Pin<Box<dyn Future<Output = Result<String, ImagingError>> + Send + 'a>>;

/// The future of one [`FrameSource::probe`]: (name, value) lines for `sdsem probe`.
pub type ProbeFuture<'a> =
    Pin<Box<dyn Future<Output = Result<Vec<(String, String)>, ImagingError>> + Send + 'a>>;

/// Who makes the frames, as far as the source knows (for the record and `sdsem probe`);
/// fields it does not know are empty.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SourceIdentity {
    /// Manufacturer.
    pub vendor: String,
    /// Instrument or server model.
    pub model: String,
    /// Software version.
    pub version: String,
    /// Serial number.
    pub serial: String,
}

impl SourceIdentity {
    /// "vendor, model, serial, version" answers (`*IDN?` of the SEM link); other answers
    /// give nothing.
    #[must_use]
    pub fn from_idn(idn: &str) -> Self {
        let parts: Vec<&str> = idn.split(',').map(str::trim).collect();
        match parts.as_slice() {
            [vendor, model, serial, version, ..] => Self {
                vendor: (*vendor).to_owned(),
                model: (*model).to_owned(),
                version: (*version).to_owned(),
                serial: (*serial).to_owned(),
            },
            _ => Self::default(),
        }
    }

    /// Whether nothing is known.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self == &Self::default()
    }
}

/// Why a trigger could not be sent (the stage link's own error).
pub type TriggerError = Box<dyn std::error::Error + Send + Sync>;

/// The future of one [`Trigger::trigger`].
pub type TriggerFuture<'a> = Pin<Box<dyn Future<Output = Result<(), TriggerError>> + Send + 'a>>;

/// Sends a command that makes the SEM store one micrograph (`imaging.trigger`, e.g. RemCon32
/// `FREC` or `MAC 1`): implemented over the stage link by the acquisition, since the SEM's
/// own stage protocol is the line that carries it.
pub trait Trigger: Send {
    /// Sends `command` and returns once the SEM accepted it.
    fn trigger<'a>(&'a mut self, command: &'a str) -> TriggerFuture<'a>;
}

/// What the acquisition knows and offers at the moment of one grab.
#[derive(Default)]
pub struct GrabContext<'a> {
    /// The stage position verified before this grab.
    pub stage: Option<StagePosition>,
    /// A line to send `imaging.trigger` over, when the stage link can carry one.
    pub trigger: Option<&'a mut dyn Trigger>,
}

/// A source of SEM frames. Object-safe, so the acquisition can hold a
/// `Box<dyn FrameSource>` chosen by configuration.
pub trait FrameSource: Send {
    /// Scans one frame as requested (size, dwell, role, bit depth) and returns
    /// it with its metadata.
    fn grab(&mut self, request: GrabRequest) -> GrabFuture<'_>;

    /// [`FrameSource::grab`] with what the acquisition knows (stage position) and offers
    /// (a trigger). Sources that need neither keep this default.
    fn grab_with<'a>(
        &'a mut self,
        request: GrabRequest,
        context: GrabContext<'a>,
    ) -> GrabFuture<'a> {
        let _ = context;
        self.grab(request)
    }

    /// Checks that the source answers and says what it is (an instrument's identity, a
    /// folder and its state); the daemon's link check between jobs.
    fn identify(&mut self) -> IdentifyFuture<'_>;

    /// Who makes the frames as far as known now: the identification answer parsed, or what
    /// the last file read recorded. Sources that learn nothing keep this default (empty).
    fn identity(&self) -> SourceIdentity {
        SourceIdentity::default()
    }

    /// What `sdsem probe` shows besides the identity, read without scanning anything
    /// (pixel size or field width, detectors, a folder's state), as (name, value) lines.
    /// Sources with nothing more to say keep this default (no lines).
    fn probe(&mut self) -> ProbeFuture<'_> {
        Box::pin(async { Ok(Vec::new()) })
    }
}

impl<S: FrameSource + ?Sized> FrameSource for Box<S> {
    fn grab(&mut self, request: GrabRequest) -> GrabFuture<'_> {
        (**self).grab(request)
    }

    fn grab_with<'a>(
        &'a mut self,
        request: GrabRequest,
        context: GrabContext<'a>,
    ) -> GrabFuture<'a> {
        (**self).grab_with(request, context)
    }

    fn identify(&mut self) -> IdentifyFuture<'_> {
        (**self).identify()
    }

    fn identity(&self) -> SourceIdentity {
        (**self).identity()
    }

    fn probe(&mut self) -> ProbeFuture<'_> {
        (**self).probe()
    }
}
