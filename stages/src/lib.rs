//! The contracts between rlmflow's engine and its operators.
//!
//! * [`kind`]: stage kinds and the artifact types they consume and produce, as data. The paper's
//!   pipeline is one [`Catalog`]; tests add their own kinds.
//! * [`operator`]: the [`Operator`] trait (one implementation of a stage kind), its typed
//!   [`Settings`], and the type-erased [`DynOperator`] the engine stores in its registry.
//! * [`context`]: what an operator is given when it runs: input paths, an output directory, a
//!   checkpoint directory that survives a crash, the seed, a thread budget and a progress handle.
//!
//! * [`grid`]: the paper's ego grid and its JSON.
//! * [`scenes`], [`labels`], [`captions`], [`tokens`]: each artifact's directory layout, its
//!   writer-side line formats and its reader; [`npy`] for their dense arrays.
//!
//! Nothing here knows about scheduling, caching or processes; nothing here knows machine learning.

pub mod captions;
pub mod context;
pub mod grid;
pub mod kind;
pub mod labels;
pub mod npy;
pub mod operator;
pub mod scenes;
pub mod tokens;

pub use context::{Context, Device, Input, Progress, Reporter};
pub use kind::{Arity, Catalog, Need, Slot, StageKind};
pub use operator::{DynOperator, Operator, OperatorSpec, Outcome, Registry, Resources, SettingError, Settings};
