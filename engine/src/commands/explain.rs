//! `rlmflow explain`: a stage's preimage, and what changed since its last run.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context as _;
use rlmflow_cache::{Digest, Store};
use rlmflow_stages::{Device, Registry};

use super::{SetArg, StoreArg, store_root};
use crate::plan::{Freshness, assess};
use crate::preflight::planned;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    /// A stage (every instance of it), one instance as a run prints it (`pretrain[alpha4]`), or a
    /// claim.
    stage: String,
    #[command(flatten)]
    set: SetArg,
    #[command(flatten)]
    store: StoreArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, stage, set, store } = args;
    explain(registry, &pipeline, &set, &stage, &store)
}

fn explain(registry: &Registry, file: &Path, set: &SetArg, stage: &str, arg: &StoreArg) -> anyhow::Result<ExitCode> {
    let p = set.load_at_look(file, registry, arg)?;
    let store = Store::open_existing(&store_root(&p, arg))?;
    let is_claim = p.claims.as_ref().is_some_and(|s| s.claims.iter().any(|c| c.name == stage));
    if p.stage(stage).is_none() && is_claim {
        let store = store.with_context(|| format!("{} has not run yet; no claim has a verdict", p.file.display()))?;
        print!("{}", crate::ui::claim_flip(&crate::claims::flip(&p, registry, &store, stage)?, stage));
        return Ok(ExitCode::SUCCESS);
    }
    let plan = planned(&p, store.as_ref(), Device::Cpu)?;
    let states = assess(&plan, registry, store.as_ref())?;
    let last = match &store {
        Some(s) => s.last_keys(&p.name)?,
        None => Default::default(),
    };
    for i in plan.instances_named(stage)? {
        let inst = &plan.instances[i];
        let stage = &p.stages[inst.stage].name;
        let last = last.get(&plan.id(i), &inst.label);
        let mut changes = Vec::new();
        if let (Freshness::Pending(_), Some(s), Some(old)) = (&states[i], &store, last)
            && let Some(before) = crate::reason::previous_preimage(s, &old)?
        {
            let unknown = Digest([0; 32]);
            let outputs: Vec<Option<Digest>> = states.iter().map(|st| Some(if let Freshness::Cached(r) = st { r.output } else { unknown })).collect();
            let now = plan.preimage(i, registry, &outputs)?.context("a cached instance's inputs are known")?;
            changes = now.diff(&before).into_iter().filter(|c| !matches!(c, rlmflow_cache::Change::InputChanged { .. })).collect();
        }
        print!("{}", crate::ui::explained(&crate::ui::Explained { label: &inst.label, stage, state: &states[i], last, changes }));
    }
    Ok(ExitCode::SUCCESS)
}
