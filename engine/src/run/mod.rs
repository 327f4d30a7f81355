//! The scheduler: walks a plan's instances in dependency order, reuses every cached action, and
//! starts the others (`rlmflow exec KEY`) through a dispatcher (`dispatch/`: child processes or
//! HyperQueue tasks), independent ones concurrently within the [`budget`]. Beside it, each in a
//! module of its own: what a waiting instance becomes ([`resolve`]), what an attempt's end means
//! ([`outcome`]), the remote cache ([`exchange`]), the results links ([`links`]), the event log
//! ([`event_log`]) and the run's provenance ([`provenance`]).

mod budget;
mod event_log;
mod exchange;
mod links;
mod outcome;
mod provenance;
mod resolve;

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use std::sync::mpsc::{self, Sender};
use std::time::Instant;

use indicatif::ProgressBar;
use rlmflow_cache::{ActionRecord, Digest, GitState, InstanceRef, PlanEntry, Refs, RunPlan, Store, now_rfc3339, run_id};
use rlmflow_remote::Pulled;
use rlmflow_stages::{Device, Registry};

use crate::config::{Executor, RemoteSettings};
use crate::dispatch::{Dispatch, Launch, Local, Report};
use crate::event::{Event, Finished, Status};
use crate::history::Counts;
use crate::gpus::Gpu;
use crate::plan::{Freshness, Plan};
use crate::preflight::Checked;
use crate::protocol::Message;
use crate::ui::Ui;
use budget::{Budget, Grant, Placed};
use event_log::EventLog;
use exchange::{Exchange, PullEnd};
use links::ResultsLinks;

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

/// What reaches the scheduler's one wait: a dispatcher's report on a running instance, or the
/// end of a pull.
enum Arrival {
    Report(Report),
    Pulled(anyhow::Result<Pulled>),
}

struct Scheduler<'a> {
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
    /// The instances running now.
    running: BTreeMap<usize, Running>,
    budget: Budget,
    plan_dirty: bool,
    events: EventLog,
    ui: Ui,
    last: Refs,
    /// Outputs re-hashed this run (`verify_inputs`).
    verified: BTreeSet<Digest>,
    dispatch: Box<dyn Dispatch>,
    exchange: Exchange<'a>,
    links: ResultsLinks,
    /// Which ready instance starts first ([`Plan::start_order`]).
    start_order: Vec<usize>,
}

/// What the run knows of one stage instance.
struct InstanceRun {
    state: State,
    /// Its record as the preflight found it fresh, until the run uses it.
    known: Option<Box<ActionRecord>>,
    /// Its peak memory estimate, where its operator makes one: what it holds of a GPU.
    estimate: Option<u64>,
    /// Where its latest attempt was placed on a GPU.
    placed: Option<Placed>,
    /// Ran out of GPU memory beside other stages: its next attempt holds a GPU alone.
    alone: bool,
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
}

/// An instance's attempts in this run.
#[derive(Clone, Copy, Default)]
struct Attempts {
    started: u32,
    /// The seconds the attempts before the current one took.
    earlier_s: f64,
}

/// A running instance's attempt.
struct Running {
    since: Instant,
    grant: Grant,
    bar: ProgressBar,
    /// The outcome its process reported (done, reused, failed, a corrupt input), until it exits.
    outcome: Option<Message>,
}

/// What a run is told of one instance before it starts.
#[derive(Default)]
pub struct Admitted {
    pub selected: bool,
    /// Its record, where the preflight found it fresh: used without reading it again.
    pub known: Option<Box<ActionRecord>>,
    /// Its peak memory estimate, where its operator makes one: what it holds of a GPU.
    pub estimate: Option<u64>,
}

impl From<Checked> for Admitted {
    fn from(c: Checked) -> Admitted {
        let known = if let Freshness::Cached(record) = c.state { Some(record) } else { None };
        Admitted { selected: c.selected, known, estimate: c.fit.map(|f| f.footprint.peak_bytes) }
    }
}

