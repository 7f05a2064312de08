//! The simulated PI GCS stage controller as a pure state machine: framed
//! commands and the simulated time in, replies out. No I/O, no clock reads.
//!
//! Each axis moves at constant speed towards its target, then settles for
//! `settle_s` before `ONT?` answers 1. Moves need the axis referenced and its
//! servo on (error 5), targets must lie within the soft limits (error 7), `STP`
//! halts every axis where it is and sets error 10, as on PI controllers.

use std::time::Duration;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sdsem_protocol::gcs::{AxisId, Command, FrameError, GcsErrorCode, Incoming, Reply};

use crate::config::{FaultConfig, FaultTrigger, StageSimConfig};
use crate::pose::StagePose;

/// What the model answers to one framed command.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Response {
    /// Bytes to send back, if any.
    pub reply: Option<Vec<u8>>,
    /// Real time to wait before sending them (late-reply fault).
    pub delay: Duration,
    /// Close the link after sending (disconnect fault).
    pub disconnect: bool,
}

/// How many times each fault fired.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FaultCounts {
    /// Replies dropped.
    pub dropped_replies: u64,
    /// Replies garbled.
    pub garbled_replies: u64,
    /// Replies delayed.
    pub late_replies: u64,
    /// Moves accepted but not executed.
    pub ignored_moves: u64,
    /// Moves with a stale on-target flag.
    pub stale_on_target: u64,
    /// Moves refused with the configured error code.
    pub move_errors: u64,
    /// Links closed.
    pub disconnects: u64,
}

/// The role an axis plays in the stage pose.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AxisRole {
    /// Specimen translation X, µm.
    X,
    /// Specimen translation Y, µm.
    Y,
    /// Tilt, degrees.
    Tilt,
}

/// The state of one axis, for tests and the SEM renderer.
#[derive(Clone, Debug, PartialEq)]
pub struct AxisSnapshot {
    /// GCS identifier.
    pub id: AxisId,
    /// Role in the pose.
    pub role: AxisRole,
    /// True position now.
    pub position: f64,
    /// Commanded target.
    pub target: f64,
    /// Whether the axis is in motion.
    pub moving: bool,
    /// Whether the axis has settled on its target (true state, faults aside).
    pub on_target: bool,
    /// Whether the axis is referenced.
    pub referenced: bool,
    /// Whether its servo is on.
    pub servo: bool,
}

/// The whole controller state at one instant.
#[derive(Clone, Debug, PartialEq)]
pub struct StageSnapshot {
    /// Simulated time, seconds.
    pub time_s: f64,
    /// True pose.
    pub pose: StagePose,
    /// Every axis, in controller order (X, Y, T).
    pub axes: Vec<AxisSnapshot>,
    /// Commands received so far (all links).
    pub commands: u64,
    /// Moves accepted so far (`MOV`/`MVR` that passed validation).
    pub moves: u64,
    /// The error code `ERR?` would answer now.
    pub last_error: GcsErrorCode,
    /// Faults fired so far.
    pub faults: FaultCounts,
}

#[derive(Clone, Debug)]
struct Axis {
    id: AxisId,
    role: AxisRole,
    min: f64,
    max: f64,
    speed: f64,
    /// Current motion segment: from `from` at `t0` towards `to` at `speed`
    /// (`from == to` when idle).
    from: f64,
    to: f64,
    t0: f64,
    /// Commanded target: what `ONT?` compares with.
    target: f64,
    /// When the axis counts as settled on `target`.
    settled_at: f64,
    referenced: bool,
    referencing: bool,
    servo: bool,
    /// Until when `ONT?`/`#5` lie (stale-flag fault).
    stale_until: f64,
}

impl Axis {
    fn position(&self, t: f64) -> f64 {
        let span = self.to - self.from;
        let travel = self.speed * (t - self.t0).max(0.0);
        if travel >= span.abs() {
            self.to
        } else {
            self.from + span.signum() * travel
        }
    }

    fn motion_end(&self) -> f64 {
        self.t0 + (self.to - self.from).abs() / self.speed
    }

    fn moving(&self, t: f64) -> bool {
        t < self.motion_end()
    }

    fn on_target(&self, t: f64) -> bool {
        self.servo && !self.referencing && !self.moving(t) && t >= self.settled_at
    }

