//! The run directory, one owner for `sdsem acquire` and the daemon: created from a validated
//! [`RunName`] with `mkdir` relative to the output directory (never through a link), private
//! to the service (mode 0750: its group reads, only its user writes), and every file in it
//! created exclusively (`O_CREAT|O_EXCL|O_NOFOLLOW`): nothing placed there beforehand is
//! followed or overwritten.

use std::ffi::OsStr;
use std::fs::File;
use std::io::{self, BufWriter};
use std::os::fd::{AsFd, OwnedFd};
use std::os::unix::fs::DirBuilderExt;
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use rustix::fs::{Mode, OFlags};

use crate::export::atomic::{Existing, OutputDir, create_new_at, open_dir, write_atomic_at};

/// Longest run name accepted, in characters.
pub const MAX_NAME_LEN: usize = 64;

/// Mode of run directories and of the output directory when sdsem creates it.
const DIR_MODE: u32 = 0o750;

/// A run's name, safe as the first part of a directory name: letters, digits, '-', '_'
/// and '.', at most [`MAX_NAME_LEN`] characters, not starting with '.'.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RunName(String);

/// Why a name cannot name a run.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "{shown} {reason}; use letters, digits, '-', '_' and '.', at most {MAX_NAME_LEN} characters, \
     not starting with '.'"
)]
pub struct NameError {
    /// The name as printed: quoted, control characters escaped, cut short when long.
    pub shown: String,
    pub reason: &'static str,
}

impl RunName {
    /// Checks `name`.
    ///
    /// # Errors
    /// [`NameError`] saying what is wrong with it.
    pub fn new(name: &str) -> Result<Self, NameError> {
        let reason = if name.is_empty() {
            Some("is empty")
        } else if name.chars().count() > MAX_NAME_LEN {
            Some("is too long")
        } else if name.starts_with('.') {
            Some("starts with '.'")
        } else if !name
            .chars()
            .all(|c| c.is_alphanumeric() || matches!(c, '-' | '_' | '.'))
        {
            Some("has a character that does not belong in a directory name")
        } else {
            None
        };
        match reason {
            Some(reason) => Err(NameError {
                shown: format!("\"{}\"", printable(name, 80)),
                reason,
            }),
            None => Ok(Self(name.to_owned())),
        }
    }

