//! `report.json` (and any JSON result): serde of the pipeline's report, written atomically.

use std::io::Write;

use serde::Serialize;

use super::ExportError;
use super::atomic::Target;

/// Writes `value` as pretty-printed JSON (with a final newline) to `path`, atomically.
///
/// # Errors
/// [`ExportError::Invalid`] when `value` cannot be serialised (e.g. a map with non-string
/// keys), [`ExportError::Write`] on I/O failure.
pub fn write_json_atomic<'a>(
    target: impl Into<Target<'a>>,
    value: &impl Serialize,
) -> Result<(), ExportError> {
    let target = target.into();
    let mut text = serde_json::to_vec_pretty(value).map_err(|e| ExportError::Invalid {
        path: target.path(),
        reason: format!("cannot serialise to JSON: {e}"),
    })?;
    text.push(b'\n');
    target.write(|w| w.write_all(&text))
}

/// Writes a report people read (`report.json`, `replay.json`, `rectification.json`) like
/// [`write_json_atomic`], with `schema_version` first and every number rounded to what it
/// means ([`crate::numbers::report_json`]).
///
/// # Errors
/// As [`write_json_atomic`]; [`ExportError::Invalid`] when `report` is not a JSON object.
pub fn write_report_atomic<'a>(
    target: impl Into<Target<'a>>,
    report: &impl Serialize,
) -> Result<(), ExportError> {
    let target = target.into();
    let value = crate::numbers::report_json(report).map_err(|e| ExportError::Invalid {
        path: target.path(),
        reason: format!("cannot serialise to JSON: {e}"),
    })?;
    write_json_atomic(target, &value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn report_is_written_and_parses_back() {
        #[derive(Serialize)]
        struct Report {
            matches: u32,
            final_error_px: f64,
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("report.json");
        write_json_atomic(
            &path,
            &Report {
                matches: 42,
                final_error_px: 0.31,
            },
        )
        .unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.ends_with('\n'));
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(v["matches"], 42);
    }

    #[test]
    fn reports_carry_their_schema_version_and_rounded_figures() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("report.json");
        write_report_atomic(
            &path,
            &serde_json::json!({"wall_s": 231.43128099999998, "inliers": 938}),
        )
        .unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains("\"schema_version\": 1"), "{text}");
        assert!(text.contains("\"wall_s\": 231.431,"), "{text}");
    }

    #[test]
    fn unserialisable_value_leaves_no_file() {
        let mut map = std::collections::HashMap::new();
        map.insert((1, 2), 3);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("report.json");
        assert!(write_json_atomic(&path, &map).is_err());
        assert!(!path.exists());
    }
}
