//! SIFT flow (Liu, Yuen, Torralba, PAMI 2011): dense correspondence by
//! matching dense SIFT descriptors under the energy of eq. (10), minimised by
//! dual-layer belief propagation, coarse to fine.

pub mod bp;
pub mod energy;
