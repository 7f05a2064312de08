//! Agreement of real height maps: the Potamogeton pollen series of
//! `../shared/data/potamogeton` (Zeiss SEM, 1536 × 2048, 55.82 nm pixels,
//! tilt axis φ = −90° in these files). No ground truth exists, but the height
//! maps of (0°, +3°), (0°, +6°) and (0°, +9°) all lie on the grid of pot_03
//! and must differ only by a plane (each pair's reconstruction frame is its
//! mid-tilt plane) and noise.
//!
//! Figures: per pair, coverage and time per stage; per two pairs, the RMSE of
//! their difference after removing its best-fit plane, over the pixels where
//! both have a height, and that common coverage [target of issue 33: ≤ 0.5 µm
//! over ≥ 90 % of the image]. Beside it, the scale between the two maps and the
//! RMSE that is left once it is removed too: a tilt angle off in the metadata
//! would show there (it does not: the scales are 1.004–1.010).

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use sdsem::app::reconstruct::load_pair;
use sdsem::vision::Image;
use sdsem::vision::Preset;
use sdsem::vision::ReconstructionParams;
use sdsem::vision::dense::Unknown;
use sdsem::vision::geometry::Figures;
use sdsem::vision::pipeline::{ReconReport, reconstruct};

/// Largest RMSE between two pairs' heights after plane removal, µm (issue 33).
pub const TARGET_RMSE_UM: f64 = 0.5;
/// Least common measured area of two pairs, fraction of the image (issue 33).
pub const TARGET_COMMON: f64 = 0.9;

/// Tilt axis of the series in the stored files (see the data's README).
pub const TILT_AXIS_DEG: f64 = -90.0;

/// The left micrograph and the right ones, in the order of the pairs.
pub const LEFT: &str = "pot_03.tif";
pub const RIGHTS: [&str; 3] = ["pot_04.tif", "pot_05.tif", "pot_06.tif"];

/// One reconstructed pair.
#[derive(Debug, Clone, Serialize)]
pub struct PairFigures {
    pub right: String,
    pub tilt_deg: f64,
    /// Fraction of pot_03's pixels with a height.
    pub coverage: f64,
    /// Fraction of pot_03's pixels whose height was interpolated, not
    /// measured (confidence 0; `fill_max_gap`, off by default).
    pub interpolated: f64,
    /// Fraction of pot_03's pixels left unknown because both directions of matching disagree
    /// (reason `left-right`: steep flanks, occlusions, mismatches).
    pub left_right: f64,
    /// Fraction of pot_03's pixels outside what both micrographs see (reason `not-seen`).
    pub not_seen: f64,
    pub report: ReconReport,
    pub wall_ms: f64,
    /// Per pixel of pot_03, why its height is unknown (for `--dump`).
    #[serde(skip)]
    pub unknown: Vec<Unknown>,
}

/// Agreement of two height maps on one grid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Agreement {
    /// Fraction of the grid where both have a height.
    pub common: f64,
    /// RMSE of the difference after removing its best-fit plane, µm.
    pub rmse_um: f64,
    /// Median |difference| after the plane, µm.
    pub median_um: f64,
    /// `k` of the least-squares fit `a ≈ k b + plane`: a tilt angle off in either pair's
    /// metadata scales its heights against the other's.
    pub scale: f64,
    /// RMSE of `a − (k b + plane)`, µm: what is left once the scale is removed too.
    pub rmse_scaled_um: f64,
}

/// Compares two height maps of the same size: the difference minus its
/// least-squares plane, over the pixels where both are finite. Sums run in
/// a fixed order (no thread dependence).
#[must_use]
pub fn agreement(a: &Image, b: &Image) -> Agreement {
    let w = a.width();
    let mut pts = Vec::new();
    for (p, (&x, &y)) in a.data().iter().zip(b.data()).enumerate() {
        if x.is_finite() && y.is_finite() {
            pts.push(((p % w) as f64, (p / w) as f64, f64::from(x) - f64::from(y)));
        }
    }
    let n = pts.len();
    if n < 4 {
        return Agreement {
            common: n as f64 / a.len().max(1) as f64,
            rmse_um: f64::NAN,
            median_um: f64::NAN,
            scale: f64::NAN,
            rmse_scaled_um: f64::NAN,
        };
    }
    // Normal equations of d ≈ c0 + c1 x + c2 y, coordinates centred for conditioning.
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (a.height() as f64 - 1.0) / 2.0);
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for &(x, y, d) in &pts {
        let r = nalgebra::Vector3::new(1.0, x - cx, y - cy);
        ata += r * r.transpose();
        atb += r * d;
    }
    let c = ata
        .lu()
        .solve(&atb)
        .unwrap_or_else(nalgebra::Vector3::zeros);
    let (scale, rmse_scaled_um) = scaled_fit(a, b, (cx, cy));
    let mut resid: Vec<f64> = pts
        .iter()
        .map(|&(x, y, d)| d - (c[0] + c[1] * (x - cx) + c[2] * (y - cy)))
        .collect();
    let rmse = (resid.iter().map(|r| r * r).sum::<f64>() / n as f64).sqrt();
    for r in &mut resid {
        *r = r.abs();
    }
    resid.sort_by(f64::total_cmp);
    Agreement {
        common: n as f64 / a.len() as f64,
        rmse_um: rmse,
        median_um: resid[n / 2],
        scale,
        rmse_scaled_um,
    }
}

