//! Reading a run record back — also a truncated one.
//!
//! The file is read linearly from the start (never through its summary, which a killed run
//! never wrote), and the first error after the header is treated as the end of the
//! readable data (DESIGN §8): every chunk completed before a crash is recovered. Chunk
//! CRCs are checked before any record of a chunk is handed out, so a damaged tail never
//! yields a half-written message.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::Read;
use std::path::Path;

use foxglove::Decode;
use foxglove::messages::{CompressedImage, Log, PointCloud, RawImage};
use mcap::records::Record;
use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
use serde::de::DeserializeOwned;

use super::entry::{LogLevel, Pixels};
use super::error::ReadError;
use super::messages::FrameInfo;
use super::topics::{self, FrameRole};
use crate::export::CloudPoint;
use crate::vision::Image;

/// Smallest record length limit: 1 GiB.
const MIN_RECORD_LIMIT: u64 = 1 << 30;

/// How the linear read of a record ended.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct ScanEnd {
    /// The file ended properly (data end, summary, footer, end magic).
    pub complete: bool,
    /// Why reading stopped early: the error that marks the end of the readable data.
    pub stopped_by: Option<String>,
    /// Bytes of the file that were read.
    pub bytes_read: u64,
}

/// A channel as announced in the record.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChannelInfo {
    pub topic: String,
    pub schema_name: String,
    pub schema_encoding: String,
    pub message_encoding: String,
}

/// One item of the data section.
#[derive(Debug)]
pub(crate) enum ScanItem<'a> {
    Header {
        profile: &'a str,
        library: &'a str,
    },
    Message {
        channel: &'a ChannelInfo,
        log_time_ns: u64,
        data: &'a [u8],
    },
    Metadata {
        name: &'a str,
        entries: &'a BTreeMap<String, String>,
    },
    Attachment {
        name: &'a str,
        media_type: &'a str,
        log_time_ns: u64,
        data: &'a [u8],
    },
}

