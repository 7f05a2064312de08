//! The `sdsem-sim` binary as a user starts it: a process, its printed endpoint, GCS over TCP.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

struct Sim {
    child: Child,
    stdout: BufReader<ChildStdout>,
}

impl Sim {
    fn start(args: &[&str]) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_sdsem-sim"))
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("start sdsem-sim");
        let stdout = BufReader::new(child.stdout.take().expect("piped stdout"));
        Self { child, stdout }
    }

    fn endpoint_line(&mut self) -> String {
        let mut line = String::new();
        self.stdout
            .read_line(&mut line)
            .expect("read endpoint line");
        line.trim_end().to_owned()
    }

    /// Closes stdin and waits (bounded) for a clean exit.
    fn close_stdin_and_wait(mut self) -> std::process::ExitStatus {
        drop(self.child.stdin.take());
        let deadline = Instant::now() + Duration::from_secs(10);
        loop {
            if let Some(status) = self.child.try_wait().expect("wait") {
                return status;
            }
            assert!(
                Instant::now() < deadline,
                "sdsem-sim did not exit after stdin closed"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Sim {
    fn drop(&mut self) {
        // Only if a test failed before the clean exit: never leave the process behind.
        if matches!(self.child.try_wait(), Ok(None)) {
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

fn connect(line: &str) -> (TcpStream, BufReader<TcpStream>) {
    let addr = line
        .strip_prefix("stage tcp://")
        .unwrap_or_else(|| panic!("unexpected endpoint line {line:?}"));
    let stream = TcpStream::connect(addr).expect("connect to the simulator");
    stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .expect("set a read timeout");
    let reader = BufReader::new(stream.try_clone().expect("clone the stream"));
    (stream, reader)
}

fn ask(stream: &mut TcpStream, reader: &mut BufReader<TcpStream>, line: &str) -> String {
    stream.write_all(line.as_bytes()).expect("send");
    let mut out = String::new();
    reader.read_line(&mut out).expect("reply");
    out
}

#[test]
fn prints_its_endpoint_serves_gcs_and_exits_when_stdin_closes() {
    let mut sim = Sim::start(&[
        "--stage-tcp",
        "127.0.0.1:0",
        "--time-scale",
        "0.001",
        "--seed",
        "3",
    ]);
    let line = sim.endpoint_line();
    let (mut s, mut r) = connect(&line);
    assert!(ask(&mut s, &mut r, "*IDN?\n").contains("sdsem-sim"));
    assert_eq!(ask(&mut s, &mut r, "FRF? X Y T\n"), "X=1 \n");
    let mut rest = String::new();
    r.read_line(&mut rest).unwrap();
    r.read_line(&mut rest).unwrap();
    assert_eq!(rest, "Y=1 \nT=1\n");
    s.write_all(b"MOV T 7.5\n").unwrap();
    assert_eq!(ask(&mut s, &mut r, "ERR?\n"), "0\n");
    // 7.5° at 1°/s + 0.2 s settling is 7.7 ms of real time at this scale.
    let deadline = Instant::now() + Duration::from_secs(5);
    while ask(&mut s, &mut r, "ONT? T\n") != "T=1\n" {
        assert!(Instant::now() < deadline, "never on target");
        std::thread::sleep(Duration::from_millis(2));
    }
    assert_eq!(ask(&mut s, &mut r, "POS? T\n"), "T=7.500000\n");
    s.write_all(b"MOV T 71\n").unwrap();
    assert_eq!(
        ask(&mut s, &mut r, "ERR?\n"),
        "7\n",
        "beyond the 70° soft limit"
    );
    drop((s, r));
    assert!(sim.close_stdin_and_wait().success());
}

#[test]
fn fault_flags_reach_the_model() {
    let mut sim = Sim::start(&[
        "--time-scale",
        "0.001",
        "--drop-reply-at",
        "1",
        "--unreferenced",
        "--tilt-max",
        "60",
    ]);
    let line = sim.endpoint_line();
    let (mut s, mut r) = connect(&line);
    s.set_read_timeout(Some(Duration::from_millis(300)))
        .unwrap();
    s.write_all(b"POS? T\n").unwrap();
    let mut buf = [0u8; 16];
    let dropped = s.read(&mut buf);
    assert!(
        dropped.is_err(),
        "the first reply must be dropped, got {dropped:?}"
    );
    assert_eq!(ask(&mut s, &mut r, "FRF? T\n"), "T=0\n");
    assert_eq!(ask(&mut s, &mut r, "TMX? T\n"), "T=60.000000\n");
    s.write_all(b"MOV T 1\n").unwrap();
    assert_eq!(ask(&mut s, &mut r, "ERR?\n"), "5\n", "unreferenced axis");
    drop((s, r));
    assert!(sim.close_stdin_and_wait().success());
}

#[test]
fn pty_endpoint_prints_the_slave_path() {
    let mut sim = Sim::start(&["--stage-pty"]);
    let line = sim.endpoint_line();
    let path = line.strip_prefix("stage ").expect("stage line");
    assert!(path.starts_with("/dev/"), "{line}");
    assert!(std::path::Path::new(path).exists());
    assert!(sim.close_stdin_and_wait().success());
}

#[test]
fn bad_flags_fail_with_a_message() {
    let out = Command::new(env!("CARGO_BIN_EXE_sdsem-sim"))
        .args(["--tilt-min", "80"])
        .stdin(Stdio::null())
        .output()
        .expect("run sdsem-sim");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("tilt"), "{err}");
}
