//! The embedded interpreter (pyo3): libpython is found through an rpath set at build time,
//! `PYTHONHOME` is pinned to the build interpreter (unless the user set it) so the embedded
//! interpreter never mixes standard libraries, and the managed environment's site-packages is
//! put first on `sys.path` (an embedded interpreter ignores venvs).

use std::ffi::CString;
use std::sync::OnceLock;

use anyhow::Context as _;
use pyo3::prelude::*;
use pyo3::types::PyModule;

use crate::Environment;

pub use pyo3;

/// Pins `PYTHONHOME` for the embedded interpreter. Call first thing in `main`, before any
/// thread starts.
pub fn pin_home() {
    if std::env::var_os("PYTHONHOME").is_none() {
        // SAFETY: called at the start of `main`, while the process has one thread.
        unsafe { std::env::set_var("PYTHONHOME", env!("RLMFLOW_BUILD_PYTHON_HOME")) };
    }
}

/// Starts the interpreter (once per process) with `env`'s packages importable.
pub fn start(env: &Environment) -> anyhow::Result<()> {
    static STARTED: OnceLock<Result<(), String>> = OnceLock::new();
    STARTED
        .get_or_init(|| {
            Python::initialize();
            Python::attach(|py| -> PyResult<()> {
                let path = py.import("sys")?.getattr("path")?;
                path.call_method1("insert", (0, env.site_packages.to_string_lossy().as_ref()))?;
                Ok(())
            })
            .map_err(|e| format!("starting the embedded Python: {e}"))
        })
        .clone()
        .map_err(anyhow::Error::msg)
}

/// Loads Python source compiled into the binary as a module named `name`.
pub fn module<'py>(py: Python<'py>, name: &str, source: &str) -> anyhow::Result<Bound<'py, PyModule>> {
    let code = CString::new(source).context("module source contains a NUL byte")?;
    let file = CString::new(format!("<rlmflow:{name}>"))?;
    let name = CString::new(name)?;
    PyModule::from_code(py, &code, &file, &name).map_err(|e| anyhow::anyhow!("loading the embedded module: {}", traceback(py, &e)))
}

/// A Python exception with its traceback, as text.
pub fn traceback(py: Python<'_>, err: &PyErr) -> String {
    let trace = err.traceback(py).and_then(|t| t.format().ok()).unwrap_or_default();
    format!("{trace}{err}")
}
