//! rlmflow's managed Python environment: one venv per lock, created from
//! `requirements.lock` (compiled into the binary) by `rlmflow setup` or on first use.
//!
//! The venv lives under the data directory (`$RLMFLOW_HOME`, else `$XDG_DATA_HOME/rlmflow`, else
//! `~/.local/share/rlmflow`) at `python/env-<digest>`, where the digest covers the lock and the
//! interpreter's version: a changed lock or interpreter gets a new environment, an unchanged one
//! is found by name. It is built in a scratch directory and renamed into place once every
//! package is installed and imports, so a half-made environment is never used.
//!
//! The interpreter is `$RLMFLOW_PYTHON` if set; else, in a binary that embeds Python, the one it
//! was built against (the venv must match the embedded libpython); else `python3`.
//!
//! With the `embed` feature, [`embed`] starts the embedded interpreter on the environment.

#[cfg(feature = "embed")]
pub mod embed;
pub mod libtorch;

use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{Context as _, bail};
use serde::{Deserialize, Serialize};

/// The pinned packages, one `name==version` per line.
pub const LOCK: &str = include_str!("../requirements.lock");
/// A lock's `name==version` lines.
fn pinned(lock: &str) -> impl Iterator<Item = &str> {
    lock.lines().filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
}

/// The `rlmflow` Python package (`libs/python/package`: reads a store's artifacts), each file as
/// `(path under site-packages, content)`: written into the environment after the lock, and part
/// of the environment's name, so a changed package gets a new environment.
pub const PACKAGE: &[(&str, &str)] =
    &[("rlmflow/__init__.py", include_str!("../package/rlmflow/__init__.py")), ("rlmflow/stage.py", include_str!("../package/rlmflow/stage.py"))];

/// Python older than this cannot install the lock (numpy 2.4 needs 3.11).
pub const MIN_VERSION: (u32, u32) = (3, 11);
const READY: &str = "rlmflow-env.json";

/// A ready environment.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Environment {
    pub root: PathBuf,
    /// The venv's interpreter.
    pub python: PathBuf,
    pub site_packages: PathBuf,
    /// `major.minor.micro` of the interpreter.
    pub version: String,
}

/// The interpreter an environment is made from.
fn base_interpreter() -> PathBuf {
    if let Some(p) = std::env::var_os("RLMFLOW_PYTHON") {
        return p.into();
    }
    #[cfg(feature = "embed")]
    return PathBuf::from(env!("RLMFLOW_BUILD_PYTHON"));
    #[cfg(not(feature = "embed"))]
    return PathBuf::from("python3");
}

pub(crate) fn data_dir() -> anyhow::Result<PathBuf> {
    if let Some(p) = std::env::var_os("RLMFLOW_HOME") {
        return Ok(p.into());
    }
    if let Some(p) = std::env::var_os("XDG_DATA_HOME") {
        return Ok(PathBuf::from(p).join("rlmflow"));
    }
    match std::env::var_os("HOME") {
        Some(home) => Ok(PathBuf::from(home).join(".local/share/rlmflow")),
        None => bail!("cannot place the Python environment: set RLMFLOW_HOME, XDG_DATA_HOME or HOME"),
    }
}

/// The interpreter's `major.minor.micro`, or a message saying what to install.
pub(crate) fn interpreter_version(python: &Path) -> anyhow::Result<String> {
    let install = format!(
        "install Python {}.{} or newer with venv and pip (e.g. `apt install python3 python3-venv`), or point RLMFLOW_PYTHON at one",
        MIN_VERSION.0, MIN_VERSION.1
    );
    let out = Command::new(python)
        .args(["-c", "import sys, venv, ensurepip; print('%d.%d.%d' % sys.version_info[:3])"])
        .stderr(Stdio::piped())
        .output()
        .with_context(|| format!("cannot run Python `{}`: {install}", python.display()))?;
    if !out.status.success() {
        bail!("`{}` cannot create environments ({}): {install}", python.display(), String::from_utf8_lossy(&out.stderr).trim());
    }
    let version = String::from_utf8_lossy(&out.stdout).trim().to_string();
    let mut parts = version.split('.').map(|p| p.parse::<u32>().unwrap_or(0));
    let (major, minor) = (parts.next().unwrap_or(0), parts.next().unwrap_or(0));
    if (major, minor) < MIN_VERSION {
        bail!("`{}` is Python {version}, too old: {install}", python.display());
    }
    #[cfg(feature = "embed")]
    if version.rsplit_once('.').map(|v| v.0) != Some(env!("RLMFLOW_BUILD_PYTHON_VERSION")) {
        bail!(
            "`{}` is Python {version}, but this binary embeds Python {}: unset RLMFLOW_PYTHON or rebuild against it (PYO3_PYTHON)",
            python.display(),
            env!("RLMFLOW_BUILD_PYTHON_VERSION")
        );
    }
    Ok(version)
}

