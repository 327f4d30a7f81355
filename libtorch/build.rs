//! Stops a build without libtorch in one line that names the command to run. Crates that link
//! libtorch take this crate as a build-dependency; it has no dependencies, so its check runs
//! long before torch-sys's build script (which waits for its own dependencies) could fail with
//! a generic message.

fn main() {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    let ready = std::env::var_os("LIBTORCH").is_some_and(|dir| std::path::Path::new(&dir).join("lib/libtorch_cpu.so").is_file());
    if !ready {
        eprintln!(
            "error: libtorch is not set up: use `cargo xtask build` / `cargo xtask test` / `cargo xtask run pipeline.toml`, which install torch 2.11.0 and set LIBTORCH (or set LIBTORCH to a torch 2.11 yourself)"
        );
        std::process::exit(1);
    }
}
