//! The contracts between rlmflow's engine and its operators.
//!
//! * [`kind`]: stage kinds and the artifact types they consume and produce, as data. The paper's
//!   pipeline is one [`Catalog`]; tests add their own kinds. [`artifact`] names the types once.
//! * [`operator`]: the [`Operator`] trait (one implementation of a stage kind) and the
//!   type-erased [`DynOperator`]; [`settings`]: its typed [`Settings`], parsed once per stage
//!   instance into [`Parsed`]; [`outline`]: what a stage's output will be, as settings tell;
//!   [`registry`]: the operators a binary knows.
//! * [`context`]: what an operator is given when it runs: input paths, an output directory, a
//!   checkpoint directory that survives a crash, the seed, a thread budget and a progress handle.
//!
//! * [`grid`]: the paper's ego grid and its JSON; [`segment`]: the segmentation metrics;
//!   [`identity`]: frame identities, the split rule and the train/test overlap check.
//! * [`scenes`], [`labels`], [`captions`], [`tokens`], [`encoder`], [`embeddings`], [`probe`]: each artifact's directory layout, its
//!   writer-side line formats and its reader; [`npy`] for their dense arrays.
//! * [`claims`]: claims comparing two metrics paired by seed, and the rule deciding them as seeds
//!   are added; [`measure`]: what an artifact measures (metrics, per-frame differences).
//! * [`numerics`]: the numeric platform a model action's bytes depend on: its kernel pins and the
//!   class of machines that share its results.
//! * [`training`]: the settings every training operator shares; [`weights`]: the check of a
//!   weights file a setting names; [`memory`]: a training action's memory, estimated from shapes;
//!   [`items`]: the seed rule of every per-item draw, and items over threads; [`reading`]: how
//!   the artifact readers read summaries and JSON Lines.
//!
//! Nothing here knows about scheduling, caching or processes, and nothing links a tensor
//! library: model shapes and training settings are plain data here, computed on elsewhere.

pub mod artifact;
pub mod captions;
pub mod claims;
pub mod context;
pub mod embeddings;
pub mod encoder;
pub mod grid;
pub mod identity;
pub mod items;
pub mod kind;
pub mod labels;
pub mod measure;
pub mod memory;
pub mod npy;
pub mod numerics;
pub mod operator;
pub mod outline;
pub mod probe;
pub mod reading;
pub mod registry;
pub mod scenes;
pub mod segment;
pub mod settings;
pub mod tokens;
pub mod training;
pub mod weights;

pub use context::{Context, Device, Input, InstanceId, Progress, Reporter};
pub use items::{item_seed, parallel_map};
pub use kind::{Arity, Catalog, Need, Slot, StageKind};
pub use memory::Footprint;
pub use numerics::{Kernels, Numerics};
pub use operator::{DynOperator, InWorker, ItemCount, Items, Operator, OperatorSpec, Outcome, Part, Resources, Sharding, Share};
pub use outline::{InputOutlines, ModelOutline, Outline};
pub use registry::Registry;
pub use settings::{FilePattern, Parsed, SettingError, Settings};
pub use training::Training;
