//! Python packages from PyPI for tests, in scratch environments of their own (never the
//! product's): installed the first time a test needs them, reused after.

use std::path::PathBuf;
use std::process::Command;

/// The venv `name` in the system's temporary directory, with `packages` installed unless every
/// one of `executables` is in its `bin/` already. `RLMFLOW_TEST_PYTHON` names the interpreter
/// (default `python3`).
pub fn scratch_venv(name: &str, executables: &[&str], packages: &[&str]) -> PathBuf {
    let env = std::env::temp_dir().join(name);
    if !executables.iter().all(|exe| env.join("bin").join(exe).exists()) {
        let python = std::env::var("RLMFLOW_TEST_PYTHON").unwrap_or_else(|_| "python3".into());
        let ok = Command::new(&python).args(["-m", "venv", env.to_str().unwrap()]).status().unwrap().success();
        assert!(ok, "creating a venv with {python}");
        let pip = Command::new(env.join("bin/pip")).args(["install", "--quiet", "--disable-pip-version-check"]).args(packages).status().unwrap();
        assert!(pip.success(), "installing {} from PyPI", packages.join(", "));
    }
    env
}
