//! Synthetic specimens of known shape: the ground truth of the simulator.
//!
//! A [`Scene`] is a height field z(s, r) over a square field of specimen
//! coordinates (µm), with a secondary-electron yield per point and a fine
//! procedural texture, built deterministically from [`SceneParams`].
//!
//! ## Specimen coordinates
//! `s` runs along the stage tilt axis, `r` across it (along n at tilt 0), `z`
//! up towards the beam; the origin is the centre of the field and lies on the
//! tilt axis. DESIGN §3 projects `(s, r, z)` at stage tilt t to image
//! coordinates `s` along a and `r·cos t + z·sin t` along n.
//!
//! ## Exactness
//! The surface *is* the bilinear interpolation of heights sampled every
//! [`SceneParams::sample_um`] on a grid aligned with (s, r). Rendering and
//! ground truth intersect rays with that very surface, so the ground truth is
//! exact, not a resampling. Texture and yield modulate brightness only.

mod kinds;
pub mod noise;

use std::fmt;
use std::str::FromStr;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Which synthetic specimen to image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SceneKind {
    /// Grains and particles of several sizes (0.4–12 µm, up to ~15 µm high) on a substrate.
    #[default]
    Particles,
    /// A metal TEM-style mesh: bars ~15 µm thick with near-vertical walls, square openings.
    Grid,
    /// A machined surface: feed marks, fractal roughness, scratches (a few µm of relief).
    Rough,
    /// A dome ~30 µm high with a dent in its flank, dusted with small particles.
    Dome,
    /// The particles of `Particles` on a flat, untextured support: only scan noise there.
    Bare,
    /// A calibration grid: thin raised bars (~2 µm high) in squares on a dark, flat, untextured floor.
    Calgrid,
    /// A rough metal surface of low contrast: `Rough`'s relief with a faint material texture.
    Metal,
}

impl SceneKind {
    /// The standard specimens, in command-line spelling order.
    pub const ALL: [Self; 4] = [Self::Particles, Self::Grid, Self::Rough, Self::Dome];
    /// The specimens that show a reconstruction's failure modes: featureless support,
    /// repetitive structure, low contrast.
    pub const HARD: [Self; 3] = [Self::Bare, Self::Calgrid, Self::Metal];

    /// The command-line / configuration name.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::Particles => "particles",
            Self::Grid => "grid",
            Self::Rough => "rough",
            Self::Dome => "dome",
            Self::Bare => "bare",
            Self::Calgrid => "calgrid",
            Self::Metal => "metal",
        }
    }
}

impl fmt::Display for SceneKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A scene name that is not one of [`SceneKind::ALL`] or [`SceneKind::HARD`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "unknown scene kind {0:?}: expected one of particles, grid, rough, dome, bare, calgrid, metal"
)]
pub struct UnknownSceneKind(pub String);

impl FromStr for SceneKind {
    type Err = UnknownSceneKind;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .chain(Self::HARD)
            .find(|k| k.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| UnknownSceneKind(s.to_owned()))
    }
}

/// What specimen to build.
///
/// | field | default | effect |
/// | --- | --- | --- |
/// | `kind` | `particles` | the specimen |
/// | `seed` | derived | same seed, same surface and texture; unset: derived from the SEM's seed (`sem.seed`, itself from `simulator.seed`); [`Scene::generate`] alone treats unset as 0 |
/// | `field_um` | 200 | side of the square specimen; outside it there is nothing (dark background) |
/// | `sample_um` | 0.1 | spacing of the height samples; memory ≈ 5 bytes × (field/spacing)² |
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SceneParams {
    pub kind: SceneKind,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    pub field_um: f64,
    pub sample_um: f64,
}

impl Default for SceneParams {
    fn default() -> Self {
        Self {
            kind: SceneKind::Particles,
            seed: None,
            field_um: 200.0,
            sample_um: 0.1,
        }
    }
}

