//! Starting and stopping the simulated instruments, in-process or from `main`.

use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use tracing::{info, warn};

use crate::SimError;
use crate::clock::{Clock, ScaledClock};
use crate::config::{SimConfig, SimEndpoint};
use crate::pose::PoseSource;
use crate::stage::SimStage;
use crate::stage_link::{serve_pty, serve_tcp};

/// One endpoint the simulator serves, e.g. `stage` at `tcp://127.0.0.1:40123`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ServiceEndpoint {
    /// Which instrument: `stage` (the SEM imaging link adds `sem`).
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
    /// Connect here to unblock `accept` (TCP servers).
    pub wake: Option<SocketAddr>,
}

impl ServiceServer {
    /// Waits for the server thread after the stop flag was set.
    fn join(self) {
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
    /// Validates `config` and starts every simulated instrument on background
    /// threads, on a clock scaled by `config.time_scale`.
    pub fn spawn(config: SimConfig) -> Result<SimHandle, SimError> {
        config.validate()?;
        let clock: Arc<dyn Clock> = Arc::new(ScaledClock::new(config.time_scale));
        Self::spawn_with_clock(config, clock)
    }

    /// Like [`Simulator::spawn`], on a given clock (tests).
    pub fn spawn_with_clock(
        config: SimConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<SimHandle, SimError> {
        config.validate()?;
        let stop = Arc::new(AtomicBool::new(false));
        let stage = Arc::new(SimStage::new(
            &config.stage,
            config.seed,
            Arc::clone(&clock),
        ));
        let mut handle = SimHandle {
            endpoints: Vec::new(),
            servers: Vec::new(),
            stage: Arc::clone(&stage),
            clock,
            stop: Arc::clone(&stop),
        };
        let server = match &config.stage.endpoint {
            SimEndpoint::Tcp(addr) => serve_tcp(*addr, stage, Arc::clone(&stop))?,
            SimEndpoint::Pty => serve_pty(stage, Arc::clone(&stop))?,
        };
        handle.add("stage", server);
        // Another instrument starts here the same way: a server function taking
        // `handle.pose_source()`, `handle.clock()` and the stop flag, returning a
        // `ServiceServer`, then `handle.add("sem", server)`.
        info!(
            seed = config.seed,
            time_scale = config.time_scale,
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
    clock: Arc<dyn Clock>,
    stop: Arc<AtomicBool>,
}

impl SimHandle {
    fn add(&mut self, service: &'static str, server: ServiceServer) {
        self.endpoints.push(ServiceEndpoint {
            service,
            address: server.endpoint.clone(),
        });
        self.servers.push(server);
    }

    /// Every endpoint served.
    pub fn endpoints(&self) -> &[ServiceEndpoint] {
        &self.endpoints
    }

    /// The stage controller's endpoint, as `sdsem`'s `stage.endpoint` accepts it.
    pub fn stage_endpoint(&self) -> &str {
        self.endpoints
            .iter()
            .find(|e| e.service == "stage")
            .map_or("", |e| e.address.as_str())
    }

    /// One machine-readable line per endpoint: `stage tcp://127.0.0.1:40123`.
    pub fn endpoint_lines(&self) -> Vec<String> {
        self.endpoints
            .iter()
            .map(|e| format!("{} {}", e.service, e.address))
            .collect()
    }

    /// Read access to the simulated stage: true pose, counters, faults fired.
    pub fn stage(&self) -> &Arc<SimStage> {
        &self.stage
    }

    /// The stage as the SEM renderer sees it.
    pub fn pose_source(&self) -> Arc<dyn PoseSource> {
        Arc::clone(&self.stage) as Arc<dyn PoseSource>
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
    use std::io::{BufRead, BufReader, Write};
    use std::net::TcpStream;
    use std::time::Duration;

    use super::*;
    use crate::config::StageSimConfig;

    fn roundtrip(stream: &mut TcpStream, reader: &mut BufReader<TcpStream>, line: &str) -> String {
        stream.write_all(line.as_bytes()).unwrap();
        let mut out = String::new();
        reader.read_line(&mut out).unwrap();
        out
    }

    #[test]
    fn serves_gcs_over_tcp_and_stops() {
        let sim = Simulator::spawn(SimConfig {
            time_scale: 0.001,
            ..SimConfig::default()
        })
        .unwrap();
        let addr = sim
            .stage_endpoint()
            .strip_prefix("tcp://")
            .unwrap()
            .to_owned();
        assert!(sim.endpoint_lines()[0].starts_with("stage tcp://127.0.0.1:"));
        let mut stream = TcpStream::connect(&addr).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(5)))
            .unwrap();
        let mut reader = BufReader::new(stream.try_clone().unwrap());
        assert_eq!(
            roundtrip(&mut stream, &mut reader, "POS? T\n"),
            "T=0.000000\n"
        );
        stream.write_all(b"MOV T 2\n").unwrap();
        // 2° at 1°/s is 2 ms of real time at this scale.
        std::thread::sleep(Duration::from_millis(20));
        assert_eq!(roundtrip(&mut stream, &mut reader, "ONT? T\n"), "T=1\n");
        assert_eq!(sim.stage().pose().tilt_deg, 2.0);
        assert_eq!(sim.stage().command_count(), 3);
        sim.stop();
    }

    #[test]
    fn pty_endpoint_serves_its_slave_path() {
        let sim = Simulator::spawn(SimConfig {
            stage: StageSimConfig {
                endpoint: SimEndpoint::Pty,
                ..StageSimConfig::default()
            },
            ..SimConfig::default()
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
    }
}