/// Reads the record at `path` linearly, handing every item of the data section to
/// `visit`; stops early, without error, at the first damaged or missing byte.
///
/// # Errors
/// [`ReadError::Open`]/[`ReadError::Io`] on I/O failure, [`ReadError::NotMcap`] when the
/// file does not start with the MCAP magic and header, and any error `visit` returns.
pub(crate) fn scan(
    path: &Path,
    mut visit: impl FnMut(ScanItem<'_>) -> Result<(), ReadError>,
) -> Result<ScanEnd, ReadError> {
    let mut file = File::open(path).map_err(|source| ReadError::Open {
        path: path.to_path_buf(),
        source,
    })?;
    let file_len = file.metadata().map(|m| m.len()).unwrap_or(u64::MAX);
    // Bounds what a garbage length field can make us allocate. The limit also applies to
    // a chunk's decompressed size, which may exceed a (truncated) file's length, hence the
    // floor well above any frame this program records.
    let limit = usize::try_from(file_len.max(MIN_RECORD_LIMIT)).unwrap_or(usize::MAX);
    let mut reader = LinearReader::new_with_options(
        LinearReaderOptions::default()
            .with_record_length_limit(limit)
            .with_prevalidate_chunk_crcs(true),
    );
    let mut schemas: HashMap<u16, (String, String)> = HashMap::new();
    let mut channels: HashMap<u16, ChannelInfo> = HashMap::new();
    let mut seen_header = false;
    let mut past_data_end = false;
    let mut bytes_read: u64 = 0;

    while let Some(event) = reader.next_event() {
        let event = match event {
            Ok(event) => event,
            Err(e) => {
                if !seen_header {
                    return Err(ReadError::NotMcap {
                        path: path.to_path_buf(),
                        cause: e.to_string(),
                    });
                }
                return Ok(ScanEnd {
                    complete: false,
                    stopped_by: Some(describe_stop(&e, bytes_read, file_len)),
                    bytes_read,
                });
            }
        };
        match event {
            LinearReadEvent::ReadRequest(need) => {
                let buf = reader.insert(need);
                let n = read_some(&mut file, buf).map_err(|source| ReadError::Io {
                    path: path.to_path_buf(),
                    source,
                })?;
                reader.notify_read(n);
                bytes_read += n as u64;
            }
            LinearReadEvent::Record { opcode, data } => {
                let record = match mcap::parse_record(opcode, data) {
                    Ok(record) => record,
                    Err(e) => {
                        if !seen_header {
                            return Err(ReadError::NotMcap {
                                path: path.to_path_buf(),
                                cause: e.to_string(),
                            });
                        }
                        return Ok(ScanEnd {
                            complete: false,
                            stopped_by: Some(format!("unreadable record: {e}")),
                            bytes_read,
                        });
                    }
                };
                match record {
                    Record::Header(header) => {
                        seen_header = true;
                        visit(ScanItem::Header {
                            profile: &header.profile,
                            library: &header.library,
                        })?;
                    }
                    // The summary repeats schemas and channels; nothing after the data
                    // end is data.
                    Record::DataEnd(_) => past_data_end = true,
                    _ if past_data_end => {}
                    Record::Schema { header, .. } => {
                        schemas.insert(header.id, (header.name, header.encoding));
                    }
                    Record::Channel(channel) => {
                        let (schema_name, schema_encoding) =
                            schemas.get(&channel.schema_id).cloned().unwrap_or_default();
                        channels.insert(
                            channel.id,
                            ChannelInfo {
                                topic: channel.topic,
                                schema_name,
                                schema_encoding,
                                message_encoding: channel.message_encoding,
                            },
                        );
                    }
                    Record::Message { header, data } => {
                        // A message on an unknown channel cannot be interpreted; the
                        // writer never produces one, so skip it rather than stop.
                        if let Some(channel) = channels.get(&header.channel_id) {
                            visit(ScanItem::Message {
                                channel,
                                log_time_ns: header.log_time,
                                data: &data,
                            })?;
                        }
                    }
                    Record::Metadata(metadata) => visit(ScanItem::Metadata {
                        name: &metadata.name,
                        entries: &metadata.metadata,
                    })?,
                    Record::Attachment { header, data, .. } => visit(ScanItem::Attachment {
                        name: &header.name,
                        media_type: &header.media_type,
                        log_time_ns: header.log_time,
                        data: &data,
                    })?,
                    _ => {}
                }
            }
        }
    }
    Ok(ScanEnd {
        complete: true,
        stopped_by: None,
        bytes_read,
    })
}

fn describe_stop(e: &mcap::McapError, bytes_read: u64, file_len: u64) -> String {
    match e {
        mcap::McapError::UnexpectedEof => format!(
            "the file ends in the middle of a record after {bytes_read} of {file_len} bytes \
             (the recording was cut off)"
        ),
        other => format!("{other} after {bytes_read} of {file_len} bytes"),
    }
}

fn read_some(file: &mut File, buf: &mut [u8]) -> std::io::Result<usize> {
    loop {
        match file.read(buf) {
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            other => return other,
        }
    }
}

/// Items extracted from a record, and how the read ended.
#[derive(Debug, Clone)]
pub struct Extract<T> {
    pub items: Vec<T>,
    pub end: ScanEnd,
}

/// An image message read back (`/sem/frame` or `/recon/height`).
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedImage {
    pub topic: String,
    pub log_time_ns: u64,
    /// `tracking` / `left` / `right` on `/sem/frame`.
    pub frame_id: String,
    pub width: u32,
    pub height: u32,
    pub pixels: Pixels,
}

impl RecordedImage {
    /// The pixels as an [`Image`]: micrographs in `[0, 1]`, 32FC1 (heights, µm) unchanged.
    ///
    /// # Errors
    /// When the message's size fields disagree with its data.
    pub fn to_image(&self) -> Result<Image, crate::vision::image::SizeMismatch> {
        self.pixels
            .to_image(self.width as usize, self.height as usize)
    }
}

/// A JSON message read back.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedJson {
    pub log_time_ns: u64,
    pub value: serde_json::Value,
}

