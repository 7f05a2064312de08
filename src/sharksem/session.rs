//! One SharkSEM session: the control connection, the data channel and what the
//! instrument said about itself. The one owner of both sockets; the stage and
//! imaging sides share it through a [`super::SharkLink`].
//!
//! - Set-up as the manual describes [TS-PDF "Session Management"; TS-PY
//!   `Connect`]: connect the control socket, `TcpGetVersion`, bind the data
//!   socket to a local port on the control connection's interface,
//!   `TcpRegDataPort(port)` (reply 0), connect the data socket *from* that port
//!   to the data port (control + 1 unless configured), then read the software
//!   version, serial number and model where the protocol version has them.
//! - Every request carries a fresh id, which the server copies into its
//!   response: a late response to a request that timed out is recognised and
//!   discarded, never taken for the answer to the next one.
//! - Void functions answer nothing (no send-response flag, as TESCAN's client
//!   does): a setting is verified by reading it back, by the caller.
//! - After a broken connection the next request sets the session up again.
//! - Every exchange goes to the observer (`/stage/io`) decoded: the function
//!   with its arguments, the response's values, round-trip time and outcome;
//!   image data as one record per frame.
//! - The data socket is read during scans and drained before each one, so
//!   chunks still in flight from a stopped scan never block the server.

use std::fmt;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use sdsem_protocol::sharksem::{
    Flags, FrameAssembler, FrameError, Message, MessageFramer, Progress, Request, Response, Version,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};
use tokio::time::Instant;
use tracing::{debug, info, warn};

use super::error::SharkError;
use crate::stage::observer::wall_ns;
use crate::stage::{IoOutcome, StageIo, StageObserver};

/// Where and how patiently to talk to the SEM.
#[derive(Clone, Debug, PartialEq)]
pub struct SessionConfig {
    /// `tcp://HOST:PORT` (or `HOST:PORT`) of the control port.
    pub endpoint: String,
    /// The data port; none: control port + 1.
    pub data_port: Option<u16>,
    /// Opening each connection.
    pub connect_timeout: Duration,
    /// Waiting for a response (requests with wait flags get more from their caller).
    pub reply_timeout: Duration,
    /// The configuration key of `reply_timeout`, for messages (`imaging.timeout_ms`).
    pub timeout_key: &'static str,
}

impl SessionConfig {
    /// `HOST:PORT` of the control port.
    ///
    /// # Errors
    /// [`SharkError::Config`] when the endpoint is not `[tcp://]HOST:PORT`.
    pub fn address(&self) -> Result<&str, SharkError> {
        let e = self.endpoint.trim();
        let addr = e.strip_prefix("tcp://").unwrap_or(e);
        let ok = addr
            .rsplit_once(':')
            .is_some_and(|(host, port)| !host.is_empty() && port.parse::<u16>().is_ok());
        if ok {
            Ok(addr)
        } else {
            Err(SharkError::Config {
                field: "endpoint",
                reason: format!("{e:?}: write tcp://HOST:PORT, e.g. tcp://192.168.1.20:8300"),
            })
        }
    }
}

/// What the instrument said about itself at set-up.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct InstrumentInfo {
    /// `TcpGetVersion`, as sent.
    pub protocol: String,
    pub version: Version,
    /// `TcpGetSWVersion` (2.0.9+).
    pub sw_version: Option<String>,
    /// `TcpGetDevice`: the serial number (2.0.3+).
    pub device: Option<String>,
    /// `TcpGetModel` (3.2.20+).
    pub model: Option<String>,
}

impl fmt::Display for InstrumentInfo {
    /// `TESCAN SharkSEM 2.0.25, software 4.2.1, device VG1234, model VEGA`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "TESCAN SharkSEM {}", self.protocol)?;
        for (label, v) in [
            ("software", &self.sw_version),
            ("device", &self.device),
            ("model", &self.model),
        ] {
            if let Some(v) = v {
                write!(f, ", {label} {v}")?;
            }
        }
        Ok(())
    }
}

struct DataChannel {
    stream: TcpStream,
    framer: MessageFramer,
}

struct Connection {
    // Declared first, dropped first: the manual closes the data socket before the control one.
    data: Option<DataChannel>,
    control: TcpStream,
    framer: MessageFramer,
    /// A request was cut in the middle of its bytes: the server is out of step.
    torn: bool,
}

