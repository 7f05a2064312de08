//! The job spool: a directory that is crash-safe by construction.
//!
//! ```text
//! SPOOL/
//!   daemon.lock     flock(2) held by the one daemon that owns the spool; holds its PID
//!   daemon.json     what the daemon is doing (its last STATUS line), for `sdsem status`
//!   config.toml     the daemon's effective configuration, which `sdsem submit` validates against
//!   submit.lock     flock(2) serialising the allocation of job ids
//!   next-id         the next job id
//!   tmp/            files being written, renamed into place once complete and synced
//!   queued/ running/ done/ failed/ interrupted/ rejected/
//!                   one `<id>.json` record per job, in the directory of its state
//! ```
//!
//! Every change is one of two atomic steps: a rewrite (write `tmp/…`, fsync,
//! rename over the record, fsync the directory) or a move to another state
//! directory (rename, fsync both directories). A job leaves `running/` by
//! first rewriting its record with its final state and reason, then moving;
//! a crash between the two leaves a record whose own `state` is ahead of its
//! directory, which readers honour and recovery completes. Ids grow with
//! submission, so the oldest queued job is the one with the smallest id.
//!
//! `sdsem submit` and `sdsem status` work while the daemon runs: submit only
//! adds new files to `queued/`, status only reads.

use std::fs::{self, File, OpenOptions};
use std::io::{self, Read, Write};
use std::os::unix::fs::{DirBuilderExt, OpenOptionsExt};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, SystemTime};

use rustix::fs::{FlockOperation, flock};
use serde::{Deserialize, Serialize};

use super::job::JobSpec;
use super::utc;
use crate::config::Config;

/// The state of a job. Its record lives in the directory of the same name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    /// Waiting its turn.
    Queued,
    /// Being run now (or was, when the daemon stopped uncleanly: recovery
    /// turns it into `Interrupted`).
    Running,
    /// Finished: its run directory holds the record and the results.
    Done,
    /// Ran and failed; the reason says why.
    Failed,
    /// Stopped before the end (SIGTERM, crash, power cut); never re-run by itself.
    Interrupted,
    /// Valid when submitted but not under the configuration in force when its
    /// turn came (e.g. tilt limits narrowed by a reload); never ran.
    Rejected,
}

impl JobState {
    /// Every state, in lifecycle order.
    pub const ALL: [Self; 6] = [
        Self::Queued,
        Self::Running,
        Self::Done,
        Self::Failed,
        Self::Interrupted,
        Self::Rejected,
    ];

    /// The state's name, as in records, directory names and `sdsem status`.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Queued => "queued",
            Self::Running => "running",
            Self::Done => "done",
            Self::Failed => "failed",
            Self::Interrupted => "interrupted",
            Self::Rejected => "rejected",
        }
    }

    /// True for the states a job never leaves.
    #[must_use]
    pub fn is_final(self) -> bool {
        self.stage() == 2
    }

    /// Position in the lifecycle: queued 0, running 1, final 2. A job only moves forward.
    fn stage(self) -> u8 {
        match self {
            Self::Queued => 0,
            Self::Running => 1,
            _ => 2,
        }
    }
}

impl std::fmt::Display for JobState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A job's number in its spool, growing with submission order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(transparent)]
pub struct JobId(pub u64);

impl std::fmt::Display for JobId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.0.fmt(f)
    }
}

impl JobId {
    fn file_name(self) -> String {
        format!("{:08}.json", self.0)
    }

    fn from_file_name(name: &str) -> Option<Self> {
        let digits = name.strip_suffix(".json")?;
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        digits.parse().ok().map(Self)
    }
}

/// What the spool knows about one job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobRecord {
    pub id: JobId,
    pub state: JobState,
    pub name: String,
    /// UTC, RFC 3339.
    pub submitted: String,
    pub started: Option<String>,
    pub finished: Option<String>,
    /// The job's run directory (MCAP, micrographs, reconstruction), once started.
    pub run_dir: Option<PathBuf>,
    /// Why the job failed, was interrupted or rejected.
    pub reason: Option<String>,
    /// The job as submitted.
    pub job: JobSpec,
}