    fn start_motion(&mut self, t: f64, target: f64, settle_s: f64) {
        self.from = self.position(t);
        self.to = target;
        self.t0 = t;
        self.target = target;
        self.settled_at = self.motion_end() + settle_s;
    }

    fn halt(&mut self, t: f64) {
        let p = self.position(t);
        self.from = p;
        self.to = p;
        self.t0 = t;
        self.target = p;
        self.settled_at = t;
        self.referencing = false;
        self.stale_until = t;
    }
}

/// The simulated controller (pure: time is an argument of every call).
#[derive(Debug)]
pub struct StageModel {
    axes: Vec<Axis>,
    settle_s: f64,
    idn: String,
    last_error: GcsErrorCode,
    faults: FaultConfig,
    rng: ChaCha8Rng,
    commands: u64,
    moves: u64,
    fired: FaultCounts,
    disconnected: bool,
}

impl StageModel {
    /// A controller at rest at the configured start pose. `config` must have been
    /// validated (`StageSimConfig::validate`). `seed` seeds the fault draws
    /// (`config.seed` is the configuration's way to set it; the caller resolves it).
    pub fn new(config: &StageSimConfig, seed: u64) -> Self {
        let axis = |id: &AxisId, role, min, max, speed, start| Axis {
            id: id.clone(),
            role,
            min,
            max,
            speed,
            from: start,
            to: start,
            t0: 0.0,
            target: start,
            settled_at: 0.0,
            referenced: config.referenced,
            referencing: false,
            servo: config.servo_on,
            stale_until: 0.0,
        };
        let c = config;
        Self {
            axes: vec![
                axis(
                    &c.axis_x,
                    AxisRole::X,
                    c.xy_min_um,
                    c.xy_max_um,
                    c.xy_speed_um_s,
                    c.start_x_um,
                ),
                axis(
                    &c.axis_y,
                    AxisRole::Y,
                    c.xy_min_um,
                    c.xy_max_um,
                    c.xy_speed_um_s,
                    c.start_y_um,
                ),
                axis(
                    &c.axis_tilt,
                    AxisRole::Tilt,
                    c.tilt_min_deg,
                    c.tilt_max_deg,
                    c.tilt_speed_deg_s,
                    c.start_tilt_deg,
                ),
            ],
            settle_s: c.settle_s,
            idn: c.idn.clone(),
            last_error: GcsErrorCode::NO_ERROR,
            faults: c.faults.clone(),
            rng: ChaCha8Rng::seed_from_u64(seed),
            commands: 0,
            moves: 0,
            fired: FaultCounts::default(),
            disconnected: false,
        }
    }

    /// The controller's axis identifiers, in controller order.
    pub fn axis_ids(&self) -> Vec<AxisId> {
        self.axes.iter().map(|a| a.id.clone()).collect()
    }

    /// Handles one framed command received at simulated time `now_s`.
    pub fn handle(&mut self, now_s: f64, incoming: Result<Incoming, FrameError>) -> Response {
        let k = self.begin_command(now_s);
        let parsed = incoming
            .map_err(|_| GcsErrorCode::COMMAND_TOO_LONG)
            .and_then(|i| Command::parse_incoming(&i, &self.axis_ids()));
        let reply = match parsed {
            Ok(command) => self.execute(now_s, &command),
            Err(code) => {
                self.last_error = code;
                None
            }
        };
        let mut response = Response::default();
        if let Some(reply) = reply {
            response = self.deliver(k, reply.to_bytes());
        }
        self.end_command(k, response)
    }

    /// The true pose at `now_s`.
    pub fn pose(&self, now_s: f64) -> StagePose {
        let mut pose = StagePose::default();
        for a in &self.axes {
            let p = a.position(now_s);
            match a.role {
                AxisRole::X => pose.x_um = p,
                AxisRole::Y => pose.y_um = p,
                AxisRole::Tilt => pose.tilt_deg = p,
            }
        }
        pose
    }

    /// The whole state at `now_s`.
    pub fn snapshot(&self, now_s: f64) -> StageSnapshot {
        StageSnapshot {
            time_s: now_s,
            pose: self.pose(now_s),
            axes: self
                .axes
                .iter()
                .map(|a| AxisSnapshot {
                    id: a.id.clone(),
                    role: a.role,
                    position: a.position(now_s),
                    target: a.target,
                    moving: a.moving(now_s),
                    on_target: a.on_target(now_s),
                    // Referencing completes lazily, at the next command.
                    referenced: a.referenced || (a.referencing && !a.moving(now_s)),
                    servo: a.servo,
                })
                .collect(),
            commands: self.commands,
            moves: self.moves,
            last_error: self.last_error,
            faults: self.fired,
        }
    }

