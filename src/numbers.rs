//! Numbers as people read them: rounded to what they mean, in logs, `report.json`,
//! `replay` and `inspect` — the one place that decides how many digits a figure gets.
//!
//! | quantity | rounded to | helper |
//! | --- | --- | --- |
//! | length, µm | 1 nm (3 decimals) | [`um`], [`fmt_um`] |
//! | angle, degrees | 1e-4° | [`deg`] |
//! | time, s / ms | 1 ms | [`secs`], key suffix `_ms` |
//! | image position or error, pixels | 1e-3 px | [`px`] |
//! | fraction of pixels | 1e-4 | key suffix `_fraction` |
//! | calibrations (`pixel_size_um`, `…_per_…`) and anything else | 6 significant digits | [`significant`] |
//!
//! Only what people read is rounded. The numbers that make a replay bit-identical — the
//! recorded configuration, `/sem/frame_info`, the micrographs' tilt and pixel size, the
//! height map itself — and what `rectification.json` gives to compute with (`H_left`,
//! `H_right`, `F`, the inlier correspondences) keep every digit.

use serde::Serialize;

/// Version of the layout of `report.json`, `replay.json`, `rectification.json` and
/// `/recon/report` (key `schema_version`): raised when a key changes meaning or goes away.
pub const REPORT_SCHEMA_VERSION: u32 = 1;

/// `value` rounded to `decimals` decimal places (negative: to tens, hundreds, …).
///
/// The result is the double nearest to the rounded decimal, so it prints as that decimal
/// (`-0.08000000000000002` → `-0.08`). NaN and infinities pass through; −0 becomes 0.
#[must_use]
pub fn round_to(value: f64, decimals: i32) -> f64 {
    if !value.is_finite() {
        return value;
    }
    // Powers of ten up to 1e22 are exact doubles, so `n / 10^d` is the nearest double to
    // the decimal n·10⁻ᵈ when n is an integer below 2⁵³.
    let decimals = decimals.clamp(-22, 22);
    let scale = 10f64.powi(decimals.abs());
    let scaled = if decimals >= 0 {
        value * scale
    } else {
        value / scale
    };
    if scaled.abs() >= 2f64.powi(52) {
        return value;
    }
    let rounded = if decimals >= 0 {
        scaled.round() / scale
    } else {
        scaled.round() * scale
    };
    if rounded == 0.0 { 0.0 } else { rounded }
}

/// `value` rounded to `digits` significant digits.
#[must_use]
pub fn significant(value: f64, digits: u32) -> f64 {
    if !value.is_finite() || value == 0.0 {
        return value;
    }
    // |value| < 10^308, so the exponent fits an i32.
    #[allow(clippy::cast_possible_truncation)]
    let magnitude = value.abs().log10().floor() as i32;
    round_to(value, digits.min(17).cast_signed() - 1 - magnitude)
}

/// A length in µm, to 1 nm.
#[must_use]
pub fn um(value: f64) -> f64 {
    round_to(value, 3)
}

/// An angle in degrees, to 1e-4°.
#[must_use]
pub fn deg(value: f64) -> f64 {
    round_to(value, 4)
}

/// A duration in seconds, to 1 ms.
#[must_use]
pub fn secs(value: f64) -> f64 {
    round_to(value, 3)
}

/// A position or an error in pixels, to 1e-3 px.
#[must_use]
pub fn px(value: f64) -> f64 {
    round_to(value, 3)
}

/// A length in µm for the terminal, to 1 nm: `7.297 µm`, `0 µm`, `< 0.001 µm` for a
/// non-zero length below 1 nm (so a tiny difference never reads as none).
#[must_use]
pub fn fmt_um(value: f64) -> String {
    if value.is_nan() {
        return "unknown".to_owned();
    }
    if value != 0.0 && value.abs() < 0.0005 {
        return if value > 0.0 {
            "< 0.001 µm".to_owned()
        } else {
            "> −0.001 µm".to_owned()
        };
    }
    format!("{} µm", um(value))
}

/// How many digits a JSON number under `key` keeps (see the module's table).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Digits {
    All,
    Decimals(i32),
    Significant(u32),
}

fn digits_for(key: &str) -> Digits {
    let lower = key.to_ascii_lowercase();
    // Matrices and correspondences people compute with, not read.
    if matches!(
        lower.as_str(),
        "h_left" | "h_right" | "f" | "inlier_correspondences"
    ) {
        return Digits::All;
    }
    if lower == "pixel_size_um" || lower.contains("_per_") {
        return Digits::Significant(6);
    }
    for (suffix, digits) in [
        ("_um", Digits::Decimals(3)),
        ("_deg", Digits::Decimals(4)),
        ("_ms", Digits::Decimals(0)),
        ("_s", Digits::Decimals(3)),
        ("_px", Digits::Decimals(3)),
        ("_mib", Digits::Decimals(1)),
        ("_fraction", Digits::Decimals(4)),
        ("coverage", Digits::Decimals(4)),
    ] {
        if lower.ends_with(suffix) {
            return digits;
        }
    }
    Digits::Significant(6)
}

fn round_number(n: &serde_json::Number, digits: Digits) -> Option<serde_json::Number> {
    if n.is_i64() || n.is_u64() {
        return None;
    }
    let v = n.as_f64()?;
    let rounded = match digits {
        Digits::All => return None,
        Digits::Decimals(d) => round_to(v, d),
        Digits::Significant(s) => significant(v, s),
    };
    serde_json::Number::from_f64(rounded)
}

