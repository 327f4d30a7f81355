//! `verify` and quarantine: re-hashing what the store holds and moving what is damaged out of
//! the way, so a damaged object or record is a miss and never served.

use std::fs;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde_json::Value;

use crate::digest::Digest;
use crate::links::Gone;
use crate::store::{ActionRecord, ActionRequest, RESPONSES, Read, RunPlan, Store, now_rfc3339, read_dir_sorted, read_json_checked, run_id};
use crate::tree::{differing_files, hash_tree};

/// An object whose files no longer match their digest.
#[derive(Clone, Debug)]
pub struct Corruption {
    pub digest: Digest,
    pub files: Vec<String>,
}

/// A store file that `verify` found unusable and quarantined.
#[derive(Clone, Debug)]
pub struct DamagedFile {
    pub path: PathBuf,
    pub problem: String,
    pub quarantined: PathBuf,
}

/// What `verify` found: damaged objects, and damaged records, requests, plans and refs.
#[derive(Clone, Debug, Default)]
pub struct VerifyReport {
    pub objects: Vec<Corruption>,
    pub files: Vec<DamagedFile>,
    /// Records (key, output) whose output was among the damaged objects: each is now a miss,
    /// and its action reruns when a pipeline needs it.
    pub records_without_output: Vec<(Digest, Digest)>,
}

impl VerifyReport {
    pub fn is_clean(&self) -> bool {
        self.objects.is_empty() && self.files.is_empty()
    }
}

impl Store {
    /// Re-hashes one object. `Ok(None)` when it matches its digest.
    pub fn check_object(&self, digest: &Digest) -> anyhow::Result<Option<Corruption>> {
        if !self.object_dir(digest).is_dir() {
            return Ok(Some(Corruption { digest: *digest, files: vec!["the object's directory is missing".into()] }));
        }
        let manifest = fs::read_to_string(self.manifest_path(digest)).with_context(|| format!("object {} has no manifest", digest.short()))?;
        let actual = hash_tree(&self.object_dir(digest))?;
        if actual.digest == *digest && Digest::of(manifest.as_bytes()) == *digest {
            return Ok(None);
        }
        let files = differing_files(&actual.manifest, &manifest);
        Ok(Some(Corruption { digest: *digest, files }))
    }

    /// Moves a damaged object out of `objects/`, so every record naming it becomes a miss, and
    /// points the results links that named it at a note saying so.
    pub fn quarantine(&self, digest: &Digest) -> anyhow::Result<PathBuf> {
        let dest = self.root().join("quarantine").join(format!("{}-{}", digest.hex(), run_id()));
        fs::create_dir_all(&dest)?;
        for (from, name) in [(self.object_dir(digest), "data"), (self.manifest_path(digest), "manifest")] {
            if from.exists() {
                fs::rename(&from, dest.join(name))?;
            }
        }
        self.note_gone(&[*digest], Gone::Damaged, &now_rfc3339())?;
        Ok(dest)
    }

    /// Re-hashes every object and reads every record, request, plan and ref. Whatever is damaged
    /// is moved to `quarantine/` and reported: a damaged object or record becomes a miss (its
    /// action reruns), a damaged ref or plan is absent (rewritten by the next run). Takes the
    /// store lock exclusively, so it waits for runs and never moves what one is writing.
    pub fn verify(&self, mut on_object: impl FnMut(&Digest)) -> anyhow::Result<VerifyReport> {
        let _lock = self.lock_exclusive()?;
        let mut report = VerifyReport::default();
        for digest in self.objects()? {
            on_object(&digest);
            if let Some(c) = self.check_object(&digest)? {
                self.quarantine(&digest)?;
                report.objects.push(c);
            }
        }
        for (path, problem) in self.unusable_files()? {
            let moved = self.quarantine_path(&path)?;
            report.files.push(DamagedFile { path, problem, quarantined: moved });
        }
        for key in self.record_keys()? {
            if let Ok(Some(record)) = self.record(&key)
                && report.objects.iter().any(|c| c.digest == record.output)
            {
                report.records_without_output.push((key, record.output));
            }
        }
        Ok(report)
    }

