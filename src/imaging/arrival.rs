//! Which file in a watched folder is the next micrograph: a pure detector fed with folder
//! listings and the time, so every rule is tested without a filesystem or a clock (VENDORS §4.2).
//!
//! - Polling only: network shares give no change events [NT, FSW].
//! - A file counts once its size and mtime stayed the same over `stable_polls` listings
//!   spanning `stable_window` [CK]; the caller then checks the TIFF structure and reports
//!   [`Arrivals::not_whole`] (wait for it to be stable again) or [`Arrivals::used`].
//! - Files present when a wait begins are never the new micrograph; a file is keyed on
//!   (name, size, mtime), so one overwritten in place or a restarted counter's name counts
//!   again, and a key once used never does.
//! - Temporary names (ignore patterns), links and special files are never candidates; a
//!   link, a special file or an oversized file is reported once.
//! - With a sidecar extension, an image is ready only with `STEM.ext` beside it, new and
//!   stable too (Hitachi, JEOL write one).

use std::collections::{BTreeMap, HashSet};
use std::time::Duration;

/// What a directory entry is, from `symlink_metadata` (links are not followed).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EntryKind {
    File,
    Dir,
    /// A symbolic link: never followed, never read.
    Symlink,
    /// A FIFO, socket or device: never opened.
    Special,
}

/// One entry of a folder listing.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ListedEntry {
    pub name: String,
    pub kind: EntryKind,
    pub len: u64,
    /// Modification time, ns since the Unix epoch (any fixed origin works: only equality matters).
    pub mtime_ns: i128,
}

/// Identity of one version of a file.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct FileKey {
    pub name: String,
    pub len: u64,
    pub mtime_ns: i128,
}

impl FileKey {
    /// The version of a listed entry.
    #[must_use]
    pub fn of(e: &ListedEntry) -> Self {
        Self {
            name: e.name.clone(),
            len: e.len,
            mtime_ns: e.mtime_ns,
        }
    }
}

/// A stable new micrograph (and its sidecar) to validate and read.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Candidate {
    pub image: FileKey,
    pub sidecar: Option<FileKey>,
}

/// Something the caller should log once.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Notice {
    /// A link with a micrograph's name: not followed.
    Symlink(String),
    /// A FIFO, socket or device with a micrograph's name: not opened.
    Special(String),
    /// Larger than the cap: not read.
    Oversize { name: String, len: u64, max: u64 },
}

/// Why the wait ended without a micrograph: what was seen, for a message that helps.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Unfinished {
    /// New files that never held still.
    pub changing: Vec<String>,
    /// New files that held still but were not whole, with the reason.
    pub not_whole: Vec<(String, String)>,
    /// New images whose sidecar never came (or never held still).
    pub without_sidecar: Vec<String>,
    /// Files skipped: links, special files, oversized files.
    pub skipped: Vec<String>,
}

impl Unfinished {
    /// Adds what `other` lists and `self` does not yet.
    fn absorb(&mut self, other: &Self) {
        fn add<T: Clone + PartialEq>(to: &mut Vec<T>, from: &[T]) {
            for x in from {
                if !to.contains(x) {
                    to.push(x.clone());
                }
            }
        }
        add(&mut self.changing, &other.changing);
        add(&mut self.not_whole, &other.not_whole);
        add(&mut self.without_sidecar, &other.without_sidecar);
        add(&mut self.skipped, &other.skipped);
    }

    /// One clause per kind, or "" when nothing new was seen.
    #[must_use]
    pub fn describe(&self) -> String {
        let mut parts = Vec::new();
        let list = |v: &[String]| v.join(", ");
        if !self.changing.is_empty() {
            parts.push(format!("still being written: {}", list(&self.changing)));
        }
        if !self.not_whole.is_empty() {
            let v: Vec<String> = self
                .not_whole
                .iter()
                .map(|(n, why)| format!("{n} ({why})"))
                .collect();
            parts.push(format!("incomplete TIFF: {}", v.join(", ")));
        }
        if !self.without_sidecar.is_empty() {
            parts.push(format!(
                "no stable sidecar beside: {}",
                list(&self.without_sidecar)
            ));
        }
        if !self.skipped.is_empty() {
            parts.push(format!("skipped: {}", list(&self.skipped)));
        }
        parts.join("; ")
    }
}

/// What one listing led to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Poll {
    /// Nothing ready yet.
    Wait,
    /// This one is stable: check and read it.
    Ready(Candidate),
    /// The wait is over without a micrograph.
    TimedOut(Unfinished),
}

/// A case-insensitive name pattern with `*` (any run) and `?` (one character).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Pattern(Vec<char>);

