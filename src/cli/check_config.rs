//! `sdsem check-config FILE`: load every layer, validate, print the result.

use std::path::Path;
use std::process::ExitCode;

use anyhow::Context;

use crate::config::Config;

pub fn run(file: &Path, overrides: &[String], quiet: bool) -> anyhow::Result<ExitCode> {
    let config = Config::load(Some(file), overrides)
        .with_context(|| format!("{} is not a valid sdsem configuration", file.display()))?;
    if !quiet {
        println!("# {}: valid. Effective configuration:", file.display());
        print!("{}", config.to_toml());
    }
    Ok(ExitCode::SUCCESS)
}
