//! Garbage collection: mark from roots, sweep the rest.
//!
//! Roots are the keys named in `refs/` (the latest key of every stage instance of every
//! pipeline, and pins) and in the plans of the newest `keep_runs` runs. A live key keeps its
//! record, request and checkpoint, its output object and its input objects. Links outside the
//! store (`results/`) are no roots and are never followed; one whose object was collected is
//! pointed at a note saying so (`links.rs`).

use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};

use crate::digest::Digest;
use crate::links::Gone;
use crate::store::{RESPONSES, Store, now_rfc3339, read_dir_sorted, remove_tree};

/// What `gc` removed (or would remove, with `dry_run`).
#[derive(Debug, Default)]
pub struct GcReport {
    /// (what, path, bytes)
    pub removed: Vec<(&'static str, PathBuf, u64)>,
    pub kept_objects: usize,
}

impl GcReport {
    pub fn bytes(&self) -> u64 {
        self.removed.iter().map(|r| r.2).sum()
    }
}

impl Store {
    /// Sweeps what no root reaches, and with `responses` the stored answers of outside services
    /// too (a stage that needs one asks again). Takes the store lock exclusively, so it waits for
    /// runs.
    pub fn gc(&self, keep_runs: usize, dry_run: bool, responses: bool) -> anyhow::Result<GcReport> {
        let _lock = self.lock_exclusive()?;
        let runs = self.runs()?;
        let (old_runs, kept_runs) = runs.split_at(runs.len().saturating_sub(keep_runs));

        let mut live_keys: BTreeSet<Digest> = BTreeSet::new();
        live_keys.extend(self.ref_keys()?);
        for run in kept_runs {
            if let Some(plan) = self.plan(run)? {
                live_keys.extend(plan.instances.iter().filter_map(|i| i.key));
            }
        }
        let mut live_objects: BTreeSet<Digest> = BTreeSet::new();
        for key in &live_keys {
            let preimage = match self.record(key)? {
                Some(record) => {
                    live_objects.insert(record.output);
                    Some(record.preimage)
                }
                None => self.request(key)?.map(|r| r.preimage),
            };
            live_objects.extend(preimage.iter().flat_map(|p| p.inputs.iter().map(|i| i.digest)));
        }

        let mut removed = Vec::new();
        let mut remove = |what: &'static str, path: PathBuf| -> anyhow::Result<()> {
            let bytes = size_of(&path);
            if !dry_run {
                if path.is_dir() { remove_tree(&path)? } else { fs::remove_file(&path)? }
            }
            removed.push((what, path, bytes));
            Ok(())
        };
        for run in old_runs {
            remove("run", self.run_dir(run))?;
        }
        let mut dead_keys: BTreeSet<Digest> = self.record_keys()?.into_iter().collect();
        dead_keys.extend(self.request_keys()?);
        dead_keys.retain(|k| !live_keys.contains(k));
        for key in &dead_keys {
            for (what, path) in [("action", self.record_path(key)), ("request", self.request_path(key))] {
                if path.exists() {
                    remove(what, path)?;
                }
            }
        }
        let mut kept_objects = 0;
        let mut collected = Vec::new();
        for digest in self.objects()? {
            if live_objects.contains(&digest) {
                kept_objects += 1;
            } else {
                remove("object", self.object_dir(&digest))?;
                remove("object manifest", self.manifest_path(&digest))?;
                collected.push(digest);
            }
        }
        for dir in read_dir_sorted(&self.root().join("checkpoints"))? {
            let key = dir.file_name().and_then(|n| n.to_str()).and_then(|n| n.parse::<Digest>().ok());
            if !key.is_some_and(|k| live_keys.contains(&k)) {
                remove("checkpoint", dir)?;
            }
        }
        for entry in read_dir_sorted(&self.root().join("quarantine"))? {
            remove("quarantined", entry)?;
        }
        for note in read_dir_sorted(&self.root().join("failures"))? {
            let key = note.file_stem().and_then(|n| n.to_str()).and_then(|n| n.parse::<Digest>().ok());
            if !key.is_some_and(|k| live_keys.contains(&k)) {
                remove("failure note", note)?;
            }
        }
        for entry in read_dir_sorted(&self.root().join("tmp"))? {
            remove("orphaned work dir", entry)?;
        }
        if responses {
            for entry in read_dir_sorted(&self.root().join(RESPONSES))? {
                remove("responses", entry)?;
            }
        }
        for entry in read_dir_sorted(&self.root().join("locks"))? {
            if entry.file_name().is_some_and(|n| n != "store.lock") {
                remove("lock file", entry)?;
            }
        }
        if !dry_run {
            self.note_gone(&collected, Gone::Collected, &now_rfc3339())?;
        }
        Ok(GcReport { removed, kept_objects })
    }
}

fn size_of(path: &Path) -> u64 {
    match fs::symlink_metadata(path) {
        Ok(m) if m.is_dir() => fs::read_dir(path).map(|rd| rd.flatten().map(|e| size_of(&e.path())).sum()).unwrap_or(0),
        Ok(m) => m.len(),
        Err(_) => 0,
    }
}

#[cfg(test)]
mod tests {

    use super::*;
    use crate::store::tests::record_for;
    use crate::tree::tests::tempdir;

    #[test]
    fn gc_keeps_what_refs_reach_and_sweeps_the_rest() {
        let store = Store::open(&tempdir("gc")).unwrap();
        let kept = record_for(&store, 1, b"kept");
        let dropped = record_for(&store, 2, b"dropped");
        let s = crate::InstanceRef { stage: "s".into(), ..Default::default() };
        store.update_last_keys("p", &[(s, "s", kept.key)]).unwrap();

        let dry = store.gc(10, true, false).unwrap();
        assert!(dry.removed.iter().any(|r| r.0 == "object"));
        assert!(store.fresh(&dropped.key).unwrap().is_some(), "dry run removes nothing");

        let report = store.gc(10, false, false).unwrap();
        assert_eq!(report.kept_objects, 1);
        assert!(store.fresh(&kept.key).unwrap().is_some());
        assert!(store.record(&dropped.key).unwrap().is_none());
        assert!(!store.has_object(&dropped.output));
    }
}
