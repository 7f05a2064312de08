//! What zero height means: the datum the heights are given against.
//!
//! Triangulated heights (eq. 19) are relative to the rectification's zero disparity, an
//! arbitrary plane of the mid-tilt frame (DESIGN §3). A microscopist reads heights above the
//! specimen support, so by default the map is levelled on it: a robust plane through the
//! lowest large flat region is found and subtracted (along the height axis, as Gwyddion's
//! plane levelling does: a shear, not a rotation; exact for the few degrees a support
//! leans in the frame).
//!
//! The support is found by RANSAC on a coarse grid of block medians: planes through three
//! random cells, scored by the cells within a tolerance of the plane minus a penalty for
//! the cells far below it (a plane with heights below it is not the lowest), then refined
//! by least squares on its inliers. Every other sample is drawn from the lowest quarter of
//! the cells, so a support seen only in a few separate patches (the corners beside a large
//! specimen) is still sampled. A plane with more than [`MAX_BELOW`] of the cells far below
//! it is no support: then the mean plane is used and the report says why. The tolerance
//! follows the map's own noise (the second differences of the grid, robustly) and is at
//! least 0.5 % of the relief.

use rand::{Rng, SeedableRng};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::Image;

/// The reference heights are given against (`reconstruction.datum`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum DatumKind {
    /// Zero on the specimen support (substrate, stub or filter around the specimen): a robust
    /// plane through the lowest large flat region is subtracted.
    #[default]
    Support,
    /// Zero on the least-squares plane through all measured heights (plane levelling).
    MeanPlane,
    /// Heights as triangulated: zero is the rectification's zero disparity, an arbitrary
    /// level; only differences of height mean something.
    None,
}

impl DatumKind {
    /// The key's value in the configuration and the report.
    #[must_use]
    pub fn name(self) -> &'static str {
        match self {
            Self::Support => "support",
            Self::MeanPlane => "mean-plane",
            Self::None => "none",
        }
    }

    /// What zero means, in one line (height.tif description, GSF title).
    #[must_use]
    pub fn zero(self) -> &'static str {
        match self {
            Self::Support => {
                "the specimen support (a plane fitted to the lowest large flat region)"
            }
            Self::MeanPlane => "the least-squares plane through all measured heights",
            Self::None => {
                "arbitrary (the rectification's zero disparity); only height differences are meaningful"
            }
        }
    }
}

/// The datum applied to a height map, as `report.json` gives it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Datum {
    /// What `reconstruction.datum` asked for.
    pub requested: DatumKind,
    /// What was applied: `mean-plane` when no support could be found.
    pub kind: DatumKind,
    /// What zero means.
    pub zero: &'static str,
    /// The plane subtracted, `h₀(x, y) = c₀ + c₁·x + c₂·y` (µm; x, y left-grid pixels).
    pub plane_um: [f64; 3],
    /// The subtracted plane's inclination in the reconstruction frame, degrees.
    pub plane_inclination_deg: f64,
    /// Support: the fraction of measured pixels within `tolerance_um` of it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub support_fraction: Option<f64>,
    /// Support: RMS height of those pixels after levelling, µm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub support_rms_um: Option<f64>,
    /// Support: the fraction of measured pixels more than 3 tolerances below it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub below_fraction: Option<f64>,
    /// Support: how far from the plane a pixel still belongs to it, µm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tolerance_um: Option<f64>,
    /// Why the support was not used.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fallback: Option<String>,
}

/// Long side of the grid of block medians the support is searched on.
const GRID: usize = 128;
/// Fewest grid cells of a support, as a fraction of the measured cells.
const MIN_SUPPORT: f64 = 0.05;
/// Weight of a cell below the plane against a cell on it.
const BELOW_PENALTY: f64 = 4.0;
/// RANSAC samples (deterministic: a fixed seed).
const ITERATIONS: usize = 2000;
/// Share of the cells from which every other sample is drawn: the lowest.
const LOW_POOL: f64 = 0.25;
/// Largest share of the cells more than 3 tolerances below an accepted support: a specimen
/// rests on its support, so a plane with half the measured area far below it is not one.
const MAX_BELOW: f64 = 0.5;

