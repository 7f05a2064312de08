//! Zeiss SmartSEM "RemCon32" remote control (sans-IO): both sides of the
//! RS-232 link as typed values and byte parsers that do no I/O.
//!
//! - client side (the `sdsem` RemCon32 stage backend): [`Command::to_bytes`],
//!   [`encode_line`] for configured raw lines, the incremental [`ReplyFramer`],
//!   and the data parsers ([`StageReading`], [`StageInit`], [`parse_number`]);
//! - server side (the simulator): [`CommandFramer`], [`Command::parse`] with the
//!   answer a RemCon32 gives to a bad line ([`ParseError::reply`]), and the
//!   [`Reply`] and data formatters.
//!
//! # Wire format (VENDORS §1; source keys in brackets)
//!
//! - 9600 baud, 8N1, no flow control [SF, SF-old, ML]. No TCP variant is known.
//! - A request is a command word, arguments separated by single spaces, and CR
//!   (LF optional) [OD-Z, SF, ML]. Queries end in `?`. An empty line is the null
//!   command, a harmless probe [OD-Z, ML].
//! - A reply is two lines ending in CR LF: `@` (accepted) or `#` (invalid) at
//!   once, then `>data` (done) or `*NNN` / `* NNN` (failed, [`RemconError`])
//!   when the command has finished. No second line follows `#` in [OD-Z] (⚠).
//! - Stage: `C95?` → `x y z t r m moving` (mm, mm, mm, °, °, mm, `1.0` moving);
//!   `C95 x y z t r m` moves every axis (tilt BEFORE rotation) and returns before
//!   the move ends; to move one axis, read `C95?` and re-send the others
//!   unchanged [2+]. The moving flag may be set late: wait ~1 s before the first
//!   poll [OD-Z]. `ABO` stops a move.

mod command;
mod data;
mod error;
mod framer;
mod reply;

pub use command::{
    Command, LineError, MAX_COMMAND_LEN, ParseError, StageTarget, TERMINATOR, encode_line,
};
pub use data::{DataError, StageInit, StageReading, parse_count, parse_number};
pub use error::RemconError;
pub use framer::{CommandFramer, LineTooLong};
pub use reply::{FrameError, MAX_REPLY_LINE_LEN, Reply, ReplyFramer};
