//! `sdsem inspect RUN.mcap`: what a run record holds, also when the run was killed.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use foxglove::Decode;
use foxglove::messages::Log;

use super::entry::LogLevel;
use super::error::ReadError;
use super::messages::RunOutcome;
use super::read::{ScanEnd, ScanItem, image_frame_id, scan};
use super::topics;

/// One topic of the record.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct TopicInspection {
    pub topic: String,
    pub schema_name: String,
    pub schema_encoding: String,
    pub message_encoding: String,
    pub messages: u64,
    pub first_ns: u64,
    pub last_ns: u64,
}

/// One attachment of the record (without its bytes).
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct AttachmentInspection {
    pub name: String,
    pub media_type: String,
    pub bytes: u64,
    pub log_time_ns: u64,
}

/// Summary of a run record, built by a linear read (works on truncated files).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RecordInspection {
    pub path: PathBuf,
    pub file_bytes: u64,
    /// How the read ended: complete file, or where and why it was cut off.
    pub end: ScanEnd,
    /// The MCAP header's library string (which program wrote it).
    pub library: String,
    pub profile: String,
    /// Topics in order of first appearance, with schema and message counts.
    pub topics: Vec<TopicInspection>,
    /// `/sem/frame` messages per frame id (tracking / left / right).
    pub frames_by_role: BTreeMap<String, u64>,
    /// First and last message log time, ns since the Unix epoch.
    pub time_range_ns: Option<(u64, u64)>,
    /// Metadata records in record order (name, key-value pairs).
    pub metadata: Vec<(String, BTreeMap<String, String>)>,
    pub attachments: Vec<AttachmentInspection>,
    /// `/log` messages per level.
    pub log_levels: BTreeMap<LogLevel, u64>,
    /// The last ERROR/FATAL log message, if any.
    pub last_error: Option<String>,
    /// The run's outcome from the [`topics::METADATA_OUTCOME`] record, if written.
    pub outcome: Option<RunOutcome>,
    /// The last `/recon/report` message.
    pub report: Option<serde_json::Value>,
}

impl RecordInspection {
    /// Messages on `topic` (0 when absent).
    #[must_use]
    pub fn message_count(&self, topic: &str) -> u64 {
        self.topics
            .iter()
            .filter(|t| t.topic == topic)
            .map(|t| t.messages)
            .sum()
    }

    /// Metadata record `name` (the last one with that name).
    #[must_use]
    pub fn metadata_record(&self, name: &str) -> Option<&BTreeMap<String, String>> {
        self.metadata
            .iter()
            .rev()
            .find(|(n, _)| n == name)
            .map(|(_, m)| m)
    }
}

