//! Logging to stderr — readable on a terminal, JSON lines when not (files, pipes), and under
//! systemd readable lines with syslog priorities for the journal — and into the `/log` topic
//! of the run being recorded.
//!
//! When stderr is the journal's stream (`$JOURNAL_STREAM` names its device and inode,
//! systemd.exec(5)), every line starts with `<N>`, the syslog level of sd-daemon(3)
//! (error 3, warning 4, info 6, debug 7), which journald turns into the entry's priority:
//! `journalctl -u sdsem -p err` lists the failures, `systemctl status sdsem` shows plain lines.

use std::io::IsTerminal;
use std::os::fd::AsFd;
use std::sync::OnceLock;

use tracing::{Event, Level, Subscriber};
use tracing_subscriber::fmt::format::{DefaultFields, JsonFields, Writer};
use tracing_subscriber::fmt::{self, FmtContext, FormatEvent, FormatFields};
use tracing_subscriber::registry::LookupSpan;
use tracing_subscriber::{EnvFilter, Layer, prelude::*};

use crate::config::LogFormat;
use crate::record::{RecordLogSwitch, record_log_layer};

static RECORD_LOGS: OnceLock<RecordLogSwitch> = OnceLock::new();

/// Whether the log on stderr is text on a terminal that can show a progress display.
static TERMINAL: OnceLock<bool> = OnceLock::new();

/// Installs the global subscriber once. `RUST_LOG` beats `filter`.
pub fn init(format: LogFormat, filter: Option<&str>) {
    let filter = EnvFilter::try_from_default_env()
        .or_else(|_| EnvFilter::try_new(filter.unwrap_or("info")))
        .unwrap_or_else(|_| EnvFilter::new("info"));
    let journal = stderr_is_journal();
    let json = match format {
        LogFormat::Json => true,
        LogFormat::Text => false,
        LogFormat::Auto => !journal && !std::io::stderr().is_terminal(),
    };
    let stderr = if json {
        fmt::layer()
            .fmt_fields(JsonFields::new())
            .event_format(Prefixed {
                journal,
                inner: fmt::format().json(),
            })
            .with_writer(std::io::stderr)
            .boxed()
    } else if journal {
        // The journal stamps each line itself.
        fmt::layer()
            .fmt_fields(DefaultFields::new())
            .event_format(Prefixed {
                journal,
                inner: fmt::format()
                    .without_time()
                    .with_target(false)
                    .with_ansi(false),
            })
            .with_writer(std::io::stderr)
            .boxed()
    } else if std::io::stderr().is_terminal() {
        // Around the progress display, if one is shown (`super::progress`).
        fmt::layer()
            .with_target(false)
            .with_ansi(colours())
            .with_writer(super::progress::TerminalLog)
            .boxed()
    } else {
        fmt::layer()
            .with_target(false)
            .with_ansi(colours())
            .with_writer(std::io::stderr)
            .boxed()
    };
    let _ = TERMINAL.set(
        !json
            && !journal
            && std::io::stderr().is_terminal()
            && std::env::var_os("TERM").is_none_or(|t| t != "dumb"),
    );
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

/// True when the log on stderr is text on a terminal (not the journal, not `TERM=dumb`): a
/// progress display can be shown there; elsewhere the stages are log lines.
pub fn terminal() -> bool {
    TERMINAL.get().copied().unwrap_or(false)
}

/// The switch that sends log events into the record of the current run.
pub fn record_logs() -> Option<&'static RecordLogSwitch> {
    RECORD_LOGS.get()
}

/// `<3>` when stderr is the journal (so `main`'s last error line has error priority), else "".
#[must_use]
pub fn journal_error_prefix() -> &'static str {
    if stderr_is_journal() { "<3>" } else { "" }
}

/// True when stderr is the stream systemd connected to the journal: `$JOURNAL_STREAM`
/// (`DEVICE:INODE`) names the same file as stderr's `fstat`.
fn stderr_is_journal() -> bool {
    let Ok(value) = std::env::var("JOURNAL_STREAM") else {
        return false;
    };
    let Ok(stat) = rustix::fs::fstat(std::io::stderr().as_fd()) else {
        return false;
    };
    is_same_stream(&value, stat.st_dev, stat.st_ino)
}

fn is_same_stream(journal_stream: &str, dev: u64, ino: u64) -> bool {
    journal_stream
        .split_once(':')
        .and_then(|(d, i)| Some((d.parse::<u64>().ok()?, i.parse::<u64>().ok()?)))
        == Some((dev, ino))
}

/// The syslog level of sd-daemon(3) for a tracing level.
fn syslog_level(level: Level) -> u8 {
    match level {
        Level::ERROR => 3,
        Level::WARN => 4,
        Level::INFO => 6,
        _ => 7,
    }
}

/// An event format that starts each line with `<N>` when writing to the journal.
struct Prefixed<F> {
    journal: bool,
    inner: F,
}

impl<S, N, F> FormatEvent<S, N> for Prefixed<F>
where
    S: Subscriber + for<'a> LookupSpan<'a>,
    N: for<'a> FormatFields<'a> + 'static,
    F: FormatEvent<S, N>,
{
    fn format_event(
        &self,
        ctx: &FmtContext<'_, S, N>,
        mut writer: Writer<'_>,
        event: &Event<'_>,
    ) -> std::fmt::Result {
        if self.journal {
            write!(writer, "<{}>", syslog_level(*event.metadata().level()))?;
        }
        self.inner.format_event(ctx, writer, event)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_journal_stream_is_recognised_by_device_and_inode() {
        assert!(is_same_stream("8:1234", 8, 1234));
        assert!(!is_same_stream("8:1234", 8, 1235));
        assert!(!is_same_stream("garbage", 8, 1234));
        assert_eq!(syslog_level(Level::ERROR), 3);
        assert_eq!(syslog_level(Level::WARN), 4);
        assert_eq!(syslog_level(Level::INFO), 6);
        assert_eq!(syslog_level(Level::DEBUG), 7);
    }
}