/// Read buffer size: a 50 ms `ScData` chunk of 16-bit pixels at 100 ns dwell is 1 MB.
const READ_CHUNK: usize = 256 * 1024;

/// One SharkSEM session (module docs).
pub struct SharkSession {
    config: SessionConfig,
    observer: Arc<dyn StageObserver>,
    conn: Option<Connection>,
    info: InstrumentInfo,
    generation: u64,
    seq: u64,
    next_id: u32,
    next_frame: u32,
    buf: Vec<u8>,
}

impl fmt::Debug for SharkSession {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("SharkSession")
            .field("endpoint", &self.config.endpoint)
            .field("connected", &self.conn.is_some())
            .field("info", &self.info)
            .finish_non_exhaustive()
    }
}

/// The request as `/stage/io` records it, wait flags appended.
fn describe(request: &Request, flags: Flags) -> String {
    if flags == Flags::NONE {
        request.to_string()
    } else {
        format!("{request} [{flags}]")
    }
}

fn nanos(d: Duration) -> u64 {
    u64::try_from(d.as_nanos()).unwrap_or(u64::MAX)
}

impl SharkSession {
    /// Connects and sets the session up (module docs), reporting every exchange to `observer`.
    ///
    /// # Errors
    /// [`SharkError`] naming the step that failed and the remedy.
    pub async fn connect(
        config: SessionConfig,
        observer: Arc<dyn StageObserver>,
    ) -> Result<Self, SharkError> {
        config.address()?;
        let mut s = Self {
            config,
            observer,
            conn: None,
            info: InstrumentInfo::default(),
            generation: 0,
            seq: 0,
            next_id: 0,
            next_frame: 0,
            buf: vec![0; READ_CHUNK],
        };
        s.open().await?;
        Ok(s)
    }

    /// The settings in use.
    #[must_use]
    pub fn config(&self) -> &SessionConfig {
        &self.config
    }

    /// What the instrument said at the last set-up.
    #[must_use]
    pub fn info(&self) -> &InstrumentInfo {
        &self.info
    }

    /// The protocol version of the server.
    #[must_use]
    pub fn version(&self) -> Version {
        self.info.version
    }

    /// Counts set-ups: a change means the connection was made afresh.
    #[must_use]
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// A new frame id for `ScScanXY` (never 0).
    pub fn next_frame_id(&mut self) -> u32 {
        self.next_frame = self.next_frame.wrapping_add(1).max(1);
        self.next_frame
    }

    /// Sets the session up on fresh connections.
    async fn open(&mut self) -> Result<(), SharkError> {
        self.conn = None;
        let endpoint = self.config.endpoint.clone();
        let addr = self.config.address()?.to_owned();
        let connect_error = |cause: String| SharkError::Connect {
            endpoint: endpoint.clone(),
            cause,
        };
        let control = tokio::time::timeout(self.config.connect_timeout, TcpStream::connect(&addr))
            .await
            .map_err(|_| {
                connect_error(format!(
                    "no connection within {:?}",
                    self.config.connect_timeout
                ))
            })?
            .map_err(|e| connect_error(e.to_string()))?;
        let _ = control.set_nodelay(true);
        let (local, peer) = match (control.local_addr(), control.peer_addr()) {
            (Ok(l), Ok(p)) => (l, p),
            (Err(e), _) | (_, Err(e)) => return Err(connect_error(e.to_string())),
        };
        self.conn = Some(Connection {
            data: None,
            control,
            framer: MessageFramer::new(),
            torn: false,
        });
        let wait = self.config.reply_timeout;
        let protocol = self.text(&Request::TcpGetVersion, wait).await?;
        let version = Version::parse(&protocol).ok_or_else(|| SharkError::BadReply {
            function: "TcpGetVersion()".into(),
            cause: sdsem_protocol::sharksem::BodyError::OutOfRange {
                what: "protocol version",
                value: protocol.clone(),
            },
        })?;
        self.info = InstrumentInfo {
            protocol,
            version,
            ..InstrumentInfo::default()
        };
        self.open_data(local, peer).await?;
        if version >= Version(2, 0, 3) {
            self.info.device = Some(self.text(&Request::TcpGetDevice, wait).await?);
        }
        if version >= Version::IS_BUSY {
            self.info.sw_version = Some(self.text(&Request::TcpGetSwVersion, wait).await?);
        }
        if version >= Version::MODEL {
            self.info.model = Some(self.text(&Request::TcpGetModel, wait).await?);
        }
        self.generation += 1;
        info!(instrument = %self.info, endpoint = %self.config.endpoint, "SharkSEM session set up");
        Ok(())
    }

