//! What the kernel pins cost and what they change, on the laptop model's training step (as the
//! `step` benchmark: `conv-tiny` radar tower, `tiny` text tower, 64 px, batch 128, SG-CLIP,
//! clipping, AdamW, 2 threads). Each measurement is a fresh process of this benchmark under one
//! kernel environment (libtorch reads its kernel choices once per process):
//!
//! - `portable` and `native`, as a model action runs with `numerics = "portable"` (the default)
//!   or `"native"`, alternating over rounds; the ratio of their medians is the pins' cost;
//! - nothing pinned, with one caller variable at a time asking for other kernels: where the
//!   weights' digest differs from the unpinned one, that library's choice changes the bytes, and
//!   its pin is needed.
//!
//! ```sh
//! cargo xtask bench -p rlmflow-torch --bench numerics
//! ```

#[path = "support/step.rs"]
mod step;

use std::process::Command;

use rlmflow_cache::Digest;
use rlmflow_nn::tch::{self, Tensor};
use rlmflow_pretrain::{ClipSettings, model_config};
use rlmflow_stages::numerics::{Cpu, KERNEL_VARIABLES, Numerics, Target, apply, other_kernels};

const CHILD: &str = "RLMFLOW_NUMERICS_BENCH_CHILD";
const ROUNDS: usize = 3;
const STEPS: usize = 8;

fn main() {
    match std::env::var(CHILD).as_deref() {
        Ok(mode) => child(mode),
        Err(_) => parent(),
    }
}

fn parent() {
    let cpu = Cpu::detect();
    println!("CPU: {} ({})", cpu.model, cpu.extensions.join(" "));
    let (mut portable, mut native) = (Vec::new(), Vec::new());
    let mut digests = Vec::new();
    for _ in 0..ROUNDS {
        let (ms, digest) = measure("portable", &[]);
        portable.push(ms);
        digests.push(("portable", digest));
        let (ms, digest) = measure("native", &[]);
        native.push(ms);
        digests.push(("native", digest));
    }
    let (p, n) = (step::median(portable), step::median(native));
    println!(
        "laptop step, batch 128, 2 threads: portable {p:.1} ms, native {n:.1} ms; portable / native {:.3} (medians of {ROUNDS} alternating rounds)",
        p / n
    );
    for mode in ["portable", "native"] {
        let mine: Vec<&Digest> = digests.iter().filter(|(m, _)| *m == mode).map(|(_, d)| d).collect();
        let same = mine.windows(2).all(|w| w[0] == w[1]);
        println!("  {mode}: weights {} in every round: {}", mine[0].short(), if same { "same bytes" } else { "DIFFERENT BYTES" });
    }
    let (_, unpinned) = measure("unpinned", &[]);
    println!("nothing pinned: weights {}", unpinned.short());
    for (var, value) in other_kernels(&cpu) {
        let (_, digest) = measure("unpinned", &[(var, value)]);
        let verdict = if digest == unpinned { "same bytes" } else { "other bytes: its pin is needed" };
        println!("  nothing pinned, {var}={value}: weights {} ({verdict})", digest.short());
    }
}

/// Runs one child under `mode` with `env` added; its ms/step and the trained weights' digest.
fn measure(mode: &str, env: &[(&str, &str)]) -> (f64, Digest) {
    let exe = std::env::current_exe().expect("this benchmark's path");
    let mut command = Command::new(exe);
    command.env(CHILD, mode).envs(env.iter().copied());
    for var in KERNEL_VARIABLES.iter().filter(|v| !env.iter().any(|(k, _)| k == *v)) {
        command.env_remove(var);
    }
    let out = command.output().expect("running a measurement");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8_lossy(&out.stdout);
    let (ms, digest) = text.trim().split_once(' ').expect("`ms digest`");
    (ms.parse().expect("milliseconds"), digest.parse().expect("a digest"))
}

/// One measurement: the kernel choices of `mode`, then the steps; prints `ms digest`.
fn child(mode: &str) {
    let cpu = Cpu::detect();
    match mode {
        "portable" => apply(Numerics::Portable, &cpu, Target::Cpu),
        "native" => apply(Numerics::Native, &cpu, Target::Cpu),
        _ => {}
    }
    tch::set_num_threads(2);
    let settings = ClipSettings { encoder: "conv-tiny".into(), text: "tiny".into(), ..ClipSettings::default() };
    let config = model_config(&settings, 64, 256, 2048, 1).expect("a valid config");
    let (ms, vs) = step::train(&config, 128, STEPS);
    let mut variables: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    variables.sort_by(|a, b| a.0.cmp(&b.0));
    let mut bytes = Vec::new();
    for (_, tensor) in variables {
        let values = Vec::<f32>::try_from(tensor.flatten(0, -1)).expect("float weights");
        bytes.extend(values.iter().flat_map(|v| v.to_le_bytes()));
    }
    println!("{ms:.3} {}", Digest::of(&bytes));
}
