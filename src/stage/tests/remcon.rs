//! The safety layer over the RemCon32 backend, against the simulator's
//! RemCon32 server (same stage model) and scripted servers, on tokio's paused
//! clock: no real sleeps.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use sdsem_protocol::remcon::{CommandFramer, RemconError};
use sdsem_sim::clock::{Clock, ManualClock};
use sdsem_sim::remcon::RemconStage;
use sdsem_sim::stage_model::StageSnapshot;
use sdsem_sim::{FaultTrigger, SimStage, StageSimConfig, StoreCommand, StoreTrigger};
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream, duplex};
use tokio::time::Instant;

use super::{Log, lines};
use crate::stage::{
    IoOutcome, MemoryObserver, NoopObserver, RemconBackend, StageAxis, StageConfig, StageDriver,
    StageError, StageEvent, StageObserver, StageProtocol,
};

type Remcon = StageDriver<RemconBackend<DuplexStream>>;

fn config() -> StageConfig {
    StageConfig {
        protocol: StageProtocol::Remcon32,
        endpoint: "tcp://127.0.0.1:1".into(),
        ..StageConfig::default()
    }
}

async fn connect(
    io: DuplexStream,
    config: StageConfig,
    observer: Arc<dyn StageObserver>,
) -> Result<Remcon, StageError> {
    let backend = RemconBackend::new(io, config.clone(), Arc::clone(&observer));
    StageDriver::with_backend(backend, config, observer).await
}

/// The simulator's RemCon32 server over a duplex stream, its clock following tokio's.
struct Server {
    stage: Arc<SimStage>,
    clock: Arc<ManualClock>,
    start: Instant,
    store: Arc<StoreTrigger>,
    log: Log,
}

impl Server {
    fn sync(&self) {
        self.clock
            .advance(self.start.elapsed().as_secs_f64() - self.clock.now_s());
    }

    fn truth(&self) -> StageSnapshot {
        self.sync();
        self.stage.snapshot()
    }

    fn sent(&self, line: &str) -> usize {
        lines(&self.log).iter().filter(|l| *l == line).count()
    }
}

fn served(sim: StageSimConfig) -> (DuplexStream, Arc<Server>) {
    sim.validate().expect("valid simulator config");
    let clock = Arc::new(ManualClock::new());
    let stage = Arc::new(SimStage::new(&sim, 1, clock.clone()));
    let store = Arc::new(StoreTrigger::default());
    let remcon = RemconStage::new(
        Arc::clone(&stage),
        &sim.remcon,
        100.0,
        1000.0,
        Arc::clone(&store),
    );
    let server = Arc::new(Server {
        stage,
        clock,
        start: Instant::now(),
        store,
        log: Arc::default(),
    });
    let (client, mut io) = duplex(4096);
    let s = Arc::clone(&server);
    tokio::spawn(async move {
        let mut framer = CommandFramer::new();
        let mut buf = [0u8; 256];
        loop {
            let n = match io.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            for &b in &buf[..n] {
                let Some(line) = framer.push(b) else {
                    continue;
                };
                if let Ok(l) = &line {
                    s.log
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .push(String::from_utf8_lossy(l).into_owned());
                }
                s.sync();
                let response = remcon.handle(line);
                if !response.delay.is_zero() {
                    tokio::time::sleep(response.delay).await;
                }
                if let Some(bytes) = response.reply
                    && io.write_all(&bytes).await.is_err()
                {
                    return;
                }
                if response.disconnect {
                    return;
                }
            }
        }
    });
    (client, server)
}

/// A RemCon32 server played by a closure over the request line.
fn scripted(mut script: impl FnMut(&str) -> Vec<u8> + Send + 'static) -> (DuplexStream, Log) {
    let (client, mut io) = duplex(4096);
    let log: Log = Arc::default();
    let seen = Arc::clone(&log);
    tokio::spawn(async move {
        let mut framer = CommandFramer::new();
        let mut buf = [0u8; 256];
        loop {
            let n = match io.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            for &b in &buf[..n] {
                let Some(Ok(line)) = framer.push(b) else {
                    continue;
                };
                let text = String::from_utf8_lossy(&line).into_owned();
                seen.lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .push(text.clone());
                let reply = script(&text);
                if io.write_all(&reply).await.is_err() {
                    return;
                }
            }
        }
    });
    (client, log)
}