    #[must_use]
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Display for RunName {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// Text from outside made safe to print on a terminal or in a log line: control characters
/// (ESC, newline, …) and bidirectional overrides escaped, cut to `max_chars` characters.
#[must_use]
pub fn printable(text: &str, max_chars: usize) -> String {
    let mut out = String::new();
    for (i, c) in text.chars().enumerate() {
        if i >= max_chars {
            let rest = text.chars().count() - i;
            out.push_str(&format!("…(+{rest} characters)"));
            break;
        }
        let bidi = matches!(c, '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}' | '\u{200e}' | '\u{200f}');
        if c.is_control() || bidi {
            out.extend(c.escape_default());
        } else {
            out.push(c);
        }
    }
    out
}

/// Why a run directory could not be made.
#[derive(Debug, thiserror::Error)]
pub enum RunDirError {
    #[error("cannot use run.output_dir {}: {source}", path.display())]
    OutputDir { path: PathBuf, source: io::Error },
    #[error("cannot create the run directory {}: {source}", path.display())]
    Create { path: PathBuf, source: io::Error },
    #[error("cannot create a run directory in {}: {stem} and its 99 numbered variants exist", dir.display())]
    Taken { dir: PathBuf, stem: String },
}

/// A fresh, empty run directory, open: files are created relative to it.
#[derive(Debug)]
pub struct RunDir {
    path: PathBuf,
    dir: OwnedFd,
}

impl RunDir {
    /// Creates `<output_dir>/<name>-<UTC time>` (then `…-2`, `…-3` if taken), creating
    /// `output_dir` first if needed (mode 0750). The output directory is the operator's and
    /// is opened as configured; the run directory is made with `mkdirat` relative to it and
    /// opened without following links.
    ///
    /// # Errors
    /// [`RunDirError`] naming the directory and the cause.
    pub fn create(output_dir: &Path, name: &RunName, now: SystemTime) -> Result<Self, RunDirError> {
        let base = std::path::absolute(output_dir).map_err(|source| RunDirError::OutputDir {
            path: output_dir.to_owned(),
            source,
        })?;
        let out_error = |source| RunDirError::OutputDir {
            path: base.clone(),
            source,
        };
        std::fs::DirBuilder::new()
            .recursive(true)
            .mode(DIR_MODE)
            .create(&base)
            .map_err(out_error)?;
        let out = open_dir(&base).map_err(out_error)?;
        let stem = format!("{name}-{}", crate::daemon::utc::compact(now));
        for n in 1..=100 {
            let dir_name = if n == 1 {
                stem.clone()
            } else {
                format!("{stem}-{n}")
            };
            let path = base.join(&dir_name);
            let create_error = |source| RunDirError::Create {
                path: path.clone(),
                source,
            };
            match rustix::fs::mkdirat(&out, dir_name.as_str(), Mode::from_raw_mode(DIR_MODE)) {
                Ok(()) => {}
                Err(rustix::io::Errno::EXIST) => continue,
                Err(e) => return Err(create_error(e.into())),
            }
            let dir = rustix::fs::openat(
                &out,
                dir_name.as_str(),
                OFlags::RDONLY | OFlags::DIRECTORY | OFlags::NOFOLLOW | OFlags::CLOEXEC,
                Mode::empty(),
            )
            .map_err(|e| create_error(e.into()))?;
            return Ok(Self { path, dir });
        }
        Err(RunDirError::Taken { dir: base, stem })
    }

    /// The directory's absolute path.
    #[must_use]
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The path of a file in it, for messages and readers.
    #[must_use]
    pub fn join(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }

    /// Creates the new file `name` in it, exclusively.
    ///
    /// # Errors
    /// `AlreadyExists` when something has that name already; the system's error otherwise.
    pub fn create_file(&self, name: &str) -> io::Result<File> {
        create_new_at(self.dir.as_fd(), OsStr::new(name), None)
    }

    /// The directory as the target of exports (the reconstruction's outputs): every file
    /// new, created exclusively through the one atomic writer, never through a link.
    ///
    /// # Errors
    /// The system's error when the directory's descriptor cannot be duplicated.
    pub fn outputs(&self) -> io::Result<OutputDir> {
        Ok(OutputDir::from_fd(
            self.path.clone(),
            self.dir.try_clone()?,
            Existing::Refuse,
        ))
    }

    /// Writes the new file `name` atomically (the one atomic writer), refusing an existing one.
    ///
    /// # Errors
    /// As [`RunDir::create_file`], and the error of the step that failed.
    pub fn write_new<F>(&self, name: &str, write: F) -> io::Result<()>
    where
        F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
    {
        write_atomic_at(
            self.dir.as_fd(),
            OsStr::new(name),
            Existing::Refuse,
            None,
            write,
        )
    }
}

#[cfg(test)]
mod tests {
    use std::io::Write;
    use std::os::unix::fs::PermissionsExt;
    use std::time::Duration;

    use super::*;

    fn at() -> SystemTime {
        SystemTime::UNIX_EPOCH + Duration::from_secs(1_740_837_909)
    }

    #[test]
    fn names_that_make_bad_directories_are_refused_and_shown_safely() {
        for name in [
            "",
            "../x",
            "a/b",
            ".hidden",
            "a b",
            "\u{1b}[31mred",
            &"x".repeat(65),
        ] {
            let err = RunName::new(name).unwrap_err();
            assert!(!err.to_string().contains('\u{1b}'), "{err}");
        }
        RunName::new("Probe_Müller.2").unwrap();
        let huge = "é".repeat(1_000_000);
        let err = RunName::new(&huge).unwrap_err().to_string();
        assert!(err.len() < 400, "{} bytes", err.len());
        assert!(err.contains("…(+"), "{err}");
        assert_eq!(
            printable("a\u{1b}b\nc\u{202e}", 10),
            "a\\u{1b}b\\nc\\u{202e}"
        );
    }

    #[test]
    fn run_dirs_do_not_collide_and_are_private() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("runs");
        let name = RunName::new("pollen").unwrap();
        let a = RunDir::create(&out, &name, at()).unwrap();
        let b = RunDir::create(&out, &name, at()).unwrap();
        assert!(a.path().ends_with("pollen-20250301T140509Z"));
        assert!(b.path().ends_with("pollen-20250301T140509Z-2"));
        let mode = std::fs::metadata(a.path()).unwrap().permissions().mode();
        assert_eq!(mode & 0o777, 0o750 & !umask(), "{mode:o}");
    }

    fn umask() -> u32 {
        let old = rustix::process::umask(Mode::from_raw_mode(0o022));
        rustix::process::umask(old);
        old.bits()
    }

    #[test]
    fn a_link_in_place_of_the_run_directory_is_not_followed() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("runs");
        std::fs::create_dir(&out).unwrap();
        let elsewhere = dir.path().join("elsewhere");
        std::fs::create_dir(&elsewhere).unwrap();
        std::os::unix::fs::symlink(&elsewhere, out.join("pollen-20250301T140509Z")).unwrap();
        let run = RunDir::create(&out, &RunName::new("pollen").unwrap(), at()).unwrap();
        assert!(run.path().ends_with("pollen-20250301T140509Z-2"));
        run.create_file("run.mcap").unwrap();
        assert_eq!(std::fs::read_dir(&elsewhere).unwrap().count(), 0);
    }

    #[test]
    fn files_placed_in_a_run_directory_are_neither_followed_nor_overwritten() {
        let dir = tempfile::tempdir().unwrap();
        let run = RunDir::create(dir.path(), &RunName::new("r").unwrap(), at()).unwrap();
        let victim = dir.path().join("victim");
        std::fs::write(&victim, b"precious").unwrap();
        std::os::unix::fs::symlink(&victim, run.join("run.mcap")).unwrap();
        std::os::unix::fs::symlink(&victim, run.join("config.toml")).unwrap();
        let err = run.create_file("run.mcap").unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::AlreadyExists);
        let err = run
            .write_new("config.toml", |w| w.write_all(b"x"))
            .unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::AlreadyExists);
        assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
        run.write_new("left.tif", |w| w.write_all(b"tiff")).unwrap();
        assert_eq!(std::fs::read(run.join("left.tif")).unwrap(), b"tiff");
        // The reconstruction's outputs too: a link placed at height.tif is left alone.
        std::os::unix::fs::symlink(&victim, run.join("height.tif")).unwrap();
        let outputs = run.outputs().unwrap();
        let err = crate::export::height_tiff::write_height_tiff(
            outputs.file("height.tif"),
            &crate::vision::Image::zeros(2, 2),
            None,
            None,
        )
        .unwrap_err();
        assert!(err.to_string().contains("exists"), "{err}");
        assert_eq!(std::fs::read(&victim).unwrap(), b"precious");
        assert!(
            outputs.read("height.tif").is_err(),
            "read back through a link"
        );
    }
}
