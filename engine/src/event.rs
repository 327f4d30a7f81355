//! The run's event log: `runs/<id>/events.jsonl`, and stdout under `run --json`. One JSON object
//! a line, each an [`Event`] with the seconds since the run started (`t`); the executor writes
//! them, `runs` and `compare` read them back, and the end-to-end tests parse what a run printed,
//! all through these types.

use std::path::PathBuf;

use rlmflow_cache::Digest;
use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::reason::RunReason;

/// One line of the log.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Logged {
    #[serde(flatten)]
    pub event: Event,
    /// Seconds since the run started, to the millisecond.
    pub t: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Event {
    RunStarted {
        run: String,
        pipeline: String,
        file: PathBuf,
        instances: usize,
        jobs: usize,
        executor: String,
    },
    /// Instance `stage` will run at `key`, for these reasons.
    StagePlanned {
        stage: String,
        key: Digest,
        reasons: Vec<RunReason>,
    },
    StageStarted {
        stage: String,
        key: Digest,
        threads: usize,
        attempt: u32,
        /// The GPU the run placed it on (`cuda:2`), where it places them.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        device: Option<String>,
    },
    /// What an operator reported while it ran (`epoch`, `resumed`, ...).
    OperatorEvent {
        stage: String,
        name: String,
        data: Value,
    },
    /// An attempt ended without a result and another follows (`retries`).
    StageRetry {
        stage: String,
        key: Digest,
        attempt: u32,
        error: String,
        log: PathBuf,
        duration_s: f64,
    },
    StageFinished(Finished),
    /// The remote's artifact is not the one its record names.
    RemoteCorrupt {
        stage: String,
        key: Digest,
        why: String,
    },
    /// The remote's record is not signed by a trusted key.
    RemoteUntrusted {
        stage: String,
        key: Digest,
        why: String,
    },
    /// The remote is not used for the rest of the run.
    RemoteDown {
        remote: String,
        why: String,
    },
    PushRefused {
        stage: String,
        key: Digest,
        why: String,
    },
    /// The remote holds a record of this key naming another output (left as it was).
    RemoteDisagrees {
        stage: String,
        key: Digest,
        output: Digest,
        why: String,
    },
    Pushed {
        stage: String,
        key: Digest,
        bytes: u64,
        seconds: f64,
    },
    /// A stored output failed its check; these files differ.
    OutputCorrupt {
        stage: String,
        digest: Digest,
        files: Vec<String>,
    },
    /// An operator found an input damaged; these instances recompute it.
    InputCorrupt {
        stage: String,
        digest: Digest,
        files: Vec<String>,
        recompute: Vec<String>,
    },
    /// The claims after a run (`run --json` prints it last, after the run's own log): each
    /// verdict at the look the run ended at.
    Claims {
        seeds: usize,
        verdicts: Vec<rlmflow_stages::claims::Verdict>,
    },
    RunFinished {
        ran: usize,
        reused: usize,
        pulled: usize,
        failed: usize,
        skipped: usize,
        wall_s: f64,
        saved_s: f64,
    },
}

/// How an instance ended in this run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Status {
    Ran,
    Reused,
    Pulled,
    Failed,
    Skipped,
}

impl Status {
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Ran => "ran",
            Status::Reused => "reused",
            Status::Pulled => "pulled",
            Status::Failed => "failed",
            Status::Skipped => "skipped",
        }
    }
}

/// A `stage_finished` event: the instance, how it ended, and what that outcome has to say.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Finished {
    pub stage: String,
    pub status: Status,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub key: Option<Digest>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output: Option<Digest>,
    /// Seconds of this attempt.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub duration_s: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub attempts: Option<u32>,
    /// Seconds of every attempt together.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub total_s: Option<f64>,
    /// Seconds the reused or pulled result took to compute.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub saved_s: Option<f64>,
    /// A pull's bytes and seconds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub bytes: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seconds: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub summary: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metrics: Option<Value>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub log: Option<PathBuf>,
    /// Why a skipped instance did not run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
}

impl Finished {
    /// `stage` ended with `status`; the outcome's fields are set with struct update syntax.
    pub fn new(stage: &str, status: Status) -> Finished {
        Finished {
            stage: stage.to_owned(),
            status,
            key: None,
            output: None,
            duration_s: None,
            attempts: None,
            total_s: None,
            saved_s: None,
            bytes: None,
            seconds: None,
            summary: None,
            metrics: None,
            error: None,
            log: None,
            reason: None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each event is one JSON object with its name under `event` and its time under `t`, and
    /// reads back as what was written.
    #[test]
    fn events_round_trip_as_one_flat_object() {
        let key = Digest::of(b"key");
        let events = [
            Event::StagePlanned { stage: "a".into(), key, reasons: vec![RunReason::NeverRun] },
            Event::StageFinished(Finished { key: Some(key), output: Some(key), saved_s: Some(1.5), ..Finished::new("a[x]", Status::Reused) }),
            Event::RunFinished { ran: 1, reused: 2, pulled: 0, failed: 0, skipped: 0, wall_s: 0.5, saved_s: 1.5 },
        ];
        for event in events {
            let line = serde_json::to_string(&Logged { event, t: 0.25 }).unwrap();
            let object: Value = serde_json::from_str(&line).unwrap();
            assert!(object["event"].is_string() && object["t"] == 0.25, "{line}");
            let back: Logged = serde_json::from_str(&line).unwrap();
            assert_eq!(serde_json::to_string(&back).unwrap(), line);
        }
        let line = serde_json::to_string(&Logged { event: Event::StageFinished(Finished::new("b", Status::Skipped)), t: 1.0 }).unwrap();
        assert_eq!(line, r#"{"event":"stage_finished","stage":"b","status":"skipped","t":1.0}"#, "unset fields are left out");
    }
}
