//! The `clipcap` caption probe (see `rlmflow_probe`): ClipCap's mapper and a GPT decoder on the
//! frozen encoder's projected CLS embedding, trained with teacher forcing on the training split
//! less a validation slice, then validation and test captions generated, parsed and scored
//! (the validation F1 is what settings are chosen on). Each epoch draws its frame order and captions from (seed,
//! epoch), so a checkpoint needs only the epoch to resume.

use std::time::Instant;

use rand::RngExt;
use rlmflow_nn::data::{Captions, Frames, Need, Splits};
use rlmflow_nn::decode::{beam_search, greedy};
use rlmflow_nn::gpt::{Gpt, GptConfig, Mapper, Steps, caption_loss};
use rlmflow_nn::tch::{self, Tensor, nn};
use rlmflow_nn::train::{Backward, EpochRng, Figures, Fit, Fitted, Placement, Step, fit, write_weights};
use rlmflow_nn::{clip, start};
use rlmflow_probe::{ClipcapSettings, Decode};
use rlmflow_stages::grid::{CELLS, Grid};
use rlmflow_stages::identity::Split;
use rlmflow_stages::probe::{self, Row, Scores, Summary, score};
use rlmflow_stages::tokens;
use rlmflow_stages::{Context, Outcome, Settings};
use serde_json::{Value, json};
use tokenizers::Tokenizer;

use crate::caption_text::caption_text;

/// Frames per forward pass when embedding, scoring or generating.
const CHUNK: usize = 64;
/// Groups of similar caption length a batch's loss is computed in (see `caption_loss`).
const LENGTH_GROUPS: usize = 4;
/// The captioner's weights in the artifact.
pub const WEIGHTS: &str = "clipcap.safetensors";

/// The decoder a preset names.
fn decoder_config(s: &ClipcapSettings, vocab: i64, context: i64) -> GptConfig {
    let (width, layers, heads) = s.decoder_shape();
    GptConfig { vocab, positions: s.prefix + context, width, layers, heads, mlp: 4 * width }
}

/// Each generated caption parsed by the LLM-free parser and scored against the true grid.
pub fn score_captions(captions: &[String], truth: &[[u32; CELLS]]) -> (Vec<Grid>, Scores) {
    let grids: Vec<Grid> = captions.iter().map(|c| rlmflow_parser::parse(c).grid).collect();
    let counts: Vec<[u32; CELLS]> = grids.iter().map(|g| g.counts).collect();
    let scores = score(&counts, truth);
    (grids, scores)
}

/// The frames with every frame's frozen projected CLS embedding, and their roles.
struct Data {
    frames: Frames,
    /// (frames, embed).
    embeddings: Tensor,
    split: Splits,
    hygiene: Vec<rlmflow_stages::identity::Overlap>,
}

impl Data {
    fn captions(&self) -> &Captions {
        self.frames.captions.as_ref().expect("loaded with captions")
    }

    fn embedding(&self, frames: &[usize]) -> Tensor {
        let index: Vec<i64> = frames.iter().map(|&f| f as i64).collect();
        self.embeddings.index_select(0, &Tensor::from_slice(&index).to_device(self.embeddings.device()))
    }
}

fn load(s: &ClipcapSettings, ctx: &Context, device: tch::Device) -> anyhow::Result<(Data, rlmflow_stages::encoder::ModelConfig)> {
    let frames = Frames::load(ctx, Need { captions: true, masks: false })?;
    let hygiene = rlmflow_stages::identity::check_inputs(ctx, &frames.labels.ids(Split::Test), s.allow_test_overlap)?;
    let (_vs, encoder) = clip::load(ctx.input("encoder")?, device, frames.side)?;
    let all: Vec<usize> = (0..frames.len()).collect();
    let progress = ctx.progress(all.len() as u64, "frames embedded");
    let parts: Vec<Tensor> = tch::no_grad(|| {
        all.chunks(CHUNK)
            .map(|chunk| {
                progress.inc(chunk.len() as u64);
                encoder.encode_image(&frames.images(chunk, device), false).embedding
            })
            .collect()
    });
    progress.finish();
    let split = frames.splits(s.validation, true);
    split.require("the caption probe (frames with captions)", true)?;
    Ok((Data { frames, embeddings: Tensor::cat(&parts, 0), split, hygiene }, encoder.config))
}

/// `clipcap`'s training, attached by the worker to `rlmflow_probe::clipcap()`.
pub fn clipcap(s: &ClipcapSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    rlmflow_nn::failure::catching(|| clipcap_on(s, ctx))
}

