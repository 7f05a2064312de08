//! The daemon under stress, as a process: `sdsem-eval soak` and `sdsem-eval kill`.
//!
//! Both start `sdsem daemon` (the `sdsem` binary given, by default the one beside this one) on a fresh spool, with the
//! stage-and-SEM simulator running in *this* process on fixed ports, so the
//! evaluation can take the instruments away and bring them back, count the
//! faults they injected and the frames they served, while the daemon only
//! sees its links.
//!
//! - **soak**: N consecutive short jobs (default 50: 0→4°, 320×240
//!   micrographs, reconstructed) while the simulator injects seeded random
//!   stage faults (dropped, garbled and late replies, i.e. timeouts; moves
//!   that do not happen, stale on-target flags, refused moves; link closes)
//!   and is switched off at random moments in the middle of jobs; a refused
//!   move switches a servo off, as on a PI controller, and the daemon waits
//!   (STATUS says why) until the evaluation, playing the operator, restarts
//!   the controller. Checks: no
//!   job stuck, every job in a final state with a reason, every MCAP readable
//!   and finished, the daemon alive throughout and exiting 0 on SIGTERM.
//!   Reports the daemon's RSS and open file descriptors after jobs 1, N/2, N.
//! - **kill**: R rounds (default 20) of: start the daemon, wait a random time
//!   (0.2–3 s: during start-up, in mid-job or between jobs), `kill -9`. Checks
//!   after each round: no job lost from the spool, no spool record damaged,
//!   no job started twice, the job that was running marked `interrupted` at
//!   the next start, every record readable with every frame it holds, and
//!   the frames the simulator served in the round against those readable (a
//!   frame in flight at the kill may be lost, nothing before it). A kill in mid-job leaves
//!   the stage tilted (the simulator lives on): the next start must read it and bring it
//!   to its safe tilt before any job starts.
//!
//! Time is the wall clock here: these are evaluations of real processes.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::net::{SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime};

use anyhow::Context;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;

use sdsem::daemon::spool::CRASH_REASON;
use sdsem::daemon::{JobRecord, JobSpec, JobState, Spool};
use sdsem::record::{self, RunStatus, topics};
use sdsem_sim::stage_model::FaultCounts;
use sdsem_sim::{FaultConfig, FaultTrigger, SimConfig, SimEndpoint, SimHandle, Simulator};

/// Real seconds per simulated second of the simulator in both evaluations.
const TIME_SCALE: f64 = 0.05;
/// A job running longer than this is stuck (a 0→4° job takes about a second).
const STUCK_AFTER: Duration = Duration::from_secs(120);
/// No job ending for this long means the daemon is stuck waiting.
const NO_PROGRESS: Duration = Duration::from_secs(180);
/// How often the spool and the simulator schedule are looked at.
const TICK: Duration = Duration::from_millis(25);

/// `sdsem-eval soak` settings.
#[derive(Debug, Clone)]
pub struct SoakOptions {
    /// The `sdsem` binary whose daemon is measured.
    pub sdsem: PathBuf,
    pub jobs: usize,
    pub seed: u64,
    /// Keep the work directory (spool, runs, daemon log) for inspection.
    pub keep: bool,
    pub json: bool,
}

/// `sdsem-eval kill` settings.
#[derive(Debug, Clone)]
pub struct KillOptions {
    /// The `sdsem` binary whose daemon is killed.
    pub sdsem: PathBuf,
    pub rounds: usize,
    pub seed: u64,
    pub keep: bool,
    pub json: bool,
}

/// Resources of the daemon process at one moment.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ProcessSample {
    /// Jobs in a final state when sampled.
    pub after_jobs: usize,
    pub rss_kib: u64,
    pub open_fds: usize,
}

/// Faults the simulator injected, summed over its restarts.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct InjectedFaults {
    pub dropped_replies: u64,
    pub garbled_replies: u64,
    pub late_replies: u64,
    pub ignored_moves: u64,
    pub stale_on_target: u64,
    pub move_errors: u64,
    pub link_closes: u64,
    /// Times the evaluation switched the simulator off in the middle of a job.
    pub simulator_off_mid_job: u64,
    /// Times the evaluation played the operator: a refused move left a servo
    /// off (as on a PI controller), the daemon waited with the links down
    /// saying so, and the controller was restarted.
    pub operator_restarts: u64,
}

impl InjectedFaults {
    fn add(&mut self, c: &FaultCounts) {
        self.dropped_replies += c.dropped_replies;
        self.garbled_replies += c.garbled_replies;
        self.late_replies += c.late_replies;
        self.ignored_moves += c.ignored_moves;
        self.stale_on_target += c.stale_on_target;
        self.move_errors += c.move_errors;
        self.link_closes += c.disconnects;
    }
}

/// The figures of `sdsem-eval soak`.
#[derive(Debug, Clone, Serialize)]
pub struct SoakReport {
    pub jobs: usize,
    pub seed: u64,
    pub wall_s: f64,
    /// Final states and how many jobs ended in each.
    pub states: BTreeMap<String, usize>,
    /// Reasons of the jobs that did not succeed, shortened, with counts.
    pub reasons: BTreeMap<String, usize>,
    pub faults: InjectedFaults,
    pub stuck_jobs: usize,
    pub jobs_without_final_state: usize,
    pub failures_without_reason: usize,
    pub records_readable: usize,
    pub records_finished: usize,
    /// Records whose outcome disagrees with the job's state.
    pub records_inconsistent: usize,
    pub job_seconds_median: f64,
    pub job_seconds_max: f64,
    pub samples: Vec<ProcessSample>,
    pub daemon_exit_code: Option<i32>,
    pub daemon_stop_s: f64,
    pub attacks: AttackFigures,
    pub problems: Vec<String>,
    pub work_dir: Option<PathBuf>,
}

