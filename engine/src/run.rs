//! The executor: walks a plan's instances in dependency order, reuses every cached action, and
//! starts the others (`rlmflow exec KEY`) through a dispatcher (`dispatch/`: child processes or
//! HyperQueue tasks), independent ones concurrently within a thread budget.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, mpsc};
use std::time::Instant;

use anyhow::Context as _;
use indicatif::ProgressBar;
use rlmflow_cache::{ActionRecord, Digest, GitState, Links, PlanEntry, Preimage, RunPlan, Store, file_safe, now_rfc3339, run_id};
use rlmflow_remote::{Pulled, Remote, RemoteError};
use rlmflow_stages::{Device, Registry};

use crate::config::{Executor as ExecutorKind, RemoteSettings};
use crate::dispatch::{Dispatch, Exit, Launch, Local, Report};
use crate::event::{Event, Finished, Logged, Status};
use crate::history::Counts;
use crate::plan::Plan;
use crate::protocol::{EXIT_CORRUPT_INPUT, Message};
use crate::pulls::{Ask, Pulls};
use crate::reason::why;
use crate::ui::Ui;

#[derive(Clone, Debug)]
pub struct RunOptions {
    /// The CPU-thread budget shared by concurrently running stages.
    pub jobs: usize,
    pub json: bool,
    pub device: Device,
    /// Re-hash every reused output before using it (by default only a stage that runs re-hashes
    /// its inputs).
    pub verify_inputs: bool,
    /// The remote cache asked on a local miss (and pushed to, when it pushes).
    pub remote: Option<RemoteSettings>,
}

#[derive(Clone, Debug)]
enum State {
    Excluded,
    Waiting,
    /// Its key is missing locally and a pull from the remote cache is under way.
    Pulling {
        key: Digest,
    },
    Ready {
        key: Digest,
    },
    Running {
        key: Digest,
    },
    Done {
        output: Digest,
    },
    Failed,
    Skipped,
}

struct Executor<'a> {
    plan: &'a Plan<'a>,
    registry: &'a Registry,
    store: &'a Store,
    opts: &'a RunOptions,
    run: String,
    /// When it started (RFC 3339), and the git state of the pipeline's work tree once it computed
    /// something (`None` inside: not a git work tree).
    started: String,
    git: Option<Option<GitState>>,
    /// What the run knows of each of the plan's instances, by index.
    instances: Vec<InstanceRun>,
    plan_dirty: bool,
    events: EventLog,
    ui: Ui,
    last: BTreeMap<String, Digest>,
    /// Outputs re-hashed this run (`verify_inputs`).
    verified: std::collections::BTreeSet<Digest>,
    dispatch: Box<dyn Dispatch>,
    /// Pulls from the remote cache, each on a thread of its own beside the running stages.
    pulls: Pulls<'a>,
    /// `[pipeline] results`: a link per instance to its current output.
    links: Option<Links>,
    /// Which ready instance starts first ([`Plan::start_order`]).
    start_order: Vec<usize>,
}

/// What the run knows of one stage instance.
struct InstanceRun {
    state: State,
    /// Its record as the preflight found it fresh, until the run uses it.
    known: Option<Box<ActionRecord>>,
    /// Its key, once its inputs are known.
    key: Option<Digest>,
    /// How it ended, and its compute time: this run's when it ran, the original computation's
    /// (which reuse saved) when reused.
    result: Option<(Status, f64)>,
    /// The numeric platform class its output's record names, once it has one.
    platform: Option<String>,
    /// How many times an input it found damaged was recomputed for it.
    recoveries: u32,
    attempts: Attempts,
    /// Whether its results link points at its work in progress.
    live_linked: bool,
}

/// An instance's attempts in this run.
#[derive(Clone, Copy, Default)]
struct Attempts {
    started: u32,
    /// The seconds the attempts before the current one took.
    earlier_s: f64,
}

/// Runs the plan; returns its summary. `known`: the records the preflight found fresh, by
/// instance (empty: none), which the run uses without reading them again.
pub fn run(
    plan: &Plan,
    registry: &Registry,
    store: &Store,
    selected: &[bool],
    known: Vec<Option<Box<ActionRecord>>>,
    opts: &RunOptions,
) -> anyhow::Result<Counts> {
    let _shared = store.lock_shared()?;
    store.sweep_tmp(None)?;
    // Before the run exists: a results directory that cannot be used stops it with nothing done.
    let links = plan.pipeline.results.as_deref().map(|dir| store.links(dir)).transpose()?;
    let run = run_id();
    let events = EventLog::create(&store.run_dir(&run), opts.json)?;
    let mut known = known.into_iter();
    let instances = selected
        .iter()
        .map(|&s| InstanceRun {
            state: if s { State::Waiting } else { State::Excluded },
            known: known.next().flatten(),
            key: None,
            result: None,
            platform: None,
            recoveries: 0,
            attempts: Attempts::default(),
            live_linked: false,
        })
        .collect();
    let ui = Ui::new(opts.json);
    let dispatch = dispatcher(plan, store, &run, opts.device, opts.remote.as_ref(), &ui)?;
    let mut ex = Executor {
        plan,
        registry,
        store,
        opts,
        run,
        started: now_rfc3339(),
        git: None,
        instances,
        plan_dirty: true,
        events,
        ui,
        last: store.last_keys(&plan.pipeline.name)?,
        verified: Default::default(),
        dispatch,
        pulls: Pulls::new(opts.remote.as_ref(), plan.instances.len()),
        links,
        start_order: plan.start_order(),
    };
    ex.execute()?;
    Ok(ex.summary())
}

