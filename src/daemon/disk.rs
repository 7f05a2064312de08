//! Free disk space, behind a trait so tests can fill the disk at will.

use std::io;
use std::path::Path;

/// Reports the space available on the filesystem holding a path.
pub trait DiskSpace {
    /// Bytes an unprivileged process may still write on `path`'s filesystem.
    ///
    /// # Errors
    /// The system's error when the filesystem cannot be queried.
    fn free_bytes(&self, path: &Path) -> io::Result<u64>;
}

/// The real filesystem, through statvfs(3).
#[derive(Debug, Default, Clone, Copy)]
pub struct Statvfs;

impl DiskSpace for Statvfs {
    fn free_bytes(&self, path: &Path) -> io::Result<u64> {
        let s = rustix::fs::statvfs(path)?;
        // f_bavail, not f_bfree: the blocks reserved for root are not ours.
        Ok(s.f_bavail.saturating_mul(s.f_frsize))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statvfs_agrees_with_df() {
        let dir = tempfile::tempdir().unwrap();
        let free = Statvfs.free_bytes(dir.path()).unwrap();
        assert!(free > 0);
        // `df --output=avail -B1` is the naive reference; allow for other writers.
        let df = std::process::Command::new("df")
            .args(["--output=avail", "-B1"])
            .arg(dir.path())
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&df.stdout);
        let avail: u64 = text.lines().nth(1).unwrap().trim().parse().unwrap();
        let diff = free.abs_diff(avail);
        assert!(diff < 64 * 1024 * 1024, "statvfs {free} vs df {avail}");
        assert!(Statvfs.free_bytes(Path::new("/no/such/dir")).is_err());
    }
}