/// A ready RemCon32 stage at rest, for scripted tests.
fn basic(line: &str) -> Vec<u8> {
    match line {
        "" => Vec::new(),
        "VER?" => b"@\r\n>SmartSEM Remote Control V06.01, February 2016\r\n".to_vec(),
        "IST?" => b"@\r\n>1 0\r\n".to_vec(),
        "C95?" => b"@\r\n>1.000000 2.000000 10.000000 0.000000 30.000000 0.000000 0.0\r\n".to_vec(),
        // Accepted, and nothing moves.
        l if l.starts_with("C95 ") => b"@\r\n>\r\n".to_vec(),
        _ => b"@\r\n*600\r\n".to_vec(),
    }
}

#[tokio::test(start_paused = true)]
async fn tilt_series_is_verified_with_every_other_axis_resent_unchanged() {
    let (io, server) = served(StageSimConfig::default());
    let observer = Arc::new(MemoryObserver::default());
    let mut stage = connect(io, config(), observer.clone()).await.unwrap();
    let id = stage.instrument().clone();
    assert_eq!(
        (id.protocol.as_str(), id.vendor.as_str()),
        ("remcon32", "Zeiss")
    );
    assert!(id.version.contains("SmartSEM"), "{id:?}");
    assert_eq!(stage.protocol(), StageProtocol::Remcon32);
    for deg in 1..=3 {
        let target = f64::from(deg);
        let report = stage.move_tilt(target).await.unwrap();
        assert!((report.positions[0].1 - target).abs() <= 0.01);
        assert!(!report.reissued);
        // The wait for the moving flag: nothing is polled before 1 s.
        assert!(report.elapsed >= Duration::from_secs(1), "{report:?}");
        let truth = server.truth();
        assert!((truth.pose.tilt_deg - target).abs() <= 0.01);
        assert!(truth.axes[2].on_target, "returned before the stage settled");
    }
    // Read-modify-write: each C95 follows a C95? and re-sends x, y, z, r, m as read.
    let log = lines(&server.log);
    for deg in 1..=3 {
        let mov = format!("C95 0.000000 0.000000 10.000000 {deg}.000000 0.000000 0.000000");
        let i = log.iter().position(|l| *l == mov).unwrap();
        assert_eq!(log[i - 1], "C95?", "{log:?}");
        assert_eq!(server.sent(&mov), 1);
    }
    assert_eq!(
        &log[..3],
        ["", "VER?", "IST?"],
        "null command, identity, initialised"
    );
    // /stage/io: decoded commands and two-line replies, with round-trip times.
    let io = observer.io_records();
    let mov = io
        .iter()
        .find(|r| r.command.as_deref().is_some_and(|c| c.starts_with("C95 ")))
        .unwrap();
    assert_eq!(mov.reply.as_deref(), Some("@\n>"));
    assert!(mov.rtt_ns.is_some() && mov.outcome == IoOutcome::Replied);
    let query = io
        .iter()
        .find(|r| r.command.as_deref() == Some("C95?"))
        .unwrap();
    assert!(
        query
            .reply
            .as_deref()
            .unwrap()
            .starts_with("@\n>0.000000 0.000000 10.000000"),
        "{query:?}"
    );
    assert_eq!(observer.states()[0].axes[2].id, "t");
}

#[tokio::test(start_paused = true)]
async fn xy_targets_in_micrometres_go_out_in_millimetres() {
    let (io, server) = served(StageSimConfig::default());
    let mut stage = connect(io, config(), Arc::new(NoopObserver)).await.unwrap();
    stage.move_xy(120.0, -35.5).await.unwrap();
    let pose = server.truth().pose;
    assert!(
        (pose.x_um - 120.0).abs() <= 0.1 && (pose.y_um + 35.5).abs() <= 0.1,
        "{pose:?}"
    );
    assert_eq!(
        server.sent("C95 0.120000 -0.035500 10.000000 0.000000 0.000000 0.000000"),
        1
    );
    let p = stage.position().await.unwrap();
    assert!((p.x_um - 120.0).abs() < 1e-6 && (p.y_um + 35.5).abs() < 1e-6);
}

