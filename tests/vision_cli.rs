//! The output contracts of `sdsem reconstruct`, `rectify` and `flow` (DESIGN §4), run as
//! processes on a pair the simulator renders with known geometry.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use sdsem::export::gsf::read_gsf;
use sdsem::export::height_tiff::read_height_tiff;
use sdsem::export::ply::read_ply;
use sdsem::imaging::file::{MicrographTags, SampleDepth, write_micrograph_tiff};
use sdsem::vision::Image;
use sdsem_sim::render::{NoiseParams, ShadingParams, View, height_map, render_noisy};
use sdsem_sim::scene::{Scene, SceneKind, SceneParams};

const W: usize = 320;
const H: usize = 240;
const TILT_DEG: f64 = 6.0;
const PIXEL_UM: f64 = 0.4;
const AXIS_DEG: f64 = -60.0;

/// The dome scene at ∓θ/2, written as sdsem micrographs (tilt, pixel size and tilt axis in
/// their metadata); the true height of the left view, µm.
fn dome_pair(dir: &Path) -> (PathBuf, PathBuf, Vec<f32>) {
    let scene = Scene::generate(&SceneParams {
        kind: SceneKind::Dome,
        seed: Some(7),
        ..SceneParams::default()
    })
    .expect("the dome scene generates");
    let view = |tilt: f64| View {
        width: W,
        height: H,
        pixel_size_um: PIXEL_UM,
        tilt_deg: tilt,
        tilt_axis_deg: AXIS_DEG,
        ..View::default()
    };
    let shading = ShadingParams::default();
    let write = |name: &str, tilt: f64, seed: u64| {
        let pixels = render_noisy(
            &scene,
            &view(tilt),
            &shading,
            &NoiseParams::default(),
            10.0,
            seed,
        );
        let image = Image::from_vec(W, H, pixels).expect("rendered at the view size");
        let mut extra = serde_json::Map::new();
        extra.insert("tilt_axis_deg".into(), AXIS_DEG.into());
        let tags = MicrographTags {
            pixel_size_um: Some(PIXEL_UM),
            tilt_deg: Some(tilt),
            extra,
        };
        let path = dir.join(name);
        write_micrograph_tiff(&path, &image, &tags, SampleDepth::Bits16).expect("TIFF written");
        path
    };
    let left = write("left.tif", -TILT_DEG / 2.0, 1);
    let right = write("right.tif", TILT_DEG / 2.0, 2);
    (left, right, height_map(&scene, &view(-TILT_DEG / 2.0)))
}

fn sdsem(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .args(args)
        .env("SDSEM_LOG__FORMAT", "text")
        .output()
        .expect("sdsem runs")
}

fn path(p: &Path) -> &str {
    p.to_str().expect("temporary paths are UTF-8")
}

/// The last line on stdout (DESIGN §4: the output's path).
fn last_line(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .last()
        .unwrap_or_default()
        .to_owned()
}

/// The relief from the micrographs' metadata alone: every file, on the left grid, with the
/// dome raised towards the beam as in the truth (after the plane DESIGN §3 allows).
#[test]
fn reconstruct_writes_the_contracted_outputs_with_the_relief_raised() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right, truth) = dome_pair(dir.path());
    let out = dir.path().join("out");
    let run = sdsem(&["reconstruct", path(&left), path(&right), "-o", path(&out)]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert_eq!(last_line(&run), path(&out));
    for name in [
        "height.tif",
        "height.gsf",
        "pointcloud.ply",
        "mesh.ply",
        "confidence.tif",
        "report.json",
    ] {
        assert!(out.join(name).is_file(), "{name} missing");
    }
    let height = read_height_tiff(&out.join("height.tif")).unwrap().height_um;
    assert_eq!(height.dimensions(), (W, H));
    let known: Vec<usize> = (0..W * H)
        .filter(|&p| height.data()[p].is_finite())
        .collect();
    assert!(known.len() * 10 > 9 * W * H, "{} known", known.len());
    // Heights up to a plane: correlate the estimate with the truth over the known pixels.
    let pairs: Vec<(f64, f64)> = known
        .iter()
        .filter(|&&p| truth[p].is_finite())
        .map(|&p| (f64::from(height.data()[p]), f64::from(truth[p])))
        .collect();
    let n = pairs.len() as f64;
    let (ma, mb) = pairs
        .iter()
        .fold((0.0, 0.0), |(a, b), (x, y)| (a + x / n, b + y / n));
    let (sab, saa, sbb) = pairs.iter().fold((0.0, 0.0, 0.0), |(ab, aa, bb), (x, y)| {
        (
            ab + (x - ma) * (y - mb),
            aa + (x - ma).powi(2),
            bb + (y - mb).powi(2),
        )
    });
    let r = sab / (saa * sbb).sqrt();
    assert!(
        r > 0.9,
        "correlation with the true relief {r:.3} (a wrong sign gives < 0)"
    );

    let confidence = read_height_tiff(&out.join("confidence.tif"))
        .unwrap()
        .height_um;
    for (h, c) in height.data().iter().zip(confidence.data()) {
        assert_eq!(h.is_finite(), c.is_finite(), "height {h}, confidence {c}");
    }
    let gsf = read_gsf(&out.join("height.gsf")).unwrap();
    assert_eq!((gsf.xres, gsf.yres), (W, H));
    let cloud = read_ply(&out.join("pointcloud.ply")).unwrap();
    assert_eq!(cloud.vertex_count(), known.len());
    let mesh = read_ply(&out.join("mesh.ply")).unwrap();
    assert!(!mesh.faces.is_empty());

    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let g = &report["reconstruction"]["geometry"];
    assert_eq!(g["tilt_deg"].as_f64(), Some(TILT_DEG));
    assert_eq!(g["pixel_size_um"].as_f64(), Some(PIXEL_UM));
    assert_eq!(g["tilt_axis_deg"].as_f64(), Some(AXIS_DEG));
    assert!(
        report["provenance"]["tilt_axis"]
            .as_str()
            .unwrap()
            .starts_with("metadata"),
        "{}",
        report["provenance"]
    );
}

