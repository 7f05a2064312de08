//! The bytes of the SharkSEM dialect: a control listener and a data listener,
//! one thread per client session, one thread per scan streaming `ScData`.

use std::io::{self, Read, Write};
use std::net::{IpAddr, Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use sdsem_protocol::sem::{Bits, GrabRequest, Role};
use sdsem_protocol::sharksem::{DataChunk, Flags, FrameError, MessageFramer, Request, Response};
use tracing::{debug, info, warn};

use super::config::SharkSemSimConfig;
use super::device::{ChunkFate, ScanJob, SharkSemDevice};
use crate::SimError;
use crate::config::SimEndpoint;
use crate::render;
use crate::simulator::ServiceServer;

/// How often blocked reads look at the stop flag.
const STOP_POLL: Duration = Duration::from_millis(50);
/// How long a scan waits for the data connection of its client to be paired, real time.
const PAIRING_GRACE: Duration = Duration::from_millis(500);
/// Attempts at finding a free control port whose successor is free too.
const BIND_ATTEMPTS: usize = 50;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// One client: its control connection, the data port it registered and its data connection.
struct Client {
    peer_ip: IpAddr,
    control: TcpStream,
    registered: Mutex<Option<u16>>,
    data: Mutex<Option<TcpStream>>,
}

impl Client {
    /// Closes both connections (the data one first, as clients do).
    fn close(&self) {
        if let Some(d) = lock(&self.data).take() {
            let _ = d.shutdown(Shutdown::Both);
        }
        let _ = self.control.shutdown(Shutdown::Both);
    }
}

struct Server {
    device: Arc<SharkSemDevice>,
    stop: Arc<AtomicBool>,
    clients: Mutex<Vec<Arc<Client>>>,
    next_scan: AtomicU64,
}

/// Binds the control and data listeners of `cfg` and serves them until `stop`.
pub(crate) fn serve(
    cfg: &SharkSemSimConfig,
    device: Arc<SharkSemDevice>,
    stop: Arc<AtomicBool>,
) -> Result<(ServiceServer, ServiceServer), SimError> {
    let SimEndpoint::Tcp(addr) = cfg.endpoint else {
        return Err(SimError::Config {
            field: "sharksem.endpoint",
            reason: "SharkSEM is TCP only".into(),
        });
    };
    let (control, data) = bind_pair(addr, cfg.data_port)?;
    let server = Arc::new(Server {
        device,
        stop,
        clients: Mutex::new(Vec::new()),
        next_scan: AtomicU64::new(0),
    });
    let spawn = |name: &str, listener: TcpListener, data_side: bool| {
        let local = listener.local_addr().map_err(|error| SimError::Listener {
            service: "SharkSEM",
            error,
        })?;
        let server = Arc::clone(&server);
        let thread = thread::Builder::new()
            .name(name.to_owned())
            .spawn(move || {
                if data_side {
                    accept_data(&listener, &server);
                } else {
                    accept_control(&listener, &server);
                }
            })
            .map_err(|error| SimError::Thread { error })?;
        let wake = if local.ip().is_unspecified() {
            SocketAddr::new(IpAddr::from([127, 0, 0, 1]), local.port())
        } else {
            local
        };
        Ok::<_, SimError>(ServiceServer {
            endpoint: format!("tcp://{local}"),
            thread,
            wake: Some(wake),
        })
    };
    let c = spawn("sharksem-control", control, false)?;
    let d = spawn("sharksem-data", data, true)?;
    info!(control = %c.endpoint, data = %d.endpoint, "SharkSEM server listening");
    Ok((c, d))
}

/// The control listener at `addr` and the data listener at `data_port`, or
/// at control + 1 (port 0: a free control port whose successor is free).
fn bind_pair(
    addr: SocketAddr,
    data_port: Option<u16>,
) -> Result<(TcpListener, TcpListener), SimError> {
    let bind = |service, addr: SocketAddr| {
        TcpListener::bind(addr).map_err(|error| SimError::Bind {
            service,
            addr,
            error,
        })
    };
    let attempts = if addr.port() == 0 && data_port.is_none() {
        BIND_ATTEMPTS
    } else {
        1
    };
    let mut last = None;
    for _ in 0..attempts {
        let control = bind("SharkSEM control", addr)?;
        let port = control.local_addr().map_or(0, |a| a.port());
        let data_addr = SocketAddr::new(addr.ip(), data_port.unwrap_or(port.wrapping_add(1)));
        match bind("SharkSEM data", data_addr) {
            Ok(data) => return Ok((control, data)),
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| SimError::Config {
        field: "sharksem.endpoint",
        reason: "no port pair found".into(),
    }))
}

fn accept_control(listener: &TcpListener, server: &Arc<Server>) {
    let mut sessions: Vec<JoinHandle<()>> = Vec::new();
    for conn in listener.incoming() {
        if server.stop.load(Ordering::Relaxed) {
            break;
        }
        sessions.retain(|h| !h.is_finished());
        let stream = match conn {
            Ok(s) => s,
            Err(e) => {
                warn!(error = %e, "SharkSEM: accept failed");
                continue;
            }
        };
        let firewall = server.device.config().firewall_friendly;
        if firewall && !lock(&server.clients).is_empty() {
            info!("SharkSEM: firewall-friendly mode serves one client: connection refused");
            let _ = stream.shutdown(Shutdown::Both);
            continue;
        }
        let Ok(peer) = stream.peer_addr() else {
            continue;
        };
        let configured = stream
            .set_read_timeout(Some(STOP_POLL))
            .and_then(|()| stream.set_nodelay(true))
            .and_then(|()| stream.try_clone());
        let control = match configured {
            Ok(c) => c,
            Err(e) => {
                warn!(error = %e, "SharkSEM: cannot configure a connection");
                continue;
            }
        };
        let client = Arc::new(Client {
            peer_ip: peer.ip(),
            control,
            registered: Mutex::new(None),
            data: Mutex::new(None),
        });
        lock(&server.clients).push(Arc::clone(&client));
        let server = Arc::clone(server);
        let spawned = thread::Builder::new()
            .name("sharksem-session".into())
            .spawn(move || {
                debug!(%peer, "SharkSEM: client connected");
                let mut session = Session::new(&server, &client);
                let end = session.run(stream);
                // Closed first: a scan blocked writing to an unread data socket fails at once.
                client.close();
                drop(session);
                match end {
                    End::Unframeable(e) => {
                        info!(%peer, error = %e, "SharkSEM: closing an unframeable connection")
                    }
                    End::Io(e) => debug!(%peer, error = %e, "SharkSEM: connection lost"),
                    end => debug!(%peer, ?end, "SharkSEM: session ended"),
                }
                lock(&server.clients).retain(|c| !Arc::ptr_eq(c, &client));
            });
        match spawned {
            Ok(h) => sessions.push(h),
            Err(e) => warn!(error = %e, "SharkSEM: cannot start a session thread"),
        }
    }
    for h in sessions {
        let _ = h.join();
    }
}

/// Pairs a data connection with the client that registered its source port
/// (in firewall-friendly mode: with the one client); others are closed.
fn accept_data(listener: &TcpListener, server: &Server) {
    let stall = Duration::from_secs_f64(server.device.config().data_stall_s);
    for conn in listener.incoming() {
        if server.stop.load(Ordering::Relaxed) {
            return;
        }
        let Ok(stream) = conn else { continue };
        let Ok(peer) = stream.peer_addr() else {
            continue;
        };
        let firewall = server.device.config().firewall_friendly;
        let client = lock(&server.clients)
            .iter()
            .find(|c| {
                lock(&c.data).is_none()
                    && (firewall
                        || (c.peer_ip == peer.ip() && *lock(&c.registered) == Some(peer.port())))
            })
            .cloned();
        let Some(client) = client else {
            info!(%peer, "SharkSEM: data connection from an unregistered port closed");
            let _ = stream.shutdown(Shutdown::Both);
            continue;
        };
        if stream
            .set_write_timeout(Some(stall))
            .and_then(|()| stream.set_nodelay(true))
            .is_err()
        {
            continue;
        }
        debug!(%peer, "SharkSEM: data connection paired");
        *lock(&client.data) = Some(stream);
    }
}

/// How a session ended.
#[derive(Debug)]
enum End {
    PeerClosed,
    Stopped,
    Fault,
    Unframeable(FrameError),
    Io(io::Error),
}

struct Session<'a> {
    server: &'a Arc<Server>,
    client: &'a Arc<Client>,
    scan: Option<(Arc<AtomicBool>, JoinHandle<()>)>,
}

