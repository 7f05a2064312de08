//! Record round trips: every topic written and read back, truncation at many offsets,
//! live reading before `finish()`, disk full, the tracing layer.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use super::*;
use crate::export::CloudPoint;
use crate::vision::Image;

const T0: u64 = 1_700_000_000_000_000_000;

fn fast_options() -> RecorderOptions {
    RecorderOptions {
        fsync: false,
        ..RecorderOptions::default()
    }
}

fn frame_info(role: FrameRole, index: u64, tilt: f64) -> FrameInfo {
    FrameInfo {
        role,
        index,
        tilt_deg: tilt,
        stage_x_um: 1.0,
        stage_y_um: -2.0,
        pixel_size_um: 0.05,
        dwell_us: 0.8,
        width: 8,
        height: 6,
        tilt_axis_deg: Some(0.0),
        drift_px: (role == FrameRole::Tracking).then_some([0.25, -0.5]),
        file: None,
    }
}

fn micrograph(seed: u32) -> Image {
    Image::from_fn(8, 6, |x, y| {
        ((x as u32 * 7 + y as u32 * 13 + seed) % 17) as f32 / 16.0
    })
}

/// Writes a run with every topic of DESIGN §5.
fn write_full_run(path: &Path) -> RecordSummary {
    let recorder = Recorder::create(path, fast_options()).unwrap();
    let rec = recorder.handle();
    let mut run = BTreeMap::new();
    run.insert("job".to_owned(), "job-42".to_owned());
    run.insert("config".to_owned(), "[stage]\nport = \"sim\"".to_owned());
    run.insert("version".to_owned(), "0.1.0".to_owned());
    run.insert("host".to_owned(), "labpc".to_owned());
    rec.metadata(topics::METADATA_RUN, run).unwrap();

    for i in 0..3u64 {
        let t = T0 + i * 1_000_000_000;
        let px = Pixels::mono8_from_image(&micrograph(i as u32));
        rec.image(topics::SEM_FRAME, t, "tracking", &px, 8, 6)
            .unwrap();
        rec.json(
            topics::SEM_FRAME_INFO,
            t,
            &frame_info(FrameRole::Tracking, i, i as f64),
        )
        .unwrap();
        let io = StageIo {
            seq: i,
            command: Some(format!("MOV T {i}")),
            attempt: 1,
            sent_wall_ns: Some(t),
            reply: None,
            reply_wall_ns: None,
            rtt_ns: None,
            outcome: crate::stage::IoOutcome::Sent,
            detail: None,
        };
        rec.json(topics::STAGE_IO, t, &io).unwrap();
        let state = StageState {
            wall_ns: t,
            event: crate::stage::StageEvent::Reached,
            axes: vec![crate::stage::AxisState {
                axis: crate::stage::StageAxis::Tilt,
                id: "T".into(),
                position: Some(i as f64),
                target: Some(i as f64),
                on_target: Some(true),
            }],
        };
        rec.json(topics::STAGE_STATE, t, &state).unwrap();
    }
    for (k, (role, tilt)) in [(FrameRole::Left, 0.0), (FrameRole::Right, 3.0)]
        .into_iter()
        .enumerate()
    {
        let t = T0 + (10 + k as u64) * 1_000_000_000;
        let px = Pixels::mono16_from_image(&micrograph(100 + k as u32));
        rec.image(topics::SEM_FRAME, t, role.as_str(), &px, 8, 6)
            .unwrap();
        rec.json(
            topics::SEM_FRAME_INFO,
            t,
            &frame_info(role, 3 + k as u64, tilt),
        )
        .unwrap();
    }
    let t = T0 + 20_000_000_000;
    let mut height = Image::from_fn(8, 6, |x, y| x as f32 * 0.5 - y as f32);
    height.set(3, 2, f32::NAN);
    rec.image(
        topics::RECON_HEIGHT,
        t,
        "left",
        &Pixels::float32_from_image(&height),
        8,
        6,
    )
    .unwrap();
    let cloud = crate::export::cloud_from_height(&height, 0.05, Some(&micrograph(100)));
    rec.point_cloud(topics::RECON_POINTCLOUD, t, "left", &cloud)
        .unwrap();
    rec.json(
        topics::RECON_REPORT,
        t,
        &serde_json::json!({"matches": 120, "final_error_px": 0.4}),
    )
    .unwrap();
    rec.log(
        t,
        LogLevel::Warning,
        "drift 2.5 px",
        "sdsem::acquisition",
        "acq.rs",
        10,
    )
    .unwrap();
    rec.attachment(
        t,
        topics::ATTACHMENT_HEIGHT_GSF,
        "application/octet-stream",
        b"GSF".to_vec(),
    )
    .unwrap();
    rec.attachment(
        t,
        topics::ATTACHMENT_MESH_PLY,
        "application/x-ply",
        b"ply\n".to_vec(),
    )
    .unwrap();
    rec.outcome(&RunOutcome {
        status: RunStatus::Succeeded,
        cause: None,
    })
    .unwrap();
    recorder.finish().unwrap()
}

