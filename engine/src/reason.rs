//! Why an instance will run, or waits: data, as the store knows it (cargo's `DirtyReason`).
//! `status --json` and `run --json` carry it as it is; the `ui` module alone puts it into words.

use rlmflow_cache::{Change, Digest, Preimage, Store};
use serde::{Deserialize, Serialize};

/// Why an instance whose key is known will run rather than be reused.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "reason", rename_all = "snake_case")]
pub enum RunReason {
    /// No earlier run of this instance is known.
    NeverRun,
    /// The last run had this key, and its output is gone (quarantined by verify, or collected).
    OutputGone,
    /// The last attempt at this key failed; `error` is its message's first line (at most 200
    /// characters), `resumes_from` what a rerun starts from where a checkpoint was kept.
    Failed { error: String, resumes_from: Option<String> },
    /// The last attempt at this key was stopped after keeping a checkpoint.
    Interrupted { resumes_from: String },
    /// The last attempt at this key was stopped before keeping anything.
    Unfinished,
    /// Another process is computing this key right now (it holds the action's lock).
    Running,
    /// The key differs from the last run's, whose record and request were collected.
    RecordCollected,
    /// The key differs from the last run's with no field of the preimage to show (an encoding
    /// change).
    KeyChanged,
    /// One field of the preimage differs from the last run's: a setting of `stage`, an input (a
    /// tracked path with the files that differ, up to five, and how many more), the operator or
    /// its version, the seed, or the numeric platform.
    Changed {
        stage: String,
        #[serde(flatten)]
        change: Change,
        #[serde(default, skip_serializing_if = "Vec::is_empty")]
        files: Vec<String>,
        #[serde(default, skip_serializing_if = "is_zero")]
        more_files: usize,
    },
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

/// Why an instance's key is not known yet: an input it reads will be recomputed first.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Waiting {
    pub slot: String,
    /// The instance that provides it.
    pub input: String,
}

/// The most changed files a reason names.
const FILES_NAMED: usize = 5;

/// Why an action with `key` is not in the store, compared with the stage's last run (`last`);
/// `resumes` is what its operator resumes from when interrupted.
pub fn why(store: Option<&Store>, last: Option<&Digest>, key: &Digest, now: &Preimage, stage: &str, resumes: &str) -> anyhow::Result<Vec<RunReason>> {
    let (Some(store), Some(last)) = (store, last) else {
        return Ok(vec![RunReason::NeverRun]);
    };
    if last == key {
        if store.record(key)?.is_some() {
            return Ok(vec![RunReason::OutputGone]);
        }
        if store.try_lock_action(key)?.is_none() {
            return Ok(vec![RunReason::Running]);
        }
        let failure = store.failure(key).map(|f| f.lines().next().unwrap_or_default().chars().take(200).collect::<String>());
        // A checkpoint folder an attempt made but wrote nothing into is nothing to resume from.
        let kept = std::fs::read_dir(store.checkpoint_dir(key)).is_ok_and(|mut d| d.next().is_some());
        let checkpoint = kept.then(|| resumes.to_owned());
        return Ok(vec![match (failure, checkpoint) {
            (Some(error), resumes_from) => RunReason::Failed { error, resumes_from },
            (None, Some(resumes_from)) => RunReason::Interrupted { resumes_from },
            (None, None) => RunReason::Unfinished,
        }]);
    }
    let Some(before) = previous_preimage(store, last)? else {
        return Ok(vec![RunReason::RecordCollected]);
    };
    let changes = now.diff(&before);
    if changes.is_empty() {
        return Ok(vec![RunReason::KeyChanged]);
    }
    Ok(changes
        .into_iter()
        .map(|change| {
            let files = changed_files(store, &change, now, &before);
            let more_files = files.len().saturating_sub(FILES_NAMED);
            RunReason::Changed { stage: stage.to_owned(), change, files: files.into_iter().take(FILES_NAMED).collect(), more_files }
        })
        .collect())
}

/// The preimage of an earlier action: from its record, or from its request if it never finished.
pub fn previous_preimage(store: &Store, key: &Digest) -> anyhow::Result<Option<Preimage>> {
    Ok(match store.record(key)? {
        Some(r) => Some(r.preimage),
        None => store.request(key)?.map(|r| r.preimage),
    })
}

/// For a changed input that is a tracked path: the files that differ, from the manifests the
/// store keeps; empty otherwise.
fn changed_files(store: &Store, change: &Change, now: &Preimage, before: &Preimage) -> Vec<String> {
    let Change::InputChanged { slot, label } = change else { return Vec::new() };
    let digest = |p: &Preimage| p.inputs.iter().find(|i| &i.slot == slot && &i.label == label).map(|i| i.digest);
    let (Some(new), Some(old)) = (digest(now), digest(before)) else { return Vec::new() };
    rlmflow_cache::external::changed_files(store, &old, &new).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_interrupted_or_failed_action_says_which_and_what_it_resumes_from() {
        let root = std::env::temp_dir().join(format!("rlmflow-why-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let store = Store::open(&root).unwrap();
        let preimage =
            Preimage { operator: "llm".into(), operator_version: 1, config: serde_json::json!({}), seed: 0, inputs: vec![], platform: None };
        let key = preimage.key();
        let reasons = |resumes: &str| why(Some(&store), Some(&key), &key, &preimage, "captions", resumes).unwrap();
        assert_eq!(reasons("its checkpoint"), [RunReason::Unfinished]);
        // Being computed by another holder of its lock: running, not interrupted.
        let held = store.lock_action(&key).unwrap();
        assert_eq!(reasons("its checkpoint"), [RunReason::Running]);
        drop(held);
        // An empty checkpoint folder holds nothing to resume from.
        std::fs::create_dir_all(store.checkpoint_dir(&key)).unwrap();
        assert_eq!(reasons("its checkpoint"), [RunReason::Unfinished]);
        std::fs::write(store.checkpoint_dir(&key).join("epoch-3.safetensors"), b"weights").unwrap();
        let cache = "its response cache (the answers it already has)";
        assert_eq!(reasons(cache), [RunReason::Interrupted { resumes_from: cache.into() }]);
        store.write_failure(&key, "batch: larger than the training share\n(details)").unwrap();
        let error = "batch: larger than the training share".to_owned();
        assert_eq!(reasons("its checkpoint"), [RunReason::Failed { error: error.clone(), resumes_from: Some("its checkpoint".into()) }]);
        std::fs::remove_dir_all(store.checkpoint_dir(&key)).unwrap();
        assert_eq!(reasons("its checkpoint"), [RunReason::Failed { error, resumes_from: None }]);
        std::fs::remove_dir_all(&root).unwrap();
    }
}
