//! What every check shares: the error of a file's diagnostics, and the TOML text read into JSON
//! values with each key's line.

use std::fmt;
use std::path::{Path, PathBuf};

use serde_json::{Map, Value};
use toml::de::{DeTable, DeValue};

use super::diagnostic::Diagnostic;
use super::{KeyLines, check_name, suggest};

/// Every problem found in one pipeline file.
#[derive(Debug)]
pub struct ConfigError {
    pub file: PathBuf,
    pub diagnostics: Vec<Diagnostic>,
    /// The command line's overrides: a problem in a key one of them set is located at it.
    pub overrides: Vec<super::overrides::Override>,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, d) in self.diagnostics.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            match super::overrides::Override::setting(&self.overrides, &d.key) {
                Some(o) => write!(f, "{} with {}: ", self.file.display(), o.shown())?,
                // Line 0: the command line's (a malformed override names itself in the key).
                None if d.line == 0 => write!(f, "{}: ", self.file.display())?,
                None => write!(f, "{}:{}: ", self.file.display(), d.line)?,
            }
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

/// Collects every problem of a pipeline file, each located by its key's line.
pub(super) struct Checker {
    pub(super) lines: KeyLines,
    pub(super) line_starts: Vec<usize>,
    pub(super) errors: Vec<Diagnostic>,
}

impl Checker {
    pub(super) fn into_error(mut self, file: &Path) -> ConfigError {
        self.errors.sort_by_key(|d| d.line);
        ConfigError { file: file.to_path_buf(), diagnostics: self.errors, overrides: Vec::new() }
    }

    pub(super) fn error(&mut self, line: usize, key: &str, message: String, help: Option<String>) {
        self.errors.push(Diagnostic { line, key: key.to_owned(), message, help });
    }

    pub(super) fn line_of(&self, offset: usize) -> usize {
        self.line_starts.partition_point(|&s| s <= offset)
    }

    /// [`KeyLines::line`].
    pub(super) fn line(&self, path: &str) -> usize {
        self.lines.line(path)
    }

    pub(super) fn index(&mut self, path: &mut Vec<String>, table: &DeTable<'_>) {
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
    pub(super) fn datetime(&mut self, line: usize, path: &str) {
        let help = "write it as a quoted string if text is meant".to_owned();
        self.error(line, path, "a TOML date or time is not a valid value for any setting".into(), Some(help));
    }

    pub(super) fn name(&mut self, path: &str, name: &str) {
        if let Err(problem) = check_name(name) {
            self.error(self.line(path), path, format!("the name {problem}"), None);
        }
    }

    pub(super) fn unknown_key(&mut self, path: &str, key: &str, valid: &[&str]) {
        let help = format!("valid keys: {}{}", valid.join(", "), suggest(key, valid));
        self.error(self.line(path), path, format!("unknown key `{key}`"), Some(help));
    }

    pub(super) fn string(&mut self, table: &Map<String, Value>, at: &str, key: &str) -> Option<String> {
        match table.get(key)? {
            Value::String(s) => Some(s.clone()),
            other => {
                let path = format!("{at}.{key}");
                self.error(self.line(&path), &path, format!("must be a string, not {other}"), None);
                None
            }
        }
    }
}

pub(super) fn line_starts(text: &str) -> Vec<usize> {
    std::iter::once(0).chain(text.match_indices('\n').map(|(i, _)| i + 1)).collect()
}

pub(super) fn to_json_table(table: &DeTable<'_>) -> Map<String, Value> {
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
