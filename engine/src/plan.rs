//! From a validated pipeline to stage instances (variants fanned out), their preimages, and
//! whether each is cached, will run (and why), or waits for an upstream that will run.

use std::collections::{BTreeMap, HashMap};

use anyhow::{Context as _, bail};
use rlmflow_cache::external::Source;
use rlmflow_cache::{ActionRecord, ActionRequest, Digest, InputDigest, InstanceRef, Preimage, Store};
use rlmflow_stages::{Arity, InstanceId, Parsed, Part, Registry, SettingError};
use serde_json::Value;

use crate::config::{Pipeline, SEED_LABEL, suggest};
use crate::platform::Platform;
use crate::reason::{RunReason, Waiting, why};

/// One stage run for one combination of upstream variants; a sharded stage's instance is its
/// parts (`scenes#0`, `scenes#1`, ...) and the merge of them (`scenes`), which consumers read.
#[derive(Clone, Debug)]
pub struct Instance {
    pub stage: usize,
    /// `scenes`, `pretrain[alpha4]`, `probe[captions=llm,pretrain=alpha4]`, or `scenes#2`.
    pub label: String,
    /// Variant dimension (the stage that declared the variants) -> variant name.
    pub assignment: BTreeMap<String, String>,
    /// Its seed, where it runs per seed (else the pipeline's `seed` is in its key).
    pub seed: Option<u64>,
    /// The operator it runs: the stage's, or the merge operator of a sharded stage.
    pub operator: String,
    /// Every setting of this instance, parsed once when the pipeline was read.
    pub settings: Parsed,
    pub inputs: Vec<InstanceInput>,
    /// Which shard it is, and the items it computes (`None`: not a shard).
    pub shard: Option<(usize, Part)>,
    /// Files or directories outside the store it reads: input slot -> path.
    pub tracked: Vec<(String, Source)>,
}

#[derive(Clone, Debug)]
pub struct InstanceInput {
    pub slot: &'static str,
    pub arity: Arity,
    /// Indices into `Plan::instances`.
    pub providers: Vec<usize>,
}

/// Every instance of a pipeline, providers before consumers.
#[derive(Debug)]
pub struct Plan<'p> {
    pub pipeline: &'p Pipeline,
    pub instances: Vec<Instance>,
    /// The content of every tracked path ([`Plan::fingerprint`]).
    pub tracked: BTreeMap<Source, Digest>,
    /// The machine's numeric platform, for the keys of actions whose bytes depend on it.
    pub platform: Platform,
}

/// An instance's variant per dimension, and its seed where it runs per seed.
type Assignment = (BTreeMap<String, String>, Option<u64>);

/// Every instance of `pipeline`, keyed for a run on this machine with the default `--device`.
pub fn plan(pipeline: &Pipeline) -> Plan<'_> {
    plan_on(pipeline, Platform::detect(rlmflow_stages::Device::Cpu))
}

/// Every instance of `pipeline`, keyed for a run on `platform`.
pub fn plan_on(pipeline: &Pipeline, platform: Platform) -> Plan<'_> {
    let mut instances: Vec<Instance> = Vec::new();
    let dims_of = crate::config::dimensions(&pipeline.stages, !pipeline.seeds.is_empty());
    // The whole (not shard) instances of each stage so far, for inputs that gather them all.
    let mut whole_of: Vec<Vec<usize>> = vec![Vec::new(); pipeline.stages.len()];
    let mut by_assignment: HashMap<(usize, Assignment), usize> = HashMap::new();
    for (s, stage) in pipeline.stages.iter().enumerate() {
        let dims = &dims_of[s];
        let mut assignments: Vec<Assignment> = vec![(BTreeMap::new(), None)];
        // In label order, which is plan order: by name, the seed as `seed`.
        let mut axes: Vec<Option<&String>> = dims.variants.iter().map(Some).collect();
        if dims.seeded {
            axes.push(None);
        }
        axes.sort_by_key(|axis| axis.map_or(SEED_LABEL, |d| d.as_str()));
        for axis in axes {
            assignments = assignments
                .into_iter()
                .flat_map(|(a, seed)| -> Vec<Assignment> {
                    match axis {
                        None => pipeline.seeds.iter().map(|&n| (a.clone(), Some(n))).collect(),
                        Some(dim) => {
                            let owner = &pipeline.stages[pipeline.stage(dim).unwrap()];
                            let names = owner.variants.iter().filter_map(|v| v.name.clone());
                            names.map(|n| (a.clone().into_iter().chain([(dim.clone(), n)]).collect(), seed)).collect()
                        }
                    }
                })
                .collect();
        }
        for (assignment, seed) in assignments {
            let variant = match assignment.get(&stage.name) {
                Some(v) => stage.variants.iter().find(|x| x.name.as_ref() == Some(v)).unwrap(),
                None => &stage.variants[0],
            };
            let inputs = stage
                .bindings
                .iter()
                .map(|b| {
                    let providers = match b.arity {
                        Arity::One => {
                            let p = b.providers[0];
                            let seed = seed.filter(|_| dims_of[p].seeded);
                            vec![by_assignment[&(p, (restrict(&assignment, &dims_of[p].variants), seed))]]
                        }
                        Arity::All => {
                            let mut all: Vec<usize> = b.providers.iter().flat_map(|&p| whole_of[p].iter().copied()).collect();
                            all.sort_by(|&x, &y| instances[x].label.cmp(&instances[y].label));
                            all.dedup();
                            all
                        }
                    };
                    InstanceInput { slot: b.slot, arity: b.arity, providers }
                })
                .collect();
            let label = label(&stage.name, &assignment, seed);
            let whole = match &stage.merge {
                None => Instance {
                    stage: s,
                    label,
                    assignment: assignment.clone(),
                    seed,
                    operator: stage.operator.clone(),
                    settings: variant.settings.clone(),
                    inputs,
                    shard: None,
                    tracked: variant.tracked.clone(),
                },
                Some(merge) => {
                    let mut parts = Vec::new();
                    for (j, (part, settings)) in variant.shards.iter().enumerate() {
                        parts.push(instances.len());
                        instances.push(Instance {
                            stage: s,
                            label: format!("{label}#{j}"),
                            assignment: assignment.clone(),
                            seed,
                            operator: stage.operator.clone(),
                            settings: settings.clone(),
                            inputs: inputs.clone(),
                            shard: Some((j, part.clone())),
                            tracked: variant.tracked.clone(),
                        });
                    }
                    let inputs = vec![InstanceInput { slot: merge.slot, arity: Arity::All, providers: parts }];
                    Instance {
                        stage: s,
                        label,
                        assignment: assignment.clone(),
                        seed,
                        operator: merge.operator.clone(),
                        settings: merge.settings.clone(),
                        inputs,
                        shard: None,
                        tracked: Vec::new(),
                    }
                }
            };
            by_assignment.insert((s, (assignment, seed)), instances.len());
            whole_of[s].push(instances.len());
            instances.push(whole);
        }
    }
    Plan { pipeline, instances, tracked: BTreeMap::new(), platform }
}

