//! The watch-folder imaging source (`imaging.protocol = "watch-folder"`, VENDORS §4): the SEM's
//! own software stores each micrograph as a TIFF in a folder sdsem reads (a share of the SEM PC).
//!
//! One grab: list the folder (what is there is old), send `imaging.trigger` over the stage
//! link when one is set, then poll the folder ([`super::arrival`] decides) until a new file
//! has held still and its TIFF is whole; read it without following links or opening
//! anything but a regular file, within the size cap; take pixel size and tilt from the
//! vendor's tags or sidecar (info bar cut off); refuse it when its tilt disagrees with the
//! stage's. A tracking frame stored larger than the tracking size asked is averaged down.

use std::io::Read;
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::time::{Duration, UNIX_EPOCH};

use sdsem_protocol::sem::{FrameMeta, GrabRequest, Role};
use tracing::{debug, info, warn};

use super::arrival::{
    ArrivalRules, Arrivals, Candidate, EntryKind, FileKey, ListedEntry, Notice, Pattern, Poll,
};
use super::file::{Micrograph, check_whole, micrograph_from_bytes};
use super::metadata::{SemMetadata, parse_sidecar};
use super::source::{GrabContext, IdentifyFuture, ProbeFuture, SourceIdentity};
use super::{
    Frame, FrameFile, FrameSource, GrabFuture, ImagingConfig, ImagingError, ImagingProtocol, Pixels,
};
use crate::vision::Image;

/// Reads micrographs the SEM stores in a folder.
#[derive(Debug)]
pub struct WatchFolderSource {
    cfg: ImagingConfig,
    arrivals: Arrivals,
    /// Frames delivered, for [`FrameMeta::frame`].
    frames: u64,
    tilt_axis_deg: f64,
    origin: tokio::time::Instant,
    /// Who stored the last file read, as its metadata says.
    stored_by: SourceIdentity,
}

/// What a file gave, before it becomes a frame.
struct Stored {
    micrograph: Micrograph,
    sidecar: Option<String>,
    mtime_ns: i128,
}

impl WatchFolderSource {
    /// A source for `cfg` (`imaging.protocol = "watch-folder"`). The files record no tilt
    /// axis: `tilt_axis_deg` (`reconstruction.tilt_axis_deg`) goes into each frame's
    /// metadata, 0 when none is given.
    ///
    /// # Errors
    /// [`ImagingError::InvalidConfig`] naming the setting.
    pub fn new(cfg: ImagingConfig, tilt_axis_deg: Option<f64>) -> Result<Self, ImagingError> {
        let cfg = ImagingConfig {
            protocol: ImagingProtocol::WatchFolder,
            ..cfg
        };
        cfg.validate()?;
        let rules = ArrivalRules {
            patterns: cfg.watch_patterns.iter().map(|p| Pattern::new(p)).collect(),
            ignore: cfg.watch_ignore.iter().map(|p| Pattern::new(p)).collect(),
            sidecar_ext: (!cfg.watch_sidecar.trim().is_empty())
                .then(|| cfg.watch_sidecar.trim().to_lowercase()),
            stable_polls: cfg.watch_stable_polls,
            stable_window: Duration::from_millis(cfg.watch_stable_ms),
            max_bytes: cfg.watch_max_file_mb.saturating_mul(1 << 20),
            timeout: Duration::from_secs_f64(cfg.watch_timeout_s),
        };
        Ok(Self {
            cfg,
            arrivals: Arrivals::new(rules),
            frames: 0,
            tilt_axis_deg: tilt_axis_deg.unwrap_or(0.0),
            origin: tokio::time::Instant::now(),
            stored_by: SourceIdentity::default(),
        })
    }

    /// A source whose folder was listed once, with what [`FrameSource::identify`] says.
    ///
    /// # Errors
    /// As [`WatchFolderSource::new`], and [`ImagingError::WatchFolder`] when the folder
    /// cannot be listed.
    pub async fn connect(
        cfg: ImagingConfig,
        tilt_axis_deg: Option<f64>,
    ) -> Result<(Self, String), ImagingError> {
        let source = Self::new(cfg, tilt_axis_deg)?;
        let id = source.describe().await?;
        Ok((source, id))
    }

