//! The `probe` stage kind's operators as the planning binary sees them: settings, specs and
//! resources. They run in the `rlmflow-torch` worker (`operators/probe/torch`); every probe keeps
//! the encoder frozen and scores with `rlmflow_stages::probe::score`.
//!
//! `linear`: closed-form ridge regression (libtorch, double precision) to the 48 cell counts, rounded and clipped at
//! zero, from the frozen encoder's features (two rows: the projected CLS embedding and the mean
//! of the patch tokens) or, with `source = "pixels"`, from the raw radar image: the pixel
//! baseline, which reads no encoder (give its stage `inputs = { encoder = [] }` so it does not fan
//! out over the encoder's variants). A third encoder row, `patches`, reads every patch token in
//! place (the spatial layout kept), as the pixel row reads every pixel: the like-for-like
//! comparison with the pixel baseline. The ridge strength is chosen on a validation slice of the
//! training split (by frame identity, episodes whole), then the ridge is refitted on all of it.
//!
//! Both probes check first that none of their test frames is among those the encoder trained on
//! or a tokenizer learnt from (`rlmflow_stages::identity`), and stop with both stages named
//! unless `allow_test_overlap` is set; the counts go into the artifact for the report.
//!
//! `clipcap`: the paper's caption probe (ClipCap). A transformer mapper turns the frozen
//! encoder's projected CLS embedding into `prefix` embeddings, and a GPT-style decoder over the
//! tokens stage's vocabulary continues them with the caption; both are trained on the training
//! captions (teacher forcing, one caption per frame per epoch), from scratch or with the decoder
//! started from GPT-2 weights at a given path. A validation slice of the training split is held
//! out for the per-epoch validation loss and a validation F1. The test frames' captions are generated (greedy
//! or length-normalised beam search, to the end token), read back by the LLM-free parser and
//! scored per cell like `linear`.

use rlmflow_stages::memory::{self, Blocks, FLOAT, TRAINED};
use rlmflow_stages::numerics::Target;
use rlmflow_stages::weights::{Expected, check_init};
use rlmflow_stages::{
    Device, Footprint, InWorker, InputOutlines, Kernels, Numerics, OperatorSpec, Outline, Resources, SettingError, Settings, Training,
};
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
    /// Share of the training split held out to choose the strength, (0, 0.5]: a validation
    /// slice by frame identity (episodes whole), like the split.
    pub holdout: f64,
    /// CPU threads libtorch uses for the encoder's features, 1..=256 (part of the result, as in
    /// pretraining).
    pub threads: usize,
    /// `portable` or `native` kernels for the encoder's features and the ridge (as in
    /// pretraining; see `rlmflow_stages::numerics`).
    pub numerics: Numerics,
    /// Run even when some test frames are among those the encoder trained on or its tokenizer
    /// learnt from (a deliberate study; the report flags the row). Off: such an overlap stops
    /// the stage.
    pub allow_test_overlap: bool,
}

impl Default for LinearSettings {
    fn default() -> Self {
        LinearSettings {
            source: Source::Encoder,
            lambdas: vec![1e-4, 1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0],
            holdout: 0.2,
            threads: 2,
            numerics: Numerics::Portable,
            allow_test_overlap: false,
        }
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

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Decode {
    Greedy,
    Beam,
}

/// What an `init` file must hold: GPT-2's blocks, by Hugging Face's names.
const GPT2_WEIGHTS: Expected = Expected {
    model: "GPT-2 (Hugging Face names)",
    names: &["h.0.attn.c_attn.weight", "transformer.h.0.attn.c_attn.weight"],
    source: "docs/guide/paper-scale.md (\"Pretrained weights\") fetches Hugging Face's `model.safetensors`",
};

/// Decoder sizes: `tiny` (laptop) and `gpt2` (GPT-2 small, which `init` weights fit).
pub const DECODERS: [&str; 2] = ["tiny", "gpt2"];

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default)]
pub struct ClipcapSettings {
    /// `tiny` (width 128, 2 blocks, 4 heads) or `gpt2` (width 768, 12 blocks, 12 heads).
    pub decoder: String,
    /// GPT-2 safetensors (Hugging Face names) to start the decoder from; empty: from scratch.
    /// Only with `decoder = "gpt2"`; GPT-2's token table is kept only if our vocabulary matched.
    pub init: String,
    /// Prefix embeddings the mapper makes (ClipCap: 10), 1..=64.
    pub prefix: i64,
    /// Mapper transformer blocks (ClipCap: 8), 1..=24.
    pub mapper_layers: i64,
    /// Share of the training split held out as the validation slice, (0, 0.5]: never trained
    /// on, it gives the per-epoch validation loss and a validation F1, on which settings such
    /// as `epochs` are chosen (the test split is only reported).
    pub validation: f64,
    pub decode: Decode,
    /// Beam width for `decode = "beam"`, 1..=64.
    pub beam: usize,
    /// Longest generated caption in tokens; 0: the tokens stage's context.
    pub max_tokens: usize,
    /// As `linear`'s: run despite test frames the encoder or a tokenizer learnt from.
    pub allow_test_overlap: bool,
    /// The schedule, optimiser and device (`rlmflow_stages::training`); `min_lr = lr` with no
    /// warmup is the paper's constant rate.
    #[serde(flatten)]
    pub training: Training,
}

