//! Slanted support for steep surfaces (beyond the paper): the flanks that fail the left–right
//! check are measured again with a window that follows a disparity plane.
//!
//! On a steep flank the disparity changes fast along the parallax: the right micrograph sees
//! the flank compressed or stretched by `1 + ∂d/∂x` against the left one, and a
//! fronto-parallel window (one disparity over the window, as in the intensity refinement)
//! matches it badly; both directions then disagree and the pixel is left unknown. Here every
//! such pixel `p = (x₀, y₀)` (reason [`Unknown::LeftRight`]) gets a disparity plane
//! `d(x₀ + δx, y₀ + δy) = d + a δx + b δy` (Bleyer et al. 2011, "PatchMatch stereo"; the
//! window of the right micrograph is the left one's under the affine map), found by
//! Gauss–Newton on the contrast-normalised micrographs over the matcher's Gaussian window,
//! coarse (pre-smoothed) then fine, from candidate planes: the line between the measured
//! pixels that bound the gap along its row and its column, the matcher's own field there, and
//! the planes of neighbours measured by an earlier pass (propagation). The plane is kept only
//! when
//! - its normalised cross-correlation over the window reaches `min_ncc`, with both slopes
//!   within `max_slope`;
//! - its disparity lies within what the measured pixels bounding the gap allow at that slope
//!   (`|d − d_end| ≤ max_slope · distance + lr_tolerance`): a match far off them is a
//!   mismatch, typically into what the other micrograph does not see;
//! - both directions agree within the stage's `lr_tolerance`: the right-to-left field at the
//!   match leads back to `p`, or else the plane fitted from the right micrograph's own window
//!   (started at the inverse plane, refined alone) does.
//!
//! Pixels in the strip the right micrograph never saw (left of where its first columns lead back
//! to by the right-to-left field, or where every disparity the measured ends allow lands before
//! its first column) are not tried: they become [`Unknown::NotSeen`].
//!
//! What passes is measured (reason [`Unknown::Measured`]), its confidence the NCC times the
//! agreement of both directions.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::support::Unknown;
use crate::vision::Image;
use crate::vision::filter::blur::normalise_contrast;

/// Parameters of the slanted support (`[reconstruction.dense.slanted]`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SlantedParams {
    /// Measure again, with slanted windows, the pixels that fail the left–right check (opt-in).
    pub enabled: bool,
    /// σ of the Gaussian window, pixels; 0: the matcher's own window.
    pub window_sigma: f32,
    /// Largest slope of the disparity plane, |∂d/∂x| and |∂d/∂y|, pixels per pixel.
    pub max_slope: f32,
    /// Least normalised cross-correlation of the slanted windows at the match.
    pub min_ncc: f32,
    /// Gauss–Newton steps per scale (coarse, then fine).
    pub iterations: usize,
    /// Passes over the pixels still unknown, each starting also from its neighbours' planes.
    pub passes: usize,
    /// Longest gap along a row or column whose measured ends give a starting plane, pixels.
    pub max_gap: usize,
    /// Re-measure bright, flat plateaus with windows that leave out their outline (opt-in;
    /// [`super::plateau`]).
    pub plateau: bool,
    /// Half-width of the plateau pass's box window, pixels.
    pub plateau_radius: usize,
    /// Largest gradient of a plateau pixel, per pixel, in the brightness range's units.
    pub plateau_max_gradient: f32,
    /// Disparities searched beyond the field's range over the plateaus, pixels.
    pub plateau_reach: f32,
    /// Least NCC of a plateau pixel's best match for it to take that disparity.
    pub plateau_min_ncc: f32,
    /// Bright pixels within this of a measured plateau pixel take the plateau's mean
    /// disparity there (its rim), pixels (0: none).
    pub plateau_rim_px: usize,
    /// With plateaus measured, leave the dark, flat pixels between them unknown (no texture).
    pub plateau_floor_unknown: bool,
    /// Least pixels of a connected plateau for it to be matched again.
    pub plateau_min_px: usize,
    /// Least |median| of the plateau's new disparities minus the matcher's for it to take them,
    /// pixels: where both agree the matcher saw the top, not its outline.
    pub plateau_min_shift_px: f32,
}

impl Default for SlantedParams {
    fn default() -> Self {
        Self {
            enabled: false,
            window_sigma: 0.0,
            max_slope: 0.8,
            min_ncc: 0.5,
            iterations: 6,
            passes: 2,
            max_gap: 128,
            plateau: false,
            plateau_radius: 16,
            plateau_max_gradient: 0.07,
            plateau_reach: 3.0,
            plateau_min_ncc: 0.2,
            plateau_rim_px: 5,
            plateau_floor_unknown: false,
            plateau_min_px: 1000,
            plateau_min_shift_px: 1.0,
        }
    }
}

impl SlantedParams {
    /// The name of the first field out of range.
    #[must_use]
    pub fn invalid_field(&self) -> Option<&'static str> {
        if !(self.window_sigma.is_finite()
            && (self.window_sigma == 0.0 || (1.0..=20.0).contains(&self.window_sigma)))
        {
            Some("slanted.window_sigma")
        } else if !(self.max_slope.is_finite() && (0.0..0.95).contains(&self.max_slope)) {
            Some("slanted.max_slope")
        } else if !(self.min_ncc.is_finite() && (0.0..=1.0).contains(&self.min_ncc)) {
            Some("slanted.min_ncc")
        } else if self.iterations > 50 {
            Some("slanted.iterations")
        } else if self.passes > 16 {
            Some("slanted.passes")
        } else if self.max_gap > 4096 {
            Some("slanted.max_gap")
        } else if !(1..=64).contains(&self.plateau_radius) {
            Some("slanted.plateau_radius")
        } else if !(self.plateau_max_gradient > 0.0 && self.plateau_max_gradient <= 1.0) {
            Some("slanted.plateau_max_gradient")
        } else if !(0.0..=32.0).contains(&self.plateau_reach) {
            Some("slanted.plateau_reach")
        } else if !(-1.0..=1.0).contains(&self.plateau_min_ncc) {
            Some("slanted.plateau_min_ncc")
        } else if self.plateau_rim_px > 32 {
            Some("slanted.plateau_rim_px")
        } else if !(self.plateau_min_shift_px.is_finite() && self.plateau_min_shift_px >= 0.0) {
            Some("slanted.plateau_min_shift_px")
        } else {
            None
        }
    }
}

