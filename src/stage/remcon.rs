//! The Zeiss SmartSEM RemCon32 backend (`stage.protocol = "remcon32"`): the
//! SEM's own stage over RS-232 (9600 8N1), a pseudo-terminal or `tcp://`
//! (a serial-to-Ethernet server), facts from VENDORS §1.
//!
//! - Connect: the null command (its answer, if any, discarded), `VER?` for the
//!   identity, `IST?` (a stage that is not initialised is refused).
//! - Moves: `C95?`, then `C95 x y z t r m` with every other axis re-sent as read
//!   (read-modify-write; tilt before rotation; mm and degrees at the wire, µm
//!   inside sdsem). The moving flag (7th value of `C95?`) is trusted only
//!   `stage.moving_flag_delay_s` after the command: it may be set late [OD-Z];
//!   before that, the safety layer takes arrival only from the positions.
//! - Stop: `ABO`. Errors `*600`…`*617` are named, with a remedy; `#` is an
//!   invalid command. Queries are retried after a timeout or a garbled reply;
//!   a move is never re-sent blindly (the safety layer re-issues it once when
//!   the read-back shows it did not happen).

use std::sync::Arc;
use std::time::Duration;

use sdsem_protocol::remcon::{
    Command, DataError, Reply, ReplyFramer, StageInit, StageReading, StageTarget, encode_line,
};
use tokio::io::{AsyncRead, AsyncWrite};
use tracing::{info, warn};

use super::backend::{BoxFuture, Connected, MotionPoll, StageBackend, StageIdentity};
use super::config::{StageAxis, StageConfig, StageProtocol, secs};
use super::error::{LinkRemedies, StageError, remcon_remedy};
use super::observer::{IoOutcome, StageObserver};
use super::wire::{Framing, Received, Wire, WireTiming};

impl Framing for ReplyFramer {
    type Reply = Reply;
    type Error = sdsem_protocol::remcon::FrameError;
    fn feed(&mut self, bytes: &[u8]) {
        Self::feed(self, bytes);
    }
    fn next_reply(&mut self) -> Option<Result<Reply, Self::Error>> {
        Self::next_reply(self)
    }
    fn reset(&mut self) {
        Self::reset(self);
    }
    fn text(reply: &Reply) -> String {
        reply.to_text()
    }
}

/// How an exchange may be repeated.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Repeat {
    /// A query or an abort: retried after a timeout, a garbled reply or a `#`.
    Retry,
    /// A command with an effect (a move, a trigger): sent once.
    Once,
}

/// A RemCon32 server (SmartSEM's RemCon32 program) behind a byte stream.
pub struct RemconBackend<T> {
    wire: Wire<T, ReplyFramer>,
    config: StageConfig,
    /// The last `C95?` answer: the axes sdsem does not drive (z, rotation, m).
    last: Option<StageReading>,
}

/// The value of an axis in a reading, in sdsem's units (µm, degrees).
fn value(r: &StageReading, axis: StageAxis) -> f64 {
    match axis {
        StageAxis::X => r.x_mm * 1000.0,
        StageAxis::Y => r.y_mm * 1000.0,
        StageAxis::Tilt => r.t_deg,
    }
}

impl<T: AsyncRead + AsyncWrite + Unpin + Send> RemconBackend<T> {
    /// A backend over `io` (nothing is sent before [`StageBackend::connect`]).
    pub fn new(io: T, config: StageConfig, observer: Arc<dyn StageObserver>) -> Self {
        let timing = WireTiming {
            reply_timeout: secs(config.reply_timeout_s),
            resync_quiet: secs(config.resync_quiet_s),
        };
        Self {
            wire: Wire::new(
                io,
                ReplyFramer::new(),
                observer,
                timing,
                LinkRemedies::new(&config),
            ),
            config,
            last: None,
        }
    }

    /// The last `C95?` answer (every axis, z, rotation and m included), if any.
    pub fn last_reading(&self) -> Option<&StageReading> {
        self.last.as_ref()
    }

