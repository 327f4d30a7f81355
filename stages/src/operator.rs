//! The Operator contract: one implementation of a stage kind, configured by a plain settings struct.

use std::fmt;
use std::ops::Range;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::context::Context;
use crate::kind::{Catalog, StageKind};
use crate::memory::Footprint;
use crate::numerics::Target;

/// An operator's settings: a plain struct with defaults (`#[serde(default, deny_unknown_fields)]`).
pub trait Settings: Serialize + DeserializeOwned + Default + Send + Sync + 'static {
    /// Settings that cannot change the result (thread counts, logging cadence). They are left out
    /// of the action key, so changing them reuses cached results.
    const NON_RESULT: &'static [&'static str] = &[];

    /// Settings that name a file or directory outside the store (relative to the pipeline file)
    /// that the operator reads: the engine tracks each by content (its digest enters the key as
    /// an input in the slot of the setting's name, `ctx.input(key)`, a snapshot of it in the
    /// store), so the path itself stays out of the key and out of the artifact. One left empty
    /// reads nothing; an operator that needs it says so in [`Settings::check`].
    const TRACKED: &'static [&'static str] = &[];

    /// The setting through which the operator receives the pipeline's claims
    /// ([`crate::claims::Spec`], from `[claims]`): the engine fills it in, so it enters the key
    /// as any setting, and a stage may not set it itself. `None`: the operator reads no claims.
    const CLAIMS: Option<&'static str> = None;

    /// Checks that types cannot express ("impossible settings"). The error names the key.
    fn check(&self) -> Result<(), SettingError> {
        Ok(())
    }

    /// Checks what tracked setting `key` names, before anything runs: `path` (resolved against
    /// the pipeline file) is a regular file or a directory; the engine refuses anything else
    /// without opening it.
    fn check_tracked(&self, _key: &str, _path: &std::path::Path) -> Result<(), SettingError> {
        Ok(())
    }

    /// The files tracked setting `key` names where it names chosen files rather than one path
    /// (a script's `sources`): patterns relative to the pipeline file, which the engine resolves
    /// inside the pipeline file's directory and tracks as one tree. `None`: the setting is one
    /// path, a string.
    fn tracked_files(&self, _key: &str) -> Option<Vec<FilePattern>> {
        None
    }

    /// The settings as an artifact may record them: those the key covers ([`result_settings`]).
    fn result_settings(&self) -> Value {
        result_settings(&serde_json::to_value(self).expect("settings serialise to JSON"), Self::NON_RESULT, Self::TRACKED)
    }
}

/// The settings an action's key covers, so an artifact that records them stays a function of its
/// key: all but the `non_result` ones and the `tracked` ones that are set or list files (their
/// content is an input of the key instead).
pub fn result_settings(settings: &Value, non_result: &[&str], tracked: &[&str]) -> Value {
    let mut value = settings.clone();
    if let Value::Object(map) = &mut value {
        for key in non_result {
            map.remove(*key);
        }
        for key in tracked {
            let named = match map.get(*key) {
                Some(Value::String(path)) => !path.is_empty(),
                // Chosen files ([`Settings::tracked_files`]): their content is the input.
                Some(Value::Array(_)) => true,
                _ => false,
            };
            if named {
                map.remove(*key);
            }
        }
    }
    value
}

/// Files a tracked setting names ([`Settings::tracked_files`]): a glob (`*`, `?`, `[..]` within
/// a name, `**` across directories) or a plain path, relative to the pipeline file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FilePattern {
    pub pattern: String,
    /// It must match at least one file; else it counts where it names a file (a command's
    /// argument that may or may not be one).
    pub required: bool,
}

/// A setting that is invalid: its dotted key (relative to the stage table) and what is valid.
#[derive(Clone, Debug, PartialEq)]
pub struct SettingError {
    pub key: String,
    pub message: String,
    /// Valid names for the key, when the key itself is unknown (used to suggest the nearest).
    pub valid: Vec<String>,
}

impl SettingError {
    pub fn new(key: impl Into<String>, message: impl Into<String>) -> Self {
        SettingError { key: key.into(), message: message.into(), valid: Vec::new() }
    }

    /// A documented bound: `Ok` when `value` lies in `range`, else an error naming the key and
    /// the bounds. Every numeric setting has one, so a setting that validates cannot exhaust
    /// memory or run forever.
    pub fn check_range<T: PartialOrd + fmt::Display>(key: &str, value: T, range: std::ops::RangeInclusive<T>) -> Result<(), SettingError> {
        if range.contains(&value) {
            return Ok(());
        }
        Err(SettingError::new(key, format!("must be in {}..={}, not {value}", range.start(), range.end())))
    }

