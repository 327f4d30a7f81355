//! Small operators for testing the engine end to end, on kinds of their own:
//! `source` (-> Text) -> `map` (Text -> Mapped) -> `measure` (Mapped -> Measure) -> `collect`
//! (gathers every Measure and Mapped); `remap` (Mapped -> Mapped) makes cycles possible;
//! `join` (gathers Texts into one) merges the shards of a sharded `write-text`.
//!
//! Each operator appends a line to the file named by `RLMFLOW_TEST_TRACE` when it starts and
//! at each step, so tests can see what ran, in which process, from which checkpoint.

use std::fs::{self, OpenOptions};
use std::io::Write;
use std::time::Duration;

use anyhow::bail;
use rlmflow_stages::measure::Measures;
use rlmflow_stages::numerics::Target;
use rlmflow_stages::{
    Catalog, Context, Device, Footprint, InputOutlines, Items, Kernels, Numerics, Operator, OperatorSpec, Outcome, Registry, Resources, SettingError,
    Settings, Sharding, Slot, StageKind,
};
use serde::{Deserialize, Serialize};

pub fn registry() -> Registry {
    let markers = vec![("Text", "text.txt"), ("Mapped", "mapped.txt"), ("Measure", "count.txt"), ("Collection", "listing.txt")];
    let measures = vec![Measures { artifact: "Measure", metrics: measure_metrics, frames: None }];
    let mut r = Registry::new(Catalog { kinds: TEST_KINDS.to_vec(), markers, measures });
    r.add(WriteText).add(Shout).add(Count).add(Sample).add(Collect).add(Echo).add(JoinText).add(Score);
    // As `rlmflow-torch` installs its chain GEMM: traced with the variable it reads.
    r.set_kernel_pin(|| {
        trace(format!("kernel pin RLMFLOW_GEMM={}", std::env::var(rlmflow_stages::numerics::GEMM_VARIABLE).unwrap_or_default()));
        Ok(())
    });
    r
}

const TEST_KINDS: &[StageKind] = &[
    StageKind { name: "source", produces: "Text", inputs: &[], per_seed: false },
    StageKind { name: "map", produces: "Mapped", inputs: &[Slot::one("text", "Text")], per_seed: false },
    StageKind { name: "measure", produces: "Measure", inputs: &[Slot::one("mapped", "Mapped")], per_seed: true },
    StageKind { name: "remap", produces: "Mapped", inputs: &[Slot::one("mapped", "Mapped")], per_seed: false },
    StageKind { name: "join", produces: "Text", inputs: &[Slot::gather("parts", "Text")], per_seed: false },
    StageKind {
        name: "collect",
        produces: "Collection",
        inputs: &[Slot::gather("measures", "Measure"), Slot::gather("mapped", "Mapped")],
        per_seed: false,
    },
];

fn trace(line: String) {
    if let Ok(path) = std::env::var("RLMFLOW_TEST_TRACE") {
        let mut f = OpenOptions::new().create(true).append(true).open(path).expect("trace file");
        // One write per line: concurrent processes append whole lines (`writeln!` writes each
        // piece of its format separately, and two processes' pieces interleaved).
        f.write_all(format!("{line} pid={}\n", std::process::id()).as_bytes()).unwrap();
    }
}

/// Writes `text` after `steps` steps of `step_ms`, checkpointing each step.
pub struct WriteText;

#[derive(Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WriteTextSettings {
    pub text: String,
    pub steps: u32,
    pub step_ms: u64,
    pub fail: bool,
    /// Fails at run time with an error about this setting (a check only the data can make).
    pub fail_on: String,
    pub panic: bool,
    pub threads: usize,
    /// Asks for a GPU (the operator never uses one): for the scheduler's GPU rule.
    pub gpu: bool,
    /// Says it cannot run without a CUDA device (as a torch stage with `device = "cuda"`).
    pub cuda: bool,
    /// Its peak memory estimate in MiB (0: none), as a model operator makes one: what it holds
    /// of a GPU the run places it on.
    pub memory_mib: u64,
    /// Its first attempt fails as libtorch does when a GPU's memory runs out.
    pub oom_once: bool,
    /// Appends the process id to the text: the kind of bug `run --check-determinism` finds.
    pub nondeterministic: bool,
    /// Its bytes follow the numeric kernels, as a model operator's do: it appends every kernel
    /// variable of its environment to the text, so a choice that reaches it shows.
    pub numerics: Option<Numerics>,
    /// A file (tracked by content) whose text goes before `text`; it must be UTF-8.
    pub from: String,
    /// Writes `text` this many times over (a large artifact from a small setting).
    pub repeat: usize,
}