#[test]
fn every_topic_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    let summary = write_full_run(&path);
    assert_eq!(summary.messages_per_topic[topics::SEM_FRAME], 5);
    assert_eq!(summary.messages_per_topic[topics::SEM_FRAME_INFO], 5);
    assert_eq!(summary.messages, 5 + 5 + 3 + 3 + 1 + 1 + 1 + 1);
    assert_eq!((summary.attachments, summary.metadata_records), (2, 2));
    assert_eq!(summary.time_range_ns, Some((T0, T0 + 20_000_000_000)));
    assert!(summary.chunks >= 7, "a chunk per frame: {}", summary.chunks);

    let inspection = read_summary(&path).unwrap();
    assert!(inspection.end.complete, "{:?}", inspection.end);
    let schema = |topic: &str| {
        inspection
            .topics
            .iter()
            .find(|t| t.topic == topic)
            .map(|t| {
                (
                    t.schema_name.as_str(),
                    t.schema_encoding.as_str(),
                    t.message_encoding.as_str(),
                )
            })
            .unwrap()
    };
    assert_eq!(
        schema(topics::SEM_FRAME),
        ("foxglove.RawImage", "protobuf", "protobuf")
    );
    assert_eq!(
        schema(topics::SEM_FRAME_INFO),
        ("sdsem.FrameInfo", "jsonschema", "json")
    );
    assert_eq!(
        schema(topics::STAGE_STATE),
        ("sdsem.StageState", "jsonschema", "json")
    );
    assert_eq!(
        schema(topics::STAGE_IO),
        ("sdsem.StageIo", "jsonschema", "json")
    );
    assert_eq!(
        schema(topics::RECON_HEIGHT),
        ("foxglove.RawImage", "protobuf", "protobuf")
    );
    assert_eq!(
        schema(topics::RECON_POINTCLOUD),
        ("foxglove.PointCloud", "protobuf", "protobuf")
    );
    assert_eq!(
        schema(topics::RECON_REPORT),
        ("sdsem.ReconReport", "jsonschema", "json")
    );
    assert_eq!(
        schema(topics::LOG),
        ("foxglove.Log", "protobuf", "protobuf")
    );
    let roles: Vec<(&str, u64)> = inspection
        .frames_by_role
        .iter()
        .map(|(k, v)| (k.as_str(), *v))
        .collect();
    assert_eq!(roles, [("left", 1), ("right", 1), ("tracking", 3)]);
    assert_eq!(
        inspection.metadata_record(topics::METADATA_RUN).unwrap()["job"],
        "job-42"
    );
    assert_eq!(
        inspection.outcome,
        Some(RunOutcome {
            status: RunStatus::Succeeded,
            cause: None
        })
    );
    assert_eq!(inspection.report.as_ref().unwrap()["matches"], 120);
    assert_eq!(inspection.attachments.len(), 2);
    assert_eq!(inspection.log_levels[&LogLevel::Warning], 1);
    let text = format_inspection(&inspection);
    assert!(
        text.contains("complete") && text.contains("succeeded"),
        "{text}"
    );
    assert!(text.contains("left 1, right 1, tracking 3"), "{text}");

    // Pixels, JSON, clouds, logs and attachments come back unchanged.
    let ends = read_images(&path, topics::SEM_FRAME, |id| id != "tracking").unwrap();
    assert!(ends.end.complete);
    assert_eq!(ends.items.len(), 2);
    assert_eq!(ends.items[0].frame_id, "left");
    assert_eq!(
        ends.items[0].pixels,
        Pixels::mono16_from_image(&micrograph(100))
    );
    let left = ends.items[0].to_image().unwrap();
    assert!((left.get(3, 2) - micrograph(100).get(3, 2)).abs() < 1e-4);

    let infos = read_json(&path, topics::SEM_FRAME_INFO).unwrap();
    let parsed: Vec<FrameInfo> = infos.items.iter().map(|j| j.parse().unwrap()).collect();
    assert_eq!(parsed[4], frame_info(FrameRole::Right, 4, 3.0));
    assert_eq!(infos.items[4].log_time_ns, T0 + 11_000_000_000);

    let heights = read_images(&path, topics::RECON_HEIGHT, |_| true).unwrap();
    let h = heights.items[0].to_image().unwrap();
    assert!(h.get(3, 2).is_nan());
    assert_eq!(h.get(7, 5), 7.0 * 0.5 - 5.0);

    let clouds = read_point_clouds(&path, topics::RECON_POINTCLOUD).unwrap();
    assert_eq!(clouds.items[0].points.len(), 47);
    let logs = read_logs(&path).unwrap();
    assert_eq!(logs.items[0].message, "drift 2.5 px");
    assert_eq!(logs.items[0].level, LogLevel::Warning);
    assert_eq!(
        (logs.items[0].file.as_str(), logs.items[0].line),
        ("acq.rs", 10)
    );
    let mesh = read_attachments(&path, |n| n == topics::ATTACHMENT_MESH_PLY).unwrap();
    assert_eq!(mesh.items[0].data, b"ply\n");
    let meta = read_metadata(&path).unwrap();
    assert_eq!(meta.items.len(), 2);
}

