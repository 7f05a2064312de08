//! The job spool: a directory that is crash-safe by construction, and that trusts
//! nothing a submitter put in it.
//!
//! ```text
//! SPOOL/            0750  owned by the daemon; its flock(2) on this directory = ownership
//!   daemon.lock     0640  the PID of the daemon that holds the spool (informational)
//!   daemon.json     0640  what the daemon is doing, its warnings, the last stage check
//!   config.toml     0640  the daemon's effective configuration, which `sdsem submit` validates against
//!   next-id         0660  the next job id, rewritten in place under the submit lock
//!   queued/         1770  sticky: a submitter adds its own records; flock(2) on it serialises submits
//!   running/ done/ failed/ interrupted/ rejected/
//!                   0750  one `<id>.json` record per job, in the directory of its state; daemon only
//!   quarantine/     0750  entries of queued/ that are not valid records, each with `<name>.reason`
//! ```
//!
//! Every change is one of two atomic steps: a rewrite (the one atomic writer: a temporary
//! file created exclusively beside the record, fsync, rename, fsync the directory) or a move
//! to another state directory (rename, fsync both directories). A job leaves `running/` by
//! first rewriting its record with its final state and reason, then moving; a crash between
//! the two leaves a record whose own `state` is ahead of its directory, which readers honour
//! and recovery completes. Ids grow with submission, so the oldest queued job is the one
//! with the smallest id; an id that exists is never given again nor overwritten.
//!
//! Every entry is read without following a link and without blocking, as a regular file
//! under a size cap ([`super::untrusted`]); whatever fails (a FIFO, a directory, a link,
//! an unreadable or huge file, garbage, a record that lies about its id or state) is moved
//! to `quarantine/` with its reason, which `sdsem status` shows. Nothing in the spool can
//! make the daemon block or exit.

use std::collections::HashSet;
use std::ffi::{OsStr, OsString};
use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::os::fd::{AsFd, OwnedFd};
use std::os::unix::ffi::OsStrExt;
use std::os::unix::fs::{DirBuilderExt, FileExt};
use std::path::{Path, PathBuf};
use std::sync::{Mutex, PoisonError};
use std::time::{Duration, Instant, SystemTime};

use rustix::fs::{FlockOperation, Mode, OFlags, RenameFlags, flock};
use serde::{Deserialize, Serialize};

use super::job::JobSpec;
use super::untrusted::{Links, UntrustedError, read_capped_at};
use super::utc;
use crate::acquisition::run_dir::printable;
use crate::config::Config;
use crate::export::atomic::{Existing, open_dir, write_atomic_at};

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
    /// Refused by the daemon when its turn came (it no longer fits the configuration in
    /// force, or its record was not one `sdsem submit` would have queued); never ran.
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

    /// The id of a record's file name, which must be the canonical one (`00000010.json`,
    /// not `0000010.json`): one file name per id.
    fn from_file_name(name: &OsStr) -> Option<Self> {
        let digits = name.as_bytes().strip_suffix(b".json")?;
        if digits.is_empty() || digits.len() > 20 || !digits.iter().all(u8::is_ascii_digit) {
            return None;
        }
        let id = Self(std::str::from_utf8(digits).ok()?.parse().ok()?);
        (id.file_name().as_bytes() == name.as_bytes()).then_some(id)
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
    /// `starting`, `ready` or `stopped`; anything but `stopped` at the next start means
    /// the daemon ended uncleanly.
    pub state: String,
    /// The daemon's current STATUS line.
    pub status: String,
    /// UTC, RFC 3339.
    pub updated: String,
    /// What the daemon noticed and wants a human to know (its lock file tampered with, …).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// The stage check after the last unclean end, if there was one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stage_check: Option<StageCheck>,
}

/// The check of the stage after an unclean end (kill -9, crash, watchdog, power cut).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageCheck {
    /// When the unclean end was noticed (UTC, RFC 3339).
    pub noticed: String,
    /// How it was noticed.
    pub cause: String,
    /// The tilt the stage was found at, degrees, once read.
    pub found_tilt_deg: Option<f64>,
    /// What was done or is awaited, in one line.
    pub action: String,
    /// True until the stage is known to be at its safe tilt; no job runs meanwhile.
    pub pending: bool,
    /// When it stopped being pending (UTC, RFC 3339).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resolved: Option<String>,
}

/// An entry of the spool that is not a job record.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Unreadable {
    /// Where it is now (in `quarantine/` once set aside).
    pub path: PathBuf,
    /// Its original name, printable (control characters escaped, cut short).
    pub name: String,
    pub cause: String,
}

/// Every job in the spool, oldest first, and anything that could not be read.
#[derive(Debug, Clone, Default)]
pub struct Listing {
    pub jobs: Vec<JobRecord>,
    /// Entries of the state directories that are not job records (not yet set aside).
    pub unreadable: Vec<Unreadable>,
    /// The latest entries set aside in `quarantine/`, oldest first.
    pub set_aside: Vec<Unreadable>,
    /// How many entries `quarantine/` holds in all.
    pub set_aside_total: usize,
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
    #[error("spool {}: {} is not usable: {cause}", spool.display(), path.display())]
    Corrupt {
        spool: PathBuf,
        path: PathBuf,
        cause: String,
    },
    #[error(
        "spool {}: another submission has held the lock on queued/ for {}s; try again, or \
         find the process holding it (fuser -v {}/queued)",
        spool.display(), SUBMIT_LOCK_WAIT.as_secs(), spool.display()
    )]
    Busy { spool: PathBuf },
    #[error(
        "spool {}: job ids are exhausted (next-id would pass {}); nothing was queued: \
         archive the spool and start a new one",
        spool.display(), u64::MAX
    )]
    IdsExhausted { spool: PathBuf },
}

fn remedy(e: &io::Error) -> &'static str {
    match e.kind() {
        io::ErrorKind::PermissionDenied => {
            "; check you may write there (members of the group owning the spool, `sdsem` for \
             the packaged service, may submit)"
        }
        _ if is_disk_full(e) => "; the disk is full",
        _ => "",
    }
}

/// True for "no space left on device" and "disk quota exceeded".
#[must_use]
pub fn is_disk_full(e: &io::Error) -> bool {
    matches!(
        e.raw_os_error(),
        Some(code) if code == rustix::io::Errno::NOSPC.raw_os_error()
            || code == rustix::io::Errno::DQUOT.raw_os_error()
    )
}

impl SpoolError {
    /// True when the cause is a full disk (or quota).
    #[must_use]
    pub fn is_disk_full(&self) -> bool {
        matches!(self, Self::Io { source, .. } if is_disk_full(source))
    }
}

