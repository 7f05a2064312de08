//! SIFT keypoints and descriptors (Lowe, IJCV 2004), following the parameters and
//! algorithms of Rey-Otero & Delbracio, "Anatomy of the SIFT method", IPOL 2014.
//!
//! Pipeline: [`scale_space`] (Gaussian octaves, DoG) → [`detector`] (3-D extrema,
//! quadratic refinement, contrast and edge tests) → [`orientation`] (36-bin histogram)
//! → [`descriptor`] (4×4×8, clipped at 0.2, bytes). Scale space, detection and description
//! run in parallel with rayon.

pub mod descriptor;
pub mod detector;
pub mod orientation;
pub mod scale_space;

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

pub use descriptor::DESCRIPTOR_LEN;
use scale_space::ScaleSpace;
pub use scale_space::ScaleSpaceBuffers;

use crate::vision::Image;

/// Parameters of SIFT; names and defaults as in IPOL "Anatomy of the SIFT method", Table 4.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SiftParams {
    /// Number of scales per octave, `n_spo` (default 3). More scales find more, less stable keypoints.
    pub n_spo: usize,
    /// Upper bound on the number of octaves, `n_oct` (default 8); the image size usually decides first.
    pub n_oct_max: usize,
    /// Inter-sample distance of the first octave, `δ_min`, in input pixels (default 0.5: the
    /// image is first upsampled ×2, as Lowe does). 1.0 skips the upsampling: ~4× faster, fewer
    /// small-scale keypoints.
    pub delta_min: f64,
    /// Blur of the first scale-space image, `σ_min`, in input pixels (default 0.8).
    pub sigma_min: f64,
    /// Assumed blur of the input image, `σ_in`, in input pixels (default 0.5).
    pub sigma_in: f64,
    /// DoG contrast threshold `C_DoG` for images in `[0, 1]` and 3 scales per octave
    /// (default 0.04/3, Lowe's value; scaled for other `n_spo`). Higher: fewer, stronger keypoints.
    pub c_dog: f64,
    /// Edge threshold `C_edge`, the largest ratio of principal curvatures (default 10).
    pub c_edge: f64,
    /// Bins of the orientation histogram, `n_bins` (default 36).
    pub n_bins: usize,
    /// Gaussian window of the orientation histogram in units of σ, `λ_ori` (default 1.5).
    pub lambda_ori: f64,
    /// Secondary orientations kept above `t` × the highest peak (default 0.8).
    pub t_ori: f64,
    /// Descriptor patch half-width in units of σ per histogram side, `λ_descr` (default 6).
    pub lambda_descr: f64,
    /// Spatial histograms per side, `n_hist` (default 4). Only 4 (with `n_ori` 8) is supported.
    pub n_hist: usize,
    /// Orientation bins per histogram, `n_ori` (default 8).
    pub n_ori: usize,
    /// Keep at most this many keypoints, the ones of highest |DoG| contrast (0 = all; default
    /// 0). Bounds the matching time on very textured images.
    pub max_keypoints: usize,
}

impl Default for SiftParams {
    fn default() -> Self {
        Self {
            n_spo: 3,
            n_oct_max: 8,
            delta_min: 0.5,
            sigma_min: 0.8,
            sigma_in: 0.5,
            c_dog: 0.04 / 3.0,
            c_edge: 10.0,
            n_bins: 36,
            lambda_ori: 1.5,
            t_ori: 0.8,
            lambda_descr: 6.0,
            n_hist: 4,
            n_ori: 8,
            max_keypoints: 0,
        }
    }
}

/// A SIFT keypoint with its descriptor. Coordinates in input pixels (x right, y down,
/// pixel centres at integers).
#[derive(Debug, Clone, PartialEq)]
pub struct Keypoint {
    pub x: f64,
    pub y: f64,
    /// Scale σ in input pixels.
    pub sigma: f64,
    /// Reference orientation, radians in `[0, 2π)`, from +x towards +y.
    pub theta: f64,
    /// Interpolated DoG value ω (contrast; sign tells blob polarity).
    pub response: f64,
    pub descriptor: [u8; DESCRIPTOR_LEN],
}

/// Why SIFT cannot run with these parameters.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SiftParamsError {
    #[error(
        "SIFT descriptor layout {n_hist}×{n_hist}×{n_ori} is not supported: only 4×4×8 (128 values)"
    )]
    Layout { n_hist: usize, n_ori: usize },
    #[error("SIFT parameter {name} = {value} is out of range: {expected}")]
    OutOfRange {
        name: &'static str,
        value: f64,
        expected: &'static str,
    },
}

