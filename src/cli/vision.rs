//! The offline commands on micrographs: `reconstruct`, `rectify`, `flow`.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::Args;

use super::ConfigArgs;
use super::progress::StageDisplay;
use crate::app::output;
use crate::app::reconstruct;
use crate::numbers;
use crate::vision::geometry::Figures;

#[derive(Debug, Args)]
pub struct ReconstructArgs {
    /// Micrograph at the lower stage tilt (TIFF, PNG, JPEG or BMP; grey).
    pub left: PathBuf,
    /// Micrograph at the higher stage tilt.
    pub right: PathBuf,
    /// Output directory: height.tif, height.gsf, pointcloud.ply, mesh.ply, confidence.tif,
    /// report.json.
    #[arg(long, short)]
    pub out: PathBuf,
    /// Replace the outputs of an earlier run in the output directory.
    #[arg(long)]
    pub force: bool,
    /// Tilt difference θ between the micrographs, degrees (default: from their metadata).
    // Negative values are taken, so that the refusal names the allowed range.
    #[arg(long, value_name = "DEG", allow_hyphen_values = true)]
    pub tilt: Option<f64>,
    /// Pixel size, µm (default: from the metadata).
    #[arg(long, value_name = "UM", allow_hyphen_values = true)]
    pub pixel_size: Option<f64>,
    /// Direction of the tilt axis in the image, degrees from +x towards +y
    /// (default: metadata, then reconstruction.tilt_axis_deg).
    #[arg(long, value_name = "DEG", allow_hyphen_values = true)]
    pub tilt_axis: Option<f64>,
    #[command(flatten)]
    pub config: ConfigArgs,
}

#[derive(Debug, Args)]
pub struct RectifyArgs {
    /// Micrograph at the lower stage tilt.
    pub left: PathBuf,
    /// Micrograph at the higher stage tilt.
    pub right: PathBuf,
    /// Output directory: rectified_left.png, rectified_right.png, matches.png, rectification.json.
    #[arg(long, short)]
    pub out: PathBuf,
    /// Replace the outputs of an earlier run in the output directory.
    #[arg(long)]
    pub force: bool,
    /// Direction of the tilt axis in the image, degrees (orients the rectified pair).
    #[arg(long, value_name = "DEG", allow_hyphen_values = true)]
    pub tilt_axis: Option<f64>,
    #[command(flatten)]
    pub config: ConfigArgs,
}

#[derive(Debug, Args)]
pub struct FlowArgs {
    /// First image.
    pub a: PathBuf,
    /// Second image.
    pub b: PathBuf,
    /// The flow from A to B as Middlebury .flo.
    #[arg(long, short)]
    pub out: PathBuf,
    /// Replace the file if it exists.
    #[arg(long)]
    pub force: bool,
    #[command(flatten)]
    pub config: ConfigArgs,
}

pub fn run_reconstruct(args: &ReconstructArgs) -> anyhow::Result<ExitCode> {
    let config = args.config.load()?;
    let created = output::Created::before(&args.out);
    let out = output::prepare_dir(&args.out, &reconstruct::files::ALL, args.force)?;
    let given = Figures {
        tilt_deg: args.tilt,
        pixel_size_um: args.pixel_size,
        tilt_axis_deg: args.tilt_axis,
    };
    let display = StageDisplay::on_stderr();
    let report = reconstruct::run(
        &args.left,
        &args.right,
        &out,
        given,
        config.reconstruction.tilt_axis_deg,
        &config.reconstruction.params(),
        &config.reconstruction.mesh,
        &|stage| display.observe(stage),
    );
    display.finish(report.is_ok());
    created.undo_on_failure(&report);
    summarise(&report?, &args.out);
    Ok(ExitCode::SUCCESS)
}