    /// `value` in (0, `max`]: a rate or a norm that must not be zero.
    pub fn check_positive(key: &str, value: f64, max: f64) -> Result<(), SettingError> {
        if value > 0.0 && value <= max {
            return Ok(());
        }
        Err(SettingError::new(key, format!("must be in (0, {max}], not {value}")))
    }
}

impl fmt::Display for SettingError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.key, self.message)
    }
}

/// An operator's run may fail with one (`anyhow::Error::new(SettingError::new(..))`, context
/// around it allowed) when only the data shows a setting is wrong: the engine then names the
/// setting's file and line.
impl std::error::Error for SettingError {}

/// What identifies an operator to the engine.
#[derive(Clone, Copy, Debug)]
pub struct OperatorSpec {
    /// The name `pipeline.toml` selects it by, e.g. `highway-env`.
    pub name: &'static str,
    /// The stage kind it implements, e.g. `scenes`.
    pub kind: &'static str,
    /// Bumped by hand whenever the operator's results change for the same settings and inputs;
    /// part of every action key.
    pub version: u32,
    /// The kind's input slots it reads; `None` means all of them. A baseline that ignores an
    /// optional input lists the others, so it does not fan out over that input's variants.
    pub inputs: Option<&'static [&'static str]>,
    /// One line for `--help`-style listings.
    pub summary: &'static str,
}

/// What an operator asks of the machine.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Resources {
    /// The most threads the operator can use; the scheduler grants up to this many.
    pub threads: usize,
    /// It uses a GPU where there is one.
    pub gpu: bool,
    /// It cannot run without a CUDA device (its `device` names one): a run checks for one before
    /// anything starts.
    pub needs_cuda: bool,
    /// Its bytes depend on the kernels it computes with (libtorch's): the engine pins them and
    /// keys the action by its numeric platform class (see [`crate::numerics`]).
    pub kernels: Option<crate::Kernels>,
}

impl Default for Resources {
    fn default() -> Self {
        Resources { threads: 1, gpu: false, needs_cuda: false, kernels: None }
    }
}

/// What a stage's output will be, as far as settings tell before anything runs: what checks
/// across stages read (an image side a ViT patch must divide, frames a batch must not exceed).
/// `None`: not known from settings.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Outline {
    /// The side of the frames' primary image, in pixels.
    pub image: Option<u64>,
    /// The frames the artifact holds.
    pub frames: Option<u64>,
    /// The groups a split keeps whole (a sequence's frames; a frame outside any is its own).
    pub groups: Option<u64>,
    /// The frames of the training split, in expectation (the split is by identity): what a
    /// batch is checked against.
    pub train_frames: Option<u64>,
    /// A tokens artifact's tokens per caption and largest vocabulary.
    pub context: Option<u64>,
    pub vocab: Option<u64>,
    /// The model an encoder artifact holds.
    pub model: Option<ModelOutline>,
}

/// An encoder's model as its consumers' memory estimates need it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModelOutline {
    pub parameters: u64,
    /// The radar tower's token width and the side of its token grid.
    pub width: u64,
    pub grid: u64,
    /// The shared space's width.
    pub embed: u64,
}

impl Outline {
    /// What two outlines (a stage's variants) agree on.
    pub fn common(self, other: Outline) -> Outline {
        fn same<T: PartialEq>(a: Option<T>, b: Option<T>) -> Option<T> {
            if a == b { a } else { None }
        }
        Outline {
            image: same(self.image, other.image),
            frames: same(self.frames, other.frames),
            groups: same(self.groups, other.groups),
            train_frames: same(self.train_frames, other.train_frames),
            context: same(self.context, other.context),
            vocab: same(self.vocab, other.vocab),
            model: same(self.model, other.model),
        }
    }

    /// The outline of input `slot`'s first artifact, if it is bound.
    pub fn of<'a>(inputs: &'a InputOutlines, slot: &str) -> Option<&'a Outline> {
        inputs.get(slot).and_then(|v| v.first())
    }

    /// The outline a stage passes on by default: that of the scenes it reads, else of its first
    /// input.
    pub fn passed_on(inputs: &InputOutlines) -> Outline {
        inputs.get("scenes").or_else(|| inputs.values().next()).and_then(|v| v.first()).copied().unwrap_or_default()
    }

    /// [`Outline::passed_on`] as an [`InWorker`]'s outline check, for settings that read nothing of it.
    pub fn pass_on<S>(_: &S, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        Ok(Outline::passed_on(inputs))
    }
}

/// The outlines of a stage's inputs, by slot (a gathered slot's in order).
pub type InputOutlines<'a> = std::collections::BTreeMap<&'a str, Vec<Outline>>;

