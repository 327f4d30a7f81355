//! The segmenters on libtorch (they run in the `rlmflow-torch` worker): `pup` on a frozen
//! encoder's patch tokens, `unet` on pixels. See `rlmflow_segment` for what each does; the
//! artifact and the metrics are `rlmflow_stages::segment`'s.
//!
//! Both share one loop. Each epoch visits the training frames in an order seeded by (seed,
//! epoch), so a checkpoint needs only the epoch; after each epoch a validation slice of the
//! training split (never trained on; by frame identity, episodes whole) is scored and a
//! checkpoint written. The test split is scored once, at the end. Both first check that no test
//! frame is among those the encoder trained on (`rlmflow_stages::identity`). The frozen encoder's tokens are computed once for every frame when they
//! fit in [`TOKEN_CACHE_BYTES`], else per batch.

use std::time::Instant;

use anyhow::bail;
use rand::seq::SliceRandom;
use rlmflow_nn::clip::{self, Clip as Model, images_from_u8};
use rlmflow_nn::optim::{AdamW, warmup_cosine};
use rlmflow_nn::segment::{Pup as PupHead, UNet, dice_bce_loss, pup_widths};
use rlmflow_nn::tch::{self, Kind, Tensor, nn};
use rlmflow_nn::train::{epoch_rng, finite, resolve_device, restore_checkpoint, save_checkpoint, write_weights};
use rlmflow_segment::{PupSettings, Schedule, UnetSettings};
use rlmflow_stages::labels::{Labels, Split};
use rlmflow_stages::npy::{Dtype, NpyWriter};
use rlmflow_stages::scenes::Scenes;
use rlmflow_stages::segment::{self, PixelCounts, SegMetrics};
use rlmflow_stages::{Context, Operator, OperatorSpec, Outcome, Resources};
use serde_json::{Value, json};

/// Frozen-encoder tokens up to this size are computed once for every frame.
pub const TOKEN_CACHE_BYTES: i64 = 2 << 30;
/// Frames per forward pass when scoring or encoding.
const CHUNK: usize = 256;

pub struct Pup;

impl Operator for Pup {
    type Settings = PupSettings;

    fn spec(&self) -> OperatorSpec {
        rlmflow_segment::pup_spec()
    }

    fn resources(&self, s: &PupSettings) -> Resources {
        rlmflow_segment::pup_resources(s)
    }

    fn run(&self, s: &PupSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let schedule = s.schedule();
        let (device, data) = prepare(&schedule, ctx, s.allow_test_overlap)?;
        let dir = ctx.input("encoder")?;
        let (_encoder_vs, encoder) = clip::load(dir, device, data.side)?;
        let vision = &encoder.config.vision;
        let widths = if s.channels.is_empty() { pup_widths(vision.grid(), data.side) } else { s.channels.clone() };
        let vs = nn::VarStore::new(device);
        tch::manual_seed(ctx.seed as i64);
        let head = PupHead::new(&vs.root(), vision.width, &widths, data.side);
        let tokens = Tokens::new(&encoder, &data, device, ctx);
        let blocks: Vec<usize> = {
            let layers = vision.layers as usize;
            let take = if s.rollout_layers == 0 { layers } else { s.rollout_layers.min(layers) };
            (layers - take..layers).collect()
        };
        let segmenter =
            Segmenter { name: "pup", vs, forward: Box::new(move |frames: &[usize], train: bool| head.forward_t(&tokens.get(frames), train)) };
        let rollout = |frames: &[usize]| {
            let images = images_from_u8(&data.pixels(frames), frames.len() as i64, data.side, device);
            tch::no_grad(|| encoder.visual.attention_rollout(&images, blocks.len()))
        };
        train(&schedule, ctx, &data, device, segmenter, Some((&blocks, &rollout)), serde_json::to_value(s)?)
    }
}

pub struct Unet;

impl Operator for Unet {
    type Settings = UnetSettings;

    fn spec(&self) -> OperatorSpec {
        rlmflow_segment::unet_spec()
    }