impl Pattern {
    #[must_use]
    pub fn new(pattern: &str) -> Self {
        Self(pattern.trim().to_lowercase().chars().collect())
    }

    #[must_use]
    pub fn matches(&self, name: &str) -> bool {
        let name: Vec<char> = name.to_lowercase().chars().collect();
        let p = &self.0;
        // Iterative wildcard match with backtracking to the last `*`.
        let (mut i, mut j) = (0, 0);
        let mut star: Option<(usize, usize)> = None;
        while j < name.len() {
            if i < p.len() && (p[i] == '?' || p[i] == name[j]) {
                i += 1;
                j += 1;
            } else if i < p.len() && p[i] == '*' {
                star = Some((i, j));
                i += 1;
            } else if let Some((si, sj)) = star {
                i = si + 1;
                j = sj + 1;
                star = Some((si, sj + 1));
            } else {
                return false;
            }
        }
        p[i..].iter().all(|&c| c == '*')
    }
}

/// The rules of one watched folder.
#[derive(Debug, Clone, PartialEq)]
pub struct ArrivalRules {
    pub patterns: Vec<Pattern>,
    pub ignore: Vec<Pattern>,
    /// Extension (no dot) of the sidecar every image needs, if any.
    pub sidecar_ext: Option<String>,
    pub stable_polls: u32,
    pub stable_window: Duration,
    pub max_bytes: u64,
    pub timeout: Duration,
}

impl ArrivalRules {
    /// Whether `name` is a micrograph's name (a pattern matches, no temporary name does).
    #[must_use]
    pub fn is_image(&self, name: &str) -> bool {
        !self.ignore.iter().any(|p| p.matches(name))
            && self.patterns.iter().any(|p| p.matches(name))
    }

    /// The name (lower case) of the sidecar `image` needs, if sidecars are configured.
    #[must_use]
    pub fn sidecar_name(&self, image: &str) -> Option<String> {
        let ext = self.sidecar_ext.as_ref()?;
        let stem = image.rsplit_once('.').map_or(image, |(s, _)| s);
        Some(format!("{stem}.{ext}").to_lowercase())
    }
}

/// How long one version of a file has been seen unchanged.
#[derive(Debug, Clone)]
struct Track {
    key: FileKey,
    since: Duration,
    polls: u32,
}

/// The detector: one per watched folder, across waits.
#[derive(Debug)]
pub struct Arrivals {
    rules: ArrivalRules,
    /// Keys used (or refused) once: never again.
    used: HashSet<FileKey>,
    /// Keys present when the current wait began.
    baseline: HashSet<FileKey>,
    /// Per name (lower case), the version seen last and since when.
    tracks: BTreeMap<String, Track>,
    /// Versions found stable but not whole, with the reason.
    not_whole: BTreeMap<String, (FileKey, String)>,
    /// Notices already given, by name and size.
    noticed: HashSet<(String, u64)>,
    began: Duration,
    last: Unfinished,
    /// Everything the current wait has seen so far (each name once per kind).
    seen: Unfinished,
}

impl Arrivals {
    #[must_use]
    pub fn new(rules: ArrivalRules) -> Self {
        Self {
            rules,
            used: HashSet::new(),
            baseline: HashSet::new(),
            tracks: BTreeMap::new(),
            not_whole: BTreeMap::new(),
            noticed: HashSet::new(),
            began: Duration::ZERO,
            last: Unfinished::default(),
            seen: Unfinished::default(),
        }
    }

    #[must_use]
    pub fn rules(&self) -> &ArrivalRules {
        &self.rules
    }

    /// Starts waiting for one new micrograph at `now`: whatever `listing` holds is old.
    pub fn begin(&mut self, now: Duration, listing: &[ListedEntry]) {
        self.baseline = listing
            .iter()
            .filter(|e| e.kind == EntryKind::File)
            .map(FileKey::of)
            .collect();
        self.tracks.clear();
        self.not_whole.clear();
        self.began = now;
        self.last = Unfinished::default();
        self.seen = Unfinished::default();
    }

    fn is_new(&self, key: &FileKey) -> bool {
        !self.baseline.contains(key) && !self.used.contains(key)
    }

    /// Updates the per-name tracks; whether `e` has been stable long enough.
    fn observe(&mut self, now: Duration, e: &ListedEntry) -> bool {
        let key = FileKey::of(e);
        let track = self
            .tracks
            .entry(e.name.to_lowercase())
            .and_modify(|t| {
                if t.key == key {
                    t.polls += 1;
                } else {
                    *t = Track {
                        key: key.clone(),
                        since: now,
                        polls: 1,
                    };
                }
            })
            .or_insert_with(|| Track {
                key: key.clone(),
                since: now,
                polls: 1,
            });
        track.polls >= self.rules.stable_polls
            && now.saturating_sub(track.since) >= self.rules.stable_window
    }

