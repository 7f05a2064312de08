//! TIFF files as SEM vendors store them (VENDORS §4.1), for the simulated store folder:
//! grey 8- or 16-bit strips, the vendor's metadata tag, and the vendor's info bar.
//!
//! | vendor | metadata | info bar | layout |
//! | --- | --- | --- | --- |
//! | Zeiss SmartSEM | tag 34118, Latin-1 `Label = value unit` lines after code lines | none (store resolution = image) | directory first, pixels after |
//! | FEI / Thermo Fisher | tag 34682, INI (`[Scan] PixelWidth` m, `[Stage] StageT` rad, `[Image] ResolutionY`) | data bar below the scan | pixels first, directory last |
//! | TESCAN | tag 50431, chunks `[u32 length][u16 type][text\0]` (2 `[MAIN]`, 3 `[SEM]`) | `ImageStripSize` rows below | pixels first, directory last |
//!
//! Written by hand (little-endian classic TIFF, uncompressed) so the byte layout — where
//! the directory lies, hence what a partially written file looks like — is the vendor's.

use serde::{Deserialize, Serialize};

/// Whose store format to imitate.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Vendor {
    #[default]
    Zeiss,
    Fei,
    Tescan,
}

impl Vendor {
    /// The vendor's name in messages.
    #[must_use]
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Zeiss => "zeiss",
            Self::Fei => "fei",
            Self::Tescan => "tescan",
        }
    }

    /// Rows of info bar stored below a scan of `height` rows (in the proportions of the
    /// public samples: FEI 68 rows for 1024, TESCAN 120 for 768) [OD-IO].
    #[must_use]
    pub fn bar_rows(self, height: usize) -> usize {
        match self {
            Self::Zeiss => 0,
            Self::Fei => (height * 68 / 1024).max(8),
            Self::Tescan => (height * 120 / 768).max(8),
        }
    }
}

/// What a stored micrograph records about itself.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredMeta {
    pub pixel_size_um: f64,
    pub dwell_us: f64,
    pub stage_x_um: f64,
    pub stage_y_um: f64,
    /// The tilt written into the metadata, degrees.
    pub tilt_deg: f64,
    /// Wall-clock time of the scan, s since the Unix epoch (for the date and time fields).
    pub unix_s: u64,
}

/// Samples of the scanned image, row-major.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Samples {
    U8(Vec<u8>),
    U16(Vec<u16>),
}

impl Samples {
    fn bits(&self) -> u16 {
        match self {
            Self::U8(_) => 8,
            Self::U16(_) => 16,
        }
    }
}

