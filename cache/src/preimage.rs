use std::collections::BTreeSet;
use std::fmt;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::digest::Digest;

/// Bumped when the encoding below changes; every key changes with it.
const PREIMAGE_FORMAT: u32 = 1;

/// One input artifact of an action.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct InputDigest {
    pub slot: String,
    /// The producing instance's label, only where the operator sees it (gathering slots);
    /// empty otherwise, so renaming an upstream stage does not rerun its consumers.
    pub label: String,
    pub digest: Digest,
}

/// Everything that can change an action's result. See the crate docs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Preimage {
    pub operator: String,
    pub operator_version: u32,
    /// Canonical settings: defaults filled in, non-result settings removed.
    pub config: Value,
    pub seed: u64,
    /// Sorted by slot, then label.
    pub inputs: Vec<InputDigest>,
    /// The class of machines that compute the same bytes, for an action whose bytes depend on
    /// its numeric kernels (`cpu/x86-64-v3/amd/portable`); absent where they do not.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub platform: Option<String>,
}

/// One field-level difference between two preimages: why an action is not fresh.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "change", rename_all = "snake_case")]
pub enum Change {
    Operator { old: String, new: String },
    OperatorVersion { old: u32, new: u32 },
    Setting { key: String, old: Option<Value>, new: Option<Value> },
    Seed { old: u64, new: u64 },
    InputChanged { slot: String, label: String },
    InputAdded { slot: String, label: String },
    InputRemoved { slot: String, label: String },
    Platform { old: Option<String>, new: Option<String> },
}

/// How much of a setting's value a change shows in words.
const SHOWN_CHARS: usize = 60;

impl fmt::Display for Change {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // A long value (a list of claims, say) shows its start: the change as data keeps it whole.
        let show = |v: &Option<Value>| {
            let text = v.as_ref().map_or("(unset)".to_owned(), canonical_json);
            match text.char_indices().nth(SHOWN_CHARS) {
                Some((cut, _)) => format!("{}... ({} characters)", &text[..cut], text.chars().count()),
                None => text,
            }
        };
        let input = |slot: &str, label: &str| {
            if label.is_empty() { slot.to_owned() } else { format!("{slot} {label}") }
        };
        match self {
            Change::Operator { old, new } => write!(f, "operator {old} -> {new}"),
            Change::OperatorVersion { old, new } => write!(f, "operator version {old} -> {new}"),
            Change::Setting { key, old, new } => write!(f, "{key} {} -> {}", show(old), show(new)),
            Change::Seed { old, new } => write!(f, "seed {old} -> {new}"),
            Change::InputChanged { slot, label } => write!(f, "input {} changed", input(slot, label)),
            Change::InputAdded { slot, label } => write!(f, "input {} added", input(slot, label)),
            Change::InputRemoved { slot, label } => write!(f, "input {} removed", input(slot, label)),
            Change::Platform { old, new } => {
                let show = |p: &Option<String>| p.clone().unwrap_or_else(|| "(none)".to_owned());
                write!(f, "numeric platform {} -> {}", show(old), show(new))
            }
        }
    }
}

impl Preimage {
    /// The action key: BLAKE3 over a versioned, length-prefixed encoding.
    pub fn key(&self) -> Digest {
        let mut h = blake3::Hasher::new();
        let mut field = |bytes: &[u8]| {
            h.update(&(bytes.len() as u64).to_le_bytes());
            h.update(bytes);
        };
        field(b"rlmflow-action");
        field(&PREIMAGE_FORMAT.to_le_bytes());
        field(self.operator.as_bytes());
        field(&self.operator_version.to_le_bytes());
        field(canonical_json(&self.config).as_bytes());
        field(&self.seed.to_le_bytes());
        field(&(self.inputs.len() as u64).to_le_bytes());
        for input in &self.inputs {
            field(input.slot.as_bytes());
            field(input.label.as_bytes());
            field(&input.digest.0);
        }
        // Absent for most actions, so their keys are what they were before the field existed.
        if let Some(platform) = &self.platform {
            field(b"platform");
            field(platform.as_bytes());
        }
        h.finalize().into()
    }

    /// What changed from `old` to `self`, field by field.
    pub fn diff(&self, old: &Preimage) -> Vec<Change> {
        let mut changes = Vec::new();
        if self.operator != old.operator {
            changes.push(Change::Operator { old: old.operator.clone(), new: self.operator.clone() });
        } else if self.operator_version != old.operator_version {
            changes.push(Change::OperatorVersion { old: old.operator_version, new: self.operator_version });
        }
        diff_values("", &old.config, &self.config, &mut changes);
        if self.seed != old.seed {
            changes.push(Change::Seed { old: old.seed, new: self.seed });
        }
        let slots = |p: &Preimage| -> BTreeSet<(String, String)> { p.inputs.iter().map(|i| (i.slot.clone(), i.label.clone())).collect() };
        let (before, after) = (slots(old), slots(self));
        for (slot, label) in after.difference(&before) {
            changes.push(Change::InputAdded { slot: slot.clone(), label: label.clone() });
        }
        for (slot, label) in before.difference(&after) {
            changes.push(Change::InputRemoved { slot: slot.clone(), label: label.clone() });
        }
        for new in &self.inputs {
            let same_slot = |o: &&InputDigest| o.slot == new.slot && o.label == new.label;
            if let Some(o) = old.inputs.iter().find(same_slot)
                && o.digest != new.digest
            {
                changes.push(Change::InputChanged { slot: new.slot.clone(), label: new.label.clone() });
            }
        }
        if self.platform != old.platform {
            changes.push(Change::Platform { old: old.platform.clone(), new: self.platform.clone() });
        }
        changes
    }
}