/// The digest naming the environment of `lock` on an interpreter of `version`, with the package.
fn env_digest(lock: &str, version: &str) -> String {
    let mut hasher = blake3::Hasher::new();
    hasher.update(format!("{lock}\0{version}").as_bytes());
    for (path, content) in PACKAGE {
        hasher.update(format!("\0{path}\0{content}").as_bytes());
    }
    hasher.finalize().to_hex()[..16].to_owned()
}

/// The interpreter's `major.minor.micro`, asked without its site packages; `None` where it does
/// not answer (`interpreter_version` then says why).
fn quick_version(python: &Path) -> Option<String> {
    let out = Command::new(python).args(["-S", "-c", "import sys; print('%d.%d.%d' % sys.version_info[:3])"]).stderr(Stdio::null()).output().ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
}

/// Where the environment for this lock and interpreter lives, whether or not it exists.
fn env_dir(lock: &str, version: &str) -> anyhow::Result<PathBuf> {
    Ok(data_dir()?.join("python").join(format!("env-{}", env_digest(lock, version))))
}

/// The `major.minor` of the interpreter this binary's environments are made from, where it is
/// known when the binary is built (it embeds Python); else `python3`.
pub const PYTHON: &str = match option_env!("RLMFLOW_BUILD_PYTHON_VERSION") {
    Some(version) => version,
    None => "python3",
};

/// What identifies rlmflow's own environment to a key, before it exists: the interpreter's
/// `major.minor` ([`PYTHON`]) and the digest of the lock (the `rlmflow` package beside it only
/// reads and reports, so a change to it changes no program's results).
pub fn identity() -> String {
    format!("{PYTHON} {}", &blake3::hash(LOCK.as_bytes()).to_hex()[..16])
}

