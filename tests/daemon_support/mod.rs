//! Test doubles for the daemon: a scripted job runner, a notification
//! recorder and a disk whose free space the test sets.

#![allow(dead_code, clippy::unwrap_used)]

pub mod process;

use std::collections::{HashMap, VecDeque};
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use sdsem::acquisition::RunDir;
use sdsem::config::Config;
use sdsem::daemon::disk::DiskSpace;
use sdsem::daemon::{JobContext, JobOutcome, JobRecord, JobRunner, Notice, Notifier};
use tokio::time::Instant;

/// How the fake runner performs a job (chosen by the job's name).
#[derive(Debug, Clone)]
pub enum Behaviour {
    /// Works `duration`, reporting progress every second; on cancellation it
    /// takes `stop_after` to make the stage safe, then returns Interrupted.
    Work {
        duration: Duration,
        stop_after: Duration,
    },
    /// Fails after `after` (e.g. the stage link is lost).
    Fail { after: Duration, reason: String },
    /// Never reports progress; returns Interrupted at once when cancelled.
    Silent,
    /// Ignores cancellation and never returns: breaks the contract.
    Deaf,
}

/// What the fake runner saw.
#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    LinkCheck {
        at: Instant,
        ok: bool,
    },
    Started {
        name: String,
        at: Instant,
        run_dir: PathBuf,
    },
    Ended {
        name: String,
        at: Instant,
        outcome: JobOutcome,
    },
    /// The stage's tilt was read (after an unclean end).
    StageRead {
        at: Instant,
        tilt: f64,
    },
    /// The stage was moved from `from` to its safe tilt.
    SafeMove {
        at: Instant,
        from: f64,
    },
}

#[derive(Debug, Default)]
pub struct Script {
    /// Behaviour per job name; others work 10 s.
    pub jobs: HashMap<String, Behaviour>,
    /// Results of the next link checks; once empty, checks succeed.
    pub link_checks: VecDeque<Result<(), String>>,
    /// The stage's tilt, degrees; a move to the safe tilt sets it.
    pub tilt: f64,
    /// How long a move to the safe tilt takes.
    pub safe_move: Duration,
}

#[derive(Debug, Clone, Default)]
pub struct FakeRunner {
    pub script: Arc<Mutex<Script>>,
    pub events: Arc<Mutex<Vec<Event>>>,
}

impl FakeRunner {
    pub fn new(script: Script) -> Self {
        Self {
            script: Arc::new(Mutex::new(script)),
            events: Arc::default(),
        }
    }

    pub fn events(&self) -> Vec<Event> {
        self.events.lock().unwrap().clone()
    }

    pub fn started(&self) -> Vec<String> {
        self.events()
            .into_iter()
            .filter_map(|e| match e {
                Event::Started { name, .. } => Some(name),
                _ => None,
            })
            .collect()
    }

    pub fn link_check_times(&self) -> Vec<(Instant, bool)> {
        self.events()
            .into_iter()
            .filter_map(|e| match e {
                Event::LinkCheck { at, ok } => Some((at, ok)),
                _ => None,
            })
            .collect()
    }

    fn log(&self, e: Event) {
        self.events.lock().unwrap().push(e);
    }
}

impl JobRunner for FakeRunner {
    async fn check_links(&mut self, _config: &Config) -> Result<(), String> {
        let result = self
            .script
            .lock()
            .unwrap()
            .link_checks
            .pop_front()
            .unwrap_or(Ok(()));
        self.log(Event::LinkCheck {
            at: Instant::now(),
            ok: result.is_ok(),
        });
        result
    }

    async fn stage_tilt(&mut self, _config: &Config) -> Result<f64, String> {
        let tilt = self.script.lock().unwrap().tilt;
        self.log(Event::StageRead {
            at: Instant::now(),
            tilt,
        });
        Ok(tilt)
    }

