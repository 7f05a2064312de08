//! Starting and stopping the simulated instruments, in-process or from `main`:
//! one configuration, one clock, one specimen, two servers.

use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use tracing::{info, warn};

use crate::SimError;
use crate::clock::{Clock, ScaledClock};
use crate::config::{SimConfig, SimEndpoint, SimStageProtocol, derive_seed};
use crate::folder_writer::{self, FolderWriter, StoreRequests};
use crate::pose::PoseSource;
use crate::remcon::RemconStage;
use crate::scene::Scene;
use crate::sem::{FrameRecord, SimSem};
use crate::sem_server;
use crate::sharksem::{self, SharkSemDevice};
use crate::stage::SimStage;
use crate::stage_link::{SessionFactory, gcs_sessions, serve_pty, serve_tcp};
use crate::stage_model::StageSnapshot;
use crate::store::{StoreCommand, StoreTrigger};

/// One endpoint the simulator serves, e.g. `stage` at `tcp://127.0.0.1:40123`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ServiceEndpoint {
    /// Which instrument: `stage` or `sem`.
    pub service: &'static str,
    /// What a client opens: `tcp://IP:PORT` or a pty slave path such as `/dev/pts/7`.
    pub address: String,
}

/// A running server thread, as every simulated instrument's server returns it.
///
/// A server watches the simulator's shared stop flag; `wake` is an address to
/// connect to so that a thread blocked in `accept` notices the flag.
#[derive(Debug)]
pub(crate) struct ServiceServer {
    /// What a client opens: `tcp://IP:PORT` or a device path.
    pub endpoint: String,
    /// The server thread.
    pub thread: JoinHandle<()>,
    /// Connect here to unblock `accept` (TCP servers): also the address a
    /// client on this machine connects to.
    pub wake: Option<SocketAddr>,
}

impl ServiceServer {
    /// Waits for the server thread after the stop flag was set.
    pub(crate) fn join(self) {
        if let Some(addr) = self.wake {
            // Unblocks accept(); failure only means the listener is already gone.
            let _ = TcpStream::connect_timeout(&addr, Duration::from_secs(1));
        }
        if self.thread.join().is_err() {
            warn!(endpoint = %self.endpoint, "simulator server thread panicked");
        }
    }
}

/// Entry point of the simulator as a library.
#[derive(Debug)]
pub struct Simulator;

impl Simulator {
    /// Validates `config`, builds the specimen (about a second for the default
    /// 200 µm field) and starts the stage controller and the SEM imaging
    /// server on background threads, on a clock scaled by `config.time_scale`.
    /// The SEM images the simulated stage.
    ///
    /// # Errors
    /// [`SimError`] naming the wrong setting, the endpoint that cannot be
    /// bound, or the thread that cannot start. Nothing keeps running then.
    pub fn spawn(config: SimConfig) -> Result<SimHandle, SimError> {
        config.validate()?;
        let clock: Arc<dyn Clock> = Arc::new(ScaledClock::new(config.time_scale));
        Self::spawn_with_clock(config, clock)
    }

