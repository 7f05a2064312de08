//! Micrograph files: loading TIFF, PNG, JPEG or BMP into an [`Image`] in `[0, 1]` with its
//! SEM metadata, and writing `left.tif`/`right.tif` with tilt and pixel size embedded.
//!
//! Accepted: grey TIFF of 8 or 16 bits (any compression the `tiff` crate decodes), 8-bit
//! palette TIFF with a grey palette (Zeiss SmartSEM writes these), grey PNG of 8 or 16
//! bits, baseline and progressive JPEG, BMP, and RGB(A) files whose channels are all equal
//! (grey saved as colour; alpha must be opaque; a JPEG's may differ by its rounding, 2 of
//! 255). The format is recognised by content, not by extension. Only the first image of a
//! multi-page TIFF is read. An info bar the vendor stored below the scan (FEI/Thermo,
//! TESCAN; see [`super::metadata`]) is cut off, and a JEOL sidecar's field width gives the
//! pixel size of what remains. Metadata come from the TIFF tags (a JPEG's Exif block holds
//! the same structure) and from a Hitachi or JEOL `.txt` sidecar, whatever the format.
//!
//! A file is untrusted: its size is checked before it is read ([`MAX_FILE_BYTES`]) and its
//! dimensions before it is decoded ([`MAX_PIXELS`]); a cut file is named as such.

use std::io::Cursor;
use std::path::{Path, PathBuf};

use tiff::decoder::{Decoder, DecodingResult, Limits};
use tiff::encoder::TiffEncoder;
use tiff::encoder::colortype::{Gray8, Gray16};
use tiff::tags::{ResolutionUnit, Tag, Type};

use super::file_raster::{Raster, bmp_truncation, jpeg_exif, jpeg_truncation};
use super::file_tiff::{RawTiff, is_tiff, patch_u16, truncation};
use super::metadata::{
    SemMetadata, TAG_FEI, TAG_FEI_OLD, TAG_TESCAN, TAG_ZEISS, parse_fei, parse_sdsem_description,
    parse_sidecar, parse_tescan, parse_zeiss, zeiss_block,
};
use crate::export::ExportError;
use crate::export::atomic::write_atomic;
use crate::vision::Image;

/// Why a micrograph could not be loaded or written.
#[derive(Debug, thiserror::Error)]
pub enum ImageFileError {
    #[error("cannot read {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path} is not an image: expected a TIFF, PNG, JPEG or BMP file")]
    NotAnImage { path: PathBuf },
    #[error("{path} is {what}, more than sdsem reads ({limit}) — bin or crop the micrograph")]
    TooLarge {
        path: PathBuf,
        what: String,
        limit: String,
    },
    #[error("{path} is not a regular file")]
    NotAFile { path: PathBuf },
    #[error("{path}: unsupported: {what} — expected a grey 8- or 16-bit micrograph")]
    Unsupported { path: PathBuf, what: String },
    #[error("{path}: cannot decode the image: {cause}")]
    Decode { path: PathBuf, cause: String },
    #[error("{path} is incomplete: {how} — an interrupted copy or transfer; copy it again")]
    Truncated { path: PathBuf, how: String },
    #[error(transparent)]
    Write(#[from] ExportError),
}

/// Largest micrograph file read, bytes: the size is checked before anything is read.
pub const MAX_FILE_BYTES: u64 = 2 << 30;

/// Most pixels of a micrograph decoded (16384 × 16384): checked from the header before the
/// pixels are decoded, so a hostile header cannot make the reader allocate gigabytes.
pub const MAX_PIXELS: u64 = 1 << 28;

/// Largest side of a micrograph decoded, pixels.
pub const MAX_SIDE: u32 = 65_535;

/// What to do with a colour image whose channels differ.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Colour {
    /// A micrograph is grey: refuse it.
    Refuse,
    /// An arbitrary image (`sdsem flow`): its Rec. 601 luma.
    Luma,
}

/// A micrograph loaded from a file.
#[derive(Debug, Clone, PartialEq)]
pub struct Micrograph {
    pub path: PathBuf,
    /// Intensities in `[0, 1]`.
    pub image: Image,
    /// Bits per sample of the file (8 or 16).
    pub bits_per_sample: u8,
    /// Pixel size, tilt and raw vendor metadata (TIFF tags and sidecar).
    pub metadata: SemMetadata,
    /// Width and height as stored, before an info bar was cut off.
    pub stored_size: (usize, usize),
}

/// Loads a micrograph and its SEM metadata (with a Hitachi or JEOL `.txt` sidecar of the
/// same stem, when there is one).
///
/// # Errors
/// [`ImageFileError`] naming the file and the cause.
pub fn load_micrograph(path: impl AsRef<Path>) -> Result<Micrograph, ImageFileError> {
    let path = path.as_ref();
    let bytes = read_bounded(path)?;
    let sidecar = sidecar_beside(path);
    micrograph_from_bytes(path, bytes, sidecar)
}

/// The bytes of a regular file of at most [`MAX_FILE_BYTES`] (checked before reading, and
/// while reading, should the file grow).
fn read_bounded(path: &Path) -> Result<Vec<u8>, ImageFileError> {
    use std::io::Read;
    let read_error = |source| ImageFileError::Read {
        path: path.to_path_buf(),
        source,
    };
    // Checked before opening: opening a FIFO would block until a writer comes.
    if !std::fs::metadata(path).map_err(read_error)?.is_file() {
        return Err(ImageFileError::NotAFile {
            path: path.to_path_buf(),
        });
    }
    let file = std::fs::File::open(path).map_err(read_error)?;
    let meta = file.metadata().map_err(read_error)?;
    let too_large = |len: u64| ImageFileError::TooLarge {
        path: path.to_path_buf(),
        what: format!("{len} bytes"),
        limit: format!("{} MiB", MAX_FILE_BYTES >> 20),
    };
    if meta.len() > MAX_FILE_BYTES {
        return Err(too_large(meta.len()));
    }
    let mut bytes = Vec::with_capacity(usize::try_from(meta.len()).unwrap_or(0));
    file.take(MAX_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(read_error)?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(too_large(bytes.len() as u64));
    }
    Ok(bytes)
}

