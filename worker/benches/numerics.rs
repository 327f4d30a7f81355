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

use std::process::Command;
use std::time::Instant;

use rlmflow_cache::Digest;
use rlmflow_nn::clip::{Clip, images_from_u8, logits};
use rlmflow_nn::loss::{Distance, soft_clip_loss, soft_targets};
use rlmflow_nn::optim::AdamW;
use rlmflow_nn::tch::{self, Kind, Tensor, nn};
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
    let (p, n) = (median(portable), median(native));
    println!("laptop step, batch 128, 2 threads: portable {p:.1} ms, native {n:.1} ms; portable / native {:.3} (medians of {ROUNDS} alternating rounds)", p / n);
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
    tch::manual_seed(0);
    let settings = ClipSettings { encoder: "conv-tiny".into(), text: "tiny".into(), ..ClipSettings::default() };
    let config = model_config(&settings, 64, 256, 2048, 1).expect("a valid config");
    let batch = 128;
    let vs = nn::VarStore::new(tch::Device::Cpu);
    let model = Clip::new(&vs.root(), &config, 0.07, false);
    let mut opt = AdamW::new(&vs, (0.9, 0.98), 1e-8, 0.05);
    let side = config.vision.image;
    let text = config.text.as_ref().expect("a text tower");
    let pixels: Vec<u8> = (0..batch * side * side).map(|i| (i * 2_654_435_761 % 251) as u8).collect();
    let images = images_from_u8(&pixels, batch, side, tch::Device::Cpu);
    let tokens = Tensor::randint_low(3, text.vocab, [batch, text.context], (Kind::Int64, tch::Device::Cpu));
    let _ = tokens.narrow(1, text.context / 2, 1).fill_(text.end_token);
    let counts = Tensor::randint(3, [batch, 48], (Kind::Float, tch::Device::Cpu));
    let mut times = Vec::new();
    for _ in 0..STEPS + 2 {
        let t0 = Instant::now();
        let image = model.encode_image(&images, true).embedding;
        let l = logits(&image, &model.encode_text(&tokens), &model.scale());
        let loss = soft_clip_loss(&l, &soft_targets(&counts, 4.0, Distance::Raw));
        let grads = opt.gradients(&loss);
        AdamW::clip_grad_norm(&grads, 1.0);
        opt.step(&grads, 1e-4);
        times.push(t0.elapsed().as_secs_f64() * 1000.0);
    }
    let mut variables: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    variables.sort_by(|a, b| a.0.cmp(&b.0));
    let mut bytes = Vec::new();
    for (_, tensor) in variables {
        let values = Vec::<f32>::try_from(tensor.flatten(0, -1)).expect("float weights");
        bytes.extend(values.iter().flat_map(|v| v.to_le_bytes()));
    }
    println!("{:.3} {}", median(times.split_off(2)), Digest::of(&bytes));
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}
