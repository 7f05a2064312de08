//! `sdsem inspect RUN.mcap`: what a record holds — topics, counts, frames,
//! outcome — also for a record cut short by a crash.

use std::path::Path;
use std::process::ExitCode;

use anyhow::Context;

use crate::record::{format_inspection, read_summary};

pub fn run(path: &Path, json: bool) -> anyhow::Result<ExitCode> {
    let inspection =
        read_summary(path).with_context(|| format!("cannot read the record {}", path.display()))?;
    if json {
        println!("{}", serde_json::to_string_pretty(&inspection)?);
    } else {
        print!("{}", format_inspection(&inspection));
    }
    Ok(ExitCode::SUCCESS)
}
