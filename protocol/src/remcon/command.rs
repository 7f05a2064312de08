//! Requests: typed commands, their wire form (client), and parsing (server).

use std::fmt;

use super::error::RemconError;
use super::reply::Reply;

/// The request terminator sdsem sends: CR (required; LF is optional) [OD-Z, SF, ML].
pub const TERMINATOR: u8 = b'\r';

/// Longest request line, terminator excluded. sdsem's own bound (the manual's
/// maximum behind error 617 is not public); the longest `C95` fits with room.
pub const MAX_COMMAND_LEN: usize = 127;

/// The target of an all-axes absolute move, `C95 x y z t r m`: mm for x, y, z, m;
/// degrees for t (tilt) and r (rotation). Tilt comes BEFORE rotation [OD-Z, SF, ML].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageTarget {
    /// X, mm.
    pub x_mm: f64,
    /// Y, mm.
    pub y_mm: f64,
    /// Z, mm.
    pub z_mm: f64,
    /// Tilt, degrees.
    pub t_deg: f64,
    /// Rotation, degrees.
    pub r_deg: f64,
    /// M (the extra Z in the tilted frame), mm.
    pub m_mm: f64,
}

impl StageTarget {
    /// The six values in wire order.
    pub fn values(&self) -> [f64; 6] {
        [
            self.x_mm, self.y_mm, self.z_mm, self.t_deg, self.r_deg, self.m_mm,
        ]
    }

    /// From the six values in wire order.
    pub fn from_values([x_mm, y_mm, z_mm, t_deg, r_deg, m_mm]: [f64; 6]) -> Self {
        Self {
            x_mm,
            y_mm,
            z_mm,
            t_deg,
            r_deg,
            m_mm,
        }
    }
}

/// The RemCon32 commands sdsem and its simulator use.
#[derive(Clone, Debug, PartialEq)]
pub enum Command {
    /// The null command: an empty line, a harmless probe sent at connect [OD-Z, ML].
    Null,
    /// `VER?`: the software version, e.g. "SmartSEM Remote Control V06.01, …".
    Version,
    /// `C95?`: `x y z t r m moving`.
    StageQuery,
    /// `C95 x y z t r m`: absolute move of every axis; returns before the move ends.
    StageMove(StageTarget),
    /// `STG?`: `x y z moving` (the 3-axis form).
    Stage3Query,
    /// `STG x y z`: absolute move of x, y, z, mm.
    Stage3Move {
        /// X, mm.
        x_mm: f64,
        /// Y, mm.
        y_mm: f64,
        /// Z, mm.
        z_mm: f64,
    },
    /// `IST?`: `type init`, init 0 = initialised [SF].
    InitialisedQuery,
    /// `ABO`: abort, stops a stage move [OD-Z].
    Abort,
    /// `PIX?`: pixel size, nm.
    PixelSizeQuery,
    /// `MAG?`: magnification.
    MagnificationQuery,
    /// `FREC`: SmartSEM stores a photo [ML].
    Record,
    /// `MAC n`: runs the SmartSEM macro "REMCONn" [SF].
    Macro(u32),
    /// `PHN?`: the photo counter [ML].
    PhotoNumberQuery,
    /// `DET?`: the detector in use, e.g. `SE2`, `InLens` [SF, ML].
    DetectorQuery,
    /// `EHT?`: the accelerating voltage, kV [OD-Z, SF].
    EhtQuery,
}

/// A number as sent: fixed six decimals (`%f`, accepted [VENDORS §1.2]); no `-0`.
fn number(v: f64) -> String {
    let v = if v == 0.0 { 0.0 } else { v };
    format!("{v:.6}")
}

impl fmt::Display for Command {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Null => Ok(()),
            Self::Version => f.write_str("VER?"),
            Self::StageQuery => f.write_str("C95?"),
            Self::StageMove(t) => {
                f.write_str("C95")?;
                for v in t.values() {
                    write!(f, " {}", number(v))?;
                }
                Ok(())
            }
            Self::Stage3Query => f.write_str("STG?"),
            Self::Stage3Move { x_mm, y_mm, z_mm } => write!(
                f,
                "STG {} {} {}",
                number(*x_mm),
                number(*y_mm),
                number(*z_mm)
            ),
            Self::InitialisedQuery => f.write_str("IST?"),
            Self::Abort => f.write_str("ABO"),
            Self::PixelSizeQuery => f.write_str("PIX?"),
            Self::MagnificationQuery => f.write_str("MAG?"),
            Self::Record => f.write_str("FREC"),
            Self::Macro(n) => write!(f, "MAC {n}"),
            Self::PhotoNumberQuery => f.write_str("PHN?"),
            Self::DetectorQuery => f.write_str("DET?"),
            Self::EhtQuery => f.write_str("EHT?"),
        }
    }
}

