//! The tilt-series acquisition: a pure state machine ([`machine`]) planned by
//! [`plan`], and the runner that performs its actions with the instruments.

pub mod machine;
pub mod plan;

pub use machine::{Action, Event, FrameRole, Outcome, Series, Tracked, TrackingConfig};
pub use plan::{PlanError, SeriesConfig, SeriesPlan};