/// Whether a micrograph file is whole (a file the SEM may still be writing): a TIFF's
/// directories and strips all inside it, a JPEG's data up to its end marker, a BMP as long as
/// its header says. `Err` says what is missing.
pub(crate) fn check_whole(bytes: &[u8]) -> Result<(), String> {
    match Raster::sniff(bytes) {
        Some(Raster::Jpeg) => jpeg_truncation(bytes).map_or(Ok(()), Err),
        Some(Raster::Bmp) => bmp_truncation(bytes).map_or(Ok(()), Err),
        Some(Raster::Png) => bytes
            .ends_with(b"IEND\xAE\x42\x60\x82")
            .then_some(())
            .ok_or_else(|| "no PNG end chunk yet".to_owned()),
        None => super::file_tiff::check_whole(bytes),
    }
}

/// Refuses dimensions beyond [`MAX_SIDE`] or [`MAX_PIXELS`], before decoding.
fn check_dimensions(path: &Path, w: u32, h: u32) -> Result<(), ImageFileError> {
    if w == 0 || h == 0 {
        return Err(decode_error(path, format!("the image is {w} × {h} pixels")));
    }
    if w > MAX_SIDE || h > MAX_SIDE || u64::from(w) * u64::from(h) > MAX_PIXELS {
        return Err(ImageFileError::TooLarge {
            path: path.to_path_buf(),
            what: format!("{w} × {h} pixels"),
            limit: format!("{MAX_PIXELS} pixels, {MAX_SIDE} a side"),
        });
    }
    Ok(())
}

/// A micrograph from the bytes of its file (named `path` in errors) and, if any, the
/// metadata of its sidecar ([`parse_sidecar`]).
///
/// # Errors
/// [`ImageFileError`] naming the file and the cause.
pub fn micrograph_from_bytes(
    path: &Path,
    bytes: Vec<u8>,
    sidecar: Option<SemMetadata>,
) -> Result<Micrograph, ImageFileError> {
    decode_file(path, bytes, sidecar, Colour::Refuse)
}

fn decode_file(
    path: &Path,
    bytes: Vec<u8>,
    sidecar: Option<SemMetadata>,
    colour: Colour,
) -> Result<Micrograph, ImageFileError> {
    let mut metadata = embedded_metadata(&bytes);
    let (image, bits_per_sample) = if is_tiff(&bytes) {
        decode_tiff(path, bytes, colour)?
    } else if let Some(format) = Raster::sniff(&bytes) {
        decode_raster(path, &bytes, format, colour)?
    } else {
        return Err(ImageFileError::NotAnImage {
            path: path.to_path_buf(),
        });
    };
    if let Some(sidecar) = sidecar {
        metadata.merge(sidecar);
    }
    let stored_size = image.dimensions();
    let image = match metadata.kept_size(stored_size.0, stored_size.1) {
        Some((w, h)) => crop(&image, w, h),
        None => image,
    };
    if metadata.pixel_size_um.is_none()
        && let Some(field) = metadata.field_width_um
    {
        // JEOL: the field of view spans the scanned width.
        #[allow(clippy::cast_precision_loss)]
        let pixel = field / image.width() as f64;
        metadata.pixel_size_um = Some(pixel);
    }
    Ok(Micrograph {
        path: path.to_path_buf(),
        image,
        bits_per_sample,
        metadata,
        stored_size,
    })
}

/// The top-left `width` × `height` of `image` (both within it).
fn crop(image: &Image, width: usize, height: usize) -> Image {
    Image::from_fn(width, height, |x, y| image.get(x, y))
}

/// Reads only the SEM metadata of a micrograph file (TIFF tags and Hitachi or JEOL sidecar).
///
/// # Errors
/// [`ImageFileError::Read`] when the file cannot be read.
pub fn read_sem_metadata(path: impl AsRef<Path>) -> Result<SemMetadata, ImageFileError> {
    let path = path.as_ref();
    let bytes = read_bounded(path)?;
    let mut metadata = embedded_metadata(&bytes);
    if let Some(sidecar) = sidecar_beside(path) {
        metadata.merge(sidecar);
    }
    Ok(metadata)
}

/// Metadata inside the file: a TIFF's tags, or those of a JPEG's Exif block.
fn embedded_metadata(bytes: &[u8]) -> SemMetadata {
    let tiff = if is_tiff(bytes) {
        Some(bytes)
    } else if Raster::sniff(bytes) == Some(Raster::Jpeg) {
        jpeg_exif(bytes)
    } else {
        None
    };
    tiff.and_then(RawTiff::parse)
        .map(|t| tiff_metadata(&t))
        .unwrap_or_default()
}

/// Metadata from the TIFF tags, in order of precedence: sdsem's description, Zeiss,
/// FEI/Thermo, Tescan.
fn tiff_metadata(tiff: &RawTiff<'_>) -> SemMetadata {
    let mut found = SemMetadata::default();
    let sources = [
        tiff.value_bytes(270).and_then(parse_sdsem_description),
        tiff.value_bytes(TAG_ZEISS).map(parse_zeiss),
        tiff.value_bytes(TAG_FEI).map(parse_fei),
        tiff.value_bytes(TAG_FEI_OLD).map(parse_fei),
        tiff.value_bytes(TAG_TESCAN)
            .map(|b| parse_tescan(b, tiff.big_endian)),
    ];
    for meta in sources.into_iter().flatten() {
        found.merge(meta);
    }
    found
}

/// The Hitachi or JEOL `.txt` header beside `path` (same stem), if there is one.
fn sidecar_beside(path: &Path) -> Option<SemMetadata> {
    ["txt", "TXT"].iter().find_map(|ext| {
        let candidate = path.with_extension(ext);
        if candidate == path {
            return None;
        }
        std::fs::read(&candidate)
            .ok()
            .and_then(|b| parse_sidecar(&b))
    })
}

