use super::*;

const POLL: Duration = Duration::from_millis(250);

fn rules() -> ArrivalRules {
    ArrivalRules {
        patterns: vec![Pattern::new("*.tif"), Pattern::new("*.tiff")],
        ignore: ["~*", ".*", "*.tmp", "*.part"]
            .iter()
            .map(|p| Pattern::new(p))
            .collect(),
        sidecar_ext: None,
        stable_polls: 3,
        stable_window: Duration::from_secs(1),
        max_bytes: 1000,
        timeout: Duration::from_secs(10),
    }
}

fn file(name: &str, len: u64, mtime: i128) -> ListedEntry {
    ListedEntry {
        name: name.into(),
        kind: EntryKind::File,
        len,
        mtime_ns: mtime,
    }
}

fn of(kind: EntryKind, name: &str) -> ListedEntry {
    ListedEntry {
        name: name.into(),
        kind,
        len: 10,
        mtime_ns: 1,
    }
}

/// Polls `listing` every 250 ms from `from` until something other than Wait comes back,
/// at most `max` polls; returns the time and the outcome.
fn poll_until(
    a: &mut Arrivals,
    from: Duration,
    max: u32,
    listing: &[ListedEntry],
    notices: &mut Vec<Notice>,
) -> (Duration, Poll) {
    let mut t = from;
    for _ in 0..max {
        let p = a.poll(t, listing, notices);
        if p != Poll::Wait {
            return (t, p);
        }
        t += POLL;
    }
    (t, Poll::Wait)
}

fn ready_name(p: &Poll) -> &str {
    match p {
        Poll::Ready(c) => &c.image.name,
        other => panic!("expected a candidate, got {other:?}"),
    }
}

#[test]
fn patterns_are_case_insensitive_wildcards() {
    let p = Pattern::new("*.tif");
    assert!(p.matches("IMG_001.TIF") && p.matches(".tif") && !p.matches("a.tiff"));
    assert!(Pattern::new("~*").matches("~$img.tif"));
    assert!(Pattern::new("img_??.t*f").matches("img_01.tiff"));
    assert!(!Pattern::new("img_??.tif").matches("img_1.tif"));
    assert!(Pattern::new("*a*b*").matches("xxaxxbxx") && !Pattern::new("*a*b").matches("ba"));
}

#[test]
fn a_growing_file_is_ready_only_after_holding_still() {
    let mut a = Arrivals::new(rules());
    let mut notices = Vec::new();
    a.begin(Duration::ZERO, &[]);
    // Written in chunks: the size changes at every listing for a second.
    let mut t = Duration::ZERO;
    for (i, len) in [100u64, 300, 500].iter().enumerate() {
        t = POLL * (i as u32 + 1);
        assert_eq!(
            a.poll(t, &[file("img.tif", *len, i as i128)], &mut notices),
            Poll::Wait
        );
    }
    assert_eq!(a.unfinished().changing, vec!["img.tif".to_owned()]);
    assert_eq!(
        a.seen().changing,
        vec!["img.tif".to_owned()],
        "once, however many listings"
    );
    // Complete from here on: 3 listings and 1 s unchanged.
    let done = [file("img.tif", 600, 9)];
    let (at, p) = poll_until(&mut a, t + POLL, 20, &done, &mut notices);
    assert_eq!(ready_name(&p), "img.tif");
    assert_eq!(
        at,
        t + POLL + Duration::from_secs(1),
        "ready after the whole window"
    );
    assert!(notices.is_empty());
}

#[test]
fn the_stability_window_and_the_poll_count_both_hold() {
    // Polls far apart: three listings are needed even when the window passed long ago.
    let mut a = Arrivals::new(rules());
    let mut n = Vec::new();
    a.begin(Duration::ZERO, &[]);
    let f = [file("a.tif", 10, 1)];
    assert_eq!(a.poll(Duration::from_secs(5), &f, &mut n), Poll::Wait);
    assert_eq!(a.poll(Duration::from_secs(6), &f, &mut n), Poll::Wait);
    assert!(matches!(
        a.poll(Duration::from_secs(7), &f, &mut n),
        Poll::Ready(_)
    ));
}

