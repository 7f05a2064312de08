//! The SEM's store folder: on request ("store one micrograph now", e.g. RemCon32 `FREC`), on
//! a timer, or called directly, the simulated SEM scans a frame at the stage pose of the
//! moment (the same [`SimSem`] renderer as the imaging link) and stores it as a vendor TIFF
//! ([`crate::vendor_tiff`]) in a folder, with the faults a share really shows:
//!
//! - written slowly, in chunks (`write_s`, `write_chunks`): partial files are visible;
//! - written under a temporary name (`~NAME`), then renamed (`temp_then_rename`);
//! - a stale file already there at start, under the name the first store will overwrite in
//!   place (`stale_file`, recording a tilt of 45°);
//! - a file recording another tilt than the stage's (`wrong_tilt`, `wrong_tilt_deg`).
//!
//! Names are `PREFIX0001.tif`, `PREFIX0002.tif`, … from `first_number`. Occurrences of
//! faults count stored micrographs from 1; random ones are drawn from the folder's seed.
//!
//! What is stored at which size: RemCon32 has no store-resolution command (VENDORS §1.5), so
//! `FREC` stores at the folder's own `width` × `height` and `dwell_us` (SmartSEM's store
//! resolution and scan speed, set by the operator), and `MAC n` runs the lab's macro REMCONn,
//! which sets its own store resolution and speed for one photo and restores them ([`FolderMacro`],
//! e.g. a quick tracking frame). A macro that is not set up answers `*616`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sdsem_protocol::sem::{Bits, GrabRequest, Role};
use serde::{Deserialize, Serialize};
use tracing::{info, warn};

use crate::SimError;
use crate::clock::Clock;
use crate::config::FaultTrigger;
use crate::sem::SimSem;
use crate::simulator::ServiceServer;
use crate::store::StoreCommand;
use crate::vendor_tiff::{self, Samples, StoredMeta, Vendor};

/// The simulated store folder (`[simulator.folder]`).
///
/// | key | default | effect |
/// | --- | --- | --- |
/// | `dir` | (required) | folder the micrographs are stored in; created if missing |
/// | `vendor` | `zeiss` | file format: `zeiss` (tag 34118), `fei` (34682, data bar), `tescan` (50431, info strip) |
/// | `prefix` | `image_` | file names `PREFIX0001.tif`, … |
/// | `first_number` | 1 | number of the first file |
/// | `width`, `height` | 1024, 768 | store resolution, pixels |
/// | `dwell_us` | 1 | pixel dwell, µs (the scan takes width × height × dwell) |
/// | `bits` | 8 | 8 or 16 |
/// | `every_s` | 0 | store one micrograph every this many simulated seconds (0: only on request) |
/// | `write_s` | 0 | simulated seconds writing one file takes, in `write_chunks` chunks |
/// | `write_chunks` | 1 | pieces a file is written in (partial files visible in between) |
/// | `temp_then_rename` | false | write `~NAME` first, then rename it to `NAME` |
/// | `stale_file` | false | at start, a finished file (tilt 45°) under the first name |
/// | `wrong_tilt` | never | micrographs whose metadata records the tilt + `wrong_tilt_deg` |
/// | `wrong_tilt_deg` | 5 | the error of such a micrograph's recorded tilt, degrees |
/// | `macros` | none | the SmartSEM macros REMCONn that `MAC n` runs: `{ number, width, height, dwell_us }` each |
/// | `seed` | derived | seed of the random faults |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FolderSimConfig {
    pub dir: PathBuf,
    pub vendor: Vendor,
    pub prefix: String,
    pub first_number: u64,
    pub width: usize,
    pub height: usize,
    pub dwell_us: f64,
    pub bits: u8,
    pub every_s: f64,
    pub write_s: f64,
    pub write_chunks: u32,
    pub temp_then_rename: bool,
    pub stale_file: bool,
    pub wrong_tilt: FaultTrigger,
    pub wrong_tilt_deg: f64,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub macros: Vec<FolderMacro>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

