//! The `clip` pretrain operator on libtorch: trains the towers `rlmflow_pretrain` configures
//! and writes the Encoder artifact (`rlmflow_stages::encoder`).
//!
//! Each epoch visits every training frame once in a seeded order, with one of its captions
//! drawn per epoch; both draws are seeded by (seed, epoch), so the epoch alone is the RNG state a
//! checkpoint needs. After each epoch the model, the optimiser's moments and the log go to the
//! checkpoint directory, so a killed run resumes at the next epoch and ends with the same
//! weights as an uninterrupted one. Test-split radar->text retrieval (each test frame's first
//! caption) is measured after every epoch.

use anyhow::Context as _;
use rand::RngExt;
use rlmflow_nn::clip::{Clip as Model, cached_contrastive, logits};
use rlmflow_nn::data::{Frames, Need, Splits};
use rlmflow_nn::tch::{self, Kind, Tensor, nn};
use rlmflow_nn::train::{Backward, EpochRng, Figures, Fit, Fitted, Loss, Placement, Step, fit, write_weights};
use rlmflow_nn::{loss, start};
use rlmflow_pretrain::{ClipSettings, Objective};
use rlmflow_stages::encoder::{self, ModelConfig};
use rlmflow_stages::identity::FrameSet;
use rlmflow_stages::tokens;
use rlmflow_stages::{Context, Outcome, Settings};
use serde_json::{Value, json};

/// `clip`'s training, attached by the worker to `rlmflow_pretrain::operator()`.
pub fn clip(s: &ClipSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    rlmflow_nn::failure::catching(|| clip_on(s, ctx))
}

fn clip_on(s: &ClipSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    tch::set_num_threads(s.training.threads as i32);
    let placement = Placement::of(&s.training, ctx.device)?;
    let device = placement.device;
    let text = s.objective != Objective::Counts;
    let frames = Frames::load(ctx, Need { captions: true, masks: false })?;
    let captions = frames.captions.as_ref().context("pretraining reads the tokens stage")?;
    let split = frames.splits(0.0, text);
    split.require(if text { "the encoder (frames with captions)" } else { "the encoder" }, false)?;
    let summary = &captions.tokens.summary;
    let config = rlmflow_pretrain::model_config(s, frames.side, captions.context, i64::from(summary.vocab), i64::from(summary.special.end))?;

    tch::manual_seed(ctx.seed as i64);
    let vs = nn::VarStore::new(device);
    let model = Model::new(&vs.root(), &config, s.tau, s.learn_tau);
    if let Some(init) = ctx.tracked_file("init")? {
        start::load(&vs, "visual.", &init, &start::CLIP_VISION)?;
    }

    let chunked = s.chunk > 0 && s.chunk < s.training.batch;
    let batch_loss = |batch: &[usize], rng: &mut EpochRng, backward: &Backward| -> anyhow::Result<Step> {
        let counts = frames.counts(batch, device);
        let images = frames.images(batch, device);
        if s.objective == Objective::Counts {
            let predicted = model.counts(&model.encode_image(&images, true).embedding);
            return Ok(Step { loss: Loss::Tensor(predicted.mse_loss(&counts, tch::Reduction::Mean)), figures: vec![("off_diagonal", 0.0)] });
        }
        let rows: Vec<usize> = batch.iter().map(|&f| captions.rows[f][rng.random_range(0..captions.rows[f].len())]).collect();
        let tokens = captions.ids(&rows, device);
        let targets = (s.objective == Objective::SgClip).then(|| loss::soft_targets(&counts, s.alpha, s.distance));
        let loss_of = |image: &Tensor, text: &Tensor| {
            let logits = logits(image, text, &model.scale());
            match &targets {
                Some(targets) => loss::soft_clip_loss(&logits, targets),
                None => loss::clip_loss(&logits),
            }
        };
        let loss = if chunked {
            let (value, gradients) = cached_contrastive(&model, &images, &tokens, s.chunk as i64, loss_of, backward);
            Loss::Computed { value, gradients }
        } else {
            Loss::Tensor(loss_of(&model.encode_image(&images, true).embedding, &model.encode_text(&tokens)))
        };
        Ok(Step { loss, figures: vec![("off_diagonal", targets.as_ref().map_or(0.0, loss::off_diagonal_mass))] })
    };
    let after_epoch = || -> anyhow::Result<Figures> {
        let mut figures = vec![("tau", 1.0 / model.scale().double_value(&[]))];
        figures.extend(evaluate(&model, &frames, &split.test, device, text));
        Ok(figures)
    };
    let fitted = fit(&vs, Fit { training: &s.training, placement, frames: &split.train, per_batch: true }, ctx, batch_loss, after_epoch)?;
    write_artifact(s, ctx, &vs, &config, &frames, &split, fitted)
}

