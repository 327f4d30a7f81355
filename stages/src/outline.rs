//! What a stage's output will be, as far as its settings tell before anything runs, and what a
//! stage's checks across stages read of its inputs'.

use crate::settings::SettingError;

/// What a stage's output will be, as far as settings tell before anything runs: what checks
/// across stages read (an image side a ViT patch must divide, frames a batch must not exceed).
/// `None`: not known from settings.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Outline {
    /// The side of the frames' primary image, in pixels.
    pub image: Option<u64>,
    /// The frames the artifact holds.
    pub frames: Option<u64>,
    /// The groups a split keeps whole (a sequence's frames; a frame outside any is its own).
    pub groups: Option<u64>,
    /// The frames of the training split, in expectation (the split is by identity): what a
    /// batch is checked against.
    pub train_frames: Option<u64>,
    /// A tokens artifact's tokens per caption and largest vocabulary.
    pub context: Option<u64>,
    pub vocab: Option<u64>,
    /// The model an encoder artifact holds.
    pub model: Option<ModelOutline>,
}

/// An encoder's model as its consumers' memory estimates need it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ModelOutline {
    pub parameters: u64,
    /// The radar tower's token width and the side of its token grid.
    pub width: u64,
    pub grid: u64,
    /// The shared space's width.
    pub embed: u64,
}

impl Outline {
    /// What two outlines (a stage's variants) agree on.
    pub fn common(self, other: Outline) -> Outline {
        fn same<T: PartialEq>(a: Option<T>, b: Option<T>) -> Option<T> {
            if a == b { a } else { None }
        }
        Outline {
            image: same(self.image, other.image),
            frames: same(self.frames, other.frames),
            groups: same(self.groups, other.groups),
            train_frames: same(self.train_frames, other.train_frames),
            context: same(self.context, other.context),
            vocab: same(self.vocab, other.vocab),
            model: same(self.model, other.model),
        }
    }

    /// The outline of input `slot`'s first artifact, if it is bound.
    pub fn of<'a>(inputs: &'a InputOutlines, slot: &str) -> Option<&'a Outline> {
        inputs.get(slot).and_then(|v| v.first())
    }

    /// The outline a stage passes on by default: that of the scenes it reads, else of its first
    /// input.
    pub fn passed_on(inputs: &InputOutlines) -> Outline {
        inputs.get("scenes").or_else(|| inputs.values().next()).and_then(|v| v.first()).copied().unwrap_or_default()
    }

    /// [`Outline::passed_on`] as an [`InWorker`]'s outline check, for settings that read nothing of it.
    pub fn pass_on<S>(_: &S, inputs: &InputOutlines) -> Result<Outline, SettingError> {
        Ok(Outline::passed_on(inputs))
    }
}

/// The outlines of a stage's inputs, by slot (a gathered slot's in order).
pub type InputOutlines<'a> = std::collections::BTreeMap<&'a str, Vec<Outline>>;
