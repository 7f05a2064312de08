//! The stage layer's errors: each names the command, the reply when there was
//! one, the cause, and what to do about it.

use std::time::Duration;

use sdsem_protocol::gcs::GcsErrorCode;
use sdsem_protocol::remcon::RemconError;

use super::config::{StageAxis, StageConfig, StageProtocol};
use super::transport::Endpoint;

/// Everything that can go wrong between sdsem and the stage controller.
#[derive(Debug, thiserror::Error)]
pub enum StageError {
    /// A configuration value is wrong.
    #[error("invalid stage configuration: {field}: {reason}")]
    Config {
        /// The field, as written in the configuration.
        field: &'static str,
        /// What is wrong and what is accepted.
        reason: String,
    },

    /// The port or connection cannot be opened.
    #[error("cannot open the stage controller at {endpoint}: {cause}; {remedy}")]
    Open {
        /// The endpoint from the configuration.
        endpoint: String,
        /// The system's reason.
        cause: String,
        /// What to check.
        remedy: String,
    },

    /// The link closed or failed.
    #[error(
        "stage link lost during `{command}`: {cause}; check the controller's power and cable \
         (or that the simulator still runs), then start the run again"
    )]
    Disconnected {
        /// The command in flight.
        command: String,
        /// What the link reported.
        cause: String,
    },

    /// A query was not answered, retries included.
    #[error("no reply to `{command}` within {timeout:?} ({attempts} attempt(s)); {remedy}")]
    NoReply {
        /// The query.
        command: String,
        /// Attempts made.
        attempts: u32,
        /// Time allowed for each.
        timeout: Duration,
        /// What to check, for this link ([`LinkRemedies`]).
        remedy: String,
    },

    /// A query was answered with garbage, retries included.
    #[error(
        "garbled reply to `{command}` ({attempts} attempt(s)), last {reply:?}: {cause}; {remedy}"
    )]
    Garbled {
        /// The query.
        command: String,
        /// The last reply, escaped (none when the bytes did not even frame).
        reply: Option<String>,
        /// Why it does not parse.
        cause: String,
        /// Attempts made.
        attempts: u32,
        /// What to check, for this link ([`LinkRemedies`]).
        remedy: String,
    },

    /// The controller refused a command: `ERR?` answered a non-zero code.
    #[error("the controller refused `{command}` with error {code}; {remedy}")]
    Controller {
        /// The refused command.
        command: String,
        /// The controller's error code (the reply to `ERR?`).
        code: GcsErrorCode,
        /// What to do.
        remedy: String,
    },

    /// A target outside the configured (or controller) limits; nothing was sent.
    #[error(
        "{axis} target {target} {unit} is outside the limits [{min}, {max}] {unit}; nothing was sent \
         to the controller: choose a target inside them, or widen {} if the stage allows it",
        .axis.limit_fields()
    )]
    OutOfLimits {
        /// The axis.
        axis: StageAxis,
        /// The refused target.
        target: f64,
        /// Lowest allowed.
        min: f64,
        /// Highest allowed.
        max: f64,
        /// Unit of the axis.
        unit: &'static str,
    },

    /// `*IDN?` does not name the expected controller.
    #[error(
        "the device at the stage endpoint answers {idn:?}, which does not contain {expected:?}; \
         check that stage.endpoint is the stage controller, or clear stage.expect_idn"
    )]
    UnexpectedIdentity {
        /// The answer to `*IDN?`.
        idn: String,
        /// The configured `expect_idn`.
        expected: String,
    },

    /// Axes are unreferenced or their servo is off, so moves would be refused.
    #[error("{}", not_ready_message(unreferenced, servo_off))]
    NotReady {
        /// Axes not referenced (`FRF?` = 0), GCS identifiers.
        unreferenced: Vec<String>,
        /// Axes with the servo off (`SVO?` = 0), GCS identifiers.
        servo_off: Vec<String>,
    },

    /// Referencing did not finish in time.
    #[error(
        "referencing {axes:?} did not finish within {timeout:?}; the stage was stopped (STP): \
         check that nothing blocks the travel to the reference switches, or raise \
         stage.reference_timeout_s"
    )]
    ReferenceTimeout {
        /// Axes still unreferenced.
        axes: Vec<String>,
        /// Time allowed.
        timeout: Duration,
    },

    /// The controller reports on target, but the axis did not go there, even
    /// after the move was re-issued once.
    #[error(
        "`{command}` did not move the {axis} axis: it stays at {position} {unit} (target {target}, \
         tolerance {tolerance}) although the controller reports it on target, and re-issuing the \
         move once did not help; check the stage for a mechanical block or a controller fault, or \
         widen {} if the controller's own on-target window is wider",
        .axis.tolerance_field()
    )]
    MoveNotExecuted {
        /// The move command.
        command: String,
        /// The axis that did not arrive.
        axis: StageAxis,
        /// Its target.
        target: f64,
        /// Where it is.
        position: f64,
        /// The tolerance applied.
        tolerance: f64,
        /// Unit of the axis.
        unit: &'static str,
    },

    /// A move did not reach its target in time; the stage was stopped.
    #[error(
        "`{command}` did not reach the target in {timeout:?}: {axis} at {position:?} (target \
         {target}); the stage was stopped: check for an obstruction, or lower {} / raise \
         stage.move_timeout_margin_s if the stage is slower than configured",
        .axis.speed_field()
    )]
    MoveTimeout {
        /// The move command.
        command: String,
        /// The first axis not on target.
        axis: StageAxis,
        /// Its target.
        target: f64,
        /// Its last known position.
        position: Option<f64>,
        /// Time allowed.
        timeout: Duration,
    },

    /// The SEM's stage over TESCAN SharkSEM (the message names the function and the remedy).
    #[error("{0}")]
    SharkSem(crate::sharksem::SharkError),

    /// The stage protocol cannot do what was asked.
    #[error("stage.protocol = \"{protocol}\" cannot send {what}; {remedy}")]
    Unsupported {
        /// The protocol in use.
        protocol: StageProtocol,
        /// What was asked.
        what: String,
        /// What to do instead.
        remedy: &'static str,
    },

    /// The SEM refused a RemCon32 command: its status line was `*NNN`.
    #[error("the SEM refused `{command}` with RemCon32 error {error}; {remedy}")]
    Remcon {
        /// The refused command.
        command: String,
        /// The error number, named.
        error: RemconError,
        /// What to do.
        remedy: &'static str,
    },

    /// The instrument answered that the command is invalid (RemCon32 `#`).
    #[error(
        "the SEM answered `#` (invalid command) to `{command}` ({attempts} attempt(s)); check \
         that stage.protocol names the instrument's language and, for imaging.trigger, the \
         command's arguments"
    )]
    InvalidCommand {
        /// The command.
        command: String,
        /// Attempts made.
        attempts: u32,
    },

    /// The SEM's stage is not initialised, so it cannot move.
    #[error(
        "the SEM's stage is not initialised (IST? answered {reply:?}); initialise the stage in \
         SmartSEM, then start again"
    )]
    NotInitialised {
        /// The answer to `IST?`.
        reply: String,
    },
}

