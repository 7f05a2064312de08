//! Rectification from what the instrument knows (issue 33): when the sparse stage cannot
//! establish the epipolar geometry (too few matches on a featureless or repetitive specimen),
//! the eucentric tilt under parallel projection (SEM) gives it instead.
//!
//! # Model
//! Tilting the stage about its axis `a = (cos φ, sin φ)` (DESIGN §3) moves every specimen point
//! along the axis normal `n = (−sin φ, cos φ)` only: its coordinate along `a` is the same in both
//! micrographs, up to what the stage and the scan add between the shots — a translation
//! (eucentric walk, drift), a small in-plane rotation and a magnification change. So both
//! images are turned by the same rotation `R` that takes `n` to +x (rows along the tilt axis,
//! parallax along the rows, disparity growing with height as on the sparse stage's canvas), and
//! the right image is then mapped by the similarity `S` whose second row makes its rows those of
//! the left: `y_left = e₁ x + e₂ y + e₀` in the right's turned coordinates.
//!
//! # Measuring `S`
//! Phase correlation (Kuglin & Hines 1975) of the whole, downsampled pair gives the global
//! shift; then each tile of a grid is correlated with its shifted counterpart. A tile's shift
//! along `a` is free of parallax, so the tiles and whatever sparse matches exist measure the
//! row offset at many places; a trimmed least-squares fit gives `e₀, e₁, e₂`. The rows'
//! residual after the fit verifies the model: a wrong tilt axis puts parallax into the rows and
//! is refused, as is a pair that does not correlate. After the dense stage, its vertical flow
//! on this canvas is the second check ([`verify_dense_rows`]).

use nalgebra::{Matrix3, Vector2, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::vision::Image;
use crate::vision::dense::support::Unknown;
use crate::vision::registration::{PhaseCorrelationParams, RegistrationError, phase_correlation};
use crate::vision::sparse::Correspondence;

/// Parameters of the rectification from the instrument's geometry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InstrumentParams {
    /// Rectify from the tilt axis when the sparse stage cannot establish the epipolar geometry
    /// (default true); false: such a pair is refused.
    pub enabled: bool,
    /// Side of the square tiles whose shift is measured by phase correlation, pixels
    /// (default 128; smaller images use half their smaller side).
    pub tile_px: usize,
    /// Smallest correlation peak over the mean absolute correlation for a tile to count
    /// (default 8, as the tracking's registration).
    pub min_peak_ratio: f64,
    /// Fewest tiles and matches that must agree on the rows (default 6).
    pub min_measurements: usize,
    /// Smallest fraction of the correlated tiles that must agree on the rows (default 0.6): with a
    /// wrong tilt axis the relief moves tiles off the rows, and only the flat ones would agree.
    pub min_agreeing_fraction: f64,
    /// Largest in-plane rotation between the shots, degrees (default 5).
    pub max_rotation_deg: f64,
    /// Largest relative magnification change between the shots (default 0.03).
    pub max_scale_change: f64,
    /// Largest RMS vertical residual of the agreeing tiles and matches after rectification,
    /// pixels (default 0.75; 0.35 on the simulator's noisy metal at 512×384, where the fit of
    /// its 25 measurements is good to a tenth of that).
    pub max_row_residual_px: f64,
    /// Largest systematic vertical flow (offset, rotation, magnification; [`dense_rows`]) the
    /// dense stage may find on this canvas, at the corners of its measured area, pixels
    /// (default 0.75, the sparse stage's limit on its rows' uncertainty at the corners; on the
    /// simulated scenes the instrument's rows read 0.04–0.55 px there).
    pub max_dense_row_offset_px: f64,
    /// Largest tilt-axis error the dense stage's vertical flow may show, degrees (default 3),
    /// judged only where its leak moves rows by more than `max_dense_row_offset_px`
    /// ([`DenseRows::leak_px`]): on a low relief the slope is not determined.
    pub max_dense_axis_error_deg: f64,
    /// A sparse geometry whose canvas leaves the correlated tiles' rows more than this far
    /// apart (median, pixels) is taken for a wrong one and replaced by the instrument's
    /// (default 0 = never check: the check costs ~0.1–0.2 s a pair, and no simulated scene has
    /// needed it — the calibration grid's wrong scale comes from the dense stage, it is the
    /// same on the exact rectification).
    pub max_sparse_row_offset_px: f64,
}

impl Default for InstrumentParams {
    fn default() -> Self {
        Self {
            enabled: true,
            tile_px: 128,
            min_peak_ratio: 8.0,
            min_measurements: 6,
            min_agreeing_fraction: 0.6,
            max_rotation_deg: 5.0,
            max_scale_change: 0.03,
            max_row_residual_px: 0.75,
            max_dense_row_offset_px: 0.75,
            max_dense_axis_error_deg: 3.0,
            max_sparse_row_offset_px: 0.0,
        }
    }
}

/// Why the instrument's geometry cannot rectify the pair.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum InstrumentError {
    #[error("the micrographs do not correlate as a whole: {0}")]
    NoCorrelation(RegistrationError),
    #[error(
        "too few places measure the rows: {found} tiles or matches agree, need {need} (the micrographs show too little texture)"
    )]
    TooFewMeasurements { found: usize, need: usize },
    #[error(
        "rows along the tilt axis φ = {tilt_axis_deg:.1}° do not align: {what} = {value:.3} exceeds {limit:.3} — check the tilt axis (--tilt-axis DEG, or reconstruction.tilt_axis_deg)"
    )]
    Rows {
        tilt_axis_deg: f64,
        what: &'static str,
        value: f64,
        limit: f64,
    },
}

