//! The `clipcap` caption probe (see `rlmflow_probe`): ClipCap's mapper and a GPT decoder on the
//! frozen encoder's projected CLS embedding, trained with teacher forcing on the training split
//! less a validation slice, then validation and test captions generated, parsed and scored
//! (the validation F1 is what settings are chosen on). Each epoch draws its frame order and captions from (seed,
//! epoch), so a checkpoint needs only the epoch to resume.

use std::path::Path;
use std::time::Instant;

use anyhow::{Context as _, bail};
use rand::RngExt;
use rand::seq::SliceRandom;
use rlmflow_nn::clip::{self, images_from_u8};
use rlmflow_nn::decode::{beam_search, greedy};
use rlmflow_nn::gpt::{Gpt, GptConfig, Mapper, Steps, caption_loss};
use rlmflow_nn::optim::{AdamW, warmup_cosine};
use rlmflow_nn::tch::{self, Tensor, nn};
use rlmflow_nn::train::{epoch_rng, finite, resolve_device, restore_checkpoint, save_checkpoint, write_weights};
use rlmflow_probe::{ClipcapSettings, Decode};
use rlmflow_stages::grid::{CELLS, Grid};
use rlmflow_stages::labels::{Labels, Split};
use rlmflow_stages::probe::{self, Row, Scores, Summary, score};
use rlmflow_stages::scenes::Scenes;
use rlmflow_stages::tokens::{self, Tokens};
use rlmflow_stages::{Context, Operator, OperatorSpec, Outcome, Resources};
use serde_json::{Value, json};
use tokenizers::Tokenizer;

/// Frames per forward pass when embedding, scoring or generating.
const CHUNK: usize = 64;
/// Groups of similar caption length a batch's loss is computed in (see `caption_loss`).
const LENGTH_GROUPS: usize = 4;
/// The captioner's weights in the artifact.
pub const WEIGHTS: &str = "clipcap.safetensors";

pub struct Clipcap;

impl Operator for Clipcap {
    type Settings = ClipcapSettings;

    fn spec(&self) -> OperatorSpec {
        rlmflow_probe::clipcap_spec()
    }

    fn resources(&self, s: &ClipcapSettings) -> Resources {
        rlmflow_probe::clipcap_resources(s)
    }

    fn run(&self, s: &ClipcapSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        run(s, ctx)
    }
}

/// The decoder a preset names.
fn decoder_config(s: &ClipcapSettings, vocab: i64, context: i64) -> GptConfig {
    let (width, layers, heads) = if s.decoder == "gpt2" { (768, 12, 12) } else { (128, 2, 4) };
    GptConfig { vocab, positions: s.prefix + context, width, layers, heads, mlp: 4 * width }
}

/// Each generated caption parsed by the LLM-free parser and scored against the true grid.
pub fn score_captions(captions: &[String], truth: &[[u32; CELLS]]) -> (Vec<Grid>, Scores) {
    let grids: Vec<Grid> = captions.iter().map(|c| rlmflow_parser::parse(c).grid).collect();
    let counts: Vec<[u32; CELLS]> = grids.iter().map(|g| g.counts).collect();
    let scores = score(&counts, truth);
    (grids, scores)
}

struct Data {
    /// Frozen projected CLS embeddings, (frames, embed).
    embeddings: Tensor,
    ids: Vec<i64>,
    context: i64,
    /// Caption rows of each frame.
    captions: Vec<Vec<usize>>,
    /// The training split without its validation slice; the slice; the test split.
    train: Vec<usize>,
    validation: Vec<usize>,
    test: Vec<usize>,
    /// Every frame's counts.
    counts: Vec<[u32; CELLS]>,
    hygiene: Vec<rlmflow_stages::identity::Overlap>,
}

impl Data {
    /// Rows' ids, (rows, context).
    fn batch(&self, rows: &[usize], device: tch::Device) -> Tensor {
        let c = self.context as usize;
        let ids: Vec<i64> = rows.iter().flat_map(|&r| self.ids[r * c..(r + 1) * c].iter().copied()).collect();
        Tensor::from_slice(&ids).view([rows.len() as i64, self.context]).to_device(device)
    }

    fn embedding(&self, frames: &[usize]) -> Tensor {
        let index: Vec<i64> = frames.iter().map(|&f| f as i64).collect();
        self.embeddings.index_select(0, &Tensor::from_slice(&index).to_device(self.embeddings.device()))
    }
}

