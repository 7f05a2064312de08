//! Typed responses: decoded by the client knowing what it asked, encoded by the simulator.

use std::fmt;

use super::body::{BodyError, BodyReader, BodyWriter, format_float, format_map, parse_map};
use super::header::{Flags, FnName, HEADER_LEN, Header};
use super::request::Request;

/// Where the stage is [TS-PDF `StgGetPosition`]: mm and degrees.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StagePosition {
    pub x_mm: f64,
    pub y_mm: f64,
    pub z_mm: f64,
    pub rotation_deg: f64,
    pub tilt_deg: f64,
    /// The sixth value of 3.x servers whose tilt-Y is motorised.
    pub tilt_y_deg: Option<f64>,
}

impl StagePosition {
    /// The values in wire order.
    #[must_use]
    pub fn values(&self) -> Vec<f64> {
        let mut v = vec![
            self.x_mm,
            self.y_mm,
            self.z_mm,
            self.rotation_deg,
            self.tilt_deg,
        ];
        v.extend(self.tilt_y_deg);
        v
    }
}

/// Stage limits [TS-PDF `StgGetLimits`]: (min, max) per axis, mm and degrees.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StageLimits {
    pub x_mm: (f64, f64),
    pub y_mm: (f64, f64),
    pub z_mm: (f64, f64),
    pub rotation_deg: (f64, f64),
    pub tilt_deg: (f64, f64),
}

impl StageLimits {
    fn pairs(&self) -> [(f64, f64); 5] {
        [
            self.x_mm,
            self.y_mm,
            self.z_mm,
            self.rotation_deg,
            self.tilt_deg,
        ]
    }
}

/// One scan speed of `ScEnumSpeeds`.
#[derive(Clone, Debug, PartialEq)]
pub struct ScanSpeed {
    pub index: u32,
    /// Pixel dwell, µs.
    pub dwell_us: f64,
}

/// One detector of `DtEnumDetectors`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Detector {
    /// `K` in `det.K.…`.
    pub index: u32,
    pub name: String,
    /// The id `DtSelect` takes.
    pub id: i32,
}

/// A decoded response.
#[derive(Clone, Debug, PartialEq)]
pub enum Response {
    /// A void function answered because [`Flags::SEND_RESPONSE`] was set.
    Void,
    /// A text value (versions, serial number, model).
    Text(String),
    /// An int value (`TcpRegDataPort`, `StgIsBusy`, `StgIsCalibrated`, `ScScanXY`, `IsBusy`, `DtGetSelected`).
    Int(i32),
    Position(StagePosition),
    Limits(StageLimits),
    /// `GetViewField`, mm.
    ViewField(f64),
    Speeds(Vec<ScanSpeed>),
    Detectors(Vec<Detector>),
    /// `DtGetEnabled`: enabled flag and bits per pixel.
    Enabled {
        enable: i32,
        bpp: i32,
    },
    /// `GetDeviceParams`: the map's entries in order.
    Params(Vec<(String, String)>),
}

