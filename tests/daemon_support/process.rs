//! A daemon under test as a child process: its stderr in a file, its
//! notifications read from a real `$NOTIFY_SOCKET`, signals sent for real.

use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use sdsem::daemon::{JobRecord, JobState, Spool};

/// Runs the `sdsem` binary to its end.
pub fn sdsem(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap()
}

pub fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// Writes a job file and returns its path as a string.
pub fn write_job(dir: &Path, file: &str, body: &str) -> String {
    let path = dir.join(file);
    std::fs::write(&path, body).unwrap();
    path.to_str().unwrap().to_owned()
}

/// `sdsem submit JOB --spool SPOOL`, which must succeed.
pub fn submit(job: &str, spool: &Path) {
    let out = sdsem(&["submit", job, "--spool", spool.to_str().unwrap()]);
    assert!(out.status.success(), "submit {job}: {}", text(&out.stderr));
}

/// The record of job `id`, as the spool has it now.
pub fn job(spool: &Path, id: u64) -> Option<JobRecord> {
    Spool::existing(spool)
        .ok()?
        .list()
        .ok()?
        .jobs
        .into_iter()
        .find(|j| j.id.0 == id)
}

pub fn state_of(spool: &Path, id: u64) -> Option<(JobState, Option<String>)> {
    job(spool, id).map(|j| (j.state, j.reason))
}

/// Waits until job `id` is in a final state; panics after `limit`.
pub fn wait_final(spool: &Path, id: u64, limit: Duration) -> JobRecord {
    let end = Instant::now() + limit;
    loop {
        if let Some(j) = job(spool, id)
            && !matches!(j.state, JobState::Queued | JobState::Running)
        {
            return j;
        }
        assert!(
            Instant::now() < end,
            "job {id} not finished within {limit:?}: {:?}",
            job(spool, id)
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

pub struct Daemon {
    pub child: Child,
    /// Notification lines, read off the socket as they come: a daemon whose
    /// datagrams nobody reads blocks in sd_notify once the queue is full.
    notify: mpsc::Receiver<String>,
    stderr: PathBuf,
    pub seen: Vec<String>,
}

impl Daemon {
    /// Starts `command` with a notify socket and a 1 s watchdog in `dir`;
    /// `tag` tells the files of several daemons apart.
    pub fn spawn(mut command: Command, dir: &Path, tag: &str) -> Self {
        let socket = dir.join(format!("notify-{tag}.sock"));
        let _ = std::fs::remove_file(&socket);
        let socket_reader = UnixDatagram::bind(&socket).unwrap();
        let (tx, notify) = mpsc::channel();
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n) = socket_reader.recv(&mut buf) {
                for line in text(&buf[..n]).lines() {
                    if tx.send(line.to_owned()).is_err() {
                        return;
                    }
                }
            }
        });
        let stderr = dir.join(format!("daemon-{tag}.log"));
        let log = std::fs::File::create(&stderr).unwrap();
        // As systemd does: $JOURNAL_STREAM names stderr, so the daemon writes `<N>` priorities.
        let meta = std::os::unix::fs::MetadataExt::dev(&log.metadata().unwrap());
        let ino = std::os::unix::fs::MetadataExt::ino(&log.metadata().unwrap());
        let child = command
            .env("JOURNAL_STREAM", format!("{meta}:{ino}"))
            .env("NOTIFY_SOCKET", &socket)
            .env("WATCHDOG_USEC", "1000000")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        Self {
            child,
            notify,
            stderr,
            seen: Vec::new(),
        }
    }

    /// `sdsem daemon --config CONFIG` (the real acquisition runner).
    pub fn sdsem(dir: &Path, config: &Path, tag: &str) -> Self {
        let mut command = Command::new(env!("CARGO_BIN_EXE_sdsem"));
        command
            .args(["--log-format", "text", "daemon", "--config"])
            .arg(config)
            .env("RUST_LOG", "info")
            // Fixed, so that a replay with another count proves independence of it.
            .env("RAYON_NUM_THREADS", "2");
        Self::spawn(command, dir, tag)
    }

    pub fn pid(&self) -> rustix::process::Pid {
        rustix::process::Pid::from_child(&self.child)
    }

    pub fn signal(&self, signal: rustix::process::Signal) {
        rustix::process::kill_process(self.pid(), signal).unwrap();
    }

    /// Reads notifications until one line satisfies `want`, at most `limit`.
    pub fn expect(&mut self, limit: Duration, want: impl Fn(&str) -> bool) -> String {
        self.expect_after(0, limit, want)
    }

    /// As [`Self::expect`], among the notifications after the first `from`.
    pub fn expect_after(
        &mut self,
        from: usize,
        limit: Duration,
        want: impl Fn(&str) -> bool,
    ) -> String {
        let end = Instant::now() + limit;
        if let Some(line) = self.seen.iter().skip(from).find(|l| want(l)) {
            return line.clone();
        }
        while let Some(left) = end.checked_duration_since(Instant::now()) {
            if let Ok(line) = self.notify.recv_timeout(left) {
                self.seen.push(line.clone());
                if want(&line) {
                    return line;
                }
            }
        }
        panic!(
            "no such notification within {limit:?}; seen {:#?}\nlog:\n{}",
            self.seen,
            self.log()
        );
    }

    pub fn wait_exit(&mut self, limit: Duration) -> (std::process::ExitStatus, Duration) {
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return (status, start.elapsed());
            }
            assert!(
                start.elapsed() < limit,
                "daemon still running after {limit:?}\nlog:\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.stderr).unwrap_or_default()
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
