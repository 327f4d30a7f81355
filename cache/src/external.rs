//! External inputs: files and directories outside the store that a stage reads (a researcher's
//! recordings), tracked by content.
//!
//! # Freshness of an external input
//!
//! An external input enters its action's key as an ordinary input: the digest of its tree (a
//! single file is a tree of one), computed exactly as an artifact's. Before the action runs,
//! the tree is copied into the store as an object of that digest (a *snapshot*), and the
//! operator reads the snapshot, never the original: a file edited during a run cannot change
//! what the run computed, and a cluster worker or remote cache receives it like any artifact.
//!
//! Hashing a large dataset on every `status` would be slow, so each file's digest is kept with
//! the size and modification time it had when it was hashed (`external/sources/`, one record
//! per source path). A file whose size and modification time are unchanged keeps its recorded
//! digest, so an unchanged tree costs one `stat` per file; any other file is hashed again. As in
//! git's "racy" rule, a file modified within [`RACY`] of its hashing is always hashed again,
//! since a coarse clock could give an edit made right after the hashing the same time. Touching
//! a file without changing it re-hashes that file and leaves the digest, and the key, as they
//! were. Every tree's manifest is kept (`external/manifests/`), so `status` and `explain` can
//! name the files that changed between two runs.

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use anyhow::{Context as _, bail};
use serde::{Deserialize, Serialize};

use crate::store::atomic_write;
use crate::tree::{Entry, is_exec, list_files, tree_info};
use crate::{Digest, Store, TreeInfo, differing_files, hash_file};

/// A file modified this close to its hashing is hashed again next time.
pub const RACY: Duration = Duration::from_secs(2);

/// The most files a tracked directory may hold: a recording is large, but a setting that names
/// `/` or `/tmp` by mistake fails after this many rather than walking the disk.
pub const MAX_FILES: usize = 1_000_000;

/// What a tracked setting names: a file or a directory (a tree of one file, or every file below
/// it), or chosen files below a directory (a script's sources), each by its path relative to
/// `root`, in order and without repeats.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Source {
    Path(PathBuf),
    Files { root: PathBuf, files: Vec<String> },
}

impl Source {
    /// The directory the tree's paths are relative to, and the paths.
    fn tree(&self) -> anyhow::Result<(PathBuf, Vec<String>)> {
        let source = match self {
            Source::Files { root, files } => return Ok((root.clone(), files.clone())),
            Source::Path(path) => path,
        };
        let meta = fs::metadata(source).with_context(|| format!("reading {}", source.display()))?;
        if meta.is_dir() {
            Ok((source.to_path_buf(), list_files(source, MAX_FILES)?))
        } else if meta.is_file() {
            let name = source.file_name().and_then(|n| n.to_str()).with_context(|| format!("{}: the file name must be UTF-8", source.display()))?;
            Ok((source.parent().unwrap_or(Path::new(".")).to_path_buf(), vec![name.to_owned()]))
        } else {
            bail!("{} is neither a file nor a directory", source.display());
        }
    }

    /// Where the digests of its files are recorded: one record per source.
    fn record_name(&self) -> String {
        let described = match self {
            Source::Path(path) => path.to_string_lossy().into_owned(),
            Source::Files { root, files } => format!("{}\0{}", root.display(), files.join("\0")),
        };
        format!("{}.json", Digest::of(described.as_bytes()).hex())
    }
}

impl std::fmt::Display for Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Source::Path(path) => write!(f, "{}", path.display()),
            Source::Files { root, files } => write!(f, "{} files of {}", files.len(), root.display()),
        }
    }
}

/// What was recorded of one source's files the last time they were hashed.
#[derive(Default, Serialize, Deserialize)]
struct Recorded {
    source: PathBuf,
    files: BTreeMap<String, Seen>,
}

#[derive(Clone, Serialize, Deserialize)]
struct Seen {
    size: u64,
    mtime_ns: u128,
    /// When it was hashed.
    hashed_ns: u128,
    exec: bool,
    digest: Digest,
}

