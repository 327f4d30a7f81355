//! `[claims]`: what the experiment is meant to show. Each claim compares metrics of the run's
//! instances (`better` and `than`, one or a list each: every pair is a comparison), paired by
//! seed, in a `direction` with a `margin`; `level` is the error rate of each claim's verdict.
//! References are checked here as settings are: the stage, its variant and the metric path, each
//! with the nearest valid name, and whether the instances vary by seed at all.

use std::collections::BTreeMap;

use rlmflow_stages::Registry;
use rlmflow_stages::claims::{Claim, Comparison, DEFAULT_LEVEL, Direction, Looks, Metric, Spec};
use serde_json::{Map, Value};

use super::checker::Checker;
use super::graph::Dims;
use super::{SEED_LABEL, Stage, suggest};

const CLAIM_KEYS: &[&str] = &["better", "than", "margin", "direction", "required", "paper"];
/// The most instances one side of a claim may list.
const MAX_SIDE: usize = 64;

/// A metric reference resolved against the stages: the metric, and whether its instance varies
/// by seed.
struct Side {
    metric: Metric,
    seeded: bool,
}

impl Checker {
    /// The `[claims]` table resolved against the validated `stages` (in order, with each one's
    /// variant dimensions `dims`), decided at `looks`; `None` without claims (or after errors).
    pub(super) fn claims(
        &mut self,
        table: Option<&Value>,
        stages: &[Stage],
        dims: &[Dims],
        looks: Option<Looks>,
        registry: &Registry,
    ) -> Option<Spec> {
        let table = match table? {
            Value::Object(t) => t,
            _ => {
                self.error(self.line("claims"), "claims", "must be a table of claims".into(), None);
                return None;
            }
        };
        let mut level = DEFAULT_LEVEL;
        let mut claims = Vec::new();
        for (name, value) in table {
            let path = format!("claims.{name}");
            match (name.as_str(), value) {
                ("level", v) => match v.as_f64().filter(|l| *l > 0.0 && *l <= 0.5) {
                    Some(l) => level = l,
                    None => self.error(self.line(&path), &path, format!("must be a number in (0, 0.5], not {v}"), Some("e.g. level = 0.05".into())),
                },
                (_, Value::Object(claim)) => {
                    self.name(&path, name);
                    if let Some(c) = self.claim(name, claim, stages, dims, registry) {
                        claims.push(c);
                    }
                }
                (_, other) => {
                    let help = "a claim is a table: [claims.NAME] with better = \"STAGE[VARIANT].METRIC\" and than = ...".into();
                    self.error(self.line(&path), &path, format!("must be a claim table (or `level`), not {other}"), Some(help));
                }
            }
        }
        if claims.is_empty() {
            if self.errors.is_empty() {
                let help = "add one: [claims.NAME] with better = \"STAGE[VARIANT].METRIC\", than = \"...\"".into();
                self.error(self.line("claims"), "claims", "declares no claim".into(), Some(help));
            }
            return None;
        }
        // Every claim's instances vary by seed (checked per comparison), so seeds are set.
        let looks = looks?;
        Some(Spec { level, looks, claims })
    }

