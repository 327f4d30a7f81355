//! `--set STAGE.KEY=VALUE` (and `pipeline.KEY=VALUE`): a setting given on the command line, applied
//! over the pipeline file's tables before they are checked, so it is validated exactly as the file
//! is. A variant the file does not declare is made only by `--set-new`, so a typo in a variant's
//! name is an error naming the nearest, not a new variant.

use serde_json::{Map, Value};

use super::diagnostic::{Diagnostic, MAX_DEPTH, too_deep};

#[derive(Clone, Debug)]
pub struct Override {
    /// As given: `pretrain.alpha=2`.
    pub text: String,
    /// The dotted key it sets: `stages.pretrain.alpha`, `pipeline.seeds`.
    pub path: String,
    value: Value,
    /// Whether it may make a variant the file does not declare (`--set-new`).
    creates: bool,
}

const HELP: &str = "write --set STAGE.KEY=VALUE with the value in TOML, e.g. --set pretrain.alpha=2, \
                    --set pretrain.variants.alpha4.epochs=20, --set scenes.images='[\"range-azimuth\"]', --set pipeline.seeds='[1, 2]'";

impl Override {
    /// `text` as `--set` gives it (`creates`: as `--set-new` does, which may make a variant).
    pub fn parse(text: &str, creates: bool) -> Result<Override, Diagnostic> {
        let flag = if creates { "--set-new" } else { "--set" };
        let bad = |message: String| Diagnostic { line: 0, key: format!("{flag} {text}"), message, help: Some(HELP.into()) };
        let Some((key, value)) = text.split_once('=') else { return Err(bad("has no `=`".into())) };
        let key = key.trim();
        if key.split('.').count() < 2 || key.split('.').any(|part| part.trim().is_empty()) {
            return Err(bad(format!("`{key}` is not STAGE.KEY")));
        }
        // One TOML value, alone: a value that smuggles in a second key is refused, and one nested
        // past the file's bound is refused before the parser recurses into it.
        let line = format!("v = {value}");
        if let Some((_, depth)) = too_deep(&line) {
            return Err(bad(format!("nested more than {MAX_DEPTH} levels deep (at least {depth}); at most {MAX_DEPTH}")));
        }
        let mut table: toml::Table = toml::from_str(&line).map_err(|e| bad(format!("`{value}` is not a TOML value: {}", e.message().trim())))?;
        let value = match (table.remove("v"), table.is_empty()) {
            (Some(parsed), true) => serde_json::to_value(parsed).map_err(|e| bad(format!("`{value}`: {e}")))?,
            _ => return Err(bad(format!("`{value}` is not one TOML value"))),
        };
        let path = if key.starts_with("pipeline.") { key.to_owned() } else { format!("stages.{key}") };
        Ok(Override { text: text.to_owned(), path, value, creates })
    }

    /// As the command line gave it: `--set pretrain.alpha=2`, `--set-new pretrain.variants.a8.alpha=8.0`.
    pub fn shown(&self) -> String {
        format!("{} {}", if self.creates { "--set-new" } else { "--set" }, self.text)
    }

    /// The last of `overrides` that set `key` (a dotted path from the file's root) or a table
    /// above it: where a problem with that key is located.
    pub fn setting<'o>(overrides: &'o [Override], key: &str) -> Option<&'o Override> {
        overrides.iter().rev().find(|o| key == o.path || key.strip_prefix(o.path.as_str()).is_some_and(|rest| rest.starts_with('.')))
    }

    /// Sets the value in the pipeline's `root` table: the stage must exist; tables below it are
    /// made where missing (a table of settings the file leaves at their defaults), but a variant
    /// only by `--set-new`.
    pub fn apply(&self, root: &Map<String, Value>) -> Result<Map<String, Value>, String> {
        let mut root = root.clone();
        let parts: Vec<&str> = self.path.split('.').map(str::trim).collect();
        let (mut table, under) = if parts[0] == "pipeline" {
            let header = root.entry("pipeline").or_insert_with(|| Value::Object(Map::new()));
            (header.as_object_mut().ok_or("`pipeline` is not a table")?, 1)
        } else {
            let stages = root.get_mut("stages").and_then(Value::as_object_mut).ok_or("the pipeline has no stages")?;
            let names: Vec<String> = stages.keys().cloned().collect();
            let stage = stages.get_mut(parts[1]).and_then(Value::as_object_mut).ok_or_else(|| {
                format!(
                    "no stage `{}`; the stages are {}{} (the header's keys are pipeline.KEY)",
                    parts[1],
                    names.join(", "),
                    super::suggest(parts[1], &names.iter().map(String::as_str).collect::<Vec<_>>())
                )
            })?;
            (stage, 2)
        };
        let (last, between) = parts[under..].split_last().ok_or("names no key")?;
        for (depth, part) in between.iter().enumerate() {
            let variant = under == 2 && depth == 1 && between[0] == "variants";
            if variant && !self.creates && !table.contains_key(*part) {
                let names: Vec<&str> = table.keys().map(String::as_str).collect();
                return Err(format!(
                    "stage `{}` has no variant `{part}`; its variants are {}{} (--set-new makes a new one)",
                    parts[1],
                    if names.is_empty() { "none".to_owned() } else { names.join(", ") },
                    super::suggest(part, &names)
                ));
            }
            let entry = table.entry(*part).or_insert_with(|| Value::Object(Map::new()));
            table = entry.as_object_mut().ok_or_else(|| format!("`{}` is not a table", parts[under - 1..under + 1 + depth].join(".")))?;
        }
        table.insert((*last).to_owned(), self.value.clone());
        Ok(root)
    }
}
