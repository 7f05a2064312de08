//! The tilt-series acquisition: a pure state machine ([`machine`]) planned by
//! [`plan`], and the [`runner`] that performs its actions with the instruments.

pub mod cancel;
pub mod instruments;
pub mod job;
pub mod machine;
pub mod plan;
pub mod probe;
pub mod run_dir;
pub mod runner;
pub mod stage_trigger;

pub use cancel::{Cancel, CancelHandle, cancel_pair};
pub use instruments::{Instruments, InstrumentsError, RunObserver};
pub use job::{JobError, JobReport, RunHooks, run_job};
pub use machine::{Action, Event, FrameRole, Outcome, Series, Tracked, TrackingConfig};
pub use plan::{PlanError, SeriesConfig, SeriesPlan};
pub use probe::{ProbeReport, probe};
pub use run_dir::{NameError, RunDir, RunDirError, RunName};
pub use runner::{Captured, SeriesContext, SeriesRecord, SeriesTimings, TrackingStep, run_series};
