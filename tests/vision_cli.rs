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
    assert!(
        !out.exists(),
        "the refused run left {} behind",
        out.display()
    );
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

/// A float32 TIFF of `W × H` (BitsPerSample 32, SampleFormat IEEE float): its samples.
fn float_tiff(path: &Path) -> Vec<f32> {
    use tiff::decoder::{Decoder, DecodingResult};
    use tiff::tags::Tag;
    let mut d =
        Decoder::new(std::fs::File::open(path).expect("height TIFF opens")).expect("a TIFF");
    assert_eq!(
        d.dimensions().expect("dimensions"),
        (W as u32, H as u32),
        "{}",
        path.display()
    );
    assert_eq!(
        d.colortype().expect("colour type"),
        tiff::ColorType::Gray(32),
        "{}",
        path.display()
    );
    assert_eq!(
        d.get_tag_u32(Tag::SampleFormat).expect("SampleFormat tag"),
        3,
        "{}: not IEEE float",
        path.display()
    );
    match d.read_image().expect("samples") {
        DecodingResult::F32(v) => v,
        _ => panic!("{}: not float samples", path.display()),
    }
}

/// A binary little-endian PLY: its header lines and the bytes after `end_header`.
fn ply_parts(path: &Path) -> (Vec<String>, usize) {
    let bytes = std::fs::read(path).expect("PLY readable");
    let end = b"end_header\n";
    let at = bytes
        .windows(end.len())
        .position(|w| w == end)
        .expect("end_header")
        + end.len();
    let header = String::from_utf8(bytes[..at].to_vec()).expect("ASCII header");
    (
        header.lines().map(str::to_owned).collect(),
        bytes.len() - at,
    )
}

fn header_count(header: &[String], element: &str) -> usize {
    let prefix = format!("element {element} ");
    header
        .iter()
        .find_map(|l| l.strip_prefix(&prefix))
        .unwrap_or_else(|| panic!("no {element} element in {header:?}"))
        .parse()
        .expect("a count")
}