/// Scene parameters out of range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SceneError {
    #[error("scene parameter {name} = {value} is out of range: {expected}")]
    OutOfRange {
        name: &'static str,
        value: f64,
        expected: &'static str,
    },
    #[error(
        "scene of {field_um} µm sampled every {sample_um} µm needs {nodes} height samples (limit {limit}): raise sample_um or shrink field_um"
    )]
    TooLarge {
        field_um: f64,
        sample_um: f64,
        nodes: u64,
        limit: u64,
    },
}

/// Brightness texture of a scene's materials (see [`kinds::albedo`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Texture {
    /// Amplitude of the fBm mottling.
    pub mottle: f64,
    /// Coarsest mottling wavelength, µm.
    pub mottle_lambda_um: f64,
    /// Grain (cell) size, µm.
    pub grain_um: f64,
    /// Brightness spread between grains.
    pub grain_contrast: f64,
    /// Darkening on grain boundaries.
    pub boundary_contrast: f64,
    /// One speck per this cell size (60 % of cells), µm.
    pub speck_cell_um: f64,
    /// Peak brightness of a speck.
    pub speck_brightness: f64,
    /// Materials of a yield below this have no texture at all (a featureless support).
    pub plain_below_yield: f64,
}

/// Heights averaged over a neighbourhood, on a coarser grid: the local mean
/// surface that the SE edge effect and cavity shadowing compare against.
#[derive(Clone, Debug)]
pub(crate) struct CoarseField {
    origin: f64,
    spacing: f64,
    n: usize,
    values: Vec<f32>,
}

impl CoarseField {
    /// Bilinear value at `(s, r)`, clamped to the field.
    pub(crate) fn at(&self, s: f64, r: f64) -> f64 {
        #[allow(clippy::cast_precision_loss)]
        let last = (self.n - 1) as f64;
        let x = ((s - self.origin) / self.spacing).clamp(0.0, last);
        let y = ((r - self.origin) / self.spacing).clamp(0.0, last);
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let (i, j) = ((x as usize).min(self.n - 2), (y as usize).min(self.n - 2));
        #[allow(clippy::cast_precision_loss)]
        let (fx, fy) = (x - i as f64, y - j as f64);
        let v = |i: usize, j: usize| f64::from(self.values[j * self.n + i]);
        let a = v(i, j) + fx * (v(i + 1, j) - v(i, j));
        let b = v(i, j + 1) + fx * (v(i + 1, j + 1) - v(i, j + 1));
        a + fy * (b - a)
    }
}

/// Cells per first-level block of the ray-marching max pyramid.
pub(crate) const BLOCK1: usize = 8;
/// Cells per second-level block.
pub(crate) const BLOCK2: usize = 64;

/// A built specimen: sampled heights, yields, texture and acceleration data.
#[derive(Clone)]
pub struct Scene {
    pub(crate) params: SceneParams,
    /// Coordinate of node 0 along s and along r (the field is square and centred).
    pub(crate) origin: f64,
    pub(crate) spacing: f64,
    /// Nodes per side.
    pub(crate) n: usize,
    /// Heights, column-major: node (i along s, j along r) at `i * n + j`, so a
    /// ray, which runs along r at fixed s, reads memory in order.
    pub(crate) heights: Vec<f32>,
    /// SE yield × 255, same layout.
    pub(crate) yields: Vec<u8>,
    /// Per column pair (i, i+1): maximum height over each block of BLOCK1 / BLOCK2 cells.
    pub(crate) block1: Vec<f32>,
    pub(crate) block2: Vec<f32>,
    pub(crate) n_block1: usize,
    pub(crate) n_block2: usize,
    /// Per column pair: maximum and minimum height.
    pub(crate) col_max: Vec<f32>,
    pub(crate) z_min: f64,
    pub(crate) z_max: f64,
    /// Local mean surface at ~0.6 µm (edge effect) and ~4 µm (cavities).
    pub(crate) edge_mean: CoarseField,
    pub(crate) cavity_mean: CoarseField,
    pub(crate) texture: Texture,
}