/// Chunk ends of the finished file, with the log times of the messages they hold.
fn chunk_ends(bytes: &[u8]) -> Vec<(u64, u64, u64)> {
    let summary = mcap::Summary::read(bytes).unwrap().unwrap();
    summary
        .chunk_indexes
        .iter()
        .map(|c| {
            (
                c.chunk_start_offset + c.chunk_length,
                c.message_start_time,
                c.message_end_time,
            )
        })
        .collect()
}

/// A recorder whose chunks are cut by frames alone (no timed flush in a test's time).
fn recorder_cut_by_frames_only(path: &Path) -> Recorder {
    Recorder::create(
        path,
        RecorderOptions {
            flush_interval: Duration::from_secs(3600),
            ..fast_options()
        },
    )
    .unwrap()
}

/// The writer only appends, so a run killed at any moment leaves a prefix of the finished
/// file. Every prefix must yield exactly the frames whose chunk it holds whole.
#[test]
fn truncated_record_recovers_every_completed_frame() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    // Only frames cut chunks here, so the oracle below is exact.
    let recorder = recorder_cut_by_frames_only(&path);
    let rec = recorder.handle();
    let frames = 12u64;
    for i in 0..frames {
        rec.json(
            topics::STAGE_IO,
            T0 + i * 10,
            &serde_json::json!({"command": "MOV"}),
        )
        .unwrap();
        let px = Pixels::mono8_from_image(&micrograph(i as u32));
        rec.image(topics::SEM_FRAME, T0 + i * 10 + 1, "tracking", &px, 8, 6)
            .unwrap();
    }
    recorder.finish().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let ends = chunk_ends(&bytes);
    // Frame i (log time T0 + 10 i + 1) is recoverable once its chunk is whole.
    let frame_end = |i: u64| {
        let t = T0 + i * 10 + 1;
        ends.iter()
            .find(|(_, a, b)| (*a..=*b).contains(&t))
            .map(|(end, _, _)| *end)
            .unwrap()
    };
    let mut offsets: Vec<u64> = (0..bytes.len() as u64).step_by(211).collect();
    for i in 0..frames {
        let e = frame_end(i);
        offsets.extend([e - 1, e, e + 1]);
    }
    offsets.push(bytes.len() as u64);
    offsets.sort_unstable();
    offsets.dedup();
    let cut = dir.path().join("cut.mcap");
    let mut last = 0;
    for &k in &offsets {
        std::fs::write(&cut, &bytes[..k as usize]).unwrap();
        let expected = (0..frames).filter(|&i| frame_end(i) <= k).count();
        match read_images(&cut, topics::SEM_FRAME, |_| true) {
            Ok(got) => {
                // Every frame whose chunk is whole comes back; the frame of the chunk being
                // cut may too, when all its compressed bytes but the LZ4 end mark are there
                // (its content CRC is checked before it is handed out).
                let n = got.items.len();
                assert!(
                    n == expected || (n == expected + 1 && k + 4 >= frame_end(n as u64 - 1)),
                    "truncated at {k} of {}: {n} frames, expected {expected}",
                    bytes.len()
                );
                assert!(n >= last, "fewer frames from a longer prefix at {k}");
                for (i, frame) in got.items.iter().enumerate() {
                    assert_eq!(
                        frame.pixels,
                        Pixels::mono8_from_image(&micrograph(i as u32))
                    );
                }
                assert_eq!(got.end.complete, k == bytes.len() as u64, "at {k}");
                if n > 0 {
                    let summary = read_summary(&cut).unwrap();
                    assert_eq!(summary.frames_by_role["tracking"], n as u64);
                    if k < bytes.len() as u64 {
                        assert!(format_inspection(&summary).contains("INCOMPLETE"));
                    }
                }
                last = n;
            }
            // Too short to hold the MCAP header: no frame could be in it.
            Err(ReadError::NotMcap { .. }) => assert_eq!((expected, last), (0, 0), "at {k}"),
            Err(e) => panic!("at {k}: {e}"),
        }
    }
    assert_eq!(last, frames as usize);
}