    /// Binds the data socket beside the control connection, registers its
    /// port, and connects it from there to the data port.
    async fn open_data(&mut self, local: SocketAddr, peer: SocketAddr) -> Result<(), SharkError> {
        let data_addr = SocketAddr::new(
            peer.ip(),
            self.config.data_port.unwrap_or(peer.port().wrapping_add(1)),
        );
        let channel_error = |cause: String| SharkError::DataChannel {
            addr: data_addr.to_string(),
            cause,
        };
        let socket = if local.is_ipv4() {
            TcpSocket::new_v4()
        } else {
            TcpSocket::new_v6()
        }
        .map_err(|e| channel_error(e.to_string()))?;
        socket
            .bind(SocketAddr::new(local.ip(), 0))
            .map_err(|e| channel_error(format!("cannot bind a local port: {e}")))?;
        let port = socket
            .local_addr()
            .map_err(|e| channel_error(e.to_string()))?
            .port();
        let request = Request::TcpRegDataPort {
            port: u32::from(port),
        };
        match self
            .exchange(&request, Flags::NONE, self.config.reply_timeout)
            .await?
        {
            Response::Int(0) => {}
            other => {
                return Err(SharkError::Refused {
                    function: request.to_string(),
                    value: other.to_string(),
                    remedy: "the server does not accept the data port: check its remote-control settings",
                });
            }
        }
        let stream = tokio::time::timeout(self.config.connect_timeout, socket.connect(data_addr))
            .await
            .map_err(|_| {
                channel_error(format!(
                    "no connection within {:?}",
                    self.config.connect_timeout
                ))
            })?
            .map_err(|e| channel_error(e.to_string()))?;
        let _ = stream.set_nodelay(true);
        debug!(%data_addr, local_port = port, "SharkSEM data channel open");
        if let Some(conn) = self.conn.as_mut() {
            conn.data = Some(DataChannel {
                stream,
                framer: MessageFramer::new(),
            });
        }
        Ok(())
    }

    /// A text value during set-up (no reconnection inside the set-up itself).
    async fn text(&mut self, request: &Request, wait: Duration) -> Result<String, SharkError> {
        match self.exchange(request, Flags::NONE, wait).await? {
            Response::Text(t) => Ok(t),
            other => Err(self.unexpected(request, &other)),
        }
    }

    /// The error for a response of the wrong kind.
    #[must_use]
    pub fn unexpected(&self, request: &Request, response: &Response) -> SharkError {
        SharkError::Refused {
            function: request.to_string(),
            value: response.to_string(),
            remedy: "an answer of another kind than the function returns: is this a TESCAN SharkSEM server?",
        }
    }

    /// Sends `request` with `flags`; when the function returns a value (or
    /// send-response is set) waits up to `wait` for the response. Void
    /// functions give [`Response::Void`] as soon as they are written. Sets the
    /// session up again first if the connection was lost.
    ///
    /// # Errors
    /// [`SharkError::NoReply`], [`SharkError::Disconnected`], [`SharkError::BadReply`] and the set-up's errors.
    pub async fn call(
        &mut self,
        request: &Request,
        flags: Flags,
        wait: Duration,
    ) -> Result<Response, SharkError> {
        if self.conn.as_ref().is_none_or(|c| c.torn) {
            if self.conn.is_some() {
                warn!("SharkSEM: a request was cut off mid-message: setting the session up again");
            }
            self.open().await?;
        }
        self.exchange(request, flags, wait).await
    }