impl Request {
    /// Client side: the response to this request, from its body. Values a newer
    /// server appends after those known here are ignored.
    ///
    /// # Errors
    /// [`BodyError`] when the body does not hold what the function returns.
    pub fn decode_response(&self, body: &[u8]) -> Result<Response, BodyError> {
        let mut r = BodyReader::new(body);
        Ok(match self {
            Self::TcpGetVersion
            | Self::TcpGetSwVersion
            | Self::TcpGetDevice
            | Self::TcpGetModel => Response::Text(r.string()?),
            Self::TcpRegDataPort { .. }
            | Self::StgIsBusy
            | Self::StgIsCalibrated
            | Self::ScScanXY(_)
            | Self::IsBusy { .. }
            | Self::DtGetSelected { .. } => Response::Int(r.int()?),
            Self::StgGetPosition => {
                let mut v = Vec::with_capacity(6);
                while !r.is_empty() && v.len() < 6 {
                    v.push(r.float()?);
                }
                if v.len() < 5 {
                    return Err(BodyError::Count {
                        what: "StgGetPosition",
                        expected: "5 or 6",
                        got: v.len(),
                    });
                }
                Response::Position(StagePosition {
                    x_mm: v[0],
                    y_mm: v[1],
                    z_mm: v[2],
                    rotation_deg: v[3],
                    tilt_deg: v[4],
                    tilt_y_deg: v.get(5).copied(),
                })
            }
            Self::StgGetLimits { .. } => {
                let mut v = [0.0; 10];
                for (i, slot) in v.iter_mut().enumerate() {
                    *slot = r.float().map_err(|e| match e {
                        BodyError::Truncated { .. } => BodyError::Count {
                            what: "StgGetLimits",
                            expected: "10",
                            got: i,
                        },
                        e => e,
                    })?;
                }
                Response::Limits(StageLimits {
                    x_mm: (v[0], v[1]),
                    y_mm: (v[2], v[3]),
                    z_mm: (v[4], v[5]),
                    rotation_deg: (v[6], v[7]),
                    tilt_deg: (v[8], v[9]),
                })
            }
            Self::GetViewField => Response::ViewField(r.float()?),
            Self::ScEnumSpeeds => Response::Speeds(parse_speeds(&r.string()?)),
            Self::DtEnumDetectors => Response::Detectors(parse_detectors(&r.string()?)),
            Self::DtGetEnabled { .. } => Response::Enabled {
                enable: r.int()?,
                bpp: r.int()?,
            },
            Self::GetDeviceParams { .. } => Response::Params(parse_map(&r.string()?)),
            Self::StgMoveTo(_)
            | Self::StgStop
            | Self::SetViewField { .. }
            | Self::DtSelect { .. }
            | Self::DtEnable { .. }
            | Self::ScStopScan => Response::Void,
        })
    }
}

/// `speed.N.dwell=µs` entries, in index order; other keys are ignored.
fn parse_speeds(text: &str) -> Vec<ScanSpeed> {
    let mut speeds: Vec<ScanSpeed> = parse_map(text)
        .into_iter()
        .filter_map(|(k, v)| {
            let index = k
                .strip_prefix("speed.")?
                .strip_suffix(".dwell")?
                .parse()
                .ok()?;
            let dwell_us = super::body::parse_float(&v).ok()?;
            Some(ScanSpeed { index, dwell_us })
        })
        .collect();
    speeds.sort_by_key(|s| s.index);
    speeds.dedup_by_key(|s| s.index);
    speeds
}

/// `det.K.name=…` and `det.K.detector=<id>` pairs, in `K` order; a detector
/// without both keys is left out.
fn parse_detectors(text: &str) -> Vec<Detector> {
    let mut names = std::collections::BTreeMap::new();
    let mut ids = std::collections::BTreeMap::new();
    for (k, v) in parse_map(text) {
        let Some(rest) = k.strip_prefix("det.") else {
            continue;
        };
        let Some((index, field)) = rest.split_once('.') else {
            continue;
        };
        let Ok(index) = index.parse::<u32>() else {
            continue;
        };
        match field {
            "name" => {
                names.entry(index).or_insert(v);
            }
            "detector" => {
                if let Ok(id) = v.parse::<i32>() {
                    ids.entry(index).or_insert(id);
                }
            }
            _ => {}
        }
    }
    names
        .into_iter()
        .filter_map(|(index, name)| ids.get(&index).map(|&id| Detector { index, name, id }))
        .collect()
}

impl Response {
    /// Server side: the body of this response.
    #[must_use]
    pub fn body(&self) -> Vec<u8> {
        let mut w = BodyWriter::new();
        match self {
            Self::Void => {}
            Self::Text(s) => {
                w.string(s);
            }
            Self::Int(v) => {
                w.int(*v);
            }
            Self::Position(p) => {
                for v in p.values() {
                    w.float(v);
                }
            }
            Self::Limits(l) => {
                for (lo, hi) in l.pairs() {
                    w.float(lo).float(hi);
                }
            }
            Self::ViewField(mm) => {
                w.float(*mm);
            }
            Self::Speeds(speeds) => {
                let entries: Vec<(String, String)> = speeds
                    .iter()
                    .map(|s| (format!("speed.{}.dwell", s.index), format_float(s.dwell_us)))
                    .collect();
                w.string(&format_map(&entries));
            }
            Self::Detectors(dets) => {
                let mut entries = Vec::new();
                for d in dets {
                    entries.push((format!("det.{}.name", d.index), d.name.clone()));
                    entries.push((format!("det.{}.detector", d.index), d.id.to_string()));
                }
                w.string(&format_map(&entries));
            }
            Self::Enabled { enable, bpp } => {
                w.int(*enable).int(*bpp);
            }
            Self::Params(entries) => {
                w.string(&format_map(entries));
            }
        }
        w.finish()
    }