/// While the run is still recording, every frame sent so far is already readable.
#[test]
fn frames_are_readable_before_finish() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("live.mcap");
    let recorder = Recorder::create(&path, fast_options()).unwrap();
    let rec = recorder.handle();
    for i in 0..4u64 {
        let px = Pixels::mono8_from_image(&micrograph(i as u32));
        rec.image(topics::SEM_FRAME, T0 + i, "tracking", &px, 8, 6)
            .unwrap();
    }
    // Wait for the writer thread to take them (bounded: the test fails rather than hangs).
    for _ in 0..500 {
        if rec.status().entries_written == 4 {
            break;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let live = read_images(&path, topics::SEM_FRAME, |_| true).unwrap();
    assert_eq!(live.items.len(), 4);
    assert!(!live.end.complete);
    let summary = read_summary(&path).unwrap();
    assert!(format_inspection(&summary).contains("unknown — the run ended without finishing"));
    recorder.finish().unwrap();
}

/// A run killed right after it started still leaves a readable record with
/// its metadata (the configuration), not an empty file.
#[test]
fn metadata_is_readable_before_the_first_frame() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("early.mcap");
    let recorder = Recorder::create(&path, fast_options()).unwrap();
    let rec = recorder.handle();
    rec.metadata(
        topics::METADATA_RUN,
        [("config".to_owned(), "[run]\n".to_owned())].into(),
    )
    .unwrap();
    for _ in 0..500 {
        if rec.status().entries_written == 1 {
            break;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let live = read_metadata(&path).unwrap();
    assert_eq!(live.items.len(), 1, "{:?}", live.end);
    assert_eq!(live.items[0].name, topics::METADATA_RUN);
    assert!(!live.end.complete);
    recorder.finish().unwrap();
}

#[test]
fn dropping_an_unfinished_recorder_still_completes_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("dropped.mcap");
    {
        let recorder = Recorder::create(&path, fast_options()).unwrap();
        recorder
            .handle()
            .json(
                topics::STAGE_IO,
                T0,
                &serde_json::json!({"command": "ERR?"}),
            )
            .unwrap();
    }
    let inspection = read_summary(&path).unwrap();
    assert!(inspection.end.complete);
    assert_eq!(inspection.message_count(topics::STAGE_IO), 1);
}

#[test]
fn sends_after_finish_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let recorder = Recorder::create(dir.path().join("r.mcap"), fast_options()).unwrap();
    let rec = recorder.handle();
    recorder.finish().unwrap();
    assert!(matches!(
        rec.json(topics::STAGE_IO, T0, &1),
        Err(RecordError::Closed)
    ));
    assert!(rec.status().finished);
    assert!(!rec.try_send_log(Entry::log(T0, LogLevel::Info, "late", "t", "f", 1).unwrap()));
}