/// What the slanted pass reads: the rectified pair with its valid pixels, and the dense stage's
/// fields on the left canvas.
struct Fields<'a> {
    vb: &'a [bool],
    /// The refined left-to-right disparity before the check masked it.
    start: &'a [f32],
    /// The vertical flow (the rectification's residual), kept as it is.
    v: &'a [f32],
    /// The right-to-left disparity on the right canvas, if matched both ways.
    backward: Option<&'a [f32]>,
    /// Per row, the first left column the right micrograph sees ([`first_seen_columns`]).
    first_seen: Vec<f32>,
}

/// How many of the right micrograph's first columns with data, per row, say where its edge lies
/// on the left canvas.
const EDGE_SAMPLES: usize = 16;

/// Per row, the first left column the right micrograph sees: the least left column that its
/// first [`EDGE_SAMPLES`] columns with data lead back to by the right-to-left field (the least,
/// so that a wrong backward match can only make the strip narrower); `−∞` where the row has no
/// such column. Left of it, a match that keeps the order along the row, as every plane with
/// `|∂d/∂x| < 1` does (`max_slope` < 0.95), lands before the right micrograph's first column.
pub(super) fn first_seen_columns(
    backward: &[f32],
    vb: &[bool],
    (w, h): (usize, usize),
) -> Vec<f32> {
    (0..h)
        .into_par_iter()
        .map(|y| {
            let row = y * w;
            (0..w)
                .filter(|&x| vb[row + x] && backward[row + x].is_finite())
                .take(EDGE_SAMPLES)
                .map(|x| x as f32 + backward[row + x])
                .fold(f32::INFINITY, f32::min)
        })
        .map(|e| if e.is_finite() { e } else { f32::NEG_INFINITY })
        .collect()
}

/// Figures of the slanted pass.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct SlantedStats {
    /// Pixels examined (those the left–right check rejected).
    pub examined: usize,
    /// Of those, pixels measured with a slanted window.
    pub measured: usize,
    /// Pixels given up, at their last pass, by the first test they failed (in the order of
    /// [`Fail`]).
    pub failed: [usize; Fail::COUNT],
}

/// Why a pixel was not measured: the first test it failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fail {
    /// No candidate plane kept enough of its window on data in both micrographs.
    NoCandidate,
    /// The window lost its data during the fit.
    Lost,
    /// After the coarse fit the windows hardly correlate (below `min_ncc` by a margin).
    CoarseNcc,
    /// After the coarse fit the disparity is far beyond what the measured ends allow.
    CoarseReach,
    /// The fine windows correlate less than `min_ncc`.
    Ncc,
    /// The disparity is beyond what the measured ends allow.
    Reach,
    /// A slope reached `max_slope`.
    Slope,
    /// Both directions disagree.
    LeftRight,
    /// Not tried again at a later pass (no neighbour measured at the last one).
    Stale,
    /// Outside what the right micrograph sees: left of the column where its first columns lead
    /// back to, or with every disparity the measured ends allow landing before its first column
    /// (the strip along the edge that the other micrograph never saw). Not measured, and reported
    /// as [`Unknown::NotSeen`].
    NotSeen,
}

impl Fail {
    /// The number of reasons.
    pub const COUNT: usize = 10;
}

/// A disparity plane about its pixel: `d + a δx + b δy`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Plane {
    d: f32,
    a: f32,
    b: f32,
}

/// One micrograph as the windows read it: contrast-normalised, with its gradient along x.
struct View<'a> {
    w: usize,
    h: usize,
    img: Vec<f32>,
    /// Per pixel the sample and the x gradient side by side (NaN where the micrograph has no
    /// data): a bilinear read touches two cache lines instead of six.
    packed: Vec<[f32; 2]>,
    valid: &'a [bool],
}

impl<'a> View<'a> {
    fn new(img: &Image, valid: &'a [bool], presmooth: f32, normalise: f32) -> Self {
        let (w, h) = img.dimensions();
        let n = normalise_contrast(img, presmooth, normalise);
        let d = n.data();
        let gx: Vec<f32> = (0..w * h)
            .into_par_iter()
            .map(|p| {
                let x = p % w;
                let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
                (d[p - x + r] - d[p - x + l]) / (r - l).max(1) as f32
            })
            .collect();
        let img = n.into_vec();
        let packed = img
            .par_iter()
            .zip(&gx)
            .zip(valid)
            .map(|((&i, &g), &v)| if v { [i, g] } else { [f32::NAN; 2] })
            .collect();
        Self {
            w,
            h,
            img,
            packed,
            valid,
        }
    }

    /// The sample at an integer pixel, `None` outside or where the micrograph has no data.
    #[inline]
    fn at(&self, x: isize, y: isize) -> Option<f32> {
        if x < 0 || y < 0 || x as usize >= self.w || y as usize >= self.h {
            return None;
        }
        let p = y as usize * self.w + x as usize;
        self.valid[p].then(|| self.img[p])
    }