/// What the daemon last said it was doing (`daemon.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DaemonStatus {
    pub pid: u32,
    /// `starting`, `ready` or `stopped`.
    pub state: String,
    /// The daemon's current STATUS line.
    pub status: String,
    /// UTC, RFC 3339.
    pub updated: String,
}

/// A file in a state directory that is not a readable job record.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Unreadable {
    pub path: PathBuf,
    pub cause: String,
}

/// Every job in the spool, oldest first, and anything that could not be read.
#[derive(Debug, Clone, Default)]
pub struct Listing {
    pub jobs: Vec<JobRecord>,
    pub unreadable: Vec<Unreadable>,
}

/// Why the spool cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum SpoolError {
    #[error("spool {}: cannot {action} {}: {source}{}", spool.display(), path.display(), remedy(source))]
    Io {
        spool: PathBuf,
        action: &'static str,
        path: PathBuf,
        source: io::Error,
    },
    #[error(
        "spool {} is in use by another sdsem daemon (PID {holder}); stop it first \
         (systemctl stop sdsem) or give this one its own --spool",
        spool.display()
    )]
    Locked { spool: PathBuf, holder: String },
    #[error("spool {}: {} is not a job record: {cause}", spool.display(), path.display())]
    Corrupt {
        spool: PathBuf,
        path: PathBuf,
        cause: String,
    },
}

fn remedy(e: &io::Error) -> &'static str {
    match e.kind() {
        io::ErrorKind::PermissionDenied => {
            "; check you may write there (members of the group owning the spool, `sdsem` for \
             the packaged service, may submit)"
        }
        io::ErrorKind::StorageFull => "; the disk is full",
        _ => "",
    }
}

/// Temp files older than this are left-overs of a crash and are removed at recovery.
const STALE_TMP: Duration = Duration::from_secs(600);

/// The reason recorded for a job found running when a daemon starts.
pub const CRASH_REASON: &str =
    "daemon stopped unexpectedly (crash or power cut) while this job ran; not re-run";

/// A spool directory. Anyone may submit and list; only the [`OwnedSpool`]
/// (the daemon holding the lock) moves jobs between states.
#[derive(Debug, Clone)]
pub struct Spool {
    root: PathBuf,
}

impl Spool {
    /// Opens a spool, creating its layout when missing. Directories are
    /// created group-writable (mode 775 less the umask; the unit's `UMask=0002`
    /// keeps it) so that members of the spool's group may submit.
    ///
    /// # Errors
    /// [`SpoolError::Io`] naming the directory that cannot be created.
    pub fn open(root: &Path) -> Result<Self, SpoolError> {
        let spool = Self {
            root: root.to_owned(),
        };
        let mut builder = fs::DirBuilder::new();
        builder.recursive(true).mode(0o775);
        for dir in std::iter::once(spool.root.clone())
            .chain(std::iter::once(spool.root.join("tmp")))
            .chain(JobState::ALL.iter().map(|s| spool.state_dir(*s)))
        {
            if !dir.is_dir() {
                builder
                    .create(&dir)
                    .map_err(|e| spool.io("create directory", &dir, e))?;
            }
        }
        Ok(spool)
    }

    /// A spool that must exist already; creates nothing (for readers such as
    /// `sdsem status`, who may not be allowed to write).
    ///
    /// # Errors
    /// [`SpoolError::Io`] when `root` holds no spool.
    pub fn existing(root: &Path) -> Result<Self, SpoolError> {
        let spool = Self {
            root: root.to_owned(),
        };
        let queued = spool.state_dir(JobState::Queued);
        match fs::metadata(&queued) {
            Ok(m) if m.is_dir() => Ok(spool),
            Ok(_) => Err(spool.io("open", &queued, io::ErrorKind::NotADirectory.into())),
            Err(e) => Err(spool.io("open", &queued, e)),
        }
    }

    /// The spool's directory.
    #[must_use]
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Where the daemon keeps its effective configuration.
    #[must_use]
    pub fn config_snapshot_path(&self) -> PathBuf {
        self.root.join("config.toml")
    }

    fn state_dir(&self, state: JobState) -> PathBuf {
        self.root.join(state.as_str())
    }

    fn record_path(&self, state: JobState, id: JobId) -> PathBuf {
        self.state_dir(state).join(id.file_name())
    }