/// Levels `height_um` (µm, NaN unknown; pixel size `pixel_size_um`) on the datum `kind`
/// and says what was done.
pub fn apply_datum(height_um: &mut Image, kind: DatumKind, pixel_size_um: f64) -> Datum {
    let mut datum = Datum {
        requested: kind,
        kind,
        zero: kind.zero(),
        plane_um: [0.0; 3],
        plane_inclination_deg: 0.0,
        support_fraction: None,
        support_rms_um: None,
        below_fraction: None,
        tolerance_um: None,
        fallback: None,
    };
    let plane = match kind {
        DatumKind::None => return datum,
        DatumKind::MeanPlane => mean_plane(height_um),
        DatumKind::Support => match support_plane(height_um) {
            Ok(found) => {
                datum.tolerance_um = Some(found.tolerance);
                Some(found.plane)
            }
            Err(reason) => {
                datum.kind = DatumKind::MeanPlane;
                datum.zero = DatumKind::MeanPlane.zero();
                datum.fallback = Some(reason);
                mean_plane(height_um)
            }
        },
    };
    let Some(c) = plane else {
        datum.kind = DatumKind::None;
        datum.zero = DatumKind::None.zero();
        datum.fallback = Some("no measured height to level on".to_owned());
        return datum;
    };
    let w = height_um.width().max(1);
    height_um
        .data_mut()
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(y, row)| {
            for (x, v) in row.iter_mut().enumerate() {
                if v.is_finite() {
                    *v = (f64::from(*v) - (c[0] + c[1] * x as f64 + c[2] * y as f64)) as f32;
                }
            }
        });
    datum.plane_um = c;
    datum.plane_inclination_deg = (c[1].hypot(c[2]) / pixel_size_um).atan().to_degrees();
    if let Some(tol) = datum.tolerance_um {
        let (mut on, mut below, mut sq, mut n) = (0usize, 0usize, 0.0f64, 0usize);
        for &v in height_um.data().iter().filter(|v| v.is_finite()) {
            let v = f64::from(v);
            n += 1;
            if v.abs() <= tol {
                on += 1;
                sq += v * v;
            } else if v < -3.0 * tol {
                below += 1;
            }
        }
        datum.support_fraction = Some(on as f64 / n.max(1) as f64);
        datum.support_rms_um = Some((sq / on.max(1) as f64).sqrt());
        datum.below_fraction = Some(below as f64 / n.max(1) as f64);
    }
    datum
}

/// A support plane and the tolerance it was found with.
struct Support {
    plane: [f64; 3],
    tolerance: f64,
}

/// One cell of the coarse grid: its centre in left-grid pixels and its median height.
#[derive(Clone, Copy)]
struct Cell {
    x: f64,
    y: f64,
    z: f64,
}

/// Block medians of the finite heights (a block at least half measured), on a grid whose long
/// side is at most [`GRID`]; `None` for blocks without enough heights. Rows of blocks in
/// parallel: each cell is its own block's median, so the grid is the same in any order.
fn block_medians(height: &Image) -> (Vec<Option<Cell>>, usize, usize) {
    let (w, h) = height.dimensions();
    let b = w.max(h).div_ceil(GRID).max(1);
    let (gw, gh) = (w.div_ceil(b), h.div_ceil(b));
    let cells = (0..gh)
        .into_par_iter()
        .flat_map_iter(|gy| {
            let mut values = Vec::with_capacity(b * b);
            (0..gw).map(move |gx| {
                let (x0, y0) = (gx * b, gy * b);
                let (x1, y1) = ((x0 + b).min(w), (y0 + b).min(h));
                values.clear();
                for y in y0..y1 {
                    values.extend(
                        height.row(y)[x0..x1]
                            .iter()
                            .map(|&v| f64::from(v))
                            .filter(|v| v.is_finite()),
                    );
                }
                let area = (x1 - x0) * (y1 - y0);
                (2 * values.len() >= area && !values.is_empty()).then(|| Cell {
                    x: (x0 + x1 - 1) as f64 / 2.0,
                    y: (y0 + y1 - 1) as f64 / 2.0,
                    z: median(&mut values).unwrap_or(f64::NAN),
                })
            })
        })
        .collect();
    (cells, gw, gh)
}

