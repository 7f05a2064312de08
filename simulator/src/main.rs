//! `sdsem-sim` binary: parse flags into a [`SimConfig`], start the simulator,
//! print one machine-readable line per endpoint on stdout (`stage tcp://127.0.0.1:40123`),
//! then serve until killed or until stdin closes.

use std::io::{IsTerminal, Read, Write};
use std::net::SocketAddr;

use anyhow::Context;
use clap::Parser;
use sdsem_protocol::gcs::AxisId;
use sdsem_sim::{FaultTrigger, SimConfig, SimEndpoint, Simulator};

/// Stage-and-SEM simulator for sdsem: a PI GCS 2.0 stage controller (axes X, Y in µm,
/// tilt T in degrees) with finite speed, settling, soft limits, referencing, servo
/// state and faults on demand.
///
/// Prints `stage ENDPOINT` on stdout once listening, then serves until killed or
/// until its stdin (when a pipe or a terminal) closes.
#[derive(Debug, Parser)]
#[command(name = "sdsem-sim", version)]
struct Args {
    /// Serve the stage controller on TCP at this address (`127.0.0.1:0` picks a free port).
    #[arg(long, value_name = "ADDR", conflicts_with = "stage_pty")]
    stage_tcp: Option<String>,
    /// Serve the stage controller on a new pseudo-terminal (its path is printed).
    #[arg(long)]
    stage_pty: bool,
    /// Seed of every random choice (faults).
    #[arg(long)]
    seed: Option<u64>,
    /// Real seconds per simulated second (0.01 = 100× faster than real time).
    #[arg(long, value_name = "F")]
    time_scale: Option<f64>,
    /// GCS identifiers of the X, Y and tilt axes.
    #[arg(long, value_name = "X,Y,T", value_delimiter = ',')]
    axis_names: Option<Vec<String>>,
    /// Low tilt soft limit, degrees.
    #[arg(long, value_name = "DEG", allow_hyphen_values = true)]
    tilt_min: Option<f64>,
    /// High tilt soft limit, degrees.
    #[arg(long, value_name = "DEG", allow_hyphen_values = true)]
    tilt_max: Option<f64>,
    /// X and Y soft limits are ±UM micrometres.
    #[arg(long, value_name = "UM")]
    xy_limit: Option<f64>,
    /// Tilt speed, degrees per simulated second.
    #[arg(long, value_name = "DEG_PER_S")]
    tilt_speed: Option<f64>,
    /// X/Y speed, micrometres per simulated second.
    #[arg(long, value_name = "UM_PER_S")]
    xy_speed: Option<f64>,
    /// Settle time before on-target, simulated seconds.
    #[arg(long, value_name = "S")]
    settle: Option<f64>,
    /// Start unreferenced, as a real controller after power-on (moves refused with error 5).
    #[arg(long)]
    unreferenced: bool,
    /// Start with the servo off (moves refused with error 5).
    #[arg(long)]
    servo_off: bool,
    /// Drop the reply to these commands (1-based count of commands received).
    #[arg(long, value_name = "K,..", value_delimiter = ',')]
    drop_reply_at: Vec<u64>,
    /// Drop any reply with this probability.
    #[arg(long, value_name = "P")]
    drop_reply_p: Option<f64>,
    /// Garble the reply to these commands.
    #[arg(long, value_name = "K,..", value_delimiter = ',')]
    garble_reply_at: Vec<u64>,
    /// Garble any reply with this probability.
    #[arg(long, value_name = "P")]
    garble_reply_p: Option<f64>,
    /// Delay the reply to these commands.
    #[arg(long, value_name = "K,..", value_delimiter = ',')]
    late_reply_at: Vec<u64>,
    /// Delay any reply with this probability.
    #[arg(long, value_name = "P")]
    late_reply_p: Option<f64>,
    /// Delay of a late reply, real seconds.
    #[arg(long, value_name = "S")]
    late_reply_delay: Option<f64>,
    /// Silently ignore these moves (1-based count of accepted MOV/MVR).
    #[arg(long, value_name = "K,..", value_delimiter = ',')]
    ignore_move_at: Vec<u64>,
    /// Silently ignore any move with this probability.
    #[arg(long, value_name = "P")]
    ignore_move_p: Option<f64>,
    /// Give these moves a stale on-target flag.
    #[arg(long, value_name = "K,..", value_delimiter = ',')]
    stale_ont_at: Vec<u64>,
    /// Give any move a stale on-target flag with this probability.
    #[arg(long, value_name = "P")]
    stale_ont_p: Option<f64>,
    /// How long a stale on-target flag lasts, simulated seconds.
    #[arg(long, value_name = "S")]
    stale_ont_duration: Option<f64>,
    /// Refuse these moves with `--move-error-code`.
    #[arg(long, value_name = "K,..", value_delimiter = ',')]
    move_error_at: Vec<u64>,
    /// Refuse any move with this probability.
    #[arg(long, value_name = "P")]
    move_error_p: Option<f64>,
    /// Error code of a refused move (default 1024, motion error: also switches the servo off).
    #[arg(long, value_name = "CODE", allow_hyphen_values = true)]
    move_error_code: Option<i32>,
    /// Close the link after this many commands (once).
    #[arg(long, value_name = "N")]
    disconnect_after: Option<u64>,
    /// Serve until killed, whatever stdin does.
    #[arg(long)]
    ignore_stdin: bool,
}

