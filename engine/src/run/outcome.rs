//! What an attempt's end means: an output committed (pushed where the remote takes pushes), a
//! damaged input recomputed, a retry within the stage's `retries`, or a failure with its log.

use std::io::Write;
use std::path::PathBuf;

use anyhow::Context as _;
use rlmflow_cache::{Digest, file_safe};

use super::{Attempts, Scheduler, State};
use crate::dispatch::Exit;
use crate::event::{Event, Finished, Status};
use crate::protocol::{EXIT_CORRUPT_INPUT, Message};

impl Scheduler<'_> {
    /// Appends the engine's word on instance `i`'s attempt to its log, so the log of an attempt
    /// that failed or was stopped says how it ended even when its process wrote nothing.
    fn note_in_log(&self, i: usize, line: &str) {
        let log = self.log_path(i);
        let appended = std::fs::OpenOptions::new().create(true).append(true).open(&log).and_then(|mut f| writeln!(f, "[rlmflow] {line}"));
        if let Err(e) = appended {
            self.ui.say(format!("  warning  could not write {}: {e}", log.display()));
        }
    }

    /// `runs/<id>/logs/<label>.log`, and `<label>.attempt-N.log` for a retry's.
    pub(super) fn log_path(&self, i: usize) -> PathBuf {
        let label = file_safe(&self.plan.instances[i].label);
        let name = match self.instances[i].attempts.started {
            0 | 1 => format!("{label}.log"),
            n => format!("{label}.attempt-{n}.log"),
        };
        self.store.run_dir(&self.run).join("logs").join(name)
    }
    /// An instance that could not be started (its worker binary is missing) fails like one
    /// whose process failed: its dependants are skipped, independent branches go on.
    pub(super) fn fail_unstarted(&mut self, i: usize, key: Digest, message: String) -> anyhow::Result<()> {
        let label = self.plan.instances[i].label.clone();
        self.instances[i].state = State::Failed;
        self.instances[i].result = Some((Status::Failed, 0.0));
        let (error, duration_s) = (Some(message.clone()), Some(0.0));
        self.events.write(Event::StageFinished(Finished { key: Some(key), error, duration_s, ..Finished::new(&label, Status::Failed) }))?;
        self.ui.say(format!("  FAILED   {label}  {message}"));
        Ok(())
    }

    pub(super) fn finish(&mut self, i: usize, exit: Exit, outcome: Option<Message>, secs: f64) -> anyhow::Result<()> {
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
                let on = self.instances[i].placed.as_ref().filter(|_| !reused).map_or(String::new(), |p| format!(" {}", p.gpu.device()));
                self.ui.say(format!("  {:<8} {label}  {time}{on}  {note}", status.as_str()));
                self.exchange.push(&label, &record, &mut self.events)?;
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
                // Out of memory where its estimate let others run beside it: once more, alone.
                let run = &mut self.instances[i];
                let shared = run.placed.as_ref().filter(|p| p.shares());
                if let Some(on) = shared.map(|p| p.gpu.device()).filter(|_| !run.alone && message.to_lowercase().contains("out of memory")) {
                    run.alone = true;
                    run.attempts.earlier_s += secs;
                    let attempt = run.attempts.started;
                    let error = format!("{message} (out of memory on {on}, which it shared: retried alone on a GPU)");
                    self.events.write(Event::StageRetry { stage: label.clone(), key, attempt, error, log: self.log_path(i), duration_s: secs })?;
                    self.ui.say(format!("  retry    {label}  out of memory on {on} beside other stages after {secs:.1}s; retried alone on a GPU"));
                    self.instances[i].state = State::Ready { key };
                    return Ok(());
                }
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
                let previous = self.last.get(&self.plan.id(i), &self.plan.instances[i].label);
                let store = self.store;
                self.links.failed(i, || Ok(previous.map(|key| store.fresh(&key)).transpose()?.flatten().map(|r| r.output)))?;
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
