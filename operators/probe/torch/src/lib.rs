//! The probes on a frozen encoder, on libtorch (they run in the `rlmflow-torch` worker). See
//! `rlmflow_probe` for what each does; the scoring rule is `rlmflow_stages::probe::score`.

mod caption_text;
mod clipcap;
mod embed;
mod ridge;

use std::path::Path;

use anyhow::bail;
use rlmflow_nn::clip;
use rlmflow_nn::data::{Frames, Need, Splits};
use rlmflow_nn::tch::{self, Kind, Tensor};
use rlmflow_probe::{LinearSettings, Source};
use rlmflow_stages::grid::CELLS;
use rlmflow_stages::identity::Split;
use rlmflow_stages::probe::{self, Row, Summary, score};
use rlmflow_stages::{Context, Outcome, Settings};
use serde_json::json;

pub use clipcap::{clipcap, score_captions};
pub use embed::embed;
use ridge::RidgeProblem;

/// `linear`'s training, attached by the worker to `rlmflow_probe::linear()`.
pub fn linear(s: &LinearSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    rlmflow_nn::failure::catching(|| linear_on(s, ctx))
}

fn linear_on(s: &LinearSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
    tch::set_num_threads(s.threads as i32);
    let data = Frames::load(ctx, Need::default())?;
    let labels = &data.labels;
    let hygiene = rlmflow_stages::identity::check_inputs(ctx, &labels.ids(Split::Test), s.allow_test_overlap)?;
    let encoder = ctx.optional_input("encoder").map(Path::to_path_buf);
    let all: Vec<usize> = (0..data.len()).collect();
    let features: Vec<(&str, Vec<f64>, usize)> = match (s.source, &encoder) {
        (Source::Pixels, _) => {
            let side = data.side as usize;
            vec![("pixels", data.pixels(&all).into_iter().map(f64::from).collect(), side * side)]
        }
        (Source::Encoder, Some(dir)) => encoder_features(dir, &data, &all, ctx)?,
        (Source::Encoder, None) => bail!("source = \"encoder\" needs an encoder input; use source = \"pixels\" for the pixel baseline"),
    };
    let counts: Vec<f64> = labels.frames.iter().flat_map(|f| f.grid.counts.iter().map(|&c| f64::from(c))).collect();
    // The strength is chosen fitting `fit` and scoring `validate`; the chosen ridge is then
    // refitted on the whole training split.
    let split = data.splits(s.holdout, false);
    split.require("a validated strength choice (`holdout` is the validation share)", true)?;
    let Splits { train: fit, validation: validate, test } = split;
    let train: Vec<usize> = labels.split(Split::Train).map(|f| f.frame as usize).collect();
    let (fit, validate) = (fit.as_slice(), validate.as_slice());
    let truth = |frames: &[usize]| -> Vec<[u32; CELLS]> { frames.iter().map(|&f| labels.frames[f].grid.counts).collect() };

    let progress = ctx.progress((features.len() * (s.lambdas.len() + 1)) as u64, "ridge fits");
    let mut rows = Vec::new();
    let mut predictions = String::new();
    for (name, x, width) in &features {
        let rows_of = |data: &[f64], w: usize, frames: &[usize]| -> Vec<f64> {
            frames.iter().flat_map(|&f| data[f * w..(f + 1) * w].iter().copied()).collect()
        };
        // The strength with the best held-out F1 (the first of equals).
        let mut best: Option<(f64, f64)> = None;
        let problem = RidgeProblem::new(&rows_of(x, *width, fit), *width, &rows_of(&counts, CELLS, fit), CELLS);
        let held_out = rows_of(x, *width, validate);
        for &lambda in &s.lambdas {
            let ridge = problem.solve(lambda)?;
            let f1 = score(&round(&ridge.predict(&held_out)), &truth(validate)).overall.f1;
            if best.is_none_or(|(_, b)| f1 > b) {
                best = Some((lambda, f1));
            }
            progress.inc(1);
        }
        let (lambda, held_f1) = best.expect("at least one strength");
        let ridge = RidgeProblem::new(&rows_of(x, *width, &train), *width, &rows_of(&counts, CELLS, &train), CELLS).solve(lambda)?;
        let predicted = round(&ridge.predict(&rows_of(x, *width, &test)));
        progress.inc(1);
        for (&frame, grid) in test.iter().zip(&predicted) {
            let grid = rlmflow_stages::grid::Grid { counts: *grid, walkers: 0, signs: Vec::new() };
            predictions.push_str(&format!("{{\"frame\":{frame},\"features\":\"{name}\",\"grid\":{}}}\n", grid.to_json()));
        }
        let scores = score(&predicted, &truth(&test));
        ctx.event("row", json!({"features": name, "lambda": lambda, "f1": scores.overall.f1}));
        rows.push(Row { features: name.to_string(), details: json!({"lambda": lambda, "held_out_f1": held_f1, "features": width}), scores });
    }
    progress.finish();
    let summary = Summary {
        format: probe::FORMAT,
        probe: "linear".into(),
        train_frames: train.len() as u64,
        test_frames: test.len() as u64,
        hygiene,
        rows: rows.clone(),
        generator: s.result_settings(),
    };
    std::fs::write(ctx.output_dir.join(probe::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    std::fs::write(ctx.output_dir.join(probe::PREDICTIONS), predictions)?;
    let text: Vec<String> = rows.iter().map(|r| format!("{} F1 {:.3}", r.features, r.scores.overall.f1)).collect();
    let metrics = json!(
        rows.iter()
            .map(|r| (
                r.features.clone(),
                json!({"f1": r.scores.overall.f1, "precision": r.scores.overall.precision, "recall": r.scores.overall.recall})
            ))
            .collect::<serde_json::Map<_, _>>()
    );
    Ok(Outcome { metrics, summary: format!("{} test frames: {}", test.len(), text.join(", ")) })
}

/// Predicted counts: rounded, at least zero.
fn round(predictions: &[f64]) -> Vec<[u32; CELLS]> {
    predictions.chunks_exact(CELLS).map(|row| std::array::from_fn(|c| row[c].round().max(0.0) as u32)).collect()
}

/// Every frame's projected CLS embedding, mean patch token and patch tokens in grid order (the
/// spatial layout kept) from the frozen encoder, each flat as the ridge reads it.
fn encoder_features(dir: &Path, data: &Frames, all: &[usize], ctx: &Context) -> anyhow::Result<Vec<(&'static str, Vec<f64>, usize)>> {
    let mut rows = Vec::new();
    for (name, t) in frozen_features(dir, data, all, ctx)? {
        let t = t.flatten(1, -1).to_kind(Kind::Double);
        let width = t.size()[1] as usize;
        rows.push((name, Vec::<f64>::try_from(t.flatten(0, -1))?, width));
    }
    Ok(rows)
}

/// The frozen encoder's features of frames `all` on the CPU in float32: `cls` (frames, embed),
/// `mean-patch` (frames, width) and `patches` (frames, tokens, width), in grid order.
fn frozen_features(dir: &Path, data: &Frames, all: &[usize], ctx: &Context) -> anyhow::Result<[(&'static str, Tensor); 3]> {
    let device = rlmflow_nn::train::resolve_device(ctx.device, rlmflow_stages::Device::Cpu)?;
    let (_vs, model) = clip::load(dir, device, data.side)?;
    let (mut cls, mut means, mut patches) = (Vec::new(), Vec::new(), Vec::new());
    let progress = ctx.progress(all.len() as u64, "frames embedded");
    tch::no_grad(|| {
        for frames in all.chunks(256) {
            let out = model.encode_image(&data.images(frames, device), false);
            let tokens = out.tokens.narrow(1, 1, out.tokens.size()[1] - 1);
            let mean = tokens.mean_dim([1].as_slice(), false, Kind::Float);
            cls.push(out.embedding.to_kind(Kind::Float).to_device(tch::Device::Cpu));
            means.push(mean.to_kind(Kind::Float).to_device(tch::Device::Cpu));
            patches.push(tokens.to_kind(Kind::Float).to_device(tch::Device::Cpu));
            progress.inc(frames.len() as u64);
        }
    });
    progress.finish();
    Ok([("cls", Tensor::cat(&cls, 0)), ("mean-patch", Tensor::cat(&means, 0)), ("patches", Tensor::cat(&patches, 0))])
}