impl Default for WriteTextSettings {
    fn default() -> Self {
        WriteTextSettings {
            text: "hello".into(),
            steps: 0,
            step_ms: 0,
            fail: false,
            fail_on: String::new(),
            panic: false,
            threads: 1,
            gpu: false,
            cuda: false,
            memory_mib: 0,
            oom_once: false,
            nondeterministic: false,
            numerics: None,
            from: String::new(),
            repeat: 1,
        }
    }
}

impl Settings for WriteTextSettings {
    const NON_RESULT: &'static [&'static str] = &["threads", "step_ms", "gpu", "cuda", "memory_mib", "oom_once"];
    const TRACKED: &'static [&'static str] = &["from"];
    fn check_tracked(&self, key: &str, path: &std::path::Path) -> Result<(), SettingError> {
        match fs::read(path) {
            Ok(bytes) if std::str::from_utf8(&bytes).is_err() => Err(SettingError::new(key, "is not UTF-8 text")),
            _ => Ok(()),
        }
    }
    fn check(&self) -> Result<(), SettingError> {
        if self.threads == 0 {
            return Err(SettingError::new("threads", "must be at least 1"));
        }
        Ok(())
    }
}

impl Operator for WriteText {
    type Settings = WriteTextSettings;
    fn spec(&self) -> OperatorSpec {
        // The version can be bumped from outside to test `operator version 1 -> 2`.
        let version = std::env::var("RLMFLOW_TEST_VERSION").ok().and_then(|v| v.parse().ok()).unwrap_or(1);
        OperatorSpec { name: "write-text", kind: "source", version, inputs: None, summary: "writes a text" }
    }
    fn resources(&self, s: &WriteTextSettings) -> Resources {
        let device = if s.cuda { Device::Cuda(0) } else { Device::Cpu };
        Resources { threads: s.threads, gpu: s.gpu || s.cuda, needs_cuda: s.cuda, kernels: s.numerics.map(|numerics| Kernels { numerics, device }) }
    }
    fn footprint(&self, s: &WriteTextSettings, _: &InputOutlines, _: Target) -> Option<Footprint> {
        (s.memory_mib > 0).then_some(Footprint { parameters: 0, peak_bytes: s.memory_mib << 20, lower_with: "`memory_mib`" })
    }
    /// A shard writes a range of the text's characters (each with every step).
    fn sharding(&self) -> Option<Sharding<WriteTextSettings>> {
        Some(Sharding {
            unit: "characters",
            items: Items::Counted {
                count: |s| s.text.chars().count() as u64,
                part: |s, r| WriteTextSettings {
                    text: s.text.chars().skip(r.start as usize).take((r.end - r.start) as usize).collect(),
                    ..s.clone()
                },
            },
            merge: "join-text",
        })
    }
    fn run(&self, s: &WriteTextSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let done_file = ctx.checkpoint_dir.join("steps-done");
        let start: u32 = fs::read_to_string(&done_file).ok().and_then(|t| t.trim().parse().ok()).unwrap_or(0);
        let gpu = std::env::var("CUDA_VISIBLE_DEVICES").unwrap_or_else(|_| "unset".into());
        trace(format!("start write-text {} from={start} threads={} out={} gpu={gpu}", ctx.stage, ctx.threads, ctx.output_dir.display()));
        if s.panic {
            panic!("asked to panic");
        }
        if s.fail {
            bail!("asked to fail");
        }
        let oomed = ctx.checkpoint_dir.join("oomed");
        if s.oom_once && !oomed.exists() {
            fs::write(&oomed, "")?;
            bail!("CUDA out of memory. Tried to allocate 20.00 GiB (GPU 0; 79.19 GiB total capacity)");
        }
        if !s.fail_on.is_empty() {
            return Err(anyhow::Error::new(SettingError::new(s.fail_on.clone(), "is wrong for this data (a check only a run can make)"))
                .context("checking the data"));
        }
        let progress = ctx.progress(s.steps as u64, "steps");
        progress.set_position(start as u64);
        for step in start..s.steps {
            std::thread::sleep(Duration::from_millis(s.step_ms));
            // Written beside and renamed over, as a real checkpoint is: a kill between the
            // truncation and the write of a plain `fs::write` (long on a busy ext4) loses it.
            let part = done_file.with_extension("part");
            fs::write(&part, (step + 1).to_string())?;
            fs::rename(&part, &done_file)?;
            trace(format!("step write-text {} {}", ctx.stage, step + 1));
            progress.inc(1);
        }
        progress.finish();
        ctx.event("wrote", serde_json::json!({"bytes": s.text.len()}));
        let mut text = if s.nondeterministic { format!("{} {}", s.text, std::process::id()) } else { s.text.clone() };
        text = text.repeat(s.repeat);
        if let Some(from) = ctx.tracked_file("from")? {
            text = fs::read_to_string(from)? + &text;
        }
        if s.numerics.is_some() {
            for var in rlmflow_stages::numerics::KERNEL_VARIABLES {
                text += &format!("\n{var}={}", std::env::var(var).unwrap_or_default());
            }
        }
        fs::write(ctx.output_dir.join("text.txt"), text)?;
        Ok(Outcome { metrics: serde_json::json!({"chars": s.text.len()}), summary: format!("{} chars", s.text.len()) })
    }
}

