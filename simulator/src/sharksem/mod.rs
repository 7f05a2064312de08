//! The SharkSEM dialect: the simulated SEM as a TESCAN microscope's remote
//! control sees it [TS-PDF, TS-CS, TS-PY; `/work/shared/VENDORS.md` §2], on
//! the same stage model, clock, specimen and renderer as the other links.
//!
//! ```text
//!  client ──control (8300)──▶ session thread ──▶ SharkSemDevice ──▶ SimStage (GCS model, µm) + SimSem (renderer)
//!         ◀──data (8301)──── scan thread ◀── begin_scan at the pose now, ScData every 50 ms of simulated time
//! ```
//!
//! What it does, as the manual says a real server does:
//! - Session: the client registers its local data port with `TcpRegDataPort`
//!   (reply 0) and connects its data socket from that port to the data port
//!   (control + 1 unless `data_port` is set); other data connections are closed.
//!   Firewall-friendly mode serves one client pair and ignores the registration.
//! - No events; bad or unknown requests, wrong arguments, malformed messages and
//!   functions newer than `version` are ignored silently (the client only times out).
//! - Wait flags are honoured: A (scan running), B (stage moving or settling), C
//!   (5 ms of optics settling after `SetViewField`); D–G are always clear.
//! - Stage: mm and degrees on the wire, µm in the model. `StgMoveTo` is ignored
//!   when the stage is busy or uncalibrated (any axis unreferenced); targets are
//!   limited to the limits silently (2.0.25's wording); missing trailing axes stay.
//!   z and rotation are not in the stage model: they change at once and do not
//!   change the image. The stage's `ignore_move` fault applies (same model).
//! - Imaging: the view field (mm, clamped) sets the pixel size = field / window
//!   width. `ScScanXY` renders the window at the stage pose of the scan start and
//!   streams the visible region row-major, 16-bit little-endian or 8-bit per the
//!   channel's `DtEnable`, one chunk per `chunk_interval_s` as the scan advances.
//!   `ScStopScan` is required after every scan: a second `ScScanXY` before it is
//!   ignored. `DtEnable` is ignored while a scan is armed.
//! - A client that leaves its data socket unread for `data_stall_s` is dropped.
//! - Faults ([`SharkSemFaults`]): lost and re-sent chunks, an ignored
//!   `SetViewField`, a dropped connection, a server that stops answering.

mod config;
mod device;
mod server;

pub use config::{SharkSemFaults, SharkSemSimConfig};
pub use device::{SharkSemCounts, SharkSemDevice};
pub(crate) use server::serve;

#[cfg(test)]
mod tests;
