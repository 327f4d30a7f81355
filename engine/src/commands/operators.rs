//! `rlmflow operators`: the stage kinds and operators this binary has, with their defaults.

use std::process::ExitCode;

use rlmflow_cache::canonical_json;
use rlmflow_stages::{ItemCount, Registry};

#[derive(clap::Args)]
pub(crate) struct Args {
    /// One JSON object per line, per operator: id (as keys name it: the name, or `NAME@KIND`
    /// for an operator serving several kinds), name, kind, version, summary, inputs, produces,
    /// merge (the operator joining its shards, or null), defaults, non_result, tracked, claims
    /// (the setting the engine fills from `[claims]`, or null).
    #[arg(long)]
    json: bool,
}

pub(crate) fn exec(args: Args, registry: &Registry) -> anyhow::Result<ExitCode> {
    let Args { json } = args;
    if json {
        for kind in &registry.catalog.kinds {
            for op in registry.operators_of(kind.name) {
                let spec = op.spec();
                let defaults = op.defaults();
                let reads = spec.inputs.map_or_else(|| kind.inputs.iter().map(|s| s.name).collect(), <[&str]>::to_vec);
                let inputs: serde_json::Map<String, serde_json::Value> = kind
                    .inputs
                    .iter()
                    .filter(|slot| reads.contains(&slot.name))
                    .map(|slot| (slot.name.to_owned(), serde_json::json!(slot.artifact.to_string())))
                    .collect();
                let id = registry.find(kind.name, spec.name).map(|(id, _)| id);
                let line = serde_json::json!({
                    "id": id, "name": spec.name, "kind": spec.kind, "version": spec.version, "summary": spec.summary,
                    "inputs": inputs, "produces": kind.produces.to_string(), "merge": op.merge(),
                    "defaults": defaults, "non_result": op.non_result_keys(), "tracked": op.tracked_keys(),
                    "claims": op.claims_key()
                });
                println!("{line}");
            }
        }
        Ok(ExitCode::SUCCESS)
    } else {
        for kind in &registry.catalog.kinds {
            let inputs: Vec<String> = kind.inputs.iter().map(|s| format!("{}: {}", s.name, s.artifact)).collect();
            println!("{} ({}) -> {}", kind.name, inputs.join(", "), kind.produces);
            for op in registry.operators_of(kind.name) {
                let spec = op.spec();
                let defaults = op.defaults();
                println!("  {} v{}: {}\n    defaults: {}", spec.name, spec.version, spec.summary, canonical_json(&defaults));
                if !op.tracked_keys().is_empty() {
                    println!("    paths tracked by content (their files' digests enter the key, not the path): {}", op.tracked_keys().join(", "));
                }
                if let Some(key) = op.claims_key() {
                    println!("    `{key}` is filled from the pipeline's [claims] (a stage does not set it)");
                }
                if !op.non_result_keys().is_empty() {
                    println!("    not part of the result (left out of the key): {}", op.non_result_keys().join(", "));
                }
                match (op.merge(), op.settings(defaults.clone()).ok().and_then(|s| op.items(&s))) {
                    (Some(merge), Some((ItemCount::Known(_), unit))) => {
                        println!("    shardable: `shards` or `shard_size` split its {unit} into parts, merged by `{merge}`")
                    }
                    (Some(merge), Some((ItemCount::OfInput(slot), unit))) => {
                        println!("    shardable: `shards = N` splits the {unit} of its `{slot}` input into N parts, merged by `{merge}`")
                    }
                    _ => {}
                }
            }
        }
        Ok(ExitCode::SUCCESS)
    }
}
