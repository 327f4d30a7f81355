//! What a run shows on a terminal: one line per event, a bar per running stage and per artifact
//! moving to or from the remote cache; plain lines when stdout is not a terminal, nothing but the
//! event log with `--json`. Where a run, the status table and the reasons are put into words,
//! an instance's record or why it would run (`inspect`), and what a check found (`checks`).
//! Tables with renderings of their own (`compare`, `digests`, `dag`, `runs`) keep them beside
//! their data; pull, push, gc, key and pin print a line each of their own.

mod checks;
mod inspect;

pub(crate) use checks::{Rejected, against, finding, store_check};
pub(crate) use inspect::{Explained, explained, shown};

use std::fmt;

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use rlmflow_cache::Change;
use rlmflow_remote::Remote;
use serde_json::json;

use crate::plan::{Freshness, Plan};
use crate::preflight::Checked;
use crate::reason::{RunReason, Waiting};

/// Progress bars on a terminal; plain lines otherwise.
#[derive(Clone)]
pub(crate) struct Ui {
    multi: MultiProgress,
    quiet: bool,
}

impl Ui {
    pub(crate) fn new(json: bool) -> Ui {
        let multi = MultiProgress::new();
        if json {
            multi.set_draw_target(ProgressDrawTarget::hidden());
        }
        Ui { multi, quiet: json }
    }

    pub(crate) fn say(&self, line: String) {
        if self.quiet {
            return;
        }
        if self.multi.is_hidden() {
            println!("{line}");
        } else {
            let _ = self.multi.println(line);
        }
    }

    /// A running stage's spinner, until the stage reports a length.
    pub(crate) fn bar(&self, label: &str) -> ProgressBar {
        let bar = self.multi.add(ProgressBar::new_spinner());
        bar.set_style(ProgressStyle::with_template("  {spinner} {prefix} {elapsed} {msg}").unwrap());
        bar.set_prefix(label.to_owned());
        bar.enable_steady_tick(std::time::Duration::from_millis(120));
        bar
    }

    pub(crate) fn bar_style() -> ProgressStyle {
        ProgressStyle::with_template("  {prefix} [{bar:30}] {pos}/{len} {msg} ({elapsed}, eta {eta})").unwrap().progress_chars("=> ")
    }

    /// A bar for `label`'s artifact moving to or from the remote cache (`verb`: "pulling",
    /// "pushing"), drawn once its bytes move (a miss, or an object the other side has, draws
    /// none) and cleared when dropped.
    pub(crate) fn transfer(&self, label: &str, verb: &str) -> TransferBar {
        TransferBar { ui: self.clone(), label: format!("{label} {verb}"), bar: None }
    }
}

/// See [`Ui::transfer`].
pub(crate) struct TransferBar {
    ui: Ui,
    label: String,
    bar: Option<ProgressBar>,
}

impl TransferBar {
    /// `done` of `total` bytes have moved.
    pub(crate) fn moved(&mut self, done: u64, total: u64) {
        let bar = self.bar.get_or_insert_with(|| {
            let bar = self.ui.multi.add(ProgressBar::new(total));
            let style = ProgressStyle::with_template("  {prefix} [{bar:30}] {bytes}/{total_bytes} ({bytes_per_sec}, eta {eta})").unwrap();
            bar.set_style(style.progress_chars("=> "));
            bar.set_prefix(self.label.clone());
            bar
        });
        bar.set_position(done);
    }
}