    async fn exchange(
        &mut self,
        request: &Request,
        flags: Flags,
        wait: Duration,
    ) -> Result<Response, SharkError> {
        self.next_id = self.next_id.wrapping_add(1).max(1);
        self.seq += 1;
        let (id, seq) = (self.next_id, self.seq);
        let command = describe(request, flags);
        let mut record = StageIo {
            seq,
            command: Some(command.clone()),
            attempt: 1,
            sent_wall_ns: Some(wall_ns()),
            reply: None,
            reply_wall_ns: None,
            rtt_ns: None,
            outcome: IoOutcome::Sent,
            detail: None,
        };
        let sent = Instant::now();
        let Self {
            conn,
            observer,
            buf,
            config,
            info,
            ..
        } = self;
        let Some(c) = conn.as_mut() else {
            return Err(SharkError::Disconnected {
                endpoint: config.endpoint.clone(),
                function: command,
                cause: "not connected".into(),
            });
        };
        let lost = |cause: String| SharkError::Disconnected {
            endpoint: config.endpoint.clone(),
            function: command.clone(),
            cause,
        };
        c.torn = true;
        let written = c.control.write_all(&request.encode(id, flags)).await;
        c.torn = false;
        if let Err(e) = written {
            record.outcome = IoOutcome::Garbled;
            record.detail = Some(format!("write failed: {e}"));
            observer.io(&record);
            *conn = None;
            return Err(lost(e.to_string()));
        }
        if !request.returns_value() && !flags.contains(Flags::SEND_RESPONSE) {
            observer.io(&record);
            return Ok(Response::Void);
        }
        let answer = tokio::time::timeout(
            wait,
            read_response(c, buf, observer.as_ref(), seq, request.name(), id),
        )
        .await;
        let (outcome, result) = match answer {
            Err(_) => (
                IoOutcome::Timeout,
                Err(SharkError::NoReply {
                    endpoint: config.endpoint.clone(),
                    function: command.clone(),
                    after: wait,
                    version: info.protocol.clone(),
                    timeout_key: config.timeout_key,
                }),
            ),
            Ok(Err(ReadError::Closed(cause))) => {
                *conn = None;
                (IoOutcome::Garbled, Err(lost(cause)))
            }
            Ok(Err(ReadError::Unframeable(cause))) => {
                *conn = None;
                (
                    IoOutcome::Garbled,
                    Err(SharkError::Unframeable {
                        endpoint: config.endpoint.clone(),
                        cause,
                    }),
                )
            }
            Ok(Ok(message)) => match request.decode_response(&message.body) {
                Ok(response) => {
                    record.reply = Some(response.to_string());
                    (IoOutcome::Replied, Ok(response))
                }
                Err(cause) => (
                    IoOutcome::Garbled,
                    Err(SharkError::BadReply {
                        function: command.clone(),
                        cause,
                    }),
                ),
            },
        };
        record.outcome = outcome;
        if outcome != IoOutcome::Replied {
            record.detail = result.as_ref().err().map(ToString::to_string);
        } else {
            record.reply_wall_ns = Some(wall_ns());
            record.rtt_ns = Some(nanos(sent.elapsed()));
        }
        observer.io(&record);
        result
    }

    /// Discards whatever the data channel holds now (chunks of a stopped scan
    /// still in flight) without waiting; returns the messages discarded.
    pub fn drain_data(&mut self) -> usize {
        let Some(data) = self.conn.as_mut().and_then(|c| c.data.as_mut()) else {
            return 0;
        };
        let mut discarded = 0;
        loop {
            while let Some(m) = data.framer.next_message() {
                if m.is_ok() {
                    discarded += 1;
                }
            }
            match data.stream.try_read(&mut self.buf) {
                Ok(0) => {
                    // Closed by the server: set up afresh at the next request.
                    self.conn = None;
                    return discarded;
                }
                Ok(n) => data.framer.push(&self.buf[..n]),
                Err(_) => return discarded,
            }
        }
    }

    /// Reads the data channel until `assembler` holds the whole frame `frame`,
    /// within `within`. One `/stage/io` record tells how the frame came.
    ///
    /// # Errors
    /// [`SharkError::Frame`] (a lost chunk, a wrong depth…), [`SharkError::DataTimeout`],
    /// [`SharkError::Disconnected`], [`SharkError::Unframeable`].
    pub async fn receive_frame(
        &mut self,
        mut assembler: FrameAssembler,
        frame: u32,
        channel: i32,
        total: u64,
        within: Duration,
    ) -> Result<FrameAssembler, SharkError> {
        self.seq += 1;
        let started = Instant::now();
        let mut record = StageIo {
            seq: self.seq,
            command: Some(format!("ScData(frame={frame}, channel={channel})")),
            attempt: 1,
            sent_wall_ns: Some(wall_ns()),
            reply: None,
            reply_wall_ns: None,
            rtt_ns: None,
            outcome: IoOutcome::Replied,
            detail: None,
        };
        let result = self
            .collect(&mut assembler, frame, total, started + within, within)
            .await;
        let stats = assembler.stats();
        record.reply = Some(format!(
            "{} of {total} pixels in {} chunks, {} re-sent, {} skipped",
            assembler.received(),
            stats.chunks,
            stats.resent,
            stats.skipped
        ));
        record.reply_wall_ns = Some(wall_ns());
        record.rtt_ns = Some(nanos(started.elapsed()));
        if let Err(e) = &result {
            record.outcome = if matches!(e, SharkError::DataTimeout { .. }) {
                IoOutcome::Timeout
            } else {
                IoOutcome::Garbled
            };
            record.detail = Some(e.to_string());
        }
        self.observer.io(&record);
        result.map(|()| assembler)
    }