#[test]
fn invalid_directory_names_the_path() {
    let err = Recorder::create("/nonexistent-dir/run.mcap", fast_options()).unwrap_err();
    assert!(
        err.to_string().contains("/nonexistent-dir/run.mcap"),
        "{err}"
    );
}

/// A full disk stops the recorder once: the status says why, later sends are refused
/// without repeating the cause, and `finish()` returns it.
#[cfg(target_os = "linux")]
#[test]
fn disk_full_is_reported_once() {
    let full = Path::new("/dev/full");
    if !full.exists() {
        return;
    }
    let recorder = Recorder::create(full, fast_options()).unwrap();
    let rec = recorder.handle();
    let px = Pixels::mono8_from_image(&micrograph(0));
    // The first frame's flush hits ENOSPC.
    let _ = rec.image(topics::SEM_FRAME, T0, "tracking", &px, 8, 6);
    for _ in 0..500 {
        if rec.status().failed.is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let failed = rec
        .status()
        .failed
        .expect("the write error is visible in the status");
    assert!(failed.contains("No space left on device"), "{failed}");
    assert!(matches!(
        rec.image(topics::SEM_FRAME, T0 + 1, "tracking", &px, 8, 6),
        Err(RecordError::Stopped { .. })
    ));
    let err = recorder.finish().unwrap_err();
    assert!(err.to_string().contains("No space left on device"), "{err}");
}

#[test]
fn tracing_layer_forwards_while_attached() {
    use tracing_subscriber::prelude::*;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("log.mcap");
    let recorder = Recorder::create(&path, fast_options()).unwrap();
    let (layer, switch) = record_log_layer(tracing::Level::INFO);
    let subscriber = tracing_subscriber::registry().with(layer);
    tracing::subscriber::with_default(subscriber, || {
        tracing::info!("before attach");
        switch.attach(recorder.handle());
        assert!(switch.is_attached());
        let span = tracing::info_span!("run");
        let _guard = span.enter();
        tracing::info!(tilt_deg = 3.0, "tilted");
        tracing::debug!("too verbose");
        tracing::error!("stage lost");
        switch.detach();
        tracing::info!("after detach");
    });
    recorder.finish().unwrap();
    let logs = read_logs(&path).unwrap();
    let messages: Vec<(&str, LogLevel)> = logs
        .items
        .iter()
        .map(|l| (l.message.as_str(), l.level))
        .collect();
    assert_eq!(
        messages,
        [
            ("run: tilted tilt_deg=3.0", LogLevel::Info),
            ("run: stage lost", LogLevel::Error)
        ]
    );
    assert!(logs.items[0].name.contains("record"));
    assert!(logs.items[0].file.ends_with("tests.rs"));
}

#[tokio::test]
async fn async_sends_wait_for_room_and_lose_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("async.mcap");
    let recorder = Recorder::create(
        &path,
        RecorderOptions {
            channel_capacity: 1,
            ..fast_options()
        },
    )
    .unwrap();
    let rec = recorder.handle();
    for i in 0..40u64 {
        let px = Pixels::mono8_from_image(&micrograph(i as u32));
        rec.send_async(Entry::image(topics::SEM_FRAME, T0 + i, "tracking", &px, 8, 6).unwrap())
            .await
            .unwrap();
    }
    let summary = tokio::task::spawn_blocking(move || recorder.finish())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(summary.messages_per_topic[topics::SEM_FRAME], 40);
}