    /// What the last wait saw before its micrograph was ready (files still being written,
    /// incomplete TIFFs, files skipped).
    #[must_use]
    pub fn last_wait(&self) -> &super::arrival::Unfinished {
        self.arrivals.seen()
    }

    /// The folder watched.
    #[must_use]
    pub fn dir(&self) -> &Path {
        &self.cfg.watch_dir
    }

    fn now(&self) -> Duration {
        self.origin.elapsed()
    }

    async fn describe(&self) -> Result<String, ImagingError> {
        let listing = self.list().await?;
        let files = listing.iter().filter(|e| e.kind == EntryKind::File).count();
        Ok(format!(
            "watch folder {} ({files} files now)",
            self.dir().display()
        ))
    }

    /// `sdsem probe`'s lines: the folder's state, the newest micrograph in it and what its
    /// metadata says (read as a grab reads it: no links followed, within the size cap), the
    /// triggers and the stability rule. Nothing is triggered.
    async fn probe_lines(&mut self) -> Result<Vec<(String, String)>, ImagingError> {
        let listing = self.list().await?;
        let rules = self.arrivals.rules().clone();
        let images: Vec<&ListedEntry> = listing
            .iter()
            .filter(|e| e.kind == EntryKind::File && rules.is_image(&e.name))
            .collect();
        let mut lines = vec![(
            "folder".to_owned(),
            format!(
                "{}: {} entries, {} micrographs ({})",
                self.dir().display(),
                listing.len(),
                images.len(),
                self.cfg.watch_patterns.join(", ")
            ),
        )];
        if let Some(newest) = images.iter().max_by_key(|e| (e.mtime_ns, e.name.clone())) {
            let age_s = (unix_ns() as i128 - newest.mtime_ns) as f64 * 1e-9;
            lines.push((
                "newest micrograph".to_owned(),
                format!(
                    "{} ({} bytes, written {age_s:.0} s ago)",
                    newest.name, newest.len
                ),
            ));
            let candidate = Candidate {
                image: FileKey::of(newest),
                sidecar: rules.sidecar_name(&newest.name).and_then(|side| {
                    listing
                        .iter()
                        .find(|e| e.kind == EntryKind::File && e.name.to_lowercase() == side)
                        .map(FileKey::of)
                }),
            };
            let (dir, max) = (self.dir().to_owned(), rules.max_bytes);
            let read = tokio::task::spawn_blocking(move || read_and_decode(&dir, &candidate, max))
                .await
                .map_err(|e| std::io::Error::other(e.to_string()));
            if let Ok(Ok(stored)) = &read {
                // Until a run reads its own files, the newest one says who stores them.
                self.stored_by = stored.micrograph.metadata.instrument();
            }
            lines.push(("its metadata".to_owned(), describe_stored(read)));
        }
        let trigger = |t: &str| {
            if t.is_empty() {
                "none: the SEM stores on its own".to_owned()
            } else {
                format!("{t:?} over the stage link")
            }
        };
        lines.push((
            "trigger, micrograph".to_owned(),
            trigger(self.cfg.trigger_for(Role::Left)),
        ));
        lines.push((
            "trigger, tracking frame".to_owned(),
            trigger(self.cfg.trigger_for(Role::Tracking)),
        ));
        lines.push((
            "stability".to_owned(),
            format!(
                "read once unchanged for {} ms over ≥ {} listings, one every {} ms \
                 (imaging.watch_stable_ms: longer than the mount's attribute cache)",
                self.cfg.watch_stable_ms, self.cfg.watch_stable_polls, self.cfg.watch_poll_ms
            ),
        ));
        Ok(lines)
    }

    async fn list(&self) -> Result<Vec<ListedEntry>, ImagingError> {
        let dir = self.dir().to_owned();
        let listed = tokio::task::spawn_blocking(move || list_dir(&dir))
            .await
            .map_err(|e| std::io::Error::other(e.to_string()))
            .and_then(|r| r);
        listed.map_err(|error| ImagingError::WatchFolder {
            dir: self.dir().to_owned(),
            error,
        })
    }

