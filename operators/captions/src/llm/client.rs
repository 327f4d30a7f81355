//! The chat-completions client: one request at a time per worker, retried with backoff (a
//! `Retry-After` header wins) on timeouts, connection failures, 429, 5xx and malformed answers,
//! any other 4xx an error with the server's message; every answer kept in the response store.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use anyhow::{Context as _, anyhow, bail};
use rlmflow_stages::Context;
use serde_json::{Value, json};

use super::LlmSettings;
use super::responses::{Answer, quarantine, store};

/// A chat-completions endpoint behind the response cache.
pub(super) struct Client {
    agent: ureq::Agent,
    url: String,
    auth: Option<String>,
    cache: PathBuf,
    /// What, besides the body, identifies an answer: endpoint and model.
    identity: String,
    retries: u32,
    backoff: Duration,
    pub(super) stats: Stats,
}

/// Answers that are worth asking again.
enum Failure {
    Retry(String, Option<Duration>),
    Fatal(anyhow::Error),
}

impl Client {
    pub(super) fn new(s: &LlmSettings, ctx: &Context) -> anyhow::Result<Client> {
        let stage = &ctx.stage;
        let auth = if s.api_key_env.is_empty() {
            None
        } else {
            let key = std::env::var(&s.api_key_env).map_err(|_| {
                anyhow!(
                    "the API key is read from the environment variable {} (stages.{stage}.api_key_env), which is not set; set it, or set api_key_env = \"\" for an endpoint without keys",
                    s.api_key_env
                )
            })?;
            Some(format!("Bearer {key}"))
        };
        let cache = match (&ctx.responses, s.response_cache.is_empty()) {
            (_, false) => PathBuf::from(&s.response_cache),
            (Some(store), true) => store.clone(),
            (None, true) => bail!("stage {stage} runs outside a store, which would keep its answers: set `response_cache`"),
        };
        std::fs::create_dir_all(&cache).with_context(|| format!("creating the response cache {}", cache.display()))?;
        let config = ureq::Agent::config_builder().timeout_global(Some(Duration::from_secs_f64(s.timeout_s))).http_status_as_error(false).build();
        Ok(Client {
            agent: config.into(),
            url: format!("{}/chat/completions", s.base_url.trim_end_matches('/')),
            auth,
            cache,
            identity: format!("{}\n{}", s.base_url.trim_end_matches('/'), s.model),
            retries: s.request_retries,
            backoff: Duration::from_secs_f64(s.backoff_s),
            stats: Stats::default(),
        })
    }