impl fmt::Debug for Scene {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Scene")
            .field("params", &self.params)
            .field("nodes_per_side", &self.n)
            .field("z_range_um", &(self.z_min, self.z_max))
            .finish_non_exhaustive()
    }
}

/// Most height samples a scene may have (2.5 GB of heights would be a mistake).
const MAX_NODES: u64 = 100_000_000;

impl Scene {
    /// Builds the specimen described by `params` (parallel; ~0.5 s for the default
    /// 200 µm field at 0.1 µm on two cores).
    ///
    /// # Errors
    /// [`SceneError`] when a parameter is out of range or the grid would be too large.
    pub fn generate(params: &SceneParams) -> Result<Self, SceneError> {
        check(params)?;
        let spacing = params.sample_um;
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let n = (params.field_um / spacing).round() as usize + 1;
        #[allow(clippy::cast_precision_loss)]
        let origin = -((n - 1) as f64) * spacing / 2.0;
        let seed = params.seed.unwrap_or(0);
        let (model, texture) = kinds::build(params.kind, seed, params.field_um);
        let mut heights = vec![0f32; n * n];
        let mut yields = vec![0u8; n * n];
        heights
            .par_chunks_mut(n)
            .zip(yields.par_chunks_mut(n))
            .enumerate()
            .for_each(|(i, (hcol, ycol))| {
                #[allow(clippy::cast_precision_loss)]
                let s = origin + i as f64 * spacing;
                for (j, (h, y)) in hcol.iter_mut().zip(ycol.iter_mut()).enumerate() {
                    #[allow(clippy::cast_precision_loss)]
                    let r = origin + j as f64 * spacing;
                    let (z, yl) = model.sample(s, r);
                    #[allow(clippy::cast_possible_truncation)]
                    {
                        *h = z as f32;
                    }
                    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
                    {
                        *y = (yl.clamp(0.0, 1.0) * 255.0).round() as u8;
                    }
                }
            });
        let (z_min, z_max) = heights
            .par_iter()
            .fold(
                || (f32::INFINITY, f32::NEG_INFINITY),
                |(lo, hi), &h| (lo.min(h), hi.max(h)),
            )
            .reduce(
                || (f32::INFINITY, f32::NEG_INFINITY),
                |a, b| (a.0.min(b.0), a.1.max(b.1)),
            );
        let cells = n - 1;
        let n_block1 = cells.div_ceil(BLOCK1);
        let n_block2 = cells.div_ceil(BLOCK2);
        let pair_max = |i: usize, j0: usize, j1: usize| -> f32 {
            let a = &heights[i * n + j0..=i * n + j1];
            let b = &heights[(i + 1) * n + j0..=(i + 1) * n + j1];
            a.iter().chain(b).copied().fold(f32::NEG_INFINITY, f32::max)
        };
        let block_maxima = |size: usize, count: usize| -> Vec<f32> {
            (0..cells)
                .into_par_iter()
                .flat_map_iter(|i| {
                    (0..count).map(move |k| pair_max(i, k * size, ((k + 1) * size).min(cells)))
                })
                .collect()
        };
        let block1 = block_maxima(BLOCK1, n_block1);
        let block2 = block_maxima(BLOCK2, n_block2);
        let col_max = (0..cells).map(|i| pair_max(i, 0, cells)).collect();
        let edge_mean = coarse_mean(&heights, n, origin, spacing, 0.3, 0.6);
        let cavity_mean = coarse_mean(&heights, n, origin, spacing, 1.0, 4.0);
        Ok(Self {
            params: SceneParams {
                seed: Some(seed),
                ..params.clone()
            },
            origin,
            spacing,
            n,
            heights,
            yields,
            block1,
            block2,
            n_block1,
            n_block2,
            col_max,
            z_min: f64::from(z_min),
            z_max: f64::from(z_max),
            edge_mean,
            cavity_mean,
            texture,
        })
    }

    /// The parameters this scene was built from, its seed filled in.
    #[must_use]
    pub fn params(&self) -> &SceneParams {
        &self.params
    }