/// What a finished operator reports besides its output files.
#[derive(Clone, Debug, Default)]
pub struct Outcome {
    /// Stored in the action record and shown by `rlmflow show`.
    pub metrics: Value,
    /// One line for the run summary.
    pub summary: String,
}

/// One implementation of a stage kind. Operators know nothing of scheduling or caching: they read
/// the context's inputs and write files into its output directory.
pub trait Operator: Send + Sync + 'static {
    type Settings: Settings;

    fn spec(&self) -> OperatorSpec;

    fn resources(&self, _settings: &Self::Settings) -> Resources {
        Resources::default()
    }

    /// The binary that runs this operator when it is not the one planning it: operators that
    /// link libtorch run in the `rlmflow-torch` worker, so `rlmflow` itself never loads it.
    fn worker(&self) -> Option<&'static str> {
        None
    }

    /// Whether a stage of this operator can run as shards (`shards = N` in `pipeline.toml`).
    fn sharding(&self) -> Option<Sharding<Self::Settings>> {
        None
    }

    /// Its output's outline given its inputs', or the setting that cannot fit them: checked when
    /// the pipeline is validated. By default it passes on its scenes' outline.
    fn outline(&self, _settings: &Self::Settings, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        Ok(Outline::passed_on(inputs))
    }

    /// Its estimated peak memory (see [`crate::memory`]), for operators that train models;
    /// `None` where it is small or unknown.
    fn footprint(&self, _settings: &Self::Settings, _inputs: &InputOutlines, _target: Target) -> Option<Footprint> {
        None
    }

    /// What an interrupted action resumes from, as `status` says it.
    fn resumes_from(&self) -> &'static str {
        "its checkpoint"
    }

    /// The dotted paths of the metrics its artifact measures with these settings (its type's
    /// [`crate::measure::Measures`]), which claims may name; empty: none declared, so a claim's
    /// metric is checked only once it is measured.
    fn metrics(&self, _settings: &Self::Settings) -> Vec<String> {
        Vec::new()
    }

    fn run(&self, settings: &Self::Settings, ctx: &mut Context) -> anyhow::Result<Outcome>;
}

/// How an operator splits one action into independent parts. Its output is a sequence of items
/// (frames, say), each computed from its own index alone; a part's settings compute some of them,
/// and the `merge` operator, gathering the parts' outputs in order, writes exactly the output the
/// unsplit action would have: so the number of shards is a scheduling choice that changes no byte
/// downstream.
pub struct Sharding<S> {
    /// What an item is, for messages: `frames`.
    pub unit: &'static str,
    pub items: Items<S>,
    /// An operator of a kind that gathers this one's artifacts into one of the same type.
    pub merge: &'static str,
}

/// Where a shardable operator's items come from, and the settings of a part of them.
pub enum Items<S> {
    /// Counted from the settings when the pipeline is planned (`procedural`'s frames); `part`
    /// gives the settings that compute items `range` only.
    Counted { count: fn(&S) -> u64, part: fn(&S, Range<u64>) -> S },
    /// The items of input `slot` (`llm`'s labelled frames), counted only when a part runs; `part`
    /// gives the settings that compute one [`Share`] of them.
    OfInput { slot: &'static str, part: fn(&S, Share) -> S },
}

/// Part `index` of `of` near-equal consecutive parts of a sequence of items.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Share {
    pub index: u64,
    pub of: u64,
}

impl Share {
    /// The items this share takes of `items`: the shares of one sequence are consecutive and
    /// cover it.
    pub fn range(self, items: u64) -> Range<u64> {
        let at = |j: u64| (j as u128 * items as u128 / self.of as u128) as u64;
        at(self.index)..at(self.index + 1)
    }
}

/// The items a shard computes, as the planner knows them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Part {
    Items(Range<u64>),
    Share(Share),
}

/// How many items a shardable operator's settings make, as the planner can know it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ItemCount {
    Known(u64),
    /// As many as input `slot` holds, known only when a part runs.
    OfInput(&'static str),
}

/// An operator that runs in a worker binary, defined once in a light crate: its spec, settings,
/// resources, outline and footprint, so the planning binary validates every setting up front
/// without the worker's libraries. The worker registers the same value with its training
/// function attached ([`InWorker::running`]), so both binaries check a pipeline alike.
pub struct InWorker<S: Settings> {
    pub spec: OperatorSpec,
    pub worker: &'static str,
    pub resources: fn(&S) -> Resources,
    /// Its settings checked against its inputs' outlines (see [`Operator::outline`]).
    pub outline: fn(&S, &InputOutlines) -> Result<Outline, SettingError>,
    /// See [`Operator::footprint`].
    pub footprint: fn(&S, &InputOutlines, Target) -> Option<Footprint>,
    /// See [`Operator::metrics`].
    pub metrics: fn(&S) -> Vec<String>,
    /// What runs an action: attached in the worker only.
    pub run: Option<fn(&S, &mut Context) -> anyhow::Result<Outcome>>,
}

