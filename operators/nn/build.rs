fn main() {
    rlmflow_libtorch::link();
    // libtorch settings tch does not expose (`src/settings.rs`), compiled against the same
    // libtorch headers torch-sys builds with.
    println!("cargo:rerun-if-changed=cpp/torch_settings.cpp");
    let libtorch = std::path::PathBuf::from(std::env::var_os("LIBTORCH").expect("rlmflow-libtorch's build script checked LIBTORCH"));
    // For the test that this process runs with the libtorch it was built against.
    println!("cargo:rustc-env=RLMFLOW_LIBTORCH={}", libtorch.display());
    cc::Build::new()
        .cpp(true)
        .std("c++17")
        .file("cpp/torch_settings.cpp")
        .include(libtorch.join("include"))
        .include(libtorch.join("include/torch/csrc/api/include"))
        .define("_GLIBCXX_USE_CXX11_ABI", "1")
        .warnings(false)
        .compile("rlmflow_torch_settings");
}
