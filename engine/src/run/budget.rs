//! The run's budget: the CPU threads shared by the stages running at once, and the GPUs of a
//! local run, each given to stages side by side while their memory estimates fit in it. It
//! decides only whether a ready stage fits, with how many threads and on which GPU; the
//! scheduler decides which ready stage asks first.

use rlmflow_stages::Resources;
use rlmflow_stages::memory::HEADROOM;

use crate::gpus::Gpu;

pub struct Budget {
    /// `--jobs`: the threads all running stages share.
    jobs: usize,
    /// The dispatcher's cap on one action's threads (a cluster worker's cores).
    max_threads: Option<usize>,
    /// The GPUs this budget places stages on; `None` where the dispatcher places them (a
    /// cluster), empty where there are none (GPU stages then run on the CPU).
    gpus: Option<Vec<Slot>>,
    /// Every granted stage holds at least one thread: none in use is none running.
    threads_in_use: usize,
}

/// One GPU and what its running stages hold of it.
struct Slot {
    gpu: Gpu,
    stages: usize,
    /// The memory estimates of its stages.
    held: u64,
    /// A stage without an estimate (or on a GPU of unknown memory) has it to itself.
    whole: bool,
}

/// What a started stage was given, returned to the budget when it ends.
#[derive(Clone, Debug, PartialEq)]
pub struct Grant {
    pub threads: usize,
    /// Whether it asked for a GPU.
    pub gpu: bool,
    /// The GPU the budget gave it, where it places them.
    pub placed: Option<Placed>,
}

/// A stage's place on a GPU: which (its position in the inventory) and the memory it holds.
#[derive(Clone, Debug, PartialEq)]
pub struct Placed {
    pub gpu: Gpu,
    slot: usize,
    /// Its estimate; `None`: the GPU is its alone.
    bytes: Option<u64>,
}

impl Placed {
    /// Whether it holds its GPU by its estimate, so others may run beside it.
    pub fn shares(&self) -> bool {
        self.bytes.is_some()
    }
}

impl Budget {
    pub fn new(jobs: usize, max_threads: Option<usize>, gpus: Option<Vec<Gpu>>) -> Budget {
        let gpus = gpus.map(|list| list.into_iter().map(|gpu| Slot { gpu, stages: 0, held: 0, whole: false }).collect());
        Budget { jobs: jobs.max(1), max_threads, gpus, threads_in_use: 0 }
    }

    /// What a stage wanting `wants`, with a peak memory `estimate`, would be given now, or
    /// `None` when it must wait for a running one to end. With nothing running a stage always
    /// starts, its threads clamped to the budget.
    pub fn grant(&self, wants: &Resources, estimate: Option<u64>) -> Option<Grant> {
        let mut threads = wants.threads.clamp(1, self.jobs).min(self.max_threads.unwrap_or(usize::MAX));
        // An operator whose bytes do not follow its thread count (no pinned kernels) starts with
        // the threads that are free: the data stage a chain waits on is not queued behind a
        // one-thread model stage for want of its second thread.
        if wants.kernels.is_none() {
            threads = threads.min(self.jobs.saturating_sub(self.threads_in_use)).max(1);
        }
        let placed = match &self.gpus {
            Some(slots) if wants.gpu && !slots.is_empty() => Some(place(slots, estimate)?),
            _ => None,
        };
        let fits = self.threads_in_use + threads <= self.jobs;
        (fits || self.threads_in_use == 0).then_some(Grant { threads, gpu: wants.gpu, placed })
    }

    pub fn take(&mut self, grant: &Grant) {
        self.threads_in_use += grant.threads;
        if let (Some(slots), Some(p)) = (&mut self.gpus, &grant.placed) {
            let slot = &mut slots[p.slot];
            slot.stages += 1;
            match p.bytes {
                Some(bytes) => slot.held += bytes,
                None => slot.whole = true,
            }
        }
    }

    pub fn release(&mut self, grant: &Grant) {
        self.threads_in_use -= grant.threads;
        if let (Some(slots), Some(p)) = (&mut self.gpus, &grant.placed) {
            let slot = &mut slots[p.slot];
            slot.stages -= 1;
            match p.bytes {
                Some(bytes) => slot.held -= bytes,
                None => slot.whole = false,
            }
        }
    }
}