/// Temp files older than this are left-overs of a crash and are removed at recovery.
const STALE_TMP: Duration = Duration::from_secs(600);
/// Largest job record read, bytes (a job file is at most 64 KiB).
const RECORD_CAP: u64 = 256 * 1024;
/// Largest `daemon.json`, `.reason` or `next-id` read, bytes.
const SMALL_CAP: u64 = 64 * 1024;
/// Largest configuration snapshot read, bytes.
const SNAPSHOT_CAP: u64 = 1024 * 1024;
/// Longest reason kept in a record, bytes.
const REASON_CAP: usize = 2000;
/// Spaces after a running record's JSON: room to write its end in place on a full disk.
const RESERVE: usize = 4096;
/// How long `submit` waits for another submission's lock.
const SUBMIT_LOCK_WAIT: Duration = Duration::from_secs(10);
/// Entries of `quarantine/` that [`Spool::list`] reads.
const SET_ASIDE_SHOWN: usize = 50;

/// Mode of every record and file the spool writes: the daemon and `sdsem status` read it
/// through the group; only its writer may change it.
const RECORD_MODE: u32 = 0o640;
/// `next-id`: group members rewrite it (in place) when they submit.
const COUNTER_MODE: u32 = 0o660;
/// The spool and every directory but `queued/`: only the daemon writes them.
const PRIVATE_DIR: u32 = 0o750;
/// `queued/`: group members add records; sticky, so none can move or delete another's.
const DROP_DIR: u32 = 0o1770;

const QUARANTINE: &str = "quarantine";
/// In `queued/`: an operator's acknowledgement after an unclean end (`sdsem daemon --ack`).
const ACK: &str = ".ack";

/// The reason recorded for a job found running when a daemon starts.
pub const CRASH_REASON: &str =
    "daemon stopped unexpectedly (crash or power cut) while this job ran; not re-run";

/// A spool directory. Anyone may submit and list; only the [`OwnedSpool`]
/// (the daemon holding the lock) moves jobs between states.
#[derive(Debug, Clone)]
pub struct Spool {
    root: PathBuf,
}

/// One entry of a state directory.
struct Entry {
    id: Option<JobId>,
    name: OsString,
}

