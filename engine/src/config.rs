//! `pipeline.toml`: parsing, validation against the registry, and diagnostics that name the
//! file, line and key, say what is valid, and suggest the nearest name.
//!
//! Everything here runs before any stage does: unknown keys, operators and stage names, bad
//! setting values, missing or ambiguous inputs, artifact type mismatches and cycles are all
//! reported together.

mod hyperqueue;

pub use hyperqueue::{HyperQueueSettings, WorkerStore};

use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::Context as _;

use rlmflow_stages::{Arity, DynOperator, InputOutlines, ItemCount, Need, Outline, Part, Registry, Share, StageKind};

use serde_json::{Map, Value};
use toml::de::{DeTable, DeValue};

/// One problem in a pipeline file.
#[derive(Clone, Debug)]
pub struct Diagnostic {
    pub line: usize,
    pub key: String,
    pub message: String,
    pub help: Option<String>,
}

/// Every problem found in one pipeline file.
#[derive(Debug)]
pub struct ConfigError {
    pub file: PathBuf,
    pub diagnostics: Vec<Diagnostic>,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, d) in self.diagnostics.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{}:{}: ", self.file.display(), d.line)?;
            if !d.key.is_empty() {
                write!(f, "{}: ", d.key)?;
            }
            write!(f, "{}", d.message)?;
            if let Some(help) = &d.help {
                write!(f, "\n    {help}")?;
            }
        }
        Ok(())
    }
}

impl std::error::Error for ConfigError {}

/// A validated pipeline: stages in dependency order, every input bound.
#[derive(Debug)]
pub struct Pipeline {
    pub file: PathBuf,
    pub name: String,
    pub seed: u64,
    /// `[pipeline] seeds`: every per-seed stage runs once per entry (empty: once, with `seed`).
    pub seeds: Vec<u64>,
    /// The store directory (relative paths in the file are relative to the file).
    pub cache: PathBuf,
    pub executor: Executor,
    /// `[pipeline.hyperqueue]`, also used when `run --executor hyperqueue` overrides a local one.
    pub hyperqueue: HyperQueueSettings,
    /// `[pipeline] remote`, `remote_push`, `remote_timeout_s`: the remote cache, if any.
    pub remote: RemoteSettings,
    pub stages: Vec<Stage>,
    /// The line of every key the file spells out, for errors found after validation.
    pub lines: KeyLines,
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

/// Where results are shared between machines (`rlmflow_remote`); `--remote` and `--push`
/// override the file.
#[derive(Clone, Debug, PartialEq)]
pub struct RemoteSettings {
    /// `s3://bucket/prefix`, `https://host/path` or `file:///path`; a relative `file://` path is
    /// relative to the pipeline file.
    pub url: Option<String>,
    /// Upload computed results (trusted writers only: CI on the main branch).
    pub push: bool,
    /// The most one request may take before the remote is given up for the run.
    pub timeout_s: f64,
    /// `remote_trusted_keys`: public keys (`NAME:BASE64`) whose signatures make a remote record
    /// usable; empty: every record is used, unverified.
    pub trusted_keys: Vec<String>,
}

/// The environment variable naming the secret key file a pushing run signs its records with
/// (never a pipeline setting: the file is shared, the key is not).
pub const SIGNING_KEY_VARIABLE: &str = "RLMFLOW_SIGNING_KEY";

impl RemoteSettings {
    /// The remote these settings name, with its trusted keys and, when pushing, the signing key
    /// of [`SIGNING_KEY_VARIABLE`].
    pub fn open(&self) -> anyhow::Result<rlmflow_remote::Remote> {
        let trusted = rlmflow_remote::signing::TrustedKeys::parse(&self.trusted_keys).context("pipeline.remote_trusted_keys")?;
        let signer = match std::env::var_os(SIGNING_KEY_VARIABLE).filter(|_| self.push) {
            None => None,
            Some(file) => {
                let text = std::fs::read_to_string(&file).with_context(|| format!("{SIGNING_KEY_VARIABLE}: reading {}", file.to_string_lossy()))?;
                Some(
                    rlmflow_remote::signing::SigningKey::parse(&text)
                        .with_context(|| format!("{SIGNING_KEY_VARIABLE} ({})", file.to_string_lossy()))?,
                )
            }
        };
        Ok(self.open_transport()?.with_trust(trusted, signer))
    }

    /// The remote as a transport between this engine and its own cluster tasks (their inputs and
    /// results): no signatures asked or made.
    pub fn open_transport(&self) -> anyhow::Result<rlmflow_remote::Remote> {
        let url = self.url.as_deref().ok_or_else(|| anyhow::anyhow!("no remote cache URL"))?;
        rlmflow_remote::Remote::open(url, self.push, std::time::Duration::from_secs_f64(self.timeout_s))
    }
}

impl Default for RemoteSettings {
    fn default() -> Self {
        RemoteSettings { url: None, push: false, timeout_s: 10.0, trusted_keys: Vec::new() }
    }
}

const REMOTE_SCHEMES: &[&str] = &["s3://", "http://", "https://", "file://"];

/// A remote URL with a relative `file://` path made absolute against `dir` (`file://` alone
/// names no directory and stays as it is, for [`rlmflow_remote::check_url`] to refuse).
pub fn resolve_remote(url: &str, dir: &Path) -> String {
    match url.strip_prefix("file://") {
        Some(path) if !path.is_empty() && !path.starts_with('/') => {
            let path = dir.join(path);
            format!("file://{}", std::path::absolute(&path).unwrap_or(path).display())
        }
        _ => url.to_owned(),
    }
}

/// `[pipeline] executor`: where actions run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Executor {
    /// Child processes of the engine.
    Local,
    /// Tasks of a HyperQueue server (`[pipeline.hyperqueue]`).
    HyperQueue,
}

impl Executor {
    pub const NAMES: &[&str] = &["local", "hyperqueue"];

