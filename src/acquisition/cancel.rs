//! Cancellation of a run: the operator (Ctrl-C, SIGTERM, the daemon stopping)
//! asks once, with a reason; every await point of the run can observe it.

use tokio::sync::watch;

/// The asking side. Cloneable; the first reason wins.
#[derive(Debug, Clone)]
pub struct CancelHandle(watch::Sender<Option<String>>);

/// The observing side, held by the run.
#[derive(Debug, Clone)]
pub struct Cancel(watch::Receiver<Option<String>>);

/// A new pair.
#[must_use]
pub fn cancel_pair() -> (CancelHandle, Cancel) {
    let (tx, rx) = watch::channel(None);
    (CancelHandle(tx), Cancel(rx))
}

impl CancelHandle {
    /// Asks the run to stop; later reasons are ignored.
    pub fn cancel(&self, reason: impl Into<String>) {
        let reason = reason.into();
        self.0.send_if_modified(|current| {
            if current.is_none() {
                *current = Some(reason);
                true
            } else {
                false
            }
        });
    }

    /// Whether a cancellation was asked.
    #[must_use]
    pub fn is_cancelled(&self) -> bool {
        self.0.borrow().is_some()
    }
}

impl Cancel {
    /// A signal that never fires (runs without an operator).
    #[must_use]
    pub fn never() -> Self {
        // The sender is dropped at once: `cancelled()` then waits forever.
        let (_, rx) = watch::channel(None);
        Self(rx)
    }

    /// The reason, once cancelled.
    #[must_use]
    pub fn reason(&self) -> Option<String> {
        self.0.borrow().clone()
    }

    /// Completes with the reason when the run is cancelled; pending forever
    /// once nobody can cancel any more.
    pub async fn cancelled(&self) -> String {
        let mut rx = self.0.clone();
        let reason = rx
            .wait_for(Option::is_some)
            .await
            .map(|reason| reason.clone().unwrap_or_default());
        match reason {
            Ok(reason) => reason,
            Err(_) => std::future::pending().await,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn cancellation_reaches_every_clone_and_keeps_the_first_reason() {
        let (trigger, signal) = cancel_pair();
        let clone = signal.clone();
        assert!(signal.reason().is_none());
        let waiter = tokio::spawn(async move { clone.cancelled().await });
        trigger.cancel("SIGTERM");
        trigger.cancel("later");
        assert_eq!(waiter.await.unwrap(), "SIGTERM");
        assert!(trigger.is_cancelled());
        assert_eq!(signal.reason().as_deref(), Some("SIGTERM"));
        assert_eq!(signal.cancelled().await, "SIGTERM");
    }

    #[tokio::test(start_paused = true)]
    async fn a_dropped_trigger_never_cancels() {
        let (trigger, signal) = cancel_pair();
        drop(trigger);
        let waited =
            tokio::time::timeout(std::time::Duration::from_secs(3600), signal.cancelled()).await;
        assert!(waited.is_err());
    }

    #[tokio::test(start_paused = true)]
    async fn never_does_not_fire() {
        let cancel = Cancel::never();
        let r = tokio::time::timeout(std::time::Duration::from_secs(5), cancel.cancelled()).await;
        assert!(r.is_err());
    }
}
