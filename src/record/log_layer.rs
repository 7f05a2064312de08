//! A tracing [`Layer`] that forwards events to `/log` of the run being recorded.
//!
//! Install the layer once at start-up; attach a [`RecorderHandle`] through the
//! [`RecordLogSwitch`] when a run starts recording and detach it when the run ends:
//!
//! ```no_run
//! use tracing_subscriber::prelude::*;
//! let (layer, switch) = sdsem::record::record_log_layer(tracing::Level::INFO);
//! tracing_subscriber::registry().with(layer).init();
//! # let recorder = sdsem::record::Recorder::create("run.mcap", Default::default()).unwrap();
//! switch.attach(recorder.handle());
//! tracing::info!("tilting to 3°"); // lands in /log of run.mcap
//! switch.detach();
//! ```
//!
//! The layer never blocks the code that logs: when the recorder's channel is full the
//! message is dropped and counted (the count is recorded at `finish()`).

use std::fmt::Write as _;
use std::sync::{Arc, RwLock};
use std::time::{SystemTime, UNIX_EPOCH};

use tracing::field::{Field, Visit};
use tracing::{Event, Level, Subscriber};
use tracing_subscriber::layer::{Context, Layer};
use tracing_subscriber::registry::LookupSpan;

use super::entry::{Entry, LogLevel};
use super::recorder::RecorderHandle;

type Slot = Arc<RwLock<Option<RecorderHandle>>>;

/// Forwards tracing events at or above a level to the attached recorder's `/log`.
#[derive(Debug)]
pub struct RecordLogLayer {
    slot: Slot,
    max_level: Level,
}

/// Attaches and detaches the recorder that [`RecordLogLayer`] forwards to.
#[derive(Debug, Clone)]
pub struct RecordLogSwitch {
    slot: Slot,
}

/// A layer forwarding events as verbose as `max_level` (e.g. `Level::INFO`: INFO, WARN,
/// ERROR) and the switch that attaches it to a run's recorder.
#[must_use]
pub fn record_log_layer(max_level: Level) -> (RecordLogLayer, RecordLogSwitch) {
    let slot: Slot = Arc::new(RwLock::new(None));
    (
        RecordLogLayer {
            slot: Arc::clone(&slot),
            max_level,
        },
        RecordLogSwitch { slot },
    )
}

impl RecordLogSwitch {
    /// Forwards events to `handle` from now on (replacing any previous recorder).
    pub fn attach(&self, handle: RecorderHandle) {
        match self.slot.write() {
            Ok(mut slot) => *slot = Some(handle),
            Err(poisoned) => *poisoned.into_inner() = Some(handle),
        }
    }

    /// Stops forwarding; returns the recorder handle that was attached.
    pub fn detach(&self) -> Option<RecorderHandle> {
        match self.slot.write() {
            Ok(mut slot) => slot.take(),
            Err(poisoned) => poisoned.into_inner().take(),
        }
    }

    /// Whether a recorder is attached.
    #[must_use]
    pub fn is_attached(&self) -> bool {
        self.slot.read().map(|s| s.is_some()).unwrap_or(false)
    }
}

fn level_of(level: &Level) -> LogLevel {
    match *level {
        Level::ERROR => LogLevel::Error,
        Level::WARN => LogLevel::Warning,
        Level::INFO => LogLevel::Info,
        _ => LogLevel::Debug,
    }
}

/// Collects the `message` field and the other fields as `key=value`.
#[derive(Default)]
struct MessageVisitor {
    message: String,
    fields: String,
}

impl Visit for MessageVisitor {
    fn record_str(&mut self, field: &Field, value: &str) {
        if field.name() == "message" {
            self.message.push_str(value);
        } else {
            let _ = write!(self.fields, " {}={value:?}", field.name());
        }
    }

    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            let _ = write!(self.message, "{value:?}");
        } else {
            let _ = write!(self.fields, " {}={value:?}", field.name());
        }
    }
}

impl<S> Layer<S> for RecordLogLayer
where
    S: Subscriber + for<'a> LookupSpan<'a>,
{
    fn on_event(&self, event: &Event<'_>, ctx: Context<'_, S>) {
        let metadata = event.metadata();
        if *metadata.level() > self.max_level {
            return;
        }
        let Ok(slot) = self.slot.read() else {
            return;
        };
        let Some(handle) = slot.as_ref() else {
            return;
        };
        let mut visitor = MessageVisitor::default();
        event.record(&mut visitor);
        let mut text = String::new();
        if let Some(scope) = ctx.event_scope(event) {
            for span in scope.from_root() {
                text.push_str(span.name());
                text.push_str(": ");
            }
        }
        text.push_str(&visitor.message);
        text.push_str(&visitor.fields);
        let now_ns = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map(|d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
            .unwrap_or(0);
        if let Ok(entry) = Entry::log(
            now_ns,
            level_of(metadata.level()),
            &text,
            metadata.target(),
            metadata.file().unwrap_or(""),
            metadata.line().unwrap_or(0),
        ) {
            handle.try_send_log(entry);
        }
    }
}
