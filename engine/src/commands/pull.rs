//! `rlmflow pull`: download from the remote cache what the store lacks.

use std::process::ExitCode;

use anyhow::{Context as _, bail};
use rlmflow_cache::{Digest, Store};
use rlmflow_stages::{Device, Registry};

use super::{Transfer, open_remote, store_root};
use crate::config;
use crate::preflight::planned;
use crate::ui::Ui;

pub(crate) fn exec(args: Transfer, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Transfer { pipeline, only, store, remote } = args;
    let p = super::at_look(config::load(&pipeline, registry)?, registry, &store)?;
    let store = Store::open(&store_root(&p, &store))?;
    let plan = planned(&p, Some(&store), Device::Cpu)?;
    let selected = plan.select(&only)?;
    let settings = remote.settings(&p)?.context("no remote cache: set `[pipeline] remote` or give --remote")?;
    let remote = open_remote(&settings)?;
    let (pulled, bytes) = pull(&plan, registry, &store, &remote, &selected)?;
    println!("pull: {pulled} results downloaded ({:.1} MB) from {}", bytes as f64 / 1e6, remote.url());
    Ok(ExitCode::SUCCESS)
}

/// Downloads the selected instances' results the local store lacks, providers first: a
/// consumer's key is known once its inputs' outputs are. Returns the results and bytes pulled.
fn pull(
    plan: &crate::plan::Plan,
    registry: &Registry,
    store: &Store,
    remote: &rlmflow_remote::Remote,
    selected: &[bool],
) -> anyhow::Result<(usize, u64)> {
    let mut outputs: Vec<Option<Digest>> = vec![None; plan.instances.len()];
    let (mut pulled, mut bytes) = (0, 0);
    let ui = Ui::new(false);
    for (i, inst) in plan.instances.iter().enumerate() {
        let Some(key) = plan.preimage(i, registry, &outputs)?.map(|p| p.key()) else { continue };
        if let Some(record) = store.fresh(&key)? {
            outputs[i] = Some(record.output);
            continue;
        }
        if !selected[i] {
            continue;
        }
        let produces = plan.pipeline.stages[inst.stage].kind.produces;
        let mut bar = ui.transfer(&inst.label, "pulling");
        let found = remote.pull(store, &key, &|dir| registry.catalog.check_artifact(produces, dir), &mut |done, total| bar.moved(done, total))?;
        drop(bar);
        match found {
            rlmflow_remote::Pulled::Hit { record, bytes: b, .. } => {
                println!("  pulled   {}  {:.1} MB", inst.label, b as f64 / 1e6);
                outputs[i] = Some(record.output);
                pulled += 1;
                bytes += b;
            }
            rlmflow_remote::Pulled::Miss => println!("  missing  {}", inst.label),
            rlmflow_remote::Pulled::Corrupt { why } => println!("  corrupt  {}  the remote's copy is not used: {why}", inst.label),
            rlmflow_remote::Pulled::Untrusted { why } => println!("  untrusted {}  the remote's record is not used: {why}", inst.label),
            rlmflow_remote::Pulled::Unreachable(why) => bail!("remote cache {}: {why}", remote.url()),
        }
    }
    Ok((pulled, bytes))
}
