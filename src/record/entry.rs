//! Entries for the recorder: messages encoded on the producer's thread, ready to write.
//!
//! Encoding (protobuf, JSON) happens where the entry is made, so the single writer thread
//! only appends bytes; an invalid message is refused at its source with a clear error.

use std::borrow::Cow;
use std::collections::BTreeMap;

use foxglove::Encode;
use foxglove::messages::{
    Color, CompressedImage, FrameTransform, FrameTransforms, ImageAnnotations, KeyValuePair, Log,
    ModelPrimitive, PackedElementField, Point2, PointCloud, Pose, Quaternion, RawImage,
    SceneEntity, SceneUpdate, TextAnnotation, Timestamp, Vector3, log::Level as FoxgloveLevel,
    packed_element_field::NumericType,
};
use serde::Serialize;

use super::error::RecordError;
use super::messages::{JsonSchema, json_schema_for};
use super::topics;
use crate::export::CloudPoint;
use crate::vision::Image;

/// Pixels of a raw image message, row-major, no padding.
#[derive(Debug, Clone, PartialEq)]
pub enum Pixels {
    /// `mono8`.
    Mono8(Vec<u8>),
    /// `mono16`, written little-endian.
    Mono16(Vec<u16>),
    /// `32FC1`, written little-endian (heights in µm, NaN unknown).
    Float32(Vec<f32>),
}

impl Pixels {
    /// The foxglove.RawImage `encoding` string.
    #[must_use]
    pub fn encoding(&self) -> &'static str {
        match self {
            Self::Mono8(_) => "mono8",
            Self::Mono16(_) => "mono16",
            Self::Float32(_) => "32FC1",
        }
    }

    /// Bytes per pixel.
    #[must_use]
    pub fn bytes_per_pixel(&self) -> usize {
        match self {
            Self::Mono8(_) => 1,
            Self::Mono16(_) => 2,
            Self::Float32(_) => 4,
        }
    }

    /// Number of pixels.
    #[must_use]
    pub fn len(&self) -> usize {
        match self {
            Self::Mono8(v) => v.len(),
            Self::Mono16(v) => v.len(),
            Self::Float32(v) => v.len(),
        }
    }

    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A micrograph in `[0, 1]` quantised to 16 bits (clamped; NaN becomes 0).
    #[must_use]
    pub fn mono16_from_image(image: &Image) -> Self {
        Self::Mono16(
            image
                .data()
                .iter()
                .map(|&v| {
                    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
                    // In [0, 65535.5) after clamping.
                    (v * 65535.0 + 0.5) as u16
                })
                .collect(),
        )
    }

    /// A micrograph in `[0, 1]` quantised to 8 bits (clamped; NaN becomes 0).
    #[must_use]
    pub fn mono8_from_image(image: &Image) -> Self {
        Self::Mono8(image.to_u8())
    }

    /// The samples of `image` as they are (height maps: µm, NaN unknown).
    #[must_use]
    pub fn float32_from_image(image: &Image) -> Self {
        Self::Float32(image.data().to_vec())
    }

    /// Samples as an [`Image`]: mono8/mono16 scaled to `[0, 1]`, 32FC1 unchanged.
    ///
    /// # Errors
    /// When `width × height` does not match the number of pixels.
    pub fn to_image(
        &self,
        width: usize,
        height: usize,
    ) -> Result<Image, crate::vision::image::SizeMismatch> {
        match self {
            Self::Mono8(v) => Image::from_u8(width, height, v),
            Self::Mono16(v) => Image::from_u16(width, height, v),
            Self::Float32(v) => Image::from_vec(width, height, v.clone()),
        }
    }

    fn to_le_bytes(&self) -> Vec<u8> {
        match self {
            Self::Mono8(v) => v.clone(),
            Self::Mono16(v) => v.iter().flat_map(|p| p.to_le_bytes()).collect(),
            Self::Float32(v) => v.iter().flat_map(|p| p.to_le_bytes()).collect(),
        }
    }

    /// Parses RawImage data of the given encoding; `None` for other encodings or a
    /// length that is not a whole number of pixels.
    #[must_use]
    pub fn from_le_bytes(encoding: &str, data: &[u8]) -> Option<Self> {
        match encoding {
            "mono8" | "8UC1" => Some(Self::Mono8(data.to_vec())),
            "mono16" | "16UC1" if data.len().is_multiple_of(2) => Some(Self::Mono16(
                data.chunks_exact(2)
                    .map(|b| u16::from_le_bytes([b[0], b[1]]))
                    .collect(),
            )),
            "32FC1" if data.len().is_multiple_of(4) => Some(Self::Float32(
                data.chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect(),
            )),
            _ => None,
        }
    }
}