/// Where a stage with `estimate` goes: an idle GPU first, so stages run side by side on
/// different GPUs; else the GPU with the most memory left where its estimate fits beside the
/// others' within the headroom. Without an estimate, or where a GPU's memory is unknown, only
/// an idle GPU, held whole.
fn place(slots: &[Slot], estimate: Option<u64>) -> Option<Placed> {
    let budget = |slot: &Slot| slot.gpu.memory.map(|m| (m as f64 * HEADROOM) as u64);
    let shares = |slot: &Slot| estimate.filter(|_| budget(slot).is_some());
    if let Some((n, slot)) = slots.iter().enumerate().find(|(_, s)| s.stages == 0) {
        return Some(Placed { gpu: slot.gpu.clone(), slot: n, bytes: shares(slot) });
    }
    let estimate = estimate?;
    let room = |slot: &Slot| budget(slot).filter(|_| !slot.whole).and_then(|b| b.checked_sub(slot.held)).filter(|&free| free >= estimate);
    let (n, slot) = slots.iter().enumerate().filter(|(_, s)| room(s).is_some()).max_by_key(|(n, s)| (room(s), std::cmp::Reverse(*n)))?;
    Some(Placed { gpu: slot.gpu.clone(), slot: n, bytes: Some(estimate) })
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
        let mut budget = Budget::new(4, None, Some(Vec::new()));
        let model = budget.grant(&wants(3, false, true), None).unwrap();
        assert_eq!(model, Grant { threads: 3, gpu: false, placed: None });
        budget.take(&model);
        // Its bytes follow its thread count: it waits rather than start with fewer.
        assert_eq!(budget.grant(&wants(2, false, true), None), None);
        // A data stage starts with the one thread left.
        let data = budget.grant(&wants(2, false, false), None).unwrap();
        assert_eq!(data.threads, 1);
        budget.take(&data);
        assert_eq!(budget.grant(&wants(1, false, false), None), None, "no thread is free");
        budget.release(&model);
        budget.release(&data);
        assert_eq!(budget.grant(&wants(2, false, true), None).unwrap().threads, 2);
    }

    fn gpu(index: usize, gib: Option<u64>) -> Gpu {
        Gpu { index, uuid: None, model: "H100".into(), memory: gib.map(|g| g << 30) }
    }

    const GIB: u64 = 1 << 30;

    #[test]
    fn stages_run_side_by_side_on_different_gpus_then_share_one_by_their_estimates() {
        let mut local = Budget::new(8, None, Some(vec![gpu(0, Some(80)), gpu(1, Some(80))]));
        let on = |grant: &Grant| grant.placed.as_ref().map(|p| p.gpu.index);
        let a = local.grant(&wants(1, true, true), Some(30 * GIB)).unwrap();
        local.take(&a);
        let b = local.grant(&wants(1, true, true), Some(30 * GIB)).unwrap();
        local.take(&b);
        assert_eq!((on(&a), on(&b)), (Some(0), Some(1)), "an idle GPU first");
        // Both busy: a third shares the one with the most memory left, within the headroom.
        let c = local.grant(&wants(1, true, true), Some(40 * GIB)).unwrap();
        local.take(&c);
        assert_eq!(on(&c), Some(0));
        assert_eq!(local.grant(&wants(1, true, true), Some(40 * GIB)).map(|g| on(&g)), Some(Some(1)));
        assert_eq!(local.grant(&wants(1, true, true), Some(60 * GIB)), None, "too large beside the others: it waits");
        assert_eq!(local.grant(&wants(1, true, true), None), None, "without an estimate: only a whole GPU");
        assert!(local.grant(&wants(1, false, true), None).is_some_and(|g| g.placed.is_none()), "a CPU stage still fits");
        local.release(&a);
        local.release(&c);
        assert_eq!(local.grant(&wants(1, true, true), Some(60 * GIB)).map(|g| on(&g)), Some(Some(0)));

        // A stage without an estimate holds its GPU whole; a GPU of unknown memory is shared by none.
        let mut one = Budget::new(8, None, Some(vec![gpu(0, None)]));
        let whole = one.grant(&wants(1, true, true), Some(GIB)).unwrap();
        one.take(&whole);
        assert_eq!(one.grant(&wants(1, true, true), Some(GIB)), None);
        one.release(&whole);
        assert!(one.grant(&wants(1, true, true), Some(GIB)).is_some());

        let mut cluster = Budget::new(8, None, None);
        let placed_by_cluster = cluster.grant(&wants(1, true, true), None).unwrap();
        cluster.take(&placed_by_cluster);
        assert!(cluster.grant(&wants(1, true, true), None).is_some_and(|g| g.gpu && g.placed.is_none()), "the cluster places GPUs itself");
        let none = Budget::new(8, None, Some(Vec::new()));
        assert!(none.grant(&wants(1, true, true), None).is_some_and(|g| g.placed.is_none()), "no GPU: it runs on the CPU");
    }

    #[test]
    fn threads_are_clamped_to_the_budget_and_the_dispatchers_cap() {
        let budget = Budget::new(2, None, Some(Vec::new()));
        assert_eq!(budget.grant(&wants(16, false, true), None).unwrap().threads, 2, "more than --jobs is clamped");
        assert_eq!(budget.grant(&wants(0, false, true), None).unwrap().threads, 1, "at least one");
        let capped = Budget::new(8, Some(3), Some(Vec::new()));
        assert_eq!(capped.grant(&wants(16, false, true), None).unwrap().threads, 3);
    }
}
