//! What the kernel pins cost and what they change, on the laptop model's training step (as the
//! `step` benchmark: `conv-tiny` radar tower, `tiny` text tower, 64 px, batch 128, SG-CLIP,
//! clipping, AdamW, 2 threads). Each measurement is a fresh process of this benchmark under one
//! kernel environment (libtorch reads its kernel choices once per process):
//!
//! - `portable` and `native`, as a model action runs with `numerics = "portable"` (the default)
//!   or `"native"`, alternating over rounds; the ratio of their medians is the pins' cost; and
//!   portable with the chain GEMM held to AVX2's 8 lanes (`RLMFLOW_GEMM_LANES=8`), which must
//!   give the portable weights (on an AVX-512 machine: the other width, the same bytes);
//! - nothing pinned, with one caller variable at a time asking for other kernels: where the
//!   weights' digest differs from the unpinned one, that library's choice changes the bytes, and
//!   its pin is needed.
//!
//! ```sh
//! cargo xtask bench -p rlmflow-torch --bench numerics
//! ```

use std::process::Command;

use rlmflow_stages::numerics::{Cpu, GEMM_LANES_VARIABLE, KERNEL_VARIABLES, other_kernels};

const ROUNDS: usize = 3;
const STEPS: &str = "8";

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn main() {
    let cpu = Cpu::detect();
    println!("CPU: {} ({})", cpu.model, cpu.extensions.join(" "));
    let (mut portable, mut native, mut lanes8) = (Vec::new(), Vec::new(), Vec::new());
    let mut digests = Vec::new();
    for _ in 0..ROUNDS {
        let (ms, digest) = measure("portable", &[]);
        portable.push(ms);
        digests.push(("portable", digest));
        let (ms, digest) = measure("native", &[]);
        native.push(ms);
        digests.push(("native", digest));
        let (ms, digest) = measure("portable", &[(GEMM_LANES_VARIABLE, "8")]);
        lanes8.push(ms);
        digests.push(("portable, chain GEMM at 8 lanes", digest));
    }
    let (p, n, p8) = (median(portable), median(native), median(lanes8));
    println!(
        "laptop step, batch 128, 2 threads: portable {p:.1} ms, native {n:.1} ms; portable / native {:.3} (medians of {ROUNDS} alternating rounds)",
        p / n
    );
    println!("  portable with the chain GEMM at 8 lanes: {p8:.1} ms, {:.3} of native", p8 / n);
    let portable_weights = &digests[0].1;
    for mode in ["portable", "native", "portable, chain GEMM at 8 lanes"] {
        let mine: Vec<&String> = digests.iter().filter(|(m, _)| *m == mode).map(|(_, d)| d).collect();
        let same = mine.windows(2).all(|w| w[0] == w[1]);
        println!("  {mode}: weights {} in every round: {}", mine[0], if same { "same bytes" } else { "DIFFERENT BYTES" });
    }
    let widths_agree = digests.iter().filter(|(m, _)| m.starts_with("portable")).all(|(_, d)| d == portable_weights);
    println!("  portable at the widest and at 8 lanes: {}", if widths_agree { "same bytes" } else { "DIFFERENT BYTES" });
    let (_, unpinned) = measure("unpinned", &[]);
    println!("nothing pinned: weights {}", unpinned);
    for (var, value) in other_kernels() {
        let (_, digest) = measure("unpinned", &[(var, value)]);
        let verdict = if digest == unpinned { "same bytes" } else { "other bytes: its pin is needed" };
        println!("  nothing pinned, {var}={value}: weights {} ({verdict})", digest);
    }
}

/// One `rlmflow-torch step` of the laptop model under `numerics` (`portable`, `native` or
/// `unpinned`) with `env` added to an environment cleared of every kernel variable: its ms/step
/// and the trained weights' digest.
fn measure(numerics: &str, env: &[(&str, &str)]) -> (f64, String) {
    let mut command = Command::new(env!("CARGO_BIN_EXE_rlmflow-torch"));
    command.args(["step", "--model", "laptop", "--batch", "128", "--steps", STEPS, "--numerics", numerics, "--digest"]).envs(env.iter().copied());
    for var in KERNEL_VARIABLES.iter().chain([&GEMM_LANES_VARIABLE]).filter(|v| !env.iter().any(|(k, _)| k == *v)) {
        command.env_remove(var);
    }
    let out = command.output().expect("running a measurement");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    let (ms, digest) = text.trim().split_once(' ').expect("`ms digest`");
    (ms.parse().expect("milliseconds"), digest[..16].to_owned())
}