    /// Bilinear sample and x gradient at a real position, `None` outside or beside a pixel
    /// without data.
    #[inline]
    fn sample(&self, x: f32, y: f32) -> Option<(f32, f32)> {
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let (x0, y0) = (x as usize, y as usize);
        if x0 + 1 >= self.w || y0 + 1 >= self.h {
            return None;
        }
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let p = y0 * self.w + x0;
        let q = p + self.w;
        let (t0, t1, b0, b1) = (
            self.packed[p],
            self.packed[p + 1],
            self.packed[q],
            self.packed[q + 1],
        );
        // A pixel without data is NaN in both entries: one test of the samples suffices.
        if (t0[0] + t1[0] + b0[0] + b1[0]).is_nan() {
            return None;
        }
        let lerp = |k: usize| {
            let top = t0[k] + fx * (t1[k] - t0[k]);
            let bottom = b0[k] + fx * (b1[k] - b0[k]);
            top + fy * (bottom - top)
        };
        Some((lerp(0), lerp(1)))
    }
}

/// The Gaussian window's samples `(δx, δy, weight)`, to 2σ, every σ/3 pixels.
fn window_taps(sigma: f32) -> Vec<(f32, f32, f32)> {
    #[allow(clippy::cast_possible_truncation)]
    let step = ((sigma / 3.0).round() as isize).max(1);
    window_taps_every(sigma, step)
}

/// The Gaussian window's samples `(δx, δy, weight)`, to 2σ, every `step` pixels.
fn window_taps_every(sigma: f32, step: isize) -> Vec<(f32, f32, f32)> {
    #[allow(clippy::cast_possible_truncation)]
    let r = (2.0 * sigma).ceil() as isize;
    let mut taps = Vec::new();
    let mut dy = -r - (-r).rem_euclid(step);
    while dy <= r {
        let mut dx = -r - (-r).rem_euclid(step);
        while dx <= r {
            let (fx, fy) = (dx as f32, dy as f32);
            let w = (-(fx * fx + fy * fy) / (2.0 * sigma * sigma)).exp();
            taps.push((fx, fy, w));
            dx += step;
        }
        dy += step;
    }
    taps
}

/// The taps of the slanted window at `(x₀, y₀)` (rows offset by `v`) that both `src` and `dst`
/// hold under `plane`: `(δx, δy, weight, A, B, B_x)`.
fn window<'a>(
    src: &'a View,
    dst: &'a View,
    taps: &'a [(f32, f32, f32)],
    (x0, y0, v): (usize, usize, f32),
    plane: Plane,
) -> impl Iterator<Item = (f32, f32, f32, f32, f32, f32)> + 'a {
    taps.iter().filter_map(move |&(dx, dy, w)| {
        #[allow(clippy::cast_possible_truncation)]
        let av = src.at(x0 as isize + dx as isize, y0 as isize + dy as isize)?;
        let xr = x0 as f32 + dx + plane.d + plane.a * dx + plane.b * dy;
        let (bv, bx) = dst.sample(xr, y0 as f32 + dy + v)?;
        Some((dx, dy, w, av, bv, bx))
    })
}

/// The slanted window of `src` at pixel `(x₀, y₀)` against `dst` under `plane` (rows offset by
/// `v`): the normalised cross-correlation, `None` where less than half the window's weight
/// has data on both sides.
fn ncc(
    src: &View,
    dst: &View,
    taps: &[(f32, f32, f32)],
    at: (usize, usize, f32),
    plane: Plane,
) -> Option<f32> {
    let (mut s1, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0f32, 0.0, 0.0, 0.0, 0.0, 0.0);
    let total: f32 = taps.iter().map(|t| t.2).sum();
    for (_, _, w, av, bv, _) in window(src, dst, taps, at, plane) {
        s1 += w;
        sa += w * av;
        sb += w * bv;
        saa += w * av * av;
        sbb += w * bv * bv;
        sab += w * av * bv;
    }
    if s1 < 0.5 * total {
        return None;
    }
    let (ma, mb) = (sa / s1, sb / s1);
    let (vaa, vbb, vab) = (saa / s1 - ma * ma, sbb / s1 - mb * mb, sab / s1 - ma * mb);
    (vaa > 1e-9 && vbb > 1e-9).then(|| vab / (vaa * vbb).sqrt())
}

