//! The SharkSEM dialect over real sockets, on a manual clock. (The data port
//! registration from a bound local port is exercised by sdsem's client tests:
//! std sockets cannot bind before connecting.)

use std::io::{Read, Write};
use std::net::{Shutdown, TcpStream};
use std::sync::Arc;
use std::time::{Duration, Instant};

use sdsem_protocol::sharksem::{
    AssembleError, Flags, FrameAssembler, Message, MessageFramer, Progress, Request, Response,
    ScanXY, StageLimits,
};

use super::SharkSemSimConfig;
use crate::clock::{Clock, ManualClock};
use crate::config::{FaultTrigger, SimConfig};
use crate::scene::SceneKind;
use crate::simulator::{SimHandle, Simulator};

fn sim(
    shark: SharkSemSimConfig,
    tweak: impl FnOnce(&mut SimConfig),
) -> (SimHandle, Arc<ManualClock>) {
    let mut c = SimConfig {
        seed: 5,
        time_scale: 0.01,
        sharksem: Some(shark),
        ..SimConfig::default()
    };
    c.sem.scene.kind = SceneKind::Grid;
    c.sem.scene.field_um = 60.0;
    c.sem.optics.width = 64;
    c.sem.optics.height = 48;
    c.sem.optics.pixel_size_um = 0.5;
    tweak(&mut c);
    let clock = Arc::new(ManualClock::with_time_scale(0.01));
    let handle = Simulator::spawn_with_clock(c, clock.clone()).unwrap();
    (handle, clock)
}

fn addr(endpoint: &str) -> &str {
    endpoint.strip_prefix("tcp://").unwrap()
}

struct Client {
    stream: TcpStream,
    framer: MessageFramer,
    id: u32,
}

impl Client {
    fn connect(endpoint: &str) -> Self {
        let stream = TcpStream::connect(addr(endpoint)).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_millis(20)))
            .unwrap();
        Self {
            stream,
            framer: MessageFramer::new(),
            id: 0,
        }
    }

    fn send(&mut self, request: &Request, flags: Flags) -> u32 {
        self.id += 1;
        self.stream
            .write_all(&request.encode(self.id, flags))
            .unwrap();
        self.id
    }

    /// The next message within `wait`, if any.
    fn next(&mut self, wait: Duration) -> Option<Message> {
        let end = Instant::now() + wait;
        let mut buf = [0u8; 4096];
        loop {
            if let Some(m) = self.framer.next_message() {
                return Some(m.unwrap());
            }
            if Instant::now() > end {
                return None;
            }
            match self.stream.read(&mut buf) {
                Ok(0) => return None,
                Ok(n) => self.framer.push(&buf[..n]),
                Err(_) => {}
            }
        }
    }

    fn call_with(&mut self, request: &Request, flags: Flags) -> Option<Response> {
        let id = self.send(request, flags);
        let m = self.next(Duration::from_secs(5))?;
        assert_eq!((m.header.name.as_str(), m.header.id), (request.name(), id));
        Some(request.decode_response(&m.body).unwrap())
    }

    fn call(&mut self, request: &Request) -> Response {
        self.call_with(request, Flags::NONE)
            .unwrap_or_else(|| panic!("no answer to {request}"))
    }

    /// Asserts that nothing comes back for a while.
    fn silent(&mut self) {
        assert!(self.next(Duration::from_millis(150)).is_none());
    }
}

fn position(c: &mut Client) -> Vec<f64> {
    match c.call(&Request::StgGetPosition) {
        Response::Position(p) => p.values(),
        other => panic!("{other:?}"),
    }
}

#[test]
fn identifies_answers_queries_and_ignores_what_it_does_not_know() {
    let (sim, _) = sim(SharkSemSimConfig::default(), |_| {});
    let lines = sim.endpoint_lines();
    let control: u16 = sim
        .sharksem_endpoint()
        .rsplit(':')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let data: u16 = sim
        .sharksem_data_endpoint()
        .rsplit(':')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(data, control + 1, "data port = control + 1: {lines:?}");
    let mut c = Client::connect(sim.sharksem_endpoint());
    assert_eq!(
        c.call(&Request::TcpGetVersion),
        Response::Text("2.0.25".into())
    );
    assert!(matches!(c.call(&Request::TcpGetDevice), Response::Text(s) if s == "SDSEMSIM0001"));
    // 3.2.20 functions do not exist on a 2.0.25 server: silence, like every bad request.
    c.send(&Request::TcpGetModel, Flags::NONE);
    c.silent();
    let mut unknown = Request::TcpGetVersion.encode(99, Flags::NONE);
    unknown[..16].copy_from_slice(b"StgGoHome\0\0\0\0\0\0\0");
    c.stream.write_all(&unknown).unwrap();
    c.silent();
    let mut bad = Request::DtSelect {
        channel: 0,
        detector: 10,
    }
    .encode(98, Flags::NONE);
    bad[16..20].copy_from_slice(&4u32.to_le_bytes());
    bad.truncate(36);
    c.stream.write_all(&bad).unwrap();
    c.silent();
    // A void function answers only when asked to.
    assert_eq!(
        c.call_with(&Request::ScStopScan, Flags::SEND_RESPONSE),
        Some(Response::Void)
    );
    let Response::Detectors(d) = c.call(&Request::DtEnumDetectors) else {
        panic!()
    };
    assert_eq!((d[1].name.as_str(), d[1].id), ("BSE", 11));
    assert_eq!(
        c.call(&Request::GetViewField),
        Response::ViewField(0.032),
        "0.5 µm × 64 px"
    );
    assert!(sim.sharksem().unwrap().counts().ignored >= 3);
}