impl<S: Settings> InWorker<S> {
    /// The operator as its worker registers it, running actions with `run`.
    pub fn running(self, run: fn(&S, &mut Context) -> anyhow::Result<Outcome>) -> InWorker<S> {
        InWorker { run: Some(run), ..self }
    }
}

impl<S: Settings> Operator for InWorker<S> {
    type Settings = S;

    fn spec(&self) -> OperatorSpec {
        self.spec
    }

    fn resources(&self, settings: &S) -> Resources {
        (self.resources)(settings)
    }

    fn worker(&self) -> Option<&'static str> {
        Some(self.worker)
    }

    fn outline(&self, settings: &S, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        (self.outline)(settings, inputs)
    }

    fn footprint(&self, settings: &S, inputs: &InputOutlines, target: Target) -> Option<Footprint> {
        (self.footprint)(settings, inputs, target)
    }

    fn metrics(&self, settings: &S) -> Vec<String> {
        (self.metrics)(settings)
    }

    fn run(&self, settings: &S, ctx: &mut Context) -> anyhow::Result<Outcome> {
        match self.run {
            Some(run) => run(settings, ctx),
            None => anyhow::bail!("operator `{}` runs in the `{}` binary, not in this one", self.spec.name, self.worker),
        }
    }
}

/// An [`Operator`] with its settings type erased, as the engine's registry stores it. Settings
/// travel as JSON objects.
pub trait DynOperator: Send + Sync {
    fn spec(&self) -> OperatorSpec;
    /// Fills in defaults and checks a stage's settings; returns every setting, canonical.
    fn settings(&self, raw: Value) -> Result<Value, SettingError>;
    /// Every setting at its default (which need not be valid alone: `import`'s `path` must be set).
    fn defaults(&self) -> Value;
    fn non_result_keys(&self) -> &'static [&'static str];
    fn tracked_keys(&self) -> &'static [&'static str];
    /// [`Settings::check_tracked`] of these settings.
    fn check_tracked(&self, settings: &Value, key: &str, path: &std::path::Path) -> Result<(), SettingError>;
    /// [`Settings::tracked_files`] of these settings.
    fn tracked_files(&self, settings: &Value, key: &str) -> Result<Option<Vec<FilePattern>>, SettingError>;
    /// What an action of these settings needs (threads, a GPU, its kernels); an error names the
    /// setting that does not parse (every planned instance's settings were normalised through
    /// [`DynOperator::settings`] first, so that would be a broken invariant, never hidden behind
    /// defaults).
    fn resources(&self, settings: &Value) -> Result<Resources, SettingError>;
    fn worker(&self) -> Option<&'static str>;
    /// The operator that merges this one's shards, when it can be sharded.
    fn merge(&self) -> Option<&'static str>;
    /// How many items these settings produce and what an item is (`frames`), when the operator
    /// can be sharded.
    fn items(&self, settings: &Value) -> Option<(ItemCount, &'static str)>;
    /// The settings of the shard computing `part`, when the operator can be sharded that way.
    fn part(&self, settings: &Value, part: &Part) -> Option<Value>;
    /// The output's outline for valid `settings` and the inputs' outlines.
    fn outline(&self, settings: &Value, inputs: &InputOutlines) -> Result<Outline, SettingError>;
    fn footprint(&self, settings: &Value, inputs: &InputOutlines, target: Target) -> Option<Footprint>;
    fn resumes_from(&self) -> &'static str;
    /// [`Operator::metrics`] of valid `settings`.
    fn metrics(&self, settings: &Value) -> Result<Vec<String>, SettingError>;
    /// [`Settings::CLAIMS`].
    fn claims_key(&self) -> Option<&'static str>;
    fn run(&self, settings: &Value, ctx: &mut Context) -> anyhow::Result<Outcome>;
}

impl<O: Operator> DynOperator for O {
    fn spec(&self) -> OperatorSpec {
        Operator::spec(self)
    }

    fn settings(&self, raw: Value) -> Result<Value, SettingError> {
        let typed = parse_settings::<O::Settings>(raw)?;
        Ok(serde_json::to_value(&typed).expect("settings serialise to JSON"))
    }

