//! One frame's imaging geometry: the parallel projection of DESIGN §3 followed
//! by pixel size, specimen offset (stage pan, eucentric walk, drift), scan
//! rotation and image centre.

use serde::{Deserialize, Serialize};

use super::trace::{SurfacePoint, Tilt};
use crate::pose::StagePose;

/// Everything that fixes where a specimen point lands in one frame.
///
/// A specimen point `(s, r, z)` maps to the pixel
/// ```text
///   q = s·a + (r·cos t + z·sin t)·n + offset_um       (µm, image plane)
///   pixel = centre + R(scan_rotation) · q / pixel_size_um
/// ```
/// with a = (cos φ, sin φ), n = (−sin φ, cos φ), φ = `tilt_axis_deg`, t =
/// `tilt_deg`, centre = ((width − 1)/2, (height − 1)/2) and R rotating from +x
/// towards +y. With a scan rotation ψ the tilt axis appears at φ + ψ.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct View {
    pub width: usize,
    pub height: usize,
    /// Pixel size, µm (default 0.1).
    pub pixel_size_um: f64,
    /// Stage tilt, degrees (default 0).
    pub tilt_deg: f64,
    /// φ: direction of the tilt axis in the image, degrees from +x towards +y (default 0).
    pub tilt_axis_deg: f64,
    /// In-plane rotation of the scan, degrees (default 0).
    pub scan_rotation_deg: f64,
    /// Where the specimen origin lands in the image plane, µm, before scan
    /// rotation: stage pan + eucentric walk + drift (default 0, 0).
    pub offset_um: [f64; 2],
}

impl Default for View {
    fn default() -> Self {
        Self {
            width: 1280,
            height: 960,
            pixel_size_um: 0.1,
            tilt_deg: 0.0,
            tilt_axis_deg: 0.0,
            scan_rotation_deg: 0.0,
            offset_um: [0.0, 0.0],
        }
    }
}

/// Precomputed trigonometry of a [`View`].
#[derive(Clone, Copy, Debug)]
pub(crate) struct Geometry {
    centre: (f64, f64),
    pixel: f64,
    rot: (f64, f64),
    a: (f64, f64),
    n: (f64, f64),
    offset: (f64, f64),
    pub tilt: Tilt,
}

impl Geometry {
    pub(crate) fn new(view: &View) -> Self {
        let (sa, ca) = view.tilt_axis_deg.to_radians().sin_cos();
        let (sr, cr) = view.scan_rotation_deg.to_radians().sin_cos();
        #[allow(clippy::cast_precision_loss)]
        let centre = (
            (view.width as f64 - 1.0) / 2.0,
            (view.height as f64 - 1.0) / 2.0,
        );
        Self {
            centre,
            pixel: view.pixel_size_um,
            rot: (cr, sr),
            a: (ca, sa),
            n: (-sa, ca),
            offset: (view.offset_um[0], view.offset_um[1]),
            tilt: Tilt::from_deg(view.tilt_deg),
        }
    }

    /// The ray of image position `(x, y)` (pixels): `(s, v)` — its position
    /// along the tilt axis and its image coordinate along n, µm.
    #[inline]
    pub(crate) fn ray(&self, x: f64, y: f64) -> (f64, f64) {
        let dx = (x - self.centre.0) * self.pixel;
        let dy = (y - self.centre.1) * self.pixel;
        let (c, s) = self.rot;
        let ux = c * dx + s * dy - self.offset.0;
        let uy = -s * dx + c * dy - self.offset.1;
        (ux * self.a.0 + uy * self.a.1, ux * self.n.0 + uy * self.n.1)
    }

    /// Image position (pixels) of specimen point `(s, r, z)`.
    #[inline]
    pub(crate) fn project(&self, s: f64, r: f64, z: f64) -> (f64, f64) {
        let v = self.tilt.v(r, z);
        let ux = s * self.a.0 + v * self.n.0 + self.offset.0;
        let uy = s * self.a.1 + v * self.n.1 + self.offset.1;
        let (c, sn) = self.rot;
        (
            self.centre.0 + (c * ux - sn * uy) / self.pixel,
            self.centre.1 + (sn * ux + c * uy) / self.pixel,
        )
    }
}

