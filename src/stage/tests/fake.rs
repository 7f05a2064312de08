//! Driver against a scripted controller and the simulator's model, paused clock.

use std::sync::Arc;
use std::time::Duration;

use sdsem_protocol::gcs::{GcsErrorCode, PositionQuery};
use sdsem_sim::{FaultTrigger, StageSimConfig};
use tokio::time::Instant;

use super::{Act, driver_config, lines, modelled, reply, scripted, snapshot};
use crate::stage::{
    IoOutcome, MemoryObserver, NoopObserver, StageAxis, StageDriver, StageError, StageEvent,
};

/// Answers to what `connect` asks, for a ready controller at the origin.
fn basic(text: &str) -> Vec<Act> {
    match text {
        "*IDN?" => reply("fake GCS controller\n"),
        "ERR?" => reply("0\n"),
        "SVO? X Y T" | "FRF? X Y T" => reply("X=1 \nY=1 \nT=1\n"),
        "TMN? X Y T" => reply("X=-5000 \nY=-5000 \nT=-5\n"),
        "TMX? X Y T" => reply("X=5000 \nY=5000 \nT=70\n"),
        "POS? X Y T" => reply("X=0 \nY=0 \nT=0\n"),
        other => panic!("unscripted command {other:?}"),
    }
}

fn count(log: &[String], line: &str) -> usize {
    log.iter().filter(|l| l.as_str() == line).count()
}

#[tokio::test(start_paused = true)]
async fn tilts_0_to_7_in_1_degree_steps_each_verified() {
    let (io, model, start, _) = modelled(StageSimConfig::default());
    let observer = Arc::new(MemoryObserver::default());
    let mut stage = StageDriver::connect(io, driver_config(), observer.clone())
        .await
        .unwrap();
    assert!(stage.identity().contains("sdsem-sim"));
    for deg in 0..=7 {
        let target = f64::from(deg);
        let report = stage.move_tilt(target).await.unwrap();
        let reached = report.positions[0].1;
        assert!(
            (reached - target).abs() <= 0.01,
            "{target}: read back {reached}"
        );
        // The true stage is there and settled when the driver says so.
        let truth = snapshot(&model, start);
        assert!((truth.pose.tilt_deg - target).abs() <= 0.01);
        assert!(
            truth.axes[2].on_target,
            "returned before the stage settled at {target}"
        );
        assert!(!report.reissued);
    }
    let states = observer.states();
    assert_eq!(
        states
            .iter()
            .filter(|s| s.event == StageEvent::Reached)
            .count(),
        8
    );
    assert_eq!(states[0].event, StageEvent::Connected);
    // Every command sent was recorded, with timestamps, and every query with its RTT.
    let io = observer.io_records();
    assert!(
        io.iter()
            .all(|r| r.sent_wall_ns.is_some() && r.command.is_some())
    );
    assert!(
        io.iter()
            .filter(|r| r.outcome == IoOutcome::Replied)
            .all(|r| r.rtt_ns.is_some() && r.reply.is_some())
    );
    assert_eq!(
        io.iter()
            .filter(|r| r.command.as_deref() == Some("MOV T 7"))
            .count(),
        1
    );
    // Serialisable for the recorder.
    let json = serde_json::to_string(&io[0]).unwrap();
    assert!(json.contains("\"outcome\":\"replied\""), "{json}");
}

#[tokio::test(start_paused = true)]
async fn xy_moves_are_verified_together() {
    let (io, model, start, log) = modelled(StageSimConfig::default());
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let report = stage.move_xy(120.0, -35.5).await.unwrap();
    assert_eq!(report.positions.len(), 2);
    let pose = snapshot(&model, start).pose;
    assert!(
        (pose.x_um - 120.0).abs() <= 0.1 && (pose.y_um + 35.5).abs() <= 0.1,
        "{pose:?}"
    );
    assert_eq!(
        count(&lines(&log), "MOV X 120 Y -35.5"),
        1,
        "one command moves both axes"
    );
}

#[tokio::test(start_paused = true)]
async fn stale_on_target_flag_does_not_end_the_move_early() {
    let mut sim = StageSimConfig::default();
    sim.faults.stale_on_target = FaultTrigger::at([1]);
    sim.faults.stale_on_target_s = 1.5;
    let (io, model, start, _) = modelled(sim);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let report = stage.move_tilt(3.0).await.unwrap();
    let truth = snapshot(&model, start);
    assert_eq!(truth.faults.stale_on_target, 1, "the fault fired");
    assert!(
        truth.axes[2].on_target && (truth.pose.tilt_deg - 3.0).abs() <= 0.01,
        "{truth:?}"
    );
    assert!(
        report.elapsed >= Duration::from_secs(3),
        "returned mid-move: {report:?}"
    );
    assert!(!report.reissued, "a moving stage is not a silent non-move");
}