    /// Server side: the whole response message to a request named `name`: the
    /// same name, its id and queue echoed, flags 0.
    #[must_use]
    pub fn encode(&self, name: &FnName, id: u32, queue: u16) -> Vec<u8> {
        let body = self.body();
        let header = Header {
            name: name.clone(),
            body_size: u32::try_from(body.len()).unwrap_or(u32::MAX),
            id,
            flags: Flags::NONE,
            queue,
        };
        let mut out = Vec::with_capacity(HEADER_LEN + body.len());
        out.extend_from_slice(&header.encode());
        out.extend_from_slice(&body);
        out
    }
}

impl fmt::Display for Response {
    /// The value in text, as `/stage/io` records it.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Void => f.write_str("done"),
            Self::Text(s) => write!(f, "{s:?}"),
            Self::Int(v) => write!(f, "{v}"),
            Self::Position(p) => {
                write!(
                    f,
                    "x={} y={} z={} rotation={} tilt={}",
                    format_float(p.x_mm),
                    format_float(p.y_mm),
                    format_float(p.z_mm),
                    format_float(p.rotation_deg),
                    format_float(p.tilt_deg)
                )?;
                if let Some(t) = p.tilt_y_deg {
                    write!(f, " tilt_y={}", format_float(t))?;
                }
                Ok(())
            }
            Self::Limits(l) => {
                let names = ["x", "y", "z", "rotation", "tilt"];
                let parts: Vec<String> = names
                    .iter()
                    .zip(l.pairs())
                    .map(|(n, (lo, hi))| {
                        format!("{n}=[{}, {}]", format_float(lo), format_float(hi))
                    })
                    .collect();
                f.write_str(&parts.join(" "))
            }
            Self::ViewField(mm) => write!(f, "{} mm", format_float(*mm)),
            Self::Speeds(s) => {
                let parts: Vec<String> = s
                    .iter()
                    .map(|s| format!("{}: {} µs", s.index, format_float(s.dwell_us)))
                    .collect();
                write!(f, "[{}]", parts.join(", "))
            }
            Self::Detectors(d) => {
                let parts: Vec<String> = d
                    .iter()
                    .map(|d| format!("{}: {:?} id {}", d.index, d.name, d.id))
                    .collect();
                write!(f, "[{}]", parts.join(", "))
            }
            Self::Enabled { enable, bpp } => write!(f, "enable={enable} bpp={bpp}"),
            Self::Params(p) => write!(f, "{} entries", p.len()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round_trip(req: &Request, resp: &Response) -> Response {
        req.decode_response(&resp.body()).unwrap()
    }

    #[test]
    fn responses_round_trip_for_their_requests() {
        let cases = [
            (Request::TcpGetVersion, Response::Text("2.0.22".into())),
            (Request::TcpRegDataPort { port: 4 }, Response::Int(0)),
            (
                Request::ScScanXY(crate::sharksem::ScanXY::full_frame(1, 2, 2, 3)),
                Response::Int(-1),
            ),
            (
                Request::StgGetPosition,
                Response::Position(StagePosition {
                    x_mm: 1.25,
                    y_mm: -0.5,
                    z_mm: 10.0,
                    rotation_deg: 90.0,
                    tilt_deg: 7.0,
                    tilt_y_deg: None,
                }),
            ),
            (
                Request::StgGetPosition,
                Response::Position(StagePosition {
                    tilt_y_deg: Some(-1.0),
                    ..StagePosition::default()
                }),
            ),
            (
                Request::StgGetLimits { kind: 0 },
                Response::Limits(StageLimits {
                    x_mm: (-40.0, 40.0),
                    y_mm: (-30.0, 30.0),
                    z_mm: (0.0, 50.0),
                    rotation_deg: (-360.0, 360.0),
                    tilt_deg: (-30.0, 90.0),
                }),
            ),
            (Request::GetViewField, Response::ViewField(0.128)),
            (
                Request::ScEnumSpeeds,
                Response::Speeds(vec![
                    ScanSpeed {
                        index: 1,
                        dwell_us: 0.1,
                    },
                    ScanSpeed {
                        index: 2,
                        dwell_us: 0.32,
                    },
                ]),
            ),
            (
                Request::DtEnumDetectors,
                Response::Detectors(vec![
                    Detector {
                        index: 0,
                        name: "SE".into(),
                        id: 0,
                    },
                    Detector {
                        index: 1,
                        name: "BSE".into(),
                        id: 4,
                    },
                ]),
            ),
            (
                Request::DtGetEnabled { channel: 0 },
                Response::Enabled { enable: 1, bpp: 16 },
            ),
            (
                Request::GetDeviceParams { set: 0 },
                Response::Params(vec![("Device".into(), "VEGA".into())]),
            ),
            (Request::ScStopScan, Response::Void),
        ];
        for (req, resp) in cases {
            assert_eq!(round_trip(&req, &resp), resp, "{req}");
        }
    }

    #[test]
    fn a_short_position_or_limits_names_the_count() {
        let body = BodyWriter::new().float(1.0).float(2.0).finish();
        let e = Request::StgGetPosition.decode_response(&body).unwrap_err();
        assert_eq!(
            e.to_string(),
            "StgGetPosition: expected 5 or 6 values, got 2"
        );
        let e = Request::StgGetLimits { kind: 1 }
            .decode_response(&body)
            .unwrap_err();
        assert!(e.to_string().contains("expected 10 values, got 2"), "{e}");
    }

    #[test]
    fn detector_and_speed_maps_tolerate_unknown_keys() {
        let text = "det.0.name=SE\ndet.0.detector=0\ndet.0.color=red\ndet.2.name=LVSTD\n\
                    det.1.detector=7\ndet.1.name=BSE\nversion=3\n";
        let body = BodyWriter::new().string(text).finish();
        let Response::Detectors(d) = Request::DtEnumDetectors.decode_response(&body).unwrap()
        else {
            panic!()
        };
        assert_eq!(
            d,
            vec![
                Detector {
                    index: 0,
                    name: "SE".into(),
                    id: 0
                },
                Detector {
                    index: 1,
                    name: "BSE".into(),
                    id: 7
                },
            ],
            "det.2 has no id: left out"
        );
        let body = BodyWriter::new()
            .string("speed.2.dwell=0.32\nspeed.1.dwell=0.1\nspeed.x.dwell=3\n")
            .finish();
        let Response::Speeds(s) = Request::ScEnumSpeeds.decode_response(&body).unwrap() else {
            panic!()
        };
        assert_eq!(s.iter().map(|s| s.index).collect::<Vec<_>>(), [1, 2]);
    }

    #[test]
    fn responses_echo_name_id_and_queue_with_zero_flags() {
        let name = FnName::new("StgIsBusy").unwrap();
        let bytes = Response::Int(1).encode(&name, 77, 3);
        let mut head = [0u8; HEADER_LEN];
        head.copy_from_slice(&bytes[..HEADER_LEN]);
        let h = Header::decode(&head).unwrap();
        assert_eq!(
            (h.name, h.id, h.queue, h.flags, h.body_size),
            (name, 77, 3, Flags::NONE, 4)
        );
    }

    #[test]
    fn records_read_like_the_manual() {
        let p = Response::Position(StagePosition {
            x_mm: 1.0,
            tilt_deg: 5.0,
            ..StagePosition::default()
        });
        assert_eq!(p.to_string(), "x=1 y=0 z=0 rotation=0 tilt=5");
        assert_eq!(Response::ViewField(0.128).to_string(), "0.128 mm");
    }
}
