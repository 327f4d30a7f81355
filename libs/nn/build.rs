fn main() {
    rlmflow_libtorch::link();
    // libtorch settings tch does not expose (`src/libtorch.rs`) and the portable numerics' matrix
    // products, compiled against the same libtorch headers torch-sys builds with; optimised in
    // every profile (the chain kernels do a model's matrix work).
    println!("cargo:rerun-if-changed=cpp/torch_settings.cpp");
    println!("cargo:rerun-if-changed=cpp/chain_gemm.cpp");
    println!("cargo:rerun-if-changed=cpp/guarded.h");
    let libtorch = std::path::PathBuf::from(std::env::var_os("LIBTORCH").expect("rlmflow-libtorch's build script checked LIBTORCH"));
    // For the test that this process runs with the libtorch it was built against.
    println!("cargo:rustc-env=RLMFLOW_LIBTORCH={}", libtorch.display());
    let mut build = cc::Build::new();
    // ATen's `parallel_for` is inline OpenMP: compiled without it, the chain GEMM would run on one
    // thread. It must be libtorch's own OpenMP runtime (the wheel's `lib/libgomp.so.1`), so a
    // process has one thread pool.
    let gomp = libtorch.join("lib/libgomp.so.1");
    if gomp.exists() {
        build.flag("-fopenmp");
        println!("cargo:rustc-link-search=native={}", libtorch.join("lib").display());
        println!("cargo:rustc-link-lib=dylib:+verbatim=libgomp.so.1");
    }
    build
        .cpp(true)
        .std("c++17")
        .file("cpp/torch_settings.cpp")
        .file("cpp/chain_gemm.cpp")
        .opt_level(2)
        // libtorch's headers as system headers: their own warnings are libtorch's, ours fail the
        // build (`-Wall -Wextra -Werror` on the two files).
        .flag("-isystem")
        .flag(libtorch.join("include").to_str().expect("a UTF-8 LIBTORCH path"))
        .flag("-isystem")
        .flag(libtorch.join("include/torch/csrc/api/include").to_str().expect("a UTF-8 LIBTORCH path"))
        .define("_GLIBCXX_USE_CXX11_ABI", "1")
        .warnings(true)
        .extra_warnings(true)
        .warnings_into_errors(true)
        .compile("rlmflow_torch_settings");
}