error_from!(StageError {
    SharkSem(crate::sharksem::SharkError)
});

/// What to check when the stage link answers nothing or garbage. Over TCP: the address and
/// the language spoken there; over a serial line: the cable and the baud rate.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct LinkRemedies {
    /// For a query not answered.
    pub silent: String,
    /// For a reply that does not parse.
    pub garbled: String,
}

impl LinkRemedies {
    /// The remedies for `config.endpoint` and `config.protocol`.
    pub fn new(config: &StageConfig) -> Self {
        let protocol = config.protocol;
        let (language, axes) = match protocol {
            StageProtocol::PiGcs => ("PI GCS", ", and that stage.axis_x/axis_y/axis_tilt match"),
            StageProtocol::Remcon32 => ("Zeiss RemCon32", ""),
            StageProtocol::Sharksem => ("TESCAN SharkSEM", ""),
        };
        match Endpoint::parse(&config.endpoint) {
            Ok(Endpoint::Tcp(addr)) => {
                let (server, alive) = match protocol {
                    StageProtocol::PiGcs => (
                        "the stage controller's TCP port",
                        "the controller is powered and not busy",
                    ),
                    // No TCP RemCon32 is known: a serial-to-Ethernet server forwards its line (VENDORS §1.1).
                    StageProtocol::Remcon32 => (
                        "a serial-to-Ethernet server on the SEM PC's RemCon32 line",
                        "RemCon32 runs on the SEM PC",
                    ),
                    StageProtocol::Sharksem => {
                        ("the SEM's SharkSEM control port", "the SEM software runs")
                    }
                };
                let check = format!(
                    "check that {addr} (stage.endpoint) is {server}, that it speaks {language} \
                     (stage.protocol = \"{protocol}\")"
                );
                Self {
                    silent: format!("{check} and that {alive}"),
                    garbled: format!("{check}{axes}"),
                }
            }
            // A serial line (an endpoint that does not parse never opened).
            _ => Self {
                silent: format!(
                    "check the cable, the baud rate (stage.baud; {}) and that the controller is \
                     powered and not busy",
                    config
                        .effective_baud()
                        .map_or_else(|| "none set".to_owned(), |b| format!("{b} in use"))
                ),
                garbled: format!(
                    "check the baud rate (stage.baud), the cable and its shielding, and that the \
                     device speaks {language} (stage.protocol = \"{protocol}\"){axes}"
                ),
            },
        }
    }
}