/// A failure exits non-zero with one line naming the cause, and leaves no output behind.
#[test]
fn reconstruct_refuses_in_one_line_without_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let (left, _, _) = dome_pair(dir.path());
    let missing = dir.path().join("missing.tif");
    let out = dir.path().join("out");
    let run = sdsem(&["reconstruct", path(&left), path(&missing), "-o", path(&out)]);
    assert!(!run.status.success());
    let stderr = String::from_utf8_lossy(&run.stderr);
    let lines: Vec<&str> = stderr.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "{stderr}");
    assert!(lines[0].contains("missing.tif"), "{stderr}");
    assert_eq!(std::fs::read_dir(&out).map_or(0, Iterator::count), 0);
}

/// `rectify`: the rectified pair, the matches and rectification.json with the keys of DESIGN
/// §4, whose homographies bring the inliers onto common rows.
#[test]
fn rectify_writes_the_rectified_pair_and_its_figures() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right, _) = dome_pair(dir.path());
    let out = dir.path().join("rect");
    let run = sdsem(&[
        "rectify",
        path(&left),
        path(&right),
        "-o",
        path(&out),
        "--tilt-axis",
        &AXIS_DEG.to_string(),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert_eq!(last_line(&run), path(&out));
    let (l, r) = (
        image::open(out.join("rectified_left.png")).unwrap(),
        image::open(out.join("rectified_right.png")).unwrap(),
    );
    assert_eq!((l.width(), l.height()), (r.width(), r.height()));
    assert!(image::open(out.join("matches.png")).is_ok());
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("rectification.json")).unwrap()).unwrap();
    for key in [
        "keypoints_left",
        "keypoints_right",
        "matches",
        "inliers",
        "initial_error_px",
        "final_error_px",
    ] {
        assert!(json[key].is_number(), "{key}: {}", json[key]);
    }
    assert!(json["inliers"].as_u64().unwrap() >= 8);
    assert!(json["final_error_px"].as_f64().unwrap() < 1.0);
    for key in ["H_left", "H_right"] {
        let rows = json[key].as_array().unwrap();
        assert_eq!(rows.len(), 3, "{key}");
        for row in rows {
            let row = row.as_array().unwrap();
            assert_eq!(row.len(), 3, "{key}");
            assert!(row.iter().all(|v| v.as_f64().is_some_and(f64::is_finite)));
        }
    }
}

/// `flow`: Middlebury .flo of the first image's size, the displacement of a shifted texture.
#[test]
fn flow_writes_a_middlebury_file_of_the_displacement() {
    let dir = tempfile::tempdir().unwrap();
    // Value noise: random values on a 3-pixel lattice, bilinearly interpolated.
    let lattice = |i: usize, j: usize| {
        let mut s = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        s ^= s >> 29;
        s = s.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        s ^= s >> 32;
        (s % 1000) as f32 / 1000.0
    };
    let texture = |x: usize, y: usize| {
        let (i, j, fx, fy) = (x / 3, y / 3, (x % 3) as f32 / 3.0, (y % 3) as f32 / 3.0);
        let top = lattice(i, j) * (1.0 - fx) + lattice(i + 1, j) * fx;
        let bottom = lattice(i, j + 1) * (1.0 - fx) + lattice(i + 1, j + 1) * fx;
        top * (1.0 - fy) + bottom * fy
    };
    let (w, h) = (96usize, 72usize);
    let a = Image::from_fn(w, h, |x, y| texture(x + 10, y + 10));
    // b(x + 3, y − 1) = a(x, y).
    let b = Image::from_fn(w, h, |x, y| texture(x + 7, y + 11));
    let (pa, pb) = (dir.path().join("a.png"), dir.path().join("b.png"));
    for (img, p) in [(&a, &pa), (&b, &pb)] {
        image::GrayImage::from_raw(w as u32, h as u32, img.to_u8())
            .unwrap()
            .save(p)
            .unwrap();
    }
    let flo = dir.path().join("f.flo");
    let run = sdsem(&[
        "flow",
        path(&pa),
        path(&pb),
        "-o",
        path(&flo),
        "--set",
        "reconstruction.dense.levels=3",
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert_eq!(last_line(&run), path(&flo));
    let bytes = std::fs::read(&flo).unwrap();
    assert_eq!(&bytes[..4], &202_021.25f32.to_le_bytes());
    let (u, v) = sdsem::export::flo::decode(&bytes).unwrap();
    assert_eq!(u.dimensions(), (w, h));
    let centre = |img: &Image| img.get(w / 2, h / 2);
    assert!((centre(&u) - 3.0).abs() < 0.3, "u {}", centre(&u));
    assert!((centre(&v) + 1.0).abs() < 0.3, "v {}", centre(&v));
}
