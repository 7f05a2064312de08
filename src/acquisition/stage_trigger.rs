//! `imaging.trigger` over the stage link: the imaging side's [`Trigger`] made of the stage
//! driver's `send_trigger` (RemCon32 `FREC` / `MAC n`: the SEM's own stage protocol is the
//! line that reaches the SEM software).

use crate::imaging::{Trigger, TriggerError, TriggerFuture};
use crate::stage::{StageBackend, StageDriver, StageProtocol};

/// The stage driver, lent to one grab as its trigger line.
pub struct StageTrigger<'a, B: StageBackend>(pub &'a mut StageDriver<B>);

impl<B: StageBackend> Trigger for StageTrigger<'_, B> {
    fn trigger<'a>(&'a mut self, command: &'a str) -> TriggerFuture<'a> {
        Box::pin(async move {
            self.0
                .send_trigger(command)
                .await
                .map(drop)
                .map_err(|e| Box::new(e) as TriggerError)
        })
    }
}

/// Whether a stage protocol reaches the SEM's software, so it can carry `imaging.trigger`.
#[must_use]
pub fn carries_sem_commands(protocol: StageProtocol) -> bool {
    match protocol {
        // A PI controller drives only its stage.
        StageProtocol::PiGcs => false,
        // RemCon32 is SmartSEM's own remote control: FREC, MAC n.
        StageProtocol::Remcon32 => true,
        // SharkSEM scans itself (imaging.protocol = "sharksem"); sdsem sends it no store command.
        StageProtocol::Sharksem => false,
    }
}
