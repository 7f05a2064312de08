//! SEM metadata: pixel size and stage tilt from the vendors' TIFF tags and sidecars
//! (DESIGN §7).
//!
//! | vendor | where | pixel size | tilt |
//! | --- | --- | --- | --- |
//! | Zeiss (SmartSEM) | TIFF tag 34118, text `Name = value unit` lines | `Image Pixel Size = 55.82 nm` (pm/nm/µm) | `Stage at T = -3.0 °` |
//! | FEI / Thermo Fisher | TIFF tag 34682 (older: 34680), INI text | `[Scan] PixelWidth` in m | `[Stage] StageT` in rad |
//! | Tescan | TIFF tag 50431, blocks of `key=value` text (MAIN, SEM, …) | `[MAIN] PixelSizeX` in m | `[SEM] StageTilt` in degrees |
//! | Hitachi | sidecar `NAME.txt`, `[SemImageFile]` section | `PixelSize=` in nm | `StagePositionT=` in degrees |
//! | JEOL | sidecar `NAME.txt`, `$KEY value` lines | `$CM_FIELD_OF_VIEW` ÷ width, else 128 mm ÷ `$CM_MAG` ÷ width | not read (the stage field's layout varies) |
//! | sdsem | ImageDescription JSON `{"sdsem":"micrograph",…}` (and a Zeiss-style 34118 block) | `pixel_size_um` | `tilt_deg` |
//!
//! Zeiss also writes `Pixel Size` (the pixel size at the scan's display resolution, e.g.
//! 111.6 nm where `Image Pixel Size` is 55.82 nm): only `Image Pixel Size` describes the
//! stored image, so it is the only one used. Zeiss text is Latin-1 (`°` is byte 0xB0);
//! UTF-8 and `deg` are accepted as well. Tescan's tag holds binary blocks (u32 size,
//! u16 type, text), as Gwyddion's `tescan.c` reads them; a plain INI text is accepted
//! too. The Hitachi tilt key `StagePositionT` follows the `StagePositionX/Y/Z/R` keys of
//! the S-4800/SU series headers.
//!
//! Vendor TIFFs may hold an info bar below the scanned image: FEI/Thermo's data bar
//! (crop to `[Image] ResolutionX × ResolutionY`), TESCAN's info strip (`[MAIN] ImageStripSize`
//! rows at the bottom), and the store size that Zeiss (`Store resolution = 1024 * 768`),
//! Hitachi (`DataSize=1280x960`) and JEOL (`$CM_FULL_SIZE 1280 960`) record [OD-IO]:
//! [`SemMetadata::kept_size`] says what to keep.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// Who wrote the metadata.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SemVendor {
    Zeiss,
    /// FEI / Thermo Fisher Scientific.
    Fei,
    Tescan,
    Hitachi,
    Jeol,
    /// Written by sdsem itself.
    Sdsem,
}

impl SemVendor {
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Zeiss => "Zeiss",
            Self::Fei => "FEI/Thermo Fisher",
            Self::Tescan => "Tescan",
            Self::Hitachi => "Hitachi",
            Self::Jeol => "JEOL",
            Self::Sdsem => "sdsem",
        }
    }
}

/// What a micrograph's metadata says about its geometry.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct SemMetadata {
    /// The vendor whose metadata was found (the first one, when several are present).
    pub vendor: Option<SemVendor>,
    /// Size of one pixel of the stored image, µm.
    pub pixel_size_um: Option<f64>,
    /// Stage tilt, degrees.
    pub tilt_deg: Option<f64>,
    /// Pixel dwell time, µs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dwell_us: Option<f64>,
    /// Width of the scanned field, µm (JEOL: the pixel size follows from the image width).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub field_width_um: Option<f64>,
    /// The part of the stored image that was scanned, when an info bar may follow it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub image_area: Option<ImageArea>,
    /// Every key-value pair found; INI keys as `Section.Key`.
    pub raw: BTreeMap<String, String>,
}

/// Which part of a stored vendor image is the scanned image (the rest is an info bar).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImageArea {
    /// The scan's size from the top-left corner (FEI/Thermo, Zeiss, Hitachi, JEOL).
    Size { width: usize, height: usize },
    /// This many rows at the bottom are an info strip (TESCAN).
    StripRows(usize),
}

