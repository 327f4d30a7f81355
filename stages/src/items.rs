//! Per-item work: each item's own seed, and items mapped over scoped threads in order.

/// The seed of item `index` (a frame, an epoch) of a run seeded `seed`: each item's draws come
/// from its own generator, never from one shared across items, so an item's result does not
/// depend on which thread, batch, shard or resumed attempt computed it.
pub fn item_seed(seed: u64, index: u64) -> u64 {
    seed ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15)
}

/// `f` over `items` on up to `threads` scoped threads, results in order.
pub fn parallel_map<T: Sync, R: Send>(items: &[T], threads: usize, f: impl Fn(&T) -> R + Sync) -> Vec<R> {
    let chunk = items.len().div_ceil(threads.max(1)).max(1);
    std::thread::scope(|scope| {
        let f = &f;
        let handles: Vec<_> = items.chunks(chunk).map(|part| scope.spawn(move || part.iter().map(f).collect::<Vec<R>>())).collect();
        handles.into_iter().flat_map(|h| h.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))).collect()
    })
}
