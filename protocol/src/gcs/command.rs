//! GCS commands as typed values: encoding (client) and parsing (server).

use std::fmt;

use super::axis::AxisId;
use super::error_code::GcsErrorCode;
use super::framer::Incoming;

/// Longest command line a controller accepts, LF excluded; longer lines set
/// [`GcsErrorCode::COMMAND_TOO_LONG`].
pub const MAX_COMMAND_LEN: usize = 256;

/// Single-byte query `#5`: bitmap of the axes in motion.
pub(crate) const BYTE_MOTION_STATUS: u8 = 0x05;
/// Single-byte query `#7`: controller ready.
pub(crate) const BYTE_READY: u8 = 0x07;
/// Single-byte command `#24`: stop all axes.
pub(crate) const BYTE_STOP_ALL: u8 = 0x18;

/// One GCS command or query of the subset spoken here.
///
/// An empty axis list in a query means "all axes", as on the controllers.
#[derive(Clone, Debug, PartialEq)]
pub enum Command {
    /// `MOV {axis target}…`: absolute move.
    Mov(Vec<(AxisId, f64)>),
    /// `MVR {axis distance}…`: move relative to the current target.
    Mvr(Vec<(AxisId, f64)>),
    /// `SVO {axis 0|1}…`: servo (closed loop) off or on.
    Svo(Vec<(AxisId, bool)>),
    /// `FRF [axis…]`: reference move to the reference switch.
    Frf(Vec<AxisId>),
    /// `STP`: stop all axes at once; sets error 10.
    Stp,
    /// `#24` (0x18): stop all axes, like `STP`.
    StopAll,
    /// `POS? [axis…]`: current positions.
    PosQ(Vec<AxisId>),
    /// `ONT? [axis…]`: on-target flags.
    OntQ(Vec<AxisId>),
    /// `SVO? [axis…]`: servo states.
    SvoQ(Vec<AxisId>),
    /// `FRF? [axis…]`: referenced states.
    FrfQ(Vec<AxisId>),
    /// `TMN? [axis…]`: low soft limits.
    TmnQ(Vec<AxisId>),
    /// `TMX? [axis…]`: high soft limits.
    TmxQ(Vec<AxisId>),
    /// `ERR?`: last error code, then reset to 0.
    ErrQ,
    /// `*IDN?`: identification string.
    IdnQ,
    /// `#5` (0x05): bitmap of axes in motion.
    MotionStatus,
    /// `#7` (0x07): controller ready (0xB1) or busy (0xB0).
    Ready,
}

