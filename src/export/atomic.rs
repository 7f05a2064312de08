//! The one atomic file writer of sdsem: a temporary file created exclusively in the target's
//! directory (`O_CREAT|O_EXCL|O_NOFOLLOW`: never through a link, never over another file),
//! filled, synced, renamed to the target, and the directory synced.
//!
//! A reader sees either the previous file or the complete new one — never a partial file that
//! looks valid. On failure the temporary file is removed. The rename replaces the target's
//! directory entry ([`Existing::Replace`]; a link there is replaced, not followed) or refuses
//! an existing one ([`Existing::Refuse`], `RENAME_NOREPLACE`), as for files that must be new.
//! Exports, micrographs, run directories and the daemon's spool all write through it.
//!
//! An export names its file by a path ([`Target::Path`]: the path's directory, an existing
//! file replaced) or by a name in an [`OutputDir`] opened once before any work, whose rule
//! for existing names ([`Existing`]) the command chose: `--force` replaces, otherwise and in
//! a run directory every file must be new.

use std::ffi::OsStr;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::os::fd::{AsFd, BorrowedFd, OwnedFd};
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use rustix::fs::{AtFlags, Mode, OFlags, RenameFlags};

use super::ExportError;

static COUNTER: AtomicU64 = AtomicU64::new(0);

/// What the writer does when the target name exists already.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Existing {
    /// Replace it (its directory entry: a link is replaced, not followed).
    Replace,
    /// Fail with `AlreadyExists` and leave it alone.
    Refuse,
}

/// Opens a directory to write in (following the links of the caller's own path).
///
/// # Errors
/// The system's error when `dir` is not a directory that can be opened.
pub fn open_dir(dir: &Path) -> io::Result<OwnedFd> {
    let dir = if dir.as_os_str().is_empty() {
        Path::new(".")
    } else {
        dir
    };
    Ok(rustix::fs::open(
        dir,
        OFlags::RDONLY | OFlags::DIRECTORY | OFlags::CLOEXEC,
        Mode::empty(),
    )?)
}

/// Creates `name` in `dir` exclusively and without following a link: a new, empty file.
/// `mode` is applied as given (whatever the umask) when set, else 0666 less the umask.
///
/// # Errors
/// `AlreadyExists` when anything (a file, a link, a directory) has that name; the system's error otherwise.
pub fn create_new_at(dir: BorrowedFd<'_>, name: &OsStr, mode: Option<u32>) -> io::Result<File> {
    check_single_component(name)?;
    let fd = rustix::fs::openat(
        dir,
        name,
        OFlags::WRONLY | OFlags::CREATE | OFlags::EXCL | OFlags::NOFOLLOW | OFlags::CLOEXEC,
        Mode::from_raw_mode(0o666),
    )?;
    if let Some(mode) = mode {
        rustix::fs::fchmod(&fd, Mode::from_raw_mode(mode))?;
    }
    Ok(File::from(fd))
}

