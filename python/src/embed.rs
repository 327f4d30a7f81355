//! The embedded interpreter (pyo3): libpython is found through an rpath set at build time,
//! `PYTHONHOME` is pinned to the build interpreter (unless the user set it) so the embedded
//! interpreter never mixes standard libraries, and the managed environment's site-packages is
//! put first on `sys.path` (an embedded interpreter ignores venvs), and numpy's kernels are
//! pinned ([`NUMPY_KERNELS`]) before anything imports it.

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

/// numpy's CPU dispatch pinned to its baseline (x86-64-v2) kernels on every x86-64 machine.
/// numpy 2.4 picks AVX2 (`X86_V3`) or AVX-512 (`X86_V4`, `AVX512_ICL`, `AVX512_SPR`) loops at
/// import, and those round differently from each other, so highway-env's drives, computed with
/// numpy, would differ between CPUs under one key. The names are numpy's own for the version
/// the lock pins: it ignores unknown ones with a warning only (`AVX512F` no longer disables
/// anything). On other architectures numpy's dispatch is left as it is.
pub const NUMPY_KERNELS: Option<(&str, &str)> =
    if cfg!(target_arch = "x86_64") { Some(("NPY_DISABLE_CPU_FEATURES", "X86_V3 X86_V4 AVX512_ICL AVX512_SPR")) } else { None };

/// Starts the interpreter (once per process) with `env`'s packages importable.
pub fn start(env: &Environment) -> anyhow::Result<()> {
    static STARTED: OnceLock<Result<(), String>> = OnceLock::new();
    STARTED
        .get_or_init(|| {
            Python::initialize();
            Python::attach(|py| -> PyResult<()> {
                if let Some((variable, value)) = NUMPY_KERNELS {
                    // Whatever the caller's environment says; numpy reads it when first imported.
                    py.import("os")?.getattr("environ")?.set_item(variable, value)?;
                }
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

#[cfg(test)]
mod tests {
    use super::*;

    /// numpy's AVX2 and AVX-512 loops are off in the embedded interpreter, whatever the caller
    /// asked (this test's process asks for every loop): on an AVX2 machine `X86_V3` would be on
    /// without the pin, on an AVX-512 one `X86_V4` too.
    #[test]
    #[cfg(target_arch = "x86_64")]
    fn numpy_computes_with_its_baseline_kernels_whatever_the_caller_asks() {
        // SAFETY: before the interpreter starts; this test binary's other tests read no environment.
        unsafe { std::env::set_var("NPY_DISABLE_CPU_FEATURES", "") };
        pin_home();
        let env = crate::ensure(&mut |_| {}).unwrap();
        start(&env).unwrap();
        let on: Vec<String> = Python::attach(|py| -> PyResult<Vec<String>> {
            let features = py.import("numpy._core._multiarray_umath")?.getattr("__cpu_features__")?;
            let mut on = Vec::new();
            for name in ["X86_V2", "X86_V3", "X86_V4", "AVX512_ICL", "AVX512_SPR"] {
                if features.get_item(name)?.extract::<bool>()? {
                    on.push(name.to_owned());
                }
            }
            Ok(on)
        })
        .unwrap();
        assert_eq!(on, ["X86_V2"], "numpy's dispatched loops beyond its baseline");
    }
}
