//! libtorch for the torch worker (`rlmflow-torch`), which links it through tch.
//!
//! tch 0.24 needs libtorch 2.11.0 exactly. The PyPI `torch==2.11.0` wheel holds a complete
//! libtorch in its `torch/` directory (headers, CMake files, shared libraries), so
//! [`ensure_libtorch`] installs the pins of `libtorch.lock` with `pip --no-deps --target` into
//! the data directory (`libtorch/torch-<digest>`, about 1.4 GB, once) and returns that
//! `torch/` directory: what torch-sys's build script reads from `LIBTORCH`. `cargo xtask`
//! calls it before cargo compiles torch-sys. A machine that has torch 2.11 already (a GPU box)
//! sets `LIBTORCH` to it instead, and nothing is installed.
//!
//! The wheel's libtorch is a CUDA build whose CUDA half (`libtorch_cuda.so`) needs cuBLAS,
//! cuDNN and the rest, several GB that a CPU machine never loads: [`ensure_cuda_packages`]
//! installs `libtorch-cuda.lock` into the same tree where an NVIDIA driver is present, or when
//! asked (`cargo xtask libtorch --cuda`, `RLMFLOW_LIBTORCH_CUDA=1`; `=0` never).

use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context as _, bail};

use crate::{MIN_VERSION, data_dir, interpreter_version, run};

/// The pinned wheels, one `name==version` per line.
pub const LIBTORCH_LOCK: &str = include_str!("../libtorch.lock");
/// The CUDA packages libtorch_cuda.so loads, one `name==version` per line.
pub const CUDA_LOCK: &str = include_str!("../libtorch-cuda.lock");
const CUDA_READY: &str = "rlmflow-libtorch-cuda.json";
/// The libtorch version tch needs.
///
/// Upgrading it (with tch, which accepts exactly one libtorch, and `libtorch.lock`): the portable
/// numerics lean on ATen internals that `libs/nn/cpp` compiles against. Re-check each:
/// 1. `chain_gemm.cpp` registers over `aten::mm`, `mm.out`, `addmm`, `addmm.out`, `addmm_`,
///    `bmm`, `bmm.out`, `baddbmm`, `baddbmm.out` and `baddbmm_` for `DispatchKey::CPU`: each
///    schema still exists with these signatures (a mismatch fails the registration when a model
///    stage starts), and no new float32 product that `nn::linear`, `matmul` or attention reaches
///    bypasses them.
/// 2. The fallbacks for other dtypes, `at::cpu::{mm,addmm,bmm,baddbmm}` (`_outf`, `_`) from
///    `ATen/ops/*_cpu_dispatch.h`, still exist.
/// 3. `at::native::resize_output` (`ATen/native/Resize.h`) still resizes an `out=` tensor as
///    ATen's own kernels do.
/// 4. `torch_settings.cpp`'s `_fused_adamw`, `_foreach_norm`, `_foreach_mul`, autocast and
///    `Context` calls keep their signatures; both files build warning-free (`-Werror`,
///    `libs/nn/build.rs`).
///
/// Then `cargo xtask test -p rlmflow-nn --test chain_gemm` (an installed `mm` is the chain
/// kernel; every product of a model step gives the same bits at every width and thread count;
/// unset, ATen's kernels return), the whole suite, and `docs/digests/` regenerated: the library
/// is in every model action's platform record, and its kernels may move the bytes.
pub const TORCH_VERSION: &str = "2.11.0";
const READY: &str = "rlmflow-libtorch.json";

/// The libtorch directory: `$LIBTORCH` if set (checked), else the one installed from the lock,
/// installed first if missing. `note` hears what is happening.
pub fn ensure_libtorch(note: &mut dyn FnMut(&str)) -> anyhow::Result<PathBuf> {
    if let Some(dir) = std::env::var_os("LIBTORCH") {
        let dir = PathBuf::from(dir);
        check_libtorch(&dir).with_context(|| format!("LIBTORCH={}", dir.display()))?;
        return Ok(dir);
    }
    let digest = blake3::hash(LIBTORCH_LOCK.as_bytes()).to_hex();
    let root = data_dir()?.join("libtorch").join(format!("torch-{}", &digest[..16]));
    let torch = root.join("torch");
    if root.join(READY).is_file() {
        return Ok(torch);
    }
    let parent = root.parent().expect("has a parent");
    fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    let lock = File::create(parent.join(".lock"))?;
    lock.lock()?;
    if root.join(READY).is_file() {
        return Ok(torch);
    }
    note(&format!("installing libtorch {TORCH_VERSION} into {} (once; about 530 MB from PyPI)", root.display()));
    let scratch = parent.join(format!(".installing-{}", std::process::id()));
    let _ = fs::remove_dir_all(&scratch);
    let result = install(&scratch, &root);
    let _ = fs::remove_dir_all(&scratch);
    result?;
    note(&format!("libtorch ready at {}", torch.display()));
    Ok(torch)
}