#[test]
fn stage_moves_rotation_before_tilt_limits_silently_and_ignores_moves_while_busy() {
    let (sim, clock) = sim(SharkSemSimConfig::default(), |_| {});
    let mut c = Client::connect(sim.sharksem_endpoint());
    assert_eq!(c.call(&Request::StgIsCalibrated), Response::Int(1));
    let Response::Limits(l) = c.call(&Request::StgGetLimits { kind: 1 }) else {
        panic!()
    };
    assert_eq!(l.tilt_deg, (-5.0, 70.0));
    assert_eq!(l.x_mm, (-5.0, 5.0));
    c.send(
        &Request::StgMoveTo(vec![0.01, 0.0, 10.0, 30.0, 4.0]),
        Flags::NONE,
    );
    assert_eq!(c.call(&Request::StgIsBusy), Response::Int(1));
    // A second move while the first runs is ignored silently.
    c.send(
        &Request::StgMoveTo(vec![0.0, 0.0, 10.0, 30.0, 1.0]),
        Flags::NONE,
    );
    // Wait B holds the query until the stage is idle: 4° at 1°/s and 0.2 s of settling.
    let t0 = clock.now_s();
    let p = match c.call_with(&Request::StgGetPosition, Flags::WAIT_B) {
        Some(Response::Position(p)) => p,
        other => panic!("{other:?}"),
    };
    assert!(clock.now_s() - t0 >= 4.2 - 1e-9, "{}", clock.now_s() - t0);
    assert_eq!((p.x_mm, p.rotation_deg, p.tilt_deg), (0.01, 30.0, 4.0));
    assert_eq!(
        sim.stage().snapshot().pose.x_um,
        10.0,
        "mm on the wire, µm in the model"
    );
    assert_eq!(sim.sharksem().unwrap().counts().ignored_moves, 1);
    // Out of range: limited silently. Missing trailing axes stay where they are.
    c.send(
        &Request::StgMoveTo(vec![0.01, 0.0, 10.0, 30.0, 95.0]),
        Flags::NONE,
    );
    c.call_with(&Request::StgIsBusy, Flags::WAIT_B);
    assert_eq!(position(&mut c)[4], 70.0);
    c.send(&Request::StgMoveTo(vec![-0.02]), Flags::NONE);
    c.call_with(&Request::StgIsBusy, Flags::WAIT_B);
    assert_eq!(position(&mut c), [-0.02, 0.0, 10.0, 30.0, 70.0]);
    // StgStop halts mid-move.
    c.send(
        &Request::StgMoveTo(vec![-0.02, 0.0, 10.0, 30.0, 60.0]),
        Flags::NONE,
    );
    // The answer proves the move was handled before the clock moves on.
    assert_eq!(c.call(&Request::StgIsBusy), Response::Int(1));
    clock.advance(2.0);
    c.send(&Request::StgStop, Flags::NONE);
    assert!((position(&mut c)[4] - 68.0).abs() < 1e-9);
}

#[test]
fn an_uncalibrated_stage_ignores_moves_and_a_3x_server_reports_tilt_y() {
    let shark = SharkSemSimConfig {
        version: "3.2.20".into(),
        tilt_y: true,
        ..SharkSemSimConfig::default()
    };
    let (sim, _) = sim(shark, |c| c.stage.referenced = false);
    let mut c = Client::connect(sim.sharksem_endpoint());
    assert_eq!(c.call(&Request::StgIsCalibrated), Response::Int(0));
    assert!(matches!(c.call(&Request::TcpGetModel), Response::Text(_)));
    c.send(
        &Request::StgMoveTo(vec![0.0, 0.0, 10.0, 0.0, 3.0]),
        Flags::NONE,
    );
    assert_eq!(
        position(&mut c),
        [0.0, 0.0, 10.0, 0.0, 0.0, 0.0],
        "six values, nothing moved"
    );
    assert_eq!(sim.sharksem().unwrap().counts().ignored_moves, 1);
}