impl SiftParams {
    /// Checks the parameters once, before any work.
    ///
    /// # Errors
    /// [`SiftParamsError`] naming the first bad parameter.
    pub fn validate(&self) -> Result<(), SiftParamsError> {
        if self.n_hist * self.n_hist * self.n_ori != DESCRIPTOR_LEN || self.n_hist != 4 {
            return Err(SiftParamsError::Layout {
                n_hist: self.n_hist,
                n_ori: self.n_ori,
            });
        }
        let checks: [(&'static str, f64, bool, &'static str); 7] = [
            ("n_spo", self.n_spo as f64, self.n_spo >= 1, "at least 1"),
            (
                "delta_min",
                self.delta_min,
                self.delta_min > 0.0 && self.delta_min <= 2.0,
                "in (0, 2]",
            ),
            (
                "sigma_min",
                self.sigma_min,
                self.sigma_min > self.sigma_in,
                "greater than sigma_in",
            ),
            ("c_dog", self.c_dog, self.c_dog >= 0.0, "non-negative"),
            ("c_edge", self.c_edge, self.c_edge > 0.0, "positive"),
            ("n_bins", self.n_bins as f64, self.n_bins >= 3, "at least 3"),
            (
                "lambda_ori",
                self.lambda_ori,
                self.lambda_ori > 0.0,
                "positive",
            ),
        ];
        for (name, value, ok, expected) in checks {
            if !ok || !value.is_finite() {
                return Err(SiftParamsError::OutOfRange {
                    name,
                    value,
                    expected,
                });
            }
        }
        if self.lambda_descr.is_nan() || self.lambda_descr <= 0.0 {
            return Err(SiftParamsError::OutOfRange {
                name: "lambda_descr",
                value: self.lambda_descr,
                expected: "positive",
            });
        }
        Ok(())
    }
}

/// Detects SIFT keypoints in `image` (samples in `[0, 1]`) and computes their descriptors.
///
/// A keypoint with several dominant orientations appears once per orientation (Lowe §5).
/// Keypoints whose descriptor patch leaves the image are dropped. The output order is
/// deterministic (by octave, scale, row, column, orientation) whatever the thread count.
///
/// # Errors
/// [`SiftParamsError`] for invalid parameters.
pub fn sift(image: &Image, params: &SiftParams) -> Result<Vec<Keypoint>, SiftParamsError> {
    sift_with(image, params, &mut ScaleSpaceBuffers::default())
}

/// [`sift`] with the scale space's working memory in `buffers`, which keep it for the next
/// image: the same keypoints as with fresh buffers.
///
/// # Errors
/// [`SiftParamsError`] for invalid parameters.
pub fn sift_with(
    image: &Image,
    params: &SiftParams,
    buffers: &mut ScaleSpaceBuffers,
) -> Result<Vec<Keypoint>, SiftParamsError> {
    params.validate()?;
    let mut ss = ScaleSpace::new(image.dimensions(), params, buffers);
    // Octave by octave in the same planes: detection reads each octave while it is whole.
    let mut extrema = Vec::new();
    for o in 0..ss.octaves.len() {
        ss.build_octave(o, image, params);
        ss.with_octave(o, |oct| {
            extrema.extend(detector::detect_octave(o, oct, params));
        });
    }
    if params.max_keypoints > 0 && extrema.len() > params.max_keypoints {
        // Keep the strongest; stable sort on a total order keeps the result deterministic.
        extrema.sort_by(|a, b| b.response.abs().total_cmp(&a.response.abs()));
        extrema.truncate(params.max_keypoints);
        extrema.sort_by(|a, b| {
            (a.octave, a.slot)
                .cmp(&(b.octave, b.slot))
                .then(a.y_oct.total_cmp(&b.y_oct))
                .then(a.x_oct.total_cmp(&b.x_oct))
        });
    }
    // The keypoints of one image (octave and slot) at a time: its gradient field, computed
    // once into two planes that every image reuses, serves their orientations and descriptors.
    let key = |i: &usize| (extrema[*i].octave, extrema[*i].slot);
    let mut by_image: Vec<usize> = (0..extrema.len()).collect();
    by_image.sort_by_key(key);
    let mut described: Vec<Vec<Keypoint>> = vec![Vec::new(); extrema.len()];
    for group in by_image.chunk_by(|a, b| key(a) == key(b)) {
        let (o, s) = key(&group[0]);
        let size = (ss.octaves[o].width, ss.octaves[o].height);
        let (img, mag, ori) = ss.kept_slot_and_two_planes(o, s);
        let grad = orientation::GradField::new(img, size, mag, ori);
        let keypoints: Vec<(usize, Vec<Keypoint>)> = group
            .par_iter()
            .map(|&i| (i, describe(&grad, &extrema[i], params)))
            .collect();
        for (i, k) in keypoints {
            described[i] = k;
        }
    }
    Ok(described.into_iter().flatten().collect())
}

