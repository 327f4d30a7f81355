//! The response store: each answer under the digest of its request, written whole or not at
//! all, the first stored answer winning, a damaged one set aside and asked for again.

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use anyhow::Context as _;
use serde_json::Value;

/// Sets a damaged stored answer aside (`<digest>.damaged`, kept for a look) so its request can
/// be answered again.
pub(super) fn quarantine(path: &Path) -> anyhow::Result<()> {
    std::fs::rename(path, path.with_extension("damaged")).with_context(|| format!("setting the damaged stored answer {} aside", path.display()))
}

/// Stores an answer under `path` unless a whole one is there already, and returns the stored
/// one: when two frames send the same request at once, both get the answer that a rerun will
/// read. The answer is written to a file of its own and linked into place, so a reader never
/// sees half of it; a damaged answer in the way is set aside and replaced.
pub(super) fn store(path: &Path, text: &str, answer: Answer) -> anyhow::Result<Answer> {
    static WRITES: AtomicU64 = AtomicU64::new(0);
    let tmp = path.with_extension(format!("tmp-{}-{}", std::process::id(), WRITES.fetch_add(1, Ordering::Relaxed)));
    let stored = match std::fs::write(&tmp, text).and_then(|()| std::fs::hard_link(&tmp, path)) {
        Ok(()) => Ok(answer),
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
            let before = std::fs::read_to_string(path).with_context(|| format!("reading the stored answer {}", path.display()));
            match before.map(|text| Answer::parse(&text)) {
                Ok(Ok(kept)) => Ok(kept),
                Ok(Err(_)) => quarantine(path)
                    .and_then(|()| std::fs::rename(&tmp, path).with_context(|| format!("storing the answer in {}", path.display())))
                    .map(|()| answer),
                Err(e) => Err(e),
            }
        }
        Err(e) => Err(e).with_context(|| format!("storing the answer in {}", path.display())),
    };
    let _ = std::fs::remove_file(&tmp);
    stored
}

/// A chat-completions answer: its captions (whitespace collapsed), each with whether it was cut
/// off at `max_tokens`, and the tokens it cost.
pub(super) struct Answer {
    pub(super) captions: Vec<(String, bool)>,
    pub(super) prompt_tokens: u64,
    pub(super) completion_tokens: u64,
}

impl Answer {
    pub(super) fn parse(text: &str) -> anyhow::Result<Answer> {
        let value: Value = serde_json::from_str(text).context("not JSON")?;
        let choices = value["choices"].as_array().context("no `choices`")?;
        let captions = choices
            .iter()
            .map(|c| {
                let text = c["message"]["content"].as_str().context("a choice without `message.content`")?;
                Ok((text.split_whitespace().collect::<Vec<_>>().join(" "), c["finish_reason"] == "length"))
            })
            .collect::<anyhow::Result<_>>()?;
        let usage = |key: &str| value["usage"][key].as_u64().unwrap_or(0);
        Ok(Answer { captions, prompt_tokens: usage("prompt_tokens"), completion_tokens: usage("completion_tokens") })
    }
}
