//! The JSON messages of the run record and their JSON schemas (DESIGN §5).
//!
//! Each JSON topic gets a channel whose schema (encoding `jsonschema`) describes its
//! messages, so Foxglove and any MCAP reader can make sense of them. The structs here
//! are the wire format; producers fill them, `sdsem replay` and `sdsem inspect` read
//! them back. Fields carry their unit in their name.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use super::topics::{self, FrameRole};

/// One `/sem/frame_info` message, published right after its `/sem/frame` image with the
/// same log time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameInfo {
    /// tracking / left / right — equal to the image's `frame_id`.
    pub role: FrameRole,
    /// Number of the frame within the run, from 0, in capture order.
    pub index: u64,
    /// Stage tilt when the frame was captured, degrees.
    pub tilt_deg: f64,
    /// Stage X when the frame was captured, µm.
    pub stage_x_um: f64,
    /// Stage Y when the frame was captured, µm.
    pub stage_y_um: f64,
    /// Pixel size of the frame, µm.
    pub pixel_size_um: f64,
    /// Pixel dwell time, µs.
    pub dwell_us: f64,
    /// Frame width, pixels.
    pub width: u32,
    /// Frame height, pixels.
    pub height: u32,
    /// Direction of the stage tilt axis in the image, degrees (φ), as the SEM reports it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tilt_axis_deg: Option<f64>,
    /// Specimen drift measured on this frame (x, y), pixels; absent when not measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drift_px: Option<[f64; 2]>,
    /// The file the frame was read from (watch folder): name, vendor, recorded tilt,
    /// stored size and averaging; absent for scanned frames.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<crate::imaging::FrameFile>,
}

// `/stage/state` and `/stage/io` carry the driver's own records
// ([`crate::stage::StageState`], [`crate::stage::StageIo`]): one definition of the
// wire format, owned by the code that produces it.
pub use crate::stage::{StageIo, StageState};

/// How a run ended; written last as the MCAP metadata record [`topics::METADATA_OUTCOME`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RunOutcome {
    pub status: RunStatus,
    /// One-line cause when the run did not succeed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cause: Option<String>,
}

/// The final state of a run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RunStatus {
    Succeeded,
    Failed,
    Aborted,
}

impl RunStatus {
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Succeeded => "succeeded",
            Self::Failed => "failed",
            Self::Aborted => "aborted",
        }
    }
}

impl RunOutcome {
    /// The metadata record's key-value map.
    #[must_use]
    pub fn to_map(&self) -> BTreeMap<String, String> {
        let mut map = BTreeMap::new();
        map.insert("status".to_owned(), self.status.as_str().to_owned());
        if let Some(cause) = &self.cause {
            map.insert("cause".to_owned(), cause.clone());
        }
        map
    }

    /// Reads the metadata record's map back; `None` when `status` is missing or unknown.
    #[must_use]
    pub fn from_map(map: &BTreeMap<String, String>) -> Option<Self> {
        let status = match map.get("status")?.as_str() {
            "succeeded" => RunStatus::Succeeded,
            "failed" => RunStatus::Failed,
            "aborted" => RunStatus::Aborted,
            _ => return None,
        };
        Some(Self {
            status,
            cause: map.get("cause").cloned(),
        })
    }
}

/// A JSON schema for a channel: its name and its text.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct JsonSchema {
    pub name: &'static str,
    pub text: &'static str,
}

/// Schema of [`FrameInfo`].
pub const FRAME_INFO_SCHEMA: JsonSchema = JsonSchema {
    name: "sdsem.FrameInfo",
    text: r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "sdsem.FrameInfo",
  "description": "Acquisition parameters of one /sem/frame message (same log time)",
  "type": "object",
  "properties": {
    "role": {"type": "string", "enum": ["tracking", "left", "right"]},
    "index": {"type": "integer", "minimum": 0, "description": "frame number in the run"},
    "tilt_deg": {"type": "number", "description": "stage tilt, degrees"},
    "stage_x_um": {"type": "number", "description": "stage X, micrometres"},
    "stage_y_um": {"type": "number", "description": "stage Y, micrometres"},
    "pixel_size_um": {"type": "number", "description": "pixel size, micrometres"},
    "dwell_us": {"type": "number", "description": "pixel dwell time, microseconds"},
    "width": {"type": "integer", "minimum": 0},
    "height": {"type": "integer", "minimum": 0},
    "tilt_axis_deg": {"type": "number", "description": "direction of the tilt axis in the image, degrees"},
    "drift_px": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2,
                 "description": "measured specimen drift (x, y), pixels"},
    "file": {"type": "object", "description": "the stored micrograph the frame was read from (watch folder)",
             "properties": {
               "name": {"type": "string"},
               "vendor": {"type": "string"},
               "sidecar": {"type": "string"},
               "recorded_tilt_deg": {"type": "number", "description": "tilt the file records, degrees"},
               "stored_width": {"type": "integer", "minimum": 0},
               "stored_height": {"type": "integer", "minimum": 0},
               "downsampled": {"type": "integer", "minimum": 1,
                               "description": "stored pixels averaged per frame pixel and side"},
               "instrument": {"type": "object", "description": "who stored it, as its metadata says",
                              "properties": {"vendor": {"type": "string"}, "model": {"type": "string"},
                                             "version": {"type": "string"}, "serial": {"type": "string"}},
                              "required": ["vendor", "model", "version", "serial"]}
             },
             "required": ["name", "stored_width", "stored_height", "downsampled"]}
  },
  "required": ["role", "index", "tilt_deg", "stage_x_um", "stage_y_um", "pixel_size_um",
               "dwell_us", "width", "height"]
}"#,
};

