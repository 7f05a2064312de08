//! `height.tif`: the height map as a single-channel float32 TIFF, µm, NaN unknown.
//!
//! The ImageDescription holds a small JSON object (`{"sdsem":"height","schema_version":1,"unit":"um",...}`)
//! with the pixel size and what zero height means (`datum`, `zero`), and the standard
//! resolution tags carry the pixel size too (pixels per cm), so GIS tools, ImageJ/Fiji and
//! Gwyddion read a calibrated field.

use std::io::{BufReader, Seek, Write};
use std::path::Path;

use tiff::decoder::{Decoder, DecodingResult, Limits};
use tiff::encoder::{
    Rational, TiffEncoder,
    colortype::{Gray8, Gray32Float},
};
use tiff::tags::{ResolutionUnit, Tag};

use super::ExportError;
use super::atomic::Target;
use crate::vision::Image;
use crate::vision::datum::Datum;
use crate::vision::dense::Unknown;

/// A height map read back from `height.tif`.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightTiff {
    /// Heights, µm, NaN unknown.
    pub height_um: Image,
    /// Pixel size from the ImageDescription, µm.
    pub pixel_size_um: Option<f64>,
    /// The datum's name from the ImageDescription (`support`, `mean-plane`, `none`).
    pub datum: Option<String>,
}

/// `value` as a TIFF rational with the largest power-of-ten denominator that fits.
pub(crate) fn rational(value: f64) -> Rational {
    let mut d: u32 = 1;
    while d < 1_000_000_000 && (value * f64::from(d) * 10.0) < f64::from(u32::MAX) {
        d *= 10;
    }
    Rational {
        // Bounded by the loop condition; values beyond u32 saturate.
        n: (value * f64::from(d))
            .round()
            .clamp(0.0, f64::from(u32::MAX)) as u32,
        d,
    }
}

/// Version of the layout of sdsem's TIFF ImageDescription JSON (height, confidence and
/// micrograph files, key `schema_version`): raised when a key changes meaning or goes away.
pub const DESCRIPTION_SCHEMA_VERSION: u32 = 1;

fn description(kind: Field, pixel_size_um: Option<f64>, datum: Option<&Datum>) -> String {
    let mut json = match kind {
        Field::Height => serde_json::json!({
            "sdsem": "height",
            "schema_version": DESCRIPTION_SCHEMA_VERSION,
            "unit": "um",
            "unknown": "NaN",
            "grid": "left micrograph",
        }),
        Field::Confidence => serde_json::json!({
            "sdsem": "confidence",
            "schema_version": DESCRIPTION_SCHEMA_VERSION,
            "unit": "1",
            "unknown": "NaN",
            "interpolated": 0,
            "grid": "left micrograph",
            "reasons": "page 2",
        }),
        Field::Reasons => serde_json::json!({
            "sdsem": "unknown-reason",
            "schema_version": DESCRIPTION_SCHEMA_VERSION,
            "grid": "left micrograph",
            "codes": Unknown::ALL
                .iter()
                .map(|u| (u.code().to_string(), serde_json::Value::from(u.name())))
                .collect::<serde_json::Map<_, _>>(),
        }),
    };
    if let Some(p) = pixel_size_um {
        json["pixel_size_um"] = serde_json::json!(p);
    }
    if let Some(d) = datum {
        json["datum"] = d.kind.name().into();
        json["zero"] = d.zero.into();
    }
    json.to_string()
}

/// What a float32 map holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Field {
    Height,
    Confidence,
    /// The reason of every unknown height, a byte per pixel ([`Unknown::code`]).
    Reasons,
}

fn encode_field<W: Write + Seek>(
    out: W,
    height_um: &Image,
    pixel_size_um: Option<f64>,
    kind: Field,
    datum: Option<&Datum>,
    reasons: Option<&[Unknown]>,
) -> tiff::TiffResult<()> {
    let (w, h) = dims_u32(height_um)?;
    let mut encoder = TiffEncoder::new(out)?;
    if let Some(reasons) = reasons {
        encode_page(&mut encoder, height_um, pixel_size_um, kind, datum)?;
        let mut image = encoder.new_image::<Gray8>(w, h)?;
        image.encoder().write_tag(
            Tag::ImageDescription,
            description(Field::Reasons, pixel_size_um, None).as_str(),
        )?;
        if let Some(p) = pixel_size_um.filter(|p| p.is_finite() && *p > 0.0) {
            image.resolution(ResolutionUnit::Centimeter, rational(1e4 / p));
        }
        let codes: Vec<u8> = reasons.iter().map(|u| u.code()).collect();
        return image.write_data(&codes);
    }
    encode_page(&mut encoder, height_um, pixel_size_um, kind, datum)
}