    fn resources(&self, s: &UnetSettings) -> Resources {
        rlmflow_segment::unet_resources(s)
    }

    fn run(&self, s: &UnetSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let schedule = s.schedule();
        let (device, data) = prepare(&schedule, ctx, false)?;
        let divisor = 1i64 << (s.channels.len() - 1);
        if data.side % divisor != 0 {
            bail!("setting `channels`: {} levels need an image side divisible by {divisor}; the scenes have {}", s.channels.len(), data.side);
        }
        let vs = nn::VarStore::new(device);
        tch::manual_seed(ctx.seed as i64);
        let unet = UNet::new(&vs.root(), &s.channels);
        let pixels = |frames: &[usize]| images_from_u8(&data.pixels(frames), frames.len() as i64, data.side, device);
        let segmenter =
            Segmenter { name: "unet", vs, forward: Box::new(move |frames: &[usize], train: bool| unet.forward_t(&pixels(frames), train)) };
        train(&schedule, ctx, &data, device, segmenter, None, serde_json::to_value(s)?)
    }
}

/// Share of the training split held out as the validation slice the per-epoch log scores.
const VALIDATION_SHARE: f64 = 0.1;

/// The heatmaps and masks of every frame, and the split: training frames less the validation
/// slice, the slice, the test frames.
struct Data {
    side: i64,
    pixels: Vec<u8>,
    masks: Vec<u8>,
    train: Vec<usize>,
    validation: Vec<usize>,
    test: Vec<usize>,
    hygiene: Vec<rlmflow_stages::identity::Overlap>,
}

impl Data {
    fn load(ctx: &Context, allow_test_overlap: bool) -> anyhow::Result<Data> {
        let scenes = Scenes::open(ctx.input("scenes")?)?;
        let labels = Labels::open(ctx.input("labels")?)?;
        labels.check_scenes(scenes.len())?;
        let hygiene = rlmflow_stages::identity::check_inputs(ctx, &labels.ids(Split::Test), allow_test_overlap)?;
        let side = scenes.summary.images[0].size;
        if labels.summary.mask.size != side {
            bail!(
                "the labels' masks are {} px but the scenes' primary image {side} px: give the stage the scenes that were labelled",
                labels.summary.mask.size
            );
        }
        let pixels = (0..scenes.len()).map(|i| scenes.heatmap(i)).collect::<anyhow::Result<Vec<_>>>()?.concat();
        let masks = (0..scenes.len()).map(|i| labels.mask(i)).collect::<anyhow::Result<Vec<_>>>()?.concat();
        let (train, validation) = labels.train_validation(VALIDATION_SHARE);
        let frames = |labels: Vec<&rlmflow_stages::labels::FrameLabel>| labels.into_iter().map(|f| f.frame as usize).collect::<Vec<_>>();
        let (train, validation) = (frames(train), frames(validation));
        let test: Vec<usize> = labels.split(Split::Test).map(|f| f.frame as usize).collect();
        if train.is_empty() || validation.is_empty() || test.is_empty() {
            bail!("{} training, {} validation and {} test frames: segmentation needs all three", train.len(), validation.len(), test.len());
        }
        Ok(Data { side: side as i64, pixels, masks, train, validation, test, hygiene })
    }

    fn frame_bytes(&self) -> usize {
        (self.side * self.side) as usize
    }

    fn pixels(&self, frames: &[usize]) -> Vec<u8> {
        let n = self.frame_bytes();
        frames.iter().flat_map(|&f| self.pixels[f * n..(f + 1) * n].iter().copied()).collect()
    }

    fn mask(&self, frame: usize) -> &[u8] {
        let n = self.frame_bytes();
        &self.masks[frame * n..(frame + 1) * n]
    }

    /// Targets in [0, 1], (frames, 1, side, side).
    fn targets(&self, frames: &[usize], device: tch::Device) -> Tensor {
        let bytes: Vec<u8> = frames.iter().flat_map(|&f| self.mask(f).iter().copied()).collect();
        Tensor::from_slice(&bytes).view([frames.len() as i64, 1, self.side, self.side]).to_device(device).to_kind(Kind::Float) / 255.0
    }
}

