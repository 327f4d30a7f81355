//! The `llm` operator: captions from any OpenAI-compatible chat-completions endpoint, asked
//! with the paper's prompts (appendix, "Natural Language Caption Generation") and checked with
//! the LLM-free parser.
//!
//! * Prompt: the paper's system prompt; the user prompt holds the frame's grid as JSON with
//!   numbers as words and the sector keys of each bin shuffled (`total_vehicles` first, as in the
//!   paper's example), the explanation of every distance bin and of every key present, the final
//!   instruction, and, for a `no_distance_numbers` share of frames, "Do not add any distance bin
//!   numbers". Shuffles and that choice are seeded per frame.
//! * Requests: `concurrency` at a time; timeouts, connection failures, 429, 5xx and malformed
//!   answers are retried up to `request_retries` times with exponential backoff from `backoff_s`
//!   (a `Retry-After` header wins); any other 4xx stops the stage with the server's message.
//! * Every answer is stored under the digest of its request (endpoint, model, body, and the
//!   attempt number) in the store's `responses/llm/` (or `response_cache`), so an interrupted or
//!   repeated run, or one that only changes how answers are judged, never asks twice for the
//!   same captions.
//! * Fidelity: each caption is parsed back; captions whose grid differs from the frame's are
//!   asked for again up to `regenerate` times, then dropped or kept (`on_mismatch`). The
//!   first-answer fidelity rate, regenerations, drops and token counts are reported.

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use anyhow::bail;
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rlmflow_parser::{number_word, parse};
use rlmflow_stages::captions::Caption;
use rlmflow_stages::grid::{DISTANCE_BINS, Grid, SECTORS};
use rlmflow_stages::labels::{FrameLabel, Labels};
use rlmflow_stages::{Context, Items, Operator, OperatorSpec, Outcome, SettingError, Settings, Sharding, Share};
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::write_captions;
use client::Client;

mod client;
mod responses;

pub struct Llm;

/// What happens to captions that still disagree with their grid after the last regeneration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OnMismatch {
    Drop,
    Keep,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LlmSettings {
    /// The API root; requests go to `{base_url}/chat/completions`.
    pub base_url: String,
    pub model: String,
    /// The environment variable holding the API key; empty for an endpoint without one.
    pub api_key_env: String,
    pub temperature: f64,
    pub top_p: f64,
    /// 1..=32,768.
    pub max_tokens: u32,
    /// Captions per frame (the request's `n`), 1..=128.
    pub n: usize,
    /// Share of frames whose prompt adds "Do not add any distance bin numbers".
    pub no_distance_numbers: f64,
    /// Times a frame's disagreeing captions are asked for again, 0..=10.
    pub regenerate: u32,
    pub on_mismatch: OnMismatch,
    /// The least share of frames that must keep a caption, [0, 1]; below it the stage fails.
    /// 1: any frame left without one is an error (lower it to allow drops).
    pub min_captioned: f64,
    /// Requests in flight at once, 1..=256.
    pub concurrency: usize,
    /// Seconds a request may take, (0, 3600].
    pub timeout_s: f64,
    /// Retries (0..=20) of a request after a timeout, a connection failure, 429, 5xx or a malformed answer.
    pub request_retries: u32,
    /// Seconds before the first retry, 0..=60; doubled each time, at most a minute.
    pub backoff_s: f64,
    /// Where answers are kept by request digest; empty: the store's `responses/llm/`, which
    /// `rlmflow verify` checks and `rlmflow gc --responses` clears. A path shares answers
    /// between stores.
    pub response_cache: String,
    /// Captions only this share of the labelled frames (set by `shards = N` on the stage).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shard: Option<Share>,
}

impl Default for LlmSettings {
    fn default() -> Self {
        LlmSettings {
            base_url: "https://api.openai.com/v1".into(),
            model: "gpt-4.1-mini".into(),
            api_key_env: "OPENAI_API_KEY".into(),
            temperature: 0.5,
            top_p: 0.9,
            max_tokens: 400,
            n: 5,
            no_distance_numbers: 0.5,
            regenerate: 2,
            on_mismatch: OnMismatch::Drop,
            min_captioned: 1.0,
            concurrency: 8,
            timeout_s: 120.0,
            request_retries: 6,
            backoff_s: 1.0,
            response_cache: String::new(),
            shard: None,
        }
    }
}

impl Settings for LlmSettings {
    const NON_RESULT: &'static [&'static str] = &["api_key_env", "concurrency", "timeout_s", "request_retries", "backoff_s", "response_cache"];

    fn check(&self) -> Result<(), SettingError> {
        let err = |key: &str, message: String| Err(SettingError::new(key, message));
        if !(self.base_url.starts_with("http://") || self.base_url.starts_with("https://")) {
            return err("base_url", format!("must start with http:// or https://, not `{}`", self.base_url));
        }
        if self.model.trim().is_empty() {
            return err("model", "must name a model".into());
        }
        if !(0.0..=2.0).contains(&self.temperature) {
            return err("temperature", format!("must be in [0, 2], not {}", self.temperature));
        }
        if !(self.top_p > 0.0 && self.top_p <= 1.0) {
            return err("top_p", format!("must be in (0, 1], not {}", self.top_p));
        }
        SettingError::check_range("max_tokens", self.max_tokens, 1..=32_768)?;
        SettingError::check_range("regenerate", self.regenerate, 0..=10)?;
        SettingError::check_range("request_retries", self.request_retries, 0..=20)?;
        if !(1..=128).contains(&self.n) {
            return err("n", format!("must be in 1..=128, not {}", self.n));
        }
        if !(0.0..=1.0).contains(&self.min_captioned) {
            return err("min_captioned", format!("must be in [0, 1], not {}", self.min_captioned));
        }
        if !(0.0..=1.0).contains(&self.no_distance_numbers) {
            return err("no_distance_numbers", format!("must be in [0, 1], not {}", self.no_distance_numbers));
        }
        SettingError::check_range("concurrency", self.concurrency, 1..=256)?;
        if !(self.timeout_s > 0.0 && self.timeout_s <= 3600.0) {
            return err("timeout_s", format!("must be in (0, 3600], not {}", self.timeout_s));
        }
        SettingError::check_range("backoff_s", self.backoff_s, 0.0..=60.0)?;
        if let Some(Share { index, of }) = self.shard
            && (of == 0 || index >= of)
        {
            return err("shard", format!("index must be below of (>= 1), not {{ index = {index}, of = {of} }}"));
        }
        Ok(())
    }
}

