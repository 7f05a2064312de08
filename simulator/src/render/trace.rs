//! Ray casting against the scene's height field under parallel projection.
//!
//! A pixel sees the specimen along a ray of the beam. In specimen coordinates
//! at stage tilt t the beam travels along −(0, −sin t, cos t); the ray of the
//! image coordinate `v` (along n) at `s` (along a) is the set of points with
//! `r·cos t + z·sin t = v`, i.e. `z(r) = (v − r·cos t) / sin t`. It stays at
//! fixed `s`, so it crosses the scene's cells along one column pair, where the
//! bilinear surface is linear in r within each cell: the first crossing is
//! found exactly, cell by cell, from the beam side (hidden surfaces removed:
//! the visible point is the one nearest the beam). Blocks of cells whose
//! maximum height lies below the ray are skipped (a two-level max pyramid).

use crate::scene::{BLOCK1, BLOCK2, Scene};

/// Which face of the specimen a ray met.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Facet {
    /// The height field, z(s, r).
    Top,
    /// A side face of the specimen block at the edge of the field (seen only
    /// when a tilted ray enters the field below its surface).
    Side,
}

/// A point of the specimen surface in specimen coordinates (µm).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    /// Along the tilt axis.
    pub s: f64,
    /// Across the tilt axis.
    pub r: f64,
    /// Height, up towards the beam.
    pub z: f64,
    pub facet: Facet,
}

/// The beam direction of a stage tilt: `(cos t, sin t)`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Tilt {
    pub cos: f64,
    pub sin: f64,
}

impl Tilt {
    pub(crate) fn from_deg(t: f64) -> Self {
        let (sin, cos) = t.to_radians().sin_cos();
        Self { cos, sin }
    }

    /// Depth of a point towards the beam (larger = nearer the beam).
    pub(crate) fn depth(self, r: f64, z: f64) -> f64 {
        -r * self.sin + z * self.cos
    }

    /// Image coordinate along n of a specimen point (DESIGN §3).
    pub(crate) fn v(self, r: f64, z: f64) -> f64 {
        r * self.cos + z * self.sin
    }
}

/// Below this |sin t| the beam is treated as exactly normal to the stage.
const NORMAL_INCIDENCE: f64 = 1e-12;

/// The visible surface point on the ray `(s, v)` at tilt `tilt`, `None` when
/// the ray misses the specimen (background).
pub(crate) fn trace(scene: &Scene, s: f64, v: f64, tilt: Tilt) -> Option<SurfacePoint> {
    let (i, a) = scene.cell(s)?;
    if tilt.sin.abs() < NORMAL_INCIDENCE {
        return vertical(scene, s, v / tilt.cos, i, a);
    }
    let cells = scene.n - 1;
    let up = tilt.sin > 0.0;
    let inv_sin = 1.0 / tilt.sin;
    let z_ray = |r: f64| (v - r * tilt.cos) * inv_sin;
    // Where the ray comes down to the highest point of its column pair.
    let z_top = f64::from(scene.col_max[i]);
    let u = ((v - z_top * tilt.sin) / tilt.cos - scene.origin) / scene.spacing;
    #[allow(clippy::cast_precision_loss)]
    let last = cells as f64;
    // `j` is the current cell; the ray runs from its entry node to its exit node.
    let mut j: isize = if up {
        if u > last {
            return None;
        }
        if u < 0.0 {
            if let Some(p) = side_hit(scene, s, i, a, 0, &z_ray) {
                return Some(p);
            }
            0
        } else {
            floor_cell(u, cells)
        }
    } else {
        if u < 0.0 {
            return None;
        }
        if u > last {
            if let Some(p) = side_hit(scene, s, i, a, cells, &z_ray) {
                return Some(p);
            }
            cells as isize - 1
        } else {
            floor_cell(u, cells)
        }
    };
    let step: isize = if up { 1 } else { -1 };
    loop {
        if j < 0 || j >= cells as isize {
            return None;
        }
        // Non-negative and below `cells` by the check above.
        #[allow(clippy::cast_sign_loss)]
        let ju = j as usize;
        if let Some(next) = skip_block(
            scene,
            i,
            ju,
            up,
            BLOCK2,
            &scene.block2,
            scene.n_block2,
            &z_ray,
        ) {
            j = next;
            continue;
        }
        if let Some(next) = skip_block(
            scene,
            i,
            ju,
            up,
            BLOCK1,
            &scene.block1,
            scene.n_block1,
            &z_ray,
        ) {
            j = next;
            continue;
        }
        if let Some(p) = cell_hit(scene, s, i, a, ju, up, &z_ray) {
            return Some(p);
        }
        j += step;
    }
}

