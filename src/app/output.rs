//! The output location of a command (`--out` of `reconstruct`, `rectify`, `flow`, `replay`),
//! made ready before any work: created, opened, probed for writing, and checked for outputs
//! of an earlier run, which are replaced only with `--force`. Every file is then written
//! through the one atomic writer into the open directory ([`OutputDir`]), so a file that
//! appears meanwhile is not overwritten either.

use std::io;
use std::path::{Path, PathBuf};

use crate::export::atomic::{Existing, OutputDir};

/// Why an output location cannot be used; each message names the remedy.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    #[error("--out {}: {} is a file, not a directory — give --out a directory path", out.display(), file.display())]
    UnderAFile { out: PathBuf, file: PathBuf },
    #[error("cannot create the output directory {}: {source} — give --out a directory you can create", out.display())]
    Create { out: PathBuf, source: io::Error },
    #[error("cannot write in the output directory {}: {source} — choose another --out, or make it writable", out.display())]
    NotWritable { out: PathBuf, source: io::Error },
    #[error(
        "{} already holds {} of an earlier run: give --force to replace {}, or another --out",
        out.display(), names.join(", "), if names.len() == 1 { "it" } else { "them" }
    )]
    Exists { out: PathBuf, names: Vec<String> },
}

/// Creates `out` (and its parents) if needed, opens it, proves it can be written in, and
/// refuses it when it already holds one of `names`, unless `force`. The outputs are then
/// written exclusively, or replacing with `force`.
///
/// # Errors
/// [`OutputError`] naming the directory, the cause and the remedy.
pub fn prepare_dir(out: &Path, names: &[&str], force: bool) -> Result<OutputDir, OutputError> {
    if let Some(file) = file_in_the_way(out) {
        return Err(OutputError::UnderAFile {
            out: out.to_owned(),
            file,
        });
    }
    std::fs::create_dir_all(out).map_err(|source| OutputError::Create {
        out: out.to_owned(),
        source,
    })?;
    let existing = if force {
        Existing::Replace
    } else {
        Existing::Refuse
    };
    let dir = OutputDir::open(out, existing).map_err(|source| OutputError::Create {
        out: out.to_owned(),
        source,
    })?;
    dir.probe().map_err(|source| OutputError::NotWritable {
        out: out.to_owned(),
        source,
    })?;
    if !force {
        let mut taken = Vec::new();
        for name in names {
            if dir.holds(name).map_err(|source| OutputError::NotWritable {
                out: out.to_owned(),
                source,
            })? {
                taken.push((*name).to_owned());
            }
        }
        if !taken.is_empty() {
            return Err(OutputError::Exists {
                out: out.to_owned(),
                names: taken,
            });
        }
    }
    Ok(dir)
}

/// An output file (`flow --out FLOW.flo`): its directory prepared as by [`prepare_dir`] for
/// the one name. Returns the directory and the file's name in it.
///
/// # Errors
/// As [`prepare_dir`]; a path that names no file is refused as a directory in the way.
pub fn prepare_file(out: &Path, force: bool) -> Result<(OutputDir, String), OutputError> {
    let Some(name) = out.file_name().map(|n| n.to_string_lossy().into_owned()) else {
        return Err(OutputError::Create {
            out: out.to_owned(),
            source: io::Error::new(io::ErrorKind::InvalidInput, "the path names no file"),
        });
    };
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if std::fs::symlink_metadata(out).is_ok_and(|m| m.is_dir()) {
        return Err(OutputError::Create {
            out: out.to_owned(),
            source: io::Error::new(
                io::ErrorKind::IsADirectory,
                "it is a directory; --out names the file to write",
            ),
        });
    }
    let dir = prepare_dir(parent, &[name.as_str()], force).map_err(|e| match e {
        OutputError::UnderAFile { file, .. } => OutputError::UnderAFile {
            out: out.to_owned(),
            file,
        },
        other => other,
    })?;
    Ok((dir, name))
}

/// The directories that preparing `out` is about to create, deepest first: a command that
/// then fails removes them again while they are empty, so a refused run leaves nothing behind.
#[derive(Debug)]
pub struct Created(Vec<PathBuf>);

