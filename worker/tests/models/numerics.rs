//! Same key, same bytes whatever kernels the caller asks for: every torch operator's action,
//! stored under the default environment, recomputed in fresh processes whose environment asks
//! libtorch for AVX-512 kernels everywhere (the first attempt of `--check-determinism`, where the
//! chain GEMM runs at the CPU's widest lanes, 16 on an AVX-512 machine) and for other kernels
//! again (its second attempt: older instruction sets, and the chain GEMM at AVX2's 8 lanes),
//! gives the stored bytes. Without the pins the second attempt differs on any AVX2
//! machine: `cargo xtask bench -p rlmflow-torch --bench numerics` shows which variable alone
//! changes the bytes.

use crate::common::rlmflow_exe;

/// Every model stage at the default `numerics` (portable), with an encoder of its own (SG-CLIP,
/// whose soft targets are the longer path), on 300 of the shared data's frames (the bytes, not
/// what is learnt, are under test). The worker tests' one check that model actions give the same
/// bytes in fresh processes.
const MODELS: &str = r#"
[stages.pretrain]
operator = "clip"
objective = "sg-clip"
alpha = 4.0
device = "cpu"
batch = 64
epochs = 1
warmup_epochs = 0.0

[stages.linear]
kind = "probe"
operator = "linear"
lambdas = [1e-2, 1.0]

[stages.clipcap]
kind = "probe"
operator = "clipcap"
device = "cpu"
epochs = 1
warmup_epochs = 0.0
batch = 32

[stages.pup]
kind = "segment"
operator = "pup"
device = "cpu"
epochs = 1
warmup_epochs = 0.0
batch = 32
channels = [16, 8, 8]

[stages.unet]
kind = "segment"
operator = "unet"
device = "cpu"
epochs = 1
warmup_epochs = 0.0
batch = 32
channels = [8, 16, 32]
"#;

/// What a caller asking for AVX-512 kernels everywhere sets.
const AVX512: &[(&str, &str)] = &[("ATEN_CPU_CAPABILITY", "avx512"), ("ONEDNN_MAX_CPU_ISA", "AVX512_CORE"), ("MKL_ENABLE_INSTRUCTIONS", "AVX512")];

#[test]
fn every_model_operator_gives_its_stored_bytes_whatever_kernels_the_caller_asks() {
    let _turn = crate::common::one_at_a_time();
    let dir =
        crate::common::scratch("numerics", &format!("{}{MODELS}", crate::common::data_stages("numerics").replace("frames = 1000", "frames = 300")));
    let (ok, out) = crate::common::rlmflow(&dir, &["run", "p.toml"]);
    assert!(ok, "{out}");
    if !std::arch::is_x86_feature_detected!("avx512f") {
        println!(
            "this machine has no AVX-512: asking for it cannot change libtorch's kernels here; the second attempts (older instruction sets) are what show the pins hold"
        );
    }
    let mut command = std::process::Command::new(rlmflow_exe());
    command.current_dir(&dir).args(["run", "p.toml"]).env_remove("MKL_CBWR").envs(AVX512.iter().copied());
    for stage in ["pretrain", "linear", "clipcap", "pup", "unet"] {
        command.args(["--check-determinism", stage]);
    }
    let out = command.output().unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    assert!(out.status.success(), "{text}");
    for stage in ["pretrain", "linear", "clipcap", "pup", "unet"] {
        assert!(text.contains(&format!("check-determinism {stage} ")), "{stage} was not checked:\n{text}");
    }
    assert_eq!(text.matches("  same bytes").count(), 5, "{text}");
    assert!(text.contains("asking for other kernels: ATEN_CPU_CAPABILITY="), "{text}");
    assert!(!text.contains("stored output"), "an attempt differs from the output stored under the default environment:\n{text}");
}