fn summarise(report: &reconstruct::ReportFile, out: &Path) {
    let r = &report.reconstruction;
    let t = &r.timings;
    eprintln!(
        "θ = {:.3}°, pixel {:.4} µm, tilt axis {:.1}°: {} inliers, rectification error {:.2} px → {:.2} px",
        r.geometry.pair.tilt_deg,
        r.geometry.pair.pixel_size_um,
        r.geometry.pair.tilt_axis_deg,
        r.sparse.inliers,
        r.sparse.initial_error_px,
        r.sparse.final_error_px
    );
    eprintln!("{}", geometry_line(&r.geometry));
    // Interpolated heights are counted on the rectified canvas (report.json:
    // dense.filled_fraction); confidence.tif marks them on the left grid.
    let filled = if r.dense.filled_fraction > 0.0 {
        format!(
            " ({:.1} % of the canvas interpolated, confidence 0)",
            100.0 * r.dense.filled_fraction
        )
    } else {
        String::new()
    };
    eprintln!(
        "heights on {:.1} % of the pixels{filled}, {:.2} … {:.2} µm (1st–99th percentile)",
        100.0 * r.depth.valid_fraction,
        r.depth.height_p01_um,
        r.depth.height_p99_um
    );
    eprintln!("{}", datum_line(&r.datum));
    if let Some(line) = precision_line(r) {
        eprintln!("{line}");
    }
    eprintln!(
        "time: sparse {:.2} s, dense {:.2} s, depth {:.2} s, total {:.2} s (with I/O {:.2} s); peak memory {}",
        t.sparse_ms / 1e3,
        t.dense_ms / 1e3,
        t.depth_ms / 1e3,
        t.total_ms / 1e3,
        report.wall_s,
        report
            .peak_rss_mib
            .map_or_else(|| "unknown".to_owned(), |m| format!("{m:.0} MiB"))
    );
    eprintln!(
        "wrote {}",
        written(
            out,
            &report.outputs.iter().map(PathBuf::from).collect::<Vec<_>>()
        )
    );
    println!("{}", out.display());
}

/// `DIR/{a, b, c}` for a summary line: the files a command wrote into `dir`.
fn written(dir: &Path, files: &[PathBuf]) -> String {
    let names: Vec<String> = files
        .iter()
        .map(|f| {
            f.file_name().map_or_else(
                || f.display().to_string(),
                |n| n.to_string_lossy().into_owned(),
            )
        })
        .collect();
    format!("{}/{{{}}}", dir.display(), names.join(", "))
}

/// Share of the relief (1st–99th percentile) above which the summary
/// advises a longer dwell or a larger tilt.
const NOISY_SHARE: f64 = 0.05;

/// What zero height is (`reconstruction.datum`), with the support's share and RMS.
fn datum_line(d: &crate::vision::datum::Datum) -> String {
    let mut line = format!("zero: {}", d.zero);
    if let (Some(share), Some(rms)) = (d.support_fraction, d.support_rms_um) {
        line += &format!(
            "; {:.1} % of the heights on it, RMS {rms:.2} µm",
            100.0 * share
        );
    }
    if let Some(why) = &d.fallback {
        line += &format!(" (no support: {why})");
    }
    line
}

/// The predicted precision in one line, with advice when the noise floor
/// is a noticeable share of the relief.
/// Which path rectified the pair and, for the instrument's, how it was verified.
fn geometry_line(g: &crate::vision::pipeline::GeometryReport) -> String {
    match (&g.instrument, &g.sparse_refused) {
        (Some(f), why) => format!(
            "geometry: instrument (tilt axis {:.1}°; sparse stage: {}): {} of {} tiles and {} of {} matches on the rows, rotation {:.2}°, scale {:.4}, rows ±{:.2} px, dense stage's rows {}",
            g.pair.tilt_axis_deg,
            why.as_deref().unwrap_or("not used"),
            f.tiles_agreeing,
            f.tiles_measured,
            f.matches_agreeing,
            f.matches_offered,
            f.rotation_deg,
            f.scale,
            f.row_residual_rms_px,
            f.dense_rows.map_or_else(
                || "not checked (tiled)".to_owned(),
                |r| format!(
                    "{:.2} px off, axis {:+.2}° (moves rows {:.2} px)",
                    r.offset_px, r.axis_error_deg, r.leak_px
                )
            ),
        ),
        (None, _) => "geometry: sparse (epipolar geometry from the matches)".to_owned(),
    }
}

fn precision_line(r: &crate::vision::pipeline::ReconReport) -> Option<String> {
    let relief = r.depth.height_p99_um - r.depth.height_p01_um;
    r.precision.as_ref().map(|p| describe_precision(p, relief))
}

/// [`precision_line`] for a floor `p` and a relief of `relief` µm.
fn describe_precision(p: &crate::vision::precision::Precision, relief: f64) -> String {
    let mut line = format!(
        "noise floor: height ±{:.3} µm ({:.3} disparity px) at the matcher's window (σ {:.1} px); image noise {:.0} % / {:.0} % of the signal",
        p.height_um,
        p.disparity_px,
        p.window_sigma_px,
        100.0 * p.noise_to_signal[0],
        100.0 * p.noise_to_signal[1]
    );
    if relief > 0.0 && p.height_um > NOISY_SHARE * relief {
        line.push_str(&format!(
            " — {:.0} % of the relief: a longer dwell or a larger tilt would resolve finer detail",
            100.0 * p.height_um / relief
        ));
    }
    line
}