/// Test-split metrics: radar->text retrieval top-1 / top-5 with a text tower, else the counts
/// head's mean squared error.
fn evaluate(model: &Model, frames: &Frames, test: &[usize], device: tch::Device, text: bool) -> Figures {
    tch::no_grad(|| {
        let chunk = 256;
        let mut images = Vec::new();
        let mut texts = Vec::new();
        for part in test.chunks(chunk) {
            images.push(model.encode_image(&frames.images(part, device), false).embedding);
            if let (true, Some(captions)) = (text, &frames.captions) {
                let rows: Vec<usize> = part.iter().map(|&f| captions.rows[f][0]).collect();
                texts.push(model.encode_text(&captions.ids(&rows, device)));
            }
        }
        let images = Tensor::cat(&images, 0);
        if !text {
            let counts = frames.counts(test, device);
            return vec![("test_mse", model.counts(&images).mse_loss(&counts, tch::Reduction::Mean).double_value(&[]))];
        }
        let similarity = logits(&images, &Tensor::cat(&texts, 0), &Tensor::from(1f32).to_device(device));
        let own = similarity.diagonal(0, 0, 1).unsqueeze(1);
        let rank = similarity.gt_tensor(&own).sum_dim_intlist([1].as_slice(), false, Kind::Int64);
        let top = |k: i64| rank.lt(k).to_kind(Kind::Float).mean(Kind::Float).double_value(&[]);
        vec![("top1", top(1)), ("top5", top(5))]
    })
}

