//! Every parallel (rayon) kernel of the vision core gives, bit for bit, what it gives on one
//! thread, on small random inputs of awkward sizes (rows that do not divide into the chunks);
//! the simplest kernels also against a serial loop written here. A kernel whose result depended
//! on how rayon splits the work would make `replay` differ from the recorded run.

use nalgebra::Matrix3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sdsem::testing::Texture;
use sdsem::vision::Image;
use sdsem::vision::dense::consistency::{left_right_check, reject_beyond};
use sdsem::vision::dense::dense_sift::{DenseSiftParams, dense_sift};
use sdsem::vision::dense::fill::fill_row_gaps;
use sdsem::vision::dense::reassign::near_discontinuity;
use sdsem::vision::dense::refine::{RefineParams, refine_flow, upsample_flow};
use sdsem::vision::dense::sift_flow::pyramid::{
    halve_descriptors, halve_image, halve_mask, upsample_offsets,
};
use sdsem::vision::dense::sift_flow::{FlowParams, sift_flow};
use sdsem::vision::dense::{DenseParams, dense_disparity};
use sdsem::vision::depth::{StereoGeometry, height_on_left_grid};
use sdsem::vision::filter::bilateral_grid::{BilateralParams, bilateral_filter};
use sdsem::vision::filter::blur::{gaussian_blur, gaussian_kernel, normalise_contrast};
use sdsem::vision::precision::{noise_sigma, predict};
use sdsem::vision::rectify::warp::warp;
use sdsem::vision::sparse::matching::{MatchParams, match_keypoints};
use sdsem::vision::sparse::sift::{SiftParams, sift};

/// Random cases per kernel.
const CASES: u64 = 6;

/// Runs `f` on a pool of `threads` threads.
fn on<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("a thread pool")
        .install(f)
}

/// `f` on one thread and on four: the results must be equal.
fn serial_and_parallel<T: Send>(f: impl Fn() -> T + Sync + Send) -> (T, T) {
    (on(1, &f), on(4, &f))
}

/// Equal bit for bit (NaN equals NaN; −0 differs from +0).
fn assert_same(what: &str, a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    if let Some(i) = (0..a.len()).find(|&i| a[i].to_bits() != b[i].to_bits()) {
        panic!(
            "{what}: sample {i} is {} serially, {} in parallel",
            a[i], b[i]
        );
    }
}

/// A size that does not fall on rayon's chunking: 9..=70 × 7..=48.
fn size(rng: &mut ChaCha8Rng) -> (usize, usize) {
    (rng.random_range(9..=70), rng.random_range(7..=48))
}

/// Value-noise texture with some pixel noise, about [0, 1].
fn textured(rng: &mut ChaCha8Rng, w: usize, h: usize) -> Image {
    let tex = Texture::new(rng.random());
    let noise: Vec<f32> = (0..w * h).map(|_| rng.random_range(-0.02..0.02)).collect();
    Image::from_fn(w, h, |x, y| {
        tex.at(x as f64, y as f64) as f32 + noise[y * w + x]
    })
}

/// `b(x) = a(x − shift)` with `shift` in whole pixels, on the same texture.
fn shifted_pair(seed: u64, w: usize, h: usize, shift: f64) -> (Image, Image) {
    let tex = Texture::new(seed);
    let a = Image::from_fn(w, h, |x, y| tex.at(x as f64, y as f64) as f32);
    let b = Image::from_fn(w, h, |x, y| tex.at(x as f64 - shift, y as f64) as f32);
    (a, b)
}

fn random_field(rng: &mut ChaCha8Rng, n: usize, lo: f32, hi: f32) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(lo..hi)).collect()
}

fn random_mask(rng: &mut ChaCha8Rng, n: usize, p_true: f64) -> Vec<bool> {
    (0..n).map(|_| rng.random_bool(p_true)).collect()
}

/// Symmetric (half-sample) mirroring into `[0, n)`, as the Gaussian blur documents it.
fn mirror(i: isize, n: usize) -> usize {
    let n = n as isize;
    let j = i.rem_euclid(2 * n);
    (if j >= n { 2 * n - 1 - j } else { j }) as usize
}

/// The obvious serial separable Gaussian blur: rows, then columns, mirrored borders.
fn gaussian_blur_reference(img: &Image, sigma: f64) -> Vec<f32> {
    let k = gaussian_kernel(sigma);
    let r = (k.len() / 2) as isize;
    let (w, h) = img.dimensions();
    let mut tmp = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0f32;
            for (i, &g) in k.iter().enumerate() {
                acc += g * img.get(mirror(x as isize + i as isize - r, w), y);
            }
            tmp[y * w + x] = acc;
        }
    }
    let mut out = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0f32;
            for (i, &g) in k.iter().enumerate() {
                acc += g * tmp[mirror(y as isize + i as isize - r, h) * w + x];
            }
            out[y * w + x] = acc;
        }
    }
    out
}