impl View {
    /// Image position (pixels, x right, y down) of a specimen point, wherever
    /// it lies (inside the frame or not, hidden or not).
    #[must_use]
    pub fn project(&self, p: &SurfacePoint) -> (f64, f64) {
        Geometry::new(self).project(p.s, p.r, p.z)
    }

    /// Whether a pixel position lies on the frame (pixel centres at integers,
    /// so the frame spans −0.5 … width − 0.5).
    #[must_use]
    pub fn contains(&self, x: f64, y: f64) -> bool {
        #[allow(clippy::cast_precision_loss)]
        let (w, h) = (self.width as f64, self.height as f64);
        x >= -0.5 && y >= -0.5 && x < w - 0.5 && y < h - 0.5
    }
}

/// The microscope's fixed imaging set-up: frame size, magnification, tilt-axis
/// direction, scan rotation, and how stage X/Y moves the image.
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `width`, `height` | 1280, 960 | the full-quality frame size |
/// | `pixel_size_um` | 0.1 | pixel size at `width`; a frame `w` pixels wide has `pixel_size_um · width / w` (same field of view, as magnification fixes it) |
/// | `tilt_axis_deg` | 0 | φ, DESIGN §3 |
/// | `scan_rotation_deg` | 0 | extra in-plane rotation of the scan |
/// | `stage_to_image` | `[[-1, 0], [0, -1]]` | image-plane shift of the specimen (µm, rows x then y) per µm of stage X and Y: by default stage +X moves the image content by −X/p pixels along +x, stage +Y by −Y/p along +y |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OpticsParams {
    pub width: usize,
    pub height: usize,
    pub pixel_size_um: f64,
    pub tilt_axis_deg: f64,
    pub scan_rotation_deg: f64,
    pub stage_to_image: [[f64; 2]; 2],
}

impl Default for OpticsParams {
    fn default() -> Self {
        Self {
            width: 1280,
            height: 960,
            pixel_size_um: 0.1,
            tilt_axis_deg: 0.0,
            scan_rotation_deg: 0.0,
            stage_to_image: [[-1.0, 0.0], [0.0, -1.0]],
        }
    }
}

impl OpticsParams {
    /// Pixel size (µm) of a frame `width` pixels wide.
    #[must_use]
    pub fn pixel_size_at(&self, width: usize) -> f64 {
        #[allow(clippy::cast_precision_loss)]
        let ratio = self.width as f64 / width.max(1) as f64;
        self.pixel_size_um * ratio
    }

    /// Image-plane shift (µm) of the specimen caused by the stage's X/Y position.
    #[must_use]
    pub fn pan_um(&self, pose: &StagePose) -> [f64; 2] {
        let m = &self.stage_to_image;
        [
            m[0][0] * pose.x_um + m[0][1] * pose.y_um,
            m[1][0] * pose.x_um + m[1][1] * pose.y_um,
        ]
    }

    /// The view of a `width × height` frame at `pose`, with the eucentric walk
    /// and drift (image-plane µm) added to the stage pan.
    #[must_use]
    pub fn view(
        &self,
        pose: &StagePose,
        width: usize,
        height: usize,
        walk_um: [f64; 2],
        drift_um: [f64; 2],
    ) -> View {
        let pan = self.pan_um(pose);
        View {
            width,
            height,
            pixel_size_um: self.pixel_size_at(width),
            tilt_deg: pose.tilt_deg,
            tilt_axis_deg: self.tilt_axis_deg,
            scan_rotation_deg: self.scan_rotation_deg,
            offset_um: [
                pan[0] + walk_um[0] + drift_um[0],
                pan[1] + walk_um[1] + drift_um[1],
            ],
        }
    }
}
