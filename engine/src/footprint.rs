//! Will each stage fit its device? Operators that train estimate an action's peak memory from
//! their settings and their inputs' outlines ([`rlmflow_stages::Footprint`]); here each
//! instance's estimate is set against the memory of the device it will run on: a CUDA device's
//! as `nvidia-smi` reports it, else this machine's RAM. `status` and `run --dry-run` show both;
//! a run refuses, before anything starts, a stage that will run and whose estimate exceeds
//! [`HEADROOM`] of its device, naming the settings that lower it (local runs: a cluster's
//! machines are not this one). Where a device's memory
//! cannot be read (no `nvidia-smi`), nothing is refused.

use std::collections::BTreeMap;

use rlmflow_stages::memory::HEADROOM;
use rlmflow_stages::numerics::Target;
use rlmflow_stages::{Device, Footprint, InputOutlines, Outline, Registry};

use crate::config::{ConfigError, Diagnostic};
use crate::gpus::Gpu;
use crate::plan::Plan;

/// An instance's estimate and where it will run.
pub struct Fit {
    pub footprint: Footprint,
    pub target: Target,
    /// The target's memory, where it can be read.
    pub capacity: Option<u64>,
}

impl Fit {
    pub fn exceeds(&self) -> bool {
        self.capacity.is_some_and(|c| self.footprint.peak_bytes as f64 > c as f64 * HEADROOM)
    }

    /// `125.1 M parameters, peak ~ 23.4 GiB (CUDA device: 79.2 GiB)`.
    pub fn describe(&self) -> String {
        let capacity = self.capacity.map_or("size unknown".to_owned(), gib);
        let memory = match self.target {
            Target::Cpu => "RAM".to_owned(),
            Target::Cuda(n) => format!("CUDA device {n}"),
        };
        format!("{:.1} M parameters, peak ~ {} ({memory}: {capacity})", self.footprint.parameters as f64 / 1e6, gib(self.footprint.peak_bytes))
    }
}

fn gib(bytes: u64) -> String {
    format!("{:.1} GiB", bytes as f64 / (1u64 << 30) as f64)
}

/// The fit of each instance that will run (`runs[i]`), for the operators that estimate one;
/// `device` is the run's `--device`, `gpus` those a local run places stages on (their memory
/// as the inventory has it). A device's memory is read only when an estimate needs it.
pub fn fits(plan: &Plan, registry: &Registry, device: Device, gpus: &[Gpu], runs: &[bool]) -> anyhow::Result<Vec<Option<Fit>>> {
    // Nothing to fit, so no outlines to derive (a run that reuses everything).
    if !runs.contains(&true) {
        return Ok(runs.iter().map(|_| None).collect());
    }
    let mut outlines: Vec<Outline> = Vec::with_capacity(plan.instances.len());
    let mut capacity = Capacities { read: BTreeMap::new(), gpus };
    let mut fits = Vec::with_capacity(plan.instances.len());
    for inst in &plan.instances {
        let op = registry.get(&inst.operator).expect("validated operator");
        let inputs: InputOutlines = inst.inputs.iter().map(|i| (i.slot, i.providers.iter().map(|&p| outlines[p]).collect())).collect();
        outlines.push(op.outline(&inst.settings, &inputs).unwrap_or_default());
        if !runs[fits.len()] {
            fits.push(None);
            continue;
        }
        let resources = op.resources(&inst.settings);
        let cuda = resources.needs_cuda || (resources.gpu && (matches!(device, Device::Cuda(_)) || !gpus.is_empty() || crate::platform::cuda_present()));
        // The device the stage names, else the run's, else the first.
        let index = match (resources.kernels.map(|k| k.device), device) {
            (Some(Device::Cuda(n)), _) | (_, Device::Cuda(n)) => n,
            _ => 0,
        };
        let target = if cuda { Target::Cuda(index) } else { Target::Cpu };
        fits.push(op.footprint(&inst.settings, &inputs, target).map(|footprint| Fit { footprint, target, capacity: capacity.of(target) }));
    }
    Ok(fits)
}

/// Device memories, read once each: a GPU's from the inventory, where it holds one (its GPUs
/// are of one model: the first stands for any), else from the driver.
struct Capacities<'g> {
    read: BTreeMap<Target, Option<u64>>,
    gpus: &'g [Gpu],
}

impl Capacities<'_> {
    fn of(&mut self, target: Target) -> Option<u64> {
        let gpus = self.gpus;
        *self.read.entry(target).or_insert_with(|| match target {
            Target::Cpu => ram(),
            Target::Cuda(n) => gpus.iter().find(|g| g.index == n).or(gpus.first()).and_then(|g| g.memory).or_else(|| cuda_memory(n)),
        })
    }
}

/// `MemTotal` of `/proc/meminfo`.
fn ram() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemTotal:"))?;
    Some(line.split_whitespace().nth(1)?.parse::<u64>().ok()? * 1024)
}

/// CUDA device `index`'s memory, from `nvidia-smi`.
fn cuda_memory(index: usize) -> Option<u64> {
    let mib: u64 = rlmflow_stages::numerics::query_gpu(index, "memory.total")?.parse().ok()?;
    Some(mib << 20)
}

/// Refuses, before anything starts, the instances that will run and whose estimate exceeds their device's memory: a config error per stage, with the settings to change.
pub fn refuse_oversized(plan: &Plan, fits: &[Option<&Fit>]) -> anyhow::Result<()> {
    let mut diagnostics: Vec<Diagnostic> = Vec::new();
    for (i, fit) in fits.iter().enumerate() {
        let Some(fit) = fit.filter(|f| f.exceeds()) else { continue };
        let inst = &plan.instances[i];
        let stage = &plan.pipeline.stages[inst.stage];
        let key = format!("stages.{}", stage.name);
        if diagnostics.iter().any(|d| d.key == key) {
            continue;
        }
        diagnostics.push(Diagnostic {
            line: stage.line,
            key,
            message: format!("`{}` would not fit: {}", inst.label, fit.describe()),
            help: Some(format!("lower it with {}", fit.footprint.lower_with)),
        });
    }
    if diagnostics.is_empty() {
        return Ok(());
    }
    Err(ConfigError { file: plan.pipeline.file.clone(), diagnostics, overrides: plan.pipeline.overrides.clone() }.into())
}