impl Drop for Session<'_> {
    fn drop(&mut self) {
        if let Some((cancel, thread)) = self.scan.take() {
            cancel.store(true, Ordering::Relaxed);
            let _ = thread.join();
        }
    }
}

impl<'a> Session<'a> {
    fn new(server: &'a Arc<Server>, client: &'a Arc<Client>) -> Self {
        Self {
            server,
            client,
            scan: None,
        }
    }

    fn run(&mut self, mut stream: TcpStream) -> End {
        let mut framer = MessageFramer::new();
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            if self.server.stop.load(Ordering::Relaxed) {
                return End::Stopped;
            }
            match stream.read(&mut buf) {
                Ok(0) => return End::PeerClosed,
                Ok(n) => framer.push(&buf[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        io::ErrorKind::WouldBlock | io::ErrorKind::TimedOut
                    ) => {}
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return End::Io(e),
            }
            while let Some(message) = framer.next_message() {
                let device = &self.server.device;
                let message = match message {
                    Ok(m) => m,
                    Err(e @ FrameError::BodyTooLarge { .. }) => return End::Unframeable(e),
                    Err(e) => {
                        // A malformed message is ignored silently, like a bad one.
                        let _ = device.admit();
                        device.ignore(&e, "malformed message");
                        continue;
                    }
                };
                let Some(disconnect) = device.admit() else {
                    continue;
                };
                if let Err(end) = self.serve(&mut stream, &message) {
                    return end;
                }
                if disconnect {
                    info!("SharkSEM: closing the client's connections (fault)");
                    device.count_disconnect();
                    return End::Fault;
                }
            }
        }
    }

