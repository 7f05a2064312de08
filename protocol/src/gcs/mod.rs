//! PI GCS 2.0 stage protocol subset (sans-IO).
//!
//! GCS ("General Command Set") is the ASCII command language of Physik Instrumente
//! (PI) motion controllers, and a common language of microscope stages. This module
//! holds both sides of the link as typed values and byte parsers that do no I/O:
//!
//! - client side (the `sdsem` stage driver): [`Command::to_bytes`], the typed
//!   [`Query`] values with their reply parsers, and the incremental [`ReplyFramer`];
//! - server side (the simulator): the incremental [`CommandFramer`],
//!   [`Command::parse_incoming`] which yields the [`GcsErrorCode`] a real controller
//!   would set, and the [`Reply`] formatters.
//!
//! # Wire format (the facts this module relies on)
//!
//! - A command is one ASCII line ended by LF: a mnemonic, then arguments separated
//!   by spaces: `MOV 1 12.5`, `POS? 1 2`, `ERR?`. Axis identifiers are configurable
//!   names (`1`, `2`, `3` on many stages; `X`, `Y`, `T` in the simulator).
//! - Commands (`MOV`, `MVR`, `SVO`, `FRF`, `STP`) never answer. A client learns
//!   whether one was accepted by asking `ERR?`, which answers the code of the last
//!   error and resets it to 0 (only the last error is kept).
//! - Queries answer one or more lines. Every line except the last ends with
//!   `" \n"` (space, LF); the last ends with a bare `"\n"`:
//!   `POS? 1 2` → `"1=12.500000 \n2=3.000000\n"`.
//! - A query that the controller rejects (unknown axis, bad syntax) does not
//!   answer at all; it only sets the error code.
//! - Two single-byte queries are answered at once, even mid-motion: `#5` (0x05)
//!   answers the "axes in motion" bitmap as a hexadecimal number (bit *i* = the
//!   *i*-th axis of the controller); `#7` (0x07) answers 0xB1 when the controller
//!   is ready and 0xB0 while it is busy (for example referencing). `#24` (0x18)
//!   stops all axes like `STP`.
//!
//! Error codes are those of PI's controller error list (`PI_CNTR_*`), see
//! [`GcsErrorCode`].

mod axis;
mod command;
mod error_code;
mod framer;
mod query;
mod reply;

pub use axis::{AxisId, AxisIdError};
pub use command::{Command, MAX_COMMAND_LEN};
pub use error_code::GcsErrorCode;
pub use framer::{
    CommandFramer, FrameError, Incoming, MAX_REPLY_LINE_LEN, MAX_REPLY_LINES, ReplyFramer,
};
pub use query::{
    ErrorQuery, IdentityQuery, MaxLimitQuery, MinLimitQuery, MotionStatus, MotionStatusQuery,
    OnTargetQuery, PositionQuery, Query, ReadyQuery, ReferencedQuery, ServoQuery,
};
pub use reply::{Reply, ReplyError, escape_bytes};
