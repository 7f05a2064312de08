//! The stages of `reconstruct`, `replay` and `acquire` as the user sees them: on a terminal a
//! progress display (what runs now, for how long, a bar for tilt steps and dense levels, and
//! a line per finished stage with its time); elsewhere — a pipe, a file, the journal,
//! `TERM=dumb`, JSON logs — one log line per finished stage with its time.
//!
//! The terminal is one per process: while a display is shown, the text log writes through it
//! ([`TerminalLog`]) so that log lines and the display do not overwrite each other.

use std::io::Write;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use tracing::info;
use tracing_subscriber::fmt::MakeWriter;

use crate::progress::{Stage, StageClock};

/// The display shown on the terminal now, if any: the log writes around it.
static SHOWN: Mutex<Option<ProgressBar>> = Mutex::new(None);

/// Shows the stages it is told, on a terminal or as log lines.
#[derive(Debug)]
pub struct StageDisplay {
    clock: StageClock,
    bar: Option<ProgressBar>,
}

impl StageDisplay {
    /// A progress display on stderr when the log there is text on a terminal
    /// ([`super::logging::terminal`]), else a log line per stage.
    #[must_use]
    pub fn on_stderr() -> Self {
        if !super::logging::terminal() {
            return Self::log_lines();
        }
        let bar = ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr());
        bar.set_style(spinner_style());
        bar.enable_steady_tick(Duration::from_millis(120));
        *SHOWN.lock().unwrap_or_else(|e| e.into_inner()) = Some(bar.clone());
        Self {
            clock: StageClock::default(),
            bar: Some(bar),
        }
    }

    /// A log line per finished stage with its time (the daemon: the journal and the record).
    #[must_use]
    pub fn log_lines() -> Self {
        Self {
            clock: StageClock::default(),
            bar: None,
        }
    }

    /// `stage` begins now: the one before it ends.
    pub fn observe(&self, stage: Stage) {
        if let Some((ended, took)) = self.clock.start(stage, Instant::now()) {
            self.ended(ended, took);
        }
        if let Some(bar) = &self.bar {
            match stage.count() {
                Some((k, n)) => {
                    bar.set_style(bar_style());
                    bar.set_length(n as u64);
                    bar.set_position(k.saturating_sub(1) as u64);
                }
                None => bar.set_style(spinner_style()),
            }
            bar.set_message(stage.to_string());
            bar.reset_elapsed();
        }
    }

    /// The last stage ends — with its time when the work `completed`; a stage that failed
    /// gets no line, its error says what happened — and the display goes away.
    pub fn finish(&self, completed: bool) {
        if let Some((ended, took)) = self.clock.finish(Instant::now())
            && completed
        {
            self.ended(ended, took);
        }
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
            SHOWN.lock().unwrap_or_else(|e| e.into_inner()).take();
        }
    }

    /// A stage ended after `took`. The tilt series logs its own steps (with their figures),
    /// so only the reconstruction's stages get a line here.
    fn ended(&self, stage: Stage, took: Duration) {
        if stage.is_acquisition() {
            return;
        }
        let seconds = crate::numbers::secs(took.as_secs_f64());
        match &self.bar {
            Some(bar) => bar.println(format!("  {stage}: {seconds:.3} s")),
            None => info!(stage = stage.name(), seconds, "{stage}: {seconds:.3} s"),
        }
    }
}

impl Drop for StageDisplay {
    fn drop(&mut self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
            SHOWN.lock().unwrap_or_else(|e| e.into_inner()).take();
        }
    }
}

fn spinner_style() -> ProgressStyle {
    ProgressStyle::with_template("{spinner} {msg} ({elapsed})")
        .unwrap_or_else(|_| ProgressStyle::default_spinner())
}

fn bar_style() -> ProgressStyle {
    ProgressStyle::with_template("{spinner} {msg} [{bar:24}] ({elapsed})")
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> ")
}

/// The text log's writer on a terminal: each event is written whole, with the display
/// (if one is shown) taken away meanwhile.
#[derive(Debug, Clone, Copy, Default)]
pub struct TerminalLog;

impl<'a> MakeWriter<'a> for TerminalLog {
    type Writer = EventBuffer;

    fn make_writer(&'a self) -> Self::Writer {
        EventBuffer(Vec::new())
    }
}

/// One log event, written to stderr when dropped.
#[derive(Debug)]
pub struct EventBuffer(Vec<u8>);

impl Write for EventBuffer {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Drop for EventBuffer {
    fn drop(&mut self) {
        let shown = SHOWN.lock().unwrap_or_else(|e| e.into_inner()).clone();
        let write = || {
            let _ = std::io::stderr().write_all(&self.0);
        };
        match shown {
            Some(bar) => bar.suspend(write),
            None => write(),
        }
    }
}
