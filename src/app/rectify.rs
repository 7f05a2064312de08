//! `sdsem rectify LEFT RIGHT --out DIR [--tilt-axis DEG]`: the sparse stage alone (DESIGN §4).

use std::path::Path;

use image::codecs::png::PngEncoder;
use image::{ExtendedColorType, ImageEncoder};

use crate::export::atomic::OutputDir;

use crate::vision::Image;
use crate::vision::rectify::RectifyError;
use crate::vision::sparse::{
    Correspondence, Side, SparseError, SparseParams, SparseResult, rectify_pair,
};

/// Loads a grey micrograph as samples in `[0, 1]` ([`crate::imaging::file::load_image`]:
/// TIFF, PNG, JPEG or BMP; colour refused).
///
/// # Errors
/// When the file cannot be read or decoded, naming the file.
pub fn load_gray(path: &Path) -> anyhow::Result<Image> {
    Ok(crate::imaging::file::load_image(path)?)
}

/// `sdsem rectify`: loads both micrographs, runs the sparse stage, and writes into `out`
/// `rectified_left.png`, `rectified_right.png` (the canvas, 0 where an image does not reach),
/// `matches.png` (both originals side by side, inlier matches as lines) and
/// `rectification.json` (figures, homographies, timings; see [`rectification_json`]).
///
/// # Errors
/// When a file cannot be read or written, or the sparse stage refuses the pair (its one-line
/// cause is the error message).
pub fn run_rectify(
    left: &Path,
    right: &Path,
    out: &OutputDir,
    tilt_axis_deg: Option<f64>,
    params: &SparseParams,
) -> anyhow::Result<RectifyOutputs> {
    let l = load_gray(left)?;
    let r = load_gray(right)?;
    let pair =
        rectify_pair(&l, &r, tilt_axis_deg, params).map_err(|e| name_files(e, left, right, ""))?;
    let [left_name, right_name, matches_name, json_name] = FILES;
    let written = (|| -> anyhow::Result<()> {
        write_gray_png(out, left_name, &pair.left.filled(0.0))?;
        write_gray_png(out, right_name, &pair.right.filled(0.0))?;
        let matches = draw_matches(&l, &r, &pair.sparse.inliers);
        out.write(matches_name, |w| {
            PngEncoder::new(w)
                .write_image(
                    matches.as_raw(),
                    matches.width(),
                    matches.height(),
                    ExtendedColorType::Rgb8,
                )
                .map_err(std::io::Error::other)
        })?;
        let json = rectification_json(&pair.sparse, tilt_axis_deg, params);
        crate::export::report::write_report_atomic(out.file(json_name), &json)?;
        Ok(())
    })();
    if let Err(e) = written {
        for name in FILES {
            out.remove(name);
        }
        return Err(e);
    }
    Ok(RectifyOutputs {
        files: FILES.map(|name| out.join(name)).to_vec(),
        inliers: pair.sparse.inliers.len(),
        initial_error_px: pair.sparse.rectification.initial_error_px,
        final_error_px: pair.sparse.rectification.final_error_px,
    })
}

/// The files `sdsem rectify` writes, in order.
pub const FILES: [&str; 4] = [
    "rectified_left.png",
    "rectified_right.png",
    "matches.png",
    "rectification.json",
];

/// What `sdsem rectify` wrote, and the figures of its summary line.
#[derive(Debug, Clone, PartialEq)]
pub struct RectifyOutputs {
    pub files: Vec<std::path::PathBuf>,
    /// Inlier matches the rectification used.
    pub inliers: usize,
    pub initial_error_px: f64,
    pub final_error_px: f64,
}

