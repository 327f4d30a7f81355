//! The Tokens artifact: a tokenizer and the token ids of every caption.
//!
//! ```text
//! tokenizer.json  Hugging Face tokenizers format (Python: tokenizers.Tokenizer.from_file)
//! tokens.npy      uint32, (captions, context): start, the caption's tokens, end, then pad;
//!                 rows in the Captions artifact's order
//! frames.npy      uint32, (captions,): the frame each row describes
//! learnt_frames.txt  the identities of the frames whose captions the vocabulary was learnt
//!                 from (the training split), one per line, sorted
//! tokens.json     summary: vocabulary size, context, special token ids, counts
//! ```

use std::path::Path;

use anyhow::bail;
use serde::{Deserialize, Serialize};

use crate::npy::Npy;

pub const SUMMARY: &str = "tokens.json";
pub const TOKENIZER: &str = "tokenizer.json";
pub const IDS: &str = "tokens.npy";
pub const FRAMES: &str = "frames.npy";
pub const LEARNT: &str = "learnt_frames.txt";
pub const FORMAT: u32 = 2;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Special {
    pub start: u32,
    pub end: u32,
    pub pad: u32,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Summary {
    pub format: u32,
    pub vocab: u32,
    pub context: usize,
    pub special: Special,
    pub captions: u64,
    /// Captions longer than the context, cut (keeping the end token).
    pub truncated: u64,
    /// Tokens per caption without padding: mean and maximum.
    pub mean_length: f64,
    pub max_length: usize,
    /// The operator's settings.
    pub generator: serde_json::Value,
}

/// A Tokens artifact, read.
pub struct Tokens {
    pub summary: Summary,
    pub ids: Npy,
    /// The frame of each row.
    pub frames: Vec<u32>,
}

impl Tokens {
    pub fn open(dir: &Path) -> anyhow::Result<Tokens> {
        let summary: Summary = crate::reading::read_summary(dir, SUMMARY, crate::artifact::TOKENS, "tokens", FORMAT)?;
        let ids = Npy::open(&dir.join(IDS))?;
        if ids.shape != [summary.captions as usize, summary.context] {
            bail!("{}: shape {:?}, expected [{}, {}]", dir.join(IDS).display(), ids.shape, summary.captions, summary.context);
        }
        let frames_npy = Npy::open(&dir.join(FRAMES))?;
        if frames_npy.shape != [summary.captions as usize] {
            bail!("{}: shape {:?}, expected [{}]", dir.join(FRAMES).display(), frames_npy.shape, summary.captions);
        }
        Ok(Tokens { summary, ids, frames: frames_npy.all_u32()? })
    }

    /// The caption rows of each of `frames` frames, in row order; an error names a row whose
    /// frame is past the end.
    pub fn rows_by_frame(&self, frames: usize) -> anyhow::Result<Vec<Vec<usize>>> {
        let mut rows = vec![Vec::new(); frames];
        for (row, &frame) in self.frames.iter().enumerate() {
            let Some(list) = rows.get_mut(frame as usize) else {
                bail!("caption {row} names frame {frame}, past the scenes' {frames}");
            };
            list.push(row);
        }
        Ok(rows)
    }

    /// Row `row`'s ids, `context` long.
    pub fn row(&self, row: usize) -> anyhow::Result<Vec<u32>> {
        self.ids.row_u32(row)
    }
}
