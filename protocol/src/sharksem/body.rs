//! Message bodies: arguments left to right, return value first in a response
//! [TS-PDF "Message body"; TS-CS; TS-PY].
//!
//! - `int` / `unsigned int`: 4 bytes little-endian.
//! - arrays (`char[]`, `int[]`…): a u32 byte count, the bytes, zero padding to a multiple of 4.
//! - string: a `char[]` holding NUL-terminated text.
//! - float: a string in C `strtod` syntax (`"3.1415e-3"`).
//! - map: a string of `key=value` lines.
//!
//! The byte count of a string is the exact length with its NUL in the manual's
//! example ("3.14" → 5, then 3 pad bytes) and the padded length in TESCAN's
//! Python client: both read the same (count, then skip to the next multiple of
//! 4). [`BodyWriter`] emits the manual's form.

use super::header::escape;

/// Why a body does not decode.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BodyError {
    /// The body ends inside a value.
    #[error("body of {len} bytes ends inside a value at byte {at} ({want} bytes more needed)")]
    Truncated { at: usize, want: usize, len: usize },
    /// An array's byte count runs past the end of the body.
    #[error("an array at byte {at} claims {count} bytes but only {left} remain in the body")]
    ArrayTooLong { at: usize, count: u32, left: usize },
    /// A float that is not a finite number in `strtod` syntax.
    #[error("{0:?} is not a finite number")]
    NotAFloat(String),
    /// Bytes are left after the last argument (server side: wrong arguments).
    #[error("{0} unexpected bytes after the last argument")]
    Trailing(usize),
    /// A value outside the range the function accepts.
    #[error("{what} = {value} is outside the accepted range")]
    OutOfRange { what: &'static str, value: String },
    /// Fewer values than the function returns or takes.
    #[error("{what}: expected {expected} values, got {got}")]
    Count {
        what: &'static str,
        expected: &'static str,
        got: usize,
    },
}

/// Encodes arguments (or return values) left to right.
#[derive(Debug, Default, Clone)]
pub struct BodyWriter {
    buf: Vec<u8>,
}

impl BodyWriter {
    /// An empty body.
    #[must_use]
    pub fn new() -> Self {
        Self::default()
    }

    /// A 32-bit signed integer.
    pub fn int(&mut self, v: i32) -> &mut Self {
        self.buf.extend_from_slice(&v.to_le_bytes());
        self
    }

    /// A 32-bit unsigned integer.
    pub fn uint(&mut self, v: u32) -> &mut Self {
        self.buf.extend_from_slice(&v.to_le_bytes());
        self
    }

    /// An array of bytes: the exact byte count, the bytes, zero padding to 4.
    ///
    /// # Panics
    /// Never for bodies of this protocol: an array longer than 4 GiB cannot be built in memory here.
    pub fn bytes(&mut self, data: &[u8]) -> &mut Self {
        let count = u32::try_from(data.len()).unwrap_or(u32::MAX);
        self.uint(count);
        self.buf.extend_from_slice(data);
        self.pad();
        self
    }

    /// A NUL-terminated string; its byte count includes the NUL (the manual's form).
    pub fn string(&mut self, s: &str) -> &mut Self {
        let mut data = Vec::with_capacity(s.len() + 1);
        data.extend(s.bytes().filter(|&b| b != 0));
        data.push(0);
        self.bytes(&data)
    }

    /// A float as a `strtod` string: shortest round-trip digits, exponent form
    /// for very small or large magnitudes.
    pub fn float(&mut self, v: f64) -> &mut Self {
        self.string(&format_float(v))
    }

    fn pad(&mut self) {
        while !self.buf.len().is_multiple_of(4) {
            self.buf.push(0);
        }
    }

    /// The encoded body.
    #[must_use]
    pub fn finish(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.buf)
    }
}

/// The text of a float on the wire.
#[must_use]
pub fn format_float(v: f64) -> String {
    let a = v.abs();
    if v == 0.0 || (1e-4..1e9).contains(&a) {
        format!("{v}")
    } else {
        format!("{v:e}")
    }
}

/// Parses a float as `strtod` would from a well-formed value: optional
/// surrounding blanks, sign, digits, point, exponent. Non-finite values are refused.
///
/// # Errors
/// [`BodyError::NotAFloat`].
pub fn parse_float(s: &str) -> Result<f64, BodyError> {
    let t = s.trim_matches(|c: char| c.is_ascii_whitespace());
    let looks_numeric = !t.is_empty()
        && t.bytes()
            .all(|b| b.is_ascii_digit() || matches!(b, b'+' | b'-' | b'.' | b'e' | b'E'));
    match t.parse::<f64>() {
        Ok(v) if looks_numeric && v.is_finite() => Ok(v),
        _ => Err(BodyError::NotAFloat(s.to_owned())),
    }
}

