//! The daemon's settings (`[daemon]` in sdsem's configuration file).

use std::path::PathBuf;
use std::time::Duration;

use serde::{Deserialize, Serialize};

/// How the service keeps its queue, paces itself and stops. Durations are seconds.
///
/// | key | default | effect |
/// | --- | --- | --- |
/// | `spool_dir` | `/var/lib/sdsem/spool` | the job queue on disk (`sdsem daemon/submit/status --spool` overrides it) |
/// | `min_free_gib` | 2 | a job does not start while the filesystem of `run.output_dir` has less free space; it waits, queued |
/// | `disk_recheck_s` | 60 | how often free space is checked again while waiting for it |
/// | `poll_interval_s` | 2 | how often an idle daemon looks for newly queued jobs |
/// | `link_check_timeout_s` | 20 | bound on one check (and reconnection) of the stage and imaging links |
/// | `backoff_initial_s` | 1 | wait after the first failed link check; doubles after each further failure |
/// | `backoff_max_s` | 60 | the longest wait between two link checks |
/// | `stop_timeout_s` | 12 | time a running job has, after SIGTERM, to bring the stage to its safe tilt and finish its record; ≤ 14 so the daemon exits within 15 s |
/// | `stall_timeout_s` | 1800 | a running job that reports no progress for this long is cancelled and fails; 0 disables |
/// | `min_step_deg` | 0.1 | the step floor: a job with a smaller tilt step is refused |
/// | `max_steps` | 300 | a job with more tilt steps is refused |
/// | `max_job_minutes` | 240 | a job whose acquisition is estimated longer (tilt moves and frames) is refused |
/// | `after_crash` | `move` | after an unclean end, a stage found off its safe tilt is moved there (`move`) or left for an operator (`wait`: no job runs until `sdsem daemon --ack`) |
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DaemonConfig {
    pub spool_dir: PathBuf,
    pub min_free_gib: f64,
    pub disk_recheck_s: f64,
    pub poll_interval_s: f64,
    pub link_check_timeout_s: f64,
    pub backoff_initial_s: f64,
    pub backoff_max_s: f64,
    pub stop_timeout_s: f64,
    pub stall_timeout_s: f64,
    pub min_step_deg: f64,
    pub max_steps: u32,
    pub max_job_minutes: f64,
    pub after_crash: AfterCrash,
}

/// What the daemon does with a stage found off its safe tilt after an unclean end.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AfterCrash {
    /// Move it to `stage.safe_tilt_deg` before anything else.
    Move,
    /// Run no job until an operator acknowledges (`sdsem daemon --ack`), then move it.
    Wait,
}

/// Default spool: inside systemd's `StateDirectory=sdsem`.
pub const DEFAULT_SPOOL_DIR: &str = "/var/lib/sdsem/spool";

/// The daemon promises to exit within this long after SIGTERM (the unit's
/// `TimeoutStopSec` leaves room above it).
pub const STOP_PROMISE: Duration = Duration::from_secs(15);

impl Default for DaemonConfig {
    fn default() -> Self {
        Self {
            spool_dir: PathBuf::from(DEFAULT_SPOOL_DIR),
            min_free_gib: 2.0,
            disk_recheck_s: 60.0,
            poll_interval_s: 2.0,
            link_check_timeout_s: 20.0,
            backoff_initial_s: 1.0,
            backoff_max_s: 60.0,
            stop_timeout_s: 12.0,
            stall_timeout_s: 1800.0,
            min_step_deg: 0.1,
            max_steps: 300,
            max_job_minutes: 240.0,
            after_crash: AfterCrash::Move,
        }
    }
}

