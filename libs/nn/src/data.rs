//! The frames a training operator reads, in memory: the one loader every torch operator shares.
//!
//! Every frame of the `scenes` input (its primary image), its labels (grid counts, split,
//! identity) and, on request, its mask and the token ids of its captions from the `tokens`
//! input. Batches come out as tensors by frame index, so an operator's loss names frames, never
//! files.

use anyhow::{Context as _, bail};
use rlmflow_stages::Context;
use rlmflow_stages::grid::CELLS;
use rlmflow_stages::identity::Split;
use rlmflow_stages::labels::{FrameLabel, Labels};
use rlmflow_stages::scenes::Scenes;
use rlmflow_stages::tokens::Tokens;
use tch::{Kind, Tensor};

use crate::clip::images_from_u8;

/// What an operator reads besides images and labels.
#[derive(Clone, Copy, Debug, Default)]
pub struct Need {
    /// The `tokens` input: every caption's token ids, by frame.
    pub captions: bool,
    /// The labels' masks (which must be the images' size).
    pub masks: bool,
}

pub struct Frames {
    /// Image side in pixels.
    pub side: i64,
    /// frames x side x side.
    pixels: Vec<u8>,
    /// frames x side x side, when loaded.
    masks: Vec<u8>,
    pub labels: Labels,
    pub captions: Option<Captions>,
}

/// The tokens stage's captions of the frames.
pub struct Captions {
    pub tokens: Tokens,
    /// captions x context token ids.
    ids: Vec<i64>,
    pub context: i64,
    /// Caption rows of each frame.
    pub rows: Vec<Vec<usize>>,
}

/// Frame indices by role: the training split less its validation slice, the slice, the test
/// split.
pub struct Splits {
    pub train: Vec<usize>,
    pub validation: Vec<usize>,
    pub test: Vec<usize>,
}

impl Frames {
    pub fn load(ctx: &Context, need: Need) -> anyhow::Result<Frames> {
        let scenes = Scenes::open(ctx.input("scenes")?)?;
        let labels = Labels::open(ctx.input("labels")?)?;
        labels.check_scenes(scenes.len())?;
        let side = scenes.summary.images[0].size;
        let pixels = (0..scenes.len()).map(|i| scenes.heatmap(i)).collect::<anyhow::Result<Vec<_>>>()?.concat();
        let mut masks = Vec::new();
        if need.masks {
            let without = scenes.summary.frames_without_positions;
            if without > 0 {
                bail!(
                    "{without} of the {} frames were imported with a grid but no actors, so no vehicle has a place in their images and there is no segmentation target: \
                     segmentation needs actors with positions (x, y in the manifest, with the image's axes, or row, col)",
                    scenes.len()
                );
            }
            if labels.summary.mask.size != side {
                bail!(
                    "the labels' masks are {} px but the scenes' primary image {side} px: give the stage the scenes that were labelled",
                    labels.summary.mask.size
                );
            }
            masks = (0..scenes.len()).map(|i| labels.mask(i)).collect::<anyhow::Result<Vec<_>>>()?.concat();
        }
        let captions = match need.captions {
            true => Some(Captions::load(Tokens::open(ctx.input("tokens")?)?, labels.frames.len())?),
            false => None,
        };
        Ok(Frames { side: side as i64, pixels, masks, labels, captions })
    }

