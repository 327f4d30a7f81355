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
    registry.add(rlmflow_segment::pup().running(rlmflow_segment_torch::pup));
    registry.add(rlmflow_segment::unet().running(rlmflow_segment_torch::unet));
    // tch 0.24's build accepts exactly this libtorch (python/libtorch.lock pins its wheel).
    registry.add_library("libtorch 2.11.0");
    registry
}

fn main() -> ExitCode {
    // libtorch decides once, at its first question about CUDA, whether it has it: load its CUDA
    // half first, where there is one and a driver (`rlmflow_nn::cuda`).
    let _ = rlmflow_nn::cuda::load(false);
    rlmflow_engine::cli::main(registry(), &[doctor::command(), step::command()])
}
