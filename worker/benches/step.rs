//! Training-step time on CPU of the laptop model (`conv-tiny` radar tower and `tiny` text tower,
//! 64 px, batch 128) and of the paper's (`vit-b16` and `paper` text, 224 px, context 400, a small
//! batch: a CPU is no A100), SG-CLIP loss, clipping and AdamW, with 2 threads; and the same model
//! and step in PyTorch (`step_reference.py`) in the same command, with the ratio (target <= 1.05).
//!
//! The reference needs an interpreter with torch 2.11 (`import torch`, the full install): point
//! `RLMFLOW_TORCH_PYTHON` at it. Without it only rlmflow's times are printed. CI never runs this.
//!
//! ```sh
//! RLMFLOW_TORCH_PYTHON=/path/to/venv/bin/python cargo xtask bench -p rlmflow-torch --bench step
//! ```

#[path = "support/step.rs"]
mod step;

use rlmflow_nn::tch;
use rlmflow_pretrain::{ClipSettings, model_config};

const THREADS: i32 = 2;
const ROUNDS: usize = 3;

fn main() {
    tch::set_num_threads(THREADS);
    let cases = [
        ("laptop: conv-tiny + tiny text, 64 px", "conv-tiny", "tiny", 64, 256, 128, 10),
        ("paper: vit-b16 + paper text, 224 px", "vit-b16", "paper", 224, 400, 4, 3),
    ];
    let python = std::env::var_os("RLMFLOW_TORCH_PYTHON");
    for (name, encoder, text, image, context, batch, steps) in cases {
        let settings = ClipSettings { encoder: encoder.into(), text: text.into(), ..ClipSettings::default() };
        let config = model_config(&settings, image, context, 2048, 1).expect("a valid config");
        // Rounds alternate between the two, so a drift in the machine's speed hits both alike.
        let (mut ours, mut theirs) = (Vec::new(), Vec::new());
        for _ in 0..ROUNDS {
            ours.push(step::train(&config, batch, steps).0);
            if let Some(python) = &python {
                let script = concat!(env!("CARGO_MANIFEST_DIR"), "/benches/step_reference.py");
                let out = std::process::Command::new(python)
                    .args([script, &serde_json::to_string(&config).unwrap(), &batch.to_string(), &steps.to_string(), &THREADS.to_string()])
                    .output()
                    .expect("running the PyTorch reference");
                assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
                theirs.push(String::from_utf8_lossy(&out.stdout).trim().parse::<f64>().expect("milliseconds"));
            }
        }
        let ours = step::median(ours);
        print!("{name}, batch {batch}: rlmflow {ours:.1} ms/step ({:.0} samples/s)", batch as f64 / ours * 1000.0);
        match theirs.is_empty() {
            false => {
                let theirs = step::median(theirs);
                println!("; PyTorch {theirs:.1} ms/step; ratio {:.3} (target <= 1.05; medians of {ROUNDS} alternating rounds)", ours / theirs);
            }
            true => println!("; set RLMFLOW_TORCH_PYTHON to an interpreter with torch 2.11 for the PyTorch reference"),
        }
    }
}