    /// Like [`Simulator::spawn`], on a given clock (tests: a
    /// [`crate::clock::ManualClock`]); `config.time_scale` is then not used.
    ///
    /// # Errors
    /// As [`Simulator::spawn`].
    pub fn spawn_with_clock(
        config: SimConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<SimHandle, SimError> {
        config.validate()?;
        let config = config.resolved();
        // The slow step first, before anything listens: a client never finds
        // a stage whose SEM is not there yet.
        let scene = Arc::new(Scene::generate(&config.sem.scene)?);
        let stop = Arc::new(AtomicBool::new(false));
        let stage_seed = config.stage.seed.unwrap_or(config.seed);
        let stage = Arc::new(SimStage::new(&config.stage, stage_seed, Arc::clone(&clock)));
        let sem = Arc::new(SimSem::new(
            &config.sem,
            scene,
            Arc::clone(&stage) as Arc<dyn PoseSource>,
            Arc::clone(&clock),
        ));
        let mut handle = SimHandle {
            endpoints: Vec::new(),
            servers: Vec::new(),
            stage: Arc::clone(&stage),
            sem: Arc::clone(&sem),
            sem_addr: SocketAddr::from(([127, 0, 0, 1], 0)),
            clock: Arc::clone(&clock),
            stop: Arc::clone(&stop),
            config: config.clone(),
            folder: None,
            store: Arc::new(StoreTrigger::default()),
            sharksem: None,
        };
        let sessions: SessionFactory = match config.stage.protocol {
            SimStageProtocol::PiGcs => gcs_sessions(stage),
            SimStageProtocol::Remcon32 => {
                // PIX? is the full field width / 1024 [SF]; MAG? by this
                // simulator's own convention: a 100 mm wide display.
                let o = &config.sem.optics;
                let field_um = o.pixel_size_um * o.width as f64;
                RemconStage::sessions(Arc::new(RemconStage::new(
                    stage,
                    &config.stage.remcon,
                    field_um * 1000.0 / 1024.0,
                    100_000.0 / field_um,
                    Arc::clone(&handle.store),
                )))
            }
        };
        // On an error below, dropping `handle` stops what already runs.
        let server = match &config.stage.endpoint {
            SimEndpoint::Tcp(addr) => serve_tcp(*addr, sessions, Arc::clone(&stop))?,
            SimEndpoint::Pty => serve_pty(&sessions, Arc::clone(&stop))?,
        };
        handle.add("stage", server);
        let SimEndpoint::Tcp(sem_addr) = config.sem.endpoint else {
            // Refused by SemSimConfig::validate already; kept as an error, not a panic.
            return Err(SimError::Config {
                field: "sem.endpoint",
                reason: "the SEM imaging link is TCP only".into(),
            });
        };
        let server = sem_server::serve_tcp(sem_addr, Arc::clone(&sem), Arc::clone(&stop))?;
        handle.sem_addr = server.wake.unwrap_or(sem_addr);
        handle.add("sem", server);
        if let Some(folder) = &config.folder {
            let seed = folder.seed.unwrap_or(config.seed);
            let writer = Arc::new(FolderWriter::new(folder, seed, Arc::clone(&sem), clock)?);
            let (requests, server) = folder_writer::serve(Arc::clone(&writer), Arc::clone(&stop))?;
            // RemCon32 FREC / MAC n: the SEM stores a micrograph on its own thread; the
            // command is done once asked, the file arrives when scanned and written. FREC
            // stores at the folder's settings, MAC n at its macro's.
            let line = requests.clone();
            let folder_config = folder.clone();
            handle.store.set_hook(Arc::new(move |request| {
                let Some(settings) = folder_config.settings_for(request.command) else {
                    let known: Vec<String> = folder_config
                        .macros
                        .iter()
                        .map(|m| m.number.to_string())
                        .collect();
                    let name = match request.command {
                        StoreCommand::Macro(n) => format!("REMCON{n}"),
                        StoreCommand::Record => "FREC".to_owned(),
                    };
                    return Err(format!(
                        "no macro {name} is set up (simulator.folder.macros has [{}])",
                        known.join(", ")
                    ));
                };
                if line.store_at(settings) {
                    Ok(())
                } else {
                    Err("the store folder has stopped".into())
                }
            }));
            handle.folder = Some((writer, requests));
            handle.add("folder", server);
        }
        if let Some(shark) = &config.sharksem {
            let device = Arc::new(SharkSemDevice::new(
                shark.clone(),
                Arc::clone(&handle.stage),
                sem,
                derive_seed(config.seed, "sharksem"),
            ));
            let (control, data) = sharksem::serve(shark, Arc::clone(&device), Arc::clone(&stop))?;
            handle.add("sharksem", control);
            handle.add("sharksem-data", data);
            handle.sharksem = Some(device);
        }
        info!(
            seed = config.seed,
            time_scale = config.time_scale,
            scene = %config.sem.scene.kind,
            "simulator running"
        );
        Ok(handle)
    }
}

/// A running simulator. Dropping it stops every server and waits for their threads.
#[derive(Debug)]
pub struct SimHandle {
    endpoints: Vec<ServiceEndpoint>,
    servers: Vec<ServiceServer>,
    stage: Arc<SimStage>,
    sem: Arc<SimSem>,
    sem_addr: SocketAddr,
    clock: Arc<dyn Clock>,
    stop: Arc<AtomicBool>,
    config: SimConfig,
    /// The store folder's writer and its request line, when configured.
    folder: Option<(Arc<FolderWriter>, StoreRequests)>,
    store: Arc<StoreTrigger>,
    sharksem: Option<Arc<SharkSemDevice>>,
}

impl SimHandle {
    fn add(&mut self, service: &'static str, server: ServiceServer) {
        self.endpoints.push(ServiceEndpoint {
            service,
            address: server.endpoint.clone(),
        });
        self.servers.push(server);
    }