    fn defaults(&self) -> Value {
        serde_json::to_value(O::Settings::default()).expect("settings serialise to JSON")
    }

    fn non_result_keys(&self) -> &'static [&'static str] {
        O::Settings::NON_RESULT
    }

    fn tracked_keys(&self) -> &'static [&'static str] {
        O::Settings::TRACKED
    }

    fn check_tracked(&self, settings: &Value, key: &str, path: &std::path::Path) -> Result<(), SettingError> {
        parse_settings::<O::Settings>(settings.clone())?.check_tracked(key, path)
    }

    fn tracked_files(&self, settings: &Value, key: &str) -> Result<Option<Vec<FilePattern>>, SettingError> {
        Ok(parse_settings::<O::Settings>(settings.clone())?.tracked_files(key))
    }

    fn resources(&self, settings: &Value) -> Result<Resources, SettingError> {
        Ok(Operator::resources(self, &parse_settings::<O::Settings>(settings.clone())?))
    }

    fn worker(&self) -> Option<&'static str> {
        Operator::worker(self)
    }

    fn merge(&self) -> Option<&'static str> {
        Operator::sharding(self).map(|s| s.merge)
    }

    fn items(&self, settings: &Value) -> Option<(ItemCount, &'static str)> {
        let sharding = Operator::sharding(self)?;
        let count = match sharding.items {
            Items::Counted { count, .. } => ItemCount::Known(count(&parse_settings::<O::Settings>(settings.clone()).ok()?)),
            Items::OfInput { slot, .. } => ItemCount::OfInput(slot),
        };
        Some((count, sharding.unit))
    }

    fn part(&self, settings: &Value, part: &Part) -> Option<Value> {
        let typed = parse_settings::<O::Settings>(settings.clone()).ok()?;
        let settings = match (Operator::sharding(self)?.items, part) {
            (Items::Counted { part, .. }, Part::Items(range)) => part(&typed, range.clone()),
            (Items::OfInput { part, .. }, Part::Share(share)) => part(&typed, *share),
            _ => return None,
        };
        Some(serde_json::to_value(&settings).expect("settings serialise to JSON"))
    }

    fn outline(&self, settings: &Value, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        Operator::outline(self, &parse_settings::<O::Settings>(settings.clone())?, inputs)
    }

    fn footprint(&self, settings: &Value, inputs: &InputOutlines, target: Target) -> Option<Footprint> {
        Operator::footprint(self, &parse_settings::<O::Settings>(settings.clone()).ok()?, inputs, target)
    }

    fn resumes_from(&self) -> &'static str {
        Operator::resumes_from(self)
    }

    fn metrics(&self, settings: &Value) -> Result<Vec<String>, SettingError> {
        Ok(Operator::metrics(self, &parse_settings::<O::Settings>(settings.clone())?))
    }

    fn claims_key(&self) -> Option<&'static str> {
        O::Settings::CLAIMS
    }

    fn run(&self, settings: &Value, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let typed = parse_settings::<O::Settings>(settings.clone()).map_err(|e| anyhow::anyhow!("invalid settings: {e}"))?;
        Operator::run(self, &typed, ctx)
    }
}

/// Typed settings from a stage's table: given keys over the operator's defaults, deserialised
/// with the failing key's path, then checked. A struct that flattens a shared group (such as
/// [`crate::Training`]) cannot deny unknown fields through serde, and serde loses the key of a
/// bad value inside the group: both are recovered here, so every struct reports alike.
fn parse_settings<S: Settings>(raw: Value) -> Result<S, SettingError> {
    let defaults = serde_json::to_value(S::default()).expect("settings serialise to JSON");
    if let Some(e) = not_finite(&defaults, &raw, &mut Vec::new()) {
        return Err(e);
    }
    let Value::Object(given) = &raw else { return deserialize::<S>(raw, &defaults).and_then(|t| t.check().map(|()| t)) };
    let typed: S = deserialize(over_defaults(&defaults, given), &defaults).map_err(|e| match e.key.is_empty() {
        true => locate::<S>(&defaults, given).unwrap_or(e),
        false => e,
    })?;
    let Value::Object(known) = serde_json::to_value(&typed).expect("settings serialise to JSON") else { return Ok(typed) };
    if let Some(unknown) = given.keys().find(|k| !known.contains_key(*k)) {
        return Err(SettingError { key: unknown.clone(), message: format!("unknown setting `{unknown}`"), valid: known.keys().cloned().collect() });
    }
    typed.check()?;
    Ok(typed)
}

/// The defaults with the given top-level keys replaced.
fn over_defaults(defaults: &Value, given: &serde_json::Map<String, Value>) -> Value {
    let mut full = defaults.clone();
    if let Value::Object(map) = &mut full {
        map.extend(given.iter().map(|(k, v)| (k.clone(), v.clone())));
    }
    full
}

