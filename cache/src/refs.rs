//! The store's refs: the key each instance of a pipeline had in its latest run
//! (`refs/pipelines/`), and keys pinned under a name (`refs/pins/`), both kept by `gc`. An
//! instance is named by what it is ([`InstanceRef`]), not by how its label renders.

use std::collections::BTreeMap;
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::digest::Digest;
use crate::instance::InstanceRef;
use crate::store::{Store, atomic_write, file_safe, read_dir_sorted};

/// Keys by instance: a pipeline's last keys, or a pin.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(from = "RefsFile", into = "RefsFile")]
pub struct Refs {
    pub instances: BTreeMap<InstanceRef, Digest>,
    /// Entries a ref written before instances were named as data holds by label: looked up by
    /// the label a run prints, and replaced by an instance's entry once a run names it.
    pub labels: BTreeMap<String, Digest>,
}

impl Refs {
    /// The key `instance` (printed as `label`) had.
    pub fn get(&self, instance: &InstanceRef, label: &str) -> Option<Digest> {
        self.instances.get(instance).or_else(|| self.labels.get(label)).copied()
    }

    /// Every key held.
    pub fn keys(&self) -> impl Iterator<Item = Digest> + '_ {
        self.instances.values().chain(self.labels.values()).copied()
    }

    pub fn len(&self) -> usize {
        self.instances.len() + self.labels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// A ref file: entries by instance; a file from before that is an object of labels.
#[derive(Serialize, Deserialize)]
#[serde(untagged)]
enum RefsFile {
    Entries {
        instances: Vec<Entry>,
        #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
        labels: BTreeMap<String, Digest>,
    },
    Labels(BTreeMap<String, Digest>),
}

#[derive(Serialize, Deserialize)]
struct Entry {
    #[serde(flatten)]
    instance: InstanceRef,
    key: Digest,
}

impl From<RefsFile> for Refs {
    fn from(file: RefsFile) -> Refs {
        match file {
            RefsFile::Entries { instances, labels } => Refs { instances: instances.into_iter().map(|e| (e.instance, e.key)).collect(), labels },
            RefsFile::Labels(labels) => Refs { instances: BTreeMap::new(), labels },
        }
    }
}

impl From<Refs> for RefsFile {
    fn from(refs: Refs) -> RefsFile {
        let instances = refs.instances.into_iter().map(|(instance, key)| Entry { instance, key }).collect();
        RefsFile::Entries { instances, labels: refs.labels }
    }
}

impl Store {
    fn pipeline_ref(&self, pipeline: &str) -> PathBuf {
        self.root().join("refs/pipelines").join(format!("{}.json", file_safe(pipeline)))
    }

    /// The key each stage instance of `pipeline` had in its latest run.
    pub fn last_keys(&self, pipeline: &str) -> anyhow::Result<Refs> {
        Ok(self.read_json(&self.pipeline_ref(pipeline))?.unwrap_or_default())
    }

    /// Records the keys a run resolved (each instance with the label it prints), keeping entries
    /// for instances it did not touch; an entry by label for one it names becomes its instance's.
    pub fn update_last_keys(&self, pipeline: &str, keys: &[(InstanceRef, &str, Digest)]) -> anyhow::Result<()> {
        let before = self.last_keys(pipeline)?;
        let mut all = before.clone();
        for (instance, label, key) in keys {
            all.labels.remove(*label);
            all.instances.insert(instance.clone(), *key);
        }
        // A rerun with the same keys (a no-op run) leaves the file as it is: no write, no sync.
        if all == before {
            return Ok(());
        }
        atomic_write(self, &self.pipeline_ref(pipeline), &serde_json::to_vec_pretty(&all)?)
    }

    /// Pins keys under a name, so `gc` keeps them and everything they used.
    pub fn pin(&self, name: &str, keys: &Refs) -> anyhow::Result<PathBuf> {
        let path = self.root().join("refs/pins").join(format!("{}.json", file_safe(name)));
        atomic_write(self, &path, &serde_json::to_vec_pretty(keys)?)?;
        Ok(path)
    }

    pub(crate) fn ref_files(&self) -> anyhow::Result<Vec<PathBuf>> {
        let mut files = read_dir_sorted(&self.root().join("refs/pipelines"))?;
        files.extend(read_dir_sorted(&self.root().join("refs/pins"))?);
        Ok(files)
    }

    /// Every key a ref holds: what `gc` keeps.
    pub(crate) fn ref_keys(&self) -> anyhow::Result<Vec<Digest>> {
        let mut keys = Vec::new();
        for file in self.ref_files()? {
            keys.extend(self.read_json::<Refs>(&file)?.iter().flat_map(Refs::keys));
        }
        Ok(keys)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn instance(stage: &str, variants: &[(&str, &str)], seed: Option<u64>) -> InstanceRef {
        InstanceRef { stage: stage.into(), variants: variants.iter().map(|(d, v)| (d.to_string(), v.to_string())).collect(), seed, shard: None }
    }

    #[test]
    fn last_keys_are_kept_by_instance_and_a_ref_by_label_is_read_and_taken_over() {
        let root = std::env::temp_dir().join(format!("rlmflow-refs-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let store = Store::open(&root).unwrap();
        let (a, b, c) = (Digest([1; 32]), Digest([2; 32]), Digest([3; 32]));
        // A ref as a store written before instances were data holds it: labels to keys.
        let old = serde_json::json!({"pretrain[alpha4,seed=2]": a, "scenes": b});
        std::fs::write(store.pipeline_ref("paper"), serde_json::to_vec(&old).unwrap()).unwrap();
        let pretrain = instance("pretrain", &[("pretrain", "alpha4")], Some(2));
        let scenes = instance("scenes", &[], None);
        let refs = store.last_keys("paper").unwrap();
        assert_eq!((refs.get(&pretrain, "pretrain[alpha4,seed=2]"), refs.get(&scenes, "scenes")), (Some(a), Some(b)));
        assert_eq!(store.ref_keys().unwrap(), [a, b]);

        // A run that names the pretrain instance keeps it by instance; the other stays by label.
        store.update_last_keys("paper", &[(pretrain.clone(), "pretrain[alpha4,seed=2]", c)]).unwrap();
        let refs = store.last_keys("paper").unwrap();
        assert_eq!(refs.instances, BTreeMap::from([(pretrain.clone(), c)]));
        assert_eq!(refs.labels, BTreeMap::from([("scenes".to_owned(), b)]));
        // Found by what it is, whatever a label would print.
        assert_eq!(refs.get(&pretrain, "another rendering"), Some(c));
        let written: serde_json::Value = serde_json::from_slice(&std::fs::read(store.pipeline_ref("paper")).unwrap()).unwrap();
        assert_eq!(written["instances"][0], serde_json::json!({"stage": "pretrain", "assignment": {"pretrain": "alpha4"}, "seed": 2, "key": c}));

        // A pin holds instances the same way, and gc's keys include it.
        let pinned = Refs { instances: BTreeMap::from([(scenes, b)]), labels: BTreeMap::new() };
        store.pin("paper-v1", &pinned).unwrap();
        let mut keys = store.ref_keys().unwrap();
        keys.sort();
        assert_eq!(keys, [b, b, c]);
        std::fs::remove_dir_all(&root).unwrap();
    }
}
