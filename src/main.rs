//! `sdsem` command line: parse, initialise logging, run, and turn the result
//! into an exit code — the only place where that happens.

use std::process::ExitCode;

use clap::Parser;

#[global_allocator]
static ALLOCATOR: sdsem::memory::PrefaultZeroed = sdsem::memory::PrefaultZeroed;

fn main() -> ExitCode {
    sdsem::memory::keep_large_buffers();
    let cli = sdsem::cli::Cli::parse();
    match sdsem::cli::run(cli) {
        Ok(code) => code,
        Err(err) => {
            // One line that names the cause chain (error priority in the journal); details went to the log.
            eprintln!("{}error: {err:#}", sdsem::cli::journal_error_prefix());
            ExitCode::FAILURE
        }
    }
}