/// The store resolution and pixel dwell of one stored micrograph.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoreSettings {
    pub width: usize,
    pub height: usize,
    pub dwell_us: f64,
}

/// A SmartSEM macro REMCONn that stores one micrograph at its own store resolution and scan
/// speed (restoring the operator's afterwards), run by RemCon32 `MAC n`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FolderMacro {
    /// n of `MAC n`.
    pub number: u32,
    pub width: usize,
    pub height: usize,
    pub dwell_us: f64,
}

impl Default for FolderSimConfig {
    fn default() -> Self {
        Self {
            dir: PathBuf::new(),
            vendor: Vendor::Zeiss,
            prefix: "image_".into(),
            first_number: 1,
            width: 1024,
            height: 768,
            dwell_us: 1.0,
            bits: 8,
            every_s: 0.0,
            write_s: 0.0,
            write_chunks: 1,
            temp_then_rename: false,
            stale_file: false,
            wrong_tilt: FaultTrigger::default(),
            wrong_tilt_deg: 5.0,
            macros: Vec::new(),
            seed: None,
        }
    }
}

fn invalid(field: &'static str, reason: impl Into<String>) -> SimError {
    SimError::Config {
        field,
        reason: reason.into(),
    }
}

impl FolderSimConfig {
    /// Checks every value, naming the first wrong field.
    ///
    /// # Errors
    /// [`SimError::Config`].
    pub fn validate(&self) -> Result<(), SimError> {
        if self.dir.as_os_str().is_empty() {
            return Err(invalid(
                "folder.dir",
                "the folder to store micrographs in is required",
            ));
        }
        if self.prefix.contains(['/', '\\', '\0']) || self.prefix.starts_with('~') {
            return Err(invalid(
                "folder.prefix",
                format!(
                    "{:?}: a plain name start, without / or a leading ~",
                    self.prefix
                ),
            ));
        }
        check_settings(
            ["folder.width", "folder.height", "folder.dwell_us"],
            &self.settings(),
        )?;
        for (i, m) in self.macros.iter().enumerate() {
            if self.macros[..i].iter().any(|o| o.number == m.number) {
                return Err(invalid(
                    "folder.macros",
                    format!("macro {} is set up twice", m.number),
                ));
            }
            check_settings(
                [
                    "folder.macros.width",
                    "folder.macros.height",
                    "folder.macros.dwell_us",
                ],
                &m.settings(),
            )?;
        }
        if self.bits != 8 && self.bits != 16 {
            return Err(invalid(
                "folder.bits",
                format!("must be 8 or 16, got {}", self.bits),
            ));
        }
        for (field, v) in [
            ("folder.every_s", self.every_s),
            ("folder.write_s", self.write_s),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(invalid(field, format!("must be ≥ 0, got {v}")));
            }
        }
        if self.write_chunks == 0 {
            return Err(invalid("folder.write_chunks", "must be 1 or more"));
        }
        if !self.wrong_tilt_deg.is_finite() {
            return Err(invalid("folder.wrong_tilt_deg", "must be a finite number"));
        }
        if !(0.0..=1.0).contains(&self.wrong_tilt.probability) {
            return Err(invalid(
                "folder.wrong_tilt.probability",
                "must lie in [0, 1]",
            ));
        }
        Ok(())
    }

    /// The operator's store resolution and dwell: what `FREC` and the timer store at.
    #[must_use]
    pub fn settings(&self) -> StoreSettings {
        StoreSettings {
            width: self.width,
            height: self.height,
            dwell_us: self.dwell_us,
        }
    }

    /// What a store request stores at: `FREC` at the folder's settings, `MAC n` at its
    /// macro's; `None` for a macro that is not set up.
    #[must_use]
    pub fn settings_for(&self, command: StoreCommand) -> Option<StoreSettings> {
        match command {
            StoreCommand::Record => Some(self.settings()),
            StoreCommand::Macro(n) => self
                .macros
                .iter()
                .find(|m| m.number == n)
                .map(FolderMacro::settings),
        }
    }

    /// The name of micrograph number `n`.
    #[must_use]
    pub fn file_name(&self, n: u64) -> String {
        format!("{}{n:04}.tif", self.prefix)
    }
}

