//! The run's exchange with the remote cache: opened on the first local miss (a warm run never
//! contacts it), each instance asked at most once, a bounded number of pulls under way at once,
//! each on a thread of its own beside the running stages; what a pull's end means; the push of
//! each computed result; and the actions whose remote copy was corrupt or untrusted, which this
//! run's push replaces. A remote that fails is a warning, told once, never a failed run.

use std::cell::OnceCell;
use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Instant;

use rlmflow_cache::{ActionRecord, Digest, Store};
use rlmflow_remote::{Pulled, Remote, RemoteError};
use rlmflow_stages::Catalog;

use super::event_log::EventLog;
use crate::config::RemoteSettings;
use crate::event::Event;
use crate::ui::Ui;

/// The most pulls from the remote cache under way at once.
const MAX_PULLS: usize = 4;

pub struct Exchange<'a> {
    settings: Option<&'a RemoteSettings>,
    store: &'a Store,
    /// Checks a pulled artifact's type before it is committed.
    catalog: Catalog,
    ui: Ui,
    remote: OnceCell<Option<Arc<Remote>>>,
    under_way: usize,
    /// Instances asked already this run (a miss is not asked again).
    asked: Vec<bool>,
    /// Actions whose remote copy was found corrupt or untrusted.
    replace: BTreeSet<Digest>,
}

/// What to do about an instance missing from the local store.
pub enum Ask {
    /// Pull it now, from this remote.
    Now(Arc<Remote>),
    /// Wait: as many pulls as allowed are under way.
    Later,
    /// Compute it: there is no usable remote, or it was asked already.
    No,
}

/// What a pull's end means for its instance.
pub enum PullEnd {
    /// Its record and artifact are in the local store, verified.
    Hit { record: Box<ActionRecord>, bytes: u64, seconds: f64 },
    /// Compute it here (a miss, or a remote copy not used, which was reported).
    Compute,
}

