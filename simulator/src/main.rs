//! `sdsem-sim` binary: build a [`SimConfig`] from an optional TOML file and the
//! flags, start the stage controller and the SEM imaging server, print one
//! machine-readable line per endpoint on stdout (`stage tcp://127.0.0.1:40123`,
//! `sem tcp://127.0.0.1:40124`, `folder /path` with a store folder), then serve
//! until killed or until stdin closes.

use std::io::{IsTerminal, Read, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Parser;
use sdsem_protocol::gcs::AxisId;
use sdsem_sim::scene::SceneKind;
use sdsem_sim::sharksem::SharkSemSimConfig;
use sdsem_sim::{FaultTrigger, SimConfig, SimEndpoint, SimStageProtocol, Simulator};

const PROTOCOLS: &str = "\
OUTPUT
  Once both instruments listen, one line per service on stdout:
    stage tcp://127.0.0.1:PORT      (or: stage /dev/pts/N with --stage-pty)
    sem tcp://127.0.0.1:PORT
    folder /PATH                    (with a store folder: --store-dir or [folder])
    sharksem tcp://127.0.0.1:PORT   (with --sharksem: the SharkSEM control port)
    sharksem-data tcp://127.0.0.1:PORT
  Logs go to stderr (RUST_LOG filters them). The simulator stops when killed
  or when its stdin, if a pipe or a terminal, closes.

STAGE LINK, --stage-protocol pi-gcs (the default; PI GCS 2.0 subset; ASCII lines ending in LF)
  Axes X, Y (µm) and T (tilt, °); --axis-names renames them.
  MOV|MVR <axis> <value> ...   SVO <axis> 0|1 ...   FRF [axes]   STP
  POS? ONT? SVO? FRF? TMN? TMX? [axes]   ERR?   *IDN?
  Single bytes: 0x05 motion bitmap, 0x07 ready (0xB1), 0x18 stop all.
  Commands do not answer: ask ERR? after one. Multi-axis replies end each
  line but the last with \" \\n\". Motion has finite speed, then settles.

STAGE LINK with --stage-protocol remcon32 (Zeiss SmartSEM RemCon32; ASCII,
  requests end in CR, LF or CR LF; replies are two lines ending in CR LF)
  @ (accepted) or # (invalid) at once, then >data (done) or *NNN (failed).
  C95? -> x y z t r m moving (mm, mm, mm, deg, deg, mm, 1.0 = moving)
  C95 x y z t r m (all axes, absolute; returns before the move ends; the
  moving flag reads 0.0 for 1 s after it although the stage travels, as
  SmartSEM's: [stage.remcon] moving_flag_delay_s)
  STG? STG x y z  IST? (type init, 0 = initialised)  ABO  VER?  PIX? (nm)
  MAG?  DET? (detector)  EHT? (kV)  FREC (store a photo)  PHN? (photo count)
  MAC n (run macro REMCONn: a [folder.macros] entry, else *616)
  Unknown words: @ then *600; wrong value count to C95/STG: # alone;
  targets beyond the limits: *603; an empty line (null command): no reply.
  Faults as for GCS; a stale on-target flag is a move that starts late (still
  stage, moving flag 0.0), a move error answers *613.

SEM LINK (TCP; one request line, one reply header line, maybe a payload)
  *IDN?                                  -> IDN <vendor>,<model>,<serial>,<version>
  PIXELSIZE? <width>                     -> PIXELSIZE <width> <um>
  GRAB <w> <h> <dwell_us> <tracking|left|right> [8|16]
                                         -> FRAME <w> <h> <bits> <nbytes> <json> + samples
  GROUNDTRUTH <frame> [<path>]           -> HEIGHTMAP <w> <h> 32 <nbytes> <json> + f32 um,
                                            or OK after writing a GSF file at <path>
  errors                                 -> ERR <code> <message>
  A frame is scanned at the stage pose of the start of its scan (in the JSON
  metadata with the scan's wall-clock start and end) and takes w*h*dwell of
  simulated time. Samples are row-major little-endian, x right, y down.

STORE FOLDER (the SEM's own software storing micrographs, VENDORS 4)
  With --store-dir (or a [folder] table) the SEM also stores micrographs as
  vendor TIFFs (zeiss: tag 34118; fei: tag 34682 and a data bar; tescan: tag
  50431 and an info strip), scanned where the stage is, named PREFIX0001.tif,
  PREFIX0002.tif, ...: every --store-every simulated seconds, and on request.
  FREC stores at the folder's width x height and dwell_us (SmartSEM's store
  resolution); MAC n at those of its [[folder.macros]] entry (number = n).
  Faults in [folder]: write_s/write_chunks (slow, partial files),
  temp_then_rename, stale_file, wrong_tilt (a recorded tilt that is off).

SHARKSEM (TESCAN remote control, binary; with --sharksem ADDR)
  The same SEM and stage as a TESCAN microscope: control port ADDR, data port
  ADDR + 1 (or --sharksem-data-port). Register the data socket's local port with
  TcpRegDataPort, then connect from it. Stage in mm and degrees (x y z rotation
  tilt); pixel size = view field / scan width; ScData chunks every 50 ms of
  simulated time; ScStopScan after every scan. Unknown or bad requests get no
  reply at all. Faults: --shark-* flags; the stage's --ignore-move-at applies.

TIME
  --time-scale is real seconds per simulated second: 0.01 makes moves,
  settling and scans 100x faster than real time. Late replies (a fault) are
  delayed in real seconds.

CONFIGURATION FILE
  --config FILE reads a TOML SimConfig: keys seed, time_scale and tables
  [stage] (with [stage.faults]), [sem] (with [sem.scene], [sem.optics],
  [sem.walk], [sem.shading], [sem.noise]), [folder] and [sharksem] (with
  [sharksem.faults]). A file with a [simulator] table
  (sdsem's configuration) is read from that table. Flags override the file.";

/// Stage-and-SEM simulator for sdsem: a PI GCS 2.0 stage controller (axes X, Y
/// in µm, tilt T in degrees) with finite speed, settling, soft limits,
/// referencing, servo state and faults on demand, and a SEM imaging server
/// that renders a known synthetic specimen where the stage is, with eucentric
/// walk, drift, scan noise and exact ground truth; optionally the same SEM and
/// stage over TESCAN SharkSEM.
#[derive(Debug, Parser)]
#[command(name = "sdsem-sim", version, after_long_help = PROTOCOLS)]
struct Args {
    /// Read a SimConfig from this TOML file first (flags override it).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Serve the stage controller on TCP at this address (`127.0.0.1:0` picks a free port; the default).
    #[arg(long, value_name = "ADDR", conflicts_with = "stage_pty")]
    stage_tcp: Option<String>,
    /// Serve the stage controller on a new pseudo-terminal (its path is printed).
    #[arg(long)]
    stage_pty: bool,
    /// The stage's language: pi-gcs (the default) or remcon32 (Zeiss SmartSEM RemCon32).
    #[arg(long, value_name = "PROTOCOL")]
    stage_protocol: Option<SimStageProtocol>,
    /// Serve the SEM imaging link on TCP at this address (`127.0.0.1:0` picks a free port; the default).
    #[arg(long, value_name = "ADDR")]
    sem_tcp: Option<String>,
    /// Also serve the SEM and stage over TESCAN SharkSEM, control port at this
    /// address (`127.0.0.1:8300`; port 0 picks a free pair), data port = control + 1.
    #[arg(long, value_name = "ADDR", help_heading = "SharkSEM")]
    sharksem: Option<String>,
    /// SharkSEM data port (default: control + 1; 0 picks any free port).
    #[arg(long, value_name = "PORT", help_heading = "SharkSEM")]
    sharksem_data_port: Option<u16>,
    /// SharkSEM protocol version served (default 2.0.25; 3.2.20 adds TcpGetModel).
    #[arg(long, value_name = "V", help_heading = "SharkSEM")]
    sharksem_version: Option<String>,
    /// Firewall-friendly mode: one control + data pair, TcpRegDataPort ignored.
    #[arg(long, help_heading = "SharkSEM")]
    sharksem_firewall_friendly: bool,
    /// StgGetPosition answers six values (tilt-Y), as 3.x stages with that axis do.
    #[arg(long, help_heading = "SharkSEM")]
    sharksem_tilt_y: bool,
    /// Never send these ScData chunks (1-based count of chunks).
    #[arg(
        long,
        value_name = "K,..",
        value_delimiter = ',',
        help_heading = "SharkSEM faults"
    )]
    shark_lose_chunk_at: Vec<u64>,
    /// Lose any chunk with this probability.
    #[arg(long, value_name = "P", help_heading = "SharkSEM faults")]
    shark_lose_chunk_p: Option<f64>,
    /// Send these ScData chunks twice.
    #[arg(
        long,
        value_name = "K,..",
        value_delimiter = ',',
        help_heading = "SharkSEM faults"
    )]
    shark_resend_chunk_at: Vec<u64>,
    /// Send any chunk twice with this probability.
    #[arg(long, value_name = "P", help_heading = "SharkSEM faults")]
    shark_resend_chunk_p: Option<f64>,
    /// Ignore these SetViewField requests silently (1-based count).
    #[arg(
        long,
        value_name = "K,..",
        value_delimiter = ',',
        help_heading = "SharkSEM faults"
    )]
    shark_ignore_view_field_at: Vec<u64>,
    /// Close the client's connections after this many requests (once).
    #[arg(long, value_name = "N", help_heading = "SharkSEM faults")]
    shark_disconnect_after: Option<u64>,
    /// Stop answering anything from this request on.
    #[arg(long, value_name = "N", help_heading = "SharkSEM faults")]
    shark_silent_after: Option<u64>,
    /// Seed of every random choice (faults, specimen, walk, scan noise).
    #[arg(long)]
    seed: Option<u64>,
    /// Real seconds per simulated second (0.01 = 100× faster than real time).
    #[arg(long, value_name = "F")]
    time_scale: Option<f64>,

    /// Specimen: particles, grid, rough or dome.
    #[arg(long, value_name = "KIND", help_heading = "SEM")]
    scene: Option<SceneKind>,
    /// Side of the square specimen, µm (default 200; smaller builds faster).
    #[arg(long, value_name = "UM", help_heading = "SEM")]
    scene_field: Option<f64>,
    /// Full-resolution frame size (default 1280x960).
    #[arg(long, value_name = "WxH", value_parser = parse_frame, help_heading = "SEM")]
    frame: Option<(usize, usize)>,
    /// Pixel size of the full-resolution frame, µm (default 0.1).
    #[arg(long, value_name = "UM", help_heading = "SEM")]
    pixel_size: Option<f64>,
    /// Direction of the stage tilt axis in the image, degrees from +x towards +y (default 0).
    #[arg(
        long,
        value_name = "DEG",
        allow_hyphen_values = true,
        help_heading = "SEM"
    )]
    tilt_axis: Option<f64>,
    /// In-plane rotation of the scan, degrees (default 0).
    #[arg(
        long,
        value_name = "DEG",
        allow_hyphen_values = true,
        help_heading = "SEM"
    )]
    scan_rotation: Option<f64>,
    /// Eucentric walk, full-resolution pixels per degree of tilt (default 5).
    #[arg(
        long,
        value_name = "PX",
        allow_hyphen_values = true,
        help_heading = "SEM"
    )]
    walk_px_per_deg: Option<f64>,
    /// Direction of the eucentric walk in the image, degrees from +x towards +y (default 60).
    #[arg(
        long,
        value_name = "DEG",
        allow_hyphen_values = true,
        help_heading = "SEM"
    )]
    walk_direction: Option<f64>,
    /// Random part of the walk: standard deviation per 2° knot, full-resolution pixels (default 3).
    #[arg(long, value_name = "PX", help_heading = "SEM")]
    walk_random_px: Option<f64>,
    /// Specimen drift in the image plane, µm per simulated second along x and y.
    #[arg(
        long,
        value_name = "X,Y",
        value_delimiter = ',',
        allow_hyphen_values = true,
        help_heading = "SEM"
    )]
    drift: Option<Vec<f64>>,

    /// GCS identifiers of the X, Y and tilt axes.
    #[arg(
        long,
        value_name = "X,Y,T",
        value_delimiter = ',',
        help_heading = "Stage"
    )]
    axis_names: Option<Vec<String>>,
    /// Low tilt soft limit, degrees.
    #[arg(
        long,
        value_name = "DEG",
        allow_hyphen_values = true,
        help_heading = "Stage"
    )]
    tilt_min: Option<f64>,
    /// High tilt soft limit, degrees.
    #[arg(
        long,
        value_name = "DEG",
        allow_hyphen_values = true,
        help_heading = "Stage"
    )]
    tilt_max: Option<f64>,
    /// X and Y soft limits are ±UM micrometres.
    #[arg(long, value_name = "UM", help_heading = "Stage")]
    xy_limit: Option<f64>,
    /// Tilt speed, degrees per simulated second.
    #[arg(long, value_name = "DEG_PER_S", help_heading = "Stage")]
    tilt_speed: Option<f64>,
    /// X/Y speed, micrometres per simulated second.
    #[arg(long, value_name = "UM_PER_S", help_heading = "Stage")]
    xy_speed: Option<f64>,
    /// Settle time before on-target, simulated seconds.
    #[arg(long, value_name = "S", help_heading = "Stage")]
    settle: Option<f64>,
    /// Start unreferenced, as a real controller after power-on (moves refused with error 5).
    #[arg(long, help_heading = "Stage")]
    unreferenced: bool,
    /// Start with the servo off (moves refused with error 5).
    #[arg(long, help_heading = "Stage")]
    servo_off: bool,

    /// Drop the reply to these commands (1-based count of commands received).
    #[arg(
        long,
        value_name = "K,..",
        value_delimiter = ',',
        help_heading = "Stage faults"
    )]
    drop_reply_at: Vec<u64>,
    /// Drop any reply with this probability.
    #[arg(long, value_name = "P", help_heading = "Stage faults")]
    drop_reply_p: Option<f64>,
    /// Garble the reply to these commands.
    #[arg(
        long,
        value_name = "K,..",
        value_delimiter = ',',
        help_heading = "Stage faults"
    )]
    garble_reply_at: Vec<u64>,
    /// Garble any reply with this probability.
    #[arg(long, value_name = "P", help_heading = "Stage faults")]
    garble_reply_p: Option<f64>,
    /// Delay the reply to these commands.
    #[arg(
        long,
        value_name = "K,..",
        value_delimiter = ',',
        help_heading = "Stage faults"
    )]
    late_reply_at: Vec<u64>,
    /// Delay any reply with this probability.
    #[arg(long, value_name = "P", help_heading = "Stage faults")]
    late_reply_p: Option<f64>,
    /// Delay of a late reply, real seconds.
    #[arg(long, value_name = "S", help_heading = "Stage faults")]
    late_reply_delay: Option<f64>,
    /// Silently ignore these moves (1-based count of accepted MOV/MVR).
    #[arg(
        long,
        value_name = "K,..",
        value_delimiter = ',',
        help_heading = "Stage faults"
    )]
    ignore_move_at: Vec<u64>,
    /// Silently ignore any move with this probability.
    #[arg(long, value_name = "P", help_heading = "Stage faults")]
    ignore_move_p: Option<f64>,
    /// Give these moves a stale on-target flag.
    #[arg(
        long,
        value_name = "K,..",
        value_delimiter = ',',
        help_heading = "Stage faults"
    )]
    stale_ont_at: Vec<u64>,
    /// Give any move a stale on-target flag with this probability.
    #[arg(long, value_name = "P", help_heading = "Stage faults")]
    stale_ont_p: Option<f64>,
    /// How long a stale on-target flag lasts, simulated seconds.
    #[arg(long, value_name = "S", help_heading = "Stage faults")]
    stale_ont_duration: Option<f64>,
    /// Refuse these moves with `--move-error-code`.
    #[arg(
        long,
        value_name = "K,..",
        value_delimiter = ',',
        help_heading = "Stage faults"
    )]
    move_error_at: Vec<u64>,
    /// Refuse any move with this probability.
    #[arg(long, value_name = "P", help_heading = "Stage faults")]
    move_error_p: Option<f64>,
    /// Error code of a refused move (default 1024, motion error: also switches the servo off).
    #[arg(
        long,
        value_name = "CODE",
        allow_hyphen_values = true,
        help_heading = "Stage faults"
    )]
    move_error_code: Option<i32>,
    /// Close the link after this many commands (once).
    #[arg(long, value_name = "N", help_heading = "Stage faults")]
    disconnect_after: Option<u64>,

    /// Also store micrographs as vendor TIFFs in this folder (created if missing).
    #[arg(long, value_name = "DIR", help_heading = "Store folder")]
    store_dir: Option<PathBuf>,
    /// File format of the stored micrographs: zeiss, fei or tescan (default zeiss).
    #[arg(long, value_name = "VENDOR", help_heading = "Store folder")]
    store_vendor: Option<sdsem_sim::vendor_tiff::Vendor>,
    /// Store one micrograph every S simulated seconds (default 0: only on request).
    #[arg(long, value_name = "S", help_heading = "Store folder")]
    store_every: Option<f64>,

    /// Serve until killed, whatever stdin does.
    #[arg(long)]
    ignore_stdin: bool,
}

