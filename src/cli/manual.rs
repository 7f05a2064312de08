//! What the command line says about itself: the examples under every `--help`, shell
//! completions (`sdsem completions SHELL`) and the manual pages (`sdsem man`), the last two
//! generated from the very definition clap parses, so they cannot drift from it.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::{Context, bail};
use clap::{Args, CommandFactory};

use super::Cli;

/// Examples under `sdsem --help`.
pub const ROOT: &str = "\
Examples:
  sdsem probe --config /etc/sdsem/sdsem.toml     what the microscope says it is; moves nothing
  sdsem acquire --config config/sim.toml         one run on the built-in simulator
  sdsem reconstruct left.tif right.tif -o out    height map, point cloud and mesh of a pair
  sdsem inspect runs/sim-20261122T062642Z/run.mcap
                                                 what a run record holds
  sdsem check-config /etc/sdsem/sdsem.toml       validate a configuration before a run
  sdsem completions bash > ~/.local/share/bash-completion/completions/sdsem
  sdsem man | man -l -                           this help as a manual page

A failing command prints one line: the cause and what to do. NO_COLOR=1 turns colours off.";

pub const ACQUIRE: &str = "\
Examples:
  sdsem acquire --config config/sim.toml
      a 0→7° run on the built-in simulator; the last line is the run directory
  sdsem acquire -c /etc/sdsem/sdsem.toml --set series.end_tilt_deg=5
      one run on the microscope, ending at 5°";

pub const PROBE: &str = "\
Examples:
  sdsem probe --config /etc/sdsem/sdsem.toml
      what the stage and the SEM say they are, where the stage is, its limits; moves nothing
  sdsem probe -c config/sim-zeiss.toml --json
      the same as JSON, here against the built-in simulator of a Zeiss SEM";

pub const RECONSTRUCT: &str = "\
Examples:
  sdsem reconstruct left.tif right.tif --out out
      tilt and pixel size from the TIFFs' SEM metadata
  sdsem reconstruct a.png b.png -o out --tilt 6 --pixel-size 0.0558 --tilt-axis -90
      files without metadata: give the geometry
  sdsem reconstruct left.tif right.tif -o out --set reconstruction.mode=paper
      the method exactly as published (integer disparities, plain bilateral grid)";

pub const RECTIFY: &str = "\
Examples:
  sdsem rectify left.tif right.tif --out rect --tilt-axis -90
      rectified_left.png, rectified_right.png, matches.png, rectification.json
  sdsem rectify left.tif right.tif -o rect --set reconstruction.sparse.matching.ratio=0.7
      stricter matching on a repetitive specimen";

pub const FLOW: &str = "\
Examples:
  sdsem flow frame1.png frame2.png --out flow.flo
  sdsem flow a.png b.png -o flow.flo --set reconstruction.mode=paper
      the SIFT flow exactly as published (integer displacements)";

pub const INSPECT: &str = "\
Examples:
  sdsem inspect runs/sim-20261122T062642Z/run.mcap
  sdsem inspect run.mcap --json | python3 -m json.tool";

pub const CHECK_CONFIG: &str = "\
Examples:
  sdsem check-config config/sim.toml
  sdsem check-config /etc/sdsem/sdsem.toml --set stage.tilt_max_deg=45 --quiet && echo valid";

pub const DAEMON: &str = "\
Examples:
  sdsem daemon --config /etc/sdsem/sdsem.toml
      as systemd runs it (systemd/sdsem.service)
  sdsem daemon --config config/sim.toml --spool /tmp/spool
      a test rig on the built-in simulator";

pub const SUBMIT: &str = "\
Examples:
  sdsem submit job.toml
      job.toml: name = \"pot-01\", start_tilt = 0.0, end_tilt = 7.0
  sdsem submit job.toml --spool /tmp/spool --config config/sim.toml";

pub const STATUS: &str = "\
Examples:
  sdsem status
  sdsem status --spool /tmp/spool --json";

pub const REPLAY: &str = "\
Examples:
  sdsem replay runs/sim-20261122T062642Z/run.mcap --out again
      says whether the height map is bit-for-bit the recorded one
  sdsem replay run.mcap -o paper --set reconstruction.mode=paper
      the same micrographs through the published method";

pub const COMPLETIONS: &str = "\
Examples:
  sdsem completions bash > ~/.local/share/bash-completion/completions/sdsem
  sdsem completions zsh > ~/.zfunc/_sdsem
  sdsem completions fish > ~/.config/fish/completions/sdsem.fish";

pub const MAN: &str = "\
Examples:
  sdsem man | man -l -
  sdsem man reconstruct | man -l -
  sdsem man --dir /usr/local/share/man/man1      every page, for `man sdsem-reconstruct`";

#[derive(Debug, Args)]
pub struct CompletionsArgs {
    /// The shell to complete for.
    #[arg(value_enum)]
    pub shell: clap_complete::Shell,
}

#[derive(Debug, Args)]
pub struct ManArgs {
    /// The command whose page to print, e.g. `reconstruct` (default: sdsem).
    pub command: Vec<String>,
    /// Write every page (sdsem.1, sdsem-reconstruct.1, …) into DIR instead.
    #[arg(long, value_name = "DIR", conflicts_with = "command")]
    pub dir: Option<PathBuf>,
}

/// The command definition as the manual shows it (without clap's `help` subcommand).
fn definition() -> clap::Command {
    let mut cmd = Cli::command().disable_help_subcommand(true);
    // Gives every subcommand its display name (`sdsem-reconstruct`) for the page titles.
    cmd.build();
    cmd
}