/// Runs the plan's instances `admitted` selects (by instance); returns its summary.
pub fn run(plan: &Plan, registry: &Registry, store: &Store, admitted: Vec<Admitted>, opts: &RunOptions) -> anyhow::Result<Counts> {
    let _shared = store.lock_shared()?;
    store.sweep_tmp(None)?;
    // Before the run exists: a results directory that cannot be used stops it with nothing done.
    let links = plan.pipeline.results.as_deref().map(|dir| store.links(dir)).transpose()?;
    let run = run_id();
    let events = EventLog::create(&store.run_dir(&run), opts.json)?;
    let instances = admitted
        .into_iter()
        .map(|a| InstanceRun {
            state: if a.selected { State::Waiting } else { State::Excluded },
            estimate: a.estimate,
            placed: None,
            alone: false,
            known: a.known,
            key: None,
            result: None,
            platform: None,
            recoveries: 0,
            attempts: Attempts::default(),
        })
        .collect();
    let ui = Ui::new(opts.json);
    let dispatch = dispatcher(plan, store, &run, opts.device, opts.remote.as_ref(), &ui)?;
    let gpus = dispatch.gpus();
    if let Some(gpus) = gpus.as_ref().filter(|g| g.len() > 1) {
        ui.say(format!("  gpus     {}", gpus.iter().map(Gpu::describe).collect::<Vec<_>>().join(", ")));
    }
    let mut scheduler = Scheduler {
        plan,
        registry,
        store,
        opts,
        run,
        started: now_rfc3339(),
        git: None,
        instances,
        running: BTreeMap::new(),
        budget: Budget::new(opts.jobs, dispatch.max_threads(), gpus),
        plan_dirty: true,
        events,
        last: store.last_keys(&plan.pipeline.name)?,
        verified: Default::default(),
        dispatch,
        exchange: Exchange::new(opts.remote.as_ref(), plan.instances.len(), store, registry.catalog.clone(), ui.clone()),
        links: ResultsLinks::for_plan(links, plan, ui.clone()),
        ui,
        start_order: plan.start_order(),
    };
    scheduler.execute()?;
    Ok(scheduler.summary())
}

/// The pipeline's dispatcher. An existing HyperQueue server is checked here, before anything runs.
fn dispatcher(plan: &Plan, store: &Store, run: &str, device: Device, remote: Option<&RemoteSettings>, ui: &Ui) -> anyhow::Result<Box<dyn Dispatch>> {
    match plan.pipeline.executor {
        Executor::Local => Ok(Box::new(Local::new(device, plan.pipeline.gpus.as_deref())?)),
        #[cfg(feature = "python")]
        Executor::HyperQueue => {
            let dir = store.run_dir(run).join("hyperqueue");
            let ui = ui.clone();
            let note = Box::new(move |note: &str| ui.say(note.to_owned()));
            let hq = crate::dispatch::HyperQueue::connect(plan.pipeline.hyperqueue.clone(), &dir, run, remote, note)?;
            Ok(Box::new(hq))
        }
        #[cfg(not(feature = "python"))]
        Executor::HyperQueue => {
            let _ = (store, run, device, remote, ui);
            anyhow::bail!("executor = \"hyperqueue\" needs the embedded Python (build rlmflow with its default `python` feature)")
        }
    }
}