/// What the hostile group member did to the spool during the soak, and what became of it.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct AttackFigures {
    /// Entries placed in `queued/` that are not records (directory, FIFO, link, …).
    pub entries_placed: usize,
    /// Of those, set aside in `quarantine/` with a reason.
    pub entries_set_aside: usize,
    /// Forged records placed straight into `queued/` (around `sdsem submit`).
    pub forged_records: usize,
    /// Of those, rejected with a reason (never run).
    pub forged_rejected: usize,
    /// Times `daemon.lock` was moved away, and times the daemon reported it.
    pub lock_file_moved: usize,
    pub lock_tampering_reported: usize,
    /// Directories created outside the output directory (must be 0).
    pub escaped_run_dirs: usize,
}
#[derive(Debug, Clone, Serialize)]
pub struct KillReport {
    pub rounds: usize,
    pub seed: u64,
    pub wall_s: f64,
    /// Kills with a job running, and with none (start-up or between jobs).
    pub kills_mid_job: usize,
    pub kills_idle: usize,
    /// Jobs left `running` by a kill, and of those, marked `interrupted`
    /// with the crash reason at the next start.
    pub jobs_cut_by_a_kill: usize,
    pub marked_interrupted_at_next_start: usize,
    pub jobs_lost: usize,
    pub jobs_started_twice: usize,
    pub spool_records_damaged: usize,
    pub records: usize,
    pub records_readable: usize,
    /// Records left unfinished by a kill (read up to where they were cut).
    pub records_cut: usize,
    /// Jobs killed before their record held a byte (the run directory was
    /// made, `run.mcap` missing or empty): nothing recorded, nothing lost.
    pub records_never_written: usize,
    pub frames_served: u64,
    pub frames_readable: u64,
    /// Largest number of frames served in one round but not readable.
    pub max_frames_lost_per_kill: u64,
    pub jobs_done: usize,
    /// Kills in mid-job that left the stage off its safe tilt.
    pub kills_leaving_stage_tilted: usize,
    /// Of those, stage checks at the next start that moved it to its safe tilt.
    pub stage_made_safe_at_next_start: usize,
    /// Jobs started while the stage check after an unclean end was pending (must be 0).
    pub jobs_started_before_stage_check: usize,
    pub final_stop_exit_code: Option<i32>,
    pub problems: Vec<String>,
    pub work_dir: Option<PathBuf>,
}

/// Runs the soak and prints its figures.
///
/// # Errors
/// When the rig cannot be set up (ports, files, the daemon binary); a daemon
/// that misbehaves is a figure, not an error.
pub fn run_soak(opts: &SoakOptions) -> anyhow::Result<SoakReport> {
    let report = soak(opts)?;
    if opts.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", format_soak(&report));
    }
    Ok(report)
}

/// Runs the kill test and prints its figures.
///
/// # Errors
/// As [`run_soak`].
pub fn run_kill(opts: &KillOptions) -> anyhow::Result<KillReport> {
    let report = kill(opts)?;
    if opts.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", format_kill(&report));
    }
    Ok(report)
}

// ---------------------------------------------------------------------------
// The rig: work directory, simulator, daemon process.

struct Rig {
    sdsem: PathBuf,
    dir: PathBuf,
    keep: bool,
    spool: PathBuf,
    config: PathBuf,
    stage_port: u16,
    sem_port: u16,
}

impl Rig {
    fn new(kind: &str, sdsem: &Path, keep: bool) -> anyhow::Result<Self> {
        let dir = std::env::temp_dir().join(format!(
            "sdsem-eval-{kind}-{}-{}",
            std::process::id(),
            SystemTime::now()
                .duration_since(SystemTime::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs())
        ));
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        Ok(Self {
            sdsem: sdsem.to_path_buf(),
            spool: dir.join("spool"),
            config: dir.join("sdsem.toml"),
            stage_port: free_port()?,
            sem_port: free_port()?,
            dir,
            keep,
        })
    }

    /// The daemon's configuration: the rig's simulator, small frames, quick
    /// timeouts (so that dropped replies cost little), short backoff.
    fn write_config(&self, reconstruct: bool) -> anyhow::Result<()> {
        let text = format!(
            r#"[run]
output_dir = {runs:?}
reconstruct = {reconstruct}

[stage]
endpoint = "tcp://127.0.0.1:{stage}"
axis_x = "X"
axis_y = "Y"
axis_tilt = "T"
poll_interval_s = 0.01
connect_timeout_s = 2.0
reply_timeout_s = 0.3

[imaging]
endpoint = "tcp://127.0.0.1:{sem}"
timeout_ms = 3000

[imaging.micrograph]
width = 320
height = 240
dwell_us = 10.0

[imaging.tracking]
width = 160
height = 120
dwell_us = 1.0

[daemon]
spool_dir = {spool:?}
min_free_gib = 0.1
poll_interval_s = 0.1
backoff_initial_s = 0.2
backoff_max_s = 1.0
link_check_timeout_s = 5.0
stall_timeout_s = 60.0
"#,
            runs = self.dir.join("runs"),
            spool = self.spool,
            stage = self.stage_port,
            sem = self.sem_port,
        );
        std::fs::write(&self.config, text)
            .with_context(|| format!("cannot write {}", self.config.display()))
    }

    fn submit(&self, count: usize, end_tilt: u32) -> anyhow::Result<Vec<JobRecord>> {
        let spool = Spool::open(&self.spool)?;
        (1..=count)
            .map(|i| {
                let spec = JobSpec::parse(&format!(
                    "name = \"job-{i:03}\"\nstart_tilt = 0\nend_tilt = {end_tilt}\n"
                ))?;
                Ok(spool.submit(spec, SystemTime::now())?)
            })
            .collect()
    }

    fn jobs(&self) -> anyhow::Result<(Vec<JobRecord>, usize)> {
        let listing = Spool::existing(&self.spool)?.list()?;
        Ok((listing.jobs, listing.unreadable.len()))
    }