impl Command {
    /// The mnemonic as documented by PI (`MOV`, `POS?`, `#5`…).
    pub fn mnemonic(&self) -> &'static str {
        match self {
            Self::Mov(_) => "MOV",
            Self::Mvr(_) => "MVR",
            Self::Svo(_) => "SVO",
            Self::Frf(_) => "FRF",
            Self::Stp => "STP",
            Self::StopAll => "#24",
            Self::PosQ(_) => "POS?",
            Self::OntQ(_) => "ONT?",
            Self::SvoQ(_) => "SVO?",
            Self::FrfQ(_) => "FRF?",
            Self::TmnQ(_) => "TMN?",
            Self::TmxQ(_) => "TMX?",
            Self::ErrQ => "ERR?",
            Self::IdnQ => "*IDN?",
            Self::MotionStatus => "#5",
            Self::Ready => "#7",
        }
    }

    /// Whether the controller answers this command (queries do, commands do not).
    pub fn expects_reply(&self) -> bool {
        matches!(
            self,
            Self::PosQ(_)
                | Self::OntQ(_)
                | Self::SvoQ(_)
                | Self::FrfQ(_)
                | Self::TmnQ(_)
                | Self::TmxQ(_)
                | Self::ErrQ
                | Self::IdnQ
                | Self::MotionStatus
                | Self::Ready
        )
    }

    /// Whether the command starts motion; such commands must never be re-sent blindly.
    pub fn starts_motion(&self) -> bool {
        matches!(self, Self::Mov(_) | Self::Mvr(_) | Self::Frf(_))
    }

    /// The bytes sent on the wire, terminator included.
    pub fn to_bytes(&self) -> Vec<u8> {
        match self {
            Self::MotionStatus => vec![BYTE_MOTION_STATUS],
            Self::Ready => vec![BYTE_READY],
            Self::StopAll => vec![BYTE_STOP_ALL],
            _ => {
                let mut line = self.to_string().into_bytes();
                line.push(b'\n');
                line
            }
        }
    }

    /// Server side: the command in one framed input, or the error code a
    /// controller sets for it. `known_axes` are the controller's axes; naming any
    /// other sets [`GcsErrorCode::INVALID_AXIS_IDENTIFIER`].
    pub fn parse_incoming(
        incoming: &Incoming,
        known_axes: &[AxisId],
    ) -> Result<Self, GcsErrorCode> {
        match incoming {
            Incoming::Single(BYTE_MOTION_STATUS) => Ok(Self::MotionStatus),
            Incoming::Single(BYTE_READY) => Ok(Self::Ready),
            Incoming::Single(BYTE_STOP_ALL) => Ok(Self::StopAll),
            Incoming::Single(_) => Err(GcsErrorCode::UNKNOWN_COMMAND),
            Incoming::Line(line) => Self::parse_line(line, known_axes),
        }
    }

    /// Server side: parses one command line (without its LF).
    pub fn parse_line(line: &[u8], known_axes: &[AxisId]) -> Result<Self, GcsErrorCode> {
        if line.len() > MAX_COMMAND_LEN {
            return Err(GcsErrorCode::COMMAND_TOO_LONG);
        }
        let text = std::str::from_utf8(line).map_err(|_| GcsErrorCode::PARAM_SYNTAX)?;
        let mut tokens = text.split_ascii_whitespace();
        let Some(mnemonic) = tokens.next() else {
            return Err(GcsErrorCode::UNKNOWN_COMMAND);
        };
        let args: Vec<&str> = tokens.collect();
        let axes = |args: &[&str]| parse_axes(args, known_axes);
        let command = match mnemonic {
            "MOV" => Self::Mov(parse_pairs(&args, known_axes, parse_real)?),
            "MVR" => Self::Mvr(parse_pairs(&args, known_axes, parse_real)?),
            "SVO" => Self::Svo(parse_pairs(&args, known_axes, parse_flag)?),
            "FRF" => Self::Frf(axes(&args)?),
            "POS?" => Self::PosQ(axes(&args)?),
            "ONT?" => Self::OntQ(axes(&args)?),
            "SVO?" => Self::SvoQ(axes(&args)?),
            "FRF?" => Self::FrfQ(axes(&args)?),
            "TMN?" => Self::TmnQ(axes(&args)?),
            "TMX?" => Self::TmxQ(axes(&args)?),
            "STP" | "ERR?" | "*IDN?" => {
                if !args.is_empty() {
                    return Err(GcsErrorCode::PARAM_SYNTAX);
                }
                match mnemonic {
                    "STP" => Self::Stp,
                    "ERR?" => Self::ErrQ,
                    _ => Self::IdnQ,
                }
            }
            _ => return Err(GcsErrorCode::UNKNOWN_COMMAND),
        };
        Ok(command)
    }

    /// The axes this command names (empty for "all axes" or axis-less commands).
    pub fn axes(&self) -> Vec<&AxisId> {
        match self {
            Self::Mov(p) | Self::Mvr(p) => p.iter().map(|(a, _)| a).collect(),
            Self::Svo(p) => p.iter().map(|(a, _)| a).collect(),
            Self::Frf(a)
            | Self::PosQ(a)
            | Self::OntQ(a)
            | Self::SvoQ(a)
            | Self::FrfQ(a)
            | Self::TmnQ(a)
            | Self::TmxQ(a) => a.iter().collect(),
            Self::Stp
            | Self::StopAll
            | Self::ErrQ
            | Self::IdnQ
            | Self::MotionStatus
            | Self::Ready => Vec::new(),
        }
    }
}

/// The printable form: the line without its LF, or `#5`/`#7`/`#24` for single bytes.
impl fmt::Display for Command {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.mnemonic())?;
        match self {
            Self::Mov(pairs) | Self::Mvr(pairs) => {
                for (axis, value) in pairs {
                    write!(f, " {axis} {}", Real(*value))?;
                }
            }
            Self::Svo(pairs) => {
                for (axis, on) in pairs {
                    write!(f, " {axis} {}", u8::from(*on))?;
                }
            }
            Self::Frf(axes)
            | Self::PosQ(axes)
            | Self::OntQ(axes)
            | Self::SvoQ(axes)
            | Self::FrfQ(axes)
            | Self::TmnQ(axes)
            | Self::TmxQ(axes) => {
                for axis in axes {
                    write!(f, " {axis}")?;
                }
            }
            Self::Stp
            | Self::StopAll
            | Self::ErrQ
            | Self::IdnQ
            | Self::MotionStatus
            | Self::Ready => {}
        }
        Ok(())
    }
}

fn parse_axis(token: &str, known_axes: &[AxisId]) -> Result<AxisId, GcsErrorCode> {
    let axis = AxisId::new(token).map_err(|_| GcsErrorCode::INVALID_AXIS_IDENTIFIER)?;
    if known_axes.contains(&axis) {
        Ok(axis)
    } else {
        Err(GcsErrorCode::INVALID_AXIS_IDENTIFIER)
    }
}

