//! TESCAN SharkSEM on the client side: one [`SharkSession`] per SEM (control
//! and data connections, set-up, every exchange recorded), shared by the
//! imaging source ([`crate::imaging::SharkSemSource`]) and, when both sides
//! name the same endpoint, the stage, through a [`SharkLink`].
//!
//! The wire protocol itself is [`sdsem_protocol::sharksem`] (sans-IO, shared
//! with the simulator); the facts are in `/work/shared/VENDORS.md` §2.

mod error;
mod session;

use std::sync::Arc;

pub use error::SharkError;
pub use session::{InstrumentInfo, SessionConfig, SharkSession};
use tokio::sync::{Mutex, MutexGuard};

use crate::stage::StageObserver;

/// A handle on one SharkSEM session. Clones share it: the session is the one
/// owner of the connections, each user locks it for the exchanges that belong
/// together (a whole frame: settings, scan, data, stop).
#[derive(Clone, Debug)]
pub struct SharkLink {
    session: Arc<Mutex<SharkSession>>,
    endpoint: String,
}

impl SharkLink {
    /// Connects and sets the session up.
    ///
    /// # Errors
    /// [`SharkError`] naming the step that failed and the remedy.
    pub async fn connect(
        config: SessionConfig,
        observer: Arc<dyn StageObserver>,
    ) -> Result<Self, SharkError> {
        let endpoint = config.endpoint.clone();
        let session = SharkSession::connect(config, observer).await?;
        Ok(Self {
            session: Arc::new(Mutex::new(session)),
            endpoint,
        })
    }

    /// The session, for a sequence of exchanges no one else may interleave with.
    pub async fn lock(&self) -> MutexGuard<'_, SharkSession> {
        self.session.lock().await
    }

    /// The control endpoint as configured.
    #[must_use]
    pub fn endpoint(&self) -> &str {
        &self.endpoint
    }
}