#[test]
fn temporary_names_are_ignored_and_the_renamed_file_counts() {
    let mut a = Arrivals::new(rules());
    let mut n = Vec::new();
    a.begin(Duration::ZERO, &[]);
    for temp in ["~img.tif", ".img.tif", "img.tif.tmp", "img.part"] {
        let (_, p) = poll_until(&mut a, Duration::ZERO, 20, &[file(temp, 10, 1)], &mut n);
        assert_eq!(p, Poll::Wait, "{temp} must be ignored");
    }
    // Renamed: same size and mtime under the final name; stable from its first sighting.
    let t = Duration::from_secs(5);
    let (at, p) = poll_until(&mut a, t, 20, &[file("img.tif", 10, 1)], &mut n);
    assert_eq!(ready_name(&p), "img.tif");
    assert_eq!(at, t + Duration::from_secs(1));
}

#[test]
fn links_and_special_files_are_reported_once_and_never_read() {
    let mut a = Arrivals::new(rules());
    let mut n = Vec::new();
    a.begin(Duration::ZERO, &[]);
    let listing = [
        of(EntryKind::Symlink, "link.tif"),
        of(EntryKind::Special, "fifo.tif"),
        of(EntryKind::Dir, "dir.tif"),
    ];
    let (_, p) = poll_until(&mut a, Duration::ZERO, 60, &listing, &mut n);
    let Poll::TimedOut(u) = p else {
        panic!("expected a timeout, got {p:?}")
    };
    assert_eq!(
        n,
        vec![
            Notice::Symlink("link.tif".into()),
            Notice::Special("fifo.tif".into())
        ],
        "each once"
    );
    assert_eq!(
        u.skipped,
        vec!["link.tif".to_owned(), "fifo.tif".to_owned()]
    );
    assert!(
        u.describe().contains("skipped: link.tif, fifo.tif"),
        "{}",
        u.describe()
    );
}

#[test]
fn an_oversized_file_is_skipped_with_a_notice() {
    let mut a = Arrivals::new(rules());
    let mut n = Vec::new();
    a.begin(Duration::ZERO, &[]);
    let (_, p) = poll_until(
        &mut a,
        Duration::ZERO,
        60,
        &[file("huge.tif", 1001, 1)],
        &mut n,
    );
    assert!(matches!(p, Poll::TimedOut(_)));
    assert_eq!(
        n,
        vec![Notice::Oversize {
            name: "huge.tif".into(),
            len: 1001,
            max: 1000
        }]
    );
}

#[test]
fn the_timeout_names_what_was_seen() {
    let mut a = Arrivals::new(rules());
    let mut n = Vec::new();
    a.begin(Duration::from_secs(100), &[]);
    let mut t = Duration::from_secs(100);
    let mut len = 1;
    let outcome = loop {
        len += 1;
        match a.poll(t, &[file("slow.tif", len, i128::from(len))], &mut n) {
            Poll::Wait => t += POLL,
            other => break other,
        }
    };
    assert_eq!(t, Duration::from_secs(110), "the timeout counts from begin");
    let Poll::TimedOut(u) = outcome else {
        panic!("{outcome:?}")
    };
    assert_eq!(u.describe(), "still being written: slow.tif");
}