impl Command {
    /// The request on the wire: the line, then CR.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut bytes = self.to_string().into_bytes();
        bytes.push(TERMINATOR);
        bytes
    }

    /// Server side: the command on a framed line (terminator removed), or
    /// what the instrument answers instead.
    pub fn parse(line: &[u8]) -> Result<Self, ParseError> {
        let Ok(text) = std::str::from_utf8(line) else {
            return Err(ParseError::Unknown);
        };
        let mut words = text.split_ascii_whitespace();
        let Some(word) = words.next() else {
            return Ok(Self::Null);
        };
        let args: Vec<&str> = words.collect();
        let numbers = |n: usize, stage: bool| -> Result<Vec<f64>, ParseError> {
            if args.len() != n {
                return Err(if stage {
                    ParseError::StageArgumentCount
                } else {
                    ParseError::ArgumentCount
                });
            }
            args.iter()
                .map(|a| {
                    a.parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or(ParseError::ParameterType)
                })
                .collect()
        };
        let bare = |c: Self| {
            if args.is_empty() {
                Ok(c)
            } else {
                Err(ParseError::ArgumentCount)
            }
        };
        match word {
            "VER?" => bare(Self::Version),
            "C95?" => bare(Self::StageQuery),
            "C95" => {
                let v = numbers(6, true)?;
                Ok(Self::StageMove(StageTarget::from_values([
                    v[0], v[1], v[2], v[3], v[4], v[5],
                ])))
            }
            "STG?" => bare(Self::Stage3Query),
            "STG" => {
                let v = numbers(3, true)?;
                Ok(Self::Stage3Move {
                    x_mm: v[0],
                    y_mm: v[1],
                    z_mm: v[2],
                })
            }
            "IST?" => bare(Self::InitialisedQuery),
            "ABO" => bare(Self::Abort),
            "PIX?" => bare(Self::PixelSizeQuery),
            "MAG?" => bare(Self::MagnificationQuery),
            "FREC" => bare(Self::Record),
            "PHN?" => bare(Self::PhotoNumberQuery),
            "DET?" => bare(Self::DetectorQuery),
            "EHT?" => bare(Self::EhtQuery),
            "MAC" => match args.as_slice() {
                [n] => n
                    .parse::<u32>()
                    .map(Self::Macro)
                    .map_err(|_| ParseError::ParameterType),
                _ => Err(ParseError::ArgumentCount),
            },
            _ => Err(ParseError::Unknown),
        }
    }
}

/// Why a server does not execute a line, and so what it answers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ParseError {
    /// An unknown word: `@`, then `*600` [OD-Z].
    Unknown,
    /// The wrong number of values to `C95`/`STG`: `#` alone [OD-Z].
    StageArgumentCount,
    /// The wrong number of arguments to another command: `@`, then `*601`.
    ArgumentCount,
    /// An argument that is not a (finite) number: `@`, then `*602`.
    ParameterType,
}

impl ParseError {
    /// The reply a RemCon32 server sends for this line.
    pub fn reply(self) -> Reply {
        match self {
            Self::Unknown => Reply::Failed(RemconError::UnknownCommand),
            Self::StageArgumentCount => Reply::Invalid,
            Self::ArgumentCount => Reply::Failed(RemconError::InvalidParameterCount),
            Self::ParameterType => Reply::Failed(RemconError::InvalidParameterType),
        }
    }
}

/// Why a raw line (a configured trigger such as `MAC 1`) cannot be sent.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum LineError {
    /// Nothing to send.
    #[error("the line is empty")]
    Empty,
    /// A byte other than printable ASCII (a terminator would cut the line in two).
    #[error("byte 0x{byte:02X} is not printable ASCII")]
    NotPrintable {
        /// The offending byte.
        byte: u8,
    },
    /// Longer than [`MAX_COMMAND_LEN`].
    #[error("the line is longer than {limit} bytes")]
    TooLong {
        /// The limit, bytes.
        limit: usize,
    },
}