impl Default for ClipcapSettings {
    fn default() -> Self {
        ClipcapSettings {
            decoder: "tiny".into(),
            init: String::new(),
            prefix: 10,
            mapper_layers: 2,
            validation: 0.1,
            decode: Decode::Greedy,
            beam: 5,
            max_tokens: 0,
            allow_test_overlap: false,
            training: Training { epochs: 4, ..Training::default() },
        }
    }
}

impl Settings for ClipcapSettings {
    const TRACKED: &'static [&'static str] = &["init"];

    fn check_tracked(&self, key: &str, path: &std::path::Path) -> Result<(), SettingError> {
        check_init(key, path, &GPT2_WEIGHTS)
    }

    fn check(&self) -> Result<(), SettingError> {
        if !DECODERS.contains(&self.decoder.as_str()) {
            return Err(SettingError::new("decoder", format!("unknown decoder `{}`; valid: {}", self.decoder, DECODERS.join(", "))));
        }
        if !self.init.is_empty() && self.decoder != "gpt2" {
            return Err(SettingError::new("init", "GPT-2 weights fit only decoder = \"gpt2\""));
        }
        SettingError::check_range("prefix", self.prefix, 1..=64)?;
        SettingError::check_range("mapper_layers", self.mapper_layers, 1..=24)?;
        if !(self.validation > 0.0 && self.validation <= 0.5) {
            return Err(SettingError::new("validation", format!("must be in (0, 0.5], not {}", self.validation)));
        }
        SettingError::check_range("beam", self.beam, 1..=64)?;
        SettingError::check_range("max_tokens", self.max_tokens, 0..=100_000)?;
        self.training.check()
    }
}

impl ClipcapSettings {
    /// The decoder's width, blocks and heads.
    pub fn decoder_shape(&self) -> (i64, i64, i64) {
        if self.decoder == "gpt2" { (768, 12, 12) } else { (128, 2, 4) }
    }
}

/// The frozen encoder held once, the mapper and decoder trained on `batch` captions: per caption
/// the mapper's blocks over its 2 x `prefix` tokens, the decoder's over `prefix` + context
/// tokens (GELU's tanh form keeps as much as QuickGELU), and the logits with their softmax and
/// gradient over the vocabulary.
fn clipcap_footprint(s: &ClipcapSettings, inputs: &InputOutlines, target: Target) -> Option<Footprint> {
    let tokens = Outline::of(inputs, "tokens")?;
    let (context, vocab, encoder) = (tokens.context?, tokens.vocab?, Outline::of(inputs, "encoder")?.model?);
    let (width, layers, _) = s.decoder_shape();
    let (width, prefix) = (width as u64, s.prefix as u64);
    let positions = prefix + context;
    let mapper = Blocks { width, layers: s.mapper_layers as u64, mlp: 4 * width, quick_gelu: false };
    let decoder = Blocks { width, layers: layers as u64, mlp: 4 * width, quick_gelu: true };
    let trained = memory::linear(encoder.embed, prefix * width)
        + prefix * width
        + mapper.parameters()
        + (vocab + positions) * width
        + decoder.parameters()
        + 2 * width;
    let per_caption = mapper.activations(2 * prefix) + decoder.activations(positions) + 3 * positions * vocab;
    let peak_bytes = encoder.parameters * FLOAT
        + trained * TRAINED
        + memory::activation_bytes(per_caption * s.training.micro_batch(), s.training.precision.on(target));
    Some(Footprint { parameters: encoder.parameters + trained, peak_bytes, lower_with: memory::LOWER_BY_ACCUMULATING })
}

fn clipcap_spec() -> OperatorSpec {
    OperatorSpec {
        name: "clipcap",
        kind: "probe",
        version: 8,
        inputs: Some(&["encoder", "scenes", "labels", "tokens"]),
        summary: "ClipCap caption probe: mapper and GPT decoder on the frozen CLS embedding, captions parsed and scored per cell",
    }
}

fn clipcap_resources(s: &ClipcapSettings) -> Resources {
    s.training.resources()
}

