//! The thin I/O around the stage model: a TCP listener or a pseudo-terminal,
//! each served on std threads. Bytes in → a dialect's [`Session`] (PI GCS:
//! [`CommandFramer`] → [`SimStage`]) → bytes out.

use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use sdsem_protocol::gcs::CommandFramer;
use serialport::SerialPort;
use tracing::{debug, info, warn};

use crate::SimError;
use crate::simulator::ServiceServer;
use crate::stage::SimStage;
use crate::stage_model::Response;

/// How often blocked reads look at the stop flag.
const STOP_POLL: Duration = Duration::from_millis(50);

/// How a served connection ended.
#[derive(Debug, PartialEq, Eq)]
enum LinkEnd {
    /// The peer closed it.
    PeerClosed,
    /// The disconnect fault closed it.
    Fault,
    /// The simulator is stopping.
    Stopped,
}

/// One connection's side of a stage dialect: bytes in, responses out.
pub(crate) trait Session: Send {
    /// Feeds one byte; a complete command gives the response to send.
    fn push(&mut self, byte: u8) -> Option<Response>;
}

/// Makes the session of each new connection.
pub(crate) type SessionFactory = Arc<dyn Fn() -> Box<dyn Session> + Send + Sync>;

/// PI GCS: the command framer in front of the shared stage.
struct GcsSession {
    framer: CommandFramer,
    stage: Arc<SimStage>,
}

impl Session for GcsSession {
    fn push(&mut self, byte: u8) -> Option<Response> {
        self.framer
            .push(byte)
            .map(|incoming| self.stage.handle(incoming))
    }
}

/// Sessions speaking PI GCS to `stage`.
pub(crate) fn gcs_sessions(stage: Arc<SimStage>) -> SessionFactory {
    Arc::new(move || {
        Box::new(GcsSession {
            framer: CommandFramer::new(),
            stage: Arc::clone(&stage),
        })
    })
}

/// Serves one byte stream until the peer leaves, a fault closes it or `stop` is set.
/// Reads must time out (at about [`STOP_POLL`]) so that `stop` is noticed.
fn serve<S: Read + Write>(
    stream: &mut S,
    session: &mut dyn Session,
    stop: &AtomicBool,
) -> io::Result<LinkEnd> {
    let mut buf = [0u8; 512];
    loop {
        if stop.load(Ordering::Relaxed) {
            return Ok(LinkEnd::Stopped);
        }
        let n = match stream.read(&mut buf) {
            Ok(0) => return Ok(LinkEnd::PeerClosed),
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                ) =>
            {
                continue;
            }
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        for &byte in &buf[..n] {
            let Some(response) = session.push(byte) else {
                continue;
            };
            if !response.delay.is_zero() && sleep_unless_stopped(response.delay, stop) {
                return Ok(LinkEnd::Stopped);
            }
            if let Some(reply) = &response.reply {
                stream.write_all(reply)?;
                stream.flush()?;
            }
            if response.disconnect {
                return Ok(LinkEnd::Fault);
            }
        }
    }
}

/// Sleeps `d` in small steps; true if `stop` was set meanwhile.
fn sleep_unless_stopped(d: Duration, stop: &AtomicBool) -> bool {
    let end = Instant::now() + d;
    loop {
        if stop.load(Ordering::Relaxed) {
            return true;
        }
        let now = Instant::now();
        if now >= end {
            return false;
        }
        thread::sleep((end - now).min(STOP_POLL));
    }
}

/// Listens on `addr` (port 0 picks one) and serves every connection on its own thread.
pub(crate) fn serve_tcp(
    addr: SocketAddr,
    sessions: SessionFactory,
    stop: Arc<AtomicBool>,
) -> Result<ServiceServer, SimError> {
    let bind = |error| SimError::Bind {
        service: "stage",
        addr,
        error,
    };
    let listener = TcpListener::bind(addr).map_err(bind)?;
    let local = listener.local_addr().map_err(bind)?;
    let wake = if local.ip().is_unspecified() {
        SocketAddr::from(([127, 0, 0, 1], local.port()))
    } else {
        local
    };
    let thread = thread::Builder::new()
        .name("stage-tcp".into())
        .spawn(move || accept_loop(&listener, &sessions, &stop))
        .map_err(|error| SimError::Thread { error })?;
    info!(%local, "stage controller listening on TCP");
    Ok(ServiceServer {
        endpoint: format!("tcp://{local}"),
        thread,
        wake: Some(wake),
    })
}

