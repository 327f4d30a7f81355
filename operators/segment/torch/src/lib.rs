//! The segmenters on libtorch (they run in the `rlmflow-torch` worker): `pup` on a frozen
//! encoder's patch tokens, `unet` on pixels. See `rlmflow_segment` for what each does; the
//! artifact and the metrics are `rlmflow_stages::segment`'s.
//!
//! Both train through `rlmflow_nn::train::fit` on the frames of `rlmflow_nn::data`: each epoch
//! visits the training frames in an order seeded by (seed, epoch), then a validation slice of
//! the training split (never trained on; by frame identity, episodes whole) is scored and a
//! checkpoint written. The test split is scored once, at the end. Both first check that no test
//! frame is among those the encoder trained on (`rlmflow_stages::identity`). The frozen
//! encoder's tokens are computed once for every frame when they fit in [`TOKEN_CACHE_BYTES`],
//! else per batch.

use rlmflow_nn::clip::{self, Clip as Model};
use rlmflow_nn::data::{Frames, Need, Splits};
use rlmflow_nn::segment::{Pup as PupHead, UNet, dice_bce_loss};
use rlmflow_nn::tch::{self, Kind, Tensor, nn};
use rlmflow_nn::train::{Backward, EpochRng, Figures, Fit, Fitted, Placement, Step, fit, write_weights};
use rlmflow_segment::{PupSettings, TOKEN_CACHE_BYTES, UnetSettings, pup_widths};
use rlmflow_stages::identity::Split;
use rlmflow_stages::npy::{Dtype, NpyWriter};
use rlmflow_stages::segment::{self, FrameScore, PixelCounts, SegMetrics};
use rlmflow_stages::{Context, Outcome, Settings, Training};
use serde_json::{Value, json};

/// Frozen-encoder tokens up to this size are computed once for every frame.
/// Frames per forward pass when scoring or encoding.
const CHUNK: usize = 256;

/// `pup`'s training, attached by the worker to `rlmflow_segment::pup()`.
pub fn pup(s: &PupSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    rlmflow_nn::failure::catching(|| pup_on(s, ctx))
}

fn pup_on(s: &PupSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    let (placement, data) = prepare(&s.training, ctx, s.allow_test_overlap)?;
    let device = placement.device;
    let (_encoder_vs, encoder) = clip::load(ctx.input("encoder")?, device, data.frames.side)?;
    let vision = &encoder.config.vision;
    let widths = if s.channels.is_empty() { pup_widths(vision.grid(), data.frames.side) } else { s.channels.clone() };
    let vs = nn::VarStore::new(device);
    tch::manual_seed(ctx.seed as i64);
    let head = PupHead::new(&vs.root(), vision.width, &widths, data.frames.side);
    let tokens = Tokens::new(&encoder, &data.frames, device, ctx);
    let blocks: Vec<usize> = {
        let layers = vision.layers as usize;
        let take = if s.rollout_layers == 0 { layers } else { s.rollout_layers.min(layers) };
        (layers - take..layers).collect()
    };
    let segmenter = Segmenter { name: "pup", vs, forward: Box::new(move |frames: &[usize], train: bool| head.forward_t(&tokens.get(frames), train)) };
    let rollout = |frames: &[usize]| tch::no_grad(|| encoder.visual.attention_rollout(&data.frames.images(frames, device), blocks.len()));
    let segmentation = Segmentation { samples: s.samples, dice_weight: s.dice_weight, generator: s.result_settings() };
    train(&s.training, &segmentation, ctx, &data, placement, segmenter, Some((&blocks, &rollout)))
}

/// `unet`'s training, attached by the worker to `rlmflow_segment::unet()`.
pub fn unet(s: &UnetSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    rlmflow_nn::failure::catching(|| unet_on(s, ctx))
}

fn unet_on(s: &UnetSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    let (placement, data) = prepare(&s.training, ctx, false)?;
    let device = placement.device;
    s.check_depth(data.frames.side as u64)?;
    let vs = nn::VarStore::new(device);
    tch::manual_seed(ctx.seed as i64);
    let unet = UNet::new(&vs.root(), &s.channels);
    let frames = &data.frames;
    let segmenter =
        Segmenter { name: "unet", vs, forward: Box::new(move |batch: &[usize], train: bool| unet.forward_t(&frames.images(batch, device), train)) };
    let segmentation = Segmentation { samples: s.samples, dice_weight: s.dice_weight, generator: s.result_settings() };
    train(&s.training, &segmentation, ctx, &data, placement, segmenter, None)
}

/// Share of the training split held out as the validation slice the per-epoch log scores.
const VALIDATION_SHARE: f64 = 0.1;

/// The settings both segmenters have besides training.
struct Segmentation {
    samples: usize,
    dice_weight: f64,
    generator: Value,
}

/// The frames with their masks, their roles and the overlap counts.
struct Data {
    frames: Frames,
    split: Splits,
    hygiene: Vec<rlmflow_stages::identity::Overlap>,
}

fn prepare(t: &Training, ctx: &Context, allow_test_overlap: bool) -> anyhow::Result<(Placement, Data)> {
    tch::set_num_threads(t.threads as i32);
    let placement = Placement::of(t, ctx.device)?;
    let frames = Frames::load(ctx, Need { captions: false, masks: true })?;
    let hygiene = rlmflow_stages::identity::check_inputs(ctx, &frames.labels.ids(Split::Test), allow_test_overlap)?;
    let split = frames.splits(VALIDATION_SHARE, false);
    split.require("segmentation", true)?;
    Ok((placement, Data { frames, split, hygiene }))
}

/// The frozen encoder's tokens after `ln_post` for any frames: from a table of every frame's
/// when it fits in memory, else encoded on demand.
struct Tokens<'a> {
    encoder: &'a Model,
    frames: &'a Frames,
    device: tch::Device,
    table: Option<Tensor>,
}