fn diff_values(prefix: &str, old: &Value, new: &Value, out: &mut Vec<Change>) {
    let join = |k: &str| if prefix.is_empty() { k.to_owned() } else { format!("{prefix}.{k}") };
    match (old, new) {
        (Value::Object(a), Value::Object(b)) => {
            let keys: BTreeSet<&String> = a.keys().chain(b.keys()).collect();
            for k in keys {
                match (a.get(k), b.get(k)) {
                    (Some(x), Some(y)) => diff_values(&join(k), x, y, out),
                    (x, y) => out.push(Change::Setting { key: join(k), old: x.cloned(), new: y.cloned() }),
                }
            }
        }
        _ if old != new => out.push(Change::Setting { key: prefix.to_owned(), old: Some(old.clone()), new: Some(new.clone()) }),
        _ => {}
    }
}

/// JSON with object keys sorted at every level, whatever map type serde_json was built with.
pub fn canonical_json(value: &Value) -> String {
    let mut out = String::new();
    write_canonical(value, &mut out);
    out
}

fn write_canonical(value: &Value, out: &mut String) {
    match value {
        Value::Object(map) => {
            let mut keys: Vec<&String> = map.keys().collect();
            keys.sort();
            out.push('{');
            for (i, k) in keys.into_iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                out.push_str(&Value::String(k.clone()).to_string());
                out.push(':');
                write_canonical(&map[k], out);
            }
            out.push('}');
        }
        Value::Array(items) => {
            out.push('[');
            for (i, v) in items.iter().enumerate() {
                if i > 0 {
                    out.push(',');
                }
                write_canonical(v, out);
            }
            out.push(']');
        }
        scalar => out.push_str(&scalar.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn preimage(config: Value) -> Preimage {
        Preimage {
            operator: "clip".into(),
            operator_version: 2,
            config,
            seed: 17,
            inputs: vec![InputDigest { slot: "scenes".into(), label: String::new(), digest: Digest::of(b"s") }],
            platform: None,
        }
    }

    #[test]
    fn key_ignores_map_order_but_not_values() {
        let a = preimage(json!({"alpha": 4.0, "objective": "sg-clip"}));
        let b = preimage(serde_json::from_str(r#"{"objective":"sg-clip","alpha":4.0}"#).unwrap());
        assert_eq!(a.key(), b.key());
        assert_ne!(a.key(), preimage(json!({"alpha": 1.0, "objective": "sg-clip"})).key());
        let mut c = a.clone();
        c.seed = 18;
        assert_ne!(a.key(), c.key());
    }

    #[test]
    fn a_platform_class_enters_the_key_and_the_diff() {
        let plain = preimage(json!({}));
        let mut portable = plain.clone();
        portable.platform = Some("cpu/x86-64-v3/amd/portable".into());
        let mut native = plain.clone();
        native.platform = Some("cpu/x86-64/native/AMD EPYC/avx2+fma".into());
        assert_ne!(plain.key(), portable.key());
        assert_ne!(portable.key(), native.key());
        let shown: Vec<String> = native.diff(&portable).iter().map(|c| c.to_string()).collect();
        assert_eq!(shown, ["numeric platform cpu/x86-64-v3/amd/portable -> cpu/x86-64/native/AMD EPYC/avx2+fma"]);
    }

    #[test]
    fn length_prefixes_keep_fields_apart() {
        let mut a = preimage(json!({}));
        let mut b = a.clone();
        a.inputs[0].slot = "ab".into();
        a.inputs[0].label = "c".into();
        b.inputs[0].slot = "a".into();
        b.inputs[0].label = "bc".into();
        assert_ne!(a.key(), b.key());
    }

    #[test]
    fn diff_names_fields() {
        let old = preimage(json!({"alpha": 4.0, "radar": {"image": 64}}));
        let mut new = preimage(json!({"alpha": 1.0, "radar": {"image": 64, "bev": true}}));
        new.operator_version = 3;
        new.inputs[0].digest = Digest::of(b"t");
        let shown: Vec<String> = new.diff(&old).iter().map(|c| c.to_string()).collect();
        assert_eq!(shown, ["operator version 2 -> 3", "alpha 4.0 -> 1.0", "radar.bev (unset) -> true", "input scenes changed"]);
        assert!(old.diff(&old).is_empty());
    }

    #[test]
    fn canonical_json_sorts_nested_keys() {
        let v: Value = serde_json::from_str(r#"{"b":{"y":1,"x":[{"d":1,"c":2}]},"a":"q"}"#).unwrap();
        assert_eq!(canonical_json(&v), r#"{"a":"q","b":{"x":[{"c":2,"d":1}],"y":1}}"#);
    }
}
