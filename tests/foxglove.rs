//! The record of a reconstructed run as Foxglove reads it: frames on `/tf`, the height preview
//! and its legend, the mesh as a glTF scene entity in µm, no second copy of `mesh.ply`; and
//! the Python reader (`tests/check_mcap.py`) reads it whole and cut short.

#![allow(clippy::unwrap_used)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use foxglove::Decode;
use foxglove::messages::{CompressedImage, FrameTransforms, ImageAnnotations, SceneUpdate};
use sdsem::record::{self, MESH_PREVIEW_MAX_VERTICES, topics};

/// One 0→3° run with a reconstruction of 640×480 micrographs on the built-in simulator.
fn reconstructed_run(dir: &Path) -> PathBuf {
    let sets = [
        format!("run.output_dir={}", dir.display()),
        "series.end_tilt_deg=3".into(),
        "imaging.micrograph.width=640".into(),
        "imaging.micrograph.height=480".into(),
        "imaging.tracking.width=160".into(),
        "imaging.tracking.height=120".into(),
        "simulator.time_scale=0.01".into(),
    ];
    let out = Command::new(env!("CARGO_BIN_EXE_sdsem"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["acquire", "--config", "config/sim.toml"])
        .args(sets.iter().flat_map(|s| ["--set", s.as_str()]))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8(out.stdout).unwrap();
    PathBuf::from(stdout.lines().last().unwrap())
}

/// The last message of each topic, raw.
fn last_messages(path: &Path) -> BTreeMap<String, (String, Vec<u8>)> {
    let bytes = std::fs::read(path).unwrap();
    let mut out = BTreeMap::new();
    for message in mcap::MessageStream::new(&bytes).unwrap() {
        let message = message.unwrap();
        let schema = message
            .channel
            .schema
            .as_ref()
            .map(|s| s.name.clone())
            .unwrap_or_default();
        out.insert(
            message.channel.topic.clone(),
            (schema, message.data.into_owned()),
        );
    }
    out
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().unwrap())
}

