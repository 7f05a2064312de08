//! Driver against the real simulator, in-process, through the real transports.

use std::sync::Arc;

use sdsem_sim::{SimConfig, SimEndpoint, Simulator, StageSimConfig};

use super::driver_config;
use crate::stage::{MemoryObserver, StageConfig, StageDriver, StageEvent};

fn fast_driver(endpoint: &str) -> StageConfig {
    StageConfig {
        endpoint: endpoint.to_owned(),
        poll_interval_s: 0.005,
        resync_quiet_s: 0.01,
        ..driver_config()
    }
}

#[tokio::test]
async fn tilt_series_over_tcp_is_verified_within_a_hundredth_of_a_degree() {
    let sim = Simulator::spawn(SimConfig {
        time_scale: 0.01,
        ..SimConfig::default()
    })
    .unwrap();
    let observer = Arc::new(MemoryObserver::default());
    let mut stage = StageDriver::open(fast_driver(sim.stage_endpoint()), observer.clone())
        .await
        .unwrap();
    for deg in 0..=7 {
        let target = f64::from(deg);
        let report = stage.move_tilt(target).await.unwrap();
        assert!((report.positions[0].1 - target).abs() <= 0.01);
        let truth = sim.stage().snapshot();
        assert!((truth.pose.tilt_deg - target).abs() <= 0.01, "{truth:?}");
        assert!(truth.axes[2].on_target);
    }
    let p = stage.position().await.unwrap();
    assert!((p.tilt_deg - 7.0).abs() <= 0.01);
    stage.move_to_safe_tilt().await.unwrap();
    assert!(sim.stage().snapshot().pose.tilt_deg.abs() <= 0.01);
    let reached = observer
        .states()
        .iter()
        .filter(|s| s.event == StageEvent::Reached)
        .count();
    assert_eq!(reached, 9);
    drop(stage);
    sim.stop();
}

#[tokio::test]
async fn tilt_series_over_a_pseudo_terminal() {
    let sim = Simulator::spawn(SimConfig {
        time_scale: 0.01,
        stage: StageSimConfig {
            endpoint: SimEndpoint::Pty,
            ..StageSimConfig::default()
        },
        ..SimConfig::default()
    })
    .unwrap();
    let endpoint = sim.stage_endpoint().to_owned();
    assert!(endpoint.starts_with("/dev/"), "{endpoint}");
    // Twice: the port must open again after the first session closes it.
    for session in 0..2 {
        let mut stage =
            StageDriver::open(fast_driver(&endpoint), Arc::new(MemoryObserver::default()))
                .await
                .unwrap();
        for step in 1..=3 {
            let target = f64::from(session * 3 + step);
            let report = stage.move_tilt(target).await.unwrap();
            assert!((report.positions[0].1 - target).abs() <= 0.01);
        }
    }
    assert!((sim.stage().snapshot().pose.tilt_deg - 6.0).abs() <= 0.01);
    sim.stop();
}

/// Prints round-trip and move timings against the in-process simulator over TCP:
/// `cargo test -p sdsem --lib stage::tests::sim::timing_figures -- --ignored --nocapture`
#[tokio::test]
#[ignore = "evaluation: prints timing figures"]
async fn timing_figures() {
    use sdsem_protocol::gcs::PositionQuery;
    use std::time::{Duration, Instant};

    let sim = Simulator::spawn(SimConfig {
        time_scale: 0.1,
        ..SimConfig::default()
    })
    .unwrap();
    let config = StageConfig {
        endpoint: sim.stage_endpoint().to_owned(),
        poll_interval_s: 0.01,
        ..driver_config()
    };
    // The PI GCS backend itself, for its typed queries.
    let link = crate::stage::transport::open(
        &config.endpoint,
        config.effective_baud(),
        Duration::from_secs(5),
    )
    .await
    .unwrap();
    let mut stage = StageDriver::connect(link, config, Arc::new(MemoryObserver::default()))
        .await
        .unwrap();
    let axes = PositionQuery(vec![
        stage.config().axis_x.clone(),
        stage.config().axis_y.clone(),
        stage.config().axis_tilt.clone(),
    ]);
    let mut rtt: Vec<f64> = Vec::new();
    for _ in 0..2000 {
        let t = Instant::now();
        stage.query(&axes).await.unwrap();
        rtt.push(t.elapsed().as_secs_f64() * 1e6);
    }
    rtt.sort_by(f64::total_cmp);
    println!(
        "POS? X Y T round trip over loopback TCP: median {:.0} µs, p99 {:.0} µs, max {:.0} µs (n = {})",
        rtt[rtt.len() / 2],
        rtt[rtt.len() * 99 / 100],
        rtt[rtt.len() - 1],
        rtt.len()
    );
    // 1°/s and 0.2 s settling, at time_scale 0.1: ideal 0.12 s per 1° step.
    let t = Instant::now();
    let mut polls = 0;
    for deg in 1..=7 {
        polls += stage.move_tilt(f64::from(deg)).await.unwrap().polls;
    }
    let per_step = t.elapsed().as_secs_f64() / 7.0;
    println!(
        "1° tilt step, verified (time_scale 0.1, poll 10 ms): {:.1} ms per step (ideal 120 ms), {:.1} polls per step",
        per_step * 1e3,
        f64::from(polls) / 7.0
    );
    sim.stop();
}