/// The content digest and manifest of `source`, re-hashing only the files whose size or
/// modification time changed since `store` last hashed them. Without a store (nothing has run
/// yet) every file is hashed.
pub fn fingerprint(store: Option<&Store>, source: &Source) -> anyhow::Result<TreeInfo> {
    let (root, files) = source.tree()?;
    let record_path = store.map(|s| s.root().join("external/sources").join(source.record_name()));
    let before: Recorded = record_path.as_ref().and_then(|p| fs::read(p).ok()).and_then(|b| serde_json::from_slice(&b).ok()).unwrap_or_default();
    let mut now = Recorded { source: root.clone(), files: BTreeMap::new() };
    let mut entries = Vec::with_capacity(files.len());
    for rel in files {
        let path = root.join(&rel);
        let meta = fs::metadata(&path).with_context(|| format!("reading {}", path.display()))?;
        let mtime_ns = nanos(meta.modified()?);
        let exec = is_exec(&meta);
        let kept = before
            .files
            .get(&rel)
            .filter(|s| s.size == meta.len() && s.mtime_ns == mtime_ns && s.exec == exec && s.hashed_ns > mtime_ns + RACY.as_nanos());
        let seen = match kept {
            Some(seen) => seen.clone(),
            None => {
                let hashed_ns = nanos(SystemTime::now());
                let digest = hash_file(&path).with_context(|| format!("hashing {}", path.display()))?;
                Seen { size: meta.len(), mtime_ns, hashed_ns, exec, digest }
            }
        };
        entries.push(Entry { rel: rel.clone(), digest: seen.digest, size: seen.size, exec });
        now.files.insert(rel, seen);
    }
    let info = tree_info(&entries);
    if let (Some(store), Some(record_path)) = (store, record_path) {
        atomic_write(store, &record_path, &serde_json::to_vec(&now)?)?;
        let manifest = manifest_path(store, &info.digest);
        if !manifest.exists() {
            atomic_write(store, &manifest, info.manifest.as_bytes())?;
        }
    }
    Ok(info)
}

/// Copies `source` into `store` as the object `digest` unless the store has it. Fails, naming
/// the source, if its content is no longer that digest (it changed after it was fingerprinted).
pub fn snapshot(store: &Store, source: &Source, digest: &Digest) -> anyhow::Result<()> {
    if store.has_object(digest) {
        return Ok(());
    }
    let dir = store.work_dir(digest)?;
    let copied = source.tree().and_then(|(root, files)| copy_files(&root, &files, &dir));
    if let Err(e) = copied {
        let _ = fs::remove_dir_all(&dir);
        return Err(e);
    }
    let info = store.commit_tree(&dir)?;
    if info.digest != *digest {
        let changed = manifest(store, digest).map(|before| differing_files(&info.manifest, &before)).unwrap_or_default();
        bail!("{source} changed while this run was reading it ({}); run again", changed.join(", "));
    }
    Ok(())
}

/// The manifest of a tree this store fingerprinted, if it has it.
pub fn manifest(store: &Store, digest: &Digest) -> Option<String> {
    fs::read_to_string(manifest_path(store, digest)).ok()
}

/// The files that differ between two fingerprinted trees (changed, added or removed), if the
/// store fingerprinted both.
pub fn changed_files(store: &Store, before: &Digest, now: &Digest) -> Option<Vec<String>> {
    Some(differing_files(&manifest(store, now)?, &manifest(store, before)?))
}

fn manifest_path(store: &Store, digest: &Digest) -> PathBuf {
    store.root().join("external/manifests").join(digest.hex())
}

fn copy_files(from: &Path, files: &[String], to: &Path) -> anyhow::Result<()> {
    for rel in files {
        let target = to.join(rel);
        fs::create_dir_all(target.parent().expect("a file below the root"))?;
        fs::copy(from.join(rel), &target).with_context(|| format!("copying {}", from.join(rel).display()))?;
    }
    Ok(())
}

