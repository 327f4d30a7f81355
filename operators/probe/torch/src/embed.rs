//! `embed`'s work, attached by the worker to `rlmflow_probe::embed()`: the frozen encoder's
//! features of every frame as `.npy` arrays (`rlmflow_stages::embeddings`).

use rlmflow_nn::data::{Frames, Need};
use rlmflow_nn::tch::Tensor;
use rlmflow_probe::EmbedSettings;
use rlmflow_stages::embeddings::{self, Frame, Summary};
use rlmflow_stages::encoder::{TOKENIZER_FRAMES, TRAINED};
use rlmflow_stages::identity::Split;
use rlmflow_stages::npy::{Dtype, NpyWriter};
use rlmflow_stages::{Context, Outcome, Settings};
use serde_json::json;

pub fn embed(s: &EmbedSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    rlmflow_nn::failure::catching(|| embed_on(s, ctx))
}

fn embed_on(s: &EmbedSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    rlmflow_nn::tch::set_num_threads(s.threads as i32);
    let data = Frames::load(ctx, Need::default())?;
    let encoder = ctx.input("encoder")?.to_path_buf();
    let all: Vec<usize> = (0..data.len()).collect();
    let out = ctx.output_dir.clone();
    let mut arrays = std::collections::BTreeMap::new();
    for (name, features) in super::frozen_features(&encoder, &data, &all, ctx)? {
        let file = match name {
            "cls" => embeddings::CLS,
            "mean-patch" => embeddings::MEAN_PATCH,
            _ if s.patches => embeddings::PATCHES,
            _ => continue,
        };
        let shape: Vec<usize> = features.size().iter().map(|&d| d as usize).collect();
        write(&out.join(file), &features, &shape)?;
        arrays.insert(file.to_owned(), shape);
    }
    let mut lines = String::new();
    for label in &data.labels.frames {
        let frame = Frame { frame: label.frame, id: label.id.clone(), split: label.split };
        lines.push_str(&(serde_json::to_string(&frame)? + "\n"));
    }
    std::fs::write(out.join(embeddings::FRAMES), lines)?;
    for set in [TRAINED, TOKENIZER_FRAMES] {
        if encoder.join(set).exists() {
            std::fs::copy(encoder.join(set), out.join(set))?;
        }
    }
    let summary = Summary {
        format: embeddings::FORMAT,
        frames: data.len() as u64,
        train_frames: data.labels.split(Split::Train).count() as u64,
        test_frames: data.labels.split(Split::Test).count() as u64,
        arrays: arrays.clone(),
        generator: s.result_settings(),
    };
    std::fs::write(out.join(embeddings::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    let shapes: Vec<String> = arrays.iter().map(|(f, shape)| format!("{f} {shape:?}")).collect();
    Ok(Outcome { metrics: json!({ "arrays": arrays }), summary: format!("{} frames: {}", data.len(), shapes.join(", ")) })
}

/// `features` (float32 on the CPU, frames first) as a `.npy` array of `shape`.
fn write(path: &std::path::Path, features: &Tensor, shape: &[usize]) -> anyhow::Result<()> {
    let mut writer = NpyWriter::create(path, Dtype::F32, shape[0], &shape[1..])?;
    for row in 0..shape[0] {
        writer.write_f32(&Vec::<f32>::try_from(features.get(row as i64).flatten(0, -1))?)?;
    }
    writer.finish()
}