impl SemMetadata {
    /// Whether neither pixel size nor tilt is known.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.pixel_size_um.is_none() && self.tilt_deg.is_none()
    }

    /// The size to keep of a `width` × `height` stored image, when it holds an info bar.
    /// `None` when the whole image is the scan, or when the recorded area does not fit
    /// inside the image (e.g. a picture rotated after storing: nothing is cut then).
    #[must_use]
    pub fn kept_size(&self, width: usize, height: usize) -> Option<(usize, usize)> {
        let (w, h) = match self.image_area? {
            ImageArea::Size {
                width: w,
                height: h,
            } => (w, h),
            ImageArea::StripRows(rows) => (width, height.checked_sub(rows)?),
        };
        (w > 0 && h > 0 && w <= width && h <= height && (w, h) != (width, height)).then_some((w, h))
    }

    /// Who stored the file, as far as its metadata says: vendor, and model, software version
    /// and serial number from the keys each vendor writes them under (Zeiss `Serial No.`,
    /// `Version`; FEI/Thermo `[System] SystemType`/`Type`, `Software`, `Dnumber`; Tescan
    /// `[MAIN] Device`, `SoftwareVersion`, `SerialNumber`; Hitachi `InstructName`,
    /// `SerialNumber`; JEOL `$CM_INSTRUMENT`, `$CM_VERSION` of the format).
    #[must_use]
    pub fn instrument(&self) -> super::SourceIdentity {
        let get = |keys: &[&str]| {
            keys.iter()
                .find_map(|k| self.raw.get(*k).filter(|v| !v.trim().is_empty()))
                .map_or_else(String::new, |v| v.trim().to_owned())
        };
        let (model, version, serial) = match self.vendor {
            Some(SemVendor::Zeiss) => (String::new(), get(&["Version"]), get(&["Serial No."])),
            Some(SemVendor::Fei) => (
                get(&["System.SystemType", "System.Type"]),
                get(&["System.Software"]),
                get(&["System.Dnumber"]),
            ),
            Some(SemVendor::Tescan) => (
                get(&["MAIN.Device", "MAIN.DeviceModel"]),
                get(&["MAIN.SoftwareVersion"]),
                get(&["MAIN.SerialNumber"]),
            ),
            Some(SemVendor::Hitachi) => (
                get(&["InstructName"]),
                String::new(),
                get(&["SerialNumber"]),
            ),
            Some(SemVendor::Jeol) => (get(&["CM_INSTRUMENT"]), String::new(), String::new()),
            Some(SemVendor::Sdsem) | None => Default::default(),
        };
        super::SourceIdentity {
            vendor: self
                .vendor
                .map_or_else(String::new, |v| v.as_str().to_owned()),
            model,
            version,
            serial,
        }
    }

    /// Fills what `self` lacks from `other` (vendor, pixel size, tilt, raw keys).
    pub fn merge(&mut self, other: Self) {
        if self.vendor.is_none() {
            self.vendor = other.vendor;
        }
        if self.pixel_size_um.is_none() {
            self.pixel_size_um = other.pixel_size_um;
        }
        if self.tilt_deg.is_none() {
            self.tilt_deg = other.tilt_deg;
        }
        if self.dwell_us.is_none() {
            self.dwell_us = other.dwell_us;
        }
        if self.field_width_um.is_none() {
            self.field_width_um = other.field_width_um;
        }
        if self.image_area.is_none() {
            self.image_area = other.image_area;
        }
        for (k, v) in other.raw {
            self.raw.entry(k).or_insert(v);
        }
    }
}

/// TIFF tag of the Zeiss SmartSEM text block.
pub const TAG_ZEISS: u16 = 34118;
/// TIFF tag of the FEI/Thermo INI text.
pub const TAG_FEI: u16 = 34682;
/// Older FEI TIFF tag with the same INI text.
pub const TAG_FEI_OLD: u16 = 34680;
/// TIFF tag of the Tescan metadata blocks.
pub const TAG_TESCAN: u16 = 50431;

/// Bytes of a vendor text as a string: UTF-16 with BOM, UTF-8 (BOM optional), else
/// Latin-1 (what Zeiss and Hitachi write); trailing NULs removed.
#[must_use]
pub fn decode_text(bytes: &[u8]) -> String {
    let utf16 = |bytes: &[u8], le: bool| {
        let units: Vec<u16> = bytes
            .chunks_exact(2)
            .map(|b| {
                if le {
                    u16::from_le_bytes([b[0], b[1]])
                } else {
                    u16::from_be_bytes([b[0], b[1]])
                }
            })
            .collect();
        String::from_utf16_lossy(&units)
    };
    let text = if let Some(rest) = bytes.strip_prefix(&[0xFF, 0xFE]) {
        utf16(rest, true)
    } else if let Some(rest) = bytes.strip_prefix(&[0xFE, 0xFF]) {
        utf16(rest, false)
    } else {
        let bytes = bytes.strip_prefix(&[0xEF, 0xBB, 0xBF]).unwrap_or(bytes);
        match std::str::from_utf8(bytes) {
            Ok(s) => s.to_owned(),
            Err(_) => bytes.iter().map(|&b| char::from(b)).collect(),
        }
    };
    text.trim_end_matches('\0').to_owned()
}