impl Spool {
    /// Opens a spool, creating its layout when missing, with the modes above whatever the
    /// umask (the daemon corrects them on the directories it owns when it takes the spool).
    ///
    /// # Errors
    /// [`SpoolError::Io`] naming the directory that cannot be created.
    pub fn open(root: &Path) -> Result<Self, SpoolError> {
        let spool = Self {
            root: root.to_owned(),
        };
        for (dir, mode) in spool.layout() {
            match fs::symlink_metadata(&dir) {
                Ok(m) if m.is_dir() => continue,
                Ok(_) => {
                    return Err(spool.io("use", &dir, io::ErrorKind::NotADirectory.into()));
                }
                Err(e) if e.kind() == io::ErrorKind::NotFound => {}
                Err(e) => return Err(spool.io("open", &dir, e)),
            }
            fs::DirBuilder::new()
                .recursive(true)
                .mode(mode & 0o777)
                .create(&dir)
                .and_then(|()| {
                    rustix::fs::chmod(&dir, Mode::from_raw_mode(mode)).map_err(Into::into)
                })
                .map_err(|e| spool.io("create directory", &dir, e))?;
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

    /// Every directory of the spool with its mode, the spool itself first.
    fn layout(&self) -> Vec<(PathBuf, u32)> {
        let mut dirs = vec![(self.root.clone(), PRIVATE_DIR)];
        for state in JobState::ALL {
            let mode = if state == JobState::Queued {
                DROP_DIR
            } else {
                PRIVATE_DIR
            };
            dirs.push((self.state_dir(state), mode));
        }
        dirs.push((self.root.join(QUARANTINE), PRIVATE_DIR));
        dirs
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

    /// The configuration the daemon published, if any (read as any spool entry).
    ///
    /// # Errors
    /// [`SpoolError::Corrupt`] when it is there but not a readable file.
    pub fn read_config_snapshot(&self) -> Result<Option<String>, SpoolError> {
        let path = self.config_snapshot_path();
        match read_capped_at(rustix::fs::CWD, &path, Links::Refuse, SNAPSHOT_CAP) {
            Ok(c) => String::from_utf8(c.bytes)
                .map(Some)
                .map_err(|e| SpoolError::Corrupt {
                    spool: self.root.clone(),
                    path,
                    cause: e.to_string(),
                }),
            Err(e) if e.is_not_found() => Ok(None),
            Err(e) => Err(SpoolError::Corrupt {
                spool: self.root.clone(),
                path,
                cause: e.to_string(),
            }),
        }
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

    /// Queues a job that was validated by the caller. Safe to call while the daemon runs
    /// and from several processes at once: the id is allocated under a lock on `queued/`,
    /// never wraps, and the record is created exclusively (an existing id is never overwritten).
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be written, [`SpoolError::Busy`] when
    /// another submission holds the lock too long, [`SpoolError::IdsExhausted`].
    pub fn submit(&self, job: JobSpec, now: SystemTime) -> Result<JobRecord, SpoolError> {
        let queued = self.state_dir(JobState::Queued);
        let lock = open_dir(&queued).map_err(|e| self.io("open", &queued, e))?;
        let t0 = Instant::now();
        loop {
            match flock(&lock, FlockOperation::NonBlockingLockExclusive) {
                Ok(()) => break,
                Err(rustix::io::Errno::WOULDBLOCK) if t0.elapsed() < SUBMIT_LOCK_WAIT => {
                    std::thread::sleep(Duration::from_millis(20));
                }
                Err(rustix::io::Errno::WOULDBLOCK) => {
                    return Err(SpoolError::Busy {
                        spool: self.root.clone(),
                    });
                }
                Err(e) => return Err(self.io("lock", &queued, e.into())),
            }
        }
        let counter_path = self.root.join("next-id");
        let mut counter =
            open_counter(&counter_path).map_err(|e| self.io("open", &counter_path, e))?;
        let mut text = String::new();
        (&mut counter)
            .take(SMALL_CAP)
            .read_to_string(&mut text)
            .map_err(|e| self.io("read", &counter_path, e))?;
        let counted = text.trim().parse::<u64>().unwrap_or(1).max(1);
        // The counter may be older than the records (crash between the two writes below)
        // or tampered with: never reuse an id that exists.
        let after_highest = match self.highest_id()? {
            Some(h) => h.0.checked_add(1),
            None => Some(1),
        };
        let id = match after_highest.map(|h| h.max(counted)) {
            Some(id) if id < u64::MAX => JobId(id),
            _ => {
                return Err(SpoolError::IdsExhausted {
                    spool: self.root.clone(),
                });
            }
        };
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
        let bytes = self.to_json(&record, &self.record_path(JobState::Queued, id), 0)?;
        self.write_file(&queued, &id.file_name(), Existing::Refuse, &bytes)?;
        let next = format!("{:020}\n", id.0 + 1);
        counter
            .write_all_at(next.as_bytes(), 0)
            .and_then(|()| counter.set_len(next.len() as u64))
            .and_then(|()| counter.sync_data())
            .map_err(|e| self.io("write", &counter_path, e))?;
        drop(lock);
        Ok(record)
    }

    fn highest_id(&self) -> Result<Option<JobId>, SpoolError> {
        let mut highest = None;
        for state in JobState::ALL {
            for entry in self.entries(state)? {
                highest = highest.max(entry.id);
            }
        }
        Ok(highest)
    }

    /// Every entry of a state directory but the hidden ones (temporary files), by id.
    fn entries(&self, state: JobState) -> Result<Vec<Entry>, SpoolError> {
        let dir = self.state_dir(state);
        let read = match fs::read_dir(&dir) {
            Ok(read) => read,
            // A directory nobody created yet holds no job.
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(self.io("list", &dir, e)),
        };
        let mut out = Vec::new();
        for entry in read {
            let name = entry.map_err(|e| self.io("list", &dir, e))?.file_name();
            if name.as_bytes().starts_with(b".") {
                continue;
            }
            out.push(Entry {
                id: JobId::from_file_name(&name),
                name,
            });
        }
        out.sort_by(|a, b| (a.id, &a.name).cmp(&(b.id, &b.name)));
        Ok(out)
    }

    /// Reads one record as an untrusted entry: `Ok(None)` when it went away meanwhile,
    /// `Err(cause)` when it is not a record of job `id`. Also returns its owner's user id.
    fn read_record(
        &self,
        state: JobState,
        entry: &Entry,
    ) -> Result<Option<(JobRecord, u32)>, String> {
        let Some(id) = entry.id else {
            return Err("not named <id>.json".into());
        };
        let path = self.state_dir(state).join(&entry.name);
        let read = match read_capped_at(rustix::fs::CWD, &path, Links::Refuse, RECORD_CAP) {
            Ok(read) => read,
            Err(e) if e.is_not_found() => return Ok(None),
            Err(e) => return Err(e.to_string()),
        };
        let record: JobRecord = serde_json::from_slice(&read.bytes)
            .map_err(|e| format!("not a job record: {}", printable(&e.to_string(), 200)))?;
        if record.id != id {
            return Err(format!(
                "its id {} does not match its file name (job {id})",
                record.id
            ));
        }
        Ok(Some((record, read.owner)))
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
            for entry in self.entries(state)? {
                match self.read_record(state, &entry) {
                    Ok(Some((mut record, _))) => {
                        record.state = effective_state(state, record.state);
                        let newer = by_id
                            .get(&record.id)
                            .is_none_or(|seen| seen.state.stage() <= record.state.stage());
                        if newer {
                            by_id.insert(record.id, record);
                        }
                    }
                    Ok(None) => {}
                    Err(cause) => unreadable.push(Unreadable {
                        path: self.state_dir(state).join(&entry.name),
                        name: shown_name(&entry.name),
                        cause,
                    }),
                }
            }
        }
        let (set_aside, set_aside_total) = self.set_aside_entries();
        Ok(Listing {
            jobs: by_id.into_values().collect(),
            unreadable,
            set_aside,
            set_aside_total,
        })
    }

    /// The latest entries of `quarantine/` with their reasons, and how many there are.
    fn set_aside_entries(&self) -> (Vec<Unreadable>, usize) {
        let dir = self.root.join(QUARANTINE);
        let Ok(read) = fs::read_dir(&dir) else {
            return (Vec::new(), 0);
        };
        let mut names: Vec<OsString> = read
            .filter_map(|e| e.ok().map(|e| e.file_name()))
            .filter(|n| !n.as_bytes().ends_with(b".reason") && !n.as_bytes().starts_with(b"."))
            .collect();
        names.sort();
        let total = names.len();
        let shown = names
            .iter()
            .skip(total.saturating_sub(SET_ASIDE_SHOWN))
            .map(|name| {
                let mut reason_name = name.clone();
                reason_name.push(".reason");
                let reason = read_capped_at(
                    rustix::fs::CWD,
                    &dir.join(&reason_name),
                    Links::Refuse,
                    SMALL_CAP,
                )
                .ok()
                .and_then(|c| serde_json::from_slice::<SetAsideReason>(&c.bytes).ok());
                match reason {
                    Some(r) => Unreadable {
                        path: dir.join(name),
                        name: printable(&r.name, 120),
                        cause: printable(&r.cause, 400),
                    },
                    None => Unreadable {
                        path: dir.join(name),
                        name: shown_name(name),
                        cause: "set aside (its reason could not be recorded)".into(),
                    },
                }
            })
            .collect();
        (shown, total)
    }

    /// What the daemon last reported, if one ever ran on this spool.
    #[must_use]
    pub fn daemon_status(&self) -> Option<DaemonStatus> {
        let path = self.root.join("daemon.json");
        let read = read_capped_at(rustix::fs::CWD, &path, Links::Refuse, SMALL_CAP).ok()?;
        serde_json::from_slice(&read.bytes).ok()
    }

    /// An operator's acknowledgement for a daemon waiting after an unclean end
    /// (`sdsem daemon --ack`): a file the daemon sees at its next turn.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when it cannot be written.
    pub fn acknowledge(&self, now: SystemTime) -> Result<PathBuf, SpoolError> {
        let queued = self.state_dir(JobState::Queued);
        let text = format!("acknowledged at {}\n", utc::rfc3339(now));
        self.write_file(&queued, ACK, Existing::Replace, text.as_bytes())?;
        Ok(queued.join(ACK))
    }

    /// Takes ownership of the spool for a daemon: only one at a time. The lock is a
    /// flock(2) on the spool directory itself, held on an open descriptor: moving or
    /// deleting `daemon.lock` does not release it. It dies with its holder (even by
    /// SIGKILL or a power cut).
    ///
    /// # Errors
    /// [`SpoolError::Locked`] naming the PID of the daemon that holds it.
    pub fn lock(self) -> Result<OwnedSpool, SpoolError> {
        let dir = open_dir(&self.root).map_err(|e| self.io("open", &self.root, e))?;
        match flock(&dir, FlockOperation::NonBlockingLockExclusive) {
            Ok(()) => {}
            Err(rustix::io::Errno::WOULDBLOCK) => {
                let holder = read_capped_at(
                    rustix::fs::CWD,
                    &self.root.join("daemon.lock"),
                    Links::Refuse,
                    64,
                )
                .ok()
                .and_then(|c| String::from_utf8(c.bytes).ok())
                .map(|s| s.trim().to_owned())
                .filter(|s| !s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()))
                .unwrap_or_else(|| "unknown".into());
                return Err(SpoolError::Locked {
                    spool: self.root.clone(),
                    holder,
                });
            }
            Err(e) => return Err(self.io("lock", &self.root, e.into())),
        }
        let stat = rustix::fs::fstat(&dir).map_err(|e| self.io("inspect", &self.root, e.into()))?;
        let owned = OwnedSpool {
            root_id: (stat.st_dev, stat.st_ino),
            _dir: dir,
            spool: self,
            lock_file: Mutex::new(None),
            stuck: Mutex::new(HashSet::new()),
        };
        owned.fix_modes();
        owned.write_pid_file()?;
        let counter = owned.root.join("next-id");
        open_counter(&counter).map_err(|e| owned.io("create", &counter, e))?;
        Ok(owned)
    }

    /// The JSON of a record; `reserve` spaces after it leave room for its end.
    fn to_json(
        &self,
        record: &JobRecord,
        path: &Path,
        reserve: usize,
    ) -> Result<Vec<u8>, SpoolError> {
        let mut bytes = serde_json::to_vec_pretty(record).map_err(|e| SpoolError::Corrupt {
            spool: self.root.clone(),
            path: path.to_owned(),
            cause: e.to_string(),
        })?;
        bytes.push(b'\n');
        bytes.resize(bytes.len() + reserve, b' ');
        Ok(bytes)
    }

    /// The one atomic writer, in a spool directory, with the spool's file mode.
    fn write_file(
        &self,
        dir: &Path,
        name: &str,
        existing: Existing,
        bytes: &[u8],
    ) -> Result<(), SpoolError> {
        let path = dir.join(name);
        let fd = open_dir(dir).map_err(|e| self.io("open", dir, e))?;
        write_atomic_at(
            fd.as_fd(),
            OsStr::new(name),
            existing,
            Some(RECORD_MODE),
            |w| w.write_all(bytes),
        )
        .map_err(|e| self.io("write", &path, e))
    }

    fn write_record(
        &self,
        state: JobState,
        record: &JobRecord,
        reserve: usize,
    ) -> Result<(), SpoolError> {
        let path = self.record_path(state, record.id);
        let bytes = self.to_json(record, &path, reserve)?;
        match self.write_file(
            &self.state_dir(state),
            &record.id.file_name(),
            Existing::Replace,
            &bytes,
        ) {
            // On a full disk a new file may be impossible; the reserve of a running
            // record takes its end in place.
            Err(e) if e.is_disk_full() => overwrite_in_place(&path, &bytes).map_err(|_| e),
            other => other,
        }
    }

    fn move_record(&self, id: JobId, from: JobState, to: JobState) -> Result<(), SpoolError> {
        let src = self.record_path(from, id);
        let dst = self.record_path(to, id);
        fs::rename(&src, &dst).map_err(|e| self.io("move", &src, e))?;
        sync_parent(&dst).map_err(|e| self.io("sync", &dst, e))?;
        sync_parent(&src).map_err(|e| self.io("sync", &src, e))
    }
}

/// Opens (creating if missing) the id counter, never through a link, group-writable.
fn open_counter(path: &Path) -> io::Result<File> {
    let fd = rustix::fs::open(
        path,
        OFlags::RDWR | OFlags::CREATE | OFlags::NOFOLLOW | OFlags::CLOEXEC | OFlags::NONBLOCK,
        Mode::from_raw_mode(COUNTER_MODE),
    )?;
    let stat = rustix::fs::fstat(&fd)?;
    if rustix::fs::FileType::from_raw_mode(stat.st_mode) != rustix::fs::FileType::RegularFile {
        return Err(io::Error::other("next-id is not a regular file"));
    }
    if stat.st_uid == rustix::process::geteuid().as_raw() {
        rustix::fs::fchmod(&fd, Mode::from_raw_mode(COUNTER_MODE))?;
    }
    Ok(File::from(fd))
}

/// Rewrites a record where it lies, padded to its length: needs no new block on a full disk.
fn overwrite_in_place(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let fd = rustix::fs::open(
        path,
        OFlags::WRONLY | OFlags::NOFOLLOW | OFlags::CLOEXEC,
        Mode::empty(),
    )?;
    let file = File::from(fd);
    let len = usize::try_from(file.metadata()?.len()).unwrap_or(usize::MAX);
    let body = trim_end_spaces(bytes);
    if body.len() > len {
        return Err(io::Error::other("no room reserved in the record"));
    }
    let mut padded = body.to_vec();
    padded.resize(len, b' ');
    file.write_all_at(&padded, 0)?;
    file.sync_data()
}

fn trim_end_spaces(bytes: &[u8]) -> &[u8] {
    let end = bytes.iter().rposition(|b| *b != b' ').map_or(0, |i| i + 1);
    &bytes[..end]
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

/// An entry's name as printed.
fn shown_name(name: &OsStr) -> String {
    printable(&name.to_string_lossy(), 120)
}

/// `quarantine/<entry>.reason`.
#[derive(Debug, Serialize, Deserialize)]
struct SetAsideReason {
    /// The entry's original name (lossy UTF-8).
    name: String,
    /// The directory it was found in.
    from: String,
    cause: String,
    /// UTC, RFC 3339.
    at: String,
}

fn sync_parent(path: &Path) -> io::Result<()> {
    let dir = path.parent().unwrap_or_else(|| Path::new("."));
    File::open(dir)?.sync_all()
}

/// A reason cut to [`REASON_CAP`] bytes, on a character boundary.
fn capped_reason(reason: Option<String>) -> Option<String> {
    reason.map(|mut r| {
        if r.len() > REASON_CAP {
            let mut end = REASON_CAP;
            while !r.is_char_boundary(end) {
                end -= 1;
            }
            r.truncate(end);
            r.push('…');
        }
        r
    })
}

/// A spool owned by this daemon (the lock is held while this value lives).
#[derive(Debug)]
pub struct OwnedSpool {
    spool: Spool,
    /// The spool directory, flock(2)ed: the ownership itself.
    _dir: OwnedFd,
    /// (device, inode) of the spool directory when it was locked.
    root_id: (u64, u64),
    /// (device, inode) of the `daemon.lock` this daemon wrote.
    lock_file: Mutex<Option<(u64, u64)>>,
    /// Entries that could not be set aside: skipped from then on.
    stuck: Mutex<HashSet<OsString>>,
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
    /// Entries of `queued/` and `running/` that are not valid records, set aside.
    pub quarantined: Vec<Unreadable>,
    /// What could not be put in order (e.g. on a full disk), with the cause; tried again
    /// at the next start.
    pub problems: Vec<String>,
}

/// Something done to the spool behind the daemon's back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Tamper {
    /// `daemon.lock` was moved, removed, replaced or rewritten; it has been written again.
    LockFile(String),
    /// The spool directory itself was moved, replaced or removed: the daemon cannot go on.
    SpoolGone(String),
}

impl OwnedSpool {
    /// Sets the modes of the layout on the directories this daemon owns.
    fn fix_modes(&self) {
        let me = rustix::process::geteuid().as_raw();
        for (dir, mode) in self.layout() {
            if let Ok(stat) = rustix::fs::lstat(&dir)
                && stat.st_uid == me
                && stat.st_mode & 0o7777 != mode
                && let Err(e) = rustix::fs::chmod(&dir, Mode::from_raw_mode(mode))
            {
                tracing::warn!(dir = %dir.display(), error = %e, "cannot set the spool directory's mode to {mode:o}");
            }
        }
    }

    fn write_pid_file(&self) -> Result<(), SpoolError> {
        let text = format!("{}\n", std::process::id());
        self.write_file(
            &self.root,
            "daemon.lock",
            Existing::Replace,
            text.as_bytes(),
        )?;
        let path = self.root.join("daemon.lock");
        let stat = rustix::fs::lstat(&path).map_err(|e| self.io("inspect", &path, e.into()))?;
        *self
            .lock_file
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some((stat.st_dev, stat.st_ino));
        Ok(())
    }

    /// Checks that the spool is still the one this daemon locked, and that `daemon.lock`
    /// is still its own; writes `daemon.lock` again when it is not.
    ///
    /// # Errors
    /// [`Tamper`] saying what was found.
    pub fn check_ownership(&self) -> Result<(), Tamper> {
        match rustix::fs::stat(&self.root) {
            Ok(s) if (s.st_dev, s.st_ino) == self.root_id => {}
            Ok(_) => {
                return Err(Tamper::SpoolGone(format!(
                    "the spool directory {} was replaced by another one",
                    self.root.display()
                )));
            }
            Err(e) => {
                return Err(Tamper::SpoolGone(format!(
                    "the spool directory {} is gone ({e})",
                    self.root.display()
                )));
            }
        }
        let path = self.root.join("daemon.lock");
        let expected = *self
            .lock_file
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let found = match rustix::fs::lstat(&path) {
            Err(rustix::io::Errno::NOENT) => Some("was moved away or removed".to_owned()),
            Err(e) => Some(format!("cannot be inspected ({e})")),
            Ok(s) if Some((s.st_dev, s.st_ino)) != expected => Some("was replaced".to_owned()),
            Ok(_) => {
                // It may be moved between the lstat and the read: that is a move, not
                // an unreadable file.
                let read = read_capped_at(rustix::fs::CWD, &path, Links::Refuse, 64);
                let moved = read.as_ref().is_err_and(UntrustedError::is_not_found);
                let pid = read.ok().and_then(|c| String::from_utf8(c.bytes).ok());
                let mine = std::process::id().to_string();
                match pid {
                    Some(p) if p.trim() == mine => None,
                    Some(p) => Some(format!(
                        "was rewritten (it said {:?})",
                        printable(p.trim(), 40)
                    )),
                    None if moved => Some("was moved away or removed".to_owned()),
                    None => Some("was made unreadable".to_owned()),
                }
            }
        };
        let Some(what) = found else {
            return Ok(());
        };
        let restored = match self.write_pid_file() {
            Ok(()) => "written again".to_owned(),
            Err(e) => format!("could not be written again: {e}"),
        };
        Err(Tamper::LockFile(format!(
            "{} {what}; this daemon (PID {}) still owns the spool — the lock is held on the \
             spool directory itself, so no second daemon can start — and daemon.lock was {restored}",
            path.display(),
            std::process::id()
        )))
    }

    /// Puts the spool back in order after a crash or power cut: a job found running is
    /// marked interrupted (never re-run silently), transitions cut short are completed,
    /// stale temporary files are removed and entries that are not records set aside.
    /// What cannot be written (a full disk) is reported in [`Recovery::problems`].
    ///
    /// # Errors
    /// [`SpoolError::Io`] when a spool directory cannot be read.
    pub fn recover(&self, now: SystemTime) -> Result<Recovery, SpoolError> {
        let mut recovery = Recovery::default();
        self.remove_stale_temps(now, &mut recovery);
        for dir_state in [JobState::Queued, JobState::Running] {
            for entry in self.entries(dir_state)? {
                let (record, owner) = match self.read_record(dir_state, &entry) {
                    Ok(Some(found)) => found,
                    Ok(None) => continue,
                    Err(cause) => {
                        recovery.quarantined.push(self.set_aside(
                            dir_state,
                            &entry.name,
                            &cause,
                            now,
                        ));
                        continue;
                    }
                };
                if record.state.stage() > dir_state.stage() {
                    if let Some(cause) = self.forged(dir_state, &record, owner) {
                        recovery.quarantined.push(self.set_aside(
                            dir_state,
                            &entry.name,
                            &cause,
                            now,
                        ));
                        continue;
                    }
                    match self.move_record(record.id, dir_state, record.state) {
                        Ok(()) => recovery.completed_moves += 1,
                        Err(e) => recovery.problems.push(e.to_string()),
                    }
                } else if dir_state == JobState::Running {
                    let record = JobRecord {
                        state: JobState::Running,
                        ..record
                    };
                    match self.finish(
                        &record,
                        JobState::Interrupted,
                        Some(CRASH_REASON.to_owned()),
                        now,
                    ) {
                        Ok(record) => recovery.interrupted.push(record),
                        Err(e) => recovery.problems.push(format!(
                            "job {} ({}) was running when the daemon stopped, but cannot be marked \
                             interrupted: {e}",
                            record.id,
                            printable(&record.name, 64)
                        )),
                    }
                }
            }
        }
        Ok(recovery)
    }

    /// Removes temporary files a crash left behind (older than [`STALE_TMP`]); other hidden
    /// entries that are not regular files are set aside.
    fn remove_stale_temps(&self, now: SystemTime, recovery: &mut Recovery) {
        let mut dirs = vec![self.root.clone(), self.root.join("tmp")];
        dirs.extend(JobState::ALL.iter().map(|s| self.state_dir(*s)));
        for dir in dirs {
            let Ok(read) = fs::read_dir(&dir) else {
                continue;
            };
            for entry in read.flatten() {
                let name = entry.file_name();
                let hidden = name.as_bytes().starts_with(b".") || dir.ends_with("tmp");
                if !hidden || name == ACK {
                    continue;
                }
                let path = dir.join(&name);
                let Ok(meta) = fs::symlink_metadata(&path) else {
                    continue;
                };
                let stale = meta
                    .modified()
                    .is_ok_and(|t| now.duration_since(t).is_ok_and(|age| age > STALE_TMP));
                if !stale {
                    continue;
                }
                if meta.is_file() || meta.is_symlink() {
                    if let Err(e) = fs::remove_file(&path) {
                        recovery
                            .problems
                            .push(format!("cannot remove {}: {e}", path.display()));
                    }
                } else if let Some(state) =
                    JobState::ALL.iter().find(|s| dir == self.state_dir(**s))
                {
                    recovery.quarantined.push(self.set_aside(
                        *state,
                        &name,
                        "a hidden entry that is not a file",
                        now,
                    ));
                }
            }
        }
    }

    /// Why a record found ahead of its directory must not be believed: in `queued/` only
    /// the daemon's own rewrite (a rejection cut short) may be ahead.
    fn forged(&self, dir_state: JobState, record: &JobRecord, owner: u32) -> Option<String> {
        (dir_state == JobState::Queued && owner != rustix::process::geteuid().as_raw()).then(|| {
            format!(
                "a record in queued/ must say \"queued\"; this one says {:?} and was not written \
                 by the daemon",
                record.state.as_str()
            )
        })
    }

    /// Moves an entry of a state directory to `quarantine/` with its reason, never
    /// following it. An entry that cannot be moved is skipped from then on.
    fn set_aside(&self, from: JobState, name: &OsStr, cause: &str, now: SystemTime) -> Unreadable {
        let src = self.state_dir(from).join(name);
        let shown = shown_name(name);
        let safe: String = name
            .as_bytes()
            .iter()
            .take(60)
            .map(|b| {
                if b.is_ascii_alphanumeric() || matches!(b, b'.' | b'-' | b'_') {
                    char::from(*b)
                } else {
                    '_'
                }
            })
            .collect();
        let quarantine = self.root.join(QUARANTINE);
        let stamp = utc::compact(now);
        let mut moved = Err(io::Error::other("no free name in quarantine/"));
        for n in 0..1000 {
            let dst = quarantine.join(format!("{stamp}-{n:03}-{from}-{safe}"));
            match rustix::fs::renameat_with(
                rustix::fs::CWD,
                &src,
                rustix::fs::CWD,
                &dst,
                RenameFlags::NOREPLACE,
            ) {
                Ok(()) => {
                    moved = Ok(dst);
                    break;
                }
                Err(rustix::io::Errno::EXIST) => {}
                Err(e) => {
                    moved = Err(e.into());
                    break;
                }
            }
        }
        match moved {
            Ok(dst) => {
                let reason = SetAsideReason {
                    name: name.to_string_lossy().chars().take(500).collect(),
                    from: from.as_str().to_owned(),
                    cause: cause.to_owned(),
                    at: utc::rfc3339(now),
                };
                let mut reason_name = dst.file_name().unwrap_or_default().to_owned();
                reason_name.push(".reason");
                let written = serde_json::to_vec_pretty(&reason)
                    .map_err(io::Error::other)
                    .and_then(|bytes| {
                        let fd = open_dir(&quarantine)?;
                        write_atomic_at(
                            fd.as_fd(),
                            &reason_name,
                            Existing::Refuse,
                            Some(RECORD_MODE),
                            |w| w.write_all(&bytes),
                        )
                    });
                if let Err(e) = written {
                    tracing::warn!(entry = %dst.display(), error = %e, "cannot record why an entry was set aside");
                }
                Unreadable {
                    path: dst,
                    name: shown,
                    cause: cause.to_owned(),
                }
            }
            Err(e) => {
                self.stuck
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .insert(name.to_owned());
                Unreadable {
                    path: src,
                    name: shown,
                    cause: format!(
                        "{cause}; it cannot be set aside ({e}) and is ignored from now on"
                    ),
                }
            }
        }
    }

    /// The oldest queued job, if any, as a fresh queued record (what a submitter may not
    /// set — start, end, run directory, reason — is dropped). Entries that are not job
    /// records are set aside and returned beside it so the caller can log them. The job
    /// itself is not checked here: [`JobSpec::effective_config`] is, by the caller.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when `queued/` cannot be read.
    pub fn next_queued(&self) -> Result<(Option<JobRecord>, Vec<Unreadable>), SpoolError> {
        let mut set_aside = Vec::new();
        let now = SystemTime::now();
        for entry in self.entries(JobState::Queued)? {
            if self
                .stuck
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .contains(&entry.name)
            {
                continue;
            }
            let (record, owner) = match self.read_record(JobState::Queued, &entry) {
                Ok(Some(found)) => found,
                Ok(None) => continue,
                Err(cause) => {
                    set_aside.push(self.set_aside(JobState::Queued, &entry.name, &cause, now));
                    continue;
                }
            };
            if record.state == JobState::Queued {
                if let Some(other) = JobState::ALL[1..]
                    .iter()
                    .find(|s| fs::symlink_metadata(self.record_path(**s, record.id)).is_ok())
                {
                    let cause = format!(
                        "job {} exists already ({other}): an id is never reused",
                        record.id
                    );
                    set_aside.push(self.set_aside(JobState::Queued, &entry.name, &cause, now));
                    continue;
                }
                if !utc::is_rfc3339(&record.submitted) {
                    let cause = "its submission time is not an RFC 3339 UTC time";
                    set_aside.push(self.set_aside(JobState::Queued, &entry.name, cause, now));
                    continue;
                }
                let record = JobRecord {
                    name: record.job.name.clone(),
                    started: None,
                    finished: None,
                    run_dir: None,
                    reason: None,
                    ..record
                };
                return Ok((Some(record), set_aside));
            }
            if let Some(cause) = self.forged(JobState::Queued, &record, owner) {
                set_aside.push(self.set_aside(JobState::Queued, &entry.name, &cause, now));
                continue;
            }
            // A rejection cut short by a crash: finish it.
            self.move_record(record.id, JobState::Queued, record.state)?;
        }
        Ok((None, set_aside))
    }

    /// Number of queued jobs.
    ///
    /// # Errors
    /// [`SpoolError::Io`] when the spool cannot be read.
    pub fn queued_count(&self) -> Result<usize, SpoolError> {
        Ok(self
            .entries(JobState::Queued)?
            .iter()
            .filter(|e| e.id.is_some())
            .count())
    }

    /// The directory job `id`'s record lies in, if any.
    #[must_use]
    pub fn state_of(&self, id: JobId) -> Option<JobState> {
        JobState::ALL
            .into_iter()
            .find(|s| fs::symlink_metadata(self.record_path(*s, id)).is_ok())
    }

    /// Marks a queued job running in `run_dir`. Its record keeps room to be ended in place.
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
        self.write_record(JobState::Running, &running, RESERVE)?;
        Ok(running)
    }

    /// Moves a queued or running job to its final state with its reason (cut to 2000 bytes).
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
            reason: capped_reason(reason),
            ..record.clone()
        };
        // Record first, then move: a crash in between leaves a record ahead of
        // its directory, which readers honour and recovery completes.
        self.write_record(from, &finished, 0)?;
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
            path,
            cause: e.to_string(),
        })?;
        self.write_file(&self.root, "daemon.json", Existing::Replace, &bytes)
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
        self.write_file(
            &self.root,
            "config.toml",
            Existing::Replace,
            text.as_bytes(),
        )
    }

    /// Removes an operator's acknowledgement, so that only one given from now on counts.
    pub fn clear_ack(&self) {
        let _ = fs::remove_file(self.state_dir(JobState::Queued).join(ACK));
    }

    /// Consumes an operator's acknowledgement: `Some(who)` when there was one.
    #[must_use]
    pub fn take_ack(&self) -> Option<String> {
        let path = self.state_dir(JobState::Queued).join(ACK);
        let stat = rustix::fs::lstat(&path).ok()?;
        let _ = fs::remove_file(&path);
        Some(format!("user id {}", stat.st_uid))
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
        assert_eq!(mode, 0o640, "{}", path.display());
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
        let hidden = fs::read_dir(dir.path().join("failed")).unwrap().count();
        assert_eq!(hidden, 1, "temporary files left behind");
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
        owned.write_record(JobState::Running, &done, 0).unwrap();
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
        assert!(
            quarantined[0].cause.starts_with("not a job record"),
            "{:?}",
            quarantined[0]
        );
        // `b` got id 8 (after the 7 on disk) and runs despite the bad file before it.
        assert_eq!(next.unwrap().id, JobId(8));
        let listing = spool.list().unwrap();
        assert!(listing.unreadable.is_empty());
        assert_eq!(listing.set_aside_total, 1);
        assert_eq!(listing.set_aside[0].name, "00000007.json");
        assert!(listing.set_aside[0].cause.starts_with("not a job record"));
    }

    /// Every hostile entry of `queued/` is set aside at once, with its reason, and the
    /// valid job behind them is the next one; nothing blocks, follows or reads unbounded.
    #[test]
    fn hostile_entries_are_set_aside_without_blocking() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        let q = dir.path().join("queued");
        fs::create_dir(q.join("00000001.json")).unwrap();
        rustix::fs::mknodat(
            rustix::fs::CWD,
            q.join("00000002.json"),
            rustix::fs::FileType::Fifo,
            Mode::from_raw_mode(0o644),
            0,
        )
        .unwrap();
        std::os::unix::fs::symlink("/dev/zero", q.join("00000003.json")).unwrap();
        fs::write(q.join("00000004.json"), vec![b' '; 300 * 1024]).unwrap();
        fs::write(q.join("00000005.json"), "garbage").unwrap();
        fs::write(q.join("bad\u{1b}[2J\nname"), "x").unwrap();
        // A record that lies about its id, and one that claims to be done already.
        let mut record = spool.submit(spec("liar"), at(0)).unwrap();
        fs::rename(q.join("00000006.json"), q.join("00000009.json")).unwrap();
        record.id = JobId(10);
        record.state = JobState::Done;
        let text = serde_json::to_string(&record).unwrap();
        fs::write(q.join("00000010.json"), text).unwrap();
        fs::set_permissions(q.join("00000010.json"), fs::Permissions::from_mode(0o644)).unwrap();
        let good = spool.submit(spec("good"), at(0)).unwrap();
        assert_eq!(good.id, JobId(11));

        let owned = spool.clone().lock().unwrap();
        let t0 = Instant::now();
        let (next, set_aside) = owned.next_queued().unwrap();
        assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
        assert_eq!(next.unwrap().name, "good");
        let causes: Vec<(&str, &str)> = set_aside
            .iter()
            .map(|u| (u.name.as_str(), u.cause.as_str()))
            .collect();
        let want = [
            ("00000001.json", "it is a directory, not a regular file"),
            ("00000002.json", "it is a FIFO, not a regular file"),
            (
                "00000003.json",
                "it is a symbolic link, which is never followed",
            ),
            ("00000004.json", "it is larger than 262144 bytes"),
            ("00000005.json", "not a job record"),
            (
                "00000009.json",
                "its id 6 does not match its file name (job 9)",
            ),
        ];
        for (name, cause) in want {
            assert!(
                causes
                    .iter()
                    .any(|(n, c)| *n == name && c.starts_with(cause)),
                "{name}: {causes:?}"
            );
        }
        assert!(
            causes
                .iter()
                .any(|(n, c)| *n == "bad\\u{1b}[2J\\nname" && *c == "not named <id>.json"),
            "{causes:?}"
        );
        // Written by the daemon's own user (as everything in this test): honoured as a
        // transition cut short. From a submitter (another user) it is set aside:
        assert!(dir.path().join("done/00000010.json").exists());
        let me = rustix::process::geteuid().as_raw();
        assert!(owned.forged(JobState::Queued, &record, me).is_none());
        let forged = owned
            .forged(JobState::Queued, &record, me.wrapping_add(1))
            .unwrap();
        assert!(forged.contains("must say \"queued\""), "{forged}");
        // Nothing followed: /dev/zero is still a device, the link moved as a link.
        let listing = spool.list().unwrap();
        assert!(listing.unreadable.is_empty(), "{:?}", listing.unreadable);
        assert!(listing.set_aside_total >= 7, "{}", listing.set_aside_total);
        assert!(
            listing
                .set_aside
                .iter()
                .all(|u| !u.name.contains('\u{1b}') && !u.cause.contains('\n')),
            "{:?}",
            listing.set_aside
        );
        // The second turn finds only the good job.
        let (next, set_aside) = owned.next_queued().unwrap();
        assert!(set_aside.is_empty());
        assert_eq!(next.unwrap().name, "good");
    }

    #[test]
    fn a_done_job_cannot_be_queued_again_nor_an_id_spelt_twice() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        spool.submit(spec("a"), at(0)).unwrap();
        let owned = spool.clone().lock().unwrap();
        let a = owned.next_queued().unwrap().0.unwrap();
        let text = fs::read(dir.path().join("queued/00000001.json")).unwrap();
        let running = owned.start(&a, Path::new("/runs/a"), at(1)).unwrap();
        owned.finish(&running, JobState::Done, None, at(2)).unwrap();
        // Its record, put back into queued/, and again under another spelling of its id.
        fs::write(dir.path().join("queued/00000001.json"), &text).unwrap();
        fs::write(dir.path().join("queued/0000001.json"), &text).unwrap();
        let (next, set_aside) = owned.next_queued().unwrap();
        assert!(next.is_none());
        let causes: Vec<&str> = set_aside.iter().map(|u| u.cause.as_str()).collect();
        assert!(causes.contains(&"not named <id>.json"), "{causes:?}");
        assert!(
            causes.contains(&"job 1 exists already (done): an id is never reused"),
            "{causes:?}"
        );
        assert_eq!(states(&spool), [(1, "a".into(), JobState::Done)]);
    }

    #[test]
    fn a_queued_record_cannot_carry_a_start_or_a_reason() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        let mut record = spool.submit(spec("a"), at(0)).unwrap();
        record.run_dir = Some("/etc".into());
        record.reason = Some("x".into());
        record.name = "../../evil".into();
        fs::write(
            dir.path().join("queued/00000001.json"),
            serde_json::to_string(&record).unwrap(),
        )
        .unwrap();
        let owned = spool.lock().unwrap();
        let next = owned.next_queued().unwrap().0.unwrap();
        assert_eq!(
            (next.name.as_str(), next.run_dir, next.reason),
            ("a", None, None)
        );
    }

    #[test]
    fn ids_never_wrap_and_an_existing_id_is_never_overwritten() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        fs::write(dir.path().join("next-id"), format!("{}\n", u64::MAX)).unwrap();
        let err = spool.submit(spec("a"), at(0)).unwrap_err();
        assert!(matches!(err, SpoolError::IdsExhausted { .. }), "{err}");
        assert!(err.to_string().contains("nothing was queued"), "{err}");
        fs::write(dir.path().join("next-id"), format!("{}\n", u64::MAX - 1)).unwrap();
        assert_eq!(
            spool.submit(spec("a"), at(0)).unwrap().id,
            JobId(u64::MAX - 1)
        );
        let err = spool.submit(spec("b"), at(0)).unwrap_err();
        assert!(matches!(err, SpoolError::IdsExhausted { .. }), "{err}");
        assert_eq!(spool.list().unwrap().jobs.len(), 1);

        // A counter set back does not give an existing id again.
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        spool.submit(spec("a"), at(0)).unwrap();
        fs::write(dir.path().join("next-id"), "1\n").unwrap();
        assert_eq!(spool.submit(spec("b"), at(0)).unwrap().id, JobId(2));
        assert_eq!(
            states(&spool),
            [
                (1, "a".into(), JobState::Queued),
                (2, "b".into(), JobState::Queued)
            ]
        );
    }

    #[test]
    fn the_layout_is_private_but_for_a_sticky_queue() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("spool");
        let old = rustix::process::umask(Mode::from_raw_mode(0o002));
        let spool = Spool::open(&root);
        rustix::process::umask(old);
        let owned = spool.unwrap().lock().unwrap();
        let mode = |p: &str| fs::metadata(root.join(p)).unwrap().permissions().mode() & 0o7777;
        assert_eq!(mode(""), 0o750);
        assert_eq!(mode("queued"), 0o1770);
        for d in [
            "running",
            "done",
            "failed",
            "interrupted",
            "rejected",
            "quarantine",
        ] {
            assert_eq!(mode(d), 0o750, "{d}");
        }
        assert_eq!(mode("next-id"), 0o660);
        assert_eq!(mode("daemon.lock"), 0o640);
        drop(owned);
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

    /// `mv daemon.lock` let a second daemon in: the lock is on the spool directory now,
    /// and the owner notices and writes its lock file again.
    #[test]
    fn moving_or_rewriting_the_lock_file_lets_no_second_owner_in_and_is_noticed() {
        let dir = tempfile::tempdir().unwrap();
        let first = Spool::open(dir.path()).unwrap().lock().unwrap();
        assert_eq!(first.check_ownership(), Ok(()));
        let lock = dir.path().join("daemon.lock");
        fs::rename(&lock, dir.path().join("moved.lock")).unwrap();
        let err = Spool::open(dir.path()).unwrap().lock().unwrap_err();
        assert!(matches!(err, SpoolError::Locked { .. }), "{err}");
        let Err(Tamper::LockFile(what)) = first.check_ownership() else {
            panic!("not noticed")
        };
        assert!(
            what.contains("was moved away or removed") && what.contains("written again"),
            "{what}"
        );
        assert_eq!(first.check_ownership(), Ok(()));
        fs::write(&lock, "1\n").unwrap();
        assert!(
            matches!(first.check_ownership(), Err(Tamper::LockFile(w)) if w.contains("was rewritten"))
        );
        // Another file with the right PID, renamed over it.
        let other = dir.path().join("other");
        fs::write(&other, format!("{}\n", std::process::id())).unwrap();
        fs::rename(&other, &lock).unwrap();
        assert!(
            matches!(first.check_ownership(), Err(Tamper::LockFile(w)) if w.contains("was replaced"))
        );
        // Someone removed the lock file; a second daemon is still refused.
        fs::remove_file(&lock).unwrap();
        assert!(Spool::open(dir.path()).unwrap().lock().is_err());
        // The spool directory itself moved: the daemon can only give up.
        fs::rename(dir.path(), dir.path().with_extension("moved")).unwrap();
        assert!(matches!(first.check_ownership(), Err(Tamper::SpoolGone(_))));
        fs::rename(dir.path().with_extension("moved"), dir.path()).unwrap();
    }

    /// On a full disk no new file can be made: the end of a running job is written into
    /// the room its record kept, so the job is not labelled a crash at the next start.
    #[test]
    fn a_running_record_can_be_ended_in_place() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        spool.submit(spec("a"), at(0)).unwrap();
        let owned = spool.clone().lock().unwrap();
        let a = owned.next_queued().unwrap().0.unwrap();
        let running = owned.start(&a, Path::new("/runs/a"), at(1)).unwrap();
        let path = dir.path().join("running/00000001.json");
        let len = fs::metadata(&path).unwrap().len();
        let ended = JobRecord {
            state: JobState::Failed,
            reason: capped_reason(Some("é".repeat(5000))),
            ..running
        };
        let bytes = spool.to_json(&ended, &path, 0).unwrap();
        overwrite_in_place(&path, &bytes).unwrap();
        assert_eq!(fs::metadata(&path).unwrap().len(), len);
        assert_eq!(states(&spool), [(1, "a".into(), JobState::Failed)]);
        let recovery = owned.recover(at(2)).unwrap();
        assert!(recovery.interrupted.is_empty());
        assert!(dir.path().join("failed/00000001.json").is_file());
    }

    #[test]
    fn stale_temp_files_are_removed_at_recovery() {
        let dir = tempfile::tempdir().unwrap();
        let spool = Spool::open(dir.path()).unwrap();
        let tmp = dir.path().join("queued/.00000001.json.tmp-1-0");
        fs::write(&tmp, "partial").unwrap();
        let owned = spool.lock().unwrap();
        owned.recover(SystemTime::now()).unwrap();
        assert!(tmp.exists(), "fresh: may be a submit in progress");
        owned
            .recover(SystemTime::now() + Duration::from_secs(3600))
            .unwrap();
        assert!(!tmp.exists());
    }
}