    fn spawn_daemon(&self, tag: &str) -> anyhow::Result<DaemonProcess> {
        let log = self.dir.join(format!("daemon-{tag}.log"));
        let child = Command::new(&self.sdsem)
            .args(["--log-format", "text", "daemon", "--config"])
            .arg(&self.config)
            .env("RUST_LOG", "info")
            .env_remove("NOTIFY_SOCKET")
            .env_remove("WATCHDOG_USEC")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log)?)
            .spawn()
            .with_context(|| format!("cannot start {} daemon", self.sdsem.display()))?;
        Ok(DaemonProcess {
            child,
            started: Instant::now(),
        })
    }

    fn finish(self) -> Option<PathBuf> {
        if self.keep {
            Some(self.dir)
        } else {
            let _ = std::fs::remove_dir_all(&self.dir);
            None
        }
    }
}

fn free_port() -> anyhow::Result<u16> {
    Ok(TcpListener::bind("127.0.0.1:0")
        .context("cannot find a free TCP port")?
        .local_addr()?
        .port())
}

struct DaemonProcess {
    child: Child,
    started: Instant,
}

impl DaemonProcess {
    fn pid(&self) -> u32 {
        self.child.id()
    }

    /// The exit code once it has exited (-signal when killed by one).
    fn exited(&mut self) -> Option<i32> {
        use std::os::unix::process::ExitStatusExt;
        self.child
            .try_wait()
            .ok()
            .flatten()
            .map(|s| s.code().unwrap_or_else(|| -s.signal().unwrap_or(0)))
    }

