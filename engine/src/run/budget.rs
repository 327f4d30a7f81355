//! The run's budget: the CPU threads shared by the stages running at once, and the GPU a local
//! run gives one stage at a time. It decides only whether a ready stage fits and with how many
//! threads; the scheduler decides which ready stage asks first.

use rlmflow_stages::Resources;

pub struct Budget {
    /// `--jobs`: the threads all running stages share.
    jobs: usize,
    /// The dispatcher's cap on one action's threads (a cluster worker's cores).
    max_threads: Option<usize>,
    /// Whether GPU stages run one at a time (locally; a cluster schedules GPUs itself).
    serialises_gpu: bool,
    /// Every granted stage holds at least one thread: none in use is none running.
    threads_in_use: usize,
    gpu_in_use: bool,
}

/// What a started stage was given, returned to the budget when it ends.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grant {
    pub threads: usize,
    pub gpu: bool,
}

impl Budget {
    pub fn new(jobs: usize, max_threads: Option<usize>, serialises_gpu: bool) -> Budget {
        Budget { jobs: jobs.max(1), max_threads, serialises_gpu, threads_in_use: 0, gpu_in_use: false }
    }

    /// What a stage wanting `wants` would be given now, or `None` when it must wait for a running
    /// one to end. With nothing running a stage always starts, its threads clamped to the budget.
    pub fn grant(&self, wants: &Resources) -> Option<Grant> {
        let mut threads = wants.threads.clamp(1, self.jobs).min(self.max_threads.unwrap_or(usize::MAX));
        // An operator whose bytes do not follow its thread count (no pinned kernels) starts with
        // the threads that are free: the data stage a chain waits on is not queued behind a
        // one-thread model stage for want of its second thread.
        if wants.kernels.is_none() {
            threads = threads.min(self.jobs.saturating_sub(self.threads_in_use)).max(1);
        }
        let fits = self.threads_in_use + threads <= self.jobs && !(wants.gpu && self.gpu_in_use && self.serialises_gpu);
        (fits || self.threads_in_use == 0).then_some(Grant { threads, gpu: wants.gpu })
    }

    pub fn take(&mut self, grant: Grant) {
        self.threads_in_use += grant.threads;
        self.gpu_in_use |= grant.gpu;
    }

    pub fn release(&mut self, grant: Grant) {
        self.threads_in_use -= grant.threads;
        self.gpu_in_use &= !grant.gpu;
    }
}

#[cfg(test)]
mod tests {
    use rlmflow_stages::{Device, Kernels, Numerics};

    use super::*;

    fn wants(threads: usize, gpu: bool, pinned: bool) -> Resources {
        let kernels = pinned.then_some(Kernels { numerics: Numerics::Portable, device: Device::Cpu });
        Resources { threads, gpu, kernels, ..Resources::default() }
    }

    #[test]
    fn stages_share_the_threads_and_a_pinned_one_waits_for_all_it_asks() {
        let mut budget = Budget::new(4, None, true);
        let model = budget.grant(&wants(3, false, true)).unwrap();
        assert_eq!(model, Grant { threads: 3, gpu: false });
        budget.take(model);
        // Its bytes follow its thread count: it waits rather than start with fewer.
        assert_eq!(budget.grant(&wants(2, false, true)), None);
        // A data stage starts with the one thread left.
        let data = budget.grant(&wants(2, false, false)).unwrap();
        assert_eq!(data.threads, 1);
        budget.take(data);
        assert_eq!(budget.grant(&wants(1, false, false)), None, "no thread is free");
        budget.release(model);
        budget.release(data);
        assert_eq!(budget.grant(&wants(2, false, true)).unwrap().threads, 2);
    }

    #[test]
    fn one_gpu_stage_at_a_time_where_the_dispatcher_serialises_them() {
        let mut local = Budget::new(8, None, true);
        let first = local.grant(&wants(1, true, true)).unwrap();
        local.take(first);
        assert_eq!(local.grant(&wants(1, true, true)), None);
        assert!(local.grant(&wants(1, false, true)).is_some(), "a CPU stage still fits");
        local.release(first);
        assert!(local.grant(&wants(1, true, true)).is_some());

        let mut cluster = Budget::new(8, None, false);
        cluster.take(cluster.grant(&wants(1, true, true)).unwrap());
        assert!(cluster.grant(&wants(1, true, true)).is_some(), "the cluster places GPUs itself");
    }

    #[test]
    fn threads_are_clamped_to_the_budget_and_the_dispatchers_cap() {
        let budget = Budget::new(2, None, true);
        assert_eq!(budget.grant(&wants(16, false, true)).unwrap().threads, 2, "more than --jobs is clamped");
        assert_eq!(budget.grant(&wants(0, false, true)).unwrap().threads, 1, "at least one");
        let capped = Budget::new(8, Some(3), true);
        assert_eq!(capped.grant(&wants(16, false, true)).unwrap().threads, 3);
    }
}
