//! The recorder: ONE writer thread owns the `mcap::Writer` and the file, fed by a bounded
//! channel; cheap-clone handles send it encoded [`Entry`]s from sync or async code.
//!
//! Durability (DESIGN §5, §8): every frame-like message (images, point clouds) closes the
//! chunk it is in and flushes it to the operating system, and so does a timer for the
//! other messages, so a run killed at any moment (even `kill -9`) leaves every completed
//! frame readable. Chunks are buffered whole and appended in one write (`disable_seeking`),
//! so a crash can never leave a chunk header that claims data it does not have.
//! `finish()` must be called: it writes the summary and returns the first error.
//!
//! Backpressure: frames and JSON messages block the sender when the channel is full (never
//! dropped); `/log` messages from the tracing layer are dropped instead, counted, and the
//! count recorded in the metadata record [`topics::METADATA_LOG_DROPS`] at `finish()`.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use mcap::records::{MessageHeader, Metadata};
use mcap::write::NoSeek;
use mcap::{Attachment, Compression, WriteOptions, Writer};
use serde::Serialize;

use super::entry::{ChannelSpec, Entry, EntryKind, LogLevel, Pixels};
use super::error::{RecordError, error_chain};
use super::messages::{FrameInfo, RunOutcome, StageIo, StageState};
use super::topics::{self, FrameRole};
use crate::export::CloudPoint;
use crate::vision::Image;

fn dims(topic: &str, image: &Image) -> Result<(u32, u32), RecordError> {
    match (u32::try_from(image.width()), u32::try_from(image.height())) {
        (Ok(w), Ok(h)) => Ok((w, h)),
        _ => Err(RecordError::InvalidMessage {
            topic: topic.to_owned(),
            reason: "image too large for a RawImage".to_owned(),
        }),
    }
}

/// Options of a [`Recorder`]; the defaults suit a run on a lab PC.
#[derive(Debug, Clone)]
pub struct RecorderOptions {
    /// Entries the channel holds before senders block (frames) or logs are dropped. Default 64.
    pub channel_capacity: usize,
    /// Longest time a non-frame message stays unflushed. Default 1 s.
    pub flush_interval: Duration,
    /// `fsync` the file at every flush, so completed frames also survive a power cut.
    /// Default true.
    pub fsync: bool,
    /// Compress chunks with LZ4. Default true.
    pub compress: bool,
}

impl Default for RecorderOptions {
    fn default() -> Self {
        Self {
            channel_capacity: 64,
            flush_interval: Duration::from_secs(1),
            fsync: true,
            compress: true,
        }
    }
}

/// What was written, returned by [`Recorder::finish`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordSummary {
    pub path: PathBuf,
    /// Messages written per topic.
    pub messages_per_topic: BTreeMap<String, u64>,
    pub messages: u64,
    pub chunks: u32,
    pub attachments: u32,
    pub metadata_records: u32,
    /// First and last message log time, ns; `None` without messages.
    pub time_range_ns: Option<(u64, u64)>,
    /// `/log` messages dropped because the channel was full.
    pub log_messages_dropped: u64,
    /// Size of the finished file, bytes.
    pub file_bytes: u64,
}

/// A snapshot of the recorder's state for producers.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecorderStatus {
    /// The write error that stopped the recorder, once it happened.
    pub failed: Option<String>,
    /// Entries written so far.
    pub entries_written: u64,
    /// `/log` messages dropped under backpressure so far.
    pub log_messages_dropped: u64,
    /// Whether `finish()` was called (new entries are refused).
    pub finished: bool,
}

#[derive(Debug, Default)]
struct Shared {
    failed: Mutex<Option<String>>,
    stopped: AtomicBool,
    finished: AtomicBool,
    written: AtomicU64,
    log_drops: AtomicU64,
}

enum Command {
    Write(Entry),
    Finish,
}

/// A cheap-clone handle to a [`Recorder`], usable from any thread.
///
/// From async code use [`Self::send_async`] (it never blocks the executor, and keeps a
/// paused tokio clock from jumping while it waits); the convenience methods block the
/// calling thread while the channel is full.
#[derive(Clone)]
pub struct RecorderHandle {
    tx: SyncSender<Command>,
    shared: Arc<Shared>,
    path: Arc<PathBuf>,
}

