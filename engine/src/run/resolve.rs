//! Moving waiting instances on once their inputs are settled: reused from the store (its output
//! re-hashed first with `--verify-inputs`), pulled from the remote cache, skipped after a failed
//! upstream, or made ready to start with the reasons it runs.

use std::sync::mpsc::Sender;

use rlmflow_cache::Digest;

use super::exchange::Ask;
use super::{Arrival, Scheduler, State};
use crate::event::{Event, Finished, Status};
use crate::reason::why;

impl Scheduler<'_> {
    /// Moves waiting instances whose inputs are settled to ready, reused, pulling or skipped.
    pub(super) fn resolve(&mut self, arrivals: &Sender<(usize, Arrival)>) -> anyhow::Result<()> {
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
            match self.exchange.ask(i) {
                Ask::Now(remote) => {
                    self.instances[i].state = State::Pulling { key };
                    let arrivals = arrivals.clone();
                    let produces = self.plan.pipeline.stages[inst.stage].kind.produces;
                    self.exchange.pull(remote, key, produces, &inst.label, move |pulled| {
                        let _ = arrivals.send((i, Arrival::Pulled(pulled)));
                    });
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
            let reasons = why(Some(self.store), self.last.get(&self.plan.id(i), &inst.label).as_ref(), &key, &preimage, &stage.name, resumes)?;
            self.ui.say(format!("  run      {}  ({})", inst.label, crate::ui::words(&reasons)));
            self.events.write(Event::StagePlanned { stage: inst.label.clone(), key, reasons })?;
            // The operator reads a snapshot of each tracked path, by the digest in its key.
            if let Err(e) = self.plan.snapshot_tracked(i, self.store) {
                self.fail_unstarted(i, key, format!("{e:#}"))?;
                continue;
            }
            self.store.write_request(&self.plan.request(i, key, preimage))?;
            self.instances[i].state = State::Ready { key };
        }
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
}
