//! The client of the SEM imaging link ([`sdsem_protocol::sem`]) over TCP: the
//! simulator's server, or an adapter in front of a real microscope.
//!
//! One request in flight; every exchange has a deadline (the configured
//! timeout, plus the scan time for `GRAB`). After an I/O error, a timeout or an
//! unreadable reply the connection is dropped and the next request reconnects,
//! so the link never continues out of step.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use sdsem_protocol::sem::{GrabRequest, Reply, ReplyDecoder, Request};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use super::{
    Frame, FrameSource, GrabFuture, IdentifyFuture, ImagingConfig, ImagingError, ProbeFuture,
    SourceIdentity,
};

/// The true height map of a simulated frame.
#[derive(Clone, Debug, PartialEq)]
pub struct GroundTruth {
    pub width: usize,
    pub height: usize,
    /// Heights (µm, up towards the beam), row-major, NaN off the specimen.
    pub heights_um: Vec<f32>,
    /// The metadata of the frame it belongs to.
    pub meta: super::FrameMeta,
}

struct Connection {
    stream: TcpStream,
    decoder: ReplyDecoder,
}

/// Client of the SEM imaging link.
pub struct SemLinkClient {
    cfg: ImagingConfig,
    conn: Option<Connection>,
    /// The last `*IDN?` answer.
    idn: String,
}

impl std::fmt::Debug for SemLinkClient {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SemLinkClient")
            .field("endpoint", &self.cfg.endpoint)
            .field("connected", &self.conn.is_some())
            .finish()
    }
}

impl SemLinkClient {
    /// A client for `cfg`; connects on the first request.
    ///
    /// # Errors
    /// [`ImagingError::InvalidConfig`] when a setting is invalid.
    pub fn new(cfg: ImagingConfig) -> Result<Self, ImagingError> {
        cfg.validate()?;
        Ok(Self {
            cfg,
            conn: None,
            idn: String::new(),
        })
    }

    /// A client connected now, with the server's `*IDN?` answer.
    ///
    /// # Errors
    /// [`ImagingError`] when the settings are invalid or the server cannot be reached.
    pub async fn connect(cfg: ImagingConfig) -> Result<(Self, String), ImagingError> {
        let mut client = Self::new(cfg)?;
        let id = client.identify().await?;
        Ok((client, id))
    }

    /// The settings in use.
    #[must_use]
    pub fn config(&self) -> &ImagingConfig {
        &self.cfg
    }

    /// The server's identification (`*IDN?`).
    ///
    /// # Errors
    /// [`ImagingError`] naming the endpoint and the remedy.
    pub async fn identify(&mut self) -> Result<String, ImagingError> {
        let request = Request::Identify;
        match self.exchange(&request, self.cfg.timeout()).await? {
            Reply::Identity(id) => {
                id.clone_into(&mut self.idn);
                Ok(id)
            }
            other => Err(self.unexpected(&request, &other)),
        }
    }

    /// `sdsem probe`'s lines: the pixel size at the micrograph and tracking widths
    /// (`PIXELSIZE?`), nothing scanned.
    async fn probe_lines(&mut self) -> Result<Vec<(String, String)>, ImagingError> {
        let mut lines = Vec::new();
        for (name, s) in [
            ("micrograph", self.cfg.micrograph.clone()),
            ("tracking frame", self.cfg.tracking.clone()),
        ] {
            let p = self.pixel_size_um(s.width).await?;
            lines.push((
                format!("pixel size, {name}"),
                format!(
                    "{p} µm at {} px wide (field {:.3} µm)",
                    s.width,
                    p * f64::from(s.width)
                ),
            ));
        }
        Ok(lines)
    }

    /// Pixel size (µm) of a frame `width` pixels wide (`PIXELSIZE?`).
    ///
    /// # Errors
    /// [`ImagingError`] naming the endpoint and the remedy.
    pub async fn pixel_size_um(&mut self, width: u32) -> Result<f64, ImagingError> {
        let request = Request::PixelSize { width };
        match self.exchange(&request, self.cfg.timeout()).await? {
            Reply::PixelSize { pixel_size_um, .. } => Ok(pixel_size_um),
            other => Err(self.unexpected(&request, &other)),
        }
    }

    /// Scans one frame (`GRAB`).
    ///
    /// # Errors
    /// [`ImagingError`] naming the endpoint and the remedy.
    pub async fn grab_frame(&mut self, grab: GrabRequest) -> Result<Frame, ImagingError> {
        let request = Request::Grab(grab);
        // The scan itself at the microscope's pace, then the usual allowance.
        let deadline = self.cfg.timeout() + Duration::from_secs_f64(grab.scan_seconds());
        match self.exchange(&request, deadline).await? {
            Reply::Frame(f) if f.width == grab.width && f.height == grab.height => {
                Ok(Frame::from_reply(f, unix_ns()))
            }
            other => Err(self.unexpected(&request, &other)),
        }
    }

    /// The true height map of frame `frame` (`GROUNDTRUTH <frame>`; simulator only).
    ///
    /// # Errors
    /// [`ImagingError`], [`ImagingError::Refused`] with code 3 for an unknown frame.
    pub async fn ground_truth(&mut self, frame: u64) -> Result<GroundTruth, ImagingError> {
        let request = Request::GroundTruth { frame, path: None };
        match self.exchange(&request, self.cfg.timeout()).await? {
            Reply::HeightMap(h) => Ok(GroundTruth {
                width: h.width as usize,
                height: h.height as usize,
                heights_um: h.heights(),
                meta: h.meta,
            }),
            other => Err(self.unexpected(&request, &other)),
        }
    }