impl std::fmt::Debug for RecorderHandle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RecorderHandle")
            .field("path", &self.path)
            .finish_non_exhaustive()
    }
}

impl RecorderHandle {
    /// The record file.
    #[must_use]
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The recorder's state: the write error once one happened, counters.
    #[must_use]
    pub fn status(&self) -> RecorderStatus {
        RecorderStatus {
            failed: self
                .shared
                .failed
                .lock()
                .map(|f| f.clone())
                .unwrap_or_else(|poisoned| poisoned.into_inner().clone()),
            entries_written: self.shared.written.load(Ordering::Relaxed),
            log_messages_dropped: self.shared.log_drops.load(Ordering::Relaxed),
            finished: self.shared.finished.load(Ordering::Relaxed),
        }
    }

    fn check_open(&self) -> Result<(), RecordError> {
        if self.shared.stopped.load(Ordering::Acquire) {
            return Err(RecordError::Stopped {
                path: self.path.as_ref().clone(),
            });
        }
        if self.shared.finished.load(Ordering::Acquire) {
            return Err(RecordError::Closed);
        }
        Ok(())
    }

    /// Queues an entry, blocking while the channel is full. Never drops it.
    ///
    /// # Errors
    /// [`RecordError::Stopped`] after a write error, [`RecordError::Closed`] after `finish()`.
    pub fn send(&self, entry: Entry) -> Result<(), RecordError> {
        self.check_open()?;
        self.tx
            .send(Command::Write(entry))
            .map_err(|_| RecordError::Closed)
    }

    /// Queues an entry from async code, waiting (without blocking the executor) while the
    /// channel is full. Never drops it.
    ///
    /// # Errors
    /// As [`Self::send`].
    pub async fn send_async(&self, entry: Entry) -> Result<(), RecordError> {
        self.check_open()?;
        match self.tx.try_send(Command::Write(entry)) {
            Ok(()) => Ok(()),
            Err(TrySendError::Disconnected(_)) => Err(RecordError::Closed),
            Err(TrySendError::Full(command)) => {
                // The blocking pool waits for room; tokio inhibits auto-advance of a paused
                // clock while a blocking task runs, so test time does not jump meanwhile.
                let tx = self.tx.clone();
                match tokio::task::spawn_blocking(move || tx.send(command).is_ok()).await {
                    Ok(true) => Ok(()),
                    Ok(false) | Err(_) => Err(RecordError::Closed),
                }
            }
        }
    }

    /// Queues a `/log` entry without ever blocking; when the channel is full the entry is
    /// dropped and counted. Returns whether it was queued.
    pub fn try_send_log(&self, entry: Entry) -> bool {
        if self.check_open().is_err() {
            return false;
        }
        match self.tx.try_send(Command::Write(entry)) {
            Ok(()) => true,
            Err(TrySendError::Full(_)) => {
                self.shared.log_drops.fetch_add(1, Ordering::Relaxed);
                false
            }
            Err(TrySendError::Disconnected(_)) => false,
        }
    }

    /// Records a foxglove.RawImage (see [`Entry::image`]).
    ///
    /// # Errors
    /// As [`Entry::image`] and [`Self::send`].
    pub fn image(
        &self,
        topic: &str,
        log_time_ns: u64,
        frame_id: &str,
        pixels: &Pixels,
        width: u32,
        height: u32,
    ) -> Result<(), RecordError> {
        self.send(Entry::image(
            topic,
            log_time_ns,
            frame_id,
            pixels,
            width,
            height,
        )?)
    }

    /// Records a foxglove.CompressedImage of PNG bytes (see [`Entry::compressed_png`]).
    ///
    /// # Errors
    /// As [`Entry::compressed_png`] and [`Self::send`].
    pub fn compressed_png(
        &self,
        topic: &str,
        log_time_ns: u64,
        frame_id: &str,
        png: Vec<u8>,
    ) -> Result<(), RecordError> {
        self.send(Entry::compressed_png(topic, log_time_ns, frame_id, png)?)
    }

    /// Records a JSON message with the topic's schema (see [`Entry::json`]).
    ///
    /// # Errors
    /// As [`Entry::json`] and [`Self::send`].
    pub fn json(
        &self,
        topic: &str,
        log_time_ns: u64,
        value: &impl Serialize,
    ) -> Result<(), RecordError> {
        self.send(Entry::json(topic, log_time_ns, value)?)
    }

