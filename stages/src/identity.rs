//! Frame identity, the split rule, and the overlap check that keeps a probe's test frames out of
//! everything its encoder learnt from.
//!
//! A frame's identity is the digest of its content (scenario, actors, every image's pixels),
//! taken where the frame is born and carried unchanged through mixes, shards and imports, so the
//! same frame has the same identity in every artifact that holds it. Frames of one sequence share
//! an episode id; the split is decided per *group*: the episode where there is one, else the
//! frame itself.
//!
//! The split rule: a group is held out for testing when
//! `BLAKE3("rlmflow split v1", split_seed, group)`, read as a number in [0, 1), is below
//! `test_fraction`. It depends on nothing but the group and the two settings, so a labels stage
//! puts the same frame in the same split whatever else its artifact holds and in whatever order,
//! and a smaller `test_fraction` holds out a subset of a larger one's test frames. The price is
//! that a stratum's test share (frames with n vehicles, say) is exact only in expectation; the
//! labels summary states the achieved share per stratum.
//!
//! The sets of frames a model learnt from travel with its artifact as sorted identity lists
//! (`FrameSet`, one hex identity per line), so a probe can count how many of its test frames its
//! encoder or tokenizer saw, and refuse to run unless told the overlap is deliberate.

use std::collections::BTreeSet;
use std::path::Path;

use anyhow::{Context as _, bail};
use serde::{Deserialize, Serialize};

/// Hex characters in an identity (128 bits).
pub const ID_CHARS: usize = 32;

/// The identity of a frame with this content.
pub fn frame_id(scenario: &str, actors_json: &str, images: &[Vec<u8>]) -> String {
    let mut h = blake3::Hasher::new_derive_key("rlmflow frame identity v1");
    for part in [scenario.as_bytes(), actors_json.as_bytes()].into_iter().chain(images.iter().map(Vec::as_slice)) {
        h.update(&(part.len() as u64).to_le_bytes());
        h.update(part);
    }
    h.finalize().to_hex()[..ID_CHARS].to_string()
}

/// Where a group falls in [0, 1) for the split rule with this seed.
pub fn split_position(group: &str, split_seed: u64) -> f64 {
    let mut h = blake3::Hasher::new_derive_key("rlmflow split v1");
    h.update(&split_seed.to_le_bytes());
    h.update(group.as_bytes());
    let bytes: [u8; 8] = h.finalize().as_bytes()[..8].try_into().expect("8 bytes");
    // 53 bits: every value is exact in an f64.
    (u64::from_le_bytes(bytes) >> 11) as f64 / (1u64 << 53) as f64
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
/// Which side of the split a frame is on.
pub enum Split {
    Train,
    Test,
}

impl Split {
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
        }
    }
}

/// What the split rule splits: a sequence's frames together, or each frame on its own.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SplitBy {
    /// A sequence's frames share one split (a frame outside any sequence is its own group).
    Episode,
    /// Each frame is split on its own (near-duplicate neighbours then straddle the split).
    Frame,
}

impl SplitBy {
    /// The group a frame with this identity and episode is split with.
    pub fn group<'a>(self, id: &'a str, episode: Option<&'a str>) -> &'a str {
        match self {
            SplitBy::Episode => episode.unwrap_or(id),
            SplitBy::Frame => id,
        }
    }
}

/// The split of a group (see the module doc).
pub fn split_of(group: &str, test_fraction: f64, split_seed: u64) -> Split {
    if split_position(group, split_seed) < test_fraction { Split::Test } else { Split::Train }
}

/// A set of frame identities: the frames a model learnt from, or a probe tests on.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct FrameSet(pub BTreeSet<String>);

impl FrameSet {
    pub fn len(&self) -> u64 {
        self.0.len() as u64
    }

    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// How many of `self`'s frames are also in `other`.
    pub fn overlap(&self, other: &FrameSet) -> u64 {
        let (small, large) = if self.0.len() <= other.0.len() { (self, other) } else { (other, self) };
        small.0.iter().filter(|id| large.0.contains(*id)).count() as u64
    }

