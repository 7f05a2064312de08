//! `sdsem-sim`: a stage-and-SEM simulator that speaks the same protocols as the
//! real instruments, so `sdsem` runs and is tested without hardware.
//!
//! ```text
//!  GCS client ──bytes──▶ stage_link (TCP / pty) ──▶ CommandFramer ──▶ SimStage
//!                                                          │  Mutex<StageModel> (pure, faults seeded)
//!                              one Clock (time_scale) ─────┤
//!                                                          ▼ PoseSource (the pose now, mid-move too)
//!  SEM client ──bytes──▶ sem_server (TCP) ──▶ RequestDecoder ──▶ SimSem ──▶ render(Scene, View)
//!                                                                   │  walk, drift, scan noise (seeded)
//!                                                                   ▼  frame records → ground truth
//!  SharkSEM client ──control + data (TCP)──▶ sharksem ──▶ the same SimStage and SimSem
//! ```
//!
//! The device models are pure or nearly so: [`stage_model::StageModel`] takes
//! framed commands and the simulated time and answers replies; [`sem::SimSem`]
//! takes SEM requests and renders frames where the stage is. The links only
//! move bytes. Time comes from one [`clock::Clock`]: `time_scale` real seconds
//! per simulated second (0.01 ⇒ 100× faster), or a manual clock in tests. One
//! [`SimConfig`] describes both instruments, one `seed` drives them.
//! [`Simulator::spawn`] builds the specimen, starts both servers on background
//! threads and returns a [`SimHandle`] with both endpoints, the stage's state,
//! the SEM's frames and their ground truth, and a way to stop.

pub mod clock;
pub mod config;
pub mod folder_writer;
pub mod pose;
pub mod remcon;
pub mod render;
pub mod scene;
pub mod sem;
pub mod sem_server;
pub mod sharksem;
pub mod simulator;
pub mod stage;
mod stage_link;
pub mod stage_model;
pub mod store;
pub mod vendor_tiff;
pub mod walk;

pub use config::{
    FaultConfig, FaultTrigger, RemconSimConfig, SemSimConfig, SimConfig, SimEndpoint,
    SimStageProtocol, StageSimConfig, derive_seed,
};
pub use folder_writer::{
    FolderMacro, FolderSimConfig, FolderWriter, StoreRequests, StoreSettings, StoredFile,
};
pub use sem::{FrameRecord, SimSem};
pub use simulator::{ServiceEndpoint, SimHandle, Simulator};
pub use stage::SimStage;
pub use store::{StoreCommand, StoreHook, StoreRequest, StoreTrigger};

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
    /// The simulated specimen cannot be built.
    #[error("cannot build the simulated specimen (sem.scene): {0}")]
    Scene(#[from] crate::scene::SceneError),
    /// A TCP endpoint cannot be bound.
    #[error(
        "cannot listen for the {service} link on {addr}: {error}; \
         listen on a local address and a free port (port 0 picks one), or stop the program \
         already listening there"
    )]
    Bind {
        /// Which link: `stage` or `SEM imaging`.
        service: &'static str,
        /// The address asked for.
        addr: std::net::SocketAddr,
        /// The system's reason (not a `source`: the message already shows it).
        error: std::io::Error,
    },
    /// A listener handed to a server cannot be used.
    #[error("cannot serve the {service} link on the listener given: {error}")]
    Listener {
        /// Which link.
        service: &'static str,
        /// The system's reason.
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
