//! The stage as a Zeiss SmartSEM RemCon32 serves it (VENDORS §1.7), from the
//! same [`StageModel`] and clock as PI GCS: `@` then `>data` for every known
//! command, `@` then `*600` for an unknown one, `#` alone for the wrong number
//! of values to `C95`/`STG`, linear motion with a moving flag, `ABO`.
//!
//! The moving flag is set late, as SmartSEM's is [OD-Z]: for `moving_flag_delay_s`
//! after every accepted move command it reads `0.0` although the stage travels.
//!
//! Faults, from [`crate::FaultConfig`] and counted as there: dropped, garbled
//! and late replies and the disconnect by command number; by move, a silently
//! ignored `C95`, a move that starts late (`stale_on_target`: the stage stands
//! still with its moving flag at `0.0` for `stale_on_target_s` after the
//! command, the reason for the ~1 s wait before the first poll [OD-Z]) and
//! `move_error`, answered `*613` (parameter unattainable). A target outside the limits is `*603`;
//! a move while the stage is not initialised, `*616`.
//!
//! Z, rotation and M are not modelled in motion: a `C95` sets them at once (a
//! tilt series re-sends them unchanged). Rotation is taken modulo 360°.

use std::sync::{Arc, Mutex, PoisonError};

use sdsem_protocol::remcon::{
    Command, CommandFramer, LineTooLong, RemconError, Reply, StageInit, StageReading, StageTarget,
};
use tracing::{debug, warn};

use crate::config::RemconSimConfig;
use crate::stage::SimStage;
use crate::stage_link::{Session, SessionFactory};
use crate::stage_model::{AxisRole, MoveRefusal, Response};
use crate::store::{StoreCommand, StoreRequest, StoreTrigger};

/// The axes the model does not move, and the photo counter.
#[derive(Debug)]
struct Extra {
    z_mm: f64,
    r_deg: f64,
    m_mm: f64,
    photos: u64,
    /// Simulated time from which the moving flag is honest again (set late after a move).
    flag_honest_at: f64,
}

/// A RemCon32 server over the shared simulated stage.
#[derive(Debug)]
pub struct RemconStage {
    stage: Arc<SimStage>,
    version: String,
    stage_type: i64,
    pixel_size_nm: f64,
    magnification: f64,
    detector: String,
    eht_kv: f64,
    moving_flag_delay_s: f64,
    extra: Mutex<Extra>,
    store: Arc<StoreTrigger>,
}

impl RemconStage {
    /// A server per `config` over `stage`; `PIX?` answers `pixel_size_nm` and
    /// `MAG?` `magnification`; `FREC`/`MAC n` go to `store`.
    pub fn new(
        stage: Arc<SimStage>,
        config: &RemconSimConfig,
        pixel_size_nm: f64,
        magnification: f64,
        store: Arc<StoreTrigger>,
    ) -> Self {
        Self {
            stage,
            version: config.version.clone(),
            stage_type: config.stage_type,
            pixel_size_nm,
            magnification,
            detector: config.detector.clone(),
            eht_kv: config.eht_kv,
            moving_flag_delay_s: config.moving_flag_delay_s,
            extra: Mutex::new(Extra {
                z_mm: config.z_mm,
                r_deg: config.rotation_deg.rem_euclid(360.0),
                m_mm: config.m_mm,
                photos: 0,
                flag_honest_at: 0.0,
            }),
            store,
        }
    }

    fn extra(&self) -> std::sync::MutexGuard<'_, Extra> {
        self.extra.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Handles one framed request line (terminator removed).
    pub fn handle(&self, line: Result<Vec<u8>, LineTooLong>) -> Response {
        let parsed = match &line {
            Err(_) => Err(Reply::Failed(RemconError::CommandTooLong)),
            Ok(l) => Command::parse(l).map_err(|e| e.reply()),
        };
        // The null command is a probe: nothing to answer, nothing counted.
        if parsed == Ok(Command::Null) {
            return Response::default();
        }
        let k = self.stage.with_model(|m, now| m.begin_command(now));
        let reply = match parsed {
            Ok(command) => self.execute(&command),
            Err(reply) => reply,
        };
        if let Ok(l) = &line {
            debug!(request = %String::from_utf8_lossy(l), reply = %reply.to_text(), "RemCon32 exchange");
        }
        let bytes = reply.to_bytes();
        self.stage.with_model(|m, _| {
            let response = m.deliver(k, bytes);
            m.end_command(k, response)
        })
    }