fn restrict(a: &BTreeMap<String, String>, dims: &[String]) -> BTreeMap<String, String> {
    a.iter().filter(|(d, _)| dims.contains(d)).map(|(d, v)| (d.clone(), v.clone())).collect()
}

/// How an instance's variants are named: the variant alone for a stage's one variant dimension,
/// else each with its dimension (`dim`, `v`); the seed always with its name (`seed=2`), so a
/// report can tell seeds from variants. By name, the seed as `seed`: a gathered input's label
/// is in its consumer's key.
pub fn variant_names(a: &BTreeMap<String, String>, seed: Option<u64>) -> Vec<(Option<&str>, String)> {
    if seed.is_none() && a.len() == 1 {
        return a.values().map(|v| (None, v.clone())).collect();
    }
    let mut names: Vec<(Option<&str>, String)> = a.iter().map(|(d, v)| (Some(d.as_str()), v.clone())).collect();
    if let Some(seed) = seed {
        let at = names.partition_point(|(d, _)| d.is_some_and(|d| d < SEED_LABEL));
        names.insert(at, (Some(SEED_LABEL), seed.to_string()));
    }
    names
}

/// `stage`, `stage[variant]` for one variant dimension, `stage[dim=v,...]` for several
/// ([`variant_names`]).
pub fn label(stage: &str, a: &BTreeMap<String, String>, seed: Option<u64>) -> String {
    if a.is_empty() && seed.is_none() {
        return stage.to_owned();
    }
    let names: Vec<String> = variant_names(a, seed).into_iter().map(|(d, v)| d.map_or_else(|| v.clone(), |d| format!("{d}={v}"))).collect();
    format!("{stage}[{}]", names.join(","))
}

