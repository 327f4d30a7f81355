//! The shipped pipelines and operators through the real `rlmflow` binary, one file per topic:
//! the shipped pipelines validate and refuse what cannot run (`shipped`), the CI pipeline end to
//! end and its results read from outside (`ci`), the caption parser and setup on the command line
//! (`commands`), the plan drawn (`dag`), sharded real operators (`shards`), highway-env's
//! determinism (`highway`), evaluation hygiene (`hygiene`), every setting's effect on the key
//! (`settings`), the generated operator reference (`reference`), dataset imports (`import`,
//! `datasets`), a user's program as a stage (`script`) and mutated inputs (`fuzz`).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use rlmflow_test_support::Scratch;
use rlmflow_test_support::openai::{FakeOpenAi, Response};

#[path = "pipelines/ci.rs"]
mod ci;
#[path = "pipelines/claims.rs"]
mod claims;
#[path = "pipelines/commands.rs"]
mod commands;
#[path = "pipelines/dag.rs"]
mod dag;
#[path = "pipelines/datasets.rs"]
mod datasets;
#[path = "pipelines/fuzz.rs"]
mod fuzz;
#[path = "pipelines/highway.rs"]
mod highway;
#[path = "pipelines/hygiene.rs"]
mod hygiene;
#[path = "pipelines/import.rs"]
mod import;
#[path = "pipelines/reference.rs"]
mod reference;
#[path = "pipelines/script.rs"]
mod script;
#[path = "pipelines/settings.rs"]
mod settings;
#[path = "pipelines/shards.rs"]
mod shards;
#[path = "pipelines/shipped.rs"]
mod shipped;

/// Runs `rlmflow ARGS` in `dir`: success and everything it printed.
fn rlmflow(dir: &Path, args: &[&str]) -> (bool, String) {
    rlmflow_test_support::cli::run(Path::new(env!("CARGO_BIN_EXE_rlmflow")), dir, args)
}

/// The repository (the shipped pipelines and examples).
fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// A scratch directory holding `p.toml` with `pipeline`.
fn scratch(name: &str, pipeline: &str) -> Scratch {
    Scratch::with_pipeline(name, pipeline)
}

/// The output digest of stage `label` of `pipeline` in the store beside `dir`'s pipeline.
fn output_digest(dir: &Path, pipeline: &str, label: &str) -> rlmflow_cache::Digest {
    rlmflow_test_support::cli::output_digest(&dir.join(".rlmflow"), pipeline, label)
}

/// An OpenAI-compatible endpoint answering every request with `n` copies of one caption per
/// frame prompt (the grid's first number words, so answers differ between frames).
fn fake_llm() -> FakeOpenAi {
    FakeOpenAi::start(|request| {
        let words: Vec<&str> = request.prompt().split('"').filter(|w| !w.is_empty() && w.chars().all(|c| c.is_ascii_lowercase())).take(6).collect();
        Response::captions(&vec![format!("The scene holds {}.", words.join(" ")); request.n()])
    })
}

/// The artifact directories in a store that hold `file`.
fn artifacts(objects: &Path, file: &str) -> Vec<PathBuf> {
    let mut found = Vec::new();
    for shard in std::fs::read_dir(objects).unwrap() {
        for object in std::fs::read_dir(shard.unwrap().path()).unwrap() {
            let path = object.unwrap().path();
            if path.join(file).exists() {
                found.push(path);
            }
        }
    }
    found
}