    /// The seed the surface and texture were built from.
    #[must_use]
    pub fn seed(&self) -> u64 {
        self.params.seed.unwrap_or(0)
    }

    /// Lowest and highest surface height, µm.
    #[must_use]
    pub fn height_range(&self) -> (f64, f64) {
        (self.z_min, self.z_max)
    }

    /// The specimen field in specimen coordinates: `[min, max]` along s and along r (µm).
    #[must_use]
    pub fn extent(&self) -> (f64, f64) {
        #[allow(clippy::cast_precision_loss)]
        let max = self.origin + (self.n - 1) as f64 * self.spacing;
        (self.origin, max)
    }

    /// Surface height (µm) at specimen point `(s, r)`: the bilinear interpolation
    /// of the samples, exactly what the renderer intersects. `None` off the field.
    #[must_use]
    pub fn height_at(&self, s: f64, r: f64) -> Option<f64> {
        let (i, a) = self.cell(s)?;
        let (j, b) = self.cell(r)?;
        let p0 = self.profile(i, a, j);
        let p1 = self.profile(i, a, j + 1);
        Some(p0 + b * (p1 - p0))
    }

    /// Cell index and fraction of a coordinate along either axis.
    #[inline]
    pub(crate) fn cell(&self, x: f64) -> Option<(usize, f64)> {
        let u = (x - self.origin) / self.spacing;
        #[allow(clippy::cast_precision_loss)]
        let last = (self.n - 1) as f64;
        if !(u >= 0.0 && u <= last) {
            return None;
        }
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let i = (u as usize).min(self.n - 2);
        #[allow(clippy::cast_precision_loss)]
        Some((i, u - i as f64))
    }

    /// Height at node row `j` on the line between columns `i` and `i + 1` at fraction `a`.
    #[inline]
    pub(crate) fn profile(&self, i: usize, a: f64, j: usize) -> f64 {
        let h0 = f64::from(self.heights[i * self.n + j]);
        let h1 = f64::from(self.heights[(i + 1) * self.n + j]);
        h0 + a * (h1 - h0)
    }

    #[inline]
    pub(crate) fn node(&self, i: usize, j: usize) -> f64 {
        let i = i.min(self.n - 1);
        let j = j.min(self.n - 1);
        f64::from(self.heights[i * self.n + j])
    }

    /// Node coordinate along either axis.
    #[inline]
    pub(crate) fn coord(&self, k: usize) -> f64 {
        #[allow(clippy::cast_precision_loss)]
        let k = k as f64;
        self.origin + k * self.spacing
    }

    /// Smooth surface gradient (∂z/∂s, ∂z/∂r) at `(s, r)`: central differences
    /// at the four surrounding nodes, interpolated bilinearly, so shading does
    /// not show the facets of the bilinear patches.
    pub(crate) fn gradient(&self, s: f64, r: f64) -> (f64, f64) {
        let (Some((i, a)), Some((j, b))) = (self.cell(s), self.cell(r)) else {
            return (0.0, 0.0);
        };
        let g = |i: usize, j: usize| -> (f64, f64) {
            let (im, ip) = (i.saturating_sub(1), (i + 1).min(self.n - 1));
            let (jm, jp) = (j.saturating_sub(1), (j + 1).min(self.n - 1));
            #[allow(clippy::cast_precision_loss)]
            let ds = (self.node(ip, j) - self.node(im, j)) / ((ip - im) as f64 * self.spacing);
            #[allow(clippy::cast_precision_loss)]
            let dr = (self.node(i, jp) - self.node(i, jm)) / ((jp - jm) as f64 * self.spacing);
            (ds, dr)
        };
        let (g00, g10, g01, g11) = (g(i, j), g(i + 1, j), g(i, j + 1), g(i + 1, j + 1));
        let lerp2 = |p: f64, q: f64, u: f64, v: f64| {
            let top = p + a * (q - p);
            let bottom = u + a * (v - u);
            top + b * (bottom - top)
        };
        (
            lerp2(g00.0, g10.0, g01.0, g11.0),
            lerp2(g00.1, g10.1, g01.1, g11.1),
        )
    }