/// Reads the record at `path` and summarises it.
///
/// # Errors
/// [`ReadError`] when the file cannot be opened or is not an MCAP file; a truncated or
/// damaged tail is not an error (see [`RecordInspection::end`]).
pub fn read_summary(path: impl AsRef<Path>) -> Result<RecordInspection, ReadError> {
    let path = path.as_ref();
    let file_bytes = std::fs::metadata(path)
        .map_err(|source| ReadError::Open {
            path: path.to_path_buf(),
            source,
        })?
        .len();
    let mut library = String::new();
    let mut profile = String::new();
    let mut topics: Vec<TopicInspection> = Vec::new();
    let mut frames_by_role: BTreeMap<String, u64> = BTreeMap::new();
    let mut time_range_ns: Option<(u64, u64)> = None;
    let mut metadata = Vec::new();
    let mut attachments = Vec::new();
    let mut log_levels = BTreeMap::new();
    let mut last_error = None;
    let mut report = None;

    let end = scan(path, |item| {
        match item {
            ScanItem::Header {
                profile: p,
                library: l,
            } => {
                p.clone_into(&mut profile);
                l.clone_into(&mut library);
            }
            ScanItem::Message {
                channel,
                log_time_ns,
                data,
            } => {
                time_range_ns = Some(match time_range_ns {
                    None => (log_time_ns, log_time_ns),
                    Some((a, b)) => (a.min(log_time_ns), b.max(log_time_ns)),
                });
                match topics
                    .iter_mut()
                    .find(|t| t.topic == channel.topic && t.schema_name == channel.schema_name)
                {
                    Some(t) => {
                        t.messages += 1;
                        t.first_ns = t.first_ns.min(log_time_ns);
                        t.last_ns = t.last_ns.max(log_time_ns);
                    }
                    None => topics.push(TopicInspection {
                        topic: channel.topic.clone(),
                        schema_name: channel.schema_name.clone(),
                        schema_encoding: channel.schema_encoding.clone(),
                        message_encoding: channel.message_encoding.clone(),
                        messages: 1,
                        first_ns: log_time_ns,
                        last_ns: log_time_ns,
                    }),
                }
                match channel.topic.as_str() {
                    topics::SEM_FRAME => {
                        let role = image_frame_id(channel, data)
                            .unwrap_or_else(|| "(undecodable)".to_owned());
                        *frames_by_role.entry(role).or_insert(0) += 1;
                    }
                    topics::LOG if channel.schema_name == "foxglove.Log" => {
                        if let Ok(log) = Log::decode(data) {
                            let level = LogLevel::from_foxglove(log.level);
                            *log_levels.entry(level).or_insert(0) += 1;
                            if level >= LogLevel::Error {
                                last_error = Some(log.message);
                            }
                        }
                    }
                    topics::RECON_REPORT if channel.message_encoding == "json" => {
                        if let Ok(value) = serde_json::from_slice(data) {
                            report = Some(value);
                        }
                    }
                    _ => {}
                }
            }
            ScanItem::Metadata { name, entries } => {
                metadata.push((name.to_owned(), entries.clone()));
            }
            ScanItem::Attachment {
                name,
                media_type,
                log_time_ns,
                data,
            } => attachments.push(AttachmentInspection {
                name: name.to_owned(),
                media_type: media_type.to_owned(),
                bytes: data.len() as u64,
                log_time_ns,
            }),
        }
        Ok(())
    })?;

    let outcome = metadata
        .iter()
        .rev()
        .find(|(name, _)| name == topics::METADATA_OUTCOME)
        .and_then(|(_, map)| RunOutcome::from_map(map));
    Ok(RecordInspection {
        path: path.to_path_buf(),
        file_bytes,
        end,
        library,
        profile,
        topics,
        frames_by_role,
        time_range_ns,
        metadata,
        attachments,
        log_levels,
        last_error,
        outcome,
        report,
    })
}