/// The first given key whose value alone, over the defaults, fails to deserialise, with its error.
fn locate<S: Settings>(defaults: &Value, given: &serde_json::Map<String, Value>) -> Option<SettingError> {
    given.iter().find_map(|(key, value)| {
        let one = serde_json::Map::from_iter([(key.clone(), value.clone())]);
        deserialize::<S>(over_defaults(defaults, &one), defaults).err().map(|e| SettingError { key: key.clone(), ..e })
    })
}

/// `value` as `S`; an error is read against `defaults` (`S::default()` as JSON).
fn deserialize<S: Settings>(value: Value, defaults: &Value) -> Result<S, SettingError> {
    serde_path_to_error::deserialize(value).map_err(|e| {
        let key = e.path().to_string();
        // Read from where the error is, never from serde's wording: a key the defaults' table
        // there lacks is unknown (and the valid keys are what a user may set: those the defaults
        // show, so an internal one such as a shard's share, skipped while unset, is not offered).
        if let Some((field, valid)) = unknown_key(defaults, &key) {
            return SettingError { message: format!("unknown setting `{field}`"), key, valid };
        }
        SettingError::new(if key == "." { String::new() } else { key }, e.inner().to_string())
    })
}

/// The first `nan` or `inf` given where the defaults hold a number: the config reader hands
/// them over as their text (JSON has no such numbers), which serde would call a type error.
/// `path` holds the keys (or item indices) down to `given`, written out only for a hit.
fn not_finite(defaults: &Value, given: &Value, path: &mut Vec<String>) -> Option<SettingError> {
    let mut inside = |segment: String, value: &Value| {
        path.push(segment);
        let found = not_finite(defaults, value, path);
        path.pop();
        found
    };
    match given {
        Value::Object(table) => table.iter().find_map(|(key, value)| inside(key.clone(), value)),
        Value::Array(items) => items.iter().enumerate().find_map(|(i, value)| inside(i.to_string(), value)),
        Value::String(text) if matches!(text.trim_start_matches(['+', '-']), "nan" | "inf") => {
            let key = path.join(".");
            number_expected(defaults, &key).then(|| SettingError::new(&key, format!("`{text}` is not a finite number")))
        }
        _ => None,
    }
}

/// The value at dotted `path` (`.`: the whole) inside `value`.
fn at<'v>(value: &'v Value, path: &str) -> Option<&'v Value> {
    path.split('.').filter(|p| !p.is_empty()).try_fold(value, |v, p| v.get(p))
}

/// `path`'s last key and the keys beside it, when the defaults hold a table at its parent that
/// lacks that key.
fn unknown_key(defaults: &Value, path: &str) -> Option<(String, Vec<String>)> {
    let (parent, field) = path.rsplit_once('.').unwrap_or(("", path));
    let table = at(defaults, parent)?.as_object()?;
    (!field.is_empty() && field != "." && !table.contains_key(field)).then(|| (field.to_owned(), table.keys().cloned().collect()))
}

/// Whether the defaults hold a number at `path` (or a list of numbers: `path` then names an item).
fn number_expected(defaults: &Value, path: &str) -> bool {
    let (parent, last) = path.rsplit_once('.').unwrap_or(("", path));
    match at(defaults, path) {
        Some(v) => v.is_number(),
        None => {
            last.parse::<usize>().is_ok() && at(defaults, parent).and_then(Value::as_array).is_some_and(|items| items.iter().all(Value::is_number))
        }
    }
}

/// The stage kinds and operators an rlmflow binary knows. Each operator has an id, the name
/// keys and plans hold: its name, or `NAME@KIND` for one of an operator serving several kinds
/// (a `script`), each kind's its own definition.
#[derive(Default)]
pub struct Registry {
    pub catalog: Catalog,
    operators: Vec<(String, Box<dyn DynOperator>)>,
    libraries: Vec<&'static str>,
    kernel_pin: Option<fn() -> anyhow::Result<()>>,
}

impl Registry {
    pub fn new(catalog: Catalog) -> Self {
        Registry { catalog, ..Registry::default() }
    }

    /// What makes this binary's numeric library compute as the kernel pins (environment
    /// variables, [`crate::numerics::apply`]) ask, where reading the variables is not enough
    /// (`rlmflow-torch` installs its chain GEMM): run once by `exec`, after the pins are set and
    /// before the operator computes anything.
    pub fn set_kernel_pin(&mut self, pin: fn() -> anyhow::Result<()>) -> &mut Self {
        self.kernel_pin = Some(pin);
        self
    }