#[test]
fn a_reconstructed_run_shows_right_in_foxglove() {
    let dir = tempfile::tempdir().unwrap();
    let run_dir = reconstructed_run(dir.path());
    let record = run_dir.join("run.mcap");
    let messages = last_messages(&record);
    let schema = |topic: &str| messages.get(topic).map(|(s, _)| s.as_str());
    assert_eq!(schema(topics::TRANSFORMS), Some("foxglove.FrameTransforms"));
    assert_eq!(
        schema(topics::RECON_HEIGHT_PREVIEW),
        Some("foxglove.CompressedImage")
    );
    assert_eq!(
        schema(topics::RECON_HEIGHT_PREVIEW_LEGEND),
        Some("foxglove.ImageAnnotations")
    );
    assert_eq!(schema(topics::RECON_MESH), Some("foxglove.SceneUpdate"));

    // `left` sits in `specimen` with its centre pixel at the origin.
    let tf = FrameTransforms::decode(messages[topics::TRANSFORMS].1.as_slice()).unwrap();
    let t = &tf.transforms[0];
    assert_eq!(
        (t.parent_frame_id.as_str(), t.child_frame_id.as_str()),
        ("specimen", "left")
    );
    let offset = t.translation.unwrap();
    let height = record::read_images(&record, topics::RECON_HEIGHT, |_| true)
        .unwrap()
        .items
        .pop()
        .unwrap();
    let clouds = record::read_point_clouds(&record, topics::RECON_POINTCLOUD).unwrap();
    let cloud = &clouds.items[0];
    assert_eq!(cloud.frame_id, "left");
    let max_x = cloud.points.iter().map(|p| p.x).fold(f32::MIN, f32::max);
    // The cloud is in µm: the field spans width × pixel size, and `specimen` centres it.
    let p = f64::from(max_x) / f64::from(height.width - 1);
    assert!(p > 0.01 && p < 1.0, "pixel size {p} µm");
    assert!(
        (offset.x + f64::from(max_x) / 2.0).abs() < 2.0 * p,
        "{offset:?}"
    );

    // The preview is an RGB picture of the height map's size, unknown pixels black.
    let preview =
        CompressedImage::decode(messages[topics::RECON_HEIGHT_PREVIEW].1.as_slice()).unwrap();
    assert_eq!(
        (preview.format.as_str(), preview.frame_id.as_str()),
        ("png", "left")
    );
    let picture = image::load_from_memory(&preview.data).unwrap().into_rgb8();
    assert_eq!(picture.dimensions(), (height.width, height.height));
    let sdsem::record::Pixels::Float32(heights) = &height.pixels else {
        panic!("32FC1 expected");
    };
    for (h, px) in heights.iter().zip(picture.pixels()).step_by(97) {
        assert_eq!(
            h.is_nan(),
            px.0 == [0, 0, 0],
            "height {h}, colour {:?}",
            px.0
        );
    }
    let legend =
        ImageAnnotations::decode(messages[topics::RECON_HEIGHT_PREVIEW_LEGEND].1.as_slice())
            .unwrap();
    assert!(
        legend.texts[0].text.contains(" µm … yellow "),
        "{:?}",
        legend.texts
    );

    // The mesh: one entity in `left` holding a GLB within the vertex bound.
    let scene = SceneUpdate::decode(messages[topics::RECON_MESH].1.as_slice()).unwrap();
    let entity = &scene.entities[0];
    assert_eq!(entity.frame_id, "left");
    let model = &entity.models[0];
    assert_eq!(model.media_type, "model/gltf-binary");
    let glb = &model.data;
    assert_eq!(&glb[..4], b"glTF");
    assert_eq!(u32_at(glb, 8) as usize, glb.len());
    let json_len = u32_at(glb, 12) as usize;
    let gltf: serde_json::Value = serde_json::from_slice(&glb[20..20 + json_len]).unwrap();
    let vertices = gltf["accessors"][0]["count"].as_u64().unwrap() as usize;
    assert!(
        vertices > 1000 && vertices <= MESH_PREVIEW_MAX_VERTICES,
        "{vertices}"
    );
    // glTF y is the height: its range is the height map's.
    let gltf_max_y = gltf["accessors"][0]["max"][1].as_f64().unwrap();
    let height_max = heights
        .iter()
        .copied()
        .filter(|h| h.is_finite())
        .fold(f32::MIN, f32::max);
    assert!(
        gltf_max_y <= f64::from(height_max) + 1e-3,
        "{gltf_max_y} vs {height_max}"
    );

    // The mesh is not attached a second time; the small results are.
    let summary = record::read_summary(&record).unwrap();
    let attached: Vec<&str> = summary
        .attachments
        .iter()
        .map(|a| a.name.as_str())
        .collect();
    assert_eq!(attached, ["height.gsf", "confidence.tif"]);
    assert!(run_dir.join("mesh.ply").is_file());

    // The report in the record carries its schema version and rounded figures.
    let report = summary.report.unwrap();
    assert_eq!(report["schema_version"], 1);
    let wall = report["wall_s"].as_f64().unwrap();
    assert_eq!(wall, (wall * 1000.0).round() / 1000.0);

    check_with_python(&record, dir.path());
}

/// `tests/check_mcap.py` reads the record whole, and a copy cut in the middle up to the cut.
fn check_with_python(record: &Path, dir: &Path) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/check_mcap.py");
    let available = Command::new("python3")
        .args(["-c", "import mcap"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !available {
        assert!(
            std::env::var_os("SDSEM_REQUIRE_PYTHON_MCAP").is_none(),
            "SDSEM_REQUIRE_PYTHON_MCAP is set but python3 cannot import mcap"
        );
        eprintln!("skipped the Python check: python3 with the mcap package is not available");
        return;
    }
    let run = |path: &Path, extra: &[&str]| {
        let out = Command::new("python3")
            .arg(&script)
            .arg(path)
            .args(extra)
            .output()
            .unwrap();
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        (out.status.success(), text)
    };
    let (ok, text) = run(record, &["--require-all-topics"]);
    assert!(ok, "{text}");
    for topic in [
        "/tf",
        "/recon/height_preview",
        "/recon/height_preview/legend",
        "/recon/mesh",
    ] {
        assert!(text.contains(topic), "{topic} not read:\n{text}");
    }
    let bytes = std::fs::read(record).unwrap();
    let cut = dir.join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let (ok, text) = run(&cut, &[]);
    assert!(
        ok && text.contains("INCOMPLETE") && text.contains("/sem/frame"),
        "{text}"
    );
}