    /// Commands received so far.
    pub fn command_count(&self) -> u64 {
        self.commands
    }

    fn finish_referencing(&mut self, now_s: f64) {
        for a in &mut self.axes {
            if a.referencing && !a.moving(now_s) {
                a.referencing = false;
                a.referenced = true;
            }
        }
    }

    /// Indices of the named axes; an empty list means all axes.
    fn select(&self, ids: &[AxisId]) -> Vec<usize> {
        if ids.is_empty() {
            return (0..self.axes.len()).collect();
        }
        ids.iter()
            .filter_map(|id| self.axes.iter().position(|a| a.id == *id))
            .collect()
    }

    fn values(&self, ids: &[AxisId], f: impl Fn(&Axis) -> f64) -> Reply {
        let v: Vec<_> = self
            .select(ids)
            .into_iter()
            .map(|i| (self.axes[i].id.clone(), f(&self.axes[i])))
            .collect();
        Reply::axis_values(&v)
    }

    fn flags(&self, ids: &[AxisId], f: impl Fn(&Axis) -> bool) -> Reply {
        let v: Vec<_> = self
            .select(ids)
            .into_iter()
            .map(|i| (self.axes[i].id.clone(), f(&self.axes[i])))
            .collect();
        Reply::axis_flags(&v)
    }

    fn execute(&mut self, now: f64, command: &Command) -> Option<Reply> {
        match command {
            Command::Mov(pairs) => {
                let targets = pairs.iter().map(|(id, v)| (id.clone(), *v)).collect();
                self.start_moves(now, targets);
                None
            }
            Command::Mvr(pairs) => {
                let targets = pairs
                    .iter()
                    .map(|(id, d)| {
                        let target = self
                            .axes
                            .iter()
                            .find(|a| a.id == *id)
                            .map_or(*d, |a| a.target + d);
                        (id.clone(), target)
                    })
                    .collect();
                self.start_moves(now, targets);
                None
            }
            Command::Svo(pairs) => {
                for (id, on) in pairs {
                    if let Some(a) = self.axes.iter_mut().find(|a| a.id == *id) {
                        if !on {
                            // Open loop: the axis stays where it is.
                            a.halt(now);
                        }
                        a.servo = *on;
                    }
                }
                None
            }
            Command::Frf(ids) => {
                let idx = self.select(ids);
                if idx.iter().any(|&i| !self.axes[i].servo) {
                    self.last_error = GcsErrorCode::MOVE_WITHOUT_REF_OR_NO_SERVO;
                    return None;
                }
                // The reference switch sits at 0 in this model.
                for i in idx {
                    let settle = self.settle_s;
                    let a = &mut self.axes[i];
                    a.start_motion(now, 0.0, settle);
                    a.referenced = false;
                    a.referencing = true;
                }
                None
            }
            Command::Stp | Command::StopAll => {
                for a in &mut self.axes {
                    a.halt(now);
                }
                self.last_error = GcsErrorCode::STOPPED;
                None
            }
            Command::PosQ(ids) => Some(self.values(ids, |a| a.position(now))),
            Command::OntQ(ids) => {
                Some(self.flags(ids, |a| now < a.stale_until || a.on_target(now)))
            }
            Command::SvoQ(ids) => Some(self.flags(ids, |a| a.servo)),
            Command::FrfQ(ids) => Some(self.flags(ids, |a| a.referenced)),
            Command::TmnQ(ids) => Some(self.values(ids, |a| a.min)),
            Command::TmxQ(ids) => Some(self.values(ids, |a| a.max)),
            Command::ErrQ => Some(Reply::error_code(std::mem::replace(
                &mut self.last_error,
                GcsErrorCode::NO_ERROR,
            ))),
            Command::IdnQ => Some(Reply::line(self.idn.clone())),
            Command::MotionStatus => {
                let bits = self
                    .axes
                    .iter()
                    .enumerate()
                    .filter(|(_, a)| a.moving(now) && now >= a.stale_until)
                    .fold(0u32, |bits, (i, _)| bits | (1 << i));
                Some(Reply::motion_bitmap(bits))
            }
            Command::Ready => Some(Reply::ready(!self.axes.iter().any(|a| a.referencing))),
        }
    }

