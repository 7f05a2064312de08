//! GCS controller error codes.

use std::fmt;

use serde::{Deserialize, Serialize};

/// An error code as answered by `ERR?` (0 = no error).
///
/// The named constants are PI's controller error list (`PI_CNTR_*` in PI's GCS
/// headers and manuals); only the ones this project meets are named, any other
/// code still round-trips.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(transparent)]
pub struct GcsErrorCode(pub i32);

impl GcsErrorCode {
    /// 0: no error.
    pub const NO_ERROR: Self = Self(0);
    /// 1: parameter syntax error.
    pub const PARAM_SYNTAX: Self = Self(1);
    /// 2: unknown command.
    pub const UNKNOWN_COMMAND: Self = Self(2);
    /// 3: command length out of limits or command buffer overrun.
    pub const COMMAND_TOO_LONG: Self = Self(3);
    /// 5: unallowable move attempted on an unreferenced axis, or move attempted with servo off.
    pub const MOVE_WITHOUT_REF_OR_NO_SERVO: Self = Self(5);
    /// 7: position out of limits.
    pub const POS_OUT_OF_LIMITS: Self = Self(7);
    /// 10: controller was stopped by command (`STP`, `#24`).
    pub const STOPPED: Self = Self(10);
    /// 15: invalid axis identifier.
    pub const INVALID_AXIS_IDENTIFIER: Self = Self(15);
    /// 17: parameter out of range.
    pub const PARAM_OUT_OF_RANGE: Self = Self(17);
    /// 22: axis identifier specified more than once.
    pub const DOUBLE_AXIS: Self = Self(22);
    /// 1024: motion error: position error too large, servo switched off automatically.
    pub const MOTION_ERROR: Self = Self(1024);

    /// Whether this code reports an error.
    pub fn is_error(self) -> bool {
        self.0 != 0
    }

    /// PI's one-line description of the code.
    pub fn description(self) -> &'static str {
        match self.0 {
            0 => "no error",
            1 => "parameter syntax error",
            2 => "unknown command",
            3 => "command length out of limits or command buffer overrun",
            5 => {
                "unallowable move attempted on unreferenced axis, or move attempted with servo off"
            }
            7 => "position out of limits",
            10 => "controller was stopped by command",
            15 => "invalid axis identifier",
            17 => "parameter out of range",
            22 => "axis identifier specified more than once",
            1024 => "motion error: position error too large, servo is switched off automatically",
            _ => "controller error (see the controller's error list)",
        }
    }
}

impl fmt::Display for GcsErrorCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({})", self.0, self.description())
    }
}