/// Splits `"55.82 nm"` into the number and what follows it.
fn number_and_unit(value: &str) -> Option<(f64, &str)> {
    let value = value.trim();
    // The longest prefix that parses as a number ("1.1165e-007", "-3.0", "55.82").
    let end = (1..=value.len())
        .rev()
        .filter(|&i| value.is_char_boundary(i))
        .find(|&i| value[..i].trim().parse::<f64>().is_ok())?;
    let number = value[..end].trim().parse::<f64>().ok()?;
    number.is_finite().then_some((number, value[end..].trim()))
}

/// A length with its unit (`pm`, `nm`, `µm`/`μm`/`um`, `mm`, `m`) in µm.
#[must_use]
pub fn parse_length_um(value: &str) -> Option<f64> {
    let (number, unit) = number_and_unit(value)?;
    let factor = match unit {
        "pm" => 1e-6,
        "nm" => 1e-3,
        "µm" | "μm" | "um" | "micron" | "microns" => 1.0,
        "mm" => 1e3,
        "m" => 1e6,
        _ => return None,
    };
    Some(number * factor)
}

/// An angle in degrees: `-3.0 °` (Latin-1 or UTF-8 degree sign), `3 deg`, or a bare number.
#[must_use]
pub fn parse_angle_deg(value: &str) -> Option<f64> {
    let (number, unit) = number_and_unit(value)?;
    let unit = unit.to_ascii_lowercase();
    (unit.is_empty() || unit.ends_with('°') || unit == "deg" || unit == "degrees" || unit == "º")
        .then_some(number)
}

/// A duration with its unit (`ns`, `µs`/`μs`/`us`, `ms`, `s`) in µs.
#[must_use]
pub fn parse_time_us(value: &str) -> Option<f64> {
    let (number, unit) = number_and_unit(value)?;
    let factor = match unit {
        "ns" => 1e-3,
        "µs" | "μs" | "us" => 1.0,
        "ms" => 1e3,
        "s" => 1e6,
        _ => return None,
    };
    Some(number * factor)
}

/// Two positive integers separated by `sep` (`"1024 * 768"`, `"1280x960"`, `"1280 960"`).
fn size_pair(value: &str, sep: &[char]) -> Option<ImageArea> {
    let mut parts = value.split(sep).map(str::trim).filter(|p| !p.is_empty());
    let width = parts.next()?.parse().ok()?;
    let height = parts.next()?.parse().ok()?;
    (parts.next().is_none() && width > 0 && height > 0).then_some(ImageArea::Size { width, height })
}

fn positive(v: Option<f64>) -> Option<f64> {
    v.filter(|v| v.is_finite() && *v > 0.0)
}

/// Parses a Zeiss SmartSEM block (TIFF tag 34118).
#[must_use]
pub fn parse_zeiss(bytes: &[u8]) -> SemMetadata {
    let text = decode_text(bytes);
    let mut raw = BTreeMap::new();
    for line in text.lines().map(str::trim) {
        // Lines like "AP_IMAGE_PIXEL_SIZE" name the parameter of the next line; the leading
        // lines are bare numbers. Both carry no value.
        let split = line.split_once('=').or_else(|| line.split_once(':'));
        if let Some((key, value)) = split {
            let key = key.trim();
            if !key.is_empty() {
                raw.entry(key.to_owned())
                    .or_insert_with(|| value.trim().to_owned());
            }
        }
    }
    let pixel_size_um = positive(raw.get("Image Pixel Size").and_then(|v| parse_length_um(v)));
    let tilt_deg = raw.get("Stage at T").and_then(|v| parse_angle_deg(v));
    SemMetadata {
        vendor: Some(SemVendor::Zeiss),
        pixel_size_um,
        tilt_deg,
        dwell_us: positive(raw.get("Dwell Time").and_then(|v| parse_time_us(v))),
        field_width_um: None,
        image_area: raw
            .get("Store resolution")
            .and_then(|v| size_pair(v, &['*'])),
        raw,
    }
}

