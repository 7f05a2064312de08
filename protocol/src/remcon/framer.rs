//! Server side: cuts the client's byte stream into request lines.

use super::command::MAX_COMMAND_LEN;

/// A request line longer than [`MAX_COMMAND_LEN`]: answered `@` then `*617`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("request longer than {limit} bytes")]
pub struct LineTooLong {
    /// The limit, bytes.
    pub limit: usize,
}

/// Cuts request lines at CR, LF or CR LF (a LF right after a CR belongs to
/// it). An empty line is the null command and is yielded as such. An overlong
/// line gives [`LineTooLong`] once and is skipped up to its terminator.
#[derive(Debug)]
pub struct CommandFramer {
    line: Vec<u8>,
    after_cr: bool,
    discarding: bool,
    max_len: usize,
}

impl Default for CommandFramer {
    fn default() -> Self {
        Self::new()
    }
}

impl CommandFramer {
    /// A framer accepting lines up to [`MAX_COMMAND_LEN`] bytes.
    pub fn new() -> Self {
        Self {
            line: Vec::new(),
            after_cr: false,
            discarding: false,
            max_len: MAX_COMMAND_LEN,
        }
    }

    /// Feeds one byte; returns a line (terminator removed) or an error when
    /// this byte completes one.
    pub fn push(&mut self, byte: u8) -> Option<Result<Vec<u8>, LineTooLong>> {
        let after_cr = std::mem::replace(&mut self.after_cr, byte == b'\r');
        match byte {
            b'\n' if after_cr => None,
            b'\r' | b'\n' => {
                if std::mem::take(&mut self.discarding) {
                    return None;
                }
                Some(Ok(std::mem::take(&mut self.line)))
            }
            _ if self.discarding => None,
            _ if self.line.len() >= self.max_len => {
                self.line.clear();
                self.discarding = true;
                Some(Err(LineTooLong {
                    limit: self.max_len,
                }))
            }
            _ => {
                self.line.push(byte);
                None
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bytewise(bytes: &[u8]) -> Vec<Result<Vec<u8>, LineTooLong>> {
        let mut f = CommandFramer::new();
        bytes.iter().filter_map(|&b| f.push(b)).collect()
    }

    #[test]
    fn cr_lf_and_crlf_each_end_one_line() {
        let ok = |s: &str| Ok(s.as_bytes().to_vec());
        assert_eq!(bytewise(b"VER?\r"), [ok("VER?")]);
        assert_eq!(bytewise(b"VER?\n"), [ok("VER?")]);
        assert_eq!(bytewise(b"VER?\r\nC95?\r\n"), [ok("VER?"), ok("C95?")]);
        // The null command, alone or between requests, in each form.
        assert_eq!(bytewise(b"\r"), [ok("")]);
        assert_eq!(bytewise(b"\r\n\r\nABO\n"), [ok(""), ok(""), ok("ABO")]);
        assert_eq!(bytewise(b"\n\n"), [ok(""), ok("")]);
    }

    #[test]
    fn an_overlong_line_is_one_error_then_framing_resumes() {
        let mut wire = vec![b'C'; MAX_COMMAND_LEN + 50];
        wire.extend_from_slice(b"\r\nPHN?\r");
        assert_eq!(
            bytewise(&wire),
            [
                Err(LineTooLong {
                    limit: MAX_COMMAND_LEN
                }),
                Ok(b"PHN?".to_vec())
            ]
        );
        let mut exact = vec![b'C'; MAX_COMMAND_LEN];
        exact.push(b'\r');
        assert_eq!(bytewise(&exact), [Ok(vec![b'C'; MAX_COMMAND_LEN])]);
    }
}
