//! `sdsem probe --config FILE [--json]`: what the stage and the SEM say they are, where the
//! stage is and its limits, as a table or JSON; moves nothing.

use std::process::ExitCode;

use anyhow::Context;

use super::ConfigArgs;
use crate::acquisition::probe;

pub fn run(args: &ConfigArgs, json: bool) -> anyhow::Result<ExitCode> {
    let config = args.load()?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let report = runtime.block_on(probe(&config)).context("probe failed")?;
    if json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", report.table());
    }
    Ok(ExitCode::SUCCESS)
}
