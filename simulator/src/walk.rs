//! Eucentric walk: the specimen wanders in the image as the stage tilts,
//! because the specimen surface is never exactly at the tilt axis's height and
//! the stage's mechanics are not perfect.
//!
//! The walk is an image-plane displacement of the specimen in µm (so it scales
//! with the frame's pixel size): a linear term plus a smooth seeded random
//! walk. It is a pure function of the tilt, so revisiting a tilt gives the same
//! offset, and it is zero at tilt 0.

use serde::{Deserialize, Serialize};

use crate::scene::noise::{gaussian, hash2, substream};

/// Eucentric walk parameters.
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `linear_um_per_deg` | 0.4 | steady drift of the specimen in the image per degree of tilt (µm; 4 px/° at 0.1 µm pixels) |
/// | `direction_deg` | 60 | its direction in the image, degrees from +x towards +y |
/// | `random_um` | 0.3 | random part: standard deviation of the change between two knots, µm per axis |
/// | `knot_deg` | 2 | tilt between knots of the random part (smooth Catmull–Rom in between) |
/// | `seed` | 11 | seed of the random part |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WalkParams {
    pub linear_um_per_deg: f64,
    pub direction_deg: f64,
    pub random_um: f64,
    pub knot_deg: f64,
    pub seed: u64,
}

impl Default for WalkParams {
    fn default() -> Self {
        Self {
            linear_um_per_deg: 0.4,
            direction_deg: 60.0,
            random_um: 0.3,
            knot_deg: 2.0,
            seed: 11,
        }
    }
}

impl WalkParams {
    /// No walk at all.
    #[must_use]
    pub fn none() -> Self {
        Self {
            linear_um_per_deg: 0.0,
            random_um: 0.0,
            ..Self::default()
        }
    }

    /// Image-plane displacement of the specimen (µm, x then y, before scan
    /// rotation) at stage tilt `tilt_deg`, relative to tilt 0.
    #[must_use]
    pub fn offset_um(&self, tilt_deg: f64) -> [f64; 2] {
        let (sd, cd) = self.direction_deg.to_radians().sin_cos();
        let linear = self.linear_um_per_deg * tilt_deg;
        let mut out = [linear * cd, linear * sd];
        if self.random_um > 0.0 && self.knot_deg > 0.0 && tilt_deg.is_finite() {
            let u = tilt_deg / self.knot_deg;
            let k0 = u.floor();
            let f = u - k0;
            // Tilts are at most a few hundred knots from 0.
            #[allow(clippy::cast_possible_truncation)]
            let k0 = k0 as i64;
            for (axis, o) in out.iter_mut().enumerate() {
                let knot = |k: i64| self.knot(axis as u64, k);
                *o += catmull_rom(knot(k0 - 1), knot(k0), knot(k0 + 1), knot(k0 + 2), f);
            }
        }
        out
    }

    /// The random walk at knot `k` of one axis: the sum of the seeded steps
    /// between knot 0 (where it is 0) and knot `k`.
    fn knot(&self, axis: u64, k: i64) -> f64 {
        let stream = substream(self.seed, 100 + axis);
        let step = |m: i64| self.random_um * gaussian(hash2(stream, m, 0));
        if k >= 0 {
            (1..=k).map(step).sum()
        } else {
            -(k + 1..=0).map(step).sum::<f64>()
        }
    }
}

/// Catmull–Rom interpolation between `p1` (f = 0) and `p2` (f = 1).
fn catmull_rom(p0: f64, p1: f64, p2: f64, p3: f64, f: f64) -> f64 {
    let f2 = f * f;
    let f3 = f2 * f;
    0.5 * (2.0 * p1
        + (p2 - p0) * f
        + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * f2
        + (3.0 * p1 - p0 - 3.0 * p2 + p3) * f3)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zero_at_zero_tilt_and_deterministic() {
        let w = WalkParams::default();
        let o = w.offset_um(0.0);
        assert!(o[0].abs() < 1e-12 && o[1].abs() < 1e-12);
        assert_eq!(w.offset_um(7.3), w.offset_um(7.3));
        let other = WalkParams {
            seed: 12,
            ..w.clone()
        };
        assert_ne!(w.offset_um(7.3), other.offset_um(7.3));
    }

    #[test]
    fn linear_term_goes_the_configured_way() {
        let w = WalkParams {
            linear_um_per_deg: 0.5,
            direction_deg: 90.0,
            random_um: 0.0,
            ..WalkParams::default()
        };
        let o = w.offset_um(10.0);
        assert!(o[0].abs() < 1e-9);
        assert!((o[1] - 5.0).abs() < 1e-9, "{o:?}");
        let back = w.offset_um(-10.0);
        assert!((back[1] + 5.0).abs() < 1e-9);
    }

    #[test]
    fn random_part_is_smooth_and_wanders() {
        let w = WalkParams {
            linear_um_per_deg: 0.0,
            ..WalkParams::default()
        };
        // Smooth: one tenth of a degree moves it far less than the knot step.
        let mut max_jump: f64 = 0.0;
        let mut max_abs: f64 = 0.0;
        for k in -300..300 {
            let t = f64::from(k) * 0.1;
            let a = w.offset_um(t);
            let b = w.offset_um(t + 0.1);
            max_jump = max_jump.max((a[0] - b[0]).abs().max((a[1] - b[1]).abs()));
            max_abs = max_abs.max(a[0].abs().max(a[1].abs()));
        }
        assert!(max_jump < 0.1, "jump {max_jump}");
        assert!(max_abs > 0.3, "the random walk barely moves: {max_abs}");
        // Continuous across knots.
        let a = w.offset_um(4.0 - 1e-9);
        let b = w.offset_um(4.0 + 1e-9);
        assert!((a[0] - b[0]).abs() < 1e-6);
    }
}
