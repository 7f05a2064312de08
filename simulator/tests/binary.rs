//! The `sdsem-sim` binary as a user starts it: a process, its printed
//! endpoints, GCS and the SEM imaging link over TCP.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use sdsem_protocol::sem::{Bits, FrameReply, GrabRequest, Reply, ReplyDecoder, Request, Role};

/// A small specimen and frame: quick to build and to render.
const SMALL: &[&str] = &[
    "--scene",
    "grid",
    "--scene-field",
    "60",
    "--frame",
    "320x240",
    "--pixel-size",
    "0.2",
];

struct Sim {
    child: Child,
    stdout: BufReader<ChildStdout>,
}

impl Sim {
    fn start(args: &[&str]) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_sdsem-sim"))
            .args(SMALL)
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

    /// Both endpoint lines, checked: the stage's then the SEM's `host:port`.
    fn endpoints(&mut self) -> (String, String) {
        let stage = self.endpoint_line();
        let sem = self.endpoint_line();
        assert!(stage.starts_with("stage tcp://127.0.0.1:"), "{stage:?}");
        let sem = sem
            .strip_prefix("sem tcp://")
            .unwrap_or_else(|| panic!("unexpected SEM endpoint line {sem:?}"))
            .to_owned();
        (stage, sem)
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
    let (line, _) = sim.endpoints();
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
    let (line, _) = sim.endpoints();
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
    assert!(sim.endpoint_line().starts_with("sem tcp://127.0.0.1:"));
    assert!(sim.close_stdin_and_wait().success());
}

#[test]
fn bad_flags_fail_with_a_message() {
    for (args, expect) in [
        (&["--tilt-min", "80"][..], "tilt"),
        (&["--scene", "mesh"][..], "particles, grid, rough, dome"),
        (&["--sem-tcp", "localhost"][..], "--sem-tcp"),
        (&["--pixel-size", "0"][..], "sem.optics.pixel_size_um"),
        (&["--frame", "640"][..], "WxH"),
        (&["--shark-lose-chunk-at", "1"][..], "--sharksem ADDR"),
        (
            &["--sharksem", "127.0.0.1:0", "--sharksem-version", "two"][..],
            "sharksem.version",
        ),
        (
            &["--config", "/nonexistent/sim.toml"][..],
            "/nonexistent/sim.toml",
        ),
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_sdsem-sim"))
            .args(args)
            .stdin(Stdio::null())
            .output()
            .expect("run sdsem-sim");
        assert!(!out.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(expect), "{args:?}: {err}");
    }
}

/// A client of the SEM imaging link.
struct SemLink {
    stream: TcpStream,
    decoder: ReplyDecoder,
}

impl SemLink {
    fn connect(addr: &str) -> Self {
        let stream = TcpStream::connect(addr).expect("connect to the SEM link");
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .expect("set a read timeout");
        Self {
            stream,
            decoder: ReplyDecoder::new(),
        }
    }

    fn ask(&mut self, request: &Request) -> Reply {
        self.stream.write_all(&request.encode()).expect("send");
        let mut buf = vec![0u8; 65536];
        loop {
            if let Some(r) = self.decoder.next_reply().expect("a valid reply") {
                return r;
            }
            let n = self.stream.read(&mut buf).expect("reply");
            assert!(n > 0, "the SEM server closed the link");
            self.decoder.push(&buf[..n]);
        }
    }

    fn grab(&mut self, width: u32, height: u32, dwell_us: f64) -> FrameReply {
        match self.ask(&Request::Grab(GrabRequest {
            width,
            height,
            dwell_us,
            role: Role::Tracking,
            bits: Bits::Sixteen,
        })) {
            Reply::Frame(f) => f,
            other => panic!("expected a frame, got {other:?}"),
        }
    }
}

fn position(s: &mut TcpStream, r: &mut BufReader<TcpStream>, axis: &str) -> f64 {
    let reply = ask(s, r, &format!("POS? {axis}\n"));
    reply
        .trim_end()
        .strip_prefix(&format!("{axis}="))
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("POS? {axis}: {reply:?}"))
}

fn wait_on_target(s: &mut TcpStream, r: &mut BufReader<TcpStream>) {
    let deadline = Instant::now() + Duration::from_secs(10);
    while ask(s, r, "ONT? T\n") != "T=1\n" {
        assert!(Instant::now() < deadline, "never on target");
        std::thread::sleep(Duration::from_millis(2));
    }
}

