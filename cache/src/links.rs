//! Links from a directory outside the store to what it holds: a pipeline's `results/`, one
//! symbolic link per stage instance to its current output, so a person finds the latest report
//! at a path that does not change.
//!
//! A link is replaced atomically (a new link renamed over the old one), so a reader sees the
//! old output or the new, never neither. The directory carries a marker file, and a directory
//! without it is written into only while empty: a setting that names someone's own directory
//! changes nothing in it. Only links are ever replaced or removed, never a file or a directory
//! that holds anything else. The store keeps the list of its link directories
//! (`refs/links.json`); `gc` and quarantine read the links there (never following them) and
//! point each one whose object they removed at a note saying why, rather than leaving it dangling.

use std::fs;
use std::io;
use std::path::{Component, Path, PathBuf};

use anyhow::{Context as _, bail};

use crate::digest::Digest;
use crate::store::{Store, atomic_write};

/// The file marking a directory as rlmflow's links.
const MARKER: &str = ".rlmflow-links";
/// Where the notes for objects no longer in the store live, inside the links directory.
const GONE: &str = ".gone";

/// Why an object a link pointed at left the store.
#[derive(Clone, Copy)]
pub(crate) enum Gone {
    /// `gc` collected it.
    Collected,
    /// Its files no longer hashed to its digest (found by `verify`, or by a run re-hashing
    /// an input or output), so it was quarantined.
    Damaged,
}

impl Gone {
    fn note_file(self) -> &'static str {
        match self {
            Gone::Collected => "COLLECTED.txt",
            Gone::Damaged => "DAMAGED.txt",
        }
    }

    fn note(self, digest: &Digest, when: &str) -> String {
        let what = match self {
            Gone::Collected => format!("was removed by `rlmflow gc` at {when}"),
            Gone::Damaged => {
                format!("was found damaged at {when} (its files no longer hash to its digest) and moved to the store's quarantine/")
            }
        };
        format!(
            "The output this link pointed at (object {digest}) {what}.\nRun the pipeline again to recompute it; the link then points at the new output.\n"
        )
    }
}

/// A directory of links into one store.
pub struct Links {
    dir: PathBuf,
    /// The store's `objects/`, canonical, as the links name it.
    objects: PathBuf,
}

impl Store {
    /// The links directory `dir`, created (and registered with this store, for `gc`) if need be.
    /// An existing directory is used only if it carries the marker or is empty.
    pub fn links(&self, dir: &Path) -> anyhow::Result<Links> {
        match fs::read_dir(dir) {
            Ok(mut entries) => {
                if !dir.join(MARKER).is_file() && entries.next().is_some() {
                    bail!(
                        "{} holds files rlmflow did not put there; name an empty or new directory for the results links (`[pipeline] results`), or \"\" for none",
                        dir.display()
                    );
                }
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(e).with_context(|| format!("reading {}", dir.display())),
        }
        fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let dir = dir.canonicalize()?;
        let marker = dir.join(MARKER);
        if !marker.is_file() {
            let text = "rlmflow's links to the current output of each stage instance; each run replaces them.\n";
            fs::write(&marker, text).with_context(|| format!("writing {}", marker.display()))?;
        }
        let mut registered = self.link_dirs()?;
        if !registered.contains(&dir) {
            registered.push(dir.clone());
            atomic_write(self, &self.link_dirs_file(), &serde_json::to_vec_pretty(&registered)?)?;
        }
        Ok(Links { dir, objects: self.root().canonicalize()?.join("objects") })
    }

    fn link_dirs_file(&self) -> PathBuf {
        self.root().join("refs/links.json")
    }

    /// The link directories runs have written into.
    pub(crate) fn link_dirs(&self) -> anyhow::Result<Vec<PathBuf>> {
        Ok(self.read_json(&self.link_dirs_file())?.unwrap_or_default())
    }

    /// Points every link of every registered directory whose target is among `gone` (objects
    /// just removed from the store) at a note saying why. Links are read, never followed.
    pub(crate) fn note_gone(&self, gone: &[Digest], why: Gone, when: &str) -> anyhow::Result<()> {
        if gone.is_empty() {
            return Ok(());
        }
        let objects = self.root().canonicalize()?.join("objects");
        let gone: std::collections::BTreeSet<&Digest> = gone.iter().collect();
        for dir in self.link_dirs()? {
            if !dir.join(MARKER).is_file() {
                continue;
            }
            let links = Links { dir, objects: objects.clone() };
            for link in links.all()? {
                let Ok(target) = fs::read_link(&link) else { continue };
                let target = normal(&link.parent().unwrap().join(target));
                let named = target.strip_prefix(&objects).ok().and_then(|rest| rest.file_name()?.to_str()?.parse::<Digest>().ok());
                let Some(digest) = named.filter(|d| gone.contains(d)) else { continue };
                let note = links.dir.join(GONE).join(digest.hex());
                fs::create_dir_all(&note)?;
                fs::write(note.join(why.note_file()), why.note(&digest, when))?;
                links.replace(&link, &note)?;
            }
        }
        Ok(())
    }
}

impl Links {
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Points `entry` (a relative path such as `pretrain/alpha4`) at `object`'s directory.
    pub fn point(&self, entry: &Path, object: &Digest) -> anyhow::Result<()> {
        self.point_at(entry, &self.objects.join(object.shard()).join(object.hex()))
    }

