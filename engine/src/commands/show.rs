//! `rlmflow show`: where a stage's outputs and record are, and where the record came from.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use rlmflow_cache::Store;
use rlmflow_stages::{Device, Registry};
use serde_json::{Value, json};

use super::{StoreArg, store_root};
use crate::config;
use crate::plan::{Freshness, Plan, assess};
use crate::preflight::planned;

#[derive(clap::Args)]
pub(crate) struct Args {
    pipeline: PathBuf,
    /// A stage (every instance of it) or one instance as a run prints it (`pretrain[alpha4]`).
    stage: String,
    /// One JSON document: every instance's state, output directory, artifact type and record.
    #[arg(long)]
    json: bool,
    #[command(flatten)]
    store: StoreArg,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { pipeline, stage, json, store } = args;
    show(registry, &pipeline, &stage, json, &store)
}

fn show(registry: &Registry, file: &Path, stage: &str, json: bool, arg: &StoreArg) -> anyhow::Result<ExitCode> {
    let p = super::at_look(config::load(file, registry)?, registry, arg)?;
    let store = Store::open_existing(&store_root(&p, arg))?;
    let plan = planned(&p, store.as_ref(), Device::Cpu)?;
    let states = assess(&plan, registry, store.as_ref())?;
    let shown = plan.instances_named(stage)?;
    if json {
        let instances: Vec<Value> = shown.iter().map(|&i| instance_json(&plan, i, &states[i], store.as_ref())).collect();
        println!("{}", json!({ "pipeline": p.name, "instances": instances }));
        return Ok(ExitCode::SUCCESS);
    }
    for i in shown {
        print!("{}", crate::ui::shown(&plan.instances[i].label, &states[i], store.as_ref()));
    }
    Ok(ExitCode::SUCCESS)
}

/// One instance as data: what a reader (the Python package) needs to open its artifact.
fn instance_json(plan: &Plan, i: usize, state: &Freshness, store: Option<&Store>) -> Value {
    let inst = &plan.instances[i];
    let stage = &plan.pipeline.stages[inst.stage];
    let mut out = json!({
        "label": inst.label,
        "stage": stage.name,
        "kind": stage.kind.name,
        "type": stage.kind.produces,
        "variants": inst.assignment,
        "seed": inst.seed,
    });
    let fields = match (state, store) {
        (Freshness::Cached(r), Some(s)) => json!({
            "state": "cached",
            "output": s.object_dir(&r.output),
            "record": serde_json::to_value(&**r).expect("a record is JSON"),
        }),
        (Freshness::Stale { reasons, .. }, _) => json!({ "state": "stale", "why": crate::ui::words(reasons) }),
        (Freshness::Pending(waiting), _) => json!({ "state": "pending", "why": waiting.to_string() }),
        (Freshness::Cached(_), None) => unreachable!("cached without a store"),
    };
    if let (Value::Object(out), Value::Object(fields)) = (&mut out, fields) {
        out.extend(fields);
    }
    out
}