fn reject_double(axes: &[&AxisId]) -> Result<(), GcsErrorCode> {
    for (i, a) in axes.iter().enumerate() {
        if axes[..i].contains(a) {
            return Err(GcsErrorCode::DOUBLE_AXIS);
        }
    }
    Ok(())
}

fn parse_axes(args: &[&str], known_axes: &[AxisId]) -> Result<Vec<AxisId>, GcsErrorCode> {
    let axes = args
        .iter()
        .map(|t| parse_axis(t, known_axes))
        .collect::<Result<Vec<_>, _>>()?;
    reject_double(&axes.iter().collect::<Vec<_>>())?;
    Ok(axes)
}

fn parse_pairs<T>(
    args: &[&str],
    known_axes: &[AxisId],
    value: fn(&str) -> Result<T, GcsErrorCode>,
) -> Result<Vec<(AxisId, T)>, GcsErrorCode> {
    if args.is_empty() || !args.len().is_multiple_of(2) {
        return Err(GcsErrorCode::PARAM_SYNTAX);
    }
    let pairs = args
        .chunks_exact(2)
        .map(|pair| Ok((parse_axis(pair[0], known_axes)?, value(pair[1])?)))
        .collect::<Result<Vec<_>, GcsErrorCode>>()?;
    reject_double(&pairs.iter().map(|(a, _)| a).collect::<Vec<_>>())?;
    Ok(pairs)
}

/// A position as sent: fixed point with nine decimals (1 pm on a mm axis,
/// 1e-9° on a tilt axis, far below any controller's resolution), trailing
/// zeros dropped, never an exponent. Computed targets such as
/// `-0.08000000000000002` are sent as `-0.08`, so the line a user reads in the
/// record is the one the controller's resolution sees.
struct Real(f64);

impl fmt::Display for Real {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = format!("{:.9}", self.0);
        let s = s.trim_end_matches('0').trim_end_matches('.');
        f.write_str(if s == "-0" { "0" } else { s })
    }
}

fn parse_real(token: &str) -> Result<f64, GcsErrorCode> {
    // Rust also accepts "inf" and "NaN", which no controller does.
    let looks_numeric = token
        .bytes()
        .all(|b| b.is_ascii_digit() || matches!(b, b'+' | b'-' | b'.' | b'e' | b'E'));
    match token.parse::<f64>() {
        Ok(v) if looks_numeric && v.is_finite() => Ok(v),
        _ => Err(GcsErrorCode::PARAM_SYNTAX),
    }
}