    async fn wait_for_frame(
        &mut self,
        request: GrabRequest,
        context: GrabContext<'_>,
    ) -> Result<Frame, ImagingError> {
        let listing = self.list().await?;
        self.arrivals.begin(self.now(), &listing);
        let command = self.cfg.trigger_for(request.role).to_owned();
        if !command.is_empty() {
            let trigger = context.trigger.ok_or_else(|| ImagingError::NoTriggerLink {
                command: command.clone(),
            })?;
            trigger
                .trigger(&command)
                .await
                .map_err(|error| ImagingError::Trigger {
                    command: command.clone(),
                    error,
                })?;
        }
        info!(
            dir = %self.dir().display(),
            role = request.role.as_str(),
            "waiting for the SEM to store a micrograph{}",
            if command.is_empty() {
                String::new()
            } else {
                format!(" (sent {command:?})")
            }
        );
        let poll = Duration::from_millis(self.cfg.watch_poll_ms);
        let mut listing_error: Option<String> = None;
        loop {
            tokio::time::sleep(poll).await;
            let listing = match self.list().await {
                Ok(l) => l,
                Err(e) => {
                    // A share can blink: keep polling until the timeout, say it once.
                    if listing_error.is_none() {
                        warn!("{e}; still watching");
                    }
                    listing_error = Some(e.to_string());
                    Vec::new()
                }
            };
            let mut notices = Vec::new();
            let outcome = self.arrivals.poll(self.now(), &listing, &mut notices);
            for notice in notices {
                log_notice(self.dir(), &notice);
            }
            match outcome {
                Poll::Wait => {}
                Poll::TimedOut(unfinished) => {
                    let mut seen = unfinished.describe();
                    if let Some(e) = listing_error {
                        seen = [seen, format!("last listing failed: {e}")]
                            .into_iter()
                            .filter(|s| !s.is_empty())
                            .collect::<Vec<_>>()
                            .join("; ");
                    }
                    return Err(ImagingError::NoNewFile {
                        dir: self.dir().to_owned(),
                        after: self.arrivals.rules().timeout,
                        trigger: command,
                        seen,
                    });
                }
                Poll::Ready(candidate) => {
                    if let Some(stored) = self.read_candidate(&candidate).await? {
                        self.arrivals.used(&candidate);
                        let name = &candidate.image.name;
                        if self.arrivals.seen().changing.contains(name) {
                            info!(file = %name, "{name} was seen while still being written: read once it held still");
                        }
                        return self.frame(stored, request, context.stage);
                    }
                }
            }
        }
    }

    /// Reads and decodes a stable candidate; `None` when it turned out not whole (it waits
    /// for another stability window). A file that is whole but unusable is refused.
    async fn read_candidate(
        &mut self,
        candidate: &Candidate,
    ) -> Result<Option<Stored>, ImagingError> {
        let dir = self.dir().to_owned();
        let max = self.arrivals.rules().max_bytes;
        let c = candidate.clone();
        let read = tokio::task::spawn_blocking(move || read_and_decode(&dir, &c, max))
            .await
            .map_err(|e| ImagingError::BadFile {
                file: self.dir().join(&candidate.image.name),
                cause: e.to_string(),
            })?;
        match read {
            Ok(stored) => Ok(Some(stored)),
            Err(Unready::NotWhole(why)) => {
                debug!(file = %candidate.image.name, "not whole yet: {why}");
                self.arrivals.not_whole(candidate, why, self.now());
                Ok(None)
            }
            Err(Unready::Refused(e)) => {
                self.arrivals.used(candidate);
                Err(e)
            }
        }
    }

