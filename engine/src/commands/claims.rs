//! `rlmflow claims`: each claim's verdict from what the store holds, computing nothing.

use std::path::PathBuf;
use std::process::ExitCode;

use rlmflow_stages::{Device, Registry};

use super::{SetArg, StoreArg, UsageError, ran_store};
use crate::event::{Event, Logged};

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    /// One JSON line: the seeds looked at and each verdict with its intervals.
    #[arg(long)]
    json: bool,
    /// The device whose keys the store's actions were computed under (cuda: a GPU run's).
    #[arg(long, default_value = "cpu")]
    device: Device,
    #[command(flatten)]
    set: SetArg,
    #[command(flatten)]
    store: StoreArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, json, device, set, store } = args;
    let mut p = set.load(&pipeline, registry)?;
    let Some(level) = p.claims.as_ref().map(|s| s.level) else {
        return Err(UsageError(format!("{} declares no [claims]", p.file.display())).into());
    };
    let store = ran_store(&p, &store, "no claim has a value")?;
    let look = crate::claims::reached(&mut p, registry, Some(&store), device)?;
    match json {
        true => {
            println!("{}", serde_json::to_string(&Logged { event: Event::Claims { seeds: look.seeds, verdicts: look.verdicts.clone() }, t: 0.0 })?)
        }
        false => print!("{}", crate::ui::claims(&look, level)),
    }
    Ok(if look.required_fails().is_empty() { ExitCode::SUCCESS } else { ExitCode::FAILURE })
}