    /// Has the server write the true height map of frame `frame` as a GSF file
    /// at `path` on its own machine (`GROUNDTRUTH <frame> <path>`; simulator only).
    ///
    /// # Errors
    /// [`ImagingError`], [`ImagingError::Refused`] when the file cannot be written.
    pub async fn save_ground_truth(&mut self, frame: u64, path: &str) -> Result<(), ImagingError> {
        let request = Request::GroundTruth {
            frame,
            path: Some(path.to_owned()),
        };
        match self.exchange(&request, self.cfg.timeout()).await? {
            Reply::Ok(_) => Ok(()),
            other => Err(self.unexpected(&request, &other)),
        }
    }

    /// Sends `request` and reads its reply within `deadline`; an `ERR` reply
    /// becomes [`ImagingError::Refused`].
    async fn exchange(
        &mut self,
        request: &Request,
        deadline: Duration,
    ) -> Result<Reply, ImagingError> {
        let endpoint = self.cfg.endpoint.clone();
        let name = describe(request);
        let result = tokio::time::timeout(deadline, self.exchange_inner(request, &name)).await;
        let outcome = match result {
            Ok(r) => r,
            Err(_) => Err(ImagingError::Timeout {
                endpoint: endpoint.clone(),
                request: name.clone(),
                after: deadline,
            }),
        };
        match outcome {
            Ok(Reply::Error { code, message }) => Err(ImagingError::Refused {
                endpoint,
                request: name,
                code: code.number(),
                message,
            }),
            Ok(reply) => Ok(reply),
            Err(e) => {
                // Out of step or gone: start afresh next time.
                self.conn = None;
                Err(e)
            }
        }
    }

    async fn exchange_inner(
        &mut self,
        request: &Request,
        name: &str,
    ) -> Result<Reply, ImagingError> {
        let endpoint = self.cfg.endpoint.clone();
        if self.conn.is_none() {
            let stream = TcpStream::connect(self.cfg.address())
                .await
                .map_err(|source| ImagingError::Connect {
                    endpoint: endpoint.clone(),
                    source,
                })?;
            let _ = stream.set_nodelay(true);
            self.conn = Some(Connection {
                stream,
                decoder: ReplyDecoder::new(),
            });
        }
        let Some(conn) = self.conn.as_mut() else {
            return Err(ImagingError::Closed {
                endpoint,
                request: name.to_owned(),
            });
        };
        let io_error = |source| ImagingError::Io {
            endpoint: endpoint.clone(),
            request: name.to_owned(),
            source,
        };
        conn.stream
            .write_all(&request.encode())
            .await
            .map_err(io_error)?;
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            let decoded = conn
                .decoder
                .next_reply()
                .map_err(|source| ImagingError::Protocol {
                    endpoint: endpoint.clone(),
                    request: name.to_owned(),
                    source,
                })?;
            if let Some(reply) = decoded {
                return Ok(reply);
            }
            // Read big payloads in big pieces.
            let want = conn
                .decoder
                .payload_remaining()
                .unwrap_or(0)
                .clamp(64 * 1024, 4 << 20);
            if buf.len() < want {
                buf.resize(want, 0);
            }
            let n = conn.stream.read(&mut buf).await.map_err(io_error)?;
            if n == 0 {
                return Err(ImagingError::Closed {
                    endpoint,
                    request: name.to_owned(),
                });
            }
            conn.decoder.push(&buf[..n]);
        }
    }

    fn unexpected(&self, request: &Request, reply: &Reply) -> ImagingError {
        let got = match reply {
            Reply::Identity(_) => "an IDN reply".to_owned(),
            Reply::PixelSize { .. } => "a PIXELSIZE reply".to_owned(),
            Reply::Frame(f) => format!("a {}×{} FRAME", f.width, f.height),
            Reply::HeightMap(_) => "a HEIGHTMAP".to_owned(),
            Reply::Ok(t) => format!("OK {t}"),
            Reply::Error { code, message } => format!("ERR {} {message}", code.number()),
        };
        ImagingError::UnexpectedReply {
            endpoint: self.cfg.endpoint.clone(),
            request: describe(request),
            got,
        }
    }
}

impl FrameSource for SemLinkClient {
    fn grab(&mut self, request: GrabRequest) -> GrabFuture<'_> {
        Box::pin(self.grab_frame(request))
    }

    fn identify(&mut self) -> IdentifyFuture<'_> {
        // The inherent `identify` (`*IDN?`).
        Box::pin(Self::identify(self))
    }

    fn identity(&self) -> SourceIdentity {
        SourceIdentity::from_idn(&self.idn)
    }

    fn probe(&mut self) -> ProbeFuture<'_> {
        Box::pin(self.probe_lines())
    }
}

/// The request as a short text for messages (the request line without its LF).
fn describe(request: &Request) -> String {
    let line = request.encode();
    String::from_utf8_lossy(&line[..line.len().saturating_sub(1)]).into_owned()
}

fn unix_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}

#[cfg(test)]
mod tests;
