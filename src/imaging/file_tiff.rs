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
        let mut tiff = Self::header(bytes)?;
        let ifd = tiff.first_ifd()?;
        tiff.entries = tiff.directory(ifd)?.0;
        Some(tiff)
    }

    /// The header alone, without a directory; `None` when it is not a TIFF header.
    fn header(bytes: &'a [u8]) -> Option<Self> {
        if !is_tiff(bytes) {
            return None;
        }
        Some(Self {
            bytes,
            big_endian: bytes[0] == b'M',
            big_tiff: bytes[2] == b'+' || bytes[3] == b'+',
            entries: Vec::new(),
        })
    }

    /// Offset of the first directory, from the header.
    fn first_ifd(&self) -> Option<usize> {
        let ifd = if self.big_tiff {
            self.u64_at(8)?
        } else {
            u64::from(self.u32_at(4)?)
        };
        usize::try_from(ifd).ok()
    }

    /// The entries of the directory at `ifd` and the offset of the next one (0: none; `None`
    /// when that field lies beyond the file).
    fn directory(&self, ifd: usize) -> Option<(Vec<RawEntry>, Option<u64>)> {
        let (count, first, entry_len, value_at) = if self.big_tiff {
            (self.u64_at(ifd)?, ifd.checked_add(8)?, 20, 12)
        } else {
            (u64::from(self.u16_at(ifd)?), ifd.checked_add(2)?, 12, 8)
        };
        let count = usize::try_from(count).ok()?;
        let end = first.checked_add(count.checked_mul(entry_len)?)?;
        let next = if self.big_tiff {
            self.u64_at(end)
        } else {
            self.u32_at(end).map(u64::from)
        };
        let mut entries = Vec::with_capacity(count);
        for i in 0..count {
            let at = first + i * entry_len;
            let tag = self.u16_at(at)?;
            let field_type = self.u16_at(at + 2)?;
            let count = if self.big_tiff {
                self.u64_at(at + 4)?
            } else {
                u64::from(self.u32_at(at + 4)?)
            };
            entries.push(RawEntry {
                tag,
                field_type,
                count,
                value_field: at + value_at,
            });
        }
        Some((entries, next))
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

    /// A SHORT, LONG or LONG8 (BigTIFF offsets) tag as integers.
    pub fn unsigned_values_wide(&self, tag: u16) -> Option<Vec<u64>> {
        let entry = self.entry(tag)?;
        if entry.field_type != 16 {
            return self.unsigned_values(tag);
        }
        let bytes = self.value_bytes(tag)?;
        Some(
            bytes
                .chunks_exact(8)
                .map(|b| {
                    let b: [u8; 8] = b.try_into().unwrap_or([0; 8]);
                    if self.big_endian {
                        u64::from_be_bytes(b)
                    } else {
                        u64::from_le_bytes(b)
                    }
                })
                .collect(),
        )
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

/// Most directories followed in one file (a loop or a hostile chain ends here).
const MAX_DIRECTORIES: usize = 4096;

/// Checks that a TIFF is whole: a header, a chain of directories inside the file without a
/// loop, and in each directory every value and every strip or tile (offset + byte count)
/// inside the file (VENDORS §4.2: a file held still can still be cut short).
///
/// # Errors
/// What is missing, in a few words (for the timeout message and the log).
pub(crate) fn check_whole(bytes: &[u8]) -> Result<(), String> {
    let mut tiff = RawTiff::header(bytes).ok_or("no TIFF header")?;
    let mut ifd = tiff.first_ifd().ok_or("header cut short")?;
    if ifd == 0 {
        return Err("no image directory yet".into());
    }
    let mut seen = std::collections::HashSet::new();
    let mut index = 0usize;
    while ifd != 0 {
        if !seen.insert(ifd) || seen.len() > MAX_DIRECTORIES {
            return Err(format!("directory chain loops at offset {ifd}"));
        }
        let (entries, next) = tiff
            .directory(ifd)
            .and_then(|(e, next)| Some((e, next?)))
            .ok_or_else(|| format!("directory {index} at offset {ifd} ends beyond the file"))?;
        tiff.entries = entries;
        for e in &tiff.entries {
            let inline_ok = field_type_size(e.field_type)
                .and_then(|s| s.checked_mul(e.count))
                .is_some_and(|len| len <= if tiff.big_tiff { 8 } else { 4 });
            if !inline_ok
                && field_type_size(e.field_type).is_some()
                && tiff.value_bytes(e.tag).is_none()
            {
                return Err(format!(
                    "tag {} of directory {index} ends beyond the file",
                    e.tag
                ));
            }
        }
        for (offsets_tag, counts_tag, what) in [(273, 279, "strip"), (324, 325, "tile")] {
            let (Some(offsets), counts) = (
                tiff.unsigned_values_wide(offsets_tag),
                tiff.unsigned_values_wide(counts_tag),
            ) else {
                continue;
            };
            let counts = counts.ok_or_else(|| {
                format!("directory {index} has {what} offsets but no byte counts")
            })?;
            if counts.len() != offsets.len() {
                return Err(format!(
                    "directory {index}: {} {what} offsets for {} byte counts",
                    offsets.len(),
                    counts.len()
                ));
            }
            for (i, (&o, &c)) in offsets.iter().zip(&counts).enumerate() {
                if o.checked_add(c).is_none_or(|end| end > bytes.len() as u64) {
                    return Err(format!(
                        "{what} {i} of directory {index} ends beyond the file"
                    ));
                }
            }
        }
        if index == 0 && tiff.entry(273).is_none() && tiff.entry(324).is_none() {
            return Err("the first directory has no image data".into());
        }
        ifd = usize::try_from(next).map_err(|_| "directory offset beyond memory".to_owned())?;
        index += 1;
    }
    Ok(())
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

    /// A real grey 16-bit TIFF from the `tiff` encoder, 3 strips of rows.
    fn encoded() -> Vec<u8> {
        use tiff::encoder::{TiffEncoder, colortype::Gray16};
        let mut out = std::io::Cursor::new(Vec::new());
        let mut enc = TiffEncoder::new(&mut out).unwrap();
        let mut img = enc.new_image::<Gray16>(64, 48).unwrap();
        img.rows_per_strip(16).unwrap();
        img.write_data(&vec![7u16; 64 * 48]).unwrap();
        out.into_inner()
    }

    #[test]
    fn a_whole_tiff_passes_and_every_cut_of_it_fails() {
        let bytes = encoded();
        check_whole(&bytes).unwrap();
        // The encoder writes pixels first and the directory last, as vendors do: every
        // shorter prefix must be refused, whatever the cut hits.
        for cut in [
            0,
            3,
            8,
            100,
            bytes.len() / 2,
            bytes.len() - 40,
            bytes.len() - 1,
        ] {
            assert!(check_whole(&bytes[..cut]).is_err(), "cut at {cut} accepted");
        }
    }

    #[test]
    fn strips_beyond_the_end_are_named() {
        let mut bytes = encoded();
        // Keep the directory but make the data region shorter: relocate by zeroing the
        // header's directory offset first → "no image directory yet".
        let mut no_dir = bytes.clone();
        no_dir[4..8].copy_from_slice(&0u32.to_le_bytes());
        assert_eq!(check_whole(&no_dir).unwrap_err(), "no image directory yet");
        // A strip byte count grown past the end of the file.
        let t = RawTiff::parse(&bytes).unwrap();
        let e = t.entry(279).unwrap();
        let counts_at = if e.count == 1 {
            e.value_field
        } else {
            t.u32_at(e.value_field).unwrap() as usize
        };
        bytes[counts_at..counts_at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        let err = check_whole(&bytes).unwrap_err();
        assert_eq!(err, "strip 0 of directory 0 ends beyond the file");
    }

    #[test]
    fn a_directory_chain_that_loops_is_refused() {
        let mut bytes = encoded();
        let first = RawTiff::header(&bytes).unwrap().first_ifd().unwrap();
        let count = u16::from_le_bytes([bytes[first], bytes[first + 1]]) as usize;
        let next_at = first + 2 + 12 * count;
        bytes[next_at..next_at + 4].copy_from_slice(&(first as u32).to_le_bytes());
        assert!(check_whole(&bytes).unwrap_err().contains("loops"));
    }
}
