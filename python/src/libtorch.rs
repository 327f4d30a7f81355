//! libtorch for the torch worker (`rlmflow-torch`), which links it through tch.
//!
//! tch 0.24 needs libtorch 2.11.0 exactly. The PyPI `torch==2.11.0` wheel holds a complete
//! libtorch in its `torch/` directory (headers, CMake files, shared libraries), so
//! [`ensure_libtorch`] installs the pins of `libtorch.lock` with `pip --no-deps --target` into
//! the data directory (`libtorch/torch-<digest>`, about 1.4 GB, once) and returns that
//! `torch/` directory: what torch-sys's build script reads from `LIBTORCH`. `cargo xtask`
//! calls it before cargo compiles torch-sys. A machine that has torch 2.11 already (a GPU box)
//! sets `LIBTORCH` to it instead, and nothing is installed.

use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{Context as _, bail};

use crate::{MIN_VERSION, data_dir, interpreter_version, run};

/// The pinned wheels, one `name==version` per line.
pub const LIBTORCH_LOCK: &str = include_str!("../libtorch.lock");
/// The libtorch version tch needs.
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

fn install(scratch: &Path, root: &Path) -> anyhow::Result<()> {
    // A throwaway venv brings a pip of its own: the system Python may have none.
    let python = std::env::var_os("RLMFLOW_PYTHON").map_or_else(|| PathBuf::from("python3"), PathBuf::from);
    interpreter_version(&python)?;
    let venv = scratch.join("pip-venv");
    run(Command::new(&python).arg("-m").arg("venv").arg(&venv), "creating a venv for pip")?;
    let lock_file = scratch.join("libtorch.lock");
    fs::write(&lock_file, LIBTORCH_LOCK)?;
    let target = scratch.join("site");
    run(
        Command::new(venv.join("bin/python"))
            .args(["-m", "pip", "install", "--no-deps", "--disable-pip-version-check", "--no-input", "-q", "--target"])
            .arg(&target)
            .arg("-r")
            .arg(&lock_file),
        "installing the libtorch wheels",
    )?;
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