fn parse_frame(s: &str) -> Result<(usize, usize), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("{s:?}: expected WxH, e.g. 1280x960"))?;
    let side = |v: &str| {
        v.trim()
            .parse::<usize>()
            .map_err(|e| format!("{s:?}: {e}; expected WxH, e.g. 1280x960"))
    };
    Ok((side(w)?, side(h)?))
}

fn tcp_endpoint(flag: &str, addr: &str) -> anyhow::Result<SimEndpoint> {
    let bare = addr.strip_prefix("tcp://").unwrap_or(addr);
    let addr: SocketAddr = bare
        .parse()
        .with_context(|| format!("{flag} {addr:?}: expected IP:PORT, e.g. 127.0.0.1:0"))?;
    Ok(SimEndpoint::Tcp(addr))
}

/// Sets the trigger only when a flag asks for it, so the file's stays otherwise.
fn trigger(slot: &mut FaultTrigger, at: Vec<u64>, p: Option<f64>) {
    if !at.is_empty() || p.is_some() {
        *slot = FaultTrigger {
            at,
            probability: p.unwrap_or(0.0),
        };
    }
}

/// Reads a [`SimConfig`] from a TOML file: the whole file, or its
/// `[simulator]` table when it has one (sdsem's configuration file).
fn load_config(path: &Path) -> anyhow::Result<SimConfig> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the configuration file {}", path.display()))?;
    let mut table: toml::Table =
        toml::from_str(&text).with_context(|| format!("{} is not valid TOML", path.display()))?;
    let table = match table.remove("simulator") {
        Some(toml::Value::Table(sim)) => sim,
        Some(_) => anyhow::bail!("{}: `simulator` must be a table", path.display()),
        None => table,
    };
    toml::Value::Table(table)
        .try_into()
        .with_context(|| format!("{}: invalid simulator configuration", path.display()))
}