/// Severity of a `/log` message (foxglove.Log levels).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize)]
pub enum LogLevel {
    Debug,
    Info,
    Warning,
    Error,
    Fatal,
}

impl LogLevel {
    fn foxglove(self) -> FoxgloveLevel {
        match self {
            Self::Debug => FoxgloveLevel::Debug,
            Self::Info => FoxgloveLevel::Info,
            Self::Warning => FoxgloveLevel::Warning,
            Self::Error => FoxgloveLevel::Error,
            Self::Fatal => FoxgloveLevel::Fatal,
        }
    }

    /// From a foxglove.Log `level` value; unknown values read as `Info`.
    #[must_use]
    pub fn from_foxglove(level: i32) -> Self {
        match FoxgloveLevel::try_from(level) {
            Ok(FoxgloveLevel::Debug) => Self::Debug,
            Ok(FoxgloveLevel::Warning) => Self::Warning,
            Ok(FoxgloveLevel::Error) => Self::Error,
            Ok(FoxgloveLevel::Fatal) => Self::Fatal,
            _ => Self::Info,
        }
    }

    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Debug => "DEBUG",
            Self::Info => "INFO",
            Self::Warning => "WARN",
            Self::Error => "ERROR",
            Self::Fatal => "FATAL",
        }
    }
}

/// Schema and message encoding of a channel.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub(crate) struct ChannelSpec {
    pub schema_name: Cow<'static, str>,
    pub schema_encoding: &'static str,
    pub schema_data: Cow<'static, [u8]>,
    pub message_encoding: &'static str,
}

impl ChannelSpec {
    fn foxglove<T: Encode>(topic: &str) -> Result<Self, RecordError> {
        let schema = T::get_schema().ok_or_else(|| RecordError::InvalidMessage {
            topic: topic.to_owned(),
            reason: "the foxglove message type has no schema".to_owned(),
        })?;
        let message_encoding = match T::get_message_encoding().as_str() {
            "protobuf" => "protobuf",
            "json" => "json",
            other => {
                return Err(RecordError::InvalidMessage {
                    topic: topic.to_owned(),
                    reason: format!("unexpected foxglove message encoding {other:?}"),
                });
            }
        };
        let schema_encoding = match schema.encoding.as_str() {
            "protobuf" => "protobuf",
            "jsonschema" => "jsonschema",
            other => {
                return Err(RecordError::InvalidMessage {
                    topic: topic.to_owned(),
                    reason: format!("unexpected foxglove schema encoding {other:?}"),
                });
            }
        };
        Ok(Self {
            schema_name: Cow::Owned(schema.name),
            schema_encoding,
            schema_data: schema.data,
            message_encoding,
        })
    }

    fn json(schema: JsonSchema) -> Self {
        Self {
            schema_name: Cow::Borrowed(schema.name),
            schema_encoding: "jsonschema",
            schema_data: Cow::Borrowed(schema.text.as_bytes()),
            message_encoding: "json",
        }
    }
}

/// What an entry writes.
#[derive(Debug)]
pub(crate) enum EntryKind {
    Message {
        topic: String,
        channel: ChannelSpec,
        log_time_ns: u64,
        data: Vec<u8>,
        /// Cut a chunk after this message so it survives a crash (frames, big results).
        cut_chunk: bool,
    },
    Metadata {
        name: String,
        entries: BTreeMap<String, String>,
    },
    Attachment {
        log_time_ns: u64,
        name: String,
        media_type: String,
        data: Vec<u8>,
    },
}

/// One record entry, encoded and ready for the writer thread.
///
/// Build it with the constructors here and hand it to
/// [`RecorderHandle::send`](super::RecorderHandle::send) (sync) or
/// [`RecorderHandle::send_async`](super::RecorderHandle::send_async) (async code).
#[derive(Debug)]
pub struct Entry {
    pub(crate) kind: EntryKind,
}

fn timestamp(log_time_ns: u64) -> Option<Timestamp> {
    let sec = u32::try_from(log_time_ns / 1_000_000_000).ok()?;
    // Below 10⁹ by construction.
    let nsec = (log_time_ns % 1_000_000_000) as u32;
    Timestamp::new_checked(sec, nsec)
}

/// At the frame's origin, axes along the frame's.
fn identity_pose() -> Pose {
    Pose {
        position: Some(Vector3 {
            x: 0.0,
            y: 0.0,
            z: 0.0,
        }),
        orientation: Some(identity_rotation()),
    }
}

