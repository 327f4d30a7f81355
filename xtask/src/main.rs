//! `cargo xtask`: the commands the README names. Each makes sure libtorch is in place (the torch
//! worker links it, and torch-sys's build script reads `LIBTORCH` before anything compiles),
//! then calls cargo with `LIBTORCH` set.
//!
//! ```text
//! cargo xtask test [ARGS]          cargo test [ARGS]; without ARGS, every test target built,
//!                                  then the end-to-end tests run beside the others
//! cargo xtask run PIPELINE [ARGS]  build rlmflow and its torch worker (release), then
//!                                  rlmflow run PIPELINE [ARGS]
//! cargo xtask build [ARGS]         cargo build [ARGS]
//! cargo xtask bench [ARGS]         cargo bench [ARGS]
//! cargo xtask rlmflow [ARGS]       build (release), then rlmflow [ARGS]: any subcommand
//! cargo xtask libtorch [--cuda]    install libtorch if missing and print where it is; with
//!                                  --cuda also the CUDA packages its CUDA half loads (about
//!                                  2.6 GB; every command installs them where an NVIDIA driver
//!                                  is present, `RLMFLOW_LIBTORCH_CUDA=0` never)
//! cargo xtask device-check [--build-only] [ARGS]
//!                                  build rlmflow and its torch worker (release), pack them
//!                                  (xz) with the libpython rlmflow embeds into
//!                                  target/device-check/ for a GPU machine, with ci.toml's
//!                                  highway-env scenes as a file remote, then run
//!                                  xtask/device-check.py ARGS on them (without a GPU: a dry
//!                                  run that checks its inputs)
//! cargo xtask digests [PIPELINE..] build (release), run each pipeline (default: examples/ci.toml
//!                                  and pipeline.toml) into its store and write its digests to
//!                                  docs/digests/NAME.digests (`rlmflow verify --against` reads
//!                                  them; the test suite checks ci.toml's)
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

/// The targets `cargo xtask test` runs when `args` name none: every library, binary and test
/// target, but not rustdoc's doc tests: the project writes none (its examples are in `docs/` and
/// `tests/`), and collecting nothing from 22 crates costs CI about 50 s. `--doc` runs them.
fn test_targets(args: &[String]) -> &'static [&'static str] {
    const SELECTORS: &[&str] =
        &["--doc", "--lib", "--bins", "--bin", "--tests", "--test", "--benches", "--bench", "--examples", "--example", "--all-targets"];
    let named = args.iter().take_while(|a| *a != "--").any(|a| SELECTORS.iter().any(|s| a == s || a.starts_with(&format!("{s}="))));
    if named { &[] } else { &["--lib", "--bins", "--tests"] }
}

