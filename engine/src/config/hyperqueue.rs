//! `[pipeline.hyperqueue]`: the cluster a run's actions go to.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use serde_json::Value;

use super::checker::Checker;

/// `[pipeline.hyperqueue]`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HyperQueueSettings {
    /// The directory of a running server (`hq server start --server-dir DIR`), relative to the
    /// pipeline file; none starts a local cluster for the run.
    pub server_dir: Option<PathBuf>,
    /// Workers in the cluster: started when local; on a server, how many the engine keeps busy.
    pub workers: usize,
    /// Cores per worker (0: this machine's): the most CPU threads one task asks for.
    pub cores: usize,
    /// Times a task that ended without an outcome is submitted again (0: the stage fails at once).
    pub retries: u32,
    /// Whether a stage that can use a GPU asks for one (the workers must have GPUs).
    pub gpus: bool,
    /// The memory of the workers' GPUs (one model), in GiB: a stage with a memory estimate then
    /// asks for the fraction of a GPU its estimate takes, so several share one; 0: a whole GPU
    /// each.
    pub gpu_memory_gib: f64,
    /// The store a task uses: `"shared"`, the run's own (on a filesystem every worker sees);
    /// `"temporary"`, a fresh one per task in the worker's temporary directory; or an absolute
    /// path, a store of each worker's own kept between tasks. Other than shared, inputs and
    /// results travel through the remote cache, which the run must push to.
    pub worker_store: String,
}

/// Where a HyperQueue task keeps its store.
#[derive(Clone, Debug, PartialEq)]
pub enum WorkerStore {
    Shared,
    Temporary,
    /// A directory on each worker.
    Own(PathBuf),
}

impl Default for HyperQueueSettings {
    fn default() -> Self {
        HyperQueueSettings { server_dir: None, workers: 1, cores: 0, retries: 1, gpus: false, gpu_memory_gib: 0.0, worker_store: "shared".into() }
    }
}

impl HyperQueueSettings {
    /// Checks ranges; returns the offending key and what is valid.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        if !(1..=4096).contains(&self.workers) {
            return Err(("workers", format!("must be in 1..=4096, not {}", self.workers)));
        }
        if self.cores > 4096 {
            return Err(("cores", format!("must be in 0..=4096 (0: this machine's cores), not {}", self.cores)));
        }
        if self.retries > 100 {
            return Err(("retries", format!("must be in 0..=100, not {}", self.retries)));
        }
        if !(0.0..=4096.0).contains(&self.gpu_memory_gib) {
            return Err(("gpu_memory_gib", format!("must be in 0..=4096 (0: a whole GPU per stage), not {}", self.gpu_memory_gib)));
        }
        self.worker_store()?;
        Ok(())
    }

    pub fn worker_store(&self) -> Result<WorkerStore, (&'static str, String)> {
        match self.worker_store.as_str() {
            "shared" => Ok(WorkerStore::Shared),
            "temporary" => Ok(WorkerStore::Temporary),
            path if path.starts_with('/') => Ok(WorkerStore::Own(PathBuf::from(path))),
            other => Err((
                "worker_store",
                format!(
                    "`{other}` is not valid; valid: \"shared\" (the run's store), \"temporary\" (one per task) or an absolute path on the workers"
                ),
            )),
        }
    }

    /// What a stage asks of `gpus/nvidia`: the share of a GPU its peak `estimate` takes within
    /// the headroom, rounded up to a hundredth, where the GPUs' memory is declared; else, or
    /// past one GPU, a whole one.
    pub fn gpu_share(&self, estimate: Option<u64>) -> f64 {
        let budget = self.gpu_memory_gib * (1u64 << 30) as f64 * rlmflow_stages::memory::HEADROOM;
        match estimate.filter(|_| budget > 0.0) {
            Some(bytes) => ((bytes as f64 / budget * 100.0).ceil() / 100.0).clamp(0.01, 1.0),
            None => 1.0,
        }
    }

    pub fn cores(&self) -> usize {
        if self.cores > 0 { self.cores } else { std::thread::available_parallelism().map_or(1, |n| n.get()) }
    }
}

impl Checker {
    /// `[pipeline.hyperqueue]`, its `server_dir` made absolute against the pipeline file.
    pub(super) fn hyperqueue(&mut self, file: &Path, table: Option<&Value>) -> HyperQueueSettings {
        let Some(table) = table else { return HyperQueueSettings::default() };
        let parsed = serde_path_to_error::deserialize::<_, HyperQueueSettings>(table.clone());
        let mut settings = match parsed {
            Ok(s) => s,
            Err(e) => {
                let inner = e.path().to_string();
                let key = if inner == "." { "pipeline.hyperqueue".to_owned() } else { format!("pipeline.hyperqueue.{inner}") };
                // The path names the failing key itself, an unknown one included.
                self.error(self.line(&key), &key, e.into_inner().to_string(), None);
                return HyperQueueSettings::default();
            }
        };
        if let Err((key, message)) = settings.check() {
            let key = format!("pipeline.hyperqueue.{key}");
            self.error(self.line(&key), &key, message, None);
        }
        if let Some(dir) = &settings.server_dir {
            let dir = file.parent().unwrap_or(Path::new(".")).join(dir);
            settings.server_dir = Some(std::path::absolute(&dir).unwrap_or(dir));
        }
        settings
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stage_asks_for_the_share_of_a_gpu_its_estimate_takes() {
        let on = |gib: f64| HyperQueueSettings { gpus: true, gpu_memory_gib: gib, ..Default::default() };
        const GIB: u64 = 1 << 30;
        // 80 GiB within the 90 % headroom is 72 GiB: 18 GiB a quarter, 20 GiB just over.
        assert_eq!(on(80.0).gpu_share(Some(18 * GIB)), 0.25);
        assert_eq!(on(80.0).gpu_share(Some(20 * GIB)), 0.28);
        assert_eq!(on(80.0).gpu_share(Some(1)), 0.01, "at least a hundredth");
        assert_eq!(on(80.0).gpu_share(Some(100 * GIB)), 1.0, "past one GPU: a whole one");
        assert_eq!(on(80.0).gpu_share(None), 1.0, "no estimate: a whole one");
        assert_eq!(on(0.0).gpu_share(Some(GIB)), 1.0, "memory not declared: a whole one");
        assert_eq!(on(-1.0).check().unwrap_err().0, "gpu_memory_gib");
    }
}
