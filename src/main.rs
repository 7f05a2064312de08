//! `sdsem` command line: parse, initialise logging, run, and turn the result
//! into an exit code — the only place where that happens.

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    let cli = sdsem::cli::Cli::parse();
    if !cli.command.outlives_its_reader() {
        end_quietly_on_broken_pipe();
    }
    match sdsem::cli::run(cli) {
        Ok(code) => code,
        Err(err) => {
            // One line that names the cause chain (error priority in the journal); details went to the log.
            eprintln!(
                "{}error: {}",
                sdsem::cli::journal_error_prefix(),
                sdsem::cli::error_line(&err)
            );
            ExitCode::FAILURE
        }
    }
}

/// Ends the process by SIGPIPE, as Unix filters do, when the reader of its output goes away
/// (`sdsem check-config … | head -1`), instead of Rust's default for a binary: SIGPIPE
/// ignored and `println!` panicking on the broken pipe.
fn end_quietly_on_broken_pipe() {
    // SAFETY: `signal` with SIG_DFL installs no handler; called before any other thread.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
