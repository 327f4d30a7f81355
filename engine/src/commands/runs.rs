//! `rlmflow runs`: a pipeline's runs, newest first (`crate::history`).

use std::path::PathBuf;
use std::process::ExitCode;

use rlmflow_stages::Registry;

use super::{StoreArg, ran_store};
use crate::config;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    /// The headline of every stage instance, reused ones too.
    #[arg(long)]
    all: bool,
    /// At most N runs.
    #[arg(long, value_name = "N")]
    last: Option<usize>,
    /// One JSON object per run and line: its plan, how each instance ended, the counts,
    /// whether it finished.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    store: StoreArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, all, last, json, store } = args;
    let p = config::load(&pipeline, registry)?;
    let store = ran_store(&p, &store, "no runs to list")?;
    let mut runs = crate::history::runs_of(&store, &p.name)?;
    runs.truncate(last.unwrap_or(usize::MAX));
    if json {
        for run in &runs {
            let mut line = serde_json::to_value(run)?;
            line["counts"] = serde_json::to_value(run.counts())?;
            println!("{line}");
        }
    } else if runs.is_empty() {
        println!("no runs of pipeline `{}` in {}", p.name, store.root().display());
    } else {
        print!("{}", crate::history::listing(&store, &runs, all)?);
    }
    Ok(ExitCode::SUCCESS)
}
