//! `rlmflow gc`: remove what no root reaches.

use std::path::PathBuf;
use std::process::ExitCode;

use rlmflow_stages::Registry;

use super::{StoreArg, existing_store};

#[derive(clap::Args)]
pub(crate) struct Args {
    /// A pipeline whose store to collect (else --cache, else ./.rlmflow).
    pipeline: Option<PathBuf>,
    #[arg(long)]
    dry_run: bool,
    #[arg(long, default_value_t = 10)]
    keep_runs: usize,
    /// Also remove the stored answers of outside services (an `llm` stage then asks its
    /// endpoint again).
    #[arg(long)]
    responses: bool,
    #[command(flatten)]
    store: StoreArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, dry_run, keep_runs, responses, store } = args;
    let store = existing_store(registry, pipeline.as_deref(), &store)?;
    let report = store.gc(keep_runs, dry_run, responses)?;
    let verb = if dry_run { "would remove" } else { "removed" };
    let mut counts: std::collections::BTreeMap<&str, usize> = Default::default();
    for (what, path, _) in &report.removed {
        *counts.entry(what).or_default() += 1;
        if dry_run {
            println!("  {verb} {what} {}", path.display());
        }
    }
    let parts: Vec<String> = counts.iter().map(|(w, n)| format!("{n} {w}")).collect();
    println!(
        "gc: {verb} {} ({:.1} MB); kept {} objects",
        if parts.is_empty() { "nothing".into() } else { parts.join(", ") },
        report.bytes() as f64 / 1e6,
        report.kept_objects
    );
    Ok(ExitCode::SUCCESS)
}
