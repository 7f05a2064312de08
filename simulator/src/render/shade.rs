//! Secondary-electron contrast of a visible surface point.
//!
//! The SE signal grows with the angle α between beam and surface normal,
//! roughly as 1/cos α (the secant law of the SE yield); more electrons escape
//! near convex edges (edge effect) and fewer from pits; the detector on one side
//! sees faces turned towards it a little brighter; the material sets the yield.

use serde::{Deserialize, Serialize};

use super::trace::{Facet, SurfacePoint, Tilt};
use crate::scene::Scene;

/// Parameters of the SE contrast model.
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `secant_gain` | 0.35 | brightening per unit of (1/cos α − 1): steep faces glow |
/// | `secant_cap` | 6 | 1/cos α is capped here (grazing faces do not explode) |
/// | `edge_gain` | 0.45 | brightening of convex features (edge effect), darkening of concave |
/// | `edge_scale_um` | 0.4 | height above the local (~0.6 µm) mean surface at which the edge effect saturates |
/// | `cavity_gain` | 0.5 | darkening of points below the ~4 µm mean surface (SE recaptured in pits) |
/// | `cavity_scale_um` | 4 | depth over which cavity darkening acts |
/// | `detector_gain` | 0.25 | extra signal from faces turned towards the detector |
/// | `detector_azimuth_deg` | −60 | detector direction in the image (from +x towards +y) |
/// | `detector_elevation_deg` | 30 | detector elevation above the stage plane |
/// | `texture` | 1 | scale of the material texture (0 turns it off) |
/// | `gain` | 1.2 | output = 1 − exp(−gain · signal): soft saturation instead of clipping |
/// | `background` | 0.03 | signal where the beam misses the specimen |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ShadingParams {
    pub secant_gain: f64,
    pub secant_cap: f64,
    pub edge_gain: f64,
    pub edge_scale_um: f64,
    pub cavity_gain: f64,
    pub cavity_scale_um: f64,
    pub detector_gain: f64,
    pub detector_azimuth_deg: f64,
    pub detector_elevation_deg: f64,
    pub texture: f64,
    pub gain: f64,
    pub background: f64,
}

impl Default for ShadingParams {
    fn default() -> Self {
        Self {
            secant_gain: 0.35,
            secant_cap: 6.0,
            edge_gain: 0.45,
            edge_scale_um: 0.4,
            cavity_gain: 0.5,
            cavity_scale_um: 4.0,
            detector_gain: 0.25,
            detector_azimuth_deg: -60.0,
            detector_elevation_deg: 30.0,
            texture: 1.0,
            gain: 1.2,
            background: 0.03,
        }
    }
}

/// Shading state for one view: the beam and detector in specimen coordinates.
pub(crate) struct Shader<'a> {
    params: &'a ShadingParams,
    tilt: Tilt,
    /// Unit vector towards the detector, specimen coordinates (s, r, z).
    detector: (f64, f64, f64),
    footprint: f64,
}

impl<'a> Shader<'a> {
    /// `tilt_axis_deg` places the detector (fixed in the chamber, given in
    /// image directions) relative to the specimen axes.
    pub(crate) fn new(
        params: &'a ShadingParams,
        tilt: Tilt,
        tilt_axis_deg: f64,
        footprint: f64,
    ) -> Self {
        // Lab frame: components along a, along n, and up the beam.
        let az = (params.detector_azimuth_deg - tilt_axis_deg).to_radians();
        let el = params.detector_elevation_deg.to_radians();
        let (ca, na, up) = (el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        // Lab (a, n, up) → specimen (s, r, z): rotate back by the stage tilt.
        let detector = (
            ca,
            na * tilt.cos - up * tilt.sin,
            na * tilt.sin + up * tilt.cos,
        );
        Self {
            params,
            tilt,
            detector,
            footprint,
        }
    }

    /// Signal in [0, 1) of a visible point, or the background for a miss.
    pub(crate) fn shade(&self, scene: &Scene, hit: Option<&SurfacePoint>) -> f64 {
        let p = self.params;
        let Some(hit) = hit else {
            return p.background;
        };
        let normal = match hit.facet {
            Facet::Top => {
                let (gs, gr) = scene.gradient(hit.s, hit.r);
                let k = 1.0 / (1.0 + gs * gs + gr * gr).sqrt();
                (-gs * k, -gr * k, k)
            }
            // The side faces at the field's edge face outward, along ∓r.
            Facet::Side => (0.0, -self.tilt.sin.signum(), 0.0),
        };
        // Unit vector towards the beam source: (0, −sin t, cos t).
        let cos_alpha = -normal.1 * self.tilt.sin + normal.2 * self.tilt.cos;
        let secant = (1.0 / cos_alpha.max(1e-6)).min(p.secant_cap);
        let f_secant = 1.0 + p.secant_gain * (secant - 1.0);
        let towards_detector =
            normal.0 * self.detector.0 + normal.1 * self.detector.1 + normal.2 * self.detector.2;
        let f_detector = (1.0 + p.detector_gain * towards_detector).max(0.0);
        let edge =
            p.edge_gain * ((hit.z - scene.edge_mean.at(hit.s, hit.r)) / p.edge_scale_um).tanh();
        let depth = (scene.cavity_mean.at(hit.s, hit.r) - hit.z).max(0.0);
        let f_cavity = (-p.cavity_gain * depth / p.cavity_scale_um).exp();
        let yld = scene.yield_at(hit.s, hit.r);
        let texture = 1.0 + p.texture * (scene.albedo(hit.s, hit.r, self.footprint, yld) - 1.0);
        let signal = yld * texture.max(0.0) * f_secant * f_detector * f_cavity * (1.0 + edge);
        1.0 - (-p.gain * signal.max(0.0)).exp()
    }
}