impl<'a> Exchange<'a> {
    pub fn new(settings: Option<&'a RemoteSettings>, instances: usize, store: &'a Store, catalog: Catalog, ui: Ui) -> Exchange<'a> {
        let (remote, asked) = (OnceCell::new(), vec![false; instances]);
        Exchange { settings, store, catalog, ui, remote, under_way: 0, asked, replace: BTreeSet::new() }
    }

    /// The remote cache, opened once; `None` when there is none or it cannot be opened (which
    /// warns once).
    fn remote(&self) -> Option<&Arc<Remote>> {
        let ui = &self.ui;
        self.remote
            .get_or_init(|| match self.settings?.open() {
                Ok(remote) => {
                    if !remote.verified() {
                        ui.say(format!("  note     remote cache {}: its records are used unverified (no `remote_trusted_keys`)", remote.url()));
                    }
                    Some(Arc::new(remote))
                }
                Err(e) => {
                    ui.say(format!("  warning  remote cache not used: {e:#}"));
                    None
                }
            })
            .as_ref()
    }

    /// Whether instance `i`, missing locally, is pulled now (counted as under way), later, or
    /// not at all. A remote that went down answers every pull at once with a miss: not asked.
    pub fn ask(&mut self, i: usize) -> Ask {
        if self.asked[i] {
            return Ask::No;
        }
        let Some(remote) = self.remote().filter(|r| r.down().is_none()).cloned() else { return Ask::No };
        if self.under_way == MAX_PULLS {
            return Ask::Later;
        }
        self.asked[i] = true;
        self.under_way += 1;
        Ask::Now(remote)
    }

    pub fn any_under_way(&self) -> bool {
        self.under_way > 0
    }

    /// Pulls `key` (artifact type `produces`) from `remote` on a thread of its own, so that stages
    /// ready meanwhile start; `ended` hears what the pull found, to hand to [`Exchange::ended`].
    pub fn pull(
        &self,
        remote: Arc<Remote>,
        key: Digest,
        produces: &'static str,
        label: &str,
        ended: impl FnOnce(anyhow::Result<Pulled>) + Send + 'static,
    ) {
        let store = self.store.clone();
        let catalog = self.catalog.clone();
        let mut bar = self.ui.transfer(label, "pulling");
        std::thread::spawn(move || {
            let pulled = remote.pull(&store, &key, &|dir| catalog.check_artifact(produces, dir), &mut |done, total| bar.moved(done, total));
            drop(bar);
            ended(pulled);
        });
    }

    /// A pull of `label`'s `key` has ended with `pulled`: a hit, or anything else reported and
    /// sent back to be computed here.
    pub fn ended(&mut self, label: &str, key: Digest, pulled: Pulled, events: &mut EventLog) -> anyhow::Result<PullEnd> {
        self.under_way -= 1;
        match pulled {
            Pulled::Hit { record, bytes, seconds } => return Ok(PullEnd::Hit { record, bytes, seconds }),
            Pulled::Miss => {}
            // Told once: every pull after the first failure answers with it at once.
            Pulled::Unreachable(why) => {
                if self.remote().is_some_and(|r| r.newly_down()) {
                    self.warn_down(&why, events)?;
                }
            }
            Pulled::Corrupt { why } => {
                events.write(Event::RemoteCorrupt { stage: label.to_owned(), key, why: why.clone() })?;
                self.ui.say(format!("  warning  {label}: the remote cache's copy is corrupt ({why}); not used, recomputing"));
                self.replace.insert(key);
            }
            // Replaced by this run's own signed record when it pushes, like a corrupt copy.
            Pulled::Untrusted { why } => {
                events.write(Event::RemoteUntrusted { stage: label.to_owned(), key, why: why.clone() })?;
                self.ui.say(format!("  warning  {label}: the remote cache's record is not trusted ({why}); not used, recomputing"));
                self.replace.insert(key);
            }
        }
        Ok(PullEnd::Compute)
    }

    fn warn_down(&self, why: &RemoteError, events: &mut EventLog) -> anyhow::Result<()> {
        let url = self.remote().map(|r| r.url().to_owned()).unwrap_or_default();
        events.write(Event::RemoteDown { remote: url.clone(), why: why.to_string() })?;
        self.ui.say(format!("  warning  remote cache {url} not used for the rest of the run: {why}"));
        Ok(())
    }

    /// Uploads a finished action's result when the remote cache takes pushes.
    pub fn push(&self, label: &str, record: &ActionRecord, events: &mut EventLog) -> anyhow::Result<()> {
        let Some(remote) = self.remote().filter(|r| r.push) else { return Ok(()) };
        let clock = Instant::now();
        let mut bar = self.ui.transfer(label, "pushing");
        let pushed = remote.push(self.store, record, self.replaces(&record.key), &mut |done, total| bar.moved(done, total))?;
        drop(bar);
        let pushed = match pushed {
            Ok(pushed) => pushed,
            // Told once: every request after the first failure answers with it at once.
            Err(why) if remote.newly_down() => return self.warn_down(&why, events),
            Err(_) => return Ok(()),
        };
        if let Some(why) = &pushed.refused {
            events.write(Event::PushRefused { stage: label.to_owned(), key: record.key, why: why.clone() })?;
            self.ui.say(format!("  warning  {label}: {why}"));
            return Ok(());
        }
        if let Some(why) = &pushed.disagrees {
            events.write(Event::RemoteDisagrees { stage: label.to_owned(), key: record.key, output: record.output, why: why.clone() })?;
            self.ui.say(format!("  WARNING  {label}: {why}"));
        }
        let seconds = clock.elapsed().as_secs_f64();
        events.write(Event::Pushed { stage: label.to_owned(), key: record.key, bytes: pushed.bytes, seconds })?;
        Ok(())
    }

    pub fn replaces(&self, key: &Digest) -> bool {
        self.replace.contains(key)
    }
}

#[cfg(test)]
mod tests {
    use std::path::{Path, PathBuf};

    use rlmflow_cache::Preimage;

    use super::*;

    struct Dirs(PathBuf);

    impl Dirs {
        fn new(name: &str) -> Dirs {
            let root = std::env::temp_dir().join(format!("rlmflow-exchange-{name}-{}", std::process::id()));
            let _ = std::fs::remove_dir_all(&root);
            std::fs::create_dir_all(root.join("remote")).unwrap();
            Dirs(root)
        }

        fn settings(&self, push: bool) -> RemoteSettings {
            RemoteSettings { url: Some(format!("file://{}", self.0.join("remote").display())), push, ..RemoteSettings::default() }
        }

        fn store(&self, name: &str) -> Store {
            Store::open(&self.0.join(name)).unwrap()
        }

        fn events(&self, name: &str) -> EventLog {
            EventLog::create(&self.0.join(name), false).unwrap()
        }

        fn events_written(&self, name: &str) -> String {
            std::fs::read_to_string(self.0.join(name).join("events.jsonl")).unwrap()
        }
    }

    impl Drop for Dirs {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    /// A computed action in `store`: its object holds `content`.
    fn computed(store: &Store, dir: &Path, content: &str) -> ActionRecord {
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(dir.join("out.txt"), content).unwrap();
        let tree = store.commit_tree(dir).unwrap();
        let config = serde_json::json!({ "content": content });
        let preimage = Preimage { operator: "demo".into(), operator_version: 1, config, seed: 0, inputs: vec![], platform: None };
        let record = ActionRecord {
            key: preimage.key(),
            preimage,
            output: tree.digest,
            files: tree.files,
            bytes: tree.bytes,
            started: String::new(),
            duration_s: 2.5,
            metrics: serde_json::Value::Null,
            summary: String::new(),
            platform: None,
            signatures: Vec::new(),
            pulled: None,
        };
        store.write_record(&record).unwrap();
        record
    }

