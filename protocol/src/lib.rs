//! Sans-IO wire protocols of sdsem.
//!
//! Both sides of every link live here, as typed values and byte parsers that do
//! no I/O, so the driver in `sdsem` and the simulator in `sdsem-sim` cannot
//! drift apart:
//!
//! - [`gcs`]: the PI GCS 2.0 subset spoken by the stage controller.
//! - [`remcon`]: Zeiss SmartSEM RemCon32, the SEM's own stage (and store triggers).
//! - [`sem`]: the line protocol of the SEM imaging link.
//! - [`sharksem`]: TESCAN SharkSEM remote control (binary, TCP): stage and imaging of TESCAN SEMs.

pub mod gcs;
pub mod remcon;
pub mod sem;
pub mod sharksem;
