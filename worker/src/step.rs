//! `rlmflow-torch step`: times the training step of the laptop model (`conv-tiny` radar tower,
//! `tiny` text tower, 64 px) or the paper's (`vit-b16` and `paper` text, 224 px, context 400):
//! CLIP's two towers on synthetic data (fixed pixels, seeded tokens and counts), SG-CLIP loss,
//! clipping and AdamW, on a device and in an arithmetic (the towers and loss inside
//! `Placement::forward`, as `fit` runs a batch). One measurement per process, so the `step` and
//! `numerics` benchmarks and `xtask/device-check.py` set each side against PyTorch's
//! (`benches/step_reference.py`, which reads the model config `--config` prints) in processes
//! that never share memory or kernel choices.

use std::process::ExitCode;
use std::time::Instant;

use clap::{Args, FromArgMatches as _};
use rlmflow_engine::cli::ExtraCommand;
use rlmflow_nn::clip::{Clip, images_from_u8, logits};
use rlmflow_nn::loss::{Distance, soft_clip_loss, soft_targets};
use rlmflow_nn::optim::AdamW;
use rlmflow_nn::tch::{self, Kind, Tensor, nn};
use rlmflow_nn::train::{Placement, named_variables};
use rlmflow_pretrain::{ClipSettings, model_config};
use rlmflow_stages::Training;
use rlmflow_stages::encoder::ModelConfig;
use rlmflow_stages::numerics::{self, Cpu, Numerics, Precision, Target};

/// Time the paper's (or the laptop model's) training step: prints the median milliseconds of a
/// step (and with --digest the trained weights' BLAKE3), for the benchmarks.
#[derive(Args)]
struct Step {
    /// `laptop` or `paper`.
    #[arg(long, default_value = "laptop")]
    model: String,
    #[arg(long, default_value_t = 128)]
    batch: i64,
    /// Timed steps, after two warm-up steps.
    #[arg(long, default_value_t = 10)]
    steps: usize,
    #[arg(long, default_value_t = 2)]
    threads: i32,
    /// `cpu` or `cuda`.
    #[arg(long, default_value = "cpu")]
    device: String,
    /// `fp32`, `tf32` (CUDA) or `bf16`.
    #[arg(long, default_value = "fp32")]
    precision: String,
    /// The kernel pins a model action runs with: `portable`, `native`, or `unpinned` (the
    /// caller's environment as it is).
    #[arg(long, default_value = "unpinned")]
    numerics: String,
    /// Print the trained weights' digest after the milliseconds.
    #[arg(long)]
    digest: bool,
    /// Print the model config as JSON (what the PyTorch reference reads) and stop.
    #[arg(long)]
    config: bool,
}

pub fn command() -> ExtraCommand {
    ExtraCommand { command: Step::augment_args(clap::Command::new("step")), run: |args| run(Step::from_arg_matches(args)?) }
}

/// The model config of `model` (`laptop` or `paper`).
fn config(model: &str) -> anyhow::Result<ModelConfig> {
    let (encoder, text, image, context) = match model {
        "laptop" => ("conv-tiny", "tiny", 64, 256),
        "paper" => ("vit-b16", "paper", 224, 400),
        other => anyhow::bail!("--model {other}: laptop or paper"),
    };
    let settings = ClipSettings { encoder: encoder.into(), text: text.into(), ..ClipSettings::default() };
    Ok(model_config(&settings, image, context, 2048, 1)?)
}

fn run(args: Step) -> anyhow::Result<ExitCode> {
    let config = config(&args.model)?;
    if args.config {
        println!("{}", serde_json::to_string(&config)?);
        return Ok(ExitCode::SUCCESS);
    }
    let target = match args.device.as_str() {
        "cpu" => Target::Cpu,
        "cuda" => Target::Cuda(0),
        other => anyhow::bail!("--device {other}: cpu or cuda"),
    };
    match args.numerics.as_str() {
        "portable" => numerics::apply(Numerics::Portable, &Cpu::detect(), target),
        "native" => numerics::apply(Numerics::Native, &Cpu::detect(), target),
        "unpinned" => {}
        other => anyhow::bail!("--numerics {other}: portable, native or unpinned"),
    }
    let precision: Precision = serde_json::from_value(serde_json::json!(args.precision))
        .map_err(|_| anyhow::anyhow!("--precision {}: fp32, tf32 or bf16", args.precision))?;
    tch::set_num_threads(args.threads);
    // The placement a training stage of these settings gets: CUDA's deterministic mode, TF32 as asked.
    let placement = Placement::of(&Training { device: target.device(), precision, ..Training::default() }, rlmflow_stages::Device::Cpu)?;
    let (ms, vs) = train(&config, args.batch, args.steps, placement);
    match args.digest {
        true => {
            let mut hasher = blake3::Hasher::new();
            for (_, tensor) in named_variables(&vs) {
                for value in Vec::<f32>::try_from(tensor.to_device(tch::Device::Cpu).flatten(0, -1))? {
                    hasher.update(&value.to_le_bytes());
                }
            }
            println!("{ms:.3} {}", hasher.finalize().to_hex());
        }
        false => println!("{ms:.3}"),
    }
    Ok(ExitCode::SUCCESS)
}

/// Runs `steps` training steps (after two warm-up steps) of a freshly seeded model of `config`
/// at `batch`: the median milliseconds of a step (the device synchronised), and the trained
/// weights.
fn train(config: &ModelConfig, batch: i64, steps: usize, placement: Placement) -> (f64, nn::VarStore) {
    let device = placement.device;
    tch::manual_seed(0);
    let vs = nn::VarStore::new(device);
    let model = Clip::new(&vs.root(), config, 0.07, false);
    let mut opt = AdamW::new(&vs, (0.9, 0.98), 1e-8, 0.05);
    let side = config.vision.image;
    let text = config.text.as_ref().expect("a text tower");
    let pixels: Vec<u8> = (0..batch * side * side).map(|i| (i * 2_654_435_761 % 251) as u8).collect();
    let images = images_from_u8(&pixels, batch, side, device);
    let tokens = Tensor::randint_low(3, text.vocab, [batch, text.context], (Kind::Int64, device));
    let _ = tokens.narrow(1, text.context / 2, 1).fill_(text.end_token);
    let counts = Tensor::randint(3, [batch, 48], (Kind::Float, device));
    let sync = || {
        if let tch::Device::Cuda(n) = device {
            tch::Cuda::synchronize(n as i64);
        }
    };
    let mut times = Vec::new();
    for _ in 0..steps + 2 {
        sync();
        let t0 = Instant::now();
        let grads = placement
            .forward(|| {
                let image = model.encode_image(&images, true).embedding;
                let l = logits(&image, &model.encode_text(&tokens), &model.scale());
                opt.gradients(&soft_clip_loss(&l, &soft_targets(&counts, 4.0, Distance::Raw)))
            })
            .expect("autocast");
        opt.clip_grad_norm(&grads, 1.0).expect("clipping");
        opt.step(&grads, 1e-4).expect("an AdamW step");
        sync();
        times.push(t0.elapsed().as_secs_f64() * 1000.0);
    }
    let mut timed = times.split_off(2);
    timed.sort_by(f64::total_cmp);
    (timed[timed.len() / 2], vs)
}