    /// Validates a (multi-axis) move as the controller does, all or nothing, then
    /// applies the move faults.
    fn start_moves(&mut self, now: f64, targets: Vec<(AxisId, f64)>) {
        let mut idx = Vec::with_capacity(targets.len());
        for (id, target) in &targets {
            let Some(i) = self.axes.iter().position(|a| a.id == *id) else {
                self.last_error = GcsErrorCode::INVALID_AXIS_IDENTIFIER;
                return;
            };
            if let Err(refusal) = self.check_target(i, *target) {
                self.last_error = match refusal {
                    MoveRefusal::NotReady => GcsErrorCode::MOVE_WITHOUT_REF_OR_NO_SERVO,
                    MoveRefusal::OutOfLimits | MoveRefusal::Fault => {
                        GcsErrorCode::POS_OUT_OF_LIMITS
                    }
                };
                return;
            }
            idx.push((i, *target));
        }
        if self.start_checked(now, &idx, false) == Err(MoveRefusal::Fault) {
            let code = GcsErrorCode(self.faults.move_error_code);
            self.last_error = code;
            if code == GcsErrorCode::MOTION_ERROR {
                for &(i, _) in &idx {
                    self.axes[i].halt(now);
                    self.axes[i].servo = false;
                }
            }
        }
    }

    /// Whether axis `i` may move to `target`.
    fn check_target(&self, i: usize, target: f64) -> Result<(), MoveRefusal> {
        let a = &self.axes[i];
        if !a.referenced || a.referencing || !a.servo {
            return Err(MoveRefusal::NotReady);
        }
        if !(a.min..=a.max).contains(&target) {
            return Err(MoveRefusal::OutOfLimits);
        }
        Ok(())
    }

    /// Counts an accepted move and applies the move faults: refused
    /// ([`MoveRefusal::Fault`]), silently ignored (`Ok(false)`), or started
    /// (`Ok(true)`, with a stale on-target flag when that fault fires; with
    /// `late_start`, the motion itself starts only when the flag turns honest).
    fn start_checked(
        &mut self,
        now: f64,
        idx: &[(usize, f64)],
        late_start: bool,
    ) -> Result<bool, MoveRefusal> {
        self.moves += 1;
        let m = self.moves;
        if fires(&self.faults.move_error, m, &mut self.rng) {
            self.fired.move_errors += 1;
            return Err(MoveRefusal::Fault);
        }
        if fires(&self.faults.ignore_move, m, &mut self.rng) {
            self.fired.ignored_moves += 1;
            return Ok(false);
        }
        let stale = fires(&self.faults.stale_on_target, m, &mut self.rng);
        if stale {
            self.fired.stale_on_target += 1;
        }
        let stale_until = if stale {
            now + self.faults.stale_on_target_s
        } else {
            now
        };
        let start = if late_start { stale_until } else { now };
        for &(i, target) in idx {
            let settle = self.settle_s;
            let a = &mut self.axes[i];
            a.start_motion(start, target, settle);
            a.stale_until = stale_until;
        }
        Ok(true)
    }

    /// Applies the reply faults of command `k` (numbered by
    /// [`Self::begin_command`]) to its reply: dropped, garbled, late.
    pub fn deliver(&mut self, k: u64, mut bytes: Vec<u8>) -> Response {
        if fires(&self.faults.drop_reply, k, &mut self.rng) {
            self.fired.dropped_replies += 1;
            return Response::default();
        }
        if fires(&self.faults.garble_reply, k, &mut self.rng) {
            self.fired.garbled_replies += 1;
            garble(&mut bytes, &mut self.rng);
        }
        let mut delay = Duration::ZERO;
        if fires(&self.faults.late_reply, k, &mut self.rng) {
            self.fired.late_replies += 1;
            delay = Duration::from_secs_f64(self.faults.late_reply_delay_s);
        }
        Response {
            reply: Some(bytes),
            delay,
            disconnect: false,
        }
    }
}

/// Why the model refuses a move, whatever the dialect (PI GCS maps these to
/// its error codes, RemCon32 to its error numbers).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MoveRefusal {
    /// An axis is unreferenced or referencing, or its servo is off.
    NotReady,
    /// A target lies outside the soft limits.
    OutOfLimits,
    /// The `move_error` fault fired.
    Fault,
}