/// What the instrument's rectification measured, for report.json.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct InstrumentFigures {
    /// Shift of the right micrograph's content relative to the left's, pixels, and the
    /// distinctness of that correlation peak.
    pub global_shift_px: [f64; 2],
    pub global_peak_ratio: f64,
    /// Tiles correlated, and those with a distinct peak.
    pub tiles: usize,
    pub tiles_measured: usize,
    /// Sparse matches offered to the fit.
    pub matches_offered: usize,
    /// Tiles and matches that agree on the rows (the fit's inliers).
    pub tiles_agreeing: usize,
    pub matches_agreeing: usize,
    /// In-plane rotation (degrees) and magnification of the right micrograph relative to the left.
    pub rotation_deg: f64,
    pub scale: f64,
    /// RMS vertical residual of the agreeing tiles and matches on the canvas, pixels.
    pub row_residual_rms_px: f64,
    /// The dense stage's check of the rows (after it ran; `None` with too few measured pixels).
    pub dense_rows: Option<DenseRows>,
}

/// The rectification from the instrument's geometry.
#[derive(Debug, Clone, PartialEq)]
pub struct InstrumentRectification {
    /// Original left/right pixel → canvas pixel; rows correspond, parallax along +x.
    pub h_left: Matrix3<f64>,
    pub h_right: Matrix3<f64>,
    pub canvas: (usize, usize),
    /// 1st and 99th percentile of the agreeing measurements' disparity on the canvas; `None`
    /// with fewer than 8.
    pub disparity_range: Option<(f64, f64)>,
    /// The tiles (centres) and matches that agree on the rows, original pixels.
    pub agreeing: Vec<Correspondence>,
    pub figures: InstrumentFigures,
}

/// One place where the row offset is measured: a point of the left micrograph and where it
/// lies in the right one (original pixels).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RowMeasurement {
    pub left: Vector2<f64>,
    pub right: Vector2<f64>,
    /// A tile's correlation (true) or a sparse match (false).
    pub tile: bool,
}

/// The rotation that takes the tilt-axis normal `n = (−sin φ, cos φ)` to +x (proper, no
/// mirror): `x' = n·p`, `y' = (−n_y, n_x)·p`.
#[must_use]
pub fn parallax_to_rows(tilt_axis_deg: f64) -> Matrix3<f64> {
    let phi = tilt_axis_deg.to_radians();
    let (nx, ny) = (-phi.sin(), phi.cos());
    Matrix3::new(nx, ny, 0.0, -ny, nx, 0.0, 0.0, 0.0, 1.0)
}

/// Images larger than this many pixels are halved for the global correlation.
const GLOBAL_MAX_PIXELS: usize = 1 << 20;
/// Smallest tile side, pixels.
const MIN_TILE: usize = 32;

/// The pair's correlation, as a whole and tile by tile.
#[derive(Debug, Clone, PartialEq)]
pub struct TileMeasurements {
    /// The tiles with a distinct peak: centre in the left micrograph, and where it lies in the
    /// right one.
    pub measured: Vec<RowMeasurement>,
    /// Tiles correlated.
    pub tiles: usize,
    /// Shift of the right micrograph's content relative to the left's, pixels, and its peak ratio.
    pub global_shift_px: [f64; 2],
    pub global_peak_ratio: f64,
}

/// The shift of the right micrograph relative to the left as a whole (on a copy halved to at
/// most a megapixel), then of each tile of a grid against its shifted counterpart.
///
/// # Errors
/// [`InstrumentError::NoCorrelation`] when the pair has no distinct global correlation peak.
pub fn tile_measurements(
    left: &Image,
    right: &Image,
    params: &InstrumentParams,
) -> Result<TileMeasurements, InstrumentError> {
    let (mut l, mut r, mut k) = (left.clone(), right.clone(), 1.0);
    while l.len() > GLOBAL_MAX_PIXELS && l.width().min(l.height()) >= 4 * MIN_TILE {
        l = crate::vision::sparse::halve(&l);
        r = crate::vision::sparse::halve(&r);
        k *= 2.0;
    }
    let global = phase_correlation(&l, &r, &PhaseCorrelationParams::default())
        .map_err(InstrumentError::NoCorrelation)?;
    drop((l, r));
    // Pixel i of a halved copy is centred on k·i + (k − 1)/2: shifts scale by k.
    let (gx, gy) = (global.dx * k, global.dy * k);
    let (w, h) = left.dimensions();
    let t = params.tile_px.min(w.min(h) / 2).max(MIN_TILE).min(w.min(h));
    let (nx, ny) = ((w / t).max(1), (h / t).max(1));
    let (mx, my) = ((w - nx * t) / 2, (h - ny * t) / 2);
    #[allow(clippy::cast_possible_truncation)]
    let (ox, oy) = (gx.round() as isize, gy.round() as isize);
    let corr = PhaseCorrelationParams {
        max_shift_fraction: 0.4,
        min_peak_ratio: params.min_peak_ratio,
    };
    let tiles: Vec<(usize, usize)> = (0..ny)
        .flat_map(|j| (0..nx).map(move |i| (mx + i * t, my + j * t)))
        .collect();
    let measured: Vec<RowMeasurement> = tiles
        .par_iter()
        .filter_map(|&(x0, y0)| {
            let (rx, ry) = (x0 as isize + ox, y0 as isize + oy);
            if rx < 0 || ry < 0 || rx as usize + t > w || ry as usize + t > h {
                return None;
            }
            let (rx, ry) = (rx as usize, ry as usize);
            let a = Image::from_fn(t, t, |x, y| left.get(x0 + x, y0 + y));
            let b = Image::from_fn(t, t, |x, y| right.get(rx + x, ry + y));
            let s = phase_correlation(&a, &b, &corr).ok()?;
            let c = (t as f64 - 1.0) / 2.0;
            let p = Vector2::new(x0 as f64 + c, y0 as f64 + c);
            Some(RowMeasurement {
                left: p,
                right: p + Vector2::new(ox as f64 + s.dx, oy as f64 + s.dy),
                tile: true,
            })
        })
        .collect();
    Ok(TileMeasurements {
        measured,
        tiles: tiles.len(),
        global_shift_px: [gx, gy],
        global_peak_ratio: global.peak_ratio,
    })
}