#[tokio::test(start_paused = true)]
async fn a_flag_that_reads_not_moving_while_the_stage_travels_does_not_end_the_move() {
    // The simulator's flag reads 0.0 for 1 s after every C95 although the stage travels.
    let (io, server) = served(StageSimConfig::default());
    assert_eq!(server.truth().faults.stale_on_target, 0);
    let observer = Arc::new(MemoryObserver::default());
    let mut stage = connect(io, config(), observer.clone()).await.unwrap();
    let started = Instant::now();
    let report = stage.move_tilt(3.0).await.unwrap();
    // 3° at 1°/s, then 0.2 s of settling the honest flag shows.
    assert!(report.elapsed >= Duration::from_secs_f64(3.2), "{report:?}");
    assert!(started.elapsed() >= Duration::from_secs_f64(3.2));
    let truth = server.truth();
    assert!((truth.pose.tilt_deg - 3.0).abs() < 1e-9, "{truth:?}");
    assert!(truth.axes[2].on_target, "settled: {truth:?}");
    // sdsem polled during the delay and saw the lie: "not moving" halfway there.
    let lies = observer
        .states()
        .iter()
        .filter(|s| s.event == StageEvent::Poll)
        .filter(|s| {
            let a = &s.axes[0];
            a.on_target == Some(true) && a.position.is_some_and(|p| p > 0.0 && p < 3.0)
        })
        .count();
    assert!(lies >= 5, "{lies} polls saw the stale flag");
}

#[tokio::test(start_paused = true)]
async fn a_short_move_is_verified_by_its_position_before_the_flag_can_be_trusted() {
    let (io, server) = served(StageSimConfig::default());
    let mut stage = connect(io, config(), Arc::new(NoopObserver)).await.unwrap();
    // 5 µm at 100 µm/s: there after 0.05 s, long before the flag's 1 s.
    let report = stage.move_xy(5.0, 0.0).await.unwrap();
    assert!(report.elapsed < Duration::from_millis(400), "{report:?}");
    assert!((server.truth().pose.x_um - 5.0).abs() < 1e-9);
    // Two polls on target with the position unchanged between them.
    assert!(report.polls >= 2, "{report:?}");
    // A move that ends within the delay but only just: never accepted while still travelling.
    let report = stage.move_xy(5.0, 80.0).await.unwrap();
    assert!(report.elapsed >= Duration::from_millis(800), "{report:?}");
    assert!((server.truth().pose.y_um - 80.0).abs() < 1e-9);
}

/// The fault the flag delay exists for: the move starts (and its flag
/// rises) 0.8 s after the command.
fn late_flag() -> StageSimConfig {
    let mut sim = StageSimConfig::default();
    sim.faults.stale_on_target = FaultTrigger::at([1]);
    sim.faults.stale_on_target_s = 0.8;
    sim
}

#[tokio::test(start_paused = true)]
async fn a_late_moving_flag_is_waited_out_not_taken_for_a_move_that_did_not_happen() {
    let (io, server) = served(late_flag());
    let driver = StageConfig {
        no_motion_timeout_s: 0.5,
        ..config()
    };
    let mut stage = connect(io, driver, Arc::new(NoopObserver)).await.unwrap();
    let report = stage.move_tilt(3.0).await.unwrap();
    assert_eq!(server.truth().faults.stale_on_target, 1, "the fault fired");
    assert!(!report.reissued, "{report:?}");
    assert!(report.elapsed >= Duration::from_secs_f64(3.8), "{report:?}");
    assert_eq!(
        server.sent("C95 0.000000 0.000000 10.000000 3.000000 0.000000 0.000000"),
        1
    );
}