/// Parses INI text into `Section.Key` → value (keys before any section keep their name).
#[must_use]
pub fn parse_ini(text: &str) -> BTreeMap<String, String> {
    let mut raw = BTreeMap::new();
    let mut section = String::new();
    for line in text.lines().map(str::trim) {
        if line.is_empty() || line.starts_with(';') || line.starts_with('#') {
            continue;
        }
        if let Some(name) = line.strip_prefix('[').and_then(|l| l.strip_suffix(']')) {
            name.trim().clone_into(&mut section);
        } else if let Some((key, value)) = line.split_once('=') {
            let key = if section.is_empty() {
                key.trim().to_owned()
            } else {
                format!("{section}.{}", key.trim())
            };
            raw.entry(key).or_insert_with(|| value.trim().to_owned());
        }
    }
    raw
}

fn number(raw: &BTreeMap<String, String>, key: &str) -> Option<f64> {
    raw.get(key)
        .and_then(|v| v.trim().parse::<f64>().ok())
        .filter(|v| v.is_finite())
}

/// Parses FEI/Thermo INI metadata (TIFF tag 34682 or 34680).
#[must_use]
pub fn parse_fei(bytes: &[u8]) -> SemMetadata {
    let raw = parse_ini(&decode_text(bytes));
    let pixel_m = number(&raw, "Scan.PixelWidth").or_else(|| number(&raw, "EScan.PixelWidth"));
    let tilt_rad = number(&raw, "Stage.StageT");
    let dwell_s = number(&raw, "Scan.Dwelltime").or_else(|| number(&raw, "EScan.Dwell"));
    let area = match (
        number(&raw, "Image.ResolutionX"),
        number(&raw, "Image.ResolutionY"),
    ) {
        // Whole numbers of pixels, as FEI writes them.
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        (Some(w), Some(h)) if w >= 1.0 && h >= 1.0 && w.fract() == 0.0 && h.fract() == 0.0 => {
            Some(ImageArea::Size {
                width: w as usize,
                height: h as usize,
            })
        }
        _ => None,
    };
    SemMetadata {
        vendor: Some(SemVendor::Fei),
        pixel_size_um: positive(pixel_m.map(|m| m * 1e6)),
        tilt_deg: tilt_rad.map(f64::to_degrees),
        dwell_us: positive(dwell_s.map(|s| s * 1e6)),
        field_width_um: None,
        image_area: area,
        raw,
    }
}

/// Splits Tescan's tag into (type, text) blocks: u32 size, u16 type, `size − 2` bytes, in
/// the file's byte order, until the type-0 block. `None` when the bytes do not follow it.
fn tescan_blocks(bytes: &[u8], big_endian: bool) -> Option<Vec<(u16, &[u8])>> {
    let mut blocks = Vec::new();
    let mut p = 0usize;
    while p + 6 <= bytes.len() {
        let size_bytes = [bytes[p], bytes[p + 1], bytes[p + 2], bytes[p + 3]];
        let size = if big_endian {
            u32::from_be_bytes(size_bytes)
        } else {
            u32::from_le_bytes(size_bytes)
        } as usize;
        let kind = if big_endian {
            u16::from_be_bytes([bytes[p + 4], bytes[p + 5]])
        } else {
            u16::from_le_bytes([bytes[p + 4], bytes[p + 5]])
        };
        if size < 2 || p + 6 + (size - 2) > bytes.len() {
            return None;
        }
        blocks.push((kind, &bytes[p + 6..p + 6 + size - 2]));
        p += 6 + size - 2;
        if kind == 0 {
            break;
        }
    }
    (!blocks.is_empty()).then_some(blocks)
}

/// Parses Tescan metadata (TIFF tag 50431).
#[must_use]
pub fn parse_tescan(bytes: &[u8], big_endian: bool) -> SemMetadata {
    let mut raw = BTreeMap::new();
    let blocks = tescan_blocks(bytes, big_endian).unwrap_or_default();
    for (kind, data) in &blocks {
        let section = match kind {
            2 => "MAIN",
            3 => "SEM",
            4 => "GAMA",
            5 => "FIB",
            _ => continue,
        };
        for (k, v) in parse_ini(&decode_text(data)) {
            raw.entry(format!("{section}.{k}")).or_insert(v);
        }
    }
    if raw.is_empty() {
        // Plain INI text ("[MAIN]\nPixelSizeX=…"), possibly after binary bytes.
        let text = decode_text(bytes);
        let start = text.find("[MAIN]").unwrap_or(0);
        raw = parse_ini(&text[start..]);
    }
    let pixel_m = number(&raw, "MAIN.PixelSizeX");
    let tilt = number(&raw, "SEM.StageTilt");
    let dwell_s = number(&raw, "SEM.DwellTime").or_else(|| number(&raw, "FIB.DwellTime"));
    let strip = raw
        .get("MAIN.ImageStripSize")
        .and_then(|v| v.trim().parse::<usize>().ok())
        .filter(|&rows| rows > 0);
    SemMetadata {
        vendor: Some(SemVendor::Tescan),
        pixel_size_um: positive(pixel_m.map(|m| m * 1e6)),
        tilt_deg: tilt,
        dwell_us: positive(dwell_s.map(|s| s * 1e6)),
        field_width_um: None,
        image_area: strip.map(ImageArea::StripRows),
        raw,
    }
}