    async fn collect(
        &mut self,
        assembler: &mut FrameAssembler,
        frame: u32,
        total: u64,
        deadline: Instant,
        within: Duration,
    ) -> Result<(), SharkError> {
        let endpoint = self.config.endpoint.clone();
        let lost = |cause: String| SharkError::Disconnected {
            endpoint: endpoint.clone(),
            function: format!("ScData(frame={frame})"),
            cause,
        };
        let Some(data) = self.conn.as_mut().and_then(|c| c.data.as_mut()) else {
            return Err(lost("no data channel".into()));
        };
        loop {
            while let Some(m) = data.framer.next_message() {
                match m {
                    Ok(m) => match assembler.push(&m) {
                        Ok(Progress::Complete) => return Ok(()),
                        Ok(_) => {}
                        Err(cause) => return Err(SharkError::Frame { frame, cause }),
                    },
                    Err(cause @ FrameError::BodyTooLarge { .. }) => {
                        self.conn = None;
                        return Err(SharkError::Unframeable { endpoint, cause });
                    }
                    Err(FrameError::BadHeader(_)) => {}
                }
            }
            if assembler.is_complete() {
                return Ok(());
            }
            let read = tokio::time::timeout_at(deadline, data.stream.read(&mut self.buf)).await;
            match read {
                Err(_) => {
                    return Err(SharkError::DataTimeout {
                        frame,
                        received: assembler.received(),
                        total,
                        after: within,
                    });
                }
                Ok(Ok(0)) => {
                    self.conn = None;
                    return Err(lost("the server closed the data channel".into()));
                }
                Ok(Ok(n)) => data.framer.push(&self.buf[..n]),
                Ok(Err(e)) => {
                    self.conn = None;
                    return Err(lost(e.to_string()));
                }
            }
        }
    }
}

enum ReadError {
    Closed(String),
    Unframeable(FrameError),
}

/// Reads the control connection until the response named `name` with id
/// `id`; anything else is recorded as a stray and discarded.
async fn read_response(
    c: &mut Connection,
    buf: &mut [u8],
    observer: &dyn StageObserver,
    seq: u64,
    name: &str,
    id: u32,
) -> Result<Message, ReadError> {
    loop {
        while let Some(m) = c.framer.next_message() {
            match m {
                Ok(m) if m.header.id == id && m.header.name.as_str() == name => return Ok(m),
                Ok(m) => stray(
                    observer,
                    seq,
                    &format!("{} (id {})", m.header.name, m.header.id),
                ),
                Err(e @ FrameError::BodyTooLarge { .. }) => return Err(ReadError::Unframeable(e)),
                Err(e) => stray(observer, seq, &e.to_string()),
            }
        }
        match c.control.read(buf).await {
            Ok(0) => return Err(ReadError::Closed("the server closed the connection".into())),
            Ok(n) => c.framer.push(&buf[..n]),
            Err(e) => return Err(ReadError::Closed(e.to_string())),
        }
    }
}

/// Records a message nobody asked for (a late response, a bad header).
fn stray(observer: &dyn StageObserver, seq: u64, what: &str) {
    debug!(what, "SharkSEM: stray message discarded");
    observer.io(&StageIo {
        seq,
        command: None,
        attempt: 1,
        sent_wall_ns: None,
        reply: Some(what.to_owned()),
        reply_wall_ns: Some(wall_ns()),
        rtt_ns: None,
        outcome: IoOutcome::Stray,
        detail: None,
    });
}