impl Created {
    /// Notes which of `out` and its ancestors do not exist yet (call before preparing).
    #[must_use]
    pub fn before(out: &Path) -> Self {
        Self(
            out.ancestors()
                .filter(|a| !a.as_os_str().is_empty())
                .take_while(|a| std::fs::symlink_metadata(a).is_err())
                .map(Path::to_owned)
                .collect(),
        )
    }

    /// Removes the noted directories when `outcome` is a failure; `rmdir` removes only
    /// empty ones, so nothing written is ever lost.
    pub fn undo_on_failure<T, E>(&self, outcome: &Result<T, E>) {
        if outcome.is_err() {
            for dir in &self.0 {
                if std::fs::remove_dir(dir).is_err() {
                    break;
                }
            }
        }
    }
}

/// The path itself or the nearest of its ancestors that exists, when that is not a directory.
fn file_in_the_way(out: &Path) -> Option<PathBuf> {
    out.ancestors()
        .filter(|a| !a.as_os_str().is_empty())
        .find_map(|a| std::fs::metadata(a).ok().map(|m| (a, m)))
        .and_then(|(a, m)| (!m.is_dir()).then(|| a.to_owned()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_output_under_a_file_is_refused_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("notes.txt");
        std::fs::write(&file, "x").unwrap();
        let err = prepare_dir(&file.join("out"), &["a"], false).unwrap_err();
        assert!(
            matches!(&err, OutputError::UnderAFile { file: f, .. } if *f == file),
            "{err}"
        );
        let err = prepare_dir(&file, &["a"], false).unwrap_err().to_string();
        assert!(err.contains("is a file, not a directory"), "{err}");
    }

    #[test]
    fn a_failed_command_removes_only_the_empty_directories_it_created() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("a/b/out");
        let created = Created::before(&out);
        prepare_dir(&out, &["x"], false).unwrap();
        created.undo_on_failure(&Ok::<(), ()>(()));
        assert!(out.is_dir());
        created.undo_on_failure(&Err::<(), ()>(()));
        assert!(!dir.path().join("a").exists());
        assert!(dir.path().is_dir());
        // A directory holding a file stays, and so do its parents.
        let created = Created::before(&out);
        prepare_dir(&out, &["x"], false).unwrap();
        std::fs::write(out.join("kept"), "x").unwrap();
        created.undo_on_failure(&Err::<(), ()>(()));
        assert!(out.join("kept").is_file());
        // An existing directory is never removed.
        std::fs::remove_file(out.join("kept")).unwrap();
        let created = Created::before(&out);
        created.undo_on_failure(&Err::<(), ()>(()));
        assert!(out.is_dir());
    }

    #[test]
    fn existing_outputs_need_force_and_the_probe_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("new/out");
        let prepared = prepare_dir(&out, &["report.json", "height.tif"], false).unwrap();
        assert_eq!(
            std::fs::read_dir(&out).unwrap().count(),
            0,
            "probe left behind"
        );
        prepared
            .write("report.json", |w| std::io::Write::write_all(w, b"{}"))
            .unwrap();
        let err = prepare_dir(&out, &["height.tif", "report.json"], false)
            .unwrap_err()
            .to_string();
        assert!(
            err.ends_with("already holds report.json of an earlier run: give --force to replace it, or another --out"),
            "{err}"
        );
        let forced = prepare_dir(&out, &["report.json"], true).unwrap();
        forced
            .write("report.json", |w| std::io::Write::write_all(w, b"[]"))
            .unwrap();
        assert_eq!(std::fs::read(out.join("report.json")).unwrap(), b"[]");
        // Without --force a file that appeared after the check is not overwritten either.
        let err = prepared
            .write("report.json", |w| std::io::Write::write_all(w, b"{}"))
            .unwrap_err();
        assert!(err.to_string().contains("exists"), "{err}");
    }

    #[test]
    fn an_output_file_is_prepared_in_its_directory() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("flows/a.flo");
        let (prepared, name) = prepare_file(&out, false).unwrap();
        assert_eq!(name, "a.flo");
        prepared
            .write(&name, |w| std::io::Write::write_all(w, b"PIEH"))
            .unwrap();
        let err = prepare_file(&out, false).unwrap_err().to_string();
        assert!(err.contains("already holds a.flo"), "{err}");
        prepare_file(&out, true).unwrap();
        let err = prepare_file(dir.path(), false).unwrap_err().to_string();
        assert!(err.contains("is a directory"), "{err}");
    }
}