impl<'a> Tokens<'a> {
    fn new(encoder: &'a Model, frames: &'a Frames, device: tch::Device, ctx: &Context) -> Tokens<'a> {
        let v = &encoder.config.vision;
        let count = frames.len() as i64;
        let bytes = count * (v.grid() * v.grid() + 1) * v.width * 4;
        let mut tokens = Tokens { encoder, frames, device, table: None };
        if bytes as u64 <= TOKEN_CACHE_BYTES {
            let all: Vec<usize> = (0..frames.len()).collect();
            let progress = ctx.progress(count as u64, "frames encoded");
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
        tch::no_grad(|| self.encoder.encode_image(&self.frames.images(frames, self.device), false).tokens)
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

/// Mask logits (batch, 1, side, side) of the frames at the given indices, in training mode or not.
type Forward<'a> = Box<dyn Fn(&[usize], bool) -> Tensor + 'a>;

/// A trainable head and how it maps frames to mask logits.
struct Segmenter<'a> {
    name: &'static str,
    vs: nn::VarStore,
    forward: Forward<'a>,
}

/// `scored` frames scored: pixel counts for the metrics, the mean loss and each frame's scores.
fn evaluate(
    segmenter: &Segmenter,
    frames: &Frames,
    scored: &[usize],
    device: tch::Device,
    dice_weight: f64,
) -> anyhow::Result<(PixelCounts, f64, Vec<FrameScore>)> {
    tch::no_grad(|| {
        let mut counts = PixelCounts::new();
        let mut loss = 0.0;
        let mut per_frame = Vec::with_capacity(scored.len());
        for batch in scored.chunks(CHUNK) {
            let logits = (segmenter.forward)(batch, false);
            loss += dice_bce_loss(&logits, &frames.masks(batch, device), dice_weight).double_value(&[]) * batch.len() as f64;
            let predicted = Vec::<f32>::try_from(logits.sigmoid().to_device(tch::Device::Cpu).to_kind(Kind::Float).flatten(0, -1))?;
            let n = (frames.side * frames.side) as usize;
            for (i, &f) in batch.iter().enumerate() {
                let (p, m) = (&predicted[i * n..(i + 1) * n], frames.mask(f));
                counts.add(p, m);
                per_frame.push(FrameScore::of(f as u64, p, m));
            }
        }
        Ok((counts, loss / scored.len() as f64, per_frame))
    })
}

type Rollout<'a> = (&'a [usize], &'a dyn Fn(&[usize]) -> Tensor);

fn train(
    t: &Training,
    segmentation: &Segmentation,
    ctx: &mut Context,
    data: &Data,
    placement: Placement,
    segmenter: Segmenter,
    rollout: Option<Rollout>,
) -> anyhow::Result<Outcome> {
    let (frames, device) = (&data.frames, placement.device);
    let batch_loss = |batch: &[usize], _: &mut EpochRng, _: &Backward| -> anyhow::Result<Step> {
        Ok(dice_bce_loss(&(segmenter.forward)(batch, true), &frames.masks(batch, device), segmentation.dice_weight).into())
    };
    let validation = || -> anyhow::Result<Figures> {
        let (counts, loss, _) = evaluate(&segmenter, frames, &data.split.validation, device, segmentation.dice_weight)?;
        let m = counts.metrics();
        Ok(vec![("validation_loss", loss), ("validation_iou", m.iou), ("validation_ap", m.ap)])
    };
    let fitted = fit(&segmenter.vs, Fit { training: t, placement, frames: &data.split.train, per_batch: false }, ctx, batch_loss, validation)?;
    let (counts, _, per_frame) = placement.forward(|| evaluate(&segmenter, frames, &data.split.test, device, segmentation.dice_weight))??;
    write_artifact(t, segmentation, ctx, data, &segmenter, rollout, fitted, (counts.metrics(), per_frame))
}

#[allow(clippy::too_many_arguments)]
fn write_artifact(
    t: &Training,
    segmentation: &Segmentation,
    ctx: &Context,
    data: &Data,
    segmenter: &Segmenter,
    rollout: Option<Rollout>,
    Fitted { log, steps }: Fitted,
    (metrics, per_frame): (SegMetrics, Vec<FrameScore>),
) -> anyhow::Result<Outcome> {
    let out = &ctx.output_dir;
    let lines: Vec<String> = per_frame.iter().map(|f| serde_json::to_string(f).map(|l| l + "\n")).collect::<Result<_, _>>()?;
    std::fs::write(out.join(segment::FRAMES), lines.concat())?;
    let test = &data.split.test;
    let n = segmentation.samples.min(test.len());
    let samples: Vec<usize> = (0..n).map(|i| test[i * test.len() / n]).collect();
    let side = data.frames.side as usize;
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
        train_frames: data.split.train.len() as u64,
        test_frames: test.len() as u64,
        hygiene: data.hygiene.clone(),
        epochs: t.epochs,
        steps,
        metrics: metrics.clone(),
        log,
        sample_frames: samples.iter().map(|&f| f as u64).collect(),
        rollout_blocks: blocks,
        generator: segmentation.generator.clone(),
    };
    std::fs::write(out.join(segment::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    let m = &metrics;
    Ok(Outcome {
        metrics: json!({"precision": m.precision, "recall": m.recall, "iou": m.iou, "dice": m.dice, "peak_iou": m.peak_iou, "ap": m.ap, "positive_rate": m.positive_rate}),
        summary: format!(
            "{} test frames: IoU {:.3} Dice {:.3} peak IoU {:.3} AP {:.3} (positive rate {:.3})",
            test.len(),
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