    /// Records a foxglove.PointCloud (see [`Entry::point_cloud`]).
    ///
    /// # Errors
    /// As [`Entry::point_cloud`] and [`Self::send`].
    pub fn point_cloud(
        &self,
        topic: &str,
        log_time_ns: u64,
        frame_id: &str,
        points: &[CloudPoint],
    ) -> Result<(), RecordError> {
        self.send(Entry::point_cloud(topic, log_time_ns, frame_id, points)?)
    }

    /// Records a foxglove.Log message, blocking like any other message (the tracing layer
    /// uses [`Self::try_send_log`] instead).
    ///
    /// # Errors
    /// As [`Self::send`].
    pub fn log(
        &self,
        log_time_ns: u64,
        level: LogLevel,
        message: &str,
        target: &str,
        file: &str,
        line: u32,
    ) -> Result<(), RecordError> {
        self.send(Entry::log(log_time_ns, level, message, target, file, line)?)
    }

    /// Writes an MCAP metadata record.
    ///
    /// # Errors
    /// As [`Self::send`].
    pub fn metadata(
        &self,
        name: &str,
        entries: BTreeMap<String, String>,
    ) -> Result<(), RecordError> {
        self.send(Entry::metadata(name, entries))
    }

    /// Writes an MCAP attachment.
    ///
    /// # Errors
    /// As [`Self::send`].
    pub fn attachment(
        &self,
        log_time_ns: u64,
        name: &str,
        media_type: &str,
        data: Vec<u8>,
    ) -> Result<(), RecordError> {
        self.send(Entry::attachment(log_time_ns, name, media_type, data))
    }

    /// Records a SEM frame: the micrograph (`[0, 1]`) as a 16-bit `/sem/frame` RawImage
    /// whose `frame_id` is `info.role`, and `info` on `/sem/frame_info`, both at
    /// `log_time_ns`. The chunk is cut and flushed after the info, so both survive a crash together.
    ///
    /// # Errors
    /// [`RecordError::InvalidMessage`] when `info.width/height` disagree with `image`, and
    /// as [`Self::send`].
    pub fn frame(
        &self,
        log_time_ns: u64,
        image: &Image,
        info: &FrameInfo,
    ) -> Result<(), RecordError> {
        let (w, h) = (info.width, info.height);
        if (w as usize, h as usize) != image.dimensions() {
            return Err(RecordError::InvalidMessage {
                topic: topics::SEM_FRAME.to_owned(),
                reason: format!(
                    "frame info says {w} × {h}, the image is {} × {}",
                    image.width(),
                    image.height()
                ),
            });
        }
        let pixels = Pixels::mono16_from_image(image);
        let image_entry = Entry::image(
            topics::SEM_FRAME,
            log_time_ns,
            info.role.as_str(),
            &pixels,
            w,
            h,
        )?;
        let info_entry =
            Entry::json(topics::SEM_FRAME_INFO, log_time_ns, info)?.cutting_chunk(true);
        self.send(image_entry.cutting_chunk(false))?;
        self.send(info_entry)
    }

    /// Records a `/stage/state` message.
    ///
    /// # Errors
    /// As [`Self::send`].
    pub fn stage_state(&self, log_time_ns: u64, state: &StageState) -> Result<(), RecordError> {
        self.json(topics::STAGE_STATE, log_time_ns, state)
    }

    /// Records a `/stage/io` message.
    ///
    /// # Errors
    /// As [`Self::send`].
    pub fn stage_io(&self, log_time_ns: u64, io: &StageIo) -> Result<(), RecordError> {
        self.json(topics::STAGE_IO, log_time_ns, io)
    }

    /// Records the height map (µm, NaN unknown, left grid) on `/recon/height` as 32FC1.
    ///
    /// # Errors
    /// As [`Entry::image`] and [`Self::send`].
    pub fn height(&self, log_time_ns: u64, height_um: &Image) -> Result<(), RecordError> {
        let (w, h) = dims(topics::RECON_HEIGHT, height_um)?;
        self.image(
            topics::RECON_HEIGHT,
            log_time_ns,
            FrameRole::Left.as_str(),
            &Pixels::float32_from_image(height_um),
            w,
            h,
        )
    }

