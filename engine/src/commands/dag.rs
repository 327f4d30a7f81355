//! `rlmflow dag`: the plan drawn as Mermaid or DOT, each instance in its state (`crate::dag`).

use std::path::PathBuf;
use std::process::ExitCode;

use rlmflow_stages::{Device, Registry};

use super::{RemoteArg, SetArg, StoreArg, store_root, warn_unasked};
use crate::preflight::Preflight;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    #[arg(long, value_enum, default_value = "mermaid")]
    format: crate::dag::Format,
    #[command(flatten)]
    set: SetArg,
    #[command(flatten)]
    store: StoreArg,
    #[command(flatten)]
    remote: RemoteArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, format, set, store, remote } = args;
    let p = set.load_at_look(&pipeline, registry, &store)?;
    let pre = Preflight::new(&p, registry, &store_root(&p, &store), Device::Cpu, &[])?;
    let remote = remote.open(&p)?;
    print!("{}", crate::dag::draw(&pre.plan, &pre.instances, remote.as_ref(), format));
    warn_unasked(remote.as_ref());
    Ok(ExitCode::SUCCESS)
}
