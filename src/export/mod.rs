//! Writers (and readers, for verification) of the result files.
pub mod flo;