/// The row map `y_left = e₁ x + e₂ y + e₀` (right's turned coordinates) fitted to the
/// measurements by trimmed least squares, and which measurements agree with it.
#[derive(Debug, Clone, PartialEq)]
struct RowFit {
    e: [f64; 3],
    agreeing: Vec<bool>,
    rms: f64,
}

/// Fits the rows: from the median offset, five rounds of least squares on the measurements
/// within `clamp(3σ, 0.5, 2)` px of the current fit (σ from the median absolute residual).
fn fit_rows(points: &[(Vector2<f64>, Vector2<f64>)]) -> Option<RowFit> {
    if points.is_empty() {
        return None;
    }
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let mut e = [
        0.0,
        1.0,
        median(points.iter().map(|(l, r)| l.y - r.y).collect()),
    ];
    let residual = |e: &[f64; 3], (l, r): &(Vector2<f64>, Vector2<f64>)| {
        l.y - (e[0] * r.x + e[1] * r.y + e[2])
    };
    let mut agreeing = vec![true; points.len()];
    for _ in 0..5 {
        let res: Vec<f64> = points.iter().map(|p| residual(&e, p)).collect();
        let sigma = 1.4826 * median(res.iter().map(|r| r.abs()).collect());
        let limit = (3.0 * sigma).clamp(0.5, 2.0);
        agreeing = res.iter().map(|r| r.abs() <= limit).collect();
        let kept: Vec<&(Vector2<f64>, Vector2<f64>)> = points
            .iter()
            .zip(&agreeing)
            .filter_map(|(p, a)| a.then_some(p))
            .collect();
        // Least squares in coordinates centred on the kept points (conditioning).
        let n = kept.len() as f64;
        if kept.len() < 3 {
            break;
        }
        let c = kept.iter().map(|(_, r)| r).sum::<Vector2<f64>>() / n;
        let cy = kept.iter().map(|(l, _)| l.y).sum::<f64>() / n;
        let mut m = nalgebra::Matrix2::zeros();
        let mut b = Vector2::zeros();
        for (l, r) in &kept {
            let d = r - c;
            m += d * d.transpose();
            b += d * (l.y - cy);
        }
        let Some(mi) = m.try_inverse() else { break };
        let s = mi * b;
        e = [s.x, s.y, cy - s.x * c.x - s.y * c.y];
    }
    let res: Vec<f64> = points.iter().map(|p| residual(&e, p)).collect();
    let kept: Vec<f64> = res
        .iter()
        .zip(&agreeing)
        .filter_map(|(r, a)| a.then_some(*r))
        .collect();
    let rms = (kept.iter().map(|r| r * r).sum::<f64>() / kept.len().max(1) as f64).sqrt();
    Some(RowFit { e, agreeing, rms })
}

fn check(
    tilt_axis_deg: f64,
    what: &'static str,
    value: f64,
    limit: f64,
) -> Result<(), InstrumentError> {
    if value <= limit && value.is_finite() {
        Ok(())
    } else {
        Err(InstrumentError::Rows {
            tilt_axis_deg,
            what,
            value,
            limit,
        })
    }
}