/// The model as other stage dialects (RemCon32, SharkSEM) drive it: the same
/// axes, motion, counters and faults as PI GCS, addressed by role.
impl StageModel {
    /// Counts a command received at `now_s` and returns its number `k` (from 1),
    /// which places the reply faults. Pair with [`Self::end_command`].
    pub fn begin_command(&mut self, now_s: f64) -> u64 {
        self.commands += 1;
        self.finish_referencing(now_s);
        self.commands
    }

    /// Finishes command `k`: the disconnect fault closes the link after it.
    pub fn end_command(&mut self, k: u64, mut response: Response) -> Response {
        if let Some(n) = self.faults.disconnect_after_commands
            && k >= n
            && !self.disconnected
        {
            self.disconnected = true;
            self.fired.disconnects += 1;
            response.disconnect = true;
        }
        response
    }

    /// Moves the axes of the given roles together to absolute targets, all or
    /// nothing, with the move faults: `Ok(true)` started, `Ok(false)` silently
    /// ignored (fault), or refused. With `late_start`, the stale-flag fault
    /// delays the motion as well as the flag (a move that starts late).
    pub fn move_roles(
        &mut self,
        now_s: f64,
        targets: &[(AxisRole, f64)],
        late_start: bool,
    ) -> Result<bool, MoveRefusal> {
        self.finish_referencing(now_s);
        let mut idx = Vec::with_capacity(targets.len());
        for &(role, target) in targets {
            let Some(i) = self.axes.iter().position(|a| a.role == role) else {
                continue;
            };
            self.check_target(i, target)?;
            idx.push((i, target));
        }
        self.start_checked(now_s, &idx, late_start)
    }

    /// Halts every axis where it is (an abort).
    pub fn halt_all(&mut self, now_s: f64) {
        for a in &mut self.axes {
            a.halt(now_s);
        }
    }

    /// The instrument's "moving" flag: some axis moves or settles, unless the
    /// stale-flag fault makes it lie (a flag set late after a move command).
    pub fn busy(&self, now_s: f64) -> bool {
        self.axes
            .iter()
            .any(|a| now_s >= a.stale_until && (a.moving(now_s) || now_s < a.settled_at))
    }

    /// Whether every axis is referenced with its servo on (moves allowed).
    pub fn ready(&self) -> bool {
        self.axes
            .iter()
            .all(|a| a.referenced && !a.referencing && a.servo)
    }

    /// The soft limits of the axis of `role`, its units.
    pub fn limits(&self, role: AxisRole) -> Option<(f64, f64)> {
        self.axes
            .iter()
            .find(|a| a.role == role)
            .map(|a| (a.min, a.max))
    }
}

/// Whether the trigger fires at occurrence `k`. The random draw happens only for
/// armed probabilities, so the random stream depends on the configuration and
/// the command sequence alone.
pub(crate) fn fires(trigger: &FaultTrigger, k: u64, rng: &mut ChaCha8Rng) -> bool {
    let listed = trigger.at.contains(&k);
    let random = trigger.probability > 0.0 && rng.random::<f64>() < trigger.probability;
    listed || random
}