/// The pipeline's dispatcher. An existing HyperQueue server is checked here, before anything runs.
fn dispatcher(plan: &Plan, store: &Store, run: &str, device: Device, remote: Option<&RemoteSettings>, ui: &Ui) -> anyhow::Result<Box<dyn Dispatch>> {
    match plan.pipeline.executor {
        ExecutorKind::Local => Ok(Box::new(Local::new(device))),
        #[cfg(feature = "python")]
        ExecutorKind::HyperQueue => {
            let dir = store.run_dir(run).join("hyperqueue");
            let ui = ui.clone();
            let note = Box::new(move |note: &str| ui.say(note.to_owned()));
            let hq = crate::dispatch::HyperQueue::connect(plan.pipeline.hyperqueue.clone(), &dir, run, remote, note)?;
            Ok(Box::new(hq))
        }
        #[cfg(not(feature = "python"))]
        ExecutorKind::HyperQueue => {
            let _ = (store, run, device, remote, ui);
            anyhow::bail!("executor = \"hyperqueue\" needs the embedded Python (build rlmflow with its default `python` feature)")
        }
    }
}

impl Executor<'_> {
    fn execute(&mut self) -> anyhow::Result<()> {
        let clock = Instant::now();
        let p = self.plan.pipeline;
        let selected = self.instances.iter().filter(|x| !matches!(x.state, State::Excluded)).count();
        let executor = self.dispatch.describe();
        self.events.write(Event::RunStarted {
            run: self.run.clone(),
            pipeline: p.name.clone(),
            file: p.file.clone(),
            instances: selected,
            jobs: self.opts.jobs,
            executor: executor.clone(),
        })?;
        self.ui.say(format!(
            "rlmflow run {} ({} stage instances, {} threads, {executor}, run {})",
            p.file.display(),
            selected,
            self.opts.jobs,
            self.run
        ));

        let (tx, rx) = mpsc::channel::<(usize, Report)>();
        let mut bars: BTreeMap<usize, ProgressBar> = BTreeMap::new();
        let mut threads_in_use = 0;
        let mut gpu_in_use = false;
        let mut started: BTreeMap<usize, (Instant, usize, bool)> = BTreeMap::new();
        let mut outcome: BTreeMap<usize, Message> = BTreeMap::new();
        loop {
            self.resolve(&tx)?;
            self.write_plan_if_dirty()?;
            // Start what fits in the budget, the longest chains first.
            for k in 0..self.start_order.len() {
                let i = self.start_order[k];
                let State::Ready { key } = self.instances[i].state else { continue };
                let op = self.registry.get(&self.plan.instances[i].operator).unwrap();
                let wants = op.resources(&self.plan.instances[i].settings)?;
                let mut threads = wants.threads.clamp(1, self.opts.jobs).min(self.dispatch.max_threads().unwrap_or(usize::MAX));
                // An operator whose bytes do not follow its thread count (no pinned kernels)
                // starts with the threads that are free: the data stage a chain waits on is not
                // queued behind a one-thread model stage for want of its second thread.
                if wants.kernels.is_none() {
                    threads = threads.min(self.opts.jobs.saturating_sub(threads_in_use)).max(1);
                }
                let fits = threads_in_use + threads <= self.opts.jobs && !(wants.gpu && gpu_in_use && self.dispatch.serialises_gpu());
                if !fits && !started.is_empty() {
                    continue;
                }
                let exe = match crate::exec::executable(op) {
                    Ok(exe) => exe,
                    Err(e) => {
                        self.fail_unstarted(i, key, format!("{e:#}"))?;
                        continue;
                    }
                };
                threads_in_use += threads;
                gpu_in_use |= wants.gpu;
                started.insert(i, (Instant::now(), threads, wants.gpu));
                self.instances[i].state = State::Running { key };
                let label = self.plan.instances[i].label.clone();
                self.instances[i].attempts.started += 1;
                self.note_git_state();
                self.events.write(Event::StageStarted { stage: label.clone(), key, threads, attempt: self.instances[i].attempts.started })?;
                bars.insert(i, self.ui.bar(&label));
                self.start(i, exe, key, threads, wants.gpu, tx.clone())?;
            }
            if started.is_empty() && !self.pulls.any_under_way() {
                break;
            }
            let (i, report) = rx.recv().expect("a running child always reports its exit, a pull its end");
            match report {
                Report::Pulled(pulled) => {
                    self.pulls.ended();
                    self.pulled(i, pulled?)?;
                }
                Report::Message(Message::Progress { position, length, message }) => {
                    let bar = &bars[&i];
                    if bar.length() != Some(length) {
                        bar.set_length(length);
                        bar.set_style(Ui::bar_style());
                    }
                    bar.set_position(position);
                    bar.set_message(message);
                }
                Report::Message(Message::Live { dir }) => self.link_live(i, &dir),
                Report::Message(Message::Event { name, data }) => {
                    self.events.write(Event::OperatorEvent { stage: self.plan.instances[i].label.clone(), name, data })?;
                }
                Report::Message(Message::Waiting) => bars[&i].set_message("waiting for another run computing it"),
                Report::Message(message) => {
                    outcome.insert(i, message);
                }
                Report::Exited(exit) => {
                    let (t0, threads, gpu) = started.remove(&i).unwrap();
                    threads_in_use -= threads;
                    gpu_in_use &= !gpu;
                    bars.remove(&i).unwrap().finish_and_clear();
                    let secs = t0.elapsed().as_secs_f64();
                    self.finish(i, exit, outcome.remove(&i), secs)?;
                }
            }
        }
        self.write_plan_if_dirty()?;
        let s = self.summary();
        // A fold from +0.0: an empty f64 `sum()` is -0.0, printed as "-0.0s".
        let saved = self
            .instances
            .iter()
            .filter_map(|x| x.result)
            .filter(|r| matches!(r.0, Status::Reused | Status::Pulled))
            .fold(0.0, |total, r| total + r.1);
        let wall = clock.elapsed().as_secs_f64();
        self.events.write(Event::RunFinished {
            ran: s.ran,
            reused: s.reused,
            pulled: s.pulled,
            failed: s.failed,
            skipped: s.skipped,
            wall_s: wall,
            saved_s: saved,
        })?;
        let pulled = if s.pulled > 0 { format!(", {} pulled", s.pulled) } else { String::new() };
        self.ui.say(format!(
            "done: {} ran, {} reused{pulled}, {} failed, {} skipped in {:.1}s; reuse saved {:.1}s",
            s.ran, s.reused, s.failed, s.skipped, wall, saved
        ));
        if s.failed > 0 {
            self.ui.say(format!("logs: {}", self.store.run_dir(&self.run).join("logs").display()));
        }
        self.ui.say(format!("  provenance  {}", self.write_provenance(wall, &executor)?.display()));
        for (label, dir) in self.final_outputs() {
            self.ui.say(format!("  output  {label}  {}", dir.display()));
        }
        if let Some(links) = &self.links {
            self.ui.say(format!("  results {}  (a link per instance to its current output)", links.dir().display()));
        }
        Ok(())
    }

    /// `runs/<id>/provenance.md`: what this run did with each instance, with its key, output and
    /// time. A report cannot hold this (its bytes depend only on its inputs, and a reused input
    /// is the same bytes as a recomputed one), so it lives in the run's record.
    fn write_provenance(&self, wall: f64, executor: &str) -> anyhow::Result<PathBuf> {
        let p = self.plan.pipeline;
        let mut md = format!(
            "# Run {}\n\n`{}` (pipeline `{}`), {executor}, {wall:.1} s, planned on {} ({}). Seconds are this run's for an instance that ran, the original computation's for one reused. A model action's numeric platform is the class of machines that compute its bytes (`rlmflow show` prints the CPU, kernels and libraries it ran with).\n\n",
            self.run,
            p.file.display(),
            p.name,
            self.plan.platform.cpu().model,
            self.plan.platform.cpu().extensions.join(" "),
        );
        if !p.overrides.is_empty() {
            // So the run can be repeated from this file alone.
            let set: Vec<String> = p.overrides.iter().map(|o| format!("`{}`", o.shown())).collect();
            md += &format!("Overrides over the file, in order: {}.\n\n", set.join(", "));
        }
        md += "| instance | status | seconds | key | output | platform |\n|---|---|---|---|---|---|\n";
        for (i, inst) in self.plan.instances.iter().enumerate() {
            let Some((status, secs)) = self.instances[i].result else { continue };
            let status = status.as_str();
            let key = self.instances[i].key.map_or("-".to_owned(), |k| k.to_string());
            let output = if let State::Done { output } = &self.instances[i].state { output.to_string() } else { "-".to_owned() };
            let platform = self.instances[i].platform.as_deref().unwrap_or("-");
            md += &format!("| {} | {status} | {secs:.1} | {key} | {output} | {platform} |\n", inst.label);
        }
        let path = self.store.run_dir(&self.run).join("provenance.md");
        std::fs::write(&path, md).with_context(|| format!("writing {}", path.display()))?;
        Ok(path)
    }

    /// Where the outputs of the instances nothing consumes are (the report, say).
    fn final_outputs(&self) -> Vec<(String, std::path::PathBuf)> {
        let mut consumed = vec![false; self.plan.instances.len()];
        for inst in &self.plan.instances {
            inst.inputs.iter().flat_map(|input| &input.providers).for_each(|&p| consumed[p] = true);
        }
        self.plan
            .instances
            .iter()
            .enumerate()
            .filter(|&(i, _)| !consumed[i])
            .filter_map(|(i, inst)| match &self.instances[i].state {
                State::Done { output } => Some((inst.label.clone(), self.store.object_dir(output))),
                _ => None,
            })
            .collect()
    }

    /// Instance `i`'s results link, where the run keeps links and `i` has one (a shard has none).
    fn results_link(&self, i: usize) -> Option<(&Links, PathBuf)> {
        Some((self.links.as_ref()?, crate::results::entry(self.plan, i)?))
    }

    /// Points instance `i`'s results link with `point` (given the links and the entry); a link
    /// that cannot be made is a warning, never a failed run. Whether it was made.
    fn link(&self, i: usize, point: impl FnOnce(&Links, &Path) -> anyhow::Result<()>) -> bool {
        let Some((links, entry)) = self.results_link(i) else { return false };
        match point(links, &entry) {
            Ok(()) => true,
            Err(e) => {
                self.ui.say(format!("  warning: {} not linked in {}: {e:#}", self.plan.instances[i].label, links.dir().display()));
                false
            }
        }
    }

    /// Instance `i` has its output: consumers may start, and its results link points at it.
    fn done(&mut self, i: usize, output: Digest) {
        self.instances[i].state = State::Done { output };
        self.instances[i].live_linked = false;
        self.link(i, |links, entry| links.point(entry, &output));
    }

    /// A running instance's work in progress is in `dir`: its results entry points there until
    /// its output is committed. A directory this machine cannot see (a cluster task's own store)
    /// is not linked.
    fn link_live(&mut self, i: usize, dir: &Path) {
        if !dir.is_dir() {
            return;
        }
        if self.link(i, |links, entry| links.point_at(entry, dir)) {
            self.instances[i].live_linked = true;
        }
    }

    /// A failed instance whose results entry was pointed at its work in progress points at its
    /// previous output again, where the store has one (its work directory may be gone).
    fn relink_previous(&mut self, i: usize) -> anyhow::Result<()> {
        if !std::mem::take(&mut self.instances[i].live_linked) {
            return Ok(());
        }
        let previous = self.last.get(&self.plan.instances[i].label).map(|key| self.store.fresh(key)).transpose()?.flatten();
        if let (Some((links, entry)), Some(record)) = (self.results_link(i), previous) {
            links.point(&entry, &record.output)?;
        }
        Ok(())
    }

    /// Instance `i`'s stage's `timeout` and `retries`.
    fn bounds(&self, i: usize) -> crate::config::Bounds {
        self.plan.pipeline.stages[self.plan.instances[i].stage].bounds
    }

    fn summary(&self) -> Counts {
        Counts::of(self.instances.iter().filter_map(|x| x.result.map(|(status, _)| status)))
    }

    /// Moves waiting instances whose inputs are settled to ready, reused, pulling or skipped.
    fn resolve(&mut self, tx: &mpsc::Sender<(usize, Report)>) -> anyhow::Result<()> {
        for i in 0..self.instances.len() {
            if !matches!(self.instances[i].state, State::Waiting) {
                continue;
            }
            let inst = &self.plan.instances[i];
            let providers = inst.inputs.iter().flat_map(|input| input.providers.iter().copied());
            if let Some(bad) = providers.clone().find(|&p| matches!(self.instances[p].state, State::Failed | State::Skipped)) {
                let upstream = self.plan.instances[bad].label.clone();
                self.instances[i].state = State::Skipped;
                self.instances[i].result = Some((Status::Skipped, 0.0));
                let label = inst.label.clone();
                let reason = Some(format!("upstream {upstream} did not finish"));
                self.events.write(Event::StageFinished(Finished { reason, ..Finished::new(&label, Status::Skipped) }))?;
                self.ui.say(format!("  skipped  {label}  (upstream {upstream} did not finish)"));
                continue;
            }
            let outputs: Vec<Option<Digest>> =
                self.instances.iter().map(|x| if let State::Done { output } = x.state { Some(output) } else { None }).collect();
            let Some(inputs) = self.plan.input_digests(i, &outputs) else { continue };
            // The record the preflight found is this instance's while its inputs are the ones
            // it was computed from (its preimage hashes to its key, and the preflight found that
            // key from this plan), so its key needs no second preimage.
            let known = self.instances[i].known.take().filter(|r| r.preimage.inputs == inputs && self.store.has_object(&r.output));
            let (key, preimage) = match &known {
                Some(record) => (record.key, None),
                None => {
                    let preimage = self.plan.preimage_with(i, self.registry, inputs.clone())?;
                    (preimage.key(), Some(preimage))
                }
            };
            if self.instances[i].key != Some(key) {
                self.instances[i].key = Some(key);
                self.plan_dirty = true;
            }
            let fresh = match known {
                Some(record) => Some(*record),
                None => self.store.fresh(&key)?,
            };
            if let Some(record) = fresh
                && self.intact(&inst.label, &record.output)?
            {
                self.done(i, record.output);
                self.instances[i].result = Some((Status::Reused, record.duration_s));
                self.instances[i].platform = record.preimage.platform.clone();
                let (output, saved_s) = (Some(record.output), Some(record.duration_s));
                self.events.write(Event::StageFinished(Finished {
                    key: Some(key),
                    output,
                    saved_s,
                    ..Finished::new(&inst.label, Status::Reused)
                }))?;
                self.ui.say(format!("  reused   {}  ({:.1}s saved)", inst.label, record.duration_s));
                continue;
            }
            match self.pulls.ask(i, &self.ui) {
                Ask::Now(remote) => {
                    self.instances[i].state = State::Pulling { key };
                    self.start_pull(i, key, remote, tx.clone());
                    continue;
                }
                Ask::Later => continue,
                Ask::No => {}
            }
            let inst = &self.plan.instances[i];
            let stage = &self.plan.pipeline.stages[inst.stage];
            let resumes = self.registry.get(&inst.operator).expect("validated operator").resumes_from();
            let preimage = match preimage {
                Some(preimage) => preimage,
                None => self.plan.preimage_with(i, self.registry, inputs)?,
            };
            let reasons = why(Some(self.store), self.last.get(&inst.label), &key, &preimage, &stage.name, resumes)?;
            self.ui.say(format!("  run      {}  ({})", inst.label, crate::ui::words(&reasons)));
            self.events.write(Event::StagePlanned { stage: inst.label.clone(), key, reasons })?;
            // The operator reads a snapshot of each tracked path, by the digest in its key.
            if let Err(e) = self.plan.snapshot_tracked(i, self.store) {
                self.fail_unstarted(i, key, format!("{e:#}"))?;
                continue;
            }
            self.write_request(i, key, preimage)?;
            self.instances[i].state = State::Ready { key };
        }
        Ok(())
    }

    /// Asks the remote cache for `key` after a local miss, on a thread of its own (stages that
    /// are ready meanwhile start); its end arrives as [`Report::Pulled`].
    fn start_pull(&self, i: usize, key: Digest, remote: Arc<Remote>, tx: mpsc::Sender<(usize, Report)>) {
        let store = self.store.clone();
        let catalog = self.registry.catalog.clone();
        let produces = self.plan.pipeline.stages[self.plan.instances[i].stage].kind.produces;
        let mut bar = self.ui.transfer(&self.plan.instances[i].label, "pulling");
        std::thread::spawn(move || {
            let pulled = remote.pull(&store, &key, &|dir| catalog.check_artifact(produces, dir), &mut |done, total| bar.moved(done, total));
            drop(bar);
            let _ = tx.send((i, Report::Pulled(pulled)));
        });
    }

    /// A pull has ended: a hit finishes the instance as `pulled` (verified, in the local store);
    /// anything else sends it back to be computed here.
    fn pulled(&mut self, i: usize, pulled: Pulled) -> anyhow::Result<()> {
        let State::Pulling { key } = self.instances[i].state else { unreachable!("a pull ended for an instance not pulling") };
        let label = self.plan.instances[i].label.clone();
        self.instances[i].state = State::Waiting;
        match pulled {
            Pulled::Hit { record, bytes, seconds } => {
                self.events.write(Event::StageFinished(Finished {
                    key: Some(key),
                    output: Some(record.output),
                    bytes: Some(bytes),
                    seconds: Some(seconds),
                    saved_s: Some(record.duration_s),
                    ..Finished::new(&label, Status::Pulled)
                }))?;
                self.ui.say(format!("  pulled   {label}  {:.1} MB in {seconds:.1}s ({:.1}s saved)", bytes as f64 / 1e6, record.duration_s));
                self.done(i, record.output);
                self.instances[i].result = Some((Status::Pulled, record.duration_s));
                self.instances[i].platform = record.preimage.platform.clone();
            }
            Pulled::Miss => {}
            // Told once: every pull after the first failure answers with it at once.
            Pulled::Unreachable(why) => {
                if self.pulls.remote(&self.ui).is_some_and(|r| r.newly_down()) {
                    self.warn_remote_down(&why)?;
                }
            }
            Pulled::Corrupt { why } => {
                self.events.write(Event::RemoteCorrupt { stage: label.clone(), key, why: why.clone() })?;
                self.ui.say(format!("  warning  {label}: the remote cache's copy is corrupt ({why}); not used, recomputing"));
                self.pulls.replace(key);
            }
            // Replaced by this run's own signed record when it pushes, like a corrupt copy.
            Pulled::Untrusted { why } => {
                self.events.write(Event::RemoteUntrusted { stage: label.clone(), key, why: why.clone() })?;
                self.ui.say(format!("  warning  {label}: the remote cache's record is not trusted ({why}); not used, recomputing"));
                self.pulls.replace(key);
            }
        }
        Ok(())
    }

    fn warn_remote_down(&mut self, why: &RemoteError) -> anyhow::Result<()> {
        let url = self.pulls.remote(&self.ui).map(|r| r.url().to_owned()).unwrap_or_default();
        self.events.write(Event::RemoteDown { remote: url.clone(), why: why.to_string() })?;
        self.ui.say(format!("  warning  remote cache {url} not used for the rest of the run: {why}"));
        Ok(())
    }

    /// Uploads a finished action's result when the remote cache takes pushes.
    fn push(&mut self, label: &str, record: &ActionRecord) -> anyhow::Result<()> {
        let Some(remote) = self.pulls.remote(&self.ui).filter(|r| r.push).cloned() else { return Ok(()) };
        let replace = self.pulls.replaces(&record.key);
        let clock = Instant::now();
        let mut bar = self.ui.transfer(label, "pushing");
        let pushed = remote.push(self.store, record, replace, &mut |done, total| bar.moved(done, total))?;
        drop(bar);
        let pushed = match pushed {
            Ok(pushed) => pushed,
            // Told once: every request after the first failure answers with it at once.
            Err(why) if remote.newly_down() => return self.warn_remote_down(&why),
            Err(_) => return Ok(()),
        };
        if let Some(why) = &pushed.refused {
            self.events.write(Event::PushRefused { stage: label.to_owned(), key: record.key, why: why.clone() })?;
            self.ui.say(format!("  warning  {label}: {why}"));
            return Ok(());
        }
        if let Some(why) = &pushed.disagrees {
            self.events.write(Event::RemoteDisagrees { stage: label.to_owned(), key: record.key, output: record.output, why: why.clone() })?;
            self.ui.say(format!("  WARNING  {label}: {why}"));
        }
        let seconds = clock.elapsed().as_secs_f64();
        self.events.write(Event::Pushed { stage: label.to_owned(), key: record.key, bytes: pushed.bytes, seconds })?;
        Ok(())
    }

    /// With `verify_inputs`, re-hashes a reused output once per run; a damaged one is
    /// quarantined, so its action reruns.
    fn intact(&mut self, label: &str, output: &Digest) -> anyhow::Result<bool> {
        if !self.opts.verify_inputs || self.verified.contains(output) {
            return Ok(true);
        }
        if let Some(corruption) = self.store.check_object(output)? {
            self.store.quarantine(output)?;
            self.ui.say(format!(
                "  corrupt  {label}: output {} failed verification ({}); quarantined, recomputing",
                output.short(),
                corruption.files.join(", ")
            ));
            self.events.write(Event::OutputCorrupt { stage: label.to_owned(), digest: *output, files: corruption.files })?;
            return Ok(false);
        }
        self.verified.insert(*output);
        Ok(true)
    }

    fn write_request(&self, i: usize, key: Digest, preimage: Preimage) -> anyhow::Result<()> {
        self.store.write_request(&self.plan.request(i, key, preimage))
    }

    /// Asks git for the work tree's state the first time the run computes something: a run that
    /// only reuses has nothing a commit could explain, and the two `git` processes were most of
    /// a no-op run's time (`cargo xtask bench -p rlmflow-e2e --bench engine`).
    fn note_git_state(&mut self) {
        if self.git.is_none() {
            self.git = Some(crate::history::git_state(&self.plan.pipeline.file));
            self.plan_dirty = true;
        }
    }

    fn write_plan_if_dirty(&mut self) -> anyhow::Result<()> {
        if !self.plan_dirty {
            return Ok(());
        }
        let instances = self
            .plan
            .instances
            .iter()
            .enumerate()
            .filter(|(i, _)| !matches!(self.instances[*i].state, State::Excluded))
            .map(|(i, inst)| PlanEntry {
                label: inst.label.clone(),
                stage: self.plan.pipeline.stages[inst.stage].name.clone(),
                assignment: inst.assignment.clone(),
                key: self.instances[i].key,
            })
            .collect();
        let overrides = self.plan.pipeline.overrides.iter().map(|o| o.shown()).collect();
        self.store.write_plan(&RunPlan {
            run: self.run.clone(),
            pipeline: self.plan.pipeline.name.clone(),
            started: self.started.clone(),
            overrides,
            git: self.git.clone().flatten(),
            instances,
        })?;
        // Recorded as soon as known, so a killed run still tells `status` what it was doing.
        let resolved: BTreeMap<String, Digest> =
            self.instances.iter().enumerate().filter_map(|(i, x)| x.key.map(|k| (self.plan.instances[i].label.clone(), k))).collect();
        self.store.update_last_keys(&self.plan.pipeline.name, &resolved)?;
        self.plan_dirty = false;
        Ok(())
    }

    /// `runs/<id>/logs/<label>.log`, and `<label>.attempt-N.log` for a retry's.
    /// Appends the engine's word on instance `i`'s attempt to its log, so the log of an attempt
    /// that failed or was stopped says how it ended even when its process wrote nothing.
    fn note_in_log(&self, i: usize, line: &str) {
        let log = self.log_path(i);
        let appended = std::fs::OpenOptions::new().create(true).append(true).open(&log).and_then(|mut f| writeln!(f, "[rlmflow] {line}"));
        if let Err(e) = appended {
            self.ui.say(format!("  warning  could not write {}: {e}", log.display()));
        }
    }

    fn log_path(&self, i: usize) -> PathBuf {
        let label = file_safe(&self.plan.instances[i].label);
        let name = match self.instances[i].attempts.started {
            0 | 1 => format!("{label}.log"),
            n => format!("{label}.attempt-{n}.log"),
        };
        self.store.run_dir(&self.run).join("logs").join(name)
    }

    fn start(&mut self, i: usize, exe: PathBuf, key: Digest, threads: usize, gpu: bool, tx: mpsc::Sender<(usize, Report)>) -> anyhow::Result<()> {
        let label = self.plan.instances[i].label.clone();
        let args = ["exec", &key.to_string(), "--store", &self.store.root().to_string_lossy(), "--threads", &threads.to_string()]
            .into_iter()
            .map(str::to_owned)
            .chain(["--device".to_owned(), self.opts.device.to_string()])
            .collect();
        let log = self.log_path(i);
        let (store, device, replace_remote) = (self.store.root().to_path_buf(), self.opts.device, self.pulls.replaces(&key));
        let timeout = self.bounds(i).timeout_s.map(std::time::Duration::from_secs_f64);
        self.dispatch.start(i, Launch { exe, args, key, store, device, replace_remote, label, threads, gpu, log, timeout }, tx)
    }

    /// An instance that could not be started (its worker binary is missing) fails like one
    /// whose process failed: its dependants are skipped, independent branches go on.
    fn fail_unstarted(&mut self, i: usize, key: Digest, message: String) -> anyhow::Result<()> {
        let label = self.plan.instances[i].label.clone();
        self.instances[i].state = State::Failed;
        self.instances[i].result = Some((Status::Failed, 0.0));
        let (error, duration_s) = (Some(message.clone()), Some(0.0));
        self.events.write(Event::StageFinished(Finished { key: Some(key), error, duration_s, ..Finished::new(&label, Status::Failed) }))?;
        self.ui.say(format!("  FAILED   {label}  {message}"));
        Ok(())
    }

    fn finish(&mut self, i: usize, exit: Exit, outcome: Option<Message>, secs: f64) -> anyhow::Result<()> {
        let label = self.plan.instances[i].label.clone();
        let State::Running { key } = self.instances[i].state else { unreachable!("finished a stage that was not running") };
        let code = exit.code();
        match outcome {
            Some(Message::Done { .. } | Message::Reused) if code == Some(0) => {
                let record = self.store.fresh(&key)?.context("a finished action has no record")?;
                let reused = matches!(outcome, Some(Message::Reused));
                self.done(i, record.output);
                let status = if reused { Status::Reused } else { Status::Ran };
                // Every attempt's time: a stage that ran on its third attempt took all three.
                let Attempts { started, earlier_s } = self.instances[i].attempts;
                let total = earlier_s + secs;
                self.instances[i].result = Some(if reused { (Status::Reused, record.duration_s) } else { (Status::Ran, total) });
                self.instances[i].platform = record.preimage.platform.clone();
                self.events.write(Event::StageFinished(Finished {
                    key: Some(key),
                    output: Some(record.output),
                    duration_s: Some(secs),
                    attempts: Some(started),
                    total_s: Some(total),
                    summary: Some(record.summary.clone()),
                    metrics: Some(record.metrics.clone()),
                    ..Finished::new(&label, status)
                }))?;
                let note = if reused { "computed by another run".to_owned() } else { record.summary.clone() };
                let time = if started > 1 { format!("{total:.1}s in {started} attempts, {secs:.1}s the last") } else { format!("{secs:.1}s") };
                self.ui.say(format!("  {:<8} {label}  {time}  {note}", status.as_str()));
                self.push(&label, &record)?;
            }
            Some(Message::CorruptInput { digest, files }) if code == Some(EXIT_CORRUPT_INPUT) && self.instances[i].recoveries < 2 => {
                self.instances[i].recoveries += 1;
                let producers: Vec<usize> =
                    (0..self.instances.len()).filter(|&j| matches!(self.instances[j].state, State::Done { output } if output == digest)).collect();
                let names: Vec<&str> = producers.iter().map(|&j| self.plan.instances[j].label.as_str()).collect();
                self.ui.say(format!(
                    "  corrupt  {label}: input {} failed verification ({}); quarantined, recomputing {}",
                    digest.short(),
                    if files.is_empty() { "missing".to_owned() } else { files.join(", ") },
                    names.join(", ")
                ));
                self.events.write(Event::InputCorrupt {
                    stage: label.clone(),
                    digest,
                    files: files.clone(),
                    recompute: names.iter().map(|n| n.to_string()).collect(),
                })?;
                for j in producers {
                    self.instances[j].state = State::Waiting;
                    self.instances[j].result = None;
                }
                self.instances[i].state = State::Waiting;
            }
            other => {
                // A setting's error or a corrupt input would fail the same way again.
                let retryable = !matches!(&other, Some(Message::Failed { setting: Some(_), .. } | Message::CorruptInput { .. }));
                let message = match other {
                    Some(Message::Failed { message, setting: Some(key) }) => {
                        let inst = &self.plan.instances[i];
                        let stage = &self.plan.pipeline.stages[inst.stage].name;
                        format!("{}: {message}", self.plan.pipeline.locate(stage, inst.assignment.get(stage).map(String::as_str), &key))
                    }
                    Some(Message::Failed { message, setting: None }) => message,
                    Some(Message::CorruptInput { digest, .. }) => format!("input {} is still corrupt after recomputing it", digest.short()),
                    _ => exit.describe(),
                };
                let bounds = self.bounds(i);
                self.note_in_log(i, &format!("attempt {} ended after {secs:.1} s: {message}", self.instances[i].attempts.started));
                if retryable && self.instances[i].attempts.started <= bounds.retries {
                    let attempt = self.instances[i].attempts.started;
                    self.instances[i].attempts.earlier_s += secs;
                    let (error, log) = (message.clone(), self.log_path(i));
                    self.events.write(Event::StageRetry { stage: label.clone(), key, attempt, error, log, duration_s: secs })?;
                    self.ui.say(format!("  retry    {label}  attempt {attempt} of {} ended after {secs:.1}s: {message}", bounds.retries + 1));
                    self.instances[i].state = State::Ready { key };
                    return Ok(());
                }
                let message = match self.instances[i].attempts.started {
                    n if n > 1 => format!("{message}, on attempt {n} of {n} (`retries = {}`)", bounds.retries),
                    _ => message,
                };
                self.instances[i].state = State::Failed;
                self.instances[i].result = Some((Status::Failed, secs));
                self.relink_previous(i)?;
                let log = self.log_path(i);
                self.events.write(Event::StageFinished(Finished {
                    key: Some(key),
                    error: Some(message.clone()),
                    log: Some(log.clone()),
                    duration_s: Some(secs),
                    ..Finished::new(&label, Status::Failed)
                }))?;
                self.ui.say(format!("  FAILED   {label}  {secs:.1}s  {message}\n           log: {}", log.display()));
            }
        }
        Ok(())
    }
}

/// `runs/<id>/events.jsonl`: one JSON object per line, flushed as written, so a killed run
/// leaves a readable log. With `--json` each line is echoed to stdout.
struct EventLog {
    file: File,
    echo: bool,
    clock: Instant,
}

impl EventLog {
    fn create(run_dir: &Path, echo: bool) -> anyhow::Result<EventLog> {
        std::fs::create_dir_all(run_dir.join("logs"))?;
        let path: PathBuf = run_dir.join("events.jsonl");
        let file = File::create(&path).with_context(|| format!("creating {}", path.display()))?;
        Ok(EventLog { file, echo, clock: Instant::now() })
    }

    fn write(&mut self, event: Event) -> anyhow::Result<()> {
        let t = (self.clock.elapsed().as_secs_f64() * 1000.0).round() / 1000.0;
        let mut line = serde_json::to_string(&Logged { event, t })?;
        line.push('\n');
        // One write a line: a killed run leaves whole lines.
        self.file.write_all(line.as_bytes())?;
        if self.echo {
            print!("{line}");
        }
        Ok(())
    }
}
