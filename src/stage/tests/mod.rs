//! Stage driver tests.
//!
//! - `fake`: against a scripted controller and against the simulator's pure
//!   device model, both over `tokio::io::duplex` on tokio's paused clock (no real
//!   sleeps: timeouts and polls advance virtual time).
//! - `sim`: against the real simulator over TCP and a pty, in-process.

mod fake;
mod sim;

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use sdsem_protocol::gcs::{AxisId, CommandFramer, Incoming, escape_bytes};
use sdsem_sim::StageSimConfig;
use sdsem_sim::stage_model::StageModel;
use tokio::io::{AsyncReadExt, AsyncWriteExt, DuplexStream, duplex};
use tokio::time::Instant;

use super::config::StageConfig;

/// The driver configured for the simulator's axis names.
fn driver_config() -> StageConfig {
    StageConfig {
        endpoint: "tcp://127.0.0.1:1".into(),
        axis_x: AxisId::new("X").expect("axis"),
        axis_y: AxisId::new("Y").expect("axis"),
        axis_tilt: AxisId::new("T").expect("axis"),
        ..StageConfig::default()
    }
}

/// What a scripted controller does with one command.
enum Act {
    /// Answer these bytes now.
    Reply(Vec<u8>),
    /// Answer these bytes after a delay (reading nothing meanwhile).
    Later(Duration, Vec<u8>),
    /// Close the connection.
    Close,
}

fn reply(s: &str) -> Vec<Act> {
    vec![Act::Reply(s.as_bytes().to_vec())]
}

/// Every command the fake received, printable.
type Log = Arc<Mutex<Vec<String>>>;

fn lines(log: &Log) -> Vec<String> {
    log.lock().unwrap_or_else(PoisonError::into_inner).clone()
}

fn printable(incoming: &Incoming) -> String {
    match incoming {
        Incoming::Line(l) => escape_bytes(l),
        Incoming::Single(b) => format!("#{b}"),
    }
}

/// A controller played by a closure over the received command text.
fn scripted(mut script: impl FnMut(&str) -> Vec<Act> + Send + 'static) -> (DuplexStream, Log) {
    let (client, mut server) = duplex(4096);
    let log: Log = Arc::default();
    let seen = Arc::clone(&log);
    tokio::spawn(async move {
        let mut framer = CommandFramer::new();
        let mut buf = [0u8; 256];
        loop {
            let n = match server.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            for &b in &buf[..n] {
                let Some(Ok(incoming)) = framer.push(b) else {
                    continue;
                };
                let text = printable(&incoming);
                seen.lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .push(text.clone());
                for act in script(&text) {
                    match act {
                        Act::Reply(bytes) => {
                            if server.write_all(&bytes).await.is_err() {
                                return;
                            }
                        }
                        Act::Later(d, bytes) => {
                            tokio::time::sleep(d).await;
                            if server.write_all(&bytes).await.is_err() {
                                return;
                            }
                        }
                        Act::Close => return,
                    }
                }
            }
        }
    });
    (client, log)
}

/// The simulator's device model behind a duplex stream, on tokio's clock.
fn modelled(config: StageSimConfig) -> (DuplexStream, Arc<Mutex<StageModel>>, Instant, Log) {
    config.validate().expect("valid simulator config");
    let model = Arc::new(Mutex::new(StageModel::new(&config, 1)));
    let shared = Arc::clone(&model);
    let start = Instant::now();
    let (client, mut server) = duplex(4096);
    let log: Log = Arc::default();
    let seen = Arc::clone(&log);
    tokio::spawn(async move {
        let mut framer = CommandFramer::new();
        let mut buf = [0u8; 256];
        loop {
            let n = match server.read(&mut buf).await {
                Ok(0) | Err(_) => return,
                Ok(n) => n,
            };
            for &b in &buf[..n] {
                let Some(incoming) = framer.push(b) else {
                    continue;
                };
                if let Ok(i) = &incoming {
                    seen.lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .push(printable(i));
                }
                let now = start.elapsed().as_secs_f64();
                let response = shared
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .handle(now, incoming);
                if !response.delay.is_zero() {
                    tokio::time::sleep(response.delay).await;
                }
                if let Some(bytes) = response.reply
                    && server.write_all(&bytes).await.is_err()
                {
                    return;
                }
                if response.disconnect {
                    return;
                }
            }
        }
    });
    (client, model, start, log)
}

/// The model's snapshot at the current (paused) tokio time.
fn snapshot(
    model: &Arc<Mutex<StageModel>>,
    start: Instant,
) -> sdsem_sim::stage_model::StageSnapshot {
    model
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .snapshot(start.elapsed().as_secs_f64())
}

/// The lead runs the driver inside spawned tasks: its futures must be `Send`.
/// (Checked by the compiler; the function is never called.)
#[allow(dead_code)]
fn driver_futures_are_send(d: &mut super::StageDriver) {
    fn send<T: Send>(_: &T) {}
    send(&d.move_tilt(1.0));
    send(&d.move_xy(1.0, 2.0));
    send(&d.position());
    send(&d.stop());
    send(&super::StageDriver::open(
        StageConfig::default(),
        Arc::new(super::NoopObserver),
    ));
}
