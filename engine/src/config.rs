//! `pipeline.toml`: parsing, validation against the registry, and diagnostics that name the
//! file, line and key, say what is valid, and suggest the nearest name.
//!
//! Everything here runs before any stage does: unknown keys, operators and stage names, bad
//! setting values, missing or ambiguous inputs, artifact type mismatches and cycles are all
//! reported together. What each part checks has its own file: the pipeline header
//! (`header`, `hyperqueue`), the stages and their bindings (`stages`), the graph (`graph`);
//! `checker` holds the diagnostics and the TOML reading they share.

mod checker;
mod claims;
mod diagnostic;
mod graph;
mod header;
mod hyperqueue;
mod overrides;
mod stages;

pub use checker::ConfigError;
pub use diagnostic::Diagnostic;
pub use graph::{Dims, dimensions};
use header::Header;
pub use header::{Executor, RemoteSettings, SIGNING_KEY_VARIABLE, SeedRule, resolve_remote};
pub use hyperqueue::{HyperQueueSettings, WorkerStore};

use checker::{Checker, line_starts, to_json_table};
use diagnostic::{MAX_DEPTH, too_deep};
pub use overrides::Override;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use rlmflow_stages::{Arity, Parsed, Part, Registry, StageKind};

use serde_json::{Map, Value};
use toml::de::DeTable;

/// A validated pipeline: stages in dependency order, every input bound.
#[derive(Debug)]
pub struct Pipeline {
    pub file: PathBuf,
    pub name: String,
    pub seed: u64,
    /// `[pipeline] seeds`: every per-seed stage runs once per entry (empty: once, with `seed`).
    /// Under a [`SeedRule`], the seeds of the look at hand ([`Pipeline::with_seeds`]).
    pub seeds: Vec<u64>,
    /// `seeds = { min, max, until = "claims" }`: seeds are added until every claim is decided.
    pub seed_rule: Option<SeedRule>,
    /// `[claims]`, resolved against the stages.
    pub claims: Option<rlmflow_stages::claims::Spec>,
    /// The store directory (relative paths in the file are relative to the file).
    pub cache: PathBuf,
    /// `[pipeline] results`: where a run links each instance to its current output
    /// (`results/report/`); `None` for `results = ""`.
    pub results: Option<PathBuf>,
    pub executor: Executor,
    /// `[pipeline] gpus` or `run --gpus`: the GPUs (by the driver's index) a local run places
    /// stages on; `None`: every GPU it sees.
    pub gpus: Option<Vec<usize>>,
    /// `[pipeline.hyperqueue]`, also used when `run --executor hyperqueue` overrides a local one.
    pub hyperqueue: HyperQueueSettings,
    /// `[pipeline] remote`, `remote_push`, `remote_timeout_s`: the remote cache, if any.
    pub remote: RemoteSettings,
    pub stages: Vec<Stage>,
    /// The line of every key the file spells out, for errors found after validation.
    pub lines: KeyLines,
    /// The command line's `--set STAGE.KEY=VALUE`s, applied over the file in order.
    pub overrides: Vec<Override>,
}

/// The line of each key of a pipeline file, by dotted path.
#[derive(Debug, Default)]
pub struct KeyLines(HashMap<String, usize>);

impl KeyLines {
    /// The line of `path`, or of its nearest ancestor the file spells out.
    pub fn line(&self, path: &str) -> usize {
        let mut p = path;
        loop {
            if let Some(&l) = self.0.get(p) {
                return l;
            }
            match p.rfind('.') {
                Some(i) => p = &p[..i],
                None => return 1,
            }
        }
    }
}

#[derive(Debug)]
pub struct Stage {
    pub name: String,
    pub kind: StageKind,
    pub operator: String,
    /// One entry per variant; a stage without variants has one unnamed entry.
    pub variants: Vec<Variant>,
    pub bindings: Vec<Binding>,
    /// Runs once per seed of `[pipeline] seeds` (its kind's default, or its `per_seed` key).
    pub per_seed: bool,
    /// How the parts of a sharded stage (`shards` or `shard_size`) join into its artifact.
    pub merge: Option<Merge>,
    /// `timeout` and `retries`: outside the key, like the executor.
    pub bounds: Bounds,
    pub line: usize,
}

/// How long each attempt of a stage's actions may take, and how many more attempts a failed or
/// timed-out one gets.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Bounds {
    /// Wall-clock seconds; none: unbounded.
    pub timeout_s: Option<f64>,
    pub retries: u32,
}

