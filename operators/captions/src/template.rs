//! The `template` operator: captions composed from a frame's grid, varied like the paper's LLM
//! captions (sentence forms, synonyms for every sector, sectors shuffled within a bin, numbers
//! as words, distance bins with numbers or in words) and exact: the LLM-free parser reads every
//! caption back to its grid (tested for every variant).

use rand::seq::SliceRandom;
use rand::{Rng, RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rlmflow_parser::number_word;
use rlmflow_stages::captions::Caption;
use rlmflow_stages::grid::{DISTANCE_BINS, Grid, SECTORS};
use rlmflow_stages::labels::{FrameLabel, Labels};
use rlmflow_stages::{Context, Operator, OperatorSpec, Outcome, SettingError, Settings};
use serde::{Deserialize, Serialize};

use crate::write_captions;

pub struct Template;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TemplateSettings {
    /// Captions per frame, 1..=100.
    pub per_frame: usize,
    /// Share of captions that name distance bins by their numbers ("from ten to twenty meters");
    /// the others use words ("close by", "at a moderate distance").
    pub distance_numbers: f64,
}

impl Default for TemplateSettings {
    fn default() -> Self {
        TemplateSettings { per_frame: 5, distance_numbers: 0.5 }
    }
}

impl Settings for TemplateSettings {
    fn check(&self) -> Result<(), SettingError> {
        SettingError::check_range("per_frame", self.per_frame, 1..=100)?;
        if !(0.0..=1.0).contains(&self.distance_numbers) {
            return Err(SettingError::new("distance_numbers", format!("must be in [0, 1], not {}", self.distance_numbers)));
        }
        Ok(())
    }
}

impl Operator for Template {
    type Settings = TemplateSettings;

    fn spec(&self) -> OperatorSpec {
        OperatorSpec {
            name: "template",
            kind: "captions",
            version: 2,
            inputs: None,
            summary: "varied captions composed from the grid, each of which the parser reads back exactly",
        }
    }

    fn run(&self, s: &TemplateSettings, ctx: &mut Context) -> anyhow::Result<Outcome> {
        let labels = Labels::open(ctx.input("labels")?)?;
        let progress = ctx.progress(labels.frames.len() as u64, "frames");
        let mut captions = Vec::with_capacity(labels.frames.len() * s.per_frame);
        for label in &labels.frames {
            captions.extend(frame_captions(s, label, ctx.seed));
            progress.inc(1);
        }
        progress.finish();
        let n = captions.len();
        write_captions(&ctx.output_dir, labels.frames.len() as u64, &captions, s.result_settings())?;
        let words: usize = captions.iter().map(|c| c.caption.split_whitespace().count()).sum();
        let mean_words = words as f64 / n.max(1) as f64;
        Ok(Outcome {
            metrics: serde_json::json!({"captions": n, "mean_words": mean_words}),
            summary: format!("{n} captions for {} frames, {mean_words:.0} words on average", labels.frames.len()),
        })
    }
}

/// A frame's captions: deterministic in (seed, frame).
fn frame_captions(s: &TemplateSettings, label: &FrameLabel, seed: u64) -> Vec<Caption> {
    let mut rng = ChaCha8Rng::seed_from_u64(rlmflow_stages::item_seed(seed, label.frame));
    (0..s.per_frame)
        .map(|_| {
            let numbers = rng.random_bool(s.distance_numbers);
            Caption {
                frame: label.frame,
                id: label.id.clone(),
                split: label.split,
                caption: compose(&label.grid, numbers, &mut Pick::Random(&mut rng)),
            }
        })
        .collect()
}

/// A random caption of `grid`.
pub fn caption(grid: &Grid, distance_numbers: bool, rng: &mut impl Rng) -> String {
    compose(grid, distance_numbers, &mut Pick::Random(rng))
}

/// The caption that takes variant `k` (modulo their number) at every choice: `k` in
/// `0..VARIANTS` visits every variant of every choice.
pub fn caption_variant(grid: &Grid, distance_numbers: bool, k: usize) -> String {
    compose(grid, distance_numbers, &mut Pick::<ChaCha8Rng>::Fixed(k))
}

/// The most variants any one choice has.
pub const VARIANTS: usize = 6;

enum Pick<'a, R> {
    Random(&'a mut R),
    Fixed(usize),
}

impl<R: Rng> Pick<'_, R> {
    fn index(&mut self, n: usize) -> usize {
        match self {
            Pick::Random(rng) => rng.random_range(0..n),
            Pick::Fixed(k) => *k % n,
        }
    }

    fn one<'o>(&mut self, options: &[&'o str]) -> &'o str {
        options[self.index(options.len())]
    }

    fn shuffle<T>(&mut self, items: &mut [T]) {
        match self {
            Pick::Random(rng) => items.shuffle(*rng),
            Pick::Fixed(k) => {
                let n = items.len().max(1);
                items.rotate_left(*k % n);
            }
        }
    }
}