impl Plan<'_> {
    /// Every instance, in the order a run starts the ready ones: the longest chain of instances
    /// waiting on it first, so the work the rest of the pipeline waits for is not queued behind
    /// work nothing waits for (cargo's job queue favours a unit by what waits on it too); plan
    /// order among equals.
    pub fn start_order(&self) -> Vec<usize> {
        let mut chain = vec![1usize; self.instances.len()];
        // Providers come before consumers: a consumer's chain is final before its providers'.
        for i in (0..self.instances.len()).rev() {
            for &p in self.instances[i].inputs.iter().flat_map(|input| &input.providers) {
                chain[p] = chain[p].max(chain[i] + 1);
            }
        }
        let mut order: Vec<usize> = (0..self.instances.len()).collect();
        order.sort_by_key(|&i| std::cmp::Reverse(chain[i]));
        order
    }

    /// The one instance `text` names, as a run prints it: `clipcap[alpha4]`, its long form
    /// `clipcap[pretrain=alpha4]`, with `seed=N` where the stage runs per seed (among several
    /// seeds one must be named); an error lists what would be valid, the nearest first.
    pub fn instance_named(&self, text: &str) -> anyhow::Result<usize> {
        match self.labelled(text)?.as_slice() {
            [one] => Ok(*one),
            many => {
                let labels: Vec<&str> = many.iter().map(|&n| self.instances[n].label.as_str()).collect();
                bail!("`{text}` names {} instances: {}; name one (its seed with `seed=N`)", many.len(), labels.join(", "))
            }
        }
    }

    /// The instances `text` names wherever a command takes a stage: every instance of the stage
    /// it names, or those its label names as a run prints it (`clipcap[alpha4]`, `pretrain[clip]`
    /// for all of that variant's seeds, `pretrain[clip,seed=2]` for one); on a typo, the nearest
    /// stage or label.
    pub fn instances_named(&self, text: &str) -> anyhow::Result<Vec<usize>> {
        if text.contains('[') {
            return self.labelled(text);
        }
        match self.pipeline.stage(text) {
            Some(s) => Ok((0..self.instances.len()).filter(|&i| self.instances[i].stage == s).collect()),
            None => {
                let names = self.pipeline.stage_names();
                let mut near = names.clone();
                near.extend(self.whole().map(|i| i.label.as_str()));
                bail!("no stage named `{text}` in {}; stages: {}{}", self.pipeline.file.display(), names.join(", "), suggest(text, &near))
            }
        }
    }

    /// The instances that are not shards.
    fn whole(&self) -> impl Iterator<Item = &Instance> {
        self.instances.iter().filter(|i| i.shard.is_none())
    }

    /// The whole instances a label names (at least one).
    fn labelled(&self, text: &str) -> anyhow::Result<Vec<usize>> {
        let (stage, items) = match text.split_once('[') {
            Some((stage, rest)) => (stage, rest.strip_suffix(']').unwrap_or(rest)),
            None => (text, ""),
        };
        let Some(s) = self.pipeline.stage(stage) else {
            let names = self.pipeline.stage_names();
            let labels: Vec<&str> = self.whole().map(|i| i.label.as_str()).collect();
            bail!("no stage named `{stage}` in {}; stages: {}{}", self.pipeline.file.display(), names.join(", "), suggest(text, &labels));
        };
        let given: Vec<&str> = items.split(',').map(str::trim).filter(|i| !i.is_empty()).collect();
        let matches = |inst: &Instance| {
            given.iter().all(|item| match item.split_once('=') {
                Some((d, v)) if d.trim() == SEED_LABEL && inst.seed.is_some() => inst.seed.is_some_and(|n| n.to_string() == v.trim()),
                Some((d, v)) => inst.assignment.get(d.trim()).is_some_and(|x| x == v.trim()),
                None => inst.assignment.len() == 1 && inst.assignment.values().next().is_some_and(|v| v == item),
            })
        };
        let of_stage = || self.instances.iter().enumerate().filter(|(_, i)| i.stage == s && i.shard.is_none());
        let found: Vec<usize> = of_stage().filter(|(_, i)| matches(i)).map(|(n, _)| n).collect();
        if found.is_empty() {
            let labels: Vec<&str> = of_stage().map(|(_, i)| i.label.as_str()).collect();
            bail!("no instance `{text}`; instances of `{stage}`: {}{}", labels.join(", "), suggest(text, &labels))
        }
        Ok(found)
    }

    /// The instances `names` name ([`Plan::instances_named`]: stages or labels) and everything
    /// upstream of them; all of them when `names` is empty.
    pub fn select(&self, names: &[String]) -> anyhow::Result<Vec<bool>> {
        let mut keep = vec![names.is_empty(); self.instances.len()];
        for name in names {
            for i in self.instances_named(name)? {
                keep[i] = true;
            }
        }
        for i in (0..self.instances.len()).rev() {
            if keep[i] {
                for input in &self.instances[i].inputs {
                    for &p in &input.providers {
                        keep[p] = true;
                    }
                }
            }
        }
        Ok(keep)
    }

    /// What instance `i` is, as the store's refs name it.
    pub fn id(&self, i: usize) -> InstanceRef {
        let inst = &self.instances[i];
        InstanceRef {
            stage: self.pipeline.stages[inst.stage].name.clone(),
            variants: inst.assignment.clone(),
            seed: inst.seed,
            shard: inst.shard.as_ref().map(|(j, _)| *j),
        }
    }

    /// The producing instance of each of instance `i`'s single-artifact inputs, by slot.
    pub fn input_labels(&self, i: usize) -> BTreeMap<String, String> {
        let one = self.instances[i].inputs.iter().filter(|input| input.arity == Arity::One);
        one.filter_map(|input| Some((input.slot.to_owned(), self.instances[*input.providers.first()?].label.clone()))).collect()
    }

    /// What an action of instance `i` with `key` is run from: its preimage, settings and inputs.
    pub fn request(&self, i: usize, key: Digest, preimage: Preimage) -> ActionRequest {
        let inst = &self.instances[i];
        ActionRequest {
            key,
            stage: inst.label.clone(),
            preimage,
            settings: inst.settings.json().clone(),
            input_labels: self.input_labels(i),
            input_instances: self.input_instances(i),
        }
    }

    /// Every input provider of instance `i` as data, by label (`{"stage", "variant"}`).
    pub fn input_instances(&self, i: usize) -> BTreeMap<String, Value> {
        let providers = self.instances[i].inputs.iter().flat_map(|input| input.providers.iter());
        providers
            .map(|&p| {
                let provider = &self.instances[p];
                let id = InstanceId {
                    stage: self.pipeline.stages[provider.stage].name.clone(),
                    variant: provider.assignment.clone(),
                    seed: provider.seed,
                };
                (provider.label.clone(), serde_json::to_value(id).expect("an instance serialises"))
            })
            .collect()
    }

    /// Digests every tracked path (`rlmflow_cache::external`: a stat per unchanged file), the
    /// inputs of the preimages that name them.
    pub fn fingerprint(&mut self, store: Option<&Store>) -> anyhow::Result<()> {
        // Each source with the first instance and setting that name it, for the error.
        let mut sources: BTreeMap<Source, (usize, &str)> = BTreeMap::new();
        for (i, inst) in self.instances.iter().enumerate() {
            for (key, source) in &inst.tracked {
                sources.entry(source.clone()).or_insert((i, key));
            }
        }
        let mut digests = BTreeMap::new();
        for (source, (i, key)) in sources {
            let inst = &self.instances[i];
            let stage = &self.pipeline.stages[inst.stage].name;
            let info = rlmflow_cache::external::fingerprint(store, &source)
                .with_context(|| self.pipeline.locate(stage, inst.assignment.get(stage).map(String::as_str), key))?;
            digests.insert(source, info.digest);
        }
        self.tracked = digests;
        Ok(())
    }

    /// Copies instance `i`'s tracked paths into the store by the digests in its key, where the
    /// operator reads them.
    pub fn snapshot_tracked(&self, i: usize, store: &Store) -> anyhow::Result<()> {
        self.instances[i].tracked.iter().try_for_each(|(_, source)| rlmflow_cache::external::snapshot(store, source, &self.tracked[source]))
    }

    /// Instance `i`'s preimage once its inputs' outputs are known (`None` before); an error for
    /// settings its operator cannot read (a broken invariant: validation normalised them).
    pub fn preimage(&self, i: usize, registry: &Registry, outputs: &[Option<Digest>]) -> Result<Option<Preimage>, SettingError> {
        let Some(inputs) = self.input_digests(i, outputs) else { return Ok(None) };
        self.preimage_with(i, registry, inputs).map(Some)
    }

    /// Instance `i`'s preimage with `inputs` ([`Plan::input_digests`]).
    pub fn preimage_with(&self, i: usize, registry: &Registry, inputs: Vec<InputDigest>) -> Result<Preimage, SettingError> {
        let inst = &self.instances[i];
        let op = registry.get(&inst.operator).expect("validated operator");
        let config = rlmflow_stages::settings::result_settings(&inst.settings, op.non_result_keys(), op.tracked_keys());
        let seed = inst.seed.unwrap_or(self.pipeline.seed);
        let platform = op.resources(&inst.settings).kernels.map(|k| self.platform.class(k));
        Ok(Preimage { operator: inst.operator.clone(), operator_version: op.spec().version, config, seed, inputs, platform })
    }

    /// Instance `i`'s inputs by digest, sorted; `None` while one's output is unknown.
    pub fn input_digests(&self, i: usize, outputs: &[Option<Digest>]) -> Option<Vec<InputDigest>> {
        let inst = &self.instances[i];
        let mut inputs = Vec::new();
        for input in &inst.inputs {
            for &p in &input.providers {
                // Gathered inputs are ordered by label; a merge's parts by their items, so
                // neither the stage's name nor the number of digits enters the key.
                let label = match (input.arity, &self.instances[p].shard) {
                    (Arity::One, _) => String::new(),
                    (Arity::All, Some((_, Part::Items(items)))) => format!("{:020}..{:020}", items.start, items.end),
                    (Arity::All, Some((_, Part::Share(share)))) => format!("{:020}/{:020}", share.index, share.of),
                    (Arity::All, None) => self.instances[p].label.clone(),
                };
                inputs.push(InputDigest { slot: input.slot.to_owned(), label, digest: outputs[p]? });
            }
        }
        for (slot, source) in &inst.tracked {
            inputs.push(InputDigest { slot: slot.clone(), label: String::new(), digest: *self.tracked.get(source)? });
        }
        inputs.sort();
        Some(inputs)
    }
}