    fn io(&self, action: &'static str, path: &Path, source: io::Error) -> SpoolError {
        SpoolError::Io {
            spool: self.root.clone(),
            action,
            path: path.to_owned(),
            source,
        }
    }

    /// Queues a job that was validated by the caller. Safe to call while the
    /// daemon runs and from several processes at once.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be written.
    pub fn submit(&self, job: JobSpec, now: SystemTime) -> Result<JobRecord, SpoolError> {
        let lock_path = self.root.join("submit.lock");
        let lock = open_lock_file(&lock_path).map_err(|e| self.io("open", &lock_path, e))?;
        flock(&lock, FlockOperation::LockExclusive)
            .map_err(|e| self.io("lock", &lock_path, e.into()))?;
        let next_path = self.root.join("next-id");
        let counted = match fs::read_to_string(&next_path) {
            Ok(text) => text.trim().parse::<u64>().unwrap_or(1),
            Err(e) if e.kind() == io::ErrorKind::NotFound => 1,
            Err(e) => return Err(self.io("read", &next_path, e)),
        };
        // The counter may be older than the records (crash between the two
        // writes below): never reuse an id that exists.
        let id = JobId(counted.max(self.highest_id()?.map_or(1, |h| h.0 + 1)));
        let record = JobRecord {
            id,
            state: JobState::Queued,
            name: job.name.clone(),
            submitted: utc::rfc3339(now),
            started: None,
            finished: None,
            run_dir: None,
            reason: None,
            job,
        };
        self.write_record(JobState::Queued, &record)?;
        self.write_atomic(&next_path, format!("{}\n", id.0 + 1).as_bytes())?;
        drop(lock);
        Ok(record)
    }

    fn highest_id(&self) -> Result<Option<JobId>, SpoolError> {
        let mut highest = None;
        for state in JobState::ALL {
            for (id, _) in self.entries(state)? {
                highest = highest.max(id);
            }
        }
        Ok(highest)
    }

    /// `(id, path)` of every file in a state directory; id `None` for a file
    /// that is not named like a record.
    fn entries(&self, state: JobState) -> Result<Vec<(Option<JobId>, PathBuf)>, SpoolError> {
        let dir = self.state_dir(state);
        let read = match fs::read_dir(&dir) {
            Ok(read) => read,
            // A directory nobody created yet holds no job.
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(self.io("list", &dir, e)),
        };
        let mut out = Vec::new();
        for entry in read {
            let entry = entry.map_err(|e| self.io("list", &dir, e))?;
            let name = entry.file_name();
            let name = name.to_string_lossy();
            if name.starts_with('.') {
                continue;
            }
            out.push((JobId::from_file_name(&name), entry.path()));
        }
        out.sort();
        Ok(out)
    }

    fn read_record(&self, path: &Path) -> Result<Option<JobRecord>, SpoolError> {
        let text = match fs::read(path) {
            Ok(t) => t,
            // Moved on by the daemon between listing and reading.
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(self.io("read", path, e)),
        };
        serde_json::from_slice(&text)
            .map(Some)
            .map_err(|e| SpoolError::Corrupt {
                spool: self.root.clone(),
                path: path.to_owned(),
                cause: e.to_string(),
            })
    }

    /// Every job, oldest first. A job being moved while we list is seen once,
    /// in its later state: directories are read in lifecycle order, jobs only
    /// move forward, and a record whose own state is ahead of its directory
    /// (an interrupted transition) counts in its own state.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when a directory cannot be read.
    pub fn list(&self) -> Result<Listing, SpoolError> {
        let mut by_id: std::collections::BTreeMap<JobId, JobRecord> = Default::default();
        let mut unreadable = Vec::new();
        for state in JobState::ALL {
            for (id, path) in self.entries(state)? {
                if id.is_none() {
                    unreadable.push(Unreadable {
                        cause: "not named <id>.json".into(),
                        path,
                    });
                    continue;
                }
                match self.read_record(&path) {
                    Ok(Some(mut record)) => {
                        record.state = effective_state(state, record.state);
                        let newer = by_id
                            .get(&record.id)
                            .is_none_or(|seen| seen.state.stage() <= record.state.stage());
                        if newer {
                            by_id.insert(record.id, record);
                        }
                    }
                    Ok(None) => {}
                    Err(SpoolError::Corrupt { cause, .. }) => {
                        unreadable.push(Unreadable { path, cause });
                    }
                    Err(e) => return Err(e),
                }
            }
        }
        Ok(Listing {
            jobs: by_id.into_values().collect(),
            unreadable,
        })
    }