/// Ways to name each sector, by sector index; each reads back to its sector.
const SECTOR_PHRASES: [[&str; 4]; 12] = [
    [
        "in the left adjacent lane ahead of us",
        "ahead of us in the lane to our left",
        "in the left lane in front of us",
        "up ahead in the lane on our left",
    ],
    ["directly to our left", "right beside us on the left", "alongside us on our left side", "next to us in the left lane"],
    ["in the left adjacent lane behind us", "behind us in the lane to our left", "following us in the left lane", "in the left lane to our rear"],
    ["directly ahead of us in the same lane", "in our lane ahead of us", "right in front of us", "ahead of us in our own lane"],
    ["directly behind us in the same lane", "following us in our lane", "behind us in our own lane", "right behind us"],
    [
        "in the right adjacent lane ahead of us",
        "ahead of us in the lane to our right",
        "in the right lane in front of us",
        "up ahead in the lane on our right",
    ],
    ["directly to our right", "right beside us on the right", "alongside us on our right side", "next to us in the right lane"],
    ["in the right adjacent lane behind us", "behind us in the lane to our right", "following us in the right lane", "in the right lane to our rear"],
    [
        "in the opposing lane ahead of us",
        "coming toward us in the oncoming lane",
        "approaching from the opposite direction ahead of us",
        "in the oncoming traffic lane in front of us",
    ],
    [
        "in the opposing lane behind us",
        "driving away behind us in the opposing lane",
        "in the oncoming lane to our rear",
        "behind us travelling in the opposite direction",
    ],
    [
        "in perpendicular or intersecting lanes ahead of us",
        "on crossing roads ahead of us",
        "crossing our path ahead of us",
        "on an intersecting road in front of us",
    ],
    [
        "in perpendicular or intersecting lanes behind us",
        "on crossing roads behind us",
        "on a cross street behind us",
        "on an intersecting road to our rear",
    ],
];

/// Distance bins in words, by bin (used only in captions without distance numbers).
const BIN_WORDS: [[&str; 3]; 4] = [
    ["Very close to us", "In our immediate vicinity", "Extremely close to our car"],
    ["Close to us", "Close by", "At close range"],
    ["At a moderate distance", "At a medium distance", "A moderate distance away"],
    ["Further away", "Farther out", "At a safe distance"],
];

/// Distance bins with numbers; `{a}` and `{b}` are the bounds in words.
const BIN_NUMBERS: [&str; 6] = [
    "From {a} to {b} meters",
    "Between {a} and {b} meters",
    "Within {a} to {b} meters of us",
    "In the {a} to {b} meter range",
    "At a distance of {a} to {b} meters",
    "In the range of {a} to {b} metres",
];

const INTROS: [&str; 5] =
    ["", "As we drive, here is what is around us. ", "Let me describe the traffic around us. ", "Here is the scene around our car. ", ""];
const TRANSITIONS: [&str; 4] = ["", "Next, ", "Then, ", "Moving on, "];

fn vehicles(n: u32, pick: &mut Pick<impl Rng>) -> String {
    if n == 1 {
        pick.one(&["one vehicle", "a vehicle", "a single vehicle", "one car", "a car", "a single car"]).into()
    } else {
        format!("{} {}", number_word(n), pick.one(&["vehicles", "cars"]))
    }
}

