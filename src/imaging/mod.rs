//! The SEM side: grabbing frames, and reading micrographs with their metadata.

pub mod file;
mod file_tiff;
pub mod metadata;