#[test]
fn reading_a_non_mcap_file_says_so() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("x.mcap");
    std::fs::write(&path, b"definitely not mcap, just text").unwrap();
    let err = read_summary(&path).unwrap_err();
    assert!(err.to_string().contains("not an MCAP file"), "{err}");
}

/// Writes a sample record for the Python check (`tests/check_mcap.py`):
/// `SDSEM_MCAP_SAMPLE=/tmp/sample.mcap cargo test -p sdsem --lib record::tests::write_sample -- --ignored`
#[test]
#[ignore = "writes a sample file for the external Python reader check"]
fn write_sample() {
    let path =
        std::env::var("SDSEM_MCAP_SAMPLE").unwrap_or_else(|_| "/tmp/sdsem-sample.mcap".into());
    let summary = write_full_run(Path::new(&path));
    println!("wrote {path}: {summary:?}");
}

#[test]
fn cloud_points_survive_record() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cloud.mcap");
    let recorder = Recorder::create(&path, fast_options()).unwrap();
    let points = [
        CloudPoint {
            x: 1.0,
            y: -2.0,
            z: 3.5,
            intensity: 0.25,
        },
        CloudPoint {
            x: f32::MAX,
            y: 0.0,
            z: -0.0,
            intensity: 1.0,
        },
    ];
    recorder
        .handle()
        .point_cloud(topics::RECON_POINTCLOUD, T0, "left", &points)
        .unwrap();
    recorder.finish().unwrap();
    let back = read_point_clouds(&path, topics::RECON_POINTCLOUD).unwrap();
    assert_eq!(back.items[0].points, points);
    assert_eq!(back.items[0].frame_id, "left");
}

#[test]
fn end_micrographs_come_back_with_their_parameters() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    let recorder = Recorder::create(&path, fast_options()).unwrap();
    let rec = recorder.handle();
    rec.frame(
        T0,
        &micrograph(1),
        &frame_info(FrameRole::Tracking, 0, -3.0),
    )
    .unwrap();
    rec.frame(
        T0 + 1,
        &micrograph(2),
        &frame_info(FrameRole::Left, 1, -3.0),
    )
    .unwrap();
    rec.frame(
        T0 + 2,
        &micrograph(3),
        &frame_info(FrameRole::Right, 2, 3.0),
    )
    .unwrap();
    let wrong = frame_info(FrameRole::Left, 3, 0.0);
    let err = rec.frame(T0 + 3, &Image::zeros(4, 4), &wrong).unwrap_err();
    assert!(err.to_string().contains("8 × 6"), "{err}");
    let mut height = Image::filled(8, 6, 1.5);
    height.set(0, 0, f32::NAN);
    rec.height(T0 + 4, &height).unwrap();
    recorder.finish().unwrap();

    let ends = read_end_micrographs(&path).unwrap();
    let left = ends.left.unwrap();
    let right = ends.right.unwrap();
    assert_eq!(left.info.unwrap().tilt_deg, -3.0);
    assert_eq!(right.info.as_ref().unwrap().tilt_deg, 3.0);
    assert_eq!(right.log_time_ns, T0 + 2);
    for (a, b) in micrograph(3).data().iter().zip(right.image.data()) {
        assert!((a - b).abs() < 1e-4);
    }
    let h = &read_images(&path, topics::RECON_HEIGHT, |id| id == "left")
        .unwrap()
        .items[0];
    assert!(h.to_image().unwrap().get(0, 0).is_nan());
}

