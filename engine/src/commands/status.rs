//! `rlmflow status`: where each stage stands, and what the remote cache holds.

use std::path::PathBuf;
use std::process::ExitCode;

use rlmflow_stages::{Device, Registry};

use super::{RemoteArg, SetArg, StoreArg, open_remote, store_root};
use crate::config;
use crate::preflight::Preflight;
use crate::ui::print_status;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    set: SetArg,
    #[command(flatten)]
    store: StoreArg,
    #[command(flatten)]
    remote: RemoteArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, json, set, store, remote } = args;
    let p = config::load_with(&pipeline, &set.set, &set.set_new, registry)?;
    let pre = Preflight::new(&p, registry, &store_root(&p, &store), Device::Cpu, &[])?;
    let remote = remote.settings(&p)?.map(|r| open_remote(&r)).transpose()?;
    print_status(&pre.plan, &pre.states, &pre.selected, &pre.fits, remote.as_ref(), json);
    if let Some(why) = remote.as_ref().and_then(|r| r.down()) {
        eprintln!("warning: remote cache {} not asked: {why}", remote.as_ref().map_or("", |r| r.url()));
    }
    Ok(ExitCode::SUCCESS)
}