    fn endpoint(&self, service: &str) -> &str {
        self.endpoints
            .iter()
            .find(|e| e.service == service)
            .map_or("", |e| e.address.as_str())
    }

    /// Every endpoint served: `stage`, then `sem`, then `folder` (its path),
    /// `sharksem` and `sharksem-data` when configured.
    pub fn endpoints(&self) -> &[ServiceEndpoint] {
        &self.endpoints
    }

    /// One machine-readable line per endpoint: `stage tcp://127.0.0.1:40123`
    /// (or `stage /dev/pts/7`), `sem tcp://127.0.0.1:40124`.
    pub fn endpoint_lines(&self) -> Vec<String> {
        self.endpoints
            .iter()
            .map(|e| format!("{} {}", e.service, e.address))
            .collect()
    }

    /// The stage controller's endpoint, as `sdsem`'s `stage.endpoint` accepts
    /// it: `tcp://IP:PORT` or a pty path.
    pub fn stage_endpoint(&self) -> &str {
        self.endpoint("stage")
    }

    /// The SEM imaging server's endpoint: `tcp://IP:PORT`.
    pub fn sem_endpoint(&self) -> &str {
        self.endpoint("sem")
    }

    /// The SharkSEM control endpoint `tcp://IP:PORT`, when configured ("" otherwise).
    pub fn sharksem_endpoint(&self) -> &str {
        self.endpoint("sharksem")
    }

    /// The SharkSEM data endpoint `tcp://IP:PORT`, when configured ("" otherwise).
    pub fn sharksem_data_endpoint(&self) -> &str {
        self.endpoint("sharksem-data")
    }

    /// The SEM as SharkSEM clients see it (view field, counters), when configured.
    pub fn sharksem(&self) -> Option<&Arc<SharkSemDevice>> {
        self.sharksem.as_ref()
    }

    /// The SEM imaging server's address as a client on this machine connects
    /// to it (`sdsem`'s `imaging.endpoint` is its `host:port`).
    pub fn sem_addr(&self) -> SocketAddr {
        self.sem_addr
    }

    /// The configuration in effect, every seed filled in (record this one).
    pub fn config(&self) -> &SimConfig {
        &self.config
    }

    /// The simulated stage: true pose, counters, faults fired.
    pub fn stage(&self) -> &Arc<SimStage> {
        &self.stage
    }

    /// The whole stage controller state now.
    pub fn stage_snapshot(&self) -> StageSnapshot {
        self.stage.snapshot()
    }

    /// The stage as the SEM sees it.
    pub fn pose_source(&self) -> Arc<dyn PoseSource> {
        Arc::clone(&self.stage) as Arc<dyn PoseSource>
    }

    /// The SEM's store folder, when configured: what it stored, and its settings.
    pub fn folder(&self) -> Option<&Arc<FolderWriter>> {
        self.folder.as_ref().map(|(w, _)| w)
    }

    /// A line to ask the store folder for one micrograph now (the RemCon32 `FREC` / `MAC n`
    /// hook), when configured.
    pub fn store_requests(&self) -> Option<StoreRequests> {
        self.folder.as_ref().map(|(_, r)| r.clone())
    }

    /// The simulated SEM.
    pub fn sem(&self) -> &Arc<SimSem> {
        &self.sem
    }

    /// The specimen being imaged (with [`crate::render`]: correspondences,
    /// visible points, height maps of any view).
    pub fn scene(&self) -> &Arc<Scene> {
        self.sem.scene()
    }

    /// How frame number `n` was taken (view and metadata), if still remembered.
    pub fn frame(&self, n: u64) -> Option<FrameRecord> {
        self.sem.frame(n)
    }

    /// The true height map of frame `n` (µm on the frame's grid, NaN off the
    /// specimen), if still remembered.
    pub fn ground_truth(&self, n: u64) -> Option<Vec<f32>> {
        self.sem.ground_truth(n)
    }

    /// The number of the last frame scanned, if any.
    pub fn last_frame(&self) -> Option<u64> {
        self.sem.last_frame()
    }