    /// Points `entry` at `target`, an absolute path (a running action's checkpoint directory).
    /// A link standing where a directory of links must go (or the other way round, when a stage
    /// gained or lost variants) is replaced; a file or a directory holding anything but links is
    /// an error naming it.
    pub fn point_at(&self, entry: &Path, target: &Path) -> anyhow::Result<()> {
        if entry.as_os_str().is_empty() || entry.components().any(|c| !matches!(c, Component::Normal(_))) || entry.starts_with(GONE) {
            bail!("results link `{}`: not a plain relative path", entry.display());
        }
        let link = self.dir.join(entry);
        let mut parent = self.dir.clone();
        for part in entry.parent().into_iter().flat_map(Path::components) {
            parent.push(part);
            match fs::symlink_metadata(&parent) {
                Ok(m) if m.file_type().is_symlink() => fs::remove_file(&parent)?,
                Ok(m) if m.is_dir() => continue,
                Ok(_) => bail!("{} is a file, where rlmflow keeps a directory of results links", parent.display()),
                Err(e) if e.kind() == io::ErrorKind::NotFound => {}
                Err(e) => return Err(e.into()),
            }
            fs::create_dir(&parent).with_context(|| format!("creating {}", parent.display()))?;
        }
        if let Ok(m) = fs::symlink_metadata(&link)
            && m.is_dir()
        {
            remove_links_only(&link)?;
        }
        self.replace(&link, target)
    }

    /// Renames a new link to `target` (relative to the link's directory) over `link`, unless it
    /// points there already (a run that reuses everything rewrites nothing).
    fn replace(&self, link: &Path, target: &Path) -> anyhow::Result<()> {
        let from = link.parent().unwrap();
        let relative = relative_path(&normal(from), &normal(target));
        if fs::read_link(link).is_ok_and(|current| current == relative) {
            return Ok(());
        }
        let tmp = from.join(format!(".{}.new-{}", link.file_name().unwrap().to_string_lossy(), std::process::id()));
        let _ = fs::remove_file(&tmp);
        std::os::unix::fs::symlink(&relative, &tmp).with_context(|| format!("linking {}", tmp.display()))?;
        fs::rename(&tmp, link).with_context(|| format!("replacing {}", link.display()))?;
        Ok(())
    }

    /// Every link under the directory (the notes' own directory aside), not following any.
    fn all(&self) -> anyhow::Result<Vec<PathBuf>> {
        let mut out = Vec::new();
        let mut stack = vec![self.dir.clone()];
        while let Some(dir) = stack.pop() {
            for entry in fs::read_dir(&dir)? {
                let entry = entry?;
                let kind = entry.file_type()?;
                if kind.is_symlink() {
                    out.push(entry.path());
                } else if kind.is_dir() && entry.file_name() != GONE {
                    stack.push(entry.path());
                }
            }
        }
        out.sort();
        Ok(out)
    }
}

/// Removes `dir` if it holds nothing but links and directories of links; an error naming it
/// otherwise, with nothing removed.
fn remove_links_only(dir: &Path) -> anyhow::Result<()> {
    fn only_links(dir: &Path) -> io::Result<bool> {
        for entry in fs::read_dir(dir)? {
            let entry = entry?;
            let kind = entry.file_type()?;
            if !(kind.is_symlink() || (kind.is_dir() && only_links(&entry.path())?)) {
                return Ok(false);
            }
        }
        Ok(true)
    }
    if !only_links(dir)? {
        bail!("{} holds files rlmflow did not put there, where a results link must go; move them away", dir.display());
    }
    fs::remove_dir_all(dir)?;
    Ok(())
}

/// `path` with `.` and `..` resolved lexically (the link directory and the store are
/// canonical already).
fn normal(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            c => out.push(c),
        }
    }
    out
}

