//! A minimal reader of a TIFF's first directory (classic and BigTIFF): raw tag bytes for
//! the SEM metadata, and the in-memory patch that lets the `tiff` crate decode palette
//! images.
//!
//! Why not only the `tiff` crate: its ASCII values must be UTF-8 (Zeiss writes Latin-1),
//! and version 0.11 refuses `PhotometricInterpretation = RGBPalette` outright. Palette
//! images are decoded by relabelling them BlackIsZero in a copy of the file — the sample
//! values are then the palette indices — and mapping the indices through the ColorMap.

/// One directory entry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct RawEntry {
    pub tag: u16,
    pub field_type: u16,
    pub count: u64,
    /// Offset of the entry's value field in the file.
    value_field: usize,
}

/// The first image directory of a TIFF held in memory.
#[derive(Debug, Clone)]
pub(crate) struct RawTiff<'a> {
    bytes: &'a [u8],
    pub big_endian: bool,
    big_tiff: bool,
    pub entries: Vec<RawEntry>,
}

fn field_type_size(field_type: u16) -> Option<u64> {
    Some(match field_type {
        1 | 2 | 6 | 7 => 1,
        3 | 8 => 2,
        4 | 9 | 11 | 13 => 4,
        5 | 10 | 12 | 16 | 17 | 18 => 8,
        _ => return None,
    })
}

/// Whether `bytes` start like a TIFF (classic or BigTIFF, either byte order).
pub(crate) fn is_tiff(bytes: &[u8]) -> bool {
    bytes.starts_with(b"II*\0")
        || bytes.starts_with(b"MM\0*")
        || bytes.starts_with(b"II+\0")
        || bytes.starts_with(b"MM\0+")
}

impl<'a> RawTiff<'a> {
    /// Parses the header and the first directory; `None` when they are malformed.
    pub fn parse(bytes: &'a [u8]) -> Option<Self> {
        if !is_tiff(bytes) {
            return None;
        }
        let big_endian = bytes[0] == b'M';
        let big_tiff = bytes[2] == b'+' || bytes[3] == b'+';
        let mut tiff = Self {
            bytes,
            big_endian,
            big_tiff,
            entries: Vec::new(),
        };
        let ifd = if big_tiff {
            tiff.u64_at(8)?
        } else {
            u64::from(tiff.u32_at(4)?)
        };
        let ifd = usize::try_from(ifd).ok()?;
        let (count, first, entry_len, value_at) = if big_tiff {
            (tiff.u64_at(ifd)?, ifd + 8, 20, 12)
        } else {
            (u64::from(tiff.u16_at(ifd)?), ifd + 2, 12, 8)
        };
        for i in 0..usize::try_from(count).ok()? {
            let at = first.checked_add(i.checked_mul(entry_len)?)?;
            let tag = tiff.u16_at(at)?;
            let field_type = tiff.u16_at(at + 2)?;
            let count = if big_tiff {
                tiff.u64_at(at + 4)?
            } else {
                u64::from(tiff.u32_at(at + 4)?)
            };
            tiff.entries.push(RawEntry {
                tag,
                field_type,
                count,
                value_field: at + value_at,
            });
        }
        Some(tiff)
    }