    /// Where "store a micrograph now" requests from the stage link (RemCon32
    /// `FREC`, `MAC n`) go: set a hook on it (the watch-folder writer).
    pub fn store_trigger(&self) -> &Arc<StoreTrigger> {
        &self.store
    }

    /// The simulator's clock.
    pub fn clock(&self) -> &Arc<dyn Clock> {
        &self.clock
    }

    /// Stops every server and waits for their threads.
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for server in self.servers.drain(..) {
            server.join();
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        self.shutdown();
    }
}

#[cfg(test)]
mod tests {
    use std::io::{BufRead, BufReader, Read, Write};
    use std::net::TcpStream;
    use std::time::{Duration, Instant};

    use sdsem_protocol::sem::{Bits, FrameReply, GrabRequest, Reply, ReplyDecoder, Request, Role};

    use super::*;
    use crate::clock::ManualClock;
    use crate::config::StageSimConfig;
    use crate::scene::SceneKind;

    /// A simulator config with a small specimen (quick to build) and a
    /// 256×192 full-resolution frame of 0.25 µm pixels.
    fn small(seed: u64, time_scale: f64) -> SimConfig {
        let mut c = SimConfig {
            seed,
            time_scale,
            ..SimConfig::default()
        };
        c.sem.scene.kind = SceneKind::Grid;
        c.sem.scene.field_um = 80.0;
        c.sem.optics.width = 256;
        c.sem.optics.height = 192;
        c.sem.optics.pixel_size_um = 0.25;
        c
    }

    struct Gcs {
        stream: TcpStream,
        reader: BufReader<TcpStream>,
    }

    impl Gcs {
        fn connect(sim: &SimHandle) -> Self {
            let addr = sim.stage_endpoint().strip_prefix("tcp://").unwrap();
            let stream = TcpStream::connect(addr).unwrap();
            stream
                .set_read_timeout(Some(Duration::from_secs(10)))
                .unwrap();
            let reader = BufReader::new(stream.try_clone().unwrap());
            Self { stream, reader }
        }

        fn send(&mut self, line: &str) {
            self.stream.write_all(line.as_bytes()).unwrap();
        }

        fn ask(&mut self, line: &str) -> String {
            self.send(line);
            let mut out = String::new();
            self.reader.read_line(&mut out).unwrap();
            out
        }
    }

    struct SemLink {
        stream: TcpStream,
        decoder: ReplyDecoder,
    }

    impl SemLink {
        fn connect(sim: &SimHandle) -> Self {
            let stream = TcpStream::connect(sim.sem_addr()).unwrap();
            stream
                .set_read_timeout(Some(Duration::from_secs(30)))
                .unwrap();
            Self {
                stream,
                decoder: ReplyDecoder::new(),
            }
        }

        fn ask(&mut self, request: &Request) -> Reply {
            self.stream.write_all(&request.encode()).unwrap();
            let mut buf = vec![0u8; 65536];
            loop {
                if let Some(r) = self.decoder.next_reply().unwrap() {
                    return r;
                }
                let n = self.stream.read(&mut buf).unwrap();
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
                other => panic!("{other:?}"),
            }
        }
    }

    #[test]
    fn serves_gcs_over_tcp_and_stops() {
        let sim = Simulator::spawn(small(0, 0.001)).unwrap();
        let lines = sim.endpoint_lines();
        assert!(lines[0].starts_with("stage tcp://127.0.0.1:"), "{lines:?}");
        assert!(lines[1].starts_with("sem tcp://127.0.0.1:"), "{lines:?}");
        assert_eq!(sim.sem_endpoint(), format!("tcp://{}", sim.sem_addr()));
        let mut gcs = Gcs::connect(&sim);
        assert_eq!(gcs.ask("POS? T\n"), "T=0.000000\n");
        gcs.send("MOV T 2\n");
        // 2° at 1°/s is 2 ms of real time at this scale.
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(gcs.ask("ONT? T\n"), "T=1\n");
        assert_eq!(sim.stage().pose().tilt_deg, 2.0);
        assert_eq!(sim.stage_snapshot().commands, 3);
        let t = Instant::now();
        sim.stop();
        assert!(t.elapsed() < Duration::from_secs(3), "{:?}", t.elapsed());
    }