/// The stage's refusal with the file(s) it concerns: the one image at fault, or the pair.
/// `stage` prefixes the cause (for example "sparse stage: " inside a whole reconstruction).
pub(crate) fn name_files(e: SparseError, left: &Path, right: &Path, stage: &str) -> anyhow::Error {
    let side = match &e {
        SparseError::ImageTooSmall { side, .. } | SparseError::NoTexture { side, .. } => {
            Some(*side)
        }
        _ => None,
    };
    let hint = tilt_axis_hint(&e).unwrap_or_default();
    match side {
        Some(Side::Left) => anyhow::anyhow!("{}: {stage}{e}", left.display()),
        Some(Side::Right) => anyhow::anyhow!("{}: {stage}{e}", right.display()),
        None => anyhow::anyhow!(
            "{} and {}: {stage}{e}{hint}",
            left.display(),
            right.display()
        ),
    }
}

/// The remedy for a rectification the tilt axis contradicts: the matches ask for other rows
/// than the given φ, or no rectification along φ is plausible — most often a wrong φ.
pub(crate) fn tilt_axis_hint(e: &SparseError) -> Option<&'static str> {
    matches!(
        e,
        SparseError::Rectify(
            RectifyError::TiltAxisMismatch { .. } | RectifyError::Implausible { .. }
        )
    )
    .then_some(
        " — check the tilt axis (--tilt-axis DEG, or reconstruction.tilt_axis_deg): the \
         direction of the stage tilt axis in the image, from +x towards +y",
    )
}

fn matrix_rows(m: &nalgebra::Matrix3<f64>) -> [[f64; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)]))
}

/// The content of `rectification.json` (DESIGN §4): counts, errors, ORSA figures, both
/// homographies as row-major nested arrays (original pixel → rectified canvas), canvas, the
/// orientation rule and per-step timings.
#[must_use]
pub fn rectification_json(
    r: &SparseResult,
    tilt_axis_deg: Option<f64>,
    params: &SparseParams,
) -> serde_json::Value {
    let rec = &r.rectification;
    serde_json::json!({
        "image_size": [r.image_size.0, r.image_size.1],
        "keypoints_left": r.keypoints_left,
        "keypoints_right": r.keypoints_right,
        "matches": r.matches.len(),
        "inliers": r.orsa_inliers,
        "inliers_used": r.inliers.len(),
        "refined_inliers": r.refined,
        "rectification_outliers": rec.outliers.len(),
        "initial_error_px": rec.initial_error_px,
        "final_error_px": rec.final_error_px,
        "error_definition": "as Monasse's reference code (IPOL 2011) prints it and the SD-SEM paper's Table 2 reports it: RMS Sampson error of the inliers used, for the rectifying fundamental matrix, before (all rotations 0, = RMS(y_left − y_right)/√2) and after the optimisation; final_dy_rms_px is the RMS of y_left − y_right on the canvas",
        "final_dy_rms_px": rec.final_dy_rms_px,
        "H_left": matrix_rows(&rec.h_left),
        "H_right": matrix_rows(&rec.h_right),
        "canvas_size": [rec.canvas.0, rec.canvas.1],
        "canvas_offset_px": [rec.canvas_offset.0, rec.canvas_offset.1],
        "right_shift_px": rec.right_shift_px,
        "fundamental_model": r.model,
        "fallback_reason": r.fallback_reason,
        "second_attempt": r.second_attempt,
        "F": matrix_rows(&r.f),
        "log10_NFA": r.log10_nfa,
        // Far below f64's range on good pairs (10^-3000): written as a power of ten.
        "NFA": format!("10^{:.1}", r.log10_nfa),
        "threshold_px": r.threshold_px,
        "orsa_iterations": r.orsa_iterations,
        "orsa_seed": params.orsa.seed,
        "focal_px": rec.focal_px,
        "rotations_deg": {
            "left_y": rec.params.left_y.to_degrees(),
            "left_z": rec.params.left_z.to_degrees(),
            "right_x": rec.params.right_x.to_degrees(),
            "right_y": rec.params.right_y.to_degrees(),
            "right_z": rec.params.right_z.to_degrees(),
        },
        "lm_iterations": rec.iterations,
        "tilt_axis_deg": tilt_axis_deg,
        "n_rectified": r.n_rectified,
        "disparity_rule": if r.n_rectified.is_some() {
            "d = x_right − x_left on the canvas grows with height (towards the beam) when n_rectified[0] > 0"
        } else {
            "tilt axis unknown: the sign of height versus d = x_right − x_left is undetermined"
        },
        "timings_ms": r.timings,
        "inlier_correspondences": r.inliers,
    })
}