#[test]
fn gaussian_blur_equals_its_serial_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for _ in 0..CASES {
        let (w, h) = size(&mut rng);
        let img = textured(&mut rng, w, h);
        let sigma = rng.random_range(0.4..3.0);
        let (s, p) = serial_and_parallel(|| gaussian_blur(&img, sigma));
        assert_same("gaussian_blur", s.data(), p.data());
        let reference = gaussian_blur_reference(&img, sigma);
        for (i, (&got, &want)) in p.data().iter().zip(&reference).enumerate() {
            assert!(
                (got - want).abs() <= 1e-5,
                "{w}×{h} σ {sigma}: sample {i} {got} ≠ {want}"
            );
        }
    }
}

#[test]
fn contrast_normalisation_and_bilateral_grid_do_not_depend_on_threads() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for _ in 0..CASES {
        let (w, h) = size(&mut rng);
        let img = textured(&mut rng, w, h);
        let (s, p) = serial_and_parallel(|| normalise_contrast(&img, 0.8, 3.0));
        assert_same("normalise_contrast", s.data(), p.data());

        // A disparity-like field with holes, with and without confidence weights.
        let values = Image::from_fn(w, h, |x, y| {
            if (x * 7 + y * 3) % 11 == 0 {
                f32::NAN
            } else {
                10.0 * img.get(x, y) + x as f32 * 0.1
            }
        });
        let weights = Image::from_vec(w, h, random_field(&mut rng, w * h, 0.0, 1.0)).expect("size");
        let params = BilateralParams {
            sigma_s: rng.random_range(1.0..4.0),
            sigma_r: rng.random_range(0.5..3.0),
        };
        for weights in [None, Some(&weights)] {
            let (s, p) = serial_and_parallel(|| bilateral_filter(&values, weights, &params).0);
            assert_same("bilateral_filter", s.data(), p.data());
        }
    }
}

/// `snap` of the warp: a coordinate within 1e-6 px outside `[0, n − 1]` goes onto the border.
fn snap(c: f64, n: usize) -> f64 {
    let hi = n.saturating_sub(1) as f64;
    if c < 0.0 && c > -1e-6 {
        0.0
    } else if c > hi && c < hi + 1e-6 {
        hi
    } else {
        c
    }
}

#[test]
fn warp_equals_its_serial_reference() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for _ in 0..CASES {
        let (w, h) = size(&mut rng);
        let src = textured(&mut rng, w, h);
        let a = rng.random_range(-0.2..0.2f64);
        let hom = Matrix3::new(
            a.cos(),
            -a.sin(),
            rng.random_range(-5.0..5.0),
            a.sin(),
            a.cos(),
            rng.random_range(-5.0..5.0),
            rng.random_range(-1e-3..1e-3),
            rng.random_range(-1e-3..1e-3),
            1.0,
        );
        let (cw, ch) = size(&mut rng);
        let (s, p) = serial_and_parallel(|| warp(&src, &hom, cw, ch).expect("invertible"));
        assert_same("warp", s.image.data(), p.image.data());
        assert_eq!(s.valid, p.valid);
        let inv = hom.try_inverse().expect("invertible");
        for y in 0..ch {
            for x in 0..cw {
                let q = inv * nalgebra::Vector3::new(x as f64, y as f64, 1.0);
                let want = if q.z > 0.0 {
                    src.sample_bilinear(snap(q.x / q.z, w), snap(q.y / q.z, h))
                } else {
                    None
                };
                let got = p.image.get(x, y);
                match want {
                    Some(v) => assert_eq!(got.to_bits(), v.to_bits(), "({x}, {y})"),
                    None => assert!(got.is_nan() && !p.valid[y * cw + x], "({x}, {y}): {got}"),
                }
            }
        }
    }
}

#[test]
fn height_and_precision_do_not_depend_on_threads() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for _ in 0..CASES {
        let (w, h) = size(&mut rng);
        let disparity = Image::from_fn(w, h, |x, y| {
            if (x + 2 * y) % 13 == 0 {
                f32::NAN
            } else {
                3.0 + 0.05 * x as f32 - 0.02 * y as f32
            }
        });
        let shift = Matrix3::new(
            1.0,
            0.0,
            rng.random_range(-2.0..2.0),
            0.0,
            1.0,
            0.5,
            0.0,
            0.0,
            1.0,
        );
        let geometry = StereoGeometry {
            tilt_deg: rng.random_range(2.0..10.0),
            pixel_size_um: rng.random_range(0.01..1.0),
            tilt_axis_deg: rng.random_range(-90.0..90.0),
        };
        let (s, p) = serial_and_parallel(|| {
            height_on_left_grid(&disparity, &Matrix3::identity(), &shift, &geometry, w, h)
                .expect("valid geometry")
        });
        assert_same("height_on_left_grid", s.data(), p.data());

        let a = textured(&mut rng, w, h);
        let b = textured(&mut rng, w, h);
        let valid = random_mask(&mut rng, w * h, 0.9);
        let (s, p) = serial_and_parallel(|| noise_sigma(&a, Some(&valid)).map(f64::to_bits));
        assert_eq!(s, p, "noise_sigma");
        let (s, p) = serial_and_parallel(|| format!("{:?}", predict(&a, &b, 30.0, 2.0, 0.1)));
        assert_eq!(s, p, "predict");
    }
}