#[derive(Clone, Debug)]
pub struct Variant {
    pub name: Option<String>,
    /// Every setting, defaults filled in, parsed once.
    pub settings: Parsed,
    /// A sharded stage's parts: the items each computes and its settings, in order.
    pub shards: Vec<(Part, Parsed)>,
    /// The files or directories outside the store it reads, by setting (`Settings::TRACKED`),
    /// made absolute against the pipeline file.
    pub tracked: Vec<(String, rlmflow_cache::external::Source)>,
}

/// The action that joins a sharded stage's parts: an operator gathering them, in order, into one
/// artifact of the stage's type.
#[derive(Clone, Debug)]
pub struct Merge {
    pub operator: String,
    pub slot: &'static str,
    pub settings: Parsed,
}

/// An input slot bound to the stages that provide it (indices into `Pipeline::stages`).
#[derive(Clone, Debug)]
pub struct Binding {
    pub slot: &'static str,
    pub arity: Arity,
    pub providers: Vec<usize>,
}

impl Pipeline {
    /// Under a [`SeedRule`], the pipeline at its look after `n` seeds (every count is valid
    /// config: the plan's size was checked at the rule's `max`).
    pub fn with_seeds(&mut self, n: usize) {
        if let Some(rule) = self.seed_rule {
            self.seeds = rule.seeds(n.clamp(rule.min, rule.max));
        }
    }

    pub fn stage(&self, name: &str) -> Option<usize> {
        self.stages.iter().position(|s| s.name == name)
    }

    pub fn stage_names(&self) -> Vec<&str> {
        self.stages.iter().map(|s| s.name.as_str()).collect()
    }

    /// Setting `key` (dotted, relative to the stage table) of a stage's variant, located as
    /// validation errors are: `p.toml:12: stages.pretrain.variants.alpha4.batch`, the variant's
    /// line where the variant sets the key, else the stage's; `p.toml with --set pretrain.batch=8:
    /// stages.pretrain.batch` where the command line set it.
    pub fn locate(&self, stage: &str, variant: Option<&str>, key: &str) -> String {
        let top = key.split('.').next().unwrap_or_default();
        let path = match variant {
            Some(v) if self.lines.0.contains_key(&format!("stages.{stage}.variants.{v}.{top}")) => format!("stages.{stage}.variants.{v}.{key}"),
            _ if key.is_empty() => format!("stages.{stage}"),
            _ => format!("stages.{stage}.{key}"),
        };
        match Override::setting(&self.overrides, &path) {
            Some(o) => format!("{} with {}: {path}", self.file.display(), o.shown()),
            None => format!("{}:{}: {path}", self.file.display(), self.lines.line(&path)),
        }
    }
}

/// How a label names an instance's seed: `pretrain[alpha4,seed=2]`.
pub const SEED_LABEL: &str = "seed";
/// The default of `[pipeline] max_instances`: the most instances (variants, seeds and shards
/// fanned out) a plan may have, checked before it is expanded. The paper's pipelines have tens.
pub const MAX_INSTANCES: u64 = 10_000;
/// The most `[pipeline] max_instances` may raise the bound to: a plan this large still fits in
/// a few hundred megabytes (a larger one would exhaust memory while it is expanded).
pub const INSTANCES_CEILING: u64 = 100_000;

/// The longest pipeline, stage, variant or pin name: names become file names in the store.
pub const MAX_NAME: usize = 128;

/// Reads and validates a pipeline file.
pub fn load(file: &Path, registry: &Registry) -> anyhow::Result<Pipeline> {
    load_with(file, &[], &[], registry)
}

/// Reads a pipeline file, applies the overrides `set` and `set_new` (`STAGE.KEY=VALUE` or
/// `pipeline.KEY=VALUE`, the value in TOML; `set_new` may make a variant) over it and validates
/// the result as if the file said so; an error in an overridden key names the override.
pub fn load_with(file: &Path, set: &[String], set_new: &[String], registry: &Registry) -> anyhow::Result<Pipeline> {
    let bytes = std::fs::read(file).map_err(|e| anyhow::anyhow!("cannot read pipeline {}: {e}", file.display()))?;
    let text = match String::from_utf8(bytes) {
        Ok(text) => text,
        Err(e) => {
            let bytes = e.as_bytes();
            let at = e.utf8_error().valid_up_to();
            let line = 1 + bytes[..at].iter().filter(|&&b| b == b'\n').count();
            let column = 1 + at - bytes[..at].iter().rposition(|&b| b == b'\n').map_or(0, |p| p + 1);
            let message = format!("not UTF-8 text: byte 0x{:02X} at column {column}; a pipeline file must be UTF-8", bytes[at]);
            return Err(ConfigError {
                file: file.to_path_buf(),
                diagnostics: vec![Diagnostic { line, key: String::new(), message, help: None }],
                overrides: Vec::new(),
            }
            .into());
        }
    };
    parse_with(file, &text, set, set_new, registry).map_err(anyhow::Error::new)
}

