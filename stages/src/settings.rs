//! An operator's settings: the [`Settings`] trait of its plain struct, how a stage's table becomes
//! one ([`parse_settings`]: given keys over the defaults, every error naming its key), and
//! [`Parsed`], the settings of one stage instance parsed once, which every question the engine
//! asks of them reads.

use std::any::Any;
use std::fmt;
use std::sync::Arc;

use serde::Serialize;
use serde::de::DeserializeOwned;
use serde_json::Value;

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

/// One stage instance's settings, parsed and checked once: the canonical JSON its key and its
/// action's request hold, and the operator's typed value, which every planning question
/// (`resources`, `outline`, `footprint`, `items`) reads without parsing again.
#[derive(Clone)]
pub struct Parsed {
    json: Value,
    typed: Arc<dyn Any + Send + Sync>,
}

impl Parsed {
    /// Settings already typed and checked.
    pub fn of<S: Settings>(typed: S) -> Parsed {
        let json = serde_json::to_value(&typed).expect("settings serialise to JSON");
        Parsed { json, typed: Arc::new(typed) }
    }

    pub fn json(&self) -> &Value {
        &self.json
    }

    /// The typed settings. Panics where they are another operator's type: the engine asks an
    /// operator only of settings it parsed.
    pub fn typed<S: Settings>(&self) -> &S {
        self.typed.downcast_ref().expect("settings parsed by the operator asked")
    }
}

impl std::ops::Deref for Parsed {
    type Target = Value;
    fn deref(&self) -> &Value {
        &self.json
    }
}

impl fmt::Debug for Parsed {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.json.fmt(f)
    }
}

impl PartialEq for Parsed {
    fn eq(&self, other: &Parsed) -> bool {
        self.json == other.json
    }
}

impl PartialEq<Value> for Parsed {
    fn eq(&self, other: &Value) -> bool {
        &self.json == other
    }
}

/// Typed settings from a stage's table: given keys over the operator's defaults, deserialised
/// with the failing key's path, then checked. A struct that flattens a shared group (such as
/// [`crate::Training`]) cannot deny unknown fields through serde, and serde loses the key of a
/// bad value inside the group: both are recovered here, so every struct reports alike.
pub(crate) fn parse_settings<S: Settings>(raw: Value) -> Result<S, SettingError> {
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