fn load(s: &ClipcapSettings, ctx: &Context, device: tch::Device) -> anyhow::Result<(Data, Tokens, rlmflow_stages::encoder::ModelConfig)> {
    let scenes = Scenes::open(ctx.input("scenes")?)?;
    let labels = Labels::open(ctx.input("labels")?)?;
    labels.check_scenes(scenes.len())?;
    let hygiene = rlmflow_stages::identity::check_inputs(ctx, &labels.ids(Split::Test), s.allow_test_overlap)?;
    let tokens = Tokens::open(ctx.input("tokens")?)?;
    let dir = ctx.input("encoder")?;
    let side = scenes.summary.images[0].size as i64;
    let (_vs, encoder) = clip::load(dir, device, side)?;
    let frames = scenes.len() as usize;
    let progress = ctx.progress(frames as u64, "frames embedded");
    let mut parts = Vec::new();
    tch::no_grad(|| -> anyhow::Result<()> {
        for start in (0..frames).step_by(CHUNK) {
            let chunk: Vec<u64> = (start as u64..(start + CHUNK).min(frames) as u64).collect();
            let pixels = chunk.iter().map(|&i| scenes.heatmap(i)).collect::<anyhow::Result<Vec<_>>>()?.concat();
            parts.push(encoder.encode_image(&images_from_u8(&pixels, chunk.len() as i64, side, device), false).embedding);
            progress.inc(chunk.len() as u64);
        }
        Ok(())
    })?;
    progress.finish();
    let captions = tokens.rows_by_frame(frames)?;
    let (train, validation) = labels.train_validation(s.validation);
    let frames_of = |labels: Vec<&rlmflow_stages::labels::FrameLabel>| {
        labels.into_iter().map(|f| f.frame as usize).filter(|&f| !captions[f].is_empty()).collect::<Vec<_>>()
    };
    let (train, validation, test) = (frames_of(train), frames_of(validation), frames_of(labels.split(Split::Test).collect()));
    if train.is_empty() || validation.is_empty() || test.is_empty() {
        bail!(
            "{} training, {} validation and {} test frames with captions: the caption probe needs all three (raise `validation` or the frame count)",
            train.len(),
            validation.len(),
            test.len()
        );
    }
    let data = Data {
        embeddings: Tensor::cat(&parts, 0),
        ids: tokens.ids.all_u32().context("reading the token ids")?.into_iter().map(i64::from).collect(),
        context: tokens.summary.context as i64,
        captions,
        train,
        validation,
        test,
        counts: labels.frames.iter().map(|f| f.grid.counts).collect(),
        hygiene,
    };
    Ok((data, tokens, encoder.config))
}