/// `reconstruct` with every geometry flag: the flags beat the micrographs' metadata (and say
/// so), and each output has its contracted format, size and units (DESIGN §4).
#[test]
fn reconstruct_flags_beat_metadata_and_each_file_has_its_format() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right, _) = dome_pair(dir.path());
    let out = dir.path().join("out");
    let (tilt, pixel) = (5.0, 0.5);
    let run = sdsem(&[
        "reconstruct",
        path(&left),
        path(&right),
        "--out",
        path(&out),
        "--tilt",
        &tilt.to_string(),
        "--pixel-size",
        &pixel.to_string(),
        "--tilt-axis",
        &AXIS_DEG.to_string(),
    ]);
    assert_eq!(
        run.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    let g = &report["reconstruction"]["geometry"];
    assert_eq!(g["tilt_deg"].as_f64(), Some(tilt));
    assert_eq!(g["pixel_size_um"].as_f64(), Some(pixel));
    assert_eq!(g["tilt_axis_deg"].as_f64(), Some(AXIS_DEG));
    let p = &report["provenance"];
    assert_eq!(p["tilt"], "--tilt", "{p}");
    assert_eq!(p["pixel_size"], "--pixel-size", "{p}");
    assert_eq!(p["tilt_axis"], "--tilt-axis", "{p}");
    assert_eq!(
        report["reconstruction"]["image_size"],
        serde_json::json!([W, H])
    );
    // Every stage's timings (DESIGN §4) and the list of what was written.
    for stage in ["sparse_ms", "dense_ms", "depth_ms", "total_ms"] {
        assert!(
            report["reconstruction"]["timings"][stage].is_number(),
            "{stage}"
        );
    }
    let written: Vec<&str> = report["outputs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    for name in [
        "height.tif",
        "height.gsf",
        "pointcloud.ply",
        "mesh.ply",
        "confidence.tif",
    ] {
        assert!(written.contains(&name), "{name} not in {written:?}");
    }

    // height.tif: float32 µm on the left grid; confidence.tif: float32 in [0, 1] where known.
    let height = float_tiff(&out.join("height.tif"));
    let known = height.iter().filter(|h| h.is_finite()).count();
    assert!(known * 10 > 9 * W * H, "{known} known");
    let confidence = float_tiff(&out.join("confidence.tif"));
    for (h, c) in height.iter().zip(&confidence) {
        assert_eq!(h.is_finite(), c.is_finite());
        assert!(!c.is_finite() || (0.0..=1.0).contains(c), "confidence {c}");
    }
    // The same heights in the GSF, in metres, over the field of view at the flag's pixel size.
    let gsf = read_gsf(&out.join("height.gsf")).unwrap();
    assert_eq!((gsf.xres, gsf.yres), (W, H));
    assert!(
        (gsf.xreal - W as f64 * pixel * 1e-6).abs() < 1e-12,
        "XReal {}",
        gsf.xreal
    );
    assert!(
        (gsf.yreal - H as f64 * pixel * 1e-6).abs() < 1e-12,
        "YReal {}",
        gsf.yreal
    );
    assert_eq!(gsf.xy_units.as_deref(), Some("m"));
    assert_eq!(gsf.z_units.as_deref(), Some("m"));

    // PLYs: binary little-endian, x y z intensity as float, one vertex per known height; the
    // mesh's faces are triangles; the file sizes are exactly what the headers announce.
    let (header, body) = ply_parts(&out.join("pointcloud.ply"));
    assert_eq!(header[0], "ply");
    assert_eq!(header[1], "format binary_little_endian 1.0");
    let vertices = header_count(&header, "vertex");
    assert_eq!(vertices, known);
    assert_eq!(report["point_count"].as_u64(), Some(known as u64));
    for prop in ["x", "y", "z"] {
        assert!(
            header.contains(&format!("property float {prop}")),
            "{header:?}"
        );
    }
    let props = header
        .iter()
        .filter(|l| l.starts_with("property float"))
        .count();
    assert_eq!(body, vertices * 4 * props);
    let (header, body) = ply_parts(&out.join("mesh.ply"));
    assert_eq!(header[1], "format binary_little_endian 1.0");
    let faces = header_count(&header, "face");
    assert!(faces > 0);
    assert_eq!(report["triangle_count"].as_u64(), Some(faces as u64));
    assert!(
        header.contains(&"property list uchar int vertex_indices".to_owned()),
        "{header:?}"
    );
    let props = header
        .iter()
        .filter(|l| l.starts_with("property float"))
        .count();
    assert_eq!(
        body,
        header_count(&header, "vertex") * 4 * props + faces * (1 + 3 * 4)
    );
}

/// Exit codes: 0 on success, 1 with one line on stderr when the work fails, 2 (with the usage)
/// when the command line is wrong — for each of `reconstruct`, `rectify` and `flow`.
#[test]
fn vision_commands_exit_with_the_contracted_codes() {
    let dir = tempfile::tempdir().unwrap();
    let (left, _, _) = dome_pair(dir.path());
    let missing = dir.path().join("missing.tif");
    for command in ["reconstruct", "rectify", "flow"] {
        let out = dir.path().join(format!("out-{command}"));
        let run = sdsem(&[command, path(&left), path(&missing), "-o", path(&out)]);
        assert_eq!(run.status.code(), Some(1), "{command}");
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert_eq!(
            stderr.lines().filter(|l| !l.trim().is_empty()).count(),
            1,
            "{command}: {stderr}"
        );
        assert!(stderr.contains("missing.tif"), "{command}: {stderr}");
        assert!(!out.exists(), "{command} left {} behind", out.display());
        assert!(
            run.stdout.is_empty(),
            "{command} printed {:?}",
            String::from_utf8_lossy(&run.stdout)
        );

        let run = sdsem(&[command, path(&left)]);
        assert_eq!(
            run.status.code(),
            Some(2),
            "{command} without its arguments"
        );
        assert!(
            String::from_utf8_lossy(&run.stderr).contains("Usage"),
            "{command}"
        );
        let run = sdsem(&[
            command,
            path(&left),
            path(&left),
            "-o",
            path(&out),
            "--no-such-flag",
        ]);
        assert_eq!(run.status.code(), Some(2), "{command} with an unknown flag");
    }
}