impl RecordedJson {
    /// The message as a typed value (e.g. [`super::FrameInfo`]).
    ///
    /// # Errors
    /// When the JSON does not fit `T`.
    pub fn parse<T: DeserializeOwned>(&self) -> Result<T, serde_json::Error> {
        T::deserialize(&self.value)
    }
}

/// A metadata record read back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MetadataRecord {
    pub name: String,
    pub entries: BTreeMap<String, String>,
}

/// An attachment read back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordedAttachment {
    pub name: String,
    pub media_type: String,
    pub log_time_ns: u64,
    pub data: Vec<u8>,
}

/// A `/log` message read back.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordedLog {
    pub log_time_ns: u64,
    pub level: LogLevel,
    pub message: String,
    pub name: String,
    pub file: String,
    pub line: u32,
}

/// A point cloud read back.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedPointCloud {
    pub log_time_ns: u64,
    pub frame_id: String,
    pub points: Vec<CloudPoint>,
}

pub(crate) fn decode_error(path: &Path, channel: &ChannelInfo, cause: impl ToString) -> ReadError {
    ReadError::Decode {
        path: path.to_path_buf(),
        topic: channel.topic.clone(),
        schema: channel.schema_name.clone(),
        cause: cause.to_string(),
    }
}

/// Decodes an image message of either foxglove image schema.
pub(crate) fn decode_image(
    path: &Path,
    channel: &ChannelInfo,
    log_time_ns: u64,
    data: &[u8],
) -> Result<RecordedImage, ReadError> {
    match channel.schema_name.as_str() {
        "foxglove.RawImage" => {
            let raw = RawImage::decode(data).map_err(|e| decode_error(path, channel, e))?;
            let row_bytes = raw.width as usize
                * match raw.encoding.as_str() {
                    "mono16" | "16UC1" => 2,
                    "32FC1" => 4,
                    _ => 1,
                };
            // Drop row padding, if a foreign writer used any.
            let packed: Vec<u8> = if raw.step as usize > row_bytes && row_bytes > 0 {
                raw.data
                    .chunks(raw.step as usize)
                    .flat_map(|row| &row[..row_bytes.min(row.len())])
                    .copied()
                    .collect()
            } else {
                raw.data.to_vec()
            };
            let pixels = Pixels::from_le_bytes(&raw.encoding, &packed).ok_or_else(|| {
                decode_error(
                    path,
                    channel,
                    format!("unsupported image encoding {:?}", raw.encoding),
                )
            })?;
            if pixels.len() != raw.width as usize * raw.height as usize {
                return Err(decode_error(
                    path,
                    channel,
                    format!(
                        "{} × {} image holds {} pixels",
                        raw.width,
                        raw.height,
                        pixels.len()
                    ),
                ));
            }
            Ok(RecordedImage {
                topic: channel.topic.clone(),
                log_time_ns,
                frame_id: raw.frame_id,
                width: raw.width,
                height: raw.height,
                pixels,
            })
        }
        "foxglove.CompressedImage" => {
            let compressed =
                CompressedImage::decode(data).map_err(|e| decode_error(path, channel, e))?;
            let decoded = image::load_from_memory(&compressed.data)
                .map_err(|e| decode_error(path, channel, e))?;
            let (width, height) = (decoded.width(), decoded.height());
            let pixels = match decoded {
                image::DynamicImage::ImageLuma16(buf) => Pixels::Mono16(buf.into_raw()),
                other => Pixels::Mono8(other.into_luma8().into_raw()),
            };
            Ok(RecordedImage {
                topic: channel.topic.clone(),
                log_time_ns,
                frame_id: compressed.frame_id,
                width,
                height,
                pixels,
            })
        }
        other => Err(decode_error(
            path,
            channel,
            format!("schema {other} is not an image schema"),
        )),
    }
}