/// Parses a Hitachi sidecar (`NAME.txt` beside the image); `None` unless it starts with
/// `[SemImageFile]`.
#[must_use]
pub fn parse_hitachi(bytes: &[u8]) -> Option<SemMetadata> {
    let text = decode_text(bytes);
    if !text.trim_start().starts_with("[SemImageFile]") {
        return None;
    }
    let raw: BTreeMap<String, String> = parse_ini(&text)
        .into_iter()
        .map(|(k, v)| {
            (
                k.strip_prefix("SemImageFile.")
                    .map(str::to_owned)
                    .unwrap_or(k),
                v,
            )
        })
        .collect();
    let pixel_nm = raw
        .get("PixelSize")
        .and_then(|v| number_and_unit(v))
        .map(|(n, _)| n);
    let tilt = raw.get("StagePositionT").and_then(|v| parse_angle_deg(v));
    Some(SemMetadata {
        vendor: Some(SemVendor::Hitachi),
        pixel_size_um: positive(pixel_nm.map(|nm| nm * 1e-3)),
        tilt_deg: tilt,
        dwell_us: None,
        field_width_um: None,
        image_area: raw.get("DataSize").and_then(|v| size_pair(v, &['x', 'X'])),
        raw,
    })
}

/// JEOL's horizontal field at magnification 1, µm (what Odemis uses when the sidecar
/// gives no field of view) [OD-IO].
const JEOL_FIELD_AT_MAG_1_UM: f64 = 128_000.0;

/// Parses a JEOL sidecar (`NAME.txt` beside the image: `$KEY value` lines, `$$` for some);
/// `None` unless every line is of that form and `CM_FORMAT` or `CM_VERSION` is present.
/// Keys are stored without their `$`s. The field of view (`$CM_FIELD_OF_VIEW 1.067mm
/// 0.800mm`, or `1.067 0.800mm`) gives the field width; without it, 128 mm ÷ `$CM_MAG`.
/// The pixel size is that width over the image's width, worked out by the image reader.
#[must_use]
pub fn parse_jeol(bytes: &[u8]) -> Option<SemMetadata> {
    let text = decode_text(bytes);
    let mut raw = BTreeMap::new();
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let rest = line.strip_prefix('$')?.trim_start_matches('$');
        let (key, value) = rest.split_once(' ').unwrap_or((rest, ""));
        raw.entry(key.to_owned())
            .or_insert_with(|| value.trim().to_owned());
    }
    if !raw.contains_key("CM_FORMAT") && !raw.contains_key("CM_VERSION") {
        return None;
    }
    let field = raw.get("CM_FIELD_OF_VIEW").and_then(|v| {
        let mut tokens = v.split_whitespace();
        let first = tokens.next()?;
        // "1.067 0.800mm": the first number takes the unit of the second.
        parse_length_um(first).or_else(|| {
            let unit = tokens
                .next()
                .and_then(|t| number_and_unit(t))
                .map_or("mm", |(_, u)| u);
            parse_length_um(&format!("{first} {unit}"))
        })
    });
    let field = field.or_else(|| {
        number(&raw, "CM_MAG")
            .filter(|m| *m > 0.0)
            .map(|m| JEOL_FIELD_AT_MAG_1_UM / m)
    });
    Some(SemMetadata {
        vendor: Some(SemVendor::Jeol),
        pixel_size_um: None,
        tilt_deg: None,
        dwell_us: None,
        field_width_um: positive(field),
        image_area: raw.get("CM_FULL_SIZE").and_then(|v| size_pair(v, &[' '])),
        raw,
    })
}

/// Parses a sidecar of either vendor that writes one (Hitachi, JEOL).
#[must_use]
pub fn parse_sidecar(bytes: &[u8]) -> Option<SemMetadata> {
    parse_hitachi(bytes).or_else(|| parse_jeol(bytes))
}

