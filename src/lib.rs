//! # sdsem — unattended 3D surface reconstruction on a scanning electron microscope
//!
//! ```text
//!  stage controller ──(PI GCS 2.0, serial/pty/TCP)──┐
//!                                                    │  stage::driver (async, one request in flight)
//!  SEM imaging link ──(line protocol, TCP)───────────┤  imaging (frames + metadata)
//!                                                    ▼
//!                     acquisition (pure state machine: tilt 1° steps, track, re-centre)
//!                                                    │ left / right micrographs
//!                                                    ▼
//!   vision (pure, rayon):  sparse SIFT → matching → ORSA → quasi-Euclidean rectification
//!                          → dense SIFT → SIFT flow (dual-layer BP, coarse to fine)
//!                          → bilateral grid → depth h = d·p / (2 sin(θ/2))
//!                                                    │
//!                                                    ▼
//!                     export (height.tif, height.gsf, pointcloud.ply, mesh.ply, confidence.tif, report.json)
//!
//!   record: one MCAP per run, fed by everything above through a bounded channel
//!   daemon: job spool, supervisor, signals, systemd notify
//! ```
//!
//! The vision core knows nothing of tokio, MCAP, configuration files or the stage;
//! the stage protocol ([`sdsem_protocol`]) does no I/O; time is an input.

/// `From` conversions for error variants whose message already shows the
/// inner error (`#[error("stage: {0}")]`): thiserror's `#[from]` would also
/// make the inner error the variant's `source`, and the one-line cause chain
/// `main` prints (`{:#}`) would then name it twice.
#[macro_export]
macro_rules! error_from {
    ($outer:ty { $($variant:ident($inner:ty)),+ $(,)? }) => {
        $(impl From<$inner> for $outer {
            fn from(e: $inner) -> Self {
                Self::$variant(e)
            }
        })+
    };
}

pub mod acquisition;
pub mod app;
pub mod cli;
pub mod config;
pub mod daemon;
pub mod export;
pub mod imaging;
pub mod numbers;
pub mod progress;
pub mod record;
pub mod sharksem;
pub mod stage;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod vision;