/// Schema of [`StageState`].
pub const STAGE_STATE_SCHEMA: JsonSchema = JsonSchema {
    name: "sdsem.StageState",
    text: r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "sdsem.StageState",
  "description": "Stage axes after a move, a poll or a stop",
  "type": "object",
  "properties": {
    "wall_ns": {"type": "integer", "minimum": 0, "description": "ns since the Unix epoch"},
    "event": {"type": "string",
              "enum": ["connected", "move_started", "poll", "move_reissued", "reached", "stopped", "position"]},
    "axes": {"type": "array", "items": {
      "type": "object",
      "properties": {
        "axis": {"type": "string", "enum": ["x", "y", "tilt"]},
        "id": {"type": "string", "description": "the controller's axis identifier"},
        "position": {"type": ["number", "null"], "description": "micrometres (x, y) or degrees (tilt)"},
        "target": {"type": ["number", "null"]},
        "on_target": {"type": ["boolean", "null"]}
      },
      "required": ["axis", "id", "position", "target", "on_target"]
    }}
  },
  "required": ["wall_ns", "event", "axes"]
}"#,
};

/// Schema of [`StageIo`].
pub const STAGE_IO_SCHEMA: JsonSchema = JsonSchema {
    name: "sdsem.StageIo",
    text: r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "sdsem.StageIo",
  "description": "One exchange with the stage controller: command line sent and reply",
  "type": "object",
  "properties": {
    "seq": {"type": "integer", "minimum": 0, "description": "exchange number since connect"},
    "command": {"type": ["string", "null"], "description": "command line as sent; null for stray bytes"},
    "attempt": {"type": "integer", "minimum": 1},
    "sent_wall_ns": {"type": ["integer", "null"], "description": "ns since the Unix epoch"},
    "reply": {"type": ["string", "null"]},
    "reply_wall_ns": {"type": ["integer", "null"]},
    "rtt_ns": {"type": ["integer", "null"], "description": "round-trip time, ns"},
    "outcome": {"type": "string", "enum": ["replied", "sent", "timeout", "garbled", "stray"]},
    "detail": {"type": ["string", "null"]}
  },
  "required": ["seq", "command", "attempt", "sent_wall_ns", "reply", "reply_wall_ns", "rtt_ns",
               "outcome", "detail"]
}"#,
};

/// Schema of `/recon/report`: the pipeline's report, every stage's figures and timings.
pub const RECON_REPORT_SCHEMA: JsonSchema = JsonSchema {
    name: "sdsem.ReconReport",
    text: r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "sdsem.ReconReport",
  "description": "Figures and timings of every reconstruction stage, as in report.json",
  "type": "object"
}"#,
};

/// Schema for JSON topics without a schema of their own.
pub const GENERIC_OBJECT_SCHEMA: JsonSchema = JsonSchema {
    name: "sdsem.Json",
    text: r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "sdsem.Json",
  "type": "object"
}"#,
};