    /// SE yield (0–1) of the material at `(s, r)`, interpolated.
    pub(crate) fn yield_at(&self, s: f64, r: f64) -> f64 {
        let (Some((i, a)), Some((j, b))) = (self.cell(s), self.cell(r)) else {
            return 0.0;
        };
        let y = |i: usize, j: usize| f64::from(self.yields[i * self.n + j]) / 255.0;
        let top = y(i, j) + a * (y(i + 1, j) - y(i, j));
        let bottom = y(i, j + 1) + a * (y(i + 1, j + 1) - y(i, j + 1));
        top + b * (bottom - top)
    }

    /// Material brightness texture at `(s, r)` of a material of yield `yld`,
    /// band-limited to `footprint` µm.
    pub(crate) fn albedo(&self, s: f64, r: f64, footprint: f64, yld: f64) -> f64 {
        kinds::albedo(&self.texture, self.seed(), s, r, footprint, yld)
    }
}

fn check(p: &SceneParams) -> Result<(), SceneError> {
    let range = |name, value: f64, lo: f64, hi: f64, expected| {
        if value.is_finite() && value >= lo && value <= hi {
            Ok(())
        } else {
            Err(SceneError::OutOfRange {
                name,
                value,
                expected,
            })
        }
    };
    range("field_um", p.field_um, 2.0, 5000.0, "2 to 5000 µm")?;
    range("sample_um", p.sample_um, 0.005, 10.0, "0.005 to 10 µm")?;
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let side = (p.field_um / p.sample_um).round() as u64 + 1;
    let nodes = side * side;
    if side < 9 {
        return Err(SceneError::OutOfRange {
            name: "sample_um",
            value: p.sample_um,
            expected: "at most field_um / 8",
        });
    }
    if nodes > MAX_NODES {
        return Err(SceneError::TooLarge {
            field_um: p.field_um,
            sample_um: p.sample_um,
            nodes,
            limit: MAX_NODES,
        });
    }
    Ok(())
}

/// Mean of the heights over a box of `radius_um` (two box passes: a tent),
/// on a grid `step_um` apart.
fn coarse_mean(
    heights: &[f32],
    n: usize,
    origin: f64,
    spacing: f64,
    step_um: f64,
    radius_um: f64,
) -> CoarseField {
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let stride = ((step_um / spacing).round() as usize).max(1);
    let m = (n - 1) / stride + 1;
    // Down-sample by averaging the nodes of each stride × stride block.
    let mut values: Vec<f32> = (0..m * m)
        .into_par_iter()
        .map(|k| {
            let (ci, cj) = (k % m, k / m);
            let mut sum = 0.0f64;
            let mut count = 0u32;
            for i in ci * stride..((ci + 1) * stride).min(n) {
                for j in cj * stride..((cj + 1) * stride).min(n) {
                    sum += f64::from(heights[i * n + j]);
                    count += 1;
                }
            }
            #[allow(clippy::cast_possible_truncation)]
            let mean = (sum / f64::from(count.max(1))) as f32;
            mean
        })
        .collect();
    #[allow(clippy::cast_precision_loss)]
    let coarse_spacing = spacing * stride as f64;
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let radius = ((radius_um / coarse_spacing / 2.0).round() as usize).max(1);
    for _ in 0..2 {
        values = box_blur_rows(&values, m, radius);
        values = transpose(&values, m);
        values = box_blur_rows(&values, m, radius);
        values = transpose(&values, m);
    }
    // Nodes of the coarse grid sit at the centres of their blocks.
    #[allow(clippy::cast_precision_loss)]
    let offset = (stride as f64 - 1.0) / 2.0 * spacing;
    CoarseField {
        origin: origin + offset,
        spacing: coarse_spacing,
        n: m,
        values,
    }
}

