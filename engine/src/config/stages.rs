//! `[stages.*]`: each stage's kind, operator, settings, variants and shards, its inputs bound to
//! the stages that provide them, and its settings checked against what its inputs will be.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::ops::Range;
use std::path::Path;

use rlmflow_cache::external::Source;
use rlmflow_stages::{Arity, DynOperator, FilePattern, InputOutlines, ItemCount, Need, Outline, Parsed, Part, Registry, Share, StageKind};
use serde_json::{Map, Value};

use super::checker::Checker;
use super::{Binding, Bounds, Merge, Stage, Variant, suggest};

/// A variant's name and the settings it overrides; `None` for a stage without variants.
type Named = Option<(String, Map<String, Value>)>;

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

const STAGE_KEYS: &[&str] = &["kind", "operator", "inputs", "variants", "per_seed", "shards", "shard_size", "timeout", "retries"];
/// The longest `timeout` a stage may set: a week, in seconds.
const MAX_TIMEOUT_S: f64 = 7.0 * 24.0 * 3600.0;
/// The most `retries` a stage may set.
const MAX_RETRIES: u64 = 100;
/// The most parts one stage instance may be split into.
const MAX_SHARDS: u64 = 4_096;

impl Checker {
    /// Checks each stage's settings against what its inputs will be (image side, frames), as far
    /// as their settings tell, in dependency order: an image a ViT patch does not divide or scenes
    /// of two sizes mixed are config errors here, not failures an hour into the run.
    pub(super) fn outlines(&mut self, stages: &[Stage], registry: &Registry) {
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

    /// Checks one stage table; returns it with its explicit `inputs` (slot -> stage names). Each
    /// step below owns its errors; the stage is returned when every variant's settings check.
    pub(super) fn stage(
        &mut self,
        name: &str,
        table: &Map<String, Value>,
        registry: &Registry,
        dir: &Path,
    ) -> Option<(Stage, BTreeMap<String, Vec<String>>)> {
        let path = format!("stages.{name}");
        let line = self.line(&path);
        let (kind, op_name, op_id) = self.kind_and_operator(name, table, registry)?;
        let op = registry.get(&op_id).expect("found by its kind and name");
        // A bad setting the variants inherit is one error, not one per variant.
        let mut reported = BTreeSet::new();
        let mut checked: Vec<Variant> = (self.variant_tables(table, &path).into_iter())
            .filter_map(|(variant, merged)| self.variant_settings(op, &path, variant, merged, dir, &mut reported))
            .collect();
        let inputs = self.explicit_inputs(table, &path, &operator_slots(registry, &op_id, &kind), &op_name);
        let per_seed = self.per_seed(table, &path, &kind);
        let bounds = self.bounds(table, &path);
        let split = self.split(table, &path);
        if checked.is_empty() {
            return None;
        }
        let merge = match split {
            Some((key, split)) => Some(self.shard(&key, op, kind, &mut checked, split, registry)?),
            None => None,
        };
        let stage = Stage { name: name.to_owned(), kind, operator: op_id, variants: checked, bindings: Vec::new(), per_seed, merge, bounds, line };
        Some((stage, inputs))
    }

    /// The stage's kind (`kind`, else its name) and operator: its name and its registry id.
    fn kind_and_operator(&mut self, name: &str, table: &Map<String, Value>, registry: &Registry) -> Option<(StageKind, String, String)> {
        let path = format!("stages.{name}");
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
                self.error(self.line(&path), &path, "missing `operator`".into(), Some(help));
            }
            return None;
        };
        let Some((id, _)) = registry.find(kind.name, &op_name) else {
            let key = format!("{path}.operator");
            let msg = match registry.named(&op_name) {
                Some(op) => format!("operator `{op_name}` implements kind `{}`, not `{}`", op.spec().kind, kind.name),
                None => format!("unknown operator `{op_name}` for stage kind `{}`", kind.name),
            };
            let help = format!("valid: {}{}", operators.join(", "), suggest(&op_name, &operators));
            self.error(self.line(&key), &key, msg, Some(help));
            return None;
        };
        let id = id.to_owned();
        Some((kind, op_name, id))
    }

    /// Each variant's settings table (the stage's keys with the variant's merged over them), with
    /// the variant's name and overrides; one unnamed table without `variants`.
    fn variant_tables(&mut self, table: &Map<String, Value>, path: &str) -> Vec<(Named, Map<String, Value>)> {
        let mut base = table.clone();
        for key in STAGE_KEYS {
            base.remove(*key);
        }
        let mut variants = Vec::new();
        match table.get("variants") {
            None => variants.push((None, base)),
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
        variants
    }

    /// One variant's settings, checked by its operator, with the paths they track; `None` (its
    /// error reported, once across variants: `reported`) when they do not check.
    fn variant_settings(
        &mut self,
        op: &dyn DynOperator,
        path: &str,
        variant: Named,
        merged: Map<String, Value>,
        dir: &Path,
        reported: &mut BTreeSet<(String, String)>,
    ) -> Option<Variant> {
        match op.settings(Value::Object(merged)) {
            Ok(settings) => {
                let tracked = self.tracked(op, &settings, path, &variant, dir, reported);
                Some(Variant { name: variant.map(|v| v.0), settings, shards: Vec::new(), tracked })
            }
            Err(e) => {
                // Point at the variant's line when the variant set the key.
                let top = e.key.split('.').next().unwrap_or_default();
                let key = match &variant {
                    Some((v, overrides)) if overrides.contains_key(top) => format!("{path}.variants.{v}.{}", e.key),
                    _ if e.key.is_empty() => path.to_owned(),
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
                None
            }
        }
    }

    /// What a variant's tracked settings name, made absolute and checked: a path each, or the
    /// chosen files of a setting that lists them ([`DynOperator::tracked_files`]).
    fn tracked(
        &mut self,
        op: &dyn DynOperator,
        settings: &Parsed,
        path: &str,
        variant: &Named,
        dir: &Path,
        reported: &mut BTreeSet<(String, String)>,
    ) -> Vec<(String, Source)> {
        let mut tracked = Vec::new();
        let root = std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf());
        for &key in op.tracked_keys() {
            let files = op.tracked_files(settings, key);
            let what = if files.is_some() { "files or globs (`probes/*.py`)" } else { "a file or directory" };
            let checked = match files {
                Some(patterns) => chosen_files(dir, &patterns).map(|files| (!files.is_empty()).then(|| Source::Files { root: root.clone(), files })),
                None => tracked_path(op, settings, key, dir),
            };
            let message = match checked {
                Ok(found) => {
                    tracked.extend(found.map(|source| (key.to_owned(), source)));
                    continue;
                }
                Err(message) => message,
            };
            let at = match variant {
                Some((v, overrides)) if overrides.contains_key(key) => format!("{path}.variants.{v}.{key}"),
                _ => format!("{path}.{key}"),
            };
            let help = Some(format!("{what}, relative to the pipeline file's directory ({})", root.display()));
            if reported.insert((at.clone(), message.clone())) {
                self.error(self.line(&at), &at, message, help);
            }
        }
        tracked
    }

    /// The stage's `inputs` table: for each slot the operator reads (`readable`), the stage names
    /// given.
    fn explicit_inputs(&mut self, table: &Map<String, Value>, path: &str, readable: &[&str], op_name: &str) -> BTreeMap<String, Vec<String>> {
        let mut inputs = BTreeMap::new();
        match table.get("inputs") {
            None => {}
            Some(Value::Object(map)) => {
                for (slot, value) in map {
                    let key = format!("{path}.inputs.{slot}");
                    if !readable.contains(&slot.as_str()) {
                        let help = format!("`{op_name}` reads: {}{}", readable.join(", "), suggest(slot, readable));
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
        inputs
    }

    /// Whether the stage runs once per seed: its `per_seed`, else its kind's.
    fn per_seed(&mut self, table: &Map<String, Value>, path: &str, kind: &StageKind) -> bool {
        match table.get("per_seed") {
            None => kind.per_seed,
            Some(Value::Bool(b)) => *b,
            Some(other) => {
                let key = format!("{path}.per_seed");
                self.error(self.line(&key), &key, format!("must be true or false, not {other}"), None);
                kind.per_seed
            }
        }
    }

    /// A stage's `timeout` (seconds) and `retries`.
    fn bounds(&mut self, table: &Map<String, Value>, path: &str) -> Bounds {
        let mut bounds = Bounds::default();
        if let Some(value) = table.get("timeout") {
            let key = format!("{path}.timeout");
            match value.as_f64().filter(|t| *t > 0.0 && *t <= MAX_TIMEOUT_S) {
                Some(t) => bounds.timeout_s = Some(t),
                None => self.error(self.line(&key), &key, format!("must be a number of seconds in (0, {MAX_TIMEOUT_S}], not {value}"), None),
            }
        }
        if let Some(value) = table.get("retries") {
            let key = format!("{path}.retries");
            match value.as_u64().filter(|n| *n <= MAX_RETRIES) {
                Some(n) => bounds.retries = n as u32,
                None => self.error(self.line(&key), &key, format!("must be an integer in 0..={MAX_RETRIES}, not {value}"), None),
            }
        }
        bounds
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
            let can: Vec<&str> = registry.operators().filter(|(_, o)| o.merge().is_some()).map(|(_, o)| o.spec().name).collect();
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
    pub(super) fn bind(&mut self, stages: &mut [Stage], explicit: &[BTreeMap<String, Vec<String>>], registry: &Registry) {
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
                    None if slot.need == Need::Named => continue,
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
}

/// The path tracked setting `key` names, absolute, once it is found to be something that can be
/// tracked; `None` where the setting is empty.
fn tracked_path(op: &dyn DynOperator, settings: &Parsed, key: &str, dir: &Path) -> Result<Option<Source>, String> {
    let given = settings.get(key).and_then(Value::as_str).unwrap_or_default();
    if given.is_empty() {
        return Ok(None);
    }
    let source = std::path::absolute(dir.join(given)).unwrap_or_else(|_| dir.join(given));
    match tracked_source(given, &source) {
        Ok(()) => op.check_tracked(settings, key, &source).map_err(|e| e.message)?,
        // Missing: the operator's word on what belongs there, where it has one.
        Err(missing) if !source.exists() => return Err(op.check_tracked(settings, key, &source).err().map_or(missing, |e| e.message)),
        Err(special) => return Err(special),
    }
    Ok(Some(Source::Path(source)))
}

/// The files `patterns` name below `dir`, relative to it, sorted: each must lie in `dir`'s tree
/// (no `..`, no absolute path, no symbolic link leading out of it) and be a regular file.
fn chosen_files(dir: &Path, patterns: &[FilePattern]) -> Result<Vec<String>, String> {
    let dir = if dir.as_os_str().is_empty() { Path::new(".") } else { dir };
    let tree = dir.canonicalize().map_err(|e| format!("{}: {e}", dir.display()))?;
    let mut files = std::collections::BTreeSet::new();
    for FilePattern { pattern, required } in patterns {
        let path = Path::new(pattern);
        let leaves = path.is_absolute() || path.components().any(|c| c == std::path::Component::ParentDir);
        if leaves {
            if *required || dir.join(path).is_file() {
                return Err(format!("`{pattern}` leaves the pipeline's directory ({}): a source must lie below it", dir.display()));
            }
            continue;
        }
        let full = dir.join(path);
        let matches = glob::glob(&full.to_string_lossy()).map_err(|e| format!("`{pattern}` is not a valid pattern: {e}"))?;
        let mut matched = 0;
        for found in matches {
            let found = found.map_err(|e| format!("`{pattern}`: {e}"))?;
            let real = found.canonicalize().map_err(|e| format!("`{pattern}`: {}: {e}", found.display()))?;
            let Ok(rel) = real.strip_prefix(&tree) else {
                return Err(format!("`{}` is a symbolic link out of the pipeline's directory (to {})", found.display(), real.display()));
            };
            if real.is_dir() {
                continue;
            }
            tracked_source(pattern, &real)?;
            // The path as the program names it, below the tree (a link within the tree is read
            // through: its target's bytes are what the key covers).
            let named = found.strip_prefix(dir).unwrap_or(rel);
            files.insert(named.to_str().ok_or_else(|| format!("`{}`: a source's path must be UTF-8", found.display()))?.to_owned());
            matched += 1;
        }
        if *required && matched == 0 {
            return Err(format!("`{pattern}` matches no file below {}", dir.display()));
        }
    }
    Ok(files.into_iter().collect())
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
