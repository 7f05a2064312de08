//! `height.gsf`: Gwyddion Simple Field (DESIGN §7).
//!
//! Layout: the line `Gwyddion Simple Field 1.0`, `key = value` lines (`XRes`, `YRes`,
//! `XReal`, `YReal` in metres, `XYUnits = m`, `ZUnits = m`, `Title`), then 1–4 NUL bytes
//! so that the header length is a multiple of 4 — never zero padding bytes, a header
//! already aligned gets four — then `XRes × YRes` little-endian float32 samples, row by
//! row; the file size must match exactly.
//!
//! Unknown heights are written as NaN. GSF has no mask, but Gwyddion's loader (2.5x and
//! later, `gsffile.c`) turns non-finite samples into a mask with
//! `gwy_app_channel_mask_of_nans()` and fills them for display, so NaN is what shows a
//! Gwyddion user exactly which pixels are unknown; older Gwyddion versions load the NaN
//! values unmasked.

use std::io::Write;
use std::path::Path;

use super::ExportError;
use super::atomic::Target;
use crate::vision::Image;

const MAGIC: &str = "Gwyddion Simple Field 1.0\n";

/// A GSF field read back, values in the file's units (metres for ours).
#[derive(Debug, Clone, PartialEq)]
pub struct GsfField {
    pub xres: usize,
    pub yres: usize,
    /// Physical width, in `xy_units`.
    pub xreal: f64,
    /// Physical height, in `xy_units`.
    pub yreal: f64,
    pub xy_units: Option<String>,
    pub z_units: Option<String>,
    pub title: Option<String>,
    /// Samples, row-major, in `z_units`.
    pub data: Vec<f32>,
}

impl GsfField {
    /// The samples as an image in µm, when the z unit is metres.
    #[must_use]
    pub fn height_um(&self) -> Option<Image> {
        if self.z_units.as_deref() != Some("m") {
            return None;
        }
        Image::from_vec(
            self.xres,
            self.yres,
            self.data
                .iter()
                .map(|&v| (f64::from(v) * 1e6) as f32)
                .collect(),
        )
        .ok()
    }
}

/// The header text and its NUL padding (1–4 bytes, total a multiple of 4).
fn header(width: usize, height: usize, pixel_size_um: f64, title: &str) -> Vec<u8> {
    let xreal_m = width as f64 * pixel_size_um * 1e-6;
    let yreal_m = height as f64 * pixel_size_um * 1e-6;
    // `{:e}` prints the shortest representation that reads back exactly.
    let text = format!(
        "{MAGIC}XRes = {width}\nYRes = {height}\nXReal = {xreal_m:e}\nYReal = {yreal_m:e}\n\
         XYUnits = m\nZUnits = m\nTitle = {title}\n"
    );
    let mut bytes = text.into_bytes();
    let padding = 4 - bytes.len() % 4;
    bytes.extend(std::iter::repeat_n(0u8, padding));
    bytes
}

/// Writes `height.gsf` atomically from a height map in µm (converted to metres).
///
/// # Errors
/// [`ExportError::Invalid`] for an empty map, a non-positive pixel size or a title with a
/// line break or NUL; [`ExportError::Write`] on I/O failure.
pub fn write_gsf<'a>(
    target: impl Into<Target<'a>>,
    height_um: &Image,
    pixel_size_um: f64,
    title: &str,
) -> Result<(), ExportError> {
    let target = target.into();
    let invalid = |reason: &str| ExportError::Invalid {
        path: target.path(),
        reason: reason.to_owned(),
    };
    if height_um.is_empty() {
        return Err(invalid("the height map is empty"));
    }
    if !(pixel_size_um.is_finite() && pixel_size_um > 0.0) {
        return Err(invalid("the pixel size must be a positive number of µm"));
    }
    if title.contains(['\n', '\r', '\0']) {
        return Err(invalid("the title must be one line without NUL"));
    }
    let head = header(height_um.width(), height_um.height(), pixel_size_um, title);
    target.write(|w| {
        w.write_all(&head)?;
        let mut row = Vec::with_capacity(height_um.width() * 4);
        for y in 0..height_um.height() {
            row.clear();
            for &v in height_um.row(y) {
                // µm → m; NaN stays NaN (unknown).
                row.extend_from_slice(&((f64::from(v) * 1e-6) as f32).to_le_bytes());
            }
            w.write_all(&row)?;
        }
        Ok(())
    })
}