pub fn run_rectify(args: &RectifyArgs) -> anyhow::Result<ExitCode> {
    let config = args.config.load()?;
    let created = output::Created::before(&args.out);
    let out = output::prepare_dir(&args.out, &crate::app::rectify::FILES, args.force)?;
    // The precedence of every command: the flag, the files' metadata, the configuration.
    let metadata = |path: &Path| {
        crate::imaging::file::read_sem_metadata(path)
            .map(|m| reconstruct::figures_of(&m))
            .unwrap_or_default()
    };
    let tilt_axis = crate::vision::geometry::GeometrySources {
        given: Figures {
            tilt_axis_deg: args.tilt_axis,
            ..Figures::default()
        },
        left: metadata(&args.left),
        right: metadata(&args.right),
        configured_tilt_axis_deg: config.reconstruction.tilt_axis_deg,
        names: [
            args.left.display().to_string(),
            args.right.display().to_string(),
        ],
    }
    .tilt_axis()
    .map(|(axis, _)| axis);
    let outputs = crate::app::rectify::run_rectify(
        &args.left,
        &args.right,
        &out,
        tilt_axis,
        &config.reconstruction.sparse,
    );
    created.undo_on_failure(&outputs);
    let outputs = outputs?;
    eprintln!(
        "{} inlier matches, rectification error {} px → {} px",
        outputs.inliers,
        numbers::px(outputs.initial_error_px),
        numbers::px(outputs.final_error_px)
    );
    eprintln!("wrote {}", written(&args.out, &outputs.files));
    println!("{}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

pub fn run_flow(args: &FlowArgs) -> anyhow::Result<ExitCode> {
    let config = args.config.load()?;
    let created = args.out.parent().map(output::Created::before);
    let (dir, name) = output::prepare_file(&args.out, args.force)?;
    let params = config.reconstruction.dense.flow;
    let flow = crate::app::flow::run(&args.a, &args.b, (&dir, &name), &params);
    if let Some(created) = &created {
        created.undo_on_failure(&flow);
    }
    let flow = flow?;
    eprintln!(
        "wrote {} ({}×{} flow from {} to {})",
        args.out.display(),
        flow.u.width(),
        flow.u.height(),
        args.a.display(),
        args.b.display()
    );
    println!("{}", args.out.display());
    Ok(ExitCode::SUCCESS)
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use crate::cli::{Cli, Command};

    /// The summary advises a longer dwell or a larger tilt only when the
    /// noise floor exceeds 5 % of the relief.
    #[test]
    fn noise_floor_advice_only_above_five_percent_of_the_relief() {
        let p = crate::vision::precision::Precision {
            noise_to_signal: [0.4, 0.41],
            window_sigma_px: 6.0,
            disparity_px: 0.1,
            height_um: 0.06,
        };
        let quiet = super::describe_precision(&p, 2.0);
        assert!(
            quiet.contains("±0.060 µm") && quiet.contains("40 % / 41 %"),
            "{quiet}"
        );
        assert!(!quiet.contains("dwell"), "{quiet}");
        let noisy = super::describe_precision(&p, 1.0);
        assert!(
            noisy.contains("6 % of the relief") && noisy.contains("dwell"),
            "{noisy}"
        );
        // No relief measured: no share to judge.
        assert!(!super::describe_precision(&p, 0.0).contains("dwell"));
    }

    /// A negative tilt or pixel size reaches the checks that explain the
    /// allowed range, instead of being taken for an unknown flag.
    #[test]
    fn negative_tilt_and_pixel_size_are_values_not_flags() {
        let cli = Cli::try_parse_from([
            "sdsem",
            "reconstruct",
            "a.tif",
            "b.tif",
            "-o",
            "out",
            "--tilt",
            "-3",
            "--pixel-size",
            "-0.1",
            "--tilt-axis",
            "-90",
        ])
        .unwrap();
        let Command::Reconstruct(args) = cli.command else {
            panic!("not reconstruct");
        };
        assert_eq!(args.tilt, Some(-3.0));
        assert_eq!(args.pixel_size, Some(-0.1));
        assert_eq!(args.tilt_axis, Some(-90.0));
    }
}
