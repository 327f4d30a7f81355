//! `script`: a stage whose work is a user's program, for any kind whose output rlmflow can
//! check (`probe`, `segment`, `files`).
//!
//! The engine keys it like any stage: its settings (the command, `settings`, the Python
//! environment's identity), its inputs, its seed, and by content the files its command and
//! `sources` name (a snapshot the program runs in, so every source byte it reads is in its key)
//! and its `environment` lock. The program is told where everything is through the environment
//! and `$RLMFLOW_STAGE`, a JSON file ([`program`]); it reports through `@rlmflow {json}` lines on
//! its stdout ([`protocol`]); what it writes is checked against its kind, and a probe's or a
//! segmenter's predictions are scored here with the paper's rule, before anything is committed
//! ([`output`]). docs/guide/your-own-stage.md is the user's page.

mod output;
mod program;
mod protocol;

use rlmflow_stages::{Context, Device, FilePattern, Operator, OperatorSpec, Outcome, Resources, SettingError, Settings};
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

/// The kinds a script may implement: those whose output rlmflow checks before committing it.
pub const KINDS: [&str; 3] = ["probe", "segment", "files"];

/// The script operator of one stage kind.
pub struct Script {
    kind: &'static str,
}

/// One script operator per kind of [`KINDS`], for `Registry::add_for_kind`.
pub fn operators() -> impl Iterator<Item = Script> {
    KINDS.into_iter().map(|kind| Script { kind })
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ScriptSettings {
    /// The command: a program and its arguments. `python` (or `python3`) is the stage's Python
    /// environment's interpreter; a program or argument naming a file of the pipeline's tree is
    /// a source (run from the snapshot); any other program is looked up on `PATH`.
    pub run: Vec<String>,
    /// Globs, relative to the pipeline file, of the files the program reads besides those `run`
    /// names: their bytes enter the key, and only they are in the directory it runs in.
    pub sources: Vec<String>,
    /// A pinned Python environment (`name==version` lines, every dependency pinned), relative to
    /// the pipeline file; empty: rlmflow's own (numpy, safetensors, tokenizers, `rlmflow`).
    pub environment: String,
    /// Passed to the program as they are (`$RLMFLOW_STAGE`'s `settings`).
    pub settings: Map<String, Value>,
    /// What the program is given: `cpu`, or `cuda`/`cuda:N` (`CUDA_VISIBLE_DEVICES`).
    pub device: Device,
    /// Threads the program may use (`$RLMFLOW_THREADS`, `OMP_NUM_THREADS`); not in the key.
    pub threads: usize,
    /// Filled in by rlmflow: the interpreter's `major.minor` and its environment's lock digest,
    /// so a key changes with the Python the program runs on.
    pub python: String,
    /// A probe or segmenter whose test frames overlap what its encoder learnt from is refused
    /// unless this is set (the report then flags it).
    pub allow_test_overlap: bool,
}

impl Default for ScriptSettings {
    fn default() -> Self {
        ScriptSettings {
            run: Vec::new(),
            sources: Vec::new(),
            environment: String::new(),
            settings: Map::new(),
            device: Device::Cpu,
            threads: 1,
            python: rlmflow_python::identity(),
            allow_test_overlap: false,
        }
    }
}

impl Settings for ScriptSettings {
    const NON_RESULT: &'static [&'static str] = &["threads"];
    const TRACKED: &'static [&'static str] = &["sources", "environment"];

    fn check(&self) -> Result<(), SettingError> {
        match self.run.first() {
            None => return Err(SettingError::new("run", "name the program and its arguments, e.g. [\"python\", \"probes/knn.py\"]")),
            Some(program) if program.trim().is_empty() => return Err(SettingError::new("run", "the program (its first item) is empty")),
            _ => {}
        }
        if self.python != rlmflow_python::identity() {
            return Err(SettingError::new("python", "is filled in by rlmflow (the interpreter and its environment); remove it"));
        }
        if self.device == Device::Auto {
            return Err(SettingError::new("device", "must be cpu, cuda or cuda:N: the program is told which"));
        }
        SettingError::check_range("threads", self.threads, 1..=256)
    }

    fn tracked_files(&self, key: &str) -> Option<Vec<FilePattern>> {
        (key == "sources").then(|| {
            let named = self.run.iter().map(|arg| FilePattern { pattern: arg.clone(), required: false });
            named.chain(self.sources.iter().map(|glob| FilePattern { pattern: glob.clone(), required: true })).collect()
        })
    }
}

impl Operator for Script {
    type Settings = ScriptSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "script",
            kind: self.kind,
            version: 1,
            inputs: None,
            summary: match self.kind {
                "probe" => "your program predicts each test frame's grid (predictions.jsonl); rlmflow scores it as every probe",
                "segment" => "your program predicts each test frame's mask (predictions.npy); rlmflow scores it as every segmenter",
                _ => "your program writes files no built-in stage reads (a table, a figure, an export)",
            },
        }
    }

    fn resources(&self, s: &ScriptSettings) -> Resources {
        let cuda = matches!(s.device, Device::Cuda(_));
        Resources { threads: s.threads, gpu: cuda, needs_cuda: cuda, kernels: None }
    }

    fn resumes_from(&self) -> &'static str {
        "its checkpoint directory, where the program left it"
    }

    fn run(&self, s: &ScriptSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let reported = program::run(s, ctx)?;
        output::check(self.kind, s, ctx, reported)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_and_sources_are_what_is_tracked_and_python_is_not_settable() {
        let s = ScriptSettings { run: vec!["python".into(), "probes/knn.py".into()], sources: vec!["probes/*.py".into()], ..Default::default() };
        assert_eq!(s.check(), Ok(()));
        let patterns = s.tracked_files("sources").unwrap();
        assert_eq!(
            patterns.iter().map(|p| (p.pattern.as_str(), p.required)).collect::<Vec<_>>(),
            [("python", false), ("probes/knn.py", false), ("probes/*.py", true)]
        );
        assert_eq!(s.tracked_files("environment"), None, "the lock is one path");
        assert_eq!(ScriptSettings::default().check().unwrap_err().key, "run");
        let set = ScriptSettings { python: "3.99 0000".into(), ..s.clone() };
        assert_eq!(set.check().unwrap_err().key, "python");
        assert_eq!(ScriptSettings { device: Device::Auto, ..s }.check().unwrap_err().key, "device");
    }
}