pub const SYSTEM_PROMPT: &str = "You are an expert at describing traffic scenes from the perspective of a driver talking to a passenger. Only output the final caption. Do not include explanations. Also do not use short word forms with apostrophe, use the full expansion of words only.";

const BIN_EXPLANATIONS: [&str; 4] = [
    "Objects within 0 to 10 meters from the ego vehicle. These are very close and may require immediate attention.",
    "Objects within 10 to 20 meters from the ego vehicle. These are close and should be monitored closely.",
    "Objects within 20 to 30 meters from the ego vehicle. These are at a moderate distance and should be noted.",
    "Objects within 30 to 40 meters from the ego vehicle. These are at a safe distance but still relevant.",
];

/// The sector keys' explanations, in `SECTORS` order.
const SECTOR_EXPLANATIONS: [&str; 12] = [
    "Vehicles in the left adjacent lane ahead of the ego vehicle.",
    "Vehicles directly to the left side of the ego vehicle.",
    "Vehicles in the left adjacent lane behind the ego vehicle.",
    "Vehicles directly ahead of the ego vehicle in the same lane.",
    "Vehicles directly behind the ego vehicle in the same lane.",
    "Vehicles in the right adjacent lane ahead of the ego vehicle.",
    "Vehicles directly to the right side of the ego vehicle.",
    "Vehicles in the right adjacent lane behind the ego vehicle.",
    "Vehicles in the opposing lane ahead of the ego vehicle.",
    "Vehicles in the opposing lane behind the ego vehicle.",
    "Vehicles in perpendicular or intersecting lanes ahead of the ego vehicle.",
    "Vehicles in perpendicular or intersecting lanes behind the ego vehicle.",
];

const INSTRUCTION: &str = "Given this data, generate natural language sentences describing the scene. Only provide the description. Do not explain how you arrived at it. Include all the fields provided even if is empty.";
pub const NO_NUMBERS: &str = "Do not add any distance bin numbers.";

/// The user prompt for a grid: the JSON (numbers as words, sectors shuffled within each bin),
/// the key explanations and the instruction.
pub fn user_prompt(grid: &Grid, no_numbers: bool, rng: &mut impl rand::Rng) -> String {
    let quote = |s: &str| serde_json::to_string(s).expect("strings serialise");
    let mut json = String::from("{\n");
    let mut present = vec![false; SECTORS.len()];
    for (bin, name) in DISTANCE_BINS.iter().enumerate() {
        let mut sectors: Vec<usize> = (0..SECTORS.len()).filter(|&s| grid.get(bin, s) > 0).collect();
        sectors.shuffle(rng);
        json += &format!("  \"{name}\": {{\n    \"total_vehicles\": {}", quote(&number_word(grid.bin_total(bin))));
        for s in sectors {
            present[s] = true;
            json += &format!(",\n    \"{}\": {}", SECTORS[s], quote(&number_word(grid.get(bin, s))));
        }
        json += "\n  },\n";
    }
    let signs: Vec<String> = grid.signs.iter().map(|s| quote(s)).collect();
    json += &format!("  \"applicable_traffic_signs\": [{}],\n  \"walkers\": {}\n}}", signs.join(", "), quote(&number_word(grid.walkers)));

    let mut out = format!("Here is the JSON data:\n{json}\n\nHere is the description of every key in the JSON data:\n\n");
    for (name, text) in DISTANCE_BINS.iter().zip(BIN_EXPLANATIONS) {
        out += &format!("Distance Bin - {name}: {text}\n");
    }
    out += "\n- total_vehicles: Total number of vehicles in the distance bin.\n";
    for (s, text) in SECTOR_EXPLANATIONS.iter().enumerate().filter(|(s, _)| present[*s]) {
        out += &format!("- {}: {text}\n", SECTORS[s]);
    }
    out += "- applicable_traffic_signs: Traffic signs that are applicable to the ego vehicle.\n- walkers: Pedestrians in the scene.\n\n";
    out += INSTRUCTION;
    if no_numbers {
        out += " ";
        out += NO_NUMBERS;
    }
    out
}