/// Rectifies the pair (samples in `[0, 1]`, left = lower tilt) from the tilt axis φ: both turned
/// so that the parallax runs along +x, the right one then mapped onto the left's rows by the
/// similarity the tiles' correlations and the `matches` (original pixels, any quality) agree on.
///
/// # Errors
/// [`InstrumentError`]: no global correlation, too few agreeing tiles and matches, or rows that
/// the fit cannot align (rotation, magnification or residual beyond their limits; most often a
/// wrong tilt axis).
pub fn instrument_rectification(
    left: &Image,
    right: &Image,
    tilt_axis_deg: f64,
    matches: &[Correspondence],
    params: &InstrumentParams,
) -> Result<InstrumentRectification, InstrumentError> {
    let TileMeasurements {
        measured: tiles,
        tiles: n_tiles,
        global_shift_px,
        global_peak_ratio,
    } = tile_measurements(left, right, params)?;
    let v = |p: [f64; 2]| Vector2::new(p[0], p[1]);
    let measurements: Vec<RowMeasurement> = tiles
        .iter()
        .copied()
        .chain(matches.iter().map(|c| RowMeasurement {
            left: v(c.left),
            right: v(c.right),
            tile: false,
        }))
        .collect();
    let rot = parallax_to_rows(tilt_axis_deg);
    let turn = |p: &Vector2<f64>| {
        let q = rot * Vector3::new(p.x, p.y, 1.0);
        Vector2::new(q.x, q.y)
    };
    let turned: Vec<(Vector2<f64>, Vector2<f64>)> = measurements
        .iter()
        .map(|m| (turn(&m.left), turn(&m.right)))
        .collect();
    let agree = |fit: &RowFit, tile: bool| {
        measurements
            .iter()
            .zip(&fit.agreeing)
            .filter(|(m, a)| **a && m.tile == tile)
            .count()
    };
    let fit = fit_rows(&turned).ok_or(InstrumentError::TooFewMeasurements {
        found: 0,
        need: params.min_measurements,
    })?;
    let (tiles_agreeing, matches_agreeing) = (agree(&fit, true), agree(&fit, false));
    if tiles_agreeing + matches_agreeing < params.min_measurements.max(3) {
        return Err(InstrumentError::TooFewMeasurements {
            found: tiles_agreeing + matches_agreeing,
            need: params.min_measurements.max(3),
        });
    }
    let [e1, e2, e0] = fit.e;
    let phi = tilt_axis_deg;
    if !tiles.is_empty() {
        check(
            phi,
            "fraction of the correlated tiles off the rows",
            1.0 - tiles_agreeing as f64 / tiles.len() as f64,
            1.0 - params.min_agreeing_fraction,
        )?;
    }
    // The similarity [[e₂, −e₁], [e₁, e₂]] undoes the right shot's turn by atan2(−e₁, e₂) and
    // its magnification 1 / |(e₁, e₂)|.
    let rotation_deg = (-e1).atan2(e2).to_degrees();
    let scale = 1.0 / e1.hypot(e2);
    check(
        phi,
        "in-plane rotation between the shots (°)",
        rotation_deg.abs(),
        params.max_rotation_deg,
    )?;
    check(
        phi,
        "magnification change between the shots",
        (scale - 1.0).abs(),
        params.max_scale_change,
    )?;
    check(
        phi,
        "RMS vertical residual of the rows (px)",
        fit.rms,
        params.max_row_residual_px,
    )?;

    // Disparities of the agreeing measurements; the right image shifted along the rows so
    // that their median is 0, as on the sparse stage's canvas.
    let s0 = Matrix3::new(e2, -e1, 0.0, e1, e2, e0, 0.0, 0.0, 1.0) * rot;
    let map = |hm: &Matrix3<f64>, p: &Vector2<f64>| {
        let q = hm * Vector3::new(p.x, p.y, 1.0);
        Vector2::new(q.x / q.z, q.y / q.z)
    };
    let mut d: Vec<f64> = measurements
        .iter()
        .zip(&fit.agreeing)
        .filter(|(_, a)| **a)
        .map(|(m, _)| map(&s0, &m.right).x - map(&rot, &m.left).x)
        .collect();
    d.sort_by(f64::total_cmp);
    let median_d = d[d.len() / 2];
    let hr0 = Matrix3::new(1.0, 0.0, -median_d, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0) * s0;
    let at = |q: f64| d[((d.len() - 1) as f64 * q).round() as usize] - median_d;
    let disparity_range = (d.len() >= 8).then(|| (at(0.01), at(0.99)));

    // Canvas: the bounding box of both turned images.
    let (w, h) = left.dimensions();
    let (wm, hm) = (w as f64 - 1.0, h as f64 - 1.0);
    let corners = [(0.0, 0.0), (wm, 0.0), (0.0, hm), (wm, hm)].map(|(x, y)| Vector2::new(x, y));
    let (mut lo, mut hi) = (
        Vector2::repeat(f64::INFINITY),
        Vector2::repeat(f64::NEG_INFINITY),
    );
    for hmat in [&rot, &hr0] {
        for c in &corners {
            let p = map(hmat, c);
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
    }
    // Snap rounding of axis-aligned turns so no column is lost.
    let snap = |v: f64| {
        if (v - v.round()).abs() < 1e-9 {
            v.round()
        } else {
            v
        }
    };
    let (lx, ly) = (snap(lo.x).floor(), snap(lo.y).floor());
    let t = Matrix3::new(1.0, 0.0, -lx, 0.0, 1.0, -ly, 0.0, 0.0, 1.0);
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let canvas = (
        (snap(hi.x) - lx).floor() as usize + 1,
        (snap(hi.y) - ly).floor() as usize + 1,
    );
    Ok(InstrumentRectification {
        h_left: t * rot,
        h_right: t * hr0,
        canvas,
        disparity_range,
        agreeing: measurements
            .iter()
            .zip(&fit.agreeing)
            .filter(|(_, a)| **a)
            .map(|(m, _)| Correspondence {
                left: [m.left.x, m.left.y],
                right: [m.right.x, m.right.y],
            })
            .collect(),
        figures: InstrumentFigures {
            global_shift_px,
            global_peak_ratio,
            tiles: n_tiles,
            tiles_measured: tiles.len(),
            matches_offered: matches.len(),
            tiles_agreeing,
            matches_agreeing,
            rotation_deg,
            scale,
            row_residual_rms_px: fit.rms,
            dense_rows: None,
        },
    })
}

/// The median |vertical offset| of `measurements` on a canvas given by `h_left`, `h_right`:
/// how far a (sparse) rectification leaves the correlated tiles' rows apart. `None` without
/// measurements.
#[must_use]
pub fn median_row_offset(
    measurements: &[RowMeasurement],
    h_left: &Matrix3<f64>,
    h_right: &Matrix3<f64>,
) -> Option<f64> {
    let y = |hm: &Matrix3<f64>, p: &Vector2<f64>| {
        let q = hm * Vector3::new(p.x, p.y, 1.0);
        q.y / q.z
    };
    let mut dy: Vec<f64> = measurements
        .iter()
        .map(|m| (y(h_right, &m.right) - y(h_left, &m.left)).abs())
        .filter(|v| v.is_finite())
        .collect();
    if dy.is_empty() {
        return None;
    }
    dy.sort_by(f64::total_cmp);
    Some(dy[dy.len() / 2])
}

/// What the dense stage's vertical flow says of the instrument's rows: the systematic part of
/// `v = a + b·x + c·y + k·d` fitted at its measured pixels ([`Unknown::Measured`]) by trimmed
/// least squares — a row offset, rotation or magnification left by the rectification shows in
/// `a + b·x + c·y`, a tilt axis off by δ in `k = tan δ` (parallax leaking into the rows). Noise
/// (a featureless support where the flow wanders) averages out instead of failing the check.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DenseRows {
    /// Largest |a + b·x + c·y| at the corners of the measured area, pixels.
    pub offset_px: f64,
    /// `atan k`, degrees.
    pub axis_error_deg: f64,
    /// What that leak does to the rows: `|k|` times the farthest of the measured disparity's
    /// 1st and 99th percentiles from its median, pixels.
    #[serde(default)]
    pub leak_px: f64,
    /// How far the rows themselves move: the farthest of the 1st and 99th percentiles of
    /// `v − (a + b·x + c·y)` from its median, pixels (a tilt axis 90° off puts the whole
    /// parallax here while the measured disparity, and so `leak_px`, stays small).
    #[serde(default)]
    pub row_reach_px: f64,
}