    /// Records the reconstruction report (the figures of `report.json`, with its
    /// `schema_version` and rounding: [`crate::numbers::report_json`]) on `/recon/report`.
    ///
    /// # Errors
    /// As [`Entry::json`] and [`Self::send`].
    pub fn report(&self, log_time_ns: u64, report: &impl Serialize) -> Result<(), RecordError> {
        let value = crate::numbers::report_json(report).map_err(|source| RecordError::Json {
            topic: topics::RECON_REPORT.to_owned(),
            source,
        })?;
        self.json(topics::RECON_REPORT, log_time_ns, &value)
    }

    /// Writes the run's outcome as the metadata record [`topics::METADATA_OUTCOME`];
    /// call it last, before [`Recorder::finish`].
    ///
    /// # Errors
    /// As [`Self::send`].
    pub fn outcome(&self, outcome: &RunOutcome) -> Result<(), RecordError> {
        self.metadata(topics::METADATA_OUTCOME, outcome.to_map())
    }
}

/// The owner of one run record: create it, hand out [`RecorderHandle`]s, then `finish()`.
pub struct Recorder {
    handle: RecorderHandle,
    thread: Option<JoinHandle<Result<RecordSummary, RecordError>>>,
}

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("path", &self.handle.path)
            .finish_non_exhaustive()
    }
}

impl Recorder {
    /// Creates (truncates) the record file at `path` and starts the writer thread.
    ///
    /// # Errors
    /// [`RecordError::Create`] when the file cannot be created, [`RecordError::Write`] when
    /// the MCAP header cannot be written, [`RecordError::Spawn`] without a thread.
    pub fn create(path: impl AsRef<Path>, options: RecorderOptions) -> Result<Self, RecordError> {
        let path = path.as_ref().to_path_buf();
        let file = File::create(&path).map_err(|source| RecordError::Create {
            path: path.clone(),
            source,
        })?;
        Self::with_file(path, file, options)
    }

    /// Records into `file`, opened by the caller (e.g. created exclusively in a run
    /// directory); `path` names it in messages.
    ///
    /// # Errors
    /// As [`Recorder::create`], but for the file's creation.
    pub fn with_file(
        path: PathBuf,
        file: File,
        options: RecorderOptions,
    ) -> Result<Self, RecordError> {
        let sink = NoSeek::new(BufWriter::with_capacity(
            1 << 20,
            FileSink {
                file,
                fsync: options.fsync,
            },
        ));
        let write_options = WriteOptions::new()
            .compression(options.compress.then_some(Compression::Lz4))
            .library(format!("sdsem {}", env!("CARGO_PKG_VERSION")))
            // Whole chunks in memory, appended in one go: a crash cannot leave a chunk
            // header that promises bytes which never arrived.
            .disable_seeking(true);
        let writer = Writer::with_options(sink, write_options).map_err(|e| RecordError::Write {
            path: path.clone(),
            doing: "writing the MCAP header",
            cause: error_chain(&e),
        })?;

        let (tx, rx) = std::sync::mpsc::sync_channel(options.channel_capacity.max(1));
        let shared = Arc::new(Shared::default());
        let state = WriterState {
            path: path.clone(),
            writer: Some(writer),
            channels: HashMap::new(),
            sequence: HashMap::new(),
            per_topic: BTreeMap::new(),
            dirty: false,
            last_flush: Instant::now(),
            error: None,
            shared: Arc::clone(&shared),
            flush_interval: options.flush_interval,
        };
        let thread = std::thread::Builder::new()
            .name("sdsem-recorder".to_owned())
            .spawn(move || state.run(&rx))
            .map_err(|source| RecordError::Spawn {
                path: path.clone(),
                source,
            })?;
        Ok(Self {
            handle: RecorderHandle {
                tx,
                shared,
                path: Arc::new(path),
            },
            thread: Some(thread),
        })
    }

    /// A handle to send entries with; clone it freely.
    #[must_use]
    pub fn handle(&self) -> RecorderHandle {
        self.handle.clone()
    }

    /// Writes everything queued, the log-drop record if any, the summary and the footer,
    /// syncs the file and returns what was written — or the first error of the run.
    ///
    /// # Errors
    /// The first [`RecordError::Write`] of the run, or [`RecordError::WriterPanicked`].
    pub fn finish(mut self) -> Result<RecordSummary, RecordError> {
        self.finish_inner()
    }