fn read_ready(root: &Path) -> anyhow::Result<Option<Environment>> {
    match fs::read(root.join(READY)) {
        Ok(bytes) => Ok(Some(serde_json::from_slice(&bytes).with_context(|| format!("{} is damaged; delete {}", READY, root.display()))?)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(e).with_context(|| format!("reading {}", root.join(READY).display())),
    }
}

/// The environment, created first if missing; `note` hears what is happening (creation takes
/// a minute and downloads from PyPI).
pub fn ensure(note: &mut dyn FnMut(&str)) -> anyhow::Result<Environment> {
    ensure_lock(LOCK, "highway_env, mcap, tokenizers, rerun, hyperqueue, safetensors, rlmflow", note)
}

/// The environment of a user's `lock` (`name==version` lines, every dependency pinned: it is
/// installed with `--no-deps`), with the `rlmflow` package, created first if missing; `imports`
/// is what it must import once made.
pub fn ensure_lock(lock: &str, imports: &str, note: &mut dyn FnMut(&str)) -> anyhow::Result<Environment> {
    let python = base_interpreter();
    // An environment that exists is found by the interpreter's version alone (a few ms); one
    // to be made needs the full check (venv and pip present, new enough).
    if let Some(version) = quick_version(&python)
        && let Some(env) = read_ready(&env_dir(lock, &version)?)?
    {
        return Ok(env);
    }
    let version = interpreter_version(&python)?;
    let root = env_dir(lock, &version)?;
    if let Some(env) = read_ready(&root)? {
        return Ok(env);
    }
    let parent = root.parent().expect("env_dir has a parent");
    fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    // One creator at a time; the others wait and then find it ready.
    let creating = File::create(parent.join(".lock"))?;
    creating.lock()?;
    if let Some(env) = read_ready(&root)? {
        return Ok(env);
    }
    note(&format!("creating the Python environment at {} (once; about a minute)", root.display()));
    let scratch = parent.join(format!(".creating-{}", std::process::id()));
    let _ = fs::remove_dir_all(&scratch);
    let result = create(&python, &scratch, &root, &version, lock, imports, note);
    if result.is_err() {
        let _ = fs::remove_dir_all(&scratch);
    }
    result
}

fn create(
    python: &Path,
    scratch: &Path,
    root: &Path,
    version: &str,
    lock: &str,
    imports: &str,
    note: &mut dyn FnMut(&str),
) -> anyhow::Result<Environment> {
    run(Command::new(python).arg("-m").arg("venv").arg(scratch), "creating the venv")?;
    let lock_file = scratch.join("requirements.lock");
    fs::write(&lock_file, lock)?;
    note(&format!("installing {} pinned packages", pinned(lock).count()));
    let venv_python = scratch.join("bin/python");
    run(
        Command::new(&venv_python)
            .args(["-m", "pip", "install", "--no-deps", "--disable-pip-version-check", "--no-input", "-q", "-r"])
            .arg(&lock_file),
        "installing the locked packages",
    )?;
    let site = Command::new(&venv_python).args(["-c", "import sysconfig; print(sysconfig.get_path('purelib'))"]).output()?;
    let site_packages = PathBuf::from(String::from_utf8_lossy(&site.stdout).trim());
    for (path, content) in PACKAGE {
        let file = site_packages.join(path);
        fs::create_dir_all(file.parent().expect("a package file has a directory"))?;
        fs::write(&file, content).with_context(|| format!("writing {}", file.display()))?;
    }
    run(Command::new(&venv_python).args(["-c", &format!("import {imports}")]), "checking the packages import")?;
    // The venv is moved into place: record paths as they will be.
    let relative = site_packages.strip_prefix(scratch).context("site-packages lies outside the venv")?.to_path_buf();
    let env = Environment { root: root.to_path_buf(), python: root.join("bin/python"), site_packages: root.join(relative), version: version.into() };
    fs::write(scratch.join(READY), serde_json::to_vec_pretty(&env)?)?;
    fs::rename(scratch, root).with_context(|| format!("moving the environment into {}", root.display()))?;
    note(&format!("Python environment ready at {}", root.display()));
    Ok(env)
}

pub(crate) fn run(cmd: &mut Command, what: &str) -> anyhow::Result<()> {
    let out = cmd.stdin(Stdio::null()).output().with_context(|| format!("{what}: cannot start {:?}", cmd.get_program()))?;
    if !out.status.success() {
        let err = String::from_utf8_lossy(&out.stderr);
        let tail: Vec<&str> = err.lines().rev().take(15).collect();
        bail!("{what} failed ({}):\n{}", out.status, tail.into_iter().rev().collect::<Vec<_>>().join("\n"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lock_pins_every_package() {
        for line in pinned(LOCK) {
            let (name, version) = line.split_once("==").unwrap_or_else(|| panic!("`{line}` is not name==version"));
            assert!(!name.is_empty() && version.chars().all(|c| c.is_ascii_digit() || c == '.'), "`{line}`");
        }
        assert!(LOCK.contains("highway-env==1.12.1"));
    }

    #[test]
    fn a_missing_or_old_interpreter_says_what_to_install() {
        let err = interpreter_version(Path::new("/nonexistent/python3")).unwrap_err();
        assert!(format!("{err:#}").contains("install Python 3.11 or newer"), "{err:#}");
        // A program that runs but is no Python with venv.
        let err = interpreter_version(Path::new("false")).unwrap_err();
        assert!(format!("{err:#}").contains("cannot create environments"), "{err:#}");
        let dir = std::env::temp_dir().join(format!("rlmflow-old-python-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let old = dir.join("python3");
        fs::write(&old, "#!/bin/sh\necho 3.8.10\n").unwrap();
        fs::set_permissions(&old, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
        let err = interpreter_version(&old).unwrap_err();
        assert!(format!("{err:#}").contains("is Python 3.8.10, too old"), "{err:#}");
    }
}
