//! The numeric platform of the machine a run plans on: the class that a platform-dependent
//! action's key carries (`rlmflow_stages::numerics`), and the check an action makes before it
//! computes that its machine is of that class.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Mutex;

use rlmflow_stages::numerics::{Cpu, Gpu, Target, class};
use rlmflow_stages::{Device, Kernels};

/// This machine, as far as kernel choice goes, for one run's `--device`.
#[derive(Debug)]
pub struct Platform {
    run_device: Device,
    cpu: Cpu,
    cuda: bool,
    /// Each CUDA device asked about, read once.
    gpus: Mutex<BTreeMap<usize, Option<Gpu>>>,
}

impl Platform {
    pub fn detect(run_device: Device) -> Platform {
        Platform { run_device, cpu: Cpu::detect(), cuda: cuda_present(), gpus: Mutex::new(BTreeMap::new()) }
    }

    /// The class of machines that compute the same bytes as this one for an action with
    /// `kernels`.
    pub fn class(&self, kernels: Kernels) -> String {
        let target = Target::of(kernels.device, self.run_device, self.cuda);
        let gpu = match target {
            Target::Cuda(n) => self.gpus.lock().expect("gpu table").entry(n).or_insert_with(|| Gpu::detect(n)).clone(),
            Target::Cpu => None,
        };
        class(kernels.numerics, &self.cpu, target, gpu.as_ref())
    }

    pub fn cpu(&self) -> &Cpu {
        &self.cpu
    }
}

/// Whether this process can see a CUDA device, as far as the driver's device nodes and
/// `CUDA_VISIBLE_DEVICES` tell: a GPU the variable hides is one libtorch in the worker will not
/// see, so a stage set to `auto` must be keyed and run on the CPU there.
pub fn cuda_present() -> bool {
    cuda_device_nodes(Path::new("/dev")) && cuda_visible(std::env::var("CUDA_VISIBLE_DEVICES").ok().as_deref())
}

/// Whether `CUDA_VISIBLE_DEVICES` (`None`: unset) leaves a device visible. As CUDA reads it, the
/// list ends at its first entry that is neither a device index nor a `GPU-`/`MIG-` UUID, so an
/// empty value, `-1` or `none` hides them all.
pub(crate) fn cuda_visible(variable: Option<&str>) -> bool {
    let Some(list) = variable else { return true };
    list.split(',').next().map(str::trim).is_some_and(|first| {
        first.parse::<u32>().is_ok() || ["GPU-", "MIG-"].iter().any(|prefix| first.len() > prefix.len() && first.starts_with(prefix))
    })
}

/// Whether `dev` holds a node the CUDA driver creates: `nvidiactl`, or `dxg` under WSL 2.
pub(crate) fn cuda_device_nodes(dev: &Path) -> bool {
    ["nvidiactl", "dxg"].iter().any(|node| dev.join(node).exists())
}
