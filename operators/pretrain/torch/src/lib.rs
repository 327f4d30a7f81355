//! The `clip` pretrain operator on libtorch: trains the towers `rlmflow_pretrain` configures
//! and writes the Encoder artifact (`rlmflow_stages::encoder`).
//!
//! Each epoch visits every training frame once in a seeded order, with one of its captions
//! drawn per epoch; both draws are seeded by (seed, epoch), so the epoch alone is the RNG state a
//! checkpoint needs. After each epoch the model, the optimiser's moments and the log go to the
//! checkpoint directory, so a killed run resumes at the next epoch and ends with the same
//! weights as an uninterrupted one. Test-split radar->text retrieval (each test frame's first
//! caption) is measured after every epoch.

mod data;

use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;

use anyhow::{Context as _, bail};
use rand::RngExt;
use rand::seq::SliceRandom;
use rlmflow_nn::clip::{Clip as Model, images_from_u8, logits};
use rlmflow_nn::loss::{self, Distance as LossDistance};
use rlmflow_nn::optim::{AdamW, warmup_cosine};
use rlmflow_nn::tch::{self, Kind, Tensor, nn};
use rlmflow_nn::train::{epoch_rng, finite, resolve_device, restore_checkpoint, save_checkpoint, write_weights};
use rlmflow_pretrain::{ClipSettings, Distance, Objective};
use rlmflow_stages::encoder::{self, ModelConfig};
use rlmflow_stages::identity::FrameSet;
use rlmflow_stages::tokens;
use rlmflow_stages::{Context, Operator, OperatorSpec, Outcome, Resources};
use serde_json::{Value, json};

pub use data::Dataset;

pub struct Clip;

impl Operator for Clip {
    type Settings = ClipSettings;

    fn spec(&self) -> OperatorSpec {
        rlmflow_pretrain::spec()
    }

    fn resources(&self, s: &ClipSettings) -> Resources {
        rlmflow_pretrain::resources(s)
    }

    fn run(&self, s: &ClipSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        train(s, ctx)
    }
}

/// Per-batch series in each epoch's log line.
const BATCH_LOSS: &str = "batch_loss";
const BATCH_OFF_DIAGONAL: &str = "batch_off_diagonal";