/// Where one instance stands before the run.
#[derive(Clone, Debug)]
pub enum Freshness {
    Cached(Box<ActionRecord>),
    /// Its key is known and not in the store.
    Stale {
        key: Digest,
        reasons: Vec<RunReason>,
        preimage: Box<Preimage>,
    },
    /// An input will be recomputed first, so its key is not known yet.
    Pending(Waiting),
}

/// The freshness of every instance, against `store` (`None`: nothing was ever run).
pub fn assess(plan: &Plan, registry: &Registry, store: Option<&Store>) -> anyhow::Result<Vec<Freshness>> {
    let last = match store {
        Some(s) => s.last_keys(&plan.pipeline.name)?,
        None => Default::default(),
    };
    let mut outputs: Vec<Option<Digest>> = vec![None; plan.instances.len()];
    let mut states = Vec::with_capacity(plan.instances.len());
    for (i, inst) in plan.instances.iter().enumerate() {
        let state = match plan.preimage(i, registry, &outputs)? {
            Some(preimage) => {
                let key = preimage.key();
                match store.map(|s| s.fresh(&key)).transpose()?.flatten() {
                    Some(record) => {
                        outputs[i] = Some(record.output);
                        Freshness::Cached(Box::new(record))
                    }
                    None => {
                        let stage = &plan.pipeline.stages[inst.stage].name;
                        let resumes = registry.get(&inst.operator).expect("validated operator").resumes_from();
                        let reasons = why(store, last.get(&plan.id(i), &inst.label).as_ref(), &key, &preimage, stage, resumes)?;
                        Freshness::Stale { key, reasons, preimage: Box::new(preimage) }
                    }
                }
            }
            None => {
                let (slot, provider) = inst
                    .inputs
                    .iter()
                    .flat_map(|input| input.providers.iter().map(move |&p| (input.slot, p)))
                    .find(|&(_, p)| outputs[p].is_none())
                    .expect("a preimage is unknown only while an input's output is");
                Freshness::Pending(Waiting { slot: slot.to_owned(), input: plan.instances[provider].label.clone() })
            }
        };
        states.push(state);
    }
    Ok(states)
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use rlmflow_stages::{Catalog, Context, Items, Operator, OperatorSpec, Outcome, Registry, Settings, Sharding, Share, Slot, StageKind};
    use serde::{Deserialize, Serialize};

    use super::*;
    use crate::config::parse;

    #[derive(Serialize, Deserialize, Default)]
    #[serde(default, deny_unknown_fields)]
    struct Knob {
        k: i64,
        nested: Nested,
    }
    #[derive(Serialize, Deserialize, Default)]
    #[serde(default, deny_unknown_fields)]
    struct Nested {
        a: i64,
        b: i64,
    }
    impl Settings for Knob {}

    struct Op(&'static str, &'static str);
    impl Operator for Op {
        type Settings = Knob;
        fn spec(&self) -> OperatorSpec {
            OperatorSpec { name: self.0, kind: self.1, version: 1, inputs: None, summary: "" }
        }
        fn run(&self, _: &Knob, _: &mut Context) -> anyhow::Result<Outcome> {
            Ok(Outcome::default())
        }
    }

    /// Makes `k` items; a part makes `k` items from `nested.a` on. It merges with `oj`.
    struct ShardedOp;
    impl Operator for ShardedOp {
        type Settings = Knob;
        fn spec(&self) -> OperatorSpec {
            OperatorSpec { name: "sa", kind: "a", version: 1, inputs: None, summary: "" }
        }
        fn sharding(&self) -> Option<Sharding<Knob>> {
            Some(Sharding {
                unit: "items",
                items: Items::Counted {
                    count: |s| s.k as u64,
                    part: |s, r| Knob { k: (r.end - r.start) as i64, nested: Nested { a: s.nested.a + r.start as i64, b: s.nested.b } },
                },
                merge: "oj",
            })
        }
        fn run(&self, _: &Knob, _: &mut Context) -> anyhow::Result<Outcome> {
            Ok(Outcome::default())
        }
    }

    /// Reads `a` and `b`; a part takes a share of `a`'s items, counted when it runs (as `llm`
    /// takes its labels'). It merges with `ojc`.
    struct SharedInputOp;
    impl Operator for SharedInputOp {
        type Settings = Knob;
        fn spec(&self) -> OperatorSpec {
            OperatorSpec { name: "sc", kind: "c", version: 1, inputs: None, summary: "" }
        }
        fn sharding(&self) -> Option<Sharding<Knob>> {
            Some(Sharding {
                unit: "items",
                items: Items::OfInput {
                    slot: "a",
                    part: |s, share| Knob { k: share.index as i64, nested: Nested { a: share.of as i64, b: s.nested.b } },
                },
                merge: "ojc",
            })
        }
        fn run(&self, _: &Knob, _: &mut Context) -> anyhow::Result<Outcome> {
            Ok(Outcome::default())
        }
    }

    const KINDS: &[StageKind] = &[
        StageKind { name: "a", produces: "A", inputs: &[], per_seed: false },
        StageKind { name: "join", produces: "A", inputs: &[Slot::gather("parts", "A")], per_seed: false },
        StageKind { name: "joinc", produces: "C", inputs: &[Slot::gather("parts", "C")], per_seed: false },
        StageKind { name: "b", produces: "B", inputs: &[], per_seed: false },
        StageKind { name: "c", produces: "C", inputs: &[Slot::one("a", "A"), Slot::one("b", "B")], per_seed: false },
        StageKind { name: "d", produces: "D", inputs: &[Slot::gather("c", "C")], per_seed: false },
    ];

    fn registry() -> Registry {
        let mut r = Registry::new(Catalog { kinds: KINDS.to_vec(), markers: Vec::new(), measures: Vec::new() });
        r.add(Op("oa", "a")).add(Op("ob", "b")).add(Op("oc", "c")).add(Op("od", "d")).add(ShardedOp).add(Op("oj", "join"));
        r.add(SharedInputOp).add(Op("ojc", "joinc"));
        r
    }

    const TWO_DIMS: &str = r#"
[stages.a]
operator = "oa"
nested = { a = 1, b = 2 }
variants = { x = { k = 1 }, y = { nested = { b = 5 } } }
[stages.b]
operator = "ob"
variants = { p = { k = 3 }, q = { k = 4 } }
[stages.c]
operator = "oc"
[stages.d]
operator = "od"
"#;

    #[test]
    fn two_variant_dimensions_fan_out_as_their_product_and_gather_into_one() {
        let r = registry();
        let p = parse(Path::new("t.toml"), TWO_DIMS, &r).unwrap();
        let plan = plan(&p);
        let labels: Vec<&str> = plan.instances.iter().map(|i| i.label.as_str()).collect();
        assert_eq!(labels, ["a[x]", "a[y]", "b[p]", "b[q]", "c[a=x,b=p]", "c[a=x,b=q]", "c[a=y,b=p]", "c[a=y,b=q]", "d"]);
        // c[a=y,b=q] reads a[y] and b[q].
        let c = &plan.instances[7];
        let inputs: Vec<&str> = c.inputs.iter().map(|i| plan.instances[i.providers[0]].label.as_str()).collect();
        assert_eq!(inputs, ["a[y]", "b[q]"]);
        assert_eq!(plan.instances[8].inputs[0].providers, [4, 5, 6, 7]);
    }

    #[test]
    fn variant_overrides_merge_into_nested_tables() {
        let r = registry();
        let p = parse(Path::new("t.toml"), TWO_DIMS, &r).unwrap();
        let plan = plan(&p);
        assert_eq!(plan.instances[0].settings, serde_json::json!({"k": 1, "nested": {"a": 1, "b": 2}}));
        assert_eq!(plan.instances[1].settings, serde_json::json!({"k": 0, "nested": {"a": 1, "b": 5}}));
    }

    /// `a` as data shared across seeds, `c` trained per seed (its `per_seed` key), `d` gathering.
    const SEEDS: &str = r#"
[pipeline]
seed = 7
seeds = [1, 2]
[stages.a]
operator = "oa"
variants = { x = {}, y = {} }
[stages.b]
operator = "ob"
[stages.c]
operator = "oc"
per_seed = true
[stages.d]
operator = "od"
"#;

    #[test]
    fn seeds_fan_out_the_per_seed_stages_and_run_with_their_seed() {
        let r = registry();
        let p = parse(Path::new("t.toml"), SEEDS, &r).unwrap();
        let plan = plan(&p);
        let labels: Vec<&str> = plan.instances.iter().map(|i| i.label.as_str()).collect();
        assert_eq!(labels, ["a[x]", "a[y]", "b", "c[a=x,seed=1]", "c[a=x,seed=2]", "c[a=y,seed=1]", "c[a=y,seed=2]", "d"]);
        // Both seeds of c[a=y] read the one a[y].
        assert_eq!(plan.instances[5].inputs[0].providers, plan.instances[6].inputs[0].providers);
        let outputs: Vec<Option<Digest>> = (0..plan.instances.len()).map(|i| Some(Digest::of(&[i as u8]))).collect();
        let seed = |i: usize| plan.preimage(i, &r, &outputs).unwrap().unwrap().seed;
        assert_eq!((seed(0), seed(2), seed(3), seed(4), seed(7)), (7, 7, 1, 2, 7));
        assert_ne!(plan.preimage(3, &r, &outputs).unwrap().unwrap().key(), plan.preimage(4, &r, &outputs).unwrap().unwrap().key());
        assert_eq!(plan.instances[7].inputs[0].providers, [3, 4, 5, 6], "the gathering stage reads every seed");
    }

    #[test]
    fn a_seed_is_a_number_of_its_own_and_labels_name_it_among_the_dimensions() {
        let r = registry();
        // `z` sorts after `seed`: labels (a gathered input's is in its consumer's key) and plan
        // order take the dimensions by name, the seed as `seed`, as they did when it was one.
        let text = SEEDS.replace("[stages.a]", "[stages.z]\nkind = \"a\"").replace("[stages.b]", "[stages.seed]\nkind = \"b\"");
        let p = parse(Path::new("t.toml"), &text, &r).unwrap();
        let plan = plan(&p);
        let labels: Vec<&str> = plan.instances.iter().map(|i| i.label.as_str()).collect();
        assert_eq!(labels, ["z[x]", "z[y]", "seed", "c[seed=1,z=x]", "c[seed=1,z=y]", "c[seed=2,z=x]", "c[seed=2,z=y]", "d"]);
        let c = &plan.instances[4];
        assert_eq!((c.seed, c.assignment.iter().collect::<Vec<_>>()), (Some(1), vec![(&"z".to_owned(), &"y".to_owned())]));
        let expected = InstanceRef { stage: "c".into(), variants: c.assignment.clone(), seed: Some(1), shard: None };
        assert_eq!(plan.id(4), expected);
        assert_eq!(plan.instances_named("c[y]").unwrap(), [4, 6]);
        assert_eq!(plan.instance_named("c[y,seed=2]").unwrap(), 6);
        assert_eq!(plan.instance_named("c[seed=2,z=y]").unwrap(), 6);
        // A stage named `seed` may vary only where labels would not name it beside the seed.
        let varied = text.replace("kind = \"b\"\noperator = \"ob\"", "kind = \"b\"\noperator = \"ob\"\nvariants = { p = {}, q = {} }");
        let e = parse(Path::new("t.toml"), &varied, &r).unwrap_err().to_string();
        assert!(e.contains("stages.seed") && e.contains("may not have variants when [pipeline] seeds is set"), "{e}");
        assert!(parse(Path::new("t.toml"), &varied.replace("seeds = [1, 2]\n", ""), &r).is_ok());
    }

    #[test]
    fn bad_seeds_are_config_errors() {
        let r = registry();
        for (seeds, expected) in
            [("[1, 1]", "lists a seed twice"), ("[]", "must list 1 to 64 seeds"), ("[-1]", "non-negative integers"), ("3", "must be a list")]
        {
            let text = SEEDS.replace("seeds = [1, 2]", &format!("seeds = {seeds}"));
            let e = parse(Path::new("t.toml"), &text, &r).unwrap_err().to_string();
            assert!(e.contains("pipeline.seeds") && e.contains(expected), "{seeds}: {e}");
        }
        let e = parse(Path::new("t.toml"), &SEEDS.replace("per_seed = true", "per_seed = 1"), &r).unwrap_err().to_string();
        assert!(e.contains("stages.c.per_seed: must be true or false"), "{e}");
    }

    #[test]
    fn gathered_labels_enter_the_key_but_single_input_labels_do_not() {
        let r = registry();
        let p = parse(Path::new("t.toml"), TWO_DIMS, &r).unwrap();
        let plan = plan(&p);
        let outputs: Vec<Option<Digest>> = (0..plan.instances.len()).map(|i| Some(Digest::of(&[i as u8]))).collect();
        let c = plan.preimage(7, &r, &outputs).unwrap().unwrap();
        assert!(c.inputs.iter().all(|i| i.label.is_empty()));
        let d = plan.preimage(8, &r, &outputs).unwrap().unwrap();
        let labels: Vec<&str> = d.inputs.iter().map(|i| i.label.as_str()).collect();
        assert_eq!(labels, ["c[a=x,b=p]", "c[a=x,b=q]", "c[a=y,b=p]", "c[a=y,b=q]"]);
    }

    const SHARDED: &str = r#"
[stages.a]
operator = "sa"
k = 10
shards = 3
variants = { x = {}, y = { k = 4 } }
[stages.b]
operator = "ob"
[stages.c]
operator = "oc"
[stages.d]
operator = "od"
"#;

    /// A stand-in output per instance: the digest of its settings, which neither a stage's name
    /// nor its place in the plan changes.
    fn outputs_by_settings(plan: &Plan) -> Vec<Option<Digest>> {
        plan.instances.iter().map(|i| Some(Digest::of(i.settings.to_string().as_bytes()))).collect()
    }

    #[test]
    fn a_sharded_stage_runs_as_parts_of_its_items_and_a_merge_that_consumers_read() {
        let r = registry();
        let p = parse(Path::new("t.toml"), SHARDED, &r).unwrap();
        let plan = plan(&p);
        let labels: Vec<&str> = plan.instances.iter().map(|i| i.label.as_str()).collect();
        assert_eq!(labels, ["a[x]#0", "a[x]#1", "a[x]#2", "a[x]", "a[y]#0", "a[y]#1", "a[y]#2", "a[y]", "b", "c[x]", "c[y]", "d"]);
        let parts: Vec<(i64, i64)> =
            plan.instances[..3].iter().map(|i| (i.settings["nested"]["a"].as_i64().unwrap(), i.settings["k"].as_i64().unwrap())).collect();
        assert_eq!(parts, [(0, 3), (3, 3), (6, 4)], "10 items in three parts");
        assert_eq!(plan.instances[6].shard.as_ref().map(|(_, p)| p), Some(&Part::Items(2..4)), "variant y has 4 items");
        let merge = &plan.instances[3];
        assert_eq!((merge.operator.as_str(), merge.inputs[0].slot, &merge.inputs[0].providers[..]), ("oj", "parts", &[0, 1, 2][..]));
        assert_eq!(plan.instances[9].inputs[0].providers, [3], "c[x] reads the merged a[x]");
        assert_eq!(plan.instances[11].inputs[0].providers, [9, 10], "a gathering stage reads no part");
        let preimage = plan.preimage(3, &r, &outputs_by_settings(&plan)).unwrap().unwrap();
        let order: Vec<&str> = preimage.inputs.iter().map(|i| i.label.as_str()).collect();
        assert_eq!(
            order,
            [
                "00000000000000000000..00000000000000000003",
                "00000000000000000003..00000000000000000006",
                "00000000000000000006..00000000000000000010"
            ]
        );
    }

    #[test]
    fn parts_and_merge_keys_do_not_depend_on_the_stage_name_and_shard_size_keeps_parts_when_items_grow() {
        let r = registry();
        let sized = SHARDED.replace("shards = 3", "shard_size = 4");
        let before = plan(&parse(Path::new("t.toml"), &sized, &r).unwrap()).instances.iter().map(|i| i.settings.clone()).collect::<Vec<_>>();
        let grown = parse(Path::new("t.toml"), &sized.replace("k = 10", "k = 13"), &r).unwrap();
        let grown = plan(&grown);
        let labels: Vec<&str> = grown.instances[..5].iter().map(|i| i.label.as_str()).collect();
        assert_eq!(labels, ["a[x]#0", "a[x]#1", "a[x]#2", "a[x]#3", "a[x]"]);
        assert_eq!(&grown.instances[0].settings, &before[0], "items 0..4 keep their settings");
        assert_eq!(&grown.instances[1].settings, &before[1], "items 4..8 keep their settings");
        assert_ne!(&grown.instances[2].settings, &before[2], "items 8..10 became 8..12");

        let p = parse(Path::new("t.toml"), SHARDED, &r).unwrap();
        let renamed = SHARDED.replace("[stages.a]", "[stages.z]\nkind = \"a\"");
        let q = parse(Path::new("t.toml"), &renamed, &r).unwrap();
        let (a, z) = (plan(&p), plan(&q));
        let z_merge = z.instances.iter().position(|i| i.label == "z[x]").unwrap();
        assert_eq!(
            a.preimage(3, &r, &outputs_by_settings(&a)).unwrap().unwrap().key(),
            z.preimage(z_merge, &r, &outputs_by_settings(&z)).unwrap().unwrap().key()
        );
    }

    #[test]
    fn bad_shard_settings_are_config_errors() {
        let r = registry();
        for (from, to, expected) in [
            ("shards = 3", "shards = 0", "stages.a.shards: must be an integer in 1..=4096, not 0"),
            ("shards = 3", "shards = 5", "stages.a.shards: 5 shards, but `sa` makes only 4 items in variant `y`"),
            ("shards = 3", "shards = 3\nshard_size = 2", "stages.a.shard_size: set `shards` or `shard_size`, not both"),
            ("[stages.b]\noperator = \"ob\"", "[stages.b]\noperator = \"ob\"\nshards = 2", "stages.b.shards: operator `ob` cannot run as shards"),
        ] {
            let e = parse(Path::new("t.toml"), &SHARDED.replace(from, to), &r).unwrap_err().to_string();
            assert!(e.contains(expected), "{to}: {e}");
        }
        let e = parse(Path::new("t.toml"), &SHARDED.replace("[stages.b]\noperator = \"ob\"", "[stages.b]\noperator = \"ob\"\nshards = 2"), &r)
            .unwrap_err();
        assert!(e.to_string().contains("operators that can: sa, sc"), "{e}");
    }

    const SHARED_INPUT: &str = r#"
[stages.a]
operator = "oa"
[stages.b]
operator = "ob"
[stages.c]
operator = "sc"
shards = 2
[stages.d]
operator = "od"
"#;

    #[test]
    fn an_operator_splitting_its_input_runs_as_shares_of_it() {
        let r = registry();
        let p = parse(Path::new("t.toml"), SHARED_INPUT, &r).unwrap();
        let plan = plan(&p);
        let labels: Vec<&str> = plan.instances.iter().map(|i| i.label.as_str()).collect();
        assert_eq!(labels, ["a", "b", "c#0", "c#1", "c", "d"]);
        assert_eq!(plan.instances[3].shard, Some((1, Part::Share(Share { index: 1, of: 2 }))));
        assert_eq!((plan.instances[3].settings["k"].as_i64(), plan.instances[3].settings["nested"]["a"].as_i64()), (Some(1), Some(2)));
        let read: Vec<&[usize]> = plan.instances[2].inputs.iter().map(|i| &i.providers[..]).collect();
        assert_eq!(read, [&[0][..], &[1][..]], "each share reads the whole input");
        assert_eq!(plan.instances[5].inputs[0].providers, [4], "d reads the merge only");
        let preimage = plan.preimage(4, &r, &outputs_by_settings(&plan)).unwrap().unwrap();
        let order: Vec<&str> = preimage.inputs.iter().map(|i| i.label.as_str()).collect();
        assert_eq!(order, ["00000000000000000000/00000000000000000002", "00000000000000000001/00000000000000000002"]);

        let e = parse(Path::new("t.toml"), &SHARED_INPUT.replace("shards = 2", "shard_size = 2"), &r).unwrap_err().to_string();
        assert!(e.contains("stages.c.shard_size: `sc` splits the items of its `a` input, which are counted only when it runs"), "{e}");
        assert!(e.contains("use `shards = N`"), "{e}");
    }
}