/// Reads a GSF file, checking the magic line, the padding and the exact size.
///
/// # Errors
/// [`ExportError::Read`] on I/O failure, [`ExportError::Format`] for any deviation.
pub fn read_gsf(path: &Path) -> Result<GsfField, ExportError> {
    let bytes = std::fs::read(path).map_err(|source| ExportError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    parse_gsf(&bytes).map_err(|reason| ExportError::Format {
        path: path.to_path_buf(),
        format: "Gwyddion Simple Field",
        reason,
    })
}

fn parse_gsf(bytes: &[u8]) -> Result<GsfField, String> {
    if !bytes.starts_with(MAGIC.as_bytes()) {
        return Err("missing the line \"Gwyddion Simple Field 1.0\"".to_owned());
    }
    let nul = bytes
        .iter()
        .position(|&b| b == 0)
        .ok_or("no NUL byte ends the header")?;
    let padding = 4 - nul % 4;
    let data_start = nul + padding;
    if bytes.len() < data_start || bytes[nul..data_start].iter().any(|&b| b != 0) {
        return Err(format!("header padding must be {padding} NUL bytes"));
    }
    let text = std::str::from_utf8(&bytes[MAGIC.len()..nul])
        .map_err(|_| "header is not UTF-8".to_owned())?;
    let mut field = GsfField {
        xres: 0,
        yres: 0,
        xreal: 1.0,
        yreal: 1.0,
        xy_units: None,
        z_units: None,
        title: None,
        data: Vec::new(),
    };
    for line in text.lines().filter(|l| !l.trim().is_empty()) {
        let (key, value) = line
            .split_once('=')
            .ok_or_else(|| format!("header line {line:?} is not key = value"))?;
        let (key, value) = (key.trim(), value.trim());
        let number = |v: &str| {
            v.parse::<f64>()
                .map_err(|_| format!("{key} = {v:?} is not a number"))
        };
        match key {
            "XRes" => field.xres = value.parse().map_err(|_| format!("bad XRes {value:?}"))?,
            "YRes" => field.yres = value.parse().map_err(|_| format!("bad YRes {value:?}"))?,
            "XReal" => field.xreal = number(value)?,
            "YReal" => field.yreal = number(value)?,
            "XYUnits" => field.xy_units = Some(value.to_owned()),
            "ZUnits" => field.z_units = Some(value.to_owned()),
            "Title" => field.title = Some(value.to_owned()),
            _ => {}
        }
    }
    if field.xres == 0 || field.yres == 0 {
        return Err("XRes and YRes must be positive".to_owned());
    }
    let expected = data_start + 4 * field.xres * field.yres;
    if bytes.len() != expected {
        return Err(format!(
            "size is {} bytes, header says {expected}",
            bytes.len()
        ));
    }
    field.data = bytes[data_start..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    Ok(field)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn padding_is_one_to_four_nul_bytes_and_never_zero() {
        for title in ["", "H", "He", "Hei", "Heig", "Height map"] {
            let h = header(7, 3, 0.1, title);
            assert_eq!(h.len() % 4, 0);
            let text_len = h.iter().position(|&b| b == 0).unwrap();
            let pad = h.len() - text_len;
            assert!(
                (1..=4).contains(&pad),
                "title {title:?}: {pad} padding bytes"
            );
        }
    }

    #[test]
    fn gsf_round_trips_metres_and_nan() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("height.gsf");
        let mut img = Image::from_fn(4, 3, |x, y| x as f32 * 2.0 + y as f32 * 0.5);
        img.set(1, 2, f32::NAN);
        write_gsf(&path, &img, 0.05582, "Height").unwrap();

        let bytes = std::fs::read(&path).unwrap();
        let text = String::from_utf8_lossy(&bytes[..bytes.iter().position(|&b| b == 0).unwrap()]);
        assert!(text.starts_with("Gwyddion Simple Field 1.0\nXRes = 4\nYRes = 3\n"));
        assert!(text.contains("XYUnits = m\n") && text.contains("ZUnits = m\n"));

        let field = read_gsf(&path).unwrap();
        assert_eq!((field.xres, field.yres), (4, 3));
        assert!((field.xreal - 4.0 * 0.05582e-6).abs() < 1e-18);
        assert!((field.yreal - 3.0 * 0.05582e-6).abs() < 1e-18);
        // 2 µm is stored as 2e-6 m.
        assert!((f64::from(field.data[1]) - 2e-6).abs() < 1e-12);
        let back = field.height_um().unwrap();
        for (a, b) in img.data().iter().zip(back.data()) {
            assert!(
                (a - b).abs() < 1e-5 || (a.is_nan() && b.is_nan()),
                "{a} vs {b}"
            );
        }
    }

    #[test]
    fn reader_rejects_wrong_size_and_padding() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("h.gsf");
        write_gsf(&path, &Image::zeros(2, 2), 1.0, "x").unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        bytes.push(0);
        std::fs::write(&path, &bytes).unwrap();
        assert!(read_gsf(&path).unwrap_err().to_string().contains("size"));
        // A 44-byte header needs 4 NUL bytes; here only 2 come before the sample.
        let mut short = b"Gwyddion Simple Field 1.0\nXRes = 1\nYRes = 1\n".to_vec();
        assert_eq!(short.len(), 44);
        short.extend([0, 0]);
        short.extend(f32::from_bits(0x3F80_0001).to_le_bytes());
        short.extend([0, 0]);
        assert!(parse_gsf(&short).unwrap_err().contains("padding"));
    }

    #[test]
    fn invalid_inputs_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("h.gsf");
        assert!(write_gsf(&p, &Image::zeros(2, 2), 0.0, "t").is_err());
        assert!(write_gsf(&p, &Image::zeros(2, 2), 1.0, "a\nb").is_err());
        assert!(!p.exists());
    }
}