/// One float32 page of `encoder`.
fn encode_page<W: Write + Seek>(
    encoder: &mut TiffEncoder<W>,
    height_um: &Image,
    pixel_size_um: Option<f64>,
    kind: Field,
    datum: Option<&Datum>,
) -> tiff::TiffResult<()> {
    let (w, h) = dims_u32(height_um)?;
    let mut image = encoder.new_image::<Gray32Float>(w, h)?;
    image.encoder().write_tag(
        Tag::ImageDescription,
        description(kind, pixel_size_um, datum).as_str(),
    )?;
    image
        .encoder()
        .write_tag(Tag::Software, concat!("sdsem ", env!("CARGO_PKG_VERSION")))?;
    if let Some(p) = pixel_size_um.filter(|p| p.is_finite() && *p > 0.0) {
        image.resolution(ResolutionUnit::Centimeter, rational(1e4 / p));
    }
    image.write_data(height_um.data())
}

pub(crate) fn dims_u32(image: &Image) -> tiff::TiffResult<(u32, u32)> {
    let w = u32::try_from(image.width()).map_err(|_| tiff::TiffError::IntSizeError)?;
    let h = u32::try_from(image.height()).map_err(|_| tiff::TiffError::IntSizeError)?;
    Ok((w, h))
}

/// Writes `height.tif` atomically: float32, µm, NaN unknown, zero at `datum` when given.
///
/// # Errors
/// [`ExportError::Invalid`] for an empty map, [`ExportError::Write`] on I/O failure.
pub fn write_height_tiff<'a>(
    target: impl Into<Target<'a>>,
    height_um: &Image,
    pixel_size_um: Option<f64>,
    datum: Option<&Datum>,
) -> Result<(), ExportError> {
    write_field(
        target.into(),
        height_um,
        pixel_size_um,
        (Field::Height, datum),
        None,
    )
}

/// Writes `confidence.tif` atomically: float32 on the height map's grid,
/// `(0, 1]` where the height is measured, 0 where it was interpolated between
/// measured neighbours, NaN where it is unknown; with `reasons` (one per pixel) a second
/// page, 8-bit, says why ([`Unknown::code`], named in its description).
///
/// # Errors
/// [`ExportError::Invalid`] for an empty map or reasons of another size, [`ExportError::Write`]
/// on I/O failure.
pub fn write_confidence_tiff<'a>(
    target: impl Into<Target<'a>>,
    confidence: &Image,
    pixel_size_um: Option<f64>,
    reasons: Option<&[Unknown]>,
) -> Result<(), ExportError> {
    let target = target.into();
    if reasons.is_some_and(|r| r.len() != confidence.len()) {
        return Err(ExportError::Invalid {
            path: target.path(),
            reason: "the unknown-reason map does not have one entry per pixel".to_owned(),
        });
    }
    write_field(
        target,
        confidence,
        pixel_size_um,
        (Field::Confidence, None),
        reasons,
    )
}

fn write_field(
    target: Target<'_>,
    map: &Image,
    pixel_size_um: Option<f64>,
    (kind, datum): (Field, Option<&Datum>),
    reasons: Option<&[Unknown]>,
) -> Result<(), ExportError> {
    if map.is_empty() {
        let what = match kind {
            Field::Height => "height",
            Field::Confidence | Field::Reasons => "confidence",
        };
        return Err(ExportError::Invalid {
            path: target.path(),
            reason: format!("the {what} map is empty"),
        });
    }
    target.write(|w| {
        encode_field(&mut *w, map, pixel_size_um, kind, datum, reasons)
            .map_err(std::io::Error::other)
    })
}