fn identity_rotation() -> Quaternion {
    Quaternion {
        x: 0.0,
        y: 0.0,
        z: 0.0,
        w: 1.0,
    }
}

fn encode<T: Encode>(topic: &str, message: &T) -> Result<Vec<u8>, RecordError> {
    let mut data = Vec::with_capacity(message.encoded_len().unwrap_or(64));
    message
        .encode(&mut data)
        .map_err(|e| RecordError::InvalidMessage {
            topic: topic.to_owned(),
            reason: format!("protobuf encoding failed: {e}"),
        })?;
    Ok(data)
}

impl Entry {
    /// Whether a chunk is cut (and flushed) right after this message. Images
    /// cut one by default; a frame's image and its `/sem/frame_info` go
    /// together, so the image is written without a cut and the info with one:
    /// a crash never leaves a frame whose tilt and pixel size are lost.
    #[must_use]
    pub fn cutting_chunk(mut self, cut: bool) -> Self {
        if let EntryKind::Message { cut_chunk, .. } = &mut self.kind {
            *cut_chunk = cut;
        }
        self
    }

    /// A foxglove.RawImage: `mono8`, `mono16` or `32FC1` by the type of `pixels`.
    ///
    /// On [`topics::SEM_FRAME`] the `frame_id` is the [`topics::FrameRole`]
    /// (`tracking` / `left` / `right`); on [`topics::RECON_HEIGHT`] it is `left`
    /// (the grid the height map lies on).
    ///
    /// # Errors
    /// [`RecordError::InvalidMessage`] when `pixels` does not hold `width × height` samples.
    pub fn image(
        topic: &str,
        log_time_ns: u64,
        frame_id: &str,
        pixels: &Pixels,
        width: u32,
        height: u32,
    ) -> Result<Self, RecordError> {
        let expected = width as usize * height as usize;
        if expected == 0 {
            return Err(RecordError::InvalidMessage {
                topic: topic.to_owned(),
                reason: format!("empty image ({width} × {height})"),
            });
        }
        if pixels.len() != expected {
            return Err(RecordError::InvalidMessage {
                topic: topic.to_owned(),
                reason: format!(
                    "{} image of {width} × {height} needs {expected} pixels, got {}",
                    pixels.encoding(),
                    pixels.len()
                ),
            });
        }
        let message = RawImage {
            timestamp: timestamp(log_time_ns),
            frame_id: frame_id.to_owned(),
            width,
            height,
            encoding: pixels.encoding().to_owned(),
            // width × bytes per pixel ≤ 4 × u32::MAX only for absurd images; refuse those.
            step: u32::try_from(width as usize * pixels.bytes_per_pixel()).map_err(|_| {
                RecordError::InvalidMessage {
                    topic: topic.to_owned(),
                    reason: format!("row of {width} pixels is too long"),
                }
            })?,
            data: pixels.to_le_bytes().into(),
        };
        Self::message::<RawImage>(topic, log_time_ns, &message, true)
    }

    /// A foxglove.CompressedImage holding PNG bytes.
    ///
    /// # Errors
    /// [`RecordError::InvalidMessage`] when `png` does not start with the PNG signature.
    pub fn compressed_png(
        topic: &str,
        log_time_ns: u64,
        frame_id: &str,
        png: Vec<u8>,
    ) -> Result<Self, RecordError> {
        if !png.starts_with(b"\x89PNG\r\n\x1a\n") {
            return Err(RecordError::InvalidMessage {
                topic: topic.to_owned(),
                reason: "the data is not a PNG file".to_owned(),
            });
        }
        let message = CompressedImage {
            timestamp: timestamp(log_time_ns),
            frame_id: frame_id.to_owned(),
            data: png.into(),
            format: "png".to_owned(),
        };
        Self::message::<CompressedImage>(topic, log_time_ns, &message, true)
    }

    /// A foxglove.PointCloud of `x y z intensity` float32 points (µm), pose identity.
    ///
    /// # Errors
    /// Only when protobuf encoding fails.
    pub fn point_cloud(
        topic: &str,
        log_time_ns: u64,
        frame_id: &str,
        points: &[CloudPoint],
    ) -> Result<Self, RecordError> {
        let field = |name: &str, offset: u32| PackedElementField {
            name: name.to_owned(),
            offset,
            r#type: NumericType::Float32 as i32,
        };
        let mut data = Vec::with_capacity(points.len() * 16);
        for p in points {
            for v in [p.x, p.y, p.z, p.intensity] {
                data.extend_from_slice(&v.to_le_bytes());
            }
        }
        let message = PointCloud {
            timestamp: timestamp(log_time_ns),
            frame_id: frame_id.to_owned(),
            pose: Some(identity_pose()),
            point_stride: 16,
            fields: vec![
                field("x", 0),
                field("y", 4),
                field("z", 8),
                field("intensity", 12),
            ],
            data: data.into(),
        };
        Self::message::<PointCloud>(topic, log_time_ns, &message, true)
    }

