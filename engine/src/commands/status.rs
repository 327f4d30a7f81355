//! `rlmflow status`: where each stage stands, and what the remote cache holds.

use std::path::PathBuf;
use std::process::ExitCode;

use rlmflow_stages::{Device, Registry};

use super::{RemoteArg, SetArg, StoreArg, store_root, warn_unasked};
use crate::preflight::Preflight;
use crate::ui::print_status;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    #[arg(long)]
    json: bool,
    /// Only these stages (or instances, as a run prints them: `pretrain[alpha4]`) and what they
    /// need (repeatable).
    #[arg(long, value_name = "STAGE")]
    only: Vec<String>,
    #[command(flatten)]
    set: SetArg,
    #[command(flatten)]
    store: StoreArg,
    #[command(flatten)]
    remote: RemoteArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, json, only, set, store, remote } = args;
    let p = set.load_at_look(&pipeline, registry, &store)?;
    let pre = Preflight::new(&p, registry, &store_root(&p, &store), Device::Cpu, &only)?;
    let remote = remote.open(&p)?;
    print_status(&pre.plan, &pre.instances, remote.as_ref(), json);
    warn_unasked(remote.as_ref());
    Ok(ExitCode::SUCCESS)
}