/// `rectify`: the PNGs have the canvas size the JSON gives, the matches image shows both
/// micrographs side by side, and `H_left`/`H_right` bring every inlier pair onto one row.
#[test]
fn rectify_homographies_put_the_inliers_on_common_rows() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right, _) = dome_pair(dir.path());
    let out = dir.path().join("rect");
    let run = sdsem(&["rectify", path(&left), path(&right), "-o", path(&out)]);
    assert_eq!(
        run.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("rectification.json")).unwrap()).unwrap();
    let canvas: Vec<u32> = json["canvas_size"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_u64().unwrap() as u32)
        .collect();
    for name in ["rectified_left.png", "rectified_right.png"] {
        let img = image::open(out.join(name)).unwrap();
        assert_eq!(vec![img.width(), img.height()], canvas, "{name}");
        assert_eq!(img.color(), image::ColorType::L8, "{name}");
    }
    let matches = image::open(out.join("matches.png")).unwrap();
    assert_eq!(
        (matches.width(), matches.height()),
        (2 * W as u32, H as u32)
    );
    let h = |key: &str| {
        let rows = json[key].as_array().unwrap();
        nalgebra::Matrix3::from_fn(|r, c| rows[r][c].as_f64().unwrap())
    };
    let (hl, hr) = (h("H_left"), h("H_right"));
    let apply = |m: &nalgebra::Matrix3<f64>, p: &serde_json::Value| {
        let q = m * nalgebra::Vector3::new(p[0].as_f64().unwrap(), p[1].as_f64().unwrap(), 1.0);
        (q.x / q.z, q.y / q.z)
    };
    let inliers = json["inlier_correspondences"].as_array().unwrap();
    assert!(inliers.len() >= 8, "{} inliers", inliers.len());
    let dy: Vec<f64> = inliers
        .iter()
        .map(|c| apply(&hl, &c["left"]).1 - apply(&hr, &c["right"]).1)
        .collect();
    let rms = (dy.iter().map(|d| d * d).sum::<f64>() / dy.len() as f64).sqrt();
    assert!(rms < 1.0, "rows differ by {rms:.3} px rms");
    let reported = json["final_dy_rms_px"].as_f64().unwrap();
    assert!(
        (rms - reported).abs() < 0.05 + 0.1 * reported,
        "rms {rms:.3}, reported {reported:.3}"
    );
}

/// `flow`: the .flo file holds exactly its header (tag, width, height) and two floats per pixel.
#[test]
fn flow_file_has_the_middlebury_layout() {
    let dir = tempfile::tempdir().unwrap();
    let (left, right, _) = dome_pair(dir.path());
    let flo = dir.path().join("f.flo");
    let run = sdsem(&[
        "flow",
        path(&left),
        path(&right),
        "--out",
        path(&flo),
        "--set",
        "reconstruction.dense.levels=2",
    ]);
    assert_eq!(
        run.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let bytes = std::fs::read(&flo).unwrap();
    assert_eq!(bytes.len(), 12 + 8 * W * H);
    assert_eq!(&bytes[..4], b"PIEH");
    let word = |i: usize| u32::from_le_bytes(bytes[i..i + 4].try_into().unwrap()) as usize;
    assert_eq!((word(4), word(8)), (W, H));
    let (u, v) = sdsem::export::flo::decode(&bytes).unwrap();
    assert_eq!((u.dimensions(), v.dimensions()), ((W, H), (W, H)));
}