fn write_artifact(
    s: &ClipSettings,
    ctx: &Context,
    vs: &nn::VarStore,
    config: &ModelConfig,
    frames: &Frames,
    split: &Splits,
    Fitted { log, steps }: Fitted,
) -> anyhow::Result<Outcome> {
    let out = &ctx.output_dir;
    write_weights(vs, &out.join(encoder::WEIGHTS))?;
    let mut config_json = serde_json::to_value(config)?;
    config_json["open_clip"] = match config.open_clip() {
        Ok(open_clip) => {
            std::fs::write(out.join(encoder::OPEN_CLIP), serde_json::to_vec_pretty(&open_clip)?)?;
            json!(encoder::OPEN_CLIP)
        }
        Err(why) => json!(format!("open_clip cannot build this model: {why}")),
    };
    std::fs::write(out.join(encoder::CONFIG), serde_json::to_vec_pretty(&config_json)?)?;
    let lines: String = log.iter().map(|l| format!("{l}\n")).collect();
    std::fs::write(out.join(encoder::LOG), lines)?;
    let mut last = log.last().cloned().unwrap_or(Value::Null);
    if let Value::Object(map) = &mut last {
        map.retain(|key, _| !key.starts_with("batch_"));
    }
    let epochs = s.training.epochs;
    let n = split.test.len() as f64;
    let summary = encoder::Summary {
        format: encoder::FORMAT,
        objective: serde_json::to_value(s.objective)?.as_str().unwrap_or_default().to_owned(),
        epochs,
        steps,
        train_frames: split.train.len() as u64,
        test_frames: split.test.len() as u64,
        last: last.clone(),
        chance_top1: 1.0 / n,
        chance_top5: (5.0 / n).min(1.0),
        generator: s.result_settings(),
    };
    std::fs::write(out.join(encoder::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    let ids = |f: &usize| frames.labels.frames[*f].id.clone();
    let trained: FrameSet = if epochs > 0 { split.train.iter().map(ids).collect() } else { FrameSet::default() };
    trained.write(&out.join(encoder::TRAINED))?;
    if config.text.is_some() {
        let learnt = FrameSet::read(&ctx.input("tokens")?.join(tokens::LEARNT))?;
        learnt.write(&out.join(encoder::TOKENIZER_FRAMES))?;
    }
    let text = match (last.get("top1"), last.get("top5")) {
        (Some(t1), Some(t5)) => {
            format!("test retrieval top-1 {:.3} top-5 {:.3} (chance {:.4})", t1.as_f64().unwrap_or(0.0), t5.as_f64().unwrap_or(0.0), 1.0 / n)
        }
        _ => format!("test counts MSE {:.3}", last.get("test_mse").and_then(Value::as_f64).unwrap_or(f64::NAN)),
    };
    Ok(Outcome { metrics: json!({"last": last, "steps": steps, "chance_top1": 1.0 / n}), summary: format!("{epochs} epochs, {steps} steps; {text}") })
}

#[cfg(test)]
mod tests {
    use rlmflow_stages::encoder::{Head, Stem, VisionConfig};

    use super::*;

    fn tiny() -> (nn::VarStore, Model) {
        let vision = VisionConfig {
            image: 32,
            stem: Stem::Patch { size: 16 },
            width: 16,
            layers: 1,
            heads: 2,
            mlp: 32,
            head: Head::Linear,
            quick_gelu: false,
        };
        let config = ModelConfig { embed: 8, vision, text: None, counts_head: 0 };
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let model = Model::new(&vs.root(), &config, 0.07, false);
        (vs, model)
    }

    fn ramp(shape: &[i64], offset: f64) -> Tensor {
        let n: i64 = shape.iter().product();
        (Tensor::arange(n, (Kind::Float, tch::Device::Cpu)) / n as f64 + offset).view(shape)
    }

    fn var(vs: &nn::VarStore, name: &str) -> Tensor {
        vs.variables()[name].shallow_clone()
    }

    #[test]
    fn clip_weights_load_from_hugging_face_and_open_clip_names() {
        let dir = std::env::temp_dir().join(format!("rlmflow-clip-init-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // A Hugging Face CLIPVisionModel layout, RGB.
        let layer = |k: &str| format!("vision_model.encoder.layers.0.{k}");
        let mut hf: Vec<(String, Tensor)> = vec![
            ("vision_model.embeddings.patch_embedding.weight".into(), ramp(&[16, 3, 16, 16], 0.0)),
            ("vision_model.embeddings.class_embedding".into(), ramp(&[16], 1.0)),
            ("vision_model.embeddings.position_embedding.weight".into(), ramp(&[5, 16], 2.0)),
            ("vision_model.pre_layrnorm.weight".into(), ramp(&[16], 3.0)),
            ("vision_model.pre_layrnorm.bias".into(), ramp(&[16], 4.0)),
            ("vision_model.post_layernorm.weight".into(), ramp(&[16], 5.0)),
            ("vision_model.post_layernorm.bias".into(), ramp(&[16], 6.0)),
            ("visual_projection.weight".into(), ramp(&[8, 16], 7.0)),
        ];
        for (i, p) in ["q_proj", "k_proj", "v_proj", "out_proj"].iter().enumerate() {
            hf.push((layer(&format!("self_attn.{p}.weight")), ramp(&[16, 16], 10.0 + i as f64)));
            hf.push((layer(&format!("self_attn.{p}.bias")), ramp(&[16], 20.0 + i as f64)));
        }
        for (k, shape) in [("layer_norm1", [16, 0]), ("layer_norm2", [16, 0]), ("mlp.fc1", [32, 16]), ("mlp.fc2", [16, 32])] {
            let weight: Vec<i64> = shape.iter().copied().filter(|&d| d > 0).collect();
            hf.push((layer(&format!("{k}.weight")), ramp(&weight, 30.0)));
            hf.push((layer(&format!("{k}.bias")), ramp(&[shape[0]], 40.0)));
        }
        let file = dir.join("hf.safetensors");
        Tensor::write_safetensors(&hf, &file).unwrap();
        let (vs, _model) = tiny();
        let visual = vs.variables().keys().filter(|k| k.starts_with("visual.")).count();
        assert_eq!(start::load(&vs, "visual.", &file, &start::CLIP_VISION).unwrap(), visual, "every radar-tower tensor has a source");
        let source: std::collections::HashMap<String, Tensor> = hf.into_iter().collect();
        let same = |a: &Tensor, b: &Tensor| (a - b).abs().max().double_value(&[]) < 1e-6;
        assert!(same(
            &var(&vs, "visual.conv1.weight"),
            &source["vision_model.embeddings.patch_embedding.weight"].sum_dim_intlist([1].as_slice(), true, Kind::Float)
        ));
        let qkv = Tensor::cat(&["q_proj", "k_proj", "v_proj"].map(|p| source[&layer(&format!("self_attn.{p}.weight"))].shallow_clone()), 0);
        assert!(same(&var(&vs, "visual.transformer.resblocks.0.attn.in_proj_weight"), &qkv));
        assert!(same(&var(&vs, "visual.proj"), &source["visual_projection.weight"].tr()));
        assert!(same(&var(&vs, "visual.transformer.resblocks.0.mlp.c_proj.weight"), &source[&layer("mlp.fc2.weight")]));

        // open_clip names, and a shape that does not fit.
        let open_clip = vec![("visual.conv1.weight".to_owned(), ramp(&[16, 3, 16, 16], 0.5)), ("visual.ln_post.bias".to_owned(), ramp(&[16], 9.0))];
        let file = dir.join("open_clip.safetensors");
        Tensor::write_safetensors(&open_clip, &file).unwrap();
        let (vs, _model) = tiny();
        assert_eq!(start::load(&vs, "visual.", &file, &start::CLIP_VISION).unwrap(), 2);
        assert!(same(&var(&vs, "visual.ln_post.bias"), &open_clip[1].1));
        let wrong = vec![("visual.class_embedding".to_owned(), ramp(&[768], 0.0))];
        Tensor::write_safetensors(&wrong, &file).unwrap();
        let err = start::load(&tiny().0, "visual.", &file, &start::CLIP_VISION).unwrap_err().to_string();
        assert!(err.contains("`visual.class_embedding` has shape [768], the model needs [16]"), "{err}");
        Tensor::write_safetensors(&[("unrelated".to_owned(), ramp(&[2], 0.0))], &file).unwrap();
        assert!(start::load(&tiny().0, "visual.", &file, &start::CLIP_VISION).unwrap_err().to_string().contains("no tensor with CLIP names"));
    }
}
