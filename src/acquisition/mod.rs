//! The tilt-series acquisition: a pure state machine, tracking and re-centring.
