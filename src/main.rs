use std::process::ExitCode;

use rlmflow_stages::{Catalog, Registry};

/// The operators this binary ships. Each operator family registers itself here.
fn registry() -> Registry {
    Registry::new(Catalog::paper())
}

fn main() -> ExitCode {
    rlmflow::cli::main(registry())
}