/// Upper-cases its input and appends `suffix`.
pub struct Shout;

#[derive(Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ShoutSettings {
    pub suffix: String,
}

impl Default for ShoutSettings {
    fn default() -> Self {
        ShoutSettings { suffix: "!".into() }
    }
}

impl Settings for ShoutSettings {}

impl Operator for Shout {
    type Settings = ShoutSettings;
    fn spec(&self) -> OperatorSpec {
        OperatorSpec { name: "shout", kind: "map", version: 1, inputs: None, summary: "upper-cases" }
    }
    fn run(&self, s: &ShoutSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        trace(format!("start shout {}", ctx.stage));
        let text = fs::read_to_string(ctx.input("text")?.join("text.txt"))?;
        fs::write(ctx.output_dir.join("mapped.txt"), format!("{}{}", text.to_uppercase(), s.suffix))?;
        Ok(Outcome::default())
    }
}

/// Writes the character count of its input: equal lengths give equal bytes (early cutoff).
pub struct Count;

#[derive(Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct NoSettings {}
impl Settings for NoSettings {}

impl Operator for Count {
    type Settings = NoSettings;
    fn spec(&self) -> OperatorSpec {
        OperatorSpec { name: "count", kind: "measure", version: 1, inputs: None, summary: "counts characters" }
    }
    fn run(&self, _: &NoSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        trace(format!("start count {}", ctx.stage));
        let text = fs::read_to_string(ctx.input("mapped")?.join("mapped.txt"))?;
        let chars = text.chars().count();
        fs::write(ctx.output_dir.join("count.txt"), chars.to_string())?;
        Ok(Outcome { metrics: serde_json::json!({"chars": chars}), summary: format!("{chars} characters") })
    }
}

/// Writes one character of its input chosen by the seed: a stochastic measure, as a training
/// stage is, for testing seed fan-out.
pub struct Sample;

impl Operator for Sample {
    type Settings = NoSettings;
    fn spec(&self) -> OperatorSpec {
        OperatorSpec { name: "sample", kind: "measure", version: 1, inputs: None, summary: "picks a character by the seed" }
    }
    fn run(&self, _: &NoSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let chars: Vec<char> = fs::read_to_string(ctx.input("mapped")?.join("mapped.txt"))?.chars().collect();
        let index = ctx.seed as usize % chars.len().max(1);
        let pick = chars.get(index).copied().unwrap_or(' ');
        fs::write(ctx.output_dir.join("count.txt"), format!("seed {} picks {pick}", ctx.seed))?;
        Ok(Outcome { metrics: serde_json::json!({"index": index}), summary: format!("picks {pick}") })
    }
}