fn unsupported(path: &Path, what: impl Into<String>) -> ImageFileError {
    ImageFileError::Unsupported {
        path: path.to_path_buf(),
        what: what.into(),
    }
}

fn decode_error(path: &Path, cause: impl ToString) -> ImageFileError {
    ImageFileError::Decode {
        path: path.to_path_buf(),
        cause: cause.to_string(),
    }
}

/// Grey levels of a palette (ColorMap: all red, then all green, then all blue, 16 bits),
/// or `None` when an entry is coloured.
fn grey_palette(colormap: &[u64], entries: usize) -> Option<Vec<f32>> {
    if colormap.len() != 3 * entries {
        return None;
    }
    (0..entries)
        .map(|i| {
            let (r, g, b) = (
                colormap[i],
                colormap[entries + i],
                colormap[2 * entries + i],
            );
            (r == g && g == b).then_some(r as f32 / 65535.0)
        })
        .collect()
}

fn decode_tiff(
    path: &Path,
    mut bytes: Vec<u8>,
    colour: Colour,
) -> Result<(Image, u8), ImageFileError> {
    if let Some(how) = truncation(&bytes) {
        return Err(ImageFileError::Truncated {
            path: path.to_path_buf(),
            how,
        });
    }
    let raw = RawTiff::parse(&bytes).ok_or_else(|| decode_error(path, "malformed TIFF header"))?;
    let photometric = raw.photometric_field();
    let palette = match photometric {
        Some((at, 3)) => {
            let bits = raw
                .unsigned_values(258)
                .and_then(|b| b.first().copied())
                .unwrap_or(1);
            if bits != 8 {
                return Err(unsupported(path, format!("{bits}-bit palette")));
            }
            let colormap = raw
                .unsigned_values(320)
                .ok_or_else(|| decode_error(path, "palette image without a ColorMap"))?;
            let grey = grey_palette(&colormap, 256)
                .ok_or_else(|| unsupported(path, "colour palette (false-colour image)"))?;
            let big_endian = raw.big_endian;
            // Relabel as BlackIsZero in our copy: the decoded samples are the indices.
            patch_u16(&mut bytes, at, 1, big_endian);
            Some(grey)
        }
        _ => None,
    };
    let mut decoder = Decoder::new(Cursor::new(bytes))
        .map_err(|e| decode_error(path, e))?
        .with_limits(Limits::unlimited());
    let (w, h) = decoder.dimensions().map_err(|e| decode_error(path, e))?;
    check_dimensions(path, w, h)?;
    let (w, h) = (w as usize, h as usize);
    let colortype = decoder.colortype().map_err(|e| match e {
        tiff::TiffError::UnsupportedError(u) => unsupported(path, u.to_string()),
        other => decode_error(path, other),
    })?;
    let (channels, bits): (usize, u8) = match colortype {
        tiff::ColorType::Gray(b) => (1, b),
        tiff::ColorType::GrayA(b) => (2, b),
        tiff::ColorType::RGB(b) => (3, b),
        tiff::ColorType::RGBA(b) => (4, b),
        other => return Err(unsupported(path, format!("colour type {other:?}"))),
    };
    if bits != 8 && bits != 16 && bits != 32 && bits != 64 {
        return Err(unsupported(path, format!("{bits}-bit samples")));
    }
    let result = decoder.read_image().map_err(|e| match e {
        tiff::TiffError::UnsupportedError(u) => unsupported(path, u.to_string()),
        other => decode_error(path, other),
    })?;
    let (samples, bits): (Vec<f32>, u8) = match result {
        DecodingResult::U8(v) => {
            if let Some(grey) = &palette {
                let image =
                    Image::from_vec(w, h, v.iter().map(|&i| grey[usize::from(i)]).collect())
                        .map_err(|e| decode_error(path, e))?;
                return Ok((image, 8));
            }
            (v.iter().map(|&s| f32::from(s) / 255.0).collect(), 8)
        }
        DecodingResult::U16(v) => (v.iter().map(|&s| f32::from(s) / 65535.0).collect(), 16),
        DecodingResult::F32(_) | DecodingResult::F64(_) => {
            return Err(unsupported(path, "floating-point samples (a height map?)"));
        }
        _ => {
            return Err(unsupported(
                path,
                "sample format other than unsigned 8/16-bit",
            ));
        }
    };
    let image = grey_from_channels(path, w, h, &samples, channels, colour, 0.0)?;
    Ok((image, bits))
}

/// One grey image from interleaved samples: grey as is, grey+alpha and RGB(A) only when
/// the colour channels agree within `tolerance` (or, for [`Colour::Luma`], as their luma) and
/// alpha is opaque.
fn grey_from_channels(
    path: &Path,
    w: usize,
    h: usize,
    samples: &[f32],
    channels: usize,
    colour: Colour,
    tolerance: f32,
) -> Result<Image, ImageFileError> {
    if samples.len() != w * h * channels {
        return Err(decode_error(
            path,
            format!("{} samples for {w} × {h} × {channels}", samples.len()),
        ));
    }
    if channels == 1 {
        return Image::from_vec(w, h, samples.to_vec()).map_err(|e| decode_error(path, e));
    }
    let rgb = channels >= 3;
    let has_alpha = channels == 2 || channels == 4;
    let mut grey = Vec::with_capacity(w * h);
    for (i, px) in samples.chunks_exact(channels).enumerate() {
        if has_alpha && px[channels - 1] < 1.0 {
            return Err(unsupported(path, "transparent pixels (alpha channel)"));
        }
        if !rgb || (px[0] == px[1] && px[1] == px[2]) {
            grey.push(px[0]);
            continue;
        }
        let (r, g, b) = (px[0], px[1], px[2]);
        if colour == Colour::Luma {
            grey.push(0.299 * r + 0.587 * g + 0.114 * b);
        } else if (r - g).abs() <= tolerance
            && (g - b).abs() <= tolerance
            && (r - b).abs() <= tolerance
        {
            grey.push((r + g + b) / 3.0);
        } else {
            return Err(unsupported(
                path,
                format!(
                    "colour: red, green and blue differ at pixel ({}, {}); save the micrograph as grey",
                    i % w,
                    i / w
                ),
            ));
        }
    }
    Image::from_vec(w, h, grey).map_err(|e| decode_error(path, e))
}