    /// Store files that cannot be used as they are: unreadable JSON, a record or request not of
    /// its key, a stored answer that is no answer, an object directory without its manifest (an
    /// interrupted commit) or a manifest without its directory.
    fn unusable_files(&self) -> anyhow::Result<Vec<(PathBuf, String)>> {
        let mut found = Vec::new();
        // Each file read, then checked against what its name promises.
        let mut check = |path: PathBuf, read: Read<Result<(), String>>| match read {
            Read::Damaged(why) => found.push((path, format!("unreadable: {why}"))),
            Read::Intact(Err(problem)) => found.push((path, problem)),
            Read::Intact(Ok(())) | Read::Absent => {}
        };
        let of_key = |key: Digest, inner: Digest| if inner == key { Ok(()) } else { Err(format!("holds key {inner}, not its own")) };
        for key in self.record_keys()? {
            let path = self.record_path(&key);
            let read = read_json_checked::<ActionRecord>(&path)?;
            check(path, map_read(read, |r| of_key(key, r.key).and_then(|()| of_key(key, r.preimage.key()))));
        }
        for key in self.request_keys()? {
            let path = self.request_path(&key);
            let read = read_json_checked::<ActionRequest>(&path)?;
            check(path, map_read(read, |r| of_key(key, r.key).and_then(|()| of_key(key, r.preimage.key()))));
        }
        for path in self.ref_files()? {
            let read = read_json_checked::<crate::refs::Refs>(&path)?;
            check(path, map_read(read, |_| Ok(())));
        }
        for run in self.runs()? {
            let path = self.run_dir(&run).join("plan.json");
            let read = read_json_checked::<RunPlan>(&path)?;
            check(path, map_read(read, |_| Ok(())));
        }
        for operator in read_dir_sorted(&self.root().join(RESPONSES))? {
            for path in read_dir_sorted(&operator)? {
                let named = path.file_stem().and_then(|s| s.to_str()).is_some_and(|s| s.parse::<Digest>().is_ok());
                if !named || path.extension().is_none_or(|e| e != "json") {
                    check(path, Read::Intact(Err("not a stored answer (`<request digest>.json`)".into())));
                    continue;
                }
                let read = read_json_checked::<Value>(&path)?;
                check(path, map_read(read, |_| Ok(())));
            }
        }
        for shard in read_dir_sorted(&self.root().join("objects"))? {
            for entry in read_dir_sorted(&shard)? {
                let name = entry.file_name().unwrap().to_string_lossy().into_owned();
                match name.strip_suffix(".tree") {
                    Some(hex) if !shard.join(hex).is_dir() => found.push((entry, "an object manifest without its directory".into())),
                    None if entry.is_dir() && !shard.join(format!("{name}.tree")).is_file() => {
                        found.push((entry, "an object directory without its manifest (an interrupted commit; never served)".into()))
                    }
                    _ => {}
                }
            }
        }
        Ok(found)
    }

    /// Moves action `key`'s record to `quarantine/` (a record found untrustworthy); its action
    /// reruns when needed.
    pub fn quarantine_record(&self, key: &Digest) -> anyhow::Result<PathBuf> {
        self.quarantine_path(&self.record_path(key))
    }

    /// Moves any store file or directory to `quarantine/`, keeping its name.
    fn quarantine_path(&self, path: &Path) -> anyhow::Result<PathBuf> {
        let name = path.file_name().map_or("unnamed".into(), |n| n.to_string_lossy().into_owned());
        let dest = self.root().join("quarantine").join(format!("{name}-{}", run_id()));
        fs::create_dir_all(dest.parent().unwrap())?;
        fs::rename(path, &dest).with_context(|| format!("quarantining {}", path.display()))?;
        Ok(dest)
    }
}

fn map_read<T, U>(read: Read<T>, f: impl FnOnce(T) -> U) -> Read<U> {
    match read {
        Read::Absent => Read::Absent,
        Read::Intact(v) => Read::Intact(f(v)),
        Read::Damaged(why) => Read::Damaged(why),
    }
}
