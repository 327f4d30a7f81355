//! `rlmflow doctor`: asks the torch worker beside this binary (`rlmflow-torch doctor`) which
//! devices the model stages can compute on, and why not CUDA where they cannot; then lists the
//! GPUs a local run places stages on. `rlmflow` itself never loads libtorch.

use std::process::{Command, ExitCode};

use anyhow::{Context as _, bail};
use rlmflow_engine::cli::ExtraCommand;

pub fn command() -> ExtraCommand {
    ExtraCommand {
        command: clap::Command::new("doctor").about("Which devices the model stages can compute on (CPU, CUDA), and why not CUDA where they cannot"),
        run: |_| run(),
    }
}

fn run() -> anyhow::Result<ExitCode> {
    let worker = std::env::current_exe().context("locating the rlmflow executable")?.with_file_name("rlmflow-torch");
    if !worker.is_file() {
        bail!("the torch worker is not beside this binary ({}): `cargo xtask build --release` builds both", worker.display());
    }
    let status = Command::new(&worker).arg("doctor").status().with_context(|| format!("running {}", worker.display()))?;
    if !status.success() {
        bail!(
            "{} doctor failed ({status}): it could not start, so no model stage can run (is libtorch where its run path or LD_LIBRARY_PATH says?)",
            worker.display()
        );
    }
    print!("{}", rlmflow_engine::gpus::inventory(None)?.lines());
    Ok(ExitCode::SUCCESS)
}