/// A PNG, JPEG or BMP: truncation and dimensions checked, then decoded within limits that
/// match the checked size.
fn decode_raster(
    path: &Path,
    bytes: &[u8],
    format: Raster,
    colour: Colour,
) -> Result<(Image, u8), ImageFileError> {
    use image::DynamicImage as D;
    if format == Raster::Jpeg
        && let Some(how) = jpeg_truncation(bytes)
    {
        return Err(ImageFileError::Truncated {
            path: path.to_path_buf(),
            how,
        });
    }
    let failed = |e: image::ImageError| match (format, bmp_truncation(bytes)) {
        (Raster::Bmp, Some(how)) => ImageFileError::Truncated {
            path: path.to_path_buf(),
            how,
        },
        _ => decode_error(path, format!("{} decoder: {e}", format.name())),
    };
    let reader = || image::ImageReader::with_format(Cursor::new(bytes), format.image_format());
    let (w, h) = reader().into_dimensions().map_err(failed)?;
    check_dimensions(path, w, h)?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(w);
    limits.max_image_height = Some(h);
    // The largest layout a decoder produces (16-bit RGBA) and its working buffers.
    limits.max_alloc = Some(u64::from(w) * u64::from(h) * 16 + (64 << 20));
    let mut reader = reader();
    reader.limits(limits);
    let decoded = reader.decode().map_err(failed)?;
    let (w, h) = (decoded.width() as usize, decoded.height() as usize);
    let to8 = |v: &[u8]| v.iter().map(|&s| f32::from(s) / 255.0).collect::<Vec<_>>();
    let to16 = |v: &[u16]| {
        v.iter()
            .map(|&s| f32::from(s) / 65535.0)
            .collect::<Vec<_>>()
    };
    let (samples, channels, bits) = match &decoded {
        D::ImageLuma8(b) => (to8(b.as_raw()), 1, 8),
        D::ImageLumaA8(b) => (to8(b.as_raw()), 2, 8),
        D::ImageRgb8(b) => (to8(b.as_raw()), 3, 8),
        D::ImageRgba8(b) => (to8(b.as_raw()), 4, 8),
        D::ImageLuma16(b) => (to16(b.as_raw()), 1, 16),
        D::ImageLumaA16(b) => (to16(b.as_raw()), 2, 16),
        D::ImageRgb16(b) => (to16(b.as_raw()), 3, 16),
        D::ImageRgba16(b) => (to16(b.as_raw()), 4, 16),
        other => {
            return Err(unsupported(
                path,
                format!("{} colour type {:?}", format.name(), other.color()),
            ));
        }
    };
    // A JPEG of a grey image saved as colour can round its channels apart.
    let tolerance = if format == Raster::Jpeg {
        2.0 / 255.0 + 1e-6
    } else {
        0.0
    };
    Ok((
        grey_from_channels(path, w, h, &samples, channels, colour, tolerance)?,
        bits,
    ))
}

/// Loads only the pixels of a micrograph, in `[0, 1]`.
///
/// # Errors
/// As [`load_micrograph`].
pub fn load_image(path: impl AsRef<Path>) -> Result<Image, ImageFileError> {
    load_micrograph(path).map(|m| m.image)
}

/// Loads the pixels of any image in a format [`load_micrograph`] reads, in `[0, 1]`, a colour
/// one as its Rec. 601 luma (`sdsem flow` compares arbitrary images, e.g. Middlebury's).
///
/// # Errors
/// As [`load_micrograph`], except for colour.
pub fn load_luma(path: impl AsRef<Path>) -> Result<Image, ImageFileError> {
    let path = path.as_ref();
    let bytes = read_bounded(path)?;
    decode_file(path, bytes, None, Colour::Luma).map(|m| m.image)
}

/// Sample depth of a written micrograph.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleDepth {
    Bits8,
    Bits16,
}

/// What to embed in a written micrograph.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MicrographTags {
    /// Pixel size, µm.
    pub pixel_size_um: Option<f64>,
    /// Stage tilt, degrees.
    pub tilt_deg: Option<f64>,
    /// Further JSON fields for the ImageDescription (e.g. role, run id, stage position).
    pub extra: serde_json::Map<String, serde_json::Value>,
}

/// The ImageDescription JSON: `{"sdsem":"micrograph","pixel_size_um":…,"tilt_deg":…,…}`.
fn description(tags: &MicrographTags) -> String {
    let mut map = tags.extra.clone();
    map.insert("sdsem".into(), "micrograph".into());
    map.insert(
        "schema_version".into(),
        crate::export::height_tiff::DESCRIPTION_SCHEMA_VERSION.into(),
    );
    if let Some(p) = tags.pixel_size_um {
        map.insert("pixel_size_um".into(), p.into());
    }
    if let Some(t) = tags.tilt_deg {
        map.insert("tilt_deg".into(), t.into());
    }
    let text = serde_json::Value::Object(map).to_string();
    // TIFF ASCII must be 7-bit: escape anything else the extra fields brought.
    text.chars()
        .map(|c| {
            if c.is_ascii() {
                c.to_string()
            } else {
                let mut units = [0u16; 2];
                c.encode_utf16(&mut units)
                    .iter()
                    .map(|u| format!("\\u{u:04x}"))
                    .collect()
            }
        })
        .collect()
}