    /// Gives the byte stream back.
    pub fn into_inner(self) -> T {
        self.wire.into_inner()
    }

    /// One exchange: the request, then `@` and its status line. `>data` is
    /// parsed by `parse`; `*NNN` is [`StageError::Remcon`]; `#`, a garbled or
    /// missing reply are retried with [`Repeat::Retry`], else errors.
    async fn exchange<R>(
        &mut self,
        text: &str,
        bytes: &[u8],
        repeat: Repeat,
        timeout: Duration,
        settle: bool,
        parse: impl Fn(&str) -> Result<R, DataError> + Send,
    ) -> Result<R, StageError> {
        let attempts = match repeat {
            Repeat::Retry => self.config.query_retries.saturating_add(1),
            Repeat::Once => 1,
        };
        let mut failure = self.wire.no_reply(text, attempts, timeout);
        for attempt in 1..=attempts {
            let sent = self
                .wire
                .send_within(bytes, text, settle, true, timeout)
                .await?;
            match self.wire.receive(sent.deadline, text).await? {
                Received::Reply(Reply::Done(data)) => match parse(&data) {
                    Ok(value) => {
                        self.wire.answered();
                        let reply = Some(Reply::Done(data).to_text());
                        self.wire
                            .record(&sent, text, attempt, reply, IoOutcome::Replied, None);
                        if attempt > 1 {
                            warn!(command = %text, attempt, "stage query recovered by a retry");
                        }
                        return Ok(value);
                    }
                    Err(e) => {
                        let reply = Reply::Done(data).to_text();
                        failure = self
                            .wire
                            .garbled(&sent, text, attempt, reply, e.to_string())
                            .await?;
                    }
                },
                Received::Reply(Reply::Failed(error)) => {
                    self.wire.answered();
                    let reply = Some(Reply::Failed(error).to_text());
                    let detail = Some(error.to_string());
                    self.wire
                        .record(&sent, text, attempt, reply, IoOutcome::Replied, detail);
                    return Err(StageError::Remcon {
                        command: text.to_owned(),
                        error,
                        remedy: remcon_remedy(error),
                    });
                }
                Received::Reply(Reply::Invalid) => {
                    let detail = Some("invalid command (#)".to_owned());
                    let reply = Some(Reply::Invalid.to_text());
                    self.wire
                        .record(&sent, text, attempt, reply, IoOutcome::Replied, detail);
                    // A second line may follow `#` (⚠ VENDORS §1.2): the next send waits it out.
                    self.wire.mark_dirty();
                    failure = StageError::InvalidCommand {
                        command: text.to_owned(),
                        attempts: attempt,
                    };
                }
                Received::Frame(e) => {
                    failure = self
                        .wire
                        .unframeable(&sent, text, attempt, e.to_string())
                        .await?;
                }
                Received::Timeout => {
                    let detail = if self.wire.framer().is_acknowledged() {
                        format!("accepted (@) but no status line within {timeout:?}")
                    } else {
                        format!("no reply within {timeout:?}")
                    };
                    failure = self
                        .wire
                        .timed_out(&sent, text, attempt, timeout, detail)
                        .await?;
                }
            }
        }
        Err(failure)
    }

    /// A query, retried; its reply parsed by `parse`.
    async fn query<R>(
        &mut self,
        command: &Command,
        parse: impl Fn(&str) -> Result<R, DataError> + Send,
    ) -> Result<R, StageError> {
        let timeout = self.wire.timing().reply_timeout;
        self.exchange(
            &command.to_string(),
            &command.to_bytes(),
            Repeat::Retry,
            timeout,
            true,
            parse,
        )
        .await
    }

    async fn read_stage(&mut self) -> Result<StageReading, StageError> {
        let r = self
            .query(&Command::StageQuery, StageReading::parse)
            .await?;
        self.last = Some(r);
        Ok(r)
    }