fn accept_loop(listener: &TcpListener, sessions: &SessionFactory, stop: &Arc<AtomicBool>) {
    let mut connections: Vec<JoinHandle<()>> = Vec::new();
    for conn in listener.incoming() {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        connections.retain(|h| !h.is_finished());
        let mut stream = match conn {
            Ok(s) => s,
            Err(e) => {
                warn!(error = %e, "stage link: accept failed");
                continue;
            }
        };
        let peer = stream.peer_addr().ok();
        if let Err(e) = stream
            .set_read_timeout(Some(STOP_POLL))
            .and_then(|()| stream.set_nodelay(true))
        {
            warn!(error = %e, "stage link: cannot configure the connection");
            continue;
        }
        let (mut session, stop) = (sessions(), Arc::clone(stop));
        let spawned = thread::Builder::new()
            .name("stage-conn".into())
            .spawn(move || {
                debug!(?peer, "stage link: client connected");
                match serve(&mut stream, session.as_mut(), &stop) {
                    Ok(LinkEnd::Fault) => {
                        info!(
                            ?peer,
                            "stage link: closing the connection (disconnect fault)"
                        );
                        let _ = stream.shutdown(std::net::Shutdown::Both);
                    }
                    Ok(end) => debug!(?peer, ?end, "stage link: connection ended"),
                    Err(e) => debug!(?peer, error = %e, "stage link: connection lost"),
                }
            });
        match spawned {
            Ok(h) => connections.push(h),
            Err(e) => warn!(error = %e, "stage link: cannot start a connection thread"),
        }
    }
    for h in connections {
        let _ = h.join();
    }
}

/// Opens a pseudo-terminal pair and serves its master side; clients open the
/// slave path like a serial port (the baud rate does nothing on a pty).
///
/// The simulator keeps the slave open too, so that the master never reads EIO
/// between clients. It takes no lock on it (neither `TIOCEXCL` nor `flock`), so a
/// client can open the path in serialport's default exclusive mode; a shared
/// `set_exclusive(false)` here would make that open fail (DESIGN §8). The
/// disconnect fault closes both sides: the pty disappears and clients read an
/// error, as with an unplugged USB adapter.
pub(crate) fn serve_pty(
    sessions: &SessionFactory,
    stop: Arc<AtomicBool>,
) -> Result<ServiceServer, SimError> {
    let pty_err = |e: serialport::Error| SimError::Pty {
        cause: e.to_string(),
    };
    let (mut master, slave) = serialport::TTYPort::pair().map_err(pty_err)?;
    master.set_timeout(STOP_POLL).map_err(pty_err)?;
    let path = slave.name().ok_or_else(|| SimError::Pty {
        cause: "the pseudo-terminal has no slave device name".into(),
    })?;
    let endpoint = path.clone();
    let mut session = sessions();
    let thread = thread::Builder::new()
        .name("stage-pty".into())
        .spawn(move || {
            match serve(&mut master, session.as_mut(), &stop) {
                Ok(LinkEnd::Fault) => {
                    info!(%path, "stage link: closing the pty (disconnect fault)")
                }
                Ok(end) => debug!(%path, ?end, "stage pty ended"),
                Err(e) => warn!(%path, error = %e, "stage pty failed"),
            }
            drop(slave);
        })
        .map_err(|error| SimError::Thread { error })?;
    info!(path = %endpoint, "stage controller on pseudo-terminal");
    Ok(ServiceServer {
        endpoint,
        thread,
        wake: None,
    })
}