/// Checks a pipeline, stage, variant or pin name; the error says what is wrong. Names become file
/// names and the labels every listing, log and provenance table shows (`probe[pretrain=alpha4]`,
/// `scenes#2`), so they hold letters, digits, `-`, `_` and `.` only, and begin with neither `.`
/// nor `-`: a name can then neither climb out of a folder nor forge a row or a label.
pub fn check_name(name: &str) -> Result<(), String> {
    const VALID: &str = "valid: ASCII letters, digits, `-`, `_` and `.`, not first `.` or `-`";
    if name.is_empty() {
        return Err("must not be empty".into());
    }
    if name.len() > MAX_NAME {
        return Err(format!("is {} bytes long; at most {MAX_NAME} (names become file names in the store)", name.len()));
    }
    if let Some(c) = name.chars().find(|c| !(c.is_ascii_alphanumeric() || "-_.".contains(*c))) {
        return Err(format!("{:?} holds {c:?}; {VALID}", name));
    }
    if name.starts_with(['.', '-']) {
        return Err(format!("{name:?} begins with {:?}; {VALID}", &name[..1]));
    }
    Ok(())
}

/// Validates pipeline text; `file` is used for messages and to resolve the cache path.
pub fn parse(file: &Path, text: &str, registry: &Registry) -> Result<Pipeline, ConfigError> {
    parse_with(file, text, &[], &[], registry)
}

/// [`parse`] with `overrides` applied over the text (see [`load_with`]).
fn parse_with(file: &Path, text: &str, set: &[String], set_new: &[String], registry: &Registry) -> Result<Pipeline, ConfigError> {
    let given = set.iter().map(|o| (o, false)).chain(set_new.iter().map(|o| (o, true)));
    let applied = given.map(|(o, creates)| Override::parse(o, creates)).collect::<Result<Vec<_>, _>>();
    let applied = match applied {
        Ok(applied) => applied,
        Err(diagnostic) => return Err(ConfigError { file: file.to_path_buf(), diagnostics: vec![diagnostic], overrides: Vec::new() }),
    };
    let mut pipeline = parse_overridden(file, text, &applied, registry).map_err(|mut e| {
        e.overrides = applied.clone();
        e
    })?;
    pipeline.overrides = applied;
    Ok(pipeline)
}

fn parse_overridden(file: &Path, text: &str, overrides: &[Override], registry: &Registry) -> Result<Pipeline, ConfigError> {
    let mut cx = Checker { lines: KeyLines::default(), line_starts: line_starts(text), errors: Vec::new() };
    if let Some((line, depth)) = too_deep(text) {
        cx.error(line, "", format!("nested more than {MAX_DEPTH} levels deep (at least {depth}); at most {MAX_DEPTH}"), None);
        return Err(cx.into_error(file));
    }
    let root = match DeTable::parse(text) {
        Ok(root) => root,
        Err(e) => {
            let line = e.span().map_or(1, |s| cx.line_of(s.start));
            cx.error(line, "", format!("invalid TOML: {}", e.message()), None);
            return Err(cx.into_error(file));
        }
    };
    cx.index(&mut Vec::new(), root.get_ref());
    let mut root = to_json_table(root.get_ref());
    for o in overrides {
        match o.apply(&root) {
            Ok(overridden) => root = overridden,
            Err(message) => cx.error(0, &o.shown(), message, None),
        }
    }
    if !cx.errors.is_empty() {
        return Err(cx.into_error(file));
    }
    let pipeline = cx.check(file, &root, registry);
    match pipeline {
        Some(p) if cx.errors.is_empty() => Ok(p),
        _ => Err(cx.into_error(file)),
    }
}

