//! `rlmflow compare`: settings and metrics side by side, for two runs of a pipeline or for the
//! variants of one run, each from the records the runs' keys name. Seeds are pooled: an
//! instance's seeds become one row of mean ± sd per metric, and a change between two runs that
//! ran the same seeds carries the standard deviation of its per-seed differences.

use std::collections::BTreeMap;

use rlmflow_cache::{ActionRecord, Digest, PlanEntry, Preimage, Store, canonical_json};
use serde::Serialize;
use serde_json::Value;

use rlmflow_stages::Registry;

use crate::config::Pipeline;
use crate::history::PastRun;

/// A metric over an instance's seeds (one value without seeds).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Stat {
    pub mean: f64,
    /// Sample standard deviation; `None` for a single value.
    pub sd: Option<f64>,
    pub n: usize,
}

impl Stat {
    fn of(values: &[f64]) -> Option<Stat> {
        let n = values.len();
        if n == 0 {
            return None;
        }
        let mean = values.iter().sum::<f64>() / n as f64;
        let sd = (n > 1).then(|| (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt());
        Some(Stat { mean, sd, n })
    }
}

/// One column's entry of a row: a setting's value or an input's digest, a metric's [`Stat`], or
/// nothing where the column has no such instance or its record was collected. JSON: the value,
/// the stat's fields, or null.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(untagged)]
pub enum Cell {
    Absent,
    Value(Value),
    Stat(Stat),
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum RowKind {
    Setting,
    Input,
    Metric,
}

/// One setting, input or metric of one instance (seeds pooled) across the table's columns.
#[derive(Debug, Serialize)]
pub struct Row {
    /// The instance without its seed: `pretrain[alpha4]`.
    pub instance: String,
    pub kind: RowKind,
    /// The setting's dotted key, the input's slot, the metric's dotted path in the record.
    pub name: String,
    /// One per column.
    pub values: Vec<Cell>,
    /// A metric of a two-run table: the second column's mean less the first's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub change: Option<Stat>,
}

/// One table: two runs, or one stage's variants in one run.
#[derive(Debug, Serialize)]
pub struct Table {
    pub title: String,
    pub columns: Vec<String>,
    pub rows: Vec<Row>,
    /// Instances left out because nothing about them differs (same keys in both runs).
    pub identical: Vec<String>,
    /// The columns' instances whose records were pulled from a remote cache unverified (no
    /// trusted keys): their numbers are the remote's word, and the table says so.
    pub unverified: Vec<String>,
}

/// One metric of an instance: each member's seed (`None` without seeds) and value.
type SeedValues = Vec<(Option<u64>, f64)>;

/// An instance with its seeds pooled: each member's seed (`None` without seeds) and record.
struct Group<'r> {
    label: String,
    members: Vec<(Option<u64>, &'r PlanEntry, Option<ActionRecord>)>,
    /// The preimage of the first member: from its record, else from its request.
    preimage: Option<Preimage>,
}

impl Group<'_> {
    /// `label` (in `run`), when a member's record was pulled unverified.
    fn unverified(&self, run: &str) -> Option<String> {
        let from = self.members.iter().find_map(|(_, _, record)| record.as_ref()?.unverified_origin())?;
        Some(format!("{} in run {run} (from {from})", self.label))
    }

    fn keys(&self) -> Vec<(Option<u64>, Option<Digest>)> {
        self.members.iter().map(|(seed, entry, _)| (*seed, entry.key)).collect()
    }

    /// Each numeric leaf of the members' metrics, by dotted path: (seed, value) per member.
    fn metrics(&self) -> BTreeMap<String, SeedValues> {
        let mut out: BTreeMap<String, SeedValues> = BTreeMap::new();
        for (seed, _, record) in &self.members {
            let Some(record) = record else { continue };
            let mut leaves = Vec::new();
            numeric_leaves("", &record.metrics, &mut leaves);
            for (path, value) in leaves {
                out.entry(path).or_default().push((*seed, value));
            }
        }
        out
    }
}

/// The label of an instance with the seed left out of its variants (`clipcap[alpha4]` for
/// `clipcap[pretrain=alpha4,seed=2]`).
fn pooled_label(entry: &PlanEntry) -> String {
    crate::plan::label(&entry.instance.stage, &entry.instance.variants, None)
}

/// The run's instances grouped over seeds, in plan order.
fn groups<'r>(store: &Store, run: &'r PastRun) -> anyhow::Result<Vec<Group<'r>>> {
    let mut out: Vec<Group> = Vec::new();
    for (entry, record) in run.records(store)? {
        let label = pooled_label(entry);
        let seed = entry.instance.seed;
        match out.iter_mut().find(|g| g.label == label) {
            Some(group) => group.members.push((seed, entry, record)),
            None => {
                let preimage = match &record {
                    Some(r) => Some(r.preimage.clone()),
                    None => entry.key.map(|key| store.request(&key)).transpose()?.flatten().map(|r| r.preimage),
                };
                out.push(Group { label, members: vec![(seed, entry, record)], preimage });
            }
        }
    }
    Ok(out)
}

