//! The SEM image of a [`Scene`]: parallel projection at any stage tilt with
//! hidden surfaces removed, secondary-electron shading, scan noise, and the
//! exact ground truth of every frame.
//!
//! ```no_run
//! use sdsem_sim::render::{self, ShadingParams, View};
//! use sdsem_sim::scene::{Scene, SceneKind, SceneParams};
//!
//! let scene = Scene::generate(&SceneParams { kind: SceneKind::Particles, seed: 7, ..Default::default() })?;
//! let left = View { tilt_deg: -3.0, ..View::default() };
//! let right = View { tilt_deg: 3.0, ..left };
//! let image_left = render::render(&scene, &left, &ShadingParams::default()); // f32 in [0, 1], row-major
//! let heights = render::height_map(&scene, &left); // µm on the left grid, NaN off the specimen
//! let flow = render::correspondences(&scene, &left, &right); // true left → right positions
//! # Ok::<(), sdsem_sim::scene::SceneError>(())
//! ```
//!
//! Geometry (DESIGN §3 and [`View`]): a specimen point `(s, r, z)` appears at
//! `s` along a and `r·cos t + z·sin t` along n, so a point `h` higher moves by
//! `h·sin θ` along n between two tilts θ apart (for small tilts).

mod noise;
mod shade;
mod trace;
mod truth;
mod view;

use rayon::prelude::*;

pub use noise::{NoiseParams, add_scan_noise};
pub use shade::ShadingParams;
pub use trace::{Facet, SurfacePoint};
pub use truth::{
    Correspondence, correspondence, correspondences, height_map, trace_pixel, visible_points,
};
pub use view::{OpticsParams, View};

use crate::scene::Scene;
use shade::Shader;
use view::Geometry;

/// Renders the noise-free SE image of `scene` in `view`: row-major `f32` in
/// `[0, 1)`, `view.width × view.height` samples. Parallel over rows.
#[must_use]
pub fn render(scene: &Scene, view: &View, shading: &ShadingParams) -> Vec<f32> {
    let geo = Geometry::new(view);
    let shader = Shader::new(shading, geo.tilt, view.tilt_axis_deg, view.pixel_size_um);
    let mut out = vec![0f32; view.width * view.height];
    out.par_chunks_mut(view.width.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, px) in row.iter_mut().enumerate() {
                #[allow(clippy::cast_precision_loss)]
                let (s, v) = geo.ray(x as f64, y as f64);
                let hit = trace::trace(scene, s, v, geo.tilt);
                #[allow(clippy::cast_possible_truncation)]
                {
                    *px = shader.shade(scene, hit.as_ref()) as f32;
                }
            }
        });
    out
}

/// Renders a frame as the microscope records it: [`render`] plus scan noise
/// for a pixel dwell of `dwell_us`, seeded by `noise_seed` (use a different
/// seed per frame).
#[must_use]
pub fn render_noisy(
    scene: &Scene,
    view: &View,
    shading: &ShadingParams,
    noise: &NoiseParams,
    dwell_us: f64,
    noise_seed: u64,
) -> Vec<f32> {
    let mut pixels = render(scene, view, shading);
    add_scan_noise(&mut pixels, dwell_us, noise, noise_seed);
    pixels
}

/// Quantises signals in `[0, 1]` to 16 bits (clamped, rounded).
#[must_use]
pub fn to_u16(pixels: &[f32]) -> Vec<u16> {
    pixels
        .iter()
        // In [0, 65535.5) after clamping.
        .map(|&v| {
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let q = (v.clamp(0.0, 1.0) * 65535.0 + 0.5) as u16;
            q
        })
        .collect()
}

/// Quantises signals in `[0, 1]` to 8 bits (clamped, rounded).
#[must_use]
pub fn to_u8(pixels: &[f32]) -> Vec<u8> {
    pixels
        .iter()
        .map(|&v| {
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            let q = (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
            q
        })
        .collect()
}

#[cfg(test)]
mod tests;