    pub fn parse(name: &str) -> Option<Executor> {
        match name {
            "local" => Some(Executor::Local),
            "hyperqueue" => Some(Executor::HyperQueue),
            _ => None,
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
    pub line: usize,
}

#[derive(Clone, Debug)]
pub struct Variant {
    pub name: Option<String>,
    /// Every setting, defaults filled in.
    pub settings: Value,
    /// A sharded stage's parts: the items each computes and its settings, in order.
    pub shards: Vec<(Part, Value)>,
    /// The files or directories outside the store it reads, by setting (`Settings::TRACKED`),
    /// made absolute against the pipeline file.
    pub tracked: Vec<(String, PathBuf)>,
}

/// The action that joins a sharded stage's parts: an operator gathering them, in order, into one
/// artifact of the stage's type.
#[derive(Clone, Debug)]
pub struct Merge {
    pub operator: String,
    pub slot: &'static str,
    pub settings: Value,
}

/// `shards = N` (N equal parts) or `shard_size = K` (parts of K items: growing the stage keeps
/// the parts it had).
#[derive(Clone, Copy, Debug)]
enum Split {
    Count(u64),
    Size(u64),
}

impl Split {
    fn ranges(self, items: u64) -> Vec<Range<u64>> {
        match self {
            Split::Count(n) => (0..n).map(|index| Share { index, of: n }.range(items)).collect(),
            Split::Size(k) => (0..items.div_ceil(k)).map(|j| j * k..(j * k).saturating_add(k).min(items)).collect(),
        }
    }
}

/// An input slot bound to the stages that provide it (indices into `Pipeline::stages`).
#[derive(Clone, Debug)]
pub struct Binding {
    pub slot: &'static str,
    pub arity: Arity,
    pub providers: Vec<usize>,
}

impl Pipeline {
    pub fn stage(&self, name: &str) -> Option<usize> {
        self.stages.iter().position(|s| s.name == name)
    }

    pub fn stage_names(&self) -> Vec<&str> {
        self.stages.iter().map(|s| s.name.as_str()).collect()
    }

    /// Setting `key` (dotted, relative to the stage table) of a stage's variant, located as
    /// validation errors are: `p.toml:12: stages.pretrain.variants.alpha4.batch`, the variant's
    /// line where the variant sets the key, else the stage's.
    pub fn locate(&self, stage: &str, variant: Option<&str>, key: &str) -> String {
        let top = key.split('.').next().unwrap_or_default();
        let path = match variant {
            Some(v) if self.lines.0.contains_key(&format!("stages.{stage}.variants.{v}.{top}")) => format!("stages.{stage}.variants.{v}.{key}"),
            _ if key.is_empty() => format!("stages.{stage}"),
            _ => format!("stages.{stage}.{key}"),
        };
        format!("{}:{}: {path}", self.file.display(), self.lines.line(&path))
    }
}

const PIPELINE_KEYS: &[&str] = &[
    "name",
    "seed",
    "seeds",
    "cache",
    "executor",
    "hyperqueue",
    "remote",
    "remote_push",
    "remote_timeout_s",
    "remote_trusted_keys",
    "max_instances",
];
const STAGE_KEYS: &[&str] = &["kind", "operator", "inputs", "variants", "per_seed", "shards", "shard_size"];
/// The most parts one stage instance may be split into.
const MAX_SHARDS: u64 = 4_096;
/// The variant dimension seeds fan out on; no stage may take its name.
pub const SEED_DIMENSION: &str = "seed";
/// The most seeds a pipeline may list.
const MAX_SEEDS: usize = 64;
/// The default of `[pipeline] max_instances`: the most instances (variants, seeds and shards
/// fanned out) a plan may have, checked before it is expanded. The paper's pipelines have tens.
pub const MAX_INSTANCES: u64 = 10_000;

/// The longest pipeline, stage, variant or pin name: names become file names in the store.
pub const MAX_NAME: usize = 128;
/// The deepest nesting of keys, tables and arrays a pipeline file may use (the shipped ones use
/// five); deeper input would exhaust the TOML parser's recursion limit.
const MAX_DEPTH: usize = 32;

/// Reads and validates a pipeline file.
pub fn load(file: &Path, registry: &Registry) -> anyhow::Result<Pipeline> {
    let bytes = std::fs::read(file).map_err(|e| anyhow::anyhow!("cannot read pipeline {}: {e}", file.display()))?;
    let text = match String::from_utf8(bytes) {
        Ok(text) => text,
        Err(e) => {
            let bytes = e.as_bytes();
            let at = e.utf8_error().valid_up_to();
            let line = 1 + bytes[..at].iter().filter(|&&b| b == b'\n').count();
            let column = 1 + at - bytes[..at].iter().rposition(|&b| b == b'\n').map_or(0, |p| p + 1);
            let message = format!("not UTF-8 text: byte 0x{:02X} at column {column}; a pipeline file must be UTF-8", bytes[at]);
            return Err(
                ConfigError { file: file.to_path_buf(), diagnostics: vec![Diagnostic { line, key: String::new(), message, help: None }] }.into()
            );
        }
    };
    parse(file, &text, registry).map_err(anyhow::Error::new)
}

/// Checks a pipeline, stage, variant or pin name; the error says what is wrong.
pub fn check_name(name: &str) -> Result<(), String> {
    if name.is_empty() {
        return Err("must not be empty".into());
    }
    if name.len() > MAX_NAME {
        return Err(format!("is {} bytes long; at most {MAX_NAME} (names become file names in the store)", name.len()));
    }
    Ok(())
}

/// The first line nested deeper than [`MAX_DEPTH`], with its depth: each open array or inline
/// table counts one, and each dot of a key (a header's, or a key's before its `=`) one more.
/// Dots in values (numbers, strings) and list items do not nest. This only needs to find input
/// far beyond any real pipeline before the parser's recursion limit does.
fn too_deep(text: &str) -> Option<(usize, usize)> {
    #[derive(Clone, Copy, PartialEq)]
    enum Quoted {
        Basic,
        Literal,
        MultiBasic,
        MultiLiteral,
    }
    let bytes = text.as_bytes();
    let at = |i: usize, s: &[u8]| bytes[i..].starts_with(s);
    // Each open array or inline table with the dots of the key that holds it.
    let mut open: Vec<(u8, usize)> = Vec::new();
    let (mut dots, mut in_key, mut quoted, mut line, mut i) = (0usize, true, None::<Quoted>, 1usize, 0usize);
    while i < bytes.len() {
        let b = bytes[i];
        i += 1;
        if b == b'\n' {
            line += 1;
            if matches!(quoted, Some(Quoted::Basic | Quoted::Literal)) {
                quoted = None; // unterminated: the parser will say so
            }
            if open.is_empty() {
                (dots, in_key) = (0, true);
            }
            continue;
        }
        match (quoted, b) {
            (Some(Quoted::Basic | Quoted::MultiBasic), b'\\') => i += 1,
            (Some(Quoted::Basic), b'"') | (Some(Quoted::Literal), b'\'') => quoted = None,
            (Some(Quoted::MultiBasic), b'"') if at(i, b"\"\"") => (quoted, i) = (None, i + 2),
            (Some(Quoted::MultiLiteral), b'\'') if at(i, b"''") => (quoted, i) = (None, i + 2),
            (Some(_), _) => {}
            (None, b'#') => i = bytes[i..].iter().position(|&c| c == b'\n').map_or(bytes.len(), |p| i + p),
            (None, b'"') if at(i, b"\"\"") => (quoted, i) = (Some(Quoted::MultiBasic), i + 2),
            (None, b'"') => quoted = Some(Quoted::Basic),
            (None, b'\'') if at(i, b"''") => (quoted, i) = (Some(Quoted::MultiLiteral), i + 2),
            (None, b'\'') => quoted = Some(Quoted::Literal),
            (None, b'=') => in_key = false,
            (None, b'.') if in_key => dots += 1,
            // A header's brackets (`[a.b]`, `[[a]]`) open nothing: its dots count as a key's.
            (None, b'[' | b']') if open.is_empty() && in_key => {}
            (None, b'[' | b'{') => {
                open.push((b, dots));
                (dots, in_key) = (0, b == b'{');
            }
            (None, b']' | b'}') => {
                dots = open.pop().map_or(0, |o| o.1);
                in_key = false;
            }
            (None, b',') if open.last().is_some_and(|o| o.0 == b'{') => (dots, in_key) = (0, true),
            _ => {}
        }
        let depth = open.len() + open.iter().map(|o| o.1).sum::<usize>() + dots;
        if depth > MAX_DEPTH {
            return Some((line, depth));
        }
    }
    None
}

/// Validates pipeline text; `file` is used for messages and to resolve the cache path.
pub fn parse(file: &Path, text: &str, registry: &Registry) -> Result<Pipeline, ConfigError> {
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
    let root = to_json_table(root.get_ref());
    let pipeline = cx.check(file, &root, registry);
    match pipeline {
        Some(p) if cx.errors.is_empty() => Ok(p),
        _ => Err(cx.into_error(file)),
    }
}

struct Checker {
    lines: KeyLines,
    line_starts: Vec<usize>,
    errors: Vec<Diagnostic>,
}

impl Checker {
    fn into_error(mut self, file: &Path) -> ConfigError {
        self.errors.sort_by_key(|d| d.line);
        ConfigError { file: file.to_path_buf(), diagnostics: self.errors }
    }

    fn error(&mut self, line: usize, key: &str, message: String, help: Option<String>) {
        self.errors.push(Diagnostic { line, key: key.to_owned(), message, help });
    }

    fn line_of(&self, offset: usize) -> usize {
        self.line_starts.partition_point(|&s| s <= offset)
    }

    /// [`KeyLines::line`].
    fn line(&self, path: &str) -> usize {
        self.lines.line(path)
    }

    fn index(&mut self, path: &mut Vec<String>, table: &DeTable<'_>) {
        for (key, value) in table {
            path.push(key.get_ref().to_string());
            let line = self.line_of(key.span().start);
            self.lines.0.entry(path.join(".")).or_insert(line);
            match value.get_ref() {
                DeValue::Table(t) => self.index(path, t),
                DeValue::Datetime(_) => self.datetime(line, &path.join(".")),
                DeValue::Array(items) => {
                    for (i, item) in items.iter().enumerate() {
                        if let DeValue::Datetime(_) = item.get_ref() {
                            self.datetime(self.line_of(item.span().start), &path.join("."));
                        }
                        if let DeValue::Table(t) = item.get_ref() {
                            path.push(i.to_string());
                            let line = self.line_of(item.span().start);
                            self.lines.0.entry(path.join(".")).or_insert(line);
                            self.index(path, t);
                            path.pop();
                        }
                    }
                }
                _ => {}
            }
            path.pop();
        }
    }

    /// No setting takes a TOML date or time; one would otherwise pass as a string.
    fn datetime(&mut self, line: usize, path: &str) {
        let help = "write it as a quoted string if text is meant".to_owned();
        self.error(line, path, "a TOML date or time is not a valid value for any setting".into(), Some(help));
    }

    fn name(&mut self, path: &str, name: &str) {
        if let Err(problem) = check_name(name) {
            self.error(self.line(path), path, format!("the name {problem}"), None);
        }
    }

    fn unknown_key(&mut self, path: &str, key: &str, valid: &[&str]) {
        let help = format!("valid keys: {}{}", valid.join(", "), suggest(key, valid));
        self.error(self.line(path), path, format!("unknown key `{key}`"), Some(help));
    }

    fn check(&mut self, file: &Path, root: &Map<String, Value>, registry: &Registry) -> Option<Pipeline> {
        for key in root.keys() {
            if key != "pipeline" && key != "stages" {
                self.unknown_key(key, key, &["pipeline", "stages"]);
            }
        }
        let header = match root.get("pipeline") {
            None => &Map::new(),
            Some(Value::Object(t)) => t,
            Some(_) => {
                self.error(self.line("pipeline"), "pipeline", "must be a table".into(), None);
                &Map::new()
            }
        };
        for key in header.keys().filter(|k| !PIPELINE_KEYS.contains(&k.as_str())) {
            self.unknown_key(&format!("pipeline.{key}"), key, PIPELINE_KEYS);
        }
        let stem = file.file_stem().map_or("pipeline".into(), |s| s.to_string_lossy().into_owned());
        let name = self.string(header, "pipeline", "name").unwrap_or(stem);
        self.name("pipeline.name", &name);
        let seed = match header.get("seed") {
            None => 0,
            Some(v) => v.as_u64().unwrap_or_else(|| {
                let msg = format!("must be a non-negative integer, not {v}");
                self.error(self.line("pipeline.seed"), "pipeline.seed", msg, None);
                0
            }),
        };
        let seeds = self.seeds(header);
        let max_instances = match header.get("max_instances") {
            None => MAX_INSTANCES,
            Some(v) => v.as_u64().filter(|n| *n >= 1).unwrap_or_else(|| {
                let msg = format!("must be a positive integer, not {v}");
                self.error(self.line("pipeline.max_instances"), "pipeline.max_instances", msg, None);
                MAX_INSTANCES
            }),
        };
        let cache = self.string(header, "pipeline", "cache").unwrap_or_else(|| ".rlmflow".into());
        let cache = file.parent().unwrap_or(Path::new(".")).join(cache);
        let cache = std::path::absolute(&cache).unwrap_or(cache);
        let executor = match self.string(header, "pipeline", "executor") {
            None => Executor::Local,
            Some(name) => Executor::parse(&name).unwrap_or_else(|| {
                let help = format!("valid executors: {}{}", Executor::NAMES.join(", "), suggest(&name, Executor::NAMES));
                self.error(self.line("pipeline.executor"), "pipeline.executor", format!("unknown executor `{name}`"), Some(help));
                Executor::Local
            }),
        };
        let hyperqueue = self.hyperqueue(file, header.get("hyperqueue"));
        let remote = self.remote(file, header);

        let stages_table = match root.get("stages") {
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
        if stages_table.len() as u64 > max_instances {
            let msg =
                format!("{} stages, and each makes at least one instance; at most {max_instances} (`[pipeline] max_instances`)", stages_table.len());
            self.error(self.line("stages"), "stages", msg, Some("raise `[pipeline] max_instances` if a plan this large is meant".into()));
            return None;
        }
        let mut stages = Vec::new();
        let mut explicit_inputs = Vec::new();
        for (name, table) in &stages_table {
            let path = format!("stages.{name}");
            self.name(&path, name);
            let Value::Object(table) = table else {
                self.error(self.line(&path), &path, "must be a table".into(), None);
                continue;
            };
            if let Some((stage, inputs)) = self.stage(name, table, registry, file.parent().unwrap_or(Path::new("."))) {
                stages.push(stage);
                explicit_inputs.push(inputs);
            }
        }
        if stages.len() != stages_table.len() {
            return None;
        }
        self.bind(&mut stages, &explicit_inputs, registry);
        if !self.errors.is_empty() {
            return None;
        }
        if !seeds.is_empty() && stages.iter().any(|s| s.name == SEED_DIMENSION) {
            let path = format!("stages.{SEED_DIMENSION}");
            let msg = "a stage may not be named `seed` when [pipeline] seeds is set: seeds fan out on a dimension of that name".into();
            self.error(self.line(&path), &path, msg, None);
            return None;
        }
        let stages = self.topological(stages)?;
        self.bounded(&stages, seeds.len(), max_instances);
        if !self.errors.is_empty() {
            return None;
        }
        self.outlines(&stages, registry);
        if !self.errors.is_empty() {
            return None;
        }
        Some(Pipeline {
            file: file.to_path_buf(),
            name,
            seed,
            seeds,
            cache,
            executor,
            hyperqueue,
            remote,
            stages,
            lines: std::mem::take(&mut self.lines),
        })
    }

    /// Refuses, before any instance exists, a plan whose variants, seeds and shards would make
    /// more than `max` instances, naming the stage where the count passes it and its factors.
    fn bounded(&mut self, stages: &[Stage], seeds: usize, max: u64) {
        let variants: HashMap<&str, u64> = stages.iter().map(|s| (s.name.as_str(), s.variants.len() as u64)).collect();
        let size = |dim: &str| if dim == SEED_DIMENSION { seeds as u64 } else { variants[dim] };
        let mut total = 0u64;
        for (stage, dims) in stages.iter().zip(dimensions(stages, seeds > 0)) {
            let parts = 1 + stage.variants.iter().map(|v| v.shards.len() as u64).max().unwrap_or(0);
            let count = dims.iter().fold(parts, |n, d| n.saturating_mul(size(d)));
            total = total.saturating_add(count);
            if total > max {
                let mut factors: Vec<String> = dims
                    .iter()
                    .map(|d| if d == SEED_DIMENSION { format!("{seeds} seeds") } else { format!("{} variants of `{d}`", size(d)) })
                    .collect();
                if parts > 1 {
                    factors.push(format!("{} shards and their merge", parts - 1));
                }
                let path = format!("stages.{}", stage.name);
                let msg = format!(
                    "the plan would have more than {max} instances (`[pipeline] max_instances`): this stage makes {count} ({}), {total} with the stages before it",
                    factors.join(" x ")
                );
                self.error(
                    stage.line,
                    &path,
                    msg,
                    Some("use fewer variants or seeds, or raise `[pipeline] max_instances` if a plan this large is meant".into()),
                );
                return;
            }
        }
    }

    /// Checks each stage's settings against what its inputs will be (image side, frames), as far
    /// as their settings tell, in dependency order: an image a ViT patch does not divide or scenes
    /// of two sizes mixed are config errors here, not failures an hour into the run.
    fn outlines(&mut self, stages: &[Stage], registry: &Registry) {
        let mut outlines: Vec<Outline> = Vec::with_capacity(stages.len());
        for stage in stages {
            let op = registry.get(&stage.operator).expect("validated operator");
            let inputs: InputOutlines = stage.bindings.iter().map(|b| (b.slot, b.providers.iter().map(|&p| outlines[p]).collect())).collect();
            let mut outline: Option<Outline> = None;
            let mut reported = std::collections::BTreeSet::new();
            for variant in &stage.variants {
                match op.outline(&variant.settings, &inputs) {
                    Ok(o) => outline = Some(outline.map_or(o, |known| known.common(o))),
                    Err(e) => {
                        let key = if e.key.is_empty() { format!("stages.{}", stage.name) } else { format!("stages.{}.{}", stage.name, e.key) };
                        if reported.insert(key.clone()) {
                            self.error(self.line(&key), &key, e.message, None);
                        }
                    }
                }
            }
            outlines.push(outline.unwrap_or_default());
        }
    }

    /// `[pipeline.hyperqueue]`, its `server_dir` made absolute against the pipeline file.
    fn hyperqueue(&mut self, file: &Path, table: Option<&Value>) -> HyperQueueSettings {
        let Some(table) = table else { return HyperQueueSettings::default() };
        let parsed = serde_path_to_error::deserialize::<_, HyperQueueSettings>(table.clone());
        let mut settings = match parsed {
            Ok(s) => s,
            Err(e) => {
                let inner = e.path().to_string();
                let key = if inner == "." { "pipeline.hyperqueue".to_owned() } else { format!("pipeline.hyperqueue.{inner}") };
                let message = e.into_inner().to_string();
                let key = match message.strip_prefix("unknown field `").and_then(|m| m.split('`').next()) {
                    Some(field) => format!("pipeline.hyperqueue.{field}"),
                    None => key,
                };
                self.error(self.line(&key), &key, message, None);
                return HyperQueueSettings::default();
            }
        };
        if let Err((key, message)) = settings.check() {
            let key = format!("pipeline.hyperqueue.{key}");
            self.error(self.line(&key), &key, message, None);
        }
        if let Some(dir) = &settings.server_dir {
            let dir = file.parent().unwrap_or(Path::new(".")).join(dir);
            settings.server_dir = Some(std::path::absolute(&dir).unwrap_or(dir));
        }
        settings
    }

    /// `remote`, `remote_push`, `remote_timeout_s` of `[pipeline]`.
    fn remote(&mut self, file: &Path, header: &Map<String, Value>) -> RemoteSettings {
        let mut remote = RemoteSettings { url: self.string(header, "pipeline", "remote"), ..RemoteSettings::default() };
        if let Some(url) = remote.url.clone() {
            let resolved = resolve_remote(&url, file.parent().unwrap_or(Path::new(".")));
            let help = "e.g. remote = \"s3://bucket/rlmflow\", \"https://cache.example/rlmflow\" (WebDAV) or \"file:///srv/rlmflow\"";
            if !REMOTE_SCHEMES.iter().any(|scheme| url.starts_with(scheme)) {
                self.error(self.line("pipeline.remote"), "pipeline.remote", format!("`{url}` is not a remote URL"), Some(help.into()));
            } else if let Err(problem) = rlmflow_remote::check_url(&resolved) {
                self.error(self.line("pipeline.remote"), "pipeline.remote", problem, Some(help.into()));
            }
            remote.url = Some(resolved);
        }
        match header.get("remote_push") {
            None => {}
            Some(Value::Bool(push)) => remote.push = *push,
            Some(other) => self.error(self.line("pipeline.remote_push"), "pipeline.remote_push", format!("must be true or false, not {other}"), None),
        }
        if let Some(value) = header.get("remote_trusted_keys") {
            let key = "pipeline.remote_trusted_keys";
            let keys: Option<Vec<String>> = value.as_array().and_then(|items| items.iter().map(|v| v.as_str().map(str::to_owned)).collect());
            match keys.map(|k| rlmflow_remote::signing::TrustedKeys::parse(&k).map(|_| k)) {
                Some(Ok(keys)) => remote.trusted_keys = keys,
                Some(Err(e)) => {
                    self.error(self.line(key), key, format!("{e:#}"), Some("a key is NAME:BASE64, as `rlmflow key generate NAME` prints it".into()))
                }
                None => self.error(self.line(key), key, format!("must be a list of public keys (strings), not {value}"), None),
            }
        }
        match header.get("remote_timeout_s").map(|v| v.as_f64().filter(|t| (0.1..=3600.0).contains(t))) {
            None => {}
            Some(Some(t)) => remote.timeout_s = t,
            Some(None) => {
                let msg = format!("must be a number of seconds in 0.1..=3600, not {}", header["remote_timeout_s"]);
                self.error(self.line("pipeline.remote_timeout_s"), "pipeline.remote_timeout_s", msg, None);
            }
        }
        remote
    }

    /// `seeds = [1, 2, 3]`: distinct non-negative integers, at most [`MAX_SEEDS`].
    fn seeds(&mut self, header: &Map<String, Value>) -> Vec<u64> {
        let key = "pipeline.seeds";
        let Some(value) = header.get("seeds") else { return Vec::new() };
        let seeds: Option<Vec<u64>> = value.as_array().and_then(|items| items.iter().map(Value::as_u64).collect());
        let problem = match &seeds {
            None => Some(format!("must be a list of non-negative integers, not {value}")),
            Some(s) if s.is_empty() || s.len() > MAX_SEEDS => Some(format!("must list 1 to {MAX_SEEDS} seeds, not {}", s.len())),
            Some(s) if (1..s.len()).any(|i| s[..i].contains(&s[i])) => Some("lists a seed twice".into()),
            Some(_) => None,
        };
        match problem {
            Some(msg) => {
                self.error(self.line(key), key, msg, Some("e.g. seeds = [1, 2, 3]".into()));
                Vec::new()
            }
            None => seeds.unwrap_or_default(),
        }
    }

    fn string(&mut self, table: &Map<String, Value>, at: &str, key: &str) -> Option<String> {
        match table.get(key)? {
            Value::String(s) => Some(s.clone()),
            other => {
                let path = format!("{at}.{key}");
                self.error(self.line(&path), &path, format!("must be a string, not {other}"), None);
                None
            }
        }
    }

    /// Checks one stage table; returns it with its explicit `inputs` (slot -> stage names).
    fn stage(&mut self, name: &str, table: &Map<String, Value>, registry: &Registry, dir: &Path) -> Option<(Stage, BTreeMap<String, Vec<String>>)> {
        let path = format!("stages.{name}");
        let line = self.line(&path);
        let kind_name = self.string(table, &path, "kind").unwrap_or_else(|| name.to_owned());
        let kinds: Vec<&str> = registry.catalog.kinds.iter().map(|k| k.name).collect();
        let Some(kind) = registry.kind(&kind_name).copied() else {
            let key = if table.contains_key("kind") { format!("{path}.kind") } else { path.clone() };
            let help = format!("valid kinds: {}{}", kinds.join(", "), suggest(&kind_name, &kinds));
            let msg = if table.contains_key("kind") {
                format!("unknown stage kind `{kind_name}`")
            } else {
                format!("`{name}` is not a stage kind; name the kind with kind = \"...\"")
            };
            self.error(self.line(&key), &key, msg, Some(help));
            return None;
        };
        let operators: Vec<&str> = registry.operators_of(kind.name).map(|o| o.spec().name).collect();
        let Some(op_name) = self.string(table, &path, "operator") else {
            if !table.contains_key("operator") {
                let help = format!("operators of kind `{}`: {}", kind.name, operators.join(", "));
                self.error(line, &path, "missing `operator`".into(), Some(help));
            }
            return None;
        };
        let op = match registry.get(&op_name) {
            Some(op) if op.spec().kind == kind.name => op,
            found => {
                let key = format!("{path}.operator");
                let msg = match found {
                    Some(op) => format!("operator `{op_name}` implements kind `{}`, not `{}`", op.spec().kind, kind.name),
                    None => format!("unknown operator `{op_name}` for stage kind `{}`", kind.name),
                };
                let help = format!("valid: {}{}", operators.join(", "), suggest(&op_name, &operators));
                self.error(self.line(&key), &key, msg, Some(help));
                return None;
            }
        };

        let mut base = table.clone();
        for key in STAGE_KEYS {
            base.remove(*key);
        }
        let mut variants = Vec::new();
        match table.get("variants") {
            None => variants.push((None, base.clone())),
            Some(Value::Object(named)) if !named.is_empty() => {
                for (variant, overrides) in named {
                    let vpath = format!("{path}.variants.{variant}");
                    self.name(&vpath, variant);
                    let Value::Object(overrides) = overrides else {
                        self.error(self.line(&vpath), &vpath, "must be a table of settings".into(), None);
                        continue;
                    };
                    let mut merged = base.clone();
                    merge(&mut merged, overrides);
                    variants.push((Some((variant.clone(), overrides.clone())), merged));
                }
            }
            Some(_) => {
                let key = format!("{path}.variants");
                let msg = "must be a non-empty table of named setting overrides".into();
                self.error(self.line(&key), &key, msg, None);
            }
        }
        let mut checked = Vec::new();
        // A bad setting the variants inherit is one error, not one per variant.
        let mut reported = std::collections::BTreeSet::new();
        for (variant, merged) in variants {
            match op.settings(Value::Object(merged)) {
                Ok(settings) => {
                    let mut tracked = Vec::new();
                    for &key in op.tracked_keys() {
                        let given = settings.get(key).and_then(Value::as_str).unwrap_or_default();
                        if given.is_empty() {
                            continue;
                        }
                        let source = std::path::absolute(dir.join(given)).unwrap_or_else(|_| dir.join(given));
                        let checked = match tracked_source(given, &source) {
                            Ok(()) => op.check_tracked(&settings, key, &source).map_err(|e| e.message),
                            // Missing: the operator's word on what belongs there, where it has one.
                            Err(missing) if !source.exists() => Err(op.check_tracked(&settings, key, &source).err().map_or(missing, |e| e.message)),
                            Err(special) => Err(special),
                        };
                        let message = match checked {
                            Ok(()) => {
                                tracked.push((key.to_owned(), source));
                                continue;
                            }
                            Err(message) => message,
                        };
                        let at = match &variant {
                            Some((v, overrides)) if overrides.contains_key(key) => format!("{path}.variants.{v}.{key}"),
                            _ => format!("{path}.{key}"),
                        };
                        let help = Some(format!("a file or directory, relative to the pipeline file's directory ({})", dir.display()));
                        if reported.insert((at.clone(), message.clone())) {
                            self.error(self.line(&at), &at, message, help);
                        }
                    }
                    checked.push(Variant { name: variant.map(|v| v.0), settings, shards: Vec::new(), tracked });
                }
                Err(e) => {
                    // Point at the variant's line when the variant set the key.
                    let top = e.key.split('.').next().unwrap_or_default();
                    let key = match &variant {
                        Some((v, overrides)) if overrides.contains_key(top) => format!("{path}.variants.{v}.{}", e.key),
                        _ if e.key.is_empty() => path.clone(),
                        _ => format!("{path}.{}", e.key),
                    };
                    let help = if e.valid.is_empty() {
                        None
                    } else {
                        let leaf = e.key.rsplit('.').next().unwrap_or_default();
                        let mut valid: Vec<&str> = e.valid.iter().map(String::as_str).collect();
                        if !e.key.contains('.') {
                            valid.extend(STAGE_KEYS);
                        }
                        Some(format!("valid keys: {}{}", valid.join(", "), suggest(leaf, &valid)))
                    };
                    if reported.insert((key.clone(), e.message.clone())) {
                        self.error(self.line(&key), &key, e.message, help);
                    }
                }
            }
        }

        let mut inputs = BTreeMap::new();
        match table.get("inputs") {
            None => {}
            Some(Value::Object(map)) => {
                let readable = operator_slots(registry, &op_name, &kind);
                for (slot, value) in map {
                    let key = format!("{path}.inputs.{slot}");
                    if !readable.contains(&slot.as_str()) {
                        let help = format!("`{op_name}` reads: {}{}", readable.join(", "), suggest(slot, &readable));
                        self.error(self.line(&key), &key, format!("unknown input slot `{slot}`"), Some(help));
                        continue;
                    }
                    let names = match value {
                        Value::String(s) => vec![s.clone()],
                        Value::Array(items) if items.iter().all(Value::is_string) => items.iter().map(|v| v.as_str().unwrap().to_owned()).collect(),
                        _ => {
                            let msg = "must be a stage name or a list of stage names".into();
                            self.error(self.line(&key), &key, msg, None);
                            continue;
                        }
                    };
                    inputs.insert(slot.clone(), names);
                }
            }
            Some(_) => {
                let key = format!("{path}.inputs");
                let msg = "must be a table: slot = \"stage\"".into();
                self.error(self.line(&key), &key, msg, None);
            }
        }
        let per_seed = match table.get("per_seed") {
            None => kind.per_seed,
            Some(Value::Bool(b)) => *b,
            Some(other) => {
                let key = format!("{path}.per_seed");
                self.error(self.line(&key), &key, format!("must be true or false, not {other}"), None);
                kind.per_seed
            }
        };
        let split = self.split(table, &path);
        if checked.is_empty() {
            return None;
        }
        let merge = match split {
            Some((key, split)) => Some(self.shard(&key, op, kind, &mut checked, split, registry)?),
            None => None,
        };
        let stage = Stage { name: name.to_owned(), kind, operator: op_name, variants: checked, bindings: Vec::new(), per_seed, merge, line };
        Some((stage, inputs))
    }

    /// A stage's `shards` or `shard_size` key, with the key's path.
    fn split(&mut self, table: &Map<String, Value>, path: &str) -> Option<(String, Split)> {
        let mut split = None;
        for (name, max, make) in [("shards", MAX_SHARDS, Split::Count as fn(u64) -> Split), ("shard_size", u64::MAX, Split::Size)] {
            let Some(value) = table.get(name) else { continue };
            let key = format!("{path}.{name}");
            match value.as_u64().filter(|n| (1..=max).contains(n)) {
                Some(_) if split.is_some() => self.error(self.line(&key), &key, "set `shards` or `shard_size`, not both".into(), None),
                Some(n) => split = Some((key, make(n))),
                None => self.error(self.line(&key), &key, format!("must be an integer in 1..={max}, not {value}"), None),
            }
        }
        split
    }

    /// Splits every variant of a sharded stage into its parts; returns how the parts merge.
    fn shard(
        &mut self,
        key: &str,
        op: &dyn DynOperator,
        kind: StageKind,
        variants: &mut [Variant],
        split: Split,
        registry: &Registry,
    ) -> Option<Merge> {
        let name = op.spec().name;
        let Some(merge) = op.merge() else {
            let can: Vec<&str> = registry.operators().filter(|o| o.merge().is_some()).map(|o| o.spec().name).collect();
            let help = format!("operators that can: {}", can.join(", "));
            self.error(self.line(key), key, format!("operator `{name}` cannot run as shards"), Some(help));
            return None;
        };
        let merger = registry.get(merge);
        let slot = merger.and_then(|m| {
            let merge_kind = registry.kind(m.spec().kind)?;
            let slot = merge_kind.inputs.iter().find(|s| s.arity == Arity::All && s.artifact == kind.produces)?;
            (merge_kind.produces == kind.produces).then_some(slot.name)
        });
        let (Some(merger), Some(slot)) = (merger, slot) else {
            let msg = format!("`{name}` merges its shards with `{merge}`, which this rlmflow lacks as an operator gathering {}", kind.produces);
            self.error(self.line(key), key, msg, None);
            return None;
        };
        for variant in variants.iter_mut() {
            let at = variant.name.as_ref().map_or(String::new(), |v| format!(" in variant `{v}`"));
            let parts: Vec<Part> = match (op.items(&variant.settings).expect("a shardable operator counts the items of valid settings"), split) {
                ((ItemCount::OfInput(_), _), Split::Count(n)) => (0..n).map(|index| Part::Share(Share { index, of: n })).collect(),
                ((ItemCount::OfInput(slot), unit), Split::Size(_)) => {
                    let msg = format!("`{name}` splits the {unit} of its `{slot}` input, which are counted only when it runs");
                    self.error(self.line(key), key, msg, Some("use `shards = N` (N near-equal parts)".into()));
                    return None;
                }
                ((ItemCount::Known(items), unit), _) => {
                    let ranges = split.ranges(items);
                    if let Split::Count(n) = split
                        && n > items
                    {
                        let msg = format!("{n} shards, but `{name}` makes only {items} {unit}{at}");
                        self.error(self.line(key), key, msg, Some("at most one shard per item".into()));
                        return None;
                    }
                    if ranges.len() as u64 > MAX_SHARDS {
                        let msg = format!("{} shards of `{name}`'s {items} {unit}{at}; at most {MAX_SHARDS}", ranges.len());
                        self.error(self.line(key), key, msg, Some("raise shard_size".into()));
                        return None;
                    }
                    ranges.into_iter().map(Part::Items).collect()
                }
            };
            variant.shards =
                parts.into_iter().map(|p| (p.clone(), op.part(&variant.settings, &p).expect("a shardable operator splits valid settings"))).collect();
        }
        let settings = merger.settings(Value::Object(Map::new())).expect("an operator's default settings are valid");
        Some(Merge { operator: merge.to_owned(), slot, settings })
    }

    /// Binds every input slot an operator reads: to the stages named in `inputs`, else to the one
    /// stage producing the slot's artifact type.
    fn bind(&mut self, stages: &mut [Stage], explicit: &[BTreeMap<String, Vec<String>>], registry: &Registry) {
        let names: Vec<String> = stages.iter().map(|s| s.name.clone()).collect();
        let name_refs: Vec<&str> = names.iter().map(String::as_str).collect();
        let index: HashMap<&str, usize> = name_refs.iter().enumerate().map(|(i, n)| (*n, i)).collect();
        let mut producers: HashMap<&str, Vec<usize>> = HashMap::new();
        for (p, s) in stages.iter().enumerate() {
            producers.entry(s.kind.produces).or_default().push(p);
        }
        for i in 0..stages.len() {
            let kind = stages[i].kind;
            let stage = stages[i].name.clone();
            let path = format!("stages.{stage}");
            for slot_name in operator_slots(registry, &stages[i].operator, &kind) {
                let slot = *kind.slot(slot_name).expect("registry checked operator slots");
                let key = format!("{path}.inputs.{slot_name}");
                let providers: Vec<usize> = match explicit[i].get(slot_name) {
                    Some(wanted) => {
                        let mut found = Vec::new();
                        for want in wanted {
                            match index.get(want.as_str()).copied() {
                                None => {
                                    let help = format!("stages: {}{}", names.join(", "), suggest(want, &name_refs));
                                    self.error(self.line(&key), &key, format!("no stage named `{want}`"), Some(help));
                                }
                                Some(p) if stages[p].kind.produces != slot.artifact => {
                                    let msg = format!(
                                        "stage `{want}` produces {}, but slot `{slot_name}` takes {}",
                                        stages[p].kind.produces, slot.artifact
                                    );
                                    self.error(self.line(&key), &key, msg, None);
                                }
                                Some(p) => found.push(p),
                            }
                        }
                        if slot.arity == Arity::One && wanted.len() > 1 {
                            let msg = format!("slot `{slot_name}` takes one stage, not {}", wanted.len());
                            self.error(self.line(&key), &key, msg, None);
                        }
                        found
                    }
                    None => {
                        let candidates: Vec<usize> = producers.get(slot.artifact).into_iter().flatten().copied().filter(|&p| p != i).collect();
                        if slot.arity == Arity::One && candidates.len() > 1 {
                            let list: Vec<&str> = candidates.iter().map(|&p| names[p].as_str()).collect();
                            let msg = format!("ambiguous input `{slot_name}`: stages {} all produce {}", list.join(", "), slot.artifact);
                            let help = format!("choose one: inputs = {{ {slot_name} = \"{}\" }}", list[0]);
                            self.error(stages[i].line, &path, msg, Some(help));
                            continue;
                        }
                        candidates
                    }
                };
                if providers.is_empty() {
                    if slot.need == Need::Required {
                        match explicit[i].get(slot_name) {
                            None => {
                                let kinds: Vec<&str> =
                                    registry.catalog.kinds.iter().filter(|k| k.produces == slot.artifact).map(|k| k.name).collect();
                                let msg = format!("missing input `{slot_name}`: no stage produces {}", slot.artifact);
                                let help = format!("add a stage of kind {}", kinds.join(" or "));
                                self.error(stages[i].line, &path, msg, Some(help));
                            }
                            Some(wanted) if wanted.is_empty() => {
                                let msg = format!("names no stage, but `{}` needs its `{slot_name}` input", stages[i].operator);
                                self.error(self.line(&key), &key, msg, Some(format!("name a stage that produces {}", slot.artifact)));
                            }
                            Some(_) => {} // each wrong name is reported above
                        }
                    }
                    continue;
                }
                stages[i].bindings.push(Binding { slot: slot.name, arity: slot.arity, providers });
            }
        }
    }

    /// Orders stages so every provider comes before its consumers; reports a cycle. A
    /// depth-first walk with its own stack: a chain as long as the file is long cannot overflow
    /// the thread's.
    fn topological(&mut self, stages: Vec<Stage>) -> Option<Vec<Stage>> {
        let n = stages.len();
        let mut order = Vec::with_capacity(n);
        let mut mark = vec![0u8; n]; // 0 new, 1 on the current path, 2 done
        let providers = |i: usize| stages[i].bindings.iter().flat_map(|b| b.providers.iter().copied()).collect::<Vec<usize>>();
        for root in 0..n {
            if mark[root] != 0 {
                continue;
            }
            // The current path: each stage with the providers it has yet to visit.
            let mut path: Vec<(usize, std::vec::IntoIter<usize>)> = vec![(root, providers(root).into_iter())];
            mark[root] = 1;
            while let Some((at, pending)) = path.last_mut() {
                let at = *at;
                match pending.next() {
                    Some(p) if mark[p] == 0 => {
                        mark[p] = 1;
                        path.push((p, providers(p).into_iter()));
                    }
                    Some(p) if mark[p] == 1 => {
                        let start = path.iter().position(|(s, _)| *s == p).expect("a stage marked on the path is on it");
                        let mut cycle: Vec<usize> = path[start..].iter().map(|(s, _)| *s).collect();
                        cycle.push(p);
                        let names: Vec<&str> = cycle.iter().rev().map(|&c| stages[c].name.as_str()).collect();
                        let first = &stages[cycle[0]];
                        let msg = format!("the stages form a cycle: {}", names.join(" -> "));
                        self.error(first.line, &format!("stages.{}", first.name), msg, Some("break it by changing one stage's `inputs`".into()));
                        return None;
                    }
                    Some(_) => {}
                    None => {
                        mark[at] = 2;
                        order.push(at);
                        path.pop();
                    }
                }
            }
        }
        let mut new_index = vec![0; n];
        for (pos, &old) in order.iter().enumerate() {
            new_index[old] = pos;
        }
        let mut slots: Vec<Option<Stage>> = stages.into_iter().map(Some).collect();
        let mut sorted: Vec<Stage> = order.iter().map(|&i| slots[i].take().unwrap()).collect();
        for stage in &mut sorted {
            for b in &mut stage.bindings {
                for p in &mut b.providers {
                    *p = new_index[*p];
                }
            }
        }
        Some(sorted)
    }
}

/// `Ok` when a tracked setting's `source` is a regular file or a directory (a symbolic link to
/// one counts as it), found without opening it: a FIFO, socket or device is refused, since
/// reading one could block forever or never end.
fn tracked_source(given: &str, source: &Path) -> Result<(), String> {
    use std::os::unix::fs::FileTypeExt;
    let kind = match std::fs::metadata(source) {
        Ok(meta) => meta.file_type(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(format!("`{given}` does not exist ({})", source.display())),
        Err(e) => return Err(format!("`{given}` cannot be read ({}: {e})", source.display())),
    };
    let special = match kind {
        k if k.is_file() || k.is_dir() => return Ok(()),
        k if k.is_fifo() => "a FIFO",
        k if k.is_socket() => "a socket",
        k if k.is_block_device() || k.is_char_device() => "a device",
        _ => "not a regular file",
    };
    Err(format!("`{given}` is {special} ({}); a tracked path must be a regular file or a directory", source.display()))
}

/// The variant dimensions each stage fans out on, sorted: its own variants, the seeds if it
/// runs per seed, and those of its single inputs; it has one instance per combination. `stages`
/// are in dependency order.
pub fn dimensions(stages: &[Stage], seeded: bool) -> Vec<Vec<String>> {
    let mut dims_of: Vec<Vec<String>> = Vec::with_capacity(stages.len());
    for stage in stages {
        let own = stage.variants.len() > 1 || stage.variants[0].name.is_some();
        let mut dims: Vec<String> = if own { vec![stage.name.clone()] } else { Vec::new() };
        if stage.per_seed && seeded {
            dims.push(SEED_DIMENSION.to_owned());
        }
        for b in stage.bindings.iter().filter(|b| b.arity == Arity::One) {
            dims.extend(dims_of[b.providers[0]].iter().cloned());
        }
        dims.sort();
        dims.dedup();
        dims_of.push(dims);
    }
    dims_of
}

/// The slots of `kind` that operator `op` reads.
fn operator_slots(registry: &Registry, op: &str, kind: &StageKind) -> Vec<&'static str> {
    match registry.get(op).and_then(|o| o.spec().inputs) {
        Some(slots) => slots.to_vec(),
        None => kind.inputs.iter().map(|s| s.name).collect(),
    }
}

/// Deep-merges `overrides` into `base` (tables merge, everything else replaces).
fn merge(base: &mut Map<String, Value>, overrides: &Map<String, Value>) {
    for (k, v) in overrides {
        match (base.get_mut(k), v) {
            (Some(Value::Object(b)), Value::Object(o)) => merge(b, o),
            _ => {
                base.insert(k.clone(), v.clone());
            }
        }
    }
}

/// ", did you mean `x`?" for the nearest candidate, if one is close.
pub fn suggest(word: &str, candidates: &[&str]) -> String {
    let best = candidates
        .iter()
        .map(|c| (strsim::damerau_levenshtein(word, c), *c))
        .filter(|(d, c)| *d > 0 && *d <= (c.len().max(word.len()) / 3).max(2))
        .min();
    best.map_or(String::new(), |(_, c)| format!("; did you mean `{c}`?"))
}

fn line_starts(text: &str) -> Vec<usize> {
    std::iter::once(0).chain(text.match_indices('\n').map(|(i, _)| i + 1)).collect()
}

fn to_json_table(table: &DeTable<'_>) -> Map<String, Value> {
    table.iter().map(|(k, v)| (k.get_ref().to_string(), to_json(v.get_ref()))).collect()
}

fn to_json(value: &DeValue<'_>) -> Value {
    match value {
        DeValue::String(s) => Value::String(s.to_string()),
        DeValue::Integer(i) => {
            let parsed = i64::from_str_radix(&i.as_str().replace('_', ""), i.radix());
            parsed.map_or_else(|_| Value::String(i.as_str().to_owned()), Value::from)
        }
        DeValue::Float(f) => {
            let text = f.as_str().replace('_', "");
            let x: f64 = match text.as_str() {
                "inf" | "+inf" => f64::INFINITY,
                "-inf" => f64::NEG_INFINITY,
                "nan" | "+nan" | "-nan" => f64::NAN,
                t => t.parse().unwrap_or(f64::NAN),
            };
            serde_json::Number::from_f64(x).map_or(Value::String(text), Value::Number)
        }
        DeValue::Boolean(b) => Value::Bool(*b),
        DeValue::Datetime(d) => Value::String(d.to_string()),
        DeValue::Array(items) => Value::Array(items.iter().map(|v| to_json(v.get_ref())).collect()),
        DeValue::Table(t) => Value::Object(to_json_table(t)),
    }
}