/// The atomic write of `name` in the open directory `dir`: see the [module documentation](self).
///
/// # Errors
/// The system's error of the step that failed (the temporary file is removed), or the error
/// `write` returns; `AlreadyExists` for an existing target with [`Existing::Refuse`].
pub fn write_atomic_at<F>(
    dir: BorrowedFd<'_>,
    name: &OsStr,
    existing: Existing,
    mode: Option<u32>,
    write: F,
) -> io::Result<()>
where
    F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
{
    check_single_component(name)?;
    let mut tmp = b".".to_vec();
    tmp.extend_from_slice(name.as_bytes());
    tmp.extend_from_slice(
        format!(
            ".tmp-{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        )
        .as_bytes(),
    );
    let tmp = OsStr::from_bytes(&tmp);
    let file = create_new_at(dir, tmp, mode)?;
    let result = (|| {
        let mut out = BufWriter::with_capacity(1 << 20, file);
        write(&mut out)?;
        let file = out.into_inner().map_err(io::IntoInnerError::into_error)?;
        file.sync_all()?;
        drop(file);
        match existing {
            Existing::Replace => rustix::fs::renameat(dir, tmp, dir, name),
            Existing::Refuse => {
                rustix::fs::renameat_with(dir, tmp, dir, name, RenameFlags::NOREPLACE)
            }
        }
        .map_err(io::Error::from)
    })();
    if let Err(e) = result {
        let _ = rustix::fs::unlinkat(dir, tmp, AtFlags::empty());
        return Err(e);
    }
    // Make the rename itself durable.
    rustix::fs::fsync(dir)?;
    Ok(())
}

/// A name inside a directory: one path component.
fn check_single_component(name: &OsStr) -> io::Result<()> {
    let bytes = name.as_bytes();
    if bytes.is_empty() || bytes.contains(&b'/') || bytes == b"." || bytes == b".." {
        return Err(io::Error::new(
            io::ErrorKind::InvalidInput,
            format!("{name:?} is not a file name"),
        ));
    }
    Ok(())
}

/// [`write_atomic_at`] for a path: its directory is opened as the path says.
fn write_path<F>(path: &Path, existing: Existing, write: F) -> Result<(), ExportError>
where
    F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
{
    let to_error = |source: io::Error| ExportError::Write {
        path: path.to_path_buf(),
        source,
    };
    let name = path.file_name().ok_or_else(|| {
        to_error(io::Error::new(
            io::ErrorKind::InvalidInput,
            "the path names no file",
        ))
    })?;
    let dir = open_dir(path.parent().unwrap_or(Path::new("."))).map_err(to_error)?;
    write_atomic_at(dir.as_fd(), name, existing, None, write).map_err(to_error)
}

/// An open directory that outputs are written into, with its rule for names that exist.
#[derive(Debug)]
pub struct OutputDir {
    path: PathBuf,
    dir: OwnedFd,
    existing: Existing,
}

impl OutputDir {
    /// Opens the directory `path` (following the links of the caller's own path).
    ///
    /// # Errors
    /// The system's error when it is not a directory that can be opened.
    pub fn open(path: &Path, existing: Existing) -> io::Result<Self> {
        Ok(Self::from_fd(path.to_owned(), open_dir(path)?, existing))
    }

    /// The directory already open as `dir`, known as `path` in messages.
    #[must_use]
    pub fn from_fd(path: PathBuf, dir: OwnedFd, existing: Existing) -> Self {
        Self {
            path,
            dir,
            existing,
        }
    }

    /// A second handle on the same directory (e.g. for a worker thread).
    ///
    /// # Errors
    /// The system's error when the descriptor cannot be duplicated.
    pub fn try_clone(&self) -> io::Result<Self> {
        Ok(Self {
            path: self.path.clone(),
            dir: self.dir.try_clone()?,
            existing: self.existing,
        })
    }

    /// The directory's path, for messages.
    #[must_use]
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// What a write does to a name that exists.
    #[must_use]
    pub fn existing(&self) -> Existing {
        self.existing
    }

    /// The path of `name` in it, for messages and readers.
    #[must_use]
    pub fn join(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }

    /// The file `name` in it, as the target of an export.
    #[must_use]
    pub fn file<'a>(&'a self, name: &'a str) -> Target<'a> {
        Target::In { dir: self, name }
    }

    /// Whether anything (a file, a link, a directory) has the name `name` in it.
    ///
    /// # Errors
    /// The system's error other than "not found".
    pub fn holds(&self, name: &str) -> io::Result<bool> {
        check_single_component(OsStr::new(name))?;
        match rustix::fs::statat(&self.dir, name, AtFlags::SYMLINK_NOFOLLOW) {
            Ok(_) => Ok(true),
            Err(rustix::io::Errno::NOENT) => Ok(false),
            Err(e) => Err(e.into()),
        }
    }

    /// Creates and removes a file in it: proves that it can be written in now.
    ///
    /// # Errors
    /// The system's error of the creation (`PermissionDenied`, a read-only file system, …).
    pub fn probe(&self) -> io::Result<()> {
        let name = format!(
            ".sdsem-probe-{}-{}",
            std::process::id(),
            COUNTER.fetch_add(1, Ordering::Relaxed)
        );
        drop(create_new_at(self.dir.as_fd(), OsStr::new(&name), None)?);
        rustix::fs::unlinkat(&self.dir, name.as_str(), AtFlags::empty())?;
        Ok(())
    }

    /// Reads the file `name` back, never through a link.
    ///
    /// # Errors
    /// The system's error; a link at `name` fails (`ELOOP`).
    pub fn read(&self, name: &str) -> io::Result<Vec<u8>> {
        check_single_component(OsStr::new(name))?;
        let fd = rustix::fs::openat(
            &self.dir,
            name,
            OFlags::RDONLY | OFlags::NOFOLLOW | OFlags::CLOEXEC,
            Mode::empty(),
        )?;
        let mut bytes = Vec::new();
        io::Read::read_to_end(&mut File::from(fd), &mut bytes)?;
        Ok(bytes)
    }

    /// Removes the file `name` from it (what a failed command wrote); a missing one is no error.
    pub fn remove(&self, name: &str) {
        let _ = rustix::fs::unlinkat(&self.dir, name, AtFlags::empty());
    }

    /// Writes the file `name` atomically, under this directory's rule for an existing one.
    ///
    /// # Errors
    /// [`ExportError::Write`] naming the file; `AlreadyExists` as its cause when the rule is
    /// [`Existing::Refuse`] and something has that name.
    pub fn write<F>(&self, name: &str, write: F) -> Result<(), ExportError>
    where
        F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
    {
        write_atomic_at(
            self.dir.as_fd(),
            OsStr::new(name),
            self.existing,
            None,
            write,
        )
        .map_err(|source| ExportError::Write {
            path: self.join(name),
            source,
        })
    }
}

/// Bytes between two starts of the write-back by [`EarlyWriteback`].
const WRITEBACK_EVERY: usize = 8 << 20;

/// A large file's writer that starts the kernel's write-back of what is written every
/// [`WRITEBACK_EVERY`] bytes, without waiting for it: the disk works while the rest is
/// encoded, and the `fsync` before the rename waits for the last part only (the 50 MB mesh
/// of a 1280×960 map waited 30 ms, both cores idle). The bytes are those written through it.
pub struct EarlyWriteback<'a> {
    out: &'a mut BufWriter<File>,
    since: usize,
}