fn not_ready_message(unreferenced: &[String], servo_off: &[String]) -> String {
    let mut what = Vec::new();
    if !servo_off.is_empty() {
        what.push(format!("servo off on axes {servo_off:?} (SVO? = 0)"));
    }
    if !unreferenced.is_empty() {
        what.push(format!("axes {unreferenced:?} not referenced (FRF? = 0)"));
    }
    format!(
        "the stage is not ready to move: {}; switch the servos on (SVO) and reference the axes \
         (FRF) with the controller's software, or set stage.auto_reference = true if moving to \
         the reference switches is safe for this specimen",
        what.join(", ")
    )
}

/// What to do about a controller error code.
pub(crate) fn remedy(code: GcsErrorCode) -> String {
    match code.0 {
        1 => "the controller did not understand the parameters: report this as an sdsem bug".into(),
        2 => "the controller does not know this command: is it a PI GCS 2.0 controller?".into(),
        5 => "reference the axes (FRF) and switch their servos on (SVO), or set \
              stage.auto_reference = true"
            .into(),
        7 => "the target is beyond the controller's soft limits (TMN?/TMX?): narrow the \
              configured limits"
            .into(),
        10 => {
            "the stage was stopped (STP, an abort or another client); start the move again".into()
        }
        15 => "stage.axis_x/axis_y/axis_tilt do not match the controller's axis identifiers \
               (the controller lists them with SAI?)"
            .into(),
        1024 => "motion error, the servo switched off: check the stage for an obstruction, then \
                 switch the servo on (SVO) and reference again"
            .into(),
        _ => "see the controller's manual for this error code".into(),
    }
}

/// What to do about a RemCon32 error number.
pub(crate) fn remcon_remedy(error: RemconError) -> &'static str {
    match error {
        RemconError::UnknownCommand => {
            "the SEM does not know this command: check that stage.protocol = \"remcon32\" suits \
             this SEM and the spelling of imaging.trigger"
        }
        RemconError::InvalidParameterCount | RemconError::InvalidParameterType => {
            "the SEM did not accept the parameters: check imaging.trigger, or report this as an \
             sdsem bug"
        }
        RemconError::ParameterOutOfRange => {
            "a target is beyond the SEM stage's range: narrow stage.xy_min_um/xy_max_um and \
             stage.tilt_min_deg/tilt_max_deg to the range SmartSEM shows for this stage"
        }
        RemconError::CommandTimeout => {
            "the SEM timed out executing it: look for a dialog or an error in SmartSEM, then \
             start again"
        }
        RemconError::Catastrophic => {
            "SmartSEM reports a catastrophic error: restart the SEM software as its manual \
             says, then start again"
        }
        RemconError::ExternalControlAbort => {
            "external control was aborted on the SEM: check that RemCon32 still runs on the \
             SEM PC and that nobody took over the stage, then start again"
        }
        RemconError::ParameterUnattainable => {
            "the stage cannot reach that position now (collision protection, working distance): \
             check the stage in SmartSEM, or narrow the limits in [stage]"
        }
        RemconError::OptionNotFitted => {
            "this SEM lacks the option (e.g. a motorised tilt): check the stage fitted"
        }
        RemconError::CannotChangeParameter | RemconError::CannotExecute => {
            "the SEM cannot do it now: check in SmartSEM that the stage is initialised, not \
             locked and not in use, then start again"
        }
        RemconError::CommandTooLong => {
            "the command is too long for RemCon32: shorten imaging.trigger"
        }
        RemconError::Other(_) => "see the RemCon32 manual for this error number",
    }
}