/// A raw command line on the wire (line, then CR), checked: one line of
/// printable ASCII, not empty, at most [`MAX_COMMAND_LEN`] bytes.
pub fn encode_line(line: &str) -> Result<Vec<u8>, LineError> {
    if line.is_empty() {
        return Err(LineError::Empty);
    }
    if let Some(&byte) = line.as_bytes().iter().find(|b| !(0x20..=0x7E).contains(*b)) {
        return Err(LineError::NotPrintable { byte });
    }
    if line.len() > MAX_COMMAND_LEN {
        return Err(LineError::TooLong {
            limit: MAX_COMMAND_LEN,
        });
    }
    let mut bytes = line.as_bytes().to_vec();
    bytes.push(TERMINATOR);
    Ok(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_end_in_cr_and_moves_put_tilt_before_rotation() {
        assert_eq!(Command::Version.to_bytes(), b"VER?\r");
        assert_eq!(Command::Null.to_bytes(), b"\r");
        assert_eq!(Command::Macro(1).to_bytes(), b"MAC 1\r");
        let t = StageTarget {
            x_mm: 12.5,
            y_mm: -0.0,
            z_mm: 10.0,
            t_deg: 3.0,
            r_deg: 180.0,
            m_mm: 0.25,
        };
        assert_eq!(
            Command::StageMove(t).to_string(),
            "C95 12.500000 0.000000 10.000000 3.000000 180.000000 0.250000"
        );
        assert!(Command::StageMove(t).to_bytes().len() <= MAX_COMMAND_LEN + 1);
        let widest = StageTarget::from_values([-152.123456; 6]);
        assert!(Command::StageMove(widest).to_string().len() <= MAX_COMMAND_LEN);
    }

    #[test]
    fn every_command_parses_back_from_its_own_line() {
        for c in [
            Command::Null,
            Command::Version,
            Command::StageQuery,
            Command::StageMove(StageTarget::from_values([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])),
            Command::Stage3Query,
            Command::Stage3Move {
                x_mm: 1.5,
                y_mm: 2.0,
                z_mm: 30.0,
            },
            Command::InitialisedQuery,
            Command::Abort,
            Command::PixelSizeQuery,
            Command::MagnificationQuery,
            Command::Record,
            Command::Macro(7),
            Command::PhotoNumberQuery,
            Command::DetectorQuery,
            Command::EhtQuery,
        ] {
            let bytes = c.to_bytes();
            assert_eq!(Command::parse(&bytes[..bytes.len() - 1]), Ok(c));
        }
    }

    #[test]
    fn bad_lines_get_the_documented_answers() {
        let p = |s: &str| Command::parse(s.as_bytes());
        assert_eq!(p("HELLO"), Err(ParseError::Unknown));
        assert_eq!(p("c95?"), Err(ParseError::Unknown), "words are upper case");
        assert_eq!(p("C95 1 2 3 4 5"), Err(ParseError::StageArgumentCount));
        assert_eq!(p("C95 1 2 3 4 5 6 7"), Err(ParseError::StageArgumentCount));
        assert_eq!(p("STG 1 2"), Err(ParseError::StageArgumentCount));
        assert_eq!(p("C95 1 2 x 4 5 6"), Err(ParseError::ParameterType));
        assert_eq!(p("C95 1 2 inf 4 5 6"), Err(ParseError::ParameterType));
        assert_eq!(p("MAC"), Err(ParseError::ArgumentCount));
        assert_eq!(p("MAC one"), Err(ParseError::ParameterType));
        assert_eq!(p("VER? 2"), Err(ParseError::ArgumentCount));
        assert_eq!(Command::parse(b"\xff\xfe"), Err(ParseError::Unknown));
        assert_eq!(ParseError::Unknown.reply().to_bytes(), b"@\r\n*600\r\n");
        assert_eq!(ParseError::StageArgumentCount.reply().to_bytes(), b"#\r\n");
    }

    #[test]
    fn raw_lines_are_checked() {
        assert_eq!(encode_line("MAC 1").unwrap(), b"MAC 1\r");
        assert_eq!(encode_line(""), Err(LineError::Empty));
        assert_eq!(
            encode_line("FREC\r"),
            Err(LineError::NotPrintable { byte: b'\r' })
        );
        assert_eq!(
            encode_line(&"X".repeat(MAX_COMMAND_LEN + 1)),
            Err(LineError::TooLong {
                limit: MAX_COMMAND_LEN
            })
        );
    }
}