    /// Applies the kernel pin, where the binary has one.
    pub fn pin_kernels(&self) -> anyhow::Result<()> {
        self.kernel_pin.map_or(Ok(()), |pin| pin())
    }

    /// Names a numeric library this binary's operators compute with (`libtorch 2.11.0`), for
    /// the provenance of the actions whose bytes depend on it.
    pub fn add_library(&mut self, name: &'static str) -> &mut Self {
        self.libraries.push(name);
        self
    }

    pub fn libraries(&self) -> &[&'static str] {
        &self.libraries
    }

    /// Adds an operator. Panics if its kind is unknown or its name taken: both are programming
    /// errors in the binary that builds the registry, caught by its first test.
    pub fn add(&mut self, op: impl DynOperator + 'static) -> &mut Self {
        let id = op.spec().name.to_owned();
        self.insert(id, Box::new(op))
    }

    /// Adds one definition of an operator that serves several kinds, as `NAME@KIND`: a stage
    /// names it by its name alone, its kind choosing the definition.
    pub fn add_for_kind(&mut self, op: impl DynOperator + 'static) -> &mut Self {
        let spec = op.spec();
        self.insert(format!("{}@{}", spec.name, spec.kind), Box::new(op))
    }

    fn insert(&mut self, id: String, op: Box<dyn DynOperator>) -> &mut Self {
        let spec = op.spec();
        let kind = self.catalog.get(spec.kind).unwrap_or_else(|| panic!("operator `{}` implements unknown stage kind `{}`", spec.name, spec.kind));
        for slot in spec.inputs.unwrap_or(&[]) {
            assert!(kind.slot(slot).is_some(), "operator `{}` reads unknown slot `{slot}`", spec.name);
        }
        assert!(self.find(spec.kind, spec.name).is_none() && self.get(&id).is_none(), "operator `{id}` registered twice");
        self.operators.push((id, op));
        self
    }

    /// The operator of id `id` (as plans and keys name it).
    pub fn get(&self, id: &str) -> Option<&dyn DynOperator> {
        self.operators.iter().find(|(i, _)| i == id).map(|(_, o)| o.as_ref())
    }

    /// The id and definition of the operator a stage of `kind` names `name`.
    pub fn find(&self, kind: &str, name: &str) -> Option<(&str, &dyn DynOperator)> {
        self.operators.iter().find(|(_, o)| o.spec().kind == kind && o.spec().name == name).map(|(i, o)| (i.as_str(), o.as_ref()))
    }

    /// The first operator named `name`, of whichever kind (for a message when a stage names an
    /// operator of another kind).
    pub fn named(&self, name: &str) -> Option<&dyn DynOperator> {
        self.operators.iter().find(|(_, o)| o.spec().name == name).map(|(_, o)| o.as_ref())
    }

    pub fn kind(&self, name: &str) -> Option<&StageKind> {
        self.catalog.get(name)
    }

    /// Operators implementing a stage kind, in registration order.
    pub fn operators_of(&self, kind: &str) -> impl Iterator<Item = &dyn DynOperator> {
        self.operators.iter().filter(move |(_, o)| o.spec().kind == kind).map(|(_, o)| o.as_ref())
    }

    /// Every operator with its id, in registration order.
    pub fn operators(&self) -> impl Iterator<Item = (&str, &dyn DynOperator)> {
        self.operators.iter().map(|(i, o)| (i.as_str(), o.as_ref()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Serialize, Deserialize, Default)]
    #[serde(default, deny_unknown_fields)]
    struct Demo {
        alpha: f64,
        threads: usize,
        nested: Nested,
    }

    #[derive(Serialize, Deserialize, Default)]
    #[serde(default, deny_unknown_fields)]
    struct Nested {
        image: u32,
    }

    impl Settings for Demo {
        const NON_RESULT: &'static [&'static str] = &["threads"];
        fn check(&self) -> Result<(), SettingError> {
            if self.alpha < 0.0 {
                return Err(SettingError::new("alpha", "must be >= 0"));
            }
            Ok(())
        }
    }

    struct DemoOp;
    impl Operator for DemoOp {
        type Settings = Demo;
        fn spec(&self) -> OperatorSpec {
            OperatorSpec { name: "demo", kind: "scenes", version: 1, inputs: None, summary: "" }
        }
        fn run(&self, _: &Demo, _: &mut Context) -> anyhow::Result<Outcome> {
            Ok(Outcome::default())
        }
    }