/// Two runs side by side: every instance whose key differs, with the settings and inputs that
/// differ and the metrics that moved (`all`: every instance, setting and metric).
pub fn runs(store: &Store, a: &PastRun, b: &PastRun, all: bool) -> anyhow::Result<Table> {
    let (ga, gb) = (groups(store, a)?, groups(store, b)?);
    let mut labels: Vec<&str> = gb.iter().map(|g| g.label.as_str()).collect();
    labels.extend(ga.iter().map(|g| g.label.as_str()).filter(|l| !gb.iter().any(|g| g.label == *l)));
    let mut table = Table {
        title: format!("run {} -> run {}", a.id(), b.id()),
        columns: vec![a.id().to_owned(), b.id().to_owned()],
        rows: Vec::new(),
        identical: Vec::new(),
        unverified: Vec::new(),
    };
    for label in labels {
        let sides = [ga.iter().find(|g| g.label == label), gb.iter().find(|g| g.label == label)];
        let ids = [a.id(), b.id()];
        table.unverified.extend(sides.iter().zip(ids).filter_map(|(g, id)| g.and_then(|g| g.unverified(id))));
        if let [Some(x), Some(y)] = sides
            && x.keys() == y.keys()
            && !all
        {
            table.identical.push(label.to_owned());
            continue;
        }
        table.rows.extend(setting_rows(label, &sides, all));
        table.rows.extend(input_rows(label, &sides, all));
        table.rows.extend(metric_rows(label, &sides, all, true));
    }
    Ok(table)
}

/// The variants of each stage of one run side by side, one table per stage: the settings that
/// tell them apart and their metrics, seeds pooled. A stage without variants or seeds shows only
/// with `all`.
pub fn variants(store: &Store, run: &PastRun, all: bool) -> anyhow::Result<Vec<Table>> {
    let groups = groups(store, run)?;
    let mut stages: Vec<&str> = Vec::new();
    for g in &groups {
        let stage = g.members[0].1.instance.stage.as_str();
        if !stages.contains(&stage) {
            stages.push(stage);
        }
    }
    let mut tables = Vec::new();
    for stage in stages {
        let columns: Vec<&Group> = groups.iter().filter(|g| g.members[0].1.instance.stage == stage).collect();
        if columns.len() < 2 && columns[0].members.len() < 2 && !all {
            continue;
        }
        let sides: Vec<Option<&Group>> = columns.iter().map(|g| Some(*g)).collect();
        let mut rows = setting_rows(stage, &sides, all);
        if all {
            rows.extend(input_rows(stage, &sides, all));
        }
        rows.extend(metric_rows(stage, &sides, all, false));
        // Instances that differ only by their inputs (a stage fanned out by another's variants)
        // and moved no metric: nothing to show.
        if rows.is_empty() && !all {
            continue;
        }
        let title = format!("{stage} in run {}", run.id());
        let unverified = columns.iter().filter_map(|g| g.unverified(run.id())).collect();
        tables.push(Table { title, columns: columns.iter().map(|g| g.label.clone()).collect(), rows, identical: Vec::new(), unverified });
    }
    Ok(tables)
}

/// The settings of the key (the first member's preimage; seeds share them) whose values differ
/// between the sides, or all of them; the seed too where there is no seed dimension.
fn setting_rows(instance: &str, sides: &[Option<&Group>], all: bool) -> Vec<Row> {
    let flat: Vec<BTreeMap<String, Value>> = sides
        .iter()
        .map(|g| {
            let mut leaves = BTreeMap::new();
            if let Some(p) = g.and_then(|g| g.preimage.as_ref()) {
                leaves.insert("operator".to_owned(), Value::from(format!("{} v{}", p.operator, p.operator_version)));
                all_leaves("", &p.config, &mut leaves);
                if g.is_some_and(|g| g.members[0].0.is_none()) {
                    leaves.insert("seed".to_owned(), p.seed.into());
                }
            }
            leaves
        })
        .collect();
    value_rows(instance, RowKind::Setting, &flat, all)
}

