//! A pipeline's past runs, read from what the store already keeps: each run's plan
//! (`runs/<id>/plan.json`: overrides, git state, instances with their keys) and event log
//! (`events.jsonl`: how each instance ended), with the records its keys name. `rlmflow runs`
//! lists them; `rlmflow compare` sets two of them side by side. No database: a run is cheap to
//! keep, and `gc --keep-runs` bounds how many are.

use std::collections::BTreeMap;
use std::io::BufRead;
use std::path::Path;
use std::process::Command;

use anyhow::bail;
use rlmflow_cache::{ActionRecord, GitState, RunPlan, Store};
use serde::Serialize;

use crate::event::{Event, Logged, Status};

/// One run of a pipeline.
#[derive(Debug, Serialize)]
pub struct PastRun {
    #[serde(flatten)]
    pub plan: RunPlan,
    /// How each instance ended, by label; an instance the run did not reach has none.
    pub outcomes: BTreeMap<String, Status>,
    /// Whether the run reached its end (a killed run, or one still going, did not).
    pub finished: bool,
    /// Whether it finished with the keys of the run before it and nothing failed: a plain
    /// rerun, in which nothing differs (`runs` folds it, `compare` passes over it unless named).
    pub repeats: bool,
}

/// How many instances of a run ended each way: what `run` returns (for the exit status and
/// tests), and what `runs` reads back from a run's events.
#[derive(Debug, Default, Serialize)]
pub struct Counts {
    pub ran: usize,
    pub reused: usize,
    pub pulled: usize,
    pub failed: usize,
    pub skipped: usize,
}

impl Counts {
    /// How many of `outcomes` ended each way.
    pub fn of(outcomes: impl Iterator<Item = Status>) -> Counts {
        let mut counts = Counts::default();
        for outcome in outcomes {
            match outcome {
                Status::Ran => counts.ran += 1,
                Status::Reused => counts.reused += 1,
                Status::Pulled => counts.pulled += 1,
                Status::Failed => counts.failed += 1,
                Status::Skipped => counts.skipped += 1,
            }
        }
        counts
    }
}

impl PastRun {
    pub fn id(&self) -> &str {
        &self.plan.run
    }

    pub fn counts(&self) -> Counts {
        Counts::of(self.outcomes.values().copied())
    }

    /// Each instance with a key, in plan order, with its record where the store still has it
    /// (`gc` may have collected it).
    pub fn records(&self, store: &Store) -> anyhow::Result<Vec<(&rlmflow_cache::PlanEntry, Option<ActionRecord>)>> {
        let mut out = Vec::new();
        for entry in &self.plan.instances {
            let Some(key) = entry.key else { continue };
            out.push((entry, store.record(&key)?));
        }
        Ok(out)
    }
}

/// The runs of pipeline `name` in `store`, newest first.
pub fn runs_of(store: &Store, name: &str) -> anyhow::Result<Vec<PastRun>> {
    let mut runs = Vec::new();
    for id in store.runs()?.into_iter().rev() {
        let Some(plan) = store.plan(&id)? else { continue };
        if plan.pipeline != name {
            continue;
        }
        let (outcomes, finished) = outcomes(&store.run_dir(&id).join("events.jsonl"));
        runs.push(PastRun { plan, outcomes, finished, repeats: false });
    }
    // Newest first: each run against the one before it in time.
    let keys = |run: &PastRun| run.plan.instances.iter().map(|e| (e.label.clone(), e.key)).collect::<Vec<_>>();
    for i in 0..runs.len().saturating_sub(1) {
        runs[i].repeats = runs[i].finished && runs[i].counts().failed == 0 && keys(&runs[i]) == keys(&runs[i + 1]);
    }
    Ok(runs)
}

/// The run of `runs` whose id is `id` or starts with it; an error lists the ids otherwise.
pub fn find<'r>(runs: &'r [PastRun], id: &str, pipeline: &str) -> anyhow::Result<&'r PastRun> {
    let matching: Vec<&PastRun> = runs.iter().filter(|r| r.id().starts_with(id)).collect();
    match matching.as_slice() {
        [one] => Ok(one),
        [] => {
            let ids: Vec<&str> = runs.iter().take(5).map(PastRun::id).collect();
            bail!(
                "no run `{id}` of pipeline `{pipeline}`; its newest: {} (`rlmflow runs` lists them all)",
                if ids.is_empty() { "none yet".to_owned() } else { ids.join(", ") }
            )
        }
        many => bail!("`{id}` names {} runs ({}); give more of the id", many.len(), many.iter().map(|r| r.id()).collect::<Vec<_>>().join(", ")),
    }
}