/// The whole file of a `width` × `height` scan as `vendor` stores it, info bar included.
///
/// # Panics
/// Never for consistent input; `samples` must hold `width * height` values.
#[must_use]
pub fn encode(
    vendor: Vendor,
    width: usize,
    height: usize,
    samples: &Samples,
    meta: &StoredMeta,
) -> Vec<u8> {
    let bar = vendor.bar_rows(height);
    let stored_h = height + bar;
    let bytes_per = usize::from(samples.bits() / 8);
    // Pixels as stored, little-endian, the bar a dark strip with a light frame.
    let mut pixels = Vec::with_capacity(width * stored_h * bytes_per);
    match samples {
        Samples::U8(v) => pixels.extend_from_slice(&v[..width * height]),
        Samples::U16(v) => {
            for s in &v[..width * height] {
                pixels.extend_from_slice(&s.to_le_bytes());
            }
        }
    }
    for y in 0..bar {
        for x in 0..width {
            let edge = y == 0 || y + 1 == bar || x == 0 || x + 1 == width;
            let (v8, v16) = if edge {
                (255u8, u16::MAX)
            } else {
                (16u8, 4096u16)
            };
            match samples {
                Samples::U8(_) => pixels.push(v8),
                Samples::U16(_) => pixels.extend_from_slice(&v16.to_le_bytes()),
            }
        }
    }
    let (tag, field_type, blob) = match vendor {
        Vendor::Zeiss => (34118u16, 2u16, zeiss_text(width, height, meta)),
        Vendor::Fei => (34682, 2, fei_text(width, height, meta)),
        Vendor::Tescan => (50431, 1, tescan_chunks(bar, meta)),
    };
    let rows_per_strip = (65536 / (width * bytes_per).max(1)).clamp(1, stored_h);
    let strips = stored_h.div_ceil(rows_per_strip);
    let strip_len = |i: usize| {
        let rows = rows_per_strip.min(stored_h - i * rows_per_strip);
        rows * width * bytes_per
    };
    let entries = 11usize;
    let ifd_len = 2 + entries * 12 + 4;
    let arrays_len = 8 * strips;
    // Directory first (Zeiss) or last (FEI, TESCAN): a partial file then lacks its
    // strips, or its directory.
    let directory_first = vendor == Vendor::Zeiss;
    let mut at = 8usize;
    let ifd_at;
    let pixels_at;
    if directory_first {
        ifd_at = at;
        at += ifd_len;
        pixels_at = at;
        at += pixels.len();
    } else {
        pixels_at = at;
        at += pixels.len();
        ifd_at = at;
        at += ifd_len;
    }
    let offsets_at = at;
    let counts_at = at + 4 * strips;
    let blob_at = at + arrays_len;
    let to32 = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);

    let mut out = Vec::with_capacity(blob_at + blob.len() + 1);
    out.extend_from_slice(b"II*\0");
    out.extend_from_slice(&to32(ifd_at).to_le_bytes());
    let mut ifd = Vec::with_capacity(ifd_len);
    ifd.extend_from_slice(&u16::try_from(entries).unwrap_or(0).to_le_bytes());
    let mut entry = |tag: u16, ty: u16, count: usize, value: u32| {
        ifd.extend_from_slice(&tag.to_le_bytes());
        ifd.extend_from_slice(&ty.to_le_bytes());
        ifd.extend_from_slice(&to32(count).to_le_bytes());
        ifd.extend_from_slice(&value.to_le_bytes());
    };
    // Tags in ascending order, SHORT values inline in the low half.
    entry(256, 4, 1, to32(width));
    entry(257, 4, 1, to32(stored_h));
    entry(258, 3, 1, u32::from(samples.bits()));
    entry(259, 3, 1, 1);
    entry(262, 3, 1, 1);
    entry(
        273,
        4,
        strips,
        if strips == 1 {
            to32(pixels_at)
        } else {
            to32(offsets_at)
        },
    );
    entry(277, 3, 1, 1);
    entry(278, 4, 1, to32(rows_per_strip));
    entry(
        279,
        4,
        strips,
        if strips == 1 {
            to32(strip_len(0))
        } else {
            to32(counts_at)
        },
    );
    entry(284, 3, 1, 1);
    entry(tag, field_type, blob.len(), to32(blob_at));
    ifd.extend_from_slice(&0u32.to_le_bytes());
    if directory_first {
        out.extend_from_slice(&ifd);
        out.extend_from_slice(&pixels);
    } else {
        out.extend_from_slice(&pixels);
        out.extend_from_slice(&ifd);
    }
    for i in 0..strips {
        out.extend_from_slice(
            &to32(pixels_at + i * rows_per_strip * width * bytes_per).to_le_bytes(),
        );
    }
    for i in 0..strips {
        out.extend_from_slice(&to32(strip_len(i)).to_le_bytes());
    }
    out.extend_from_slice(&blob);
    out
}

/// Date and time of `unix_s` (UTC) as (year, month, day, hour, minute, second).
fn civil(unix_s: u64) -> (i64, u32, u32, u64, u64, u64) {
    let days = i64::try_from(unix_s / 86_400).unwrap_or(0);
    let secs = unix_s % 86_400;
    // Days to civil date (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = u32::try_from(doy - (153 * mp + 2) / 5 + 1).unwrap_or(1);
    let m = u32::try_from(if mp < 10 { mp + 3 } else { mp - 9 }).unwrap_or(1);
    let y = yoe + era * 400 + i64::from(m <= 2);
    (y, m, d, secs / 3600, secs / 60 % 60, secs % 60)
}