/// A record cut anywhere never holds a frame without its `/sem/frame_info`
/// (replay needs the tilt and pixel size of the end micrographs).
#[test]
fn a_cut_record_never_separates_a_frame_from_its_info() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.mcap");
    let recorder = recorder_cut_by_frames_only(&path);
    let rec = recorder.handle();
    rec.frame(T0, &micrograph(1), &frame_info(FrameRole::Left, 0, -3.0))
        .unwrap();
    rec.json(
        topics::STAGE_IO,
        T0 + 1,
        &serde_json::json!({"command": "MOV"}),
    )
    .unwrap();
    rec.frame(
        T0 + 2,
        &micrograph(2),
        &frame_info(FrameRole::Right, 1, 3.0),
    )
    .unwrap();
    rec.height(T0 + 3, &Image::filled(8, 6, 1.0)).unwrap();
    recorder.finish().unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.path().join("cut.mcap");
    let (mut left_seen, mut right_seen) = (false, false);
    for len in (0..bytes.len()).step_by(7) {
        std::fs::write(&cut, &bytes[..len]).unwrap();
        let Ok(ends) = read_end_micrographs(&cut) else {
            continue;
        };
        for m in [ends.left, ends.right].into_iter().flatten() {
            assert!(
                m.info.is_some(),
                "{:?} frame without info at {len} bytes",
                m.role
            );
            left_seen |= m.role == FrameRole::Left;
            right_seen |= m.role == FrameRole::Right;
        }
    }
    assert!(left_seen && right_seen, "the cuts reached both frames");
}

/// Logs may be dropped under backpressure, never silently: what was written plus what
/// was counted as dropped is what was sent, and the count is in the record.
#[test]
fn log_drops_are_counted_and_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("logs.mcap");
    let recorder = Recorder::create(
        &path,
        RecorderOptions {
            channel_capacity: 1,
            ..fast_options()
        },
    )
    .unwrap();
    let rec = recorder.handle();
    let sent = 5000;
    let mut queued = 0;
    for i in 0..sent {
        let entry = Entry::log(T0 + i, LogLevel::Info, "tick", "t", "f.rs", 1).unwrap();
        queued += usize::from(rec.try_send_log(entry));
    }
    let summary = recorder.finish().unwrap();
    let written = read_logs(&path).unwrap().items.len();
    assert_eq!(written, queued);
    assert_eq!(written as u64 + summary.log_messages_dropped, sent);
    let drops = read_metadata(&path)
        .unwrap()
        .items
        .into_iter()
        .find(|m| m.name == topics::METADATA_LOG_DROPS);
    match drops {
        Some(m) => assert_eq!(
            m.entries["dropped"],
            summary.log_messages_dropped.to_string()
        ),
        None => assert_eq!(summary.log_messages_dropped, 0),
    }
}

/// The child half of `killed_run_keeps_every_flushed_frame`: records frames until killed,
/// publishing how many are flushed. Does nothing unless the parent test started it.
#[test]
#[ignore = "child process of killed_run_keeps_every_flushed_frame"]
fn child_records_until_killed() {
    let Some(path) = std::env::var_os("SDSEM_KILL_CHILD_RECORD") else {
        return;
    };
    let path = std::path::PathBuf::from(path);
    let progress = path.with_extension("progress");
    let recorder = Recorder::create(&path, fast_options()).unwrap();
    let rec = recorder.handle();
    for i in 0u64.. {
        rec.frame(
            T0 + i,
            &micrograph(i as u32),
            &frame_info(FrameRole::Tracking, i, 0.0),
        )
        .unwrap();
        // Two entries per frame (image, info); the chunk is flushed with the info, so the
        // counter moves only once both are written.
        while rec.status().entries_written < 2 * (i + 1) {
            std::thread::yield_now();
        }
        let tmp = path.with_extension("progress.tmp");
        std::fs::write(&tmp, (i + 1).to_string()).unwrap();
        std::fs::rename(&tmp, &progress).unwrap();
    }
    drop(recorder);
}