fn clipcap_on(s: &ClipcapSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    tch::set_num_threads(s.training.threads as i32);
    let placement = Placement::of(&s.training, ctx.device)?;
    let device = placement.device;
    let (data, encoder) = load(s, ctx, device)?;
    let captions = data.captions();
    let tokenizer_path = ctx.input("tokens")?.join(tokens::TOKENIZER);
    let tokenizer = Tokenizer::from_file(&tokenizer_path).map_err(|e| anyhow::anyhow!("reading {}: {e}", tokenizer_path.display()))?;
    let summary = &captions.tokens.summary;
    let (start, end, pad) = (i64::from(summary.special.start), i64::from(summary.special.end), i64::from(summary.special.pad));

    tch::manual_seed(ctx.seed as i64);
    let vs = nn::VarStore::new(device);
    let config = decoder_config(s, i64::from(summary.vocab), captions.context);
    let mapper = Mapper::new(&(vs.root() / "mapper"), encoder.embed, config.width, s.prefix, s.mapper_layers, config.heads);
    let gpt = Gpt::new(&(vs.root() / "gpt"), &config);
    if let Some(init) = ctx.tracked_file("init")? {
        let loaded = start::load(&vs, "gpt.", &init, &start::GPT2)?;
        ctx.event("init", json!({"path": s.init, "tensors": loaded}));
    }

    let loss = |frames: &[usize], rows: &[usize]| {
        caption_loss(&gpt, &mapper.forward(&data.embedding(frames)), &captions.ids(rows, device), pad, LENGTH_GROUPS)
    };
    let batch_loss = |frames: &[usize], rng: &mut EpochRng, _: &Backward| -> anyhow::Result<Step> {
        let rows: Vec<usize> = frames.iter().map(|&f| captions.rows[f][rng.random_range(0..captions.rows[f].len())]).collect();
        Ok(loss(frames, &rows).into())
    };
    let validation_loss = || -> anyhow::Result<Figures> {
        let sum: f64 = tch::no_grad(|| {
            data.split
                .validation
                .chunks(CHUNK)
                .map(|frames| {
                    let rows: Vec<usize> = frames.iter().map(|&f| captions.rows[f][0]).collect();
                    loss(frames, &rows).double_value(&[]) * frames.len() as f64
                })
                .sum()
        });
        Ok(vec![("validation_loss", sum / data.split.validation.len() as f64)])
    };
    let Fitted { log, .. } =
        fit(&vs, Fit { training: &s.training, placement, frames: &data.split.train, per_batch: false }, ctx, batch_loss, validation_loss)?;

    // Generate the validation and test captions.
    let context = captions.context as usize;
    let max_tokens = if s.max_tokens == 0 { context } else { s.max_tokens.min(context) };
    let clock = Instant::now();
    let (validation, test) = (&data.split.validation, &data.split.test);
    let progress = ctx.progress((validation.len() + test.len()) as u64, "captions generated");
    let generate = |frames: &[usize]| -> anyhow::Result<Vec<String>> {
        let mut captions = Vec::with_capacity(frames.len());
        tch::no_grad(|| -> anyhow::Result<()> {
            for frames in frames.chunks(CHUNK) {
                let sequences = placement.forward(|| {
                    let prefix = mapper.forward(&data.embedding(frames));
                    let mut steps = Steps::new(&gpt, &prefix, start);
                    match s.decode {
                        Decode::Greedy => greedy(&mut steps, end, max_tokens),
                        Decode::Beam => beam_search(&mut steps, s.beam, end, max_tokens),
                    }
                })?;
                for ids in sequences {
                    let ids: Vec<u32> = ids.into_iter().take_while(|&t| t != end).map(|t| t as u32).collect();
                    captions.push(caption_text(&tokenizer, &ids)?.trim().to_owned());
                }
                progress.inc(frames.len() as u64);
            }
            Ok(())
        })?;
        Ok(captions)
    };
    let truth = |frames: &[usize]| frames.iter().map(|&f| data.frames.labels.frames[f].grid.counts).collect::<Vec<_>>();
    let (_, validation_scores) = score_captions(&generate(validation)?, &truth(validation));
    let generated = generate(test)?;
    progress.finish();
    let seconds = clock.elapsed().as_secs_f64();
    let count = validation.len() + generated.len();
    ctx.event("generated", json!({"captions": count, "seconds": seconds, "captions_per_second": count as f64 / seconds}));

    let (grids, scores) = score_captions(&generated, &truth(test));
    let mut predictions = String::new();
    for ((&frame, caption), grid) in test.iter().zip(&generated).zip(&grids) {
        predictions.push_str(&format!("{{\"frame\":{frame},\"features\":\"cls\",\"grid\":{},\"caption\":{}}}\n", grid.to_json(), json!(caption)));
    }
    let details = json!({
        "decode": s.decode, "beam": s.beam, "max_tokens": max_tokens, "decoder": config.width, "log": log,
        "validation_frames": validation.len(), "validation_f1": validation_scores.overall.f1,
    });
    let row = Row { features: "cls".into(), details, scores: scores.clone() };
    let summary = Summary {
        format: probe::FORMAT,
        probe: "clipcap".into(),
        train_frames: data.split.train.len() as u64,
        test_frames: test.len() as u64,
        hygiene: data.hygiene.clone(),
        rows: vec![row],
        generator: s.result_settings(),
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
            generated.len(),
            s.decode,
            scores.overall.f1,
            scores.overall.precision,
            scores.overall.recall,
            validation_scores.overall.f1,
            last.get("validation_loss").and_then(Value::as_f64).unwrap_or(f64::NAN)
        ),
    })
}