    /// The frame from a stored micrograph: tilt checked, pixel size required, averaged
    /// down to the tracking size when larger.
    fn frame(
        &mut self,
        stored: Stored,
        request: GrabRequest,
        stage: Option<crate::stage::StagePosition>,
    ) -> Result<Frame, ImagingError> {
        let Stored {
            micrograph: m,
            sidecar,
            mtime_ns,
        } = stored;
        let meta = &m.metadata;
        if let (true, Some(recorded), Some(stage)) =
            (self.cfg.watch_check_tilt, meta.tilt_deg, stage)
            && (recorded - stage.tilt_deg).abs() > self.cfg.tilt_tolerance_deg
        {
            return Err(ImagingError::WrongTilt {
                file: m.path.clone(),
                recorded_deg: recorded,
                stage_deg: stage.tilt_deg,
                tolerance_deg: self.cfg.tilt_tolerance_deg,
            });
        }
        if self.cfg.watch_check_tilt && meta.tilt_deg.is_none() {
            warn!(file = %m.path.display(), "the file records no stage tilt to check: the stage's is used");
        }
        let pixel = meta
            .pixel_size_um
            .filter(|p| p.is_finite() && *p > 0.0)
            .ok_or_else(|| ImagingError::NoPixelSize {
                file: m.path.clone(),
            })?;
        let factor = if request.role == Role::Tracking {
            downsample_factor(m.image.dimensions(), (request.width, request.height))
        } else {
            1
        };
        let image = if factor > 1 {
            box_average(&m.image, factor)
        } else {
            m.image.clone()
        };
        let (w, h) = image.dimensions();
        let pixels = if m.bits_per_sample == 8 {
            Pixels::U8(image.to_u8())
        } else {
            Pixels::U16(
                image
                    .data()
                    .iter()
                    .map(|&v| (f64::from(v.clamp(0.0, 1.0)) * 65535.0).round() as u16)
                    .collect(),
            )
        };
        self.frames += 1;
        let end_ns = u64::try_from(mtime_ns.max(0)).unwrap_or(u64::MAX);
        let dwell_us = meta.dwell_us.unwrap_or(0.0);
        #[allow(
            clippy::cast_precision_loss,
            clippy::cast_possible_truncation,
            clippy::cast_sign_loss
        )]
        let scan_ns = (dwell_us * 1e3 * (m.stored_size.0 * m.stored_size.1) as f64) as u64;
        let tilt_deg = stage.map(|s| s.tilt_deg).or(meta.tilt_deg).unwrap_or(0.0);
        #[allow(clippy::cast_precision_loss)]
        let frame_meta = FrameMeta {
            frame: self.frames,
            role: request.role,
            pixel_size_um: pixel * f64::from(factor),
            dwell_us,
            stage_x_um: stage.map_or(0.0, |s| s.x_um),
            stage_y_um: stage.map_or(0.0, |s| s.y_um),
            tilt_deg,
            tilt_axis_deg: self.tilt_axis_deg,
            scan_rotation_deg: 0.0,
            scan_start_unix_ns: end_ns.saturating_sub(scan_ns),
            scan_end_unix_ns: end_ns,
        };
        let name = m
            .path
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let instrument = meta.instrument();
        instrument.clone_into(&mut self.stored_by);
        info!(
            file = %name,
            recorded_tilt_deg = meta.tilt_deg,
            pixel_size_um = pixel,
            "micrograph {name} read ({w}×{h}{})",
            if factor > 1 {
                format!(", averaged {factor}×{factor} from {}×{}", m.image.width(), m.image.height())
            } else {
                String::new()
            }
        );
        Ok(Frame {
            width: w,
            height: h,
            pixels,
            meta: frame_meta,
            received_unix_ns: unix_ns(),
            origin: Some(FrameFile {
                name,
                vendor: meta.vendor.map(|v| v.as_str().to_owned()),
                sidecar,
                recorded_tilt_deg: meta.tilt_deg,
                stored_width: u32::try_from(m.stored_size.0).unwrap_or(u32::MAX),
                stored_height: u32::try_from(m.stored_size.1).unwrap_or(u32::MAX),
                downsampled: factor,
                instrument,
            }),
        })
    }
}