fn set<T>(slot: &mut T, value: Option<T>) {
    if let Some(v) = value {
        *slot = v;
    }
}

impl Args {
    fn into_config(self) -> anyhow::Result<SimConfig> {
        let mut c = match &self.config {
            Some(path) => load_config(path)?,
            None => SimConfig::default(),
        };
        if let Some(addr) = &self.stage_tcp {
            c.stage.endpoint = tcp_endpoint("--stage-tcp", addr)?;
        }
        if self.stage_pty {
            c.stage.endpoint = SimEndpoint::Pty;
        }
        set(&mut c.stage.protocol, self.stage_protocol);
        if let Some(addr) = &self.sem_tcp {
            c.sem.endpoint = tcp_endpoint("--sem-tcp", addr)?;
        }
        set(&mut c.seed, self.seed);
        set(&mut c.time_scale, self.time_scale);
        self.apply_sharksem(&mut c)?;

        let m = &mut c.sem;
        set(&mut m.scene.kind, self.scene);
        set(&mut m.scene.field_um, self.scene_field);
        if let Some((w, h)) = self.frame {
            (m.optics.width, m.optics.height) = (w, h);
        }
        set(&mut m.optics.pixel_size_um, self.pixel_size);
        set(&mut m.optics.tilt_axis_deg, self.tilt_axis);
        set(&mut m.optics.scan_rotation_deg, self.scan_rotation);
        set(&mut m.walk.px_per_deg, self.walk_px_per_deg);
        set(&mut m.walk.direction_deg, self.walk_direction);
        set(&mut m.walk.random_px, self.walk_random_px);
        if let Some(d) = &self.drift {
            let [x, y] = d.as_slice() else {
                anyhow::bail!("--drift takes two values, e.g. --drift 0.01,-0.02");
            };
            m.drift_um_per_s = [*x, *y];
        }

        let s = &mut c.stage;
        if let Some(names) = &self.axis_names {
            let ids = AxisId::list(names).context("--axis-names")?;
            let [x, y, t] = ids.as_slice() else {
                anyhow::bail!("--axis-names takes three identifiers, e.g. --axis-names 1,2,3");
            };
            (s.axis_x, s.axis_y, s.axis_tilt) = (x.clone(), y.clone(), t.clone());
        }
        set(&mut s.tilt_min_deg, self.tilt_min);
        set(&mut s.tilt_max_deg, self.tilt_max);
        if let Some(l) = self.xy_limit {
            (s.xy_min_um, s.xy_max_um) = (-l, l);
        }
        set(&mut s.tilt_speed_deg_s, self.tilt_speed);
        set(&mut s.xy_speed_um_s, self.xy_speed);
        set(&mut s.settle_s, self.settle);
        s.referenced &= !self.unreferenced;
        s.servo_on &= !self.servo_off;

        let f = &mut s.faults;
        trigger(&mut f.drop_reply, self.drop_reply_at, self.drop_reply_p);
        trigger(
            &mut f.garble_reply,
            self.garble_reply_at,
            self.garble_reply_p,
        );
        trigger(&mut f.late_reply, self.late_reply_at, self.late_reply_p);
        set(&mut f.late_reply_delay_s, self.late_reply_delay);
        trigger(&mut f.ignore_move, self.ignore_move_at, self.ignore_move_p);
        trigger(&mut f.stale_on_target, self.stale_ont_at, self.stale_ont_p);
        set(&mut f.stale_on_target_s, self.stale_ont_duration);
        trigger(&mut f.move_error, self.move_error_at, self.move_error_p);
        set(&mut f.move_error_code, self.move_error_code);
        if self.disconnect_after.is_some() {
            f.disconnect_after_commands = self.disconnect_after;
        }
        if let Some(dir) = self.store_dir {
            c.folder.get_or_insert_with(Default::default).dir = dir;
        }
        if self.store_vendor.is_some() || self.store_every.is_some() {
            let Some(folder) = c.folder.as_mut() else {
                anyhow::bail!(
                    "--store-vendor and --store-every need --store-dir (or a [folder] table)"
                );
            };
            set(&mut folder.vendor, self.store_vendor);
            set(&mut folder.every_s, self.store_every);
        }
        c.validate()?;
        Ok(c)
    }