impl Drop for TransferBar {
    fn drop(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

/// Prints the warnings every store met during the command (damage read as absent), each once:
/// what every command ends with.
pub(crate) fn print_store_warnings() {
    for warning in rlmflow_cache::take_all_warnings() {
        eprintln!("warning: {warning}");
    }
}

/// Prints where each selected instance stands (`status`, `run --dry-run`), with the memory
/// estimate of each that will run.
pub(crate) fn print_status(plan: &Plan, instances: &[Checked], remote: Option<&Remote>, json: bool) {
    let width = plan.instances.iter().map(|i| i.label.len()).max().unwrap_or(0);
    if let Some(remote) = remote.filter(|r| !r.verified() && !json) {
        println!("  note      remote cache {}: its records are used unverified (no `remote_trusted_keys`)", remote.url());
    }
    for (i, Checked { state, fit, .. }) in instances.iter().enumerate().filter(|(_, c)| c.selected) {
        let label = &plan.instances[i].label;
        if json {
            let memory = fit.as_ref().map(|f| {
                json!({"parameters": f.footprint.parameters, "peak_bytes": f.footprint.peak_bytes, "capacity_bytes": f.capacity, "fits": !f.exceeds()})
            });
            let line = match state {
                Freshness::Cached(r) => json!({"stage": label, "state": "cached", "key": r.key, "output": r.output}),
                Freshness::Stale { key, reasons, .. } => {
                    let remote = remote.map(|r| r.holds(key));
                    json!({"stage": label, "state": "will run", "key": key, "reasons": reasons, "memory": memory, "remote_holds": remote})
                }
                Freshness::Pending(waiting) => json!({"stage": label, "state": "pending", "waiting": waiting, "memory": memory}),
            };
            println!("{line}");
            continue;
        }
        match state {
            Freshness::Cached(r) => println!("  cached    {label:width$}  (ran {:.1}s, {})", r.duration_s, r.started),
            Freshness::Stale { key, reasons, .. } => {
                let held = if remote.is_some_and(|r| r.holds(key)) { "; the remote cache holds it" } else { "" };
                println!("  will run  {label:width$}  {}{held}", words(reasons));
            }
            Freshness::Pending(waiting) => println!("  pending   {label:width$}  {waiting}"),
        }
        if let (false, Some(fit)) = (matches!(state, Freshness::Cached(_)), fit) {
            let verdict = if fit.exceeds() { "  DOES NOT FIT" } else { "" };
            println!("            {:width$}  {}{verdict}", "", fit.describe());
        }
    }
}

/// The claims at a look, as `run` ends and `rlmflow claims` prints them: a line per claim (its
/// verdict, at how many seeds, the paper's figures) and one per comparison (the mean paired
/// difference and its interval against the margin).
pub(crate) fn claims(look: &crate::claims::Look, level: f64) -> String {
    use rlmflow_stages::claims::{Decision, signed};
    let rule = match look.max_seeds {
        Some(max) => format!("seeds added one at a time up to {max}"),
        None => "the listed seeds".to_owned(),
    };
    let decided = look.verdicts.iter().filter(|v| v.decision != Decision::Undecided).count();
    // The seeds the verdicts read: a look whose instances are not all computed reads fewer.
    let read = look.verdicts.iter().flat_map(|v| &v.comparisons).map(|c| c.differences.len()).max().unwrap_or(0);
    let mut out = format!(
        "claims: {decided} of {} decided after {read} seeds ({rule}; each verdict wrong with probability at most {level})\n",
        look.verdicts.len()
    );
    let width = look.verdicts.iter().map(|v| v.claim.len()).max().unwrap_or(0);
    for v in &look.verdicts {
        let word = match v.decision {
            Decision::Holds => "holds",
            Decision::Fails => "FAILS",
            Decision::Undecided => "undecided",
        };
        let at = match v.decided_at {
            Some(n) => format!("at {n} seeds"),
            None => format!("at {} seeds", v.seeds),
        };
        let required = if v.required { " (required)" } else { "" };
        let paper = v.paper.as_ref().map_or(String::new(), |p| format!("; the paper: {p}"));
        out += &format!("  {word:<9}  {:width$}  {at}{required}{paper}\n", v.claim);
        for c in &v.comparisons {
            let interval = match c.interval {
                Some((lo, hi)) => format!("interval [{}, {}] against margin {}", signed(lo), signed(hi), signed(v.margin)),
                None => "too few seeds for an interval".to_owned(),
            };
            let mean = c.mean.map_or("-".to_owned(), signed);
            out += &format!("             {} vs {}: {mean} over {} seeds, {interval}\n", c.better, c.than, c.differences.len());
        }
    }
    if !look.missing.is_empty() {
        out += &format!("  not in the store yet (a run computes them): {}\n", look.missing.join(", "));
    }
    out
}

/// `explain CLAIM`: the claim's verdict in the newest run that computed it, and the change
/// that made it read otherwise than in the run before.
pub(crate) fn claim_flip(flip: &crate::claims::ClaimFlip, claim: &str) -> String {
    let decision = |v: &rlmflow_stages::claims::Verdict| format!("{:?} at {} seeds", v.decision, v.seeds).to_lowercase();
    let (run, verdict) = &flip.now;
    let mut out = format!("claim {claim}: {} in run {run}\n", decision(verdict));
    match &flip.before {
        None => out += "  every earlier run that computed it decided the same\n",
        Some((then, old, changed)) => {
            out += &format!("  {} in run {then}, before; what changed since:\n", decision(old));
            if changed.is_empty() {
                out += "    no setting or version: only seeds or upstream outputs (the same settings gave other values)\n";
            }
            for c in changed {
                let words = match &c.changes {
                    Some(changes) => changes.iter().map(|change| describe(&c.stage, change)).collect::<Vec<_>>().join("; "),
                    None => "changed (a record was collected, so not what)".to_owned(),
                };
                out += &format!("    {}: {words}\n", c.label);
            }
        }
    }
    out
}

/// Reasons as one line: `never run`, `pretrain.alpha 1 -> 4; input tokens changed`.
pub(crate) fn words(reasons: &[RunReason]) -> String {
    reasons.iter().map(ToString::to_string).collect::<Vec<_>>().join("; ")
}

impl fmt::Display for RunReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            RunReason::NeverRun => write!(f, "never run"),
            RunReason::OutputGone => write!(f, "its output is gone (quarantined by verify, or collected)"),
            RunReason::Failed { error, resumes_from: Some(from) } => write!(f, "failed: {error}; a rerun resumes from {from}"),
            RunReason::Failed { error, resumes_from: None } => write!(f, "failed: {error}"),
            RunReason::Interrupted { resumes_from } => write!(f, "interrupted; resumes from {resumes_from}"),
            RunReason::Unfinished => write!(f, "its last attempt did not finish"),
            RunReason::Running => write!(f, "being computed now by another run"),
            RunReason::RecordCollected => write!(f, "changed since its last run (whose record was collected)"),
            RunReason::KeyChanged => write!(f, "changed since its last run"),
            RunReason::Changed { stage, change, files, more_files } => {
                write!(f, "{}", describe(stage, change))?;
                if !files.is_empty() {
                    let more = if *more_files > 0 { format!(" and {more_files} more") } else { String::new() };
                    write!(f, ": {}{more} changed", files.join(", "))?;
                }
                Ok(())
            }
        }
    }
}

