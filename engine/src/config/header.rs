//! The `[pipeline]` header: the remote cache, the executor, seeds.

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use serde_json::{Map, Value};

use super::checker::Checker;
use super::hyperqueue::HyperQueueSettings;
use super::{INSTANCES_CEILING, MAX_INSTANCES, suggest};

/// `[pipeline]`, checked.
pub(super) struct Header {
    pub name: String,
    pub seed: u64,
    pub seeds: Vec<u64>,
    pub seed_rule: Option<SeedRule>,
    pub max_instances: u64,
    pub cache: PathBuf,
    pub results: Option<PathBuf>,
    pub executor: Executor,
    pub gpus: Option<Vec<usize>>,
    pub hyperqueue: HyperQueueSettings,
    pub remote: RemoteSettings,
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
        Ok(self.open_transport()?.with_trust(trusted, self.signing_key()?))
    }

    /// When pushing, the key of [`SIGNING_KEY_VARIABLE`] (if set) the records are signed with;
    /// an error for a file that cannot be read or holds no key.
    pub fn signing_key(&self) -> anyhow::Result<Option<rlmflow_remote::signing::SigningKey>> {
        let Some(file) = std::env::var_os(SIGNING_KEY_VARIABLE).filter(|_| self.push) else { return Ok(None) };
        let text = std::fs::read_to_string(&file).with_context(|| format!("{SIGNING_KEY_VARIABLE}: reading {}", file.to_string_lossy()))?;
        let key =
            rlmflow_remote::signing::SigningKey::parse(&text).with_context(|| format!("{SIGNING_KEY_VARIABLE} ({})", file.to_string_lossy()))?;
        Ok(Some(key))
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

pub(super) const PIPELINE_KEYS: &[&str] = &[
    "name",
    "seed",
    "seeds",
    "cache",
    "results",
    "executor",
    "gpus",
    "hyperqueue",
    "remote",
    "remote_push",
    "remote_timeout_s",
    "remote_trusted_keys",
    "max_instances",
];
/// The most seeds a pipeline may list.
const MAX_SEEDS: usize = 64;

impl Checker {
    /// `results` of `[pipeline]`: `results` beside the file by default, `""` for none. Never
    /// the store or inside it, nor the pipeline's own directory or an ancestor of the store (a
    /// run replaces the links it holds).
    pub(super) fn results_dir(&mut self, file: &Path, header: &Map<String, Value>, cache: &Path) -> Option<PathBuf> {
        let setting = self.string(header, "pipeline", "results").unwrap_or_else(|| "results".into());
        if setting.is_empty() {
            return None;
        }
        let base = file.parent().unwrap_or(Path::new("."));
        let dir = std::path::absolute(base.join(&setting)).unwrap_or_else(|_| base.join(&setting));
        let base = std::path::absolute(base).unwrap_or_else(|_| base.to_path_buf());
        let clean = |p: &Path| p.components().collect::<PathBuf>();
        let (d, c) = (clean(&dir), clean(cache));
        if d.starts_with(&c) || c.starts_with(&d) || d == clean(&base) {
            let help = "a directory of its own, such as \"results\", or \"\" for none".to_owned();
            let msg = format!("`{setting}` would mix the run's links with the store or the pipeline's own files");
            self.error(self.line("pipeline.results"), "pipeline.results", msg, Some(help));
            return None;
        }
        Some(dir)
    }

    /// `remote`, `remote_push`, `remote_timeout_s` of `[pipeline]`.
    pub(super) fn remote(&mut self, file: &Path, header: &Map<String, Value>) -> RemoteSettings {
        let mut remote = RemoteSettings { url: self.string(header, "pipeline", "remote"), ..RemoteSettings::default() };
        if let Some(url) = remote.url.clone() {
            let resolved = resolve_remote(&url, file.parent().unwrap_or(Path::new(".")));
            let help = "e.g. remote = \"s3://bucket/rlmflow\", \"https://cache.example/rlmflow\" (WebDAV) or \"file:///srv/rlmflow\"";
            if !REMOTE_SCHEMES.iter().any(|scheme| url.starts_with(scheme)) {
                self.error(self.line("pipeline.remote"), "pipeline.remote", format!("`{url}` is not a remote URL"), Some(help.into()));
            } else if let Err(problem) = rlmflow_remote::check_url(&resolved) {
                self.error(self.line("pipeline.remote"), "pipeline.remote", problem.to_string(), Some(help.into()));
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

    /// `seeds = [1, 2, 3]`: distinct non-negative integers, at most [`MAX_SEEDS`]; or
    /// `seeds = { first = 1, min = 3, max = 12, until = "claims" }`: the seeds a run starts with
    /// (`min` of them from `first`) and the rule that adds more.
    pub(super) fn seeds(&mut self, header: &Map<String, Value>) -> (Vec<u64>, Option<SeedRule>) {
        let key = "pipeline.seeds";
        let Some(value) = header.get("seeds") else { return (Vec::new(), None) };
        if let Value::Object(table) = value {
            return match self.seed_rule(table) {
                Some(rule) => (rule.seeds(rule.min), Some(rule)),
                None => (Vec::new(), None),
            };
        }
        let seeds: Option<Vec<u64>> = value.as_array().and_then(|items| items.iter().map(Value::as_u64).collect());
        let problem = match &seeds {
            None => Some(format!("must be a list of non-negative integers or a table {{ min, max, until = \"claims\" }}, not {value}")),
            Some(s) if s.is_empty() || s.len() > MAX_SEEDS => Some(format!("must list 1 to {MAX_SEEDS} seeds, not {}", s.len())),
            Some(s) if (1..s.len()).any(|i| s[..i].contains(&s[i])) => Some("lists a seed twice".into()),
            Some(_) => None,
        };
        match problem {
            Some(msg) => {
                self.error(self.line(key), key, msg, Some("e.g. seeds = [1, 2, 3]".into()));
                (Vec::new(), None)
            }
            None => (seeds.unwrap_or_default(), None),
        }
    }

    fn seed_rule(&mut self, table: &Map<String, Value>) -> Option<SeedRule> {
        const KEYS: &[&str] = &["first", "min", "max", "until"];
        let key = "pipeline.seeds";
        for k in table.keys().filter(|k| !KEYS.contains(&k.as_str())) {
            self.unknown_key(&format!("{key}.{k}"), k, KEYS);
        }
        let mut count = |name: &str, default: u64, range: std::ops::RangeInclusive<u64>| -> Option<u64> {
            match table.get(name) {
                None => Some(default),
                Some(v) => v.as_u64().filter(|n| range.contains(n)).or_else(|| {
                    let msg = format!("must be an integer in {}..={}, not {v}", range.start(), range.end());
                    self.error(self.line(&format!("{key}.{name}")), &format!("{key}.{name}"), msg, None);
                    None
                }),
            }
        };
        let first = count("first", 1, 0..=u64::MAX - MAX_SEEDS as u64);
        let min = count("min", 3, 2..=MAX_SEEDS as u64);
        let max = count("max", 12, 2..=MAX_SEEDS as u64);
        match table.get("until") {
            Some(Value::String(until)) if until == "claims" => {}
            other => {
                let shown = other.map_or("nothing".to_owned(), Value::to_string);
                let help = "seeds = { min = 3, max = 12, until = \"claims\" } adds seeds until every claim of [claims] is decided".into();
                self.error(self.line(&format!("{key}.until")), &format!("{key}.until"), format!("must be \"claims\", not {shown}"), Some(help));
                return None;
            }
        }
        let (first, min, max) = (first?, min? as usize, max? as usize);
        if min > max {
            self.error(self.line(key), key, format!("`min` ({min}) is more than `max` ({max})"), None);
            return None;
        }
        Some(SeedRule { first, min, max })
    }
}

/// `[pipeline] seeds = { first, min, max, until = "claims" }`: a run starts with `min` seeds
/// from `first` and adds the next one until every claim is decided, or `max` are done.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SeedRule {
    pub first: u64,
    pub min: usize,
    pub max: usize,
}

impl SeedRule {
    /// The first `n` seeds.
    pub fn seeds(&self, n: usize) -> Vec<u64> {
        (0..n as u64).map(|i| self.first + i).collect()
    }
}

impl Checker {
    /// `[pipeline]`: its keys, the name (the file's stem by default), seeds, the instance bound,
    /// the store, results links, executor and remote.
    pub(super) fn header(&mut self, file: &Path, root: &Map<String, Value>) -> Header {
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
        let (seeds, seed_rule) = self.seeds(header);
        if seed_rule.is_some() && !root.contains_key("claims") {
            let help = "add [claims], or list the seeds: seeds = [1, 2, 3]".to_owned();
            let msg = "adds seeds until the claims are decided, and the file has no [claims]".into();
            self.error(self.line("pipeline.seeds"), "pipeline.seeds", msg, Some(help));
        }
        let max_instances = match header.get("max_instances") {
            None => MAX_INSTANCES,
            Some(v) => v.as_u64().filter(|n| (1..=INSTANCES_CEILING).contains(n)).unwrap_or_else(|| {
                let msg = format!("must be a positive integer up to {INSTANCES_CEILING}, not {v}");
                self.error(self.line("pipeline.max_instances"), "pipeline.max_instances", msg, None);
                MAX_INSTANCES
            }),
        };
        let cache = self.string(header, "pipeline", "cache").unwrap_or_else(|| ".rlmflow".into());
        let cache = file.parent().unwrap_or(Path::new(".")).join(cache);
        let cache = std::path::absolute(&cache).unwrap_or(cache);
        let results = self.results_dir(file, header, &cache);
        let executor = match self.string(header, "pipeline", "executor") {
            None => Executor::Local,
            Some(name) => Executor::parse(&name).unwrap_or_else(|| {
                let help = format!("valid executors: {}{}", Executor::NAMES.join(", "), suggest(&name, Executor::NAMES));
                self.error(self.line("pipeline.executor"), "pipeline.executor", format!("unknown executor `{name}`"), Some(help));
                Executor::Local
            }),
        };
        let gpus = header.get("gpus").and_then(|value| {
            let list: Option<Vec<usize>> = value.as_array().and_then(|items| items.iter().map(|v| v.as_u64().map(|n| n as usize)).collect());
            let problem = match &list {
                None => format!("must be a list of GPU indices, not {value}"),
                Some(l) if l.is_empty() => "lists no GPU; leave it out to use every GPU".into(),
                Some(l) if (1..l.len()).any(|i| l[..i].contains(&l[i])) => "lists a GPU twice".into(),
                Some(_) => return list,
            };
            self.error(self.line("pipeline.gpus"), "pipeline.gpus", problem, Some("e.g. gpus = [0, 1] (as nvidia-smi numbers them)".into()));
            None
        });
        let hyperqueue = self.hyperqueue(file, header.get("hyperqueue"));
        let remote = self.remote(file, header);
        Header { name, seed, seeds, seed_rule, max_instances, cache, results, executor, gpus, hyperqueue, remote }
    }
}
