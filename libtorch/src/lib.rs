//! For the build scripts of crates that link libtorch: [`link`] records libtorch's library
//! directory as the run path of their binaries and tests, so they find libtorch without a library
//! path set. (`LD_LIBRARY_PATH` still wins over it: on a machine with its own torch 2.11, point it
//! there.) This crate's own build script stops a build that has no libtorch (see `build.rs`).

/// Prints the cargo instructions; call from `build.rs`.
pub fn link() {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    if let Some(dir) = std::env::var_os("LIBTORCH") {
        let lib = std::path::Path::new(&dir).join("lib");
        println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
    }
}