impl Operator for Llm {
    type Settings = LlmSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "llm",
            kind: "captions",
            version: 3,
            inputs: None,
            summary: "captions from an OpenAI-compatible endpoint with the paper's prompts, checked by the parser",
        }
    }

    /// A shard captions a share of the labelled frames; `concat-captions` joins the shares into
    /// the whole's bytes.
    fn resumes_from(&self) -> &'static str {
        "its response cache (the answers it already has)"
    }

    fn sharding(&self) -> Option<Sharding<LlmSettings>> {
        Some(Sharding {
            unit: "frames",
            items: Items::OfInput { slot: "labels", part: |s, share| LlmSettings { shard: Some(share), ..s.clone() } },
            merge: "concat-captions",
        })
    }

    fn run(&self, s: &LlmSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let labels = Labels::open(ctx.input("labels")?)?;
        let client = Client::new(s, ctx)?;
        let frames = match s.shard {
            Some(share) => {
                let range = share.range(labels.frames.len() as u64);
                &labels.frames[range.start as usize..range.end as usize]
            }
            None => &labels.frames[..],
        };
        let seed = ctx.seed;
        let progress = ctx.progress(frames.len() as u64, "frames");
        let results: Mutex<Vec<Option<FrameCaptions>>> = Mutex::new(vec![None; frames.len()]);
        let next = AtomicUsize::new(0);
        let failed = AtomicBool::new(false);
        let first_error: Mutex<Option<anyhow::Error>> = Mutex::new(None);
        std::thread::scope(|scope| {
            for _ in 0..s.concurrency.min(frames.len().max(1)) {
                scope.spawn(|| {
                    while !failed.load(Ordering::Relaxed) {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        let Some(label) = frames.get(i) else { break };
                        match caption_frame(s, label, seed, &client) {
                            Ok(done) => {
                                results.lock().unwrap()[i] = Some(done);
                                progress.set_message(client.stats.line());
                                progress.inc(1);
                            }
                            Err(e) => {
                                failed.store(true, Ordering::Relaxed);
                                first_error.lock().unwrap().get_or_insert(e.context(format!("frame {}", label.frame)));
                            }
                        }
                    }
                });
            }
        });
        progress.finish();
        if let Some(e) = first_error.into_inner().unwrap() {
            return Err(e);
        }

        let results: Vec<FrameCaptions> = results.into_inner().unwrap().into_iter().map(|r| r.expect("every frame ran")).collect();
        let mut captions = Vec::new();
        let mut statistics = Statistics::default();
        for (label, r) in frames.iter().zip(&results) {
            captions.extend(r.captions.iter().map(|c| Caption { frame: label.frame, id: label.id.clone(), split: label.split, caption: c.clone() }));
            statistics.add(&r.statistics);
        }
        let statistics = statistics.finish();
        let captioned = frames.len() as u64 - statistics.frames_without_captions;
        if (captioned as f64) < s.min_captioned * frames.len() as f64 {
            bail!(
                "{} of {} frames kept no caption ({} of {} answers faithful on first asking, {} cut off at max_tokens = {}, {} received of {} asked for); \
                 raise `regenerate` or `max_tokens`, set `on_mismatch = \"keep\"`, or lower `min_captioned` (now {}) to allow frames without captions",
                statistics.frames_without_captions,
                frames.len(),
                statistics.first_answers_faithful,
                statistics.first_answers,
                statistics.cut_off,
                s.max_tokens,
                statistics.received,
                statistics.requested,
                s.min_captioned
            );
        }
        let mut metrics = serde_json::to_value(&statistics).expect("statistics serialise");
        metrics["requests"] = client.stats.json();
        write_captions(&ctx.output_dir, frames.len() as u64, &captions, generator(s, &statistics))?;
        Ok(Outcome {
            summary: format!(
                "{} captions for {} frames ({} received of {} asked for); {:.1}% faithful on first answer, {} cut off, {} regenerated, {} dropped, {} kept unfaithful; {}",
                captions.len(),
                frames.len(),
                statistics.received,
                statistics.requested,
                100.0 * statistics.first_answer_fidelity,
                statistics.cut_off,
                statistics.regenerated,
                statistics.dropped,
                statistics.kept_mismatched,
                client.stats.line()
            ),
            metrics,
        })
    }
}

/// The Captions summary's `generator`: the settings the key covers and what the captions cost
/// and how faithful they were. How many requests this run sent or found cached is not in it
/// (that depends on the response cache, not on the captions): it is in the action's metrics.
fn generator(s: &LlmSettings, statistics: &Statistics) -> Value {
    json!({"settings": s.result_settings(), "statistics": statistics})
}

/// The `generator` of the whole when `parts` are the generators of every share of one `llm`
/// stage, in order: the settings without the share and the statistics summed. `None` otherwise.
pub fn join_shares(parts: &[&Value]) -> Option<Value> {
    let mut settings: Option<LlmSettings> = None;
    let mut total = Statistics::default();
    for (j, part) in parts.iter().enumerate() {
        let mut s: LlmSettings = serde_json::from_value(part.get("settings")?.clone()).ok()?;
        if s.shard != Some(Share { index: j as u64, of: parts.len() as u64 }) {
            return None;
        }
        s.shard = None;
        match &settings {
            None => settings = Some(s),
            Some(first) if first.result_settings() == s.result_settings() => {}
            Some(_) => return None,
        }
        total.add(&serde_json::from_value(part.get("statistics")?.clone()).ok()?);
    }
    Some(generator(&settings?, &total.finish()))
}

/// One frame's outcome.
#[derive(Clone, Debug, Default)]
struct FrameCaptions {
    captions: Vec<String>,
    statistics: Statistics,
}

/// How captions fared against the parser and what their answers cost: per frame, and summed
/// over frames (or over the shares of a stage).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Statistics {
    captions: u64,
    frames_without_captions: u64,
    /// `first_answers_faithful / first_answers`.
    first_answer_fidelity: f64,
    /// Captions in the first answer, and how many of them matched the grid.
    first_answers: u64,
    first_answers_faithful: u64,
    /// Captions asked for (every request's `n`, summed), and received (servers that ignore `n`
    /// send fewer; the rest is asked for again).
    requested: u64,
    received: u64,
    /// Captions asked for again because they disagreed with the grid or were cut off.
    regenerated: u64,
    /// Answers that stopped at `max_tokens` (`finish_reason = "length"`): never faithful.
    cut_off: u64,
    dropped: u64,
    kept_mismatched: u64,
    /// The tokens of every answer used, whether asked now or read from the response cache.
    prompt_tokens: u64,
    completion_tokens: u64,
}

impl Statistics {
    fn add(&mut self, other: &Statistics) {
        self.captions += other.captions;
        self.frames_without_captions += other.frames_without_captions;
        self.first_answers += other.first_answers;
        self.first_answers_faithful += other.first_answers_faithful;
        self.requested += other.requested;
        self.received += other.received;
        self.regenerated += other.regenerated;
        self.cut_off += other.cut_off;
        self.dropped += other.dropped;
        self.kept_mismatched += other.kept_mismatched;
        self.prompt_tokens += other.prompt_tokens;
        self.completion_tokens += other.completion_tokens;
    }

