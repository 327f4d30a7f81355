//! What `run`, its dry run and `status` establish before anything runs, in one place: the plan
//! with the content of every tracked path, each instance's freshness, which instances are
//! selected and will run, whether each fits this machine, and the refusals that follow.

use std::path::Path;

use rlmflow_cache::Store;
use rlmflow_stages::{Device, Registry};

use crate::config::{ConfigError, Diagnostic, Executor, Pipeline};
use crate::dispatch::{Dispatch as _, Local};
use crate::gpus::Gpu;
use crate::footprint::{Fit, fits, refuse_oversized};
use crate::plan::{Freshness, Plan, assess, plan_on};
use crate::platform::Platform;

/// A pipeline checked against its store, before anything runs.
pub struct Preflight<'p> {
    pub plan: Plan<'p>,
    /// The store, where the pipeline has one yet (a preflight creates none).
    pub store: Option<Store>,
    /// What it found of each of the plan's instances, in plan order.
    pub instances: Vec<Checked>,
    /// The GPUs a local run places stages on (none for a cluster, which places them itself).
    pub gpus: Vec<Gpu>,
}

/// What the preflight found of one instance.
pub struct Checked {
    pub state: Freshness,
    /// `--only` selects it (every instance is selected without it).
    pub selected: bool,
    /// Its memory estimate against its device, where it will run and has one.
    pub fit: Option<Fit>,
}

impl Checked {
    /// Selected and not reused from the store.
    pub fn runs(&self) -> bool {
        self.selected && !matches!(self.state, Freshness::Cached(_))
    }
}

impl<'p> Preflight<'p> {
    /// The pipeline's preflight for a run on `device` with the store at `root`, of the stages
    /// `only` names (all when empty).
    pub fn new(pipeline: &'p Pipeline, registry: &Registry, root: &Path, device: Device, only: &[String]) -> anyhow::Result<Preflight<'p>> {
        let store = Store::open_existing(root)?;
        let gpus = match pipeline.executor {
            Executor::Local => Local::new(device, pipeline.gpus.as_deref())?.gpus().unwrap_or_default(),
            Executor::HyperQueue => Vec::new(),
        };
        let plan = planned(pipeline, store.as_ref(), device)?;
        let selected = plan.select(only)?;
        let states = assess(&plan, registry, store.as_ref())?;
        let mut instances: Vec<Checked> = states.into_iter().zip(selected).map(|(state, selected)| Checked { state, selected, fit: None }).collect();
        let runs: Vec<bool> = instances.iter().map(Checked::runs).collect();
        for (checked, fit) in instances.iter_mut().zip(fits(&plan, registry, device, &gpus, &runs)?) {
            checked.fit = fit;
        }
        Ok(Preflight { plan, store, instances, gpus })
    }

    /// Refuses, on the local executor, a run with an instance larger than this machine holds.
    pub fn refuse_oversized(&self) -> anyhow::Result<()> {
        if self.plan.pipeline.executor != Executor::Local {
            return Ok(());
        }
        let fits: Vec<Option<&Fit>> = self.instances.iter().map(|c| c.fit.as_ref()).collect();
        refuse_oversized(&self.plan, &fits)
    }

    /// Refuses, on the local executor, a run in which a stage that must run needs a CUDA device
    /// and the run has no GPU to place it on.
    pub fn refuse_cuda_stages(&self, registry: &Registry) -> anyhow::Result<()> {
        if self.plan.pipeline.executor != Executor::Local || !self.gpus.is_empty() {
            return Ok(());
        }
        refuse_cuda_stages(&self.plan, registry, &self.instances)
    }
}

/// The pipeline's plan for a run on `device`, with the content of every tracked path (recorded
/// in `store`, if any).
pub fn planned<'p>(pipeline: &'p Pipeline, store: Option<&Store>, device: Device) -> anyhow::Result<Plan<'p>> {
    let mut plan = plan_on(pipeline, Platform::detect(device));
    plan.fingerprint(store)?;
    Ok(plan)
}

/// Refuses a local run, before anything starts, in which a stage that must run needs a CUDA
/// device this machine does not have: a config error with the stage's line and what is valid.
fn refuse_cuda_stages(plan: &Plan, registry: &Registry, instances: &[Checked]) -> anyhow::Result<()> {
    let mut stages = std::collections::BTreeSet::new();
    for (inst, checked) in plan.instances.iter().zip(instances) {
        let op = registry.get(&inst.operator).expect("validated operator");
        if checked.runs() && op.resources(&inst.settings).needs_cuda {
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