/// The median (the mean of the middle two of an even count: a block's centre on a plane).
fn median(v: &mut [f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let mid = v.len() / 2;
    let odd = v.len() % 2 == 1;
    let (lower, m, _) = v.select_nth_unstable_by(mid, f64::total_cmp);
    let m = *m;
    if odd {
        return Some(m);
    }
    let below = lower.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    Some(0.5 * (below + m))
}

/// The noise of the grid's heights: 1.4826 · median |second difference| / √6, which a plane
/// (any tilt) does not raise.
fn grid_noise(cells: &[Option<Cell>], gw: usize, gh: usize) -> Option<f64> {
    let z = |x: usize, y: usize| cells[y * gw + x].map(|c| c.z);
    let mut d = Vec::new();
    for y in 0..gh {
        for x in 0..gw {
            if x + 2 < gw
                && let (Some(a), Some(b), Some(c)) = (z(x, y), z(x + 1, y), z(x + 2, y))
            {
                d.push((a - 2.0 * b + c).abs());
            }
            if y + 2 < gh
                && let (Some(a), Some(b), Some(c)) = (z(x, y), z(x, y + 1), z(x, y + 2))
            {
                d.push((a - 2.0 * b + c).abs());
            }
        }
    }
    median(&mut d).map(|m| 1.4826 * m / 6f64.sqrt())
}

/// The sample plane with the highest score — the cells within `tolerance` of it minus
/// [`BELOW_PENALTY`] per cell more than 3 tolerances below it — among those with at least
/// `min_cells` cells on them; the first of equal scores. Scored in parallel, chosen in order.
fn best_sample(
    samples: &[[f64; 3]],
    pts: &[Cell],
    tolerance: f64,
    min_cells: usize,
) -> Option<([f64; 3], f64)> {
    let scores: Vec<Option<f64>> = samples
        .par_iter()
        .map(|plane| {
            let (mut on, mut below) = (0usize, 0usize);
            for c in pts {
                let r = residual(plane, c);
                if r.abs() <= tolerance {
                    on += 1;
                } else if r < -3.0 * tolerance {
                    below += 1;
                }
            }
            (on >= min_cells).then_some(on as f64 - BELOW_PENALTY * below as f64)
        })
        .collect();
    let mut best: Option<([f64; 3], f64)> = None;
    for (plane, score) in samples.iter().zip(scores) {
        if let Some(score) = score
            && best.is_none_or(|(_, s)| score > s)
        {
            best = Some((*plane, score));
        }
    }
    best
}

/// The plane through three cells, `None` when they are (nearly) collinear.
fn plane_through(a: Cell, b: Cell, c: Cell) -> Option<[f64; 3]> {
    let (ux, uy, uz) = (b.x - a.x, b.y - a.y, b.z - a.z);
    let (vx, vy, vz) = (c.x - a.x, c.y - a.y, c.z - a.z);
    let det = ux * vy - uy * vx;
    if det.abs() < 1e-9 * (ux.hypot(uy) * vx.hypot(vy)).max(1.0) || det.abs() < 1.0 {
        return None;
    }
    // z = a.z + g·(x − a.x) + k·(y − a.y), with (g, k) solving the two edge equations.
    let g = (uz * vy - vz * uy) / det;
    let k = (ux * vz - vx * uz) / det;
    Some([a.z - g * a.x - k * a.y, g, k])
}

fn residual(p: &[f64; 3], c: &Cell) -> f64 {
    c.z - (p[0] + p[1] * c.x + p[2] * c.y)
}

/// Least-squares plane through `(x, y, z)` points, `None` when they do not span a plane.
fn fit_plane(points: impl Iterator<Item = (f64, f64, f64)>) -> Option<[f64; 3]> {
    // Centred normal equations for numerical safety on large pixel coordinates.
    let pts: Vec<(f64, f64, f64)> = points.collect();
    let n = pts.len() as f64;
    if pts.len() < 3 {
        return None;
    }
    let (mx, my, mz) = pts.iter().fold((0.0, 0.0, 0.0), |(a, b, c), p| {
        (a + p.0 / n, b + p.1 / n, c + p.2 / n)
    });
    let (mut sxx, mut sxy, mut syy, mut sxz, mut syz) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for &(x, y, z) in &pts {
        let (x, y, z) = (x - mx, y - my, z - mz);
        sxx += x * x;
        sxy += x * y;
        syy += y * y;
        sxz += x * z;
        syz += y * z;
    }
    let det = sxx * syy - sxy * sxy;
    if det.abs() <= 1e-12 * (sxx * syy).max(1e-300) {
        return None;
    }
    let g = (sxz * syy - syz * sxy) / det;
    let k = (syz * sxx - sxz * sxy) / det;
    Some([mz - g * mx - k * my, g, k])
}

/// The least-squares plane through every finite height.
fn mean_plane(height: &Image) -> Option<[f64; 3]> {
    let w = height.width();
    fit_plane(
        height
            .data()
            .iter()
            .enumerate()
            .filter(|(_, v)| v.is_finite())
            .map(|(p, v)| ((p % w) as f64, (p / w) as f64, f64::from(*v))),
    )
}

/// The specimen support: the lowest large flat region's plane, or why there is none.
fn support_plane(height: &Image) -> Result<Support, String> {
    let (cells, gw, gh) = block_medians(height);
    let pts: Vec<Cell> = cells.iter().flatten().copied().collect();
    let n = pts.len();
    if n < 30 {
        return Err(format!(
            "too few measured heights to find the support ({n} of {} grid cells)",
            gw * gh
        ));
    }
    let mut zs: Vec<f64> = pts.iter().map(|c| c.z).collect();
    zs.sort_by(f64::total_cmp);
    let relief = zs[(n - 1) * 99 / 100] - zs[(n - 1) / 100];
    let noise = grid_noise(&cells, gw, gh).unwrap_or(0.0);
    let tolerance = (3.0 * noise).max(0.005 * relief).max(1e-6);
    let min_cells = ((MIN_SUPPORT * n as f64).ceil() as usize).max(10);

    // Cell indices by height: the first `low` of them are the lowest quarter.
    let mut by_height: Vec<usize> = (0..n).collect();
    by_height.sort_by(|&a, &b| pts[a].z.total_cmp(&pts[b].z));
    let low = ((LOW_POOL * n as f64).ceil() as usize).clamp(3, n);

    // The samples are drawn in order from one seeded generator, as a loop would draw them; their
    // scores are independent, so they are counted in parallel.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0x5EED_DA7A);
    let samples: Vec<[f64; 3]> = (0..ITERATIONS)
        .filter_map(|it| {
            let pool = if it % 2 == 0 { low } else { n };
            let mut draw = || by_height[rng.random_range(0..pool)];
            let (i, j, k) = (draw(), draw(), draw());
            if i == j || j == k || i == k {
                return None;
            }
            plane_through(pts[i], pts[j], pts[k])
        })
        .collect();
    let best = best_sample(&samples, &pts, tolerance, min_cells);
    let Some((mut plane, _)) = best else {
        return Err(format!(
            "no flat region covers {:.0} % of the measured area",
            MIN_SUPPORT * 100.0
        ));
    };
    // Least squares on the inliers, twice: the sample's three cells carry their noise.
    for _ in 0..3 {
        let inliers = pts
            .iter()
            .filter(|c| residual(&plane, c).abs() <= tolerance)
            .map(|c| (c.x, c.y, c.z));
        match fit_plane(inliers) {
            Some(p) => plane = p,
            None => break,
        }
    }
    let below = pts
        .iter()
        .filter(|c| residual(&plane, c) < -3.0 * tolerance)
        .count();
    if below as f64 > MAX_BELOW * n as f64 {
        return Err(format!(
            "no flat region lies below the rest: the lowest candidate leaves {:.0} % of the \
             measured area more than {:.2} µm below it",
            100.0 * below as f64 / n as f64,
            3.0 * tolerance
        ));
    }
    Ok(Support { plane, tolerance })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A support leaning in the frame (offset 4 µm, 0.01 and −0.02 µm per pixel) with a
    /// 3 µm spherical cap on it, slight noise and a band of unknown heights.
    fn support_with_bump(w: usize, h: usize) -> Image {
        let mut seed = 7u32;
        Image::from_fn(w, h, |x, y| {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let noise = (f64::from(seed >> 8) / f64::from(1u32 << 24) - 0.5) * 0.02;
            if y < 5 {
                return f32::NAN;
            }
            let support = 4.0 + 0.01 * x as f64 - 0.02 * y as f64;
            let (dx, dy) = (x as f64 - 100.0, y as f64 - 75.0);
            let r2 = dx * dx + dy * dy;
            let bump = if r2 < 45.0 * 45.0 {
                3.0 * (1.0 - r2 / (45.0 * 45.0))
            } else {
                0.0
            };
            (support + bump + noise) as f32
        })
    }

    #[test]
    fn the_support_is_zero_and_a_bump_keeps_its_height() {
        let mut map = support_with_bump(200, 150);
        let datum = apply_datum(&mut map, DatumKind::Support, 0.1);
        assert_eq!(datum.kind, DatumKind::Support);
        assert!(datum.fallback.is_none());
        for (x, y) in [(10, 140), (190, 10), (5, 80), (195, 145)] {
            assert!(
                map.get(x, y).abs() < 0.03,
                "support at ({x}, {y}): {}",
                map.get(x, y)
            );
        }
        assert!(
            (map.get(100, 75) - 3.0).abs() < 0.03,
            "bump top {}",
            map.get(100, 75)
        );
        assert!(map.get(100, 2).is_nan(), "unknown stays unknown");
        assert!((datum.plane_um[1] - 0.01).abs() < 1e-3 && (datum.plane_um[2] + 0.02).abs() < 1e-3);
        let expect = (0.01f64.hypot(0.02) / 0.1).atan().to_degrees();
        assert!(
            (datum.plane_inclination_deg - expect).abs() < 0.1,
            "{datum:?}"
        );
        assert!(datum.support_fraction.unwrap() > 0.6, "{datum:?}");
        assert!(datum.below_fraction.unwrap() < 0.01, "{datum:?}");
    }

    /// A raised plateau larger than the visible support is not taken for it: the support
    /// is the lowest large region.
    #[test]
    fn the_lowest_large_region_wins_over_a_larger_plateau() {
        let mut map = Image::from_fn(160, 120, |x, y| {
            let base = 1.0 + 0.005 * y as f64;
            (if x >= 56 { base + 5.0 } else { base }) as f32
        });
        apply_datum(&mut map, DatumKind::Support, 0.1);
        assert!(map.get(10, 60).abs() < 1e-3, "{}", map.get(10, 60));
        assert!(
            (map.get(120, 60) - 5.0).abs() < 1e-3,
            "{}",
            map.get(120, 60)
        );
    }

    /// A cap filling most of the frame (as the simulator's dome does at 1280×960): the
    /// support shows only in the four corners, ~10 % of the map in separate patches.
    #[test]
    fn a_support_seen_only_in_the_corners_is_found() {
        let mut seed = 11u32;
        let mut map = Image::from_fn(256, 192, |x, y| {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let noise = (f64::from(seed >> 8) / f64::from(1u32 << 24) - 0.5) * 0.02;
            let support = -18.0 + 0.004 * x as f64 - 0.003 * y as f64;
            let r2 = (x as f64 - 128.0).powi(2) + (y as f64 - 96.0).powi(2);
            let cap = 25.0 * (1.0 - r2 / (128.0 * 128.0));
            (support + cap.max(0.0) + noise) as f32
        });
        let datum = apply_datum(&mut map, DatumKind::Support, 0.1);
        assert_eq!(datum.kind, DatumKind::Support, "{datum:?}");
        for (x, y) in [(2, 2), (253, 2), (2, 189), (253, 189)] {
            assert!(
                map.get(x, y).abs() < 0.05,
                "corner ({x}, {y}): {}",
                map.get(x, y)
            );
        }
        assert!(
            (map.get(128, 96) - 25.0).abs() < 0.05,
            "top {}",
            map.get(128, 96)
        );
        assert!(datum.below_fraction.unwrap() < 0.01, "{datum:?}");
    }

    /// Where the only flat region has most of the map far below it (a rough floor with no
    /// flat part), it is not taken for the support: the mean plane is used, and why is said.
    #[test]
    fn a_plane_with_most_of_the_map_below_it_is_no_support() {
        let mut map = Image::from_fn(160, 120, |x, y| {
            if x < 56 {
                return (2.0 + 0.002 * y as f64) as f32;
            }
            // 8-pixel blocks at pseudo-random depths 3–8 µm below: no plane holds 5 % of them.
            let mut h =
                (((x / 8) as u64) << 32 | (y / 8) as u64).wrapping_add(0x9E37_79B9_7F4A_7C15);
            h = (h ^ (h >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            let r = ((h ^ (h >> 31)) >> 40) as f64 / f64::from(1u32 << 24);
            (-1.0 - 5.0 * r) as f32
        });
        let datum = apply_datum(&mut map, DatumKind::Support, 0.1);
        assert_eq!(
            (datum.requested, datum.kind),
            (DatumKind::Support, DatumKind::MeanPlane),
            "{datum:?}"
        );
        assert!(
            datum
                .fallback
                .as_deref()
                .unwrap()
                .contains("below the rest"),
            "{datum:?}"
        );
    }

    #[test]
    fn mean_plane_and_none() {
        let original = support_with_bump(200, 150);
        let mut none = original.clone();
        let datum = apply_datum(&mut none, DatumKind::None, 0.1);
        assert_eq!(datum.kind, DatumKind::None);
        let bits = |m: &Image| m.data().iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&none), bits(&original));
        let mut mean = original;
        let datum = apply_datum(&mut mean, DatumKind::MeanPlane, 0.1);
        assert_eq!(datum.kind, DatumKind::MeanPlane);
        let finite: Vec<f64> = mean
            .data()
            .iter()
            .filter(|v| v.is_finite())
            .map(|&v| f64::from(v))
            .collect();
        let avg = finite.iter().sum::<f64>() / finite.len() as f64;
        assert!(avg.abs() < 1e-3, "mean {avg}");
        // The bump lifts the mean plane: the support reads below zero.
        assert!(mean.get(10, 140) < -0.1, "{}", mean.get(10, 140));
    }

    #[test]
    fn too_few_heights_fall_back_to_the_mean_plane_and_say_why() {
        let mut map = Image::from_fn(40, 30, |x, y| if x < 2 && y < 10 { 1.0 } else { f32::NAN });
        let datum = apply_datum(&mut map, DatumKind::Support, 0.1);
        assert_eq!(
            (datum.requested, datum.kind),
            (DatumKind::Support, DatumKind::MeanPlane)
        );
        assert!(datum.fallback.unwrap().contains("too few"), "fallback");
        let mut empty = Image::filled(8, 8, f32::NAN);
        let datum = apply_datum(&mut empty, DatumKind::Support, 0.1);
        assert_eq!(datum.kind, DatumKind::None);
    }

    /// The parallel block medians and RANSAC scores equal a serial loop's, to the bit.
    #[test]
    fn parallel_support_search_equals_the_serial_loop() {
        let map = support_with_bump(333, 211);
        let (w, h) = map.dimensions();
        let (cells, gw, gh) = block_medians(&map);
        let b = w.max(h).div_ceil(GRID);
        let mut serial = Vec::new();
        for gy in 0..gh {
            for gx in 0..gw {
                let (x0, y0) = (gx * b, gy * b);
                let (x1, y1) = ((x0 + b).min(w), (y0 + b).min(h));
                let mut z: Vec<f64> = (y0..y1)
                    .flat_map(|y| (x0..x1).map(move |x| (x, y)))
                    .map(|(x, y)| f64::from(map.get(x, y)))
                    .filter(|v| v.is_finite())
                    .collect();
                let enough = 2 * z.len() >= (x1 - x0) * (y1 - y0) && !z.is_empty();
                serial.push(enough.then(|| (x0 + x1 - 1, y0 + y1 - 1, median(&mut z).unwrap())));
            }
        }
        let got: Vec<_> = cells
            .iter()
            .map(|c| c.map(|c| ((2.0 * c.x) as usize, (2.0 * c.y) as usize, c.z)))
            .collect();
        assert_eq!(got.len(), gw * gh);
        assert_eq!(got, serial);

        let pts: Vec<Cell> = cells.iter().flatten().copied().collect();
        let mut samples = Vec::new();
        for i in 0..300 {
            let (a, b, c) = (
                pts[i * 7 % pts.len()],
                pts[i * 13 % pts.len()],
                pts[i * 29 % pts.len()],
            );
            samples.extend(plane_through(a, b, c));
        }
        let (tolerance, min_cells) = (0.05, 10);
        let mut best: Option<([f64; 3], f64)> = None;
        for plane in &samples {
            let (mut on, mut below) = (0usize, 0usize);
            for c in &pts {
                let r = residual(plane, c);
                if r.abs() <= tolerance {
                    on += 1;
                } else if r < -3.0 * tolerance {
                    below += 1;
                }
            }
            let score = on as f64 - BELOW_PENALTY * below as f64;
            if on >= min_cells && best.is_none_or(|(_, s)| score > s) {
                best = Some((*plane, score));
            }
        }
        assert!(best.is_some());
        assert_eq!(best_sample(&samples, &pts, tolerance, min_cells), best);
    }

    #[test]
    fn names_read_back_from_the_configuration() {
        for kind in [DatumKind::Support, DatumKind::MeanPlane, DatumKind::None] {
            let v = serde_json::to_value(kind).unwrap();
            assert_eq!(v, kind.name());
            assert_eq!(serde_json::from_value::<DatumKind>(v).unwrap(), kind);
        }
    }
}