    fn finish_inner(&mut self) -> Result<RecordSummary, RecordError> {
        let Some(thread) = self.thread.take() else {
            return Err(RecordError::Closed);
        };
        // New sends are refused from here on; what is queued is still written.
        self.handle.shared.finished.store(true, Ordering::Release);
        // The writer thread is alive until it sees Finish, so this only fails if it
        // panicked, which join() reports below.
        let _ = self.handle.tx.send(Command::Finish);
        thread.join().unwrap_or_else(|_| {
            Err(RecordError::WriterPanicked {
                path: self.handle.path.as_ref().clone(),
            })
        })
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        if self.thread.is_some() {
            tracing::error!(
                path = %self.handle.path.display(),
                "run record dropped without Recorder::finish(); finishing it now — \
                 call finish() explicitly to get its errors"
            );
            if let Err(e) = self.finish_inner() {
                tracing::error!(path = %self.handle.path.display(), "finishing the dropped run record failed: {e}");
            }
        }
    }
}

/// The file under the MCAP writer: `flush()` pushes to the OS and, if asked, to the disk.
struct FileSink {
    file: File,
    fsync: bool,
}

impl Write for FileSink {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.file.write(buf)
    }

    fn write_all(&mut self, buf: &[u8]) -> io::Result<()> {
        self.file.write_all(buf)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.file.flush()?;
        if self.fsync {
            self.file.sync_data()?;
        }
        Ok(())
    }
}

type McapWriter = Writer<NoSeek<BufWriter<FileSink>>>;