impl FrameSource for WatchFolderSource {
    fn grab(&mut self, request: GrabRequest) -> GrabFuture<'_> {
        Box::pin(self.wait_for_frame(request, GrabContext::default()))
    }

    fn grab_with<'a>(
        &'a mut self,
        request: GrabRequest,
        context: GrabContext<'a>,
    ) -> GrabFuture<'a> {
        Box::pin(self.wait_for_frame(request, context))
    }

    fn identify(&mut self) -> IdentifyFuture<'_> {
        Box::pin(self.describe())
    }

    fn identity(&self) -> SourceIdentity {
        self.stored_by.clone()
    }

    fn probe(&mut self) -> ProbeFuture<'_> {
        Box::pin(self.probe_lines())
    }
}

fn log_notice(dir: &Path, notice: &Notice) {
    match notice {
        Notice::Symlink(name) => {
            warn!(dir = %dir.display(), "{name} is a symbolic link: not followed, not read");
        }
        Notice::Special(name) => {
            warn!(dir = %dir.display(), "{name} is not a regular file (FIFO, socket or device): not opened");
        }
        Notice::Oversize { name, len, max } => warn!(
            dir = %dir.display(),
            "{name} is {len} bytes, above imaging.watch_max_file_mb ({max} bytes): not read"
        ),
    }
}

/// Lists `dir` without following links: each entry's own type, size and mtime.
fn list_dir(dir: &Path) -> std::io::Result<Vec<ListedEntry>> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        let Ok(name) = entry.file_name().into_string() else {
            debug!(dir = %dir.display(), "a name that is not UTF-8: skipped");
            continue;
        };
        // Gone between the listing and the look: the next listing tells.
        let Ok(meta) = std::fs::symlink_metadata(entry.path()) else {
            continue;
        };
        let t = meta.file_type();
        let kind = if t.is_symlink() {
            EntryKind::Symlink
        } else if t.is_dir() {
            EntryKind::Dir
        } else if t.is_file() {
            EntryKind::File
        } else {
            EntryKind::Special
        };
        let mtime_ns = meta
            .modified()
            .map_or(0, |m| match m.duration_since(UNIX_EPOCH) {
                Ok(d) => i128::try_from(d.as_nanos()).unwrap_or(i128::MAX),
                Err(e) => -i128::try_from(e.duration().as_nanos()).unwrap_or(i128::MAX),
            });
        out.push(ListedEntry {
            name,
            kind,
            len: meta.len(),
            mtime_ns,
        });
    }
    Ok(out)
}

/// Why a stable candidate is not read now.
enum Unready {
    /// Not whole yet: wait for it.
    NotWhole(String),
    /// Whole but unusable: refused.
    Refused(ImagingError),
}

/// Opens a regular file without following a link or blocking on a FIFO, and reads at most
/// `max` bytes; anything else is an error.
fn read_capped(path: &Path, max: u64) -> std::io::Result<Vec<u8>> {
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
        .open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(std::io::Error::other("not a regular file"));
    }
    if meta.len() > max {
        return Err(std::io::Error::other(format!(
            "{} bytes, above the cap of {max}",
            meta.len()
        )));
    }
    let mut bytes = Vec::with_capacity(usize::try_from(meta.len()).unwrap_or(0));
    file.take(max + 1).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max {
        return Err(std::io::Error::other(format!(
            "grew above the cap of {max} bytes"
        )));
    }
    Ok(bytes)
}