fn xtask(args: Vec<String>) -> anyhow::Result<ExitCode> {
    let Some((command, rest)) = args.split_first() else {
        bail!("usage: cargo xtask <test|run|build|bench|rlmflow|libtorch|device-check|digests|llm-check> [ARGS]");
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
    // rlmflow and its torch worker in release; whether they built.
    let build_release = || -> anyhow::Result<bool> {
        Ok(status(cargo().args(["build", "--release", "--bins", "-p", "rlmflow", "-p", "rlmflow-torch"]))? == ExitCode::SUCCESS)
    };
    match command.as_str() {
        "libtorch" => {
            println!("{}", libtorch.display());
            Ok(ExitCode::SUCCESS)
        }
        "test" if rest.is_empty() => test_everything(&cargo),
        "test" => status(cargo().arg("test").args(test_targets(rest)).args(rest)),
        "build" | "bench" => status(cargo().arg(command).args(rest)),
        "run" | "rlmflow" => {
            if !build_release()? {
                return Ok(ExitCode::FAILURE);
            }
            let mut rlmflow = Command::new(target_dir()?.join("release/rlmflow"));
            if command == "run" {
                rlmflow.arg("run");
            }
            status(rlmflow.args(rest))
        }
        "device-check" => {
            if !build_release()? {
                return Ok(ExitCode::FAILURE);
            }
            let packed = target_dir()?.join("device-check");
            pack(&target_dir()?.join("release"), &libtorch, &packed)?;
            seed_ci(&target_dir()?.join("release/rlmflow"), &packed)?;
            if rest.iter().any(|a| a == "--build-only") {
                println!(
                    "{}: carry it to the GPU machine and run `python3 xtask/device-check.py --bin {}` there",
                    packed.display(),
                    packed.display()
                );
                return Ok(ExitCode::SUCCESS);
            }
            let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("device-check.py");
            status(Command::new("python3").arg(script).arg("--bin").arg(&packed).args(rest))
        }
        "digests" => {
            if !build_release()? {
                return Ok(ExitCode::FAILURE);
            }
            let root = workspace_root()?;
            let pipelines: Vec<PathBuf> = if rest.is_empty() {
                vec![root.join("examples/ci.toml"), root.join("pipeline.toml")]
            } else {
                rest.iter().map(PathBuf::from).collect()
            };
            let rlmflow = target_dir()?.join("release/rlmflow");
            for pipeline in pipelines {
                if !status(Command::new(&rlmflow).arg("run").arg(&pipeline))?.eq(&ExitCode::SUCCESS) {
                    return Ok(ExitCode::FAILURE);
                }
                let out = Command::new(&rlmflow).arg("digests").arg(&pipeline).output().context("running rlmflow digests")?;
                if !out.status.success() {
                    bail!("rlmflow digests {}: {}", pipeline.display(), String::from_utf8_lossy(&out.stderr).trim());
                }
                let name = pipeline.file_name().context("a pipeline file")?.to_string_lossy().into_owned();
                let file = root.join("docs/digests").join(format!("{name}.digests"));
                std::fs::write(&file, &out.stdout).with_context(|| format!("writing {}", file.display()))?;
                println!("{}", file.display());
            }
            Ok(ExitCode::SUCCESS)
        }
        "llm-check" => {
            if !status(cargo().args(["build", "--bin", "rlmflow", "-p", "rlmflow"]))?.eq(&ExitCode::SUCCESS) {
                return Ok(ExitCode::FAILURE);
            }
            let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/llm_check.py");
            status(Command::new("python3").arg(script).arg(target_dir()?.join("debug/rlmflow")))
        }
        other => bail!("unknown xtask `{other}`; valid: test, run, build, bench, rlmflow, libtorch, device-check, digests, llm-check"),
    }
}

/// The release binaries of `release`, xz-compressed, the libpython `rlmflow` embeds and the
/// OpenMP runtime the worker's GEMM links (`libtorch`'s own, which a torch packaged without it in
/// `lib/` lacks), in `into`: what a GPU machine without Rust needs (`xtask/device-check.py`
/// unpacks them).
fn pack(release: &std::path::Path, libtorch: &std::path::Path, into: &std::path::Path) -> anyhow::Result<()> {
    std::fs::create_dir_all(into)?;
    for name in ["rlmflow", "rlmflow-torch"] {
        let _ = std::fs::remove_file(into.join(name));
        let packed = std::fs::File::create(into.join(format!("{name}.xz")))?;
        let ok = Command::new("xz").args(["-T0", "-6", "-c"]).arg(release.join(name)).stdout(packed).status().context("running xz")?;
        if !ok.success() {
            bail!("xz could not pack {}", release.join(name).display());
        }
    }
    let python = std::env::var_os("PYO3_PYTHON").unwrap_or_else(|| "python3".into());
    let query = "import os, sysconfig; print(os.path.join(sysconfig.get_config_var('LIBDIR'), sysconfig.get_config_var('INSTSONAME')))";
    let out = Command::new(&python).args(["-c", query]).output().context("asking Python for its libpython")?;
    let libpython = PathBuf::from(String::from_utf8_lossy(&out.stdout).trim());
    let name = libpython.file_name().context("libpython's file name")?;
    std::fs::copy(&libpython, into.join(name)).with_context(|| format!("copying {}", libpython.display()))?;
    let openmp = libtorch.join("lib/libgomp.so.1");
    std::fs::copy(&openmp, into.join("libgomp.so.1")).with_context(|| format!("copying {}", openmp.display()))?;
    Ok(())
}

/// `examples/ci.toml`'s highway-env scenes in a file remote, `into/ci-seeds`: the device check
/// computes the rest of ci.toml on the GPU machine's CPU, which has no network to make the
/// Python environment highway-env needs. The pipeline runs from a copy beside its store, so the
/// user's `examples/results` links stay as they were.
fn seed_ci(rlmflow: &std::path::Path, into: &std::path::Path) -> anyhow::Result<()> {
    let root = workspace_root()?;
    let work = target_dir()?.join("device-check-seeding");
    std::fs::create_dir_all(&work)?;
    let pipeline = work.join("ci.toml");
    std::fs::copy(root.join("examples/ci.toml"), &pipeline).context("copying examples/ci.toml")?;
    let remote = format!("file://{}", std::path::absolute(into.join("ci-seeds"))?.display());
    for command in ["run", "push"] {
        let mut seed = Command::new(rlmflow);
        seed.arg(command).arg(&pipeline).args(["--only", "scenes", "--remote", &remote]);
        if status(&mut seed)? != ExitCode::SUCCESS {
            bail!("rlmflow {command} {} --only scenes failed", pipeline.display());
        }
    }
    Ok(())
}

/// The package whose tests `cargo xtask test` runs beside the others, and its test target: the
/// engine's end-to-end tests spend most of their time waiting on throttled links, servers and
/// child processes (47 CPU-seconds in 55 s on 2 cores), room the other test binaries, run one
/// after another, leave. The package's library and binary hold no tests of their own.
const BESIDE: (&str, &str) = ("rlmflow-e2e", "e2e");

/// `cargo xtask test` without arguments (what CI runs): every test target built first, then
/// [`BESIDE`]'s tests run beside the rest, their output held and printed whole when they end.
/// The end-to-end target is named with `--test` over the default members rather than by its
/// package alone, so cargo resolves the same features and builds nothing twice.
fn test_everything(cargo: &dyn Fn() -> Command) -> anyhow::Result<ExitCode> {
    let (package, target) = BESIDE;
    let rest = [test_targets(&[]), &["--workspace", "--exclude", package, "--exclude", "xtask"][..]].concat();
    let beside = ["--test", target];
    for selection in [&rest[..], &beside[..]] {
        if status(cargo().args(["test", "--no-run"]).args(selection))? != ExitCode::SUCCESS {
            return Ok(ExitCode::FAILURE);
        }
    }
    let log_path = target_dir()?.join(format!("{package}.log"));
    let log = std::fs::File::create(&log_path).with_context(|| format!("creating {}", log_path.display()))?;
    let mut running = cargo().arg("test").args(beside).stdout(log.try_clone()?).stderr(log).spawn().context("starting cargo test")?;
    let others = status(cargo().arg("test").args(&rest));
    let finished = running.wait().context("waiting for cargo test")?;
    println!("\n{package}'s tests, run beside the others ({}):", log_path.display());
    print!("{}", std::fs::read_to_string(&log_path).with_context(|| format!("reading {}", log_path.display()))?);
    if !finished.success() {
        return Ok(ExitCode::FAILURE);
    }
    others
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
    Ok(workspace_root()?.join("target"))
}

/// The workspace's root directory, where `xtask/` lives.
fn workspace_root() -> anyhow::Result<PathBuf> {
    Ok(PathBuf::from(env!("CARGO_MANIFEST_DIR")).parent().context("xtask lives in the workspace")?.to_path_buf())
}