impl fmt::Display for Waiting {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "input {} ({}) will be recomputed first", self.slot, self.input)
    }
}

/// A change as `status` prints it: settings are prefixed with the stage (`pretrain.alpha ...`).
pub(crate) fn describe(stage: &str, change: &Change) -> String {
    match change {
        Change::Setting { .. } => format!("{stage}.{change}"),
        _ => change.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_reason_reads_as_the_terminal_has_always_shown_it() {
        let changed = |change: Change, files: &[&str], more_files: usize| RunReason::Changed {
            stage: "pretrain".into(),
            change,
            files: files.iter().map(|f| f.to_string()).collect(),
            more_files,
        };
        let cases = [
            (RunReason::NeverRun, "never run"),
            (RunReason::OutputGone, "its output is gone (quarantined by verify, or collected)"),
            (
                RunReason::Failed { error: "batch: too large".into(), resumes_from: Some("its checkpoint".into()) },
                "failed: batch: too large; a rerun resumes from its checkpoint",
            ),
            (RunReason::Failed { error: "batch: too large".into(), resumes_from: None }, "failed: batch: too large"),
            (RunReason::Interrupted { resumes_from: "its checkpoint".into() }, "interrupted; resumes from its checkpoint"),
            (RunReason::Unfinished, "its last attempt did not finish"),
            (RunReason::RecordCollected, "changed since its last run (whose record was collected)"),
            (RunReason::KeyChanged, "changed since its last run"),
            (changed(Change::Setting { key: "alpha".into(), old: Some(json!(1)), new: Some(json!(4)) }, &[], 0), "pretrain.alpha 1 -> 4"),
            (changed(Change::OperatorVersion { old: 1, new: 2 }, &[], 0), "operator version 1 -> 2"),
            (
                changed(Change::InputChanged { slot: "source".into(), label: String::new() }, &["a.npy", "b.npy"], 3),
                "input source changed: a.npy, b.npy and 3 more changed",
            ),
        ];
        for (reason, words) in cases {
            assert_eq!(reason.to_string(), words);
        }
        assert_eq!(Waiting { slot: "scenes".into(), input: "scenes[a]".into() }.to_string(), "input scenes (scenes[a]) will be recomputed first");
    }

    #[test]
    fn a_reason_as_data_names_its_kind_and_fields() {
        let reason = RunReason::Changed {
            stage: "map".into(),
            change: Change::Setting { key: "suffix".into(), old: Some(json!("!")), new: Some(json!("!!")) },
            files: vec![],
            more_files: 0,
        };
        let expected = json!({"reason": "changed", "stage": "map", "change": "setting", "key": "suffix", "old": "!", "new": "!!"});
        assert_eq!(serde_json::to_value(&reason).unwrap(), expected);
        let failed = RunReason::Failed { error: "boom".into(), resumes_from: None };
        assert_eq!(serde_json::to_value(&failed).unwrap(), json!({"reason": "failed", "error": "boom", "resumes_from": null}));
    }
}