/// Parses sdsem's own ImageDescription JSON; `None` for any other description.
#[must_use]
pub fn parse_sdsem_description(bytes: &[u8]) -> Option<SemMetadata> {
    let value: serde_json::Value = serde_json::from_str(&decode_text(bytes)).ok()?;
    if value.get("sdsem")?.as_str()? != "micrograph" {
        return None;
    }
    let raw = value
        .as_object()?
        .iter()
        .map(|(k, v)| {
            (
                k.clone(),
                v.as_str().map_or_else(|| v.to_string(), str::to_owned),
            )
        })
        .collect();
    Some(SemMetadata {
        vendor: Some(SemVendor::Sdsem),
        pixel_size_um: positive(
            value
                .get("pixel_size_um")
                .and_then(serde_json::Value::as_f64),
        ),
        tilt_deg: value
            .get("tilt_deg")
            .and_then(serde_json::Value::as_f64)
            .filter(|t| t.is_finite()),
        raw,
        ..SemMetadata::default()
    })
}

/// The Zeiss-style block sdsem writes into tag 34118 (Latin-1, `\r\n` lines, parameter
/// name lines before value lines, as SmartSEM does), so Zeiss-aware readers find the
/// pixel size and tilt.
#[must_use]
pub fn zeiss_block(pixel_size_um: Option<f64>, tilt_deg: Option<f64>) -> Vec<u8> {
    let mut text = String::new();
    if let Some(p) = pixel_size_um {
        text.push_str(&format!(
            "AP_IMAGE_PIXEL_SIZE\r\nImage Pixel Size = {:.4} nm\r\n",
            p * 1e3
        ));
    }
    if let Some(t) = tilt_deg {
        text.push_str(&format!("AP_STAGE_AT_T\r\nStage at T = {t:.3} \u{b0}\r\n"));
    }
    text.push_str(&format!(
        "SV_SOFTWARE\r\nSoftware = sdsem {}\r\n",
        env!("CARGO_PKG_VERSION")
    ));
    // Latin-1: every char here is below U+0100.
    let mut bytes: Vec<u8> = text
        .chars()
        .map(|c| u8::try_from(c).unwrap_or(b'?'))
        .collect();
    bytes.push(0);
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An excerpt of the Potamogeton pot_02.tif block, with its Latin-1 degree sign.
    const ZEISS_SAMPLE: &[u8] =
        b"0\r\n0\r\n0\r\n1.116500e-007\r\nDP_TILTED\r\nStage Tilted = No\r\n\
AP_TILT_ANGLE\r\nTilt Angle =  30.0 \xb0\r\nAP_PIXEL_SIZE\r\nPixel Size = 111.6 nm\r\n\
AP_IMAGE_PIXEL_SIZE\r\nImage Pixel Size = 55.82 nm\r\nAP_STAGE_AT_T\r\nStage at T =  -3.0 \xb0\r\n\
AP_DATE\r\nDate :8 Mar 2016\r\n\0\0\0";

    #[test]
    fn zeiss_reads_image_pixel_size_and_stage_tilt() {
        let m = parse_zeiss(ZEISS_SAMPLE);
        assert_eq!(m.vendor, Some(SemVendor::Zeiss));
        assert!((m.pixel_size_um.unwrap() - 0.05582).abs() < 1e-12);
        assert_eq!(m.tilt_deg, Some(-3.0));
        assert_eq!(m.raw["Date"], "8 Mar 2016");
        assert_eq!(m.raw["Tilt Angle"], "30.0 \u{b0}");
    }

    #[test]
    fn the_instrument_comes_from_each_vendors_own_keys() {
        let zeiss = parse_zeiss(
            b"SV_SERIAL_NUMBER\r\nSerial No. = 4711\r\nSV_VERSION\r\nVersion = V06.03\r\n",
        );
        let id = zeiss.instrument();
        assert_eq!(
            (id.vendor.as_str(), id.version.as_str(), id.serial.as_str()),
            ("Zeiss", "V06.03", "4711")
        );
        let fei = parse_fei(b"[System]\r\nType=SEM\r\nDnumber=D1234\r\nSoftware=9.4\r\n");
        let id = fei.instrument();
        assert_eq!(
            (id.model.as_str(), id.version.as_str(), id.serial.as_str()),
            ("SEM", "9.4", "D1234")
        );
        let tescan = parse_tescan(b"[MAIN]\nDevice=MIRA3\nSerialNumber=VG99\n", false);
        let id = tescan.instrument();
        assert_eq!(
            (id.vendor.as_str(), id.model.as_str(), id.serial.as_str()),
            ("Tescan", "MIRA3", "VG99")
        );
        assert!(SemMetadata::default().instrument().is_empty());
    }

    #[test]
    fn zeiss_units_and_degree_encodings() {
        for (text, um) in [
            ("Image Pixel Size = 1.2 µm", 1.2),
            ("Image Pixel Size = 1.2 μm", 1.2),
            ("Image Pixel Size = 980 pm", 0.00098),
            ("Image Pixel Size = 3.5nm", 0.0035),
        ] {
            let m = parse_zeiss(text.as_bytes());
            assert!((m.pixel_size_um.unwrap() - um).abs() < 1e-12, "{text}");
        }
        for text in [
            "Stage at T = 12.5 °".as_bytes(),
            b"Stage at T = 12.5 \xb0",
            b"Stage at T = 12.5 deg",
        ] {
            assert_eq!(parse_zeiss(text).tilt_deg, Some(12.5));
        }
        assert_eq!(
            parse_zeiss(b"Image Pixel Size = 5 furlongs").pixel_size_um,
            None
        );
        assert_eq!(parse_zeiss(b"Stage at T = 0.2 rad").tilt_deg, None);
    }

    #[test]
    fn fei_converts_metres_and_radians() {
        let text =
            b"[User]\r\nDate=12/01/2016\r\n[Scan]\r\nDwelltime=3e-006\r\nPixelWidth=1.5e-008\r\n\
PixelHeight=1.5e-008\r\n[Stage]\r\nStageX=0.0021\r\nStageT=0.10472\r\n";
        let m = parse_fei(text);
        assert_eq!(m.vendor, Some(SemVendor::Fei));
        assert!((m.pixel_size_um.unwrap() - 0.015).abs() < 1e-12);
        assert!((m.tilt_deg.unwrap() - 6.0).abs() < 1e-3);
        assert_eq!(m.raw["Scan.Dwelltime"], "3e-006");
    }

    #[test]
    fn tescan_blocks_and_plain_ini() {
        let main = b"Device=MIRA\r\nPixelSizeX=2.5e-08\r\nPixelSizeY=2.5e-08\r\n";
        let sem = b"HV=5000\r\nStageTilt=15.5\r\n";
        let mut tag = Vec::new();
        for (kind, data) in [(1u16, &b"\xff\xd8jpeg"[..]), (2, &main[..]), (3, &sem[..])] {
            tag.extend(((data.len() + 2) as u32).to_le_bytes());
            tag.extend(kind.to_le_bytes());
            tag.extend_from_slice(data);
        }
        tag.extend(2u32.to_le_bytes());
        tag.extend(0u16.to_le_bytes());
        let m = parse_tescan(&tag, false);
        assert!((m.pixel_size_um.unwrap() - 0.025).abs() < 1e-12);
        assert_eq!(m.tilt_deg, Some(15.5));
        assert_eq!(m.raw["MAIN.Device"], "MIRA");

        let plain = b"\x00\x01junk[MAIN]\r\nPixelSizeX=1e-07\r\n[SEM]\r\nStageTilt=-2\r\n";
        let m = parse_tescan(plain, false);
        assert!((m.pixel_size_um.unwrap() - 0.1).abs() < 1e-12);
        assert_eq!(m.tilt_deg, Some(-2.0));
    }

    #[test]
    fn hitachi_sidecar_in_nanometres() {
        let text = b"[SemImageFile]\r\nInstructName=S-4800\r\nSerialNumber=123\r\n\
DataSize=1280x960\r\nPixelSize=24.8\r\nStagePositionX=12500000\r\nStagePositionT=5.0\r\n";
        let m = parse_hitachi(text).unwrap();
        assert_eq!(m.vendor, Some(SemVendor::Hitachi));
        assert!((m.pixel_size_um.unwrap() - 0.0248).abs() < 1e-12);
        assert_eq!(m.tilt_deg, Some(5.0));
        assert_eq!(m.raw["InstructName"], "S-4800");
        // UTF-16 with BOM, as some Hitachi software writes.
        let utf16: Vec<u8> = [0xFF, 0xFE]
            .into_iter()
            .chain(
                "[SemImageFile]\r\nPixelSize=10\r\n"
                    .encode_utf16()
                    .flat_map(u16::to_le_bytes),
            )
            .collect();
        assert!((parse_hitachi(&utf16).unwrap().pixel_size_um.unwrap() - 0.01).abs() < 1e-12);
        assert!(parse_hitachi(b"just some notes").is_none());
    }

    #[test]
    fn own_blocks_parse_back() {
        let z = parse_zeiss(&zeiss_block(Some(0.05582), Some(-3.0)));
        assert!((z.pixel_size_um.unwrap() - 0.05582).abs() < 1e-9);
        assert_eq!(z.tilt_deg, Some(-3.0));
        let d = br#"{"sdsem":"micrograph","pixel_size_um":0.1,"tilt_deg":9.0}"#;
        let m = parse_sdsem_description(d).unwrap();
        assert_eq!((m.pixel_size_um, m.tilt_deg), (Some(0.1), Some(9.0)));
        assert!(parse_sdsem_description(br#"{"sdsem":"height"}"#).is_none());
        assert!(parse_sdsem_description(b"ImageJ=1.52\nunit=micron").is_none());
    }

    #[test]
    fn merge_keeps_first_values() {
        let mut a = SemMetadata {
            vendor: Some(SemVendor::Sdsem),
            pixel_size_um: Some(0.1),
            ..SemMetadata::default()
        };
        a.merge(parse_zeiss(ZEISS_SAMPLE));
        assert_eq!(a.vendor, Some(SemVendor::Sdsem));
        assert_eq!(a.pixel_size_um, Some(0.1));
        assert_eq!(a.tilt_deg, Some(-3.0));
    }

    #[test]
    fn info_bars_and_dwell_of_each_vendor() {
        let z = parse_zeiss(
            b"AP_DWELL\r\nDwell Time = 50 ns\r\nDP_STORE\r\nStore resolution = 1024 * 768\r\n",
        );
        assert_eq!(z.dwell_us, Some(0.05));
        assert_eq!(z.kept_size(1024, 768), None, "no bar stored");
        assert_eq!(z.kept_size(1024, 884), Some((1024, 768)), "data zone below");
        assert_eq!(
            z.kept_size(768, 1024),
            None,
            "rotated after storing: left alone"
        );

        let f = parse_fei(
            b"[Image]\r\nResolutionX=1536\r\nResolutionY=1024\r\n[Scan]\r\nDwelltime=1e-006\r\n",
        );
        assert_eq!(f.kept_size(1536, 1092), Some((1536, 1024)));
        assert!((f.dwell_us.unwrap() - 1.0).abs() < 1e-12);

        let mut tag = Vec::new();
        for (kind, data) in [
            (2u16, &b"ImageStripSize=120\nPixelSizeX=2.5012e-6\n\0"[..]),
            (3, &b"DwellTime=3.2000e-6\nStageTilt=0.0\n\0"[..]),
        ] {
            tag.extend(((data.len() + 2) as u32).to_le_bytes());
            tag.extend(kind.to_le_bytes());
            tag.extend_from_slice(data);
        }
        let t = parse_tescan(&tag, false);
        assert_eq!(t.kept_size(1024, 888), Some((1024, 768)));
        assert!((t.dwell_us.unwrap() - 3.2).abs() < 1e-9);
        assert!((t.pixel_size_um.unwrap() - 2.5012).abs() < 1e-9);
        assert_eq!(t.kept_size(1024, 100), None, "strip taller than the image");

        let h = parse_hitachi(b"[SemImageFile]\r\nDataSize=1280x960\r\n").unwrap();
        assert_eq!(h.kept_size(1280, 1024), Some((1280, 960)));
    }

    #[test]
    fn jeol_sidecar_gives_the_field_width() {
        let text = b"$CM_FORMAT JEOL-SEM\n$CM_VERSION 3.0\n$CM_MAG 50\n$$SM_WD 9.07\n\
$CM_STAGE_POS 5.483 0.831 8.5 -0.0 0.0 0.000\n$CM_FULL_SIZE 1280 960\n$CM_TITLE \n";
        let m = parse_jeol(text).unwrap();
        assert_eq!(m.vendor, Some(SemVendor::Jeol));
        // No field of view: 128 mm at magnification 1.
        assert!((m.field_width_um.unwrap() - 2560.0).abs() < 1e-9);
        assert_eq!(m.raw["SM_WD"], "9.07");
        assert_eq!(m.raw["CM_TITLE"], "");
        assert_eq!(
            m.tilt_deg, None,
            "the stage field's layout varies: not read"
        );
        assert_eq!(m.kept_size(1280, 1024), Some((1280, 960)));
        for fov in ["1.067mm 0.800mm", "1.067 0.800mm"] {
            let t = format!("$CM_FORMAT JEOL/EO\n$CM_MAG 120\n$CM_FIELD_OF_VIEW {fov}\n");
            let m = parse_jeol(t.as_bytes()).unwrap();
            assert!((m.field_width_um.unwrap() - 1067.0).abs() < 1e-9, "{fov}");
        }
        assert!(
            parse_jeol(b"$SOMETHING else\n").is_none(),
            "not a JEOL header"
        );
        assert!(parse_jeol(b"notes\n$CM_FORMAT JEOL\n").is_none());
        assert_eq!(parse_sidecar(text).unwrap().vendor, Some(SemVendor::Jeol));
        assert_eq!(
            parse_sidecar(b"[SemImageFile]\r\nPixelSize=1\r\n")
                .unwrap()
                .vendor,
            Some(SemVendor::Hitachi)
        );
    }
}