/// The inputs whose digests differ between the sides (all with `all`), by slot and label.
fn input_rows(instance: &str, sides: &[Option<&Group>], all: bool) -> Vec<Row> {
    let inputs: Vec<BTreeMap<String, Value>> = sides
        .iter()
        .map(|g| {
            let inputs = g.and_then(|g| g.preimage.as_ref()).map(|p| p.inputs.as_slice()).unwrap_or_default();
            let name = |slot: &str, label: &str| if label.is_empty() { slot.to_owned() } else { format!("{slot} ({label})") };
            inputs.iter().map(|i| (name(&i.slot, &i.label), Value::from(i.digest.to_string()))).collect()
        })
        .collect();
    value_rows(instance, RowKind::Input, &inputs, all)
}

/// A row per name of any side's values (null where a side lacks it): those that differ, or all.
fn value_rows(instance: &str, kind: RowKind, sides: &[BTreeMap<String, Value>], all: bool) -> Vec<Row> {
    let mut names: Vec<&String> = sides.iter().flat_map(|f| f.keys()).collect();
    names.sort();
    names.dedup();
    names
        .into_iter()
        .filter_map(|name| {
            let values: Vec<Cell> = sides.iter().map(|f| f.get(name).map_or(Cell::Absent, |v| Cell::Value(v.clone()))).collect();
            let differs = values.iter().any(|v| *v != values[0]);
            (differs || all).then(|| Row { instance: instance.to_owned(), kind, name: name.clone(), values, change: None })
        })
        .collect()
}

/// Each metric's [`Stat`] per side; the ones that differ (all with `all`). With `change` (two
/// sides), the second's mean less the first's, with the sd of the per-seed differences where
/// both sides have the same seeds.
fn metric_rows(instance: &str, sides: &[Option<&Group>], all: bool, change: bool) -> Vec<Row> {
    let metrics: Vec<BTreeMap<String, SeedValues>> = sides.iter().map(|g| g.map(Group::metrics).unwrap_or_default()).collect();
    let mut names: Vec<&String> = metrics.iter().flat_map(|m| m.keys()).collect();
    names.sort();
    names.dedup();
    let mut rows = Vec::new();
    for name in names {
        let series: Vec<&[(Option<u64>, f64)]> = metrics.iter().map(|m| m.get(name).map(Vec::as_slice).unwrap_or_default()).collect();
        let differs = series.iter().any(|s| *s != series[0]);
        if !differs && !all {
            continue;
        }
        let stats: Vec<Option<Stat>> = series.iter().map(|s| Stat::of(&s.iter().map(|(_, v)| *v).collect::<Vec<_>>())).collect();
        let values = stats.iter().map(|s| s.clone().map_or(Cell::Absent, Cell::Stat)).collect();
        let delta = match (change, series.as_slice(), stats.as_slice()) {
            (true, [a, b], [Some(sa), Some(sb)]) => {
                let seeds = |s: &[(Option<u64>, f64)]| s.iter().map(|(seed, _)| *seed).collect::<Vec<_>>();
                if seeds(a) == seeds(b) && a.len() > 1 {
                    Stat::of(&a.iter().zip(b.iter()).map(|((_, x), (_, y))| y - x).collect::<Vec<_>>())
                } else {
                    Some(Stat { mean: sb.mean - sa.mean, sd: None, n: sa.n.min(sb.n) })
                }
            }
            _ => None,
        };
        rows.push(Row { instance: instance.to_owned(), kind: RowKind::Metric, name: name.clone(), values, change: delta });
    }
    rows
}

/// Every leaf of `value` (arrays whole) by dotted path.
fn all_leaves(prefix: &str, value: &Value, out: &mut BTreeMap<String, Value>) {
    match value {
        Value::Object(map) if !map.is_empty() => {
            for (k, v) in map {
                all_leaves(&join(prefix, k), v, out);
            }
        }
        _ => {
            out.insert(prefix.to_owned(), value.clone());
        }
    }
}

