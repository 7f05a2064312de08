//! `sdsem status`: the jobs of a spool and what the daemon is doing.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::Args;
use serde::Serialize;

use crate::acquisition::run_dir::printable;
use crate::config::Config;
use crate::daemon::spool::{DaemonStatus, Unreadable};
use crate::daemon::{JobRecord, Spool};

#[derive(Debug, Args)]
pub struct StatusArgs {
    /// The daemon's spool (default: daemon.spool_dir of --config, else /var/lib/sdsem/spool).
    #[arg(long, value_name = "DIR")]
    pub spool: Option<PathBuf>,
    /// Configuration whose daemon.spool_dir names the spool.
    #[arg(long, short = 'c', value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// One JSON document on stdout, for scripts.
    #[arg(long)]
    pub json: bool,
}

/// `sdsem status --json`.
#[derive(Debug, Serialize)]
struct Report<'a> {
    spool: PathBuf,
    daemon: Option<DaemonReport>,
    jobs: &'a [JobRecord],
    unreadable: &'a [Unreadable],
    /// The latest entries set aside in `quarantine/`, with their reasons.
    set_aside: &'a [Unreadable],
    set_aside_total: usize,
}

#[derive(Debug, Serialize)]
struct DaemonReport {
    #[serde(flatten)]
    last: DaemonStatus,
    /// Whether that process still exists.
    alive: bool,
}

pub fn run(args: &StatusArgs) -> anyhow::Result<ExitCode> {
    let config = match &args.config {
        Some(path) => Some(Config::load(Some(path), &[])?),
        None => None,
    };
    let dir = super::submit::spool_dir(args.spool.as_deref(), config.as_ref())?;
    let spool = Spool::existing(&dir).with_context(|| {
        format!(
            "no spool at {}: nothing was submitted there yet; name the daemon's with --spool DIR \
             or --config FILE",
            dir.display()
        )
    })?;
    let listing = spool.list()?;
    let daemon = spool.daemon_status().map(|last| DaemonReport {
        alive: last.state != "stopped" && process_exists(last.pid),
        last,
    });
    if args.json {
        let report = Report {
            spool: spool.root().to_owned(),
            daemon,
            jobs: &listing.jobs,
            unreadable: &listing.unreadable,
            set_aside: &listing.set_aside,
            set_aside_total: listing.set_aside_total,
        };
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(ExitCode::SUCCESS);
    }
    // Everything printed may come from outside: escaped and cut short.
    let p = |text: &str| printable(text, 300);
    match &daemon {
        Some(d) if d.alive => println!("daemon: PID {}: {}", d.last.pid, p(&d.last.status)),
        Some(d) => println!(
            "daemon: not running (last seen {}: {})",
            p(&d.last.updated),
            p(&d.last.status)
        ),
        None => println!("daemon: has never run on this spool"),
    }
    if let Some(d) = &daemon {
        if let Some(check) = &d.last.stage_check {
            let state = if check.pending { "PENDING" } else { "done" };
            println!(
                "stage check after an unclean end ({}, {state}): {}; {}",
                p(&check.noticed),
                p(&check.cause),
                p(&check.action)
            );
        }
        for w in &d.last.warnings {
            println!("warning: {}", p(w));
        }
    }
    if listing.jobs.is_empty() {
        println!("no jobs in {}", spool.root().display());
    } else {
        print!("{}", table(&listing.jobs));
    }
    if listing.set_aside_total > 0 {
        println!(
            "set aside in {}/quarantine ({} in all{}):",
            spool.root().display(),
            listing.set_aside_total,
            if listing.set_aside_total > listing.set_aside.len() {
                format!(", the latest {} shown", listing.set_aside.len())
            } else {
                String::new()
            }
        );
        for u in &listing.set_aside {
            println!("  {}: {}", p(&u.name), p(&u.cause));
        }
    }
    for u in &listing.unreadable {
        eprintln!(
            "warning: {} is not a job record: {}",
            p(&u.name),
            p(&u.cause)
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn process_exists(pid: u32) -> bool {
    std::path::Path::new(&format!("/proc/{pid}")).exists()
}

/// The human table: id, name, state, submitted, finished, run dir, reason.
fn table(jobs: &[JobRecord]) -> String {
    let header = [
        "ID",
        "NAME",
        "STATE",
        "SUBMITTED",
        "FINISHED",
        "RUN DIR",
        "REASON",
    ];
    let rows: Vec<[String; 7]> = jobs
        .iter()
        .map(|j| {
            [
                j.id.to_string(),
                printable(&j.name, 64),
                j.state.to_string(),
                printable(&j.submitted, 30),
                j.finished
                    .as_deref()
                    .map_or_else(|| "-".into(), |t| printable(t, 30)),
                j.run_dir
                    .as_ref()
                    .map_or_else(|| "-".into(), |p| printable(&p.display().to_string(), 200)),
                printable(j.reason.as_deref().unwrap_or_default(), 500),
            ]
        })
        .collect();
    let mut widths = header.map(|h| h.chars().count());
    for row in &rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let mut out = String::new();
    let mut line = |cells: &[&str]| {
        let mut text = String::new();
        for (i, (cell, w)) in cells.iter().zip(widths).enumerate() {
            if i + 1 == cells.len() {
                text.push_str(cell);
            } else {
                text.push_str(&format!("{cell:<w$}  "));
            }
        }
        out.push_str(text.trim_end());
        out.push('\n');
    };
    line(&header);
    for row in &rows {
        line(&row.each_ref().map(String::as_str));
    }
    out
}
