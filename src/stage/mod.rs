//! The specimen stage: async driver over any byte stream, and the one place that opens ports.
//!
//! - [`transport`]: opens `stage.endpoint` (serial device, pty, `tcp://HOST:PORT`).
//! - [`driver`]: [`StageDriver`], generic over `AsyncRead + AsyncWrite`: one request
//!   in flight, timeouts, bounded retries of queries, every move verified.
//! - [`observer`]: what the driver reports (every exchange, every position that
//!   matters) as serialisable records for the recorder.
//! - The wire protocol itself (sans-IO) is [`sdsem_protocol::gcs`], shared with the simulator.

pub mod config;
pub mod driver;
pub mod error;
pub mod observer;
pub mod transport;

pub use config::{StageAxis, StageConfig};
pub use driver::{MoveReport, StageDriver, StagePosition};
pub use error::StageError;
pub use observer::{
    AxisState, IoOutcome, MemoryObserver, NoopObserver, StageEvent, StageIo, StageObserver,
    StageState,
};
pub use transport::{Endpoint, StageLink};

#[cfg(test)]
mod tests;
