//! `rlmflow pin`: keep a pipeline's current results under a name, so gc keeps them.

use std::path::PathBuf;
use std::process::ExitCode;

use rlmflow_cache::Refs;
use rlmflow_stages::{Device, Registry};

use super::{StoreArg, ran_store};
use crate::config;
use crate::plan::{Freshness, assess};
use crate::preflight::planned;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    name: String,
    /// Pin only these stages (or instances, as a run prints them: `pretrain[alpha4]`) and what
    /// they need (repeatable).
    #[arg(long, value_name = "STAGE")]
    only: Vec<String>,
    #[command(flatten)]
    store: StoreArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, name, only, store } = args;
    config::check_name(&name).map_err(|problem| anyhow::anyhow!("the pin name {problem}"))?;
    let p = super::at_look(config::load(&pipeline, registry)?, registry, &store)?;
    let store = ran_store(&p, &store, "nothing to pin")?;
    let plan = planned(&p, Some(&store), Device::Cpu)?;
    let selected = plan.select(&only)?;
    let states = assess(&plan, registry, Some(&store))?;
    let instances = states
        .iter()
        .enumerate()
        .filter(|&(i, _)| selected[i])
        .filter_map(|(i, s)| match s {
            Freshness::Cached(r) => Some((plan.id(i), r.key)),
            _ => None,
        })
        .collect();
    let keys = Refs { instances, labels: Default::default() };
    let path = store.pin(&name, &keys)?;
    println!("pinned {} cached stage instances in {}", keys.len(), path.display());
    Ok(ExitCode::SUCCESS)
}