#[tokio::test(start_paused = true)]
async fn a_move_that_silently_did_not_happen_is_reissued_once() {
    let mut sim = StageSimConfig::default();
    sim.faults.ignore_move = FaultTrigger::at([1]);
    let (io, model, start, log) = modelled(sim);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let report = stage.move_tilt(2.0).await.unwrap();
    assert!(report.reissued);
    assert_eq!(count(&lines(&log), "MOV T 2"), 2);
    let truth = snapshot(&model, start);
    assert_eq!(truth.faults.ignored_moves, 1);
    assert!((truth.pose.tilt_deg - 2.0).abs() <= 0.01);
}

#[tokio::test(start_paused = true)]
async fn a_move_that_never_happens_is_an_error_after_one_retry() {
    let mut sim = StageSimConfig::default();
    sim.faults.ignore_move = FaultTrigger::probability(1.0);
    let (io, _, _, log) = modelled(sim);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let err = stage.move_tilt(2.0).await.unwrap_err();
    assert!(
        matches!(err, StageError::MoveNotExecuted { axis: StageAxis::Tilt, target, position, .. } if target == 2.0 && position == 0.0),
        "{err}"
    );
    assert_eq!(count(&lines(&log), "MOV T 2"), 2, "re-issued exactly once");
    assert!(
        err.to_string()
            .contains("re-issuing the move once did not help")
    );
}

#[tokio::test(start_paused = true)]
async fn out_of_limit_targets_are_refused_before_anything_is_sent() {
    let (io, log) = scripted(basic);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let before = lines(&log).len();
    for bad in [70.5, -5.01, f64::NAN, f64::INFINITY] {
        let err = stage.move_tilt(bad).await.unwrap_err();
        assert!(
            matches!(
                err,
                StageError::OutOfLimits {
                    axis: StageAxis::Tilt,
                    ..
                }
            ),
            "{err}"
        );
        assert!(err.to_string().contains("nothing was sent"));
    }
    let err = stage.move_xy(0.0, 5000.5).await.unwrap_err();
    assert!(
        matches!(
            err,
            StageError::OutOfLimits {
                axis: StageAxis::Y,
                ..
            }
        ),
        "{err}"
    );
    assert_eq!(
        lines(&log).len(),
        before,
        "a command went out: {:?}",
        &lines(&log)[before..]
    );
}

#[tokio::test(start_paused = true)]
async fn controller_soft_limits_narrow_the_configured_ones() {
    let (io, log) = scripted(|t| match t {
        "TMX? X Y T" => reply("X=5000 \nY=5000 \nT=45\n"),
        other => basic(other),
    });
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    assert_eq!(stage.limits(StageAxis::Tilt), (-5.0, 45.0));
    let before = lines(&log).len();
    assert!(
        matches!(stage.move_tilt(50.0).await, Err(StageError::OutOfLimits { max, .. }) if max == 45.0)
    );
    assert_eq!(lines(&log).len(), before);
}

