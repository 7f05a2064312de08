//! Logging to stderr — readable on a terminal, JSON lines when not (journald,
//! files), so a headless lab PC's logs can be searched by field — and into the
//! `/log` topic of the run being recorded.

use std::io::IsTerminal;
use std::sync::OnceLock;

use tracing::Level;
use tracing_subscriber::{EnvFilter, Layer, fmt, prelude::*};

use crate::config::LogFormat;
use crate::record::{RecordLogSwitch, record_log_layer};

static RECORD_LOGS: OnceLock<RecordLogSwitch> = OnceLock::new();

/// Installs the global subscriber once. `RUST_LOG` beats `filter`.
pub fn init(format: LogFormat, filter: Option<&str>) {
    let filter = EnvFilter::try_from_default_env()
        .or_else(|_| EnvFilter::try_new(filter.unwrap_or("info")))
        .unwrap_or_else(|_| EnvFilter::new("info"));
    let json = match format {
        LogFormat::Json => true,
        LogFormat::Text => false,
        LogFormat::Auto => !std::io::stderr().is_terminal(),
    };
    let stderr = if json {
        fmt::layer().json().with_writer(std::io::stderr).boxed()
    } else {
        fmt::layer()
            .with_target(false)
            .with_ansi(colours())
            .with_writer(std::io::stderr)
            .boxed()
    };
    let (record_layer, switch) = record_log_layer(Level::INFO);
    let installed = tracing_subscriber::registry()
        .with(stderr.with_filter(filter))
        .with(record_layer)
        .try_init()
        .is_ok();
    if installed {
        let _ = RECORD_LOGS.set(switch);
    }
}

/// Whether the text log is coloured, decided as clap decides it for the help: a non-empty
/// `NO_COLOR` and `CLICOLOR=0` turn colours off, `CLICOLOR_FORCE` on, else a terminal.
fn colours() -> bool {
    anstream::AutoStream::choice(&std::io::stderr()) != anstream::ColorChoice::Never
}

/// The switch that sends log events into the record of the current run.
pub fn record_logs() -> Option<&'static RecordLogSwitch> {
    RECORD_LOGS.get()
}