    /// A new connection's session.
    pub(crate) fn session(self: &Arc<Self>) -> Box<dyn Session> {
        Box::new(RemconSession {
            framer: CommandFramer::new(),
            server: Arc::clone(self),
        })
    }

    /// Sessions for every connection to `server`.
    pub(crate) fn sessions(server: Arc<Self>) -> SessionFactory {
        Arc::new(move || server.session())
    }

    fn reading(&self) -> StageReading {
        let (pose, busy, now) = self
            .stage
            .with_model(|m, now| (m.pose(now), m.busy(now), now));
        let e = self.extra();
        StageReading {
            x_mm: pose.x_um / 1000.0,
            y_mm: pose.y_um / 1000.0,
            z_mm: e.z_mm,
            t_deg: pose.tilt_deg,
            r_deg: e.r_deg,
            m_mm: e.m_mm,
            moving: busy && now >= e.flag_honest_at,
        }
    }

    fn move_to(&self, target: StageTarget) -> Reply {
        let targets = [
            (AxisRole::X, target.x_mm * 1000.0),
            (AxisRole::Y, target.y_mm * 1000.0),
            (AxisRole::Tilt, target.t_deg),
        ];
        match self
            .stage
            .with_model(|m, now| m.move_roles(now, &targets, true).map(|s| (s, now)))
        {
            Ok((started, now)) => {
                if started {
                    let mut e = self.extra();
                    e.z_mm = target.z_mm;
                    e.r_deg = target.r_deg.rem_euclid(360.0);
                    e.m_mm = target.m_mm;
                    e.flag_honest_at = now + self.moving_flag_delay_s;
                }
                Reply::Done(String::new())
            }
            Err(MoveRefusal::OutOfLimits) => Reply::Failed(RemconError::ParameterOutOfRange),
            Err(MoveRefusal::NotReady) => Reply::Failed(RemconError::CannotExecute),
            Err(MoveRefusal::Fault) => Reply::Failed(RemconError::ParameterUnattainable),
        }
    }

    fn store(&self, command: StoreCommand) -> Reply {
        let photo_number = {
            let mut e = self.extra();
            e.photos += 1;
            e.photos
        };
        // No lock held: the hook may render the stage where it is.
        match self.store.fire(&StoreRequest {
            command,
            photo_number,
        }) {
            Ok(()) => Reply::Done(String::new()),
            Err(cause) => {
                warn!(?command, %cause, "the simulated SEM could not store the micrograph");
                Reply::Failed(RemconError::CannotExecute)
            }
        }
    }

    fn execute(&self, command: &Command) -> Reply {
        match command {
            Command::Null => Reply::Done(String::new()),
            Command::Version => Reply::Done(self.version.clone()),
            Command::StageQuery => Reply::Done(self.reading().to_data()),
            Command::StageMove(target) => self.move_to(*target),
            Command::Stage3Query => {
                let r = self.reading();
                Reply::Done(format!(
                    "{:.6} {:.6} {:.6} {}",
                    r.x_mm,
                    r.y_mm,
                    r.z_mm,
                    if r.moving { "1.0" } else { "0.0" }
                ))
            }
            Command::Stage3Move { x_mm, y_mm, z_mm } => {
                let r = self.reading();
                self.move_to(StageTarget {
                    x_mm: *x_mm,
                    y_mm: *y_mm,
                    z_mm: *z_mm,
                    ..StageTarget::from_values([r.x_mm, r.y_mm, r.z_mm, r.t_deg, r.r_deg, r.m_mm])
                })
            }
            Command::InitialisedQuery => {
                let initialised = self.stage.with_model(|m, _| m.ready());
                Reply::Done(
                    StageInit {
                        stage_type: self.stage_type,
                        initialised,
                    }
                    .to_data(),
                )
            }
            Command::Abort => {
                self.stage.with_model(|m, now| m.halt_all(now));
                Reply::Done(String::new())
            }
            Command::PixelSizeQuery => Reply::Done(format!("{:.4}", self.pixel_size_nm)),
            Command::MagnificationQuery => Reply::Done(format!("{:.1}", self.magnification)),
            Command::Record => self.store(StoreCommand::Record),
            Command::Macro(n) => self.store(StoreCommand::Macro(*n)),
            Command::PhotoNumberQuery => Reply::Done(self.extra().photos.to_string()),
            Command::DetectorQuery => Reply::Done(self.detector.clone()),
            Command::EhtQuery => Reply::Done(format!("{:.3}", self.eht_kv)),
        }
    }
}

