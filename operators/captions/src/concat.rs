//! The `concat-captions` operator (kind `mix-captions`): one Captions artifact holding the
//! captions of several that caption disjoint frames of one labelling, in the order the engine
//! gathers them, each input's frames after the last input's. This is how the engine merges the
//! shares of a sharded `llm` stage.
//!
//! The summary's `generator` is the whole's when the inputs are the shares of one `llm` stage in
//! order (`llm::join_shares`), so the bytes are those of one action captioning every frame;
//! otherwise it lists each input's generator and frame count.

use anyhow::{Context as _, bail};
use rlmflow_stages::captions::Captions;
use rlmflow_stages::{Context, Operator, OperatorSpec, Outcome, Settings};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::llm::join_shares;
use crate::write_captions;

pub struct ConcatCaptions;

#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ConcatCaptionsSettings {}

impl Settings for ConcatCaptionsSettings {}

impl Operator for ConcatCaptions {
    type Settings = ConcatCaptionsSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "concat-captions",
            kind: "mix-captions",
            version: 2,
            inputs: None,
            summary: "the captions of several Captions artifacts of disjoint frames, one after another, as one",
        }
    }

    fn run(&self, _: &ConcatCaptionsSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let inputs = ctx.gathered("captions");
        if inputs.is_empty() {
            bail!("`concat-captions` needs at least one captions input (set `inputs = {{ captions = [...] }}`)");
        }
        let progress = ctx.progress(inputs.len() as u64, "inputs");
        let mut frames = 0;
        let mut captions = Vec::new();
        let mut generators = Vec::new();
        let mut last: Option<(&str, u64)> = None;
        for input in inputs {
            let part = Captions::open(&input.path).with_context(|| format!("opening the captions of `{}`", input.label))?;
            if let (Some((before, end)), Some(first)) = (last, part.captions.first())
                && first.frame <= end
            {
                bail!(
                    "`{}` captions frame {} but `{before}` already captioned frame {end}: the inputs of `concat-captions` must caption disjoint frames, each after the last",
                    input.label,
                    first.frame
                );
            }
            if let Some(c) = part.captions.last() {
                last = Some((input.label.as_str(), c.frame));
            }
            frames += part.summary.frames;
            captions.extend(part.captions);
            generators.push(json!({"frames": part.summary.frames, "generator": part.summary.generator}));
            progress.inc(1);
        }
        let parts: Vec<&Value> = generators.iter().map(|g| &g["generator"]).collect();
        let joined = join_shares(&parts);
        let summary = format!(
            "{} captions of {frames} frames from {} inputs{}",
            captions.len(),
            inputs.len(),
            if joined.is_some() { " (the shares of one llm stage, joined)" } else { "" }
        );
        write_captions(&ctx.output_dir, frames, &captions, joined.unwrap_or_else(|| json!({"parts": generators})))?;
        progress.finish();
        Ok(Outcome { metrics: json!({"inputs": inputs.len(), "frames": frames, "captions": captions.len()}), summary })
    }
}