/// Every number of `value` outside arrays, by dotted path.
fn numeric_leaves(prefix: &str, value: &Value, out: &mut Vec<(String, f64)>) {
    match value {
        Value::Object(map) => map.iter().for_each(|(k, v)| numeric_leaves(&join(prefix, k), v, out)),
        Value::Number(n) => out.extend(n.as_f64().map(|f| (prefix.to_owned(), f))),
        _ => {}
    }
}

fn join(prefix: &str, key: &str) -> String {
    if prefix.is_empty() { key.to_owned() } else { format!("{prefix}.{key}") }
}

/// Two instances' per-frame outputs side by side: the test frames where they differ most.
#[derive(Debug, Serialize)]
pub struct Frames {
    pub a: String,
    pub b: String,
    #[serde(flatten)]
    pub differences: rlmflow_stages::measure::FrameDifferences,
}

/// The frames where instances `a` and `b` (labels as a run prints them) differ, from their
/// outputs in `store`; both must be computed and of one artifact type that keeps per-frame
/// outputs.
pub fn frames(p: &Pipeline, registry: &Registry, store: &Store, a: &str, b: &str) -> anyhow::Result<Frames> {
    let plan = crate::preflight::planned(p, Some(store), rlmflow_stages::Device::Cpu)?;
    let states = crate::plan::assess(&plan, registry, Some(store))?;
    let output = |text: &str| -> anyhow::Result<(String, &'static str, std::path::PathBuf)> {
        let i = plan.instance_named(text)?;
        let inst = &plan.instances[i];
        let crate::plan::Freshness::Cached(record) = &states[i] else {
            anyhow::bail!("{} is not computed in {}: `rlmflow run` computes it", inst.label, store.root().display());
        };
        Ok((inst.label.clone(), p.stages[inst.stage].kind.produces, store.object_dir(&record.output)))
    };
    let ((la, ta, da), (lb, tb, db)) = (output(a)?, output(b)?);
    if ta != tb {
        anyhow::bail!("{la} is a {ta} and {lb} a {tb}: per-frame outputs compare within one artifact type");
    }
    let Some(compare) = registry.catalog.measures(ta).and_then(|m| m.frames) else {
        anyhow::bail!("a {ta} keeps no per-frame outputs to compare (probes and segmenters do)");
    };
    Ok(Frames { a: la, b: lb, differences: compare(&da, &db)? })
}

impl Frames {
    /// The `top` most different frames as aligned columns.
    pub fn terminal(&self, top: usize) -> String {
        let d = &self.differences;
        let mut out = format!("{} against {}: {} of {} test frames differ ({})\n", self.a, self.b, d.frames.len(), d.compared, d.unit);
        let rows: Vec<[String; 5]> =
            d.frames.iter().take(top).map(|f| [f.frame.to_string(), f.row.clone(), number(f.differ), f.a.clone(), f.b.clone()]).collect();
        if rows.is_empty() {
            return out + "  no frame differs\n";
        }
        let header = ["frame".to_owned(), "row".into(), "differ".into(), self.a.clone(), self.b.clone()];
        let widths: Vec<usize> = (0..5).map(|c| std::iter::once(&header).chain(&rows).map(|r| r[c].chars().count()).max().unwrap_or(0)).collect();
        for row in std::iter::once(&header).chain(&rows) {
            let cells: Vec<String> = row.iter().zip(&widths).map(|(c, w)| format!("{c:<w$}")).collect();
            out += &format!("  {}\n", cells.join("  ").trim_end());
        }
        if d.frames.len() > top {
            out += &format!("  ... and {} more (--top N)\n", d.frames.len() - top);
        }
        out
    }
}

// ---- rendering ----

/// A number to four significant digits (integers whole).
fn number(x: f64) -> String {
    if x.fract() == 0.0 && x.abs() < 1e15 {
        return format!("{x:.0}");
    }
    let digits = if x == 0.0 { 0 } else { x.abs().log10().floor() as i32 };
    format!("{x:.*}", (3 - digits).clamp(0, 6) as usize)
}

/// What a cell shows: a setting's value as TOML would write it, a digest's first 12 hex, a
/// metric's mean ± sd (n).
fn cell(kind: RowKind, cell: &Cell) -> String {
    match (kind, cell) {
        (_, Cell::Absent | Cell::Value(Value::Null)) => "-".to_owned(),
        (_, Cell::Stat(s)) => stat(s, false),
        (RowKind::Input, Cell::Value(Value::String(digest))) => digest.chars().take(12).collect(),
        (_, Cell::Value(Value::String(s))) => s.clone(),
        (_, Cell::Value(v)) => canonical_json(v),
    }
}