/// Writes `img` as an 8-bit grey PNG named `name` in `out`.
fn write_gray_png(out: &OutputDir, name: &str, img: &Image) -> anyhow::Result<()> {
    let (w, h) = img.dimensions();
    let (w, h) = (u32::try_from(w)?, u32::try_from(h)?);
    let bytes = img.to_u8();
    out.write(name, |file| {
        PngEncoder::new(file)
            .write_image(&bytes, w, h, ExtendedColorType::L8)
            .map_err(std::io::Error::other)
    })?;
    Ok(())
}

/// Both originals side by side (left | right) with each inlier match drawn as a line.
#[must_use]
pub fn draw_matches(left: &Image, right: &Image, inliers: &[Correspondence]) -> image::RgbImage {
    let (wl, hl) = left.dimensions();
    let (wr, hr) = right.dimensions();
    let (w, h) = (wl + wr, hl.max(hr));
    #[allow(clippy::cast_possible_truncation)]
    let mut canvas = image::RgbImage::new(w as u32, h as u32);
    for (img, x0) in [(left, 0usize), (right, wl)] {
        let bytes = img.to_u8();
        for y in 0..img.height() {
            for x in 0..img.width() {
                let v = bytes[y * img.width() + x];
                #[allow(clippy::cast_possible_truncation)]
                canvas.put_pixel((x0 + x) as u32, y as u32, image::Rgb([v, v, v]));
            }
        }
    }
    for (i, c) in inliers.iter().enumerate() {
        // A few distinct hues so neighbouring lines can be told apart.
        let colour = [[40, 220, 40], [240, 200, 0], [0, 200, 255], [255, 80, 200]][i % 4];
        draw_line(
            &mut canvas,
            c.left,
            [c.right[0] + wl as f64, c.right[1]],
            image::Rgb(colour),
        );
    }
    canvas
}