/// Scans one frame in firewall-friendly mode (the data socket may come from
/// any port) and reassembles it.
fn scan(
    c: &mut Client,
    data: &mut Client,
    frame_id: u32,
    w: u32,
    h: u32,
) -> Result<(FrameAssembler, Vec<Progress>), AssembleError> {
    let scan = ScanXY::full_frame(frame_id, w, h, 1000);
    assert_eq!(c.call(&Request::ScScanXY(scan)), Response::Int(0));
    let mut asm = FrameAssembler::new(frame_id, 0, 16, u64::from(w * h));
    let mut progress = Vec::new();
    while !asm.is_complete() {
        let m = data.next(Duration::from_secs(10)).expect("data");
        progress.push(asm.push(&m)?);
    }
    Ok((asm, progress))
}

fn firewall_pair(sim: &SimHandle) -> (Client, Client) {
    let mut c = Client::connect(sim.sharksem_endpoint());
    // The answer proves the session exists before its data connection arrives.
    c.call(&Request::TcpGetVersion);
    let d = Client::connect(sim.sharksem_data_endpoint());
    (c, d)
}

#[test]
fn a_scan_streams_chunks_at_the_view_field_and_must_be_stopped() {
    let shark = SharkSemSimConfig {
        firewall_friendly: true,
        ..SharkSemSimConfig::default()
    };
    let (sim, clock) = sim(shark, |_| {});
    let (mut c, mut d) = firewall_pair(&sim);
    // Registration is ignored but answered in firewall-friendly mode.
    assert_eq!(
        c.call(&Request::TcpRegDataPort { port: 1234 }),
        Response::Int(0)
    );
    c.send(&Request::SetViewField { mm: 0.064 }, Flags::NONE);
    c.send(
        &Request::DtSelect {
            channel: 0,
            detector: 10,
        },
        Flags::NONE,
    );
    c.send(
        &Request::DtEnable {
            channel: 0,
            enable: 1,
            bpp: Some(16),
        },
        Flags::NONE,
    );
    assert_eq!(
        c.call(&Request::DtGetEnabled { channel: 0 }),
        Response::Enabled { enable: 1, bpp: 16 }
    );
    assert_eq!(
        c.call(&Request::DtGetSelected { channel: 0 }),
        Response::Int(10)
    );
    let t0 = clock.now_s();
    let (asm, progress) = scan(&mut c, &mut d, 7, 32, 24).unwrap();
    // 768 px × 1 µs = 0.768 ms: one chunk at the first 50 ms tick.
    assert_eq!(progress, [Progress::Complete]);
    assert!((clock.now_s() - t0 - 0.05).abs() < 1e-9);
    let pixels = asm.into_u16();
    assert!(
        pixels.iter().any(|&p| p != pixels[0]),
        "an image, not a constant"
    );
    let frame = sim.sem().last_frame().unwrap();
    let view = sim.frame(frame).unwrap().view;
    assert!((view.pixel_size_um - 2.0).abs() < 1e-12, "64 µm over 32 px");
    // ScStopScan is required: a second scan before it is ignored.
    c.send(
        &Request::ScScanXY(ScanXY::full_frame(8, 4, 4, 1000)),
        Flags::NONE,
    );
    c.silent();
    c.send(&Request::ScStopScan, Flags::NONE);
    // A slow scan arrives chunk by chunk: 32 × 24 × 100 µs = 76.8 ms.
    let scan = ScanXY::full_frame(9, 32, 24, 100_000);
    assert_eq!(c.call(&Request::ScScanXY(scan)), Response::Int(0));
    let mut asm = FrameAssembler::new(9, 0, 16, 768);
    let mut chunks = 0;
    while !asm.is_complete() {
        asm.push(&d.next(Duration::from_secs(10)).unwrap()).unwrap();
        chunks += 1;
    }
    assert_eq!(chunks, 2, "0.05 s then 0.0768 s");
    // Wait A: the query waits for the end of the scan (already over here).
    assert_eq!(
        c.call_with(&Request::IsBusy { mask: 1 << 8 }, Flags::WAIT_A),
        Some(Response::Int(0))
    );
    c.send(&Request::ScStopScan, Flags::NONE);
    // A bad region is refused with a negative value.
    let bad = ScanXY {
        right: 40,
        ..ScanXY::full_frame(10, 32, 24, 100)
    };
    assert_eq!(c.call(&Request::ScScanXY(bad)), Response::Int(-1));
}