    fn finish(mut self) -> Statistics {
        self.first_answer_fidelity = self.first_answers_faithful as f64 / self.first_answers.max(1) as f64;
        self
    }
}

/// Asks for a frame's captions until `n` agree with its grid or the regenerations run out. Within
/// a round, choices a server did not send (one that ignores `n`) are asked for again, one
/// request at a time at most as many times as were missing; each request has its own number,
/// so the response cache tells them apart.
fn caption_frame(s: &LlmSettings, label: &FrameLabel, seed: u64, client: &Client) -> anyhow::Result<FrameCaptions> {
    let mut rng = ChaCha8Rng::seed_from_u64(rlmflow_stages::item_seed(seed, label.frame));
    let no_numbers = rng.random_bool(s.no_distance_numbers);
    let prompt = user_prompt(&label.grid, no_numbers, &mut rng);
    let mut out = FrameCaptions::default();
    let f = &mut out.statistics;
    let mut mismatched = Vec::new();
    let mut request = 0;
    for round in 0..=s.regenerate {
        let needed = s.n - out.captions.len();
        if needed == 0 {
            break;
        }
        if round > 0 {
            f.regenerated += needed as u64;
        }
        let (mut answered, mut asks) = (0, 0);
        while answered < needed && asks < needed {
            let ask = needed - answered;
            let answer = client.complete(&request_body(s, &prompt, ask), request)?;
            (request, asks) = (request + 1, asks + 1);
            f.requested += ask as u64;
            f.prompt_tokens += answer.prompt_tokens;
            f.completion_tokens += answer.completion_tokens;
            let got: Vec<(String, bool)> = answer.captions.into_iter().take(ask).collect();
            f.received += got.len() as u64;
            answered += got.len();
            for (caption, cut) in got {
                f.cut_off += u64::from(cut);
                let ok = !cut && parse(&caption).grid == label.grid;
                if round == 0 {
                    f.first_answers += 1;
                    f.first_answers_faithful += u64::from(ok);
                }
                if ok { out.captions.push(caption) } else { mismatched.push(caption) }
            }
        }
    }
    let missing = s.n - out.captions.len();
    match s.on_mismatch {
        OnMismatch::Keep => {
            let kept = missing.min(mismatched.len());
            f.kept_mismatched = kept as u64;
            out.captions.extend(mismatched.drain(..kept));
            f.dropped = mismatched.len() as u64;
        }
        OnMismatch::Drop => f.dropped = mismatched.len() as u64,
    }
    f.captions = out.captions.len() as u64;
    f.frames_without_captions = u64::from(out.captions.is_empty());
    Ok(out)
}

fn request_body(s: &LlmSettings, prompt: &str, n: usize) -> String {
    json!({
        "model": s.model,
        "messages": [{"role": "system", "content": SYSTEM_PROMPT}, {"role": "user", "content": prompt}],
        "temperature": s.temperature,
        "top_p": s.top_p,
        "max_tokens": s.max_tokens,
        "n": n,
    })
    .to_string()
}

#[cfg(test)]
mod tests {
    use std::path::{Path, PathBuf};
    use std::time::Duration;

    use super::client::{MAX_WAIT, retry_after};
    use super::responses::{Answer, store};
    use std::collections::HashMap;
    use std::sync::Arc;

    use rlmflow_test_support::openai::{FakeOpenAi, Response};

    use rlmflow_stages::captions::{self, Captions};
    use rlmflow_stages::context::Silent;
    use rlmflow_stages::grid::CELLS;
    use rlmflow_stages::{Device, Input};

    use crate::ConcatCaptions;
    use rlmflow_stages::identity::{Split, SplitBy};
    use rlmflow_stages::labels::{self, MaskGeometry};
    use rlmflow_stages::npy::{Dtype, NpyWriter};

    use super::*;

    /// What the fake endpoint does with one request.
    enum Reply {
        Captions(usize),
        /// Captions that stopped at `max_tokens` (`finish_reason = "length"`).
        CutOff(usize),
        Status(u16, &'static str),
        Malformed,
        Slow(Duration),
    }

    /// Which answers start with a caption of another grid.
    #[derive(Clone, Copy, PartialEq)]
    enum Wrong {
        Never,
        /// The first answer to each prompt.
        FirstAnswer,
        Always,
    }

    type Script = dyn Fn(usize, &str, usize) -> Reply + Send + Sync;

