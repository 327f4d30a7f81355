//! `rlmflow compare`: two runs, or one run's variants, side by side (`crate::compare` builds the tables).

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context as _;
use rlmflow_stages::Registry;

use super::{StoreArg, UsageError, ran_store};
use crate::config;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    /// Run ids, or unique beginnings of them (`rlmflow runs` lists them); or two instances of
    /// a probe or segmenter (`'clipcap[clip]' 'clipcap[random]'`), for the test frames where
    /// their outputs differ most.
    #[arg(value_name = "RUN", num_args = 0..=2)]
    runs: Vec<String>,
    /// With two instances: how many of the most different frames to list.
    #[arg(long, default_value_t = 10)]
    top: usize,
    /// Compare the variants of each stage of one run (default: the latest).
    #[arg(long)]
    variants: bool,
    /// Every instance, setting and metric, not only those that differ.
    #[arg(long)]
    all: bool,
    #[arg(long, conflicts_with = "markdown")]
    json: bool,
    /// Markdown tables, for pasting into a note or an issue.
    #[arg(long)]
    markdown: bool,
    #[command(flatten)]
    store: StoreArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, runs: ids, top, variants, all, json, markdown, store } = args;
    let p = super::at_look(config::load(&pipeline, registry)?, registry, &store)?;
    let store = ran_store(&p, &store, "nothing to compare")?;
    let stage_of = |text: &str| text.split('[').next().map(str::to_owned).unwrap_or_default();
    if let [a, b] = ids.as_slice()
        && p.stage(&stage_of(a)).is_some()
    {
        let frames = crate::compare::frames(&p, registry, &store, a, b)?;
        match json {
            true => println!("{}", serde_json::to_string(&frames)?),
            false => print!("{}", frames.terminal(top)),
        }
        return Ok(ExitCode::SUCCESS);
    }
    let runs = crate::history::runs_of(&store, &p.name)?;
    // Unnamed runs are the newest that are not plain reruns, in which nothing differs.
    let computing: Vec<&crate::history::PastRun> = runs.iter().filter(|r| !r.repeats).collect();
    let pick = |id: Option<&String>, newest: usize| -> anyhow::Result<&crate::history::PastRun> {
        match id {
            Some(id) => crate::history::find(&runs, id, &p.name),
            None => computing.get(newest).copied().with_context(|| {
                format!(
                    "pipeline `{}` has {} run(s) in {} besides plain reruns ({} in all); compare needs {} (name runs to compare others)",
                    p.name,
                    computing.len(),
                    store.root().display(),
                    runs.len(),
                    newest + 1
                )
            }),
        }
    };
    let tables = if variants {
        if ids.len() > 1 {
            return Err(UsageError("--variants compares the variants of one run: give at most one RUN".into()).into());
        }
        crate::compare::variants(&store, pick(ids.first(), 0)?, all)?
    } else {
        let (a, b) = match ids.as_slice() {
            [] => (pick(None, 1)?, pick(None, 0)?),
            [a] => (pick(Some(a), 0)?, pick(None, 0)?),
            [a, b, ..] => (pick(Some(a), 0)?, pick(Some(b), 0)?),
        };
        vec![crate::compare::runs(&store, a, b, all)?]
    };
    for table in &tables {
        match (json, markdown) {
            (true, _) => println!("{}", serde_json::to_string(table)?),
            (_, true) => println!("{}", table.markdown()),
            _ => print!("{}", table.terminal()),
        }
    }
    Ok(ExitCode::SUCCESS)
}