/// Each instance's last `stage_finished` status, and whether the log ends with `run_finished`.
/// A line a killed run cut short is skipped: the log is flushed line by line, so only the last
/// can be.
fn outcomes(events: &Path) -> (BTreeMap<String, Status>, bool) {
    let mut outcomes = BTreeMap::new();
    let mut finished = false;
    let Ok(file) = std::fs::File::open(events) else { return (outcomes, finished) };
    for line in std::io::BufReader::new(file).lines() {
        let Ok(line) = line else { break };
        let Ok(logged) = serde_json::from_str::<Logged>(&line) else { continue };
        match logged.event {
            Event::StageFinished(f) => {
                outcomes.insert(f.stage, f.status);
            }
            Event::RunFinished { .. } => finished = true,
            _ => {}
        }
    }
    (outcomes, finished)
}

/// The git commit of the work tree holding `file`, and whether its tracked files have changed;
/// `None` outside a git work tree or without git. Untracked files do not count: the store and
/// `results/` usually sit untracked beside the pipeline.
pub fn git_state(file: &Path) -> Option<GitState> {
    let dir = file.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let git = |args: &[&str]| -> Option<String> {
        let out = Command::new("git").arg("-C").arg(dir).args(args).stdin(std::process::Stdio::null()).output().ok()?;
        out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_owned())
    };
    let commit = git(&["rev-parse", "--verify", "HEAD"])?;
    let dirty = !git(&["status", "--porcelain", "--untracked-files=no"])?.is_empty();
    Some(GitState { commit, dirty })
}

/// `rlmflow runs`: each run, newest first, with its git state, overrides and counts, then the
/// headline (the record's summary) of each instance it computed or pulled; consecutive plain
/// reruns ([`PastRun::repeats`]) folded into one line (`all`: every run, every instance).
pub fn listing(store: &Store, runs: &[PastRun], all: bool) -> anyhow::Result<String> {
    let mut out = String::new();
    let mut folded: Vec<&PastRun> = Vec::new();
    let fold = |folded: &mut Vec<&PastRun>, out: &mut String| {
        if let (Some(newest), Some(oldest)) = (folded.first(), folded.last()) {
            let span = if folded.len() == 1 { newest.id().to_owned() } else { format!("{} back to {}", newest.id(), oldest.id()) };
            *out += &format!("{} rerun{} with the keys of the run before: {span}\n", folded.len(), if folded.len() == 1 { "" } else { "s" });
        }
        folded.clear();
    };
    for run in runs {
        // Plain reruns fold into one line (each shown with --all).
        if !all && run.repeats {
            folded.push(run);
            continue;
        }
        fold(&mut folded, &mut out);
        let git = match &run.plan.git {
            Some(g) => format!("  git {}{}", &g.commit[..g.commit.len().min(12)], if g.dirty { " (dirty)" } else { "" }),
            None => String::new(),
        };
        // Each as the command line gave it (a run from before the flag was recorded: `--set`).
        let set: String = run.plan.overrides.iter().map(|o| if o.starts_with("--set") { format!("  {o}") } else { format!("  --set {o}") }).collect();
        out += &format!("{}  {}{git}{set}\n", run.id(), run.plan.started);
        let c = run.counts();
        let end = if run.finished { "" } else { "; did not finish (killed, or still running)" };
        out += &format!("  {} ran, {} reused, {} pulled, {} failed, {} skipped{end}\n", c.ran, c.reused, c.pulled, c.failed, c.skipped);
        for (entry, record) in run.records(store)? {
            let outcome = run.outcomes.get(&entry.label).copied();
            if !all && !matches!(outcome, Some(Status::Ran | Status::Pulled | Status::Failed)) {
                continue;
            }
            let headline = match &record {
                Some(r) => r.summary.clone(),
                None if outcome == Some(Status::Failed) => "(see the run's log)".to_owned(),
                None => "(record collected by gc)".to_owned(),
            };
            let outcome = outcome.map_or("-", Status::as_str);
            out += &format!("{}\n", format!("    {outcome:<7} {}  {headline}", entry.label).trim_end());
        }
    }
    fold(&mut folded, &mut out);
    Ok(out)
}