/// Gauss–Newton on the plane and an offset of the intensities over the slanted window:
/// `r = B(x₀ + δx + d + a δx + b δy, y₀ + δy + v) + β − A(x₀ + δx, y₀ + δy)`, Jacobian
/// `(B_x, B_x δx, B_x δy, 1)`. Steps are bounded (a pixel, a tenth of slope) and the slopes
/// clamped to `max_slope`; [`Fail::Lost`] when the window loses its data. With `keep`, a
/// disparity interval and its reason, the fit stops as soon as its disparity is further outside
/// than the steps left could bring it back (the result would fail the same test).
fn gauss_newton(
    src: &View,
    dst: &View,
    taps: &[(f32, f32, f32)],
    at: (usize, usize, f32),
    mut plane: Plane,
    (iterations, max_slope): (usize, f32),
    keep: Option<(Interval, Fail)>,
) -> Result<Plane, Fail> {
    use nalgebra::{Matrix4, Vector4};
    let total: f64 = taps.iter().map(|t| f64::from(t.2)).sum();
    let mut beta = 0.0f64;
    for k in 0..iterations {
        // The normal equations' upper triangle (10 sums) and right side: J = (B_x, B_x δx,
        // B_x δy, 1) is B_x (1, δx, δy) and 1, so every sum is a moment of w B_x² , w B_x or w.
        let mut m = [0.0f64; 10];
        let mut g = Vector4::<f64>::zeros();
        for (dx, dy, w, av, bv, bx) in window(src, dst, taps, at, plane) {
            let (w, bx, dx, dy) = (f64::from(w), f64::from(bx), f64::from(dx), f64::from(dy));
            let (wb, wbb) = (w * bx, w * bx * bx);
            let r = f64::from(bv) + beta - f64::from(av);
            m[0] += wbb;
            m[1] += wbb * dx;
            m[2] += wbb * dy;
            m[3] += wb;
            m[4] += wbb * dx * dx;
            m[5] += wbb * dx * dy;
            m[6] += wb * dx;
            m[7] += wbb * dy * dy;
            m[8] += wb * dy;
            m[9] += w;
            g[0] += wb * r;
            g[1] += wb * dx * r;
            g[2] += wb * dy * r;
            g[3] += w * r;
        }
        if m[9] < 0.5 * total {
            return Err(Fail::Lost);
        }
        #[rustfmt::skip]
        let hm = Matrix4::new(
            m[0], m[1], m[2], m[3],
            m[1], m[4], m[5], m[6],
            m[2], m[5], m[7], m[8],
            m[3], m[6], m[8], m[9],
        );
        // A little damping keeps a window without texture along one direction solvable.
        let lam = 1e-3 * hm.trace() / 4.0 + 1e-9;
        let step = (hm + Matrix4::identity() * lam)
            .cholesky()
            .ok_or(Fail::Lost)?
            .solve(&(-g));
        #[allow(clippy::cast_possible_truncation)]
        let (dd, da, db) = (
            (step[0] as f32).clamp(-1.0, 1.0),
            (step[1] as f32).clamp(-0.1, 0.1),
            (step[2] as f32).clamp(-0.1, 0.1),
        );
        plane.d += dd;
        plane.a = (plane.a + da).clamp(-max_slope, max_slope);
        plane.b = (plane.b + db).clamp(-max_slope, max_slope);
        beta += step[3];
        if dd.abs() < 1e-3 && da.abs() < 1e-4 && db.abs() < 1e-4 {
            break;
        }
        // Each step moves the disparity by a pixel at most.
        #[allow(clippy::cast_precision_loss)]
        if let Some((interval, why)) = keep
            && interval.beyond(plane.d, (iterations - 1 - k) as f32)
        {
            return Err(why);
        }
    }
    Ok(plane)
}

/// The disparities the measured pixels around a gap allow: `[lo, hi]`, empty when `lo > hi`.
#[derive(Debug, Clone, Copy)]
struct Interval {
    lo: f32,
    hi: f32,
}

impl Interval {
    /// Whether `d` lies more than `slack` outside.
    fn beyond(self, d: f32, slack: f32) -> bool {
        d > self.hi + slack || d < self.lo - slack
    }
}

/// The plane of the right-to-left match that inverts `plane` (left pixel `x₀` on `x₀ + d`):
/// at right pixel `q` it leads back to `x₀ + (q − x₀ − d) / (1 + a)`.
fn inverse(plane: Plane, x0: usize, q: usize) -> Plane {
    let s = 1.0 + plane.a;
    let back = x0 as f32 + (q as f32 - x0 as f32 - plane.d) / s;
    Plane {
        d: back - q as f32,
        a: -plane.a / s,
        b: -plane.b / s,
    }
}

/// The measured pixel nearest to `p` in each direction along a line of `n` pixels with stride
/// `stride` (a row or a column), within `max_gap`: `(offset, disparity)`.
fn bounds(
    raw: &[f32],
    p: usize,
    pos: usize,
    n: usize,
    stride: usize,
    max_gap: usize,
) -> [Option<(f32, f32)>; 2] {
    let mut out = [None, None];
    for k in 1..=max_gap.min(pos) {
        let d = raw[p - k * stride];
        if d.is_finite() {
            out[0] = Some((-(k as f32), d));
            break;
        }
    }
    for k in 1..=max_gap.min(n - 1 - pos) {
        let d = raw[p + k * stride];
        if d.is_finite() {
            out[1] = Some((k as f32, d));
            break;
        }
    }
    out
}

/// The line through the measured ends of a gap: `(value at the pixel, slope)`.
fn line(ends: [Option<(f32, f32)>; 2]) -> Option<(f32, f32)> {
    match ends {
        [Some((o0, d0)), Some((o1, d1))] => {
            let slope = (d1 - d0) / (o1 - o0);
            Some((d0 - o0 * slope, slope))
        }
        [Some((_, d)), None] | [None, Some((_, d))] => Some((d, 0.0)),
        [None, None] => None,
    }
}

/// Candidate planes closer than this in disparity (pixels) and in both slopes are one: the
/// coarse fit, which starts from the best, moves them by more in its first step.
const SAME_D: f32 = 0.05;
const SAME_SLOPE: f32 = 0.005;

/// How far below `min_ncc` the coarse fit may correlate and still go on to the fine one.
const COARSE_NCC_SLACK: f32 = 0.15;

/// Pre-smoothing of the fine scale, pixels: keeps bilinear sampling from pulling the match
/// towards whole pixels.
const FINE_PRESMOOTH: f32 = 0.7;

/// The neighbours whose planes a pixel may start from.
const NEIGHBOURS: [(isize, isize); 8] = [
    (-1, 0),
    (1, 0),
    (0, -1),
    (0, 1),
    (-4, 0),
    (4, 0),
    (0, -4),
    (0, 4),
];

/// The measured pixels nearest to a pixel along its row (left, right) and column (up, down):
/// `(offset, disparity)`.
type Ends = [Option<(f32, f32)>; 4];

/// [`Ends`] of pixel `p` within `max_gap`.
fn ends_of(raw: &[f32], p: usize, (w, h): (usize, usize), max_gap: usize) -> Ends {
    let [l, r] = bounds(raw, p, p % w, w, 1, max_gap);
    let [u, d] = bounds(raw, p, p / w, h, w, max_gap);
    [l, r, u, d]
}