/// `clipcap` as `rlmflow` registers it: validated and planned here, run by the worker.
pub fn clipcap() -> InWorker<ClipcapSettings> {
    InWorker {
        spec: clipcap_spec(),
        worker: WORKER,
        resources: clipcap_resources,
        outline: |s, inputs| s.training.outline(inputs),
        footprint: clipcap_footprint,
        metrics: |_| rlmflow_stages::probe::metric_names(&["cls"]),
        run: None,
    }
}

fn linear_spec() -> OperatorSpec {
    OperatorSpec {
        name: "linear",
        kind: "probe",
        version: 5,
        inputs: Some(&["encoder", "scenes", "labels"]),
        summary: "closed-form ridge (libtorch) from frozen encoder features or raw pixels to the 48 cell counts",
    }
}

fn linear_resources(s: &LinearSettings) -> Resources {
    // Features come from the encoder on the run's device (`auto`: CUDA where there is one).
    Resources { threads: s.threads, kernels: Some(Kernels { numerics: s.numerics, device: Device::Auto }), ..Resources::default() }
}

/// `linear` as `rlmflow` registers it: validated and planned here, run by the worker.
pub fn linear() -> InWorker<LinearSettings> {
    InWorker {
        spec: linear_spec(),
        worker: WORKER,
        resources: linear_resources,
        outline: Outline::pass_on,
        footprint: |_, _, _| None,
        metrics: linear_metrics,
        run: None,
    }
}

/// The rows `linear` scores: the encoder's three feature sets, or the pixels.
fn linear_metrics(s: &LinearSettings) -> Vec<String> {
    match s.source {
        Source::Encoder => rlmflow_stages::probe::metric_names(&["cls", "mean-patch", "patches"]),
        Source::Pixels => rlmflow_stages::probe::metric_names(&["pixels"]),
    }
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EmbedSettings {
    /// Also write every patch token (`patches.npy`, frames x tokens x width x 4 bytes: the
    /// largest array by far); off: the CLS embedding and the mean patch token only.
    pub patches: bool,
    /// CPU threads libtorch uses, 1..=256 (part of the result, as in pretraining).
    pub threads: usize,
    /// `portable` or `native` kernels (see `rlmflow_stages::numerics`).
    pub numerics: Numerics,
}

impl Default for EmbedSettings {
    fn default() -> Self {
        EmbedSettings { patches: true, threads: 2, numerics: Numerics::Portable }
    }
}

impl Settings for EmbedSettings {
    fn check(&self) -> Result<(), SettingError> {
        SettingError::check_range("threads", self.threads, 1..=256)
    }
}

/// `frozen` (kind `embed`) as `rlmflow` registers it: the frozen encoder's features of every
/// frame, as `.npy` arrays with the split, for a probe of the user's own (a script) that reads
/// them with numpy. Run by the worker.
pub fn embed() -> InWorker<EmbedSettings> {
    InWorker {
        spec: OperatorSpec {
            name: "frozen",
            kind: "embed",
            version: 1,
            inputs: None,
            summary: "a frozen encoder's CLS embedding, mean patch token and patch tokens of every frame, as .npy arrays with the split",
        },
        worker: WORKER,
        resources: |s| Resources {
            threads: s.threads,
            kernels: Some(Kernels { numerics: s.numerics, device: Device::Auto }),
            ..Resources::default()
        },
        outline: Outline::pass_on,
        footprint: |_, _, _| None,
        metrics: |_| Vec::new(),
        run: None,
    }
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
        let key = |v: serde_json::Value| clipcap().settings(v).unwrap_err().key;
        assert_eq!(key(serde_json::json!({"decoder": "gpt3"})), "decoder");
        assert_eq!(key(serde_json::json!({"init": "/w/gpt2.safetensors"})), "init");
        assert_eq!(key(serde_json::json!({"decode": "sample"})), "decode");
        assert_eq!(key(serde_json::json!({"beam": 0})), "beam");
        let dir = std::env::temp_dir().join(format!("rlmflow-probe-init-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let gpt2 = dir.join("gpt2.safetensors");
        let zeros = [0u8; 16];
        let tensor = safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![2, 2], &zeros).unwrap();
        safetensors::serialize_to_file([("h.0.attn.c_attn.weight", tensor)], &None, &gpt2).unwrap();
        // The file is checked once the engine has resolved the tracked path.
        let settings = clipcap().settings(serde_json::json!({"decoder": "gpt2", "init": gpt2})).unwrap();
        assert!(clipcap().check_tracked(&settings, "init", &gpt2).is_ok());
        assert_eq!(clipcap().check_tracked(&settings, "init", &dir.join("absent.safetensors")).unwrap_err().key, "init");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