fn prepare(s: &Schedule, ctx: &Context, allow_test_overlap: bool) -> anyhow::Result<(tch::Device, Data)> {
    tch::set_num_threads(s.threads as i32);
    Ok((resolve_device(&s.device, ctx.device)?, Data::load(ctx, allow_test_overlap)?))
}

/// The frozen encoder's tokens after `ln_post` for any frames: from a table of every frame's
/// when it fits in memory, else encoded on demand.
struct Tokens<'a> {
    encoder: &'a Model,
    data: &'a Data,
    device: tch::Device,
    table: Option<Tensor>,
}

impl<'a> Tokens<'a> {
    fn new(encoder: &'a Model, data: &'a Data, device: tch::Device, ctx: &Context) -> Tokens<'a> {
        let v = &encoder.config.vision;
        let frames = data.pixels.len() as i64 / (data.side * data.side);
        let bytes = frames * (v.grid() * v.grid() + 1) * v.width * 4;
        let mut tokens = Tokens { encoder, data, device, table: None };
        if bytes <= TOKEN_CACHE_BYTES {
            let all: Vec<usize> = (0..frames as usize).collect();
            let progress = ctx.progress(frames as u64, "frames encoded");
            let parts: Vec<Tensor> = all
                .chunks(CHUNK)
                .map(|chunk| {
                    let t = tokens.encode(chunk);
                    progress.inc(chunk.len() as u64);
                    t
                })
                .collect();
            progress.finish();
            tokens.table = Some(Tensor::cat(&parts, 0));
        }
        tokens
    }

    fn encode(&self, frames: &[usize]) -> Tensor {
        let images = images_from_u8(&self.data.pixels(frames), frames.len() as i64, self.data.side, self.device);
        tch::no_grad(|| self.encoder.encode_image(&images, false).tokens)
    }

    fn get(&self, frames: &[usize]) -> Tensor {
        match &self.table {
            Some(table) => {
                let index: Vec<i64> = frames.iter().map(|&f| f as i64).collect();
                table.index_select(0, &Tensor::from_slice(&index).to_device(self.device))
            }
            None => self.encode(frames),
        }
    }
}

/// A trainable head and how it maps frames to mask logits (batch, 1, side, side).
struct Segmenter<'a> {
    name: &'static str,
    vs: nn::VarStore,
    forward: Box<dyn Fn(&[usize], bool) -> Tensor + 'a>,
}

/// `scored` frames scored: pixel counts for the metrics and the mean loss.
fn evaluate(segmenter: &Segmenter, data: &Data, scored: &[usize], device: tch::Device, dice_weight: f64) -> anyhow::Result<(PixelCounts, f64)> {
    tch::no_grad(|| {
        let mut counts = PixelCounts::new();
        let mut loss = 0.0;
        for frames in scored.chunks(CHUNK) {
            let logits = (segmenter.forward)(frames, false);
            loss += dice_bce_loss(&logits, &data.targets(frames, device), dice_weight).double_value(&[]) * frames.len() as f64;
            let predicted = Vec::<f32>::try_from(logits.sigmoid().to_device(tch::Device::Cpu).flatten(0, -1))?;
            for (i, &f) in frames.iter().enumerate() {
                let n = data.frame_bytes();
                counts.add(&predicted[i * n..(i + 1) * n], data.mask(f));
            }
        }
        Ok((counts, loss / scored.len() as f64))
    })
}

type Rollout<'a> = (&'a [usize], &'a dyn Fn(&[usize]) -> Tensor);