fn trigger(at: Vec<u64>, p: Option<f64>) -> FaultTrigger {
    FaultTrigger {
        at,
        probability: p.unwrap_or(0.0),
    }
}

impl Args {
    fn into_config(self) -> anyhow::Result<SimConfig> {
        let mut c = SimConfig::default();
        if let Some(addr) = &self.stage_tcp {
            let addr = addr.strip_prefix("tcp://").unwrap_or(addr);
            let addr: SocketAddr = addr.parse().with_context(|| {
                format!("--stage-tcp {addr:?}: expected IP:PORT, e.g. 127.0.0.1:0")
            })?;
            c.stage.endpoint = SimEndpoint::Tcp(addr);
        }
        if self.stage_pty {
            c.stage.endpoint = SimEndpoint::Pty;
        }
        c.seed = self.seed.unwrap_or(c.seed);
        c.time_scale = self.time_scale.unwrap_or(c.time_scale);
        let s = &mut c.stage;
        if let Some(names) = &self.axis_names {
            let ids = AxisId::list(names).context("--axis-names")?;
            let [x, y, t] = ids.as_slice() else {
                anyhow::bail!("--axis-names takes three identifiers, e.g. --axis-names 1,2,3");
            };
            (s.axis_x, s.axis_y, s.axis_tilt) = (x.clone(), y.clone(), t.clone());
        }
        s.tilt_min_deg = self.tilt_min.unwrap_or(s.tilt_min_deg);
        s.tilt_max_deg = self.tilt_max.unwrap_or(s.tilt_max_deg);
        if let Some(l) = self.xy_limit {
            (s.xy_min_um, s.xy_max_um) = (-l, l);
        }
        s.tilt_speed_deg_s = self.tilt_speed.unwrap_or(s.tilt_speed_deg_s);
        s.xy_speed_um_s = self.xy_speed.unwrap_or(s.xy_speed_um_s);
        s.settle_s = self.settle.unwrap_or(s.settle_s);
        s.referenced &= !self.unreferenced;
        s.servo_on &= !self.servo_off;
        let f = &mut s.faults;
        f.drop_reply = trigger(self.drop_reply_at, self.drop_reply_p);
        f.garble_reply = trigger(self.garble_reply_at, self.garble_reply_p);
        f.late_reply = trigger(self.late_reply_at, self.late_reply_p);
        f.late_reply_delay_s = self.late_reply_delay.unwrap_or(f.late_reply_delay_s);
        f.ignore_move = trigger(self.ignore_move_at, self.ignore_move_p);
        f.stale_on_target = trigger(self.stale_ont_at, self.stale_ont_p);
        f.stale_on_target_s = self.stale_ont_duration.unwrap_or(f.stale_on_target_s);
        f.move_error = trigger(self.move_error_at, self.move_error_p);
        f.move_error_code = self.move_error_code.unwrap_or(f.move_error_code);
        f.disconnect_after_commands = self.disconnect_after;
        c.validate()?;
        Ok(c)
    }
}

/// Whether stdin can tell us to stop by closing: a terminal, a pipe or a socket.
/// `/dev/null` (systemd, background jobs) cannot, so it is not watched.
fn stdin_is_watchable() -> bool {
    use std::os::unix::fs::FileTypeExt;
    if std::io::stdin().is_terminal() {
        return true;
    }
    std::fs::metadata("/proc/self/fd/0").is_ok_and(|m| {
        let t = m.file_type();
        t.is_fifo() || t.is_socket()
    })
}

fn main() {
    if let Err(e) = run() {
        // One line with the whole cause chain; the exit code says it failed.
        eprintln!("sdsem-sim: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_ansi(std::io::stderr().is_terminal())
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    let args = Args::parse();
    let watch_stdin = !args.ignore_stdin && stdin_is_watchable();
    let config = args.into_config()?;
    let sim = Simulator::spawn(config)?;
    let mut stdout = std::io::stdout().lock();
    for line in sim.endpoint_lines() {
        writeln!(stdout, "{line}")?;
    }
    stdout.flush()?;
    drop(stdout);
    if watch_stdin {
        // Read and discard until EOF: the parent closing our stdin means "stop".
        let mut sink = [0u8; 256];
        let mut stdin = std::io::stdin().lock();
        while !matches!(stdin.read(&mut sink), Ok(0) | Err(_)) {}
        tracing::info!("stdin closed: stopping");
        sim.stop();
        Ok(())
    } else {
        loop {
            std::thread::park();
        }
    }
}