/// A human-readable summary for `sdsem inspect`.
#[must_use]
pub fn format_inspection(inspection: &RecordInspection) -> String {
    let mut out = String::new();
    let i = inspection;
    // Writing to a String cannot fail.
    let _ = writeln!(out, "{}  ({})", i.path.display(), human_bytes(i.file_bytes));
    if i.end.complete {
        let _ = writeln!(out, "  record:      complete (summary and footer present)");
    } else {
        let _ = writeln!(
            out,
            "  record:      INCOMPLETE — {}; everything before it was recovered",
            i.end.stopped_by.as_deref().unwrap_or("unknown cause")
        );
    }
    if !i.library.is_empty() {
        let _ = writeln!(out, "  written by:  {}", i.library);
    }
    match i.time_range_ns {
        Some((a, b)) => {
            let _ = writeln!(
                out,
                "  time:        {} → {}  ({:.1} s)",
                utc_time(a),
                utc_time(b),
                (b - a) as f64 * 1e-9
            );
        }
        None => {
            let _ = writeln!(out, "  time:        no messages");
        }
    }
    let outcome = match (&i.outcome, &i.report, i.end.complete) {
        (Some(o), _, _) => match &o.cause {
            Some(cause) => format!("{} — {cause}", o.status.as_str()),
            None => o.status.as_str().to_owned(),
        },
        (None, Some(_), _) => "no final state recorded; a reconstruction report is present".into(),
        (None, None, false) => "unknown — the run ended without finishing its record".into(),
        (None, None, true) => "no final state recorded".into(),
    };
    let _ = writeln!(out, "  outcome:     {outcome}");
    let frames: Vec<String> = i
        .frames_by_role
        .iter()
        .map(|(role, n)| format!("{role} {n}"))
        .collect();
    let _ = writeln!(
        out,
        "  frames:      {}",
        if frames.is_empty() {
            "none".to_owned()
        } else {
            frames.join(", ")
        }
    );
    let _ = writeln!(out, "  topics:");
    let width = i.topics.iter().map(|t| t.topic.len()).max().unwrap_or(0);
    for t in &i.topics {
        let _ = writeln!(
            out,
            "    {:<width$}  {:>6} msgs  {} ({})",
            t.topic, t.messages, t.schema_name, t.message_encoding
        );
    }
    for (name, entries) in &i.metadata {
        // Short one-line values inline (job, version, host); long ones (the configuration)
        // by size only.
        let items: Vec<String> = entries
            .iter()
            .map(|(k, v)| {
                if v.len() <= 48 && !v.contains('\n') {
                    format!("{k}={v}")
                } else {
                    format!("{k} ({} lines)", v.lines().count())
                }
            })
            .collect();
        let _ = writeln!(out, "  metadata:    {name}: {}", items.join(", "));
    }
    for a in &i.attachments {
        let _ = writeln!(
            out,
            "  attachment:  {} ({}, {})",
            a.name,
            a.media_type,
            human_bytes(a.bytes)
        );
    }
    if !i.log_levels.is_empty() {
        let levels: Vec<String> = i
            .log_levels
            .iter()
            .rev()
            .map(|(level, n)| format!("{n} {}", level.as_str()))
            .collect();
        let _ = writeln!(out, "  log:         {}", levels.join(", "));
    }
    if let Some(e) = &i.last_error {
        let _ = writeln!(out, "  last error:  {e}");
    }
    out
}

fn human_bytes(bytes: u64) -> String {
    const UNITS: [&str; 4] = ["B", "KiB", "MiB", "GiB"];
    let mut value = bytes as f64;
    let mut unit = 0;
    while value >= 1024.0 && unit + 1 < UNITS.len() {
        value /= 1024.0;
        unit += 1;
    }
    if unit == 0 {
        format!("{bytes} B")
    } else {
        format!("{value:.1} {}", UNITS[unit])
    }
}

/// `YYYY-MM-DD hh:mm:ss.mmm UTC` from ns since the Unix epoch.
#[must_use]
pub fn utc_time(ns: u64) -> String {
    jiff::Timestamp::from_nanosecond(i128::from(ns))
        .unwrap_or(jiff::Timestamp::MAX)
        .strftime("%Y-%m-%d %H:%M:%S%.3f UTC")
        .to_string()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_time_matches_known_instants() {
        assert_eq!(utc_time(0), "1970-01-01 00:00:00.000 UTC");
        // 2016-03-08 10:44:48 UTC, the Potamogeton capture time.
        assert_eq!(
            utc_time(1_457_433_888_123_000_000),
            "2016-03-08 10:44:48.123 UTC"
        );
        // Leap day.
        assert_eq!(
            utc_time(951_782_400_000_000_000),
            "2000-02-29 00:00:00.000 UTC"
        );
    }

    #[test]
    fn human_bytes_picks_a_unit() {
        assert_eq!(human_bytes(12), "12 B");
        assert_eq!(human_bytes(1536), "1.5 KiB");
        assert_eq!(human_bytes(5 * 1024 * 1024), "5.0 MiB");
    }
}