impl Checker {
    /// The checks in order, each a step of its own that reports its errors; a step whose
    /// output the next needs stops the walk when it fails.
    fn check(&mut self, file: &Path, root: &Map<String, Value>, registry: &Registry) -> Option<Pipeline> {
        for key in root.keys() {
            if !["pipeline", "stages", "claims"].contains(&key.as_str()) {
                self.unknown_key(key, key, &["pipeline", "stages", "claims"]);
            }
        }
        let header = self.header(file, root);
        let mut stages_table = self.stages_table(root, header.max_instances)?;
        self.claims_not_set_by_stages(&mut stages_table, registry);
        let (mut stages, explicit_inputs) = self.stages(&stages_table, registry, file.parent().unwrap_or(Path::new(".")))?;
        self.bind(&mut stages, &explicit_inputs, registry);
        if !self.errors.is_empty() {
            return None;
        }
        self.no_varied_stage_named_seed(&stages, &header.seeds)?;
        let mut stages = self.topological(stages)?;
        self.bounded(&stages, header.seed_rule.map_or(header.seeds.len(), |r| r.max), header.max_instances);
        if !self.errors.is_empty() {
            return None;
        }
        self.outlines(&stages, registry);
        if !self.errors.is_empty() {
            return None;
        }
        let looks = match header.seed_rule {
            Some(rule) => Some(rlmflow_stages::claims::Looks { first: rule.min, last: rule.max }),
            None if header.seeds.is_empty() => None,
            None => Some(rlmflow_stages::claims::Looks { first: header.seeds.len(), last: header.seeds.len() }),
        };
        let dims = dimensions(&stages, !header.seeds.is_empty());
        let claims = self.claims(root.get("claims"), &stages, &dims, looks, registry);
        if let Some(spec) = &claims {
            self.hand_claims(spec, &mut stages, registry);
        }
        if !self.errors.is_empty() {
            return None;
        }
        let Header { name, seed, seeds, seed_rule, cache, results, executor, gpus, hyperqueue, remote, .. } = header;
        Some(Pipeline {
            file: file.to_path_buf(),
            name,
            seed,
            seeds,
            seed_rule,
            claims,
            cache,
            results,
            executor,
            gpus,
            hyperqueue,
            remote,
            stages,
            lines: std::mem::take(&mut self.lines),
            overrides: Vec::new(),
        })
    }

    /// `[stages]`: a non-empty table, of at most `max_instances` stages.
    fn stages_table(&mut self, root: &Map<String, Value>, max_instances: u64) -> Option<Map<String, Value>> {
        let table = match root.get("stages") {
            Some(Value::Object(t)) if !t.is_empty() => t.clone(),
            Some(Value::Object(_)) | None => {
                let help = "add one, e.g. [stages.scenes] with operator = \"procedural\"".to_owned();
                self.error(self.line("stages"), "stages", "the pipeline has no stages".into(), Some(help));
                return None;
            }
            Some(_) => {
                self.error(self.line("stages"), "stages", "must be a table of stage tables".into(), None);
                return None;
            }
        };
        if table.len() as u64 > max_instances {
            let msg = format!("{} stages, and each makes at least one instance; at most {max_instances} (`[pipeline] max_instances`)", table.len());
            self.error(self.line("stages"), "stages", msg, Some("raise `[pipeline] max_instances` if a plan this large is meant".into()));
            return None;
        }
        Some(table)
    }

    /// Every stage table checked ([`Checker::stage`]), with its explicit inputs; `None` when one
    /// does not check.
    fn stages(&mut self, table: &Map<String, Value>, registry: &Registry, dir: &Path) -> Option<StagesWithInputs> {
        let (mut stages, mut explicit_inputs) = (Vec::new(), Vec::new());
        for (name, table) in table {
            let path = format!("stages.{name}");
            self.name(&path, name);
            let Value::Object(table) = table else {
                self.error(self.line(&path), &path, "must be a table".into(), None);
                continue;
            };
            if let Some((stage, inputs)) = self.stage(name, table, registry, dir) {
                stages.push(stage);
                explicit_inputs.push(inputs);
            }
        }
        (stages.len() == table.len()).then_some((stages, explicit_inputs))
    }

    /// A stage named `seed` with variants, beside seeds, would give labels two `seed=` items
    /// (`probe[seed=a,seed=2]`) that a reader could not tell apart.
    fn no_varied_stage_named_seed(&mut self, stages: &[Stage], seeds: &[u64]) -> Option<()> {
        let varied = |s: &Stage| s.variants.len() > 1 || s.variants[0].name.is_some();
        if !seeds.is_empty() && stages.iter().any(|s| s.name == SEED_LABEL && varied(s)) {
            let path = format!("stages.{SEED_LABEL}");
            let msg = "a stage named `seed` may not have variants when [pipeline] seeds is set: labels name the seed `seed=N`, and its variants would read the same".into();
            self.error(self.line(&path), &path, msg, Some("rename the stage".into()));
            return None;
        }
        Some(())
    }
}

/// The checked stages and, for each, the stages its `inputs` names by slot.
type StagesWithInputs = (Vec<Stage>, Vec<BTreeMap<String, Vec<String>>>);

/// ", did you mean `x`?" for the nearest candidate, if one is close.
pub fn suggest(word: &str, candidates: &[&str]) -> String {
    let best = candidates
        .iter()
        .map(|c| (strsim::damerau_levenshtein(word, c), *c))
        .filter(|(d, c)| *d > 0 && *d <= (c.len().max(word.len()) / 3).max(2))
        .min();
    best.map_or(String::new(), |(_, c)| format!("; did you mean `{c}`?"))
}
