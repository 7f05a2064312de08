//! The geometry of a stereo pair (DESIGN §3) and where each of its figures comes from: one
//! precedence for every command — what the user gives for this run (the command line), then
//! the micrographs' metadata (or, in an acquisition, what the instruments reported with them),
//! then the configuration.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// How the pair was taken.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PairGeometry {
    /// θ = tilt(right) − tilt(left), degrees, in (0, 60].
    pub tilt_deg: f64,
    /// Pixel size of both micrographs, µm.
    pub pixel_size_um: f64,
    /// φ: direction of the tilt axis in the image, degrees from +x towards +y.
    pub tilt_axis_deg: f64,
}

/// Largest tilt difference accepted: beyond it the pair hardly overlaps and
/// the small-angle matching of the method breaks down.
pub const MAX_TILT_DEG: f64 = 60.0;

/// Largest relative difference of the two micrographs' pixel sizes taken for the same size.
const PIXEL_SIZE_TOLERANCE: f64 = 0.01;

/// What one source says about a pair; `None` where it says nothing.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Figures {
    /// Given for the pair: θ; in a micrograph's metadata: the stage tilt it was taken at.
    pub tilt_deg: Option<f64>,
    pub pixel_size_um: Option<f64>,
    pub tilt_axis_deg: Option<f64>,
}

/// Every source of a pair's geometry.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct GeometrySources {
    /// What the user gave for this run (`--tilt`, `--pixel-size`, `--tilt-axis`).
    pub given: Figures,
    /// The left and right micrographs' metadata.
    pub left: Figures,
    pub right: Figures,
    /// `reconstruction.tilt_axis_deg`.
    pub configured_tilt_axis_deg: Option<f64>,
    /// How errors and the provenance name the two micrographs (their files, or "left"/"right").
    pub names: [String; 2],
}

/// Where each figure came from (`tilt`, `pixel_size`, `tilt_axis`), for report.json.
pub type Provenance = BTreeMap<String, String>;

/// Why a pair's geometry cannot be settled.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    #[error(
        "LEFT must be the micrograph at the lower tilt: {left} is at {left_deg}°, {right} at {right_deg}° (swap them, or give --tilt)"
    )]
    NotLowerTilt {
        left: String,
        right: String,
        left_deg: f64,
        right_deg: f64,
    },
    #[error(
        "no tilt difference: the micrographs carry no stage tilt in their metadata; give --tilt DEG"
    )]
    NoTilt,
    #[error(
        "the micrographs have different pixel sizes ({left_um} µm in {left}, {right_um} µm in {right}): they must be taken at the same magnification"
    )]
    PixelSizesDiffer {
        left: String,
        right: String,
        left_um: f64,
        right_um: f64,
    },
    #[error("no pixel size: the files carry no SEM metadata with one; give --pixel-size UM")]
    NoPixelSize,
    #[error(
        "no tilt axis: neither given nor in the micrographs' metadata; give --tilt-axis DEG or set reconstruction.tilt_axis_deg (the direction of the stage tilt axis in the image, from +x towards +y; it decides the sign of the relief)"
    )]
    NoTiltAxis,
}

impl GeometrySources {
    /// φ and where it came from: given, then the left's metadata, the right's, then the
    /// configuration; `None` when no source has it.
    #[must_use]
    pub fn tilt_axis(&self) -> Option<(f64, String)> {
        let [left, right] = &self.names;
        [
            (self.given.tilt_axis_deg, "--tilt-axis".to_owned()),
            (self.left.tilt_axis_deg, format!("metadata of {left}")),
            (self.right.tilt_axis_deg, format!("metadata of {right}")),
            (
                self.configured_tilt_axis_deg,
                "reconstruction.tilt_axis_deg".to_owned(),
            ),
        ]
        .into_iter()
        .find_map(|(value, source)| value.map(|v| (v, source)))
    }

