//! `rlmflow push`: upload every cached result to the remote cache.

use std::process::ExitCode;

use anyhow::Context as _;
use rlmflow_stages::{Device, Registry};

use super::{Transfer, open_remote, ran_store};
use crate::config;
use crate::plan::{Freshness, assess};
use crate::preflight::planned;
use crate::ui::Ui;

pub(crate) fn exec(args: Transfer, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Transfer { pipeline, only, store, remote } = args;
    let p = super::at_look(config::load(&pipeline, registry)?, registry, &store)?;
    let store = ran_store(&p, &store, "nothing to push")?;
    let plan = planned(&p, Some(&store), Device::Cpu)?;
    let selected = plan.select(&only)?;
    let settings = remote.settings(&p)?.context("no remote cache: set `[pipeline] remote` or give --remote")?;
    let remote = open_remote(&config::RemoteSettings { push: true, ..settings })?;
    let (mut pushed, mut bytes) = (0, 0);
    let ui = Ui::new(false);
    for (i, state) in assess(&plan, registry, Some(&store))?.iter().enumerate().filter(|(i, _)| selected[*i]) {
        let Freshness::Cached(record) = state else { continue };
        let mut bar = ui.transfer(&plan.instances[i].label, "pushing");
        let sent = remote.push(&store, record, false, &mut |done, total| bar.moved(done, total))?;
        drop(bar);
        let sent = sent.map_err(|why| anyhow::anyhow!("remote cache {}: {why}", remote.url()))?;
        if let Some(why) = &sent.disagrees {
            println!("  WARNING  {}: {why}", plan.instances[i].label);
        }
        if let Some(why) = &sent.refused {
            println!("  warning  {}: {why}", plan.instances[i].label);
            continue;
        }
        let sent = sent.bytes;
        println!("  {}  {}  {:.1} MB", if sent > 0 { "pushed" } else { "held  " }, plan.instances[i].label, sent as f64 / 1e6);
        pushed += usize::from(sent > 0);
        bytes += sent;
    }
    println!("push: {pushed} results uploaded ({:.1} MB) to {}", bytes as f64 / 1e6, remote.url());
    Ok(ExitCode::SUCCESS)
}