    /// One identity per line, sorted.
    pub fn write(&self, path: &Path) -> anyhow::Result<()> {
        let text: String = self.0.iter().map(|id| format!("{id}\n")).collect();
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
    }

    pub fn read(path: &Path) -> anyhow::Result<FrameSet> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let mut set = BTreeSet::new();
        for (i, line) in text.lines().enumerate() {
            if line.len() != ID_CHARS || !line.bytes().all(|b| b.is_ascii_hexdigit()) {
                bail!("{}:{}: not a frame identity ({ID_CHARS} hex characters)", path.display(), i + 1);
            }
            set.insert(line.to_owned());
        }
        Ok(FrameSet(set))
    }
}

impl FromIterator<String> for FrameSet {
    fn from_iter<I: IntoIterator<Item = String>>(iter: I) -> FrameSet {
        FrameSet(iter.into_iter().collect())
    }
}

/// What a probe's test frames were compared with.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Overlap {
    /// `encoder training` (the frames the radar tower trained on), `encoder's tokenizer` or
    /// `tokenizer` (the frames whose captions a vocabulary was learnt from).
    pub against: String,
    /// The input slot that carried the set (`encoder`, `tokens`); the instance behind it is
    /// the engine's to name (stage names stay out of artifacts, as they are out of keys).
    pub slot: String,
    /// Frames it learnt from.
    pub frames: u64,
    /// The probe's test frames.
    pub test_frames: u64,
    /// Test frames among `frames`.
    pub overlap: u64,
    /// The probe opted in to a non-zero overlap (`allow_test_overlap`).
    pub allowed: bool,
}

/// One set of frames something upstream learnt from: what it is, the slot that carried it, the
/// producing instance (for the message) and the set.
pub struct Learnt<'a> {
    pub against: &'static str,
    pub slot: &'static str,
    pub label: &'a str,
    pub set: FrameSet,
}

/// Counts the probe's test frames among each learnt set and refuses a non-zero count unless
/// `allow` is set. `stage` is the probe's instance.
pub fn check_overlap(stage: &str, test: &FrameSet, learnt: &[Learnt], allow: bool) -> anyhow::Result<Vec<Overlap>> {
    let mut out = Vec::new();
    for Learnt { against, slot, label: source, set } in learnt {
        let overlap = test.overlap(set);
        if overlap > 0 && !allow {
            bail!(
                "{stage}: {overlap} of its {} test frames are among the {} frames `{source}` learnt from ({against}); a probe must test \
                 on frames its encoder and tokenizer never saw. Give every labels stage the same `test_fraction` and `split_seed` (a \
                 frame's split follows its identity), or set `allow_test_overlap = true` on this stage for a deliberate study (the \
                 report then flags the row)",
                test.len(),
                set.len()
            );
        }
        out.push(Overlap {
            against: against.to_string(),
            slot: slot.to_string(),
            frames: set.len(),
            test_frames: test.len(),
            overlap,
            allowed: allow,
        });
    }
    Ok(out)
}