    fn claim(&mut self, name: &str, table: &Map<String, Value>, stages: &[Stage], dims: &[Dims], registry: &Registry) -> Option<Claim> {
        let path = format!("claims.{name}");
        for key in table.keys().filter(|k| !CLAIM_KEYS.contains(&k.as_str())) {
            self.unknown_key(&format!("{path}.{key}"), key, CLAIM_KEYS);
        }
        let better = self.side(&path, "better", table, stages, dims, registry);
        let than = self.side(&path, "than", table, stages, dims, registry);
        let margin = match table.get("margin") {
            None => 0.0,
            Some(v) => v.as_f64().filter(|m| m.is_finite()).unwrap_or_else(|| {
                self.error(self.line(&format!("{path}.margin")), &format!("{path}.margin"), format!("must be a finite number, not {v}"), None);
                0.0
            }),
        };
        let direction = match table.get("direction").map(|v| (v, v.as_str())) {
            None | Some((_, Some("higher"))) => Direction::Higher,
            Some((_, Some("lower"))) => Direction::Lower,
            Some((v, _)) => {
                let key = format!("{path}.direction");
                self.error(
                    self.line(&key),
                    &key,
                    format!("must be \"higher\" or \"lower\", not {v}"),
                    Some("\"higher\": better's metric is the larger (F1); \"lower\": the smaller (a loss)".into()),
                );
                Direction::Higher
            }
        };
        let required = match table.get("required") {
            None => false,
            Some(Value::Bool(b)) => *b,
            Some(v) => {
                self.error(self.line(&format!("{path}.required")), &format!("{path}.required"), format!("must be true or false, not {v}"), None);
                false
            }
        };
        let paper = self.string(table, &path, "paper");
        let (better, than) = (better?, than?);
        let mut comparisons = Vec::new();
        for b in &better {
            for t in &than {
                if !b.seeded && !t.seeded {
                    let msg = format!(
                        "cannot be decided: neither `{}` nor `{}` varies by seed, so there is no per-seed difference to test",
                        b.metric.label(),
                        t.metric.label()
                    );
                    let help = "set [pipeline] seeds (a list, or { min = 3, max = 12, until = \"claims\" }) and keep the stages per seed".into();
                    self.error(self.line(&path), &path, msg, Some(help));
                    return None;
                }
                if b.metric == t.metric {
                    self.error(self.line(&path), &path, format!("compares `{}` with itself", b.metric.label()), None);
                    return None;
                }
                comparisons.push(Comparison { better: b.metric.clone(), than: t.metric.clone() });
            }
        }
        Some(Claim { name: name.to_owned(), comparisons, margin, direction, required, paper })
    }

    /// `better` or `than` of a claim: one reference or a list of them.
    fn side(
        &mut self,
        claim: &str,
        key: &str,
        table: &Map<String, Value>,
        stages: &[Stage],
        dims: &[Dims],
        registry: &Registry,
    ) -> Option<Vec<Side>> {
        let path = format!("{claim}.{key}");
        let texts: Vec<&str> = match table.get(key) {
            None => {
                let help = "e.g. \"clipcap[pretrain=alpha1].cls.bins.30-40m.f1\" (STAGE[VARIANT].METRIC)".into();
                self.error(self.line(claim), claim, format!("missing `{key}`"), Some(help));
                return None;
            }
            Some(Value::String(s)) => vec![s],
            Some(Value::Array(items)) if !items.is_empty() && items.len() <= MAX_SIDE && items.iter().all(Value::is_string) => {
                items.iter().filter_map(Value::as_str).collect()
            }
            Some(v) => {
                let msg = format!("must be a metric reference or a list of 1 to {MAX_SIDE} of them, not {v}");
                self.error(self.line(&path), &path, msg, None);
                return None;
            }
        };
        let resolved: Vec<Option<Side>> = texts.iter().map(|t| self.reference(&path, t, stages, dims, registry)).collect();
        resolved.into_iter().collect()
    }

