use std::process::ExitCode;

use rlmflow_stages::{Catalog, Registry};

/// The operators this binary ships. Each operator family registers itself here.
fn registry() -> Registry {
    let mut registry = Registry::new(Catalog::paper());
    registry.add(rlmflow_scenes::Procedural);
    registry
}

fn main() -> ExitCode {
    rlmflow::cli::main(registry())
}
