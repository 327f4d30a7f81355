//! The Operator contract: one implementation of a stage kind, configured by a plain settings struct.

use std::ops::Range;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::context::Context;
use crate::memory::Footprint;
use crate::numerics::Target;
use crate::outline::{InputOutlines, Outline};
use crate::settings::{FilePattern, Parsed, SettingError, Settings, parse_settings};

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
    pub kernels: Option<crate::numerics::Kernels>,
}

impl Default for Resources {
    fn default() -> Self {
        Resources { threads: 1, gpu: false, needs_cuda: false, kernels: None }
    }
}

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

/// An [`Operator`] with its settings type erased, as the engine's registry stores it. A stage's
/// settings are parsed once ([`DynOperator::settings`]) and handed back as [`Parsed`], so every
/// later question reads the typed value.
pub trait DynOperator: Send + Sync {
    fn spec(&self) -> OperatorSpec;
    /// Fills in defaults and checks a stage's settings: every setting, canonical, and typed.
    fn settings(&self, raw: Value) -> Result<Parsed, SettingError>;
    /// Every setting at its default (which need not be valid alone: `import`'s `path` must be set).
    fn defaults(&self) -> Value;
    fn non_result_keys(&self) -> &'static [&'static str];
    fn tracked_keys(&self) -> &'static [&'static str];
    /// [`Settings::check_tracked`] of these settings.
    fn check_tracked(&self, settings: &Parsed, key: &str, path: &std::path::Path) -> Result<(), SettingError>;
    /// [`Settings::tracked_files`] of these settings.
    fn tracked_files(&self, settings: &Parsed, key: &str) -> Option<Vec<FilePattern>>;
    /// What an action of these settings needs (threads, a GPU, its kernels).
    fn resources(&self, settings: &Parsed) -> Resources;
    fn worker(&self) -> Option<&'static str>;
    /// The operator that merges this one's shards, when it can be sharded.
    fn merge(&self) -> Option<&'static str>;
    /// How many items these settings produce and what an item is (`frames`), when the operator
    /// can be sharded.
    fn items(&self, settings: &Parsed) -> Option<(ItemCount, &'static str)>;
    /// The settings of the shard computing `part`, when the operator can be sharded that way.
    fn part(&self, settings: &Parsed, part: &Part) -> Option<Parsed>;
    /// The output's outline for these settings and the inputs' outlines.
    fn outline(&self, settings: &Parsed, inputs: &InputOutlines) -> Result<Outline, SettingError>;
    fn footprint(&self, settings: &Parsed, inputs: &InputOutlines, target: Target) -> Option<Footprint>;
    fn resumes_from(&self) -> &'static str;
    /// [`Operator::metrics`] of these settings.
    fn metrics(&self, settings: &Parsed) -> Vec<String>;
    /// [`Settings::CLAIMS`].
    fn claims_key(&self) -> Option<&'static str>;
    fn run(&self, settings: &Parsed, ctx: &mut Context) -> anyhow::Result<Outcome>;
}

impl<O: Operator> DynOperator for O {
    fn spec(&self) -> OperatorSpec {
        Operator::spec(self)
    }

    fn settings(&self, raw: Value) -> Result<Parsed, SettingError> {
        Ok(Parsed::of(parse_settings::<O::Settings>(raw)?))
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

    fn check_tracked(&self, settings: &Parsed, key: &str, path: &std::path::Path) -> Result<(), SettingError> {
        settings.typed::<O::Settings>().check_tracked(key, path)
    }

    fn tracked_files(&self, settings: &Parsed, key: &str) -> Option<Vec<FilePattern>> {
        settings.typed::<O::Settings>().tracked_files(key)
    }

    fn resources(&self, settings: &Parsed) -> Resources {
        Operator::resources(self, settings.typed())
    }

    fn worker(&self) -> Option<&'static str> {
        Operator::worker(self)
    }

    fn merge(&self) -> Option<&'static str> {
        Operator::sharding(self).map(|s| s.merge)
    }

    fn items(&self, settings: &Parsed) -> Option<(ItemCount, &'static str)> {
        let sharding = Operator::sharding(self)?;
        let count = match sharding.items {
            Items::Counted { count, .. } => ItemCount::Known(count(settings.typed())),
            Items::OfInput { slot, .. } => ItemCount::OfInput(slot),
        };
        Some((count, sharding.unit))
    }

    fn part(&self, settings: &Parsed, part: &Part) -> Option<Parsed> {
        let typed = settings.typed();
        let settings = match (Operator::sharding(self)?.items, part) {
            (Items::Counted { part, .. }, Part::Items(range)) => part(typed, range.clone()),
            (Items::OfInput { part, .. }, Part::Share(share)) => part(typed, *share),
            _ => return None,
        };
        Some(Parsed::of(settings))
    }

    fn outline(&self, settings: &Parsed, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        Operator::outline(self, settings.typed(), inputs)
    }

    fn footprint(&self, settings: &Parsed, inputs: &InputOutlines, target: Target) -> Option<Footprint> {
        Operator::footprint(self, settings.typed(), inputs, target)
    }

    fn resumes_from(&self) -> &'static str {
        Operator::resumes_from(self)
    }

    fn metrics(&self, settings: &Parsed) -> Vec<String> {
        Operator::metrics(self, settings.typed())
    }

    fn claims_key(&self) -> Option<&'static str> {
        O::Settings::CLAIMS
    }

    fn run(&self, settings: &Parsed, ctx: &mut Context) -> anyhow::Result<Outcome> {
        Operator::run(self, settings.typed(), ctx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        fn resources(&self, s: &Demo) -> Resources {
            Resources { threads: s.threads, ..Resources::default() }
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

    /// Settings are parsed once: every later question reads the typed value, and never settings
    /// another operator parsed.
    #[test]
    fn parsed_settings_answer_every_question_from_the_typed_value() {
        let parsed = DemoOp.settings(serde_json::json!({"threads": 3})).unwrap();
        assert_eq!(parsed.typed::<Demo>().threads, 3);
        assert_eq!(DynOperator::resources(&DemoOp, &parsed).threads, 3);
        assert_eq!(parsed, serde_json::json!({"alpha": 0.0, "threads": 3, "nested": {"image": 0}}));
        let other = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| DynOperator::metrics(&GroupOp, &parsed)));
        assert!(other.is_err(), "settings another operator parsed are never read as this one's");
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
