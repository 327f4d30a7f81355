//! `cargo xtask`: the commands the README names. Each makes sure libtorch is in place (the torch
//! worker links it, and torch-sys's build script reads `LIBTORCH` before anything compiles),
//! then calls cargo with `LIBTORCH` set.
//!
//! ```text
//! cargo xtask test [ARGS]          cargo test [ARGS]
//! cargo xtask run PIPELINE [ARGS]  build rlmflow and its torch worker (release), then
//!                                  rlmflow run PIPELINE [ARGS]
//! cargo xtask build [ARGS]         cargo build [ARGS]
//! cargo xtask bench [ARGS]         cargo bench [ARGS]
//! cargo xtask rlmflow [ARGS]       build (release), then rlmflow [ARGS]: any subcommand
//! cargo xtask libtorch [--cuda]    install libtorch if missing and print where it is; with
//!                                  --cuda also the CUDA packages its CUDA half loads (about
//!                                  2.6 GB; every command installs them where an NVIDIA driver
//!                                  is present, `RLMFLOW_LIBTORCH_CUDA=0` never)
//! cargo xtask llm-check            build rlmflow, then run tests/llm_check.py: the `llm`
//!                                  operator against a real llama.cpp server (opt-in; it
//!                                  compiles llama.cpp, about 11 minutes on 2 cores)
//! ```
//!
//! `LIBTORCH` set beforehand (a machine with torch 2.11 already) is used instead of installing.

use std::path::PathBuf;
use std::process::{Command, ExitCode};

use anyhow::{Context as _, bail};

fn main() -> ExitCode {
    match xtask(std::env::args().skip(1).collect()) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn xtask(args: Vec<String>) -> anyhow::Result<ExitCode> {
    let Some((command, rest)) = args.split_first() else {
        bail!("usage: cargo xtask <test|run|build|bench|rlmflow|libtorch|llm-check> [ARGS]");
    };
    let note = &mut |note: &str| eprintln!("xtask: {note}");
    let ours = std::env::var_os("LIBTORCH").is_none();
    let libtorch = rlmflow_python::libtorch::ensure_libtorch(note)?;
    // A libtorch of the user's own (LIBTORCH) comes with its CUDA libraries or without.
    if ours && rlmflow_python::libtorch::cuda_wanted(command == "libtorch" && rest.iter().any(|a| a == "--cuda")) {
        rlmflow_python::libtorch::ensure_cuda_packages(&libtorch, note)?;
    }
    let cargo = || {
        let mut cmd = Command::new(std::env::var_os("CARGO").unwrap_or_else(|| "cargo".into()));
        cmd.env("LIBTORCH", &libtorch).env("LIBTORCH_CXX11_ABI", "1");
        cmd
    };
    match command.as_str() {
        "libtorch" => {
            println!("{}", libtorch.display());
            Ok(ExitCode::SUCCESS)
        }
        "test" | "build" | "bench" => status(cargo().arg(command).args(rest)),
        "run" | "rlmflow" => {
            if !status(cargo().args(["build", "--release", "--bins", "-p", "rlmflow", "-p", "rlmflow-torch"]))?.eq(&ExitCode::SUCCESS) {
                return Ok(ExitCode::FAILURE);
            }
            let mut rlmflow = Command::new(target_dir()?.join("release/rlmflow"));
            if command == "run" {
                rlmflow.arg("run");
            }
            status(rlmflow.args(rest))
        }
        "llm-check" => {
            if !status(cargo().args(["build", "--bin", "rlmflow", "-p", "rlmflow"]))?.eq(&ExitCode::SUCCESS) {
                return Ok(ExitCode::FAILURE);
            }
            let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/llm_check.py");
            status(Command::new("python3").arg(script).arg(target_dir()?.join("debug/rlmflow")))
        }
        other => bail!("unknown xtask `{other}`; valid: test, run, build, bench, rlmflow, libtorch, llm-check"),
    }
}

fn status(cmd: &mut Command) -> anyhow::Result<ExitCode> {
    let status = cmd.status().with_context(|| format!("running {:?}", cmd.get_program()))?;
    Ok(if status.success() { ExitCode::SUCCESS } else { ExitCode::from(status.code().unwrap_or(1).clamp(1, 255) as u8) })
}

/// Cargo's target directory: `CARGO_TARGET_DIR`, else `target/` in the workspace.
fn target_dir() -> anyhow::Result<PathBuf> {
    if let Some(dir) = std::env::var_os("CARGO_TARGET_DIR") {
        return Ok(dir.into());
    }
    let manifest = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    Ok(manifest.parent().context("xtask lives in the workspace")?.join("target"))
}
