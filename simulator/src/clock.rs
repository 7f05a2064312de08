//! Time in the simulator: one [`Clock`] for every simulated instrument.
//!
//! Three kinds of time meet in a simulator, and each has one source here:
//!
//! | what | unit | used for |
//! | --- | --- | --- |
//! | simulated time, [`Clock::now_s`] | seconds since the simulator started | stage motion and settling, specimen drift |
//! | wall-clock time, [`Clock::unix_ns`] | ns since the Unix epoch | timestamps a client reads (scan start and end of a frame) |
//! | waiting, [`Clock::sleep_until`] | simulated seconds | the scan time of a frame |
//!
//! `time_scale` is **real seconds per simulated second** everywhere: 0.01 makes
//! the instruments 100× faster than real time (a 1° tilt step at 1°/s lasts
//! 10 ms, a 12 s scan 0.12 s), 1 is real time. Only link-level delays (the
//! late-reply fault) are in real seconds, because they exist to exercise the
//! client's real timeouts.
//!
//! [`ScaledClock`] runs on the system clock; [`ManualClock`] moves only when a
//! test advances it or the simulator waits on it, so tests never sleep.

use std::fmt::Debug;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// How often a long wait looks at its cancel flag, real time.
const CANCEL_POLL: Duration = Duration::from_millis(50);

/// The simulator's time: simulated seconds, wall-clock timestamps, and waiting.
pub trait Clock: Send + Sync + Debug {
    /// Simulated seconds since the simulator started; never decreases.
    fn now_s(&self) -> f64;

    /// Wall-clock time now, ns since the Unix epoch; never decreases. On a
    /// [`ScaledClock`] this is real time (a scan of 12 simulated seconds at
    /// `time_scale` 0.01 spans 0.12 s of timestamps).
    fn unix_ns(&self) -> u64;

    /// Blocks until the simulated time reaches `until_s` (returns true), or
    /// until `cancel` is set (returns false, possibly early).
    fn sleep_until(&self, until_s: f64, cancel: &AtomicBool) -> bool;
}

fn system_unix_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

/// Real time scaled: `time_scale` real seconds per simulated second.
#[derive(Debug)]
pub struct ScaledClock {
    origin: Instant,
    origin_unix_ns: u64,
    time_scale: f64,
}

impl ScaledClock {
    /// Starts now. `time_scale` must be positive and finite (checked by
    /// `SimConfig::validate`; other values are replaced by 1).
    #[must_use]
    pub fn new(time_scale: f64) -> Self {
        let time_scale = if time_scale.is_finite() && time_scale > 0.0 {
            time_scale
        } else {
            1.0
        };
        Self {
            origin: Instant::now(),
            origin_unix_ns: system_unix_ns(),
            time_scale,
        }
    }

    /// Real seconds per simulated second.
    #[must_use]
    pub fn time_scale(&self) -> f64 {
        self.time_scale
    }

    /// How long a simulated duration lasts in real time.
    #[must_use]
    pub fn real_duration(&self, sim_s: f64) -> Duration {
        Duration::try_from_secs_f64(sim_s * self.time_scale).unwrap_or(Duration::ZERO)
    }
}

impl Clock for ScaledClock {
    fn now_s(&self) -> f64 {
        self.origin.elapsed().as_secs_f64() / self.time_scale
    }

    /// The system's wall clock at start, advanced by the monotonic clock, so
    /// that timestamps never run backwards when the system clock is stepped.
    fn unix_ns(&self) -> u64 {
        let elapsed = u64::try_from(self.origin.elapsed().as_nanos()).unwrap_or(u64::MAX);
        self.origin_unix_ns.saturating_add(elapsed)
    }

    fn sleep_until(&self, until_s: f64, cancel: &AtomicBool) -> bool {
        loop {
            let rest = self.real_duration(until_s - self.now_s());
            if rest.is_zero() {
                return true;
            }
            if cancel.load(Ordering::Relaxed) {
                return false;
            }
            std::thread::sleep(rest.min(CANCEL_POLL));
        }
    }
}