    /// Executes one request and writes its response, if any.
    fn serve(
        &mut self,
        stream: &mut TcpStream,
        message: &sdsem_protocol::sharksem::Message,
    ) -> Result<(), End> {
        let device = &self.server.device;
        let h = &message.header;
        let request = match Request::decode(h.name.as_str(), &message.body) {
            Ok(r) => r,
            Err(e) => {
                device.ignore(&e, "not understood");
                return Ok(());
            }
        };
        if !device.wait_clear(h.flags, &self.server.stop) {
            return Err(End::Stopped);
        }
        let handled = device.handle(&request);
        if let Some(port) = handled.register_port {
            *lock(&self.client.registered) = Some(port);
        }
        if let Some(job) = handled.scan {
            self.start_scan(job);
        }
        let reply = handled.reply.or_else(|| {
            h.flags
                .contains(Flags::SEND_RESPONSE)
                .then_some(Response::Void)
        });
        if let Some(reply) = reply {
            let bytes = reply.encode(&h.name, h.id, h.queue);
            stream
                .write_all(&bytes)
                .and_then(|()| stream.flush())
                .map_err(End::Io)?;
        }
        Ok(())
    }

    fn start_scan(&mut self, job: ScanJob) {
        if let Some((cancel, thread)) = self.scan.take() {
            // Stopped or finished already (ScScanXY needs ScStopScan first).
            cancel.store(true, Ordering::Relaxed);
            let _ = thread.join();
        }
        let cancel = Arc::clone(&job.cancel);
        let server = Arc::clone(self.server);
        let client = Arc::clone(self.client);
        let n = server.next_scan.fetch_add(1, Ordering::Relaxed);
        let spawned = thread::Builder::new()
            .name(format!("sharksem-scan-{n}"))
            .spawn(move || stream_scan(&server, &client, &job));
        match spawned {
            Ok(t) => self.scan = Some((cancel, t)),
            Err(e) => warn!(error = %e, "SharkSEM: cannot start a scan thread"),
        }
    }
}

