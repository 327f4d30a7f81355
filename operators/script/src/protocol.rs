//! What a program says to rlmflow: one JSON object a line on its stdout, after `@rlmflow `.
//!
//! ```text
//! @rlmflow {"progress": {"position": 3, "length": 10, "message": "folds"}}
//! @rlmflow {"event": "fold", "data": {"k": 10, "f1": 0.41}}
//! @rlmflow {"metrics": {"f1": 0.41}}
//! @rlmflow {"summary": "k=10 F1 0.410"}
//! @rlmflow {"live": "curves"}
//! ```
//!
//! Progress becomes the stage's bar, events go to the run's event log, metrics (merged, later
//! keys over earlier) into the action's record (`show`), the summary onto the `ran` line; `live`
//! names a directory below the checkpoint directory that shows the work as it goes (TensorBoard
//! event files), which `results/` links to until the output is committed. Any other line is the
//! program's own output and goes to the stage's log.

use serde_json::{Map, Value};

pub const PREFIX: &str = "@rlmflow ";

/// One message.
#[derive(Debug, PartialEq)]
pub enum Message {
    Progress {
        position: u64,
        length: u64,
        message: String,
    },
    Event {
        name: String,
        data: Value,
    },
    Metrics(Map<String, Value>),
    Summary(String),
    /// A directory, relative to the checkpoint directory.
    Live(String),
}

const VALID: &str = "valid: {\"progress\": {\"position\", \"length\", \"message\"}}, {\"event\": NAME, \"data\": {..}}, {\"metrics\": {..}}, {\"summary\": TEXT}, {\"live\": DIR}";

/// The message of a protocol line (its text after [`PREFIX`]), or what is wrong with it.
pub fn parse(text: &str) -> Result<Message, String> {
    let value: Value = serde_json::from_str(text).map_err(|e| format!("not JSON ({e}); {VALID}"))?;
    let Value::Object(mut map) = value else { return Err(format!("not a JSON object; {VALID}")) };
    let key = match map.keys().find(|k| *k != "data") {
        Some(k) => k.clone(),
        None => return Err(format!("names no message; {VALID}")),
    };
    let body = map.remove(&key).expect("the key is in the map");
    let extra = map.keys().any(|k| k != "data" || key != "event");
    if extra {
        return Err(format!(
            "holds more than one message ({}); {VALID}",
            std::iter::once(key.as_str()).chain(map.keys().map(String::as_str)).collect::<Vec<_>>().join(", ")
        ));
    }
    match (key.as_str(), body) {
        ("progress", Value::Object(p)) => {
            let count = |field: &str| p.get(field).and_then(Value::as_u64).ok_or_else(|| format!("`progress.{field}` must be a whole number"));
            let (position, length) = (count("position")?, count("length")?);
            let message = match p.get("message") {
                None => String::new(),
                Some(Value::String(m)) => m.clone(),
                Some(_) => return Err("`progress.message` must be a string".into()),
            };
            Ok(Message::Progress { position, length, message })
        }
        ("event", Value::String(name)) if !name.is_empty() => {
            let data = map.remove("data").unwrap_or(Value::Object(Map::new()));
            Ok(Message::Event { name, data })
        }
        ("metrics", Value::Object(metrics)) => Ok(Message::Metrics(metrics)),
        ("summary", Value::String(summary)) => Ok(Message::Summary(summary)),
        ("live", Value::String(dir)) => {
            let relative = std::path::Path::new(&dir);
            if relative.is_absolute() || relative.components().any(|c| c == std::path::Component::ParentDir) {
                return Err(format!("`live` names a directory relative to $RLMFLOW_CHECKPOINT, not `{dir}`"));
            }
            Ok(Message::Live(dir))
        }
        ("progress" | "event" | "metrics" | "summary" | "live", _) => Err(format!("`{key}` has the wrong type; {VALID}")),
        _ => Err(format!("unknown message `{key}`; {VALID}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn each_message_parses_and_a_malformed_one_says_what_is_valid() {
        assert_eq!(
            parse(r#"{"progress": {"position": 3, "length": 10, "message": "folds"}}"#),
            Ok(Message::Progress { position: 3, length: 10, message: "folds".into() })
        );
        assert_eq!(parse(r#"{"event": "fold", "data": {"k": 10}}"#), Ok(Message::Event { name: "fold".into(), data: json!({"k": 10}) }));
        assert_eq!(parse(r#"{"data": {"k": 10}, "event": "fold"}"#), Ok(Message::Event { name: "fold".into(), data: json!({"k": 10}) }));
        assert_eq!(parse(r#"{"metrics": {"f1": 0.5}}"#), Ok(Message::Metrics(json!({"f1": 0.5}).as_object().unwrap().clone())));
        assert_eq!(parse(r#"{"summary": "done"}"#), Ok(Message::Summary("done".into())));
        assert_eq!(parse(r#"{"live": "curves"}"#), Ok(Message::Live("curves".into())));
        // Each error says what is wrong; one that is not a message at all lists the valid ones.
        for (line, says, lists) in [
            ("{oops", "not JSON", true),
            ("[1]", "not a JSON object", true),
            ("{}", "names no message", true),
            (r#"{"progress": {"position": -1, "length": 2}}"#, "`progress.position` must be a whole number", false),
            (r#"{"metrics": 3}"#, "`metrics` has the wrong type", true),
            (r#"{"metric": {}}"#, "unknown message `metric`", true),
            (r#"{"summary": "a", "metrics": {}}"#, "more than one message", true),
            (r#"{"live": "../elsewhere"}"#, "relative to $RLMFLOW_CHECKPOINT", false),
        ] {
            let e = parse(line).unwrap_err();
            assert!(e.contains(says) && e.contains("valid:") == lists, "{line}: {e}");
        }
    }
}