/// Reads the frame id of an image message without converting its pixels.
pub(crate) fn image_frame_id(channel: &ChannelInfo, data: &[u8]) -> Option<String> {
    match channel.schema_name.as_str() {
        "foxglove.RawImage" => RawImage::decode(data).ok().map(|m| m.frame_id),
        "foxglove.CompressedImage" => CompressedImage::decode(data).ok().map(|m| m.frame_id),
        _ => None,
    }
}

/// Image messages of `topic` whose frame id passes `keep` (e.g. the end micrographs:
/// `read_images(path, topics::SEM_FRAME, |id| id != "tracking")`).
///
/// # Errors
/// As [`scan`], and [`ReadError::Decode`] for an undecodable image.
pub fn read_images(
    path: impl AsRef<Path>,
    topic: &str,
    keep: impl Fn(&str) -> bool,
) -> Result<Extract<RecordedImage>, ReadError> {
    let path = path.as_ref();
    let mut items = Vec::new();
    let end = scan(path, |item| {
        if let ScanItem::Message {
            channel,
            log_time_ns,
            data,
        } = item
            && channel.topic == topic
            && image_frame_id(channel, data).is_some_and(|id| keep(&id))
        {
            items.push(decode_image(path, channel, log_time_ns, data)?);
        }
        Ok(())
    })?;
    Ok(Extract { items, end })
}

/// JSON messages of `topic`, in record order.
///
/// # Errors
/// As [`scan`], and [`ReadError::Decode`] for a message that is not JSON.
pub fn read_json(path: impl AsRef<Path>, topic: &str) -> Result<Extract<RecordedJson>, ReadError> {
    let path = path.as_ref();
    let mut items = Vec::new();
    let end = scan(path, |item| {
        if let ScanItem::Message {
            channel,
            log_time_ns,
            data,
        } = item
            && channel.topic == topic
            && channel.message_encoding == "json"
        {
            let value = serde_json::from_slice(data).map_err(|e| decode_error(path, channel, e))?;
            items.push(RecordedJson { log_time_ns, value });
        }
        Ok(())
    })?;
    Ok(Extract { items, end })
}

/// All metadata records, in record order.
///
/// # Errors
/// As [`scan`].
pub fn read_metadata(path: impl AsRef<Path>) -> Result<Extract<MetadataRecord>, ReadError> {
    let mut items = Vec::new();
    let end = scan(path.as_ref(), |item| {
        if let ScanItem::Metadata { name, entries } = item {
            items.push(MetadataRecord {
                name: name.to_owned(),
                entries: entries.clone(),
            });
        }
        Ok(())
    })?;
    Ok(Extract { items, end })
}

/// Attachments whose name passes `keep`, with their bytes.
///
/// # Errors
/// As [`scan`].
pub fn read_attachments(
    path: impl AsRef<Path>,
    keep: impl Fn(&str) -> bool,
) -> Result<Extract<RecordedAttachment>, ReadError> {
    let mut items = Vec::new();
    let end = scan(path.as_ref(), |item| {
        if let ScanItem::Attachment {
            name,
            media_type,
            log_time_ns,
            data,
        } = item
            && keep(name)
        {
            items.push(RecordedAttachment {
                name: name.to_owned(),
                media_type: media_type.to_owned(),
                log_time_ns,
                data: data.to_vec(),
            });
        }
        Ok(())
    })?;
    Ok(Extract { items, end })
}

