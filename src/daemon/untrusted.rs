//! Reading files that others may have placed: a job file given to `sdsem submit`, every
//! entry of the spool. Opened without blocking (`O_NONBLOCK`: a FIFO or a device never
//! hangs the reader) and, for spool entries, without following a link (`O_NOFOLLOW`); then
//! `fstat` must say "regular file" of at most a cap, and no more than the cap is ever read.

use std::fs::File;
use std::io::{self, Read};
use std::os::fd::{AsFd, BorrowedFd};
use std::path::Path;

use rustix::fs::{FileType, Mode, OFlags};

/// Why a file from outside was not read.
#[derive(Debug, thiserror::Error)]
pub enum UntrustedError {
    #[error("cannot open it: {0}")]
    Open(io::Error),
    #[error("it is a symbolic link, which is never followed")]
    Link,
    #[error("it is {0}, not a regular file")]
    NotRegular(&'static str),
    #[error("it is larger than {cap} bytes")]
    TooLarge { cap: u64 },
    #[error("cannot read it: {0}")]
    Read(io::Error),
}

impl UntrustedError {
    /// True when the file is simply not there (moved on between listing and reading).
    #[must_use]
    pub fn is_not_found(&self) -> bool {
        matches!(self, Self::Open(e) if e.kind() == io::ErrorKind::NotFound)
    }
}

/// Whether the last component of the path may be a link to follow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Links {
    /// A path the user gave on the command line.
    Follow,
    /// An entry in a directory others can write (the spool).
    Refuse,
}

/// Reads at most `cap` bytes of the regular file at `path`, never blocking on it.
///
/// # Errors
/// [`UntrustedError`] saying what the entry is instead, or why it could not be read.
pub fn read_capped(path: &Path, links: Links, cap: u64) -> Result<Vec<u8>, UntrustedError> {
    read_capped_at(rustix::fs::CWD, path, links, cap).map(|c| c.bytes)
}

/// What [`read_capped_at`] read, and who owns the file.
#[derive(Debug)]
pub struct Capped {
    pub bytes: Vec<u8>,
    /// The file owner's user id.
    pub owner: u32,
}

/// [`read_capped`] of `path` relative to the open directory `dir`.
///
/// # Errors
/// As [`read_capped`].
pub fn read_capped_at(
    dir: BorrowedFd<'_>,
    path: &Path,
    links: Links,
    cap: u64,
) -> Result<Capped, UntrustedError> {
    let mut flags = OFlags::RDONLY | OFlags::NONBLOCK | OFlags::CLOEXEC | OFlags::NOCTTY;
    if links == Links::Refuse {
        flags |= OFlags::NOFOLLOW;
    }
    let fd = match rustix::fs::openat(dir, path, flags, Mode::empty()) {
        Ok(fd) => fd,
        Err(rustix::io::Errno::LOOP) if links == Links::Refuse => return Err(UntrustedError::Link),
        Err(e) => return Err(UntrustedError::Open(e.into())),
    };
    let owner = check_regular(fd.as_fd(), cap)?;
    let mut bytes = Vec::new();
    File::from(fd)
        .take(cap + 1)
        .read_to_end(&mut bytes)
        .map_err(UntrustedError::Read)?;
    if bytes.len() as u64 > cap {
        return Err(UntrustedError::TooLarge { cap });
    }
    Ok(Capped { bytes, owner })
}

/// `fstat` of an open file: a regular file of at most `cap` bytes (its owner's id), or the
/// reason why not.
fn check_regular(fd: BorrowedFd<'_>, cap: u64) -> Result<u32, UntrustedError> {
    let stat = rustix::fs::fstat(fd).map_err(|e| UntrustedError::Open(e.into()))?;
    let kind = match FileType::from_raw_mode(stat.st_mode) {
        FileType::RegularFile => {
            return if u64::try_from(stat.st_size).unwrap_or(u64::MAX) > cap {
                Err(UntrustedError::TooLarge { cap })
            } else {
                Ok(stat.st_uid)
            };
        }
        FileType::Directory => "a directory",
        FileType::Fifo => "a FIFO",
        FileType::CharacterDevice => "a character device",
        FileType::BlockDevice => "a block device",
        FileType::Socket => "a socket",
        FileType::Symlink => return Err(UntrustedError::Link),
        FileType::Unknown => "of an unknown type",
    };
    Err(UntrustedError::NotRegular(kind))
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, Instant};

    use super::*;

    #[test]
    fn special_files_links_and_large_files_are_refused_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("fifo");
        rustix::fs::mknodat(
            rustix::fs::CWD,
            &fifo,
            FileType::Fifo,
            Mode::from_raw_mode(0o644),
            0,
        )
        .unwrap();
        let link = dir.path().join("zero");
        std::os::unix::fs::symlink("/dev/zero", &link).unwrap();
        let big = dir.path().join("big");
        std::fs::write(&big, vec![b' '; 5000]).unwrap();
        let small = dir.path().join("small");
        std::fs::write(&small, b"{}").unwrap();

        let t0 = Instant::now();
        let refuse = |p: &Path| read_capped(p, Links::Refuse, 4096).unwrap_err().to_string();
        assert_eq!(refuse(&fifo), "it is a FIFO, not a regular file");
        assert_eq!(
            refuse(&link),
            "it is a symbolic link, which is never followed"
        );
        assert_eq!(refuse(dir.path()), "it is a directory, not a regular file");
        assert_eq!(refuse(&big), "it is larger than 4096 bytes");
        assert!(refuse(&dir.path().join("none")).starts_with("cannot open it: "));
        // A link given on the command line is followed, and /dev/zero is still refused.
        let err = read_capped(&link, Links::Follow, 4096).unwrap_err();
        assert_eq!(
            err.to_string(),
            "it is a character device, not a regular file"
        );
        let err = read_capped(Path::new("/dev/zero"), Links::Follow, 4096).unwrap_err();
        assert!(matches!(err, UntrustedError::NotRegular(_)));
        assert!(t0.elapsed() < Duration::from_secs(2), "{:?}", t0.elapsed());
        assert_eq!(read_capped(&small, Links::Refuse, 4096).unwrap(), b"{}");
    }
}