/// The schema the recorder uses for JSON messages on `topic`.
#[must_use]
pub fn json_schema_for(topic: &str) -> JsonSchema {
    match topic {
        topics::SEM_FRAME_INFO => FRAME_INFO_SCHEMA,
        topics::STAGE_STATE => STAGE_STATE_SCHEMA,
        topics::STAGE_IO => STAGE_IO_SCHEMA,
        topics::RECON_REPORT => RECON_REPORT_SCHEMA,
        _ => GENERIC_OBJECT_SCHEMA,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn schema_properties(schema: JsonSchema) -> (Vec<String>, Vec<String>) {
        let value: serde_json::Value = serde_json::from_str(schema.text).unwrap();
        let props = value["properties"]
            .as_object()
            .map(|m| m.keys().cloned().collect())
            .unwrap_or_default();
        let required = value["required"]
            .as_array()
            .map(|a| a.iter().map(|v| v.as_str().unwrap().to_owned()).collect())
            .unwrap_or_default();
        (props, required)
    }

    /// Every field a message carries is described by its schema, and every field the
    /// schema requires is always present — so the schema cannot drift from the struct.
    fn assert_schema_matches(schema: JsonSchema, full: &impl Serialize, minimal: &impl Serialize) {
        let (props, required) = schema_properties(schema);
        let full = serde_json::to_value(full).unwrap();
        for key in full.as_object().unwrap().keys() {
            assert!(
                props.contains(key),
                "{}: field {key} not in schema",
                schema.name
            );
        }
        assert_eq!(
            full.as_object().unwrap().len(),
            props.len(),
            "{}",
            schema.name
        );
        let minimal = serde_json::to_value(minimal).unwrap();
        let minimal_keys: Vec<&String> = minimal.as_object().unwrap().keys().collect();
        for key in &required {
            assert!(
                minimal_keys.contains(&key),
                "{}: required {key} missing",
                schema.name
            );
        }
        assert_eq!(minimal_keys.len(), required.len(), "{}", schema.name);
    }

    #[test]
    fn frame_info_schema_describes_the_struct() {
        let mut info = FrameInfo {
            role: FrameRole::Left,
            index: 3,
            tilt_deg: -3.0,
            stage_x_um: 1.0,
            stage_y_um: 2.0,
            pixel_size_um: 0.05582,
            dwell_us: 1.2,
            width: 2048,
            height: 1536,
            tilt_axis_deg: Some(0.0),
            drift_px: Some([0.5, -1.0]),
            file: Some(crate::imaging::FrameFile {
                name: "img_001.tif".into(),
                vendor: Some("Zeiss".into()),
                sidecar: None,
                recorded_tilt_deg: Some(-3.0),
                stored_width: 2048,
                stored_height: 1536,
                downsampled: 1,
                instrument: crate::imaging::SourceIdentity {
                    vendor: "Zeiss".into(),
                    version: "V06.03".into(),
                    serial: "4711".into(),
                    ..Default::default()
                },
            }),
        };
        let full = info.clone();
        info.drift_px = None;
        info.tilt_axis_deg = None;
        info.file = None;
        assert_schema_matches(FRAME_INFO_SCHEMA, &full, &info);
    }

    #[test]
    fn stage_schemas_describe_the_structs() {
        use crate::stage::{AxisState, IoOutcome, StageAxis, StageEvent};
        let state = StageState {
            wall_ns: 1,
            event: StageEvent::Reached,
            axes: vec![AxisState {
                axis: StageAxis::Tilt,
                id: "T".into(),
                position: Some(1.0),
                target: Some(1.0),
                on_target: Some(true),
            }],
        };
        assert_schema_matches(STAGE_STATE_SCHEMA, &state, &state);
        let axis_schema: serde_json::Value = serde_json::from_str(STAGE_STATE_SCHEMA.text).unwrap();
        let axis_props = axis_schema["properties"]["axes"]["items"]["properties"]
            .as_object()
            .unwrap();
        let axis_value = serde_json::to_value(&state.axes[0]).unwrap();
        for key in axis_value.as_object().unwrap().keys() {
            assert!(
                axis_props.contains_key(key),
                "axis field {key} not in schema"
            );
        }
        let io = StageIo {
            seq: 3,
            command: Some("POS? T".into()),
            attempt: 1,
            sent_wall_ns: Some(1),
            reply: Some("T=1.000000".into()),
            reply_wall_ns: Some(2),
            rtt_ns: Some(1),
            outcome: IoOutcome::Replied,
            detail: None,
        };
        assert_schema_matches(STAGE_IO_SCHEMA, &io, &io);
    }

    #[test]
    fn outcome_round_trips_through_metadata_map() {
        let outcome = RunOutcome {
            status: RunStatus::Failed,
            cause: Some("stage did not reach 12°".into()),
        };
        assert_eq!(RunOutcome::from_map(&outcome.to_map()), Some(outcome));
        let mut map = BTreeMap::new();
        map.insert("status".to_owned(), "exploded".to_owned());
        assert_eq!(RunOutcome::from_map(&map), None);
    }
}