    /// One `STAGE[VARIANT].METRIC` (`STAGE.METRIC` for a stage without variants).
    fn reference(&mut self, path: &str, text: &str, stages: &[Stage], dims: &[Dims], registry: &Registry) -> Option<Side> {
        let line = self.line(path);
        let names: Vec<&str> = stages.iter().map(|s| s.name.as_str()).collect();
        let (stage_name, variant_text, metric) = match text.find('[') {
            Some(open) => {
                let Some(close) = text[open..].find(']').map(|c| open + c) else {
                    self.error(line, path, format!("`{text}` opens `[` and never closes it"), None);
                    return None;
                };
                let Some(metric) = text[close + 1..].strip_prefix('.') else {
                    self.error(line, path, format!("`{text}` names no metric after its instance"), Some("e.g. \"clipcap[alpha1].cls.f1\"".into()));
                    return None;
                };
                (&text[..open], Some(&text[open + 1..close]), metric)
            }
            None => {
                // The longest stage name the reference begins with (stage names may hold dots).
                let stage = names.iter().filter(|n| text.starts_with(&format!("{n}."))).max_by_key(|n| n.len());
                match stage {
                    Some(n) => (*n, None, &text[n.len() + 1..]),
                    None => (text.split('.').next().unwrap_or(text), None, ""),
                }
            }
        };
        let Some(s) = stages.iter().position(|st| st.name == stage_name) else {
            let help = format!("stages: {}{}", names.join(", "), suggest(stage_name, &names));
            self.error(line, path, format!("`{text}`: no stage named `{stage_name}`"), Some(help));
            return None;
        };
        let stage = &stages[s];
        let variant = self.variant(path, text, stage, &dims[s], variant_text, stages)?;
        let kind = stage.kind;
        if registry.catalog.measures(kind.produces).is_none() {
            let msg = format!("`{text}`: stage `{stage_name}` makes a {} artifact, which measures nothing a claim can compare", kind.produces);
            self.error(line, path, msg, Some("claims compare the metrics of encoder, probe and segment stages".into()));
            return None;
        }
        if metric.is_empty() {
            self.error(line, path, format!("`{text}` names no metric"), Some(format!("e.g. \"{stage_name}.METRIC\"")));
            return None;
        }
        let settings = match variant.get(&stage.name) {
            Some(v) => stage.variants.iter().find(|x| x.name.as_deref() == Some(v.as_str())).unwrap_or(&stage.variants[0]),
            None => &stage.variants[0],
        };
        let op = registry.get(&stage.operator).expect("validated operator");
        let declared = op.metrics(&settings.settings);
        if !declared.is_empty() && !declared.iter().any(|m| m == metric) {
            let candidates: Vec<&str> = declared.iter().map(String::as_str).collect();
            let nearest = suggest(metric, &candidates);
            // Per-bin figures are many: named by their pattern.
            let top: Vec<&str> = candidates.iter().filter(|c| !c.contains(".bins")).copied().collect();
            let bins = if top.len() < candidates.len() { ", and each ROW.bins.BIN.FIGURE and ROW.bins_mean.FIGURE" } else { "" };
            let help = format!("`{}` measures {}{bins}{nearest}", stage.operator, top.join(", "));
            self.error(line, path, format!("`{text}`: `{stage_name}` has no metric `{metric}`"), Some(help));
            return None;
        }
        let seeded = dims[s].seeded;
        Some(Side { metric: Metric { stage: stage.name.clone(), variant, path: metric.to_owned() }, seeded })
    }