    async fn connect_inner(&mut self) -> Result<Connected, StageError> {
        // Whatever a previous session left in the output is not ours; then the
        // null command, a harmless probe [OD-Z, ML], whose answer (if any) is discarded.
        self.wire.resync(Duration::ZERO, "connect").await?;
        let null = "(null command)";
        let sent = self
            .wire
            .send(&Command::Null.to_bytes(), null, true, false)
            .await?;
        self.wire.record_sent(&sent, null);
        self.wire.resync(Duration::ZERO, null).await?;

        let version = self.query(&Command::Version, |d| Ok(d.to_owned())).await?;
        if !self.config.expect_idn.is_empty() && !version.contains(&self.config.expect_idn) {
            return Err(StageError::UnexpectedIdentity {
                idn: version,
                expected: self.config.expect_idn.clone(),
            });
        }
        let smartsem = version.to_ascii_lowercase().contains("smartsem");
        if !smartsem {
            warn!(version = %version, "the RemCon32 server does not name SmartSEM in VER?");
        }
        info!(version = %version, "SEM identified (RemCon32)");

        let init = self
            .query(&Command::InitialisedQuery, |d| {
                StageInit::parse(d).map(|i| (i, d.to_owned()))
            })
            .await;
        match init {
            Ok((i, _)) if i.initialised => {}
            Ok((_, reply)) => return Err(StageError::NotInitialised { reply }),
            Err(StageError::Remcon { error, .. }) => {
                info!(%error, "the SEM does not answer IST?; stage initialisation not checked");
            }
            Err(e) => return Err(e),
        }
        Ok(Connected {
            identity: StageIdentity {
                protocol: StageProtocol::Remcon32.as_str().to_owned(),
                vendor: if smartsem { "Zeiss" } else { "" }.to_owned(),
                model: String::new(),
                version: version.clone(),
                serial: String::new(),
                raw: version,
            },
            // RemCon32 reports no stage limits: the configured ones stand.
            limits: [None; 3],
        })
    }

    async fn positions(&mut self, axes: &[StageAxis]) -> Result<Vec<f64>, StageError> {
        let r = self.read_stage().await?;
        Ok(axes.iter().map(|&a| value(&r, a)).collect())
    }

    async fn start_move_inner(
        &mut self,
        targets: &[(StageAxis, f64)],
    ) -> Result<String, StageError> {
        // C95 moves every axis: the others are re-sent as read [2+].
        let r = self.read_stage().await?;
        let mut target =
            StageTarget::from_values([r.x_mm, r.y_mm, r.z_mm, r.t_deg, r.r_deg, r.m_mm]);
        for &(axis, v) in targets {
            match axis {
                StageAxis::X => target.x_mm = v / 1000.0,
                StageAxis::Y => target.y_mm = v / 1000.0,
                StageAxis::Tilt => target.t_deg = v,
            }
        }
        let command = Command::StageMove(target);
        let text = command.to_string();
        let timeout = self.wire.timing().reply_timeout;
        self.exchange(
            &text,
            &command.to_bytes(),
            Repeat::Once,
            timeout,
            true,
            |_| Ok(()),
        )
        .await?;
        Ok(text)
    }

    async fn moving(&mut self, axes: &[StageAxis]) -> Result<MotionPoll, StageError> {
        let r = self.read_stage().await?;
        Ok(MotionPoll {
            settled: vec![!r.moving; axes.len()],
            positions: Some(axes.iter().map(|&a| value(&r, a)).collect()),
        })
    }

    async fn abort(&mut self) -> Result<(), StageError> {
        let command = Command::Abort;
        let timeout = self.wire.timing().reply_timeout;
        // No resynchronisation wait first: stopping must not be delayed.
        self.exchange(
            &command.to_string(),
            &command.to_bytes(),
            Repeat::Retry,
            timeout,
            false,
            |_| Ok(()),
        )
        .await?;
        info!("stage stopped (ABO)");
        Ok(())
    }

