//! Large simulated pairs for issue 32's memory and speed targets (4096×3072, 8192×6144):
//! the ground truth written beside a case's micrographs (`dense --size WxH --write-pairs`),
//! and the score of a `sdsem reconstruct` height map against it (`score-height`). Both run
//! row by row with constant memory per pixel, so an 8192×6144 case needs a few hundred MiB,
//! not the gigabytes of [`super::dense::evaluate_case`]'s per-pixel correspondences.

use std::path::Path;

use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;
use sdsem::export::height_tiff::{read_height_tiff, write_height_tiff};
use sdsem::vision::Image;
use sdsem_sim::render::{View, correspondence, trace_pixel};
use sdsem_sim::scene::Scene;

/// The true height (µm) of every pixel of the left view that both views see, NaN elsewhere:
/// the same pixels and values [`super::dense::evaluate_case`] scores (its `visible` mask and
/// `height_map`), traced per pixel instead of held as correspondences.
#[must_use]
pub fn truth_seen_in_both(scene: &Scene, left: &View, right: &View) -> Vec<f32> {
    let w = left.width.max(1);
    let mut out = vec![f32::NAN; left.width * left.height];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, h) in row.iter_mut().enumerate() {
            let (fx, fy) = (x as f64, y as f64);
            if let Some(p) = trace_pixel(scene, left, fx, fy)
                && correspondence(scene, left, right, fx, fy).is_some_and(|c| c.is_visible())
            {
                *h = p.z as f32;
            }
        }
    });
    out
}

/// Writes the truth as `<stem>_truth.tif` (float32 µm, NaN where not seen in both).
pub fn write_truth(scene: &Scene, left: &View, right: &View, path: &Path) -> anyhow::Result<()> {
    let truth = Image::from_vec(
        left.width,
        left.height,
        truth_seen_in_both(scene, left, right),
    )
    .expect("the truth has the view's size");
    write_height_tiff(path, &truth, Some(left.pixel_size_um), None)?;
    Ok(())
}

/// A height map against the truth, over the pixels the truth marks as seen in both.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct HeightScore {
    /// Fraction of the seen pixels with a height.
    pub coverage: f64,
    /// True height range (1st to 99th percentile) over the seen pixels, µm.
    pub height_range_um: f64,
    /// RMSE of the error after removing its best-fit plane, µm.
    pub rmse_um: f64,
    /// `rmse_um / height_range_um`.
    pub rmse_relative: f64,
    /// Slope of estimated against true height with a plane: `est = s·true + a + b·x + c·y`.
    pub height_scale: f64,
}

/// Least squares accumulated one row at a time: the normal equations.
struct Normal {
    ata: DMatrix<f64>,
    atb: DVector<f64>,
}

impl Normal {
    fn new(unknowns: usize) -> Self {
        Self {
            ata: DMatrix::zeros(unknowns, unknowns),
            atb: DVector::zeros(unknowns),
        }
    }
    fn add(&mut self, a: &[f64], b: f64) {
        for (i, ai) in a.iter().enumerate() {
            self.atb[i] += ai * b;
            for (j, aj) in a.iter().enumerate() {
                self.ata[(i, j)] += ai * aj;
            }
        }
    }
    fn solve(self) -> Option<DVector<f64>> {
        self.ata.lu().solve(&self.atb)
    }
}