/// A run killed with SIGKILL in the middle of recording keeps every frame it had flushed.
#[cfg(unix)]
#[test]
fn killed_run_keeps_every_flushed_frame() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("killed.mcap");
    let progress = path.with_extension("progress");
    let mut child = std::process::Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "record::tests::child_records_until_killed",
            "--ignored",
            "--test-threads=1",
        ])
        .env("SDSEM_KILL_CHILD_RECORD", &path)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let read_progress = || {
        std::fs::read_to_string(&progress)
            .ok()
            .and_then(|s| s.parse::<usize>().ok())
            .unwrap_or(0)
    };
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    while read_progress() < 20 {
        assert!(
            std::time::Instant::now() < deadline,
            "child made no progress"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    let flushed = read_progress();
    let frames = read_images(&path, topics::SEM_FRAME, |_| true).unwrap();
    assert!(!frames.end.complete);
    assert!(
        frames.items.len() >= flushed,
        "{} frames recovered, {flushed} were flushed",
        frames.items.len()
    );
    for (i, f) in frames.items.iter().enumerate() {
        assert_eq!(f.pixels, Pixels::mono16_from_image(&micrograph(i as u32)));
    }
    let inspection = read_summary(&path).unwrap();
    assert!(format_inspection(&inspection).contains("INCOMPLETE"));
}

/// Indicative figures for full-size frames (the CPU is shared while we develop):
/// `cargo test -p sdsem --lib record::tests::throughput -- --ignored --nocapture`
#[test]
#[ignore = "evaluation: prints timings"]
fn throughput() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("big.mcap");
    let (w, h) = (2048usize, 1536usize);
    let frames = 20u64;
    // A textured micrograph (LZ4 does not shrink noise, nor does it for real SEM frames).
    let mut state = 12345u32;
    let image = Image::from_fn(w, h, |x, y| {
        state = state.wrapping_mul(1_103_515_245).wrapping_add(12345);
        let noise = (state >> 16) as f32 / 65536.0;
        0.5 + 0.3 * ((x as f32 * 0.01).sin() * (y as f32 * 0.013).cos()) + 0.1 * noise
    });
    for fsync in [false, true] {
        let recorder = Recorder::create(
            &path,
            RecorderOptions {
                fsync,
                ..RecorderOptions::default()
            },
        )
        .unwrap();
        let rec = recorder.handle();
        let start = std::time::Instant::now();
        for i in 0..frames {
            let mut info = frame_info(FrameRole::Tracking, i, i as f64);
            info.width = w as u32;
            info.height = h as u32;
            rec.frame(T0 + i * 1_000_000_000, &image, &info).unwrap();
        }
        let summary = recorder.finish().unwrap();
        let write = start.elapsed();
        let start = std::time::Instant::now();
        let inspection = read_summary(&path).unwrap();
        let inspect = start.elapsed();
        assert_eq!(inspection.frames_by_role["tracking"], frames);
        println!(
            "fsync={fsync}: {frames} frames {w}x{h} mono16 written in {:.2} s ({:.0} ms/frame, \
             encode+write+flush), file {:.1} MiB ({:.0}% of raw), read_summary {:.2} s",
            write.as_secs_f64(),
            write.as_secs_f64() * 1e3 / frames as f64,
            summary.file_bytes as f64 / (1 << 20) as f64,
            100.0 * summary.file_bytes as f64 / (frames as f64 * (w * h * 2) as f64),
            inspect.as_secs_f64()
        );
    }
}
