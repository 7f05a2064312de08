//! `sdsem submit JOB.toml`: validate a job and queue it for the daemon.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::SystemTime;

use anyhow::Context;
use clap::Args;

use crate::config::Config;
use crate::daemon::{JobSpec, Spool};

#[derive(Debug, Args)]
pub struct SubmitArgs {
    /// The job file (TOML: name, start_tilt, end_tilt, step, optional [capture] and
    /// [reconstruction] overrides).
    pub job: PathBuf,
    /// The daemon's spool (default: daemon.spool_dir of --config, else /var/lib/sdsem/spool).
    #[arg(long, value_name = "DIR")]
    pub spool: Option<PathBuf>,
    /// Validate against this configuration instead of the one the daemon
    /// published in its spool.
    #[arg(long, short = 'c', value_name = "FILE")]
    pub config: Option<PathBuf>,
}

/// Where a submission's configuration comes from, for the messages.
enum Basis {
    File(PathBuf),
    Daemon(PathBuf),
    Defaults,
}

impl std::fmt::Display for Basis {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::File(p) => write!(f, "{}", p.display()),
            Self::Daemon(p) => write!(f, "the daemon's configuration ({})", p.display()),
            Self::Defaults => f.write_str(
                "the built-in defaults, as no daemon has published its configuration in this \
                 spool (pass --config to check against yours)",
            ),
        }
    }
}

pub fn run(args: &SubmitArgs) -> anyhow::Result<ExitCode> {
    let spec = JobSpec::load(&args.job)
        .with_context(|| format!("job {} refused, nothing queued", args.job.display()))?;
    let file_config = match &args.config {
        Some(path) => Some(Config::load(Some(path), &[])?),
        None => None,
    };
    let spool_dir = spool_dir(args.spool.as_deref(), file_config.as_ref())?;
    let (base, basis) = match (file_config, &args.config) {
        (Some(config), Some(path)) => (config, Basis::File(path.clone())),
        _ => daemon_or_default_config(&spool_dir)?,
    };
    if let Err(e) = spec.effective_config(&base) {
        anyhow::bail!(
            "job {} refused, nothing queued: {e}; checked against {basis}",
            args.job.display()
        );
    }
    let spool = Spool::open(&spool_dir)?;
    let record = spool.submit(spec, SystemTime::now())?;
    println!(
        "queued job {} ({}) in {}",
        record.id,
        record.name,
        spool.root().display()
    );
    Ok(ExitCode::SUCCESS)
}

/// `--spool`, else `daemon.spool_dir` of the given configuration, else of
/// the defaults and environment (`SDSEM_DAEMON__SPOOL_DIR`).
pub(super) fn spool_dir(spool: Option<&Path>, config: Option<&Config>) -> anyhow::Result<PathBuf> {
    if let Some(dir) = spool {
        return Ok(dir.to_owned());
    }
    if let Some(config) = config {
        return Ok(config.daemon.spool_dir.clone());
    }
    Ok(Config::load(None, &[])?.daemon.spool_dir)
}

/// The configuration the daemon published in its spool, else the defaults.
fn daemon_or_default_config(spool_dir: &Path) -> anyhow::Result<(Config, Basis)> {
    let snapshot = spool_dir.join("config.toml");
    let text = match Spool::existing(spool_dir) {
        Ok(spool) => spool.read_config_snapshot()?,
        Err(_) => None,
    };
    match text {
        Some(text) => {
            // Already effective: the submitter's environment must not change it.
            let config = Config::from_layers(Some(&text), Some(&snapshot), &[], std::iter::empty())
                .with_context(|| {
                    format!(
                        "the daemon's configuration {} is unreadable",
                        snapshot.display()
                    )
                })?;
            Ok((config, Basis::Daemon(snapshot)))
        }
        None => Ok((Config::load(None, &[])?, Basis::Defaults)),
    }
}
