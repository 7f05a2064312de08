//! The SEM side: grabbing frames, and reading micrographs with their metadata.
