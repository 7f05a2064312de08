//! `sdsem reconstruct LEFT RIGHT --out DIR`: a calibrated height map, point
//! cloud and mesh from a stereo pair of micrographs (DESIGN §4).
//!
//! Tilt and pixel size come from the files' SEM metadata unless given; the output
//! directory is prepared before any work ([`super::output`]); every output is computed
//! before the first is written, and a failed write removes what was written, so no
//! partial set of outputs looks valid.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::bail;
use serde::Serialize;

use crate::export::atomic::OutputDir;
use crate::export::{self, ExportError, MeshParams, ply};
use crate::imaging::file::{Micrograph, load_micrograph};
use crate::imaging::metadata::SemMetadata;
use crate::progress::{Observer, Stage};
use crate::record::RecordError;
use crate::vision::geometry::{Figures, GeometrySources, PairGeometry, Provenance};
use crate::vision::pipeline::{
    ReconReport, ReconstructError, Reconstruction, reconstruct_observed,
};
use crate::vision::{Image, ReconstructionParams};

/// Output file names (DESIGN §4).
pub mod files {
    pub const HEIGHT_TIFF: &str = "height.tif";
    pub const HEIGHT_GSF: &str = "height.gsf";
    pub const POINT_CLOUD: &str = "pointcloud.ply";
    pub const MESH: &str = "mesh.ply";
    /// Beyond DESIGN §4: the per-pixel confidence of `height.tif`.
    pub const CONFIDENCE_TIFF: &str = "confidence.tif";
    pub const REPORT: &str = "report.json";
    /// Every file a reconstruction writes, the report last.
    pub const ALL: [&str; 6] = [
        HEIGHT_TIFF,
        HEIGHT_GSF,
        POINT_CLOUD,
        MESH,
        CONFIDENCE_TIFF,
        REPORT,
    ];
}

/// A pair ready to reconstruct, with where each geometric figure came from.
#[derive(Debug)]
pub struct LoadedPair {
    pub left: Micrograph,
    pub right: Micrograph,
    pub geometry: PairGeometry,
    pub provenance: Provenance,
}

/// What a micrograph's metadata says about the pair.
#[must_use]
pub fn figures_of(metadata: &SemMetadata) -> Figures {
    Figures {
        tilt_deg: metadata.tilt_deg,
        pixel_size_um: metadata.pixel_size_um,
        tilt_axis_deg: metadata
            .raw
            .get("tilt_axis_deg")
            .and_then(|v| v.parse::<f64>().ok()),
    }
}

/// Loads both micrographs and settles θ, the pixel size and the tilt axis
/// ([`GeometrySources::resolve`]: `given` first, then the files' metadata, then
/// `configured_tilt_axis_deg`).
///
/// # Errors
/// A one-line cause naming the file or the missing figure and how to give it.
pub fn load_pair(
    left: &Path,
    right: &Path,
    given: Figures,
    configured_tilt_axis_deg: Option<f64>,
) -> anyhow::Result<LoadedPair> {
    // Decoded at the same time; the left one's error first.
    let (l, r) = rayon::join(|| load_micrograph(left), || load_micrograph(right));
    let (l, r) = (l?, r?);
    if l.image.dimensions() != r.image.dimensions() {
        bail!(
            "the micrographs differ in size: {} is {}×{}, {} is {}×{}",
            left.display(),
            l.image.width(),
            l.image.height(),
            right.display(),
            r.image.width(),
            r.image.height()
        );
    }
    let (geometry, provenance) = GeometrySources {
        given,
        left: figures_of(&l.metadata),
        right: figures_of(&r.metadata),
        configured_tilt_axis_deg,
        names: [left.display().to_string(), right.display().to_string()],
    }
    .resolve()?;
    Ok(LoadedPair {
        left: l,
        right: r,
        geometry,
        provenance,
    })
}

/// Why a reconstruction's outputs could not be made, written or recorded.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    #[error("{0}")]
    Reconstruct(ReconstructError),
    /// The refusal and its likely remedy (a wrong tilt axis).
    #[error("{error}{hint}")]
    Hinted {
        error: ReconstructError,
        hint: &'static str,
    },
    #[error("{0}")]
    Export(ExportError),
    #[error("cannot read back {path}: {source}")]
    ReadBack {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("record: {0}")]
    Record(RecordError),
}

error_from!(OutputError {
    Reconstruct(ReconstructError),
    Export(ExportError),
    Record(RecordError),
});