/// The least-squares fit `a ≈ k b + c0 + c1 x + c2 y` over the pixels where both are finite
/// (coordinates centred on `c`): `(k, RMSE of the rest)`. Sums in a fixed order.
fn scaled_fit(a: &Image, b: &Image, (cx, cy): (f64, f64)) -> (f64, f64) {
    let w = a.width();
    let rows = || {
        a.data()
            .iter()
            .zip(b.data())
            .enumerate()
            .filter(|(_, (x, y))| x.is_finite() && y.is_finite())
            .map(move |(p, (&x, &y))| {
                let r = nalgebra::Vector4::new(
                    f64::from(y),
                    1.0,
                    (p % w) as f64 - cx,
                    (p / w) as f64 - cy,
                );
                (r, f64::from(x))
            })
    };
    let mut ata = nalgebra::Matrix4::<f64>::zeros();
    let mut atb = nalgebra::Vector4::<f64>::zeros();
    let mut n = 0usize;
    for (r, t) in rows() {
        ata += r * r.transpose();
        atb += r * t;
        n += 1;
    }
    let Some(c) = ata.lu().solve(&atb) else {
        return (f64::NAN, f64::NAN);
    };
    let sum: f64 = rows().map(|(r, t)| (t - c.dot(&r)).powi(2)).sum();
    (c[0], (sum / n.max(1) as f64).sqrt())
}

/// Reconstructs the three pairs of the series under `dir` in `mode`.
///
/// # Errors
/// A missing file or a failed reconstruction, with its cause.
pub fn reconstruct_series(
    dir: &Path,
    mode: Preset,
    quick: bool,
    set: &[String],
) -> anyhow::Result<Vec<(PairFigures, Image, Vec<bool>)>> {
    let mut params = ReconstructionParams::preset(mode);
    params.dense = super::dense::apply_overrides(&params.dense, set)?;
    let rights: &[&str] = if quick { &RIGHTS[..2] } else { &RIGHTS };
    let mut out = Vec::new();
    for right in rights {
        let t = Instant::now();
        let pair = load_pair(
            &dir.join(LEFT),
            &dir.join(right),
            Figures {
                tilt_axis_deg: Some(TILT_AXIS_DEG),
                ..Figures::default()
            },
            None,
        )?;
        let recon = reconstruct(&pair.left.image, &pair.right.image, &pair.geometry, &params)
            .map_err(|e| anyhow::anyhow!("{LEFT} + {right}: {e}"))?;
        let known = recon
            .height_um
            .data()
            .iter()
            .filter(|v| v.is_finite())
            .count();
        let interpolated: Vec<bool> = recon.confidence.data().iter().map(|&c| c == 0.0).collect();
        let n_interpolated = interpolated.iter().filter(|&&i| i).count();
        let share = |why: Unknown| {
            recon.unknown.iter().filter(|&&u| u == why).count() as f64 / recon.unknown.len() as f64
        };
        out.push((
            PairFigures {
                right: (*right).to_owned(),
                tilt_deg: pair.geometry.tilt_deg,
                coverage: known as f64 / recon.height_um.len() as f64,
                interpolated: n_interpolated as f64 / recon.height_um.len() as f64,
                left_right: share(Unknown::LeftRight),
                not_seen: share(Unknown::NotSeen),
                report: recon.report,
                wall_ms: t.elapsed().as_secs_f64() * 1e3,
                unknown: recon.unknown,
            },
            recon.height_um,
            interpolated,
        ));
    }
    Ok(out)
}