/// The overlap check of a probe or segmenter: its test frames against the frames its `encoder`
/// input (or the encoder behind its `embeddings`) trained on and its tokenizer learnt from, and
/// those its own `tokens` input (if any) learnt from. Refuses a non-zero overlap unless `allow`.
pub fn check_inputs(ctx: &crate::context::Context, test: &FrameSet, allow: bool) -> anyhow::Result<Vec<Overlap>> {
    let mut learnt = Vec::new();
    let label = |slot: &'static str| ctx.input_label(slot).filter(|l| !l.is_empty()).unwrap_or(slot);
    // An encoder, and the features of a frozen one, which carry its sets with them.
    for slot in ["encoder", "embeddings"] {
        let Some(dir) = ctx.optional_input(slot) else { continue };
        let set = FrameSet::read(&dir.join(crate::encoder::TRAINED))?;
        learnt.push(Learnt { against: "encoder training", slot, label: label(slot), set });
        let tokenizer = dir.join(crate::encoder::TOKENIZER_FRAMES);
        if tokenizer.exists() {
            learnt.push(Learnt { against: "encoder's tokenizer", slot, label: label(slot), set: FrameSet::read(&tokenizer)? });
        }
    }
    if let Some(dir) = ctx.optional_input("tokens") {
        let set = FrameSet::read(&dir.join(crate::tokens::LEARNT))?;
        learnt.push(Learnt { against: "tokenizer", slot: "tokens", label: label("tokens"), set });
    }
    let rows = check_overlap(&ctx.stage, test, &learnt, allow)?;
    for row in &rows {
        ctx.event("overlap", serde_json::to_value(row)?);
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ids(range: std::ops::Range<u32>) -> Vec<String> {
        range.map(|i| frame_id("s", &format!("[{i}]"), &[vec![i as u8; 4]])).collect()
    }

    #[test]
    fn identities_follow_content_only() {
        let a = frame_id("highway", "[]", &[vec![1, 2, 3]]);
        assert_eq!(a.len(), ID_CHARS);
        assert_eq!(a, frame_id("highway", "[]", &[vec![1, 2, 3]]));
        assert_ne!(a, frame_id("highway", "[]", &[vec![1, 2, 4]]));
        assert_ne!(a, frame_id("merge", "[]", &[vec![1, 2, 3]]));
        // Length prefixes: moving a byte between parts changes the identity.
        assert_ne!(frame_id("s", "ab", &[vec![]]), frame_id("s", "a", &[b"b".to_vec()]));
    }

    #[test]
    fn the_split_is_a_function_of_the_group_and_nested_in_the_test_fraction() {
        let groups = ids(0..4000);
        let at = |f: f64| groups.iter().map(|g| split_of(g, f, 3)).collect::<Vec<_>>();
        let (small, large) = (at(0.1), at(0.2));
        for (s, l) in small.iter().zip(&large) {
            assert!(*s == Split::Train || *l == Split::Test, "a 10% test frame is a 20% test frame");
        }
        let share = large.iter().filter(|s| **s == Split::Test).count() as f64 / 4000.0;
        assert!((share - 0.2).abs() < 0.02, "{share}");
        assert_ne!(large, groups.iter().map(|g| split_of(g, 0.2, 4)).collect::<Vec<_>>(), "the seed matters");
    }

    #[test]
    fn sets_round_trip_and_count_their_overlap() {
        let dir = std::env::temp_dir().join(format!("rlmflow-identity-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let a: FrameSet = ids(0..10).into_iter().collect();
        let b: FrameSet = ids(7..20).into_iter().collect();
        assert_eq!((a.overlap(&b), b.overlap(&a)), (3, 3));
        a.write(&dir.join("a.txt")).unwrap();
        assert_eq!(FrameSet::read(&dir.join("a.txt")).unwrap(), a);
        std::fs::write(dir.join("bad.txt"), format!("{}\nzz\n", ids(0..1)[0])).unwrap();
        let e = FrameSet::read(&dir.join("bad.txt")).unwrap_err().to_string();
        assert!(e.ends_with("bad.txt:2: not a frame identity (32 hex characters)"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_overlap_is_refused_with_both_stages_named_unless_allowed() {
        let test: FrameSet = ids(0..10).into_iter().collect();
        let seen: FrameSet = ids(8..30).into_iter().collect();
        let clean: FrameSet = ids(10..30).into_iter().collect();
        let learnt = |against, label, set: &FrameSet| Learnt { against, slot: "encoder", label, set: set.clone() };
        let e = check_overlap("clipcap[vanilla]", &test, &[learnt("encoder training", "pretrain[vanilla]", &seen)], false).unwrap_err();
        let e = e.to_string();
        assert!(e.starts_with("clipcap[vanilla]: 2 of its 10 test frames are among the 22 frames `pretrain[vanilla]` learnt from"), "{e}");
        assert!(e.contains("allow_test_overlap = true"), "{e}");
        let rows = check_overlap("p", &test, &[learnt("encoder training", "e", &clean), learnt("tokenizer", "t", &seen)], true).unwrap();
        assert_eq!(rows.iter().map(|r| (r.overlap, r.allowed)).collect::<Vec<_>>(), [(0, true), (2, true)]);
    }
}