struct RemconSession {
    framer: CommandFramer,
    server: Arc<RemconStage>,
}

impl Session for RemconSession {
    fn push(&mut self, byte: u8) -> Option<Response> {
        self.framer.push(byte).map(|line| self.server.handle(line))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::ManualClock;
    use crate::config::{FaultTrigger, StageSimConfig};
    use sdsem_protocol::remcon::ReplyFramer;

    fn server(config: StageSimConfig) -> (Arc<RemconStage>, Arc<ManualClock>, Arc<StoreTrigger>) {
        config.validate().unwrap();
        let clock = Arc::new(ManualClock::new());
        let stage = Arc::new(SimStage::new(&config, 5, clock.clone()));
        let store = Arc::new(StoreTrigger::default());
        let s = RemconStage::new(stage, &config.remcon, 250.0, 1000.0, Arc::clone(&store));
        (Arc::new(s), clock, store)
    }

    /// Sends `line` byte by byte (CR LF) through a session; the replies framed.
    fn ask(s: &Arc<RemconStage>, line: &str) -> Vec<Reply> {
        let mut session = s.session();
        let mut framer = ReplyFramer::new();
        for &b in line.as_bytes().iter().chain(b"\r\n") {
            if let Some(r) = session.push(b).and_then(|r| r.reply) {
                framer.feed(&r);
            }
        }
        std::iter::from_fn(|| framer.next_reply())
            .map(Result::unwrap)
            .collect()
    }

    fn data(s: &Arc<RemconStage>, line: &str) -> String {
        match ask(s, line).as_slice() {
            [Reply::Done(d)] => d.clone(),
            other => panic!("{line}: {other:?}"),
        }
    }

    fn reading(s: &Arc<RemconStage>) -> StageReading {
        StageReading::parse(&data(s, "C95?")).unwrap()
    }

    #[test]
    fn c95_moves_linearly_with_a_moving_flag_set_late_then_settles() {
        let (s, clock, _) = server(StageSimConfig::default());
        assert!(data(&s, "VER?").contains("SmartSEM"));
        assert_eq!(data(&s, "IST?"), "1 0");
        let r = reading(&s);
        assert!(!r.moving);
        assert_eq!((r.z_mm, r.m_mm), (10.0, 0.0));
        // x 0.05 mm = 50 µm at 100 µm/s; tilt 2° at 1°/s.
        assert_eq!(data(&s, "C95 0.05 0 10 2 0 0"), "");
        // For the flag's delay (1 s) it reads 0.0 although the stage travels.
        clock.advance(0.5);
        let early = reading(&s);
        assert!(
            !early.moving && (early.t_deg - 0.5).abs() < 1e-9,
            "{early:?}"
        );
        clock.advance(0.5);
        let mid = reading(&s);
        assert!(mid.moving);
        assert!((mid.t_deg - 1.0).abs() < 1e-9 && (mid.x_mm - 0.05).abs() < 1e-9);
        clock.advance(1.1);
        assert!(reading(&s).moving, "settling");
        clock.advance(0.2);
        let end = reading(&s);
        assert!(!end.moving && end.t_deg == 2.0, "{end:?}");
    }

    #[test]
    fn bad_requests_get_the_documented_replies() {
        let (s, _, _) = server(StageSimConfig::default());
        assert_eq!(
            ask(&s, "HELLO"),
            [Reply::Failed(RemconError::UnknownCommand)]
        );
        assert_eq!(ask(&s, "C95 1 2 3"), [Reply::Invalid]);
        assert_eq!(
            ask(&s, "C95 0 0 10 71 0 0"),
            [Reply::Failed(RemconError::ParameterOutOfRange)],
            "tilt beyond the 70° limit"
        );
        let long = "C".repeat(300);
        assert_eq!(ask(&s, &long), [Reply::Failed(RemconError::CommandTooLong)]);
        // The null command is answered with nothing.
        assert!(ask(&s, "").is_empty());
        assert_eq!(
            s.stage.command_count(),
            4,
            "the null command is not counted"
        );
    }

    #[test]
    fn abort_stops_a_move_where_it_is() {
        let (s, clock, _) = server(StageSimConfig::default());
        data(&s, "C95 0 0 10 10 0 0");
        clock.advance(2.0);
        assert_eq!(data(&s, "ABO"), "");
        clock.advance(5.0);
        let r = reading(&s);
        assert!(!r.moving && (r.t_deg - 2.0).abs() < 1e-9, "{r:?}");
    }

    #[test]
    fn ignored_late_flag_and_refused_moves_as_configured() {
        let mut c = StageSimConfig::default();
        c.faults.ignore_move = FaultTrigger::at([1]);
        c.faults.stale_on_target = FaultTrigger::at([2]);
        c.faults.stale_on_target_s = 0.5;
        c.faults.move_error = FaultTrigger::at([3]);
        // The fault alone, without the flag's usual delay.
        c.remcon.moving_flag_delay_s = 0.0;
        let (s, clock, _) = server(c);
        // 1: answered as done, nothing moves.
        assert_eq!(data(&s, "C95 0 0 10 3 0 0"), "");
        clock.advance(5.0);
        assert_eq!(reading(&s).t_deg, 0.0);
        // 2: for 0.5 s the stage stands still and its flag reads idle.
        data(&s, "C95 0 0 10 3 0 0");
        clock.advance(0.3);
        let early = reading(&s);
        assert!(!early.moving && early.t_deg == 0.0, "{early:?}");
        clock.advance(0.5);
        let late = reading(&s);
        assert!(late.moving && (late.t_deg - 0.3).abs() < 1e-9, "{late:?}");
        clock.advance(5.0);
        // 3: refused, parameter unattainable.
        assert_eq!(
            ask(&s, "C95 0 0 10 1 0 0"),
            [Reply::Failed(RemconError::ParameterUnattainable)]
        );
        let f = s.stage.snapshot().faults;
        assert_eq!(
            (f.ignored_moves, f.stale_on_target, f.move_errors),
            (1, 1, 1)
        );
    }

    #[test]
    fn an_uninitialised_stage_says_so_and_refuses_moves() {
        let (s, _, _) = server(StageSimConfig {
            referenced: false,
            ..StageSimConfig::default()
        });
        assert_eq!(data(&s, "IST?"), "1 1");
        assert_eq!(
            ask(&s, "C95 0 0 10 1 0 0"),
            [Reply::Failed(RemconError::CannotExecute)]
        );
    }

    #[test]
    fn frec_and_mac_reach_the_store_hook_and_count_photos() {
        let (s, _, store) = server(StageSimConfig::default());
        assert_eq!(data(&s, "PHN?"), "0");
        assert_eq!(data(&s, "FREC"), "", "no hook: done, nothing stored");
        let seen = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&seen);
        store.set_hook(Arc::new(move |r| {
            sink.lock().unwrap().push(*r);
            if r.command == StoreCommand::Macro(2) {
                Err("disk full".into())
            } else {
                Ok(())
            }
        }));
        assert_eq!(data(&s, "FREC"), "");
        assert_eq!(data(&s, "MAC 1"), "");
        assert_eq!(
            ask(&s, "MAC 2"),
            [Reply::Failed(RemconError::CannotExecute)]
        );
        assert_eq!(data(&s, "PHN?"), "4");
        let seen = seen.lock().unwrap();
        assert_eq!(
            seen.iter()
                .map(|r| (r.command, r.photo_number))
                .collect::<Vec<_>>(),
            [
                (StoreCommand::Record, 2),
                (StoreCommand::Macro(1), 3),
                (StoreCommand::Macro(2), 4)
            ]
        );
        assert_eq!(store.requests(), 4);
        assert_eq!(data(&s, "PIX?"), "250.0000");
        assert_eq!(data(&s, "DET?"), "SE2");
        assert_eq!(data(&s, "EHT?"), "5.000");
    }

