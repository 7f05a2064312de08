//! The instruments of a run: the stage driver, the frame source chosen by
//! `imaging.protocol` (the SEM link or a watched folder) and, when the
//! configuration asks for it, the in-process simulator behind them. One owner
//! for all three, so a run (or the daemon between runs) holds them together.

use std::sync::{Arc, Mutex, PoisonError};

use tracing::info;

use super::stage_trigger::carries_sem_commands;
use crate::config::Config;
use crate::imaging::{
    FrameSource, ImagingConfig, ImagingError, ImagingProtocol, SemLinkClient, WatchFolderSource,
};
use crate::record::RecorderHandle;
use crate::stage::{StageConfig, StageDriver, StageError, StageIo, StageObserver, StageState};

/// Why the instruments cannot be reached.
#[derive(Debug, thiserror::Error)]
pub enum InstrumentsError {
    #[error("cannot start the simulator: {0}")]
    Simulator(sdsem_sim::SimError),
    #[error("stage: {0}")]
    Stage(StageError),
    #[error("SEM imaging: {0}")]
    Imaging(ImagingError),
}

error_from!(InstrumentsError {
    Simulator(sdsem_sim::SimError),
    Stage(StageError),
    Imaging(ImagingError),
});

/// Forwards the driver's records to the record of the run in progress, if any.
/// The driver keeps one observer for its whole life; runs come and go.
#[derive(Default)]
pub struct RunObserver {
    recorder: Mutex<Option<RecorderHandle>>,
}

impl RunObserver {
    /// From now on, records go to `recorder`.
    pub fn attach(&self, recorder: RecorderHandle) {
        *self.recorder.lock().unwrap_or_else(PoisonError::into_inner) = Some(recorder);
    }

    /// Stops recording (the run is over).
    pub fn detach(&self) {
        *self.recorder.lock().unwrap_or_else(PoisonError::into_inner) = None;
    }

    fn with(&self, f: impl FnOnce(&RecorderHandle)) {
        if let Some(r) = self
            .recorder
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .as_ref()
        {
            f(r);
        }
    }
}

impl StageObserver for RunObserver {
    fn io(&self, e: &StageIo) {
        // A record error is reported once, by the recorder's finish().
        self.with(|r| {
            let t = e
                .sent_wall_ns
                .or(e.reply_wall_ns)
                .unwrap_or_else(crate::stage::observer::wall_ns);
            let _ = r.stage_io(t, e);
        });
    }

    fn state(&self, s: &StageState) {
        self.with(|r| {
            let _ = r.stage_state(s.wall_ns, s);
        });
    }
}

/// The connected instruments.
pub struct Instruments {
    pub stage: StageDriver,
    /// The frame source `imaging.protocol` chose.
    pub imaging: Box<dyn FrameSource>,
    /// Identification strings, for the record.
    pub stage_identity: String,
    pub sem_identity: String,
    pub observer: Arc<RunObserver>,
    /// Kept alive as long as the links that point at it.
    simulator: Option<sdsem_sim::SimHandle>,
}

impl Instruments {
    /// Starts the simulator when configured, then opens and checks both links.
    ///
    /// # Errors
    /// [`InstrumentsError`] naming the link and the remedy.
    pub async fn connect(config: &Config) -> Result<Self, InstrumentsError> {
        Self::connect_observed(config, Arc::default()).await
    }

    /// [`Instruments::connect`] reporting to `observer` from the first byte on:
    /// a run that connects its own instruments attaches its record first, so
    /// the connection handshake (`*IDN?`, `SVO?`, `FRF?`, limits) is in
    /// `/stage/io` too.
    ///
    /// # Errors
    /// As [`Instruments::connect`].
    pub async fn connect_observed(
        config: &Config,
        observer: Arc<RunObserver>,
    ) -> Result<Self, InstrumentsError> {
        let (stage_config, imaging_config, simulator) = Self::endpoints(config)?;
        if imaging_config.protocol == ImagingProtocol::WatchFolder
            && !carries_sem_commands(stage_config.protocol)
            && let Some(command) = imaging_config.triggers().first()
        {
            // Refused before anything is opened or moved.
            return Err(ImagingError::NoTriggerLink {
                command: (*command).to_owned(),
            }
            .into());
        }
        let dyn_observer: Arc<dyn StageObserver> = observer.clone();
        let stage = StageDriver::open(stage_config, dyn_observer).await?;
        let stage_identity = stage.identity().to_owned();
        let (imaging, sem_identity) =
            Self::frame_source(imaging_config, config.reconstruction.tilt_axis_deg).await?;
        info!(stage = %stage_identity, sem = %sem_identity, "instruments connected");
        Ok(Self {
            stage,
            imaging,
            stage_identity,
            sem_identity,
            observer,
            simulator,
        })
    }

    /// The frame source of `imaging.protocol`, connected, with its identification.
    async fn frame_source(
        imaging: ImagingConfig,
        tilt_axis_deg: Option<f64>,
    ) -> Result<(Box<dyn FrameSource>, String), ImagingError> {
        Ok(match imaging.protocol {
            ImagingProtocol::SdsemLink => {
                let (client, id) = SemLinkClient::connect(imaging).await?;
                (Box::new(client), id)
            }
            ImagingProtocol::WatchFolder => {
                let (source, id) = WatchFolderSource::connect(imaging, tilt_axis_deg).await?;
                (Box::new(source), id)
            }
        })
    }

    /// The effective link configurations: the configured endpoints, or those
    /// of a freshly started simulator.
    fn endpoints(
        config: &Config,
    ) -> Result<(StageConfig, ImagingConfig, Option<sdsem_sim::SimHandle>), InstrumentsError> {
        let mut stage = config.stage.clone();
        let mut imaging = config.imaging.clone();
        let Some(sim_config) = &config.simulator else {
            return Ok((stage, imaging, None));
        };
        let sim = sdsem_sim::Simulator::spawn(sim_config.clone())?;
        stage.endpoint = sim.stage_endpoint().to_owned();
        imaging.endpoint = sim.sem_endpoint().to_owned();
        if let Some(folder) = sim.folder() {
            // The simulated SEM's store folder is the one to watch.
            imaging.watch_dir = folder.dir().to_owned();
        }
        info!(
            stage = %stage.endpoint,
            sem = %imaging.endpoint,
            "simulator started in this process"
        );
        Ok((stage, imaging, Some(sim)))
    }

    /// The in-process simulator, when there is one (tests read its ground truth).
    #[must_use]
    pub fn simulator(&self) -> Option<&sdsem_sim::SimHandle> {
        self.simulator.as_ref()
    }
}