    /// A foxglove.FrameTransforms: each `(parent, child, translation)` places the child
    /// frame's origin at `translation` in its parent, axes parallel (no rotation).
    ///
    /// # Errors
    /// Only when protobuf encoding fails.
    pub fn frame_transforms(
        topic: &str,
        log_time_ns: u64,
        transforms: &[(&str, &str, [f64; 3])],
    ) -> Result<Self, RecordError> {
        let message = FrameTransforms {
            transforms: transforms
                .iter()
                .map(|&(parent, child, [x, y, z])| FrameTransform {
                    timestamp: timestamp(log_time_ns),
                    parent_frame_id: parent.to_owned(),
                    child_frame_id: child.to_owned(),
                    translation: Some(Vector3 { x, y, z }),
                    rotation: Some(identity_rotation()),
                })
                .collect(),
        };
        Self::message::<FrameTransforms>(topic, log_time_ns, &message, false)
    }

    /// A foxglove.SceneUpdate with one entity `id` in `frame_id` holding one model
    /// (foxglove.ModelPrimitive) embedded as `data` of `media_type`, at the frame's origin,
    /// scale 1; `metadata` shows beside it in Foxglove.
    ///
    /// # Errors
    /// [`RecordError::InvalidMessage`] for empty model data.
    pub fn scene_model(
        topic: &str,
        log_time_ns: u64,
        frame_id: &str,
        id: &str,
        model: (&str, Vec<u8>),
        metadata: &[(&str, String)],
    ) -> Result<Self, RecordError> {
        let (media_type, data) = model;
        if data.is_empty() {
            return Err(RecordError::InvalidMessage {
                topic: topic.to_owned(),
                reason: "empty model".to_owned(),
            });
        }
        let message = SceneUpdate {
            deletions: Vec::new(),
            entities: vec![SceneEntity {
                timestamp: timestamp(log_time_ns),
                frame_id: frame_id.to_owned(),
                id: id.to_owned(),
                lifetime: None,
                frame_locked: true,
                metadata: metadata
                    .iter()
                    .map(|(key, value)| KeyValuePair {
                        key: (*key).to_owned(),
                        value: value.clone(),
                    })
                    .collect(),
                models: vec![ModelPrimitive {
                    pose: Some(identity_pose()),
                    scale: Some(Vector3 {
                        x: 1.0,
                        y: 1.0,
                        z: 1.0,
                    }),
                    color: None,
                    override_color: false,
                    url: String::new(),
                    media_type: media_type.to_owned(),
                    data: data.into(),
                }],
                ..SceneEntity::default()
            }],
        };
        Self::message::<SceneUpdate>(topic, log_time_ns, &message, true)
    }

    /// A foxglove.ImageAnnotations of text lines at the top left of an image, white on a
    /// dark box (a legend).
    ///
    /// # Errors
    /// Only when protobuf encoding fails.
    pub fn image_text(
        topic: &str,
        log_time_ns: u64,
        lines: &[String],
    ) -> Result<Self, RecordError> {
        const FONT_PX: f64 = 14.0;
        let message = ImageAnnotations {
            timestamp: timestamp(log_time_ns),
            texts: lines
                .iter()
                .zip(1u32..)
                .map(|(text, row)| TextAnnotation {
                    timestamp: timestamp(log_time_ns),
                    // Bottom-left corner of the line, in image pixels.
                    position: Some(Point2 {
                        x: 4.0,
                        y: f64::from(row) * (FONT_PX + 4.0),
                    }),
                    text: text.clone(),
                    font_size: FONT_PX,
                    text_color: Some(Color {
                        r: 1.0,
                        g: 1.0,
                        b: 1.0,
                        a: 1.0,
                    }),
                    background_color: Some(Color {
                        r: 0.0,
                        g: 0.0,
                        b: 0.0,
                        a: 0.7,
                    }),
                    metadata: Vec::new(),
                })
                .collect(),
            ..ImageAnnotations::default()
        };
        Self::message::<ImageAnnotations>(topic, log_time_ns, &message, false)
    }