    fn slice(&self, at: usize, len: usize) -> Option<&'a [u8]> {
        self.bytes.get(at..at.checked_add(len)?)
    }

    fn u16_at(&self, at: usize) -> Option<u16> {
        let b: [u8; 2] = self.slice(at, 2)?.try_into().ok()?;
        Some(if self.big_endian {
            u16::from_be_bytes(b)
        } else {
            u16::from_le_bytes(b)
        })
    }

    fn u32_at(&self, at: usize) -> Option<u32> {
        let b: [u8; 4] = self.slice(at, 4)?.try_into().ok()?;
        Some(if self.big_endian {
            u32::from_be_bytes(b)
        } else {
            u32::from_le_bytes(b)
        })
    }

    fn u64_at(&self, at: usize) -> Option<u64> {
        let b: [u8; 8] = self.slice(at, 8)?.try_into().ok()?;
        Some(if self.big_endian {
            u64::from_be_bytes(b)
        } else {
            u64::from_le_bytes(b)
        })
    }

    pub fn entry(&self, tag: u16) -> Option<RawEntry> {
        self.entries.iter().copied().find(|e| e.tag == tag)
    }

    /// The raw bytes of a tag's value (in the file's byte order).
    pub fn value_bytes(&self, tag: u16) -> Option<&'a [u8]> {
        let entry = self.entry(tag)?;
        let len =
            usize::try_from(field_type_size(entry.field_type)?.checked_mul(entry.count)?).ok()?;
        let inline = if self.big_tiff { 8 } else { 4 };
        if len <= inline {
            self.slice(entry.value_field, len)
        } else {
            let offset = if self.big_tiff {
                self.u64_at(entry.value_field)?
            } else {
                u64::from(self.u32_at(entry.value_field)?)
            };
            self.slice(usize::try_from(offset).ok()?, len)
        }
    }

    /// A SHORT or LONG tag as integers.
    pub fn unsigned_values(&self, tag: u16) -> Option<Vec<u64>> {
        let entry = self.entry(tag)?;
        let bytes = self.value_bytes(tag)?;
        let mut out = Vec::new();
        match entry.field_type {
            3 => {
                for b in bytes.chunks_exact(2) {
                    let b = [b[0], b[1]];
                    out.push(u64::from(if self.big_endian {
                        u16::from_be_bytes(b)
                    } else {
                        u16::from_le_bytes(b)
                    }));
                }
            }
            4 => {
                for b in bytes.chunks_exact(4) {
                    let b = [b[0], b[1], b[2], b[3]];
                    out.push(u64::from(if self.big_endian {
                        u32::from_be_bytes(b)
                    } else {
                        u32::from_le_bytes(b)
                    }));
                }
            }
            _ => return None,
        }
        Some(out)
    }

    /// Where the (inline, SHORT) PhotometricInterpretation value sits, to patch it.
    pub fn photometric_field(&self) -> Option<(usize, u16)> {
        let entry = self.entry(262)?;
        if entry.field_type != 3 || entry.count != 1 {
            return None;
        }
        Some((entry.value_field, self.u16_at(entry.value_field)?))
    }
}

/// How a TIFF held in `bytes` was cut short, if it was (an interrupted copy or transfer): its
/// header, its first directory or its image data (strips or tiles) runs past the last byte.
/// `None` when all of it is there, also for a TIFF malformed in another way.
pub(crate) fn truncation(bytes: &[u8]) -> Option<String> {
    let len = bytes.len() as u64;
    if !is_tiff(bytes) {
        return None;
    }
    let big_tiff = bytes[2] == b'+' || bytes[3] == b'+';
    let header = if big_tiff { 16 } else { 8 };
    if len < header {
        return Some(format!("it ends after {len} bytes, inside the TIFF header"));
    }
    let Some(tiff) = RawTiff::parse(bytes) else {
        let partial = RawTiff {
            bytes,
            big_endian: bytes[0] == b'M',
            big_tiff,
            entries: Vec::new(),
        };
        let ifd = if big_tiff {
            partial.u64_at(8)?
        } else {
            u64::from(partial.u32_at(4)?)
        };
        let (count_len, entry_len) = if big_tiff { (8, 20) } else { (2, 12) };
        let at = usize::try_from(ifd).ok()?;
        let entries = if big_tiff {
            partial.u64_at(at)
        } else {
            partial.u16_at(at).map(u64::from)
        };
        let whole = entries.is_some_and(|n| {
            n.checked_mul(entry_len)
                .and_then(|b| b.checked_add(ifd + count_len))
                .is_some_and(|end| end <= len)
        });
        return (!whole).then(|| {
            format!(
                "its image directory at byte {ifd} is not all there: the file ends at byte {len}"
            )
        });
    };
    let mut end = 0u64;
    for (offsets, counts) in [(273, 279), (324, 325)] {
        if let (Some(o), Some(c)) = (tiff.unsigned_values(offsets), tiff.unsigned_values(counts)) {
            for (o, c) in o.iter().zip(&c) {
                end = end.max(o.saturating_add(*c));
            }
        }
    }
    (end > len).then(|| format!("its image data runs to byte {end}, the file ends at byte {len}"))
}