#[tokio::test(start_paused = true)]
async fn without_the_wait_the_late_flag_would_cost_a_second_move_command() {
    let (io, server) = served(late_flag());
    let driver = StageConfig {
        no_motion_timeout_s: 0.5,
        moving_flag_delay_s: 0.0,
        ..config()
    };
    let mut stage = connect(io, driver, Arc::new(NoopObserver)).await.unwrap();
    let report = stage.move_tilt(3.0).await.unwrap();
    assert!(report.reissued, "{report:?}");
    assert_eq!(
        server.sent("C95 0.000000 0.000000 10.000000 3.000000 0.000000 0.000000"),
        2
    );
}

#[tokio::test(start_paused = true)]
async fn an_ignored_move_is_reissued_once_then_refused() {
    let mut sim = StageSimConfig::default();
    sim.faults.ignore_move = FaultTrigger::at([1]);
    let (io, server) = served(sim);
    let observer = Arc::new(MemoryObserver::default());
    let mut stage = connect(io, config(), observer.clone()).await.unwrap();
    let report = stage.move_tilt(2.0).await.unwrap();
    assert!(report.reissued);
    let mov = "C95 0.000000 0.000000 10.000000 2.000000 0.000000 0.000000";
    assert_eq!(server.sent(mov), 2);
    assert!(
        observer
            .states()
            .iter()
            .any(|s| s.event == StageEvent::MoveReissued)
    );

    let mut sim = StageSimConfig::default();
    sim.faults.ignore_move = FaultTrigger::probability(1.0);
    let (io, server) = served(sim);
    let mut stage = connect(io, config(), Arc::new(NoopObserver)).await.unwrap();
    let err = stage.move_tilt(2.0).await.unwrap_err();
    assert!(
        matches!(err, StageError::MoveNotExecuted { axis: StageAxis::Tilt, target, .. } if target == 2.0),
        "{err}"
    );
    assert_eq!(server.sent(mov), 2, "re-issued exactly once");
    assert!(err.to_string().contains(mov), "{err}");
}

#[tokio::test(start_paused = true)]
async fn refusals_are_named_with_their_remedy_and_not_resent() {
    // The configured limits are wider than the simulated stage's 70°: the SEM says 603.
    let (io, server) = served(StageSimConfig::default());
    let driver = StageConfig {
        tilt_max_deg: 80.0,
        ..config()
    };
    let mut stage = connect(io, driver, Arc::new(NoopObserver)).await.unwrap();
    let err = stage.move_tilt(75.0).await.unwrap_err();
    assert!(
        matches!(
            err,
            StageError::Remcon {
                error: RemconError::ParameterOutOfRange,
                ..
            }
        ),
        "{err}"
    );
    let msg = err.to_string();
    assert!(
        msg.contains("603 (parameter out of range)") && msg.contains("stage.tilt_min_deg"),
        "{msg}"
    );
    assert_eq!(
        server.sent("C95 0.000000 0.000000 10.000000 75.000000 0.000000 0.000000"),
        1
    );

    let mut sim = StageSimConfig::default();
    sim.faults.move_error = FaultTrigger::at([1]);
    let (io, server) = served(sim);
    let mut stage = connect(io, config(), Arc::new(NoopObserver)).await.unwrap();
    let err = stage.move_tilt(4.0).await.unwrap_err();
    assert!(
        err.to_string().contains("613 (parameter unattainable)"),
        "{err}"
    );
    // Our own limits are still checked first: nothing is sent beyond them.
    let before = lines(&server.log).len();
    assert!(matches!(
        stage.move_tilt(71.0).await,
        Err(StageError::OutOfLimits { .. })
    ));
    assert_eq!(lines(&server.log).len(), before);
}

#[tokio::test(start_paused = true)]
async fn a_stage_that_is_not_initialised_is_refused_at_connect() {
    let sim = StageSimConfig {
        referenced: false,
        ..StageSimConfig::default()
    };
    let (io, server) = served(sim);
    let err = connect(io, config(), Arc::new(NoopObserver))
        .await
        .err()
        .unwrap();
    assert!(matches!(err, StageError::NotInitialised { .. }), "{err}");
    assert!(err.to_string().contains("SmartSEM"), "{err}");
    assert!(
        !lines(&server.log).iter().any(|l| l.starts_with("C95 ")),
        "nothing may move"
    );
}