/// Everything one pixel's measurement reads.
struct Context<'a> {
    coarse: (View<'a>, View<'a>),
    fine: (View<'a>, View<'a>),
    taps: Vec<(f32, f32, f32)>,
    /// The coarse scale's taps, sparser: it is smoothed more.
    coarse_taps: Vec<(f32, f32, f32)>,
    fields: &'a Fields<'a>,
    params: &'a SlantedParams,
    lr_tolerance: f32,
    w: usize,
    h: usize,
}

/// A measured pixel: its plane, NCC and agreement of both directions in `[0, 1]`.
struct Measured {
    plane: Plane,
    ncc: f32,
    agreement: f32,
}

impl Context<'_> {
    /// The candidate planes at `p`: the lines across the gap along its row and column, the
    /// matcher's own disparity with those slopes and flat, and the neighbours' planes.
    fn candidates(&self, ends: &Ends, planes: &[Option<Plane>], p: usize) -> Vec<Plane> {
        let (w, h) = (self.w, self.h);
        let (x, y) = (p % w, p / w);
        let row = line([ends[0], ends[1]]);
        let col = line([ends[2], ends[3]]);
        let slope = self.params.max_slope;
        let (a, b) = (
            row.map_or(0.0, |r| r.1.clamp(-slope, slope)),
            col.map_or(0.0, |c| c.1.clamp(-slope, slope)),
        );
        let mut out = Vec::with_capacity(12);
        // Neighbours on one surface carry nearly the same plane: one of them is tried.
        let push = |out: &mut Vec<Plane>, c: Plane| {
            if !out.iter().any(|o| {
                (o.d - c.d).abs() <= SAME_D
                    && (o.a - c.a).abs() <= SAME_SLOPE
                    && (o.b - c.b).abs() <= SAME_SLOPE
            }) {
                out.push(c);
            }
        };
        if let Some((d, _)) = row {
            push(&mut out, Plane { d, a, b });
        }
        if let Some((d, _)) = col {
            push(&mut out, Plane { d, a, b });
        }
        let s = self.fields.start[p];
        if s.is_finite() {
            push(&mut out, Plane { d: s, a, b });
            push(
                &mut out,
                Plane {
                    d: s,
                    a: 0.0,
                    b: 0.0,
                },
            );
        }
        for &(ox, oy) in &NEIGHBOURS {
            let (nx, ny) = (x as isize + ox, y as isize + oy);
            if nx < 0 || ny < 0 || nx as usize >= w || ny as usize >= h {
                continue;
            }
            if let Some(q) = planes[ny as usize * w + nx as usize] {
                // The neighbour's plane, carried to this pixel.
                push(
                    &mut out,
                    Plane {
                        d: q.d - q.a * ox as f32 - q.b * oy as f32,
                        ..q
                    },
                );
            }
        }
        out
    }

    /// [`gauss_newton`] with this pass's window and parameters.
    fn refine(
        &self,
        (src, dst): (&View, &View),
        taps: &[(f32, f32, f32)],
        at: (usize, usize, f32),
        start: Plane,
        keep: Option<(Interval, Fail)>,
    ) -> Result<Plane, Fail> {
        let params = self.params;
        gauss_newton(
            src,
            dst,
            taps,
            at,
            start,
            (params.iterations, params.max_slope),
            keep,
        )
    }

    /// The slanted measurement of left pixel `p` from the candidates, if it passes.
    fn measure(&self, p: usize, candidates: &[Plane], ends: &Ends) -> Result<Measured, Fail> {
        let (x, y) = (p % self.w, p / self.w);
        let v = self.fields.v[p];
        let at = (x, y, if v.is_finite() { v } else { 0.0 });
        let params = self.params;
        // The disparity cannot change faster than the steepest plane allowed: the measured
        // pixels around the gap bound it (a match far off them is a mismatch, e.g. into what
        // the other micrograph does not see).
        let reach = |o: f32| params.max_slope * o.abs() + self.lr_tolerance;
        let allowed = ends.iter().flatten().fold(
            Interval {
                lo: f32::NEG_INFINITY,
                hi: f32::INFINITY,
            },
            |i, &(o, e)| Interval {
                lo: i.lo.max(e - reach(o)),
                hi: i.hi.min(e + reach(o)),
            },
        );
        // The strip the right micrograph never saw: no window there can match.
        #[allow(clippy::cast_precision_loss)]
        let xf = x as f32;
        if xf + allowed.hi < 0.0 || xf < self.fields.first_seen[y] - self.lr_tolerance {
            return Err(Fail::NotSeen);
        }
        let (ca, cb) = (&self.coarse.0, &self.coarse.1);
        let best = candidates
            .iter()
            .filter_map(|&c| ncc(ca, cb, &self.coarse_taps, at, c).map(|s| (s, c)))
            .max_by(|l, r| l.0.total_cmp(&r.0))
            .ok_or(Fail::NoCandidate)?
            .1;
        let beyond = |d: f32, slack: f32| allowed.beyond(d, slack);
        #[allow(clippy::cast_precision_loss)]
        let coarse_slack = params.iterations as f32;
        let coarse = self.refine(
            (ca, cb),
            &self.coarse_taps,
            at,
            best,
            Some((
                Interval {
                    lo: allowed.lo - coarse_slack,
                    hi: allowed.hi + coarse_slack,
                },
                Fail::CoarseReach,
            )),
        )?;
        // Hopeless pixels stop here, before the fine fit: the coarse windows hardly correlate
        // (they correlate better than the fine ones, being smoother), or the plane is further
        // off the ends than the fine fit could bring it back.
        let coarse_score = ncc(ca, cb, &self.coarse_taps, at, coarse).ok_or(Fail::Lost)?;
        if coarse_score < params.min_ncc - COARSE_NCC_SLACK {
            return Err(Fail::CoarseNcc);
        }
        if beyond(coarse.d, coarse_slack) {
            return Err(Fail::CoarseReach);
        }
        let (fa, fb) = (&self.fine.0, &self.fine.1);
        let plane = self.refine(
            (fa, fb),
            &self.taps,
            at,
            coarse,
            Some((allowed, Fail::Reach)),
        )?;
        let score = ncc(fa, fb, &self.taps, at, plane).ok_or(Fail::Lost)?;
        if score < params.min_ncc {
            return Err(Fail::Ncc);
        }
        if beyond(plane.d, 0.0) {
            return Err(Fail::Reach);
        }
        if plane.a.abs() >= params.max_slope || plane.b.abs() >= params.max_slope {
            return Err(Fail::Slope);
        }
        let residual = self.backward_residual(at, plane).ok_or(Fail::LeftRight)?;
        let tol = self.lr_tolerance.max(1e-3);
        if residual > self.lr_tolerance {
            return Err(Fail::LeftRight);
        }
        Ok(Measured {
            plane,
            ncc: score,
            agreement: (-(residual / tol).powi(2)).exp(),
        })
    }

    /// How far the right-to-left match at `p`'s match leads from `p`, pixels: by the
    /// right-to-left field, or else by the inverse plane refined on the right micrograph's own
    /// window (which must correlate as well). `None` when neither leads anywhere.
    fn backward_residual(&self, at: (usize, usize, f32), plane: Plane) -> Option<f32> {
        let (x, y, v) = at;
        let (xr, yr) = (x as f32 + plane.d, y as f32 + v);
        let by_field = self
            .fields
            .backward
            .and_then(|bw| bilinear(bw, self.w, self.h, xr, yr))
            .map(|u| (plane.d + u).abs());
        if let Some(r) = by_field.filter(|&r| r <= self.lr_tolerance) {
            return Some(r);
        }
        self.fields.backward?;
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let (qx, qy) = (xr.round(), yr.round());
        if qx < 0.0 || qy < 0.0 || qx as usize >= self.w || qy as usize >= self.h {
            return by_field;
        }
        #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
        let (qx, qy) = (qx as usize, qy as usize);
        if !self.fields.vb[qy * self.w + qx] {
            return by_field;
        }
        let start = inverse(plane, x, qx);
        let back_at = (qx, qy, y as f32 - qy as f32);
        let params = self.params;
        let (fa, fb) = (&self.fine.1, &self.fine.0);
        let back = self
            .refine((fa, fb), &self.taps, back_at, start, None)
            .ok()?;
        let score = ncc(fa, fb, &self.taps, back_at, back)?;
        if score < params.min_ncc {
            return by_field;
        }
        // The right pixel's match, against where the forward plane puts it: left pixels.
        let r = (back.d - start.d).abs();
        Some(by_field.map_or(r, |f| f.min(r)))
    }
}