    /// The variant a reference names, by dimension: `[alpha4]` where the stage fans out over one
    /// dimension, `[pretrain=alpha4,captions=llm]` in general; every dimension but the seed's.
    fn variant(
        &mut self,
        path: &str,
        text: &str,
        stage: &Stage,
        dims: &Dims,
        given: Option<&str>,
        stages: &[Stage],
    ) -> Option<BTreeMap<String, String>> {
        let line = self.line(path);
        let dims: Vec<&str> = dims.variants.iter().map(String::as_str).collect();
        let values = |d: &str| -> Vec<&str> {
            stages.iter().find(|s| s.name == d).map(|s| s.variants.iter().filter_map(|v| v.name.as_deref()).collect()).unwrap_or_default()
        };
        let mut variant = BTreeMap::new();
        for item in given.unwrap_or_default().split(',').map(str::trim).filter(|i| !i.is_empty()) {
            let (dim, value) = match item.split_once('=') {
                Some((d, v)) => (d.trim(), v.trim()),
                None if dims.len() == 1 => (dims[0], item),
                None => {
                    let msg = format!("`{text}`: `{item}` names no dimension, and `{}` fans out over {}", stage.name, dims.join(", "));
                    self.error(
                        line,
                        path,
                        msg,
                        Some(format!("name each: [{}]", dims.iter().map(|d| format!("{d}=...")).collect::<Vec<_>>().join(","))),
                    );
                    return None;
                }
            };
            if dim == SEED_LABEL && !dims.contains(&dim) {
                let msg = format!("`{text}`: a claim pools its instances' seeds, pairing them; leave `seed` out");
                self.error(line, path, msg, None);
                return None;
            }
            if !dims.contains(&dim) {
                let help = match dims.is_empty() {
                    true => format!("`{}` has no variants: write `{}.METRIC`", stage.name, stage.name),
                    false => format!("its dimensions: {}{}", dims.join(", "), suggest(dim, &dims)),
                };
                self.error(line, path, format!("`{text}`: `{}` does not vary by `{dim}`", stage.name), Some(help));
                return None;
            }
            let valid = values(dim);
            if !valid.contains(&value) {
                let help = format!("variants of `{dim}`: {}{}", valid.join(", "), suggest(value, &valid));
                self.error(line, path, format!("`{text}`: `{dim}` has no variant `{value}`"), Some(help));
                return None;
            }
            variant.insert(dim.to_owned(), value.to_owned());
        }
        if let Some(missing) = dims.iter().find(|d| !variant.contains_key(**d)) {
            let help = format!("variants of `{missing}`: {}", values(missing).join(", "));
            self.error(line, path, format!("`{text}` names no variant of `{missing}`, over which `{}` fans out", stage.name), Some(help));
            return None;
        }
        Some(variant)
    }

    /// Refuses a stage table (or a variant) that sets the setting its operator receives the
    /// claims through: only `[claims]` sets it. The key is taken out of `tables`, so its value
    /// is not checked as a setting as well.
    pub(super) fn claims_not_set_by_stages(&mut self, tables: &mut Map<String, Value>, registry: &Registry) {
        for (name, table) in tables.iter_mut() {
            let Value::Object(table) = table else { continue };
            let operator = table.get("operator").and_then(Value::as_str);
            let Some(key) = operator.and_then(|o| registry.get(o)).and_then(|op| op.claims_key()) else { continue };
            let mut set = Vec::new();
            if table.remove(key).is_some() {
                set.push(format!("stages.{name}.{key}"));
            }
            if let Some(Value::Object(variants)) = table.get_mut("variants") {
                for (variant, v) in variants.iter_mut() {
                    if v.as_object_mut().and_then(|v| v.remove(key)).is_some() {
                        set.push(format!("stages.{name}.variants.{variant}.{key}"));
                    }
                }
            }
            for path in set {
                let help = "declare claims in [claims]; every stage that reads them gets them".to_owned();
                self.error(self.line(&path), &path, format!("is filled from the file's [claims]; a stage does not set `{key}`"), Some(help));
            }
        }
    }

    /// Hands the claims to every stage whose operator reads them (the report), as its setting:
    /// in its key, so a changed claim redoes the report.
    pub(super) fn hand_claims(&mut self, spec: &Spec, stages: &mut [Stage], registry: &Registry) {
        let value = serde_json::to_value(spec).expect("claims serialise");
        for stage in stages.iter_mut() {
            let op = registry.get(&stage.operator).expect("validated operator");
            let Some(key) = op.claims_key() else { continue };
            for variant in &mut stage.variants {
                let mut settings = variant.settings.json().clone();
                settings[key] = value.clone();
                match op.settings(settings) {
                    Ok(s) => variant.settings = s,
                    Err(e) => self.error(self.line("claims"), "claims", format!("stage `{}` cannot read them: {e}", stage.name), None),
                }
            }
        }
    }
}