    #[test]
    fn the_sem_images_the_simulated_stage_where_it_is() {
        // A manual clock: time passes only when the test or a scan says so.
        let clock = Arc::new(ManualClock::with_time_scale(0.01));
        let sim = Simulator::spawn_with_clock(small(3, 0.01), clock.clone()).unwrap();
        let (mut gcs, mut sem) = (Gcs::connect(&sim), SemLink::connect(&sim));
        let before = sem.grab(64, 48, 1.0);
        assert_eq!(before.meta.tilt_deg, 0.0);
        gcs.send("MOV T 4 X 10\n");
        assert_eq!(gcs.ask("ERR?\n"), "0\n");
        clock.advance(2.0);
        // Mid-move: the frame shows the stage where it is at the start of the scan.
        let mid = sem.grab(64, 48, 1.0);
        let pos = gcs.ask("POS? T\n");
        assert!((mid.meta.tilt_deg - 2.0).abs() < 0.01, "{:?}", mid.meta);
        assert!(pos.starts_with("T=2.0"), "{pos}");
        clock.advance(10.0);
        assert_eq!(gcs.ask("ONT? T\n"), "T=1\n");
        let after = sem.grab(64, 48, 1.0);
        assert_eq!(
            (after.meta.tilt_deg, after.meta.stage_x_um),
            (4.0, 10.0),
            "the pose in the metadata is the stage's"
        );
        assert_ne!(after.data, before.data, "the image shows the new pose");
        // The handle sees the same frames, their views and ground truth.
        assert_eq!(sim.last_frame(), Some(after.meta.frame));
        let record = sim.frame(after.meta.frame).unwrap();
        assert_eq!(record.meta, after.meta);
        assert_eq!(record.view.tilt_deg, 4.0);
        let truth = sim.ground_truth(after.meta.frame).unwrap();
        assert_eq!(truth.len(), 64 * 48);
        assert!(truth.iter().any(|h| h.is_finite()));
        assert_eq!(sim.scene().params().kind, SceneKind::Grid);
        sim.stop();
    }

    #[test]
    fn scan_time_and_motion_time_follow_the_time_scale_exactly_on_a_manual_clock() {
        for time_scale in [1.0, 0.01] {
            let clock = Arc::new(ManualClock::with_time_scale(time_scale));
            let sim = Simulator::spawn_with_clock(small(1, time_scale), clock.clone()).unwrap();
            let mut sem = SemLink::connect(&sim);
            let mut gcs = Gcs::connect(&sim);
            gcs.send("MOV T 3\n");
            // The answer to ERR? proves the move was handled before the scan
            // advances the clock (the two links are served by different threads).
            assert_eq!(gcs.ask("ERR?\n"), "0\n");
            // 100 × 50 × 200 µs = 1 simulated second of scan, during which the stage moves 1°.
            let t0 = clock.now_s();
            let f = sem.grab(100, 50, 200.0);
            assert!((clock.now_s() - t0 - 1.0).abs() < 1e-9);
            let real_ns = f.meta.scan_end_unix_ns - f.meta.scan_start_unix_ns;
            let expect = 1e9 * time_scale;
            assert!(
                (real_ns as f64 - expect).abs() < 2.0,
                "scan of 1 simulated s at time_scale {time_scale}: {real_ns} ns"
            );
            assert_eq!(gcs.ask("POS? T\n"), "T=1.000000\n");
            sim.stop();
        }
    }

    #[test]
    fn time_scale_shortens_real_scans_and_moves_in_proportion() {
        // Real clocks: lower bounds are exact (a wait never ends early), the
        // comparison between scales is generous (10× apart).
        let measure = |time_scale: f64| {
            let sim = Simulator::spawn(small(1, time_scale)).unwrap();
            let mut sem = SemLink::connect(&sim);
            let mut gcs = Gcs::connect(&sim);
            // 64 × 64 × 1000 µs = 4.096 simulated seconds of scan.
            let t = Instant::now();
            sem.grab(64, 64, 1000.0);
            let scan = t.elapsed();
            // 4° at 1°/s + 0.2 s settling = 4.2 simulated seconds.
            let t = Instant::now();
            gcs.send("MOV T 4\n");
            while gcs.ask("ONT? T\n") != "T=1\n" {
                std::thread::sleep(Duration::from_millis(1));
            }
            let motion = t.elapsed();
            sim.stop();
            (scan, motion)
        };
        let (slow_scan, slow_motion) = measure(0.05);
        let (fast_scan, fast_motion) = measure(0.005);
        assert!(
            slow_scan >= Duration::from_secs_f64(4.096 * 0.05),
            "{slow_scan:?}"
        );
        assert!(
            fast_scan >= Duration::from_secs_f64(4.096 * 0.005),
            "{fast_scan:?}"
        );
        assert!(
            slow_motion >= Duration::from_secs_f64(4.2 * 0.05),
            "{slow_motion:?}"
        );
        assert!(
            fast_motion >= Duration::from_secs_f64(4.2 * 0.005),
            "{fast_motion:?}"
        );
        assert!(fast_scan < slow_scan, "{fast_scan:?} vs {slow_scan:?}");
        assert!(
            fast_motion < slow_motion,
            "{fast_motion:?} vs {slow_motion:?}"
        );
    }

