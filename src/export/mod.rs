//! Writers (and readers, for verification) of the result files.
//!
//! Every writer is atomic: it writes a temporary file beside the target, syncs it and
//! renames it into place ([`atomic`]), so a crash or a full disk never leaves a partial
//! file that looks valid.
//!
//! 3D coordinates (point cloud, mesh) are in µm in a right-handed frame seen from the
//! beam: x = column·p (right), y = −row·p (up in the image), z = height (towards the beam),
//! so viewers show the surface the way the micrograph shows it. See [`ply`].

pub mod atomic;
mod error;
pub mod gsf;
pub mod height_tiff;
pub mod ply;
pub mod report;

pub use error::ExportError;
pub use ply::{CloudPoint, MeshParams, cloud_from_height};
