//! `rlmflow show`: where a stage's outputs and record are, and where the record came from.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use rlmflow_cache::{Store, canonical_json};
use rlmflow_stages::{Device, Registry};

use super::{StoreArg, instances_of, store_root};
use crate::config;
use crate::plan::{Freshness, assess};
use crate::preflight::planned;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    stage: String,
    #[command(flatten)]
    store: StoreArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, stage, store } = args;
    show(registry, &pipeline, &stage, &store)
}

fn show(registry: &Registry, file: &Path, stage: &str, arg: &StoreArg) -> anyhow::Result<ExitCode> {
    let p = super::at_look(config::load(file, registry)?, registry, arg)?;
    let store = Store::open_existing(&store_root(&p, arg))?;
    let plan = planned(&p, store.as_ref(), Device::Cpu)?;
    let states = assess(&plan, registry, store.as_ref())?;
    for i in instances_of(&plan, stage)? {
        let label = &plan.instances[i].label;
        match (&states[i], &store) {
            (Freshness::Cached(r), Some(s)) => {
                println!("{label}: cached");
                println!("  output:  {}", s.object_dir(&r.output).display());
                println!("  files:   {} ({:.1} MB)", r.files, r.bytes as f64 / 1e6);
                println!("  key:     {}", r.key);
                println!("  ran:     {} for {:.1}s", r.started, r.duration_s);
                match &r.pulled {
                    None => println!("  origin:  computed here"),
                    Some(rlmflow_cache::PulledFrom { remote, signed_by: Some(key) }) => {
                        println!("  origin:  pulled from {remote}, signed by {key}")
                    }
                    Some(rlmflow_cache::PulledFrom { remote, signed_by: None }) => {
                        println!("  origin:  pulled from {remote} UNVERIFIED (no trusted keys): its summary and metrics are the remote's word")
                    }
                }
                let unverified = if r.unverified_origin().is_some() { " (unverified)" } else { "" };
                if !r.summary.is_empty() {
                    println!("  summary{unverified}: {}", r.summary);
                }
                if !r.metrics.is_null() {
                    println!("  metrics{unverified}: {}", canonical_json(&r.metrics));
                }
                // A record from before its operator kept one, or a damaged one, shows none.
                if let Some(platform) = r.platform.clone().and_then(|p| serde_json::from_value::<rlmflow_stages::numerics::PlatformRecord>(p).ok()) {
                    platform.to_string().lines().for_each(|line| println!("  {line}"));
                }
            }
            (Freshness::Stale { reasons, .. }, _) => println!("{label}: not computed yet ({})", crate::ui::words(reasons)),
            (Freshness::Pending(waiting), _) => println!("{label}: not computed yet ({waiting})"),
            (Freshness::Cached(_), None) => unreachable!("cached without a store"),
        }
    }
    Ok(ExitCode::SUCCESS)
}
