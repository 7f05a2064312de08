//! The specimen stage: one safety layer above one backend per protocol, and
//! the one place that opens ports.
//!
//! - [`transport`]: opens `stage.endpoint` (serial device, pty, `tcp://HOST:PORT`).
//! - [`backend`]: [`StageBackend`], what differs per protocol (identify, read,
//!   start a move, poll, stop, raw commands). Backends: [`gcs`] (PI GCS 2.0),
//!   [`remcon`] (Zeiss SmartSEM RemCon32) and [`sharksem`] (a TESCAN SEM's own stage).
//! - [`driver`]: [`StageDriver`], the safety layer above any backend: limits,
//!   move timeouts, every move verified by read-back, one re-issue, safe tilt, stop.
//! - [`observer`]: what the driver reports (every exchange, every position that
//!   matters) as serialisable records for the recorder.
//! - The wire protocols themselves (sans-IO) are in [`sdsem_protocol`], shared
//!   with the simulator.
//!
//! Adding a protocol: a variant of [`StageProtocol`], a module implementing
//! [`StageBackend`], and its arm in [`open_backend`].

pub mod backend;
pub mod config;
pub mod driver;
pub mod error;
pub mod gcs;
pub mod observer;
pub mod remcon;
pub mod sharksem;
pub mod transport;
mod wire;

use std::sync::Arc;

use crate::sharksem::SharkLink;

pub use backend::{BoxFuture, Connected, MotionPoll, StageBackend, StageIdentity};
pub use config::{StageAxis, StageConfig, StageProtocol};
pub use driver::{MoveReport, StageDriver, StagePosition};
pub use error::StageError;
pub use gcs::GcsBackend;
pub use observer::{
    AxisState, IoOutcome, MemoryObserver, NoopObserver, StageEvent, StageIo, StageObserver,
    StageState,
};
pub use remcon::RemconBackend;
pub use sharksem::SharkSemBackend;
pub use transport::{Endpoint, StageLink};

/// Opens `config.endpoint` and returns the backend `config.protocol` names,
/// not yet connected (the safety layer calls [`StageBackend::connect`]).
///
/// # Errors
/// [`StageError::Open`] naming the endpoint and the remedy.
pub async fn open_backend(
    config: &StageConfig,
    observer: Arc<dyn StageObserver>,
) -> Result<Box<dyn StageBackend>, StageError> {
    let timeout = config::secs(config.connect_timeout_s);
    Ok(match config.protocol {
        StageProtocol::PiGcs | StageProtocol::Remcon32 => {
            let link = transport::open(&config.endpoint, config.effective_baud(), timeout).await?;
            match config.protocol {
                StageProtocol::Remcon32 => {
                    Box::new(RemconBackend::new(link, config.clone(), observer))
                }
                _ => Box::new(GcsBackend::new(link, config.clone(), observer)),
            }
        }
        // Its own session: Instruments shares one with the imaging source when both use it.
        StageProtocol::Sharksem => {
            let link =
                SharkLink::connect(SharkSemBackend::session_config(config), observer).await?;
            Box::new(SharkSemBackend::new(link))
        }
    })
}

#[cfg(test)]
mod tests;