/// Decodes values left to right from a body.
#[derive(Debug, Clone)]
pub struct BodyReader<'a> {
    body: &'a [u8],
    at: usize,
}

impl<'a> BodyReader<'a> {
    /// A reader at the start of `body`.
    #[must_use]
    pub fn new(body: &'a [u8]) -> Self {
        Self { body, at: 0 }
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], BodyError> {
        let left = self.body.len() - self.at;
        if n > left {
            return Err(BodyError::Truncated {
                at: self.at,
                want: n - left,
                len: self.body.len(),
            });
        }
        let s = &self.body[self.at..self.at + n];
        self.at += n;
        Ok(s)
    }

    /// Bytes not read yet.
    #[must_use]
    pub fn remaining(&self) -> usize {
        self.body.len() - self.at
    }

    /// Whether every byte was read.
    #[must_use]
    pub fn is_empty(&self) -> bool {
        self.remaining() == 0
    }

    /// A 32-bit signed integer.
    ///
    /// # Errors
    /// [`BodyError::Truncated`].
    pub fn int(&mut self) -> Result<i32, BodyError> {
        let b = self.take(4)?;
        Ok(i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// A 32-bit unsigned integer.
    ///
    /// # Errors
    /// [`BodyError::Truncated`].
    pub fn uint(&mut self) -> Result<u32, BodyError> {
        let b = self.take(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// An array's bytes; the padding after them is skipped (a body that ends
    /// before its last padding is accepted).
    ///
    /// # Errors
    /// [`BodyError::Truncated`] or [`BodyError::ArrayTooLong`].
    pub fn bytes(&mut self) -> Result<&'a [u8], BodyError> {
        let at = self.at;
        let count = self.uint()?;
        let left = self.remaining();
        let n = usize::try_from(count).unwrap_or(usize::MAX);
        if n > left {
            return Err(BodyError::ArrayTooLong { at, count, left });
        }
        let data = self.take(n)?;
        let padded = self.at.next_multiple_of(4).min(self.body.len());
        self.at = padded;
        Ok(data)
    }

    /// A string: the array up to its first NUL (the whole array if it has none);
    /// bytes that are not UTF-8 are replaced.
    ///
    /// # Errors
    /// As [`Self::bytes`].
    pub fn string(&mut self) -> Result<String, BodyError> {
        let data = self.bytes()?;
        let end = data.iter().position(|&b| b == 0).unwrap_or(data.len());
        Ok(String::from_utf8_lossy(&data[..end]).into_owned())
    }

    /// A float sent as a string.
    ///
    /// # Errors
    /// As [`Self::bytes`], or [`BodyError::NotAFloat`].
    pub fn float(&mut self) -> Result<f64, BodyError> {
        let data = self.bytes()?;
        let end = data.iter().position(|&b| b == 0).unwrap_or(data.len());
        match std::str::from_utf8(&data[..end]) {
            Ok(s) => parse_float(s),
            Err(_) => Err(BodyError::NotAFloat(escape(&data[..end]))),
        }
    }

    /// Fails if bytes are left (server side: a request with extra arguments is wrong).
    ///
    /// # Errors
    /// [`BodyError::Trailing`].
    pub fn end(&self) -> Result<(), BodyError> {
        match self.remaining() {
            0 => Ok(()),
            n => Err(BodyError::Trailing(n)),
        }
    }
}

/// The `key=value` lines of a map, in order. Lines without `=` and empty
/// keys are skipped ("ignore keys of an unknown form"); CR before LF is dropped.
#[must_use]
pub fn parse_map(text: &str) -> Vec<(String, String)> {
    text.split('\n')
        .map(|l| l.strip_suffix('\r').unwrap_or(l))
        .filter_map(|l| l.split_once('='))
        .filter(|(k, _)| !k.trim().is_empty())
        .map(|(k, v)| (k.trim().to_owned(), v.trim().to_owned()))
        .collect()
}

/// A map as text: one `key=value` line each, each ended by LF.
#[must_use]
pub fn format_map<K: AsRef<str>, V: AsRef<str>>(entries: &[(K, V)]) -> String {
    entries
        .iter()
        .map(|(k, v)| format!("{}={}\n", k.as_ref(), v.as_ref()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn strings_use_the_exact_count_and_pad_to_four() {
        let body = BodyWriter::new().string("2.75").finish();
        assert_eq!(body, b"\x05\0\0\x002.75\0\0\0\0");
        let body = BodyWriter::new().string("abc").finish();
        assert_eq!(
            body, b"\x04\0\0\0abc\0",
            "no padding when the NUL ends on a boundary"
        );
        let body = BodyWriter::new().string("").finish();
        assert_eq!(body, b"\x01\0\0\0\0\0\0\0");
    }

    #[test]
    fn both_length_forms_read_the_same() {
        // Manual form: count 5; TESCAN's Python client: padded count 8.
        for bytes in [
            &b"\x05\0\0\x002.75\0\0\0\0\x07\0\0\0"[..],
            &b"\x08\0\0\x002.75\0\0\0\0\x07\0\0\0"[..],
        ] {
            let mut r = BodyReader::new(bytes);
            assert_eq!(r.float().unwrap(), 2.75);
            assert_eq!(r.int().unwrap(), 7);
            r.end().unwrap();
        }
    }

    #[test]
    fn values_round_trip() {
        let body = BodyWriter::new()
            .int(-3)
            .uint(4_000_000_000)
            .float(0.128)
            .float(-1.5e-7)
            .float(0.0)
            .string("SE detector")
            .bytes(&[1, 2, 3, 4, 5])
            .finish();
        assert_eq!(body.len() % 4, 0);
        let mut r = BodyReader::new(&body);
        assert_eq!(r.int().unwrap(), -3);
        assert_eq!(r.uint().unwrap(), 4_000_000_000);
        assert_eq!(r.float().unwrap(), 0.128);
        assert_eq!(r.float().unwrap(), -1.5e-7);
        assert_eq!(r.float().unwrap(), 0.0);
        assert_eq!(r.string().unwrap(), "SE detector");
        assert_eq!(r.bytes().unwrap(), &[1, 2, 3, 4, 5]);
        assert!(r.is_empty());
    }

    #[test]
    fn floats_are_strtod_strings() {
        assert_eq!(format_float(0.128), "0.128");
        assert_eq!(format_float(1e-7), "1e-7");
        assert_eq!(format_float(-90.0), "-90");
        for (s, v) in [
            ("3.1415e-3", 3.1415e-3),
            (" 12 ", 12.0),
            ("+1.", 1.0),
            (".5E2", 50.0),
        ] {
            assert_eq!(parse_float(s).unwrap(), v, "{s}");
        }
        for s in ["", "nan", "inf", "1e999", "0x10", "1,5", "12abc"] {
            assert!(parse_float(s).is_err(), "{s:?}");
        }
    }

    #[test]
    fn hostile_bodies_fail_cleanly() {
        let mut r = BodyReader::new(&[1, 2]);
        assert!(matches!(r.int(), Err(BodyError::Truncated { want: 2, .. })));
        let mut r = BodyReader::new(b"\xFF\xFF\xFF\xFFabcd");
        assert!(matches!(
            r.bytes(),
            Err(BodyError::ArrayTooLong {
                count: u32::MAX,
                left: 4,
                ..
            })
        ));
        let mut r = BodyReader::new(b"\x03\0\0\0ab\xFF\0");
        assert!(matches!(r.float(), Err(BodyError::NotAFloat(s)) if s.contains("\\xFF")));
        // A string without NUL and without its last padding still reads.
        let mut r = BodyReader::new(b"\x03\0\0\0abc");
        assert_eq!(r.string().unwrap(), "abc");
        assert_eq!(
            BodyReader::new(b"\0\0\0\0").end(),
            Err(BodyError::Trailing(4))
        );
    }

    #[test]
    fn maps_are_key_value_lines() {
        let m = parse_map("speed.1.dwell=0.1\r\nspeed.2.dwell=0.32\njunk\n=x\n\n");
        assert_eq!(
            m,
            vec![
                ("speed.1.dwell".to_owned(), "0.1".to_owned()),
                ("speed.2.dwell".to_owned(), "0.32".to_owned())
            ]
        );
        assert_eq!(format_map(&[("a", "1"), ("b", "x=y")]), "a=1\nb=x=y\n");
        assert_eq!(
            parse_map("b=x=y\n"),
            vec![("b".to_owned(), "x=y".to_owned())]
        );
    }
}