fn train(
    s: &Schedule,
    ctx: &mut Context,
    data: &Data,
    device: tch::Device,
    segmenter: Segmenter,
    rollout: Option<Rollout>,
    generator: Value,
) -> anyhow::Result<Outcome> {
    let batch = s.batch as usize;
    let steps_per_epoch = (data.train.len() / batch) as u64;
    if steps_per_epoch == 0 {
        bail!("batch {batch} is larger than the {} training frames; lower `batch`", data.train.len());
    }
    let total = s.epochs * steps_per_epoch;
    let warmup = (s.warmup_epochs * steps_per_epoch as f64).round() as u64;
    let mut opt = AdamW::new(&segmenter.vs, (0.9, 0.999), 1e-8, s.weight_decay);
    let mut log = restore_checkpoint(&segmenter.vs, &mut opt, &ctx.checkpoint_dir)?;
    if !log.is_empty() {
        ctx.event("resumed", json!({"epoch": log.len()}));
    }
    let progress = ctx.progress(total, "steps");
    progress.set_position(opt.steps() as u64);
    for epoch in log.len() as u64..s.epochs {
        let clock = Instant::now();
        let mut order = data.train.clone();
        order.shuffle(&mut epoch_rng(ctx.seed, epoch));
        let mut losses = Vec::with_capacity(steps_per_epoch as usize);
        for (step, frames) in order.chunks_exact(batch).enumerate() {
            let global = epoch * steps_per_epoch + step as u64;
            let lr = warmup_cosine(global, total, warmup, s.warmup_lr, s.lr, s.min_lr);
            let loss = dice_bce_loss(&(segmenter.forward)(frames, true), &data.targets(frames, device), s.dice_weight);
            losses.push(finite(loss.double_value(&[]), global + 1, epoch + 1)?);
            let grads = opt.gradients(&loss);
            AdamW::clip_grad_norm(&grads, s.clip_norm);
            opt.step(&grads, lr);
            progress.set_position(global + 1);
            progress.set_message(format!("epoch {}/{} loss {:.3}", epoch + 1, s.epochs, losses[losses.len() - 1]));
        }
        let (counts, validation_loss) = evaluate(&segmenter, data, &data.validation, device, s.dice_weight)?;
        let m = counts.metrics();
        let line = json!({
            "epoch": epoch + 1, "step": (epoch + 1) * steps_per_epoch,
            "loss": losses.iter().sum::<f64>() / losses.len() as f64,
            "lr": warmup_cosine((epoch + 1) * steps_per_epoch - 1, total, warmup, s.warmup_lr, s.lr, s.min_lr),
            "validation_loss": validation_loss, "validation_iou": m.iou, "validation_ap": m.ap,
        });
        let mut event = line.clone();
        event["seconds"] = clock.elapsed().as_secs_f64().into();
        ctx.event("epoch", event);
        log.push(line);
        save_checkpoint(&segmenter.vs, &opt, &log, &ctx.checkpoint_dir)?;
    }
    progress.finish();
    let metrics = evaluate(&segmenter, data, &data.test, device, s.dice_weight)?.0.metrics();
    write_artifact(s, ctx, data, &segmenter, rollout, &log, total, metrics, generator)
}

