//! The `tokens` stage kind's operator, `bpe`: a byte-level BPE tokenizer (Hugging Face
//! `tokenizers`) trained on the training split's captions, and the ids of every caption.
//!
//! Everything the ids depend on lives in `tokenizer.json`: the byte-level pre-tokenizer, the
//! `<start> $A <end>` template, truncation to `context` (on the right, before the template adds
//! `<end>`, so a cut caption still ends in `<end>`) and padding with `<pad>` to `context`. The
//! ids are computed by the tokenizer read back from that file, so Python's
//! `Tokenizer.from_file("tokenizer.json").encode(caption).ids` gives the same rows.

use std::collections::HashSet;
use std::path::Path;

use anyhow::{Context as _, anyhow};
use rlmflow_stages::captions::Captions;
use rlmflow_stages::identity::FrameSet;
use rlmflow_stages::identity::Split;
use rlmflow_stages::npy::{Dtype, NpyWriter};
use rlmflow_stages::tokens::{self, Special};
use rlmflow_stages::{Context, InputOutlines, Operator, OperatorSpec, Outcome, Outline, Resources, SettingError, Settings};
use serde::{Deserialize, Serialize};
use tokenizers::models::bpe::{BPE, BpeTrainerBuilder};
use tokenizers::pre_tokenizers::byte_level::ByteLevel;
use tokenizers::processors::template::TemplateProcessing;
use tokenizers::{AddedToken, NormalizerWrapper, PaddingDirection, PaddingParams, PaddingStrategy, Tokenizer, TokenizerBuilder, TokenizerImpl};
use tokenizers::{TruncationDirection, TruncationParams, TruncationStrategy};

pub const START: &str = "<start>";
pub const END: &str = "<end>";
pub const PAD: &str = "<pad>";

/// Byte-level BPE starts from the 256 byte symbols; the three special tokens come first.
const MIN_VOCAB: usize = 256 + 3;

pub struct Bpe;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BpeSettings {
    /// Vocabulary size, special tokens and the 256 byte symbols included, 259..=262,144.
    pub vocab: usize,
    /// Tokens per caption, `<start>` and `<end>` included, 3..=8,192; shorter captions are padded.
    pub context: usize,
    /// Merges of pairs seen fewer times than this are not learnt.
    pub min_frequency: u64,
}

impl Default for BpeSettings {
    fn default() -> Self {
        BpeSettings { vocab: 2048, context: 256, min_frequency: 2 }
    }
}

impl Settings for BpeSettings {
    fn check(&self) -> Result<(), SettingError> {
        // The least: 256 byte symbols and 3 special tokens; <start>, one token, <end>.
        SettingError::check_range("vocab", self.vocab, MIN_VOCAB..=262_144)?;
        SettingError::check_range("context", self.context, 3..=8_192)?;
        Ok(())
    }
}

impl Operator for Bpe {
    type Settings = BpeSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "bpe",
            kind: "tokens",
            version: 2,
            inputs: None,
            summary: "byte-level BPE trained on the training captions (Hugging Face tokenizers)",
        }
    }

    fn resources(&self, _: &BpeSettings) -> Resources {
        Resources { threads: usize::MAX, ..Resources::default() }
    }

    fn outline(&self, s: &BpeSettings, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        Ok(Outline { context: Some(s.context as u64), vocab: Some(s.vocab as u64), ..Outline::passed_on(inputs) })
    }

    fn run(&self, s: &BpeSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let captions = Captions::open(ctx.input("captions")?)?;
        let pool = rayon::ThreadPoolBuilder::new().num_threads(ctx.threads.max(1)).build()?;
        let train: Vec<&str> = captions.captions.iter().filter(|c| c.split == Split::Train).map(|c| c.caption.as_str()).collect();
        if train.is_empty() {
            anyhow::bail!("no training captions to learn a vocabulary from ({} captions, none in the train split)", captions.captions.len());
        }
        let learnt: FrameSet = captions.captions.iter().filter(|c| c.split == Split::Train).map(|c| c.id.clone()).collect();
        learnt.write(&ctx.output_dir.join(tokens::LEARNT))?;
        let progress = ctx.progress(captions.captions.len() as u64, "captions");
        let path = ctx.output_dir.join(tokens::TOKENIZER);
        pool.install(|| train_tokenizer(s, &train, &path))?;
        ctx.event("trained", serde_json::json!({"training_captions": train.len()}));

        let tokenizer = Tokenizer::from_file(&path).map_err(|e| anyhow!("reading back {}: {e}", path.display()))?;
        let special = Special { start: id(&tokenizer, START)?, end: id(&tokenizer, END)?, pad: id(&tokenizer, PAD)? };
        let rows = captions.captions.len();
        let mut ids = NpyWriter::create(&ctx.output_dir.join(tokens::IDS), Dtype::U32, rows, &[s.context])?;
        let mut frames = NpyWriter::create(&ctx.output_dir.join(tokens::FRAMES), Dtype::U32, rows, &[])?;
        let (mut truncated, mut total_len, mut max_len) = (0u64, 0usize, 0usize);
        for chunk in captions.captions.chunks(4096) {
            let texts: Vec<&str> = chunk.iter().map(|c| c.caption.as_str()).collect();
            let encodings = pool.install(|| tokenizer.encode_batch(texts, true)).map_err(|e| anyhow!("tokenising: {e}"))?;
            for (caption, encoding) in chunk.iter().zip(&encodings) {
                let len = encoding.get_attention_mask().iter().filter(|&&m| m == 1).count();
                truncated += u64::from(!encoding.get_overflowing().is_empty());
                total_len += len;
                max_len = max_len.max(len);
                ids.write_u32(encoding.get_ids())?;
                frames.write_u32(&[caption.frame as u32])?;
            }
            progress.inc(chunk.len() as u64);
        }
        ids.finish()?;
        frames.finish()?;
        progress.finish();

        let vocab = tokenizer.get_vocab_size(true) as u32;
        let summary = tokens::Summary {
            format: tokens::FORMAT,
            vocab,
            context: s.context,
            special,
            captions: rows as u64,
            truncated,
            mean_length: total_len as f64 / rows.max(1) as f64,
            max_length: max_len,
            generator: s.result_settings(),
        };
        std::fs::write(ctx.output_dir.join(tokens::SUMMARY), serde_json::to_vec_pretty(&summary)?)?;
        let metrics =
            serde_json::json!({"vocab": vocab, "captions": rows, "truncated": truncated, "mean_length": summary.mean_length, "max_length": max_len});
        Ok(Outcome {
            metrics,
            summary: format!(
                "{rows} captions, vocabulary {vocab}, {:.0} tokens on average, {truncated} truncated to {}",
                summary.mean_length, s.context
            ),
        })
    }
}