/// The contents of `report.json`.
#[derive(Debug, Clone, Serialize)]
pub struct ReportFile {
    pub sdsem_version: &'static str,
    pub left: PathBuf,
    pub right: PathBuf,
    /// Where θ, the pixel size and the tilt axis came from.
    pub provenance: Provenance,
    pub reconstruction: ReconReport,
    pub outputs: Vec<String>,
    /// Triangles and points written.
    pub point_count: usize,
    pub triangle_count: usize,
    pub triangles_cut_at_discontinuities: usize,
    /// Wall time of the whole command (loading and writing included), s.
    pub wall_s: f64,
    /// Peak resident memory of the process, MiB (Linux VmHWM).
    pub peak_rss_mib: Option<f64>,
}

/// Reconstructs `left`/`right` into `out` (prepared by [`super::output::prepare_dir`]),
/// telling `progress` each stage.
///
/// # Errors
/// A one-line cause; nothing is left in `out` that looks like a result.
#[allow(clippy::too_many_arguments)]
pub fn run(
    left: &Path,
    right: &Path,
    out: &OutputDir,
    given: Figures,
    configured_tilt_axis_deg: Option<f64>,
    params: &ReconstructionParams,
    mesh: &MeshParams,
    progress: Observer<'_>,
) -> anyhow::Result<ReportFile> {
    let t0 = Instant::now();
    let pair = load_pair(left, right, given, configured_tilt_axis_deg)?;
    let recon = reconstruct_observed(
        &pair.left.image,
        &pair.right.image,
        &pair.geometry,
        params,
        progress,
    )
    .map_err(|e| match e {
        // The sparse stage's refusals concern one image or the pair: name them.
        ReconstructError::Sparse(e) => super::rectify::name_files(e, left, right, "sparse stage: "),
        // Neither path rectified the pair: both images are concerned.
        e @ ReconstructError::Unrectifiable { .. } => {
            anyhow::anyhow!("{} and {}: {e}", left.display(), right.display())
        }
        e => e.into(),
    })?;
    // The exports read the left micrograph alone.
    drop(pair.right);
    let mut report = ReportFile {
        sdsem_version: env!("CARGO_PKG_VERSION"),
        left: left.to_owned(),
        right: right.to_owned(),
        provenance: pair.provenance,
        reconstruction: recon.report.clone(),
        outputs: Vec::new(),
        point_count: 0,
        triangle_count: 0,
        triangles_cut_at_discontinuities: 0,
        wall_s: 0.0,
        peak_rss_mib: None,
    };
    write_outputs(
        out,
        &recon,
        &pair.left.image,
        mesh,
        &mut report,
        t0,
        progress,
    )?;
    Ok(report)
}

/// Reconstructs an acquired pair into `out` and, when recording, publishes the
/// results: `/recon/height`, `/recon/pointcloud`, the Foxglove views of
/// [`RecorderHandle::reconstruction`](crate::record::RecorderHandle::reconstruction),
/// `/recon/report` and the `height.gsf` and `confidence.tif` attachments (DESIGN §5).
/// Used by `acquire` and `replay`, so both run the very same code.
///
/// # Errors
/// The reconstruction's or the writing's one-line cause.
#[allow(clippy::too_many_arguments)]
pub fn reconstruct_recorded_pair(
    left: &Image,
    right: &Image,
    (geometry, provenance): (&PairGeometry, Provenance),
    config: &crate::config::ReconstructionConfig,
    out: &OutputDir,
    rec: Option<&crate::record::RecorderHandle>,
    sources: (&Path, &Path),
    progress: Observer<'_>,
) -> Result<(ReportFile, Reconstruction), OutputError> {
    let t0 = Instant::now();
    let recon =
        reconstruct_observed(left, right, geometry, &config.params(), progress).map_err(|e| {
            match &e {
                ReconstructError::Sparse(s) => match super::rectify::tilt_axis_hint(s) {
                    Some(hint) => OutputError::Hinted { error: e, hint },
                    None => e.into(),
                },
                _ => e.into(),
            }
        })?;
    let mut report = ReportFile {
        sdsem_version: env!("CARGO_PKG_VERSION"),
        left: sources.0.to_owned(),
        right: sources.1.to_owned(),
        provenance,
        reconstruction: recon.report.clone(),
        outputs: Vec::new(),
        point_count: 0,
        triangle_count: 0,
        triangles_cut_at_discontinuities: 0,
        wall_s: 0.0,
        peak_rss_mib: None,
    };
    write_outputs(out, &recon, left, &config.mesh, &mut report, t0, progress)?;
    if let Some(rec) = rec {
        progress(Stage::Record);
        let t = crate::stage::observer::wall_ns();
        rec.reconstruction(
            t,
            &crate::record::ReconstructionView {
                height_um: &recon.height_um,
                intensity: left,
                pixel_size_um: geometry.pixel_size_um,
                mesh: &config.mesh,
            },
        )?;
        rec.report(t, &report)?;
        // mesh.ply stays in the run directory: the record shows the mesh as /recon/mesh.
        for (name, media_type) in [
            (files::HEIGHT_GSF, "application/x-gwyddion-gsf"),
            (files::CONFIDENCE_TIFF, "image/tiff"),
        ] {
            let bytes = out.read(name).map_err(|source| OutputError::ReadBack {
                path: out.join(name),
                source,
            })?;
            rec.attachment(t, name, media_type, bytes)?;
        }
    }
    Ok((report, recon))
}