/// A failed writer operation: what was being done, and why it failed.
type WriteFailure = (&'static str, String);

fn failure(doing: &'static str, e: &dyn std::error::Error) -> WriteFailure {
    (doing, error_chain(e))
}

struct WriterState {
    path: PathBuf,
    writer: Option<McapWriter>,
    /// Channel id per (topic, schema name).
    channels: HashMap<(String, String), u16>,
    sequence: HashMap<u16, u32>,
    per_topic: BTreeMap<String, u64>,
    dirty: bool,
    last_flush: Instant,
    error: Option<RecordError>,
    shared: Arc<Shared>,
    flush_interval: Duration,
}

impl WriterState {
    fn run(mut self, rx: &Receiver<Command>) -> Result<RecordSummary, RecordError> {
        loop {
            match rx.recv_timeout(self.flush_interval) {
                Ok(Command::Write(entry)) => {
                    if self.error.is_none() {
                        self.write(entry);
                    }
                }
                Ok(Command::Finish) => {
                    // Entries that raced with finish() are written, not lost.
                    while let Ok(Command::Write(entry)) = rx.try_recv() {
                        if self.error.is_none() {
                            self.write(entry);
                        }
                    }
                    break;
                }
                Err(RecvTimeoutError::Disconnected) => break,
                Err(RecvTimeoutError::Timeout) => {}
            }
            if self.error.is_none()
                && self.dirty
                && self.last_flush.elapsed() >= self.flush_interval
            {
                self.flush();
            }
        }
        self.finish()
    }

    /// Records the first write error: the producer sees it in the status, `finish()`
    /// returns it, and nothing more is written.
    fn fail(&mut self, (doing, cause): WriteFailure) {
        let error = RecordError::Write {
            path: self.path.clone(),
            doing,
            cause,
        };
        if let Ok(mut failed) = self.shared.failed.lock() {
            *failed = Some(error.to_string());
        }
        self.shared.stopped.store(true, Ordering::Release);
        self.error = Some(error);
    }

    fn write(&mut self, entry: Entry) {
        match self.try_write(entry) {
            Ok(()) => {
                self.shared.written.fetch_add(1, Ordering::Relaxed);
            }
            Err(f) => self.fail(f),
        }
    }

    fn try_write(&mut self, entry: Entry) -> Result<(), WriteFailure> {
        let Some(writer) = self.writer.as_mut() else {
            return Ok(());
        };
        match entry.kind {
            EntryKind::Message {
                topic,
                channel,
                log_time_ns,
                data,
                cut_chunk,
            } => {
                let key = (topic, channel.schema_name.clone().into_owned());
                let channel_id = match self.channels.get(&key) {
                    Some(&id) => id,
                    None => {
                        let id = add_channel(writer, &key.0, &channel)?;
                        self.channels.insert(key.clone(), id);
                        id
                    }
                };
                let sequence = self.sequence.entry(channel_id).or_insert(0);
                *sequence = sequence.wrapping_add(1);
                let header = MessageHeader {
                    channel_id,
                    sequence: *sequence,
                    log_time: log_time_ns,
                    publish_time: log_time_ns,
                };
                writer
                    .write_to_known_channel(&header, &data)
                    .map_err(|e| failure("writing a message", &e))?;
                *self.per_topic.entry(key.0).or_insert(0) += 1;
                self.dirty = true;
                if cut_chunk {
                    self.try_flush()?;
                }
            }
            EntryKind::Metadata { name, entries } => {
                writer
                    .write_metadata(&Metadata {
                        name,
                        metadata: entries,
                    })
                    .map_err(|e| failure("writing a metadata record", &e))?;
                // Rare and precious (the run's configuration, its outcome): on
                // disk at once, so a run killed before its first frame still
                // leaves a readable record saying what it was.
                self.try_flush()?;
            }
            EntryKind::Attachment {
                log_time_ns,
                name,
                media_type,
                data,
            } => writer
                .attach(&Attachment {
                    log_time: log_time_ns,
                    create_time: log_time_ns,
                    name,
                    media_type,
                    data: data.into(),
                })
                .map_err(|e| failure("writing an attachment", &e))?,
        }
        Ok(())
    }

    /// Closes the open chunk and pushes it to the OS (and the disk with `fsync`).
    fn try_flush(&mut self) -> Result<(), WriteFailure> {
        if let Some(writer) = self.writer.as_mut() {
            writer
                .flush()
                .map_err(|e| failure("flushing a chunk", &e))?;
            self.dirty = false;
            self.last_flush = Instant::now();
        }
        Ok(())
    }

    fn flush(&mut self) {
        if let Err(f) = self.try_flush() {
            self.fail(f);
        }
    }

    fn finish(mut self) -> Result<RecordSummary, RecordError> {
        let drops = self.shared.log_drops.load(Ordering::Relaxed);
        if drops > 0 && self.error.is_none() {
            let mut entries = BTreeMap::new();
            entries.insert("dropped".to_owned(), drops.to_string());
            self.write(Entry::metadata(topics::METADATA_LOG_DROPS, entries));
        }
        if let Some(error) = self.error.take() {
            // into_inner() marks the writer finished without writing, so its Drop does not
            // try to append a summary after a failure.
            if let Some(writer) = self.writer.take() {
                drop(writer.into_inner());
            }
            return Err(error);
        }
        let Some(mut writer) = self.writer.take() else {
            return Err(RecordError::Closed);
        };
        let fail = |(doing, cause): WriteFailure| RecordError::Write {
            path: self.path.clone(),
            doing,
            cause,
        };
        let summary = writer
            .finish()
            .map_err(|e| fail(failure("writing the summary", &e)))?;
        let file = writer
            .into_inner()
            .into_inner()
            .into_inner()
            .map_err(|e| fail(failure("flushing the end of the file", e.error())))?
            .file;
        file.sync_all()
            .map_err(|e| fail(failure("syncing the file", &e)))?;
        let file_bytes = file.metadata().map(|m| m.len()).unwrap_or(0);
        let stats = summary.stats.unwrap_or_default();
        Ok(RecordSummary {
            path: self.path,
            messages: stats.message_count,
            messages_per_topic: self.per_topic,
            chunks: stats.chunk_count,
            attachments: stats.attachment_count,
            metadata_records: stats.metadata_count,
            time_range_ns: (stats.message_count > 0)
                .then_some((stats.message_start_time, stats.message_end_time)),
            log_messages_dropped: drops,
            file_bytes,
        })
    }
}

fn add_channel(
    writer: &mut McapWriter,
    topic: &str,
    channel: &ChannelSpec,
) -> Result<u16, WriteFailure> {
    let schema_id = writer
        .add_schema(
            &channel.schema_name,
            channel.schema_encoding,
            &channel.schema_data,
        )
        .map_err(|e| failure("adding a schema", &e))?;
    writer
        .add_channel(schema_id, topic, channel.message_encoding, &BTreeMap::new())
        .map_err(|e| failure("adding a channel", &e))
}