impl Scheduler<'_> {
    fn execute(&mut self) -> anyhow::Result<()> {
        let clock = Instant::now();
        let executor = self.dispatch.describe();
        self.announce(&executor)?;
        let (arrivals, arrived) = mpsc::channel::<(usize, Arrival)>();
        loop {
            self.resolve(&arrivals)?;
            self.write_plan_if_dirty()?;
            self.start_ready(&arrivals)?;
            if self.running.is_empty() && !self.exchange.any_under_way() {
                break;
            }
            let (i, arrival) = arrived.recv().expect("a running child always reports its exit, a pull its end");
            self.arrive(i, arrival)?;
        }
        self.write_plan_if_dirty()?;
        self.conclude(clock.elapsed().as_secs_f64(), &executor)
    }

    fn announce(&mut self, executor: &str) -> anyhow::Result<()> {
        let p = self.plan.pipeline;
        let selected = self.instances.iter().filter(|x| !matches!(x.state, State::Excluded)).count();
        self.events.write(Event::RunStarted {
            run: self.run.clone(),
            pipeline: p.name.clone(),
            file: p.file.clone(),
            instances: selected,
            jobs: self.opts.jobs,
            executor: executor.to_owned(),
        })?;
        let (file, jobs, run) = (p.file.display(), self.opts.jobs, &self.run);
        self.ui.say(format!("rlmflow run {file} ({selected} stage instances, {jobs} threads, {executor}, run {run})"));
        Ok(())
    }

    /// Starts the ready instances that fit in the budget, the longest chains first.
    fn start_ready(&mut self, arrivals: &Sender<(usize, Arrival)>) -> anyhow::Result<()> {
        for k in 0..self.start_order.len() {
            let i = self.start_order[k];
            let State::Ready { key } = self.instances[i].state else { continue };
            let op = self.registry.get(&self.plan.instances[i].operator).expect("validated operator");
            let wants = op.resources(&self.plan.instances[i].settings);
            // Without its estimate a stage is given a GPU whole.
            let estimate = self.instances[i].estimate.filter(|_| !self.instances[i].alone);
            let Some(grant) = self.budget.grant(&wants, estimate) else { continue };
            let exe = match crate::exec::executable(op) {
                Ok(exe) => exe,
                Err(e) => {
                    self.fail_unstarted(i, key, format!("{e:#}"))?;
                    continue;
                }
            };
            self.budget.take(&grant);
            self.instances[i].state = State::Running { key };
            self.instances[i].attempts.started += 1;
            self.note_git_state();
            let label = self.plan.instances[i].label.clone();
            let (threads, attempt) = (grant.threads, self.instances[i].attempts.started);
            let device = grant.placed.as_ref().map(|p| p.gpu.device());
            self.events.write(Event::StageStarted { stage: label.clone(), key, threads, attempt, device })?;
            self.instances[i].placed = grant.placed.clone();
            let bar = self.ui.bar(&label);
            let launch = self.launch(i, exe, key, &grant);
            self.running.insert(i, Running { since: Instant::now(), grant, bar, outcome: None });
            let arrivals = arrivals.clone();
            let reports = Arc::new(move |report| {
                let _ = arrivals.send((i, Arrival::Report(report)));
            });
            self.dispatch.start(launch, reports)?;
        }
        Ok(())
    }

    fn launch(&self, i: usize, exe: std::path::PathBuf, key: Digest, grant: &Grant) -> Launch {
        let (threads, gpu, placed) = (grant.threads, grant.gpu, grant.placed.as_ref().map(|p| p.gpu.clone()));
        let args = ["exec", &key.to_string(), "--store", &self.store.root().to_string_lossy(), "--threads", &threads.to_string()]
            .into_iter()
            .map(str::to_owned)
            .chain(["--device".to_owned(), self.opts.device.to_string()])
            .collect();
        let (label, log, store, device) = (self.plan.instances[i].label.clone(), self.log_path(i), self.store.root().to_path_buf(), self.opts.device);
        let replace_remote = self.exchange.replaces(&key);
        let timeout = self.bounds(i).timeout_s.map(std::time::Duration::from_secs_f64);
        let estimate = self.instances[i].estimate;
        Launch { exe, args, key, store, device, replace_remote, label, threads, gpu, placed, estimate, log, timeout }
    }

    /// What a running instance's process or a pull reported.
    fn arrive(&mut self, i: usize, arrival: Arrival) -> anyhow::Result<()> {
        let report = match arrival {
            Arrival::Pulled(pulled) => return self.pulled(i, pulled?),
            Arrival::Report(report) => report,
        };
        let running = self.running.get_mut(&i).expect("a report on a running instance");
        match report {
            Report::Message(Message::Progress { position, length, message }) => {
                if running.bar.length() != Some(length) {
                    running.bar.set_length(length);
                    running.bar.set_style(Ui::bar_style());
                }
                running.bar.set_position(position);
                running.bar.set_message(message);
            }
            Report::Message(Message::Live { dir }) => self.links.live(i, &dir),
            Report::Message(Message::Event { name, data }) => {
                self.events.write(Event::OperatorEvent { stage: self.plan.instances[i].label.clone(), name, data })?;
            }
            Report::Message(Message::Waiting) => running.bar.set_message("waiting for another run computing it"),
            Report::Message(message) => running.outcome = Some(message),
            Report::Exited(exit) => {
                let running = self.running.remove(&i).unwrap();
                self.budget.release(&running.grant);
                running.bar.finish_and_clear();
                self.finish(i, exit, running.outcome, running.since.elapsed().as_secs_f64())?;
            }
        }
        Ok(())
    }

    /// A pull has ended: a hit finishes the instance as `pulled` (verified, in the local store);
    /// anything else sends it back to be computed here.
    fn pulled(&mut self, i: usize, pulled: Pulled) -> anyhow::Result<()> {
        let State::Pulling { key } = self.instances[i].state else { unreachable!("a pull ended for an instance not pulling") };
        let label = self.plan.instances[i].label.clone();
        self.instances[i].state = State::Waiting;
        let PullEnd::Hit { record, bytes, seconds } = self.exchange.ended(&label, key, pulled, &mut self.events)? else { return Ok(()) };
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
        Ok(())
    }

    /// Instance `i` has its output: consumers may start, and its results link points at it.
    fn done(&mut self, i: usize, output: Digest) {
        self.instances[i].state = State::Done { output };
        self.links.done(i, &output);
    }

    /// The run's last event and lines, and its provenance.
    fn conclude(&mut self, wall_s: f64, executor: &str) -> anyhow::Result<()> {
        let s = self.summary();
        // A fold from +0.0: an empty f64 `sum()` is -0.0, printed as "-0.0s".
        let saved_s = self
            .instances
            .iter()
            .filter_map(|x| x.result)
            .filter(|r| matches!(r.0, Status::Reused | Status::Pulled))
            .fold(0.0, |total, r| total + r.1);
        let Counts { ran, reused, pulled, failed, skipped } = s;
        self.events.write(Event::RunFinished { ran, reused, pulled, failed, skipped, wall_s, saved_s })?;
        let pulled = if pulled > 0 { format!(", {pulled} pulled") } else { String::new() };
        self.ui
            .say(format!("done: {ran} ran, {reused} reused{pulled}, {failed} failed, {skipped} skipped in {wall_s:.1}s; reuse saved {saved_s:.1}s"));
        let run_dir = self.store.run_dir(&self.run);
        if failed > 0 {
            self.ui.say(format!("logs: {}", run_dir.join("logs").display()));
        }
        let p = self.plan.pipeline;
        let header = provenance::RunHeader {
            run: &self.run,
            file: &p.file,
            pipeline: &p.name,
            executor,
            wall_s,
            cpu: &self.plan.platform.cpu().model,
            extensions: &self.plan.platform.cpu().extensions,
            overrides: p.overrides.iter().map(|o| o.shown()).collect(),
        };
        let rows: Vec<provenance::Row> = (self.plan.instances.iter().zip(&self.instances))
            .filter_map(|(inst, x)| {
                let (status, seconds) = x.result?;
                let output = if let State::Done { output } = x.state { Some(output) } else { None };
                Some(provenance::Row { label: &inst.label, status, seconds, key: x.key, output, platform: x.platform.as_deref() })
            })
            .collect();
        self.ui.say(format!("  provenance  {}", provenance::write(&run_dir, &header, &rows)?.display()));
        for i in provenance::finals(&self.plan.instances) {
            if let State::Done { output } = &self.instances[i].state {
                self.ui.say(format!("  output  {}  {}", self.plan.instances[i].label, self.store.object_dir(output).display()));
            }
        }
        if let Some(dir) = self.links.dir() {
            self.ui.say(format!("  results {}  (a link per instance to its current output)", dir.display()));
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

    /// Asks git for the work tree's state the first time the run computes something: a run that
    /// only reuses has nothing a commit could explain, and the two `git` processes were most of
    /// a no-op run's time (`cargo xtask bench -p rlmflow-e2e --bench engine`).
    fn note_git_state(&mut self) {
        if self.git.is_none() {
            self.git = Some(crate::history::git_state(&self.plan.pipeline.file));
            self.plan_dirty = true;
        }
    }

    /// The run's plan in its record, and the pipeline's last keys, as soon as they change: a
    /// killed run still tells `status` what it was doing.
    fn write_plan_if_dirty(&mut self) -> anyhow::Result<()> {
        if !self.plan_dirty {
            return Ok(());
        }
        let instances = (self.plan.instances.iter().zip(&self.instances).enumerate())
            .filter(|(_, (_, x))| !matches!(x.state, State::Excluded))
            .map(|(i, (inst, x))| PlanEntry { label: inst.label.clone(), instance: self.plan.id(i), key: x.key })
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
        let resolved: Vec<(InstanceRef, &str, Digest)> = (self.plan.instances.iter().zip(&self.instances).enumerate())
            .filter_map(|(i, (inst, x))| x.key.map(|k| (self.plan.id(i), inst.label.as_str(), k)))
            .collect();
        self.store.update_last_keys(&self.plan.pipeline.name, &resolved)?;
        self.plan_dirty = false;
        Ok(())
    }
}