    /// Runs a pull to its end on this thread.
    fn pull(exchange: &Exchange, key: Digest) -> Pulled {
        let remote = exchange.remote().cloned().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        exchange.pull(remote, key, "demo", "demo", move |pulled| tx.send(pulled).unwrap());
        rx.recv().unwrap().unwrap()
    }

    #[test]
    fn each_instance_is_asked_once_and_at_most_four_pulls_are_under_way() {
        let dirs = Dirs::new("asks");
        let (settings, store) = (dirs.settings(false), dirs.store("store"));
        let mut exchange = Exchange::new(Some(&settings), 6, &store, Catalog::paper(), Ui::new(true));
        for i in 0..MAX_PULLS {
            assert!(matches!(exchange.ask(i), Ask::Now(_)), "instance {i}");
        }
        assert!(matches!(exchange.ask(0), Ask::No), "asked already");
        assert!(matches!(exchange.ask(4), Ask::Later), "four are under way");
        let mut events = dirs.events("run");
        assert!(matches!(exchange.ended("a", Digest::of(b"a"), Pulled::Miss, &mut events).unwrap(), PullEnd::Compute));
        assert!(matches!(exchange.ask(4), Ask::Now(_)));
        assert!(exchange.any_under_way());

        let mut none = Exchange::new(None, 1, &store, Catalog::paper(), Ui::new(true));
        assert!(matches!(none.ask(0), Ask::No), "no remote: compute");
    }

    #[test]
    fn a_pushed_result_is_pulled_into_another_store_and_a_miss_is_computed() {
        let dirs = Dirs::new("roundtrip");
        let (pushing, pulling) = (dirs.settings(true), dirs.settings(false));
        let (here, there) = (dirs.store("here"), dirs.store("there"));
        let record = computed(&here, &dirs.0.join("out"), "trained");
        let mut events = dirs.events("push-run");
        Exchange::new(Some(&pushing), 1, &here, Catalog::paper(), Ui::new(true)).push("demo", &record, &mut events).unwrap();
        assert!(dirs.events_written("push-run").contains("\"event\":\"pushed\""), "{}", dirs.events_written("push-run"));

        let mut exchange = Exchange::new(Some(&pulling), 2, &there, Catalog::paper(), Ui::new(true));
        let mut events = dirs.events("pull-run");
        assert!(matches!(exchange.ask(0), Ask::Now(_)));
        let PullEnd::Hit { record: pulled, .. } = exchange.ended("demo", record.key, pull(&exchange, record.key), &mut events).unwrap() else {
            panic!("not a hit")
        };
        assert_eq!(pulled.output, record.output);
        assert!(there.has_object(&record.output) && there.fresh(&record.key).unwrap().is_some(), "the pull is in the local store");

        let other = computed(&dirs.store("unpushed"), &dirs.0.join("out2"), "never pushed");
        assert!(matches!(exchange.ask(1), Ask::Now(_)));
        assert!(matches!(exchange.ended("other", other.key, pull(&exchange, other.key), &mut events).unwrap(), PullEnd::Compute));
        assert!(!exchange.any_under_way());
    }

    #[test]
    fn an_untrusted_or_corrupt_copy_is_reported_computed_and_replaced_by_the_push() {
        let dirs = Dirs::new("replace");
        let (settings, store) = (dirs.settings(true), dirs.store("store"));
        let mut exchange = Exchange::new(Some(&settings), 2, &store, Catalog::paper(), Ui::new(true));
        let mut events = dirs.events("run");
        let (forged, damaged) = (Digest::of(b"forged"), Digest::of(b"damaged"));
        for (i, key, pulled) in [(0, forged, Pulled::Untrusted { why: "unsigned".into() }), (1, damaged, Pulled::Corrupt { why: "bad tree".into() })]
        {
            assert!(matches!(exchange.ask(i), Ask::Now(_)));
            assert!(matches!(exchange.ended("x", key, pulled, &mut events).unwrap(), PullEnd::Compute));
        }
        assert!(exchange.replaces(&forged) && exchange.replaces(&damaged) && !exchange.replaces(&Digest::of(b"other")));
        let written = dirs.events_written("run");
        assert!(written.contains("\"event\":\"remote_untrusted\"") && written.contains("\"event\":\"remote_corrupt\""), "{written}");
    }
}