/// Replaces one content byte (never a separator or a line end) by garbage:
/// `#` (which no GCS reply contains) or 0xFF (never valid on the wire).
fn garble(bytes: &mut Vec<u8>, rng: &mut ChaCha8Rng) {
    let content: Vec<usize> = (0..bytes.len())
        .filter(|&i| !matches!(bytes[i], b' ' | b'\n' | b'\r'))
        .collect();
    let junk = if rng.random::<bool>() { b'#' } else { 0xFF };
    if content.is_empty() {
        bytes.insert(0, junk);
    } else {
        let i = content[rng.random_range(0..content.len())];
        bytes[i] = junk;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sdsem_protocol::gcs::{ErrorQuery, OnTargetQuery, PositionQuery, Query, ReplyFramer};

    fn model(config: StageSimConfig) -> StageModel {
        config.validate().unwrap();
        StageModel::new(&config, 7)
    }

    fn line(s: &str) -> Result<Incoming, FrameError> {
        Ok(Incoming::Line(s.as_bytes().to_vec()))
    }

    fn send(m: &mut StageModel, t: f64, s: &str) -> Option<Vec<u8>> {
        m.handle(t, line(s)).reply
    }

    fn parse<Q: Query>(q: &Q, bytes: &[u8]) -> Q::Output {
        let mut f = ReplyFramer::new();
        f.feed(bytes);
        q.parse_reply(&f.next_reply().unwrap().unwrap()).unwrap()
    }

    fn t_axis() -> AxisId {
        AxisId::new("T").unwrap()
    }

    fn pos_t(m: &mut StageModel, t: f64) -> f64 {
        let bytes = send(m, t, "POS? T").unwrap();
        parse(&PositionQuery(vec![t_axis()]), &bytes)[0].1
    }

    fn ont_t(m: &mut StageModel, t: f64) -> bool {
        let bytes = send(m, t, "ONT? T").unwrap();
        parse(&OnTargetQuery(vec![t_axis()]), &bytes)[0].1
    }

    fn err(m: &mut StageModel, t: f64) -> GcsErrorCode {
        parse(&ErrorQuery, &send(m, t, "ERR?").unwrap())
    }

    #[test]
    fn tilt_moves_at_finite_speed_then_settles() {
        let mut m = model(StageSimConfig::default());
        assert_eq!(send(&mut m, 0.0, "MOV T 7"), None, "commands do not answer");
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::NO_ERROR);
        assert!((pos_t(&mut m, 3.5) - 3.5).abs() < 1e-9, "1°/s by default");
        assert!(!ont_t(&mut m, 3.5));
        assert_eq!(
            send(&mut m, 3.5, "\x05"),
            None,
            "a line, not the single byte"
        );
        let moving = m.handle(3.5, Ok(Incoming::Single(0x05))).reply.unwrap();
        assert_eq!(moving, b"4\n", "bit 2 = the third axis, T");
        // Arrived at 7 s but settling for 0.2 s.
        assert_eq!(pos_t(&mut m, 7.1), 7.0);
        assert!(!ont_t(&mut m, 7.1));
        assert!(ont_t(&mut m, 7.25));
        assert_eq!(
            m.handle(7.25, Ok(Incoming::Single(0x05))).reply.unwrap(),
            b"0\n"
        );
        assert_eq!(m.pose(7.25).tilt_deg, 7.0);
    }

    #[test]
    fn multi_axis_queries_answer_in_the_documented_format() {
        let mut m = model(StageSimConfig::default());
        send(&mut m, 0.0, "MOV X 100 Y -50");
        let r = send(&mut m, 0.5, "POS?").unwrap();
        assert_eq!(r, b"X=50.000000 \nY=-50.000000 \nT=0.000000\n");
        let r = send(&mut m, 0.5, "ONT? T X").unwrap();
        assert_eq!(r, b"T=1 \nX=0\n");
        assert_eq!(send(&mut m, 0.5, "TMX? T").unwrap(), b"T=70.000000\n");
        assert_eq!(send(&mut m, 0.5, "TMN? T").unwrap(), b"T=-5.000000\n");
    }

    #[test]
    fn relative_move_adds_to_the_target() {
        let mut m = model(StageSimConfig::default());
        send(&mut m, 0.0, "MOV T 2");
        send(&mut m, 0.5, "MVR T 1");
        assert_eq!(m.snapshot(0.5).axes[2].target, 3.0);
        assert_eq!(pos_t(&mut m, 10.0), 3.0);
    }

    #[test]
    fn out_of_limit_targets_are_refused_with_error_7() {
        let mut m = model(StageSimConfig::default());
        send(&mut m, 0.0, "MOV T 70.5");
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::POS_OUT_OF_LIMITS);
        send(&mut m, 0.0, "MOV X 10 T -6");
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::POS_OUT_OF_LIMITS);
        assert_eq!(
            m.pose(5.0),
            StagePose::default(),
            "all or nothing: X did not move"
        );
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::NO_ERROR, "reading clears");
    }

    #[test]
    fn unreferenced_or_servo_off_axes_refuse_moves_with_error_5() {
        let mut m = model(StageSimConfig {
            referenced: false,
            servo_on: false,
            start_tilt_deg: 0.5,
            ..StageSimConfig::default()
        });
        assert_eq!(send(&mut m, 0.0, "FRF? T").unwrap(), b"T=0\n");
        send(&mut m, 0.0, "MOV T 1");
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::MOVE_WITHOUT_REF_OR_NO_SERVO);
        // Referencing needs the servo on, too.
        send(&mut m, 0.0, "FRF T");
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::MOVE_WITHOUT_REF_OR_NO_SERVO);
        send(&mut m, 0.0, "SVO T 1");
        send(&mut m, 0.0, "FRF T");
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::NO_ERROR);
        // Referencing moves 0.5° to the switch at 0: busy meanwhile.
        assert_eq!(
            m.handle(0.0, Ok(Incoming::Single(0x07))).reply.unwrap(),
            [0xB0, b'\n']
        );
        assert_eq!(send(&mut m, 0.2, "FRF? T").unwrap(), b"T=0\n");
        assert_eq!(send(&mut m, 1.0, "FRF? T").unwrap(), b"T=1\n");
        assert_eq!(pos_t(&mut m, 1.0), 0.0);
        assert_eq!(
            m.handle(1.0, Ok(Incoming::Single(0x07))).reply.unwrap(),
            [0xB1, b'\n']
        );
        send(&mut m, 1.0, "MOV T 1");
        assert_eq!(err(&mut m, 1.0), GcsErrorCode::NO_ERROR);
        assert_eq!(pos_t(&mut m, 3.0), 1.0);
    }

    #[test]
    fn stop_halts_mid_move_and_sets_error_10() {
        let mut m = model(StageSimConfig::default());
        send(&mut m, 0.0, "MOV T 10");
        send(&mut m, 2.0, "STP");
        assert_eq!(err(&mut m, 2.0), GcsErrorCode::STOPPED);
        assert_eq!(pos_t(&mut m, 5.0), 2.0);
        assert!(ont_t(&mut m, 5.0), "the target is where it stopped");
        // #24 does the same.
        send(&mut m, 5.0, "MOV T 10");
        m.handle(6.0, Ok(Incoming::Single(0x18)));
        assert_eq!(err(&mut m, 6.0), GcsErrorCode::STOPPED);
        assert_eq!(pos_t(&mut m, 9.0), 3.0);
    }

    #[test]
    fn bad_commands_set_the_controller_codes_and_do_not_answer() {
        let mut m = model(StageSimConfig::default());
        assert_eq!(send(&mut m, 0.0, "POS? Q"), None);
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::INVALID_AXIS_IDENTIFIER);
        assert_eq!(send(&mut m, 0.0, "HELLO"), None);
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::UNKNOWN_COMMAND);
        send(&mut m, 0.0, "MOV T x");
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::PARAM_SYNTAX);
        m.handle(0.0, Err(FrameError::LineTooLong { limit: 256 }));
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::COMMAND_TOO_LONG);
        // Only the last error is kept.
        send(&mut m, 0.0, "HELLO");
        send(&mut m, 0.0, "POS? Q");
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::INVALID_AXIS_IDENTIFIER);
        assert_eq!(m.command_count(), 11);
    }

    #[test]
    fn dropped_garbled_and_late_replies_at_given_commands() {
        let mut cfg = StageSimConfig::default();
        cfg.faults.drop_reply = FaultTrigger::at([1]);
        cfg.faults.garble_reply = FaultTrigger::at([2]);
        cfg.faults.late_reply = FaultTrigger::at([3]);
        let mut m = model(cfg);
        assert_eq!(m.handle(0.0, line("POS? T")), Response::default());
        let garbled = send(&mut m, 0.0, "POS? T").unwrap();
        assert_ne!(garbled, b"T=0.000000\n");
        assert_eq!(garbled.len(), b"T=0.000000\n".len());
        assert!(garbled.ends_with(b"\n"));
        let late = m.handle(0.0, line("POS? T"));
        assert_eq!(late.reply.as_deref(), Some(&b"T=0.000000\n"[..]));
        assert_eq!(late.delay, Duration::from_secs(2));
        assert_eq!(send(&mut m, 0.0, "POS? T").unwrap(), b"T=0.000000\n");
        let f = m.snapshot(0.0).faults;
        assert_eq!(
            (f.dropped_replies, f.garbled_replies, f.late_replies),
            (1, 1, 1)
        );
    }

    #[test]
    fn garbled_replies_never_parse() {
        let mut cfg = StageSimConfig::default();
        cfg.faults.garble_reply = FaultTrigger::probability(1.0);
        let mut m = model(cfg);
        let q = PositionQuery(vec![AxisId::new("X").unwrap(), t_axis()]);
        for _ in 0..200 {
            let bytes = send(&mut m, 0.0, "POS? X T").unwrap();
            let mut f = ReplyFramer::new();
            f.feed(&bytes);
            let parsed = f.next_reply().unwrap().map(|r| q.parse_reply(&r));
            assert!(!matches!(parsed, Ok(Ok(_))), "garbled {bytes:?} parsed");
        }
    }

    #[test]
    fn ignored_move_silently_does_nothing() {
        let mut cfg = StageSimConfig::default();
        cfg.faults.ignore_move = FaultTrigger::at([2]);
        let mut m = model(cfg);
        send(&mut m, 0.0, "MOV T 1");
        send(&mut m, 2.0, "MOV T 2");
        assert_eq!(err(&mut m, 2.0), GcsErrorCode::NO_ERROR);
        assert!(ont_t(&mut m, 2.0), "still on its old target");
        assert_eq!(pos_t(&mut m, 5.0), 1.0);
        send(&mut m, 5.0, "MOV T 2");
        assert_eq!(pos_t(&mut m, 10.0), 2.0);
        assert_eq!(m.snapshot(10.0).faults.ignored_moves, 1);
    }

    #[test]
    fn stale_on_target_flag_lies_for_a_while() {
        let mut cfg = StageSimConfig::default();
        cfg.faults.stale_on_target = FaultTrigger::at([1]);
        let mut m = model(cfg);
        send(&mut m, 0.0, "MOV T 3");
        assert!(ont_t(&mut m, 0.1), "stale: says on target while moving");
        assert_eq!(
            m.handle(0.1, Ok(Incoming::Single(0x05))).reply.unwrap(),
            b"0\n"
        );
        assert!(
            (pos_t(&mut m, 0.1) - 0.1).abs() < 1e-9,
            "but the position moves"
        );
        assert!(!ont_t(&mut m, 0.6), "after 0.5 s the flag is honest again");
        assert!(ont_t(&mut m, 3.3));
    }

    #[test]
    fn move_error_refuses_the_move_and_switches_the_servo_off() {
        let mut cfg = StageSimConfig::default();
        cfg.faults.move_error = FaultTrigger::at([1]);
        let mut m = model(cfg);
        send(&mut m, 0.0, "MOV T 3");
        assert_eq!(err(&mut m, 0.0), GcsErrorCode::MOTION_ERROR);
        assert_eq!(pos_t(&mut m, 5.0), 0.0);
        assert_eq!(send(&mut m, 5.0, "SVO? T").unwrap(), b"T=0\n");
    }

    #[test]
    fn disconnect_after_n_commands_fires_once() {
        let mut cfg = StageSimConfig::default();
        cfg.faults.disconnect_after_commands = Some(2);
        let mut m = model(cfg);
        assert!(!m.handle(0.0, line("ERR?")).disconnect);
        let second = m.handle(0.0, line("POS? T"));
        assert!(second.disconnect);
        assert!(second.reply.is_some(), "the N-th command is still answered");
        assert!(!m.handle(0.0, line("ERR?")).disconnect);
    }

    #[test]
    fn probabilistic_faults_are_deterministic_for_a_seed() {
        let mut cfg = StageSimConfig::default();
        cfg.faults.drop_reply = FaultTrigger::probability(0.3);
        cfg.faults.garble_reply = FaultTrigger::probability(0.3);
        cfg.faults.ignore_move = FaultTrigger::probability(0.3);
        let run = |seed| {
            let mut m = StageModel::new(&cfg, seed);
            let mut out = Vec::new();
            for i in 0..100 {
                let t = f64::from(i);
                out.push(send(&mut m, t, &format!("MOV T {}", i % 7)));
                out.push(send(&mut m, t, "POS? T"));
            }
            (out, m.snapshot(100.0).faults)
        };
        let (a, fa) = run(1);
        let (b, fb) = run(1);
        let (c, _) = run(2);
        assert_eq!(a, b);
        assert_eq!(fa, fb);
        assert_ne!(a, c, "another seed gives other faults");
        assert!(
            fa.dropped_replies > 10 && fa.garbled_replies > 5 && fa.ignored_moves > 10,
            "{fa:?}"
        );
    }
}
