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

/// Whether this machine has a CUDA device, as far as the driver's device nodes tell.
pub fn cuda_present() -> bool {
    cuda_device_nodes(Path::new("/dev"))
}

/// Whether `dev` holds a node the CUDA driver creates: `nvidiactl`, or `dxg` under WSL 2.
pub(crate) fn cuda_device_nodes(dev: &Path) -> bool {
    ["nvidiactl", "dxg"].iter().any(|node| dev.join(node).exists())
}