    #[test]
    fn reply_faults_apply_to_both_lines() {
        let mut c = StageSimConfig::default();
        c.faults.drop_reply = FaultTrigger::at([1]);
        c.faults.disconnect_after_commands = Some(2);
        let (s, _, _) = server(c);
        assert!(ask(&s, "VER?").is_empty(), "dropped");
        let mut session = s.session();
        let mut last = None;
        for &b in b"C95?\r" {
            last = session.push(b).or(last);
        }
        let r = last.unwrap();
        assert!(r.disconnect && r.reply.is_some(), "answered, then closed");
    }

    #[test]
    fn the_simulator_serves_remcon32_over_tcp_and_a_pty() {
        use std::io::{Read, Write};
        use std::time::Duration;

        use crate::config::{SimConfig, SimEndpoint, SimStageProtocol};
        use crate::scene::SceneKind;

        for endpoint in [
            SimEndpoint::Tcp(std::net::SocketAddr::from(([127, 0, 0, 1], 0))),
            SimEndpoint::Pty,
        ] {
            let mut c = SimConfig {
                time_scale: 0.001,
                ..SimConfig::default()
            };
            c.stage.protocol = SimStageProtocol::Remcon32;
            c.stage.endpoint = endpoint;
            c.sem.scene.kind = SceneKind::Grid;
            c.sem.scene.field_um = 60.0;
            c.sem.optics.width = 128;
            c.sem.optics.height = 96;
            c.sem.optics.pixel_size_um = 0.5;
            let sim = crate::Simulator::spawn(c).unwrap();
            let fired = Arc::new(Mutex::new(0u32));
            let count = Arc::clone(&fired);
            sim.store_trigger().set_hook(Arc::new(move |_| {
                *count.lock().unwrap() += 1;
                Ok(())
            }));
            let mut link: Box<dyn ReadWrite> = match sim.stage_endpoint().strip_prefix("tcp://") {
                Some(addr) => {
                    let s = std::net::TcpStream::connect(addr).unwrap();
                    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
                    Box::new(s)
                }
                None => Box::new(
                    serialport::new(sim.stage_endpoint(), 9600)
                        .timeout(Duration::from_secs(10))
                        .open_native()
                        .unwrap(),
                ),
            };
            let mut ask = |line: &str| -> Reply {
                link.write_all(format!("{line}\r").as_bytes()).unwrap();
                let mut framer = ReplyFramer::new();
                let mut byte = [0u8; 1];
                loop {
                    if let Some(r) = framer.next_reply() {
                        return r.unwrap();
                    }
                    link.read_exact(&mut byte).unwrap();
                    framer.feed(&byte);
                }
            };
            assert!(matches!(ask("VER?"), Reply::Done(v) if v.contains("SmartSEM")));
            // 128 px × 0.5 µm = 64 µm wide: PIX? = 64000 nm / 1024.
            assert_eq!(ask("PIX?"), Reply::Done("62.5000".into()));
            assert_eq!(ask("C95 0 0 10 2 0 0"), Reply::Done(String::new()));
            std::thread::sleep(Duration::from_millis(50));
            assert_eq!(ask("FREC"), Reply::Done(String::new()));
            let Reply::Done(data) = ask("C95?") else {
                panic!("C95? failed")
            };
            let r = StageReading::parse(&data).unwrap();
            assert!(!r.moving && r.t_deg == 2.0, "{r:?}");
            assert_eq!(*fired.lock().unwrap(), 1);
            assert_eq!(
                sim.stage_snapshot().pose.tilt_deg,
                2.0,
                "the same stage model"
            );
            drop(link);
            sim.stop();
        }
    }

    trait ReadWrite: std::io::Read + std::io::Write {}
    impl<T: std::io::Read + std::io::Write> ReadWrite for T {}
}