/// Scores `estimate` against `truth` (same size; NaN = unknown / not seen). Coordinates are
/// centred and scaled to the width before the plane fits, which keeps the normal equations
/// well conditioned at 50 million pixels.
///
/// # Errors
/// When the sizes differ or the truth sees no pixel.
pub fn score_height(truth: &Image, estimate: &Image) -> anyhow::Result<HeightScore> {
    anyhow::ensure!(
        (truth.width(), truth.height()) == (estimate.width(), estimate.height()),
        "the truth is {}×{} but the height map {}×{}",
        truth.width(),
        truth.height(),
        estimate.width(),
        estimate.height()
    );
    let w = truth.width();
    let (cx, cy, s) = (
        w as f64 / 2.0,
        truth.height() as f64 / 2.0,
        1.0 / w.max(1) as f64,
    );
    let xy = |p: usize| ((((p % w) as f64) - cx) * s, (((p / w) as f64) - cy) * s);
    let pairs = || {
        truth
            .data()
            .iter()
            .zip(estimate.data())
            .enumerate()
            .filter(|(_, (t, _))| t.is_finite())
    };
    let mut seen: Vec<f32> = pairs().map(|(_, (t, _))| *t).collect();
    anyhow::ensure!(!seen.is_empty(), "the truth sees no pixel");
    let n_seen = seen.len();
    let mut plane = Normal::new(3);
    let mut scale = Normal::new(4);
    let mut known = 0usize;
    for (p, (&t, &e)) in pairs().filter(|(_, (_, e))| e.is_finite()) {
        let (x, y) = xy(p);
        let (t, e) = (f64::from(t), f64::from(e));
        plane.add(&[1.0, x, y], e - t);
        scale.add(&[1.0, x, y, t], e);
        known += 1;
    }
    let (rmse_um, height_scale) = if known == 0 {
        (f64::NAN, f64::NAN)
    } else {
        let c = plane.solve().unwrap_or_else(|| DVector::zeros(3));
        let sse: f64 = pairs()
            .filter(|(_, (_, e))| e.is_finite())
            .map(|(p, (&t, &e))| {
                let (x, y) = xy(p);
                let r = f64::from(e) - f64::from(t) - (c[0] + c[1] * x + c[2] * y);
                r * r
            })
            .sum();
        (
            (sse / known as f64).sqrt(),
            scale.solve().map_or(f64::NAN, |c| c[3]),
        )
    };
    let mut quantile = |q: f64| {
        let i = ((n_seen - 1) as f64 * q).round() as usize;
        f64::from(*seen.select_nth_unstable_by(i, f32::total_cmp).1)
    };
    let height_range_um = quantile(0.99) - quantile(0.01);
    Ok(HeightScore {
        coverage: known as f64 / n_seen as f64,
        height_range_um,
        rmse_um,
        rmse_relative: rmse_um / height_range_um,
        height_scale,
    })
}

/// `sdsem-eval score-height TRUTH HEIGHT`: prints the score (a table line or JSON).
pub fn run_score(truth: &Path, height: &Path, json: bool) -> anyhow::Result<()> {
    let t = read_height_tiff(truth)?.height_um;
    let e = read_height_tiff(height)?.height_um;
    let s = score_height(&t, &e)?;
    if json {
        println!("{}", serde_json::to_string(&s)?);
    } else {
        println!(
            "coverage {:.1} % | height range {:.2} µm | RMSE {:.3} µm ({:.2} % of range) | scale {:.3}",
            100.0 * s.coverage,
            s.height_range_um,
            s.rmse_um,
            100.0 * s.rmse_relative,
            s.height_scale
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tilted, scaled, half-covered copy of the truth scores as such: the plane goes, the
    /// scale and the coverage are measured, unseen pixels do not count.
    #[test]
    fn score_removes_the_plane_and_measures_scale_and_coverage() {
        let (w, h) = (64, 48);
        let truth: Vec<f32> = (0..w * h)
            .map(|p| {
                let (x, y) = ((p % w) as f32, (p / w) as f32);
                if x < 4.0 {
                    f32::NAN // not seen in both
                } else {
                    ((x * 0.3).sin() + (y * 0.2).cos()) * 5.0
                }
            })
            .collect();
        let est: Vec<f32> = truth
            .iter()
            .enumerate()
            .map(|(p, t)| {
                let (x, y) = ((p % w) as f32, (p / w) as f32);
                // Unknown on the bottom half, and an unseen pixel with a height is ignored.
                if y >= 24.0 {
                    f32::NAN
                } else if t.is_nan() {
                    100.0
                } else {
                    0.9 * t + 3.0 + 0.05 * x - 0.02 * y
                }
            })
            .collect();
        let truth = Image::from_vec(w, h, truth).unwrap();
        let s = score_height(&truth, &Image::from_vec(w, h, est).unwrap()).unwrap();
        assert!((s.coverage - 0.5).abs() < 1e-9, "{s:?}");
        assert!((s.height_scale - 0.9).abs() < 1e-6, "{s:?}");
        // Error = −0.1·t + plane: its RMSE is a tenth of the truth's spread, not zero.
        assert!(s.rmse_um > 0.1 && s.rmse_um < 0.6, "{s:?}");
        assert!(
            s.height_range_um > 15.0 && s.height_range_um <= 20.0,
            "{s:?}"
        );
        let wrong = Image::from_vec(w, 1, vec![0.0; w]).unwrap();
        assert!(score_height(&truth, &wrong).is_err());
    }
}