    fn sample(&self, after_jobs: usize) -> Option<ProcessSample> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.pid())).ok()?;
        let rss_kib = status
            .lines()
            .find(|l| l.starts_with("VmRSS:"))?
            .split_whitespace()
            .nth(1)?
            .parse()
            .ok()?;
        let open_fds = std::fs::read_dir(format!("/proc/{}/fd", self.pid()))
            .ok()?
            .count();
        Some(ProcessSample {
            after_jobs,
            rss_kib,
            open_fds,
        })
    }

    fn terminate(&self) -> anyhow::Result<()> {
        let pid = rustix::process::Pid::from_raw(i32::try_from(self.pid())?)
            .context("no such process")?;
        rustix::process::kill_process(pid, rustix::process::Signal::TERM)
            .context("cannot send SIGTERM to the daemon")
    }

    fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Waits for the exit, at most `limit`; kills it if it overruns.
    fn wait(&mut self, limit: Duration) -> (Option<i32>, Duration) {
        let t0 = Instant::now();
        while t0.elapsed() < limit {
            if let Some(code) = self.exited() {
                return (Some(code), t0.elapsed());
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        self.kill9();
        (None, t0.elapsed())
    }
}

impl Drop for DaemonProcess {
    fn drop(&mut self) {
        if self.exited().is_none() {
            self.kill9();
        }
    }
}

/// The simulator, switched on and off by the evaluation.
struct Instruments {
    base: SimConfig,
    running: Option<SimHandle>,
    faults: InjectedFaults,
    /// Frames served by simulators already switched off.
    frames_before: u64,
}

impl Instruments {
    fn new(stage_port: u16, sem_port: u16) -> Self {
        let mut base = SimConfig {
            time_scale: TIME_SCALE,
            ..SimConfig::default()
        };
        base.stage.endpoint = SimEndpoint::Tcp(SocketAddr::from(([127, 0, 0, 1], stage_port)));
        base.sem.endpoint = SimEndpoint::Tcp(SocketAddr::from(([127, 0, 0, 1], sem_port)));
        // A smaller specimen builds faster at every restart; the field of view fits.
        base.sem.scene.field_um = 150.0;
        Self {
            base,
            running: None,
            faults: InjectedFaults::default(),
            frames_before: 0,
        }
    }

    fn on(&mut self, seed: u64, faults: FaultConfig) -> anyhow::Result<()> {
        let mut config = self.base.clone();
        config.seed = seed;
        config.stage.faults = faults;
        // The ports of the previous simulator may take a moment to be free.
        let t0 = Instant::now();
        loop {
            match Simulator::spawn(config.clone()) {
                Ok(sim) => {
                    self.running = Some(sim);
                    return Ok(());
                }
                Err(e) if t0.elapsed() < Duration::from_secs(10) => {
                    tracing::debug!("simulator start: {e}; retrying");
                    std::thread::sleep(Duration::from_millis(50));
                }
                Err(e) => return Err(e).context("cannot start the simulator"),
            }
        }
    }

    fn off(&mut self) {
        if let Some(sim) = self.running.take() {
            self.faults.add(&sim.stage_snapshot().faults);
            // Frames are numbered from 1: the last number is the count.
            self.frames_before += sim.last_frame().unwrap_or(0);
            sim.stop();
        }
    }

    fn is_on(&self) -> bool {
        self.running.is_some()
    }

    /// The simulated stage's tilt now (0 when switched off).
    fn stage_tilt(&self) -> f64 {
        self.running
            .as_ref()
            .map_or(0.0, |sim| sim.stage_snapshot().pose.tilt_deg)
    }

    /// Frames served so far, by every simulator switched on.
    fn frames_served(&self) -> u64 {
        self.frames_before
            + self
                .running
                .as_ref()
                .and_then(SimHandle::last_frame)
                .unwrap_or(0)
    }
}

/// The hostile group member of the soak: what it placed in the spool.
#[derive(Default)]
struct Attacker {
    rounds: usize,
    /// Entries that are not records, by the name `sdsem status` shows.
    entries: Vec<String>,
    forged: Vec<u64>,
    locks_moved: usize,
}

impl Attacker {
    /// One round: entries that once blocked, crashed or fooled the daemon, dropped into
    /// `queued/` under the names of jobs already ended (so they are at the head of the
    /// queue), forged records under fresh ids, and `daemon.lock` moved away.
    fn attack(&mut self, rig: &Rig, ended: &[u64], template: &JobRecord) -> anyhow::Result<()> {
        use std::os::unix::fs::PermissionsExt;
        self.rounds += 1;
        let round = self.rounds;
        let q = rig.spool.join("queued");
        let mut free = ended.iter().rev().map(|id| format!("{id:08}.json"));
        let mut place = |make: &dyn Fn(&Path) -> std::io::Result<()>| -> anyhow::Result<()> {
            if let Some(name) = free.next() {
                make(&q.join(&name))?;
                self.entries.push(name);
            }
            Ok(())
        };
        place(&|p| std::fs::create_dir(p))?;
        place(&|p| {
            rustix::fs::mknodat(
                rustix::fs::CWD,
                p,
                rustix::fs::FileType::Fifo,
                rustix::fs::Mode::from_raw_mode(0o666),
                0,
            )
            .map_err(Into::into)
        })?;
        place(&|p| std::os::unix::fs::symlink("/dev/zero", p))?;
        place(&|p| {
            std::fs::write(p, "x")?;
            std::fs::set_permissions(p, std::fs::Permissions::from_mode(0o000))
        })?;
        place(&|p| std::fs::write(p, vec![b'{'; 300 * 1024]))?;
        place(&|p| std::fs::write(p, "{\"id\": 1, \"state\": "))?;
        let evil = format!("\u{1b}[2J\u{1b}]0;pwned-{round}\u{7}\n.json");
        std::fs::write(q.join(&evil), "{}")?;
        self.entries
            .push(sdsem::acquisition::run_dir::printable(&evil, 120));
        let edits: [&dyn Fn(&mut serde_json::Value); 3] = [
            &|v| {
                v["name"] = "../../pub/evil".into();
                v["job"]["name"] = "../../pub/evil".into();
            },
            &|v| v["job"]["step"] = 1e-9.into(),
            &|v| {
                v["job"]["capture"] = serde_json::json!({"tracking": {"max_correction_um": 500.0}});
            },
        ];
        for (k, edit) in edits.iter().enumerate() {
            let id = 1_000_000 + 10 * round as u64 + k as u64;
            let mut v = serde_json::to_value(template)?;
            v["id"] = id.into();
            edit(&mut v);
            std::fs::write(q.join(format!("{id:08}.json")), v.to_string())?;
            self.forged.push(id);
        }
        if std::fs::rename(
            rig.spool.join("daemon.lock"),
            rig.dir.join(format!("stolen-{round}.lock")),
        )
        .is_ok()
        {
            self.locks_moved += 1;
        }
        Ok(())
    }

    /// What became of the attacks, from the spool at the end.
    fn figures(
        &self,
        listing: &sdsem::daemon::spool::Listing,
        status: Option<&sdsem::daemon::spool::DaemonStatus>,
    ) -> AttackFigures {
        let set_aside: std::collections::HashSet<&str> =
            listing.set_aside.iter().map(|u| u.name.as_str()).collect();
        let forged: Vec<&JobRecord> = listing
            .jobs
            .iter()
            .filter(|j| self.forged.contains(&j.id.0))
            .collect();
        AttackFigures {
            entries_placed: self.entries.len(),
            entries_set_aside: self
                .entries
                .iter()
                .filter(|n| set_aside.contains(n.as_str()))
                .count(),
            forged_records: self.forged.len(),
            forged_rejected: forged
                .iter()
                .filter(|j| j.state == JobState::Rejected && j.reason.is_some())
                .count(),
            lock_file_moved: self.locks_moved,
            lock_tampering_reported: status.map_or(0, |s| {
                s.warnings
                    .iter()
                    .filter(|w| w.contains("daemon.lock"))
                    .count()
            }),
            escaped_run_dirs: forged.iter().filter(|j| j.run_dir.is_some()).count(),
        }
    }
}

/// The stage faults of one simulator life: seeded random replies and moves
/// that go wrong, and, one life in two, a link close after a random count of
/// commands (a job sends a few hundred).
fn random_faults(rng: &mut ChaCha8Rng) -> FaultConfig {
    FaultConfig {
        drop_reply: FaultTrigger::probability(0.003),
        garble_reply: FaultTrigger::probability(0.003),
        late_reply: FaultTrigger::probability(0.002),
        late_reply_delay_s: 0.6,
        ignore_move: FaultTrigger::probability(0.03),
        stale_on_target: FaultTrigger::probability(0.03),
        move_error: FaultTrigger::probability(0.008),
        disconnect_after_commands: rng.random_bool(0.5).then(|| rng.random_range(50..1500)),
        ..FaultConfig::default()
    }
}

/// Checks one run record as a user would read it: every frame decodes and
/// the frames are numbered without a gap. Returns (frames, finished, outcome).
fn check_record(path: &Path) -> Result<(u64, bool, Option<RunStatus>), String> {
    let summary = record::read_summary(path).map_err(|e| e.to_string())?;
    let frames =
        record::read_images(path, topics::SEM_FRAME, |_| true).map_err(|e| e.to_string())?;
    for f in &frames.items {
        f.to_image()
            .map_err(|e| format!("{}: frame at {} ns: {e}", path.display(), f.log_time_ns))?;
    }
    let infos = record::read_json(path, topics::SEM_FRAME_INFO).map_err(|e| e.to_string())?;
    for (expected, info) in infos.items.iter().enumerate() {
        let index = info.value.get("index").and_then(serde_json::Value::as_u64);
        if index != Some(expected as u64) {
            return Err(format!(
                "{}: frame info {expected} has index {index:?}: a frame is missing",
                path.display()
            ));
        }
    }
    Ok((
        frames.items.len() as u64,
        summary.end.complete,
        summary.outcome.map(|o| o.status),
    ))
}

fn shorten(reason: &str) -> String {
    // Group reasons by their cause, not by the numbers in them.
    let cut: String = reason
        .chars()
        .map(|c| if c.is_ascii_digit() { '#' } else { c })
        .collect();
    let cut = cut.split(';').next().unwrap_or("").trim();
    if cut.chars().count() > 110 {
        format!("{}…", cut.chars().take(110).collect::<String>())
    } else {
        cut.to_owned()
    }
}

// ---------------------------------------------------------------------------
// Soak.

#[allow(clippy::too_many_lines)]
fn soak(opts: &SoakOptions) -> anyhow::Result<SoakReport> {
    let t0 = Instant::now();
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let rig = Rig::new("soak", &opts.sdsem, opts.keep)?;
    rig.write_config(true)?;
    let mut instruments = Instruments::new(rig.stage_port, rig.sem_port);
    instruments.on(rng.random(), random_faults(&mut rng))?;
    let submitted = rig.submit(opts.jobs, 4)?;
    let mut daemon = rig.spawn_daemon("soak")?;
    eprintln!(
        "soak: {} jobs, seed {}, daemon PID {}, work dir {}",
        opts.jobs,
        opts.seed,
        daemon.pid(),
        rig.dir.display()
    );

    let checkpoints = checkpoints(opts.jobs);
    let last_id = submitted.last().map_or(0, |j| j.id.0);
    // Five attacks on the spool, spread over the soak.
    let mut attack_at: Vec<usize> = (1..=5)
        .map(|k| k * opts.jobs / 6)
        .filter(|&k| k > 0)
        .collect();
    attack_at.dedup();
    let mut attacker = Attacker::default();
    let mut samples = Vec::new();
    let mut problems = Vec::new();
    let mut running: Option<(u64, Instant)> = None;
    let mut off_at: Option<Instant> = None;
    let mut on_at: Option<Instant> = None;
    let mut durations: Vec<f64> = Vec::new();
    let mut finals_seen = 0;
    let mut stuck = 0;
    let mut last_progress = Instant::now();
    let deadline = Instant::now() + Duration::from_secs(60) * u32::try_from(opts.jobs)?;
    loop {
        std::thread::sleep(TICK);
        if let Some(code) = daemon.exited() {
            problems.push(format!(
                "the daemon exited with {code} in the middle of the soak"
            ));
            break;
        }
        let now = Instant::now();
        if off_at.is_some_and(|t| now >= t) {
            off_at = None;
            if instruments.is_on() {
                instruments.off();
                instruments.faults.simulator_off_mid_job += 1;
                on_at = Some(now + Duration::from_millis(rng.random_range(200..1500)));
            }
        }
        if on_at.is_some_and(|t| now >= t) {
            on_at = None;
            instruments.on(rng.random(), random_faults(&mut rng))?;
        }
        // The operator's part: a servo switched off by a refused move keeps
        // the daemon waiting (rightly) until someone restarts the controller.
        if instruments.is_on()
            && on_at.is_none()
            && off_at.is_none()
            && Spool::existing(&rig.spool)?
                .daemon_status()
                .is_some_and(|d| d.status.contains("servo off"))
        {
            instruments.off();
            instruments.faults.operator_restarts += 1;
            on_at = Some(now + Duration::from_millis(300));
        }
        // Hostile entries are seen as unreadable until the daemon sets them aside: only
        // what is left at the end counts. The forged records are not the soak's jobs.
        let (mut jobs, _) = rig.jobs()?;
        let forged_final = jobs
            .iter()
            .filter(|j| attacker.forged.contains(&j.id.0) && j.state.is_final())
            .count();
        jobs.retain(|j| j.id.0 <= last_id);
        let current = jobs.iter().find(|j| j.state == JobState::Running);
        match (current, running) {
            (Some(job), Some((id, since))) if job.id.0 == id => {
                if since.elapsed() > STUCK_AFTER {
                    stuck += 1;
                    problems.push(format!("job {id} stuck in running for {STUCK_AFTER:?}"));
                    break;
                }
            }
            (Some(job), _) => {
                if let Some((_, since)) = running {
                    durations.push(since.elapsed().as_secs_f64());
                }
                running = Some((job.id.0, now));
                // One job in eight loses its instruments at a random moment.
                if instruments.is_on() && off_at.is_none() && rng.random_bool(0.125) {
                    off_at = Some(now + Duration::from_millis(rng.random_range(50..1200)));
                }
            }
            (None, Some((_, since))) => {
                durations.push(since.elapsed().as_secs_f64());
                running = None;
            }
            (None, None) => {}
        }
        // Instruments switched off by a link-close fault's aftermath stay on;
        // only the evaluation switches them off, and always back on.
        if !instruments.is_on() && on_at.is_none() {
            instruments.on(rng.random(), random_faults(&mut rng))?;
        }
        let finals = jobs.iter().filter(|j| j.state.is_final()).count();
        if finals > finals_seen {
            last_progress = now;
        } else if now.duration_since(last_progress) > NO_PROGRESS {
            let status = Spool::existing(&rig.spool)?
                .daemon_status()
                .map(|d| d.status)
                .unwrap_or_default();
            problems.push(format!(
                "no job ended for {NO_PROGRESS:?}; the daemon says: {status}"
            ));
            break;
        }
        for k in (finals_seen + 1)..=finals {
            if checkpoints.contains(&k)
                && let Some(s) = daemon.sample(k)
            {
                samples.push(s);
            }
        }
        finals_seen = finals;
        if attack_at.first().is_some_and(|&k| finals >= k) {
            attack_at.remove(0);
            let ended: Vec<u64> = jobs
                .iter()
                .filter(|j| j.state.is_final())
                .map(|j| j.id.0)
                .collect();
            attacker.attack(&rig, &ended, &submitted[0])?;
        }
        if finals == submitted.len() && forged_final == attacker.forged.len() {
            break;
        }
        if now > deadline {
            problems.push("the soak did not finish in time".into());
            break;
        }
    }

    let stop_sent = Instant::now();
    daemon.terminate()?;
    let (exit_code, _) = daemon.wait(Duration::from_secs(20));
    let daemon_stop_s = stop_sent.elapsed().as_secs_f64();
    if exit_code != Some(0) {
        problems.push(format!("the daemon's exit on SIGTERM: {exit_code:?}"));
    }
    instruments.off();

    let spool = Spool::existing(&rig.spool)?;
    let listing = spool.list()?;
    let attacks = attacker.figures(&listing, spool.daemon_status().as_ref());
    if !listing.unreadable.is_empty() {
        problems.push(format!(
            "{} entries of the spool were never set aside: {:?}",
            listing.unreadable.len(),
            listing.unreadable
        ));
    }
    if attacks.entries_set_aside != attacks.entries_placed
        || attacks.forged_rejected != attacks.forged_records
        || attacks.lock_tampering_reported != attacks.lock_file_moved
        || attacks.escaped_run_dirs > 0
    {
        problems.push(format!("attacks on the spool not all handled: {attacks:?}"));
    }
    let jobs: Vec<JobRecord> = listing
        .jobs
        .into_iter()
        .filter(|j| j.id.0 <= last_id)
        .collect();
    let mut states = BTreeMap::new();
    let mut reasons = BTreeMap::new();
    let (mut without_final, mut without_reason) = (0, 0);
    let (mut readable, mut finished, mut inconsistent) = (0, 0, 0);
    for job in &jobs {
        *states.entry(job.state.to_string()).or_insert(0) += 1;
        if !job.state.is_final() {
            without_final += 1;
        }
        if job.state != JobState::Done {
            match &job.reason {
                Some(r) if !r.trim().is_empty() => *reasons.entry(shorten(r)).or_insert(0) += 1,
                _ => without_reason += 1,
            }
        }
        let Some(dir) = &job.run_dir else { continue };
        match check_record(&dir.join(sdsem::acquisition::job::files::RECORD)) {
            Ok((_, complete, outcome)) => {
                readable += 1;
                finished += usize::from(complete);
                let expected = match job.state {
                    JobState::Done => Some(RunStatus::Succeeded),
                    JobState::Failed => Some(RunStatus::Failed),
                    JobState::Interrupted => Some(RunStatus::Aborted),
                    _ => None,
                };
                if outcome != expected {
                    inconsistent += 1;
                    problems.push(format!(
                        "job {} is {} but its record says {outcome:?}",
                        job.id, job.state
                    ));
                }
            }
            Err(e) => problems.push(format!("job {}: record unreadable: {e}", job.id)),
        }
    }
    durations.sort_by(f64::total_cmp);
    Ok(SoakReport {
        jobs: submitted.len(),
        seed: opts.seed,
        wall_s: t0.elapsed().as_secs_f64(),
        states,
        reasons,
        faults: instruments.faults,
        stuck_jobs: stuck,
        jobs_without_final_state: without_final,
        failures_without_reason: without_reason,
        records_readable: readable,
        records_finished: finished,
        records_inconsistent: inconsistent,
        job_seconds_median: durations.get(durations.len() / 2).copied().unwrap_or(0.0),
        job_seconds_max: durations.last().copied().unwrap_or(0.0),
        samples,
        daemon_exit_code: exit_code,
        daemon_stop_s,
        attacks,
        problems,
        work_dir: rig.finish(),
    })
}

/// The start of the line-part saying the stage was moved to its safe tilt after an unclean end.
const MOVED: &str = "moved to its safe tilt (";
/// ... or that it was found there.
const FOUND: &str = "found at its safe tilt (";

/// Where a daemon's log says its stage check after an unclean end ended, if it did.
fn stage_check_line(log: &str) -> Option<usize> {
    [log.find(MOVED), log.find(FOUND)]
        .into_iter()
        .flatten()
        .min()
}

/// Jobs a daemon started, by its log, before its stage check after an unclean end ended
/// (all of them when the check never ended); 0 after a clean end.
fn started_before_stage_check(log: &str) -> usize {
    if !log.contains("ended uncleanly") {
        return 0;
    }
    let end = stage_check_line(log).unwrap_or(log.len());
    log[..end].matches("job started").count()
}

/// True when a record holds nothing at all: missing, or empty.
fn record_never_written(path: &Path) -> bool {
    std::fs::metadata(path).map_or(true, |m| m.len() == 0)
}

/// Jobs after which the daemon's resources are sampled: 1, the middle, the last.
fn checkpoints(jobs: usize) -> Vec<usize> {
    let mut c = vec![1, jobs.div_ceil(2), jobs];
    c.dedup();
    c
}

fn format_soak(r: &SoakReport) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "soak: {} jobs, seed {}, {:.0} s; job time median {:.2} s, max {:.2} s",
        r.jobs, r.seed, r.wall_s, r.job_seconds_median, r.job_seconds_max
    );
    let states: Vec<String> = r.states.iter().map(|(k, v)| format!("{k} {v}")).collect();
    let _ = writeln!(s, "final states: {}", states.join(", "));
    let f = &r.faults;
    let _ = writeln!(
        s,
        "faults injected: {} dropped, {} garbled, {} late replies; {} ignored moves, {} stale \
         on-target, {} refused moves; {} link closes; simulator off mid-job {} times; \
         operator restarts after a servo went off {}",
        f.dropped_replies,
        f.garbled_replies,
        f.late_replies,
        f.ignored_moves,
        f.stale_on_target,
        f.move_errors,
        f.link_closes,
        f.simulator_off_mid_job,
        f.operator_restarts
    );
    let _ = writeln!(s, "reasons of jobs not done:");
    for (reason, n) in &r.reasons {
        let _ = writeln!(s, "  {n:3} × {reason}");
    }
    let _ = writeln!(
        s,
        "stuck {}, without final state {}, not done without reason {}",
        r.stuck_jobs, r.jobs_without_final_state, r.failures_without_reason
    );
    let _ = writeln!(
        s,
        "records: {} readable, {} finished, {} disagreeing with their job's state",
        r.records_readable, r.records_finished, r.records_inconsistent
    );
    let _ = writeln!(s, "daemon   after job   RSS MiB   open fds");
    for p in &r.samples {
        #[allow(clippy::cast_precision_loss)]
        let mib = p.rss_kib as f64 / 1024.0;
        let _ = writeln!(
            s,
            "         {:9}   {mib:7.1}   {:8}",
            p.after_jobs, p.open_fds
        );
    }
    let a = &r.attacks;
    let _ = writeln!(
        s,
        "spool attacks: {} hostile entries, {} set aside with a reason; {} forged records, {} \
         rejected with a reason; daemon.lock moved {} times, reported {}; run directories \
         outside the output directory {}",
        a.entries_placed,
        a.entries_set_aside,
        a.forged_records,
        a.forged_rejected,
        a.lock_file_moved,
        a.lock_tampering_reported,
        a.escaped_run_dirs
    );
    let _ = writeln!(
        s,
        "SIGTERM at the end: exit {:?} after {:.2} s",
        r.daemon_exit_code, r.daemon_stop_s
    );
    write_problems(&mut s, &r.problems, r.work_dir.as_deref());
    s
}