    /// What the daemon last reported, if one ever ran on this spool.
    #[must_use]
    pub fn daemon_status(&self) -> Option<DaemonStatus> {
        let text = fs::read(self.root.join("daemon.json")).ok()?;
        serde_json::from_slice(&text).ok()
    }

    /// Takes ownership of the spool for a daemon: only one at a time. The
    /// lock is released when the [`OwnedSpool`] is dropped or the process ends
    /// (even by SIGKILL or a power cut: flock locks die with their holder).
    ///
    /// # Errors
    /// [`SpoolError::Locked`] naming the PID of the daemon that holds it.
    pub fn lock(self) -> Result<OwnedSpool, SpoolError> {
        let path = self.root.join("daemon.lock");
        let mut file = OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .mode(0o644)
            .open(&path)
            .map_err(|e| self.io("open", &path, e))?;
        if let Err(e) = flock(&file, FlockOperation::NonBlockingLockExclusive) {
            if e == rustix::io::Errno::WOULDBLOCK {
                let mut holder = String::new();
                // The holder writes its PID right after locking; it may not have yet.
                let _ = file.read_to_string(&mut holder);
                let holder = holder.trim();
                return Err(SpoolError::Locked {
                    spool: self.root.clone(),
                    holder: if holder.is_empty() {
                        "unknown".into()
                    } else {
                        holder.to_owned()
                    },
                });
            }
            return Err(self.io("lock", &path, e.into()));
        }
        let write_pid = |file: &mut File| -> io::Result<()> {
            file.set_len(0)?;
            file.write_all(format!("{}\n", std::process::id()).as_bytes())?;
            file.sync_all()
        };
        write_pid(&mut file).map_err(|e| self.io("write", &path, e))?;
        Ok(OwnedSpool {
            spool: self,
            _lock: file,
        })
    }

    fn write_record(&self, state: JobState, record: &JobRecord) -> Result<(), SpoolError> {
        let bytes = serde_json::to_vec_pretty(record).map_err(|e| SpoolError::Corrupt {
            spool: self.root.clone(),
            path: self.record_path(state, record.id),
            cause: e.to_string(),
        })?;
        self.write_atomic(&self.record_path(state, record.id), &bytes)
    }

