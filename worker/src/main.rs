//! `rlmflow-torch`: the worker binary for the operators that link libtorch. The `rlmflow`
//! engine plans them (their settings live in light crates) and starts this binary per action
//! with the same entry point, protocol, store and locks as `rlmflow exec`, so `rlmflow` itself
//! never loads libtorch. It finds libtorch by its run path, or through `LD_LIBRARY_PATH` on a
//! machine with its own torch 2.11. It has no embedded Python, so it runs on a GPU machine
//! without one.

use std::process::ExitCode;

use rlmflow_stages::{Catalog, Registry};

fn registry() -> Registry {
    let mut registry = Registry::new(Catalog::paper());
    registry.add(rlmflow_pretrain_torch::Clip);
    registry.add(rlmflow_probe_torch::Linear);
    registry.add(rlmflow_probe_torch::Clipcap);
    registry.add(rlmflow_segment_torch::Pup);
    registry.add(rlmflow_segment_torch::Unet);
    // tch 0.24's build accepts exactly this libtorch (python/libtorch.lock pins its wheel).
    registry.add_library("libtorch 2.11.0");
    registry
}

fn main() -> ExitCode {
    rlmflow_engine::cli::main(registry(), &[])
}