    async fn move_to_safe_tilt(&mut self, config: &Config) -> Result<f64, String> {
        let (from, duration) = {
            let s = self.script.lock().unwrap();
            (s.tilt, s.safe_move)
        };
        tokio::time::sleep(duration).await;
        self.script.lock().unwrap().tilt = config.stage.safe_tilt_deg;
        self.log(Event::SafeMove {
            at: Instant::now(),
            from,
        });
        Ok(config.stage.safe_tilt_deg)
    }

    async fn run(
        &mut self,
        job: &JobRecord,
        _config: &Config,
        run_dir: &RunDir,
        ctx: JobContext,
    ) -> JobOutcome {
        self.log(Event::Started {
            name: job.name.clone(),
            at: Instant::now(),
            run_dir: run_dir.path().to_owned(),
        });
        // What a real run leaves: its record, in its own directory.
        use std::io::Write;
        run_dir
            .create_file("run.mcap")
            .unwrap()
            .write_all(job.name.as_bytes())
            .unwrap();
        let behaviour = self
            .script
            .lock()
            .unwrap()
            .jobs
            .get(&job.name)
            .cloned()
            .unwrap_or(Behaviour::Work {
                duration: Duration::from_secs(10),
                stop_after: Duration::from_secs(1),
            });
        let outcome = match behaviour {
            Behaviour::Work {
                duration,
                stop_after,
            } => {
                let end = Instant::now() + duration;
                let mut second = 0;
                loop {
                    tokio::select! {
                        () = tokio::time::sleep_until(end) => break JobOutcome::Completed,
                        () = tokio::time::sleep(Duration::from_secs(1)) => {
                            second += 1;
                            ctx.progress.report(format!("working, {second} s"));
                        }
                        reason = ctx.cancel.cancelled() => {
                            tokio::time::sleep(stop_after).await;
                            break JobOutcome::Interrupted {
                                reason: format!("stage back at its safe tilt after {second} s ({reason})"),
                            };
                        }
                    }
                }
            }
            Behaviour::Fail { after, reason } => {
                tokio::time::sleep(after).await;
                JobOutcome::Failed { reason }
            }
            Behaviour::Silent => {
                let reason = ctx.cancel.cancelled().await;
                JobOutcome::Interrupted { reason }
            }
            Behaviour::Deaf => std::future::pending().await,
        };
        self.log(Event::Ended {
            name: job.name.clone(),
            at: Instant::now(),
            outcome: outcome.clone(),
        });
        outcome
    }
}

/// Records every notification with its (tokio) time.
#[derive(Debug, Clone, Default)]
pub struct Recorder(pub Arc<Mutex<Vec<(Instant, Notice)>>>);

impl Notifier for Recorder {
    fn notify(&mut self, notice: Notice) {
        self.0.lock().unwrap().push((Instant::now(), notice));
    }
}

impl Recorder {
    pub fn notices(&self) -> Vec<Notice> {
        self.0
            .lock()
            .unwrap()
            .iter()
            .map(|(_, n)| n.clone())
            .collect()
    }

    pub fn statuses(&self) -> Vec<String> {
        self.notices()
            .into_iter()
            .filter_map(|n| match n {
                Notice::Status(s) => Some(s),
                _ => None,
            })
            .collect()
    }

    pub fn watchdogs_between(&self, from: Instant, to: Instant) -> usize {
        self.0
            .lock()
            .unwrap()
            .iter()
            .filter(|(t, n)| *n == Notice::Watchdog && *t >= from && *t < to)
            .count()
    }
}

/// A disk whose free space the test sets.
#[derive(Debug, Clone)]
pub struct FakeDisk(pub Arc<AtomicU64>);

impl FakeDisk {
    pub fn with_gib(gib: u64) -> Self {
        Self(Arc::new(AtomicU64::new(gib << 30)))
    }

    pub fn set_gib(&self, gib: u64) {
        self.0.store(gib << 30, Ordering::SeqCst);
    }
}

impl DiskSpace for FakeDisk {
    fn free_bytes(&self, _path: &Path) -> io::Result<u64> {
        Ok(self.0.load(Ordering::SeqCst))
    }
}
