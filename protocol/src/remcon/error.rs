//! RemCon32 error numbers, as the status line `*NNN` reports them.

use std::fmt;

/// An error number of a `*NNN` status line. The named ones are the manual's
/// table as quoted by [OD-Z] and [SF] (VENDORS §1.2); any other number still
/// round-trips as [`RemconError::Other`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RemconError {
    /// 600: unknown command.
    UnknownCommand,
    /// 601: invalid number of parameters.
    InvalidParameterCount,
    /// 602: invalid parameter type.
    InvalidParameterType,
    /// 603: parameter out of range.
    ParameterOutOfRange,
    /// 604: command timeout.
    CommandTimeout,
    /// 605: catastrophic error, reboot system.
    Catastrophic,
    /// 611: unexpected external-control abort.
    ExternalControlAbort,
    /// 613: parameter unattainable.
    ParameterUnattainable,
    /// 614: option not fitted.
    OptionNotFitted,
    /// 615: cannot change that parameter.
    CannotChangeParameter,
    /// 616: cannot execute that command.
    CannotExecute,
    /// 617: command exceeded the maximum length.
    CommandTooLong,
    /// A number outside the documented table.
    Other(u16),
}

impl RemconError {
    /// Every named error, in number order.
    pub const NAMED: [Self; 12] = [
        Self::UnknownCommand,
        Self::InvalidParameterCount,
        Self::InvalidParameterType,
        Self::ParameterOutOfRange,
        Self::CommandTimeout,
        Self::Catastrophic,
        Self::ExternalControlAbort,
        Self::ParameterUnattainable,
        Self::OptionNotFitted,
        Self::CannotChangeParameter,
        Self::CannotExecute,
        Self::CommandTooLong,
    ];

    /// The error of a number.
    pub fn from_number(n: u16) -> Self {
        Self::NAMED
            .into_iter()
            .find(|e| e.number() == n)
            .unwrap_or(Self::Other(n))
    }

    /// The number on the wire.
    pub fn number(self) -> u16 {
        match self {
            Self::UnknownCommand => 600,
            Self::InvalidParameterCount => 601,
            Self::InvalidParameterType => 602,
            Self::ParameterOutOfRange => 603,
            Self::CommandTimeout => 604,
            Self::Catastrophic => 605,
            Self::ExternalControlAbort => 611,
            Self::ParameterUnattainable => 613,
            Self::OptionNotFitted => 614,
            Self::CannotChangeParameter => 615,
            Self::CannotExecute => 616,
            Self::CommandTooLong => 617,
            Self::Other(n) => n,
        }
    }

    /// The manual's text for the number.
    pub fn text(self) -> &'static str {
        match self {
            Self::UnknownCommand => "unknown command",
            Self::InvalidParameterCount => "invalid number of parameters",
            Self::InvalidParameterType => "invalid parameter type",
            Self::ParameterOutOfRange => "parameter out of range",
            Self::CommandTimeout => "command timeout",
            Self::Catastrophic => "catastrophic error, reboot system",
            Self::ExternalControlAbort => "unexpected external-control abort",
            Self::ParameterUnattainable => "parameter unattainable",
            Self::OptionNotFitted => "option not fitted",
            Self::CannotChangeParameter => "cannot change that parameter",
            Self::CannotExecute => "cannot execute that command",
            Self::CommandTooLong => "command exceeded the maximum length",
            Self::Other(_) => "not in the RemCon32 error table",
        }
    }
}

impl fmt::Display for RemconError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({})", self.number(), self.text())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_round_trip_and_name_their_text() {
        for e in RemconError::NAMED {
            assert_eq!(RemconError::from_number(e.number()), e);
        }
        assert_eq!(
            RemconError::from_number(603).to_string(),
            "603 (parameter out of range)"
        );
        assert_eq!(RemconError::from_number(612), RemconError::Other(612));
        assert_eq!(RemconError::Other(612).number(), 612);
    }
}
