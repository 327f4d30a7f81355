//! What `run`, its dry run and `status` establish before anything runs, in one place: the plan
//! with the content of every tracked path, each instance's freshness, which instances are
//! selected and will run, whether each fits this machine, and the refusals that follow.

use std::path::Path;

use rlmflow_cache::Store;
use rlmflow_stages::{Device, Registry};

use crate::config::{ConfigError, Diagnostic, Executor, Pipeline};
use crate::dispatch::{Dispatch as _, Local};
use crate::footprint::{Fit, fits, refuse_oversized};
use crate::plan::{Freshness, Plan, assess, plan_on};
use crate::platform::Platform;

/// A pipeline checked against its store, before anything runs.
pub struct Preflight<'p> {
    pub plan: Plan<'p>,
    /// The store, where the pipeline has one yet (a preflight creates none).
    pub store: Option<Store>,
    pub states: Vec<Freshness>,
    /// The instances `--only` selects (all without it).
    pub selected: Vec<bool>,
    /// Selected and not reused from the store.
    pub runs: Vec<bool>,
    pub fits: Vec<Option<Fit>>,
}

impl<'p> Preflight<'p> {
    /// The pipeline's preflight for a run on `device` with the store at `root`, of the stages
    /// `only` names (all when empty).
    pub fn new(pipeline: &'p Pipeline, registry: &Registry, root: &Path, device: Device, only: &[String]) -> anyhow::Result<Preflight<'p>> {
        let store = Store::open_existing(root)?;
        let plan = planned(pipeline, store.as_ref(), device)?;
        let selected = plan.select(only)?;
        let states = assess(&plan, registry, store.as_ref())?;
        let runs = will_run(&states, &selected);
        let fits = fits(&plan, registry, device, &runs)?;
        Ok(Preflight { plan, store, states, selected, runs, fits })
    }

    /// Refuses, on the local executor, a run with an instance larger than this machine holds.
    pub fn refuse_oversized(&self) -> anyhow::Result<()> {
        if self.plan.pipeline.executor != Executor::Local {
            return Ok(());
        }
        refuse_oversized(&self.plan, &self.fits)
    }

    /// Refuses, on the local executor, a run on `device` in which a stage that must run needs a
    /// CUDA device this machine does not have.
    pub fn refuse_cuda_stages(&self, registry: &Registry, device: Device) -> anyhow::Result<()> {
        if self.plan.pipeline.executor != Executor::Local || Local::new(device).cuda_possible() {
            return Ok(());
        }
        refuse_cuda_stages(&self.plan, registry, &self.runs)
    }
}

/// The pipeline's plan for a run on `device`, with the content of every tracked path (recorded
/// in `store`, if any).
pub fn planned<'p>(pipeline: &'p Pipeline, store: Option<&Store>, device: Device) -> anyhow::Result<Plan<'p>> {
    let mut plan = plan_on(pipeline, Platform::detect(device));
    plan.fingerprint(store)?;
    Ok(plan)
}

/// Which instances are selected and will run (not reused from the store).
fn will_run(states: &[Freshness], selected: &[bool]) -> Vec<bool> {
    states.iter().zip(selected).map(|(state, &s)| s && !matches!(state, Freshness::Cached(_))).collect()
}

/// Refuses a local run, before anything starts, in which a stage that must run needs a CUDA
/// device this machine does not have: a config error with the stage's line and what is valid.
fn refuse_cuda_stages(plan: &Plan, registry: &Registry, runs: &[bool]) -> anyhow::Result<()> {
    let mut stages = std::collections::BTreeSet::new();
    for (i, inst) in plan.instances.iter().enumerate() {
        let op = registry.get(&inst.operator).expect("validated operator");
        if runs[i] && op.resources(&inst.settings).needs_cuda {
            stages.insert(inst.stage);
        }
    }
    if stages.is_empty() {
        return Ok(());
    }
    let diagnostics = stages
        .into_iter()
        .map(|s| {
            let stage = &plan.pipeline.stages[s];
            Diagnostic {
                line: stage.line,
                key: format!("stages.{}", stage.name),
                message: "needs a CUDA device (its `device` names one), and this machine has none: no CUDA driver device nodes, and the run did not say `--device cuda`".into(),
                help: Some("valid here: device = \"auto\" (CUDA where there is one) or \"cpu\"".into()),
            }
        })
        .collect();
    Err(ConfigError { file: plan.pipeline.file.clone(), diagnostics, overrides: plan.pipeline.overrides.clone() }.into())
}
