//! The instruments of a run: the stage driver, the frame source chosen by
//! `imaging.protocol` (the SEM link, a watched folder or SharkSEM) and, when
//! the configuration asks for it, the in-process simulator behind them. One
//! owner for all three, so a run (or the daemon between runs) holds them
//! together. A TESCAN SEM that is both stage and imaging is reached through one
//! SharkSEM session that both use.

use std::sync::{Arc, Mutex, PoisonError};

use tracing::info;

use super::stage_trigger::carries_sem_commands;
use crate::config::Config;
use crate::imaging::{
    FrameSource, ImagingConfig, ImagingError, ImagingProtocol, SemLinkClient, SharkSemSource,
    WatchFolderSource,
};
use crate::record::RecorderHandle;
use crate::sharksem::{SessionConfig, SharkLink};
use crate::stage::{
    SharkSemBackend, StageBackend, StageConfig, StageDriver, StageError, StageIo, StageObserver,
    StageProtocol, StageState,
};

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
    /// When stage and imaging are both `sharksem` at the same endpoint they
    /// share one session (one control and one data connection).
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
        let shared = match shared_session(&stage_config, &imaging_config) {
            Some(session) => Some(
                SharkLink::connect(session, Arc::clone(&dyn_observer))
                    .await
                    .map_err(StageError::from)?,
            ),
            None => None,
        };
        let stage = match &shared {
            Some(link) => {
                let backend: Box<dyn StageBackend> = Box::new(SharkSemBackend::new(link.clone()));
                StageDriver::with_backend(backend, stage_config, Arc::clone(&dyn_observer)).await?
            }
            None => StageDriver::open(stage_config, Arc::clone(&dyn_observer)).await?,
        };
        let stage_identity = stage.identity().to_owned();
        let (imaging, sem_identity) = Self::frame_source(
            imaging_config,
            config.reconstruction.tilt_axis_deg,
            dyn_observer,
            shared,
        )
        .await?;
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

    /// The frame source of `imaging.protocol`, connected (on the `shared`
    /// SharkSEM session when there is one), with its identification.
    async fn frame_source(
        imaging: ImagingConfig,
        tilt_axis_deg: Option<f64>,
        observer: Arc<dyn StageObserver>,
        shared: Option<SharkLink>,
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
            ImagingProtocol::Sharksem => {
                let (source, id) = match shared {
                    Some(link) => SharkSemSource::with_link(link, &imaging, tilt_axis_deg).await?,
                    None => SharkSemSource::connect(&imaging, tilt_axis_deg, observer).await?,
                };
                (Box::new(source), id)
            }
        })
    }

    /// The effective link configurations: the configured endpoints, or those
    /// of a freshly started simulator (with its SharkSEM dialect when either
    /// side speaks it).
    fn endpoints(
        config: &Config,
    ) -> Result<(StageConfig, ImagingConfig, Option<sdsem_sim::SimHandle>), InstrumentsError> {
        let mut stage = config.stage.clone();
        let mut imaging = config.imaging.clone();
        let Some(sim_config) = &config.simulator else {
            return Ok((stage, imaging, None));
        };
        let mut sim_config = sim_config.clone();
        let shark = stage.protocol == StageProtocol::Sharksem
            || imaging.protocol == ImagingProtocol::Sharksem;
        if shark && sim_config.sharksem.is_none() {
            sim_config.sharksem = Some(sdsem_sim::sharksem::SharkSemSimConfig::default());
        }
        let sim = sdsem_sim::Simulator::spawn(sim_config)?;
        stage.endpoint = match stage.protocol {
            StageProtocol::Sharksem => sim.sharksem_endpoint(),
            StageProtocol::PiGcs | StageProtocol::Remcon32 => sim.stage_endpoint(),
        }
        .to_owned();
        if imaging.protocol == ImagingProtocol::Sharksem {
            imaging.endpoint = sim.sharksem_endpoint().to_owned();
            imaging.data_port = sim
                .sharksem_data_endpoint()
                .rsplit(':')
                .next()
                .and_then(|p| p.parse().ok());
        } else {
            imaging.endpoint = sim.sem_endpoint().to_owned();
        }
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

/// The one session stage and imaging share when both speak SharkSEM to the
/// same endpoint: the imaging data port, the longer of their timeouts.
fn shared_session(stage: &StageConfig, imaging: &ImagingConfig) -> Option<SessionConfig> {
    let bare = |e: &str| {
        let e = e.trim();
        e.strip_prefix("tcp://").unwrap_or(e).to_owned()
    };
    let same = stage.protocol == StageProtocol::Sharksem
        && imaging.protocol == ImagingProtocol::Sharksem
        && bare(&stage.endpoint) == bare(&imaging.endpoint);
    same.then(|| {
        let stage_side = SharkSemBackend::session_config(stage);
        let imaging_side = SharkSemSource::session_config(imaging);
        SessionConfig {
            data_port: imaging.data_port,
            connect_timeout: stage_side.connect_timeout.max(imaging_side.connect_timeout),
            reply_timeout: stage_side.reply_timeout.max(imaging_side.reply_timeout),
            timeout_key: "imaging.timeout_ms (or stage.reply_timeout_s, the longer is used)",
            ..imaging_side
        }
    })
}
