//! A pipeline's claims against its store: each comparison's values measured from the artifacts
//! the store holds (through each artifact type's `Measures`, so the engine knows no metric), the
//! verdicts by `rlmflow_stages::claims`, and, under a seed rule, the look the store has reached.
//! Nothing here computes an instance: `run` computes what a look is missing, then asks again.

use std::collections::{BTreeMap, HashMap};

use anyhow::{Context as _, bail};
use rlmflow_cache::{Digest, Store};
use rlmflow_stages::claims::{Metric, Values, Verdict, decide};
use rlmflow_stages::{Device, Registry};
use serde::Serialize;

use crate::config::{Pipeline, suggest};
use crate::plan::{Freshness, assess};
use crate::preflight::planned;

/// One instance as the claims read it: its stage, variant (with its seed) and output, where
/// the store has one.
pub struct Measured<'a> {
    pub stage: &'a str,
    pub assignment: &'a BTreeMap<String, String>,
    pub seed: Option<u64>,
    pub output: Option<Digest>,
    pub label: &'a str,
}

/// The claims at one look.
#[derive(Debug, Serialize)]
pub struct Look {
    /// Seeds at this look (those of a fixed `seeds` list).
    pub seeds: usize,
    /// Under a seed rule, the most it adds.
    pub max_seeds: Option<usize>,
    pub verdicts: Vec<Verdict>,
    /// Instances a claim reads that the store does not hold at this look: what a run computes.
    pub missing: Vec<String>,
}

impl Look {
    /// Whether a claim marked `required` fails.
    pub fn required_fails(&self) -> Vec<&Verdict> {
        self.verdicts.iter().filter(|v| v.required && v.decision == rlmflow_stages::claims::Decision::Fails).collect()
    }
}

/// The verdicts of `p`'s claims over `instances`; the instances of a claim that have no output
/// are listed instead of being read. A metric the artifact does not measure is an error naming
/// the claim's line.
pub fn evaluate(p: &Pipeline, registry: &Registry, store: &Store, instances: &[Measured]) -> anyhow::Result<(Vec<Verdict>, Vec<String>)> {
    let Some(spec) = &p.claims else { return Ok((Vec::new(), Vec::new())) };
    let mut measured: HashMap<Digest, serde_json::Value> = HashMap::new();
    let mut missing = Vec::new();
    let mut verdicts = Vec::new();
    for claim in &spec.claims {
        let mut values = Vec::new();
        for comparison in &claim.comparisons {
            let mut side = |metric: &Metric, key: &str| -> anyhow::Result<Values> {
                let at = || format!("{}:{}: claims.{}.{key}", p.file.display(), p.lines.line(&format!("claims.{}.{key}", claim.name)), claim.name);
                let mut seeded = BTreeMap::new();
                let mut fixed = None;
                for m in instances.iter().filter(|m| reads(metric, m)) {
                    let Some(output) = m.output else {
                        missing.push(m.label.to_owned());
                        continue;
                    };
                    let metrics = match measured.get(&output) {
                        Some(v) => v.clone(),
                        None => {
                            let stage = p.stage(m.stage).map(|s| &p.stages[s]).context("a claim's stage")?;
                            let measures = registry.catalog.measures(stage.kind.produces).context("a claim's artifact measures")?;
                            let dir = store.object_dir(&output);
                            let v = (measures.metrics)(&dir).with_context(|| format!("{}: measuring {}", at(), m.label))?;
                            measured.insert(output, v.clone());
                            v
                        }
                    };
                    let Some(value) = rlmflow_stages::measure::lookup(&metrics, &metric.path) else {
                        let paths = rlmflow_stages::measure::paths(&metrics);
                        let names: Vec<&str> = paths.iter().map(String::as_str).collect();
                        bail!("{}: {} measures no `{}`{}", at(), m.label, metric.path, suggest(&metric.path, &names));
                    };
                    match m.seed {
                        Some(seed) => {
                            seeded.insert(seed, value);
                        }
                        None => fixed = Some(value),
                    }
                }
                Ok(match fixed {
                    Some(v) => Values::Fixed(v),
                    None => Values::Seeded(seeded),
                })
            };
            let better = side(&comparison.better, "better")?;
            let than = side(&comparison.than, "than")?;
            values.push((better, than));
        }
        verdicts.push(decide(claim, spec.level, spec.looks, &values));
    }
    missing.sort();
    missing.dedup();
    Ok((verdicts, missing))
}

/// Whether instance `m` is one of those `metric` pools over seeds.
fn reads(metric: &Metric, m: &Measured) -> bool {
    m.stage == metric.stage && *m.assignment == metric.variant
}

/// The look `store` has reached for `p`, on `device`'s keys: under a seed rule, from `min`
/// seeds up, the first look whose claim instances the store lacks (what a run computes next),
/// else the first at which every claim is decided, else the last; with fixed seeds, the one
/// look. `p` is left at that look's seeds.
pub fn reached(p: &mut Pipeline, registry: &Registry, store: Option<&Store>, device: Device) -> anyhow::Result<Look> {
    let (first, last) = match p.seed_rule {
        Some(rule) => (rule.min, rule.max),
        None => (p.seeds.len(), p.seeds.len()),
    };
    let mut n = first;
    loop {
        p.with_seeds(n);
        let look = look(p, registry, store, device)?;
        let decided = rlmflow_stages::claims::all_decided(&look.verdicts);
        if !look.missing.is_empty() || decided || n >= last {
            return Ok(look);
        }
        n += 1;
    }
}