impl<'a> EarlyWriteback<'a> {
    #[must_use]
    pub fn new(out: &'a mut BufWriter<File>) -> Self {
        Self { out, since: 0 }
    }
}

impl Write for EarlyWriteback<'_> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.out.write(buf)?;
        self.since += n;
        if self.since >= WRITEBACK_EVERY {
            self.since = 0;
            self.out.flush()?;
            start_writeback(self.out.get_ref());
        }
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }
}

/// Starts writing `file`'s dirty pages to the disk, not waiting (`sync_file_range` with
/// `SYNC_FILE_RANGE_WRITE`); advisory: the `fsync` that follows is what makes the file durable.
fn start_writeback(file: &File) {
    #[cfg(target_os = "linux")]
    {
        use std::os::fd::AsRawFd;
        // SAFETY: a system call on a descriptor `file` keeps open; it touches no memory of ours.
        let _ =
            unsafe { libc::sync_file_range(file.as_raw_fd(), 0, 0, libc::SYNC_FILE_RANGE_WRITE) };
    }
    #[cfg(not(target_os = "linux"))]
    let _ = file;
}

/// Where an export writes its file.
#[derive(Debug, Clone, Copy)]
pub enum Target<'a> {
    /// A path: its directory is opened as the path says and an existing file is replaced.
    Path(&'a Path),
    /// A name in an open output directory, under that directory's rule.
    In { dir: &'a OutputDir, name: &'a str },
}

impl<'a> From<&'a Path> for Target<'a> {
    fn from(path: &'a Path) -> Self {
        Self::Path(path)
    }
}

impl<'a> From<&'a PathBuf> for Target<'a> {
    fn from(path: &'a PathBuf) -> Self {
        Self::Path(path)
    }
}

impl Target<'_> {
    /// The file's path, for messages.
    #[must_use]
    pub fn path(&self) -> PathBuf {
        match self {
            Self::Path(p) => p.to_path_buf(),
            Self::In { dir, name } => dir.join(name),
        }
    }

    /// Writes the file atomically.
    ///
    /// # Errors
    /// [`ExportError::Write`] naming the file when any step fails, or the error `write` returns.
    pub fn write<F>(&self, write: F) -> Result<(), ExportError>
    where
        F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
    {
        match self {
            Self::Path(p) => write_path(p, Existing::Replace, write),
            Self::In { dir, name } => dir.write(name, write),
        }
    }
}

/// Writes `path` atomically, replacing what is there: `write` fills a buffered temporary
/// file, which is flushed, synced and renamed over `path`; the directory is synced too.
///
/// # Errors
/// [`ExportError::Write`] naming `path` when any step fails (the temporary file is removed),
/// or the error `write` returns.
pub fn write_atomic<F>(path: &Path, write: F) -> Result<(), ExportError>
where
    F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
{
    write_path(path, Existing::Replace, write)
}