/// All `/log` messages.
///
/// # Errors
/// As [`scan`], and [`ReadError::Decode`] for an undecodable message.
pub fn read_logs(path: impl AsRef<Path>) -> Result<Extract<RecordedLog>, ReadError> {
    let path = path.as_ref();
    let mut items = Vec::new();
    let end = scan(path, |item| {
        if let ScanItem::Message {
            channel,
            log_time_ns,
            data,
        } = item
            && channel.topic == topics::LOG
            && channel.schema_name == "foxglove.Log"
        {
            let log = Log::decode(data).map_err(|e| decode_error(path, channel, e))?;
            items.push(RecordedLog {
                log_time_ns,
                level: LogLevel::from_foxglove(log.level),
                message: log.message,
                name: log.name,
                file: log.file,
                line: log.line,
            });
        }
        Ok(())
    })?;
    Ok(Extract { items, end })
}

/// All point clouds of `topic` with `x y z intensity` float32 fields.
///
/// # Errors
/// As [`scan`], and [`ReadError::Decode`] for a cloud of another layout.
pub fn read_point_clouds(
    path: impl AsRef<Path>,
    topic: &str,
) -> Result<Extract<RecordedPointCloud>, ReadError> {
    let path = path.as_ref();
    let mut items = Vec::new();
    let end = scan(path, |item| {
        if let ScanItem::Message {
            channel,
            log_time_ns,
            data,
        } = item
            && channel.topic == topic
            && channel.schema_name == "foxglove.PointCloud"
        {
            let cloud = PointCloud::decode(data).map_err(|e| decode_error(path, channel, e))?;
            let names: Vec<(&str, u32)> = cloud
                .fields
                .iter()
                .map(|f| (f.name.as_str(), f.offset))
                .collect();
            if names != [("x", 0), ("y", 4), ("z", 8), ("intensity", 12)]
                || cloud.point_stride != 16
            {
                return Err(decode_error(
                    path,
                    channel,
                    "expected float32 fields x y z intensity with stride 16",
                ));
            }
            let f = |b: &[u8]| f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            let points = cloud
                .data
                .chunks_exact(16)
                .map(|p| CloudPoint {
                    x: f(&p[0..4]),
                    y: f(&p[4..8]),
                    z: f(&p[8..12]),
                    intensity: f(&p[12..16]),
                })
                .collect();
            items.push(RecordedPointCloud {
                log_time_ns,
                frame_id: cloud.frame_id,
                points,
            });
        }
        Ok(())
    })?;
    Ok(Extract { items, end })
}

/// An end micrograph read back with its acquisition parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordedMicrograph {
    pub role: FrameRole,
    pub log_time_ns: u64,
    /// Intensities in `[0, 1]`.
    pub image: Image,
    /// The `/sem/frame_info` of the same log time (tilt, pixel size, …), if recorded.
    pub info: Option<FrameInfo>,
}

/// The left and right micrographs of a run, for `sdsem replay`.
#[derive(Debug, Clone, PartialEq)]
pub struct EndMicrographs {
    pub left: Option<RecordedMicrograph>,
    pub right: Option<RecordedMicrograph>,
    pub end: ScanEnd,
}

/// The last `left` and `right` frames of the record with their frame info, in one pass.
///
/// # Errors
/// As [`scan`], and [`ReadError::Decode`] for an undecodable frame or frame info.
pub fn read_end_micrographs(path: impl AsRef<Path>) -> Result<EndMicrographs, ReadError> {
    let path = path.as_ref();
    let mut ends = EndCollector::default();
    let end = scan(path, |item| ends.visit(path, &item))?;
    ends.finish(path, end)
}

/// Collects the end micrographs and their frame info from the items of a scan.
#[derive(Default)]
struct EndCollector {
    frames: Vec<(FrameRole, RecordedImage)>,
    infos: Vec<(u64, FrameInfo)>,
}