fn write_problems(s: &mut String, problems: &[String], work_dir: Option<&Path>) {
    if problems.is_empty() {
        let _ = writeln!(s, "problems: none");
    } else {
        let _ = writeln!(s, "problems ({}):", problems.len());
        for p in problems {
            let _ = writeln!(s, "  {p}");
        }
    }
    if let Some(dir) = work_dir {
        let _ = writeln!(s, "work dir kept: {}", dir.display());
    }
}

// ---------------------------------------------------------------------------
// Kill.

#[allow(clippy::too_many_lines)]
fn kill(opts: &KillOptions) -> anyhow::Result<KillReport> {
    let t0 = Instant::now();
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let rig = Rig::new("kill", &opts.sdsem, opts.keep)?;
    rig.write_config(false)?;
    let mut instruments = Instruments::new(rig.stage_port, rig.sem_port);
    instruments.on(opts.seed, FaultConfig::default())?;
    // More than enough: a round runs at most a few 0→6° jobs.
    let submitted = rig.submit(opts.rounds * 4 + 10, 6)?;
    let ids: Vec<u64> = submitted.iter().map(|j| j.id.0).collect();
    eprintln!(
        "kill: {} rounds, seed {}, {} jobs queued, work dir {}",
        opts.rounds,
        opts.seed,
        ids.len(),
        rig.dir.display()
    );

    let mut report = KillReport {
        rounds: opts.rounds,
        seed: opts.seed,
        wall_s: 0.0,
        kills_mid_job: 0,
        kills_idle: 0,
        jobs_cut_by_a_kill: 0,
        marked_interrupted_at_next_start: 0,
        jobs_lost: 0,
        jobs_started_twice: 0,
        spool_records_damaged: 0,
        records: 0,
        records_readable: 0,
        records_cut: 0,
        records_never_written: 0,
        frames_served: 0,
        frames_readable: 0,
        max_frames_lost_per_kill: 0,
        jobs_done: 0,
        kills_leaving_stage_tilted: 0,
        stage_made_safe_at_next_start: 0,
        jobs_started_before_stage_check: 0,
        final_stop_exit_code: None,
        problems: Vec::new(),
        work_dir: None,
    };
    // First (started, run dir) seen for each job: they must never change.
    let mut first_start: BTreeMap<u64, (Option<String>, Option<PathBuf>)> = BTreeMap::new();
    let mut cut: Vec<u64> = Vec::new();
    let mut readable_frames: BTreeMap<u64, u64> = BTreeMap::new();
    let mut reported = std::collections::BTreeSet::new();
    let mut left_tilted: Option<usize> = None;

    for round in 1..=opts.rounds + 1 {
        let last = round > opts.rounds;
        let frames_before = instruments.frames_served();
        let mut daemon = rig.spawn_daemon(&format!("{round:02}"))?;
        // Jobs a previous kill cut are marked at start-up, before READY.
        if !cut.is_empty() {
            let t = Instant::now();
            while t.elapsed() < Duration::from_secs(10) {
                let (jobs, _) = rig.jobs()?;
                if cut.iter().all(|id| {
                    jobs.iter()
                        .any(|j| j.id.0 == *id && j.state != JobState::Running)
                }) {
                    break;
                }
                std::thread::sleep(TICK);
            }
        }
        // A kill that left the stage tilted: the stage is read and moved before any job.
        let log_path = rig.dir.join(format!("daemon-{round:02}.log"));
        if left_tilted.take().is_some() {
            let t = Instant::now();
            let resolved = loop {
                let log = std::fs::read_to_string(&log_path).unwrap_or_default();
                if let Some(at) = stage_check_line(&log) {
                    break Some(log[at..].starts_with(MOVED));
                }
                if t.elapsed() > Duration::from_secs(20) {
                    break None;
                }
                std::thread::sleep(TICK);
            };
            match resolved {
                Some(true) => report.stage_made_safe_at_next_start += 1,
                other => report.problems.push(format!(
                    "round {round}: the stage left tilted by the last kill was not moved to its \
                     safe tilt at this start ({other:?}; the stage is at {:.3}°)",
                    instruments.stage_tilt()
                )),
            }
        }
        let (jobs, _) = rig.jobs()?;
        for id in cut.drain(..) {
            match jobs.iter().find(|j| j.id.0 == id) {
                Some(j)
                    if j.state == JobState::Interrupted
                        && j.reason.as_deref() == Some(CRASH_REASON) =>
                {
                    report.marked_interrupted_at_next_start += 1;
                }
                other => report.problems.push(format!(
                    "round {round}: job {id}, cut by the last kill, is {:?} after the restart",
                    other.map(|j| (j.state, j.reason.clone()))
                )),
            }
        }
        if last {
            std::thread::sleep(Duration::from_millis(500));
            daemon.terminate()?;
            let (code, _) = daemon.wait(Duration::from_secs(20));
            report.final_stop_exit_code = code;
            if code != Some(0) {
                report
                    .problems
                    .push(format!("final SIGTERM: exit {code:?}"));
            }
        } else {
            let wait = Duration::from_millis(rng.random_range(200..3000));
            while daemon.started.elapsed() < wait {
                std::thread::sleep(TICK);
            }
            let (before, _) = rig.jobs()?;
            daemon.kill9();
            let mid_job = before.iter().any(|j| j.state == JobState::Running);
            if mid_job {
                report.kills_mid_job += 1;
            } else {
                report.kills_idle += 1;
            }
            // The simulator lives on: a move in flight ends where it was going.
            std::thread::sleep(Duration::from_millis(300));
            if instruments.stage_tilt().abs() > 0.05 {
                report.kills_leaving_stage_tilted += 1;
                left_tilted = Some(round);
            }
        }

        let early =
            started_before_stage_check(&std::fs::read_to_string(&log_path).unwrap_or_default());
        if early > 0 {
            report.jobs_started_before_stage_check += early;
            report.problems.push(format!(
                "round {round}: {early} job(s) started before the stage check after an unclean end"
            ));
        }
        let (jobs, damaged) = rig.jobs()?;
        report.spool_records_damaged += damaged;
        for id in &ids {
            if !jobs.iter().any(|j| j.id.0 == *id) {
                report.jobs_lost += 1;
                report
                    .problems
                    .push(format!("round {round}: job {id} is gone from the spool"));
            }
        }
        for j in &jobs {
            if j.started.is_none() {
                continue;
            }
            let now = (j.started.clone(), j.run_dir.clone());
            match first_start.get(&j.id.0) {
                None => {
                    first_start.insert(j.id.0, now);
                }
                Some(first) if *first != now => {
                    report.jobs_started_twice += 1;
                    report
                        .problems
                        .push(format!("round {round}: job {} was started again", j.id));
                }
                Some(_) => {}
            }
            if j.state == JobState::Running && !last {
                cut.push(j.id.0);
                report.jobs_cut_by_a_kill += 1;
            }
        }
        // Records: every one readable, every frame in it, numbered without gaps.
        let mut round_readable = 0;
        for j in &jobs {
            let Some(dir) = &j.run_dir else { continue };
            let path = dir.join(sdsem::acquisition::job::files::RECORD);
            match check_record(&path) {
                Ok((frames, _, _)) => {
                    let before = readable_frames.insert(j.id.0, frames).unwrap_or(0);
                    round_readable += frames.saturating_sub(before);
                }
                // Killed between marking the job running and creating its
                // record, or before the record's first bytes reached the disk:
                // nothing was recorded, and the frame count below shows
                // whether anything was lost.
                Err(_) if record_never_written(&path) => {}
                Err(e) => {
                    if reported.insert(j.id.0) {
                        report
                            .problems
                            .push(format!("round {round}: job {}: {e}", j.id));
                    }
                }
            }
        }
        let served = instruments.frames_served() - frames_before;
        report.frames_served += served;
        report.frames_readable += round_readable;
        report.max_frames_lost_per_kill = report
            .max_frames_lost_per_kill
            .max(served.saturating_sub(round_readable));
    }
    instruments.off();

    let (jobs, _) = rig.jobs()?;
    for j in &jobs {
        if j.state == JobState::Done {
            report.jobs_done += 1;
        }
        let Some(dir) = &j.run_dir else { continue };
        let path = dir.join(sdsem::acquisition::job::files::RECORD);
        match check_record(&path) {
            Ok((_, complete, _)) => {
                report.records += 1;
                report.records_readable += 1;
                report.records_cut += usize::from(!complete);
            }
            Err(_) if record_never_written(&path) => report.records_never_written += 1,
            Err(_) => report.records += 1,
        }
    }
    report.wall_s = t0.elapsed().as_secs_f64();
    report.work_dir = rig.finish();
    Ok(report)
}