fn is_are(n: u32) -> &'static str {
    if n == 1 { "is" } else { "are" }
}

fn capitalise(s: &str) -> String {
    let mut chars = s.chars();
    chars.next().map(|c| c.to_uppercase().chain(chars).collect()).unwrap_or_default()
}

/// The sentence about one distance bin.
fn bin_sentence(grid: &Grid, bin: usize, numbers: bool, pick: &mut Pick<impl Rng>) -> String {
    let intro = if numbers {
        pick.one(&BIN_NUMBERS).replace("{a}", &number_word(bin as u32 * 10)).replace("{b}", &number_word(bin as u32 * 10 + 10))
    } else {
        pick.one(&BIN_WORDS[bin]).to_owned()
    };
    let transition = if bin == 0 { "" } else { pick.one(&TRANSITIONS) };
    let intro = if transition.is_empty() { intro } else { format!("{transition}{}{}", intro[..1].to_lowercase(), &intro[1..]) };
    let total = grid.bin_total(bin);
    if total == 0 {
        return format!(
            "{intro}, {}.",
            pick.one(&["there are no vehicles", "I do not see any vehicles", "there are zero vehicles", "the road is empty of vehicles"])
        );
    }
    let mut sectors: Vec<usize> = (0..SECTORS.len()).filter(|&s| grid.get(bin, s) > 0).collect();
    pick.shuffle(&mut sectors);
    let items: Vec<String> = sectors.iter().map(|&s| format!("{} {}", vehicles(grid.get(bin, s), pick), pick.one(&SECTOR_PHRASES[s]))).collect();
    if sectors.len() == 1 && total > 1 {
        let where_ = pick.one(&SECTOR_PHRASES[sectors[0]]);
        let all = if total == 2 {
            pick.one(&["both of which are", "both of them", "all of which are"])
        } else {
            pick.one(&["all of which are", "all of them"])
        };
        return format!("{intro}, there are {} in total, {all} {where_}.", vehicles(total, pick));
    }
    let list = join(&items, pick);
    match pick.index(4) {
        0 if total > 1 => format!("{intro}, there {} {} in total, with {list}.", is_are(total), vehicles(total, pick)),
        1 => format!("{intro}, I can see {list}."),
        2 => format!("{intro}, there {} {list}.", is_are(grid.get(bin, sectors[0]))),
        _ if total > 1 => format!("{intro}, we have {} altogether: {list}.", vehicles(total, pick)),
        _ => format!("{intro}, I can see {list}."),
    }
}

/// `a, b and c`, with varied joiners.
fn join(items: &[String], pick: &mut Pick<impl Rng>) -> String {
    let mut out = String::new();
    for (i, item) in items.iter().enumerate() {
        if i > 0 {
            out += if i + 1 == items.len() { pick.one(&[" and ", ", and ", ", plus ", " and also "]) } else { ", " };
        }
        out += item;
    }
    out
}

fn walkers_sentence(n: u32, pick: &mut Pick<impl Rng>) -> String {
    match n {
        0 => pick.one(&["There are no walkers on the road.", "I do not see any pedestrians.", "No pedestrians are around."]).into(),
        1 => pick.one(&["There is one walker nearby.", "I can see a single pedestrian.", "A pedestrian is around us."]).into(),
        n => format!("{} {}", capitalise(&number_word(n)), pick.one(&["pedestrians are around us.", "walkers are on the road."])),
    }
}

fn signs_sentence(signs: &[String], pick: &mut Pick<impl Rng>) -> String {
    if signs.is_empty() {
        return pick
            .one(&["There are no applicable traffic signs.", "I do not see any traffic signs that apply to us.", "No traffic signs apply to us."])
            .into();
    }
    let named: Vec<String> =
        signs.iter().map(|s| format!("{} {s} sign", if s.starts_with(['a', 'e', 'i', 'o', 'u']) { "an" } else { "a" })).collect();
    format!("{} {}.", pick.one(&["I notice", "There is", "Ahead there is"]), join(&named, pick))
}

