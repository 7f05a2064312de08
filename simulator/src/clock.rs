//! Simulated time: an input to the device models, never read from the system directly.

use std::fmt::Debug;
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant};

/// The simulated time, seconds since the simulator started.
pub trait Clock: Send + Sync + Debug {
    /// Simulated seconds now; never decreases.
    fn now_s(&self) -> f64;
}

/// Real time scaled: `time_scale` real seconds per simulated second
/// (0.01 ⇒ the simulated instruments run 100× faster than real time).
#[derive(Debug)]
pub struct ScaledClock {
    origin: Instant,
    time_scale: f64,
}

impl ScaledClock {
    /// Starts now. `time_scale` must be positive (checked by `SimConfig::validate`).
    pub fn new(time_scale: f64) -> Self {
        Self {
            origin: Instant::now(),
            time_scale,
        }
    }

    /// Real seconds per simulated second.
    pub fn time_scale(&self) -> f64 {
        self.time_scale
    }

    /// How long a simulated duration lasts in real time.
    pub fn real_duration(&self, sim_s: f64) -> Duration {
        Duration::from_secs_f64((sim_s * self.time_scale).max(0.0))
    }
}

impl Clock for ScaledClock {
    fn now_s(&self) -> f64 {
        self.origin.elapsed().as_secs_f64() / self.time_scale
    }
}

/// A clock that moves only when told to: for unit tests.
#[derive(Debug, Default)]
pub struct ManualClock {
    now_s: Mutex<f64>,
}

impl ManualClock {
    /// Starts at 0 s.
    pub fn new() -> Self {
        Self::default()
    }

    /// Moves time forward by `dt_s` seconds (negative values are ignored).
    pub fn advance(&self, dt_s: f64) {
        let mut now = self.now_s.lock().unwrap_or_else(PoisonError::into_inner);
        *now += dt_s.max(0.0);
    }
}

impl Clock for ManualClock {
    fn now_s(&self) -> f64 {
        *self.now_s.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manual_clock_moves_only_forward() {
        let c = ManualClock::new();
        assert_eq!(c.now_s(), 0.0);
        c.advance(1.5);
        c.advance(-3.0);
        assert_eq!(c.now_s(), 1.5);
    }

    #[test]
    fn scaled_clock_runs_faster_with_a_small_scale() {
        let c = ScaledClock::new(0.001);
        assert_eq!(c.real_duration(2.0), Duration::from_millis(2));
        std::thread::sleep(Duration::from_millis(5));
        // 5 ms real ≥ 5 simulated seconds.
        assert!(c.now_s() >= 5.0, "{}", c.now_s());
    }
}
