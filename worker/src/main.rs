//! `rlmflow-torch`: the worker binary for the operators that link libtorch. The `rlmflow`
//! engine plans them (their settings live in light crates) and starts this binary per action
//! with the same entry point, protocol, store and locks as `rlmflow exec`, so `rlmflow` itself
//! never loads libtorch. It finds libtorch by its run path, or through `LD_LIBRARY_PATH` on a
//! machine with its own torch 2.11. It has no embedded Python, so it runs on a GPU machine
//! without one. `rlmflow-torch doctor` says which devices it can compute on.

use std::process::ExitCode;

use rlmflow_stages::{Catalog, Registry};

mod doctor;
mod step;

fn registry() -> Registry {
    let mut registry = Registry::new(Catalog::paper());
    // The operators `rlmflow` plans, each defined once in its light crate, with its training.
    registry.add(rlmflow_pretrain::operator().running(rlmflow_pretrain_torch::clip));
    registry.add(rlmflow_probe::linear().running(rlmflow_probe_torch::linear));
    registry.add(rlmflow_probe::clipcap().running(rlmflow_probe_torch::clipcap));
    registry.add(rlmflow_probe::embed().running(rlmflow_probe_torch::embed));
    registry.add(rlmflow_segment::pup().running(rlmflow_segment_torch::pup));
    registry.add(rlmflow_segment::unet().running(rlmflow_segment_torch::unet));
    // tch 0.24's build accepts exactly this libtorch (libs/python/libtorch.lock pins its wheel;
    // `rlmflow_python::libtorch::TORCH_VERSION` lists what to re-check on an upgrade).
    registry.add_library("libtorch 2.11.0");
    // The chain GEMM is installed once, before the operator makes its first tensor.
    registry.set_kernel_pin(|| rlmflow_nn::libtorch::pin_gemm().map(drop));
    registry
}

fn main() -> ExitCode {
    keep_freed_memory();
    // libtorch decides once, at its first question about CUDA, whether it has it: load its CUDA
    // half first, where there is one and a driver (`rlmflow_nn::cuda`).
    let _ = rlmflow_nn::cuda::load(false);
    rlmflow_engine::cli::main(registry(), &[doctor::command(), step::command()])
}

/// glibc hands each freed block above its threshold (128 KiB, raised only to the largest block
/// freed so far) back to the kernel and trims the heap's free top, so a training step, which
/// allocates the same activations every step, pays page faults and zeroing for them every time.
/// Blocks up to 32 MiB (glibc's ceiling) stay in the heap and its top is kept: a third of the
/// page faults and 3-5 % of the laptop step. Only where memory comes from changes: c10 aligns
/// every tensor to 64 bytes either way, so the results are the same bytes.
fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only sets allocator parameters; called before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, libc::c_int::MAX);
    }
}