    /// θ, the pixel size and φ, each from the first source that has it: given, then the
    /// micrographs' metadata (left's, then right's), then the configuration (φ only).
    ///
    /// # Errors
    /// [`GeometryError`] for a figure no source has, or metadata that contradict themselves.
    pub fn resolve(&self) -> Result<(PairGeometry, Provenance), GeometryError> {
        let [left, right] = &self.names;
        let mut provenance = Provenance::new();
        let mut note = |key: &str, source: String| {
            provenance.insert(key.to_owned(), source);
        };
        let tilt_deg = match (self.given.tilt_deg, self.left.tilt_deg, self.right.tilt_deg) {
            (Some(t), _, _) => {
                note("tilt", "--tilt".to_owned());
                t
            }
            (None, Some(tl), Some(tr)) => {
                if tr <= tl {
                    return Err(GeometryError::NotLowerTilt {
                        left: left.clone(),
                        right: right.clone(),
                        left_deg: tl,
                        right_deg: tr,
                    });
                }
                note("tilt", format!("metadata: {tl}° (left) → {tr}° (right)"));
                tr - tl
            }
            _ => return Err(GeometryError::NoTilt),
        };
        let pixel_size_um = match (
            self.given.pixel_size_um,
            self.left.pixel_size_um,
            self.right.pixel_size_um,
        ) {
            (Some(p), _, _) => {
                note("pixel_size", "--pixel-size".to_owned());
                p
            }
            (None, Some(pl), pr) => {
                if let Some(pr) = pr
                    && (pr - pl).abs() > PIXEL_SIZE_TOLERANCE * pl.abs()
                {
                    return Err(GeometryError::PixelSizesDiffer {
                        left: left.clone(),
                        right: right.clone(),
                        left_um: pl,
                        right_um: pr,
                    });
                }
                note("pixel_size", format!("metadata of {left}"));
                pl
            }
            (None, None, Some(pr)) => {
                note("pixel_size", format!("metadata of {right}"));
                pr
            }
            (None, None, None) => return Err(GeometryError::NoPixelSize),
        };
        let (tilt_axis_deg, source) = self.tilt_axis().ok_or(GeometryError::NoTiltAxis)?;
        note("tilt_axis", source);
        Ok((
            PairGeometry {
                tilt_deg,
                pixel_size_um,
                tilt_axis_deg,
            },
            provenance,
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sources() -> GeometrySources {
        GeometrySources {
            given: Figures::default(),
            left: Figures {
                tilt_deg: Some(1.0),
                pixel_size_um: Some(0.1),
                tilt_axis_deg: Some(-60.0),
            },
            right: Figures {
                tilt_deg: Some(6.0),
                pixel_size_um: Some(0.1),
                tilt_axis_deg: Some(-60.0),
            },
            configured_tilt_axis_deg: Some(30.0),
            names: ["l.tif".to_owned(), "r.tif".to_owned()],
        }
    }

    /// Command line → metadata → configuration, figure by figure.
    #[test]
    fn each_figure_comes_from_the_first_source_that_has_it() {
        let (g, p) = sources().resolve().unwrap();
        assert_eq!(
            (g.tilt_deg, g.pixel_size_um, g.tilt_axis_deg),
            (5.0, 0.1, -60.0)
        );
        assert_eq!(p["tilt_axis"], "metadata of l.tif");
        let mut s = sources();
        s.given = Figures {
            tilt_deg: Some(4.0),
            pixel_size_um: Some(0.2),
            tilt_axis_deg: Some(90.0),
        };
        let (g, p) = s.resolve().unwrap();
        assert_eq!(
            (g.tilt_deg, g.pixel_size_um, g.tilt_axis_deg),
            (4.0, 0.2, 90.0)
        );
        assert_eq!(p["tilt_axis"], "--tilt-axis");
        let mut s = sources();
        s.left.tilt_axis_deg = None;
        assert_eq!(
            s.resolve().unwrap().0.tilt_axis_deg,
            -60.0,
            "the right's metadata"
        );
        s.right.tilt_axis_deg = None;
        let (g, p) = s.resolve().unwrap();
        assert_eq!(g.tilt_axis_deg, 30.0);
        assert_eq!(p["tilt_axis"], "reconstruction.tilt_axis_deg");
        s.configured_tilt_axis_deg = None;
        assert_eq!(s.resolve().unwrap_err(), GeometryError::NoTiltAxis);
    }

    #[test]
    fn contradicting_or_missing_metadata_are_named() {
        let mut s = sources();
        s.right.tilt_deg = Some(0.0);
        let e = s.resolve().unwrap_err().to_string();
        assert!(e.contains("l.tif is at 1°") && e.contains("swap"), "{e}");
        let mut s = sources();
        s.right.pixel_size_um = Some(0.2);
        let e = s.resolve().unwrap_err().to_string();
        assert!(e.contains("0.2 µm in r.tif"), "{e}");
        s.right.pixel_size_um = Some(0.1005);
        assert!(s.resolve().is_ok(), "within 1 %");
        let mut s = sources();
        s.left.tilt_deg = None;
        assert_eq!(s.resolve().unwrap_err(), GeometryError::NoTilt);
        let mut s = sources();
        s.left.pixel_size_um = None;
        assert_eq!(s.resolve().unwrap().0.pixel_size_um, 0.1);
        s.right.pixel_size_um = None;
        assert_eq!(s.resolve().unwrap_err(), GeometryError::NoPixelSize);
    }
}