fn draw_line(img: &mut image::RgbImage, a: [f64; 2], b: [f64; 2], colour: image::Rgb<u8>) {
    let steps = (b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil().max(1.0);
    #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
    let n = steps as usize;
    for k in 0..=n {
        let t = k as f64 / steps;
        let (x, y) = (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
        if x >= 0.0 && y >= 0.0 && x < f64::from(img.width()) && y < f64::from(img.height()) {
            #[allow(clippy::cast_possible_truncation, clippy::cast_sign_loss)]
            img.put_pixel(x as u32, y as u32, colour);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use anyhow::Context;

    fn save_png(img: &Image, path: &Path) -> anyhow::Result<()> {
        let (w, h) = img.dimensions();
        let buf = image::GrayImage::from_raw(u32::try_from(w)?, u32::try_from(h)?, img.to_u8())
            .context("image buffer size")?;
        Ok(buf.save(path)?)
    }

    fn prepared(out: &Path) -> OutputDir {
        crate::app::output::prepare_dir(out, &FILES, true).unwrap()
    }

    #[test]
    fn rectify_command_writes_images_and_json() {
        let pair = crate::vision::sparse::tests::sem_pair(256, 200, -90.0, (-4.0, 4.0), 0.5, false);
        let dir = tempfile::tempdir().unwrap();
        let (l, r) = (dir.path().join("l.png"), dir.path().join("r.png"));
        save_png(&pair.left, &l).unwrap();
        save_png(&pair.right, &r).unwrap();
        let out = dir.path().join("out");
        run_rectify(
            &l,
            &r,
            &prepared(&out),
            Some(-90.0),
            &SparseParams::default(),
        )
        .unwrap();
        for f in ["rectified_left.png", "rectified_right.png", "matches.png"] {
            assert!(image::open(out.join(f)).is_ok(), "{f}");
        }
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("rectification.json")).unwrap())
                .unwrap();
        for key in [
            "keypoints_left",
            "keypoints_right",
            "matches",
            "inliers",
            "initial_error_px",
            "final_error_px",
            "H_left",
            "H_right",
            "NFA",
            "threshold_px",
            "timings_ms",
        ] {
            assert!(json.get(key).is_some(), "missing {key}");
        }
        // H_left / H_right from the JSON put the true correspondences on the same row.
        let h = |k: &str| {
            let m = &json[k];
            nalgebra::Matrix3::from_fn(|i, j| m[i][j].as_f64().unwrap())
        };
        let (hl, hr) = (h("H_left"), h("H_right"));
        let mut dy: Vec<f64> = pair
            .truth
            .iter()
            .map(|c| {
                let a = hl * nalgebra::Vector3::new(c.left[0], c.left[1], 1.0);
                let b = hr * nalgebra::Vector3::new(c.right[0], c.right[1], 1.0);
                (a.y / a.z - b.y / b.z).abs()
            })
            .collect();
        dy.sort_by(f64::total_cmp);
        assert!(dy[dy.len() / 2] < 0.3, "median |Δy| {}", dy[dy.len() / 2]);
        // The PNG canvas matches the canvas size in the JSON.
        let rl = image::open(out.join("rectified_left.png")).unwrap();
        assert_eq!(
            json["canvas_size"][0].as_u64().unwrap(),
            u64::from(rl.width())
        );
    }

    #[test]
    fn bad_inputs_are_refused_naming_the_file_and_the_cause() {
        let dir = tempfile::tempdir().unwrap();
        let pair = crate::vision::sparse::tests::sem_pair(200, 160, -90.0, (-3.0, 3.0), 0.0, false);
        let (l, r) = (dir.path().join("left.png"), dir.path().join("right.png"));
        save_png(&pair.left, &l).unwrap();
        save_png(&pair.right, &r).unwrap();
        let notes = dir.path().join("notes.txt");
        std::fs::write(&notes, "hello").unwrap();
        let small = dir.path().join("small.png");
        save_png(
            &Image::from_fn(180, 160, |x, y| pair.right.get(x, y)),
            &small,
        )
        .unwrap();
        let blank = dir.path().join("blank.png");
        save_png(&Image::filled(200, 160, 0.4), &blank).unwrap();
        let out = dir.path().join("out");
        let p = SparseParams::default();
        let out_dir = prepared(&out);
        // What `main` prints: the cause chain on one line.
        let fail = |a: &Path, b: &Path| {
            let e = run_rectify(a, b, &out_dir, Some(-90.0), &p).unwrap_err();
            format!("{e:#}")
        };
        let e = fail(&l, &notes);
        assert!(e.contains("notes.txt") && e.contains("not an image"), "{e}");
        let e = fail(&dir.path().join("missing.tif"), &r);
        assert!(
            e.contains("missing.tif") && e.contains("cannot read"),
            "{e}"
        );
        let e = fail(&l, &small);
        assert!(
            e.contains("left.png")
                && e.contains("small.png")
                && e.contains("differ in size: 200×160 vs 180×160"),
            "{e}"
        );
        let e = fail(&l, &blank);
        assert!(
            e.starts_with(&format!("{}: right image has no texture", blank.display())),
            "{e}"
        );
        assert!(!e.contains('\n'), "{e}");
        assert_eq!(
            std::fs::read_dir(&out).unwrap().count(),
            0,
            "nothing is written for a refused pair"
        );
    }

    #[test]
    fn reads_png() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.png");
        image::GrayImage::from_raw(3, 2, vec![0, 51, 102, 153, 204, 255])
            .unwrap()
            .save(&p)
            .unwrap();
        let img = load_gray(&p).unwrap();
        assert_eq!(img.dimensions(), (3, 2));
        assert!((img.get(1, 0) - 0.2).abs() < 1e-3);
    }
}