/// Samples at most this many measured pixels for [`dense_rows`].
const DENSE_ROWS_SAMPLES: usize = 200_000;

/// [`DenseRows`] from the dense stage's vertical flow and disparity on the canvas; `None` with
/// fewer than 100 measured pixels or a degenerate fit.
#[must_use]
pub fn dense_rows(vertical: &Image, disparity: &Image, unknown: &[Unknown]) -> Option<DenseRows> {
    let (w, h) = vertical.dimensions();
    let n_measured = unknown.iter().filter(|u| **u == Unknown::Measured).count();
    let step = (n_measured / DENSE_ROWS_SAMPLES).max(1);
    let (sx, sy) = (w.max(2) as f64 / 2.0, h.max(2) as f64 / 2.0);
    // (x, y, d, v) with x, y scaled to [−1, 1].
    let samples: Vec<[f64; 4]> = (0..w * h)
        .filter(|&p| unknown.get(p) == Some(&Unknown::Measured))
        .step_by(step)
        .filter_map(|p| {
            let (v, d) = (vertical.data()[p], disparity.data()[p]);
            (v.is_finite() && d.is_finite()).then(|| {
                [
                    (p % w) as f64 / sx - 1.0,
                    (p / w) as f64 / sy - 1.0,
                    f64::from(d),
                    f64::from(v),
                ]
            })
        })
        .collect();
    fit_dense_rows(&samples)
}

/// [`DenseRows`] from samples `(x, y, disparity, vertical flow)` of measured pixels on a
/// `canvas`-sized canvas (a tiled dense stage keeps only these,
/// [`crate::vision::dense::tile::CanvasDisparity::row_samples`]); `None` as [`dense_rows`].
#[must_use]
pub fn dense_rows_of_samples(samples: &[[f32; 4]], canvas: (usize, usize)) -> Option<DenseRows> {
    let (sx, sy) = (canvas.0.max(2) as f64 / 2.0, canvas.1.max(2) as f64 / 2.0);
    let samples: Vec<[f64; 4]> = samples
        .iter()
        .filter(|s| s[2].is_finite() && s[3].is_finite())
        .map(|s| {
            [
                f64::from(s[0]) / sx - 1.0,
                f64::from(s[1]) / sy - 1.0,
                f64::from(s[2]),
                f64::from(s[3]),
            ]
        })
        .collect();
    fit_dense_rows(&samples)
}