#[tokio::test(start_paused = true)]
async fn dropped_reply_is_explained_by_err_then_retried() {
    let mut first = true;
    let (io, log) = scripted(move |t| match t {
        "POS? X Y T" if first => {
            first = false;
            Vec::new()
        }
        other => basic(other),
    });
    let observer = Arc::new(MemoryObserver::default());
    let t0 = Instant::now();
    let mut stage = StageDriver::connect(io, driver_config(), observer.clone())
        .await
        .unwrap();
    // One timeout (1 s) plus the wait for a late reply (1 s).
    assert!(t0.elapsed() >= Duration::from_secs(2));
    let log = lines(&log);
    let i = log.iter().position(|l| l == "POS? X Y T").unwrap();
    assert_eq!(&log[i..i + 3], ["POS? X Y T", "ERR?", "POS? X Y T"]);
    let io = observer.io_records();
    assert!(
        io.iter()
            .any(|r| r.outcome == IoOutcome::Timeout && r.command.as_deref() == Some("POS? X Y T"))
    );
    assert!(
        io.iter()
            .any(|r| r.attempt == 2 && r.outcome == IoOutcome::Replied)
    );
    stage.position().await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn garbled_and_unframeable_replies_are_retried() {
    let mut n = 0;
    let (io, log) = scripted(move |t| match t {
        "POS? T" => {
            n += 1;
            match n {
                1 => reply("T=1.0#0000\n"),
                2 => vec![Act::Reply(b"T=\xff\xfe\n".to_vec())],
                _ => reply("T=1.000000\n"),
            }
        }
        other => basic(other),
    });
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let pos = stage
        .query(&PositionQuery(vec![stage.config().axis_tilt.clone()]))
        .await
        .unwrap();
    assert_eq!(pos[0].1, 1.0);
    assert_eq!(count(&lines(&log), "POS? T"), 3);
}

#[tokio::test(start_paused = true)]
async fn overlong_garbage_line_is_survived() {
    let mut n = 0;
    let (io, _) = scripted(move |t| match t {
        "POS? T" => {
            n += 1;
            if n == 1 {
                vec![Act::Reply(vec![b'7'; 10_000])]
            } else {
                reply("T=2.000000\n")
            }
        }
        other => basic(other),
    });
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let pos = stage
        .query(&PositionQuery(vec![stage.config().axis_tilt.clone()]))
        .await
        .unwrap();
    assert_eq!(pos[0].1, 2.0);
}

#[tokio::test(start_paused = true)]
async fn retries_are_bounded() {
    let (io, log) = scripted(|t| match t {
        "POS? T" => Vec::new(),
        other => basic(other),
    });
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let err = stage
        .query(&PositionQuery(vec![stage.config().axis_tilt.clone()]))
        .await
        .unwrap_err();
    assert!(
        matches!(err, StageError::NoReply { attempts: 3, .. }),
        "{err}"
    );
    assert_eq!(count(&lines(&log), "POS? T"), 3, "1 + query_retries (2)");
    assert!(err.to_string().contains("POS? T"));
}

#[tokio::test(start_paused = true)]
async fn late_reply_is_discarded_not_taken_for_the_next_answer() {
    let mut n = 0;
    let (io, _) = scripted(move |t| match t {
        "POS? T" => {
            n += 1;
            if n == 1 {
                // Older value, 1.5 s late (timeout 1 s).
                vec![Act::Later(
                    Duration::from_millis(1500),
                    b"T=1.000000\n".to_vec(),
                )]
            } else {
                reply("T=2.000000\n")
            }
        }
        other => basic(other),
    });
    let observer = Arc::new(MemoryObserver::default());
    let mut stage = StageDriver::connect(io, driver_config(), observer.clone())
        .await
        .unwrap();
    let tilt = stage.config().axis_tilt.clone();
    let pos = stage
        .query(&PositionQuery(vec![tilt.clone()]))
        .await
        .unwrap();
    assert_eq!(pos[0].1, 2.0, "the late, older answer was taken");
    let io = observer.io_records();
    assert!(
        io.iter()
            .any(|r| r.outcome == IoOutcome::Stray && r.reply.as_deref() == Some("T=1.000000"))
    );
    // Nothing stays queued to answer a later question.
    assert_eq!(
        stage.query(&PositionQuery(vec![tilt])).await.unwrap()[0].1,
        2.0
    );
}

#[tokio::test(start_paused = true)]
async fn late_replies_from_the_simulator_model_are_survived() {
    let mut sim = StageSimConfig::default();
    sim.faults.late_reply = FaultTrigger::probability(0.2);
    sim.faults.late_reply_delay_s = 1.2;
    let (io, model, start, _) = modelled(sim);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    for deg in [1.0, 2.0, 3.0] {
        let r = stage.move_tilt(deg).await.unwrap();
        assert!((r.positions[0].1 - deg).abs() <= 0.01);
    }
    let truth = snapshot(&model, start);
    assert!(
        truth.faults.late_replies > 0,
        "the fault never fired: {truth:?}"
    );
    assert!((truth.pose.tilt_deg - 3.0).abs() <= 0.01);
}

#[tokio::test(start_paused = true)]
async fn a_cancelled_query_does_not_shift_the_replies() {
    let mut n = 0;
    let (io, _) = scripted(move |t| match t {
        "POS? T" => {
            n += 1;
            if n == 1 {
                vec![Act::Later(
                    Duration::from_millis(300),
                    b"T=1.000000\n".to_vec(),
                )]
            } else {
                reply("T=2.000000\n")
            }
        }
        other => basic(other),
    });
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let tilt = stage.config().axis_tilt.clone();
    let cut = tokio::time::timeout(
        Duration::from_millis(100),
        stage.query(&PositionQuery(vec![tilt.clone()])),
    )
    .await;
    assert!(cut.is_err(), "the query should have been cancelled");
    let pos = stage.query(&PositionQuery(vec![tilt])).await.unwrap();
    assert_eq!(pos[0].1, 2.0);
}

#[tokio::test(start_paused = true)]
async fn connect_says_exactly_what_is_not_ready() {
    let sim = StageSimConfig {
        referenced: false,
        servo_on: false,
        ..StageSimConfig::default()
    };
    let (io, _, _, log) = modelled(sim);
    let err = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .err()
        .unwrap();
    match &err {
        StageError::NotReady {
            unreferenced,
            servo_off,
        } => {
            assert_eq!(unreferenced, &["X", "Y", "T"]);
            assert_eq!(servo_off, &["X", "Y", "T"]);
        }
        other => panic!("{other}"),
    }
    let msg = err.to_string();
    assert!(
        msg.contains("servo off")
            && msg.contains("not referenced")
            && msg.contains("auto_reference"),
        "{msg}"
    );
    assert!(
        !lines(&log)
            .iter()
            .any(|l| l.starts_with("FRF ") || l.starts_with("SVO ")),
        "nothing may move"
    );
}

#[tokio::test(start_paused = true)]
async fn auto_reference_switches_servos_on_and_references() {
    let sim = StageSimConfig {
        referenced: false,
        servo_on: false,
        start_tilt_deg: 3.0,
        ..StageSimConfig::default()
    };
    let (io, model, start, _) = modelled(sim);
    let config = crate::stage::StageConfig {
        auto_reference: true,
        ..driver_config()
    };
    let mut stage = StageDriver::connect(io, config, Arc::new(NoopObserver))
        .await
        .unwrap();
    let truth = snapshot(&model, start);
    assert!(
        truth.axes.iter().all(|a| a.referenced && a.servo),
        "{truth:?}"
    );
    stage.move_tilt(1.0).await.unwrap();
}

#[tokio::test(start_paused = true)]
async fn wrong_axis_names_are_explained_by_the_controller_error() {
    let (io, _, _, _) = modelled(StageSimConfig::default());
    // Defaults 1, 2, 3: the simulator's axes are X, Y, T.
    let config = crate::stage::StageConfig {
        endpoint: "tcp://127.0.0.1:1".into(),
        ..crate::stage::StageConfig::default()
    };
    let err = StageDriver::connect(io, config, Arc::new(NoopObserver))
        .await
        .err()
        .unwrap();
    assert!(
        matches!(&err, StageError::Controller { code, .. } if *code == GcsErrorCode::INVALID_AXIS_IDENTIFIER),
        "{err}"
    );
    assert!(err.to_string().contains("axis_tilt"), "{err}");
}

#[tokio::test(start_paused = true)]
async fn controller_error_on_a_move_is_reported_with_its_remedy() {
    let mut sim = StageSimConfig::default();
    sim.faults.move_error = FaultTrigger::at([1]);
    let (io, _, _, log) = modelled(sim);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let err = stage.move_tilt(4.0).await.unwrap_err();
    assert!(
        matches!(&err, StageError::Controller { code, command, .. } if *code == GcsErrorCode::MOTION_ERROR && command == "MOV T 4"),
        "{err}"
    );
    assert!(err.to_string().contains("obstruction"));
    assert_eq!(
        count(&lines(&log), "MOV T 4"),
        1,
        "a refused move is not re-sent"
    );
}

#[tokio::test(start_paused = true)]
async fn a_move_that_does_not_finish_in_time_stops_the_stage() {
    // The stage is 100× slower than the driver expects.
    let sim = StageSimConfig {
        tilt_speed_deg_s: 0.01,
        ..StageSimConfig::default()
    };
    let (io, model, start, log) = modelled(sim);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let err = stage.move_tilt(5.0).await.unwrap_err();
    // 5° at 1°/s × 3 + 5 s margin.
    assert!(
        matches!(err, StageError::MoveTimeout { timeout, .. } if timeout == Duration::from_secs(20)),
        "{err}"
    );
    assert!(lines(&log).iter().any(|l| l == "STP"));
    let truth = snapshot(&model, start);
    assert!(!truth.axes[2].moving, "still moving after the timeout");
    assert!(truth.pose.tilt_deg < 1.0);
}

#[tokio::test(start_paused = true)]
async fn stop_halts_a_moving_stage() {
    let (io, model, start, _) = modelled(StageSimConfig::default());
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    // Abort a long move after 2 s, as a Ctrl-C handler does.
    let aborted = tokio::time::timeout(Duration::from_secs(2), stage.move_tilt(30.0)).await;
    assert!(aborted.is_err());
    stage.stop().await.unwrap();
    let at = snapshot(&model, start).pose.tilt_deg;
    tokio::time::sleep(Duration::from_secs(5)).await;
    let later = snapshot(&model, start);
    assert_eq!(later.pose.tilt_deg, at, "kept moving after STP");
    assert!(at > 1.0 && at < 3.0, "{at}");
}

#[tokio::test(start_paused = true)]
async fn disconnect_is_an_error_naming_the_command() {
    let mut sim = StageSimConfig::default();
    // connect uses 7 commands; the link drops after the first of the move.
    sim.faults.disconnect_after_commands = Some(8);
    let (io, _, _, _) = modelled(sim);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let err = stage.move_tilt(1.0).await.unwrap_err();
    assert!(matches!(&err, StageError::Disconnected { .. }), "{err}");
    assert!(err.to_string().contains("MOV T 1"), "{err}");
}

#[tokio::test(start_paused = true)]
async fn closed_link_during_a_query_is_an_error() {
    let (io, _) = scripted(|t| match t {
        "POS? T" => vec![Act::Close],
        other => basic(other),
    });
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let err = stage
        .query(&PositionQuery(vec![stage.config().axis_tilt.clone()]))
        .await
        .unwrap_err();
    assert!(
        matches!(&err, StageError::Disconnected { command, .. } if command == "POS? T"),
        "{err}"
    );
}

#[tokio::test(start_paused = true)]
async fn unexpected_identity_is_refused() {
    let (io, _) = scripted(basic);
    let config = crate::stage::StageConfig {
        expect_idn: "C-884".into(),
        ..driver_config()
    };
    let err = StageDriver::connect(io, config, Arc::new(NoopObserver))
        .await
        .err()
        .unwrap();
    assert!(
        matches!(&err, StageError::UnexpectedIdentity { idn, .. } if idn == "fake GCS controller"),
        "{err}"
    );
}

#[tokio::test(start_paused = true)]
async fn probabilistic_faults_on_every_reply_kind_are_survived() {
    let mut sim = StageSimConfig::default();
    sim.faults.drop_reply = FaultTrigger::probability(0.05);
    sim.faults.garble_reply = FaultTrigger::probability(0.05);
    sim.faults.stale_on_target = FaultTrigger::probability(0.3);
    let (io, model, start, _) = modelled(sim);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    for deg in 1..=7 {
        let target = f64::from(deg);
        match stage.move_tilt(target).await {
            Ok(r) => assert!((r.positions[0].1 - target).abs() <= 0.01),
            // A dropped ERR? reply can lose nothing but time; any other error is a bug.
            Err(e) => panic!("move to {target} lost: {e}"),
        }
    }
    let f = snapshot(&model, start).faults;
    assert!(
        f.dropped_replies + f.garbled_replies > 0,
        "no fault fired: {f:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn a_babbling_device_fails_connect_instead_of_hanging() {
    let (client, mut server) = tokio::io::duplex(4096);
    tokio::spawn(async move {
        use tokio::io::AsyncWriteExt;
        // Noise every 10 ms, forever (until the driver goes away).
        while server.write_all(b"\xf0\x0f~~").await.is_ok() {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    });
    let t0 = Instant::now();
    let err = StageDriver::connect(client, driver_config(), Arc::new(NoopObserver))
        .await
        .err()
        .unwrap();
    assert!(
        matches!(err, StageError::Garbled { .. } | StageError::NoReply { .. }),
        "{err}"
    );
    assert!(t0.elapsed() < Duration::from_secs(30), "{:?}", t0.elapsed());
}

#[tokio::test(start_paused = true)]
async fn a_watch_folder_trigger_over_pi_gcs_is_refused_and_nothing_is_sent() {
    let (io, log) = scripted(basic);
    let mut stage = StageDriver::connect(io, driver_config(), Arc::new(NoopObserver))
        .await
        .unwrap();
    let before = lines(&log).len();
    let err = stage.send_trigger("FREC").await.unwrap_err();
    assert!(matches!(err, StageError::Unsupported { .. }), "{err}");
    let msg = err.to_string();
    assert!(
        msg.contains("pi-gcs") && msg.contains("imaging.trigger"),
        "{msg}"
    );
    // A line that is not one printable command is refused before the backend sees it.
    for bad in ["", "FREC\r", " FREC", "MAC\n1"] {
        let err = stage.send_trigger(bad).await.unwrap_err();
        assert!(
            err.to_string().contains("imaging.trigger"),
            "{bad:?}: {err}"
        );
    }
    assert_eq!(lines(&log).len(), before);
}
