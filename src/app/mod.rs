//! Commands of the `sdsem` binary as library functions (anyhow at this edge only).

pub mod flow;
pub mod output;
pub mod reconstruct;
pub mod rectify;
pub mod replay;
