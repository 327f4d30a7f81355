//! A scratch directory per test, in the build's target directory: removed when the test passes,
//! kept (and named on stderr) when it fails, for a look at what it left; `cargo clean` removes
//! what failed tests kept, and the system's temporary directory never sees them.

use std::path::{Path, PathBuf};

pub struct Scratch {
    dir: PathBuf,
}

impl Scratch {
    /// A fresh, empty `NAME-PID` under [`root`] (a leftover of the same name is removed first).
    pub fn new(name: &str) -> Scratch {
        let dir = root().join(format!("{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("creating {}: {e}", dir.display()));
        Scratch { dir }
    }

    /// A fresh scratch directory holding `p.toml` with `pipeline`.
    pub fn with_pipeline(name: &str, pipeline: &str) -> Scratch {
        let scratch = Scratch::new(name);
        scratch.write("p.toml", pipeline);
        scratch
    }

    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// Writes `text` to `name` inside, creating its parents.
    pub fn write(&self, name: &str, text: &str) -> PathBuf {
        let path = self.dir.join(name);
        std::fs::create_dir_all(path.parent().expect("inside the scratch directory")).unwrap();
        std::fs::write(&path, text).unwrap_or_else(|e| panic!("writing {}: {e}", path.display()));
        path
    }
}

/// Where scratch directories go: `tmp/scratch` in the target directory of the running test
/// binary (`<target>/<profile>/deps/<binary>`; `tmp` is cargo's `CARGO_TARGET_TMPDIR`), or the
/// system's temporary directory for a binary run from elsewhere.
pub fn root() -> PathBuf {
    let exe = std::env::current_exe().expect("the test binary's path");
    let target = exe.ancestors().find(|dir| dir.file_name() == Some("deps".as_ref())).and_then(|deps| deps.parent()?.parent());
    target.map_or_else(|| std::env::temp_dir().join("rlmflow-scratch"), |target| target.join("tmp/scratch"))
}

/// A directory the tests of one process share (a run several of them read): `name` under `root`,
/// the test binary's `CARGO_TARGET_TMPDIR`. Shared state lives in a static, which is never
/// dropped, so it cannot remove itself as a [`Scratch`] does: it replaces what the process before
/// left there instead, and stays inside the build's scratch space.
pub fn shared_dir(root: &Path, name: &str) -> PathBuf {
    let dir = root.join(name);
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("creating {}: {e}", dir.display()));
    dir
}

impl std::ops::Deref for Scratch {
    type Target = Path;

    fn deref(&self) -> &Path {
        &self.dir
    }
}

impl AsRef<Path> for Scratch {
    fn as_ref(&self) -> &Path {
        &self.dir
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        if std::thread::panicking() {
            eprintln!("kept for a look: {}", self.dir.display());
        } else {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Scratch;

    #[test]
    fn a_passing_test_leaves_nothing_and_a_failing_one_keeps_its_directory() {
        let passed = Scratch::new("scratch-passes");
        passed.write("a/b.txt", "x");
        let path = passed.to_path_buf();
        assert!(path.starts_with(super::root()) && super::root().ends_with("tmp/scratch"), "in the target directory: {}", path.display());
        drop(passed);
        assert!(!path.exists());

        let kept = std::thread::spawn(|| {
            let failed = Scratch::new("scratch-fails");
            failed.write("left.txt", "y");
            let path = failed.to_path_buf();
            std::panic::panic_any(path);
        })
        .join()
        .unwrap_err();
        let kept = kept.downcast::<std::path::PathBuf>().unwrap();
        assert!(kept.join("left.txt").is_file(), "a failing test's directory stays");
        std::fs::remove_dir_all(*kept).unwrap();
    }
}
