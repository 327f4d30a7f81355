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

/// The variant dimension the engine fans seeds out on.
pub const SEED: &str = "seed";

/// A stage instance as the engine names it (`rlmflow_stages::InstanceId`): its stage and, per
/// variant dimension (the stage that declared the variants, or `seed`), its variant.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Instance {
    pub stage: String,
    pub assignment: BTreeMap<String, String>,
}

impl From<&InstanceId> for Instance {
    fn from(id: &InstanceId) -> Instance {
        Instance { stage: id.stage.clone(), assignment: id.variant.clone() }
    }
}

impl Instance {
    /// The seed this instance ran with, when seeds fan out.
    pub fn seed(&self) -> Option<&str> {
        self.assignment.get(SEED).map(String::as_str)
    }

    /// The instance with its seed left out: instances with the same row differ only in seed.
    pub fn row(&self) -> Instance {
        let mut row = self.clone();
        row.assignment.remove(SEED);
        row
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
        upstream.assignment.iter().all(|(d, v)| match d.as_str() {
            SEED if self.seed().is_none() => true,
            _ => self.assignment.get(d) == Some(v),
        })
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
        self.encoders.iter().filter(|e| !e.instance.assignment.is_empty()).find(|e| instance.reads(&e.instance)).or_else(|| {
            // A single unvaried encoder stage is read by every probe that reads one.
            (self.encoders.len() == 1 && self.encoders[0].instance.assignment.is_empty()).then(|| &self.encoders[0])
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
        Instance { stage: stage.into(), assignment: variant.iter().map(|(d, v)| (d.to_string(), v.to_string())).collect() }
    }

    #[test]
    fn instances_relate_by_stage_and_variant() {
        let plain = id("unet", &[]);
        assert_eq!((plain.stage.as_str(), plain.assignment.len(), plain.variant()), ("unet", 0, String::new()));
        let one = id("clipcap", &[("pretrain", "alpha4")]);
        assert_eq!(one.variant(), "alpha4");
        assert!(one.reads(&id("pretrain", &[("pretrain", "alpha4")])));
        assert!(!one.reads(&id("pretrain", &[("pretrain", "alpha1")])));
        let two = id("clipcap", &[("pretrain", "alpha4"), ("seed", "2")]);
        assert_eq!(two.seed(), Some("2"));
        assert_eq!(two.row().variant(), "alpha4");
        assert_eq!(two.row(), id("clipcap", &[("pretrain", "alpha4"), ("seed", "3")]).row());
        assert!(two.reads(&id("pretrain", &[("pretrain", "alpha4"), ("seed", "2")])));
        assert!(!two.reads(&id("pretrain", &[("pretrain", "alpha4"), ("seed", "3")])));
        assert!(two.row().reads(&id("pretrain", &[("pretrain", "alpha4"), ("seed", "3")])));
    }
}
