//! The 32-byte message header shared by requests, responses and `ScData` [TS-PDF, TS-CS, TS-PY].

use std::fmt;

/// Bytes in a header.
pub const HEADER_LEN: usize = 32;
/// Longest function name: 15 characters and a NUL fill the 16-byte field.
pub const MAX_NAME_LEN: usize = 15;

/// Why a header or a function name is refused.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum HeaderError {
    /// The name field holds no name, a byte outside printable ASCII, or no NUL terminator.
    #[error("function name {0:?} is not 1–15 printable ASCII characters ended by NUL")]
    BadName(String),
}

/// A SharkSEM function name: 1–15 printable ASCII characters, case-sensitive.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FnName(String);

impl FnName {
    /// Checks `name`.
    ///
    /// # Errors
    /// [`HeaderError::BadName`] for an empty or overlong name or one with
    /// bytes outside printable ASCII.
    pub fn new(name: &str) -> Result<Self, HeaderError> {
        let ok =
            (1..=MAX_NAME_LEN).contains(&name.len()) && name.bytes().all(|b| b.is_ascii_graphic());
        if ok {
            Ok(Self(name.to_owned()))
        } else {
            Err(HeaderError::BadName(name.to_owned()))
        }
    }

    /// The name.
    #[must_use]
    pub fn as_str(&self) -> &str {
        &self.0
    }

    /// Decodes the 16-byte field: the name up to its first NUL, zero padding after it.
    fn decode(field: &[u8; 16]) -> Result<Self, HeaderError> {
        let end = field.iter().position(|&b| b == 0);
        let Some(end) = end else {
            return Err(HeaderError::BadName(escape(field)));
        };
        let name = std::str::from_utf8(&field[..end])
            .map_err(|_| HeaderError::BadName(escape(&field[..end])))?;
        Self::new(name).map_err(|_| HeaderError::BadName(escape(&field[..end])))
    }
}

impl fmt::Display for FnName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

/// Printable text of raw bytes for messages (`\xNN` for the others).
pub(crate) fn escape(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len());
    for &b in bytes {
        if b.is_ascii_graphic() || b == b' ' {
            s.push(char::from(b));
        } else {
            s.push_str(&format!("\\x{b:02X}"));
        }
    }
    s
}

/// The request flags of the header's u16 flags field [TS-PDF "Message header"].
///
/// Bit 0 asks for a response even from a void function, bit 1 puts the
/// request at the head of the server's queue; bits 8–14 are the wait flags A–G:
/// the server holds the request until each condition named is clear.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Flags(pub u16);

impl Flags {
    /// No flag: a void function sends no response.
    pub const NONE: Self = Self(0);
    /// Bit 0: always respond, even for a void function.
    pub const SEND_RESPONSE: Self = Self(1 << 0);
    /// Bit 1: put the request at the head of the server's queue.
    pub const JUMP: Self = Self(1 << 1);
    /// Wait A: e-beam scanning inactive.
    pub const WAIT_A: Self = Self(1 << 8);
    /// Wait B: stage and detector motion idle.
    pub const WAIT_B: Self = Self(1 << 9);
    /// Wait C: e-beam optics stable.
    pub const WAIT_C: Self = Self(1 << 10);
    /// Wait D: no e-beam automatic procedure running.
    pub const WAIT_D: Self = Self(1 << 11);
    /// Wait E: FIB scanning inactive.
    pub const WAIT_E: Self = Self(1 << 12);
    /// Wait F: FIB optics stable.
    pub const WAIT_F: Self = Self(1 << 13);
    /// Wait G: no FIB automatic procedure running.
    pub const WAIT_G: Self = Self(1 << 14);
    /// Every wait flag (bits 8–14).
    pub const WAIT_MASK: Self = Self(0x7F00);

    /// Whether every bit of `other` is set here.
    #[must_use]
    pub fn contains(self, other: Self) -> bool {
        self.0 & other.0 == other.0
    }

    /// Only the wait flags.
    #[must_use]
    pub fn waits(self) -> Self {
        Self(self.0 & Self::WAIT_MASK.0)
    }
}

impl std::ops::BitOr for Flags {
    type Output = Self;
    fn bitor(self, rhs: Self) -> Self {
        Self(self.0 | rhs.0)
    }
}

