//! `rlmflow-test`: the rlmflow command line with the test operators of this crate.

fn main() -> std::process::ExitCode {
    rlmflow_engine::cli::main(rlmflow_e2e::registry(), &[])
}
