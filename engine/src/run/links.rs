//! The run's `[pipeline] results` links: each instance's entry points at its output once it has
//! one, at its work in progress while a stage reports a live directory, and back at its previous
//! output when a run shown live fails. An entry is a path made of its stage and variants, so
//! `results/report/report.html` is always the latest report and `results/pretrain/alpha4/` the
//! latest encoder of variant `alpha4`. The links themselves (atomic replacement, what `gc` does
//! to them) are the store's (`rlmflow_cache::Links`); a link that cannot be made is a warning,
//! never a failed run.

use std::path::{Path, PathBuf};

use rlmflow_cache::{Digest, Links, file_safe};

use crate::plan::{Plan, variant_names};
use crate::ui::Ui;

pub struct ResultsLinks {
    links: Option<Links>,
    /// Each instance's entry under the links directory (`None`: a shard, whose stage's merged
    /// output has the entry).
    entries: Vec<Option<PathBuf>>,
    labels: Vec<String>,
    /// Whether the entry points at the instance's work in progress.
    live: Vec<bool>,
    ui: Ui,
}

/// The link of instance `i`, relative to the results directory: `stage`, then one component per
/// variant named as its label names it (`pretrain/alpha4`, `clipcap/captions=llm/pretrain=alpha4`,
/// `pretrain/seed=2`). A shard has none. Names are made file-safe as the store's are.
pub fn entry(plan: &Plan, i: usize) -> Option<PathBuf> {
    let inst = &plan.instances[i];
    if inst.shard.is_some() {
        return None;
    }
    let mut path = PathBuf::from(file_safe(&plan.pipeline.stages[inst.stage].name));
    for (dimension, variant) in variant_names(&inst.assignment, inst.seed) {
        path.push(match dimension {
            Some(d) => format!("{}={}", file_safe(d), file_safe(&variant)),
            None => file_safe(&variant),
        });
    }
    Some(path)
}

impl ResultsLinks {
    /// The links of `plan`'s instances in `links` (`None`: the run keeps none).
    pub fn for_plan(links: Option<Links>, plan: &Plan, ui: Ui) -> ResultsLinks {
        let entries = (0..plan.instances.len()).map(|i| entry(plan, i)).collect();
        ResultsLinks::new(links, entries, plan.instances.iter().map(|x| x.label.clone()).collect(), ui)
    }

    fn new(links: Option<Links>, entries: Vec<Option<PathBuf>>, labels: Vec<String>, ui: Ui) -> ResultsLinks {
        let live = vec![false; entries.len()];
        ResultsLinks { links, entries, labels, live, ui }
    }

    /// The links directory, where the run keeps one.
    pub fn dir(&self) -> Option<&Path> {
        self.links.as_ref().map(Links::dir)
    }

    /// Points instance `i`'s entry with `point`; whether it was made.
    fn point(&self, i: usize, point: impl FnOnce(&Links, &Path) -> anyhow::Result<()>) -> bool {
        let (Some(links), Some(entry)) = (&self.links, &self.entries[i]) else { return false };
        match point(links, entry) {
            Ok(()) => true,
            Err(e) => {
                self.ui.say(format!("  warning: {} not linked in {}: {e:#}", self.labels[i], links.dir().display()));
                false
            }
        }
    }

    /// Instance `i` has its output.
    pub fn done(&mut self, i: usize, output: &Digest) {
        self.live[i] = false;
        self.point(i, |links, entry| links.point(entry, output));
    }

    /// A running instance's work in progress is in `dir`: its entry points there until its
    /// output is committed. A directory this machine cannot see (a cluster task's own store) is
    /// not linked.
    pub fn live(&mut self, i: usize, dir: &Path) {
        if dir.is_dir() && self.point(i, |links, entry| links.point_at(entry, dir)) {
            self.live[i] = true;
        }
    }

    /// Instance `i` failed: an entry pointed at its work in progress (which may be gone) points
    /// at its previous output again, where `previous` finds one.
    pub fn failed(&mut self, i: usize, previous: impl FnOnce() -> anyhow::Result<Option<Digest>>) -> anyhow::Result<()> {
        if !std::mem::take(&mut self.live[i]) {
            return Ok(());
        }
        if let (Some(links), Some(entry), Some(output)) = (&self.links, &self.entries[i], previous()?) {
            links.point(entry, &output)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use rlmflow_cache::Store;

    use super::*;

    struct Fixture {
        root: PathBuf,
        store: Store,
        results: PathBuf,
    }

    impl Fixture {
        fn new(name: &str) -> Fixture {
            let root = std::env::temp_dir().join(format!("rlmflow-links-{name}-{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&root);
            let store = Store::open(&root.join("store")).unwrap();
            Fixture { results: root.join("results"), root, store }
        }

        /// An object holding `file`, committed to the store.
        fn object(&self, file: &str) -> Digest {
            let dir = self.root.join(format!("out-{file}"));
            std::fs::create_dir_all(&dir).unwrap();
            std::fs::write(dir.join(file), file).unwrap();
            self.store.commit_tree(&dir).unwrap().digest
        }

        fn links(&self) -> ResultsLinks {
            let entries = vec![Some(PathBuf::from("pretrain/alpha4")), None];
            let labels = vec!["pretrain[alpha4]".to_owned(), "scenes[part=0]".to_owned()];
            ResultsLinks::new(Some(self.store.links(&self.results).unwrap()), entries, labels, Ui::new(true))
        }

        fn shown(&self) -> PathBuf {
            self.results.join("pretrain/alpha4")
        }
    }

    impl Drop for Fixture {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.root);
        }
    }

    #[test]
    fn an_entry_follows_the_output_then_the_work_in_progress_then_the_output_again() {
        let f = Fixture::new("follow");
        let mut links = f.links();
        let first = f.object("v1");
        links.done(0, &first);
        assert!(f.shown().join("v1").is_file());
        links.done(1, &first);
        assert!(!f.results.join("scenes").exists(), "a shard has no entry");

        let work = f.root.join("work");
        std::fs::create_dir_all(&work).unwrap();
        std::fs::write(work.join("step-10"), "").unwrap();
        links.live(0, &work);
        assert!(f.shown().join("step-10").is_file(), "the entry shows the work in progress");

        let second = f.object("v2");
        links.done(0, &second);
        assert!(f.shown().join("v2").is_file());
        // Committed: a later failure does not move it back.
        links.failed(0, || panic!("not asked: the entry is not live")).unwrap();
        assert!(f.shown().join("v2").is_file());
    }

    #[test]
    fn a_failed_live_instance_points_at_its_previous_output() {
        let f = Fixture::new("failed");
        let mut links = f.links();
        let previous = f.object("v1");
        let work = f.root.join("work");
        std::fs::create_dir_all(&work).unwrap();
        links.live(0, &work);
        links.live(0, &f.root.join("elsewhere"));
        assert_eq!(std::fs::read_link(f.shown()).unwrap().file_name(), Some("work".as_ref()), "an unseen directory is not linked");
        links.failed(0, || Ok(Some(previous))).unwrap();
        assert!(f.shown().join("v1").is_file());
    }
}