    /// Looks at one listing taken at `now`; `notices` receives what to log (each once).
    pub fn poll(
        &mut self,
        now: Duration,
        listing: &[ListedEntry],
        notices: &mut Vec<Notice>,
    ) -> Poll {
        let mut unfinished = Unfinished::default();
        let mut ready: Vec<Candidate> = Vec::new();
        let mut stable_files: BTreeMap<String, (FileKey, bool)> = BTreeMap::new();
        let present: HashSet<String> = listing.iter().map(|e| e.name.to_lowercase()).collect();
        self.tracks.retain(|name, _| present.contains(name));
        // Every regular file is tracked: images and sidecars alike.
        for e in listing.iter().filter(|e| e.kind == EntryKind::File) {
            let stable = self.observe(now, e);
            stable_files.insert(e.name.to_lowercase(), (FileKey::of(e), stable));
        }
        for e in listing {
            if !self.rules.is_image(&e.name) {
                continue;
            }
            let key = FileKey::of(e);
            match e.kind {
                EntryKind::Dir => continue,
                EntryKind::Symlink | EntryKind::Special => {
                    if self.noticed.insert((e.name.clone(), u64::MAX)) {
                        notices.push(if e.kind == EntryKind::Symlink {
                            Notice::Symlink(e.name.clone())
                        } else {
                            Notice::Special(e.name.clone())
                        });
                    }
                    unfinished.skipped.push(e.name.clone());
                    continue;
                }
                EntryKind::File => {}
            }
            if !self.is_new(&key) {
                continue;
            }
            if e.len > self.rules.max_bytes {
                if self.noticed.insert((e.name.clone(), e.len)) {
                    notices.push(Notice::Oversize {
                        name: e.name.clone(),
                        len: e.len,
                        max: self.rules.max_bytes,
                    });
                }
                unfinished.skipped.push(e.name.clone());
                continue;
            }
            let lower = e.name.to_lowercase();
            let stable = e.len > 0 && stable_files.get(&lower).is_some_and(|s| s.1);
            if !stable {
                // A version found broken waits for a new stability window (see `not_whole`).
                match self.not_whole.get(&lower) {
                    Some((old, why)) if *old == key => {
                        unfinished.not_whole.push((e.name.clone(), why.clone()));
                    }
                    _ => unfinished.changing.push(e.name.clone()),
                }
                continue;
            }
            let sidecar = match self.rules.sidecar_name(&e.name) {
                None => None,
                Some(side) => match stable_files.get(&side) {
                    Some((skey, true))
                        if skey.len > 0
                            && skey.len <= self.rules.max_bytes
                            && self.is_new(skey) =>
                    {
                        Some(skey.clone())
                    }
                    _ => {
                        unfinished.without_sidecar.push(e.name.clone());
                        continue;
                    }
                },
            };
            ready.push(Candidate {
                image: key,
                sidecar,
            });
        }
        self.seen.absorb(&unfinished);
        // The oldest first, then by name: the order the SEM stored them.
        ready.sort_by(|a, b| {
            (a.image.mtime_ns, &a.image.name).cmp(&(b.image.mtime_ns, &b.image.name))
        });
        if let Some(c) = ready.into_iter().next() {
            return Poll::Ready(c);
        }
        self.last = unfinished;
        if now.saturating_sub(self.began) >= self.rules.timeout {
            return Poll::TimedOut(self.last.clone());
        }
        Poll::Wait
    }

    /// The candidate was stable but its TIFF is not whole (`why`): it is checked again only
    /// after holding still for another stability window.
    pub fn not_whole(&mut self, candidate: &Candidate, why: impl Into<String>, now: Duration) {
        let name = candidate.image.name.to_lowercase();
        if let Some(t) = self.tracks.get_mut(&name) {
            t.since = now;
            t.polls = 1;
        }
        self.not_whole
            .insert(name, (candidate.image.clone(), why.into()));
    }

    /// The candidate was read (used or refused): never a candidate again.
    pub fn used(&mut self, candidate: &Candidate) {
        self.used.insert(candidate.image.clone());
        if let Some(s) = &candidate.sidecar {
            self.used.insert(s.clone());
        }
        self.not_whole.remove(&candidate.image.name.to_lowercase());
    }

    /// What the last listing showed that was not (yet) a micrograph.
    #[must_use]
    pub fn unfinished(&self) -> &Unfinished {
        &self.last
    }

    /// Everything the current (or last) wait saw that was not yet a micrograph: e.g. the
    /// micrograph itself while it was still being written.
    #[must_use]
    pub fn seen(&self) -> &Unfinished {
        &self.seen
    }
}

#[cfg(test)]
mod tests;