/// The reference: every cell from the edge of the field, no skipping. The
/// fast [`trace`] must agree with it.
#[cfg(test)]
pub(crate) fn trace_naive(scene: &Scene, s: f64, v: f64, tilt: Tilt) -> Option<SurfacePoint> {
    let (i, a) = scene.cell(s)?;
    if tilt.sin.abs() < NORMAL_INCIDENCE {
        return vertical(scene, s, v / tilt.cos, i, a);
    }
    let cells = scene.n - 1;
    let up = tilt.sin > 0.0;
    let z_ray = |r: f64| (v - r * tilt.cos) / tilt.sin;
    let entry = if up { 0 } else { cells };
    if let Some(p) = side_hit(scene, s, i, a, entry, &z_ray) {
        return Some(p);
    }
    let order: Box<dyn Iterator<Item = usize>> = if up {
        Box::new(0..cells)
    } else {
        Box::new((0..cells).rev())
    };
    for j in order {
        if let Some(p) = cell_hit(scene, s, i, a, j, up, &z_ray) {
            return Some(p);
        }
    }
    None
}

fn floor_cell(u: f64, cells: usize) -> isize {
    // `u` is within [0, cells] here.
    #[allow(clippy::cast_possible_truncation)]
    let j = u.floor() as isize;
    j.min(cells as isize - 1)
}

fn vertical(scene: &Scene, s: f64, r: f64, i: usize, a: f64) -> Option<SurfacePoint> {
    let (j, b) = scene.cell(r)?;
    let p0 = scene.profile(i, a, j);
    let p1 = scene.profile(i, a, j + 1);
    Some(SurfacePoint {
        s,
        r,
        z: p0 + b * (p1 - p0),
        facet: Facet::Top,
    })
}

/// A ray entering the field through its side below the surface meets the side face.
fn side_hit(
    scene: &Scene,
    s: f64,
    i: usize,
    a: f64,
    node: usize,
    z_ray: &impl Fn(f64) -> f64,
) -> Option<SurfacePoint> {
    let r = scene.coord(node);
    let z = z_ray(r);
    (z < scene.profile(i, a, node)).then_some(SurfacePoint {
        s,
        r,
        z,
        facet: Facet::Side,
    })
}

/// The next cell after the block of `size` cells holding cell `j`, when the
/// ray passes above everything in that block.
#[allow(clippy::too_many_arguments)]
#[inline]
fn skip_block(
    scene: &Scene,
    i: usize,
    j: usize,
    up: bool,
    size: usize,
    maxima: &[f32],
    per_column: usize,
    z_ray: &impl Fn(f64) -> f64,
) -> Option<isize> {
    let k = j / size;
    let cells = scene.n - 1;
    // The ray descends along the march, so it is lowest at the block's exit node.
    let exit = if up {
        ((k + 1) * size).min(cells)
    } else {
        k * size
    };
    if z_ray(scene.coord(exit)) > f64::from(maxima[i * per_column + k]) {
        // Block boundaries are small non-negative indices.
        #[allow(clippy::cast_possible_wrap)]
        let next = if up { exit as isize } else { exit as isize - 1 };
        Some(next)
    } else {
        None
    }
}

/// The crossing of the ray with the surface in cell `j`, if it goes below it there.
#[inline]
fn cell_hit(
    scene: &Scene,
    s: f64,
    i: usize,
    a: f64,
    j: usize,
    up: bool,
    z_ray: &impl Fn(f64) -> f64,
) -> Option<SurfacePoint> {
    let (je, jx) = if up { (j, j + 1) } else { (j + 1, j) };
    let (re, rx) = (scene.coord(je), scene.coord(jx));
    let dx = z_ray(rx) - scene.profile(i, a, jx);
    if dx > 0.0 {
        return None;
    }
    let de = z_ray(re) - scene.profile(i, a, je);
    // Both the ray and the surface are linear in r within the cell.
    let lambda = if de > dx {
        (de / (de - dx)).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let r = re + lambda * (rx - re);
    Some(SurfacePoint {
        s,
        r,
        z: z_ray(r),
        facet: Facet::Top,
    })
}