fn parse_flag(token: &str) -> Result<bool, GcsErrorCode> {
    match token {
        "0" => Ok(false),
        "1" => Ok(true),
        _ => Err(GcsErrorCode::PARAM_SYNTAX),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn axes() -> Vec<AxisId> {
        AxisId::list(&["X", "Y", "T"]).unwrap()
    }

    fn ax(s: &str) -> AxisId {
        AxisId::new(s).unwrap()
    }

    #[test]
    fn encodes_the_documented_wire_form() {
        assert_eq!(
            Command::Mov(vec![(ax("1"), 12.5)]).to_bytes(),
            b"MOV 1 12.5\n"
        );
        assert_eq!(
            Command::Mov(vec![(ax("X"), -3.0), (ax("T"), 7.25)]).to_bytes(),
            b"MOV X -3 T 7.25\n"
        );
        assert_eq!(
            Command::PosQ(vec![ax("1"), ax("2")]).to_bytes(),
            b"POS? 1 2\n"
        );
        assert_eq!(Command::PosQ(vec![]).to_bytes(), b"POS?\n");
        assert_eq!(Command::Svo(vec![(ax("1"), true)]).to_bytes(), b"SVO 1 1\n");
        assert_eq!(Command::Frf(vec![ax("1")]).to_bytes(), b"FRF 1\n");
        assert_eq!(Command::Stp.to_bytes(), b"STP\n");
        assert_eq!(Command::ErrQ.to_bytes(), b"ERR?\n");
        assert_eq!(Command::IdnQ.to_bytes(), b"*IDN?\n");
        assert_eq!(Command::MotionStatus.to_bytes(), [0x05]);
        assert_eq!(Command::Ready.to_bytes(), [0x07]);
        assert_eq!(Command::StopAll.to_bytes(), [0x18]);
    }

    #[test]
    fn tiny_and_large_values_are_sent_without_exponent() {
        let line = Command::Mov(vec![(ax("X"), 1e-7), (ax("Y"), 1e7)]).to_string();
        assert_eq!(line, "MOV X 0.0000001 Y 10000000");
    }

    #[test]
    fn computed_targets_are_sent_to_nine_decimals() {
        let line = Command::Mov(vec![
            (ax("X"), -0.08000000000000002),
            (ax("Y"), -1e-12),
            (ax("T"), 2.0 / 3.0),
        ])
        .to_string();
        assert_eq!(line, "MOV X -0.08 Y 0 T 0.666666667");
        let line = Command::Mvr(vec![(ax("T"), 1.0)]).to_string();
        assert_eq!(line, "MVR T 1");
    }

    #[test]
    fn every_command_round_trips_through_the_server_parser() {
        let cmds = vec![
            Command::Mov(vec![(ax("X"), 100.25), (ax("T"), -4.5)]),
            Command::Mvr(vec![(ax("Y"), -0.001)]),
            Command::Svo(vec![(ax("X"), true), (ax("Y"), false)]),
            Command::Frf(vec![]),
            Command::Frf(vec![ax("T")]),
            Command::Stp,
            Command::StopAll,
            Command::PosQ(vec![ax("X"), ax("Y"), ax("T")]),
            Command::OntQ(vec![ax("T")]),
            Command::SvoQ(vec![]),
            Command::FrfQ(vec![ax("X")]),
            Command::TmnQ(vec![ax("T")]),
            Command::TmxQ(vec![]),
            Command::ErrQ,
            Command::IdnQ,
            Command::MotionStatus,
            Command::Ready,
        ];
        for cmd in cmds {
            let bytes = cmd.to_bytes();
            let incoming = match bytes.as_slice() {
                [single] => Incoming::Single(*single),
                [line @ .., b'\n'] => Incoming::Line(line.to_vec()),
                other => panic!("unterminated {other:?}"),
            };
            assert_eq!(Command::parse_incoming(&incoming, &axes()), Ok(cmd));
        }
    }

    #[test]
    fn malformed_lines_give_the_controller_error_codes() {
        let cases: &[(&str, GcsErrorCode)] = &[
            ("FOO 1", GcsErrorCode::UNKNOWN_COMMAND),
            ("mov X 1", GcsErrorCode::UNKNOWN_COMMAND),
            ("MOV", GcsErrorCode::PARAM_SYNTAX),
            ("MOV X", GcsErrorCode::PARAM_SYNTAX),
            ("MOV X abc", GcsErrorCode::PARAM_SYNTAX),
            ("MOV X inf", GcsErrorCode::PARAM_SYNTAX),
            ("MOV X NaN", GcsErrorCode::PARAM_SYNTAX),
            ("MOV Q 1", GcsErrorCode::INVALID_AXIS_IDENTIFIER),
            ("MOV x 1", GcsErrorCode::INVALID_AXIS_IDENTIFIER),
            ("MOV X 1 X 2", GcsErrorCode::DOUBLE_AXIS),
            ("POS? Q", GcsErrorCode::INVALID_AXIS_IDENTIFIER),
            ("POS? X=", GcsErrorCode::INVALID_AXIS_IDENTIFIER),
            ("SVO X 2", GcsErrorCode::PARAM_SYNTAX),
            ("ERR? X", GcsErrorCode::PARAM_SYNTAX),
            ("STP now", GcsErrorCode::PARAM_SYNTAX),
            ("", GcsErrorCode::UNKNOWN_COMMAND),
        ];
        for (line, code) in cases {
            assert_eq!(
                Command::parse_line(line.as_bytes(), &axes()),
                Err(*code),
                "line {line:?}"
            );
        }
        assert_eq!(
            Command::parse_line(&[b'A'; MAX_COMMAND_LEN + 1], &axes()),
            Err(GcsErrorCode::COMMAND_TOO_LONG)
        );
        assert_eq!(
            Command::parse_line(b"MOV X \xff", &axes()),
            Err(GcsErrorCode::PARAM_SYNTAX)
        );
        assert_eq!(
            Command::parse_incoming(&Incoming::Single(0x06), &axes()),
            Err(GcsErrorCode::UNKNOWN_COMMAND)
        );
    }

    #[test]
    fn tolerates_repeated_spaces_and_tabs() {
        assert_eq!(
            Command::parse_line(b"MOV  X\t1.5 ", &axes()),
            Ok(Command::Mov(vec![(ax("X"), 1.5)]))
        );
    }

    #[test]
    fn classifies_commands() {
        assert!(Command::Mov(vec![]).starts_motion());
        assert!(Command::Frf(vec![]).starts_motion());
        assert!(!Command::PosQ(vec![]).starts_motion());
        assert!(!Command::Stp.expects_reply());
        assert!(Command::Ready.expects_reply());
        assert!(!Command::Svo(vec![]).expects_reply());
    }
}
