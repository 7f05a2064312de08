//! Middlebury `.flo` optical-flow files (Baker et al., "A database and
//! evaluation methodology for optical flow").
//!
//! Layout, little-endian: the float 202021.25 (the bytes `PIEH`), width and
//! height as i32, then `(u, v)` float32 pairs row-major. Components above 1e9
//! mean "unknown"; we write unknown (`NaN`) as 1e10 and read them back as `NaN`.

use std::io::{Read, Write};

use crate::vision::Image;

/// The tag that opens every `.flo` file.
pub const TAG: f32 = 202_021.25;
/// Written for unknown flow; anything above [`UNKNOWN_THRESHOLD`] reads as unknown.
pub const UNKNOWN: f32 = 1e10;
pub const UNKNOWN_THRESHOLD: f32 = 1e9;
/// Refuse absurd sizes before allocating (a corrupt header).
const MAX_SIDE: usize = 1 << 16;

#[derive(Debug, thiserror::Error)]
pub enum FloError {
    #[error("not a Middlebury .flo file: tag {found} instead of 202021.25")]
    BadTag { found: f32 },
    #[error(
        ".flo header says {width}×{height}, which is not a usable image size; the file is corrupt"
    )]
    BadSize { width: i64, height: i64 },
    #[error(
        ".flo file ends after {got} bytes, {expected} expected for its size; the file is truncated"
    )]
    Truncated { expected: usize, got: usize },
    #[error(
        "u is {u_width}×{u_height} but v is {v_width}×{v_height}; both flow components must share a size"
    )]
    ComponentMismatch {
        u_width: usize,
        u_height: usize,
        v_width: usize,
        v_height: usize,
    },
    #[error("reading or writing the .flo file: {0}")]
    Io(std::io::Error),
}

error_from!(FloError { Io(std::io::Error) });

/// Encodes a flow field (`NaN` = unknown).
///
/// # Errors
/// [`FloError::ComponentMismatch`] when `u` and `v` differ in size.
pub fn encode(u: &Image, v: &Image) -> Result<Vec<u8>, FloError> {
    if u.dimensions() != v.dimensions() {
        return Err(FloError::ComponentMismatch {
            u_width: u.width(),
            u_height: u.height(),
            v_width: v.width(),
            v_height: v.height(),
        });
    }
    let (w, h) = u.dimensions();
    let mut out = Vec::with_capacity(12 + 8 * w * h);
    out.extend_from_slice(&TAG.to_le_bytes());
    for side in [w, h] {
        let side = i32::try_from(side).map_err(|_| FloError::BadSize {
            width: w as i64,
            height: h as i64,
        })?;
        out.extend_from_slice(&side.to_le_bytes());
    }
    for (&a, &b) in u.data().iter().zip(v.data()) {
        for c in [a, b] {
            let c = if c.is_finite() { c } else { UNKNOWN };
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    Ok(out)
}

/// Decodes a `.flo` file into `(u, v)`, unknown components as `NaN`.
///
/// # Errors
/// [`FloError`] for a wrong tag, an implausible size or a truncated file.
pub fn decode(bytes: &[u8]) -> Result<(Image, Image), FloError> {
    let word = |i: usize| -> Option<[u8; 4]> { bytes.get(i..i + 4)?.try_into().ok() };
    let header = (word(0), word(4), word(8));
    let (Some(tag), Some(wb), Some(hb)) = header else {
        return Err(FloError::Truncated {
            expected: 12,
            got: bytes.len(),
        });
    };
    let tag = f32::from_le_bytes(tag);
    if tag != TAG {
        return Err(FloError::BadTag { found: tag });
    }
    let (wi, hi) = (i32::from_le_bytes(wb), i32::from_le_bytes(hb));
    let (Ok(w), Ok(h)) = (usize::try_from(wi), usize::try_from(hi)) else {
        return Err(FloError::BadSize {
            width: i64::from(wi),
            height: i64::from(hi),
        });
    };
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        return Err(FloError::BadSize {
            width: i64::from(wi),
            height: i64::from(hi),
        });
    }
    let expected = 12 + 8 * w * h;
    if bytes.len() < expected {
        return Err(FloError::Truncated {
            expected,
            got: bytes.len(),
        });
    }
    let mut u = Vec::with_capacity(w * h);
    let mut v = Vec::with_capacity(w * h);
    for pair in bytes[12..expected].chunks_exact(8) {
        let read = |b: &[u8]| {
            let x = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            if x.is_finite() && x.abs() <= UNKNOWN_THRESHOLD {
                x
            } else {
                f32::NAN
            }
        };
        u.push(read(&pair[..4]));
        v.push(read(&pair[4..]));
    }
    Ok((
        Image::from_vec(w, h, u).expect("w × h samples decoded"),
        Image::from_vec(w, h, v).expect("w × h samples decoded"),
    ))
}

/// Writes a flow field as `.flo`.
///
/// # Errors
/// [`FloError`] from [`encode`] or the writer.
pub fn write<W: Write>(mut out: W, u: &Image, v: &Image) -> Result<(), FloError> {
    out.write_all(&encode(u, v)?)?;
    out.flush()?;
    Ok(())
}

/// Reads a `.flo` file.
///
/// # Errors
/// [`FloError`] from the reader or [`decode`].
pub fn read<R: Read>(mut input: R) -> Result<(Image, Image), FloError> {
    let mut bytes = Vec::new();
    input.read_to_end(&mut bytes)?;
    decode(&bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_keeps_values_and_unknowns() {
        let u = Image::from_fn(3, 2, |x, y| {
            if (x, y) == (1, 1) {
                f32::NAN
            } else {
                x as f32 - 0.5
            }
        });
        let v = Image::from_fn(3, 2, |x, y| (y * 3 + x) as f32 * 0.25);
        let bytes = encode(&u, &v).unwrap();
        assert_eq!(&bytes[..4], b"PIEH");
        assert_eq!(bytes.len(), 12 + 8 * 6);
        let (u2, v2) = decode(&bytes).unwrap();
        assert!(u2.get(1, 1).is_nan());
        assert_eq!(u2.get(2, 0), 1.5);
        assert_eq!(v2, v);
    }

    #[test]
    fn rejects_corrupt_files() {
        let u = Image::zeros(2, 2);
        let bytes = encode(&u, &u).unwrap();
        assert!(matches!(
            decode(&bytes[..bytes.len() - 1]),
            Err(FloError::Truncated { .. })
        ));
        let mut bad = bytes.clone();
        bad[0] = 0;
        assert!(matches!(decode(&bad), Err(FloError::BadTag { .. })));
        let mut neg = bytes;
        neg[4..8].copy_from_slice(&(-3i32).to_le_bytes());
        assert!(matches!(decode(&neg), Err(FloError::BadSize { .. })));
        assert!(matches!(
            encode(&Image::zeros(2, 2), &Image::zeros(3, 2)),
            Err(FloError::ComponentMismatch { .. })
        ));
    }
}