/// SmartSEM's block: a few numbers, a count, then pairs of code and `Label = value` lines,
/// Latin-1 (`°` is 0xB0), CR LF.
fn zeiss_text(width: usize, height: usize, m: &StoredMeta) -> Vec<u8> {
    let (y, mo, d, h, mi, s) = civil(m.unix_s);
    const MONTHS: [&str; 12] = [
        "Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec",
    ];
    let month = MONTHS[(mo as usize).saturating_sub(1).min(11)];
    #[allow(clippy::cast_precision_loss)]
    let pairs = [
        (
            "DP_IMAGE_STORE",
            format!("Store resolution = {width} * {height}"),
        ),
        (
            "AP_IMAGE_PIXEL_SIZE",
            format!("Image Pixel Size = {:.2} nm", m.pixel_size_um * 1e3),
        ),
        (
            "AP_PIXEL_SIZE",
            format!("Pixel Size = {:.2} nm", m.pixel_size_um * 1e3),
        ),
        (
            "AP_WIDTH",
            format!("Width = {:.2} \u{b5}m", m.pixel_size_um * width as f64),
        ),
        (
            "DP_DWELL_TIME",
            format!("Dwell Time = {:.0} ns", m.dwell_us * 1e3),
        ),
        (
            "AP_STAGE_AT_X",
            format!("Stage at X = {:.4} mm", m.stage_x_um * 1e-3),
        ),
        (
            "AP_STAGE_AT_Y",
            format!("Stage at Y = {:.4} mm", m.stage_y_um * 1e-3),
        ),
        (
            "AP_STAGE_AT_T",
            format!("Stage at T = {:5.1} \u{b0}", m.tilt_deg),
        ),
        ("AP_STAGE_AT_R", "Stage at R =   0.0 \u{b0}".to_owned()),
        ("AP_DATE", format!("Date :{d} {month} {y}")),
        ("AP_TIME", format!("Time :{h:02}:{mi:02}:{s:02}")),
        ("SV_SERIAL_NUMBER", "Serial No. = sdsem-sim".to_owned()),
        (
            "SV_VERSION",
            format!("Version = sdsem-sim {}", env!("CARGO_PKG_VERSION")),
        ),
    ];
    let mut text = format!(
        "0\r\n0\r\n0\r\n{:e}\r\n{}\r\n",
        m.pixel_size_um * 1e-6,
        pairs.len()
    );
    for (code, line) in pairs {
        text.push_str(code);
        text.push_str("\r\n");
        text.push_str(&line);
        text.push_str("\r\n");
    }
    let mut bytes: Vec<u8> = text
        .chars()
        .map(|c| u8::try_from(c).unwrap_or(b'?'))
        .collect();
    bytes.push(0);
    bytes
}

/// xT's INI: metres, seconds, radians; `[Image]` gives the scan's size above the data bar.
fn fei_text(width: usize, height: usize, m: &StoredMeta) -> Vec<u8> {
    let (y, mo, d, h, mi, s) = civil(m.unix_s);
    let (h12, ampm) = match h {
        0 => (12, "AM"),
        1..=11 => (h, "AM"),
        12 => (12, "PM"),
        _ => (h - 12, "PM"),
    };
    let p = m.pixel_size_um * 1e-6;
    #[allow(clippy::cast_precision_loss)]
    let text = format!(
        "[User]\r\nDate={mo:02}/{d:02}/{y}\r\nTime={h12:02}:{mi:02}:{s:02} {ampm}\r\n\r\n\
[System]\r\nType=SEM\r\nDnumber=sdsem-sim\r\n\r\n\
[Beam]\r\nBeam=EBeam\r\n\r\n\
[Scan]\r\nInternalScan=true\r\nDwelltime={:e}\r\nPixelWidth={p:e}\r\nPixelHeight={p:e}\r\n\
HorFieldsize={:e}\r\nVerFieldsize={:e}\r\n\r\n\
[Stage]\r\nStageX={:e}\r\nStageY={:e}\r\nStageZ=0\r\nStageR=0\r\nStageT={:e}\r\n\r\n\
[Image]\r\nResolutionX={width}\r\nResolutionY={height}\r\n\r\n",
        m.dwell_us * 1e-6,
        p * width as f64,
        p * height as f64,
        m.stage_x_um * 1e-6,
        m.stage_y_um * 1e-6,
        m.tilt_deg.to_radians(),
    );
    let mut bytes = text.into_bytes();
    bytes.push(0);
    bytes
}

