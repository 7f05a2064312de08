//! `sdsem-sim`: a stage-and-SEM simulator that speaks the same protocols as the
//! real instruments, so `sdsem` runs and is tested without hardware.
//!
//! ```text
//!  client ──bytes──▶ stage_link (TCP / pty, std threads) ──▶ CommandFramer ──▶ SimStage
//!                                                                    │  Mutex<StageModel> (pure)
//!                                                 Clock (scaled) ────┤  faults (seeded)
//!                                                                    ▼
//!                                      PoseSource ──▶ SEM renderer (where the stage is now)
//! ```
//!
//! The device model ([`stage_model::StageModel`]) is pure: framed commands and the
//! simulated time in, replies out. The links only move bytes. Time comes from a
//! [`clock::Clock`]: real time scaled by `time_scale`, or a manual clock in tests.
//! [`Simulator::spawn`] starts everything on background threads and returns a
//! [`SimHandle`] with the endpoints, read access to the model, and a way to stop.

pub mod clock;
pub mod config;
pub mod pose;
pub mod render;
pub mod scene;
pub mod sem_server;
pub mod simulator;
pub mod stage;
mod stage_link;
pub mod stage_model;
pub mod walk;

pub use config::{FaultConfig, FaultTrigger, SimConfig, SimEndpoint, StageSimConfig};
pub use simulator::{ServiceEndpoint, SimHandle, Simulator};
pub use stage::SimStage;

/// Why the simulator cannot start.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A configuration value is wrong.
    #[error("invalid simulator configuration: {field}: {reason}")]
    Config {
        /// The field, as written in the configuration.
        field: &'static str,
        /// What is wrong and what is accepted.
        reason: String,
    },
    /// The TCP endpoint cannot be bound.
    #[error(
        "cannot listen for the stage link on {addr}: {error}; \
         listen on a local address and a free port (port 0 picks one), or stop the program \
         already listening there"
    )]
    Bind {
        /// The address asked for.
        addr: std::net::SocketAddr,
        /// The system's reason (not a `source`: the message already shows it).
        error: std::io::Error,
    },
    /// No pseudo-terminal can be created.
    #[error(
        "cannot create a pseudo-terminal for the stage link: {cause}; \
         check that /dev/ptmx exists and is writable, or use a TCP endpoint"
    )]
    Pty {
        /// The system's reason.
        cause: String,
    },
    /// A server thread cannot be started.
    #[error("cannot start a simulator thread: {error}")]
    Thread {
        /// The system's reason.
        error: std::io::Error,
    },
}