/// Writes `bytes` to `path` atomically.
///
/// # Errors
/// As [`write_atomic`].
pub fn write_bytes_atomic(path: &Path, bytes: &[u8]) -> Result<(), ExportError> {
    write_atomic(path, |w| w.write_all(bytes))
}

/// Writes a file that must be new: as [`write_atomic`], but an existing `path` (file, link or
/// directory) is left alone and the write fails with `AlreadyExists`.
///
/// # Errors
/// As [`write_atomic`].
pub fn write_new_atomic<F>(path: &Path, write: F) -> Result<(), ExportError>
where
    F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
{
    write_path(path, Existing::Refuse, write)
}

#[cfg(test)]
mod tests {
    use std::fs;

    use super::*;

    /// Through the early write-back, past several of its starts, the file holds what was written.
    #[test]
    fn early_writeback_writes_the_bytes_written() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.bin");
        let bytes: Vec<u8> = (0..2 * WRITEBACK_EVERY + 12_345)
            .map(|i| (i * 31 % 251) as u8)
            .collect();
        write_atomic(&path, |w| {
            let mut early = EarlyWriteback::new(w);
            for chunk in bytes.chunks(1_000_003) {
                early.write_all(chunk)?;
            }
            early.flush()
        })
        .unwrap();
        assert_eq!(fs::read(&path).unwrap(), bytes);
    }

    #[test]
    fn replaces_target_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        fs::write(&path, b"old").unwrap();
        write_bytes_atomic(&path, b"new contents").unwrap();
        assert_eq!(fs::read(&path).unwrap(), b"new contents");
        let names: Vec<_> = fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(names.len(), 1, "temporary file left behind");
    }

    #[test]
    fn failed_write_keeps_old_file_and_cleans_up() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.bin");
        fs::write(&path, b"old").unwrap();
        let err = write_atomic(&path, |w| {
            w.write_all(b"partial")?;
            Err(io::Error::other("simulated failure"))
        })
        .unwrap_err();
        assert!(err.to_string().contains("out.bin"), "{err}");
        assert_eq!(fs::read(&path).unwrap(), b"old");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn missing_directory_is_reported_with_the_path() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("no/such/dir/out.bin");
        let err = write_bytes_atomic(&path, b"x").unwrap_err();
        assert!(err.to_string().contains("no/such/dir/out.bin"), "{err}");
    }

    #[test]
    fn a_link_at_the_target_is_never_followed() {
        let dir = tempfile::tempdir().unwrap();
        let victim = dir.path().join("victim");
        fs::write(&victim, b"precious").unwrap();
        let link = dir.path().join("out.bin");
        std::os::unix::fs::symlink(&victim, &link).unwrap();
        // Must be new: the link is an existing entry, left alone.
        let err = write_new_atomic(&link, |w| w.write_all(b"evil")).unwrap_err();
        let ExportError::Write { source, .. } = &err else {
            panic!("{err}")
        };
        assert_eq!(source.kind(), io::ErrorKind::AlreadyExists, "{err}");
        assert!(fs::symlink_metadata(&link).unwrap().is_symlink());
        // Replace: the link itself is replaced by the file; its target is untouched.
        write_bytes_atomic(&link, b"new").unwrap();
        assert_eq!(fs::read(&victim).unwrap(), b"precious");
        assert!(fs::symlink_metadata(&link).unwrap().is_file());
        assert_eq!(fs::read(&link).unwrap(), b"new");
    }

    #[test]
    fn exclusive_creation_refuses_links_and_existing_files() {
        let dir = tempfile::tempdir().unwrap();
        let fd = open_dir(dir.path()).unwrap();
        fs::write(dir.path().join("taken"), b"x").unwrap();
        std::os::unix::fs::symlink("/dev/null", dir.path().join("link")).unwrap();
        for name in ["taken", "link"] {
            let err = create_new_at(fd.as_fd(), OsStr::new(name), None).unwrap_err();
            assert_eq!(err.kind(), io::ErrorKind::AlreadyExists, "{name}");
        }
        for name in ["", "a/b", ".."] {
            let err = create_new_at(fd.as_fd(), OsStr::new(name), None).unwrap_err();
            assert_eq!(err.kind(), io::ErrorKind::InvalidInput, "{name:?}");
        }
        let mut f = create_new_at(fd.as_fd(), OsStr::new("fresh"), Some(0o640)).unwrap();
        f.write_all(b"ok").unwrap();
        use std::os::unix::fs::PermissionsExt;
        let mode = fs::metadata(dir.path().join("fresh"))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o640);
    }
}