/// TESCAN's chunks: `[u32 length = 2 + text][u16 type][text, NUL-terminated]`.
fn tescan_chunks(bar: usize, m: &StoredMeta) -> Vec<u8> {
    let (y, mo, d, h, mi, s) = civil(m.unix_s);
    let p = m.pixel_size_um * 1e-6;
    let main = format!(
        "AccFrames=1\nDate={y}-{mo:02}-{d:02}\nDevice=sdsem-sim\nImageStripSize={bar}\n\
PixelSizeX={p:e}\nPixelSizeY={p:e}\nSerialNumber=sdsem-sim\nTime={h:02}:{mi:02}:{s:02}\n"
    );
    let sem = format!(
        "DwellTime={:e}\nHV=10.0000e3\nScanRotation=0.0\nStageRotation=0.0\nStageTilt={}\n\
StageX={:e}\nStageY={:e}\n",
        m.dwell_us * 1e-6,
        m.tilt_deg,
        m.stage_x_um * 1e-6,
        m.stage_y_um * 1e-6,
    );
    let mut out = Vec::new();
    for (kind, text) in [(2u16, main), (3, sem)] {
        let mut data = text.into_bytes();
        data.push(0);
        out.extend_from_slice(
            &u32::try_from(data.len() + 2)
                .unwrap_or(u32::MAX)
                .to_le_bytes(),
        );
        out.extend_from_slice(&kind.to_le_bytes());
        out.extend_from_slice(&data);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn meta() -> StoredMeta {
        StoredMeta {
            pixel_size_um: 0.05582,
            dwell_us: 0.1,
            stage_x_um: 1500.0,
            stage_y_um: -20.0,
            tilt_deg: -3.0,
            unix_s: 1_700_000_000,
        }
    }

    /// Reads (tag → (type, count, value-or-offset)) of the first directory.
    fn directory(bytes: &[u8]) -> std::collections::BTreeMap<u16, (u16, u32, u32)> {
        let u16_at = |a: usize| u16::from_le_bytes([bytes[a], bytes[a + 1]]);
        let u32_at = |a: usize| u32::from_le_bytes(bytes[a..a + 4].try_into().unwrap());
        let ifd = u32_at(4) as usize;
        (0..usize::from(u16_at(ifd)))
            .map(|i| {
                let e = ifd + 2 + 12 * i;
                (u16_at(e), (u16_at(e + 2), u32_at(e + 4), u32_at(e + 8)))
            })
            .collect()
    }

    #[test]
    fn each_vendor_stores_its_bar_and_tag() {
        let samples = Samples::U8((0..64 * 48).map(|i| (i % 251) as u8).collect());
        for (vendor, tag, stored_h) in [
            (Vendor::Zeiss, 34118u16, 48u32),
            (Vendor::Fei, 34682, 48 + 8),
            (Vendor::Tescan, 50431, 48 + 8),
        ] {
            let bytes = encode(vendor, 64, 48, &samples, &meta());
            let dir = directory(&bytes);
            assert_eq!(dir[&256].2, 64, "{vendor:?}");
            assert_eq!(dir[&257].2, stored_h, "{vendor:?}");
            let (_, count, at) = dir[&tag];
            let blob = &bytes[at as usize..at as usize + count as usize];
            let text = String::from_utf8_lossy(blob);
            match vendor {
                Vendor::Zeiss => {
                    assert!(
                        blob.windows(19).any(|w| w == b"Stage at T =  -3.0 "),
                        "{text}"
                    );
                    assert!(blob.contains(&0xB0), "Latin-1 degree sign");
                    assert!(text.contains("Image Pixel Size = 55.82 nm"), "{text}");
                    assert!(text.contains("Store resolution = 64 * 48"), "{text}");
                }
                Vendor::Fei => {
                    assert!(text.contains("ResolutionY=48"), "{text}");
                    assert!(text.contains("PixelWidth=5.582e-8"), "{text}");
                    assert!(text.contains("StageT=-5.23598"), "{text}");
                }
                Vendor::Tescan => {
                    let len = u32::from_le_bytes(blob[..4].try_into().unwrap()) as usize;
                    assert_eq!(u16::from_le_bytes([blob[4], blob[5]]), 2, "[MAIN] first");
                    assert_eq!(
                        blob[4 + len - 1],
                        0,
                        "NUL-terminated, length counts the type"
                    );
                    assert!(
                        text.contains("ImageStripSize=8") && text.contains("StageTilt=-3"),
                        "{text}"
                    );
                }
            }
            // The scan's first pixels sit where the strip offsets say.
            let (_, strips, offsets) = dir[&273];
            let first = if strips == 1 {
                offsets as usize
            } else {
                u32::from_le_bytes(
                    bytes[offsets as usize..offsets as usize + 4]
                        .try_into()
                        .unwrap(),
                ) as usize
            };
            assert_eq!(&bytes[first..first + 3], &[0, 1, 2], "{vendor:?}");
        }
    }

    #[test]
    fn civil_dates() {
        assert_eq!(civil(0), (1970, 1, 1, 0, 0, 0));
        assert_eq!(civil(1_700_000_000), (2023, 11, 14, 22, 13, 20));
        assert_eq!(civil(951_782_400), (2000, 2, 29, 0, 0, 0));
    }
}