fn stat(s: &Stat, signed: bool) -> String {
    let mean = if signed && s.mean >= 0.0 { format!("+{}", number(s.mean)) } else { number(s.mean) };
    match s.sd {
        Some(sd) => format!("{mean} ± {} (n={})", number(sd), s.n),
        None => mean,
    }
}

impl Table {
    /// The header and the cells of each row, as text.
    fn text(&self) -> (Vec<String>, Vec<Vec<String>>) {
        let change = self.rows.iter().any(|r| r.change.is_some());
        let mut header = vec!["instance".to_owned(), "".to_owned()];
        header.extend(self.columns.iter().cloned());
        if change {
            header.push("change".to_owned());
        }
        let rows = self
            .rows
            .iter()
            .map(|r| {
                let what = match r.kind {
                    RowKind::Setting => r.name.clone(),
                    RowKind::Input => format!("input {}", r.name),
                    RowKind::Metric => format!("metric {}", r.name),
                };
                let mut cells = vec![r.instance.clone(), what];
                cells.extend(r.values.iter().map(|v| cell(r.kind, v)));
                if change {
                    cells.push(r.change.as_ref().map_or(String::new(), |c| stat(c, true)));
                }
                cells
            })
            .collect();
        (header, rows)
    }

    /// Aligned columns for a terminal.
    pub fn terminal(&self) -> String {
        let (header, rows) = self.text();
        let mut out = format!("{}\n", self.title);
        if rows.is_empty() {
            out += "  nothing differs\n";
        } else {
            let widths: Vec<usize> =
                (0..header.len()).map(|c| std::iter::once(&header).chain(&rows).map(|r| r[c].chars().count()).max().unwrap_or(0)).collect();
            for row in std::iter::once(&header).chain(&rows) {
                let cells: Vec<String> = row.iter().zip(&widths).map(|(c, w)| format!("{c:<w$}")).collect();
                out += &format!("  {}\n", cells.join("  ").trim_end());
            }
        }
        if !self.identical.is_empty() {
            out += &format!("  same keys, same results: {}\n", self.identical.join(", "));
        }
        if !self.unverified.is_empty() {
            out += &format!("  {}\n", self.unverified_note());
        }
        out
    }

    /// The line naming the instances whose numbers were pulled unverified.
    fn unverified_note(&self) -> String {
        format!("UNVERIFIED: the numbers of {} come from records pulled without trusted keys (the remote's word)", self.unverified.join(", "))
    }

    /// A Markdown table, for pasting into a note or an issue.
    pub fn markdown(&self) -> String {
        let (header, rows) = self.text();
        let escape = |c: &str| c.replace('|', "\\|");
        let line = |cells: &[String]| format!("| {} |\n", cells.iter().map(|c| escape(c)).collect::<Vec<_>>().join(" | "));
        let mut out = format!("### {}\n\n", self.title);
        if rows.is_empty() {
            out += "Nothing differs.\n";
        } else {
            out += &line(&header);
            out += &format!("|{}\n", "---|".repeat(header.len()));
            rows.iter().for_each(|r| out += &line(r));
        }
        if !self.identical.is_empty() {
            out += &format!("\nSame keys, same results: {}.\n", self.identical.join(", "));
        }
        if !self.unverified.is_empty() {
            out += &format!("\n{}.\n", self.unverified_note());
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stat_pools_seeds_into_mean_and_sample_sd() {
        assert_eq!(Stat::of(&[]), None);
        assert_eq!(Stat::of(&[0.5]), Some(Stat { mean: 0.5, sd: None, n: 1 }));
        let s = Stat::of(&[1.0, 2.0, 3.0]).unwrap();
        assert_eq!((s.mean, s.sd, s.n), (2.0, Some(1.0), 3));
    }

    #[test]
    fn numbers_show_four_significant_digits_and_changes_their_sign() {
        assert_eq!(number(0.123456), "0.1235");
        assert_eq!(number(12.3456), "12.35");
        assert_eq!(number(1234.56), "1235");
        assert_eq!(number(480.0), "480");
        assert_eq!(number(0.0), "0");
        assert_eq!(stat(&Stat { mean: 0.01, sd: None, n: 1 }, true), "+0.01000");
        assert_eq!(stat(&Stat { mean: -0.25, sd: Some(0.125), n: 3 }, true), "-0.2500 ± 0.1250 (n=3)");
    }
}