impl FolderMacro {
    /// What this macro stores at.
    #[must_use]
    pub fn settings(&self) -> StoreSettings {
        StoreSettings {
            width: self.width,
            height: self.height,
            dwell_us: self.dwell_us,
        }
    }
}

/// Checks a store resolution and dwell, naming `fields` (width, height, dwell).
fn check_settings(fields: [&'static str; 3], s: &StoreSettings) -> Result<(), SimError> {
    let max = sdsem_protocol::sem::MAX_SIDE as usize;
    for (field, side) in [(fields[0], s.width), (fields[1], s.height)] {
        if side == 0 || side > max {
            return Err(invalid(
                field,
                format!("must be 1 to {max} pixels, got {side}"),
            ));
        }
    }
    if !(s.dwell_us.is_finite() && s.dwell_us > 0.0) {
        return Err(invalid(
            fields[2],
            format!("must be > 0, got {}", s.dwell_us),
        ));
    }
    Ok(())
}

/// One micrograph stored.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredFile {
    pub path: PathBuf,
    /// The SEM's frame number (ground truth: [`SimSem::frame`]).
    pub frame: u64,
    /// The stage tilt when it was scanned, degrees.
    pub tilt_deg: f64,
    /// The tilt its metadata records, degrees (differs under `wrong_tilt`).
    pub recorded_tilt_deg: f64,
}

#[derive(Debug)]
struct WriterState {
    next_number: u64,
    stored: u64,
    rng: ChaCha8Rng,
    log: Vec<StoredFile>,
}

/// Stores micrographs of the simulated SEM into a folder. Safe to share between threads;
/// one store at a time.
pub struct FolderWriter {
    cfg: FolderSimConfig,
    sem: Arc<SimSem>,
    clock: Arc<dyn Clock>,
    state: Mutex<WriterState>,
    /// Held through one store (scan and write): one at a time, as one SEM stores.
    busy: Mutex<()>,
}

impl std::fmt::Debug for FolderWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FolderWriter")
            .field("dir", &self.cfg.dir)
            .field("vendor", &self.cfg.vendor)
            .finish_non_exhaustive()
    }
}

impl FolderWriter {
    /// A writer for `cfg` storing what `sem` scans, faults seeded by `cfg.seed` or else
    /// `seed`. Creates the folder if needed and, with `stale_file`, the stale file.
    ///
    /// # Errors
    /// [`SimError::Config`] for a wrong setting or a folder that cannot be made or written.
    pub fn new(
        cfg: &FolderSimConfig,
        seed: u64,
        sem: Arc<SimSem>,
        clock: Arc<dyn Clock>,
    ) -> Result<Self, SimError> {
        cfg.validate()?;
        std::fs::create_dir_all(&cfg.dir).map_err(|e| {
            invalid(
                "folder.dir",
                format!("cannot create {}: {e}", cfg.dir.display()),
            )
        })?;
        let writer = Self {
            cfg: cfg.clone(),
            sem,
            clock,
            state: Mutex::new(WriterState {
                next_number: cfg.first_number,
                stored: 0,
                rng: ChaCha8Rng::seed_from_u64(cfg.seed.unwrap_or(seed)),
                log: Vec::new(),
            }),
            busy: Mutex::new(()),
        };
        if cfg.stale_file {
            writer.write_stale().map_err(|e| {
                invalid(
                    "folder.dir",
                    format!("cannot write in {}: {e}", cfg.dir.display()),
                )
            })?;
        }
        Ok(writer)
    }

    fn state(&self) -> std::sync::MutexGuard<'_, WriterState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The folder written to.
    #[must_use]
    pub fn dir(&self) -> &Path {
        &self.cfg.dir
    }

    /// The settings in effect.
    #[must_use]
    pub fn config(&self) -> &FolderSimConfig {
        &self.cfg
    }