#[test]
fn nothing_is_used_twice_but_rewritten_files_count_again() {
    let mut a = Arrivals::new(rules());
    let mut n = Vec::new();
    // A stale file from before the start is never the new micrograph.
    let stale = file("img_001.tif", 50, 1);
    a.begin(Duration::ZERO, std::slice::from_ref(&stale));
    let (_, p) = poll_until(
        &mut a,
        Duration::ZERO,
        41,
        std::slice::from_ref(&stale),
        &mut n,
    );
    assert!(
        matches!(p, Poll::TimedOut(ref u) if u.describe().is_empty()),
        "{p:?}"
    );

    // A new one is used; once used, it is not offered again, even in a later wait that
    // began before it existed.
    a.begin(Duration::from_secs(20), std::slice::from_ref(&stale));
    let new = file("img_002.tif", 60, 2);
    let (_, p) = poll_until(
        &mut a,
        Duration::from_secs(20),
        20,
        &[stale.clone(), new.clone()],
        &mut n,
    );
    let Poll::Ready(c) = p else { panic!("{p:?}") };
    assert_eq!(c.image.name, "img_002.tif");
    a.used(&c);
    a.begin(Duration::from_secs(40), std::slice::from_ref(&stale));
    let (_, p) = poll_until(
        &mut a,
        Duration::from_secs(40),
        41,
        &[stale.clone(), new],
        &mut n,
    );
    assert!(matches!(p, Poll::TimedOut(_)), "{p:?}");

    // Overwritten in place (the counter restarted): same name, new mtime and size → new.
    a.begin(Duration::from_secs(60), std::slice::from_ref(&stale));
    let rewritten = file("img_001.tif", 50, 3);
    let (_, p) = poll_until(&mut a, Duration::from_secs(60), 20, &[rewritten], &mut n);
    assert_eq!(ready_name(&p), "img_001.tif");
}

#[test]
fn the_oldest_new_file_comes_first() {
    let mut a = Arrivals::new(rules());
    let mut n = Vec::new();
    a.begin(Duration::ZERO, &[]);
    let listing = [file("b.tif", 10, 5), file("a.tif", 10, 7)];
    let (_, p) = poll_until(&mut a, Duration::ZERO, 20, &listing, &mut n);
    assert_eq!(ready_name(&p), "b.tif");
}

#[test]
fn a_broken_tiff_waits_for_another_window_and_is_named_at_the_timeout() {
    let mut a = Arrivals::new(rules());
    let mut n = Vec::new();
    a.begin(Duration::ZERO, &[]);
    let f = [file("img.tif", 100, 1)];
    let (at, p) = poll_until(&mut a, Duration::ZERO, 20, &f, &mut n);
    let Poll::Ready(c) = p else { panic!("{p:?}") };
    a.not_whole(&c, "strip 3 ends beyond the file", at);
    // Not offered again before it held still for a whole window more.
    assert_eq!(a.poll(at + POLL, &f, &mut n), Poll::Wait);
    assert_eq!(
        a.unfinished().not_whole,
        vec![(
            "img.tif".to_owned(),
            "strip 3 ends beyond the file".to_owned()
        )]
    );
    let (again, p) = poll_until(&mut a, at + POLL, 20, &f, &mut n);
    assert_eq!(ready_name(&p), "img.tif");
    assert_eq!(again, at + Duration::from_secs(1));
    a.not_whole(&c, "strip 3 ends beyond the file", again);
    let (_, p) = poll_until(&mut a, again + POLL, 60, &[], &mut n);
    assert!(matches!(p, Poll::TimedOut(_)));
}

#[test]
fn an_image_with_a_sidecar_waits_for_both() {
    let mut r = rules();
    r.sidecar_ext = Some("txt".into());
    let mut a = Arrivals::new(r);
    let mut n = Vec::new();
    // An old sidecar of the same stem (a restarted counter) does not count.
    let old_side = file("IMG.TXT", 20, 1);
    a.begin(Duration::ZERO, std::slice::from_ref(&old_side));
    let image = file("img.tif", 100, 2);
    let (_, p) = poll_until(
        &mut a,
        Duration::ZERO,
        20,
        &[image.clone(), old_side],
        &mut n,
    );
    assert_eq!(p, Poll::Wait);
    assert_eq!(a.unfinished().without_sidecar, vec!["img.tif".to_owned()]);
    // The new sidecar arrives, and holds still: both go together.
    let side = file("IMG.TXT", 25, 3);
    let t = Duration::from_secs(6);
    let (at, p) = poll_until(&mut a, t, 20, &[image, side], &mut n);
    let Poll::Ready(c) = p else { panic!("{p:?}") };
    assert_eq!(c.sidecar.unwrap().name, "IMG.TXT");
    assert_eq!(at, t + Duration::from_secs(1));
}