/// A clock that moves only when told to: for tests.
///
/// [`Clock::sleep_until`] advances it at once, so a frame's scan "takes" its
/// simulated time without any real wait, and everything else on the same
/// clock (the stage's motion) sees that time pass. Its wall clock starts at a
/// fixed instant and advances by `time_scale` × the simulated time, as a
/// [`ScaledClock`]'s would: timestamps are reproducible.
#[derive(Debug)]
pub struct ManualClock {
    now_s: Mutex<f64>,
    time_scale: f64,
}

impl Default for ManualClock {
    fn default() -> Self {
        Self::new()
    }
}

impl ManualClock {
    /// Wall-clock time at simulated time 0: 2024-01-01T00:00:00Z.
    pub const START_UNIX_NS: u64 = 1_704_067_200_000_000_000;

    /// Starts at 0 s, at real time (`time_scale` 1).
    #[must_use]
    pub fn new() -> Self {
        Self::with_time_scale(1.0)
    }

    /// Starts at 0 s; wall-clock timestamps advance `time_scale` seconds per
    /// simulated second (non-positive values are replaced by 1).
    #[must_use]
    pub fn with_time_scale(time_scale: f64) -> Self {
        Self {
            now_s: Mutex::new(0.0),
            time_scale: if time_scale.is_finite() && time_scale > 0.0 {
                time_scale
            } else {
                1.0
            },
        }
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

    fn unix_ns(&self) -> u64 {
        let real_ns = (self.now_s() * self.time_scale * 1e9).round();
        // Non-negative, and far below 2^64 ns for any test.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let real_ns = real_ns as u64;
        Self::START_UNIX_NS.saturating_add(real_ns)
    }

    fn sleep_until(&self, until_s: f64, cancel: &AtomicBool) -> bool {
        if cancel.load(Ordering::Relaxed) {
            return false;
        }
        let mut now = self.now_s.lock().unwrap_or_else(PoisonError::into_inner);
        if until_s.is_finite() && until_s > *now {
            *now = until_s;
        }
        true
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
    fn manual_clock_sleeps_instantly_and_scales_its_timestamps() {
        let c = ManualClock::with_time_scale(0.01);
        let go = AtomicBool::new(false);
        assert!(c.sleep_until(12.0, &go));
        assert_eq!(c.now_s(), 12.0);
        // 12 simulated seconds are 0.12 s of wall clock at this scale.
        assert_eq!(c.unix_ns() - ManualClock::START_UNIX_NS, 120_000_000);
        assert!(c.sleep_until(3.0, &go), "the past is already reached");
        assert_eq!(c.now_s(), 12.0);
        assert!(!c.sleep_until(20.0, &AtomicBool::new(true)));
        assert_eq!(c.now_s(), 12.0, "a cancelled wait does not advance");
    }

    #[test]
    fn scaled_clock_runs_faster_with_a_small_scale() {
        let c = ScaledClock::new(0.001);
        assert_eq!(c.real_duration(2.0), Duration::from_millis(2));
        assert_eq!(c.real_duration(-1.0), Duration::ZERO);
        let t0 = c.unix_ns();
        std::thread::sleep(Duration::from_millis(5));
        // 5 ms real ≥ 5 simulated seconds; timestamps advance in real time.
        assert!(c.now_s() >= 5.0, "{}", c.now_s());
        assert!(c.unix_ns() - t0 >= 5_000_000);
    }

    #[test]
    fn scaled_sleep_waits_the_scaled_time_and_can_be_cancelled() {
        let c = ScaledClock::new(0.01);
        let go = AtomicBool::new(false);
        let real = Instant::now();
        // 3 simulated seconds: at least 30 ms of real time.
        assert!(c.sleep_until(c.now_s() + 3.0, &go));
        assert!(real.elapsed() >= Duration::from_millis(30));
        let stop = AtomicBool::new(true);
        let real = Instant::now();
        assert!(!c.sleep_until(c.now_s() + 1e6, &stop));
        assert!(real.elapsed() < Duration::from_secs(5));
    }
}
