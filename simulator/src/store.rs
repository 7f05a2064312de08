//! "Store a micrograph now": what a stage-link command (RemCon32 `FREC`,
//! `MAC n`) asks of the SEM, handed to whoever writes micrographs (the
//! watch-folder writer) through a hook set on the running simulator.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, PoisonError, RwLock};

/// The command that asked.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StoreCommand {
    /// RemCon32 `FREC`: SmartSEM stores a photo.
    Record,
    /// RemCon32 `MAC n`: SmartSEM runs the macro "REMCONn" (a lab's store macro).
    Macro(u32),
}

/// One request to store a micrograph.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StoreRequest {
    /// What asked.
    pub command: StoreCommand,
    /// The photo counter after this request (`PHN?` answers it from now on).
    pub photo_number: u64,
}

/// Called in the link's thread, before the command's status line is sent, with
/// no simulator lock held (it may read the stage pose and render). `Err`
/// answers the command with a failure (RemCon32 `*616`) and says why in the log.
pub type StoreHook = Arc<dyn Fn(&StoreRequest) -> Result<(), String> + Send + Sync>;

/// Where store requests go: a hook, or nowhere (they are counted either way).
#[derive(Default)]
pub struct StoreTrigger {
    hook: RwLock<Option<StoreHook>>,
    requests: AtomicU64,
}

impl std::fmt::Debug for StoreTrigger {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StoreTrigger")
            .field("hooked", &self.is_hooked())
            .field("requests", &self.requests())
            .finish()
    }
}

impl StoreTrigger {
    /// From now on, store requests call `hook`.
    pub fn set_hook(&self, hook: StoreHook) {
        *self.hook.write().unwrap_or_else(PoisonError::into_inner) = Some(hook);
    }

    /// From now on, store requests are only counted.
    pub fn clear_hook(&self) {
        *self.hook.write().unwrap_or_else(PoisonError::into_inner) = None;
    }

    /// Whether a hook is set.
    pub fn is_hooked(&self) -> bool {
        self.hook
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .is_some()
    }

    /// Requests received so far.
    pub fn requests(&self) -> u64 {
        self.requests.load(Ordering::Relaxed)
    }

    /// Hands one request to the hook (none set: done, nothing stored).
    pub fn fire(&self, request: &StoreRequest) -> Result<(), String> {
        self.requests.fetch_add(1, Ordering::Relaxed);
        let hook = self
            .hook
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone();
        hook.map_or(Ok(()), |h| h(request))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    #[test]
    fn requests_reach_the_hook_once_set_and_are_counted_always() {
        let t = StoreTrigger::default();
        let request = StoreRequest {
            command: StoreCommand::Record,
            photo_number: 1,
        };
        assert_eq!(t.fire(&request), Ok(()));
        let seen = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&seen);
        t.set_hook(Arc::new(move |r| {
            sink.lock().unwrap().push(*r);
            if r.command == StoreCommand::Macro(9) {
                Err("no macro REMCON9".into())
            } else {
                Ok(())
            }
        }));
        assert!(t.is_hooked());
        let m9 = StoreRequest {
            command: StoreCommand::Macro(9),
            photo_number: 2,
        };
        assert_eq!(t.fire(&m9), Err("no macro REMCON9".into()));
        assert_eq!(*seen.lock().unwrap(), [m9]);
        t.clear_hook();
        assert_eq!(t.fire(&request), Ok(()));
        assert_eq!(t.requests(), 3);
    }
}