#[allow(clippy::too_many_arguments)]
fn write_artifact(
    s: &Schedule,
    ctx: &Context,
    data: &Data,
    segmenter: &Segmenter,
    rollout: Option<Rollout>,
    log: &[Value],
    steps: u64,
    metrics: SegMetrics,
    generator: Value,
) -> anyhow::Result<Outcome> {
    let out = &ctx.output_dir;
    let n = s.samples.min(data.test.len());
    let samples: Vec<usize> = (0..n).map(|i| data.test[i * data.test.len() / n]).collect();
    let side = data.side as usize;
    let mut writer = NpyWriter::create(&out.join(segment::SAMPLES), Dtype::U8, n, &[side, side])?;
    if n > 0 {
        let predicted = tch::no_grad(|| (segmenter.forward)(&samples, false).sigmoid());
        write_u8_maps(&mut writer, &predicted, |_| 1.0)?;
    }
    writer.finish()?;
    let mut blocks = Vec::new();
    if let Some((used, rollout)) = rollout {
        blocks = used.to_vec();
        let maps = if n > 0 { Some(rollout(&samples)) } else { None };
        let grid = maps.as_ref().map_or(0, |m| m.size()[1] as usize);
        let mut writer = NpyWriter::create(&out.join(segment::ROLLOUT), Dtype::U8, n, &[grid, grid])?;
        if let Some(maps) = maps {
            // Each map scaled to its own maximum.
            let peaks = maps.flatten(1, -1).amax([1].as_slice(), false).clamp_min(1e-12);
            write_u8_maps(&mut writer, &maps, |i| 1.0 / peaks.double_value(&[i as i64]))?;
        }
        writer.finish()?;
    }
    write_weights(&segmenter.vs, &out.join(segment::WEIGHTS))?;
    let summary = segment::Summary {
        format: segment::FORMAT,
        operator: segmenter.name.into(),
        train_frames: data.train.len() as u64,
        test_frames: data.test.len() as u64,
        hygiene: data.hygiene.clone(),
        epochs: s.epochs,
        steps,
        metrics: metrics.clone(),
        log: log.to_vec(),
        sample_frames: samples.iter().map(|&f| f as u64).collect(),
        rollout_blocks: blocks,
        generator,
    };
    std::fs::write(out.join(segment::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    let m = &metrics;
    Ok(Outcome {
        metrics: json!({"precision": m.precision, "recall": m.recall, "iou": m.iou, "dice": m.dice, "peak_iou": m.peak_iou, "ap": m.ap, "positive_rate": m.positive_rate}),
        summary: format!(
            "{} test frames: IoU {:.3} Dice {:.3} peak IoU {:.3} AP {:.3} (positive rate {:.3})",
            data.test.len(),
            m.iou,
            m.dice,
            m.peak_iou,
            m.ap,
            m.positive_rate
        ),
    })
}

/// Writes each map of `maps` (frames first, values in [0, 1] after scaling frame i by
/// `scale(i)`) as bytes, value x 255 rounded.
fn write_u8_maps(writer: &mut NpyWriter, maps: &Tensor, scale: impl Fn(usize) -> f64) -> anyhow::Result<()> {
    let frames = maps.size()[0];
    for i in 0..frames {
        let map = maps.get(i).flatten(0, -1).to_device(tch::Device::Cpu).to_kind(Kind::Double);
        let values = Vec::<f64>::try_from(map * scale(i as usize))?;
        writer.write_u8(&values.iter().map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8).collect::<Vec<_>>())?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use rlmflow_pretrain::{ClipSettings, ENCODERS, model_config};

    use super::*;

    #[test]
    fn the_pup_decoder_gives_one_full_size_map_per_frame_for_every_encoder_size() {
        for (name, side) in ENCODERS.iter().zip([64, 64, 224]) {
            let s = ClipSettings { encoder: name.to_string(), objective: rlmflow_pretrain::Objective::Counts, ..Default::default() };
            let vision = model_config(&s, side, 8, 10, 1).unwrap().vision;
            let vs = nn::VarStore::new(tch::Device::Cpu);
            let grid = vision.grid();
            let head = PupHead::new(&vs.root(), vision.width, &pup_widths(grid, side), side);
            let tokens = Tensor::zeros([2, grid * grid + 1, vision.width], (Kind::Float, tch::Device::Cpu));
            assert_eq!(head.forward_t(&tokens, false).size(), [2, 1, side, side], "{name}: {grid}x{grid}x{} tokens", vision.width);
        }
        // vit-b16 is the paper's table: 768 x 14 x 14 in, four stages.
        let vs = nn::VarStore::new(tch::Device::Cpu);
        let _ = PupHead::new(&vs.root(), 768, &pup_widths(14, 224), 224);
        let shapes: Vec<Vec<i64>> = (0..4).map(|i| vs.variables()[&format!("stages.{i}.conv.weight")].size()).collect();
        assert_eq!(shapes, [vec![256, 768, 3, 3], vec![256, 256, 3, 3], vec![128, 256, 3, 3], vec![64, 128, 3, 3]]);
    }
}