/// The keypoints of one extremum: one per dominant orientation whose descriptor patch lies
/// in the image.
fn describe(
    grad: &orientation::GradField<'_>,
    e: &detector::Extremum,
    params: &SiftParams,
) -> Vec<Keypoint> {
    orientation::orientations(grad, e, params)
        .into_iter()
        .filter_map(|theta| {
            descriptor::describe(grad, e, theta, params).map(|descriptor| Keypoint {
                x: e.x,
                y: e.y,
                sigma: e.sigma,
                theta,
                response: e.response,
                descriptor,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Smooth random blobs: a texture with many well-separated extrema.
    pub(crate) fn blobs(w: usize, h: usize, seed: u64) -> Image {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let centres: Vec<(f64, f64, f64, f64)> = (0..(w * h / 150))
            .map(|_| {
                (
                    rng.random_range(0.0..w as f64),
                    rng.random_range(0.0..h as f64),
                    rng.random_range(1.5..4.0),
                    if rng.random_bool(0.5) { 1.0 } else { -1.0 } * rng.random_range(0.5..1.0),
                )
            })
            .collect();
        let mut img = Image::filled(w, h, 0.5);
        for (cx, cy, s, a) in centres {
            let r = (3.0 * s) as isize;
            for y in (cy as isize - r).max(0)..(cy as isize + r + 1).min(h as isize) {
                for x in (cx as isize - r).max(0)..(cx as isize + r + 1).min(w as isize) {
                    let d2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
                    let v = img.get(x as usize, y as usize)
                        + (0.4 * a * (-d2 / (2.0 * s * s)).exp()) as f32;
                    img.set(x as usize, y as usize, v);
                }
            }
        }
        img
    }

    #[test]
    fn blank_image_has_no_keypoints() {
        let kp = sift(&Image::filled(200, 150, 0.3), &SiftParams::default()).unwrap();
        assert!(kp.is_empty());
    }

    #[test]
    fn finds_isolated_blob_at_its_centre_and_scale() {
        // One Gaussian blob of σ = 4 px: a DoG extremum at its centre with σ near 4·… (Lowe:
        // a blob of std s is detected at scale ≈ s·√2 for the normalised Laplacian).
        let img = Image::from_fn(96, 96, |x, y| {
            let d2 = (x as f64 - 47.3).powi(2) + (y as f64 - 50.6).powi(2);
            (0.2 + 0.6 * (-d2 / (2.0 * 16.0)).exp()) as f32
        });
        let kp = sift(&img, &SiftParams::default()).unwrap();
        let best = kp
            .iter()
            .max_by(|a, b| a.response.abs().total_cmp(&b.response.abs()))
            .expect("a keypoint");
        assert!(
            (best.x - 47.3).abs() < 0.3 && (best.y - 50.6).abs() < 0.3,
            "{best:?}"
        );
        assert!(best.sigma > 3.5 && best.sigma < 7.0, "σ = {}", best.sigma);
    }

    #[test]
    fn keypoints_follow_a_shift() {
        let img = blobs(160, 120, 3);
        // Shift by (7, −4) whole pixels: the same keypoints, moved.
        let shifted = Image::from_fn(160, 120, |x, y| {
            img.get_clamped(x as isize - 7, y as isize + 4)
        });
        let p = SiftParams::default();
        let a = sift(&img, &p).unwrap();
        let b = sift(&shifted, &p).unwrap();
        assert!(a.len() > 20, "{} keypoints", a.len());
        let inside: Vec<_> = a
            .iter()
            .filter(|k| k.x > 30.0 && k.x < 130.0 && k.y > 30.0 && k.y < 90.0)
            .collect();
        let found = inside
            .iter()
            .filter(|k| {
                b.iter().any(|q| {
                    (q.x - k.x - 7.0).abs() < 0.1
                        && (q.y - k.y + 4.0).abs() < 0.1
                        && q.descriptor == k.descriptor
                })
            })
            .count();
        assert!(
            found * 10 >= inside.len() * 9,
            "{found} of {}",
            inside.len()
        );
    }

    /// Buffers that served a larger and then a smaller image give the keypoints that fresh ones
    /// give, with and without the keypoint cap.
    #[test]
    fn reused_buffers_give_the_keypoints_of_fresh_ones() {
        let (large, small) = (blobs(200, 150, 5), blobs(130, 97, 6));
        let mut buffers = ScaleSpaceBuffers::default();
        for params in [
            SiftParams::default(),
            SiftParams {
                delta_min: 1.0,
                sigma_min: 1.6,
                max_keypoints: 12,
                ..SiftParams::default()
            },
        ] {
            for img in [&large, &small, &large] {
                let fresh = sift(img, &params).unwrap();
                assert!(!fresh.is_empty());
                assert_eq!(sift_with(img, &params, &mut buffers).unwrap(), fresh);
            }
        }
    }

    #[test]
    fn rejects_unsupported_layout() {
        let p = SiftParams {
            n_ori: 6,
            ..SiftParams::default()
        };
        assert!(matches!(p.validate(), Err(SiftParamsError::Layout { .. })));
    }
}