#[test]
fn a_frame_grabbed_after_a_stage_move_shows_the_new_pose() {
    let mut sim = Sim::start(&["--time-scale", "0.001", "--seed", "5"]);
    let (stage, sem_addr) = sim.endpoints();
    let (mut s, mut r) = connect(&stage);
    let mut sem = SemLink::connect(&sem_addr);
    assert!(
        matches!(sem.ask(&Request::Identify), Reply::Identity(id) if id.contains("virtual-sem"))
    );
    let before = sem.grab(80, 60, 1.0);
    assert_eq!((before.meta.tilt_deg, before.meta.stage_x_um), (0.0, 0.0));
    s.write_all(b"MOV T 6 X 4\n").unwrap();
    assert_eq!(ask(&mut s, &mut r, "ERR?\n"), "0\n");
    wait_on_target(&mut s, &mut r);
    let (x, tilt) = (position(&mut s, &mut r, "X"), position(&mut s, &mut r, "T"));
    assert_eq!((x, tilt), (4.0, 6.0));
    let after = sem.grab(80, 60, 1.0);
    assert_eq!(after.meta.frame, before.meta.frame + 1);
    assert_eq!(
        (
            after.meta.stage_x_um,
            after.meta.stage_y_um,
            after.meta.tilt_deg
        ),
        (x, 0.0, tilt),
        "the FRAME metadata carries the stage's pose"
    );
    // 80 px of a 320 px, 0.2 µm frame: 0.8 µm pixels.
    assert!((after.meta.pixel_size_um - 0.8).abs() < 1e-12);
    let (a, b) = (before.samples_u16(), after.samples_u16());
    let changed = a
        .iter()
        .zip(&b)
        .filter(|(p, q)| p.abs_diff(**q) > 2000)
        .count();
    assert!(
        changed > a.len() / 20,
        "tilting 6° and panning 4 µm must change the image: {changed} of {} pixels",
        a.len()
    );
    // The ground truth of that frame is served too, with the same metadata.
    let Reply::HeightMap(truth) = sem.ask(&Request::GroundTruth {
        frame: after.meta.frame,
        path: None,
    }) else {
        panic!("no ground truth")
    };
    assert_eq!(truth.meta, after.meta);
    assert!(truth.heights().iter().any(|h| h.is_finite()));
    drop((s, r, sem));
    assert!(sim.close_stdin_and_wait().success());
}

#[test]
fn the_same_seed_gives_the_same_frames_in_two_processes() {
    let grab = |seed: &str| {
        let mut sim = Sim::start(&["--time-scale", "0.001", "--seed", seed]);
        let (stage, sem_addr) = sim.endpoints();
        let (mut s, mut r) = connect(&stage);
        let mut sem = SemLink::connect(&sem_addr);
        let mut frames = Vec::new();
        for tilt in [0, 3] {
            s.write_all(format!("MOV T {tilt}\n").as_bytes()).unwrap();
            wait_on_target(&mut s, &mut r);
            frames.push(sem.grab(64, 48, 2.0).data);
        }
        drop((s, r, sem));
        assert!(sim.close_stdin_and_wait().success());
        frames
    };
    let a = grab("9");
    assert_eq!(a, grab("9"), "same seed, same specimen, walk and noise");
    assert_ne!(a, grab("10"), "another seed, another specimen");
}

#[test]
fn the_time_scale_shortens_the_scan() {
    // 100 × 100 × 100 µs = 1 simulated second of scan.
    let scan_ns = |time_scale: &str| {
        let mut sim = Sim::start(&["--time-scale", time_scale]);
        let (_, sem_addr) = sim.endpoints();
        let mut sem = SemLink::connect(&sem_addr);
        let t = Instant::now();
        let f = sem.grab(100, 100, 100.0);
        let real = t.elapsed();
        drop(sem);
        assert!(sim.close_stdin_and_wait().success());
        let stamped = f.meta.scan_end_unix_ns - f.meta.scan_start_unix_ns;
        assert!(
            real.as_nanos() >= u128::from(stamped),
            "{real:?} < {stamped} ns"
        );
        stamped
    };
    let slow = scan_ns("0.2");
    let fast = scan_ns("0.02");
    // Lower bounds are exact (a wait never ends early); upper bounds generous.
    assert!(slow >= 200_000_000, "{slow} ns at time_scale 0.2");
    assert!(fast >= 20_000_000, "{fast} ns at time_scale 0.02");
    assert!(fast < slow, "{fast} ns at 0.02 vs {slow} ns at 0.2");
    assert!(slow < 1_000_000_000, "{slow} ns: slower than real time");
}

#[test]
fn a_config_file_is_read_and_flags_override_it() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("sdsem.toml");
    // sdsem's configuration file: the simulator reads its [simulator] table only.
    std::fs::write(
        &path,
        r#"
[run]
name = "not the simulator's"

[simulator]
seed = 4
time_scale = 0.001

[simulator.stage]
tilt_max_deg = 60.0

[simulator.sem.optics]
tilt_axis_deg = 30.0
scan_rotation_deg = 10.0

[simulator.sem.walk]
px_per_deg = 2.0
"#,
    )
    .unwrap();
    let path = path.to_str().unwrap();
    let mut sim = Sim::start(&["--config", path, "--scan-rotation", "-5"]);
    let (stage, sem_addr) = sim.endpoints();
    let (mut s, mut r) = connect(&stage);
    assert_eq!(ask(&mut s, &mut r, "TMX? T\n"), "T=60.000000\n");
    let f = SemLink::connect(&sem_addr).grab(32, 24, 1.0);
    assert_eq!(
        (f.meta.tilt_axis_deg, f.meta.scan_rotation_deg),
        (30.0, -5.0)
    );
    drop((s, r));
    assert!(sim.close_stdin_and_wait().success());

    std::fs::write(
        dir.path().join("bad.toml"),
        "[sem.walk]\nlinear_um_per_deg = 1\n",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_sdsem-sim"))
        .args(["--config", dir.path().join("bad.toml").to_str().unwrap()])
        .stdin(Stdio::null())
        .output()
        .expect("run sdsem-sim");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("linear_um_per_deg"), "{err}");
}