fn train(s: &ClipSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    tch::set_num_threads(s.threads as i32);
    let device = resolve_device(&s.device, ctx.device)?;
    let text = s.objective != Objective::Counts;
    let data = Dataset::load(ctx.input("scenes")?, ctx.input("labels")?, ctx.input("tokens")?, text)?;
    let config =
        rlmflow_pretrain::model_config(s, data.side, data.context, data.vocab, data.end_token).map_err(|e| anyhow::anyhow!("setting `{e}`"))?;

    tch::manual_seed(ctx.seed as i64);
    let vs = nn::VarStore::new(device);
    let model = Model::new(&vs.root(), &config, s.tau, s.learn_tau);
    if !s.init.is_empty() {
        load_clip_vision(&vs, Path::new(&s.init))?;
    }
    let mut opt = AdamW::new(&vs, (s.betas[0], s.betas[1]), s.eps, s.weight_decay);

    let batch = s.batch as usize;
    let steps_per_epoch = (data.train.len() / batch) as u64;
    if steps_per_epoch == 0 && s.epochs > 0 {
        bail!("batch {batch} is larger than the {} training frames; lower `batch`", data.train.len());
    }
    let total = s.epochs * steps_per_epoch;
    let warmup = (s.warmup_epochs * steps_per_epoch as f64).round() as u64;

    // Resume from the last finished epoch.
    let mut log = restore_checkpoint(&vs, &mut opt, &ctx.checkpoint_dir)?;
    if !log.is_empty() {
        ctx.event("resumed", json!({"epoch": log.len()}));
    }

    let progress = ctx.progress(total, "steps");
    progress.set_position(opt.steps() as u64);
    let scale = |m: &Model| m.scale().double_value(&[]);
    for epoch in log.len() as u64..s.epochs {
        let clock = Instant::now();
        let mut rng = epoch_rng(ctx.seed, epoch);
        let mut order = data.train.clone();
        order.shuffle(&mut rng);
        let (mut batch_loss, mut batch_off) = (Vec::new(), Vec::new());
        for step in 0..steps_per_epoch {
            let global = epoch * steps_per_epoch + step;
            let lr = warmup_cosine(global, total, warmup, s.warmup_lr, s.lr, s.min_lr);
            let frames = &order[step as usize * batch..(step as usize + 1) * batch];
            let images = images_from_u8(&data.image_pixels(frames), batch as i64, data.side, device);
            let counts = Tensor::from_slice(&data.frame_counts(frames)).view([batch as i64, -1]).to_device(device);
            let image = model.encode_image(&images, true).embedding;
            let (loss, off) = match s.objective {
                Objective::Counts => (model.counts(&image).mse_loss(&counts, tch::Reduction::Mean), 0.0),
                objective => {
                    let rows: Vec<usize> = frames.iter().map(|&f| data.captions[f][rng.random_range(0..data.captions[f].len())]).collect();
                    let tokens = Tensor::from_slice(&data.caption_tokens(&rows)).view([batch as i64, data.context]).to_device(device);
                    let logits = logits(&image, &model.encode_text(&tokens), &model.scale());
                    if objective == Objective::SgClip {
                        let distance = match s.distance {
                            Distance::Raw => LossDistance::Raw,
                            Distance::PairTotal => LossDistance::PairTotal,
                        };
                        let targets = loss::soft_targets(&counts, s.alpha, distance);
                        (loss::soft_clip_loss(&logits, &targets), loss::off_diagonal_mass(&targets))
                    } else {
                        (loss::clip_loss(&logits), 0.0)
                    }
                }
            };
            let value = finite(loss.double_value(&[]), global + 1, epoch + 1)?;
            let grads = opt.gradients(&loss);
            AdamW::clip_grad_norm(&grads, s.clip_norm);
            opt.step(&grads, lr);
            batch_loss.push(value);
            batch_off.push(off);
            progress.set_position(global + 1);
            progress.set_message(format!("epoch {}/{} loss {value:.3}", epoch + 1, s.epochs));
        }
        let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
        let mut line = json!({
            "epoch": epoch + 1, "step": (epoch + 1) * steps_per_epoch, "loss": mean(&batch_loss),
            "lr": warmup_cosine((epoch + 1) * steps_per_epoch - 1, total, warmup, s.warmup_lr, s.lr, s.min_lr),
            "tau": 1.0 / scale(&model), "off_diagonal": mean(&batch_off),
        });
        evaluate(&model, &data, device, text).into_iter().for_each(|(k, v)| line[k] = v.into());
        // Times go to the event log only: the artifact holds what the key determines.
        let mut event = line.clone();
        event["seconds"] = clock.elapsed().as_secs_f64().into();
        ctx.event("epoch", event);
        // Per batch, in the log only (not in events or the summary).
        line[BATCH_LOSS] = batch_loss.into();
        line[BATCH_OFF_DIAGONAL] = batch_off.into();
        log.push(line);
        save_checkpoint(&vs, &opt, &log, &ctx.checkpoint_dir)?;
    }
    progress.finish();
    if s.epochs == 0 {
        let mut line = json!({"epoch": 0, "step": 0, "tau": 1.0 / scale(&model)});
        evaluate(&model, &data, device, text).into_iter().for_each(|(k, v)| line[k] = v.into());
        log.push(line);
    }
    write_artifact(s, ctx, &vs, &config, &data, &log, total)
}