    /// Writes `bytes` to `target` so that readers and a crash see either the
    /// old or the new content, never a part.
    fn write_atomic(&self, target: &Path, bytes: &[u8]) -> Result<(), SpoolError> {
        static COUNTER: AtomicU64 = AtomicU64::new(0);
        let stem = target
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let tmp = self.root.join("tmp").join(format!(
            "{stem}.{}.{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        ));
        let write = || -> io::Result<()> {
            let mut file = OpenOptions::new()
                .write(true)
                .create_new(true)
                .mode(RECORD_MODE)
                .open(&tmp)?;
            // Whatever the writer's umask: a submitter with umask 077 would
            // otherwise queue a record the daemon cannot read (and stop on).
            file.set_permissions(std::os::unix::fs::PermissionsExt::from_mode(RECORD_MODE))?;
            file.write_all(bytes)?;
            file.sync_all()
        };
        if let Err(e) = write().and_then(|()| fs::rename(&tmp, target)) {
            let _ = fs::remove_file(&tmp);
            return Err(self.io("write", target, e));
        }
        sync_parent(target).map_err(|e| self.io("sync", target, e))
    }

    fn move_record(&self, id: JobId, from: JobState, to: JobState) -> Result<(), SpoolError> {
        let src = self.record_path(from, id);
        let dst = self.record_path(to, id);
        fs::rename(&src, &dst).map_err(|e| self.io("move", &src, e))?;
        sync_parent(&dst).map_err(|e| self.io("sync", &dst, e))?;
        sync_parent(&src).map_err(|e| self.io("sync", &src, e))
    }
}

/// The state a reader believes: a record written ahead of its move counts in
/// its own state, and one moved but not yet rewritten counts where it lies.
fn effective_state(dir: JobState, recorded: JobState) -> JobState {
    if recorded.stage() > dir.stage() {
        recorded
    } else {
        dir
    }
}

/// Mode of every file the spool writes: readable by the daemon and by
/// `sdsem status` whoever wrote it (the spool directories keep others out).
const RECORD_MODE: u32 = 0o664;

fn open_lock_file(path: &Path) -> io::Result<File> {
    // Read-only suffices for flock, and works for submitters who cannot write
    // a lock file created by someone else.
    match File::open(path) {
        Err(e) if e.kind() == io::ErrorKind::NotFound => OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .mode(0o664)
            .open(path),
        other => other,
    }
}

fn sync_parent(path: &Path) -> io::Result<()> {
    let dir = path.parent().unwrap_or_else(|| Path::new("."));
    File::open(dir)?.sync_all()
}

/// A spool owned by this daemon (the lock is held while this value lives).
#[derive(Debug)]
pub struct OwnedSpool {
    spool: Spool,
    _lock: File,
}

impl std::ops::Deref for OwnedSpool {
    type Target = Spool;
    fn deref(&self) -> &Spool {
        &self.spool
    }
}

/// What recovery found and did.
#[derive(Debug, Clone, Default)]
pub struct Recovery {
    /// Jobs that were running when the previous daemon died, now `interrupted`.
    pub interrupted: Vec<JobRecord>,
    /// Transitions a crash had cut short, now completed.
    pub completed_moves: usize,
    /// Records that could not be read, moved out of `queued/` and `running/`
    /// into `rejected/` (with the extension `.unreadable`) so they block nothing.
    pub quarantined: Vec<Unreadable>,
}

impl OwnedSpool {
    /// Puts the spool back in order after a crash or power cut: a job found
    /// running is marked interrupted (never re-run silently), transitions cut
    /// short are completed, stale temp files are removed.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be written.
    pub fn recover(&self, now: SystemTime) -> Result<Recovery, SpoolError> {
        let mut recovery = Recovery::default();
        let tmp = self.root.join("tmp");
        for entry in fs::read_dir(&tmp).map_err(|e| self.io("list", &tmp, e))? {
            let path = entry.map_err(|e| self.io("list", &tmp, e))?.path();
            let stale = fs::metadata(&path)
                .and_then(|m| m.modified())
                .is_ok_and(|t| now.duration_since(t).is_ok_and(|age| age > STALE_TMP));
            if stale {
                fs::remove_file(&path).map_err(|e| self.io("remove", &path, e))?;
            }
        }
        for dir_state in [JobState::Queued, JobState::Running] {
            for (id, path) in self.entries(dir_state)? {
                let record = match (id, self.read_record(&path)) {
                    (Some(_), Ok(Some(record))) => record,
                    (Some(_), Ok(None)) => continue,
                    (None, _) => {
                        recovery
                            .quarantined
                            .push(self.quarantine(&path, "not named <id>.json")?);
                        continue;
                    }
                    (Some(_), Err(SpoolError::Corrupt { cause, .. })) => {
                        recovery.quarantined.push(self.quarantine(&path, &cause)?);
                        continue;
                    }
                    (Some(_), Err(e)) => return Err(e),
                };
                if record.state.stage() > dir_state.stage() {
                    self.move_record(record.id, dir_state, record.state)?;
                    recovery.completed_moves += 1;
                } else if dir_state == JobState::Running {
                    let record = JobRecord {
                        state: JobState::Running,
                        ..record
                    };
                    let record = self.finish(
                        &record,
                        JobState::Interrupted,
                        Some(CRASH_REASON.to_owned()),
                        now,
                    )?;
                    recovery.interrupted.push(record);
                }
            }
        }
        Ok(recovery)
    }

    fn quarantine(&self, path: &Path, cause: &str) -> Result<Unreadable, SpoolError> {
        let name = path
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let dst = self
            .state_dir(JobState::Rejected)
            .join(format!("{name}.unreadable"));
        fs::rename(path, &dst).map_err(|e| self.io("move", path, e))?;
        sync_parent(&dst).map_err(|e| self.io("sync", &dst, e))?;
        Ok(Unreadable {
            path: dst,
            cause: cause.to_owned(),
        })
    }

    /// The oldest queued job, if any. Unreadable records are quarantined
    /// (see [`Recovery::quarantined`]) and returned beside it so the caller can log them.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be read.
    pub fn next_queued(&self) -> Result<(Option<JobRecord>, Vec<Unreadable>), SpoolError> {
        let mut quarantined = Vec::new();
        for (id, path) in self.entries(JobState::Queued)? {
            match (id, self.read_record(&path)) {
                (Some(_), Ok(Some(record))) if record.state == JobState::Queued => {
                    return Ok((Some(record), quarantined));
                }
                (Some(_), Ok(Some(record))) => {
                    // A rejection cut short by a crash: finish it.
                    self.move_record(record.id, JobState::Queued, record.state)?;
                }
                (Some(_), Ok(None)) => {}
                (None, _) => quarantined.push(self.quarantine(&path, "not named <id>.json")?),
                (Some(_), Err(SpoolError::Corrupt { cause, .. })) => {
                    quarantined.push(self.quarantine(&path, &cause)?);
                }
                (Some(_), Err(e)) => return Err(e),
            }
        }
        Ok((None, quarantined))
    }

    /// Number of queued jobs.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be read.
    pub fn queued_count(&self) -> Result<usize, SpoolError> {
        Ok(self
            .entries(JobState::Queued)?
            .iter()
            .filter(|(id, _)| id.is_some())
            .count())
    }

    /// Marks a queued job running in `run_dir`.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be written.
    pub fn start(
        &self,
        record: &JobRecord,
        run_dir: &Path,
        now: SystemTime,
    ) -> Result<JobRecord, SpoolError> {
        self.move_record(record.id, JobState::Queued, JobState::Running)?;
        let running = JobRecord {
            state: JobState::Running,
            started: Some(utc::rfc3339(now)),
            run_dir: Some(run_dir.to_owned()),
            ..record.clone()
        };
        self.write_record(JobState::Running, &running)?;
        Ok(running)
    }

    /// Moves a queued or running job to its final state with its reason.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be written.
    ///
    /// # Panics
    /// If `state` is not final (a programming error).
    pub fn finish(
        &self,
        record: &JobRecord,
        state: JobState,
        reason: Option<String>,
        now: SystemTime,
    ) -> Result<JobRecord, SpoolError> {
        assert!(state.is_final(), "finish() into non-final state {state}");
        let from = record.state;
        let finished = JobRecord {
            state,
            finished: Some(utc::rfc3339(now)),
            reason,
            ..record.clone()
        };
        // Record first, then move: a crash in between leaves a record ahead of
        // its directory, which readers honour and recovery completes.
        self.write_record(from, &finished)?;
        self.move_record(record.id, from, state)?;
        Ok(finished)
    }

    /// Publishes what the daemon is doing, for `sdsem status`.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be written.
    pub fn write_daemon_status(&self, status: &DaemonStatus) -> Result<(), SpoolError> {
        let path = self.root.join("daemon.json");
        let bytes = serde_json::to_vec_pretty(status).map_err(|e| SpoolError::Corrupt {
            spool: self.root.clone(),
            path: path.clone(),
            cause: e.to_string(),
        })?;
        self.write_atomic(&path, &bytes)
    }

    /// Publishes the daemon's effective configuration, which `sdsem submit`
    /// validates new jobs against.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be written.
    pub fn write_config_snapshot(&self, config: &Config) -> Result<(), SpoolError> {
        let text = format!(
            "# The running sdsem daemon's effective configuration (written at start and on \
             reload).\n# `sdsem submit` validates jobs against it. Edits here have no effect.\n{}",
            config.to_toml()
        );
        self.write_atomic(&self.config_snapshot_path(), text.as_bytes())
    }
}

#[cfg(test)]
mod tests {
    use std::time::UNIX_EPOCH;

    use super::*;

    #[test]
    fn records_are_readable_by_the_daemon_whatever_the_submitters_umask() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        // The process umask is shared by the test threads; 0o022 (a common
        // default, and no narrower than theirs) would not show the fault.
        let old = rustix::process::umask(rustix::fs::Mode::from_raw_mode(0o077));
        let record = spool.submit(spec("private"), at(0));
        rustix::process::umask(old);
        let record = record.unwrap();
        let path = spool.record_path(JobState::Queued, record.id);
        let mode = fs::metadata(&path).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o664, "{}", path.display());
    }