/// The trimmed least-squares fit of [`DenseRows`] to samples `(x, y, d, v)`, `x, y` in `[−1, 1]`.
fn fit_dense_rows(samples: &[[f64; 4]]) -> Option<DenseRows> {
    if samples.len() < 100 {
        return None;
    }
    let d_mid = {
        let mut d: Vec<f64> = samples.iter().map(|s| s[2]).collect();
        let m = d.len() / 2;
        *d.select_nth_unstable_by(m, f64::total_cmp).1
    };
    let mut keep = vec![true; samples.len()];
    let mut coef = nalgebra::Vector4::zeros();
    for _ in 0..3 {
        let mut ata = nalgebra::Matrix4::<f64>::zeros();
        let mut atb = nalgebra::Vector4::<f64>::zeros();
        for (s, _) in samples.iter().zip(&keep).filter(|(_, k)| **k) {
            let row = nalgebra::Vector4::new(1.0, s[0], s[1], s[2] - d_mid);
            ata += row * row.transpose();
            atb += row * s[3];
        }
        coef = ata.try_inverse()? * atb;
        let res: Vec<f64> = samples
            .iter()
            .map(|s| {
                (s[3] - coef.dot(&nalgebra::Vector4::new(1.0, s[0], s[1], s[2] - d_mid))).abs()
            })
            .collect();
        let mut sorted = res.clone();
        let m = sorted.len() / 2;
        let mad = *sorted.select_nth_unstable_by(m, f64::total_cmp).1;
        let limit = (3.0 * 1.4826 * mad).max(0.5);
        keep = res.iter().map(|r| *r <= limit).collect();
    }
    // The farthest of the 1st and 99th percentiles from the median.
    let reach = |mut d: Vec<f64>| {
        let q = |d: &mut [f64], f: f64| {
            let i = ((d.len() - 1) as f64 * f).round() as usize;
            *d.select_nth_unstable_by(i, f64::total_cmp).1
        };
        let (lo, mid, hi) = (q(&mut d, 0.01), q(&mut d, 0.5), q(&mut d, 0.99));
        (mid - lo).abs().max((hi - mid).abs())
    };
    // The leak's reach: the measured disparities' spread.
    let d_reach = reach(samples.iter().map(|s| s[2]).collect());
    let row_reach_px = reach(
        samples
            .iter()
            .map(|s| s[3] - coef[0] - coef[1] * s[0] - coef[2] * s[1])
            .collect(),
    );
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for s in samples {
        for i in 0..2 {
            lo[i] = lo[i].min(s[i]);
            hi[i] = hi[i].max(s[i]);
        }
    }
    let offset_px = [
        (lo[0], lo[1]),
        (hi[0], lo[1]),
        (lo[0], hi[1]),
        (hi[0], hi[1]),
    ]
    .iter()
    .map(|(x, y)| (coef[0] + coef[1] * x + coef[2] * y).abs())
    .fold(0.0, f64::max);
    Some(DenseRows {
        offset_px,
        axis_error_deg: coef[3].atan().to_degrees(),
        leak_px: coef[3].abs() * d_reach,
        row_reach_px,
    })
}

