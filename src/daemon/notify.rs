//! What the daemon tells its service manager: READY, STATUS, WATCHDOG,
//! RELOADING, STOPPING (sd_notify(3)), behind a trait so tests can record it.

use std::time::Duration;

/// One notification to the service manager.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Notice {
    /// Start-up is complete (links checked).
    Ready,
    /// What the daemon is doing, in one line.
    Status(String),
    /// The main loop is alive and healthy.
    Watchdog,
    /// A configuration reload begins (`READY` follows when it is done).
    Reloading,
    /// Shutdown begins.
    Stopping,
}

/// Receives the daemon's notifications.
pub trait Notifier {
    fn notify(&mut self, notice: Notice);
}

/// Sends notifications to systemd over `$NOTIFY_SOCKET`; does nothing when
/// the variable is unset (not started by systemd).
#[derive(Debug, Default)]
pub struct SystemdNotifier {
    warned: bool,
}

impl SystemdNotifier {
    /// How often to send `WATCHDOG=1`: half of `WatchdogSec=` (from
    /// `$WATCHDOG_USEC`), as sd_watchdog_enabled(3) advises; `None` when the
    /// service has no watchdog.
    #[must_use]
    pub fn watchdog_interval() -> Option<Duration> {
        sd_notify::watchdog_enabled()
            .filter(|d| !d.is_zero())
            .map(|d| d / 2)
    }
}

impl Notifier for SystemdNotifier {
    fn notify(&mut self, notice: Notice) {
        use sd_notify::NotifyState;
        let monotonic;
        let states: Vec<NotifyState<'_>> = match &notice {
            Notice::Ready => vec![NotifyState::Ready],
            Notice::Status(s) => vec![NotifyState::Status(s)],
            Notice::Watchdog => vec![NotifyState::Watchdog],
            Notice::Reloading => {
                // systemd ≥ 253 wants the reload's start time beside RELOADING=1.
                monotonic = NotifyState::monotonic_usec_now().ok();
                let mut v = vec![NotifyState::Reloading];
                v.extend(monotonic);
                v
            }
            Notice::Stopping => vec![NotifyState::Stopping],
        };
        if let Err(e) = sd_notify::notify(&states)
            && !self.warned
        {
            // Logged once: a broken notify socket would otherwise flood the journal.
            tracing::warn!(error = %e, "cannot notify the service manager");
            self.warned = true;
        }
    }
}