/// Reads a float32 height TIFF back (any single-channel float32 TIFF).
///
/// # Errors
/// [`ExportError::Read`] on I/O failure, [`ExportError::Format`] when it is not a
/// single-channel float32 TIFF.
pub fn read_height_tiff(path: &Path) -> Result<HeightTiff, ExportError> {
    let format = |reason: String| ExportError::Format {
        path: path.to_path_buf(),
        format: "float32 height TIFF",
        reason,
    };
    let file = std::fs::File::open(path).map_err(|source| ExportError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let mut decoder = Decoder::new(BufReader::new(file))
        .map_err(|e| format(e.to_string()))?
        .with_limits(Limits::unlimited());
    let (w, h) = decoder.dimensions().map_err(|e| format(e.to_string()))?;
    let description = decoder
        .get_tag_ascii_string(Tag::ImageDescription)
        .ok()
        .and_then(|d| serde_json::from_str::<serde_json::Value>(&d).ok());
    let pixel_size_um = description
        .as_ref()
        .and_then(|v| v["pixel_size_um"].as_f64());
    let datum = description
        .as_ref()
        .and_then(|v| v["datum"].as_str().map(str::to_owned));
    let data = match decoder.read_image().map_err(|e| format(e.to_string()))? {
        DecodingResult::F32(data) => data,
        _ => return Err(format("samples are not float32".to_owned())),
    };
    let height_um =
        Image::from_vec(w as usize, h as usize, data).map_err(|e| format(e.to_string()))?;
    Ok(HeightTiff {
        height_um,
        pixel_size_um,
        datum,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first page stays what readers of the confidence knew; the second says why a
    /// height is unknown, its codes named in the description.
    #[test]
    fn confidence_carries_the_reasons_on_a_second_page() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("confidence.tif");
        let conf = Image::from_vec(3, 2, vec![0.5, f32::NAN, 0.0, 1.0, f32::NAN, 0.25]).unwrap();
        let reasons = [
            Unknown::Measured,
            Unknown::NoTexture,
            Unknown::Interpolated,
            Unknown::Measured,
            Unknown::Ambiguous,
            Unknown::Measured,
        ];
        write_confidence_tiff(&path, &conf, Some(0.1), Some(&reasons)).unwrap();
        let back = read_height_tiff(&path).unwrap();
        assert!(back.height_um.get(1, 0).is_nan() && back.height_um.get(0, 0) == 0.5);
        let mut decoder = Decoder::new(std::fs::File::open(&path).unwrap()).unwrap();
        assert!(decoder.more_images());
        decoder.next_image().unwrap();
        let description: serde_json::Value =
            serde_json::from_str(&decoder.get_tag_ascii_string(Tag::ImageDescription).unwrap())
                .unwrap();
        assert_eq!(description["sdsem"], "unknown-reason");
        assert_eq!(description["codes"]["4"], "no-texture");
        let DecodingResult::U8(codes) = decoder.read_image().unwrap() else {
            panic!("8-bit reasons expected");
        };
        assert_eq!(codes, [0, 4, 1, 0, 5, 0]);
        assert!(write_confidence_tiff(&path, &conf, None, Some(&reasons[..2])).is_err());
    }

    #[test]
    fn height_round_trips_with_nan_and_pixel_size() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("height.tif");
        let mut img = Image::from_fn(5, 3, |x, y| x as f32 * 0.25 - y as f32 * 1.5);
        img.set(2, 1, f32::NAN);
        let mut datum_map = img.clone();
        let datum = crate::vision::datum::apply_datum(
            &mut datum_map,
            crate::vision::datum::DatumKind::None,
            0.05582,
        );
        write_height_tiff(&path, &img, Some(0.05582), Some(&datum)).unwrap();
        let back = read_height_tiff(&path).unwrap();
        assert_eq!(back.pixel_size_um, Some(0.05582));
        assert_eq!(back.datum.as_deref(), Some("none"));
        assert_eq!(back.height_um.dimensions(), (5, 3));
        for (a, b) in img.data().iter().zip(back.height_um.data()) {
            assert!(a == b || (a.is_nan() && b.is_nan()), "{a} vs {b}");
        }
        assert!(back.height_um.get(2, 1).is_nan());
        // The description names its layout's version, for readers written against it.
        let mut decoder = Decoder::new(std::fs::File::open(&path).unwrap()).unwrap();
        let description: serde_json::Value =
            serde_json::from_str(&decoder.get_tag_ascii_string(Tag::ImageDescription).unwrap())
                .unwrap();
        assert_eq!(description["sdsem"], "height");
        assert_eq!(description["schema_version"], DESCRIPTION_SCHEMA_VERSION);
    }

    #[test]
    fn rational_keeps_precision() {
        let r = rational(1e4 / 0.05582);
        let v = f64::from(r.n) / f64::from(r.d);
        assert!((v - 1e4 / 0.05582).abs() / v < 1e-6, "{v}");
    }

    #[test]
    fn empty_map_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let err = write_height_tiff(&dir.path().join("h.tif"), &Image::zeros(0, 0), None, None)
            .unwrap_err();
        assert!(err.to_string().contains("empty"));
    }
}
