//! The report's inputs, read and related: which encoder each probe read, what each row is (a
//! paper method, a sanity row), and which instances are the same row under another seed.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use rlmflow_stages::encoder::{self, Encoder};
use rlmflow_stages::labels::Labels;
use rlmflow_stages::scenes::Scenes;
use rlmflow_stages::{Context, InstanceId, probe, segment};
use serde_json::Value;

use crate::paper::Method;

/// A stage instance as the engine names it (`rlmflow_stages::InstanceId`): its stage, per
/// variant dimension (the stage that declared the variants) its variant, and its seed.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Instance {
    pub stage: String,
    pub assignment: BTreeMap<String, String>,
    pub seed: Option<u64>,
}

impl From<&InstanceId> for Instance {
    fn from(id: &InstanceId) -> Instance {
        Instance { stage: id.stage.clone(), assignment: id.variant.clone(), seed: id.seed }
    }
}

impl Instance {
    /// The instance with its seed left out: instances with the same row differ only in seed.
    pub fn row(&self) -> Instance {
        Instance { seed: None, ..self.clone() }
    }

    /// Whether it is one of several of its stage: it has variants or a seed.
    fn varies(&self) -> bool {
        !self.assignment.is_empty() || self.seed.is_some()
    }

    /// The variant part a table shows (`alpha4`, `captions=llm, pretrain=alpha4`), empty for none.
    pub fn variant(&self) -> String {
        let named = self.assignment.len() > 1;
        let parts: Vec<String> = self.assignment.iter().map(|(d, v)| if named && !d.is_empty() { format!("{d}={v}") } else { v.clone() }).collect();
        parts.join(", ")
    }

    /// Whether `upstream` (an encoder) is the instance this one read: every dimension of the
    /// upstream has this one's value. A row, which has no seed, reads every seed of its encoder.
    pub fn reads(&self, upstream: &Instance) -> bool {
        let seed = upstream.seed.is_none() || self.seed.is_none() || upstream.seed == self.seed;
        seed && upstream.assignment.iter().all(|(d, v)| self.assignment.get(d) == Some(v))
    }
}

/// What a table row stands for.
#[derive(Clone, Debug, PartialEq)]
pub enum Role {
    /// A method the paper reports, with its numbers beside ours.
    Paper(Method),
    /// The encoder untrained (`epochs = 0`): what pretraining added is the difference.
    RandomInit,
    /// The radar tower trained on the counts directly: an upper reference.
    Counts,
    /// A probe on raw pixels: no encoder at all.
    Pixels,
    /// An encoder the paper has no row for (another alpha, say).
    Other,
}

impl Role {
    pub fn describe(&self) -> String {
        match self {
            Role::Paper(m) => m.name(),
            Role::RandomInit => "random init (sanity)".into(),
            Role::Counts => "trained on counts (upper reference)".into(),
            Role::Pixels => "pixels (baseline)".into(),
            Role::Other => "other".into(),
        }
    }
}

pub struct EncoderRun {
    /// The producing instance's label, as the run names it.
    pub label: String,
    pub instance: Instance,
    pub encoder: Encoder,
    /// `train.jsonl`, one line per epoch.
    pub log: Vec<Value>,
}

impl EncoderRun {
    pub fn role(&self) -> Role {
        let generator = &self.encoder.summary.generator;
        match (self.encoder.summary.epochs, self.encoder.summary.objective.as_str()) {
            (0, _) => Role::RandomInit,
            (_, "counts") => Role::Counts,
            (_, "clip") => Role::Paper(Method::VanillaClip),
            (_, "sg-clip") => match generator["alpha"].as_f64() {
                Some(alpha) => Role::Paper(Method::SgClip(alpha)),
                None => Role::Other,
            },
            _ => Role::Other,
        }
    }

    /// The objective as a table shows it: `clip`, `sg-clip α=4`, `counts`.
    pub fn objective(&self) -> String {
        let s = &self.encoder.summary;
        match (s.objective.as_str(), s.generator["alpha"].as_f64()) {
            ("sg-clip", Some(alpha)) => format!("sg-clip α={alpha}"),
            (o, _) => o.to_owned(),
        }
    }
}

pub struct ProbeRun {
    pub label: String,
    pub instance: Instance,
    pub summary: probe::Summary,
    pub dir: PathBuf,
}

pub struct SegRun {
    pub label: String,
    pub instance: Instance,
    pub summary: segment::Summary,
    pub dir: PathBuf,
}

/// Everything the report reads.
pub struct Study {
    pub encoders: Vec<EncoderRun>,
    pub probes: Vec<ProbeRun>,
    pub segments: Vec<SegRun>,
    pub labels: Option<Labels>,
    pub scenes: Option<Scenes>,
}