fn round_value(value: &mut serde_json::Value, digits: Digits) {
    if digits == Digits::All {
        return;
    }
    match value {
        serde_json::Value::Number(n) => {
            if let Some(r) = round_number(n, digits) {
                *n = r;
            }
        }
        serde_json::Value::Array(items) => {
            for item in items {
                round_value(item, digits);
            }
        }
        serde_json::Value::Object(map) => {
            for (key, item) in map.iter_mut() {
                round_value(item, digits_for(key));
            }
        }
        _ => {}
    }
}

/// Rounds every number of a report to what it means, by the unit its key names
/// (see the module's table); arrays take the rule of their key.
pub fn round_for_people(value: &mut serde_json::Value) {
    round_value(value, Digits::Significant(6));
}

/// A report as people read it: `schema_version` first, then the fields of `report`, every
/// number rounded by [`round_for_people`].
///
/// # Errors
/// When `report` does not serialise to a JSON object.
pub fn report_json(report: &impl Serialize) -> Result<serde_json::Value, serde_json::Error> {
    let value = serde_json::to_value(report)?;
    let serde_json::Value::Object(fields) = value else {
        return Err(serde::ser::Error::custom("a report must be a JSON object"));
    };
    let mut map = serde_json::Map::new();
    map.insert("schema_version".to_owned(), REPORT_SCHEMA_VERSION.into());
    for (k, v) in fields {
        if k != "schema_version" {
            map.insert(k, v);
        }
    }
    let mut value = serde_json::Value::Object(map);
    round_for_people(&mut value);
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_prints_the_decimal_it_means() {
        assert_eq!(um(-0.08000000000000002).to_string(), "-0.08");
        assert_eq!(um(0.42000000000000015).to_string(), "0.42");
        assert_eq!(secs(231.43128099999998).to_string(), "231.431");
        assert_eq!(deg(7.000_000_4).to_string(), "7");
        assert_eq!(px(1.6317467752650625).to_string(), "1.632");
        assert_eq!(um(-0.0000001).to_string(), "0", "no −0");
        assert_eq!(significant(36_626_745.195, 6).to_string(), "36626700");
        assert_eq!(significant(-2387.737438880652, 6).to_string(), "-2387.74");
        assert_eq!(significant(0.05582, 6).to_string(), "0.05582");
        assert!(um(f64::NAN).is_nan());
        // Beyond 2⁵² units of the last place there is nothing to round.
        assert_eq!(um(1e300), 1e300);
    }

    #[test]
    fn lengths_read_in_nanometres_and_tiny_ones_stay_visible() {
        assert_eq!(fmt_um(7.296_999_9), "7.297 µm");
        assert_eq!(fmt_um(0.0), "0 µm");
        assert_eq!(fmt_um(3e-7), "< 0.001 µm");
        assert_eq!(fmt_um(-0.25), "-0.25 µm");
        assert_eq!(fmt_um(f64::NAN), "unknown");
    }

    #[test]
    fn reports_round_by_unit_and_keep_homographies_and_calibrations() {
        let report = serde_json::json!({
            "wall_s": 231.43128099999998,
            "geometry": {"tilt_deg": 7.000_000_01, "pixel_size_um": 0.055_823_1, "tilt_axis_deg": -60.000_000_3},
            "sparse": {
                "final_error_px": 0.11185825819610111,
                "h_left": [[-0.007202634113628958, 1.001982039884958, 10.160070505302496]],
                "timings": {"sift_ms": 266.928138},
                "inliers": 938,
            },
            "depth": {"height_p99_um": 8.027016639709473, "valid_fraction": 0.9853141276041667,
                      "um_per_disparity_px": 0.819020411969913},
            "energy": [36626745.19594765, 0.1234567891],
            "peak_rss_mib": 403.734375,
        });
        let v = report_json(&report).unwrap();
        let text = v.to_string();
        assert!(
            text.starts_with(r#"{"schema_version":1,"#),
            "version first: {text}"
        );
        assert_eq!(v["wall_s"], serde_json::json!(231.431));
        assert_eq!(v["geometry"]["tilt_deg"], serde_json::json!(7.0));
        assert_eq!(v["geometry"]["pixel_size_um"], serde_json::json!(0.0558231));
        assert_eq!(v["geometry"]["tilt_axis_deg"], serde_json::json!(-60.0));
        assert_eq!(v["sparse"]["final_error_px"], serde_json::json!(0.112));
        assert_eq!(
            v["sparse"]["h_left"][0][0],
            serde_json::json!(-0.007202634113628958)
        );
        assert_eq!(v["sparse"]["timings"]["sift_ms"], serde_json::json!(267.0));
        assert_eq!(v["sparse"]["inliers"], serde_json::json!(938));
        assert_eq!(v["depth"]["height_p99_um"], serde_json::json!(8.027));
        assert_eq!(v["depth"]["valid_fraction"], serde_json::json!(0.9853));
        assert_eq!(
            v["depth"]["um_per_disparity_px"],
            serde_json::json!(0.81902)
        );
        assert_eq!(v["energy"], serde_json::json!([36626700.0, 0.123457]));
        assert_eq!(v["peak_rss_mib"], serde_json::json!(403.7));
        // Struct order is kept after the version.
        let keys: Vec<&String> = v.as_object().unwrap().keys().collect();
        assert_eq!(keys[1], "wall_s");
    }
}