#[test]
fn sharksem_flag_serves_the_dialect_with_its_faults() {
    use sdsem_protocol::sharksem::{Flags, MessageFramer, Request, Response};
    let mut sim = Sim::start(&[
        "--sharksem",
        "127.0.0.1:0",
        "--sharksem-version",
        "3.2.20",
        "--shark-silent-after",
        "3",
    ]);
    let _ = sim.endpoints();
    let control = sim.endpoint_line();
    let data = sim.endpoint_line();
    let control = control
        .strip_prefix("sharksem tcp://")
        .unwrap_or_else(|| panic!("{control:?}"))
        .to_owned();
    let data_port: u16 = data
        .strip_prefix("sharksem-data tcp://127.0.0.1:")
        .unwrap_or_else(|| panic!("{data:?}"))
        .parse()
        .expect("a port");
    let control_port: u16 = control
        .rsplit(':')
        .next()
        .and_then(|p| p.parse().ok())
        .expect("a port");
    assert_eq!(data_port, control_port + 1);
    let mut stream = TcpStream::connect(&control).expect("connect");
    stream
        .set_read_timeout(Some(Duration::from_millis(500)))
        .expect("timeout");
    let mut framer = MessageFramer::new();
    let mut ask = |request: &Request| -> Option<Response> {
        stream
            .write_all(&request.encode(1, Flags::NONE))
            .expect("send");
        let mut buf = [0u8; 1024];
        loop {
            if let Some(m) = framer.next_message() {
                return Some(
                    request
                        .decode_response(&m.expect("framed").body)
                        .expect("decoded"),
                );
            }
            match stream.read(&mut buf) {
                Ok(n) if n > 0 => framer.push(&buf[..n]),
                _ => return None,
            }
        }
    };
    assert_eq!(
        ask(&Request::TcpGetVersion),
        Some(Response::Text("3.2.20".into()))
    );
    assert!(matches!(
        ask(&Request::TcpGetModel),
        Some(Response::Text(_))
    ));
    assert_eq!(
        ask(&Request::TcpGetVersion),
        None,
        "silent from the third request on"
    );
    assert!(sim.close_stdin_and_wait().success());
}

#[test]
fn stage_protocol_remcon32_serves_the_zeiss_dialect() {
    let mut sim = Sim::start(&[
        "--stage-protocol",
        "remcon32",
        "--time-scale",
        "0.001",
        "--ignore-move-at",
        "1",
    ]);
    let (line, _) = sim.endpoints();
    let (mut s, mut r) = connect(&line);
    // Two lines per reply, each ending in CR LF.
    let two = |s: &mut TcpStream, r: &mut BufReader<TcpStream>, request: &str| {
        let first = ask(s, r, request);
        let mut second = String::new();
        r.read_line(&mut second).unwrap();
        first + &second
    };
    assert!(two(&mut s, &mut r, "VER?\r").starts_with("@\r\n>SmartSEM"));
    assert_eq!(two(&mut s, &mut r, "HELLO\r\n"), "@\r\n*600\r\n");
    // The first move is silently ignored, the second happens.
    assert_eq!(two(&mut s, &mut r, "C95 0 0 10 3 0 0\r"), "@\r\n>\r\n");
    std::thread::sleep(Duration::from_millis(20));
    assert_eq!(
        two(&mut s, &mut r, "C95?\n"),
        "@\r\n>0.000000 0.000000 10.000000 0.000000 0.000000 0.000000 0.0\r\n"
    );
    assert_eq!(two(&mut s, &mut r, "C95 0 0 10 3 0 0\r"), "@\r\n>\r\n");
    std::thread::sleep(Duration::from_millis(20));
    assert!(two(&mut s, &mut r, "C95?\r").ends_with(" 3.000000 0.000000 0.000000 0.0\r\n"));
    // The wrong number of values: `#` alone, and the link stays in step.
    assert_eq!(ask(&mut s, &mut r, "C95 1 2\r"), "#\r\n");
    assert!(two(&mut s, &mut r, "PHN?\r").starts_with("@\r\n>0"));
    drop((s, r));
    assert!(sim.close_stdin_and_wait().success());
}
