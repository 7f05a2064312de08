//! `sdsem check-config FILE`: load every layer, validate, print the result.

use std::path::Path;
use std::process::ExitCode;

use crate::config::Config;

pub fn run(file: &Path, overrides: &[String], quiet: bool) -> anyhow::Result<ExitCode> {
    // The error names the layer at fault: the file, an SDSEM_ variable or a --set.
    let config = Config::load(Some(file), overrides)?;
    if !quiet {
        println!("# {}: valid. Effective configuration:", file.display());
        print!("{}", config.to_toml());
    }
    Ok(ExitCode::SUCCESS)
}