    #[test]
    fn settings_fill_defaults_and_canonicalise_numbers() {
        let v = DemoOp.settings(serde_json::json!({"alpha": 4})).unwrap();
        assert_eq!(v, serde_json::json!({"alpha": 4.0, "threads": 0, "nested": {"image": 0}}));
    }

    #[test]
    fn unknown_keys_name_the_key_and_list_valid_ones() {
        let e = DemoOp.settings(serde_json::json!({"alpah": 1.0})).unwrap_err();
        assert_eq!(e.key, "alpah");
        assert_eq!(e.valid, vec!["alpha", "nested", "threads"]);
        let e = DemoOp.settings(serde_json::json!({"nested": {"imag": 3}})).unwrap_err();
        assert_eq!(e.key, "nested.imag");
        assert_eq!(e.valid, vec!["image"]);
    }

    /// What an action needs comes from settings that parse; others are an error naming the key,
    /// never the defaults' resources in silence.
    #[test]
    fn resources_of_settings_that_do_not_parse_name_the_key() {
        let valid = DemoOp.settings(serde_json::json!({"alpha": 1.0})).unwrap();
        assert_eq!(DynOperator::resources(&DemoOp, &valid).unwrap(), Resources::default());
        let e = DynOperator::resources(&DemoOp, &serde_json::json!({"alpha": "fast"})).unwrap_err();
        assert_eq!(e.key, "alpha");
    }

    #[test]
    fn an_internal_setting_is_not_offered_as_a_valid_key() {
        #[derive(Debug, Serialize, Deserialize, Default)]
        #[serde(default, deny_unknown_fields)]
        struct Sharded {
            frames: u64,
            #[serde(skip_serializing_if = "Option::is_none")]
            shard: Option<u64>,
        }
        impl Settings for Sharded {}
        let e = parse_settings::<Sharded>(serde_json::json!({"frame": 3})).unwrap_err();
        assert_eq!((e.key.as_str(), e.valid.clone()), ("frame", vec!["frames".to_owned()]));
    }

    #[test]
    fn type_errors_and_checks_name_the_key() {
        let e = DemoOp.settings(serde_json::json!({"nested": {"image": "big"}})).unwrap_err();
        assert_eq!(e.key, "nested.image");
        assert!(e.message.contains("invalid type"), "{}", e.message);
        let e = DemoOp.settings(serde_json::json!({"alpha": "nan"})).unwrap_err();
        assert_eq!((e.key.as_str(), e.message.as_str()), ("alpha", "`nan` is not a finite number"));
        let e = DemoOp.settings(serde_json::json!({"alpha": -1.0})).unwrap_err();
        assert_eq!((e.key.as_str(), e.message.as_str()), ("alpha", "must be >= 0"));
    }

    /// Settings with a shared group flattened in, as the torch operators hold `Training`.
    #[derive(Serialize, Deserialize)]
    #[serde(default)]
    struct WithGroup {
        alpha: f64,
        #[serde(flatten)]
        group: Group,
    }

    #[derive(Serialize, Deserialize)]
    struct Group {
        lr: f64,
        epochs: u64,
    }

    impl Default for WithGroup {
        fn default() -> Self {
            WithGroup { alpha: 1.0, group: Group { lr: 0.5, epochs: 3 } }
        }
    }

    impl Settings for WithGroup {}

    struct GroupOp;
    impl Operator for GroupOp {
        type Settings = WithGroup;
        fn spec(&self) -> OperatorSpec {
            OperatorSpec { name: "group", kind: "scenes", version: 1, inputs: None, summary: "" }
        }
        fn run(&self, _: &WithGroup, _: &mut Context) -> anyhow::Result<Outcome> {
            Ok(Outcome::default())
        }
    }

    #[test]
    fn a_flattened_group_keeps_flat_keys_the_operators_defaults_and_named_errors() {
        assert_eq!(GroupOp.settings(serde_json::json!({"lr": 1})).unwrap(), serde_json::json!({"alpha": 1.0, "lr": 1.0, "epochs": 3}));
        let e = GroupOp.settings(serde_json::json!({"alpha": 2.0, "lr": "fast"})).unwrap_err();
        assert_eq!(e.key, "lr");
        assert!(e.message.contains("invalid type"), "{}", e.message);
        let e = GroupOp.settings(serde_json::json!({"lr": "-inf"})).unwrap_err();
        assert_eq!((e.key.as_str(), e.message.as_str()), ("lr", "`-inf` is not a finite number"));
        let e = GroupOp.settings(serde_json::json!({"epoch": 2})).unwrap_err();
        assert_eq!((e.key.as_str(), e.message.as_str()), ("epoch", "unknown setting `epoch`"));
        assert_eq!(e.valid, ["alpha", "epochs", "lr"]);
    }
}
