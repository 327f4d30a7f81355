//! Training-step time of the laptop model (`conv-tiny` radar tower and `tiny` text tower, 64 px)
//! and of the paper's (`vit-b16` and `paper` text, 224 px, context 400), SG-CLIP loss, clipping
//! and AdamW: `rlmflow-torch step` against the same model and step in PyTorch
//! (`step_reference.py`), each measurement in its own process, rounds alternating, with the
//! ratios (target: time ratio <= 1.05 in fp32; for bf16, rlmflow's samples/s at least PyTorch's
//! autocast, ratio >= 1.0).
//!
//! The reference needs an interpreter with torch 2.11 (`import torch`, the full install): point
//! `RLMFLOW_TORCH_PYTHON` at it. Without it only rlmflow's times are printed. CI never runs this.
//!
//! ```sh
//! RLMFLOW_TORCH_PYTHON=/path/to/venv/bin/python cargo xtask bench -p rlmflow-torch --bench step
//! # fp32 against bf16 autocast on this CPU:
//! cargo xtask bench -p rlmflow-torch --bench step -- --model laptop --precision fp32,bf16
//! ```
//!
//! Options: `--device cpu|cuda` (default cpu), `--precision` (a list of fp32, tf32, bf16; default
//! fp32), `--model laptop|paper` (default both), `--batch N,..` (default 128 for the laptop
//! model, 4 for the paper's), `--steps N`, `--rounds N` (3), `--threads N` (2).

use std::collections::BTreeMap;
use std::process::Command;

const WORKER: &str = env!("CARGO_BIN_EXE_rlmflow-torch");

fn options() -> BTreeMap<String, String> {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| a != "--bench").collect();
    args.chunks(2).filter_map(|pair| Some((pair[0].strip_prefix("--")?.to_owned(), pair.get(1)?.clone()))).collect()
}

/// Runs one measurement process; its milliseconds per step.
fn measure(command: &mut Command) -> f64 {
    let out = command.output().expect("running a measurement");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8_lossy(&out.stdout).trim().parse::<f64>().expect("milliseconds")
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

fn main() {
    let opts = options();
    let get = |key: &str, default: &str| opts.get(key).cloned().unwrap_or_else(|| default.to_owned());
    let (device, threads) = (get("device", "cpu"), get("threads", "2"));
    let rounds: usize = get("rounds", "3").parse().expect("--rounds");
    let models = opts.get("model").map_or(vec!["laptop".to_owned(), "paper".to_owned()], |m| vec![m.clone()]);
    let python = std::env::var_os("RLMFLOW_TORCH_PYTHON");
    let reference = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/step_reference.py");
    for model in &models {
        let (batches, steps) = if model == "laptop" { ("128", "10") } else { ("4", "3") };
        let config = Command::new(WORKER).args(["step", "--model", model, "--config"]).output().expect("the model config");
        let config = String::from_utf8_lossy(&config.stdout).trim().to_owned();
        for batch in get("batch", batches).split(',') {
            for precision in get("precision", "fp32").split(',') {
                let steps = get("steps", steps);
                // Rounds alternate between the two, so a drift in the machine's speed hits both alike.
                let (mut ours, mut theirs) = (Vec::new(), Vec::new());
                for _ in 0..rounds {
                    let args =
                        ["--model", model, "--batch", batch, "--steps", &steps, "--threads", &threads, "--device", &device, "--precision", precision];
                    ours.push(measure(Command::new(WORKER).arg("step").args(args)));
                    if let Some(python) = &python {
                        theirs.push(measure(Command::new(python).args([reference, &config, batch, &steps, &threads, &device, precision])));
                    }
                }
                let ours = median(ours);
                let batch: f64 = batch.parse().expect("--batch");
                let rate = |ms: f64| batch / ms * 1000.0;
                print!("{model}, {device} {precision}, batch {batch}: rlmflow {ours:.1} ms/step ({:.0} samples/s)", rate(ours));
                match theirs.is_empty() {
                    false => {
                        let theirs = median(theirs);
                        println!(
                            "; PyTorch {theirs:.1} ms/step ({:.0} samples/s); time ratio {:.3}, samples/s ratio {:.3} (medians of {rounds} alternating rounds)",
                            rate(theirs),
                            ours / theirs,
                            theirs / ours
                        );
                    }
                    true => println!("; set RLMFLOW_TORCH_PYTHON to an interpreter with torch 2.11 for the PyTorch reference"),
                }
            }
        }
    }
}
