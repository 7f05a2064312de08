//! PNG, JPEG and BMP micrographs: recognised by content, checked for truncation and size
//! before the `image` crate decodes them, and the metadata a JPEG carries in its Exif block.
//!
//! Public SEM stereo data sets are often JPEG; some SEM software exports BMP. Neither format
//! carries the vendors' TIFF tags, so their tilt and pixel size come from a sidecar
//! (see [`super::file`]) or from an Exif block that holds a TIFF directory.

/// A raster format read through the `image` crate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Raster {
    Png,
    Jpeg,
    Bmp,
}

impl Raster {
    /// The format `bytes` start with, if one of these.
    pub(crate) fn sniff(bytes: &[u8]) -> Option<Self> {
        if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
            Some(Self::Png)
        } else if bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
            Some(Self::Jpeg)
        } else if is_bmp(bytes) {
            Some(Self::Bmp)
        } else {
            None
        }
    }

    pub(crate) fn image_format(self) -> image::ImageFormat {
        match self {
            Self::Png => image::ImageFormat::Png,
            Self::Jpeg => image::ImageFormat::Jpeg,
            Self::Bmp => image::ImageFormat::Bmp,
        }
    }

    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::Png => "PNG",
            Self::Jpeg => "JPEG",
            Self::Bmp => "BMP",
        }
    }
}

/// `BM`, then a DIB header of one of the sizes Windows and OS/2 define: two letters alone
/// would take any text starting with "BM" for a bitmap.
fn is_bmp(bytes: &[u8]) -> bool {
    bytes.starts_with(b"BM")
        && bytes
            .get(14..18)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .is_some_and(|size| matches!(size, 12 | 16 | 40 | 52 | 56 | 64 | 108 | 124))
}

/// Why a JPEG is incomplete: its entropy-coded data does not reach the end-of-image marker.
/// Lenient decoders fill a cut JPEG with grey; a micrograph with a grey band would match as
/// a flat region, so a cut file is refused instead. `None` when complete (or not a JPEG whose
/// segments can be followed: the decoder then names the fault).
pub(crate) fn jpeg_truncation(bytes: &[u8]) -> Option<String> {
    let len = bytes.len();
    let mut at = 2;
    // Marker segments up to the first scan: each `FF xx` with a big-endian length.
    loop {
        let marker = segment_marker(bytes, &mut at)?;
        match marker {
            None => return Some(format!("it ends at byte {len}, before the image data")),
            Some(0xD9) => return None,
            Some(m) if (0xD0..=0xD7).contains(&m) || m == 0x01 => {}
            Some(m) => {
                let Some(seg) = bytes.get(at..at + 2) else {
                    return Some(format!("it ends at byte {len}, inside a header segment"));
                };
                let seg_len = usize::from(u16::from_be_bytes([seg[0], seg[1]]));
                if at + seg_len > len {
                    return Some(format!(
                        "a header segment runs to byte {}, but the file ends at byte {len}",
                        at + seg_len
                    ));
                }
                at += seg_len;
                if m == 0xDA {
                    // Entropy-coded data: FF 00 is a stuffed byte, FF D0–D7 a restart marker;
                    // any other marker ends the scan.
                    loop {
                        let Some(ff) = bytes
                            .get(at..)
                            .and_then(|b| b.iter().position(|&v| v == 0xFF))
                        else {
                            return Some(format!(
                                "its image data stops at byte {len} without the end-of-image marker"
                            ));
                        };
                        at += ff;
                        match bytes.get(at + 1) {
                            Some(0x00 | 0xD0..=0xD7 | 0xFF) => at += 1,
                            Some(_) => break,
                            None => {
                                return Some(format!(
                                    "its image data stops at byte {len} without the end-of-image marker"
                                ));
                            }
                        }
                    }
                }
            }
        }
    }
}

/// Reads the marker at `at` (after any `FF` fill bytes) and moves past it: `Some(None)` at
/// the end of the data, `None` when the bytes there are not a marker.
fn segment_marker(bytes: &[u8], at: &mut usize) -> Option<Option<u8>> {
    if *at >= bytes.len() {
        return Some(None);
    }
    if bytes[*at] != 0xFF {
        return None;
    }
    while bytes.get(*at) == Some(&0xFF) {
        *at += 1;
    }
    let marker = bytes.get(*at).copied();
    *at += 1;
    Some(marker)
}

/// Why a BMP that failed to decode is incomplete: the size its header states is beyond the
/// end of the file.
pub(crate) fn bmp_truncation(bytes: &[u8]) -> Option<String> {
    let stated = bytes
        .get(2..6)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))?;
    (u64::from(stated) > bytes.len() as u64).then(|| {
        format!(
            "its header states {stated} bytes, but the file ends at byte {}",
            bytes.len()
        )
    })
}

/// The TIFF structure of a JPEG's Exif block (APP1 `Exif\0\0`), where tools keep the
/// ImageDescription and, at times, the vendors' tags.
pub(crate) fn jpeg_exif(bytes: &[u8]) -> Option<&[u8]> {
    let mut at = 2;
    loop {
        let marker = segment_marker(bytes, &mut at)??;
        if marker == 0xDA || marker == 0xD9 {
            return None;
        }
        if (0xD0..=0xD7).contains(&marker) || marker == 0x01 {
            continue;
        }
        let seg = bytes.get(at..at + 2)?;
        let seg_len = usize::from(u16::from_be_bytes([seg[0], seg[1]]));
        let body = bytes.get(at + 2..at + seg_len)?;
        if marker == 0xE1
            && let Some(tiff) = body.strip_prefix(b"Exif\0\0")
        {
            return Some(tiff);
        }
        at += seg_len;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn jpeg(w: u32, h: u32) -> Vec<u8> {
        let img =
            image::GrayImage::from_fn(w, h, |x, y| image::Luma([((x * 7 + y * 13) % 251) as u8]));
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Jpeg).unwrap();
        out.into_inner()
    }

    #[test]
    fn formats_are_told_by_content() {
        assert_eq!(Raster::sniff(&jpeg(8, 8)), Some(Raster::Jpeg));
        assert_eq!(Raster::sniff(b"\x89PNG\r\n\x1a\n...."), Some(Raster::Png));
        let mut bmp = b"BM".to_vec();
        bmp.extend([0; 12]);
        bmp.extend(40u32.to_le_bytes());
        assert_eq!(Raster::sniff(&bmp), Some(Raster::Bmp));
        assert_eq!(Raster::sniff(b"BMW owners' manual, chapter 1"), None);
        assert_eq!(Raster::sniff(b"hello"), None);
    }

    #[test]
    fn a_cut_jpeg_is_found_at_every_length() {
        let whole = jpeg(24, 16);
        assert_eq!(jpeg_truncation(&whole), None);
        for end in 3..whole.len() {
            assert!(
                jpeg_truncation(&whole[..end]).is_some(),
                "cut at {end} of {} not found",
                whole.len()
            );
        }
    }

    #[test]
    fn a_bmp_shorter_than_its_header_says_is_cut() {
        let mut bmp = b"BM".to_vec();
        bmp.extend(1000u32.to_le_bytes());
        bmp.extend([0; 20]);
        assert!(bmp_truncation(&bmp).unwrap().contains("states 1000 bytes"));
        bmp[2..6].copy_from_slice(&26u32.to_le_bytes());
        assert_eq!(bmp_truncation(&bmp), None);
    }
}