fn compose(grid: &Grid, numbers: bool, pick: &mut Pick<impl Rng>) -> String {
    let mut out = pick.one(&INTROS).to_owned();
    let sentences: Vec<String> = (0..DISTANCE_BINS.len()).map(|bin| bin_sentence(grid, bin, numbers, pick)).collect();
    out += &sentences.join(" ");
    let mut tail = [walkers_sentence(grid.walkers, pick), signs_sentence(&grid.signs, pick)];
    pick.shuffle(&mut tail);
    if grid.walkers == 0 && grid.signs.is_empty() && pick.index(3) == 0 {
        out += pick.one(&[" There are no walkers and no traffic signs.", " I see no pedestrians and no traffic signs."]);
    } else {
        out += &format!(" {} {}", tail[0], tail[1]);
    }
    out
}

#[cfg(test)]
mod tests {
    use rlmflow_parser::parse;
    use rlmflow_stages::grid::CELLS;

    use super::*;

    /// A random grid: mostly empty cells, some crowded ones, sometimes walkers and signs.
    fn random_grid(rng: &mut ChaCha8Rng) -> Grid {
        let mut grid = Grid::default();
        let fill = rng.random_range(0.0..0.4);
        for c in 0..CELLS {
            if rng.random_bool(fill) {
                grid.counts[c] = if rng.random_bool(0.8) { rng.random_range(1..4) } else { rng.random_range(4..25) };
            }
        }
        if rng.random_bool(0.3) {
            grid.walkers = rng.random_range(1..6);
        }
        let mut signs: Vec<String> =
            ["stop", "yield", "speed limit", "give way", "roundabout"].iter().filter(|_| rng.random_bool(0.2)).map(|s| s.to_string()).collect();
        signs.sort();
        grid.signs = signs;
        grid
    }

    #[test]
    fn every_variant_of_every_template_parses_back_to_its_grid() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut checked = 0;
        for _ in 0..300 {
            let grid = random_grid(&mut rng);
            for k in 0..VARIANTS * 4 {
                for numbers in [true, false] {
                    let text = caption_variant(&grid, numbers, k);
                    let parsed = parse(&text);
                    assert_eq!(parsed.grid, grid, "{text}\nwarnings: {:?}", parsed.warnings);
                    assert!(parsed.warnings.is_empty(), "{text}: {:?}", parsed.warnings);
                    checked += 1;
                }
            }
        }
        for _ in 0..3000 {
            let grid = random_grid(&mut rng);
            let text = caption(&grid, rng.random_bool(0.5), &mut rng);
            assert_eq!(parse(&text).grid, grid, "{text}");
            checked += 1;
        }
        assert_eq!(checked, 300 * VARIANTS * 8 + 3000);
    }

    #[test]
    fn captions_mention_every_bin_and_vary() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let grid = random_grid(&mut rng);
        let with_numbers = caption(&grid, true, &mut rng);
        for bound in ["ten", "twenty", "thirty", "forty"] {
            assert!(with_numbers.contains(bound), "{with_numbers}");
        }
        let without = caption(&grid, false, &mut rng);
        assert!(!without.contains("meter") && !without.contains("metre"), "{without}");
        assert!(!without.chars().any(|c| c.is_ascii_digit()), "numbers are words: {without}");
        let distinct: std::collections::BTreeSet<String> = (0..20).map(|_| caption(&grid, true, &mut rng)).collect();
        assert!(distinct.len() >= 15, "{} distinct captions of 20", distinct.len());
    }

    #[test]
    fn captions_are_deterministic_per_seed_and_frame() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        let label =
            FrameLabel { frame: 9, id: "9".repeat(32), episode: None, split: rlmflow_stages::identity::Split::Test, grid: random_grid(&mut rng) };
        let s = TemplateSettings::default();
        let a = frame_captions(&s, &label, 1);
        assert_eq!(a.len(), 5);
        assert_eq!(a, frame_captions(&s, &label, 1));
        assert_ne!(a, frame_captions(&s, &label, 2));
        assert!(a.iter().all(|c| c.frame == 9 && c.split == rlmflow_stages::identity::Split::Test));
    }
}
