//! `--set STAGE.KEY=VALUE`: a setting given on the command line, applied over the pipeline file's
//! tables before they are checked, so it is validated exactly as the file is.

use serde_json::{Map, Value};

use super::diagnostic::{Diagnostic, MAX_DEPTH, too_deep};

#[derive(Clone, Debug)]
pub struct Override {
    /// As given: `pretrain.alpha=2`.
    pub text: String,
    /// The dotted key it sets: `stages.pretrain.alpha`.
    pub path: String,
    value: Value,
}

const HELP: &str = "write --set STAGE.KEY=VALUE with the value in TOML, e.g. --set pretrain.alpha=2, \
                    --set pretrain.variants.alpha4.epochs=20, --set scenes.images='[\"range-azimuth\"]'";

impl Override {
    pub fn parse(text: &str) -> Result<Override, Diagnostic> {
        let bad = |message: String| Diagnostic { line: 0, key: format!("--set {text}"), message, help: Some(HELP.into()) };
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
        Ok(Override { text: text.to_owned(), path: format!("stages.{key}"), value })
    }

    /// The last of `overrides` that set `key` (a dotted path from the file's root) or a table
    /// above it: where a problem with that key is located.
    pub fn setting<'o>(overrides: &'o [Override], key: &str) -> Option<&'o Override> {
        overrides.iter().rev().find(|o| key == o.path || key.strip_prefix(o.path.as_str()).is_some_and(|rest| rest.starts_with('.')))
    }

    /// Sets the value in the pipeline's `root` table: the stage must exist; tables below it are
    /// made where missing (a new variant, say).
    pub fn apply(&self, root: &Map<String, Value>) -> Result<Map<String, Value>, String> {
        let mut root = root.clone();
        let parts: Vec<&str> = self.path.split('.').map(str::trim).collect();
        let stages = root.get_mut("stages").and_then(Value::as_object_mut).ok_or("the pipeline has no stages")?;
        let names: Vec<String> = stages.keys().cloned().collect();
        let mut table = stages.get_mut(parts[1]).and_then(Value::as_object_mut).ok_or_else(|| {
            format!(
                "no stage `{}`; the stages are {}{}",
                parts[1],
                names.join(", "),
                super::suggest(parts[1], &names.iter().map(String::as_str).collect::<Vec<_>>())
            )
        })?;
        let (last, between) = parts[2..].split_last().expect("STAGE.KEY has a key");
        for (depth, part) in between.iter().enumerate() {
            let entry = table.entry(*part).or_insert_with(|| Value::Object(Map::new()));
            table = entry.as_object_mut().ok_or_else(|| format!("`{}` is not a table", parts[1..3 + depth].join(".")))?;
        }
        table.insert((*last).to_owned(), self.value.clone());
        Ok(root)
    }
}
