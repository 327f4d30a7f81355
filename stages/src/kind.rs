//! Stage kinds: what a stage consumes and produces, independent of how (the operator).

use crate::artifact::*;
use crate::measure::Measures;

/// How many upstream artifacts an input slot takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Arity {
    /// Exactly one upstream instance; the stage fans out over the upstream's variants.
    One,
    /// Every instance of every providing stage (the report gathers variants side by side).
    All,
}

/// Whether a stage can run without the input.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Need {
    Required,
    Optional,
    /// Bound only to the stages the stage's `inputs` names (a `files` stage reads what it is
    /// given, not every artifact of the type).
    Named,
}

/// One named input of a stage kind.
#[derive(Clone, Copy, Debug)]
pub struct Slot {
    pub name: &'static str,
    /// The artifact type the slot accepts, e.g. `Scenes`.
    pub artifact: &'static str,
    pub need: Need,
    pub arity: Arity,
}

impl Slot {
    pub const fn one(name: &'static str, artifact: &'static str) -> Slot {
        Slot { name, artifact, need: Need::Required, arity: Arity::One }
    }
    pub const fn optional(name: &'static str, artifact: &'static str) -> Slot {
        Slot { name, artifact, need: Need::Optional, arity: Arity::One }
    }
    pub const fn gather(name: &'static str, artifact: &'static str) -> Slot {
        Slot { name, artifact, need: Need::Optional, arity: Arity::All }
    }
    /// The one stage `inputs` names (fanning out over its variants), none unless it names one.
    pub const fn named_one(name: &'static str, artifact: &'static str) -> Slot {
        Slot { name, artifact, need: Need::Named, arity: Arity::One }
    }
    /// Every instance of the stages `inputs` names, none unless it names some.
    pub const fn named(name: &'static str, artifact: &'static str) -> Slot {
        Slot { name, artifact, need: Need::Named, arity: Arity::All }
    }
    /// Every instance of the providing stages, at least one of them.
    pub const fn gather_some(name: &'static str, artifact: &'static str) -> Slot {
        Slot { name, artifact, need: Need::Required, arity: Arity::All }
    }
}

/// A stage kind: a named transformation from input artifacts to one output artifact.
#[derive(Clone, Copy, Debug)]
pub struct StageKind {
    pub name: &'static str,
    pub produces: &'static str,
    pub inputs: &'static [Slot],
    /// Whether its stages run once per seed when `[pipeline] seeds` is set (training does;
    /// data is shared across seeds). A stage's `per_seed` key overrides it.
    pub per_seed: bool,
}

impl StageKind {
    pub fn slot(&self, name: &str) -> Option<&Slot> {
        self.inputs.iter().find(|s| s.name == name)
    }
}

/// The set of stage kinds a registry knows, and the file that marks each artifact type.
#[derive(Clone, Debug, Default)]
pub struct Catalog {
    pub kinds: Vec<StageKind>,
    /// An artifact type and a file every artifact of it holds: what tells an artifact's type
    /// from its files (a pulled record naming another type's artifact is refused by it).
    pub markers: Vec<(&'static str, &'static str)>,
    /// How the artifact types that measure something are measured (claims, per-frame
    /// differences).
    pub measures: Vec<crate::measure::Measures>,
}

impl Catalog {
    pub fn get(&self, name: &str) -> Option<&StageKind> {
        self.kinds.iter().find(|k| k.name == name)
    }

    /// The stage kinds of the paper's pipeline (docs/reference/artifacts.md describes each).
    pub fn paper() -> Catalog {
        Catalog { kinds: PAPER_KINDS.to_vec(), markers: PAPER_MARKERS.to_vec(), measures: PAPER_MEASURES.to_vec() }
    }

    /// How artifacts of type `artifact` are measured, if they are.
    pub fn measures(&self, artifact: &str) -> Option<&crate::measure::Measures> {
        self.measures.iter().find(|m| m.artifact == artifact)
    }

    /// `Ok` when the artifact in `dir` is of type `artifact` as far as its files tell (a type
    /// without a marker passes); else what is wrong.
    pub fn check_artifact(&self, artifact: &str, dir: &std::path::Path) -> Result<(), String> {
        match self.markers.iter().find(|(t, _)| *t == artifact) {
            Some((_, marker)) if !dir.join(marker).is_file() => Err(format!("its artifact holds no `{marker}`: it is not a {artifact} artifact")),
            _ => Ok(()),
        }
    }
}