impl EndCollector {
    fn visit(&mut self, path: &Path, item: &ScanItem<'_>) -> Result<(), ReadError> {
        let ScanItem::Message {
            channel,
            log_time_ns,
            data,
        } = item
        else {
            return Ok(());
        };
        if channel.topic == topics::SEM_FRAME
            && let Some(role) = image_frame_id(channel, data)
                .and_then(|id| id.parse::<FrameRole>().ok())
                .filter(|r| *r != FrameRole::Tracking)
        {
            self.frames.retain(|(r, _)| *r != role);
            self.frames
                .push((role, decode_image(path, channel, *log_time_ns, data)?));
        } else if channel.topic == topics::SEM_FRAME_INFO && channel.message_encoding == "json" {
            let info: FrameInfo =
                serde_json::from_slice(data).map_err(|e| decode_error(path, channel, e))?;
            if info.role != FrameRole::Tracking {
                self.infos.push((*log_time_ns, info));
            }
        }
        Ok(())
    }

    fn finish(mut self, path: &Path, end: ScanEnd) -> Result<EndMicrographs, ReadError> {
        let left = self.pick(path, FrameRole::Left)?;
        let right = self.pick(path, FrameRole::Right)?;
        Ok(EndMicrographs { left, right, end })
    }

    fn pick(
        &mut self,
        path: &Path,
        role: FrameRole,
    ) -> Result<Option<RecordedMicrograph>, ReadError> {
        let Some(pos) = self.frames.iter().position(|(r, _)| *r == role) else {
            return Ok(None);
        };
        let (_, frame) = self.frames.swap_remove(pos);
        let image = frame.to_image().map_err(|e| ReadError::Decode {
            path: path.to_path_buf(),
            topic: topics::SEM_FRAME.to_owned(),
            schema: "foxglove.RawImage".to_owned(),
            cause: e.to_string(),
        })?;
        let info = self
            .infos
            .iter()
            .rev()
            .find(|(t, i)| i.role == role && *t == frame.log_time_ns)
            .or_else(|| self.infos.iter().rev().find(|(_, i)| i.role == role))
            .map(|(_, i)| i.clone());
        Ok(Some(RecordedMicrograph {
            role,
            log_time_ns: frame.log_time_ns,
            image,
            info,
        }))
    }
}

/// What `sdsem replay` needs from a record, read in one pass.
#[derive(Debug, Clone)]
pub struct ReplayInputs {
    /// The entries of the `sdsem.run` metadata record (job, effective configuration, …).
    pub run: Option<BTreeMap<String, String>>,
    /// How the run ended (`sdsem.outcome`), if the record got that far.
    pub outcome: Option<super::RunOutcome>,
    /// The end micrographs with their frame info; `end` says how the read ended.
    pub ends: EndMicrographs,
    /// The last `/recon/height` message (32FC1, µm).
    pub height: Option<RecordedImage>,
}

/// The run metadata, the outcome, the end micrographs and the recorded height map.
///
/// # Errors
/// As [`scan`], and [`ReadError::Decode`] for an undecodable frame or height map.
pub fn read_replay_inputs(path: impl AsRef<Path>) -> Result<ReplayInputs, ReadError> {
    let path = path.as_ref();
    let mut ends = EndCollector::default();
    let mut run = None;
    let mut outcome = None;
    let mut height = None;
    let end = scan(path, |item| {
        match &item {
            ScanItem::Metadata { name, entries } if *name == topics::METADATA_RUN => {
                run = Some((*entries).clone());
            }
            ScanItem::Metadata { name, entries } if *name == topics::METADATA_OUTCOME => {
                outcome = super::RunOutcome::from_map(entries);
            }
            ScanItem::Message {
                channel,
                log_time_ns,
                data,
            } if channel.topic == topics::RECON_HEIGHT => {
                height = Some(decode_image(path, channel, *log_time_ns, data)?);
            }
            _ => {}
        }
        ends.visit(path, &item)
    })?;
    Ok(ReplayInputs {
        run,
        outcome,
        ends: ends.finish(path, end)?,
        height,
    })
}
