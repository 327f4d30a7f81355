//! The `scenes` stage kind's operators. `procedural` (pure Rust) places vehicles, without
//! dynamics, on sampled road layouts and renders them through the shared radar model.

mod layout;
mod procedural;
mod render;
mod writer;

pub use procedural::{Procedural, ProceduralSettings};