/// The relative path from directory `from` to `to`, both absolute and normal.
fn relative_path(from: &Path, to: &Path) -> PathBuf {
    let (f, t): (Vec<_>, Vec<_>) = (from.components().collect(), to.components().collect());
    let common = f.iter().zip(&t).take_while(|(a, b)| a == b).count();
    let mut out: PathBuf = f[common..].iter().map(|_| Component::ParentDir).collect();
    out.extend(&t[common..]);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("rlmflow-links-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn relative_paths_climb_to_the_common_ancestor() {
        assert_eq!(
            relative_path(Path::new("/a/b/results/pretrain"), Path::new("/a/b/.rlmflow/objects/ab/cd")),
            PathBuf::from("../../.rlmflow/objects/ab/cd")
        );
        assert_eq!(relative_path(Path::new("/a"), Path::new("/a/b")), PathBuf::from("b"));
    }

    #[test]
    fn links_replace_links_and_never_anything_else() {
        let root = scratch("replace");
        let store = Store::open(&root.join("store")).unwrap();
        let links = store.links(&root.join("results")).unwrap();
        let (one, two) = (root.join("one"), root.join("two"));
        fs::create_dir_all(&one).unwrap();
        fs::create_dir_all(&two).unwrap();
        links.point_at(Path::new("pretrain"), &one).unwrap();
        assert_eq!(fs::canonicalize(root.join("results/pretrain")).unwrap(), one.canonicalize().unwrap());
        // Pointed where it points already, the link is left as it is (no new link renamed in).
        let inode = |p: &Path| std::os::unix::fs::MetadataExt::ino(&fs::symlink_metadata(p).unwrap());
        let before = inode(&root.join("results/pretrain"));
        links.point_at(Path::new("pretrain"), &one).unwrap();
        assert_eq!(inode(&root.join("results/pretrain")), before);
        // The stage gained variants: its link becomes a directory of links.
        links.point_at(Path::new("pretrain/alpha4"), &two).unwrap();
        assert_eq!(fs::canonicalize(root.join("results/pretrain/alpha4")).unwrap(), two.canonicalize().unwrap());
        // ... and lost them again.
        links.point_at(Path::new("pretrain"), &one).unwrap();
        assert!(fs::symlink_metadata(root.join("results/pretrain")).unwrap().file_type().is_symlink());
        // A file of the user's where a link must go is never removed.
        fs::create_dir_all(root.join("results/report")).unwrap();
        fs::write(root.join("results/report/notes.txt"), "mine").unwrap();
        let err = links.point_at(Path::new("report"), &one).unwrap_err().to_string();
        assert!(err.contains("results/report holds files rlmflow did not put there"), "{err}");
        assert_eq!(fs::read_to_string(root.join("results/report/notes.txt")).unwrap(), "mine");
        assert!(links.point_at(Path::new("../escape"), &one).is_err());
        // A directory that is not rlmflow's and not empty is left alone.
        fs::create_dir_all(root.join("mine")).unwrap();
        fs::write(root.join("mine/a.txt"), "a").unwrap();
        let err = store.links(&root.join("mine")).err().unwrap().to_string();
        assert!(err.contains("holds files rlmflow did not put there"), "{err}");
        assert_eq!(fs::read_dir(root.join("mine")).unwrap().count(), 1);
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn a_link_to_an_object_found_damaged_points_at_a_note_saying_so() {
        let root = scratch("damaged");
        let store = Store::open(&root.join("store")).unwrap();
        let record = crate::store::tests::record_for(&store, 1, b"payload");
        let links = store.links(&root.join("results")).unwrap();
        links.point(Path::new("report"), &record.output).unwrap();
        assert_eq!(fs::read_to_string(root.join("results/report/data.txt")).unwrap(), "payload");

        let file = store.object_dir(&record.output).join("data.txt");
        fs::set_permissions(&file, std::os::unix::fs::PermissionsExt::from_mode(0o644)).unwrap();
        fs::write(&file, b"pAyload").unwrap();
        assert_eq!(store.verify(|_| {}).unwrap().objects.len(), 1);
        let note = fs::read_to_string(root.join("results/report/DAMAGED.txt")).unwrap();
        let named = format!("(object {})", record.output);
        assert!(note.contains(&named) && note.contains("was found damaged") && note.contains("Run the pipeline again"), "{note}");
        fs::remove_dir_all(&root).unwrap();
    }
}