/// Writes a micrograph in `[0, 1]` as a grey TIFF (8 or 16 bits, uncompressed) with the
/// tilt and pixel size in an ImageDescription JSON, in a Zeiss-style tag 34118 block (read
/// by Zeiss-aware tools and by [`load_micrograph`]) and in the resolution tags (pixels per
/// cm, for ImageJ/Fiji scale). Written atomically.
///
/// # Errors
/// [`ImageFileError::Write`] on I/O failure or an empty image.
pub fn write_micrograph_tiff(
    path: impl AsRef<Path>,
    image: &Image,
    tags: &MicrographTags,
    depth: SampleDepth,
) -> Result<(), ImageFileError> {
    let path = path.as_ref();
    if image.is_empty() {
        return Err(ExportError::Invalid {
            path: path.to_path_buf(),
            reason: "the micrograph is empty".to_owned(),
        }
        .into());
    }
    let description = description(tags);
    let zeiss = zeiss_block(tags.pixel_size_um, tags.tilt_deg);
    write_atomic(path, |w| {
        encode_micrograph(&mut *w, image, tags, depth, &description, &zeiss)
            .map_err(std::io::Error::other)
    })?;
    Ok(())
}

/// [`write_micrograph_tiff`]'s encoding into any seekable writer (e.g. a file created
/// exclusively in a run directory).
///
/// # Errors
/// The encoder's error.
pub fn encode_micrograph_tiff<W: std::io::Write + std::io::Seek>(
    out: W,
    image: &Image,
    tags: &MicrographTags,
    depth: SampleDepth,
) -> tiff::TiffResult<()> {
    if image.is_empty() {
        return Err(tiff::TiffError::FormatError(
            tiff::TiffFormatError::InvalidDimensions(0, 0),
        ));
    }
    let description = description(tags);
    let zeiss = zeiss_block(tags.pixel_size_um, tags.tilt_deg);
    encode_micrograph(out, image, tags, depth, &description, &zeiss)
}

fn encode_micrograph<W: std::io::Write + std::io::Seek>(
    out: W,
    image: &Image,
    tags: &MicrographTags,
    depth: SampleDepth,
    description: &str,
    zeiss: &[u8],
) -> tiff::TiffResult<()> {
    let (w, h) = crate::export::height_tiff::dims_u32(image)?;
    let mut encoder = TiffEncoder::new(out)?;
    macro_rules! write_with {
        ($color:ty, $data:expr) => {{
            let mut img = encoder.new_image::<$color>(w, h)?;
            let dir = img.encoder();
            dir.write_tag(Tag::ImageDescription, description)?;
            dir.write_tag(Tag::Software, concat!("sdsem ", env!("CARGO_PKG_VERSION")))?;
            // Latin-1 text as an ASCII entry, like SmartSEM writes it.
            let entry = dir.write_entry_bytes(Type::ASCII, zeiss)?;
            let mut extra = tiff::Directory::empty();
            extra.extend([(Tag::Unknown(TAG_ZEISS), entry)]);
            dir.extend_from(&extra);
            if let Some(p) = tags.pixel_size_um.filter(|p| p.is_finite() && *p > 0.0) {
                img.resolution(
                    ResolutionUnit::Centimeter,
                    crate::export::height_tiff::rational(1e4 / p),
                );
            }
            img.write_data($data)
        }};
    }
    match depth {
        SampleDepth::Bits8 => {
            let data = image.to_u8();
            write_with!(Gray8, &data)
        }
        SampleDepth::Bits16 => {
            let data = quantise_u16(image);
            write_with!(Gray16, &data)
        }
    }
}