/// Writes every output of a reconstruction into `out` (under its rule for existing
/// files: new ones only, or replaced with `--force`); on failure removes whatever it wrote.
///
/// # Errors
/// The file that could not be written and why.
pub fn write_outputs(
    out: &OutputDir,
    recon: &Reconstruction,
    intensity: &Image,
    mesh_params: &MeshParams,
    report: &mut ReportFile,
    started: Instant,
    progress: Observer<'_>,
) -> Result<(), OutputError> {
    progress(Stage::Export);
    let p = recon.report.geometry.pair.pixel_size_um;
    let gsf_title = format!("sdsem height, zero = {}", recon.report.datum.zero);
    let height = &recon.height_um;

    // The files are independent: written at the same time (the mesh, the
    // largest, beside the rest). The report goes last: its presence says
    // the set is complete. On any failure every file written is removed.
    let names = [
        files::HEIGHT_TIFF,
        files::HEIGHT_GSF,
        files::POINT_CLOUD,
        files::MESH,
        files::CONFIDENCE_TIFF,
    ];
    let [tiff, gsf, cloud_path, mesh_path, confidence_path] = names.map(|name| out.file(name));
    let (mesh_written, (cloud_written, ((tiff_written, confidence_written), gsf_written))) =
        rayon::join(
            || {
                ply::write_mesh_from_height(
                    mesh_path,
                    height,
                    p,
                    Some(intensity),
                    mesh_params,
                    true,
                )
            },
            || {
                rayon::join(
                    || ply::write_point_cloud_from_height(cloud_path, height, p, Some(intensity)),
                    || {
                        rayon::join(
                            || {
                                (
                                    export::height_tiff::write_height_tiff(
                                        tiff,
                                        &recon.height_um,
                                        Some(p),
                                        Some(&recon.report.datum),
                                    ),
                                    export::height_tiff::write_confidence_tiff(
                                        confidence_path,
                                        &recon.confidence,
                                        Some(p),
                                        Some(&recon.unknown),
                                    ),
                                )
                            },
                            || export::gsf::write_gsf(gsf, &recon.height_um, p, &gsf_title),
                        )
                    },
                )
            },
        );
    if let (Ok(points), Ok(mesh)) = (&cloud_written, &mesh_written) {
        report.point_count = *points;
        report.triangle_count = mesh.triangles;
        report.triangles_cut_at_discontinuities = mesh.cut_triangles;
    }
    let results = [
        tiff_written,
        gsf_written,
        cloud_written.map(drop),
        mesh_written.map(drop),
        confidence_written,
    ];
    let written: Vec<&str> = names
        .iter()
        .zip(&results)
        .filter(|(_, r)| r.is_ok())
        .map(|(n, _)| *n)
        .collect();
    let result = (|| -> Result<(), OutputError> {
        for r in results {
            r?;
        }
        report.outputs = files::ALL.map(str::to_owned).to_vec();
        report.wall_s = started.elapsed().as_secs_f64();
        report.peak_rss_mib = peak_rss_mib();
        export::report::write_report_atomic(out.file(files::REPORT), report)?;
        Ok(())
    })();
    if result.is_err() {
        for name in written {
            out.remove(name);
        }
    }
    result
}

