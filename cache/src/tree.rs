//! Content digests of artifact directories.

use std::fs;
use std::io;
use std::os::unix::fs::PermissionsExt;
use std::path::Path;

use anyhow::{Context, bail};

use crate::digest::Digest;

/// The digest of an artifact directory and its manifest.
#[derive(Clone, Debug)]
pub struct TreeInfo {
    pub digest: Digest,
    pub files: u64,
    pub bytes: u64,
    /// One line per file, sorted by path: `<blake3> <size> <x|-> <path>`. The tree digest is the
    /// BLAKE3 of this text, so a manifest on disk can be checked against its name.
    pub manifest: String,
}

const MANIFEST_HEADER: &str = "rlmflow-tree 1\n";

/// BLAKE3 of a file's contents (memory-mapped when large).
pub fn hash_file(path: &Path) -> io::Result<Digest> {
    let mut hasher = blake3::Hasher::new();
    hasher.update_mmap(path)?;
    Ok(hasher.finalize().into())
}

/// Hashes every regular file below `root`. Symbolic links and non-UTF-8 names are errors: an
/// artifact must mean the same bytes on every machine.
pub fn hash_tree(root: &Path) -> anyhow::Result<TreeInfo> {
    let files = list_files(root, usize::MAX)?;
    let mut entries = Vec::with_capacity(files.len());
    for rel in files {
        let path = root.join(&rel);
        let meta = fs::metadata(&path)?;
        let digest = hash_file(&path).with_context(|| format!("hashing {}", path.display()))?;
        entries.push(Entry { rel, digest, size: meta.len(), exec: is_exec(&meta) });
    }
    Ok(tree_info(&entries))
}

/// One file of a tree, as its manifest line records it.
pub(crate) struct Entry {
    pub rel: String,
    pub digest: Digest,
    pub size: u64,
    pub exec: bool,
}

pub(crate) fn is_exec(meta: &fs::Metadata) -> bool {
    meta.permissions().mode() & 0o111 != 0
}

/// The manifest and digest of a tree's files, sorted by path.
pub(crate) fn tree_info(entries: &[Entry]) -> TreeInfo {
    let mut manifest = String::from(MANIFEST_HEADER);
    for e in entries {
        manifest.push_str(&format!("{} {} {} {}\n", e.digest, e.size, if e.exec { 'x' } else { '-' }, e.rel));
    }
    TreeInfo { digest: Digest::of(manifest.as_bytes()), files: entries.len() as u64, bytes: entries.iter().map(|e| e.size).sum(), manifest }
}

/// Every regular file below `root`, relative, sorted; an error naming the first entry that is
/// anything else (a symbolic link could point outside the tree, a FIFO never end), or the first
/// file past `max`.
pub(crate) fn list_files(root: &Path, max: usize) -> anyhow::Result<Vec<String>> {
    use std::os::unix::fs::FileTypeExt;
    let mut files = Vec::new();
    // Directories still to read, relative to `root` (a loop, not recursion: depth is the disk's).
    let mut pending = vec![String::new()];
    while let Some(prefix) = pending.pop() {
        let dir = root.join(&prefix);
        for entry in fs::read_dir(&dir).with_context(|| format!("reading {}", dir.display()))? {
            let entry = entry.with_context(|| format!("reading {}", dir.display()))?;
            let name = entry.file_name();
            let Some(name) = name.to_str() else {
                bail!("{}: file names in artifacts must be UTF-8", entry.path().display());
            };
            if name.contains('\n') {
                bail!("{}: file names in artifacts cannot contain newlines", entry.path().display());
            }
            let rel = if prefix.is_empty() { name.to_owned() } else { format!("{prefix}/{name}") };
            let kind = entry.file_type().with_context(|| format!("reading {}", entry.path().display()))?;
            let special = match kind {
                k if k.is_dir() => {
                    pending.push(rel);
                    continue;
                }
                k if k.is_file() => {
                    if files.len() == max {
                        bail!(
                            "{}: more than {max} files below {} (this one is past the limit); a tree holds at most {max}",
                            entry.path().display(),
                            root.display()
                        );
                    }
                    files.push(rel);
                    continue;
                }
                k if k.is_symlink() => "a symbolic link",
                k if k.is_fifo() => "a FIFO",
                k if k.is_socket() => "a socket",
                _ => "a device",
            };
            bail!("{}: {special}; a tree may hold only regular files and directories", entry.path().display());
        }
    }
    files.sort();
    Ok(files)
}

/// Files of `actual` whose content differs from `expected` (both manifests), or that are
/// missing or extra.
pub fn differing_files(actual: &str, expected: &str) -> Vec<String> {
    let lines = |m: &str| -> Vec<(String, String)> {
        m.lines().skip(1).filter_map(|l| l.splitn(4, ' ').nth(3).map(|p| (p.to_owned(), l.to_owned()))).collect()
    };
    let expected = lines(expected);
    let found = lines(actual);
    let mut damaged: Vec<String> = expected.iter().filter(|e| !found.contains(e)).map(|e| e.0.clone()).collect();
    damaged.extend(found.iter().filter(|f| !expected.iter().any(|e| e.0 == f.0)).map(|f| f.0.clone()));
    damaged.sort();
    damaged.dedup();
    damaged
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn tree_digest_depends_on_content_and_names_only() {
        let a = tempdir("tree-a");
        let b = tempdir("tree-b");
        for d in [&a, &b] {
            fs::create_dir_all(d.join("sub")).unwrap();
            fs::write(d.join("sub/x.bin"), b"hello").unwrap();
            fs::write(d.join("y.json"), b"{}").unwrap();
        }
        let (ta, tb) = (hash_tree(&a).unwrap(), hash_tree(&b).unwrap());
        assert_eq!(ta.digest, tb.digest);
        assert_eq!((ta.files, ta.bytes), (2, 7));
        fs::write(b.join("y.json"), b"{ }").unwrap();
        assert_ne!(hash_tree(&b).unwrap().digest, ta.digest);
        assert_eq!(differing_files(&hash_tree(&b).unwrap().manifest, &ta.manifest), ["y.json"]);
        fs::write(b.join("extra"), b"").unwrap();
        assert_eq!(differing_files(&hash_tree(&b).unwrap().manifest, &ta.manifest), ["extra", "y.json"]);
    }

    #[test]
    fn symlinks_are_rejected() {
        let a = tempdir("tree-link");
        std::os::unix::fs::symlink("/etc/passwd", a.join("l")).unwrap();
        let err = hash_tree(&a).unwrap_err().to_string();
        assert!(err.contains("only regular files"), "{err}");
    }

    pub(crate) fn tempdir(name: &str) -> std::path::PathBuf {
        let d = std::env::temp_dir().join(format!("rlmflow-cache-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        fs::create_dir_all(&d).unwrap();
        d
    }
}