impl fmt::Display for Flags {
    /// `send-response|wait-B`, or `none`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let mut parts: Vec<String> = Vec::new();
        if self.contains(Self::SEND_RESPONSE) {
            parts.push("send-response".into());
        }
        if self.contains(Self::JUMP) {
            parts.push("jump".into());
        }
        for (i, letter) in ['A', 'B', 'C', 'D', 'E', 'F', 'G'].into_iter().enumerate() {
            if self.0 & (1 << (8 + i)) != 0 {
                parts.push(format!("wait-{letter}"));
            }
        }
        let other = self.0 & !0x7F03;
        if other != 0 {
            parts.push(format!("0x{other:04X}"));
        }
        if parts.is_empty() {
            f.write_str("none")
        } else {
            f.write_str(&parts.join("|"))
        }
    }
}

/// One message header (32 bytes, little-endian, no alignment).
///
/// | offset | size | field |
/// | --- | --- | --- |
/// | 0 | 16 | function name, NUL-padded |
/// | 16 | 4 | body size, bytes (padding included) |
/// | 20 | 4 | id, copied by the server into its response |
/// | 24 | 2 | flags ([`Flags`]); 0 in responses |
/// | 26 | 2 | queue, echoed back |
/// | 28 | 4 | reserved, 0 |
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Header {
    pub name: FnName,
    pub body_size: u32,
    pub id: u32,
    pub flags: Flags,
    pub queue: u16,
}

impl Header {
    /// The 32 bytes of this header.
    #[must_use]
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut out = [0u8; HEADER_LEN];
        out[..self.name.0.len()].copy_from_slice(self.name.0.as_bytes());
        out[16..20].copy_from_slice(&self.body_size.to_le_bytes());
        out[20..24].copy_from_slice(&self.id.to_le_bytes());
        out[24..26].copy_from_slice(&self.flags.0.to_le_bytes());
        out[26..28].copy_from_slice(&self.queue.to_le_bytes());
        out
    }

    /// Decodes 32 bytes. The reserved field is not checked (the manual asks for 0, nothing depends on it).
    ///
    /// # Errors
    /// [`HeaderError::BadName`] when the name field is not a name.
    pub fn decode(bytes: &[u8; HEADER_LEN]) -> Result<Self, HeaderError> {
        let mut name = [0u8; 16];
        name.copy_from_slice(&bytes[..16]);
        let u32_at =
            |i: usize| u32::from_le_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
        let u16_at = |i: usize| u16::from_le_bytes([bytes[i], bytes[i + 1]]);
        Ok(Self {
            name: FnName::decode(&name)?,
            body_size: u32_at(16),
            id: u32_at(20),
            flags: Flags(u16_at(24)),
            queue: u16_at(26),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_layout_is_little_endian_at_the_documented_offsets() {
        let h = Header {
            name: FnName::new("StgMoveTo").unwrap(),
            body_size: 0x0102_0304,
            id: 7,
            flags: Flags::WAIT_B | Flags::SEND_RESPONSE,
            queue: 2,
        };
        let b = h.encode();
        assert_eq!(&b[..10], b"StgMoveTo\0");
        assert!(b[10..16].iter().all(|&x| x == 0));
        assert_eq!(&b[16..20], &[4, 3, 2, 1]);
        assert_eq!(&b[20..24], &[7, 0, 0, 0]);
        assert_eq!(
            &b[24..26],
            &[0x01, 0x02],
            "send-response bit 0, wait B bit 9"
        );
        assert_eq!(&b[26..28], &[2, 0]);
        assert_eq!(&b[28..], &[0, 0, 0, 0]);
        assert_eq!(Header::decode(&b).unwrap(), h);
    }

    #[test]
    fn names_are_checked() {
        assert!(FnName::new("TcpGetSWVersion").is_ok(), "15 characters fit");
        assert!(FnName::new("TcpGetSWVersionX").is_err());
        assert!(FnName::new("").is_err());
        assert!(FnName::new("Stg Move").is_err());
        let mut field = [b'A'; HEADER_LEN];
        assert!(Header::decode(&field).is_err(), "no NUL in 16 bytes");
        field[..16].copy_from_slice(b"\0ScData\0\0\0\0\0\0\0\0\0");
        assert!(Header::decode(&field).is_err(), "empty name");
        field[..16].copy_from_slice(b"Sc\xFFData\0\0\0\0\0\0\0\0\0");
        let e = Header::decode(&field).unwrap_err().to_string();
        assert!(e.contains("\\xFF"), "{e}");
    }

    #[test]
    fn flags_print_their_names() {
        assert_eq!(Flags::NONE.to_string(), "none");
        assert_eq!((Flags::WAIT_A | Flags::WAIT_G).to_string(), "wait-A|wait-G");
        assert_eq!(Flags(0x8004).to_string(), "0x8004");
        assert_eq!((Flags::WAIT_B | Flags::JUMP).waits(), Flags::WAIT_B);
    }
}
