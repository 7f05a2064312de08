//! The MCAP record of a run: writer thread, Foxglove schemas, reading back.
