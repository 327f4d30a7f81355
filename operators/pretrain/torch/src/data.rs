//! The training data in memory: every frame's radar image and counts, the split, and the
//! token ids of every caption with the frame it describes.

use anyhow::{Context as _, bail};
use rlmflow_stages::grid::CELLS;
use rlmflow_stages::labels::{Labels, Split};
use rlmflow_stages::scenes::Scenes;
use rlmflow_stages::tokens::Tokens;

pub struct Dataset {
    /// frames x side x side pixels.
    pub images: Vec<u8>,
    pub side: i64,
    /// frames x 48.
    pub counts: Vec<f32>,
    /// Every frame's identity.
    pub ids: Vec<String>,
    /// Frames of each split that have at least one caption (all frames without a text tower).
    pub train: Vec<usize>,
    pub test: Vec<usize>,
    /// captions x context token ids.
    pub tokens: Vec<i64>,
    pub context: i64,
    pub vocab: i64,
    pub end_token: i64,
    /// Caption rows of each frame.
    pub captions: Vec<Vec<usize>>,
}

impl Dataset {
    pub fn load(scenes: &std::path::Path, labels: &std::path::Path, tokens: &std::path::Path, need_captions: bool) -> anyhow::Result<Dataset> {
        let scenes = Scenes::open(scenes)?;
        let labels = Labels::open(labels)?;
        let tokens = Tokens::open(tokens)?;
        labels.check_scenes(scenes.len())?;
        let side = scenes.summary.images[0].size as i64;
        let mut images = Vec::with_capacity(scenes.len() as usize * (side * side) as usize);
        for i in 0..scenes.len() {
            images.extend(scenes.heatmap(i)?);
        }
        let counts = labels.frames.iter().flat_map(|f| f.grid.counts.iter().map(|&c| c as f32)).collect();
        let context = tokens.summary.context as i64;
        let ids = tokens.ids.all_u32().context("reading the token ids")?;
        let captions = tokens.rows_by_frame(labels.frames.len())?;
        let split = |s: Split| labels.split(s).map(|f| f.frame as usize).filter(|&f| !need_captions || !captions[f].is_empty()).collect::<Vec<_>>();
        let (train, test) = (split(Split::Train), split(Split::Test));
        if train.is_empty() || test.is_empty() {
            bail!("{} training and {} test frames with captions: the encoder needs both", train.len(), test.len());
        }
        Ok(Dataset {
            images,
            side,
            counts,
            ids: labels.frames.iter().map(|f| f.id.clone()).collect(),
            train,
            test,
            tokens: ids.into_iter().map(i64::from).collect(),
            context,
            vocab: i64::from(tokens.summary.vocab),
            end_token: i64::from(tokens.summary.special.end),
            captions,
        })
    }

    pub fn image_pixels(&self, frames: &[usize]) -> Vec<u8> {
        let n = (self.side * self.side) as usize;
        frames.iter().flat_map(|&f| self.images[f * n..(f + 1) * n].iter().copied()).collect()
    }

    pub fn frame_counts(&self, frames: &[usize]) -> Vec<f32> {
        frames.iter().flat_map(|&f| self.counts[f * CELLS..(f + 1) * CELLS].iter().copied()).collect()
    }

    pub fn caption_tokens(&self, rows: &[usize]) -> Vec<i64> {
        let n = self.context as usize;
        rows.iter().flat_map(|&r| self.tokens[r * n..(r + 1) * n].iter().copied()).collect()
    }
}