    fn spec(name: &str) -> JobSpec {
        JobSpec::parse(&format!("name = {name:?}\nstart_tilt = 0\nend_tilt = 5\n")).unwrap()
    }

    fn at(s: u64) -> SystemTime {
        UNIX_EPOCH + Duration::from_secs(1_740_837_909 + s)
    }

    fn states(spool: &Spool) -> Vec<(u64, String, JobState)> {
        spool
            .list()
            .unwrap()
            .jobs
            .into_iter()
            .map(|j| (j.id.0, j.name, j.state))
            .collect()
    }

    #[test]
    fn submit_orders_jobs_and_transitions_move_them() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        for name in ["a", "b", "c"] {
            spool.submit(spec(name), at(0)).unwrap();
        }
        let owned = spool.clone().lock().unwrap();
        let (first, _) = owned.next_queued().unwrap();
        let first = first.unwrap();
        assert_eq!(first.name, "a");
        let running = owned.start(&first, Path::new("/runs/a"), at(1)).unwrap();
        assert_eq!(owned.queued_count().unwrap(), 2);
        assert_eq!(running.started.as_deref(), Some("2025-03-01T14:05:10Z"));
        owned
            .finish(&running, JobState::Failed, Some("link lost".into()), at(2))
            .unwrap();
        let (second, _) = owned.next_queued().unwrap();
        owned
            .finish(
                &second.unwrap(),
                JobState::Rejected,
                Some("limits".into()),
                at(3),
            )
            .unwrap();
        assert_eq!(
            states(&spool),
            [
                (1, "a".into(), JobState::Failed),
                (2, "b".into(), JobState::Rejected),
                (3, "c".into(), JobState::Queued)
            ]
        );
        let failed = &spool.list().unwrap().jobs[0];
        assert_eq!(failed.reason.as_deref(), Some("link lost"));
        assert_eq!(failed.run_dir.as_deref(), Some(Path::new("/runs/a")));
        assert!(dir.path().join("failed/00000001.json").is_file());
        assert_eq!(fs::read_dir(dir.path().join("tmp")).unwrap().count(), 0);
    }

    #[test]
    fn ids_are_never_reused_even_without_the_counter() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        spool.submit(spec("a"), at(0)).unwrap();
        spool.submit(spec("b"), at(0)).unwrap();
        fs::remove_file(dir.path().join("next-id")).unwrap();
        assert_eq!(spool.submit(spec("c"), at(0)).unwrap().id, JobId(3));
        // Deleting old records does not reuse their ids either.
        fs::remove_file(dir.path().join("queued/00000003.json")).unwrap();
        assert_eq!(spool.submit(spec("d"), at(0)).unwrap().id, JobId(4));
    }

    #[test]
    fn concurrent_submitters_get_distinct_ids() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        let ids: Vec<u64> = std::thread::scope(|s| {
            let handles: Vec<_> = (0..8)
                .map(|i| {
                    let spool = spool.clone();
                    s.spawn(move || {
                        (0..5)
                            .map(|k| {
                                spool
                                    .submit(spec(&format!("j{i}-{k}")), at(0))
                                    .unwrap()
                                    .id
                                    .0
                            })
                            .collect::<Vec<_>>()
                    })
                })
                .collect();
            handles
                .into_iter()
                .flat_map(|h| h.join().unwrap())
                .collect()
        });
        let mut sorted = ids.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted, (1..=40).collect::<Vec<_>>());
    }

    #[test]
    fn a_job_left_running_by_a_crash_is_interrupted_and_the_queue_goes_on() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        spool.submit(spec("a"), at(0)).unwrap();
        spool.submit(spec("b"), at(0)).unwrap();
        {
            let owned = spool.clone().lock().unwrap();
            let a = owned.next_queued().unwrap().0.unwrap();
            owned.start(&a, Path::new("/runs/a"), at(1)).unwrap();
            // Power cut: the daemon vanishes without finishing `a`.
        }
        let owned = spool.clone().lock().unwrap();
        let recovery = owned.recover(at(100)).unwrap();
        assert_eq!(recovery.interrupted.len(), 1);
        let a = &recovery.interrupted[0];
        assert_eq!((a.name.as_str(), a.state), ("a", JobState::Interrupted));
        assert_eq!(a.reason.as_deref(), Some(CRASH_REASON));
        assert_eq!(a.run_dir.as_deref(), Some(Path::new("/runs/a")));
        // Nothing is re-run: the next job is `b`.
        assert_eq!(owned.next_queued().unwrap().0.unwrap().name, "b");
        // A second recovery finds nothing more to do.
        let again = owned.recover(at(200)).unwrap();
        assert!(again.interrupted.is_empty() && again.completed_moves == 0);
    }

    #[test]
    fn a_crash_between_record_and_move_is_completed_not_undone() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        spool.submit(spec("a"), at(0)).unwrap();
        let owned = spool.clone().lock().unwrap();
        let a = owned.next_queued().unwrap().0.unwrap();
        let running = owned.start(&a, Path::new("/runs/a"), at(1)).unwrap();
        // The final record was written, then power went before the rename.
        let done = JobRecord {
            state: JobState::Done,
            finished: Some("x".into()),
            ..running
        };
        owned.write_record(JobState::Running, &done).unwrap();
        assert_eq!(states(&spool), [(1, "a".into(), JobState::Done)]);
        let recovery = owned.recover(at(2)).unwrap();
        assert!(recovery.interrupted.is_empty());
        assert_eq!(recovery.completed_moves, 1);
        assert!(dir.path().join("done/00000001.json").is_file());
        assert!(!dir.path().join("running/00000001.json").exists());
    }

    #[test]
    fn a_job_seen_in_two_directories_counts_once_in_its_later_state() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        let a = spool.submit(spec("a"), at(0)).unwrap();
        // As a reader racing a move would see it: in queued/ and in done/.
        fs::copy(
            dir.path().join("queued/00000001.json"),
            dir.path().join("done/00000001.json"),
        )
        .unwrap();
        assert_eq!(states(&spool), [(a.id.0, "a".into(), JobState::Done)]);
    }

    #[test]
    fn unreadable_records_are_reported_and_quarantined() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        fs::write(dir.path().join("queued/00000007.json"), "{ not json").unwrap();
        spool.submit(spec("b"), at(0)).unwrap();
        let listing = spool.list().unwrap();
        assert_eq!(listing.jobs.len(), 1);
        assert_eq!(listing.unreadable.len(), 1);
        let owned = spool.clone().lock().unwrap();
        let (next, quarantined) = owned.next_queued().unwrap();
        assert_eq!(quarantined.len(), 1);
        // `b` got id 8 (after the 7 on disk) and runs despite the bad file before it.
        assert_eq!(next.unwrap().id, JobId(8));
        assert!(
            dir.path()
                .join("rejected/00000007.json.unreadable")
                .is_file()
        );
    }

    #[test]
    fn a_second_owner_is_refused_with_the_holders_pid() {
        let dir = tempfile::tempdir().unwrap();
        let first = Spool::open(dir.path()).unwrap().lock().unwrap();
        let err = Spool::open(dir.path()).unwrap().lock().unwrap_err();
        let msg = err.to_string();
        assert!(
            msg.contains(&format!("PID {}", std::process::id())),
            "{msg}"
        );
        assert!(msg.contains("in use by another sdsem daemon"), "{msg}");
        drop(first);
        Spool::open(dir.path()).unwrap().lock().unwrap();
    }

    #[test]
    fn stale_temp_files_are_removed_at_recovery() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        fs::write(dir.path().join("tmp/00000001.json.1.0"), "partial").unwrap();
        let owned = spool.lock().unwrap();
        owned.recover(SystemTime::now()).unwrap();
        assert!(
            dir.path().join("tmp/00000001.json.1.0").exists(),
            "fresh: may be a submit in progress"
        );
        owned
            .recover(SystemTime::now() + Duration::from_secs(3600))
            .unwrap();
        assert!(!dir.path().join("tmp/00000001.json.1.0").exists());
    }
}