impl Study {
    pub fn read(ctx: &Context) -> anyhow::Result<Study> {
        let mut encoders = Vec::new();
        for input in ctx.gathered("encoder") {
            let encoder = Encoder::open(&input.path)?;
            let log = read_log(&input.path.join(encoder::LOG))?;
            encoders.push(EncoderRun { label: input.label.clone(), instance: Instance::from(&input.instance), encoder, log });
        }
        let probes = ctx
            .gathered("probe")
            .iter()
            .map(|i| {
                Ok(ProbeRun {
                    label: i.label.clone(),
                    instance: Instance::from(&i.instance),
                    summary: probe::read_summary(&i.path)?,
                    dir: i.path.clone(),
                })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let segments = ctx
            .gathered("segment")
            .iter()
            .map(|i| {
                Ok(SegRun {
                    label: i.label.clone(),
                    instance: Instance::from(&i.instance),
                    summary: segment::read_summary(&i.path)?,
                    dir: i.path.clone(),
                })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        let labels = ctx.optional_input("labels").map(Labels::open).transpose()?;
        let scenes = ctx.optional_input("scenes").map(Scenes::open).transpose()?;
        if let (Some(labels), Some(scenes)) = (&labels, &scenes) {
            labels.check_scenes(scenes.len()).with_context(|| format!("report {}", ctx.stage))?;
        }
        if probes.is_empty() && segments.is_empty() && encoders.is_empty() {
            bail!("report {} has nothing to report: it gathers no encoder, probe or segment stage", ctx.stage);
        }
        Ok(Study { encoders, probes, segments, labels, scenes })
    }

    /// The encoder an instance read, if any.
    pub fn encoder_of(&self, instance: &Instance) -> Option<&EncoderRun> {
        self.encoders.iter().filter(|e| e.instance.varies()).find(|e| instance.reads(&e.instance)).or_else(|| {
            // A single unvaried encoder stage is read by every probe that reads one.
            (self.encoders.len() == 1 && !self.encoders[0].instance.varies()).then(|| &self.encoders[0])
        })
    }

    /// What a probe or segmenter row stands for.
    pub fn role(&self, instance: &Instance, operator: &str, features: &str) -> Role {
        if features == "pixels" {
            return Role::Pixels;
        }
        if operator == "unet" {
            return Role::Paper(Method::UNet);
        }
        self.encoder_of(instance).map_or(Role::Other, EncoderRun::role)
    }
}

fn read_log(path: &Path) -> anyhow::Result<Vec<Value>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(n, l)| serde_json::from_str(l).with_context(|| format!("{}:{}: not a JSON line", path.display(), n + 1)))
        .collect()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// An instance of `stage` with these variants.
    pub fn id(stage: &str, variant: &[(&str, &str)]) -> Instance {
        Instance { stage: stage.into(), assignment: variant.iter().map(|(d, v)| (d.to_string(), v.to_string())).collect(), seed: None }
    }

    /// The instance of `stage` with these variants and `seed`.
    pub fn seeded(stage: &str, variant: &[(&str, &str)], seed: u64) -> Instance {
        Instance { seed: Some(seed), ..id(stage, variant) }
    }

    #[test]
    fn instances_relate_by_stage_and_variant() {
        let plain = id("unet", &[]);
        assert_eq!((plain.stage.as_str(), plain.assignment.len(), plain.variant()), ("unet", 0, String::new()));
        let one = id("clipcap", &[("pretrain", "alpha4")]);
        assert_eq!(one.variant(), "alpha4");
        assert!(one.reads(&id("pretrain", &[("pretrain", "alpha4")])));
        assert!(!one.reads(&id("pretrain", &[("pretrain", "alpha1")])));
        let two = seeded("clipcap", &[("pretrain", "alpha4")], 2);
        assert_eq!(two.row().variant(), "alpha4");
        assert_eq!(two.row(), seeded("clipcap", &[("pretrain", "alpha4")], 3).row());
        assert!(two.reads(&seeded("pretrain", &[("pretrain", "alpha4")], 2)));
        assert!(!two.reads(&seeded("pretrain", &[("pretrain", "alpha4")], 3)));
        assert!(two.row().reads(&seeded("pretrain", &[("pretrain", "alpha4")], 3)));
        // An encoder that varies by seed alone is told apart by it.
        assert!(seeded("clipcap", &[], 2).reads(&seeded("pretrain", &[], 2)) && !seeded("clipcap", &[], 2).reads(&seeded("pretrain", &[], 3)));
    }
}
