//! `rlmflow-test`: the rlmflow command line with the test operators of this crate.

fn main() -> std::process::ExitCode {
    rlmflow::cli::main(rlmflow_e2e::registry())
}