    /// A JSON message with the topic's schema ([`json_schema_for`]).
    ///
    /// # Errors
    /// [`RecordError::Json`] when `value` cannot be serialised.
    pub fn json(
        topic: &str,
        log_time_ns: u64,
        value: &impl Serialize,
    ) -> Result<Self, RecordError> {
        Self::json_with_schema(topic, log_time_ns, json_schema_for(topic), value)
    }

    /// A JSON message with an explicit schema (for topics beyond the contract).
    ///
    /// # Errors
    /// [`RecordError::Json`] when `value` cannot be serialised.
    pub fn json_with_schema(
        topic: &str,
        log_time_ns: u64,
        schema: JsonSchema,
        value: &impl Serialize,
    ) -> Result<Self, RecordError> {
        let data = serde_json::to_vec(value).map_err(|source| RecordError::Json {
            topic: topic.to_owned(),
            source,
        })?;
        Ok(Self {
            kind: EntryKind::Message {
                topic: topic.to_owned(),
                channel: ChannelSpec::json(schema),
                log_time_ns,
                data,
                cut_chunk: false,
            },
        })
    }

    /// A foxglove.Log message on [`topics::LOG`].
    ///
    /// # Errors
    /// Only when protobuf encoding fails.
    pub fn log(
        log_time_ns: u64,
        level: LogLevel,
        message: &str,
        name: &str,
        file: &str,
        line: u32,
    ) -> Result<Self, RecordError> {
        let message = Log {
            timestamp: timestamp(log_time_ns),
            level: level.foxglove() as i32,
            message: message.to_owned(),
            name: name.to_owned(),
            file: file.to_owned(),
            line,
        };
        Self::message::<Log>(topics::LOG, log_time_ns, &message, false)
    }

    /// An MCAP metadata record (e.g. [`topics::METADATA_RUN`] with job, configuration,
    /// version and host).
    #[must_use]
    pub fn metadata(name: &str, entries: BTreeMap<String, String>) -> Self {
        Self {
            kind: EntryKind::Metadata {
                name: name.to_owned(),
                entries,
            },
        }
    }

    /// An MCAP attachment (e.g. [`topics::ATTACHMENT_HEIGHT_GSF`]).
    #[must_use]
    pub fn attachment(log_time_ns: u64, name: &str, media_type: &str, data: Vec<u8>) -> Self {
        Self {
            kind: EntryKind::Attachment {
                log_time_ns,
                name: name.to_owned(),
                media_type: media_type.to_owned(),
                data,
            },
        }
    }

    fn message<T: Encode>(
        topic: &str,
        log_time_ns: u64,
        message: &T,
        cut_chunk: bool,
    ) -> Result<Self, RecordError> {
        Ok(Self {
            kind: EntryKind::Message {
                topic: topic.to_owned(),
                channel: ChannelSpec::foxglove::<T>(topic)?,
                log_time_ns,
                data: encode(topic, message)?,
                cut_chunk,
            },
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_refuses_wrong_pixel_count() {
        let err = Entry::image(
            topics::SEM_FRAME,
            0,
            "left",
            &Pixels::Mono8(vec![0; 5]),
            3,
            2,
        )
        .unwrap_err();
        assert!(err.to_string().contains("needs 6 pixels, got 5"), "{err}");
    }

    #[test]
    fn pixels_round_trip_through_bytes() {
        for px in [
            Pixels::Mono8(vec![0, 7, 255]),
            Pixels::Mono16(vec![0, 513, 65535]),
            Pixels::Float32(vec![-1.5, f32::INFINITY, 3.25]),
        ] {
            let back = Pixels::from_le_bytes(px.encoding(), &px.to_le_bytes()).unwrap();
            assert_eq!(back, px);
        }
        assert!(Pixels::from_le_bytes("mono16", &[1, 2, 3]).is_none());
        assert!(Pixels::from_le_bytes("rgb8", &[1, 2, 3]).is_none());
    }

    #[test]
    fn mono16_quantises_micrograph_and_survives_nan() {
        let img = Image::from_vec(4, 1, vec![0.0, 1.0, 0.5, f32::NAN]).unwrap();
        let Pixels::Mono16(v) = Pixels::mono16_from_image(&img) else {
            panic!("not mono16")
        };
        assert_eq!(v, vec![0, 65535, 32768, 0]);
    }

    #[test]
    fn png_must_be_png() {
        assert!(Entry::compressed_png(topics::SEM_FRAME, 0, "left", b"GIF89a".to_vec()).is_err());
    }
}
