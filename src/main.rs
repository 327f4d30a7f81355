use std::process::ExitCode;

mod doctor;
mod parse;

use rlmflow_stages::{Catalog, Registry};

/// The operators this binary ships. Each operator family registers itself here.
fn registry() -> Registry {
    let mut registry = Registry::new(Catalog::paper());
    registry.add(rlmflow_scenes::Procedural);
    registry.add(rlmflow_scenes::Import);
    registry.add(rlmflow_scenes::Concat);
    registry.add(rlmflow_labels::EgoGrid);
    registry.add(rlmflow_captions::Template);
    registry.add(rlmflow_captions::Llm);
    registry.add(rlmflow_captions::ConcatCaptions);
    registry.add(rlmflow_tokens::Bpe);
    // Planned here, run by the rlmflow-torch worker.
    registry.add(rlmflow_pretrain::operator());
    registry.add(rlmflow_probe::linear());
    registry.add(rlmflow_probe::clipcap());
    registry.add(rlmflow_probe::embed());
    registry.add(rlmflow_segment::pup());
    registry.add(rlmflow_segment::unet());
    registry.add(rlmflow_report::Paper);
    // A user's program as a stage of each kind whose output rlmflow checks.
    for script in rlmflow_script::operators() {
        registry.add_for_kind(script);
    }
    #[cfg(feature = "python")]
    registry.add(rlmflow_scenes::HighwayEnv);
    registry
}

fn main() -> ExitCode {
    rlmflow_engine::cli::main(registry(), &[parse::command(), doctor::command()])
}