    pub fn len(&self) -> usize {
        self.labels.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn frame_bytes(&self) -> usize {
        (self.side * self.side) as usize
    }

    /// The frames' pixels, one image after another.
    pub fn pixels(&self, frames: &[usize]) -> Vec<u8> {
        let n = self.frame_bytes();
        frames.iter().flat_map(|&f| self.pixels[f * n..(f + 1) * n].iter().copied()).collect()
    }

    /// The frames' images as the towers take them, (frames, 1, side, side) in [-1, 1].
    pub fn images(&self, frames: &[usize], device: tch::Device) -> Tensor {
        images_from_u8(&self.pixels(frames), frames.len() as i64, self.side, device)
    }

    /// The frames' 48 cell counts, (frames, 48) floats.
    pub fn counts(&self, frames: &[usize], device: tch::Device) -> Tensor {
        let counts: Vec<f32> = frames.iter().flat_map(|&f| self.labels.frames[f].grid.counts.iter().map(|&c| c as f32)).collect();
        Tensor::from_slice(&counts).view([frames.len() as i64, CELLS as i64]).to_device(device)
    }

    /// Frame `frame`'s mask bytes (loaded with [`Need::masks`]).
    pub fn mask(&self, frame: usize) -> &[u8] {
        let n = self.frame_bytes();
        &self.masks[frame * n..(frame + 1) * n]
    }

    /// The frames' masks as targets in [0, 1], (frames, 1, side, side).
    pub fn masks(&self, frames: &[usize], device: tch::Device) -> Tensor {
        let bytes: Vec<u8> = frames.iter().flat_map(|&f| self.mask(f).iter().copied()).collect();
        Tensor::from_slice(&bytes).view([frames.len() as i64, 1, self.side, self.side]).to_device(device).to_kind(Kind::Float) / 255.0
    }

    /// The roles of the frames: a validation slice of about `validation` of the training split's
    /// groups (none for 0; by frame identity, episodes whole), and with `captioned` only frames
    /// that have a caption.
    pub fn splits(&self, validation: f64, captioned: bool) -> Splits {
        let keep = |labels: Vec<&FrameLabel>| -> Vec<usize> {
            let rows = self.captions.as_ref().map(|c| &c.rows);
            labels.into_iter().map(|f| f.frame as usize).filter(|&f| !captioned || rows.is_some_and(|r| !r[f].is_empty())).collect()
        };
        let (train, validation) = match validation > 0.0 {
            true => self.labels.train_validation(validation),
            false => (self.labels.split(Split::Train).collect(), Vec::new()),
        };
        Splits { train: keep(train), validation: keep(validation), test: keep(self.labels.split(Split::Test).collect()) }
    }
}

impl Splits {
    /// An error naming the empty roles unless every role `user` needs has frames (`validation`
    /// only when it holds a slice).
    pub fn require(&self, user: &str, validation: bool) -> anyhow::Result<()> {
        let (t, v, e) = (self.train.len(), self.validation.len(), self.test.len());
        if t == 0 || e == 0 || (validation && v == 0) {
            let counts =
                if validation { format!("{t} training, {v} validation and {e} test frames") } else { format!("{t} training and {e} test frames") };
            // Advice that can help: the share that is empty, or more frames.
            let advice = if e == 0 {
                "more frames, or a larger test_fraction in the labels stage"
            } else if t == 0 {
                "more frames, or a smaller test_fraction in the labels stage"
            } else {
                "more frames, or a larger `validation` share"
            };
            bail!("{counts}: {user} needs frames in each ({advice})");
        }
        Ok(())
    }
}

impl Captions {
    fn load(tokens: Tokens, frames: usize) -> anyhow::Result<Captions> {
        let ids = tokens.ids.all_u32().context("reading the token ids")?.into_iter().map(i64::from).collect();
        let rows = tokens.rows_by_frame(frames)?;
        Ok(Captions { context: tokens.summary.context as i64, ids, rows, tokens })
    }

    /// Caption rows' token ids, (rows, context).
    pub fn ids(&self, rows: &[usize], device: tch::Device) -> Tensor {
        let c = self.context as usize;
        let ids: Vec<i64> = rows.iter().flat_map(|&r| self.ids[r * c..(r + 1) * c].iter().copied()).collect();
        Tensor::from_slice(&ids).view([rows.len() as i64, self.context]).to_device(device)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_empty_role_is_an_error_naming_the_counts_and_who_needs_them() {
        let split = Splits { train: vec![0, 1], validation: Vec::new(), test: vec![2] };
        assert!(split.require("the encoder", false).is_ok(), "no validation slice asked for");
        let e = split.require("segmentation", true).unwrap_err().to_string();
        assert_eq!(e, "2 training, 0 validation and 1 test frames: segmentation needs frames in each (more frames, or a larger `validation` share)");
        let none = Splits { train: Vec::new(), validation: Vec::new(), test: vec![2] };
        assert_eq!(
            none.require("the encoder", false).unwrap_err().to_string(),
            "0 training and 1 test frames: the encoder needs frames in each (more frames, or a smaller test_fraction in the labels stage)"
        );
    }
}
