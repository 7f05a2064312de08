//! `sdsem replay RUN.mcap --out DIR [--set KEY=VALUE]`: reconstruct a run
//! again from its record and say whether the height map is bit-identical.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;

use crate::app::replay::{self, Comparison};
use crate::numbers;

#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// The run record, e.g. runs/sim-…/run.mcap (also a truncated one).
    pub record: PathBuf,
    /// Output directory: height.tif, height.gsf, pointcloud.ply, mesh.ply,
    /// confidence.tif, report.json, and replay.json with the comparison.
    #[arg(long, short)]
    pub out: PathBuf,
    /// Replace the outputs of an earlier replay in the output directory.
    #[arg(long)]
    pub force: bool,
    /// Change a parameter of the recorded configuration, e.g.
    /// `--set reconstruction.mode=paper` (repeatable); the comparison is then
    /// informative, not a failure.
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub overrides: Vec<String>,
    /// Print the replay report as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Exit code when, without `--set`, the replay does not reproduce the record.
const EXIT_MISMATCH: u8 = 2;

pub fn run(args: &ReplayArgs) -> anyhow::Result<ExitCode> {
    let created = crate::app::output::Created::before(&args.out);
    let out = crate::app::output::prepare_dir(&args.out, &replay::FILES, args.force)?;
    let display = super::progress::StageDisplay::on_stderr();
    let report = replay::replay(&args.record, &out, &args.overrides, &|stage| {
        display.observe(stage);
    });
    display.finish(report.is_ok());
    created.undo_on_failure(&report);
    let report = report?;
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&crate::numbers::report_json(&report)?)?
        );
    } else {
        if let Some(note) = &report.record_note {
            eprintln!("note: {note}");
        }
        let g = &report.geometry;
        println!(
            "replayed {} with the configuration from {}{}: θ {}°, pixel {} µm, φ {}°; heights on {:.1} % of the left grid",
            report.record.display(),
            report.config_source,
            if report.overrides.is_empty() {
                String::new()
            } else {
                format!(" and --set {}", report.overrides.join(" --set "))
            },
            numbers::deg(g.tilt_deg),
            numbers::significant(g.pixel_size_um, 6),
            numbers::deg(g.tilt_axis_deg),
            100.0 * report.reconstruction.reconstruction.depth.valid_fraction
        );
        println!("{}", report.comparison.summary());
        eprintln!(
            "wrote {}/{{{}, {}}}",
            report.out.display(),
            report.reconstruction.outputs.join(", "),
            replay::REPLAY_REPORT
        );
        println!("{}", report.out.display());
    }
    if report.is_mismatch() {
        eprintln!(
            "replay does not reproduce the record: {} (the pipeline should be deterministic; \
             report it with both files)",
            report.comparison.summary()
        );
        return Ok(ExitCode::from(EXIT_MISMATCH));
    }
    if !args.overrides.is_empty() && matches!(report.comparison, Comparison::Identical { .. }) {
        eprintln!("note: the overrides did not change the height map");
    }
    Ok(ExitCode::SUCCESS)
}
