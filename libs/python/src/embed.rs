//! The embedded interpreter (pyo3): libpython is found through an rpath set at build time,
//! `PYTHONHOME` is pinned to the build interpreter (unless the user set it) so the embedded
//! interpreter never mixes standard libraries, and the managed environment's site-packages is
//! put first on `sys.path` (an embedded interpreter ignores venvs), and numpy's kernels are
//! pinned ([`numpy_kernels`]) before anything imports it.

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

/// numpy's kernels pinned, as environment variables it reads when first imported, so that
/// highway-env's drives (computed with numpy) are the same bytes under one key on every x86-64
/// machine of a tier:
///
/// - its own CPU dispatch to its baseline (x86-64-v2) loops: numpy 2.4 picks AVX2 (`X86_V3`) or
///   AVX-512 (`X86_V4`, `AVX512_ICL`, `AVX512_SPR`) loops at import, and those round
///   differently. The names are numpy's own for the version the lock pins: it ignores unknown
///   ones with a warning only (`AVX512F` no longer disables anything).
/// - the kernels of the OpenBLAS it bundles, which picks them by the CPU (SkylakeX on an AVX-512
///   machine, Haswell on an AVX2 one) and whose dot products round differently: Haswell's
///   wherever the CPU has AVX2 and FMA, else Nehalem's (numpy's baseline needs SSE4.2 anyway).
///   Found by running highway-env under QEMU as an AVX2 CPU on an AVX-512 one: with numpy's
///   loops pinned, the roundabout and merge scenarios still parted until this was pinned too.
///
/// On other architectures nothing is pinned.
pub fn numpy_kernels() -> Vec<(&'static str, &'static str)> {
    #[cfg(target_arch = "x86_64")]
    {
        let v3 = std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma");
        vec![("NPY_DISABLE_CPU_FEATURES", "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"), ("OPENBLAS_CORETYPE", if v3 { "Haswell" } else { "Nehalem" })]
    }
    #[cfg(not(target_arch = "x86_64"))]
    Vec::new()
}

/// Starts the interpreter (once per process) with `env`'s packages importable.
pub fn start(env: &Environment) -> anyhow::Result<()> {
    static STARTED: OnceLock<Result<(), String>> = OnceLock::new();
    STARTED
        .get_or_init(|| {
            Python::initialize();
            Python::attach(|py| -> PyResult<()> {
                for (variable, value) in numpy_kernels() {
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

    /// numpy's AVX2 and AVX-512 loops are off in the embedded interpreter, and its OpenBLAS
    /// computes with Haswell's kernels (on an AVX2 machine), whatever the caller asked (this
    /// test's process asks for every loop and for Sandybridge's BLAS kernels): on an AVX2 machine
    /// `X86_V3` would be on without the pin, on an AVX-512 one `X86_V4` too, and the BLAS core
    /// would be the caller's.
    #[test]
    #[cfg(target_arch = "x86_64")]
    fn numpy_computes_with_its_baseline_kernels_whatever_the_caller_asks() {
        // SAFETY: before the interpreter starts; this test binary's other tests read no environment.
        unsafe {
            std::env::set_var("NPY_DISABLE_CPU_FEATURES", "");
            std::env::set_var("OPENBLAS_CORETYPE", "Sandybridge");
        }
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
        // The bundled OpenBLAS's core, as it reports it.
        let core: String = Python::attach(|py| -> PyResult<String> {
            let source = c"import ctypes, glob, os, numpy\nlib = ctypes.CDLL(glob.glob(os.path.join(os.path.dirname(numpy.__file__) + '.libs', 'libscipy_openblas*'))[0])\nlib.scipy_openblas_get_corename64_.restype = ctypes.c_char_p\ncore = lib.scipy_openblas_get_corename64_().decode()\n";
            let globals = pyo3::types::PyDict::new(py);
            py.run(source, Some(&globals), None)?;
            globals.get_item("core")?.expect("core").extract()
        })
        .unwrap();
        let v3 = std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma");
        assert_eq!(core.to_lowercase(), if v3 { "haswell" } else { "nehalem" }, "OpenBLAS's kernels");
    }
}
