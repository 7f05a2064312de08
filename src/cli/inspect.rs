//! `sdsem inspect RUN.mcap`: what a record holds — topics, counts, frames,
//! outcome — also for a record cut short by a crash.

use std::path::Path;
use std::process::ExitCode;

use crate::record::{format_inspection, read_summary};

pub fn run(path: &Path, json: bool) -> anyhow::Result<ExitCode> {
    // Every ReadError names the file already.
    let inspection = read_summary(path)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&inspection)?);
    } else {
        print!("{}", format_inspection(&inspection));
    }
    Ok(ExitCode::SUCCESS)
}