    #[test]
    fn one_seed_gives_the_same_frames_and_faults_in_two_simulators() {
        let run = |seed: u64| {
            let mut config = small(seed, 1.0);
            config.stage.faults.ignore_move = crate::config::FaultTrigger::probability(0.5);
            let clock = Arc::new(ManualClock::new());
            let sim = Simulator::spawn_with_clock(config, clock.clone()).unwrap();
            let (mut gcs, mut sem) = (Gcs::connect(&sim), SemLink::connect(&sim));
            let mut frames = Vec::new();
            for k in 1..=4 {
                gcs.send(&format!("MOV T {k}\n"));
                assert_eq!(gcs.ask("ERR?\n"), "0\n");
                clock.advance(5.0);
                let f = sem.grab(48, 32, 2.0);
                frames.push((f.meta, f.data));
            }
            let faults = sim.stage_snapshot().faults;
            let resolved = sim.config().clone();
            sim.stop();
            (frames, faults, resolved)
        };
        let (a, fa, ca) = run(21);
        let (b, fb, cb) = run(21);
        let (c, _, cc) = run(22);
        assert_eq!(ca, cb);
        assert_eq!(fa, fb, "the same moves are ignored");
        assert_eq!(a, b, "the same frames, metadata and timestamps included");
        assert_ne!(ca.sem.scene.seed, cc.sem.scene.seed);
        assert_ne!(
            a.iter().map(|f| &f.1).collect::<Vec<_>>(),
            c.iter().map(|f| &f.1).collect::<Vec<_>>(),
            "another seed, another specimen"
        );
    }

    #[test]
    fn pty_endpoint_serves_its_slave_path() {
        let sim = Simulator::spawn(SimConfig {
            stage: StageSimConfig {
                endpoint: SimEndpoint::Pty,
                ..StageSimConfig::default()
            },
            ..small(0, 1.0)
        })
        .unwrap();
        let path = sim.stage_endpoint().to_owned();
        assert!(path.starts_with("/dev/"), "{path}");
        let mut port = serialport::new(&path, 115_200)
            .timeout(Duration::from_secs(5))
            .open_native()
            .unwrap();
        port.write_all(b"ERR?\n").unwrap();
        let mut reader = BufReader::new(port);
        let mut out = String::new();
        reader.read_line(&mut out).unwrap();
        assert_eq!(out, "0\n");
        drop(reader);
        // The path can be opened again by the next client.
        let port = serialport::new(&path, 115_200).open_native();
        assert!(port.is_ok(), "{port:?}");
        drop(port);
        sim.stop();
    }

    #[test]
    fn invalid_config_is_refused_before_anything_starts() {
        let mut c = SimConfig::default();
        c.stage.settle_s = -1.0;
        assert!(matches!(Simulator::spawn(c), Err(SimError::Config { .. })));
        let mut c = small(0, 1.0);
        c.sem.scene.field_um = 1.0;
        let e = Simulator::spawn(c).unwrap_err();
        assert!(matches!(e, SimError::Scene(_)), "{e}");
    }

    #[test]
    fn a_busy_port_names_the_link() {
        let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let mut c = small(0, 1.0);
        c.sem.endpoint = SimEndpoint::Tcp(taken.local_addr().unwrap());
        let e = Simulator::spawn(c).unwrap_err().to_string();
        assert!(e.contains("SEM imaging") && e.contains("port 0"), "{e}");
    }
}
