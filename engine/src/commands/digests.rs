//! `rlmflow digests`: every instance's key and output digest, for another machine to compare.

use std::path::PathBuf;
use std::process::ExitCode;

use rlmflow_stages::{Device, Registry};

use super::{SetArg, StoreArg, ran_store};
use crate::plan::assess;
use crate::preflight::planned;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    #[command(flatten)]
    set: SetArg,
    #[command(flatten)]
    store: StoreArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, set, store } = args;
    let p = set.load_at_look(&pipeline, registry, &store)?;
    let store = ran_store(&p, &store, "nothing to list")?;
    let plan = planned(&p, Some(&store), Device::Cpu)?;
    let states = assess(&plan, registry, Some(&store))?;
    print!("{}", crate::digests::render(&p, &plan, &states, &rlmflow_stages::numerics::Cpu::detect())?);
    Ok(ExitCode::SUCCESS)
}