fn box_blur_rows(v: &[f32], m: usize, radius: usize) -> Vec<f32> {
    let mut out = vec![0f32; m * m];
    out.par_chunks_mut(m).enumerate().for_each(|(row, o)| {
        let line = &v[row * m..(row + 1) * m];
        let mut prefix = Vec::with_capacity(m + 1);
        prefix.push(0f64);
        for &x in line {
            let last = prefix[prefix.len() - 1];
            prefix.push(last + f64::from(x));
        }
        for (k, o) in o.iter_mut().enumerate() {
            let lo = k.saturating_sub(radius);
            let hi = (k + radius + 1).min(m);
            #[allow(clippy::cast_possible_truncation, clippy::cast_precision_loss)]
            {
                *o = ((prefix[hi] - prefix[lo]) / (hi - lo) as f64) as f32;
            }
        }
    });
    out
}

fn transpose(v: &[f32], m: usize) -> Vec<f32> {
    let mut out = vec![0f32; m * m];
    for j in 0..m {
        for i in 0..m {
            out[i * m + j] = v[j * m + i];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small(kind: SceneKind, seed: u64) -> Scene {
        Scene::generate(&SceneParams {
            kind,
            seed: Some(seed),
            field_um: 40.0,
            sample_um: 0.1,
        })
        .unwrap()
    }

    #[test]
    fn kind_names_round_trip() {
        for k in SceneKind::ALL.into_iter().chain(SceneKind::HARD) {
            assert_eq!(k.to_string().parse::<SceneKind>().unwrap(), k);
        }
        assert!("Grid".parse::<SceneKind>().is_ok());
        let err = "mesh".parse::<SceneKind>().unwrap_err();
        assert!(err.to_string().contains("particles, grid, rough, dome"));
    }

    #[test]
    fn same_seed_same_scene_other_seed_other_scene() {
        let a = small(SceneKind::Particles, 4);
        let b = small(SceneKind::Particles, 4);
        let c = small(SceneKind::Particles, 5);
        assert_eq!(a.heights, b.heights);
        assert_ne!(a.heights, c.heights);
    }

    #[test]
    fn height_at_interpolates_the_samples() {
        let sc = small(SceneKind::Rough, 1);
        let (s, r) = (sc.coord(100), sc.coord(57));
        assert!((sc.height_at(s, r).unwrap() - sc.node(100, 57)).abs() < 1e-9);
        let mid = sc.height_at(s + 0.5 * sc.spacing, r).unwrap();
        assert!((mid - 0.5 * (sc.node(100, 57) + sc.node(101, 57))).abs() < 1e-9);
        assert_eq!(sc.height_at(1e3, 0.0), None);
    }

    #[test]
    fn block_maxima_bound_every_cell() {
        let sc = small(SceneKind::Grid, 2);
        let cells = sc.n - 1;
        for i in (0..cells).step_by(37) {
            for j in 0..cells {
                let m = sc.node(i, j).max(sc.node(i + 1, j));
                assert!(f64::from(sc.block1[i * sc.n_block1 + j / BLOCK1]) >= m);
                assert!(f64::from(sc.block2[i * sc.n_block2 + j / BLOCK2]) >= m);
                assert!(f64::from(sc.col_max[i]) >= m);
            }
        }
    }

    #[test]
    fn rejects_bad_parameters_with_the_remedy() {
        let err = Scene::generate(&SceneParams {
            field_um: 5000.0,
            sample_um: 0.01,
            ..SceneParams::default()
        })
        .unwrap_err();
        assert!(err.to_string().contains("raise sample_um"));
        assert!(
            Scene::generate(&SceneParams {
                sample_um: f64::NAN,
                ..SceneParams::default()
            })
            .is_err()
        );
    }

    #[test]
    fn params_deny_unknown_fields() {
        let ok: SceneParams = serde_json::from_str(r#"{"kind":"dome","seed":3}"#).unwrap();
        assert_eq!(ok.kind, SceneKind::Dome);
        assert_eq!(ok.field_um, 200.0);
        assert!(serde_json::from_str::<SceneParams>(r#"{"kinds":"dome"}"#).is_err());
    }
}