/// The claims of `p` at its seeds, from the outputs `store` holds at this plan's keys.
fn look(p: &Pipeline, registry: &Registry, store: Option<&Store>, device: Device) -> anyhow::Result<Look> {
    let plan = planned(p, store, device)?;
    let states = assess(&plan, registry, store)?;
    let instances: Vec<Measured> = plan
        .instances
        .iter()
        .zip(&states)
        .filter(|(inst, _)| inst.shard.is_none())
        .map(|(inst, state)| Measured {
            stage: &p.stages[inst.stage].name,
            assignment: &inst.assignment,
            seed: inst.seed,
            output: if let Freshness::Cached(r) = state { Some(r.output) } else { None },
            label: &inst.label,
        })
        .collect();
    let (verdicts, missing) = match store {
        Some(store) => evaluate(p, registry, store, &instances)?,
        None => {
            // Nothing was ever run: every claim instance is missing.
            let missing = instances.iter().filter(|m| claim_metrics(p).any(|metric| reads(metric, m))).map(|m| m.label.to_owned()).collect();
            (Vec::new(), missing)
        }
    };
    Ok(Look { seeds: p.seeds.len(), max_seeds: p.seed_rule.map(|r| r.max), verdicts, missing })
}

/// Every metric a claim of `p` reads.
fn claim_metrics(p: &Pipeline) -> impl Iterator<Item = &Metric> {
    p.claims.iter().flat_map(|s| &s.claims).flat_map(|c| &c.comparisons).flat_map(|c| [&c.better, &c.than])
}

/// The stages a claim of `p` reads: what a look computes (with what they need).
pub fn claim_stages(p: &Pipeline) -> Vec<String> {
    let mut stages: Vec<String> = claim_metrics(p).map(|m| m.stage.clone()).collect();
    stages.sort();
    stages.dedup();
    stages
}

/// A claim's verdict in a run, and the change since the run before in which it read otherwise.
pub struct ClaimFlip {
    /// The newest run's id and verdict.
    pub now: (String, Verdict),
    /// The newest earlier run with another decision, and what changed in between: per instance
    /// whose key moved (its label and stage), its changes other than its inputs' (`None`: a
    /// record was collected, so they are unknown).
    pub before: Option<(String, Verdict, Vec<Changed>)>,
}

/// One instance whose key moved between two runs: its label, stage and own changes.
pub struct Changed {
    pub label: String,
    pub stage: String,
    pub changes: Option<Vec<rlmflow_cache::Change>>,
}

/// `claim`'s verdict in each of the pipeline's runs (by today's definition), newest first,
/// up to the first that decided otherwise.
pub fn flip(p: &Pipeline, registry: &Registry, store: &Store, claim: &str) -> anyhow::Result<ClaimFlip> {
    let runs = crate::history::runs_of(store, &p.name)?;
    let mut verdicts = Vec::new();
    for run in &runs {
        let records = run.records(store)?;
        let instances: Vec<Measured> = records
            .iter()
            .map(|(e, r)| Measured {
                stage: &e.instance.stage,
                assignment: &e.instance.variants,
                seed: e.instance.seed,
                output: r.as_ref().map(|r| r.output),
                label: &e.label,
            })
            .collect();
        let (all, missing) = evaluate(p, registry, store, &instances)?;
        let verdict = all.into_iter().find(|v| v.claim == claim).context("the claim")?;
        // A run that did not compute every instance the claim reads says nothing of it.
        if missing.is_empty() && verdict.comparisons.iter().all(|c| !c.differences.is_empty()) {
            verdicts.push((run, verdict, records));
        }
    }
    let Some((newest, verdict, now_records)) = verdicts.first() else {
        bail!("no run of `{}` holds every instance claim `{claim}` reads; `rlmflow run` computes them", p.name);
    };
    let before = verdicts.iter().skip(1).find(|(_, v, _)| v.decision != verdict.decision).map(|(run, v, records)| {
        let mut changed = Vec::new();
        for (entry, record) in now_records {
            let Some(old) = records.iter().find(|(e, _)| e.label == entry.label) else { continue };
            if old.0.key == entry.key {
                continue;
            }
            let changes = match (record, &old.1) {
                (Some(now), Some(then)) => {
                    let own: Vec<_> =
                        now.preimage.diff(&then.preimage).into_iter().filter(|c| !matches!(c, rlmflow_cache::Change::InputChanged { .. })).collect();
                    if own.is_empty() {
                        continue;
                    }
                    Some(own)
                }
                _ => None,
            };
            changed.push(Changed { label: entry.label.clone(), stage: entry.instance.stage.clone(), changes });
        }
        (run.id().to_owned(), v.clone(), changed)
    });
    Ok(ClaimFlip { now: (newest.id().to_owned(), verdict.clone()), before })
}