/// Whether to install the CUDA packages: `asked` (`--cuda`), else `RLMFLOW_LIBTORCH_CUDA`
/// (`1` or `0`), else whether this machine has an NVIDIA driver.
pub fn cuda_wanted(asked: bool) -> bool {
    match std::env::var("RLMFLOW_LIBTORCH_CUDA").as_deref() {
        _ if asked => true,
        Ok("1") => true,
        Ok("0") => false,
        _ => Path::new("/proc/driver/nvidia/version").exists() || Path::new("/dev/nvidiactl").exists(),
    }
}

/// Installs the CUDA packages of `CUDA_LOCK` beside the libtorch `torch` that [`ensure_libtorch`]
/// installed (its parent holds the wheels' tree, where libtorch_cuda.so's run path looks), once.
pub fn ensure_cuda_packages(torch: &Path, note: &mut dyn FnMut(&str)) -> anyhow::Result<()> {
    let root = torch.parent().context("libtorch has a parent directory")?;
    if root.join(CUDA_READY).is_file() {
        return Ok(());
    }
    if !root.join(READY).is_file() {
        bail!("{} was not installed by rlmflow (no {READY}): install the CUDA packages its torch needs yourself", torch.display());
    }
    let lock = File::create(root.join(".cuda-lock"))?;
    lock.lock()?;
    if root.join(CUDA_READY).is_file() {
        return Ok(());
    }
    note(&format!("installing the CUDA packages libtorch_cuda loads into {} (once; about 2.6 GB from PyPI)", root.display()));
    let scratch = root.join(format!(".installing-cuda-{}", std::process::id()));
    let _ = fs::remove_dir_all(&scratch);
    let result = pip_install(&scratch, CUDA_LOCK, "installing the CUDA packages").and_then(|site| merge(&site, root));
    let _ = fs::remove_dir_all(&scratch);
    result?;
    fs::write(root.join(CUDA_READY), CUDA_LOCK)?;
    note("CUDA packages ready");
    Ok(())
}

/// Moves every entry of `from` into `into` that `into` lacks (directories merged), so packages
/// that share a namespace directory (`nvidia/cu13/lib`) end in one tree.
fn merge(from: &Path, into: &Path) -> anyhow::Result<()> {
    let mut pending = vec![(from.to_path_buf(), into.to_path_buf())];
    while let Some((source, target)) = pending.pop() {
        if !target.exists() {
            fs::rename(&source, &target).with_context(|| format!("moving {} to {}", source.display(), target.display()))?;
        } else if source.is_dir() && target.is_dir() {
            for entry in fs::read_dir(&source)? {
                let entry = entry?;
                pending.push((entry.path(), target.join(entry.file_name())));
            }
        }
    }
    Ok(())
}

/// Installs `lock` with `pip --no-deps --target` into `scratch/site`, from a throwaway venv (the
/// system Python may have no pip); returns that directory.
fn pip_install(scratch: &Path, lock: &str, what: &str) -> anyhow::Result<PathBuf> {
    let python = std::env::var_os("RLMFLOW_PYTHON").map_or_else(|| PathBuf::from("python3"), PathBuf::from);
    interpreter_version(&python)?;
    let venv = scratch.join("pip-venv");
    run(Command::new(&python).arg("-m").arg("venv").arg(&venv), "creating a venv for pip")?;
    let lock_file = scratch.join("requirements.lock");
    fs::write(&lock_file, lock)?;
    let target = scratch.join("site");
    run(
        Command::new(venv.join("bin/python"))
            .args(["-m", "pip", "install", "--no-deps", "--disable-pip-version-check", "--no-input", "-q", "--target"])
            .arg(&target)
            .arg("-r")
            .arg(&lock_file),
        what,
    )?;
    Ok(target)
}