fn read_and_decode(dir: &Path, c: &Candidate, max: u64) -> Result<Stored, Unready> {
    let path = dir.join(&c.image.name);
    let refused = |cause: String| {
        Unready::Refused(ImagingError::BadFile {
            file: path.clone(),
            cause,
        })
    };
    let bytes = read_capped(&path, max).map_err(|e| match e.kind() {
        // Gone or locked by the SEM PC (a share's deny-write mode): not ready yet.
        std::io::ErrorKind::NotFound | std::io::ErrorKind::PermissionDenied => {
            Unready::NotWhole(format!("cannot open it yet: {e}"))
        }
        _ => refused(e.to_string()),
    })?;
    if bytes.len() as u64 != c.image.len {
        return Err(Unready::NotWhole(format!(
            "changed while read ({} bytes listed, {} read)",
            c.image.len,
            bytes.len()
        )));
    }
    check_whole(&bytes).map_err(Unready::NotWhole)?;
    let sidecar = match &c.sidecar {
        None => None,
        Some(side) => {
            let side_path = dir.join(&side.name);
            let text = read_capped(&side_path, max)
                .map_err(|e| Unready::NotWhole(format!("cannot read {}: {e}", side.name)))?;
            let parsed = parse_sidecar(&text);
            if parsed.is_none() {
                warn!(file = %side.name, "the sidecar is neither a Hitachi nor a JEOL header: ignored");
            }
            Some((side.name.clone(), parsed))
        }
    };
    let (side_name, side_meta): (Option<String>, Option<SemMetadata>) = match sidecar {
        Some((n, m)) => (Some(n), m),
        None => (None, None),
    };
    let micrograph = micrograph_from_bytes(&path, bytes, side_meta).map_err(|e| {
        // Whole but undecodable: the SEM stores something we cannot read.
        refused(e.to_string())
    })?;
    Ok(Stored {
        micrograph,
        sidecar: side_name,
        mtime_ns: c.image.mtime_ns,
    })
}

/// What a probe says of the newest stored micrograph.
fn describe_stored(read: std::io::Result<Result<Stored, Unready>>) -> String {
    match read {
        Err(e) => format!("cannot read it: {e}"),
        Ok(Err(Unready::NotWhole(why))) => format!("not whole (still being written?): {why}"),
        Ok(Err(Unready::Refused(e))) => e.to_string(),
        Ok(Ok(stored)) => {
            let m = &stored.micrograph;
            let meta = &m.metadata;
            let id = meta.instrument();
            let mut parts = vec![
                meta.vendor.map_or_else(
                    || "no vendor metadata".to_owned(),
                    |v| v.as_str().to_owned(),
                ),
                format!(
                    "stored {}×{}, image {}×{}, {} bit",
                    m.stored_size.0,
                    m.stored_size.1,
                    m.image.width(),
                    m.image.height(),
                    m.bits_per_sample
                ),
            ];
            parts.push(meta.pixel_size_um.map_or_else(
                || "NO pixel size: such a file would be refused".to_owned(),
                |p| format!("pixel {p} µm (field {:.3} µm)", p * m.image.width() as f64),
            ));
            if let Some(t) = meta.tilt_deg {
                parts.push(format!("stage tilt {t}°"));
            }
            if let Some(d) = meta.dwell_us {
                parts.push(format!("dwell {d} µs"));
            }
            for (name, value) in [
                ("model", &id.model),
                ("version", &id.version),
                ("serial", &id.serial),
            ] {
                if !value.is_empty() {
                    parts.push(format!("{name} {value}"));
                }
            }
            parts.join(", ")
        }
    }
}

/// The smallest whole factor that brings `stored` within `wanted` (1: it already fits).
fn downsample_factor(stored: (usize, usize), wanted: (u32, u32)) -> u32 {
    let (w, h) = stored;
    let (tw, th) = (wanted.0.max(1) as usize, wanted.1.max(1) as usize);
    let f = w.div_ceil(tw).max(h.div_ceil(th)).max(1);
    u32::try_from(f).unwrap_or(u32::MAX)
}

/// Averages `factor` × `factor` blocks (a remainder at the right or bottom is dropped).
fn box_average(image: &Image, factor: u32) -> Image {
    let f = factor as usize;
    let (w, h) = (image.width() / f, image.height() / f);
    #[allow(clippy::cast_precision_loss)]
    let n = (f * f) as f32;
    Image::from_fn(w.max(1), h.max(1), |x, y| {
        let mut sum = 0.0f32;
        for yy in y * f..(y * f + f).min(image.height()) {
            for xx in x * f..(x * f + f).min(image.width()) {
                sum += image.get(xx, yy);
            }
        }
        sum / n
    })
}

fn unix_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

#[cfg(test)]
mod tests;