    /// Every micrograph stored so far, in order.
    #[must_use]
    pub fn stored(&self) -> Vec<StoredFile> {
        self.state().log.clone()
    }

    /// A finished file from "an earlier session" under the first name: flat grey, tilt 45°.
    fn write_stale(&self) -> std::io::Result<()> {
        let (w, h) = (self.cfg.width, self.cfg.height);
        let samples = match self.cfg.bits {
            8 => Samples::U8(vec![128; w * h]),
            _ => Samples::U16(vec![32768; w * h]),
        };
        let meta = StoredMeta {
            pixel_size_um: self.sem.config().optics.pixel_size_at(w),
            dwell_us: self.cfg.dwell_us,
            stage_x_um: 0.0,
            stage_y_um: 0.0,
            tilt_deg: 45.0,
            unix_s: self.clock.unix_ns() / 1_000_000_000,
        };
        let bytes = vendor_tiff::encode(self.cfg.vendor, w, h, &samples, &meta);
        std::fs::write(
            self.dir().join(self.cfg.file_name(self.cfg.first_number)),
            bytes,
        )
    }

    /// Scans one frame where the stage is now and stores it at the folder's settings (taking
    /// the scan time and the write time on the clock). `cancel` ends a scan or a slow write
    /// early (the simulator is stopping): the file is then left as far as it got.
    ///
    /// # Errors
    /// The file cannot be written.
    pub fn store(&self, cancel: &AtomicBool) -> std::io::Result<StoredFile> {
        self.store_at(&self.cfg.settings(), cancel)
    }

    /// [`Self::store`] at the given store resolution and dwell (a macro's).
    ///
    /// # Errors
    /// The file cannot be written.
    pub fn store_at(
        &self,
        settings: &StoreSettings,
        cancel: &AtomicBool,
    ) -> std::io::Result<StoredFile> {
        let _one_at_a_time = self.busy.lock().unwrap_or_else(PoisonError::into_inner);
        let (number, wrong) = {
            let mut state = self.state();
            let number = state.next_number;
            state.next_number += 1;
            state.stored += 1;
            let k = state.stored;
            (number, fires(&self.cfg.wrong_tilt, k, &mut state.rng))
        };
        let (w, h) = (settings.width, settings.height);
        let grab = GrabRequest {
            width: u32::try_from(w).unwrap_or(u32::MAX),
            height: u32::try_from(h).unwrap_or(u32::MAX),
            dwell_us: settings.dwell_us,
            role: Role::Left,
            bits: if self.cfg.bits == 8 {
                Bits::Eight
            } else {
                Bits::Sixteen
            },
        };
        let reply = self.sem.grab(&grab, cancel);
        let samples = match grab.bits {
            Bits::Eight => Samples::U8(reply.data.clone()),
            Bits::Sixteen => Samples::U16(
                reply
                    .data
                    .chunks_exact(2)
                    .map(|c| u16::from_le_bytes([c[0], c[1]]))
                    .collect(),
            ),
        };
        let m = &reply.meta;
        let recorded = m.tilt_deg + if wrong { self.cfg.wrong_tilt_deg } else { 0.0 };
        let meta = StoredMeta {
            pixel_size_um: m.pixel_size_um,
            dwell_us: m.dwell_us,
            stage_x_um: m.stage_x_um,
            stage_y_um: m.stage_y_um,
            tilt_deg: recorded,
            unix_s: m.scan_end_unix_ns / 1_000_000_000,
        };
        let bytes = vendor_tiff::encode(self.cfg.vendor, w, h, &samples, &meta);
        let name = self.cfg.file_name(number);
        let path = self.dir().join(&name);
        let written = if self.cfg.temp_then_rename {
            self.dir().join(format!("~{name}"))
        } else {
            path.clone()
        };
        self.write_slowly(&written, &bytes, cancel)?;
        if written != path {
            std::fs::rename(&written, &path)?;
        }
        let stored = StoredFile {
            path,
            frame: m.frame,
            tilt_deg: m.tilt_deg,
            recorded_tilt_deg: recorded,
        };
        info!(
            file = %name,
            tilt_deg = m.tilt_deg,
            recorded_tilt_deg = recorded,
            "micrograph stored"
        );
        self.state().log.push(stored.clone());
        Ok(stored)
    }