const PAPER_MARKERS: &[(&str, &str)] = &[
    (SCENES, crate::scenes::SUMMARY),
    (LABELS, crate::labels::SUMMARY),
    (CAPTIONS, crate::captions::SUMMARY),
    (TOKENS, crate::tokens::SUMMARY),
    (ENCODER, crate::encoder::SUMMARY),
    (PROBE_REPORT, crate::probe::SUMMARY),
    (SEG_REPORT, crate::segment::SUMMARY),
    (REPORT, "metrics.json"),
    (EMBEDDINGS, crate::embeddings::SUMMARY),
];

/// The paper's artifact types that measure: encoders, probe and segmentation reports.
const PAPER_MEASURES: &[Measures] = &[
    Measures { artifact: ENCODER, metrics: |dir| Ok(crate::encoder::metrics(&crate::encoder::Encoder::open(dir)?.summary)), frames: None },
    Measures {
        artifact: PROBE_REPORT,
        metrics: |dir| Ok(crate::probe::metrics(&crate::probe::read_summary(dir)?)),
        frames: Some(crate::probe::frame_differences),
    },
    Measures {
        artifact: SEG_REPORT,
        metrics: |dir| Ok(crate::segment::metrics(&crate::segment::read_summary(dir)?)),
        frames: Some(crate::segment::frame_differences),
    },
];

const PAPER_KINDS: &[StageKind] = &[
    StageKind { name: "scenes", produces: SCENES, inputs: &[], per_seed: false },
    // Several Scenes artifacts as one (drives mixed with placed scenes, for pretraining).
    StageKind { name: "mix", produces: SCENES, inputs: &[Slot::gather_some("scenes", SCENES)], per_seed: false },
    StageKind { name: "labels", produces: LABELS, inputs: &[Slot::one("scenes", SCENES)], per_seed: false },
    StageKind { name: "captions", produces: CAPTIONS, inputs: &[Slot::one("labels", LABELS)], per_seed: false },
    // Several Captions artifacts of disjoint frames as one (the shares of a sharded llm stage).
    StageKind { name: "mix-captions", produces: CAPTIONS, inputs: &[Slot::gather_some("captions", CAPTIONS)], per_seed: false },
    StageKind { name: "tokens", produces: TOKENS, inputs: &[Slot::one("captions", CAPTIONS)], per_seed: false },
    StageKind {
        name: "pretrain",
        produces: ENCODER,
        inputs: &[Slot::one("scenes", SCENES), Slot::one("labels", LABELS), Slot::one("tokens", TOKENS)],
        per_seed: true,
    },
    StageKind {
        name: "probe",
        produces: PROBE_REPORT,
        // Optional: a pixel baseline reads no encoder (`inputs = { encoder = [] }`).
        inputs: &[
            Slot::optional("encoder", ENCODER),
            Slot::one("scenes", SCENES),
            Slot::one("labels", LABELS),
            Slot::one("tokens", TOKENS),
            // A frozen encoder's features, for a probe that reads them rather than the encoder.
            Slot::named_one("embeddings", EMBEDDINGS),
        ],
        per_seed: true,
    },
    StageKind {
        name: "segment",
        produces: SEG_REPORT,
        inputs: &[
            Slot::optional("encoder", ENCODER),
            Slot::one("scenes", SCENES),
            Slot::one("labels", LABELS),
            Slot::named_one("embeddings", EMBEDDINGS),
        ],
        per_seed: true,
    },
    // A frozen encoder's features of every frame of its scenes, with the labels' split.
    StageKind {
        name: "embed",
        produces: EMBEDDINGS,
        inputs: &[Slot::one("encoder", ENCODER), Slot::one("scenes", SCENES), Slot::one("labels", LABELS)],
        per_seed: true,
    },
    StageKind {
        name: "report",
        produces: REPORT,
        inputs: &[
            Slot::gather("probe", PROBE_REPORT),
            Slot::gather("segment", SEG_REPORT),
            Slot::gather("encoder", ENCODER),
            // The frames the samples are drawn from: the scenes and labels the probes read.
            Slot::optional("scenes", SCENES),
            Slot::optional("labels", LABELS),
        ],
        per_seed: false,
    },
    // A user's program whose output no built-in stage reads (a figure, a table, an export): it
    // reads the artifacts its `inputs` names.
    StageKind {
        name: "files",
        produces: FILES,
        inputs: &[
            Slot::named("scenes", SCENES),
            Slot::named("labels", LABELS),
            Slot::named("captions", CAPTIONS),
            Slot::named("tokens", TOKENS),
            Slot::named("encoder", ENCODER),
            Slot::named("probe", PROBE_REPORT),
            Slot::named("segment", SEG_REPORT),
            Slot::named("report", REPORT),
            Slot::named("embeddings", EMBEDDINGS),
            Slot::named("files", FILES),
        ],
        per_seed: false,
    },
];