fn nanos(t: SystemTime) -> u128 {
    t.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tree::tests::tempdir;

    #[test]
    fn an_unchanged_tree_is_not_hashed_again_and_an_edit_is_seen() {
        let root = tempdir("external");
        let (data, store) = (root.join("data"), Store::open(&root.join("store")).unwrap());
        fs::create_dir_all(data.join("sub")).unwrap();
        fs::write(data.join("a.npy"), b"one").unwrap();
        fs::write(data.join("sub/b.npy"), b"two").unwrap();
        let source = Source::Path(data.clone());
        let first = fingerprint(Some(&store), &source).unwrap();
        assert_eq!(first.digest, crate::hash_tree(&data).unwrap().digest, "the digest an artifact of these files would have");
        // Pretend the files were hashed long after they were written: their digests are kept.
        let record = store.root().join("external/sources").join(format!("{}.json", Digest::of(data.to_string_lossy().as_bytes()).hex()));
        let mut recorded: Recorded = serde_json::from_slice(&fs::read(&record).unwrap()).unwrap();
        for seen in recorded.files.values_mut() {
            seen.hashed_ns = seen.mtime_ns + 10 * RACY.as_nanos();
            seen.digest = Digest::of(b"kept");
        }
        fs::write(&record, serde_json::to_vec(&recorded).unwrap()).unwrap();
        assert_ne!(fingerprint(Some(&store), &source).unwrap().digest, first.digest, "kept digests were used, nothing re-hashed");
        // An edit changes size or time: that file is hashed again, the other kept.
        fs::write(data.join("a.npy"), b"uno!").unwrap();
        let edited = fingerprint(Some(&store), &source).unwrap();
        assert!(edited.manifest.contains(&format!("{} 4 - a.npy", Digest::of(b"uno!"))), "{}", edited.manifest);
        assert!(edited.manifest.contains(&format!("{} 3 - sub/b.npy", Digest::of(b"kept"))), "{}", edited.manifest);
        // Hashed afresh, the edit is named against the first tree.
        fs::remove_file(&record).unwrap();
        let fresh = fingerprint(Some(&store), &source).unwrap();
        assert_eq!(changed_files(&store, &first.digest, &fresh.digest).unwrap(), ["a.npy"]);
        snapshot(&store, &source, &fresh.digest).unwrap();
        assert!(store.has_object(&fresh.digest));
        assert!(snapshot(&store, &source, &first.digest).unwrap_err().to_string().contains("changed while this run was reading it (a.npy)"));
    }

    #[test]
    fn a_file_is_a_tree_of_one() {
        let root = tempdir("external-file");
        fs::write(root.join("scenes.mcap"), b"mcap").unwrap();
        let store = Store::open(&root.join("store")).unwrap();
        let source = Source::Path(root.join("scenes.mcap"));
        let info = fingerprint(Some(&store), &source).unwrap();
        snapshot(&store, &source, &info.digest).unwrap();
        assert_eq!(fs::read(store.object_dir(&info.digest).join("scenes.mcap")).unwrap(), b"mcap");
    }

    #[test]
    fn chosen_files_are_a_tree_of_those_files_alone() {
        let root = tempdir("external-files");
        fs::create_dir_all(root.join("probes")).unwrap();
        fs::write(root.join("probes/knn.py"), b"print(1)").unwrap();
        fs::write(root.join("probes/notes.txt"), b"not a source").unwrap();
        fs::write(root.join("run.sh"), b"exit 0").unwrap();
        let store = Store::open(&root.join("store")).unwrap();
        let source = Source::Files { root: root.clone(), files: vec!["probes/knn.py".into(), "run.sh".into()] };
        let info = fingerprint(Some(&store), &source).unwrap();
        snapshot(&store, &source, &info.digest).unwrap();
        let object = store.object_dir(&info.digest);
        assert_eq!(list_files(&object, 10).unwrap(), ["probes/knn.py", "run.sh"]);
        // A file outside the choice changes nothing; a chosen one changes the digest.
        fs::write(root.join("probes/notes.txt"), b"edited").unwrap();
        assert_eq!(fingerprint(Some(&store), &source).unwrap().digest, info.digest);
        fs::write(root.join("probes/knn.py"), b"print(2)").unwrap();
        let edited = fingerprint(Some(&store), &source).unwrap();
        assert_eq!(changed_files(&store, &info.digest, &edited.digest).unwrap(), ["probes/knn.py"]);
    }
}