/// Test-split metrics: radar->text retrieval top-1 / top-5 with a text tower, else the counts
/// head's mean squared error.
fn evaluate(model: &Model, data: &Dataset, device: tch::Device, text: bool) -> Vec<(&'static str, f64)> {
    tch::no_grad(|| {
        let chunk = 256;
        let mut images = Vec::new();
        let mut texts = Vec::new();
        for frames in data.test.chunks(chunk) {
            let pixels = images_from_u8(&data.image_pixels(frames), frames.len() as i64, data.side, device);
            images.push(model.encode_image(&pixels, false).embedding);
            if text {
                let rows: Vec<usize> = frames.iter().map(|&f| data.captions[f][0]).collect();
                let tokens = Tensor::from_slice(&data.caption_tokens(&rows)).view([frames.len() as i64, data.context]).to_device(device);
                texts.push(model.encode_text(&tokens));
            }
        }
        let images = Tensor::cat(&images, 0);
        if !text {
            let counts = Tensor::from_slice(&data.frame_counts(&data.test)).view([data.test.len() as i64, -1]).to_device(device);
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
    data: &Dataset,
    log: &[Value],
    steps: u64,
) -> anyhow::Result<Outcome> {
    let out = &ctx.output_dir;
    write_weights(vs, &out.join(encoder::WEIGHTS))?;
    std::fs::write(out.join(encoder::CONFIG), serde_json::to_vec_pretty(config)?)?;
    let lines: String = log.iter().map(|l| format!("{l}\n")).collect();
    std::fs::write(out.join(encoder::LOG), lines)?;
    let mut last = log.last().cloned().unwrap_or(Value::Null);
    if let Value::Object(map) = &mut last {
        map.remove(BATCH_LOSS);
        map.remove(BATCH_OFF_DIAGONAL);
    }
    let n = data.test.len() as f64;
    let summary = encoder::Summary {
        format: encoder::FORMAT,
        objective: serde_json::to_value(s.objective)?.as_str().unwrap_or_default().to_owned(),
        epochs: s.epochs,
        steps,
        train_frames: data.train.len() as u64,
        test_frames: data.test.len() as u64,
        last: last.clone(),
        chance_top1: 1.0 / n,
        chance_top5: (5.0 / n).min(1.0),
        generator: serde_json::to_value(s)?,
    };
    std::fs::write(out.join(encoder::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    let trained: FrameSet = if s.epochs > 0 { data.train.iter().map(|&f| data.ids[f].clone()).collect() } else { FrameSet::default() };
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
    Ok(Outcome {
        metrics: json!({"last": last, "steps": steps, "chance_top1": 1.0 / n}),
        summary: format!("{} epochs, {steps} steps; {text}", s.epochs),
    })
}

/// Starts the radar tower from a CLIP ViT-B/16 safetensors file with open_clip names
/// (`visual.conv1.weight`, `visual.transformer.resblocks.N...`) or Hugging Face names
/// (`vision_model.embeddings.patch_embedding.weight`, `vision_model.encoder.layers.N...`). The
/// RGB patch kernel is summed over its colour channels for the one radar channel; the
/// projection is kept only where its shape fits.
pub fn load_clip_vision(vs: &nn::VarStore, path: &Path) -> anyhow::Result<usize> {
    let source: HashMap<String, Tensor> =
        Tensor::read_safetensors(path).with_context(|| format!("reading CLIP weights from {}", path.display()))?.into_iter().collect();
    let ours = vs.variables();
    let mut loaded = 0;
    tch::no_grad(|| -> anyhow::Result<()> {
        for (name, mut var) in ours {
            let Some(rest) = name.strip_prefix("visual.") else { continue };
            let Some(found) = clip_source(&source, rest) else { continue };
            let found = if rest == "conv1.weight" && found.size().get(1) == Some(&3) {
                found.sum_dim_intlist([1].as_slice(), true, found.kind())
            } else {
                found
            };
            if found.size() != var.size() {
                if rest == "proj" {
                    continue;
                }
                bail!("{}: `{name}` has shape {:?}, the model needs {:?}", path.display(), found.size(), var.size());
            }
            var.copy_(&found.to_kind(var.kind()));
            loaded += 1;
        }
        Ok(())
    })?;
    if loaded == 0 {
        bail!("{}: no tensor with open_clip (visual.*) or Hugging Face (vision_model.*) CLIP names", path.display());
    }
    Ok(loaded)
}

/// The tensor of `source` for our `visual.<rest>`, under either naming.
fn clip_source(source: &HashMap<String, Tensor>, rest: &str) -> Option<Tensor> {
    if let Some(t) = source.get(&format!("visual.{rest}")) {
        return Some(t.shallow_clone());
    }
    let hf = |k: &str| source.get(&format!("vision_model.{k}")).map(Tensor::shallow_clone);
    let layer = |i: &str, k: &str| format!("encoder.layers.{i}.{k}");
    match rest {
        "conv1.weight" => hf("embeddings.patch_embedding.weight"),
        "class_embedding" => hf("embeddings.class_embedding"),
        "positional_embedding" => hf("embeddings.position_embedding.weight"),
        "ln_pre.weight" => hf("pre_layrnorm.weight"),
        "ln_pre.bias" => hf("pre_layrnorm.bias"),
        "ln_post.weight" => hf("post_layernorm.weight"),
        "ln_post.bias" => hf("post_layernorm.bias"),
        "proj" => source.get("visual_projection.weight").map(|t| t.tr()),
        _ => {
            let rest = rest.strip_prefix("transformer.resblocks.")?;
            let (i, key) = rest.split_once('.')?;
            let qkv = |suffix: &str| -> Option<Tensor> {
                let parts: Option<Vec<Tensor>> =
                    ["q_proj", "k_proj", "v_proj"].iter().map(|p| hf(&layer(i, &format!("self_attn.{p}.{suffix}")))).collect();
                parts.map(|p| Tensor::cat(&p, 0))
            };
            match key {
                "attn.in_proj_weight" => qkv("weight"),
                "attn.in_proj_bias" => qkv("bias"),
                "attn.out_proj.weight" => hf(&layer(i, "self_attn.out_proj.weight")),
                "attn.out_proj.bias" => hf(&layer(i, "self_attn.out_proj.bias")),
                "ln_1.weight" => hf(&layer(i, "layer_norm1.weight")),
                "ln_1.bias" => hf(&layer(i, "layer_norm1.bias")),
                "ln_2.weight" => hf(&layer(i, "layer_norm2.weight")),
                "ln_2.bias" => hf(&layer(i, "layer_norm2.bias")),
                "mlp.c_fc.weight" => hf(&layer(i, "mlp.fc1.weight")),
                "mlp.c_fc.bias" => hf(&layer(i, "mlp.fc1.bias")),
                "mlp.c_proj.weight" => hf(&layer(i, "mlp.fc2.weight")),
                "mlp.c_proj.bias" => hf(&layer(i, "mlp.fc2.bias")),
                _ => None,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use rlmflow_stages::encoder::{Head, Stem, VisionConfig};

    use super::*;

    fn tiny() -> (nn::VarStore, Model) {
        let vision = VisionConfig { image: 32, stem: Stem::Patch { size: 16 }, width: 16, layers: 1, heads: 2, mlp: 32, head: Head::Linear };
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
        assert_eq!(load_clip_vision(&vs, &file).unwrap(), visual, "every radar-tower tensor has a source");
        let source: HashMap<String, Tensor> = hf.into_iter().collect();
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
        assert_eq!(load_clip_vision(&vs, &file).unwrap(), 2);
        assert!(same(&var(&vs, "visual.ln_post.bias"), &open_clip[1].1));
        let wrong = vec![("visual.class_embedding".to_owned(), ramp(&[768], 0.0))];
        Tensor::write_safetensors(&wrong, &file).unwrap();
        let err = load_clip_vision(&tiny().0, &file).unwrap_err().to_string();
        assert!(err.contains("`visual.class_embedding` has shape [768], the model needs [16]"), "{err}");
        Tensor::write_safetensors(&[("unrelated".to_owned(), ramp(&[2], 0.0))], &file).unwrap();
        assert!(load_clip_vision(&tiny().0, &file).unwrap_err().to_string().contains("no tensor with open_clip"));
    }
}