    /// Writes `bytes` in `write_chunks` pieces over `write_s` simulated seconds.
    fn write_slowly(&self, path: &Path, bytes: &[u8], cancel: &AtomicBool) -> std::io::Result<()> {
        let mut file = std::fs::File::create(path)?;
        let chunks = self.cfg.write_chunks.max(1) as usize;
        let step_s = self.cfg.write_s / chunks as f64;
        let mut t = self.clock.now_s();
        for (i, chunk) in bytes
            .chunks(bytes.len().div_ceil(chunks).max(1))
            .enumerate()
        {
            if i > 0 && step_s > 0.0 {
                t += step_s;
                if !self.clock.sleep_until(t, cancel) {
                    break;
                }
            }
            file.write_all(chunk)?;
            file.flush()?;
        }
        Ok(())
    }
}

/// Whether the fault fires at occurrence `k` (the random draw only for armed probabilities).
fn fires(trigger: &FaultTrigger, k: u64, rng: &mut ChaCha8Rng) -> bool {
    let listed = trigger.at.contains(&k);
    let random = trigger.probability > 0.0 && rng.random::<f64>() < trigger.probability;
    listed || random
}

/// Asks the folder's thread to store one micrograph now, without waiting for it (what the
/// SEM does on RemCon32 `FREC` / `MAC n`). Cheap to clone, safe to share.
#[derive(Clone, Debug)]
pub struct StoreRequests {
    tx: mpsc::Sender<Option<StoreSettings>>,
}

impl StoreRequests {
    /// Queues one store at the folder's settings; false when the folder's thread has stopped.
    pub fn store_now(&self) -> bool {
        self.tx.send(None).is_ok()
    }

    /// Queues one store at `settings` (a macro's); false when the folder's thread has stopped.
    pub fn store_at(&self, settings: StoreSettings) -> bool {
        self.tx.send(Some(settings)).is_ok()
    }
}

/// How often the folder's thread looks at its stop flag and its timer, real time.
const TICK: Duration = Duration::from_millis(10);

/// Runs the folder on its own thread: stores on each request and, with `every_s`, on a
/// timer, until `stop` is set.
pub(crate) fn serve(
    writer: Arc<FolderWriter>,
    stop: Arc<AtomicBool>,
) -> Result<(StoreRequests, ServiceServer), SimError> {
    let (tx, rx) = mpsc::channel::<Option<StoreSettings>>();
    let endpoint = writer.dir().display().to_string();
    let thread = std::thread::Builder::new()
        .name("sim-folder".into())
        .spawn(move || {
            let every = writer.cfg.every_s;
            let mut due = if every > 0.0 {
                writer.clock.now_s() + every
            } else {
                f64::INFINITY
            };
            while !stop.load(Ordering::Relaxed) {
                let mut store = match rx.recv_timeout(TICK) {
                    Ok(settings) => Some(settings.unwrap_or_else(|| writer.cfg.settings())),
                    Err(RecvTimeoutError::Timeout) => None,
                    Err(RecvTimeoutError::Disconnected) => {
                        // No one can ask any more: the timer alone remains.
                        std::thread::sleep(TICK);
                        None
                    }
                };
                if writer.clock.now_s() >= due {
                    store.get_or_insert_with(|| writer.cfg.settings());
                    due += every;
                }
                if let Some(settings) = store
                    && let Err(e) = writer.store_at(&settings, &stop)
                {
                    warn!(dir = %writer.dir().display(), "cannot store a micrograph: {e}");
                }
            }
        })
        .map_err(|error| SimError::Thread { error })?;
    Ok((
        StoreRequests { tx },
        ServiceServer {
            endpoint,
            thread,
            wake: None,
        },
    ))
}

#[cfg(test)]
mod tests;