    /// A chat-completions endpoint on localhost. It reads the grid back out of the prompt and
    /// answers with template captions of it; `script(request number, prompt, n)` picks the reply,
    /// `wrong` which answers start with a caption of another grid.
    fn fake_llm(script: Box<Script>, wrong: Wrong) -> FakeOpenAi {
        let answered = Mutex::new(std::collections::HashSet::new());
        FakeOpenAi::start(move |request| {
            let (prompt, n) = (request.prompt(), request.n());
            // Asked only of an answer with captions: a failed request answers nothing.
            let wrong_first = || match wrong {
                Wrong::Never => false,
                Wrong::Always => true,
                Wrong::FirstAnswer => answered.lock().unwrap().insert(prompt.to_owned()),
            };
            match script(request.number, prompt, n) {
                _ if request.authorization != "Bearer sk-test" => Response::error(401, "Incorrect API key provided"),
                Reply::Captions(k) => Response::json(&answer(prompt, k, wrong_first())),
                Reply::CutOff(k) => {
                    let mut cut = answer(prompt, k, false);
                    cut["choices"].as_array_mut().unwrap().iter_mut().for_each(|c| c["finish_reason"] = json!("length"));
                    Response::json(&cut)
                }
                Reply::Status(code, message) => Response::error(code, message),
                Reply::Malformed => Response { status: 200, body: r#"{"choices": [{"message": "#.to_owned(), retry_after: false },
                Reply::Slow(d) => {
                    // Past the client's timeout: nobody reads this answer.
                    std::thread::sleep(d);
                    Response::json(&answer(prompt, n, false))
                }
            }
        })
    }

    /// The grid in a prompt's JSON, numbers read back from words.
    fn prompt_grid(prompt: &str) -> Grid {
        let words: HashMap<String, u64> = (0..100).map(|n| (number_word(n), n as u64)).collect();
        let json = &prompt[prompt.find('{').unwrap()..prompt.find("\n\nHere is the description").unwrap()];
        let mut value: Value = serde_json::from_str(json).unwrap();
        fn numbers(v: &mut Value, words: &HashMap<String, u64>) {
            match v {
                Value::String(s) if words.contains_key(s.as_str()) => *v = json!(words[s.as_str()]),
                Value::Object(m) => m.values_mut().for_each(|v| numbers(v, words)),
                _ => {}
            }
        }
        numbers(&mut value, &words);
        Grid::from_json(&value).unwrap()
    }

    fn answer(prompt: &str, k: usize, wrong_first: bool) -> Value {
        let grid = prompt_grid(prompt);
        let mut rng = ChaCha8Rng::seed_from_u64(prompt.len() as u64);
        let no_numbers = prompt.contains(NO_NUMBERS);
        let choices: Vec<Value> = (0..k)
            .map(|i| {
                let mut g = grid.clone();
                if wrong_first && i == 0 {
                    g.counts[i % CELLS] += 1;
                }
                json!({"index": i, "message": {"role": "assistant", "content": crate::caption(&g, !no_numbers, &mut rng)}})
            })
            .collect();
        json!({"choices": choices, "usage": {"prompt_tokens": 700, "completion_tokens": 150 * k}})
    }

    fn scratch(name: &str) -> PathBuf {
        let root = std::env::temp_dir().join(format!("rlmflow-llm-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        for d in ["labels", "out", "ckpt", "cache"] {
            std::fs::create_dir_all(root.join(d)).unwrap();
        }
        root
    }

    /// A Labels artifact of `frames` random grids (1 x 1 masks).
    fn write_labels(root: &Path, frames: u64) -> Vec<Grid> {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let grids: Vec<Grid> = (0..frames)
            .map(|_| {
                let mut g = Grid::default();
                for _ in 0..rng.random_range(0..8) {
                    g.counts[rng.random_range(0..CELLS)] += 1;
                }
                g.walkers = rng.random_range(0..3);
                g
            })
            .collect();
        let dir = root.join("labels");
        let lines: String = grids
            .iter()
            .enumerate()
            .map(|(i, g)| {
                FrameLabel { frame: i as u64, id: format!("{i:032x}"), episode: None, split: Split::Train, grid: g.clone() }.to_line() + "\n"
            })
            .collect();
        std::fs::write(dir.join(labels::LINES), lines).unwrap();
        let mut masks = NpyWriter::create(&dir.join(labels::MASKS), Dtype::U8, frames as usize, &[1, 1]).unwrap();
        for _ in 0..frames {
            masks.write_u8(&[0]).unwrap();
        }
        masks.finish().unwrap();
        let summary = labels::Summary {
            format: labels::FORMAT,
            frames,
            train: frames,
            test: 0,
            split: labels::SplitSummary {
                rule: String::new(),
                by: SplitBy::Frame,
                test_fraction: 0.0,
                seed: 0,
                groups: frames,
                test_groups: 0,
                strata: vec![],
            },
            nearest_neighbour: None,
            rule: Default::default(),
            mask: MaskGeometry { size: 1, radius_px: 1.0, sigma_px: 1.0 },
            cells: Default::default(),
            vehicles_per_frame: vec![],
        };
        std::fs::write(dir.join(labels::SUMMARY), serde_json::to_vec(&summary).unwrap()).unwrap();
        grids
    }

    fn settings(server: &FakeOpenAi, root: &Path) -> LlmSettings {
        LlmSettings {
            base_url: server.url.clone(),
            model: "fake".into(),
            api_key_env: "RLMFLOW_TEST_LLM_KEY".into(),
            n: 3,
            concurrency: 3,
            timeout_s: 0.5,
            backoff_s: 0.01,
            response_cache: root.join("cache").display().to_string(),
            ..LlmSettings::default()
        }
    }

    fn run(root: &Path, s: &LlmSettings) -> anyhow::Result<Outcome> {
        // SAFETY: every test sets the same value; nothing reads it concurrently in a way that
        // could see a torn write.
        unsafe { std::env::set_var("RLMFLOW_TEST_LLM_KEY", "sk-test") };
        let _ = std::fs::remove_dir_all(root.join("out"));
        std::fs::create_dir_all(root.join("out")).unwrap();
        let mut ctx = Context::standalone("captions", &[("labels", &root.join("labels"))], &root.join("out"), &root.join("ckpt"), 5, 1);
        Operator::run(&Llm, s, &mut ctx)
    }

    #[test]
    fn failures_are_retried_wrong_captions_regenerated_and_answers_never_asked_twice() {
        let root = scratch("main");
        let grids = write_labels(&root, 12);
        let server = fake_llm(
            Box::new(|number, _, n| match number {
                0 => Reply::Status(429, "Rate limit reached"),
                1 => Reply::Status(500, "The server had an error"),
                2 => Reply::Malformed,
                3 => Reply::Slow(Duration::from_millis(1500)),
                _ => Reply::Captions(n),
            }),
            Wrong::FirstAnswer,
        );
        let s = settings(&server, &root);
        let outcome = run(&root, &s).unwrap();
        let m = &outcome.metrics;
        assert_eq!(m["requests"]["retries"], 4, "{m}");
        // Each frame's first answer has one wrong caption of three; it is asked for again, and
        // the second answer is right.
        assert_eq!(m["first_answer_fidelity"].as_f64().unwrap(), 2.0 / 3.0, "{m}");
        assert_eq!((m["regenerated"].as_u64(), m["dropped"].as_u64()), (Some(12), Some(12)), "{m}");
        assert_eq!(m["captions"], 12 * 3, "{m}");
        let captions = Captions::open(&root.join("out")).unwrap();
        for c in &captions.captions {
            assert_eq!(parse(&c.caption).grid, grids[c.frame as usize], "{}", c.caption);
        }
        assert_eq!((m["requests"]["sent"].as_u64(), m["requests"]["prompt_tokens"].as_u64()), (Some(24), Some(700 * 24)), "{m}");

        assert_eq!((m["prompt_tokens"].as_u64(), m["first_answers"].as_u64()), (Some(700 * 24), Some(36)), "{m}");
        let summary = std::fs::read(root.join("out/captions.json")).unwrap();

        // The same run again asks nothing: every answer comes from the response cache, and the
        // artifact, which records what the answers cost rather than what this run sent, is
        // the same bytes.
        let sent = server.requests();
        let again = run(&root, &s).unwrap();
        assert_eq!(server.requests(), sent);
        assert_eq!(again.metrics["requests"]["from_cache"], 24);
        assert_eq!(std::fs::read(root.join("out/captions.jsonl")).unwrap(), captions_bytes(&captions));
        assert_eq!(std::fs::read(root.join("out/captions.json")).unwrap(), summary);
        std::fs::remove_dir_all(&root).unwrap();
    }

    /// Runs `llm` into `root/<dir>`; returns its two files.
    fn run_into(root: &Path, s: &LlmSettings, dir: &str) -> (Vec<u8>, Vec<u8>) {
        run(root, s).unwrap();
        std::fs::rename(root.join("out"), root.join(dir)).unwrap();
        let read = |f: &str| std::fs::read(root.join(dir).join(f)).unwrap();
        (read(captions::SUMMARY), read(captions::LINES))
    }

    /// A share captions its own frames and asks the endpoint what the whole stage would; shares
    /// join only in order, and one alone is listed as a part. (That the joined shares are the
    /// whole stage's bytes is checked through the binary, in `tests/pipelines/shards.rs`.)
    #[test]
    fn shares_ask_the_whole_stages_questions_and_join_only_in_order() {
        let root = scratch("shares");
        write_labels(&root, 10);
        let server = fake_llm(Box::new(|_, _, n| Reply::Captions(n)), Wrong::FirstAnswer);
        let s = settings(&server, &root);
        // Shares first, so they ask the endpoint and the whole reads every answer from the cache.
        let mut inputs = Vec::new();
        for index in 0..3 {
            let share = LlmSettings { shard: Some(Share { index, of: 3 }), ..s.clone() };
            let dir = format!("share{index}");
            let (summary, _) = run_into(&root, &share, &dir);
            let frames = serde_json::from_slice::<Value>(&summary).unwrap()["frames"].as_u64().unwrap();
            assert_eq!(frames, Share { index, of: 3 }.range(10).count() as u64);
            inputs.push(Input::new(format!("{index:020}"), root.join(dir)));
        }
        let sent = server.requests();
        run_into(&root, &s, "whole");
        assert_eq!(server.requests(), sent, "the shares asked every question the whole asks");

        let ckpt = root.join("ckpt");
        let mut ctx = Context::new(
            "captions".into(),
            [("captions".to_owned(), inputs.clone())].into(),
            root.join("out"),
            ckpt.clone(),
            5,
            1,
            Device::Cpu,
            Arc::new(Silent),
        );
        std::fs::create_dir_all(root.join("out")).unwrap();
        let outcome = Operator::run(&ConcatCaptions, &Default::default(), &mut ctx).unwrap();
        assert!(outcome.summary.contains("joined"), "{}", outcome.summary);
        let read = |f: &str| std::fs::read(root.join("out").join(f)).unwrap();

        // Out of order, the shares are refused; one share alone is listed, not passed off as the whole.
        std::fs::remove_dir_all(root.join("out")).unwrap();
        std::fs::create_dir_all(root.join("out")).unwrap();
        let swapped = vec![inputs[1].clone(), inputs[0].clone()];
        let mut ctx = Context::new(
            "captions".into(),
            [("captions".to_owned(), swapped)].into(),
            root.join("out"),
            ckpt.clone(),
            5,
            1,
            Device::Cpu,
            Arc::new(Silent),
        );
        let err = Operator::run(&ConcatCaptions, &Default::default(), &mut ctx).unwrap_err().to_string();
        assert!(err.contains("must caption disjoint frames, each after the last"), "{err}");
        let mut ctx = Context::new(
            "captions".into(),
            [("captions".to_owned(), inputs[1..2].to_vec())].into(),
            root.join("out"),
            ckpt,
            5,
            1,
            Device::Cpu,
            Arc::new(Silent),
        );
        Operator::run(&ConcatCaptions, &Default::default(), &mut ctx).unwrap();
        let summary: Value = serde_json::from_slice(&read(captions::SUMMARY)).unwrap();
        assert_eq!(summary["generator"]["parts"][0]["generator"]["settings"]["shard"], json!({"index": 1, "of": 3}), "{summary}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    fn captions_bytes(c: &Captions) -> Vec<u8> {
        c.captions.iter().map(|c| c.to_line() + "\n").collect::<String>().into_bytes()
    }

    #[test]
    fn the_first_stored_answer_to_a_request_wins() {
        let root = scratch("store");
        let path = root.join("cache").join("digest.json");
        let text = |caption: &str| json!({"choices": [{"message": {"content": caption}}]}).to_string();
        let first = text("From zero to ten meters,   there are no vehicles.");
        assert_eq!(
            store(&path, &first, Answer::parse(&first).unwrap()).unwrap().captions,
            [("From zero to ten meters, there are no vehicles.".to_owned(), false)]
        );
        // A second answer to the same request (sent at the same time by another frame) yields
        // the stored one, so both frames agree with what a rerun reads.
        let second = text("Close by, a single car is right in front of us.");
        assert_eq!(
            store(&path, &second, Answer::parse(&second).unwrap()).unwrap().captions,
            [("From zero to ten meters, there are no vehicles.".to_owned(), false)]
        );
        assert_eq!(std::fs::read_to_string(&path).unwrap(), first);
        assert_eq!(std::fs::read_dir(root.join("cache")).unwrap().count(), 1, "no scratch files left");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn a_damaged_stored_answer_is_set_aside_and_asked_for_once() {
        let root = scratch("damaged");
        write_labels(&root, 4);
        let server = fake_llm(Box::new(|_, _, n| Reply::Captions(n)), Wrong::Never);
        let s = settings(&server, &root);
        run(&root, &s).unwrap();
        let cache = root.join("cache");
        let stored: Vec<PathBuf> = std::fs::read_dir(&cache).unwrap().map(|e| e.unwrap().path()).collect();
        std::fs::write(&stored[0], b"{\"choices\": [{\"mess").unwrap();
        let sent = server.requests();
        let again = run(&root, &s).unwrap();
        assert_eq!(server.requests(), sent + 1, "the damaged answer's request, once");
        assert_eq!(again.metrics["requests"]["repaired"], 1, "{}", again.metrics);
        assert!(Answer::parse(&std::fs::read_to_string(&stored[0]).unwrap()).is_ok(), "replaced by a whole answer");
        assert_eq!(std::fs::read(stored[0].with_extension("damaged")).unwrap(), b"{\"choices\": [{\"mess", "kept aside");
        run(&root, &s).unwrap();
        assert_eq!(server.requests(), sent + 1, "repaired once, not asked again");
        // Two answers racing for a damaged file: the one stored replaces it.
        let path = cache.join("race.json");
        std::fs::write(&path, "not json").unwrap();
        let text = json!({"choices": [{"message": {"content": "No vehicles."}}]}).to_string();
        assert_eq!(store(&path, &text, Answer::parse(&text).unwrap()).unwrap().captions[0].0, "No vehicles.");
        assert_eq!(std::fs::read_to_string(&path).unwrap(), text);
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn retry_after_is_read_only_as_a_bounded_number_of_seconds() {
        assert_eq!(retry_after(" 2.5 "), Some(Duration::from_millis(2500)));
        assert_eq!(retry_after("86400"), Some(MAX_WAIT));
        for bad in ["-1", "NaN", "inf", "1e400", "Wed, 21 Oct 2015 07:28:00 GMT", ""] {
            assert_eq!(retry_after(bad), None, "{bad}");
        }
    }

    #[test]
    fn a_server_that_ignores_n_is_asked_again_for_the_rest_and_counted_honestly() {
        let root = scratch("ignores-n");
        write_labels(&root, 4);
        // llama.cpp's server answers one choice whatever `n` asks.
        let server = fake_llm(Box::new(|_, _, _| Reply::Captions(1)), Wrong::Never);
        let s = LlmSettings { regenerate: 0, ..settings(&server, &root) };
        let m = run(&root, &s).unwrap().metrics;
        // Per frame: 3 asked, 1 came; 2 asked, 1 came; 1 asked, 1 came.
        assert_eq!((m["captions"].as_u64(), m["requested"].as_u64(), m["received"].as_u64()), (Some(12), Some(24), Some(12)), "{m}");
        assert_eq!(m["requests"]["sent"], 12, "{m}");
        let bodies: Vec<u64> = server.bodies().iter().map(|b| b["n"].as_u64().unwrap()).collect();
        assert_eq!(bodies.iter().filter(|&&n| n == 3).count(), 4);
        // A rerun asks nothing: each of a frame's requests has its own cached answer.
        let again = run(&root, &s).unwrap().metrics;
        assert_eq!((again["requests"]["sent"].as_u64(), again["captions"].as_u64()), (Some(0), Some(12)), "{again}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn answers_cut_off_at_max_tokens_are_never_faithful_and_are_counted() {
        let root = scratch("cut-off");
        write_labels(&root, 3);
        // The first answer to each prompt is cut off.
        let seen = Mutex::new(std::collections::HashSet::new());
        let server = fake_llm(
            Box::new(move |_, prompt, n| if seen.lock().unwrap().insert(prompt.to_owned()) { Reply::CutOff(n) } else { Reply::Captions(n) }),
            Wrong::Never,
        );
        let s = LlmSettings { regenerate: 1, ..settings(&server, &root) };
        let m = run(&root, &s).unwrap().metrics;
        // Each frame's first answer is cut off (template captions that would parse right): all
        // three regenerated, and the second answers kept.
        assert_eq!((m["cut_off"].as_u64(), m["first_answers_faithful"].as_u64(), m["regenerated"].as_u64()), (Some(9), Some(0), Some(9)), "{m}");
        assert_eq!(m["captions"], 9, "{m}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn frames_left_without_captions_fail_the_stage_unless_drops_are_allowed() {
        let root = scratch("none-kept");
        write_labels(&root, 4);
        let server = fake_llm(Box::new(|_, _, n| Reply::CutOff(n)), Wrong::Never);
        let s = LlmSettings { regenerate: 1, ..settings(&server, &root) };
        let e = run(&root, &s).unwrap_err().to_string();
        assert!(e.starts_with("4 of 4 frames kept no caption (0 of 12 answers faithful on first asking, 24 cut off at max_tokens = 400"), "{e}");
        assert!(e.contains("lower `min_captioned` (now 1)"), "{e}");
        assert!(!root.join("out").join(captions::SUMMARY).exists(), "no partial artifact");
        let allowed = run(&root, &LlmSettings { min_captioned: 0.0, ..s }).unwrap().metrics;
        assert_eq!((allowed["captions"].as_u64(), allowed["frames_without_captions"].as_u64()), (Some(0), Some(4)));
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn an_interrupted_stage_resumes_from_its_response_cache() {
        assert_eq!(Operator::resumes_from(&Llm), "its response cache (the answers it already has)");
    }

    #[test]
    fn settings_the_key_leaves_out_leave_the_bytes_alone() {
        let root = scratch("non-result");
        write_labels(&root, 5);
        let server = fake_llm(Box::new(|_, _, n| Reply::Captions(n)), Wrong::FirstAnswer);
        let s = settings(&server, &root);
        let one = run_into(&root, &LlmSettings { concurrency: 1, request_retries: 2, timeout_s: 5.0, backoff_s: 0.5, ..s.clone() }, "one");
        let other = LlmSettings { concurrency: 4, request_retries: 9, api_key_env: "RLMFLOW_TEST_LLM_KEY".into(), ..s };
        assert_eq!(run_into(&root, &other, "other"), one, "captions.json and captions.jsonl");
        let summary: Value = serde_json::from_slice(&one.0).unwrap();
        for key in LlmSettings::NON_RESULT {
            assert!(summary["generator"]["settings"].get(key).is_none(), "`{key}` is recorded: {summary}");
        }
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn unfaithful_captions_are_dropped_or_kept_as_configured() {
        let root = scratch("mismatch");
        write_labels(&root, 4);
        let server = fake_llm(Box::new(|_, _, n| Reply::Captions(n)), Wrong::Always);
        let s = LlmSettings { regenerate: 1, ..settings(&server, &root) };
        let dropped = run(&root, &s).unwrap().metrics;
        assert_eq!(dropped["frames_without_captions"], 0, "{dropped}");
        // Per frame: three asked, one wrong; one asked again, wrong again.
        assert_eq!((dropped["captions"].as_u64(), dropped["dropped"].as_u64(), dropped["kept_mismatched"].as_u64()), (Some(8), Some(8), Some(0)));
        let kept = run(&root, &LlmSettings { on_mismatch: OnMismatch::Keep, ..s }).unwrap().metrics;
        assert_eq!((kept["captions"].as_u64(), kept["dropped"].as_u64(), kept["kept_mismatched"].as_u64()), (Some(12), Some(4), Some(4)));
        assert_eq!(kept["requests"]["from_cache"], 8, "judging differently asks nothing again");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn client_errors_stop_the_stage_with_the_servers_message() {
        let root = scratch("4xx");
        write_labels(&root, 2);
        let server = fake_llm(Box::new(|_, _, _| Reply::Status(400, "Invalid value for 'top_p'")), Wrong::Never);
        let e = run(&root, &settings(&server, &root)).unwrap_err();
        assert!(format!("{e:#}").contains("answered 400: Invalid value for 'top_p'"), "{e:#}");
        let s = LlmSettings { request_retries: 2, ..settings(&server, &root) };
        let server = fake_llm(Box::new(|_, _, _| Reply::Status(503, "overloaded")), Wrong::Never);
        let e = run(&root, &LlmSettings { base_url: server.url.clone(), concurrency: 1, ..s }).unwrap_err();
        assert!(format!("{e:#}").contains("gave up after 3 tries: 503: overloaded"), "{e:#}");
        assert_eq!(server.requests(), 3);
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn a_missing_or_wrong_key_is_named() {
        let root = scratch("key");
        write_labels(&root, 1);
        let server = fake_llm(Box::new(|_, _, n| Reply::Captions(n)), Wrong::Never);
        let s = LlmSettings { api_key_env: "RLMFLOW_TEST_UNSET_KEY".into(), ..settings(&server, &root) };
        let e = run(&root, &s).unwrap_err().to_string();
        assert!(e.contains("RLMFLOW_TEST_UNSET_KEY (stages.captions.api_key_env)"), "{e}");
        let e = run(&root, &LlmSettings { api_key_env: String::new(), ..s }).unwrap_err();
        assert!(format!("{e:#}").contains("answered 401: Incorrect API key provided; check the API key"), "{e:#}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn requests_carry_the_papers_prompts_and_sampling_settings() {
        let root = scratch("prompt");
        write_labels(&root, 6);
        let server = fake_llm(Box::new(|_, _, n| Reply::Captions(n)), Wrong::Never);
        run(&root, &LlmSettings { no_distance_numbers: 1.0, ..settings(&server, &root) }).unwrap();
        let bodies = server.bodies();
        assert_eq!(bodies.len(), 6);
        for body in bodies.iter() {
            assert_eq!(
                (body["temperature"].as_f64(), body["top_p"].as_f64(), body["max_tokens"].as_u64(), body["n"].as_u64()),
                (Some(0.5), Some(0.9), Some(400), Some(3))
            );
            assert_eq!(body["messages"][0]["content"], SYSTEM_PROMPT);
            let prompt = body["messages"][1]["content"].as_str().unwrap();
            assert!(prompt.starts_with("Here is the JSON data:\n{\n  \"0-10m\": {\n    \"total_vehicles\": \""), "{prompt}");
            assert!(prompt.contains("\"walkers\": \"") && prompt.contains("\"applicable_traffic_signs\": []"), "{prompt}");
            assert!(prompt.contains("Distance Bin - 30-40m: Objects within 30 to 40 meters from the ego vehicle."), "{prompt}");
            assert!(prompt.ends_with(&format!("{INSTRUCTION} {NO_NUMBERS}")), "{prompt}");
        }
        // Keys are shuffled within a bin: over many prompts, two sectors appear in both orders.
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let mut grid = Grid::default();
        grid.set(0, 0, 2);
        grid.set(0, 9, 1);
        let orders: std::collections::BTreeSet<bool> = (0..20)
            .map(|_| {
                let p = user_prompt(&grid, false, &mut rng);
                p.find("left_lane_front_side\": \"two\"").unwrap() < p.find("opposing_lane_back\": \"one\"").unwrap()
            })
            .collect();
        assert_eq!(orders.len(), 2);
        assert!(!user_prompt(&grid, false, &mut rng).contains(NO_NUMBERS));
        std::fs::remove_dir_all(&root).unwrap();
    }
}