fn id(tokenizer: &Tokenizer, token: &str) -> anyhow::Result<u32> {
    tokenizer.token_to_id(token).with_context(|| format!("the tokenizer has no {token} token"))
}

/// Learns the vocabulary from `captions` and saves the complete tokenizer to `path`.
fn train_tokenizer(s: &BpeSettings, captions: &[&str], path: &Path) -> anyhow::Result<()> {
    let specials: Vec<AddedToken> = [START, END, PAD].iter().map(|t| AddedToken::from(*t, true)).collect();
    let mut trainer = BpeTrainerBuilder::new()
        .show_progress(false)
        .vocab_size(s.vocab)
        .min_frequency(s.min_frequency)
        .special_tokens(specials)
        .initial_alphabet(ByteLevel::alphabet().into_iter().collect::<HashSet<char>>())
        .build();
    let mut tokenizer: TokenizerImpl<BPE, NormalizerWrapper, ByteLevel, TemplateProcessing, ByteLevel> = TokenizerBuilder::new()
        .with_model(BPE::default())
        .with_normalizer(None)
        .with_pre_tokenizer(Some(ByteLevel::default()))
        .with_post_processor(None)
        .with_decoder(Some(ByteLevel::default()))
        .build()
        .map_err(|e| anyhow!("building the tokenizer: {e}"))?;
    tokenizer.train(&mut trainer, captions.iter()).map_err(|e| anyhow!("training the tokenizer: {e}"))?;
    let special = |t: &str| tokenizer.token_to_id(t).with_context(|| format!("training lost the {t} token"));
    let (start, end, pad) = (special(START)?, special(END)?, special(PAD)?);
    let template = TemplateProcessing::builder()
        .try_single(format!("{START} $A {END}"))
        .and_then(|b| b.try_pair(format!("{START} $A {END} $B:1 {END}:1")))
        .map_err(|e| anyhow!("template: {e}"))?
        .special_tokens(vec![(START, start), (END, end)])
        .build()
        .map_err(|e| anyhow!("template: {e}"))?;
    tokenizer.with_post_processor(Some(template));
    tokenizer
        .with_truncation(Some(TruncationParams {
            direction: TruncationDirection::Right,
            max_length: s.context,
            strategy: TruncationStrategy::LongestFirst,
            stride: 0,
        }))
        .map_err(|e| anyhow!("truncation: {e}"))?;
    tokenizer.with_padding(Some(PaddingParams {
        strategy: PaddingStrategy::Fixed(s.context),
        direction: PaddingDirection::Right,
        pad_to_multiple_of: None,
        pad_id: pad,
        pad_type_id: 0,
        pad_token: PAD.into(),
    }));
    tokenizer.save(path, false).map_err(|e| anyhow!("writing {}: {e}", path.display()))
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use rlmflow_stages::captions::{self, Caption};
    use rlmflow_stages::tokens::Tokens;

    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let root = std::env::temp_dir().join(format!("rlmflow-tokens-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        for d in ["captions", "out", "ckpt"] {
            std::fs::create_dir_all(root.join(d)).unwrap();
        }
        root
    }

    /// A Captions artifact: the training captions, plus test captions full of a word the
    /// training captions never use.
    fn write_captions(root: &Path, train: &[String]) -> Vec<Caption> {
        let mut all: Vec<Caption> = train
            .iter()
            .enumerate()
            .map(|(i, c)| Caption { frame: i as u64, id: format!("{i:032x}"), split: Split::Train, caption: c.clone() })
            .collect();
        for i in 0..20 {
            all.push(Caption {
                frame: (train.len() + i) as u64,
                id: format!("{:032x}", train.len() + i),
                split: Split::Test,
                caption: "zqxj zqxj zqxj zqxj zqxj".into(),
            });
        }
        let lines: String = all.iter().map(|c| c.to_line() + "\n").collect();
        std::fs::write(root.join("captions").join(captions::LINES), lines).unwrap();
        let summary =
            captions::Summary { format: captions::FORMAT, frames: all.len() as u64, captions: all.len() as u64, generator: serde_json::Value::Null };
        std::fs::write(root.join("captions").join(captions::SUMMARY), serde_json::to_vec(&summary).unwrap()).unwrap();
        all
    }

    fn run(root: &Path, s: &BpeSettings) -> Tokens {
        let mut ctx = Context::standalone("tokens", &[("captions", &root.join("captions"))], &root.join("out"), &root.join("ckpt"), 1, 2);
        Operator::run(&Bpe, s, &mut ctx).unwrap();
        Tokens::open(&root.join("out")).unwrap()
    }

    fn training_captions() -> Vec<String> {
        (0..200)
            .map(|i| {
                format!(
                    "From ten to twenty meters, there are {} vehicles in the right adjacent lane ahead of us. There are no walkers.",
                    ["two", "three", "four"][i % 3]
                )
            })
            .collect()
    }

    #[test]
    fn rows_hold_start_caption_end_and_padding_and_decode_back() {
        let root = scratch("rows");
        let all = write_captions(&root, &training_captions());
        let s = BpeSettings { vocab: 400, context: 64, min_frequency: 2 };
        let tokens = run(&root, &s);
        let sp = tokens.summary.special.clone();
        assert_eq!((sp.start, sp.end, sp.pad), (0, 1, 2));
        assert_eq!(tokens.summary.captions, all.len() as u64);
        assert!(tokens.summary.vocab <= 400 && tokens.summary.vocab > MIN_VOCAB as u32, "{}", tokens.summary.vocab);
        let tokenizer = Tokenizer::from_file(root.join("out").join(tokens::TOKENIZER)).unwrap();
        for (row, caption) in all.iter().enumerate() {
            let ids = tokens.row(row).unwrap();
            assert_eq!(ids.len(), 64);
            assert_eq!(ids[0], sp.start);
            let end = ids.iter().position(|&t| t == sp.end).unwrap();
            assert!(ids[end + 1..].iter().all(|&t| t == sp.pad), "padding after <end>");
            assert_eq!(tokenizer.decode(&ids[1..end], true).unwrap().trim(), caption.caption);
            assert_eq!(tokens.frames[row] as u64, caption.frame);
        }
        // Merges come from the training split only.
        let vocab = tokenizer.get_vocab(true);
        assert!(vocab.keys().any(|t| t.contains("vehicles")), "frequent training words become tokens");
        assert!(!vocab.keys().any(|t| t.contains("zq")), "test captions taught the tokenizer nothing");
        assert_eq!(tokens.summary.truncated, 0);
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn long_captions_are_cut_keeping_the_end_token() {
        let root = scratch("cut");
        let mut train = training_captions();
        train[0] = train[0].repeat(10);
        write_captions(&root, &train);
        let tokens = run(&root, &BpeSettings { vocab: 300, context: 16, min_frequency: 2 });
        let ids = tokens.row(0).unwrap();
        assert_eq!(ids.len(), 16);
        assert_eq!((ids[0], ids[15]), (tokens.summary.special.start, tokens.summary.special.end));
        assert!(!ids[1..15].contains(&tokens.summary.special.pad));
        assert_eq!(tokens.summary.max_length, 16);
        assert!(tokens.summary.truncated >= 1);
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn training_is_deterministic() {
        let (a, b) = (scratch("det-a"), scratch("det-b"));
        for root in [&a, &b] {
            write_captions(root, &training_captions());
            run(root, &BpeSettings { vocab: 350, context: 48, min_frequency: 2 });
        }
        for file in [tokens::TOKENIZER, tokens::IDS] {
            assert_eq!(std::fs::read(a.join("out").join(file)).unwrap(), std::fs::read(b.join("out").join(file)).unwrap(), "{file}");
        }
        std::fs::remove_dir_all(&a).unwrap();
        std::fs::remove_dir_all(&b).unwrap();
    }

    #[test]
    fn impossible_settings_name_their_key() {
        assert_eq!(BpeSettings { vocab: 100, ..Default::default() }.check().unwrap_err().key, "vocab");
        assert_eq!(BpeSettings { context: 2, ..Default::default() }.check().unwrap_err().key, "context");
    }
}