fn install(scratch: &Path, root: &Path) -> anyhow::Result<()> {
    let target = pip_install(scratch, LIBTORCH_LOCK, "installing the libtorch wheels")?;
    check_libtorch(&target.join("torch"))?;
    fs::write(target.join(READY), LIBTORCH_LOCK)?;
    fs::rename(&target, root).with_context(|| format!("moving libtorch into {}", root.display()))?;
    Ok(())
}

/// Checks that `dir` is a libtorch of the version tch needs.
pub fn check_libtorch(dir: &Path) -> anyhow::Result<()> {
    if !dir.join("lib/libtorch_cpu.so").is_file() || !dir.join("include/torch").is_dir() {
        bail!("{} is not a libtorch (no lib/libtorch_cpu.so and include/torch)", dir.display());
    }
    // The wheel records its version in version.py; a libtorch zip in build-version.
    let recorded = fs::read_to_string(dir.join("version.py"))
        .ok()
        .and_then(|v| v.lines().find_map(|l| l.strip_prefix("__version__ = ").map(|s| s.trim_matches(['\'', '"']).to_owned())))
        .or_else(|| fs::read_to_string(dir.join("build-version")).ok());
    let version = recorded.as_deref().map(|v| v.trim().split('+').next().unwrap_or_default().to_owned());
    match version {
        Some(v) if v == TORCH_VERSION => Ok(()),
        Some(v) => bail!(
            "{} holds torch {v}; tch needs {TORCH_VERSION} (Python {}.{}+ installs it: unset LIBTORCH)",
            dir.display(),
            MIN_VERSION.0,
            MIN_VERSION.1
        ),
        None => bail!("{} records no torch version (version.py or build-version)", dir.display()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cuda_lock_pins_the_libraries_libtorch_cuda_needs() {
        let pins: Vec<&str> = CUDA_LOCK.lines().filter(|l| !l.trim().is_empty() && !l.starts_with('#')).collect();
        for line in &pins {
            let (name, version) = line.split_once("==").unwrap_or_else(|| panic!("`{line}` is not name==version"));
            assert!(name.starts_with("nvidia-") && version.chars().all(|c| c.is_ascii_digit() || c == '.'), "`{line}`");
        }
        // libtorch_cuda.so's NEEDED entries beyond the two packages of libtorch.lock.
        for library in ["nvidia-cublas==", "nvidia-cudnn-cu13==", "nvidia-nccl-cu13==", "nvidia-cusparselt-cu13==", "nvidia-nvshmem-cu13=="] {
            assert!(pins.iter().any(|p| p.starts_with(library)), "{library}");
        }
    }

    #[test]
    fn packages_sharing_a_namespace_directory_merge_into_one_tree() {
        let dir = std::env::temp_dir().join(format!("rlmflow-merge-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        let (from, into) = (dir.join("from"), dir.join("into"));
        fs::create_dir_all(from.join("nvidia/cu13/lib")).unwrap();
        fs::create_dir_all(from.join("nvidia/cudnn/lib")).unwrap();
        fs::create_dir_all(into.join("nvidia/cu13/lib")).unwrap();
        fs::write(from.join("nvidia/cu13/lib/libcublas.so.13"), "new").unwrap();
        fs::write(from.join("nvidia/cudnn/lib/libcudnn.so.9"), "new").unwrap();
        fs::write(from.join("nvidia/__init__.py"), "new").unwrap();
        fs::write(into.join("nvidia/cu13/lib/libcudart.so.13"), "kept").unwrap();
        fs::write(into.join("nvidia/__init__.py"), "kept").unwrap();
        merge(&from, &into).unwrap();
        let read = |p: &str| fs::read_to_string(into.join(p)).unwrap();
        assert_eq!(read("nvidia/cu13/lib/libcudart.so.13"), "kept");
        assert_eq!(read("nvidia/cu13/lib/libcublas.so.13"), "new");
        assert_eq!(read("nvidia/cudnn/lib/libcudnn.so.9"), "new");
        assert_eq!(read("nvidia/__init__.py"), "kept", "an existing file is not replaced");
        fs::remove_dir_all(&dir).unwrap();
    }
}