impl DaemonConfig {
    /// Checks every value, naming the first wrong key.
    ///
    /// # Errors
    /// A message naming the key, the value and what is accepted.
    pub fn validate(&self) -> Result<(), String> {
        if self.spool_dir.as_os_str().is_empty() {
            return Err(
                "daemon.spool_dir is empty: give a directory, e.g. /var/lib/sdsem/spool".into(),
            );
        }
        for (key, v) in [
            ("daemon.disk_recheck_s", self.disk_recheck_s),
            ("daemon.poll_interval_s", self.poll_interval_s),
            ("daemon.link_check_timeout_s", self.link_check_timeout_s),
            ("daemon.backoff_initial_s", self.backoff_initial_s),
            ("daemon.stop_timeout_s", self.stop_timeout_s),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{key} = {v} must be a positive number of seconds"));
            }
        }
        for (key, v) in [
            ("daemon.min_step_deg", self.min_step_deg),
            ("daemon.max_job_minutes", self.max_job_minutes),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{key} = {v} must be a positive number"));
            }
        }
        if self.max_steps == 0 {
            return Err("daemon.max_steps = 0 must be at least 1".into());
        }
        for (key, v) in [
            ("daemon.min_free_gib", self.min_free_gib),
            ("daemon.stall_timeout_s", self.stall_timeout_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{key} = {v} must be a number ≥ 0"));
            }
        }
        if !(self.backoff_max_s.is_finite() && self.backoff_max_s >= self.backoff_initial_s) {
            return Err(format!(
                "daemon.backoff_max_s = {} must be at least daemon.backoff_initial_s = {}",
                self.backoff_max_s, self.backoff_initial_s
            ));
        }
        let limit = STOP_PROMISE.as_secs_f64() - 1.0;
        if self.stop_timeout_s > limit {
            return Err(format!(
                "daemon.stop_timeout_s = {} must be at most {limit} s: the daemon promises to \
                 exit within {} s of SIGTERM",
                self.stop_timeout_s,
                STOP_PROMISE.as_secs()
            ));
        }
        Ok(())
    }

    /// Minimum free space in bytes.
    #[must_use]
    pub fn min_free_bytes(&self) -> u64 {
        // Validated finite and ≥ 0; `as` saturates anything absurd.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let bytes = (self.min_free_gib * GIB) as u64;
        bytes
    }

    #[must_use]
    pub fn disk_recheck(&self) -> Duration {
        secs(self.disk_recheck_s)
    }

    #[must_use]
    pub fn poll_interval(&self) -> Duration {
        secs(self.poll_interval_s)
    }

    #[must_use]
    pub fn link_check_timeout(&self) -> Duration {
        secs(self.link_check_timeout_s)
    }

    #[must_use]
    pub fn stop_timeout(&self) -> Duration {
        secs(self.stop_timeout_s)
    }

    /// `None` when stall detection is off.
    #[must_use]
    pub fn stall_timeout(&self) -> Option<Duration> {
        (self.stall_timeout_s > 0.0).then(|| secs(self.stall_timeout_s))
    }

    /// The wait before link check number `failures + 1`, after `failures`
    /// consecutive failures (≥ 1): initial × 2^(failures − 1), capped.
    #[must_use]
    pub fn backoff(&self, failures: u32) -> Duration {
        let exponent = i32::try_from(failures.saturating_sub(1).min(62)).unwrap_or(62);
        secs((self.backoff_initial_s * 2f64.powi(exponent)).min(self.backoff_max_s))
    }
}

/// Bytes in a GiB.
pub const GIB: f64 = 1024.0 * 1024.0 * 1024.0;

fn secs(s: f64) -> Duration {
    Duration::try_from_secs_f64(s.max(0.0)).unwrap_or(Duration::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_partial_tables_keep_them() {
        DaemonConfig::default().validate().unwrap();
        let c: DaemonConfig =
            toml::from_str("spool_dir = \"/tmp/s\"\nmin_free_gib = 0.5\n").unwrap();
        assert_eq!(c.spool_dir, PathBuf::from("/tmp/s"));
        assert_eq!(c.min_free_bytes(), 512 * 1024 * 1024);
        assert_eq!(c.stop_timeout_s, 12.0);
        let err = toml::from_str::<DaemonConfig>("spool = \"/x\"\n").unwrap_err();
        assert!(err.to_string().contains("spool"), "{err}");
    }

    #[test]
    fn backoff_doubles_then_caps() {
        let c = DaemonConfig {
            backoff_initial_s: 1.0,
            backoff_max_s: 10.0,
            ..DaemonConfig::default()
        };
        let waits: Vec<u64> = (1..=6).map(|n| c.backoff(n).as_secs()).collect();
        assert_eq!(waits, [1, 2, 4, 8, 10, 10]);
        assert_eq!(c.backoff(u32::MAX).as_secs(), 10);
    }

    #[test]
    fn stop_timeout_must_fit_the_promise() {
        let c = DaemonConfig {
            stop_timeout_s: 20.0,
            ..DaemonConfig::default()
        };
        let err = c.validate().unwrap_err();
        assert!(err.contains("daemon.stop_timeout_s = 20"), "{err}");
        let c = DaemonConfig {
            backoff_max_s: 0.5,
            ..DaemonConfig::default()
        };
        assert!(c.validate().unwrap_err().contains("daemon.backoff_max_s"));
        let c = DaemonConfig {
            min_step_deg: f64::NAN,
            ..DaemonConfig::default()
        };
        assert!(
            c.validate()
                .unwrap_err()
                .contains("daemon.min_step_deg = NaN")
        );
        let c: DaemonConfig = toml::from_str("after_crash = \"wait\"\n").unwrap();
        assert_eq!(c.after_crash, AfterCrash::Wait);
        assert!(toml::from_str::<DaemonConfig>("after_crash = \"pray\"\n").is_err());
    }
}