/// `sdsem-eval potamogeton`: the pairs in both modes, their pairwise agreement.
///
/// # Errors
/// When the data are missing or a reconstruction fails.
pub fn run(
    opts: &super::EvalOptions,
    mode: Option<Preset>,
    set: &[String],
    dump: Option<&Path>,
) -> anyhow::Result<()> {
    let dir = opts.data()?.join("potamogeton");
    let modes = mode.map_or(vec![Preset::Improved, Preset::Paper], |m| vec![m]);
    let mut json = Vec::new();
    for mode in modes {
        let series = reconstruct_series(&dir, mode, opts.quick, set)?;
        let m = format!("{mode:?}").to_lowercase();
        if let Some(dir) = dump {
            std::fs::create_dir_all(dir)?;
            for (f, height, _) in &series {
                let stem = format!("{m}_{}", f.right.trim_end_matches(".tif"));
                let bytes: Vec<u8> = height.data().iter().flat_map(|v| v.to_le_bytes()).collect();
                std::fs::write(dir.join(format!("{stem}_height.f32")), bytes)?;
                let codes: Vec<u8> = f.unknown.iter().map(|u| u.code()).collect();
                std::fs::write(dir.join(format!("{stem}_unknown.u8")), codes)?;
            }
        }
        let mut agreements = Vec::new();
        for (f, _, _) in &series {
            if !opts.json {
                let t = &f.report.timings;
                let d = &f.report.dense.timings;
                println!(
                    "{m:<8} {LEFT} + {} (θ {:.0}°) | cover {:>5.1} %{} (unknown: left-right {:.1} %, not seen {:.1} %) | heights {:>6.2} … {:>6.2} µm | inliers {} rect err {:.2} px | sparse {:>5.0} ms dense {:>5.0} ms (BP {:.0}, re-assign {:.0}, refine {:.0}, LR {:.0}, filter {:.0}) depth {:>4.0} ms | {:.1} s wall",
                    f.right,
                    f.tilt_deg,
                    100.0 * f.coverage,
                    if f.interpolated > 0.0 {
                        format!(" ({:.1} % interpolated)", 100.0 * f.interpolated)
                    } else {
                        String::new()
                    },
                    100.0 * f.left_right,
                    100.0 * f.not_seen,
                    f.report.depth.height_p01_um,
                    f.report.depth.height_p99_um,
                    f.report.sparse.inliers,
                    f.report.sparse.final_error_px,
                    t.sparse_ms,
                    t.dense_ms,
                    d.matching_ms,
                    d.reassign_ms,
                    d.refine_ms,
                    d.consistency_ms,
                    d.filter_ms,
                    t.depth_ms,
                    f.wall_ms / 1e3
                );
            }
        }
        for i in 0..series.len() {
            for j in i + 1..series.len() {
                let a = agreement(&series[i].1, &series[j].1);
                let ok = a.rmse_um <= TARGET_RMSE_UM && a.common >= TARGET_COMMON;
                // Of the common area, the share interpolated in either map.
                let either = series[i]
                    .2
                    .iter()
                    .zip(&series[j].2)
                    .zip(series[i].1.data().iter().zip(series[j].1.data()))
                    .filter(|((p, q), (x, y))| (**p || **q) && x.is_finite() && y.is_finite())
                    .count() as f64
                    / series[i].1.len() as f64;
                if !opts.json {
                    println!(
                        "{m:<8} (0°, +{:.0}°) vs (0°, +{:.0}°): RMSE {:.2} µm, median {:.2} µm after plane removal, over {:.1} % of the image{} (scale {:.4}, then RMSE {:.2} µm) | {}",
                        series[i].0.tilt_deg,
                        series[j].0.tilt_deg,
                        a.rmse_um,
                        a.median_um,
                        100.0 * a.common,
                        if either > 0.0 {
                            format!(" ({:.1} % interpolated in either map)", 100.0 * either)
                        } else {
                            String::new()
                        },
                        a.scale,
                        a.rmse_scaled_um,
                        if ok {
                            "ok".to_owned()
                        } else {
                            format!(
                                "misses the target (≤ {TARGET_RMSE_UM} µm over ≥ {:.0} %)",
                                100.0 * TARGET_COMMON
                            )
                        }
                    );
                }
                agreements.push(serde_json::json!({
                    "a": series[i].0.right, "b": series[j].0.right, "agreement": a,
                    "interpolated_in_either": either,
                }));
            }
        }
        json.push(serde_json::json!({
            "mode": m,
            "pairs": series.iter().map(|(f, _, _)| f).collect::<Vec<_>>(),
            "agreement": agreements,
        }));
    }
    if opts.json {
        println!("{}", serde_json::to_string_pretty(&json)?);
    } else {
        println!(
            "target (issue 33): pairwise RMSE ≤ {TARGET_RMSE_UM} µm after plane removal over ≥ {:.0} % of the image (grain ≈ 43 µm high)",
            100.0 * TARGET_COMMON
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn agreement_ignores_a_plane_and_measures_the_rest() {
        let a = Image::from_fn(40, 30, |x, y| ((x * 7 + y * 3) % 5) as f32);
        let b = Image::from_fn(40, 30, |x, y| {
            if x < 4 {
                f32::NAN
            } else {
                a.get(x, y) + 2.0 + 0.1 * x as f32 - 0.05 * y as f32
            }
        });
        let g = agreement(&a, &b);
        assert!(g.rmse_um < 1e-4, "{g:?}");
        assert!((g.common - 36.0 / 40.0).abs() < 1e-12);
        let c = Image::from_fn(40, 30, |x, y| {
            a.get(x, y) + if (x + y) % 2 == 0 { 1.0 } else { -1.0 }
        });
        let g = agreement(&a, &c);
        assert!((g.rmse_um - 1.0).abs() < 0.01, "{g:?}");
    }

    #[test]
    fn a_scale_between_the_maps_is_found_and_removed() {
        let a = Image::from_fn(40, 30, |x, y| ((x * 7 + y * 3) % 5) as f32 * 10.0);
        // b: a's heights 2 % smaller, on another plane.
        let b = Image::from_fn(40, 30, |x, y| a.get(x, y) / 1.02 + 1.0 + 0.1 * y as f32);
        let g = agreement(&a, &b);
        assert!(g.rmse_um > 0.1, "{g:?}");
        assert!((g.scale - 1.02).abs() < 1e-4, "{g:?}");
        assert!(g.rmse_scaled_um < 1e-3, "{g:?}");
    }
}