    /// `sdsem probe`'s lines: the axes sdsem does not drive, then the SEM's state by
    /// queries that change nothing; one the SEM refuses (`*600`, `#`) is a line saying so.
    async fn probe_lines(&mut self) -> Result<Vec<(String, String)>, StageError> {
        let r = self.read_stage().await?;
        let mut lines = vec![(
            "C95? (all axes)".to_owned(),
            format!(
                "x {} mm, y {} mm, z {} mm, tilt {}°, rotation {}°, m {} mm, {}",
                r.x_mm,
                r.y_mm,
                r.z_mm,
                r.t_deg,
                r.r_deg,
                r.m_mm,
                if r.moving { "moving" } else { "not moving" }
            ),
        )];
        let queries = [
            (
                Command::InitialisedQuery,
                "IST? stage type, initialised (0)",
                "",
            ),
            (
                Command::PixelSizeQuery,
                "PIX? pixel size",
                " nm (field width / 1024)",
            ),
            (Command::MagnificationQuery, "MAG? magnification", " ×"),
            (Command::DetectorQuery, "DET? detector", ""),
            (Command::EhtQuery, "EHT? accelerating voltage", " kV"),
            (Command::PhotoNumberQuery, "PHN? photo number", ""),
        ];
        for (command, name, unit) in queries {
            let value = match self.query(&command, |d| Ok(d.to_owned())).await {
                Ok(data) => format!("{data}{unit}"),
                Err(StageError::Remcon { error, .. }) => format!("not answered: {error}"),
                Err(StageError::InvalidCommand { .. }) => {
                    "not answered: invalid command (#)".into()
                }
                Err(e) => return Err(e),
            };
            lines.push((name.to_owned(), value));
        }
        Ok(lines)
    }

    async fn raw(&mut self, line: &str, timeout: Duration) -> Result<String, StageError> {
        let bytes = encode_line(line).map_err(|e| StageError::Config {
            field: "imaging.trigger",
            reason: format!("{line:?}: {e}"),
        })?;
        self.exchange(line, &bytes, Repeat::Once, timeout, true, |d| {
            Ok(d.to_owned())
        })
        .await
    }
}

impl<T: AsyncRead + AsyncWrite + Unpin + Send> StageBackend for RemconBackend<T> {
    fn protocol(&self) -> StageProtocol {
        StageProtocol::Remcon32
    }

    fn connect(&mut self) -> BoxFuture<'_, Result<Connected, StageError>> {
        Box::pin(self.connect_inner())
    }

    fn axis_name(&self, axis: StageAxis) -> String {
        match axis {
            StageAxis::X => "x",
            StageAxis::Y => "y",
            StageAxis::Tilt => "t",
        }
        .to_owned()
    }

    fn read_position<'a>(
        &'a mut self,
        axes: &'a [StageAxis],
    ) -> BoxFuture<'a, Result<Vec<f64>, StageError>> {
        Box::pin(self.positions(axes))
    }

    fn start_move<'a>(
        &'a mut self,
        targets: &'a [(StageAxis, f64)],
    ) -> BoxFuture<'a, Result<String, StageError>> {
        Box::pin(self.start_move_inner(targets))
    }

    fn flag_delay(&self) -> Duration {
        secs(self.config.moving_flag_delay_s)
    }

    fn poll_motion<'a>(
        &'a mut self,
        axes: &'a [StageAxis],
    ) -> BoxFuture<'a, Result<MotionPoll, StageError>> {
        Box::pin(self.moving(axes))
    }

    fn stop(&mut self) -> BoxFuture<'_, Result<(), StageError>> {
        Box::pin(self.abort())
    }

    fn send_raw<'a>(
        &'a mut self,
        line: &'a str,
        timeout: Duration,
    ) -> BoxFuture<'a, Result<String, StageError>> {
        Box::pin(self.raw(line, timeout))
    }

    fn probe_facts(&mut self) -> BoxFuture<'_, Result<Vec<(String, String)>, StageError>> {
        Box::pin(self.probe_lines())
    }
}