#[test]
fn pyramid_and_descriptor_kernels_do_not_depend_on_threads() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    for _ in 0..CASES {
        let (w, h) = size(&mut rng);
        let img = textured(&mut rng, w, h);
        let (s, p) = serial_and_parallel(|| halve_image(&img));
        assert_same("halve_image", s.data(), p.data());
        let params = DenseSiftParams {
            cell_size: rng.random_range(1..=3),
        };
        let (s, p) = serial_and_parallel(|| dense_sift(&img, &params));
        assert!(s.data() == p.data(), "dense_sift");
        let (hs, hp) = serial_and_parallel(|| halve_descriptors(&s));
        assert!(hs.data() == hp.data(), "halve_descriptors");
        let mask = random_mask(&mut rng, w * h, 0.7);
        let (s, p) = serial_and_parallel(|| halve_mask(&mask, w, h));
        assert_eq!(s, p, "halve_mask");
        let (wc, hc) = (w.div_ceil(2), h.div_ceil(2));
        let coarse = random_field(&mut rng, wc * hc, -4.0, 4.0);
        let (s, p) = serial_and_parallel(|| upsample_offsets(&coarse, wc, hc, w, h));
        assert_eq!(s, p, "upsample_offsets");
        let (s, p) = serial_and_parallel(|| upsample_flow(&coarse, wc, hc, w, h, 2.0));
        assert_same("upsample_flow", &s, &p);
    }
}

#[test]
fn consistency_fill_and_discontinuity_do_not_depend_on_threads() {
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    for _ in 0..CASES {
        let (w, h) = size(&mut rng);
        let field = |rng: &mut ChaCha8Rng| {
            Image::from_vec(w, h, random_field(rng, w * h, -3.0, 3.0)).expect("size")
        };
        let (u, v, ur, vr) = (
            field(&mut rng),
            field(&mut rng),
            field(&mut rng),
            field(&mut rng),
        );
        let (s, p) = serial_and_parallel(|| left_right_check(&u, &v, &ur, &vr, 1.0));
        assert_same(
            "left_right_check residual",
            s.residual.data(),
            p.residual.data(),
        );
        assert_eq!(s.rejected, p.rejected, "left_right_check");
        let smooth = random_mask(&mut rng, w * h, 0.5);
        let (s2, p2) =
            serial_and_parallel(|| reject_beyond(&s.residual, (0.5, 1.5), Some(&smooth)));
        assert_eq!(s2, p2, "reject_beyond");

        let mut holes = Image::from_fn(w, h, |x, y| 0.1 * x as f32 + 0.01 * y as f32);
        for i in 0..w * h {
            if rng.random_bool(0.3) {
                holes.data_mut()[i] = f32::NAN;
            }
        }
        let inside = random_mask(&mut rng, w * h, 0.9);
        let (s, p) = serial_and_parallel(|| {
            let mut d = holes.clone();
            let filled = fill_row_gaps(&mut d, &inside, 6);
            (d, filled)
        });
        assert_same("fill_row_gaps", s.0.data(), p.0.data());
        assert_eq!(s.1, p.1, "fill_row_gaps filled");

        let reliable = random_mask(&mut rng, w * h, 0.8);
        let (s, p) = serial_and_parallel(|| near_discontinuity(u.data(), &reliable, w, h, 1.0, 2));
        assert_eq!(s, p, "near_discontinuity");
    }
}

#[test]
fn flow_refinement_does_not_depend_on_threads() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for _ in 0..CASES {
        let (w, h) = size(&mut rng);
        let (a, b) = shifted_pair(rng.random(), w, h, 1.5);
        let u = random_field(&mut rng, w * h, 0.5, 2.5);
        let v = random_field(&mut rng, w * h, -0.5, 0.5);
        let valid = random_mask(&mut rng, w * h, 0.9);
        let params = RefineParams::default();
        let (s, p) =
            serial_and_parallel(|| refine_flow(&a, &b, Some(&valid), None, (&u, &v), 0, &params));
        assert_same("refine_flow u", &s.u, &p.u);
        assert_same("refine_flow v", &s.v, &p.v);
        assert_same("refine_flow ncc", &s.ncc, &p.ncc);
        assert_eq!(s.clamped, p.clamped, "refine_flow clamped");
    }
}