#[tokio::test(start_paused = true)]
async fn abo_stops_a_moving_stage() {
    let (io, server) = served(StageSimConfig::default());
    let mut stage = connect(io, config(), Arc::new(NoopObserver)).await.unwrap();
    let aborted = tokio::time::timeout(Duration::from_secs(2), stage.move_tilt(30.0)).await;
    assert!(aborted.is_err());
    stage.stop().await.unwrap();
    assert_eq!(server.sent("ABO"), 1);
    let at = server.truth().pose.tilt_deg;
    tokio::time::sleep(Duration::from_secs(5)).await;
    assert_eq!(server.truth().pose.tilt_deg, at, "kept moving after ABO");
    assert!(at > 1.0 && at < 3.0, "{at}");
    // The driver is usable after the cut exchange.
    stage.move_tilt(1.0).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn a_trigger_reaches_the_sems_store_and_is_recorded() {
    let (io, server) = served(StageSimConfig::default());
    let observer = Arc::new(MemoryObserver::default());
    let mut stage = connect(io, config(), observer.clone()).await.unwrap();
    let stored = Arc::new(Mutex::new(Vec::new()));
    let sink = Arc::clone(&stored);
    server.store.set_hook(Arc::new(move |r| {
        sink.lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(r.command);
        match r.command {
            StoreCommand::Macro(9) => Err("no macro REMCON9".into()),
            _ => Ok(()),
        }
    }));
    assert_eq!(stage.send_trigger("FREC").await.unwrap(), "");
    assert_eq!(stage.send_trigger("MAC 1").await.unwrap(), "");
    let err = stage.send_trigger("MAC 9").await.unwrap_err();
    assert!(
        err.to_string()
            .contains("616 (cannot execute that command)"),
        "{err}"
    );
    let err = stage.send_trigger("SNAP").await.unwrap_err();
    assert!(
        err.to_string().contains("600 (unknown command)")
            && err.to_string().contains("imaging.trigger"),
        "{err}"
    );
    assert_eq!(
        *stored.lock().unwrap_or_else(PoisonError::into_inner),
        [
            StoreCommand::Record,
            StoreCommand::Macro(1),
            StoreCommand::Macro(9)
        ]
    );
    let io = observer.io_records();
    let frec = io
        .iter()
        .find(|r| r.command.as_deref() == Some("FREC"))
        .unwrap();
    assert_eq!(
        (frec.reply.as_deref(), frec.outcome),
        (Some("@\n>"), IoOutcome::Replied)
    );
    // A trigger is sent once, never repeated.
    assert_eq!(server.sent("MAC 9"), 1);
}

#[tokio::test(start_paused = true)]
async fn lost_and_garbled_query_replies_are_retried() {
    let mut sim = StageSimConfig::default();
    // Commands 1 VER?, 2 IST?, 3 C95? (position at connect): dropped, then garbled.
    sim.faults.drop_reply = FaultTrigger::at([3]);
    sim.faults.garble_reply = FaultTrigger::at([4]);
    let (io, server) = served(sim);
    let observer = Arc::new(MemoryObserver::default());
    let mut stage = connect(io, config(), observer.clone()).await.unwrap();
    let outcomes: Vec<IoOutcome> = observer
        .io_records()
        .iter()
        .filter(|r| r.command.as_deref() == Some("C95?"))
        .map(|r| r.outcome)
        .collect();
    assert_eq!(
        outcomes,
        [IoOutcome::Timeout, IoOutcome::Garbled, IoOutcome::Replied]
    );
    let f = server.truth().faults;
    assert_eq!((f.dropped_replies, f.garbled_replies), (1, 1));
    stage.move_tilt(1.0).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn a_silent_server_is_a_clear_error_naming_the_query() {
    let (io, log) = scripted(|_| Vec::new());
    let err = connect(io, config(), Arc::new(NoopObserver))
        .await
        .err()
        .unwrap();
    assert!(
        matches!(&err, StageError::NoReply { command, attempts: 3, .. } if command == "VER?"),
        "{err}"
    );
    // Over TCP the remedy names the address and the language, not a baud rate.
    let text = err.to_string();
    assert!(
        text.contains("check that 127.0.0.1:1 (stage.endpoint) is a serial-to-Ethernet server")
            && text.contains(
                "speaks Zeiss RemCon32 (stage.protocol = \"remcon32\") and that RemCon32 runs"
            )
            && !text.contains("baud"),
        "{text}"
    );
    assert_eq!(lines(&log).iter().filter(|l| *l == "VER?").count(), 3);

    // Over a serial line: the cable and the baud rate in use.
    let (io, _) = scripted(|_| Vec::new());
    let serial = StageConfig {
        endpoint: "/dev/ttyUSB0".into(),
        ..config()
    };
    let err = connect(io, serial, Arc::new(NoopObserver))
        .await
        .err()
        .unwrap();
    assert!(
        err.to_string()
            .contains("check the cable, the baud rate (stage.baud; 9600 in use)"),
        "{err}"
    );
}

#[tokio::test(start_paused = true)]
async fn replies_that_do_not_parse_are_clear_errors() {
    // `#` to every VER?, once with a second line after it (accepted and discarded).
    let mut n = 0;
    let (io, _) = scripted(move |l| match l {
        "VER?" => {
            n += 1;
            if n == 1 {
                b"#\r\n*601\r\n".to_vec()
            } else {
                b"#\r\n".to_vec()
            }
        }
        other => basic(other),
    });
    let observer = Arc::new(MemoryObserver::default());
    let err = connect(io, config(), observer.clone()).await.err().unwrap();
    assert!(
        matches!(&err, StageError::InvalidCommand { attempts: 3, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("stage.protocol"), "{err}");
    assert!(
        observer
            .io_records()
            .iter()
            .any(|r| r.outcome == IoOutcome::Stray),
        "the line after `#` was discarded"
    );

    // A C95? answer of six values is garbled every time.
    let (io, _) = scripted(|l| match l {
        "C95?" => b"@\r\n>1 2 3 4 5 6\r\n".to_vec(),
        other => basic(other),
    });
    let err = connect(io, config(), Arc::new(NoopObserver))
        .await
        .err()
        .unwrap();
    assert!(
        matches!(&err, StageError::Garbled { command, attempts: 3, .. } if command == "C95?"),
        "{err}"
    );
    assert!(err.to_string().contains("seven numbers"), "{err}");
}

#[tokio::test(start_paused = true)]
async fn rotation_and_z_of_a_real_stage_are_resent_as_read() {
    let (io, log) = scripted(basic);
    let mut stage = connect(io, config(), Arc::new(NoopObserver)).await.unwrap();
    // The scripted stage never moves: the move is re-issued once, then refused;
    // what matters here is what was sent.
    let _ = stage.move_tilt(5.0).await;
    let sent = lines(&log);
    let mov = "C95 1.000000 2.000000 10.000000 5.000000 30.000000 0.000000";
    assert_eq!(sent.iter().filter(|l| *l == mov).count(), 2, "{sent:?}");
    let p = stage.position().await.unwrap();
    assert_eq!((p.x_um, p.y_um, p.tilt_deg), (1000.0, 2000.0, 0.0));
}

#[tokio::test(start_paused = true)]
async fn a_lost_link_names_the_command() {
    let mut sim = StageSimConfig::default();
    // VER?, IST?, C95? at connect; the move's C95? (start), C95? (read-modify-write),
    // after which the link drops.
    sim.faults.disconnect_after_commands = Some(5);
    let (io, _) = served(sim);
    let mut stage = connect(io, config(), Arc::new(NoopObserver)).await.unwrap();
    let err = stage.move_tilt(1.0).await.unwrap_err();
    assert!(matches!(&err, StageError::Disconnected { .. }), "{err}");
    assert!(err.to_string().contains("C95 "), "{err}");
}