fn run(s: &ClipcapSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    tch::set_num_threads(s.threads as i32);
    let device = resolve_device(&s.device, ctx.device)?;
    let (data, tokens, encoder) = load(s, ctx, device)?;
    let tokenizer_path = ctx.input("tokens")?.join(tokens::TOKENIZER);
    let tokenizer = Tokenizer::from_file(&tokenizer_path).map_err(|e| anyhow::anyhow!("reading {}: {e}", tokenizer_path.display()))?;
    let special = &tokens.summary.special;
    let (start, end, pad) = (i64::from(special.start), i64::from(special.end), i64::from(special.pad));

    tch::manual_seed(ctx.seed as i64);
    let vs = nn::VarStore::new(device);
    let config = decoder_config(s, i64::from(tokens.summary.vocab), data.context);
    let mapper = Mapper::new(&(vs.root() / "mapper"), encoder.embed, config.width, s.prefix, s.mapper_layers, config.heads);
    let gpt = Gpt::new(&(vs.root() / "gpt"), &config);
    if !s.init.is_empty() {
        let loaded = Gpt::load_gpt2(&vs, "gpt.", Path::new(&s.init))?;
        ctx.event("init", json!({"path": s.init, "tensors": loaded}));
    }

    let batch = s.batch as usize;
    let steps_per_epoch = (data.train.len() / batch) as u64;
    if steps_per_epoch == 0 {
        bail!("batch {batch} is larger than the {} training frames; lower `batch`", data.train.len());
    }
    let total = s.epochs * steps_per_epoch;
    let warmup = (s.warmup_epochs * steps_per_epoch as f64).round() as u64;
    let mut opt = AdamW::new(&vs, (0.9, 0.999), 1e-8, s.weight_decay);
    let mut log = restore_checkpoint(&vs, &mut opt, &ctx.checkpoint_dir)?;
    if !log.is_empty() {
        ctx.event("resumed", json!({"epoch": log.len()}));
    }
    let progress = ctx.progress(total, "steps");
    progress.set_position(opt.steps() as u64);
    for epoch in log.len() as u64..s.epochs {
        let clock = Instant::now();
        let mut rng = epoch_rng(ctx.seed, epoch);
        let mut order = data.train.clone();
        order.shuffle(&mut rng);
        let mut losses = Vec::new();
        for (step, frames) in order.chunks_exact(batch).enumerate() {
            let global = epoch * steps_per_epoch + step as u64;
            let lr = warmup_cosine(global, total, warmup, s.warmup_lr, s.lr, s.min_lr);
            let rows: Vec<usize> = frames.iter().map(|&f| data.captions[f][rng.random_range(0..data.captions[f].len())]).collect();
            let loss = caption_loss(&gpt, &mapper.forward(&data.embedding(frames)), &data.batch(&rows, device), pad, LENGTH_GROUPS);
            losses.push(finite(loss.double_value(&[]), global + 1, epoch + 1)?);
            let grads = opt.gradients(&loss);
            AdamW::clip_grad_norm(&grads, s.clip_norm);
            opt.step(&grads, lr);
            progress.set_position(global + 1);
            progress.set_message(format!("epoch {}/{} loss {:.3}", epoch + 1, s.epochs, losses[losses.len() - 1]));
        }
        let validation_loss = tch::no_grad(|| {
            let mut sum = 0.0;
            for frames in data.validation.chunks(CHUNK) {
                let rows: Vec<usize> = frames.iter().map(|&f| data.captions[f][0]).collect();
                let loss = caption_loss(&gpt, &mapper.forward(&data.embedding(frames)), &data.batch(&rows, device), pad, LENGTH_GROUPS);
                sum += loss.double_value(&[]) * frames.len() as f64;
            }
            sum / data.validation.len() as f64
        });
        let line = json!({
            "epoch": epoch + 1, "step": (epoch + 1) * steps_per_epoch,
            "loss": losses.iter().sum::<f64>() / losses.len() as f64,
            "lr": warmup_cosine((epoch + 1) * steps_per_epoch - 1, total, warmup, s.warmup_lr, s.lr, s.min_lr),
            "validation_loss": validation_loss,
        });
        let mut event = line.clone();
        event["seconds"] = clock.elapsed().as_secs_f64().into();
        ctx.event("epoch", event);
        log.push(line);
        save_checkpoint(&vs, &opt, &log, &ctx.checkpoint_dir)?;
    }
    progress.finish();

    // Generate the validation and test captions.
    let max_tokens = if s.max_tokens == 0 { data.context as usize } else { s.max_tokens.min(data.context as usize) };
    let clock = Instant::now();
    let progress = ctx.progress((data.validation.len() + data.test.len()) as u64, "captions generated");
    let generate = |frames: &[usize]| -> anyhow::Result<Vec<String>> {
        let mut captions = Vec::with_capacity(frames.len());
        tch::no_grad(|| -> anyhow::Result<()> {
            for frames in frames.chunks(CHUNK) {
                let prefix = mapper.forward(&data.embedding(frames));
                let mut steps = Steps::new(&gpt, &prefix, start);
                let sequences = match s.decode {
                    Decode::Greedy => greedy(&mut steps, end, max_tokens),
                    Decode::Beam => beam_search(&mut steps, s.beam, end, max_tokens),
                };
                for ids in sequences {
                    let ids: Vec<u32> = ids.into_iter().take_while(|&t| t != end).map(|t| t as u32).collect();
                    captions.push(tokenizer.decode(&ids, true).map_err(|e| anyhow::anyhow!("decoding a generated caption: {e}"))?.trim().to_owned());
                }
                progress.inc(frames.len() as u64);
            }
            Ok(())
        })?;
        Ok(captions)
    };
    let truth = |frames: &[usize]| frames.iter().map(|&f| data.counts[f]).collect::<Vec<_>>();
    let (_, validation_scores) = score_captions(&generate(&data.validation)?, &truth(&data.validation));
    let captions = generate(&data.test)?;
    progress.finish();
    let seconds = clock.elapsed().as_secs_f64();
    let generated = data.validation.len() + captions.len();
    ctx.event("generated", json!({"captions": generated, "seconds": seconds, "captions_per_second": generated as f64 / seconds}));

    let (grids, scores) = score_captions(&captions, &truth(&data.test));
    let mut predictions = String::new();
    for ((&frame, caption), grid) in data.test.iter().zip(&captions).zip(&grids) {
        predictions.push_str(&format!("{{\"frame\":{frame},\"features\":\"cls\",\"grid\":{},\"caption\":{}}}\n", grid.to_json(), json!(caption)));
    }
    let details = json!({
        "decode": s.decode, "beam": s.beam, "max_tokens": max_tokens, "decoder": config.width, "log": log,
        "validation_frames": data.validation.len(), "validation_f1": validation_scores.overall.f1,
    });
    let row = Row { features: "cls".into(), details, scores: scores.clone() };
    let summary = Summary {
        format: probe::FORMAT,
        probe: "clipcap".into(),
        train_frames: data.train.len() as u64,
        test_frames: data.test.len() as u64,
        hygiene: data.hygiene.clone(),
        rows: vec![row],
        generator: serde_json::to_value(s)?,
    };
    let out = &ctx.output_dir;
    std::fs::write(out.join(probe::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    std::fs::write(out.join(probe::PREDICTIONS), predictions)?;
    write_weights(&vs, &out.join(WEIGHTS))?;
    let last: &Value = log.last().unwrap_or(&Value::Null);
    Ok(Outcome {
        metrics: json!({
            "cls": {"f1": scores.overall.f1, "precision": scores.overall.precision, "recall": scores.overall.recall},
            "validation_f1": validation_scores.overall.f1, "last": last,
        }),
        summary: format!(
            "{} test captions ({:?}): F1 {:.3} (P {:.3} R {:.3}); validation F1 {:.3}, loss {:.3}",
            captions.len(),
            s.decode,
            scores.overall.f1,
            scores.overall.precision,
            scores.overall.recall,
            validation_scores.overall.f1,
            last.get("validation_loss").and_then(Value::as_f64).unwrap_or(f64::NAN)
        ),
    })
}
