//! Ground truth of rendered frames: what each pixel sees, its height, and where
//! a specimen point appears in another view. Computed by the very ray cast the
//! renderer uses, at exact (sub-pixel) positions: nothing is resampled.

use rayon::prelude::*;

use super::trace::{self, SurfacePoint};
use super::view::{Geometry, View};
use crate::scene::Scene;

/// Two depths along a ray closer than this (µm) are the same surface point.
const SAME_POINT_UM: f64 = 1e-6;

/// The specimen point seen at image position `(x, y)` (pixels, may be
/// fractional) of `view`; `None` where the beam misses the specimen.
#[must_use]
pub fn trace_pixel(scene: &Scene, view: &View, x: f64, y: f64) -> Option<SurfacePoint> {
    let geo = Geometry::new(view);
    let (s, v) = geo.ray(x, y);
    trace::trace(scene, s, v, geo.tilt)
}

/// The visible specimen point of every pixel centre, row-major.
#[must_use]
pub fn visible_points(scene: &Scene, view: &View) -> Vec<Option<SurfacePoint>> {
    let geo = Geometry::new(view);
    let w = view.width.max(1);
    (0..view.width * view.height)
        .into_par_iter()
        .map(|k| {
            #[allow(clippy::cast_precision_loss)]
            let (s, v) = geo.ray((k % w) as f64, (k / w) as f64);
            trace::trace(scene, s, v, geo.tilt)
        })
        .collect()
}

/// Height (µm, specimen z) of the visible point at every pixel centre,
/// row-major; `NaN` where the beam misses the specimen. This is the map a
/// reconstruction on this frame's grid is scored against (up to a plane:
/// DESIGN §3 reconstructs relative to the mid-tilt plane).
#[must_use]
pub fn height_map(scene: &Scene, view: &View) -> Vec<f32> {
    visible_points(scene, view)
        .into_iter()
        .map(|p| {
            #[allow(clippy::cast_possible_truncation)]
            p.map_or(f32::NAN, |p| p.z as f32)
        })
        .collect()
}

/// Where a point of one view appears in another.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Correspondence {
    /// Position in the other view, pixels (sub-pixel, exact).
    pub x: f64,
    pub y: f64,
    /// The position lies on the other frame.
    pub in_frame: bool,
    /// Something nearer the beam hides the point in the other view.
    pub occluded: bool,
}

impl Correspondence {
    /// Seen in the other frame: on it and not hidden.
    #[must_use]
    pub fn is_visible(&self) -> bool {
        self.in_frame && !self.occluded
    }
}

/// The true correspondence of image position `(x, y)` of `from` in `to`:
/// the specimen point it sees, projected into `to`, with its visibility there.
/// `None` where `from` sees no specimen.
#[must_use]
pub fn correspondence(
    scene: &Scene,
    from: &View,
    to: &View,
    x: f64,
    y: f64,
) -> Option<Correspondence> {
    let p = trace_pixel(scene, from, x, y)?;
    Some(locate(scene, &Geometry::new(to), to, &p))
}

/// [`correspondence`] of every pixel centre of `from`, row-major.
#[must_use]
pub fn correspondences(scene: &Scene, from: &View, to: &View) -> Vec<Option<Correspondence>> {
    let geo_to = Geometry::new(to);
    visible_points(scene, from)
        .into_par_iter()
        .map(|p| p.map(|p| locate(scene, &geo_to, to, &p)))
        .collect()
}

fn locate(scene: &Scene, geo: &Geometry, view: &View, p: &SurfacePoint) -> Correspondence {
    let (x, y) = geo.project(p.s, p.r, p.z);
    let (s, v) = geo.ray(x, y);
    // The ray through the projection passes through `p`; the point is hidden
    // when that ray meets the surface nearer the beam first.
    let occluded = trace::trace(scene, s, v, geo.tilt).is_none_or(|q| {
        geo.tilt.depth(q.r, q.z) > geo.tilt.depth(p.r, p.z) + SAME_POINT_UM * (1.0 + p.z.abs())
    });
    Correspondence {
        x,
        y,
        in_frame: view.contains(x, y),
        occluded,
    }
}