fn quantise_u16(image: &Image) -> Vec<u16> {
    image
        .data()
        .iter()
        .map(|&v| {
            let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
            // In [0, 65535.5) after clamping.
            (v * 65535.0 + 0.5) as u16
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imaging::metadata::SemVendor;

    fn ramp(w: usize, h: usize) -> Image {
        Image::from_fn(w, h, |x, y| (x + y * w) as f32 / (w * h - 1) as f32)
    }

    #[test]
    fn written_micrograph_reads_back_with_tilt_and_pixel_size() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("left.tif");
        let img = ramp(7, 5);
        let mut tags = MicrographTags {
            pixel_size_um: Some(0.05582),
            tilt_deg: Some(-3.0),
            ..MicrographTags::default()
        };
        tags.extra.insert("role".into(), "left".into());
        write_micrograph_tiff(&path, &img, &tags, SampleDepth::Bits16).unwrap();

        let m = load_micrograph(&path).unwrap();
        assert_eq!(m.bits_per_sample, 16);
        assert_eq!(m.image.dimensions(), (7, 5));
        for (a, b) in img.data().iter().zip(m.image.data()) {
            assert!((a - b).abs() <= 0.5 / 65535.0 + 1e-7, "{a} vs {b}");
        }
        assert_eq!(m.metadata.vendor, Some(SemVendor::Sdsem));
        assert_eq!(m.metadata.pixel_size_um, Some(0.05582));
        assert_eq!(m.metadata.tilt_deg, Some(-3.0));
        assert_eq!(m.metadata.raw["role"], "left");

        // A Zeiss-aware reader that ignores our JSON finds the same values in tag 34118.
        let bytes = std::fs::read(&path).unwrap();
        let raw = RawTiff::parse(&bytes).unwrap();
        assert_eq!(
            raw.entry(TAG_ZEISS).unwrap().field_type,
            2,
            "ASCII like SmartSEM"
        );
        let zeiss = parse_zeiss(raw.value_bytes(TAG_ZEISS).unwrap());
        assert!((zeiss.pixel_size_um.unwrap() - 0.05582).abs() < 1e-9);
        assert_eq!(zeiss.tilt_deg, Some(-3.0));
        // Resolution tags: pixels per centimetre.
        assert_eq!(raw.unsigned_values(296), Some(vec![3]));
    }

    #[test]
    fn eight_bit_micrograph_round_trips_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("right.tif");
        let img = Image::from_u8(4, 2, &[0, 1, 2, 3, 128, 200, 254, 255]).unwrap();
        write_micrograph_tiff(&path, &img, &MicrographTags::default(), SampleDepth::Bits8).unwrap();
        let m = load_micrograph(&path).unwrap();
        assert_eq!(m.bits_per_sample, 8);
        assert_eq!(m.image.to_u8(), img.to_u8());
        assert!(m.metadata.pixel_size_um.is_none() && m.metadata.tilt_deg.is_none());
    }

    /// An 8-bit palette TIFF like SmartSEM's: grey 8-bit written, then relabelled as
    /// palette with an inverted grey ColorMap, so indices and grey levels differ.
    fn palette_tiff(path: &Path, indices: &[u8], w: u32, h: u32, colour: bool) {
        let mut colormap = vec![0u16; 768];
        for i in 0..256 {
            let g = (255 - i) as u16 * 257;
            colormap[i] = g;
            colormap[256 + i] = if colour && i == 7 { 0 } else { g };
            colormap[512 + i] = g;
        }
        let mut bytes = Cursor::new(Vec::new());
        {
            let mut enc = TiffEncoder::new(&mut bytes).unwrap();
            let mut img = enc.new_image::<Gray8>(w, h).unwrap();
            img.encoder()
                .write_tag(Tag::ColorMap, &colormap[..])
                .unwrap();
            img.write_data(indices).unwrap();
        }
        let mut bytes = bytes.into_inner();
        let (at, be) = {
            let raw = RawTiff::parse(&bytes).unwrap();
            (raw.photometric_field().unwrap().0, raw.big_endian)
        };
        patch_u16(&mut bytes, at, 3, be);
        std::fs::write(path, bytes).unwrap();
    }

    #[test]
    fn grey_palette_tiff_maps_indices_through_the_colormap() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pal.tif");
        palette_tiff(&path, &[0, 7, 255, 128], 2, 2, false);
        let m = load_micrograph(&path).unwrap();
        assert_eq!(m.image.to_u8(), vec![255, 248, 0, 127]);
    }

    #[test]
    fn colour_palette_is_refused_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("pal.tif");
        palette_tiff(&path, &[0, 7, 255, 128], 2, 2, true);
        let err = load_micrograph(&path).unwrap_err().to_string();
        assert!(
            err.contains("pal.tif") && err.contains("colour palette"),
            "{err}"
        );
    }

    #[test]
    fn png_grey_and_grey_rgb_load_but_colour_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let grey = dir.path().join("grey.png");
        image::GrayImage::from_raw(2, 1, vec![10, 250])
            .unwrap()
            .save(&grey)
            .unwrap();
        assert_eq!(load_image(&grey).unwrap().to_u8(), vec![10, 250]);

        let grey16 = dir.path().join("grey16.png");
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(2, 1, vec![0u16, 65535])
            .unwrap()
            .save(&grey16)
            .unwrap();
        let m = load_micrograph(&grey16).unwrap();
        assert_eq!(
            (m.bits_per_sample, m.image.data().to_vec()),
            (16, vec![0.0, 1.0])
        );

        let rgb = dir.path().join("rgb.png");
        image::RgbImage::from_raw(2, 1, vec![5, 5, 5, 9, 9, 9])
            .unwrap()
            .save(&rgb)
            .unwrap();
        assert_eq!(load_image(&rgb).unwrap().to_u8(), vec![5, 9]);

        let colour = dir.path().join("colour.png");
        image::RgbImage::from_raw(1, 1, vec![5, 6, 5])
            .unwrap()
            .save(&colour)
            .unwrap();
        let err = load_image(&colour).unwrap_err().to_string();
        assert!(
            err.contains("colour.png")
                && err.contains("unsupported: colour: red, green and blue differ at pixel (0, 0)"),
            "{err}"
        );
    }

    #[test]
    fn non_images_and_missing_files_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("notes.tif");
        std::fs::write(&path, b"hello").unwrap();
        let err = load_image(&path).unwrap_err().to_string();
        assert!(
            err.contains("notes.tif") && err.contains("not an image"),
            "{err}"
        );
        let err = load_image(dir.path().join("missing.tif"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("missing.tif"), "{err}");
    }

    #[test]
    fn float_tiff_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("height.tif");
        crate::export::height_tiff::write_height_tiff(&path, &Image::zeros(2, 2), None, None)
            .unwrap();
        let err = load_image(&path).unwrap_err().to_string();
        assert!(err.contains("floating-point"), "{err}");
    }

    #[test]
    fn hitachi_sidecar_supplies_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("img01.png");
        image::GrayImage::from_raw(1, 1, vec![1])
            .unwrap()
            .save(&path)
            .unwrap();
        std::fs::write(
            dir.path().join("img01.txt"),
            "[SemImageFile]\r\nPixelSize=99.2\r\nStagePositionT=10\r\n",
        )
        .unwrap();
        let m = load_micrograph(&path).unwrap();
        assert_eq!(m.metadata.vendor, Some(SemVendor::Hitachi));
        assert!((m.metadata.pixel_size_um.unwrap() - 0.0992).abs() < 1e-12);
        assert_eq!(m.metadata.tilt_deg, Some(10.0));
    }

    /// An 8-bit grey TIFF whose row y holds the value y, with `tag` = `text`.
    fn rows_tiff(path: &Path, w: u32, h: u32, tag: u16, text: &str) {
        let data: Vec<u8> = (0..h)
            .flat_map(|y| std::iter::repeat_n(y as u8, w as usize))
            .collect();
        let mut file = std::fs::File::create(path).unwrap();
        let mut enc = TiffEncoder::new(&mut file).unwrap();
        let mut img = enc.new_image::<Gray8>(w, h).unwrap();
        img.encoder().write_tag(Tag::Unknown(tag), text).unwrap();
        img.write_data(&data).unwrap();
    }

    #[test]
    fn a_data_bar_below_the_scan_is_cut_off() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("fei.tif");
        let ini = "[Image]\r\nResolutionX=8\r\nResolutionY=4\r\n[Scan]\r\nPixelWidth=2e-08\r\n\
[Stage]\r\nStageT=0.05235987756\r\n";
        rows_tiff(&path, 8, 6, TAG_FEI, ini);
        let m = load_micrograph(&path).unwrap();
        assert_eq!(m.stored_size, (8, 6));
        assert_eq!(m.image.dimensions(), (8, 4));
        assert_eq!(m.image.to_u8()[8 * 3], 3, "the scan's last row is kept");
        assert!((m.metadata.tilt_deg.unwrap() - 3.0).abs() < 1e-9);
        assert!((m.metadata.pixel_size_um.unwrap() - 0.02).abs() < 1e-12);
    }

    #[test]
    fn a_jeol_sidecar_gives_the_pixel_size_of_the_kept_width() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("jeol_001.tif");
        rows_tiff(&path, 10, 8, 305, "JEOL");
        std::fs::write(
            dir.path().join("jeol_001.txt"),
            "$CM_FORMAT JEOL/EO\n$CM_VERSION 1.0\n$CM_FIELD_OF_VIEW 1.000mm 0.600mm\n$CM_FULL_SIZE 10 6\n",
        )
        .unwrap();
        let m = load_micrograph(&path).unwrap();
        assert_eq!(m.metadata.vendor, Some(SemVendor::Jeol));
        assert_eq!(m.image.dimensions(), (10, 6));
        assert!((m.metadata.pixel_size_um.unwrap() - 100.0).abs() < 1e-9);
    }

    fn encoded(img: &image::DynamicImage, format: image::ImageFormat) -> Vec<u8> {
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, format).unwrap();
        out.into_inner()
    }

    fn textured_grey(w: u32, h: u32) -> image::GrayImage {
        image::GrayImage::from_fn(w, h, |x, y| {
            image::Luma([((x * 37 + y * 91 + x * y) % 256) as u8])
        })
    }

    #[test]
    fn jpeg_and_bmp_round_trip_with_sidecar_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let grey = textured_grey(40, 30);
        // BMP is lossless: the grey levels come back exactly.
        let bmp = dir.path().join("scan.bmp");
        std::fs::write(&bmp, encoded(&grey.clone().into(), image::ImageFormat::Bmp)).unwrap();
        let m = load_micrograph(&bmp).unwrap();
        assert_eq!((m.image.dimensions(), m.bits_per_sample), ((40, 30), 8));
        assert_eq!(m.image.to_u8(), grey.as_raw().clone());
        // JPEG, grey and grey saved as colour: within the compression's error.
        let rgb = image::DynamicImage::ImageLuma8(grey.clone()).into_rgb8();
        for (name, img) in [
            ("grey.jpg", image::DynamicImage::ImageLuma8(grey.clone())),
            ("rgb.jpeg", image::DynamicImage::ImageRgb8(rgb)),
        ] {
            let path = dir.path().join(name);
            std::fs::write(&path, encoded(&img, image::ImageFormat::Jpeg)).unwrap();
            std::fs::write(
                path.with_extension("txt"),
                "[SemImageFile]\r\nPixelSize=99.2\r\nStagePositionT=10\r\n",
            )
            .unwrap();
            let m = load_micrograph(&path).unwrap();
            assert_eq!(m.image.dimensions(), (40, 30), "{name}");
            let mean_error = m
                .image
                .to_u8()
                .iter()
                .zip(grey.as_raw())
                .map(|(a, b)| f64::from(a.abs_diff(*b)))
                .sum::<f64>()
                / 1200.0;
            assert!(
                mean_error < 12.0,
                "{name}: mean error {mean_error} grey levels"
            );
            assert_eq!(m.metadata.vendor, Some(SemVendor::Hitachi), "{name}");
            assert_eq!(m.metadata.tilt_deg, Some(10.0), "{name}");
            assert!((m.metadata.pixel_size_um.unwrap() - 0.0992).abs() < 1e-12);
            assert_eq!(read_sem_metadata(&path).unwrap().tilt_deg, Some(10.0));
        }
    }

    #[test]
    fn a_jpeg_exif_block_gives_tilt_and_pixel_size() {
        let dir = tempfile::tempdir().unwrap();
        // A TIFF directory with sdsem's description, as the Exif block of a JPEG.
        let tags = MicrographTags {
            pixel_size_um: Some(0.25),
            tilt_deg: Some(7.5),
            ..MicrographTags::default()
        };
        let mut tiff = Cursor::new(Vec::new());
        encode_micrograph_tiff(&mut tiff, &Image::zeros(1, 1), &tags, SampleDepth::Bits8).unwrap();
        let tiff = tiff.into_inner();
        let jpeg = encoded(&textured_grey(16, 16).into(), image::ImageFormat::Jpeg);
        let mut with_exif = jpeg[..2].to_vec();
        with_exif.extend([0xFF, 0xE1]);
        with_exif.extend(u16::try_from(2 + 6 + tiff.len()).unwrap().to_be_bytes());
        with_exif.extend(b"Exif\0\0");
        with_exif.extend(&tiff);
        with_exif.extend(&jpeg[2..]);
        let path = dir.path().join("exif.jpg");
        std::fs::write(&path, &with_exif).unwrap();
        let m = load_micrograph(&path).unwrap();
        assert_eq!(m.image.dimensions(), (16, 16));
        assert_eq!(m.metadata.tilt_deg, Some(7.5));
        assert_eq!(m.metadata.pixel_size_um, Some(0.25));
    }

    #[test]
    fn colour_jpeg_and_bmp_are_refused_as_micrographs_but_read_as_luma() {
        let dir = tempfile::tempdir().unwrap();
        let colour = image::RgbImage::from_fn(32, 24, |x, y| {
            image::Rgb([(x * 8) as u8, (y * 10) as u8, 200])
        });
        for (name, format) in [
            ("colour.jpg", image::ImageFormat::Jpeg),
            ("colour.bmp", image::ImageFormat::Bmp),
        ] {
            let path = dir.path().join(name);
            std::fs::write(&path, encoded(&colour.clone().into(), format)).unwrap();
            let err = load_micrograph(&path).unwrap_err().to_string();
            assert!(
                err.contains(name)
                    && err.contains("colour: red, green and blue differ")
                    && err.contains("save the micrograph as grey"),
                "{err}"
            );
            let luma = load_luma(&path).unwrap();
            assert_eq!(luma.dimensions(), (32, 24));
        }
    }

    #[test]
    fn cut_jpeg_and_bmp_files_are_named_incomplete() {
        let dir = tempfile::tempdir().unwrap();
        let grey = textured_grey(40, 30);
        for (name, format) in [
            ("cut.jpg", image::ImageFormat::Jpeg),
            ("cut.bmp", image::ImageFormat::Bmp),
        ] {
            let whole = encoded(&grey.clone().into(), format);
            assert_eq!(check_whole(&whole), Ok(()), "{name}");
            for end in [whole.len() / 3, whole.len() - 2] {
                assert!(check_whole(&whole[..end]).is_err(), "{name} cut at {end}");
                let path = dir.path().join(name);
                std::fs::write(&path, &whole[..end]).unwrap();
                let err = load_micrograph(&path).unwrap_err().to_string();
                assert!(
                    err.contains(name) && err.contains("is incomplete"),
                    "{name} cut at {end}: {err}"
                );
            }
        }
    }

    #[test]
    fn a_png_still_being_written_is_not_whole() {
        let png = encoded(&textured_grey(8, 8).into(), image::ImageFormat::Png);
        assert_eq!(check_whole(&png), Ok(()));
        assert!(check_whole(&png[..png.len() - 5]).is_err());
    }

    /// Hostile files: garbage, flipped bytes and headers claiming huge images end in an
    /// error naming the file, never in a panic or a giant allocation.
    #[test]
    fn hostile_jpeg_and_bmp_files_are_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("hostile.img");
        let load = |bytes: &[u8]| {
            std::fs::write(&path, bytes).unwrap();
            load_micrograph(&path).map(|_| ())
        };
        for start in [
            &[0xFF, 0xD8, 0xFF][..],
            b"BM\0\0\0\0\0\0\0\0\0\0\0\0\x28\0\0\0",
        ] {
            let mut garbage = start.to_vec();
            garbage.extend((0..4000u32).map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8));
            let err = load(&garbage).unwrap_err().to_string();
            assert!(err.contains("hostile.img"), "{err}");
        }
        let grey = textured_grey(24, 16);
        for format in [image::ImageFormat::Jpeg, image::ImageFormat::Bmp] {
            let whole = encoded(&grey.clone().into(), format);
            let mut seed = 0x9E37_79B9_7F4A_7C15_u64;
            for _ in 0..300 {
                let mut bytes = whole.clone();
                for _ in 0..4 {
                    seed ^= seed << 13;
                    seed ^= seed >> 7;
                    seed ^= seed << 17;
                    let at = (seed % bytes.len() as u64) as usize;
                    bytes[at] = (seed >> 32) as u8;
                }
                // Any outcome but a panic: a flipped pixel byte still decodes.
                let _ = load(&bytes);
            }
        }
        // A BMP header claiming 60000 × 60000 pixels: refused from the header.
        let mut huge = encoded(&grey.into(), image::ImageFormat::Bmp);
        huge[18..22].copy_from_slice(&60_000i32.to_le_bytes());
        huge[22..26].copy_from_slice(&60_000i32.to_le_bytes());
        let err = load(&huge).unwrap_err().to_string();
        assert!(
            err.contains("60000 × 60000 pixels") && err.contains("bin or crop"),
            "{err}"
        );
    }

    #[test]
    fn a_directory_or_fifo_is_not_read_as_a_micrograph() {
        let dir = tempfile::tempdir().unwrap();
        let err = load_micrograph(dir.path()).unwrap_err().to_string();
        assert!(err.contains("not a regular file"), "{err}");
        // A FIFO is refused without opening it (which would wait for a writer).
        let fifo = dir.path().join("pipe.tif");
        let c = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: mkfifo reads the NUL-terminated path and creates a node; nothing else.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let err = load_micrograph(&fifo).unwrap_err().to_string();
        assert!(
            err.contains("pipe.tif") && err.contains("not a regular file"),
            "{err}"
        );
    }

    fn data_dir() -> PathBuf {
        std::env::var_os("SDSEM_DATA").map_or_else(
            || Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data"),
            PathBuf::from,
        )
    }

    /// Real Zeiss palette TIFFs: `SDSEM_DATA=/work/shared/data cargo test -p sdsem --lib
    /// imaging::file -- --ignored`.
    #[test]
    #[ignore = "needs the Potamogeton data set"]
    fn potamogeton_zeiss_metadata_and_pixels() {
        let dir = data_dir().join("potamogeton");
        let m = load_micrograph(dir.join("pot_03.tif")).unwrap();
        assert_eq!(m.metadata.vendor, Some(SemVendor::Zeiss));
        assert_eq!(m.metadata.tilt_deg, Some(0.0));
        assert!((m.metadata.pixel_size_um.unwrap() - 0.05582).abs() < 1e-9);
        assert_eq!(m.image.dimensions(), (1536, 2048));
        assert_eq!(m.bits_per_sample, 8);
        let (lo, hi) = m.image.finite_range().unwrap();
        assert!(lo >= 0.0 && hi <= 1.0 && hi - lo > 0.5, "range {lo}..{hi}");
        for (file, tilt) in [
            ("pot_00.tif", -9.0),
            ("pot_04.tif", 3.0),
            ("pot_06.tif", 9.0),
        ] {
            let meta = read_sem_metadata(dir.join(file)).unwrap();
            assert_eq!(meta.tilt_deg, Some(tilt), "{file}");
        }
    }
}