fn format_kill(r: &KillReport) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "kill -9: {} rounds, seed {}, {:.0} s; killed mid-job {} times, idle or starting {} times",
        r.rounds, r.seed, r.wall_s, r.kills_mid_job, r.kills_idle
    );
    let _ = writeln!(
        s,
        "jobs cut by a kill {}, marked interrupted (crash reason) at the next start {}",
        r.jobs_cut_by_a_kill, r.marked_interrupted_at_next_start
    );
    let _ = writeln!(
        s,
        "jobs lost {}, started twice {}, damaged spool records {}; jobs done meanwhile {}",
        r.jobs_lost, r.jobs_started_twice, r.spool_records_damaged, r.jobs_done
    );
    let _ = writeln!(
        s,
        "records {}: readable {}, cut off by a kill {}; killed before the record's first byte {}",
        r.records, r.records_readable, r.records_cut, r.records_never_written
    );
    let _ = writeln!(
        s,
        "frames served by the simulator {}, readable in the records {}; at most {} lost per kill",
        r.frames_served, r.frames_readable, r.max_frames_lost_per_kill
    );
    let _ = writeln!(
        s,
        "kills leaving the stage tilted {}, moved to its safe tilt at the next start {}; jobs \
         started before the stage check {}",
        r.kills_leaving_stage_tilted,
        r.stage_made_safe_at_next_start,
        r.jobs_started_before_stage_check
    );
    let _ = writeln!(s, "final SIGTERM: exit {:?}", r.final_stop_exit_code);
    write_problems(&mut s, &r.problems, r.work_dir.as_deref());
    s
}

