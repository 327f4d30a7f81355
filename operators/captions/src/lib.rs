//! The `captions` stage kind's operators: `template` composes captions from the grid; `llm` asks
//! any OpenAI-compatible chat-completions endpoint with the paper's prompts and checks every
//! answer with the LLM-free parser. Both write the same Captions artifact. `concat-captions`
//! (kind `mix-captions`) joins Captions artifacts of disjoint frames: the shares of a sharded
//! `llm` stage.

mod concat;
mod llm;
mod template;

use std::path::Path;

use rlmflow_stages::captions::{self, Caption};

pub use concat::{ConcatCaptions, ConcatCaptionsSettings};
pub use llm::{Llm, LlmSettings, NO_NUMBERS, OnMismatch, SYSTEM_PROMPT, user_prompt};
pub use template::{Template, TemplateSettings, VARIANTS, caption, caption_variant};

/// Writes the Captions artifact: the lines, then the summary.
fn write_captions(dir: &Path, frames: u64, captions: &[Caption], generator: serde_json::Value) -> anyhow::Result<()> {
    let lines: String = captions.iter().map(|c| c.to_line() + "\n").collect();
    std::fs::write(dir.join(captions::LINES), lines)?;
    let summary = captions::Summary { format: captions::FORMAT, frames, captions: captions.len() as u64, generator };
    std::fs::write(dir.join(captions::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
    Ok(())
}