/// The manual page of `cmd`, with the program's name and version as its source.
fn page(cmd: clap::Command) -> clap_mangen::Man {
    clap_mangen::Man::new(cmd)
        .source(concat!("sdsem ", env!("CARGO_PKG_VERSION")))
        .manual("sdsem manual")
}

/// Prints the completion script for `shell`.
///
/// # Errors
/// When stdout cannot be written.
pub fn completions(args: &CompletionsArgs) -> anyhow::Result<ExitCode> {
    let mut cmd = Cli::command();
    let mut out = Vec::new();
    clap_complete::generate(args.shell, &mut cmd, "sdsem", &mut out);
    std::io::stdout().write_all(&out)?;
    Ok(ExitCode::SUCCESS)
}

/// Prints one manual page as roff, or writes every page into `--dir`.
///
/// # Errors
/// An unknown command (with the ones there are), or a page that cannot be written.
pub fn man(args: &ManArgs) -> anyhow::Result<ExitCode> {
    if let Some(dir) = &args.dir {
        for path in write_pages(dir)? {
            println!("{}", path.display());
        }
        return Ok(ExitCode::SUCCESS);
    }
    let mut cmd = definition();
    for name in &args.command {
        let known: Vec<String> = cmd
            .get_subcommands()
            .map(|c| c.get_name().to_owned())
            .collect();
        let Some(sub) = cmd.find_subcommand(name).cloned() else {
            bail!(
                "no command {name:?} in {}: the pages are for {}",
                cmd.get_display_name().unwrap_or("sdsem"),
                known.join(", ")
            );
        };
        cmd = sub;
    }
    let mut roff = Vec::new();
    page(cmd).render(&mut roff)?;
    std::io::stdout().write_all(&roff)?;
    Ok(ExitCode::SUCCESS)
}

/// Writes `sdsem.1` and one page per (sub)command into `dir`; returns the files written.
fn write_pages(dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut written = Vec::new();
    let mut pending = vec![definition()];
    while let Some(cmd) = pending.pop() {
        let man = page(cmd.clone());
        let path = dir.join(man.get_filename());
        let mut roff = Vec::new();
        man.render(&mut roff)?;
        crate::export::atomic::write_atomic(&path, |w| w.write_all(&roff))?;
        written.push(path);
        pending.extend(
            cmd.get_subcommands()
                .filter(|c| c.get_name() != "help")
                .cloned(),
        );
    }
    written.sort();
    Ok(written)
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::*;

    /// Every command's `--help` ends with examples that parse as that command.
    #[test]
    fn every_help_has_examples_that_parse() {
        let mut pending = vec![(Vec::<String>::new(), definition())];
        let mut checked = 0;
        while let Some((path, cmd)) = pending.pop() {
            let help = cmd
                .get_after_help()
                .map(ToString::to_string)
                .unwrap_or_default();
            assert!(
                help.starts_with("Examples:"),
                "sdsem {} has no examples",
                path.join(" ")
            );
            for line in help
                .lines()
                .filter(|l| l.trim_start().starts_with("sdsem "))
            {
                // The command itself: before its description (after two spaces) and
                // without a shell redirection or pipe after it.
                let command = line.trim_start().split("  ").next().unwrap_or_default();
                let words: Vec<&str> = command
                    .split_whitespace()
                    .take_while(|w| !matches!(*w, ">" | "|" | "&&"))
                    .collect();
                let words = shell_words(&words.join(" "));
                let parsed = Cli::try_parse_from(&words);
                assert!(
                    parsed.is_ok(),
                    "{line:?} does not parse: {:?}",
                    parsed.err()
                );
                assert!(
                    words[1..].starts_with(&path) || path.is_empty(),
                    "{line:?} is not an example of sdsem {}",
                    path.join(" ")
                );
            }
            checked += 1;
            for sub in cmd.get_subcommands().filter(|c| c.get_name() != "help") {
                let mut p = path.clone();
                p.push(sub.get_name().to_owned());
                pending.push((p, sub.clone()));
            }
        }
        assert!(checked >= 13, "{checked} commands");
    }

    /// Splits on spaces outside double quotes (enough for the examples above).
    fn shell_words(line: &str) -> Vec<String> {
        let mut words = vec![String::new()];
        let mut quoted = false;
        for c in line.chars() {
            match c {
                '"' => quoted = !quoted,
                ' ' if !quoted => words.push(String::new()),
                c => words.last_mut().expect("never empty").push(c),
            }
        }
        words.retain(|w| !w.is_empty());
        words
    }

    /// The examples only name keys the command reads: no `series.*` for the commands
    /// that work on micrographs.
    #[test]
    fn offline_commands_do_not_suggest_series_keys() {
        let cmd = definition();
        for name in ["reconstruct", "rectify", "flow"] {
            let sub = cmd.find_subcommand(name).unwrap();
            let help = sub.clone().render_long_help().to_string();
            assert!(!help.contains("series."), "sdsem {name} --help:\n{help}");
            assert!(help.contains("--set reconstruction."), "{name}");
        }
    }

    #[test]
    fn man_dir_writes_a_page_per_command() {
        let dir = tempfile::tempdir().unwrap();
        let pages = write_pages(dir.path()).unwrap();
        let names: Vec<String> = pages
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        for want in ["sdsem.1", "sdsem-reconstruct.1", "sdsem-flow.1"] {
            assert!(names.iter().any(|n| n == want), "{want} not in {names:?}");
        }
        let page = std::fs::read_to_string(dir.path().join("sdsem-reconstruct.1")).unwrap();
        assert!(page.contains(".TH sdsem-reconstruct 1"), "{page}");
        assert!(page.contains("\\-\\-tilt\\-axis"), "{page}");
    }
}