#[test]
fn lost_and_resent_chunks_and_an_ignored_view_field_are_seeded_faults() {
    let mut shark = SharkSemSimConfig {
        firewall_friendly: true,
        chunk_interval_s: 0.001,
        ..SharkSemSimConfig::default()
    };
    shark.faults.lose_chunk = FaultTrigger::at([3]);
    shark.faults.resend_chunk = FaultTrigger::at([6]);
    shark.faults.ignore_view_field = FaultTrigger::at([1]);
    let (sim, _) = sim(shark, |_| {});
    let (mut c, mut d) = firewall_pair(&sim);
    c.send(&Request::SetViewField { mm: 0.1 }, Flags::NONE);
    assert_eq!(
        c.call(&Request::GetViewField),
        Response::ViewField(0.032),
        "ignored"
    );
    c.send(&Request::SetViewField { mm: 0.1 }, Flags::NONE);
    assert_eq!(c.call(&Request::GetViewField), Response::ViewField(0.1));
    c.send(
        &Request::DtEnable {
            channel: 0,
            enable: 1,
            bpp: Some(16),
        },
        Flags::NONE,
    );
    // 1 µs dwell, 1 ms chunks: 1000 pixels a chunk.
    let err = scan(&mut c, &mut d, 1, 64, 48).unwrap_err();
    assert_eq!(
        err,
        AssembleError::LostChunk {
            received: 2000,
            index: 3000
        }
    );
    c.send(&Request::ScStopScan, Flags::NONE);
    // The next frame sees the re-send.
    let (asm, progress) = scan(&mut c, &mut d, 2, 64, 48).unwrap();
    assert!(
        progress.contains(&Progress::Resent { from: 1000 }),
        "{progress:?}"
    );
    assert!(asm.is_complete());
    let n = sim.sharksem().unwrap().counts();
    assert_eq!(
        (n.lost_chunks, n.resent_chunks, n.ignored_view_fields),
        (1, 1, 1)
    );
}

#[test]
fn data_from_an_unregistered_port_is_refused() {
    let (sim, _) = sim(SharkSemSimConfig::default(), |_| {});
    let mut c = Client::connect(sim.sharksem_endpoint());
    assert_eq!(
        c.call(&Request::TcpRegDataPort { port: 1 }),
        Response::Int(0)
    );
    let mut d = Client::connect(sim.sharksem_data_endpoint());
    // The server closes it: a read gives end of stream.
    let mut buf = [0u8; 1];
    d.stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    assert_eq!(d.stream.read(&mut buf).unwrap(), 0);
}

#[test]
fn a_dropped_connection_and_a_silent_server() {
    let mut shark = SharkSemSimConfig::default();
    shark.faults.disconnect_after_requests = Some(2);
    shark.faults.silent_after_requests = Some(4);
    let (sim, _) = sim(shark, |_| {});
    let mut c = Client::connect(sim.sharksem_endpoint());
    c.call(&Request::TcpGetVersion);
    // The second request is answered, then both connections close.
    c.call(&Request::StgIsBusy);
    let mut buf = [0u8; 1];
    c.stream
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    assert_eq!(c.stream.read(&mut buf).unwrap(), 0);
    let mut c = Client::connect(sim.sharksem_endpoint());
    c.call(&Request::TcpGetVersion);
    // From the fourth request on, nothing answers, for any client.
    c.send(&Request::TcpGetVersion, Flags::NONE);
    c.silent();
    let _ = c.stream.shutdown(Shutdown::Both);
    let mut c = Client::connect(sim.sharksem_endpoint());
    c.send(&Request::GetViewField, Flags::NONE);
    c.silent();
    assert!(sim.sharksem().unwrap().is_hung());
}

#[test]
fn limits_report_the_stage_model() {
    let (sim, _) = sim(SharkSemSimConfig::default(), |c| {
        c.stage.tilt_min_deg = -10.0;
        c.stage.tilt_max_deg = 45.0;
    });
    let mut c = Client::connect(sim.sharksem_endpoint());
    let Response::Limits(StageLimits { tilt_deg, z_mm, .. }) =
        c.call(&Request::StgGetLimits { kind: 0 })
    else {
        panic!()
    };
    assert_eq!((tilt_deg, z_mm), ((-10.0, 45.0), (0.0, 50.0)));
    // Only types 0 and 1 exist.
    c.send(&Request::StgGetLimits { kind: 2 }, Flags::NONE);
    c.silent();
}