    /// The SharkSEM flags: `--sharksem` (or a `[sharksem]` table in the file)
    /// enables the dialect; the other flags change it.
    fn apply_sharksem(&self, c: &mut SimConfig) -> anyhow::Result<()> {
        let tweaks = self.sharksem_data_port.is_some()
            || self.sharksem_version.is_some()
            || self.sharksem_firewall_friendly
            || self.sharksem_tilt_y
            || !self.shark_lose_chunk_at.is_empty()
            || self.shark_lose_chunk_p.is_some()
            || !self.shark_resend_chunk_at.is_empty()
            || self.shark_resend_chunk_p.is_some()
            || !self.shark_ignore_view_field_at.is_empty()
            || self.shark_disconnect_after.is_some()
            || self.shark_silent_after.is_some();
        if self.sharksem.is_none() && c.sharksem.is_none() {
            if tweaks {
                anyhow::bail!(
                    "the SharkSEM flags need --sharksem ADDR (e.g. --sharksem 127.0.0.1:8300)"
                );
            }
            return Ok(());
        }
        let s = c.sharksem.get_or_insert_with(SharkSemSimConfig::default);
        if let Some(addr) = &self.sharksem {
            s.endpoint = tcp_endpoint("--sharksem", addr)?;
        }
        if self.sharksem_data_port.is_some() {
            s.data_port = self.sharksem_data_port;
        }
        set(&mut s.version, self.sharksem_version.clone());
        s.firewall_friendly |= self.sharksem_firewall_friendly;
        s.tilt_y |= self.sharksem_tilt_y;
        let f = &mut s.faults;
        trigger(
            &mut f.lose_chunk,
            self.shark_lose_chunk_at.clone(),
            self.shark_lose_chunk_p,
        );
        trigger(
            &mut f.resend_chunk,
            self.shark_resend_chunk_at.clone(),
            self.shark_resend_chunk_p,
        );
        trigger(
            &mut f.ignore_view_field,
            self.shark_ignore_view_field_at.clone(),
            None,
        );
        if self.shark_disconnect_after.is_some() {
            f.disconnect_after_requests = self.shark_disconnect_after;
        }
        if self.shark_silent_after.is_some() {
            f.silent_after_requests = self.shark_silent_after;
        }
        Ok(())
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
