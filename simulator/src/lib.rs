//! `sdsem-sim`: a stage-and-SEM simulator that speaks the same protocols as the
//! real instruments, so `sdsem` runs and is tested without hardware.

pub mod pose;
pub mod render;
pub mod scene;
pub mod sem_server;
pub mod walk;