/// Writes `value` as a SHORT at `at` in the file's byte order.
pub(crate) fn patch_u16(bytes: &mut [u8], at: usize, value: u16, big_endian: bool) {
    let b = if big_endian {
        value.to_be_bytes()
    } else {
        value.to_le_bytes()
    };
    if let Some(dst) = bytes.get_mut(at..at + 2) {
        dst.copy_from_slice(&b);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hand-made little-endian TIFF directory: ImageWidth 3, an ASCII tag inline and
    /// one at an offset.
    fn tiny_tiff(big_endian: bool) -> Vec<u8> {
        let w16 = |v: u16| {
            if big_endian {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        };
        let w32 = |v: u32| {
            if big_endian {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        };
        let mut b = Vec::new();
        b.extend(if big_endian { *b"MM\0*" } else { *b"II*\0" });
        b.extend(w32(8));
        b.extend(w16(3));
        // ImageWidth SHORT 1 = 3
        b.extend(w16(256));
        b.extend(w16(3));
        b.extend(w32(1));
        b.extend(w16(3));
        b.extend([0, 0]);
        // Photometric SHORT 1 = 3 (palette)
        b.extend(w16(262));
        b.extend(w16(3));
        b.extend(w32(1));
        b.extend(w16(3));
        b.extend([0, 0]);
        // 34118 ASCII 9 at offset 50
        b.extend(w16(34118));
        b.extend(w16(2));
        b.extend(w32(9));
        b.extend(w32(50));
        b.extend(w32(0));
        assert_eq!(b.len(), 50);
        b.extend(b"A = 1 \xb0\r\0");
        b
    }

    /// A file cut short is told apart from a whole one, at each place a cut can fall.
    #[test]
    fn truncation_names_what_is_missing() {
        let whole = tiny_tiff(false);
        assert_eq!(truncation(&whole), None);
        assert!(
            truncation(&whole[..6])
                .unwrap()
                .contains("inside the TIFF header")
        );
        let cut = truncation(&whole[..20]).unwrap();
        assert!(
            cut.contains("image directory at byte 8") && cut.contains("ends at byte 20"),
            "{cut}"
        );
        // Strip data promised beyond the end: StripOffsets 100, StripByteCounts 64.
        let mut strips = whole[..8].to_vec();
        strips.extend(2u16.to_le_bytes());
        for (tag, value) in [(273u16, 100u32), (279, 64)] {
            strips.extend(tag.to_le_bytes());
            strips.extend(4u16.to_le_bytes());
            strips.extend(1u32.to_le_bytes());
            strips.extend(value.to_le_bytes());
        }
        strips.extend(0u32.to_le_bytes());
        strips.resize(120, 0);
        let cut = truncation(&strips).unwrap();
        assert!(
            cut.contains("runs to byte 164, the file ends at byte 120"),
            "{cut}"
        );
        strips.resize(164, 0);
        assert_eq!(truncation(&strips), None);
        // Not a TIFF, or a TIFF malformed otherwise: not a truncation.
        assert_eq!(truncation(b"\x89PNG\r\n"), None);
    }

    #[test]
    fn reads_inline_and_offset_values_in_both_byte_orders() {
        for be in [false, true] {
            let bytes = tiny_tiff(be);
            let t = RawTiff::parse(&bytes).unwrap();
            assert_eq!(t.unsigned_values(256), Some(vec![3]));
            assert_eq!(t.value_bytes(34118), Some(&b"A = 1 \xb0\r\0"[..]));
            assert_eq!(t.photometric_field().map(|f| f.1), Some(3));
            assert!(t.value_bytes(270).is_none());
        }
    }

    #[test]
    fn patch_relabels_photometric() {
        let mut bytes = tiny_tiff(true);
        let (at, _) = RawTiff::parse(&bytes).unwrap().photometric_field().unwrap();
        patch_u16(&mut bytes, at, 1, true);
        assert_eq!(
            RawTiff::parse(&bytes)
                .unwrap()
                .photometric_field()
                .unwrap()
                .1,
            1
        );
    }

    #[test]
    fn garbage_is_not_a_tiff() {
        assert!(RawTiff::parse(b"II*\0\xff\xff\xff\x7f").is_none());
        assert!(RawTiff::parse(b"GIF89a").is_none());
    }
}
