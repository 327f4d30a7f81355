//! With `embed`: link libpython by rpath, and record the build interpreter (path, version,
//! base prefix) for the managed environment and `PYTHONHOME`.

fn main() {
    #[cfg(feature = "embed")]
    embed();
}

#[cfg(feature = "embed")]
fn embed() {
    pyo3_build_config::add_libpython_rpath_link_args();
    let config = pyo3_build_config::get();
    let python = config.executable().map(str::to_string).expect("pyo3 found no Python interpreter; set PYO3_PYTHON to one (3.11 or newer)");
    let out = std::process::Command::new(&python)
        .args(["-c", "import sys; print(sys.base_prefix)"])
        .output()
        .unwrap_or_else(|e| panic!("cannot run {python}: {e}"));
    assert!(out.status.success(), "{python} failed to report its base prefix");
    let home = String::from_utf8(out.stdout).expect("UTF-8 prefix").trim().to_string();
    println!("cargo:rustc-env=RLMFLOW_BUILD_PYTHON={python}");
    println!("cargo:rustc-env=RLMFLOW_BUILD_PYTHON_HOME={home}");
    println!("cargo:rustc-env=RLMFLOW_BUILD_PYTHON_VERSION={}.{}", config.version().major, config.version().minor);
    println!("cargo:rerun-if-env-changed=PYO3_PYTHON");
}
