//! The `probe` stage kind's operators as the planning binary sees them: settings, specs and
//! resources. They run in the `rlmflow-torch` worker (`operators/probe/torch`); every probe keeps
//! the encoder frozen and scores with `rlmflow_stages::probe::score`.
//!
//! `linear`: closed-form ridge regression (faer) to the 48 cell counts, rounded and clipped at
//! zero, from the frozen encoder's features (two rows: the projected CLS embedding and the mean
//! of the patch tokens) or, with `source = "pixels"`, from the raw radar image: the pixel
//! baseline, which reads no encoder (give its stage `inputs = { encoder = [] }` so it does not fan
//! out over the encoder's variants). The ridge strength is chosen on a held-out share of the
//! training split, then the ridge is refitted on all of it.

use rlmflow_stages::{InWorker, OperatorSpec, Resources, SettingError, Settings};
use serde::{Deserialize, Serialize};

/// The binary the probes run in.
pub const WORKER: &str = "rlmflow-torch";

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Source {
    Encoder,
    Pixels,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LinearSettings {
    pub source: Source,
    /// Ridge strengths tried (times the number of training frames), each in (0, 1e9].
    pub lambdas: Vec<f64>,
    /// Share of the training split held out to choose the strength, (0, 0.5].
    pub holdout: f64,
    /// CPU threads libtorch uses for the encoder's features, 1..=256 (part of the result, as in
    /// pretraining).
    pub threads: usize,
}

impl Default for LinearSettings {
    fn default() -> Self {
        LinearSettings { source: Source::Encoder, lambdas: vec![1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0], holdout: 0.2, threads: 2 }
    }
}

impl Settings for LinearSettings {
    fn check(&self) -> Result<(), SettingError> {
        if self.lambdas.is_empty() || self.lambdas.len() > 64 {
            return Err(SettingError::new("lambdas", "must list 1..=64 strengths"));
        }
        for (i, l) in self.lambdas.iter().enumerate() {
            if !(*l > 0.0 && *l <= 1e9) {
                return Err(SettingError::new(format!("lambdas.{i}"), format!("must be in (0, 1e9], not {l}")));
            }
        }
        if !(self.holdout > 0.0 && self.holdout <= 0.5) {
            return Err(SettingError::new("holdout", format!("must be in (0, 0.5], not {}", self.holdout)));
        }
        SettingError::check_range("threads", self.threads, 1..=256)
    }
}

pub fn linear_spec() -> OperatorSpec {
    OperatorSpec {
        name: "linear",
        kind: "probe",
        version: 1,
        inputs: Some(&["encoder", "scenes", "labels"]),
        summary: "closed-form ridge (faer) from frozen encoder features or raw pixels to the 48 cell counts",
    }
}

pub fn linear_resources(s: &LinearSettings) -> Resources {
    Resources { threads: s.threads, gpu: false }
}

/// `linear` as `rlmflow` registers it: validated and planned here, run by the worker.
pub fn linear() -> InWorker<LinearSettings> {
    InWorker { spec: linear_spec(), worker: WORKER, resources: linear_resources }
}

#[cfg(test)]
mod tests {
    use rlmflow_stages::DynOperator;

    use super::*;

    #[test]
    fn impossible_settings_name_their_key() {
        let key = |v: serde_json::Value| linear().settings(v).unwrap_err().key;
        assert_eq!(key(serde_json::json!({"source": "pixel"})), "source");
        assert_eq!(key(serde_json::json!({"lambdas": []})), "lambdas");
        assert_eq!(key(serde_json::json!({"lambdas": [1.0, -2.0]})), "lambdas.1");
        assert_eq!(key(serde_json::json!({"holdout": 0.9})), "holdout");
    }
}