/// A Measure's metrics: `score.json` where [`Score`] wrote one, else `chars` of a count.
fn measure_metrics(dir: &std::path::Path) -> anyhow::Result<serde_json::Value> {
    match fs::read_to_string(dir.join("score.json")) {
        Ok(text) => Ok(serde_json::from_str(&text)?),
        Err(_) => Ok(serde_json::json!({"chars": fs::read_to_string(dir.join("count.txt"))?.trim().parse::<f64>().ok()})),
    }
}

/// A noisy measurement, as a trained model's metric is: `mean` plus `sd` times a normal draw of
/// the seed, the mean and the input's length (so an upstream change moves it), in `score.json`.
pub struct Score;

#[derive(Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct ScoreSettings {
    pub mean: f64,
    pub sd: f64,
}
impl Settings for ScoreSettings {}

impl Operator for Score {
    type Settings = ScoreSettings;
    fn spec(&self) -> OperatorSpec {
        OperatorSpec { name: "score", kind: "measure", version: 1, inputs: None, summary: "a noisy score by the seed" }
    }
    fn metrics(&self, _: &ScoreSettings) -> Vec<String> {
        vec!["score.value".into()]
    }
    fn run(&self, s: &ScoreSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        trace(format!("start score {} seed {}", ctx.stage, ctx.seed));
        let chars = fs::read_to_string(ctx.input("mapped")?.join("mapped.txt"))?.chars().count() as u64;
        // Two uniforms from the seed (splitmix64), a normal draw by Box-Muller.
        let mix = |x: u64| {
            let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        };
        let draw = ctx.seed ^ chars ^ s.mean.to_bits();
        let (u, v) = (mix(draw).max(1e-300), mix(draw.wrapping_mul(31) ^ 1));
        let value = s.mean + s.sd * (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos();
        let metrics = serde_json::json!({"score": {"value": value}});
        fs::write(ctx.output_dir.join("score.json"), metrics.to_string())?;
        fs::write(ctx.output_dir.join("count.txt"), format!("{value}"))?;
        Ok(Outcome { metrics, summary: format!("score {value:.3}") })
    }
}

/// Gathers every measure (and every mapped text) into one listing, by upstream label.
pub struct Collect;

impl Operator for Collect {
    type Settings = NoSettings;
    fn spec(&self) -> OperatorSpec {
        OperatorSpec { name: "collect", kind: "collect", version: 1, inputs: Some(&["measures"]), summary: "gathers" }
    }
    fn run(&self, _: &NoSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        trace(format!("start collect {}", ctx.stage));
        let mut listing = String::new();
        for input in ctx.gathered("measures") {
            listing.push_str(&format!("{} {}\n", input.label, fs::read_to_string(input.path.join("count.txt"))?));
        }
        fs::write(ctx.output_dir.join("listing.txt"), listing)?;
        Ok(Outcome::default())
    }
}

/// Copies its input (kind `remap`, which consumes what it produces).
pub struct Echo;

impl Operator for Echo {
    type Settings = NoSettings;
    fn spec(&self) -> OperatorSpec {
        OperatorSpec { name: "echo", kind: "remap", version: 1, inputs: None, summary: "copies" }
    }
    fn run(&self, _: &NoSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        fs::copy(ctx.input("mapped")?.join("mapped.txt"), ctx.output_dir.join("mapped.txt"))?;
        Ok(Outcome::default())
    }
}

/// Joins gathered texts in order: the merge of a sharded `write-text`.
pub struct JoinText;

impl Operator for JoinText {
    type Settings = NoSettings;
    fn spec(&self) -> OperatorSpec {
        OperatorSpec { name: "join-text", kind: "join", version: 1, inputs: None, summary: "joins texts" }
    }
    fn run(&self, _: &NoSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        trace(format!("start join-text {}", ctx.stage));
        let mut text = String::new();
        for input in ctx.gathered("parts") {
            text.push_str(&fs::read_to_string(input.path.join("text.txt"))?);
        }
        fs::write(ctx.output_dir.join("text.txt"), text)?;
        Ok(Outcome::default())
    }
}