/// Peak resident set size of this process, MiB, from `/proc/self/status`.
#[must_use]
pub fn peak_rss_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::{Texture, dome, render};

    fn save_png(path: &Path, img: &Image) {
        image::GrayImage::from_raw(img.width() as u32, img.height() as u32, img.to_u8())
            .expect("buffer of w × h bytes")
            .save(path)
            .expect("temporary PNG written");
    }

    fn textured(w: usize, h: usize, seed: u64) -> Image {
        let t = Texture::new(seed);
        Image::from_fn(w, h, |x, y| t.at(x as f64, y as f64) as f32)
    }

    /// Runs `reconstruct` on `left`/`right` and returns its one-line error,
    /// checking that the output directory holds nothing afterwards.
    fn refused(dir: &Path, left: &Path, right: &Path, given: Figures) -> String {
        let out = dir.join("out");
        let prepared = super::super::output::prepare_dir(&out, &files::ALL, false).unwrap();
        let err = run(
            left,
            right,
            &prepared,
            given,
            None,
            &ReconstructionParams::default(),
            &MeshParams::default(),
            &crate::progress::unobserved,
        )
        .expect_err("the pair must be refused");
        let line = format!("{err:#}");
        assert!(!line.contains('\n'), "not one line: {line}");
        let left_behind = std::fs::read_dir(&out).map_or(0, Iterator::count);
        assert_eq!(left_behind, 0, "outputs left behind after: {line}");
        line
    }

    #[test]
    fn bad_inputs_are_refused_in_one_line_without_outputs() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let a = d.join("a.png");
        let b = d.join("b.png");
        let small = d.join("small.png");
        let flat = d.join("flat.png");
        let other = d.join("other.png");
        let text = d.join("notes.png");
        save_png(&a, &textured(160, 120, 1));
        save_png(&b, &textured(160, 120, 1).map(|v| 0.9 * v + 0.05));
        save_png(&small, &textured(150, 120, 1));
        save_png(&flat, &Image::filled(160, 120, 0.5));
        save_png(&other, &textured(160, 120, 77));
        std::fs::write(&text, "not an image\n").unwrap();
        let flags = Figures {
            tilt_deg: Some(5.0),
            pixel_size_um: Some(0.1),
            tilt_axis_deg: Some(0.0),
        };

        let e = refused(d, &a, &small, flags);
        assert!(e.contains("differ in size"), "{e}");
        let e = refused(d, &a, &text, flags);
        assert!(e.contains("notes.png") && e.contains("not an image"), "{e}");
        for tilt in [0.0, -3.0, 61.0] {
            let e = refused(
                d,
                &a,
                &b,
                Figures {
                    tilt_deg: Some(tilt),
                    ..flags
                },
            );
            assert!(e.contains("tilt"), "θ = {tilt}: {e}");
        }
        let e = refused(
            d,
            &a,
            &b,
            Figures {
                pixel_size_um: None,
                ..flags
            },
        );
        assert!(
            e.contains("no pixel size") && e.contains("--pixel-size"),
            "{e}"
        );
        let e = refused(
            d,
            &a,
            &b,
            Figures {
                tilt_deg: None,
                ..flags
            },
        );
        assert!(e.contains("--tilt"), "{e}");
        let e = refused(d, &flat, &flat, flags);
        assert!(e.contains("texture"), "{e}");
        // Two unrelated specimens: no overlap, no epipolar geometry; both files named.
        let e = refused(d, &a, &other, flags);
        assert!(e.contains("sparse stage"), "{e}");
        assert!(
            e.contains(&a.display().to_string()) && e.contains(&other.display().to_string()),
            "{e}"
        );
    }

    /// A dome seen with a horizontal parallax (φ = −90°): every output is
    /// written, the GSF obeys DESIGN §7, the relief comes out raised, and the
    /// report carries the energies of every level and the flow statistics.
    /// Reconstructs the 192×144 dome pair of the tests below (written into
    /// `dir`) into `out`, telling `progress` each stage.
    fn reconstruct_dome(
        dir: &Path,
        out: &OutputDir,
        progress: Observer<'_>,
    ) -> anyhow::Result<ReportFile> {
        let (w, h) = (192, 144);
        let pair = render(
            w,
            h,
            Texture::new(5),
            &dome(w, h, 0.0, 6.0, 0.35),
            0.0,
            0.005,
        );
        let (l, r) = (dir.join("l.png"), dir.join("r.png"));
        save_png(&l, &pair.left);
        save_png(&r, &pair.right);
        let mut params = ReconstructionParams::default();
        params.dense.flow.levels = 3;
        run(
            &l,
            &r,
            out,
            Figures {
                tilt_deg: Some(6.0),
                pixel_size_um: Some(0.05),
                tilt_axis_deg: Some(-90.0),
            },
            None,
            &params,
            &MeshParams::default(),
            progress,
        )
    }

    #[test]
    fn a_pair_gives_every_output_with_the_relief_raised() {
        let (w, h) = (192, 144);
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let prepared = super::super::output::prepare_dir(&out, &files::ALL, false).unwrap();
        let stages = crate::progress::StageLog::default();
        let report = reconstruct_dome(dir.path(), &prepared, &|s| stages.push(s)).unwrap();
        // Every stage is told once, in order.
        let expected = [Stage::Sparse, Stage::Dense, Stage::Depth, Stage::Export];
        assert_eq!(stages.stages(), expected);
        for name in [
            files::HEIGHT_TIFF,
            files::HEIGHT_GSF,
            files::POINT_CLOUD,
            files::MESH,
            files::CONFIDENCE_TIFF,
            files::REPORT,
        ] {
            assert!(out.join(name).is_file(), "{name} missing");
        }
        // The confidence is known exactly where the height is, measured
        // (no filling by default): in (0, 1].
        let heights = crate::export::height_tiff::read_height_tiff(&out.join(files::HEIGHT_TIFF))
            .unwrap()
            .height_um;
        let confidence =
            crate::export::height_tiff::read_height_tiff(&out.join(files::CONFIDENCE_TIFF))
                .unwrap()
                .height_um;
        assert_eq!(confidence.dimensions(), (w, h));
        for (hv, c) in heights.data().iter().zip(confidence.data()) {
            assert_eq!(hv.is_finite(), c.is_finite(), "height {hv}, confidence {c}");
            if c.is_finite() {
                assert!(*c > 0.0 && *c <= 1.0, "confidence {c}");
            }
        }
        let gsf = std::fs::read(out.join(files::HEIGHT_GSF)).unwrap();
        let data_start = gsf.len() - w * h * 4;
        assert_eq!(data_start % 4, 0);
        let pad = gsf[..data_start]
            .iter()
            .rev()
            .take_while(|&&b| b == 0)
            .count();
        assert!((1..=4).contains(&pad), "{pad} NUL bytes");
        let field = crate::export::gsf::read_gsf(&out.join(files::HEIGHT_GSF)).unwrap();
        assert_eq!((field.xres, field.yres), (w, h));
        let height = field.height_um().unwrap();
        let centre = height.get(w / 2, h / 2);
        let rim = height.get(w / 2, h / 2 + 55);
        assert!(
            f64::from(centre - rim) > 0.5 * 6.0 * params_um_per_px(),
            "centre {centre}, rim {rim}"
        );
        // Zero is the support around the dome (DESIGN §3 heights, levelled on it), in every
        // output: the GSF above, height.tif and the report.
        let peak = 6.0 * params_um_per_px();
        assert!(
            f64::from(rim).abs() < 0.05 * peak,
            "support at {rim} µm, not 0"
        );
        assert!(
            (f64::from(centre) / peak - 1.0).abs() < 0.1,
            "dome top {centre} µm, expected {peak}"
        );
        let tiff =
            crate::export::height_tiff::read_height_tiff(&out.join(files::HEIGHT_TIFF)).unwrap();
        assert_eq!(tiff.datum.as_deref(), Some("support"));
        assert_eq!(tiff.height_um.get(w / 2, h / 2 + 55), rim);
        assert!(
            field
                .title
                .as_deref()
                .unwrap()
                .contains("zero = the specimen support")
        );

        let json: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join(files::REPORT)).unwrap()).unwrap();
        let dense = &json["reconstruction"]["dense"];
        let levels = dense["levels"].as_array().unwrap();
        assert!(!levels.is_empty());
        for l in levels {
            let e: Vec<f64> = l["energy"]
                .as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap())
                .collect();
            assert_eq!(e.len(), l["iterations"].as_u64().unwrap() as usize);
            assert!(
                e.last().unwrap() <= e.first().unwrap(),
                "energy rose: {e:?}"
            );
        }
        assert!(dense["flow"]["v2_over_u2"].as_f64().unwrap() < 0.1);
        let table4 = &json["reconstruction"]["rectification"];
        for key in ["v2_over_u2_before", "v2_over_u2_after", "v2_over_u2_dense"] {
            let v = table4[key].as_f64().unwrap();
            assert!((0.0..0.1).contains(&v), "{key} = {v}");
        }
        assert!(table4["rmse_after_px"].as_f64().unwrap() < 0.5);
        assert!(json["peak_rss_mib"].as_f64().unwrap() > 0.0);
        // The noise floor: present in the file, in pixels and µm by eq. (19) (the file
        // rounds them to 1e-3 px and 1 nm, so the relation is checked unrounded).
        assert!(json["reconstruction"]["precision"]["height_um"].is_number());
        let precision = report.reconstruction.precision.as_ref().unwrap();
        let (px, um) = (precision.disparity_px, precision.height_um);
        assert!(px > 0.0 && px < 1.0, "{precision:?}");
        assert!(
            (um / px / params_um_per_px() - 1.0).abs() < 1e-9,
            "{precision:?}"
        );
        assert_eq!(json["schema_version"], 1);
        let datum = &json["reconstruction"]["datum"];
        assert_eq!(
            (&datum["requested"], &datum["kind"]),
            (&"support".into(), &"support".into())
        );
        assert!(datum["support_fraction"].as_f64().unwrap() > 0.4, "{datum}");
        assert_eq!(report.outputs.len(), 6);
    }

    /// One output that cannot be written (a directory stands at its path):
    /// the error names it, and none of the files written beside it, nor the
    /// report, nor a temporary file is left behind.
    #[test]
    fn a_failed_output_takes_the_others_with_it() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir_all(out.join(files::MESH).join("occupied")).unwrap();
        // --force: the directory in the way is left to the writer, which cannot replace it.
        let prepared = super::super::output::prepare_dir(&out, &files::ALL, true).unwrap();
        let err = reconstruct_dome(dir.path(), &prepared, &crate::progress::unobserved)
            .expect_err("mesh.ply cannot be written");
        assert!(format!("{err:#}").contains(files::MESH), "{err:#}");
        let left: Vec<String> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(left, [files::MESH], "left behind: {left:?}");
    }

    /// One precedence for the tilt axis, whichever command settles it: the
    /// command line, then the micrographs' metadata (the SEM's report in an
    /// acquisition and its replay), then `reconstruction.tilt_axis_deg`.
    #[test]
    fn the_tilt_axis_comes_first_from_the_command_line_then_the_micrographs_then_the_configuration()
    {
        use crate::acquisition::job::{EndGeometry, pair_geometry_of};
        use crate::imaging::file::{MicrographTags, SampleDepth, write_micrograph_tiff};
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, tilt: f64, axis: Option<f64>| {
            let mut extra = serde_json::Map::new();
            if let Some(a) = axis {
                extra.insert("tilt_axis_deg".into(), a.into());
            }
            let tags = MicrographTags {
                pixel_size_um: Some(0.1),
                tilt_deg: Some(tilt),
                extra,
            };
            let path = dir.path().join(name);
            write_micrograph_tiff(&path, &textured(64, 48, 3), &tags, SampleDepth::Bits16).unwrap();
            path
        };
        let end = |tilt: f64, axis: Option<f64>| EndGeometry {
            tilt_deg: tilt,
            pixel_size_um: 0.1,
            tilt_axis_deg: axis,
        };
        let mut config = crate::config::Config::default();
        config.reconstruction.tilt_axis_deg = Some(30.0);
        for sem in [Some(-60.0), None] {
            let want = sem.unwrap_or(30.0);
            let (l, r) = (write("l.tif", 0.0, sem), write("r.tif", 5.0, sem));
            let pair = load_pair(&l, &r, Figures::default(), Some(30.0)).unwrap();
            assert_eq!(
                pair.geometry.tilt_axis_deg, want,
                "reconstruct, SEM {sem:?}"
            );
            let (acquired, provenance) =
                pair_geometry_of(&config, end(0.0, sem), end(5.0, sem)).unwrap();
            assert_eq!(acquired, pair.geometry, "acquire and replay, SEM {sem:?}");
            assert_eq!(
                provenance["tilt_axis"].starts_with("metadata"),
                sem.is_some(),
                "{provenance:?}"
            );
            let given = Figures {
                tilt_axis_deg: Some(90.0),
                ..Figures::default()
            };
            let pair = load_pair(&l, &r, given, Some(30.0)).unwrap();
            assert_eq!(pair.geometry.tilt_axis_deg, 90.0);
            assert_eq!(pair.provenance["tilt_axis"], "--tilt-axis");
        }
    }

    /// µm of height per pixel of disparity of the test above (θ = 6°, 0.05 µm).
    fn params_um_per_px() -> f64 {
        0.05 / (2.0 * 3f64.to_radians().sin())
    }
}