    /// The answer to `body` (the `attempt`-th time this body is asked).
    pub(super) fn complete(&self, body: &str, attempt: u32) -> anyhow::Result<Answer> {
        let digest = blake3::hash(format!("{}\n{attempt}\n{body}", self.identity).as_bytes()).to_hex();
        let path = self.cache.join(format!("{digest}.json"));
        if let Ok(text) = std::fs::read_to_string(&path) {
            match Answer::parse(&text) {
                Ok(answer) => {
                    self.stats.cached.fetch_add(1, Ordering::Relaxed);
                    return Ok(answer);
                }
                // Damaged (a disk fault, a hand edit): set aside once and asked again, so the
                // next run reads the new answer rather than asking forever.
                Err(_) => {
                    quarantine(&path)?;
                    self.stats.repaired.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
        let mut tries = 0;
        loop {
            let failure = match self.post(body) {
                Ok(text) => match Answer::parse(&text) {
                    Ok(answer) => {
                        self.stats.sent.fetch_add(1, Ordering::Relaxed);
                        self.stats.prompt_tokens.fetch_add(answer.prompt_tokens, Ordering::Relaxed);
                        self.stats.completion_tokens.fetch_add(answer.completion_tokens, Ordering::Relaxed);
                        return store(&path, &text, answer);
                    }
                    Err(e) => Failure::Retry(format!("malformed answer: {e}"), None),
                },
                Err(f) => f,
            };
            match failure {
                Failure::Fatal(e) => return Err(e),
                Failure::Retry(why, _) if tries >= self.retries => bail!("{}: gave up after {} tries: {why}", self.url, tries + 1),
                Failure::Retry(_, wait) => {
                    let backoff = self.backoff.saturating_mul(1 << tries.min(16)).min(MAX_WAIT);
                    std::thread::sleep(wait.unwrap_or(backoff));
                    tries += 1;
                    self.stats.retries.fetch_add(1, Ordering::Relaxed);
                }
            }
        }
    }

    fn post(&self, body: &str) -> Result<String, Failure> {
        let mut request = self.agent.post(&self.url).header("Content-Type", "application/json");
        if let Some(auth) = &self.auth {
            request = request.header("Authorization", auth);
        }
        let mut response = match request.send(body) {
            Ok(r) => r,
            Err(
                e @ (ureq::Error::Timeout(_)
                | ureq::Error::Io(_)
                | ureq::Error::ConnectionFailed
                | ureq::Error::Protocol(_)
                | ureq::Error::BodyStalled),
            ) => {
                return Err(Failure::Retry(e.to_string(), None));
            }
            Err(e) => return Err(Failure::Fatal(anyhow!("{}: {e}", self.url))),
        };
        let status = response.status().as_u16();
        let retry_after = response.headers().get("retry-after").and_then(|v| retry_after(v.to_str().ok()?));
        let text = response.body_mut().read_to_string().map_err(|e| Failure::Retry(format!("reading the answer: {e}"), None))?;
        match status {
            200..=299 => Ok(text),
            429 | 500..=599 => Err(Failure::Retry(format!("{status}: {}", server_message(&text)), retry_after)),
            _ => {
                let hint = match status {
                    401 | 403 => "; check the API key",
                    404 => "; check base_url and model",
                    _ => "",
                };
                Err(Failure::Fatal(anyhow!("{} answered {status}: {}{hint}", self.url, server_message(&text))))
            }
        }
    }
}

/// The longest a retry waits, whatever the backoff or a server's `Retry-After` asks for.
pub(super) const MAX_WAIT: Duration = Duration::from_secs(60);

/// A `Retry-After` header's seconds, at most [`MAX_WAIT`]; `None` for anything but a finite,
/// non-negative number (an HTTP date, a negative or NaN value), so the backoff applies.
pub(super) fn retry_after(header: &str) -> Option<Duration> {
    let seconds = header.trim().parse::<f64>().ok().filter(|s| s.is_finite() && *s >= 0.0)?;
    Some(Duration::from_secs_f64(seconds.min(MAX_WAIT.as_secs_f64())))
}

/// The `error.message` of an OpenAI-style error body, else the body itself (shortened).
fn server_message(text: &str) -> String {
    serde_json::from_str::<Value>(text)
        .ok()
        .and_then(|v| v["error"]["message"].as_str().map(str::to_owned))
        .unwrap_or_else(|| text.chars().take(300).collect())
}

/// Request counters, shared by the workers.
#[derive(Default)]
pub(super) struct Stats {
    sent: AtomicU64,
    cached: AtomicU64,
    retries: AtomicU64,
    /// Stored answers found damaged, set aside and asked for again.
    repaired: AtomicU64,
    prompt_tokens: AtomicU64,
    completion_tokens: AtomicU64,
}

impl Stats {
    pub(super) fn line(&self) -> String {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        format!(
            "{} requests ({} from cache, {} retries), {} prompt + {} completion tokens",
            get(&self.sent) + get(&self.cached),
            get(&self.cached),
            get(&self.retries),
            get(&self.prompt_tokens),
            get(&self.completion_tokens)
        )
    }

    pub(super) fn json(&self) -> Value {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        json!({"sent": get(&self.sent), "from_cache": get(&self.cached), "retries": get(&self.retries), "repaired": get(&self.repaired), "prompt_tokens": get(&self.prompt_tokens), "completion_tokens": get(&self.completion_tokens)})
    }
}
