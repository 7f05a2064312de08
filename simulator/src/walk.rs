//! Eucentric walk: the specimen wanders in the image as the stage tilts,
//! because the specimen surface is never exactly at the tilt axis's height and
//! the stage's mechanics are not perfect.
//!
//! The walk is stated as microscopists measure it, in pixels of the
//! full-resolution frame (the acquisition issue's "eucentric walk at 5 px/°
//! plus random walk"): a linear term plus a smooth seeded random walk. The
//! specimen really moves in µm, so [`WalkParams::offset_um`] multiplies by the
//! full-resolution pixel size (`optics.pixel_size_um`): 5 px/° at 0.1 µm pixels
//! is 0.5 µm/°, which a 320-pixel tracking frame of the same field (0.4 µm
//! pixels) sees as 1.25 px/°. It is a pure function of the tilt, so revisiting
//! a tilt gives the same offset, and it is zero at tilt 0.

use serde::{Deserialize, Serialize};

use crate::scene::noise::{gaussian, hash2, substream};

/// Eucentric walk parameters.
///
/// | field | default | effect |
/// | --- | --- | --- |
/// Pixels (px) are those of the full-resolution frame (`optics.pixel_size_um`).
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `px_per_deg` | 5 | steady walk of the specimen in the image per degree of tilt, full-resolution px (0.5 µm/° at 0.1 µm pixels); a well-aligned eucentric stage walks a few px/° at high magnification |
/// | `direction_deg` | 60 | its direction in the image, degrees from +x towards +y (before scan rotation) |
/// | `random_px` | 3 | random part: standard deviation of the change between two knots, full-resolution px per image axis |
/// | `knot_deg` | 2 | tilt between knots of the random part (smooth Catmull–Rom in between) |
/// | `seed` | derived | seed of the random part; unset: derived from the SEM's seed (`sem.seed`, itself from `simulator.seed`); used alone, unset is 0 |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WalkParams {
    pub px_per_deg: f64,
    pub direction_deg: f64,
    pub random_px: f64,
    pub knot_deg: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

impl Default for WalkParams {
    fn default() -> Self {
        Self {
            px_per_deg: 5.0,
            direction_deg: 60.0,
            random_px: 3.0,
            knot_deg: 2.0,
            seed: None,
        }
    }
}

impl WalkParams {
    /// No walk at all.
    #[must_use]
    pub fn none() -> Self {
        Self {
            px_per_deg: 0.0,
            random_px: 0.0,
            ..Self::default()
        }
    }

    /// Image-plane displacement of the specimen (µm, x then y, before scan
    /// rotation) at stage tilt `tilt_deg`, relative to tilt 0, for a
    /// full-resolution pixel size of `pixel_size_um`.
    #[must_use]
    pub fn offset_um(&self, tilt_deg: f64, pixel_size_um: f64) -> [f64; 2] {
        let [x, y] = self.offset_px(tilt_deg);
        [x * pixel_size_um, y * pixel_size_um]
    }

    /// The same displacement in full-resolution pixels.
    #[must_use]
    pub fn offset_px(&self, tilt_deg: f64) -> [f64; 2] {
        let (sd, cd) = self.direction_deg.to_radians().sin_cos();
        let linear = self.px_per_deg * tilt_deg;
        let mut out = [linear * cd, linear * sd];
        if self.random_px > 0.0 && self.knot_deg > 0.0 && tilt_deg.is_finite() {
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
        let stream = substream(self.seed.unwrap_or(0), 100 + axis);
        let step = |m: i64| self.random_px * gaussian(hash2(stream, m, 0));
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

    fn seeded(seed: u64) -> WalkParams {
        WalkParams {
            seed: Some(seed),
            ..WalkParams::default()
        }
    }

    #[test]
    fn zero_at_zero_tilt_and_deterministic() {
        let w = seeded(11);
        let o = w.offset_px(0.0);
        assert!(o[0].abs() < 1e-12 && o[1].abs() < 1e-12);
        assert_eq!(w.offset_px(7.3), w.offset_px(7.3));
        assert_ne!(w.offset_px(7.3), seeded(12).offset_px(7.3));
    }

    #[test]
    fn linear_term_goes_the_configured_way_in_full_resolution_pixels() {
        let w = WalkParams {
            px_per_deg: 5.0,
            direction_deg: 90.0,
            random_px: 0.0,
            ..WalkParams::default()
        };
        let o = w.offset_px(10.0);
        assert!(o[0].abs() < 1e-9);
        assert!((o[1] - 50.0).abs() < 1e-9, "{o:?}");
        // 5 px/° of 0.1 µm pixels: the specimen moves 0.5 µm/°.
        let um = w.offset_um(10.0, 0.1);
        assert!((um[1] - 5.0).abs() < 1e-9, "{um:?}");
        let back = w.offset_um(-10.0, 0.1);
        assert!((back[1] + 5.0).abs() < 1e-9);
    }

    #[test]
    fn default_is_a_few_pixels_per_degree() {
        let w = WalkParams {
            random_px: 0.0,
            ..WalkParams::default()
        };
        let [x, y] = w.offset_px(1.0);
        let per_deg = x.hypot(y);
        assert!((2.0..=10.0).contains(&per_deg), "{per_deg} px/°");
    }

    #[test]
    fn random_part_is_smooth_and_wanders() {
        let w = WalkParams {
            px_per_deg: 0.0,
            ..seeded(11)
        };
        // Smooth: one tenth of a degree moves it far less than the knot step.
        let mut max_jump: f64 = 0.0;
        let mut max_abs: f64 = 0.0;
        for k in -300..300 {
            let t = f64::from(k) * 0.1;
            let a = w.offset_px(t);
            let b = w.offset_px(t + 0.1);
            max_jump = max_jump.max((a[0] - b[0]).abs().max((a[1] - b[1]).abs()));
            max_abs = max_abs.max(a[0].abs().max(a[1].abs()));
        }
        assert!(max_jump < 1.0, "jump {max_jump} px");
        assert!(max_abs > 3.0, "the random walk barely moves: {max_abs} px");
        // Continuous across knots.
        let a = w.offset_px(4.0 - 1e-9);
        let b = w.offset_px(4.0 + 1e-9);
        assert!((a[0] - b[0]).abs() < 1e-6);
    }
}
