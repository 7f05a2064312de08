//! `sdsem probe`: connect to the instruments as a run would, say what they are and where the
//! stage is, and move nothing — no referencing (`stage.auto_reference` is forced off), no move,
//! no scan, no trigger. The first thing to run against a new microscope.

use serde::Serialize;

use super::instruments::{Instruments, InstrumentsError};
use crate::config::Config;
use crate::imaging::SourceIdentity;
use crate::stage::{StageAxis, StageIdentity, StagePosition};

/// One line of what an instrument says, in its own words (command or key, then the answer).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Fact {
    pub name: String,
    pub value: String,
}

/// The limits of one axis: configured, reported by the instrument, enforced (the configured
/// ones narrowed to the instrument's), and whether the stage stands within them now.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct AxisLimits {
    pub axis: StageAxis,
    pub unit: &'static str,
    pub configured: (f64, f64),
    pub instrument: Option<(f64, f64)>,
    pub enforced: (f64, f64),
    pub position: f64,
    pub inside: bool,
}

/// The stage as probed.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct StageProbe {
    pub protocol: String,
    pub endpoint: String,
    pub identity: StageIdentity,
    pub position: StagePosition,
    pub limits: Vec<AxisLimits>,
    /// The configured safe tilt, and whether the enforced tilt limits allow it.
    pub safe_tilt_deg: f64,
    pub safe_tilt_inside: bool,
    pub facts: Vec<Fact>,
}

/// The imaging source as probed.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ImagingProbe {
    pub protocol: String,
    /// The source's identification answer (`*IDN?`, a folder and its state).
    pub identification: String,
    /// Who makes the frames, as far as the source knows (empty fields: unknown).
    pub identity: SourceIdentity,
    pub facts: Vec<Fact>,
}

/// What `sdsem probe` found.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ProbeReport {
    /// Whether the instruments are sdsem's in-process simulator (`[simulator]` configured).
    pub simulator: bool,
    pub stage: StageProbe,
    pub imaging: ImagingProbe,
}

fn facts(lines: Vec<(String, String)>) -> Vec<Fact> {
    lines
        .into_iter()
        .map(|(name, value)| Fact { name, value })
        .collect()
}

/// Connects as a run would (checks included), reads, and disconnects; moves nothing.
///
/// # Errors
/// [`InstrumentsError`] naming the link, the cause and the remedy.
pub async fn probe(config: &Config) -> Result<ProbeReport, InstrumentsError> {
    let mut config = config.clone();
    // Referencing moves the axes: a probe reports an unreferenced stage instead.
    config.stage.auto_reference = false;
    let mut instruments = Instruments::connect(&config).await?;
    let stage = &mut instruments.stage;
    let position = stage.position().await?;
    let limits = StageAxis::ALL
        .into_iter()
        .map(|axis| {
            let enforced = stage.limits(axis);
            let at = position.get(axis);
            AxisLimits {
                axis,
                unit: axis.unit(),
                configured: config.stage.limits(axis),
                instrument: stage.instrument_limits(axis),
                enforced,
                position: at,
                inside: (enforced.0..=enforced.1).contains(&at),
            }
        })
        .collect();
    let tilt = stage.limits(StageAxis::Tilt);
    let safe_tilt_deg = config.stage.safe_tilt_deg;
    let stage_facts = facts(stage.backend_mut().probe_facts().await?);
    let stage = StageProbe {
        protocol: stage.protocol().as_str().to_owned(),
        endpoint: stage.config().endpoint.clone(),
        identity: stage.instrument().clone(),
        position,
        limits,
        safe_tilt_deg,
        safe_tilt_inside: (tilt.0..=tilt.1).contains(&safe_tilt_deg),
        facts: stage_facts,
    };
    let imaging_facts = facts(instruments.imaging.probe().await?);
    let imaging = ImagingProbe {
        protocol: config.imaging.protocol.as_str().to_owned(),
        identification: instruments.sem_identity.clone(),
        identity: instruments.imaging.identity(),
        facts: imaging_facts,
    };
    Ok(ProbeReport {
        simulator: instruments.simulator().is_some(),
        stage,
        imaging,
    })
}

impl ProbeReport {
    /// The report as an aligned two-column table, one fact a line.
    #[must_use]
    pub fn table(&self) -> String {
        let mut rows: Vec<(String, String)> = Vec::new();
        let s = &self.stage;
        section(&mut rows, "STAGE");
        rows.push(("protocol".into(), s.protocol.clone()));
        rows.push((
            "endpoint".into(),
            if self.simulator {
                format!("{} (in-process simulator)", s.endpoint)
            } else {
                s.endpoint.clone()
            },
        ));
        push_identity(
            &mut rows,
            [
                ("vendor", &s.identity.vendor),
                ("model", &s.identity.model),
                ("version", &s.identity.version),
                ("serial", &s.identity.serial),
            ],
        );
        rows.push(("identification".into(), s.identity.raw.clone()));
        for l in &s.limits {
            let show = |(lo, hi): (f64, f64)| format!("[{lo}, {hi}]");
            rows.push((
                format!("{}, {}", l.axis, l.unit),
                format!(
                    "at {}{}; limits {} enforced (configured {}, instrument {})",
                    l.position,
                    if l.inside {
                        ""
                    } else {
                        " — OUTSIDE the limits"
                    },
                    show(l.enforced),
                    show(l.configured),
                    l.instrument.map_or_else(|| "not reported".to_owned(), show),
                ),
            ));
        }
        rows.push((
            "safe tilt".into(),
            format!(
                "{}°{}",
                s.safe_tilt_deg,
                if s.safe_tilt_inside {
                    ""
                } else {
                    " — OUTSIDE the tilt limits: set stage.safe_tilt_deg"
                }
            ),
        ));
        rows.extend(s.facts.iter().map(|f| (f.name.clone(), f.value.clone())));
        let i = &self.imaging;
        section(&mut rows, "IMAGING");
        rows.push(("protocol".into(), i.protocol.clone()));
        rows.push(("identification".into(), i.identification.clone()));
        push_identity(
            &mut rows,
            [
                ("vendor", &i.identity.vendor),
                ("model", &i.identity.model),
                ("version", &i.identity.version),
                ("serial", &i.identity.serial),
            ],
        );
        rows.extend(i.facts.iter().map(|f| (f.name.clone(), f.value.clone())));
        let width = rows
            .iter()
            .map(|(k, _)| k.chars().count())
            .max()
            .unwrap_or(0);
        let mut out = String::new();
        for (k, v) in rows.iter().skip(1) {
            if v.is_empty() {
                out.push_str(k);
            } else {
                out.push_str(&format!("  {k:<width$}  {v}"));
            }
            out.push('\n');
        }
        out
    }
}

/// A blank line, then a section title.
fn section(rows: &mut Vec<(String, String)>, title: &str) {
    rows.push((String::new(), String::new()));
    rows.push((title.to_owned(), String::new()));
}

fn push_identity(rows: &mut Vec<(String, String)>, fields: [(&str, &String); 4]) {
    for (name, value) in fields {
        if !value.is_empty() {
            rows.push((name.to_owned(), value.clone()));
        }
    }
}