/// Scans `job` and streams its pixels as `ScData` chunks, one every
/// `chunk_interval_s` of simulated time, until the region is complete (once
/// for a single scan, again and again for a continuous one) or the scan is stopped.
fn stream_scan(server: &Server, client: &Client, job: &ScanJob) {
    let device = &server.device;
    let clock = Arc::clone(device.clock());
    let cfg = device.config();
    let s = job.scan;
    // Checked by ScScanXY: the region lies inside the window.
    let total = s.region_pixels().unwrap_or(0);
    let dwell_s = job.dwell_us * 1e-6;
    loop {
        let start_s = clock.now_s();
        let grab = GrabRequest {
            width: s.width,
            height: s.height,
            dwell_us: job.dwell_us,
            role: Role::Tracking,
            bits: Bits::Sixteen,
        };
        let (meta, pixels) = device.sem().begin_scan(&grab, Some(job.pixel_size_um));
        let region = crop(&pixels, &s);
        let wide = render::to_u16(&region);
        let narrow = render::to_u8(&region);
        let mut sent: u64 = 0;
        let mut k: u64 = 0;
        while sent < total {
            k += 1;
            #[allow(clippy::cast_precision_loss)]
            let at = start_s + k as f64 * cfg.chunk_interval_s;
            if !clock.sleep_until(at, &job.cancel) || job.cancel.load(Ordering::Relaxed) {
                return;
            }
            // Pixels scanned by then; the epsilon keeps 0.002 s / 2 µs at 1000, not 999.
            #[allow(
                clippy::cast_possible_truncation,
                clippy::cast_sign_loss,
                clippy::cast_precision_loss
            )]
            let upto =
                ((k as f64 * cfg.chunk_interval_s / dwell_s + 1e-6).floor() as u64).min(total);
            if upto == sent {
                continue;
            }
            let fate = device.next_chunk();
            for &(channel, bpp) in &job.channels {
                // Both bounds ≤ total, the region's pixel count in memory.
                let (a, b) = (sent as usize, upto as usize);
                let data = if bpp == 8 {
                    narrow[a..b].to_vec()
                } else {
                    wide[a..b].iter().flat_map(|p| p.to_le_bytes()).collect()
                };
                let chunk = DataChunk {
                    frame_id: s.frame_id,
                    channel,
                    index: u32::try_from(sent).unwrap_or(u32::MAX),
                    bpp: i32::from(bpp),
                    data,
                }
                .encode();
                let copies = match fate {
                    ChunkFate::Send => 1,
                    ChunkFate::Lose => 0,
                    ChunkFate::SendTwice => 2,
                };
                for _ in 0..copies {
                    if let Err(e) = send_data(client, &chunk) {
                        warn!(error = %e, "SharkSEM: the client does not read its data socket: dropping it");
                        device.count_disconnect();
                        client.close();
                        return;
                    }
                }
            }
            sent = upto;
        }
        let _ = device.sem().end_scan(meta.frame);
        if s.single != 0 {
            device.scan_finished(&job.cancel);
            return;
        }
    }
}

/// Writes to the client's data connection; without one the data is lost, as on
/// the real server. A connection the client has just opened may still be
/// waiting in the data listener's backlog: it gets [`PAIRING_GRACE`] to be paired.
fn send_data(client: &Client, bytes: &[u8]) -> io::Result<()> {
    let give_up = Instant::now() + PAIRING_GRACE;
    loop {
        let mut data = lock(&client.data);
        if let Some(stream) = data.as_mut() {
            return stream.write_all(bytes);
        }
        drop(data);
        if Instant::now() >= give_up {
            return Ok(());
        }
        thread::sleep(Duration::from_millis(2));
    }
}

/// The visible region of a rendered window, row-major.
fn crop(pixels: &[f32], s: &sdsem_protocol::sharksem::ScanXY) -> Vec<f32> {
    let w = s.width as usize;
    let mut out = Vec::new();
    for y in s.top..=s.bottom {
        let row = y as usize * w;
        out.extend_from_slice(&pixels[row + s.left as usize..=row + s.right as usize]);
    }
    out
}