/// True when the figures meet the issue's targets.
#[must_use]
pub fn soak_passed(r: &SoakReport) -> bool {
    let a = &r.attacks;
    r.problems.is_empty()
        && a.entries_set_aside == a.entries_placed
        && a.forged_rejected == a.forged_records
        && a.lock_tampering_reported == a.lock_file_moved
        && a.escaped_run_dirs == 0
        && r.stuck_jobs == 0
        && r.jobs_without_final_state == 0
        && r.failures_without_reason == 0
        && r.records_inconsistent == 0
}

/// True when the figures meet the issue's targets.
#[must_use]
pub fn kill_passed(r: &KillReport) -> bool {
    r.problems.is_empty()
        && r.jobs_lost == 0
        && r.jobs_started_twice == 0
        && r.spool_records_damaged == 0
        && r.records == r.records_readable
        && r.marked_interrupted_at_next_start == r.jobs_cut_by_a_kill
        && r.max_frames_lost_per_kill <= 1
        && r.stage_made_safe_at_next_start == r.kills_leaving_stage_tilted
        && r.jobs_started_before_stage_check == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checkpoints_are_first_middle_last() {
        assert_eq!(checkpoints(50), [1, 25, 50]);
        assert_eq!(checkpoints(1), [1]);
        assert_eq!(checkpoints(2), [1, 2]);
    }

    #[test]
    fn reasons_group_by_cause() {
        assert_eq!(
            shorten("tilt move to 4° failed: reply timeout after 0.3 s; the stage could not"),
            "tilt move to #° failed: reply timeout after #.# s"
        );
    }
}
