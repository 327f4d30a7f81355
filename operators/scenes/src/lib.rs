//! The `scenes` stage kind's operators, and `concat` (kind `mix`), which joins Scenes artifacts. `procedural` (pure Rust) places vehicles, without
//! dynamics, on sampled road layouts; `highway-env` (with the `highway` feature) simulates
//! traffic in highway-env through the embedded Python. Both render through the shared radar
//! model and write the same Scenes artifact; `import` writes it from a researcher's own recordings.

mod concat;
mod datasets;
mod geometry;
#[cfg(feature = "highway")]
mod highway;
mod import;
mod layout;
mod procedural;
mod raw;
mod render;
mod writer;

pub use concat::{Concat, ConcatSettings};
pub use datasets::UnknownClasses;
#[cfg(feature = "highway")]
pub use highway::{HighwayEnv, HighwaySettings, SCENARIOS, ScenarioMix};
pub use import::{Axes, AzimuthBins, Format, Import, ImportSettings, Layout};
pub use procedural::{Procedural, ProceduralSettings};
pub use raw::Power;
pub use render::{Rendered, Renderer, Scene, Vehicle};
pub use writer::SceneWriter;