/// A field sampled bilinearly at a real position, `None` outside or where not finite.
fn bilinear(f: &[f32], w: usize, h: usize, x: f32, y: f32) -> Option<f32> {
    if !(x >= 0.0 && y >= 0.0 && x <= (w - 1) as f32 && y <= (h - 1) as f32) {
        return None;
    }
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let (x0, y0) = (
        (x as usize).min(w.saturating_sub(2)),
        (y as usize).min(h.saturating_sub(2)),
    );
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let (a, b, c, d) = (
        f[y0 * w + x0],
        f[y0 * w + x1],
        f[y1 * w + x0],
        f[y1 * w + x1],
    );
    let top = a + fx * (b - a);
    let bottom = c + fx * (d - c);
    let v = top + fy * (bottom - top);
    v.is_finite().then_some(v)
}

/// Measures again, with slanted windows, the pixels of the disparity `raw` that the left–right
/// check left unknown (step 6 of the dense stage, with `slanted.enabled`): the rectified pair
/// `(a, b)` and its valid pixels, the forward field before the check masked it (`start`), the
/// vertical flow and the backward field; `raw`, the confidence and the reasons change where a
/// slanted window measures the pixel.
pub(crate) fn measure_steep(
    (a, b): (&Image, &Image),
    (va, vb): (&[bool], &[bool]),
    (start, v, backward): (&[f32], &Image, Option<&[f32]>),
    (raw, confidence, unknown): (&mut Image, &mut Image, &mut [Unknown]),
    dense: &super::DenseParams,
) -> SlantedStats {
    let params = &dense.slanted;
    let (w, h) = raw.dimensions();
    let fields = Fields {
        vb,
        start,
        v: v.data(),
        backward,
        first_seen: backward.map_or_else(
            || vec![f32::NEG_INFINITY; h],
            |bw| first_seen_columns(bw, vb, (w, h)),
        ),
    };
    let fields = &fields;
    #[allow(clippy::cast_possible_truncation)]
    let sigma = if params.window_sigma > 0.0 {
        params.window_sigma
    } else {
        crate::vision::pipeline::matcher_window_sigma(dense) as f32
    };
    let normalise_sigma = dense.flow.refinement().map_or(2.5, |r| r.normalise_sigma);
    let lr_tolerance = dense.lr_tolerance;
    let ((ca, cb), (fa, fb)) = rayon::join(
        || {
            rayon::join(
                || View::new(a, va, 1.5, normalise_sigma * 1.5),
                || View::new(b, vb, 1.5, normalise_sigma * 1.5),
            )
        },
        || {
            rayon::join(
                || View::new(a, va, FINE_PRESMOOTH, normalise_sigma),
                || View::new(b, vb, FINE_PRESMOOTH, normalise_sigma),
            )
        },
    );
    let ctx = Context {
        coarse: (ca, cb),
        fine: (fa, fb),
        taps: window_taps(sigma),
        // σ/2 apart: the coarse scale is smoothed by 1.5 pixels more.
        #[allow(clippy::cast_possible_truncation)]
        coarse_taps: window_taps_every(sigma, ((sigma / 2.0).round() as isize).max(1)),
        fields,
        params,
        lr_tolerance,
        w,
        h,
    };
    let mut pending: Vec<usize> = (0..w * h)
        .filter(|&p| unknown[p] == Unknown::LeftRight)
        .collect();
    let examined = pending.len();
    let mut planes: Vec<Option<Plane>> = vec![None; w * h];
    // The pass that measured each pixel (0: none yet).
    let mut pass_of = vec![0u8; w * h];
    let mut measured = 0;
    let mut last_fail = vec![Fail::Stale; w * h];
    let mut not_seen = 0;
    for pass in 1..=params.passes.max(1) {
        // After the first pass only pixels beside a plane the last pass found have a new start.
        let fresh = |p: usize| {
            let (x, y) = ((p % w) as isize, (p / w) as isize);
            NEIGHBOURS.iter().any(|&(ox, oy)| {
                let (nx, ny) = (x + ox, y + oy);
                nx >= 0
                    && ny >= 0
                    && (nx as usize) < w
                    && (ny as usize) < h
                    && usize::from(pass_of[ny as usize * w + nx as usize]) + 1 == pass
            })
        };
        let results: Vec<Result<Measured, Fail>> = pending
            .par_iter()
            .map(|&p| {
                if pass > 1 && !fresh(p) {
                    return Err(Fail::Stale);
                }
                let ends = ends_of(raw.data(), p, (w, h), params.max_gap);
                let c = ctx.candidates(&ends, &planes, p);
                ctx.measure(p, &c, &ends)
            })
            .collect();
        let mut still = Vec::new();
        let (d_out, conf) = (raw.data_mut(), confidence.data_mut());
        for (p, r) in pending.into_iter().zip(results) {
            match r {
                Ok(m) => {
                    d_out[p] = m.plane.d;
                    conf[p] = m.ncc * m.agreement;
                    unknown[p] = Unknown::Measured;
                    planes[p] = Some(m.plane);
                    #[allow(clippy::cast_possible_truncation)]
                    {
                        pass_of[p] = pass as u8;
                    }
                    measured += 1;
                }
                Err(Fail::NotSeen) => {
                    // Outside what the right micrograph sees: no later pass can measure it.
                    unknown[p] = Unknown::NotSeen;
                    not_seen += 1;
                }
                Err(why) => {
                    // A pixel not tried again keeps the reason of its last try.
                    if why != Fail::Stale {
                        last_fail[p] = why;
                    }
                    still.push(p);
                }
            }
        }
        pending = still;
        if pending.is_empty() {
            break;
        }
    }
    let mut failed = [0; Fail::COUNT];
    for &p in &pending {
        failed[last_fail[p] as usize] += 1;
    }
    failed[Fail::NotSeen as usize] = not_seen;
    tracing::debug!(examined, measured, ?failed, "slanted support");
    SlantedStats {
        examined,
        measured,
        failed,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{Layer, Texture, render};
    use crate::vision::dense::DenseParams;

    /// A flat floor, a flank rising 0.5 px of disparity per pixel along the parallax, and a
    /// flat top: the right micrograph sees the flank stretched by 1.5.
    fn flank(x: f64) -> f64 {
        4.0 + 0.5 * (x.clamp(70.0, 130.0) - 70.0)
    }

    fn flank_pair() -> crate::testing::SyntheticPair {
        let layers = vec![Layer {
            disparity: Box::new(|x, _| flank(x)),
            region: Box::new(|_, _| true),
        }];
        render(256, 96, Texture::new(5), &layers, 0.0, 0.01)
    }

    /// The stage's state after the left–right check: the pixels `gap` picks unknown (their
    /// reason left-right), the rest measured at the pair's true disparity.
    fn after_left_right(
        pair: &crate::testing::SyntheticPair,
        gap: impl Fn(usize) -> bool,
    ) -> (Image, Vec<Unknown>) {
        let (w, h) = pair.left.dimensions();
        let raw = Image::from_fn(w, h, |x, y| {
            if gap(y * w + x) {
                f32::NAN
            } else {
                pair.disparity.get(x, y)
            }
        });
        let unknown = (0..w * h)
            .map(|p| {
                if gap(p) {
                    Unknown::LeftRight
                } else {
                    Unknown::Measured
                }
            })
            .collect();
        (raw, unknown)
    }

    /// The flank's pixels away from its ends (where the plane is exact) and the border.
    fn on_flank(p: usize, w: usize) -> bool {
        let (x, y) = (p % w, p / w);
        (82..118).contains(&x) && (16..80).contains(&y)
    }

    #[test]
    fn a_steep_flank_is_measured_with_slanted_windows_where_a_flat_window_fails() {
        let pair = flank_pair();
        let (w, h) = pair.left.dimensions();
        let dense = DenseParams {
            slanted: SlantedParams {
                enabled: true,
                ..SlantedParams::default()
            },
            ..DenseParams::default()
        };
        // The stage's state after the left–right check: the flank unknown, the rest measured,
        // no forward start and no backward field on the flank to lean on.
        let (mut raw, mut unknown) = after_left_right(&pair, |p| (70..130).contains(&(p % w)));
        let mut confidence = Image::filled(w, h, 1.0);
        let start = vec![f32::NAN; w * h];
        let backward = vec![f32::NAN; w * h];
        let valid = vec![true; w * h];
        let v = Image::zeros(w, h);
        let stats = measure_steep(
            (&pair.left, &pair.right),
            (&valid, &valid),
            (&start, &v, Some(&backward)),
            (&mut raw, &mut confidence, &mut unknown),
            &dense,
        );
        assert_eq!(stats.examined, 60 * h);
        let mut errors: Vec<f32> = (0..w * h)
            .filter(|&p| on_flank(p, w))
            .map(|p| (raw.data()[p] - pair.disparity.data()[p]).abs())
            .collect();
        let n = errors.len();
        errors.sort_by(|a, b| b.total_cmp(a));
        let measured = errors.iter().filter(|e| e.is_finite()).count();
        assert!(
            measured as f64 >= 0.95 * n as f64,
            "{measured} of {n} measured"
        );
        let worst = errors[n - measured];
        assert!(worst <= 0.2, "worst error {worst} px");

        // A fronto-parallel window at the true disparity does not correlate there.
        let view = |img: &Image| View::new(img, &valid, 0.0, 2.5);
        let (a, b) = (view(&pair.left), view(&pair.right));
        let taps = window_taps(6.0);
        let d = flank(100.0) as f32;
        let flat = ncc(&a, &b, &taps, (100, 48, 0.0), Plane { d, a: 0.0, b: 0.0 }).unwrap();
        let slanted = ncc(&a, &b, &taps, (100, 48, 0.0), Plane { d, a: 0.5, b: 0.0 }).unwrap();
        assert!(
            flat < 0.5 && slanted > 0.95,
            "NCC flat {flat}, slanted {slanted}"
        );
    }

    #[test]
    fn an_occluded_strip_stays_unknown() {
        // A raised band hides the floor beside it in the right view: no plane can match there.
        let layers = crate::testing::raised_band(100.0, 160.0, 3.0, 12.0);
        let pair = render(256, 96, Texture::new(9), &layers, 0.0, 0.01);
        let (w, h) = pair.left.dimensions();
        let dense = DenseParams {
            slanted: SlantedParams {
                enabled: true,
                ..SlantedParams::default()
            },
            ..DenseParams::default()
        };
        let hidden: Vec<bool> = pair.visible.iter().map(|v| !v).collect();
        assert!(hidden.iter().filter(|&&o| o).count() > 5 * h);
        let mut raw = Image::from_fn(w, h, |x, y| {
            if hidden[y * w + x] {
                f32::NAN
            } else {
                pair.disparity.get(x, y)
            }
        });
        let mut unknown: Vec<Unknown> = hidden
            .iter()
            .map(|&o| {
                if o {
                    Unknown::LeftRight
                } else {
                    Unknown::Measured
                }
            })
            .collect();
        let mut confidence = Image::filled(w, h, 1.0);
        let valid = vec![true; w * h];
        // The backward field of the band and the floor, as a matcher would give it.
        let backward = Image::from_fn(w, h, |x, _| {
            let x = x as f32;
            if (115.0..175.0).contains(&x) {
                -15.0
            } else {
                -3.0
            }
        });
        let start = vec![f32::NAN; w * h];
        let stats = measure_steep(
            (&pair.left, &pair.right),
            (&valid, &valid),
            (&start, &Image::zeros(w, h), Some(backward.data())),
            (&mut raw, &mut confidence, &mut unknown),
            &dense,
        );
        assert!(
            // At `min_ncc` 0.5 the strip's rims, where the window reaches the visible floor,
            // may pass (11 % here); its interior stays unknown.
            stats.measured * 8 <= stats.examined,
            "{} of {} hidden pixels measured",
            stats.measured,
            stats.examined
        );
    }

    #[test]
    fn the_strip_the_right_micrograph_never_saw_is_not_seen_and_not_measured() {
        // The right micrograph sees the scene 20 px further left: left columns 0..20 never.
        let layers = vec![Layer {
            disparity: Box::new(|_, _| -20.0),
            region: Box::new(|_, _| true),
        }];
        let pair = render(160, 64, Texture::new(3), &layers, 0.0, 0.01);
        let (w, h) = pair.left.dimensions();
        let dense = DenseParams {
            slanted: SlantedParams {
                enabled: true,
                ..SlantedParams::default()
            },
            ..DenseParams::default()
        };
        // After the left–right check the first 32 columns are unknown, the rest measured.
        let gap = |p: usize| p % w < 32;
        let (mut raw, mut unknown) = after_left_right(&pair, gap);
        let mut confidence = Image::filled(w, h, 1.0);
        let valid = vec![true; w * h];
        // The right-to-left field leads the right micrograph's first column to left column 20.
        let backward = vec![20.0; w * h];
        let stats = measure_steep(
            (&pair.left, &pair.right),
            (&valid, &valid),
            (&vec![f32::NAN; w * h], &Image::zeros(w, h), Some(&backward)),
            (&mut raw, &mut confidence, &mut unknown),
            &dense,
        );
        let strip = |p: usize| p % w < 18;
        for p in (0..w * h).filter(|&p| strip(p)) {
            assert_eq!(unknown[p], Unknown::NotSeen, "pixel {p}");
            assert!(raw.data()[p].is_nan());
        }
        assert_eq!(stats.failed[Fail::NotSeen as usize], 18 * h);
        // Beside the strip, what the right micrograph sees is measured.
        let seen = (0..w * h)
            .filter(|&p| (22..32).contains(&(p % w)) && (8..h - 8).contains(&(p / w)))
            .collect::<Vec<_>>();
        let measured = seen
            .iter()
            .filter(|&&p| unknown[p] == Unknown::Measured)
            .count();
        assert!(
            measured * 10 >= seen.len() * 9,
            "{measured} of {}",
            seen.len()
        );
        // Without a right-to-left field nothing tells the strip apart here: it is tried.
        let (mut raw2, mut unknown2) = after_left_right(&pair, gap);
        let stats = measure_steep(
            (&pair.left, &pair.right),
            (&valid, &valid),
            (&vec![f32::NAN; w * h], &Image::zeros(w, h), None),
            (&mut raw2, &mut Image::filled(w, h, 1.0), &mut unknown2),
            &dense,
        );
        assert_eq!(stats.failed[Fail::NotSeen as usize], 0);
    }
}
