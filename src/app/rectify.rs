//! `sdsem rectify LEFT RIGHT --out DIR [--tilt-axis DEG]`: the sparse stage alone (DESIGN §4).

use std::path::Path;

use anyhow::{Context, bail};

use crate::vision::Image;

/// Loads a grey micrograph as samples in `[0, 1]`: 8/16-bit grey or palette TIFF (the palette
/// turned into luminance), or anything the `image` crate reads (PNG …), converted to luma.
///
/// Interim loader until `imaging::file` (SEM TIFF with metadata) is merged.
///
/// # Errors
/// When the file cannot be read or decoded, naming the file.
pub fn load_gray(path: &Path) -> anyhow::Result<Image> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    if bytes.starts_with(b"II*\0") || bytes.starts_with(b"MM\0*") {
        return load_tiff(&bytes).with_context(|| format!("cannot decode TIFF {}", path.display()));
    }
    let img = image::load_from_memory(&bytes)
        .with_context(|| format!("{} is not an image this program reads (PNG or TIFF)", path.display()))?;
    let luma = img.to_luma16();
    let (w, h) = luma.dimensions();
    Ok(Image::from_u16(w as usize, h as usize, luma.as_raw())?)
}

fn load_tiff(bytes: &[u8]) -> anyhow::Result<Image> {
    use tiff::ColorType;
    use tiff::decoder::{Decoder, DecodingResult};
    use tiff::tags::Tag;
    // The `tiff` crate refuses palette images; read the indices as grey samples by
    // relabelling the photometric interpretation in a copy, then apply the colour map.
    let mut bytes = bytes.to_vec();
    let palette_file = relabel_palette_as_grey(&mut bytes);
    let mut dec = Decoder::new(std::io::Cursor::new(bytes))?;
    let (w, h) = dec.dimensions()?;
    let (w, h) = (w as usize, h as usize);
    let color = dec.colortype()?;
    let (color, palette) = match color {
        ColorType::Gray(8) if palette_file => (ColorType::Palette(8), Some(dec.get_tag_u16_vec(Tag::ColorMap)?)),
        c => (c, None),
    };
    let data = dec.read_image()?;
    match (color, data) {
        (ColorType::Gray(8), DecodingResult::U8(v)) => Ok(Image::from_u8(w, h, &v)?),
        (ColorType::Gray(16), DecodingResult::U16(v)) => Ok(Image::from_u16(w, h, &v)?),
        (ColorType::Palette(8), DecodingResult::U8(v)) => {
            let map = palette.unwrap_or_default();
            let n = map.len() / 3;
            if n == 0 {
                bail!("palette TIFF without a colour map");
            }
            // Luminance of each palette entry (Rec. 601), in [0, 1].
            let lum: Vec<f32> = (0..n)
                .map(|i| {
                    let (r, g, b) = (f32::from(map[i]), f32::from(map[n + i]), f32::from(map[2 * n + i]));
                    (0.299 * r + 0.587 * g + 0.114 * b) / 65535.0
                })
                .collect();
            let samples = v.iter().map(|&i| lum.get(usize::from(i)).copied().unwrap_or(0.0)).collect();
            Ok(Image::from_vec(w, h, samples)?)
        }
        (ColorType::RGB(8), DecodingResult::U8(v)) => {
            let samples = v
                .chunks_exact(3)
                .map(|p| (0.299 * f32::from(p[0]) + 0.587 * f32::from(p[1]) + 0.114 * f32::from(p[2])) / 255.0)
                .collect();
            Ok(Image::from_vec(w, h, samples)?)
        }
        (c, _) => bail!("unsupported TIFF colour type {c:?}: expected 8/16-bit grey, 8-bit palette or 8-bit RGB"),
    }
}

/// In the first IFD, changes PhotometricInterpretation 3 (RGB palette) into 1 (grey);
/// true when it did.
fn relabel_palette_as_grey(bytes: &mut [u8]) -> bool {
    let le = bytes.starts_with(b"II");
    let u16_at = |b: &[u8], i: usize| -> Option<u16> {
        let a: [u8; 2] = b.get(i..i + 2)?.try_into().ok()?;
        Some(if le { u16::from_le_bytes(a) } else { u16::from_be_bytes(a) })
    };
    let u32_at = |b: &[u8], i: usize| -> Option<u32> {
        let a: [u8; 4] = b.get(i..i + 4)?.try_into().ok()?;
        Some(if le { u32::from_le_bytes(a) } else { u32::from_be_bytes(a) })
    };
    let Some(ifd) = u32_at(bytes, 4) else { return false };
    let ifd = ifd as usize;
    let Some(n) = u16_at(bytes, ifd) else { return false };
    for k in 0..usize::from(n) {
        let e = ifd + 2 + 12 * k;
        // Tag 262, type SHORT, count 1, value 3 stored in the first two value bytes.
        if u16_at(bytes, e) == Some(262) && u16_at(bytes, e + 2) == Some(3) && u16_at(bytes, e + 8) == Some(3) {
            let one = if le { 1u16.to_le_bytes() } else { 1u16.to_be_bytes() };
            bytes[e + 8..e + 10].copy_from_slice(&one);
            return true;
        }
    }
    false
}