/// The dense stage's check of the instrument's rows ([`dense_rows`]).
///
/// # Errors
/// [`InstrumentError::Rows`] when the systematic row offset exceeds
/// [`InstrumentParams::max_dense_row_offset_px`] or the parallax leaking into the rows shows a
/// tilt axis more than [`InstrumentParams::max_dense_axis_error_deg`] off.
pub fn verify_dense_rows(
    rows: &DenseRows,
    tilt_axis_deg: f64,
    params: &InstrumentParams,
) -> Result<(), InstrumentError> {
    check(
        tilt_axis_deg,
        "systematic vertical flow of the dense stage at the corners (px)",
        rows.offset_px,
        params.max_dense_row_offset_px,
    )?;
    // The axis is judged by what it does to the rows: on a low relief the leak's slope is not
    // determined (the calibration grid's 2.9 px: a few per cent of wrong matches at the
    // disparity's ends, whose vertical flow slides along the bars' edges, read 3–30°), and an
    // axis error that moves no row by more than the rows' own limit does not harm the matching.
    // Only when the rows themselves stay within it too: with the axis far off, the parallax is
    // in the rows and the measured disparity, hence the leak, is small.
    let limit = params.max_dense_row_offset_px;
    if rows.leak_px <= limit && rows.row_reach_px <= limit {
        return Ok(());
    }
    check(
        tilt_axis_deg,
        "tilt-axis error the dense stage's vertical flow shows (°)",
        rows.axis_error_deg.abs(),
        params.max_dense_axis_error_deg,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::vision::sparse::tests::sem_pair;

    /// Where `c.right` lands against `c.left` on the canvas: (disparity, vertical offset).
    fn on_canvas(r: &InstrumentRectification, c: &Correspondence) -> (f64, f64) {
        let map = |hm: &Matrix3<f64>, p: [f64; 2]| {
            let q = hm * Vector3::new(p[0], p[1], 1.0);
            (q.x / q.z, q.y / q.z)
        };
        let (a, b) = (map(&r.h_left, c.left), map(&r.h_right, c.right));
        (b.0 - a.0, b.1 - a.1)
    }

    #[test]
    fn the_turn_takes_the_parallax_direction_to_plus_x_without_a_mirror() {
        for phi in [-90.0f64, 0.0, 30.0, 135.0] {
            let r = parallax_to_rows(phi);
            let n = Vector3::new(-phi.to_radians().sin(), phi.to_radians().cos(), 0.0);
            let q = r * n;
            assert!((q.x - 1.0).abs() < 1e-12 && q.y.abs() < 1e-12, "φ {phi}");
            assert!((r.determinant() - 1.0).abs() < 1e-12);
        }
    }

    /// A simulated SEM pair (parallax along n, right shot turned by 0.7° and shifted): the
    /// rows of the true correspondences align within a tenth of a pixel, with no sparse match
    /// at all, and a raised point has the larger disparity.
    #[test]
    fn recovers_rotation_and_shift_of_a_known_pair() {
        for phi in [-90.0, 20.0] {
            let pair = sem_pair(320, 256, phi, (-4.0, 4.0), 0.7, false);
            let p = InstrumentParams {
                tile_px: 64,
                ..InstrumentParams::default()
            };
            let r = instrument_rectification(&pair.left, &pair.right, phi, &[], &p).unwrap();
            let f = r.figures;
            assert!(
                (f.rotation_deg - 0.7).abs() < 0.1,
                "φ {phi}: rotation {}",
                f.rotation_deg
            );
            assert!((f.scale - 1.0).abs() < 0.005, "φ {phi}: scale {}", f.scale);
            let mut dy: Vec<f64> = pair
                .truth
                .iter()
                .map(|c| on_canvas(&r, c).1.abs())
                .collect();
            dy.sort_by(f64::total_cmp);
            let (med, p95) = (dy[dy.len() / 2], dy[dy.len() * 95 / 100]);
            assert!(
                med < 0.1 && p95 < 0.3,
                "φ {phi}: |Δy| median {med}, p95 {p95}"
            );
            let near = |p: [f64; 2]| {
                pair.truth
                    .iter()
                    .min_by(|a, b| {
                        let da = (a.left[0] - p[0]).hypot(a.left[1] - p[1]);
                        let db = (b.left[0] - p[0]).hypot(b.left[1] - p[1]);
                        da.total_cmp(&db)
                    })
                    .copied()
                    .unwrap()
            };
            let (top, flat) = (
                on_canvas(&r, &near(pair.top)).0,
                on_canvas(&r, &near(pair.flat)).0,
            );
            assert!(
                top > flat + 2.0,
                "φ {phi}: disparity top {top}, flat {flat}"
            );
            // Every corner of both micrographs lies on the canvas.
            for hm in [&r.h_left, &r.h_right] {
                for (x, y) in [(0.0, 0.0), (319.0, 0.0), (0.0, 255.0), (319.0, 255.0)] {
                    let q = hm * Vector3::new(x, y, 1.0);
                    assert!(
                        q.x > -1e-6
                            && q.y > -1e-6
                            && q.x < r.canvas.0 as f64
                            && q.y < r.canvas.1 as f64,
                        "φ {phi}: corner at {q:?} off {:?}",
                        r.canvas
                    );
                }
            }
        }
    }

    /// The same pair with a tilt axis 90° off: the relief's parallax runs across the rows, and
    /// the residual refuses it, naming the tilt axis.
    #[test]
    fn a_wrong_tilt_axis_leaves_a_vertical_residual_and_is_refused() {
        let pair = sem_pair(320, 256, -90.0, (-10.0, 10.0), 0.0, false);
        let p = InstrumentParams {
            tile_px: 64,
            ..InstrumentParams::default()
        };
        assert!(instrument_rectification(&pair.left, &pair.right, -90.0, &[], &p).is_ok());
        let e = instrument_rectification(&pair.left, &pair.right, 0.0, &[], &p).unwrap_err();
        assert!(matches!(e, InstrumentError::Rows { .. }), "{e}");
        assert!(e.to_string().contains("check the tilt axis"), "{e}");
    }

    #[test]
    fn unrelated_or_blank_micrographs_are_refused() {
        let pair = sem_pair(256, 192, -90.0, (-3.0, 3.0), 0.0, false);
        let blank = Image::filled(256, 192, 0.4);
        let p = InstrumentParams::default();
        let e = instrument_rectification(&pair.left, &blank, -90.0, &[], &p).unwrap_err();
        assert!(matches!(e, InstrumentError::NoCorrelation(_)), "{e}");
        let other = sem_pair(256, 192, 0.0, (-3.0, 3.0), 0.0, true);
        assert!(instrument_rectification(&pair.left, &other.left, -90.0, &[], &p).is_err());
    }

    /// Wrong matches among right ones do not move the rows; a sparse canvas whose rows are off
    /// shows in the median row offset.
    #[test]
    fn matches_refine_the_rows_and_wrong_ones_are_left_out() {
        let pair = sem_pair(320, 256, -90.0, (-4.0, 4.0), 0.5, false);
        let mut matches: Vec<Correspondence> = pair.truth.iter().step_by(7).copied().collect();
        let good = matches.len();
        for c in pair.truth.iter().step_by(23).take(5) {
            matches.push(Correspondence {
                left: c.left,
                right: [c.right[0] + 3.0, c.right[1] + 9.0],
            });
        }
        let p = InstrumentParams {
            tile_px: 64,
            ..InstrumentParams::default()
        };
        let r = instrument_rectification(&pair.left, &pair.right, -90.0, &matches, &p).unwrap();
        assert!(r.figures.matches_agreeing >= good - 1 && r.figures.matches_agreeing <= good);
        let tiles = tile_measurements(&pair.left, &pair.right, &p)
            .unwrap()
            .measured;
        let off = median_row_offset(&tiles, &r.h_left, &r.h_right).unwrap();
        assert!(off < 0.2, "{off}");
        let shifted = Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 3.0, 0.0, 0.0, 1.0) * r.h_right;
        let off = median_row_offset(&tiles, &r.h_left, &shifted).unwrap();
        assert!((off - 3.0).abs() < 0.3, "{off}");
    }

    /// A vertical flow of noise plus a known offset, rotation and leak of the disparity: the
    /// fit recovers the systematic part, and the noise alone passes the check.
    #[test]
    fn the_dense_check_sees_systematic_rows_through_noise() {
        let (w, h) = (200, 100);
        // Disparities −5 … 5, median 0: the offset is read at the median disparity.
        let d = Image::from_fn(w, h, |x, y| ((x * 7 + y * 3) % 21) as f32 * 0.5 - 5.0);
        let noise = |x: usize, y: usize| (((x * 31 + y * 17) % 13) as f32 - 6.0) * 0.15;
        let u = vec![Unknown::Measured; w * h];
        let clean = Image::from_fn(w, h, noise);
        let r = dense_rows(&clean, &d, &u).unwrap();
        let p = InstrumentParams::default();
        assert!(verify_dense_rows(&r, 0.0, &p).is_ok(), "{r:?}");
        // 0.3 px offset, rows turned by 0.5 px over the width (0.8 px at a corner), 4° of
        // parallax leaking.
        let k = 4f32.to_radians().tan();
        let v = Image::from_fn(w, h, |x, y| {
            noise(x, y) + 0.3 + 0.5 * x as f32 / w as f32 + k * d.get(x, y)
        });
        let r = dense_rows(&v, &d, &u).unwrap();
        assert!((r.axis_error_deg - 4.0).abs() < 0.3, "{r:?}");
        assert!((r.offset_px - 0.8).abs() < 0.1, "{r:?}");
        assert!(verify_dense_rows(&r, 0.0, &p).is_err());
        assert!(dense_rows(&v, &d, &vec![Unknown::NoTexture; w * h]).is_none());
    }

    /// A low relief (disparities −1 … 1 px) without a leak, but with a few per cent of wrong
    /// matches at the disparity's ends whose vertical flow slid along an edge 15° off the rows
    /// (the calibration grid's bars): the fitted slope reads several degrees, yet it moves no
    /// row by more than the rows' limit, and the check passes. The same slope over ±20 px of
    /// relief fails it.
    #[test]
    fn the_dense_check_judges_the_axis_by_the_rows_it_moves() {
        let (w, h) = (200, 100);
        let slide = 15f32.to_radians().tan();
        let noise = |x: usize, y: usize| (((x * 31 + y * 17) % 13) as f32 - 6.0) * 0.05;
        let wrong = |x: usize, y: usize| (x * 13 + y * 7) % 100 < 4;
        let d = Image::from_fn(w, h, |x, y| {
            let d = ((x * 7 + y * 3) % 21) as f32 * 0.1 - 1.0;
            if wrong(x, y) { d.signum() * 2.5 } else { d }
        });
        let v = Image::from_fn(w, h, |x, y| {
            noise(x, y)
                + if wrong(x, y) {
                    slide * (d.get(x, y) - d.get(x, y).signum())
                } else {
                    0.0
                }
        });
        let u = vec![Unknown::Measured; w * h];
        let r = dense_rows(&v, &d, &u).unwrap();
        let p = InstrumentParams::default();
        assert!(r.axis_error_deg.abs() > p.max_dense_axis_error_deg, "{r:?}");
        assert!(r.leak_px < p.max_dense_row_offset_px, "{r:?}");
        assert!(verify_dense_rows(&r, 0.0, &p).is_ok(), "{r:?}");
        // A real leak of 4° over ±20 px of relief moves the extreme rows by 1.4 px.
        let k = 4f32.to_radians().tan();
        let d = Image::from_fn(w, h, |x, y| ((x * 7 + y * 3) % 21) as f32 * 2.0 - 20.0);
        let v = Image::from_fn(w, h, |x, y| noise(x, y) + k * d.get(x, y));
        let r = dense_rows(&v, &d, &u).unwrap();
        assert!((r.leak_px - 1.4).abs() < 0.1, "{r:?}");
        assert!(verify_dense_rows(&r, 0.0, &p).is_err());
        // An axis 90° off: the parallax (±6 px) is in the rows, the measured disparity is
        // noise with a faint trace of it; the slope reads degrees, the leak looks small, the
        // rows move by the whole parallax.
        let relief = |x: usize, y: usize| ((x * 7 + y * 3) % 21) as f32 * 0.6 - 6.0;
        let d = Image::from_fn(w, h, |x, y| noise(x, y) + 0.0005 * relief(x, y));
        let v = Image::from_fn(w, h, relief);
        let r = dense_rows(&v, &d, &u).unwrap();
        assert!(r.axis_error_deg.abs() > p.max_dense_axis_error_deg, "{r:?}");
        assert!(r.leak_px < p.max_dense_row_offset_px, "{r:?}");
        assert!(r.row_reach_px > 5.0, "{r:?}");
        assert!(verify_dense_rows(&r, 0.0, &p).is_err(), "{r:?}");
    }
}
