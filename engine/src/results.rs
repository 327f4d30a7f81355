//! Where each stage instance's current output is linked under `[pipeline] results`: a path
//! made of its stage and variants, so `results/report/report.html` is always the latest report
//! and `results/pretrain/alpha4/` the latest encoder of variant `alpha4`. The links themselves
//! (atomic replacement, what `gc` does to them) are the store's (`rlmflow_cache::Links`).

use std::path::PathBuf;

use rlmflow_cache::file_safe;

use crate::plan::{Plan, variant_names};

/// The link of instance `i`, relative to the results directory: `stage`, then one component per
/// variant named as its label names it (`pretrain/alpha4`, `clipcap/captions=llm/pretrain=alpha4`,
/// `pretrain/seed=2`). A shard has none (its stage's merged output does). Names are made
/// file-safe as the store's are.
pub fn entry(plan: &Plan, i: usize) -> Option<PathBuf> {
    let inst = &plan.instances[i];
    if inst.shard.is_some() {
        return None;
    }
    let mut path = PathBuf::from(file_safe(&plan.pipeline.stages[inst.stage].name));
    for (dimension, variant) in variant_names(&inst.assignment) {
        path.push(match dimension {
            Some(d) => format!("{}={}", file_safe(d), file_safe(variant)),
            None => file_safe(variant),
        });
    }
    Some(path)
}