#[test]
fn sift_and_matching_do_not_depend_on_threads() {
    let mut rng = ChaCha8Rng::seed_from_u64(8);
    for _ in 0..3 {
        let (w, h) = (rng.random_range(80..=130), rng.random_range(60..=100));
        let (a, b) = shifted_pair(rng.random(), w, h, 3.0);
        let params = SiftParams::default();
        let (ka, kap) = serial_and_parallel(|| sift(&a, &params).expect("valid parameters"));
        assert_eq!(ka, kap, "sift");
        let kb = sift(&b, &params).expect("valid parameters");
        assert!(!ka.is_empty() && !kb.is_empty(), "{w}×{h}: no keypoints");
        let (s, p) = serial_and_parallel(|| match_keypoints(&ka, &kb, &MatchParams::default()));
        assert_eq!(format!("{s:?}"), format!("{p:?}"), "match_keypoints");
    }
}

/// The whole dense stage (SIFT flow with BP, sub-pixel, re-assignment, refinement, left–right
/// check, fill, grids) on one thread and on four, both presets.
#[test]
fn sift_flow_and_dense_disparity_do_not_depend_on_threads() {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for _ in 0..2 {
        let (w, h) = (rng.random_range(40..=72), rng.random_range(30..=52));
        let (a, b) = shifted_pair(rng.random(), w, h, 2.0);
        for preset in [
            sdsem::vision::Preset::Paper,
            sdsem::vision::Preset::Improved,
        ] {
            let flow = FlowParams {
                levels: 2,
                ..FlowParams::preset(preset)
            };
            let (s, p) = serial_and_parallel(|| sift_flow(&a, &b, &flow).expect("flow"));
            assert_same("sift_flow u", s.u.data(), p.u.data());
            assert_same("sift_flow v", s.v.data(), p.v.data());

            let mut params = DenseParams::preset(preset);
            params.flow.levels = 2;
            let (s, p) = serial_and_parallel(|| {
                dense_disparity(&a, &b, None, None, &params).expect("dense")
            });
            assert_same("dense disparity", s.disparity.data(), p.disparity.data());
            assert_same("dense raw", s.raw.data(), p.raw.data());
            assert_same("dense vertical", s.vertical.data(), p.vertical.data());
            assert_same("dense confidence", s.confidence.data(), p.confidence.data());
            assert_eq!(s.occluded, p.occluded, "occluded");
            assert_eq!(s.filled, p.filled, "filled");
            assert_eq!(s.disparity.dimensions(), (w, h));
        }
    }
}

/// The whole reconstruction (SIFT, matching, ORSA, inlier refinement, rectification and warp,
/// the dense stage, height and its resampling to the left grid) on a small rendered dome pair.
#[test]
fn the_whole_reconstruction_does_not_depend_on_threads() {
    use sdsem::vision::geometry::PairGeometry;
    use sdsem::vision::pipeline::reconstruct;
    use sdsem::vision::{Preset, ReconstructionParams};
    use sdsem_sim::render::{NoiseParams, ShadingParams, View, render_noisy};
    use sdsem_sim::scene::{Scene, SceneKind, SceneParams};

    let (w, h, tilt, axis) = (320, 240, 6.0, -60.0);
    let scene = Scene::generate(&SceneParams {
        kind: SceneKind::Dome,
        seed: Some(7),
        ..SceneParams::default()
    })
    .expect("the dome scene generates");
    let render = |tilt_deg: f64, seed: u64| {
        let view = View {
            width: w,
            height: h,
            pixel_size_um: 0.4,
            tilt_deg,
            tilt_axis_deg: axis,
            ..View::default()
        };
        let pixels = render_noisy(
            &scene,
            &view,
            &ShadingParams::default(),
            &NoiseParams::default(),
            10.0,
            seed,
        );
        Image::from_vec(w, h, pixels).expect("rendered at the view size")
    };
    let (left, right) = (render(-tilt / 2.0, 1), render(tilt / 2.0, 2));
    let geometry = PairGeometry {
        tilt_deg: tilt,
        pixel_size_um: 0.4,
        tilt_axis_deg: axis,
    };
    // The paper preset's sparse stage refuses this small pair; the dense stage of both presets
    // is covered above.
    let params = ReconstructionParams::preset(Preset::Improved);
    let (s, p) = serial_and_parallel(|| {
        reconstruct(&left, &right, &geometry, &params).expect("reconstructs")
    });
    assert_same("height", s.height_um.data(), p.height_um.data());
    assert_same("confidence", s.confidence.data(), p.confidence.data());
    let known = s.height_um.data().iter().filter(|v| v.is_finite()).count();
    assert!(known * 2 > w * h, "{known} known heights");
}
