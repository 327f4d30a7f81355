//! The LLM-free caption parser: caption text back to the paper's grid, no model involved.
//!
//! A caption is read as a sequence of clauses (split at punctuation and at `and`, `with`,
//! `while`, `but`, `whereas`, `plus`). A distance-bin mention (`from ten to twenty meters`,
//! `between 20 and 30 meters`, `0-10m`; or, in a sentence without numbers, `very close`,
//! `close`, `at a moderate distance`, `further away` / `at a safe distance`) sets the bin for
//! what follows. In each clause a count (`three`, `3`, `a single`, `a`, `no`, `all of which`,
//! `both of them`) is attached to the sector phrase it sits with (`in the right adjacent lane
//! ahead of us`, `directly to our left`, `coming toward us in the opposing lane`, `in
//! perpendicular or intersecting lanes behind us`); a count without a sector carries to the next
//! clause that names a sector without a count (`two vehicles, one ahead of us in our lane and one
//! behind us`). `in total` / `altogether` counts are the bin's total, which `all of which`
//! refers to. Clauses about walkers (pedestrians) and traffic signs are read on their own.
//!
//! Whatever is not understood is skipped with a warning; garbage yields an empty grid and a
//! warning, never a panic.

mod numbers;

use rlmflow_stages::grid::Grid;

pub use numbers::number_word;

/// A parse: the grid and what could not be read.
#[derive(Clone, Debug, PartialEq)]
pub struct Parsed {
    pub grid: Grid,
    pub warnings: Vec<String>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Token<'a> {
    /// Lower case, a slice of the lower-cased caption.
    Word(&'a str),
    Number(u32),
    /// A number that is no count: negative, fractional, in exponent form or above
    /// [`MAX_COUNT`]. The clause holding it is skipped with a warning.
    NotACount(&'a str, &'static str),
    /// A distance-bin mention.
    Bin(usize),
    /// Clause punctuation (`,` `;` `:` brackets).
    Stop,
    /// Sentence end (`.` `!` `?`), also a clause end.
    End,
}

/// The largest count read; a caption claiming more vehicles describes no real scene.
pub const MAX_COUNT: u32 = 10_000;

const CLAUSE_WORDS: [&str; 6] = ["and", "with", "while", "but", "whereas", "plus"];
const UNITS: [&str; 5] = ["meters", "metres", "meter", "metre", "m"];
const VEHICLE_WORDS: [&str; 6] = ["vehicle", "vehicles", "car", "cars", "truck", "trucks"];
const WALKER_WORDS: [&str; 4] = ["walker", "walkers", "pedestrian", "pedestrians"];

pub fn parse(caption: &str) -> Parsed {
    let lower = caption.to_ascii_lowercase();
    let tokens = bins(numbers::words_to_numbers(tokenize(&lower)));
    let mut grid = Grid::default();
    let mut warnings = Vec::new();
    let mut bin: Option<usize> = None;
    let mut total: Option<u32> = None;
    let mut pending: Option<u32> = None;
    let mut seen_bin = false;
    // The last assignment (bin, sector, count, its words): a following count-less clause may
    // refine its sector ("in the lane to our right, behind us").
    let mut last: Option<(usize, usize, u32, Vec<&str>)> = None;
    let clauses = tokens.split_inclusive(|t| matches!(t, Token::Stop | Token::End) || matches!(t, Token::Word(w) if CLAUSE_WORDS.contains(w)));
    let mut new_sentence = false;
    for clause in clauses {
        // Refinement stays within a sentence.
        if std::mem::replace(&mut new_sentence, clause.last() == Some(&Token::End)) {
            last = None;
        }
        if let Some(b) = clause.iter().find_map(|t| if let Token::Bin(b) = t { Some(*b) } else { None }) {
            bin = Some(b);
            seen_bin = true;
            total = None;
            pending = None;
            last = None;
        }
        let words: Vec<&str> = clause.iter().filter_map(|t| if let Token::Word(w) = t { Some(*w) } else { None }).collect();
        if let Some((number, reason)) = clause.iter().find_map(|t| if let Token::NotACount(n, r) = t { Some((n, r)) } else { None }) {
            warnings.push(format!("`{number}` is {reason}; clause `{}` skipped", words.join(" ")));
            continue;
        }
        let has = |w: &str| words.contains(&w);
        if WALKER_WORDS.iter().any(|w| has(w)) {
            grid.walkers = count(clause, &words).unwrap_or(0);
            continue;
        }
        if has("sign") || has("signs") {
            for name in signs(&words) {
                if !grid.signs.contains(&name) {
                    grid.signs.push(name);
                }
            }
            continue;
        }
        let named = sector(&words);
        let is_total = has("total") || has("altogether") || (has("in") && has("all") && !has("of"));
        let mut n = count(clause, &words);
        if n.is_none() && (has("all") || has("both") || has("each")) && named.is_some() {
            n = if has("both") { Some(2) } else { total };
            if n.is_none() {
                warnings.push(format!("`{}`: `all` without a total before it", words.join(" ")));
            }
        }
        match (named, n) {
            (None, Some(n)) if is_total => total = Some(n),
            (None, Some(n)) => pending = Some(n),
            (Some(_), None) if pending.is_none() => {
                if let Some((b, old, n, before)) = last.take() {
                    let joined: Vec<&str> = before.iter().chain(words.iter()).copied().collect();
                    if let Some(refined) = sector(&joined) {
                        grid.set(b, old, grid.get(b, old) - n);
                        grid.set(b, refined, grid.get(b, refined).saturating_add(n));
                    }
                }
            }
            (Some(s), n) => {
                let n = n.or(pending).expect("matched above");
                pending = None;
                match bin {
                    Some(b) => {
                        grid.set(b, s, grid.get(b, s).saturating_add(n));
                        last = Some((b, s, n, words.clone()));
                    }
                    None => warnings.push(format!("`{}`: vehicles before any distance bin", words.join(" "))),
                }
            }
            (None, None) => {}
        }
    }
    if !seen_bin {
        warnings.push("no distance bin recognised; the grid is empty".into());
    }
    // Labels list signs sorted; the order of mention carries no meaning.
    grid.signs.sort();
    Parsed { grid, warnings }
}

/// Words, numbers and clause punctuation of a lower-cased caption.
fn tokenize(text: &str) -> Vec<Token<'_>> {
    let bytes = text.as_bytes();
    let mut out = Vec::with_capacity(bytes.len() / 5);
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        if c.is_ascii_alphabetic() || c == b'\'' {
            let start = i;
            while i < bytes.len() && (bytes[i].is_ascii_alphabetic() || bytes[i] == b'\'') {
                i += 1;
            }
            out.push(Token::Word(&text[start..i]));
            continue;
        }
        if c.is_ascii_digit() {
            // A minus sign right before the digits (not a range such as `0-10`) makes it negative.
            let negative =
                out.last() == Some(&Token::Word("-")) && i > 0 && bytes[i - 1] == b'-' && !matches!(out.iter().rev().nth(1), Some(Token::Number(_)));
            let start = if negative { i - 1 } else { i };
            let mut n: u64 = 0;
            while i < bytes.len() && bytes[i].is_ascii_digit() {
                n = n.saturating_mul(10).saturating_add(u64::from(bytes[i] - b'0'));
                i += 1;
            }
            let digit_at = |k: usize| bytes.get(k).is_some_and(u8::is_ascii_digit);
            let fraction = bytes.get(i) == Some(&b'.') && digit_at(i + 1);
            let exponent =
                matches!(bytes.get(i), Some(b'e' | b'E')) && (digit_at(i + 1) || (matches!(bytes.get(i + 1), Some(b'-' | b'+')) && digit_at(i + 2)));
            if fraction || exponent {
                i += 1;
                // The rest of the number: digits, letters and signs, and points between digits.
                while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || b"+-".contains(&bytes[i]) || (bytes[i] == b'.' && digit_at(i + 1))) {
                    i += 1;
                }
            }
            let reason = if negative {
                Some("a negative count")
            } else if fraction || exponent {
                Some("not a whole count")
            } else if n > u64::from(MAX_COUNT) {
                Some("a count above 10000")
            } else {
                None
            };
            match reason {
                Some(reason) => {
                    if negative {
                        out.pop();
                    }
                    out.push(Token::NotACount(&text[start..i], reason));
                }
                None => out.push(Token::Number(n as u32)),
            }
            continue;
        }
        match c {
            b'.' | b'!' | b'?' => out.push(Token::End),
            b',' | b';' | b':' | b'(' | b')' => out.push(Token::Stop),
            b'-' => out.push(Token::Word("-")),
            _ => {}
        }
        i += 1;
    }
    out
}

/// Replaces distance-bin mentions with [`Token::Bin`]: numeric ranges everywhere, qualitative
/// phrases only in sentences without a numeric range.
fn bins(tokens: Vec<Token<'_>>) -> Vec<Token<'_>> {
    let word = |t: Option<&Token>, options: &[&str]| matches!(t, Some(Token::Word(w)) if options.contains(w));
    let mut out = Vec::with_capacity(tokens.len());
    let mut i = 0;
    while i < tokens.len() {
        // NUM (to | - | and) NUM [unit]
        if let (Some(Token::Number(a)), Some(Token::Number(b))) = (tokens.get(i), tokens.get(i + 2))
            && word(tokens.get(i + 1), &["to", "-", "and"])
            && b > a
            && b - a == 10
            && a.is_multiple_of(10)
            && *a <= 30
        {
            out.push(Token::Bin(*a as usize / 10));
            i += 3;
            if word(tokens.get(i), &UNITS) {
                i += 1;
            }
            continue;
        }
        out.push(tokens[i]);
        i += 1;
    }
    // Qualitative mentions, per sentence without a numeric one.
    let mut result = Vec::with_capacity(out.len());
    let mut start = 0;
    for end in sentence_ends(&out) {
        let sentence = &out[start..end];
        start = end;
        if sentence.iter().any(|t| matches!(t, Token::Bin(_))) {
            result.extend_from_slice(sentence);
            continue;
        }
        let mut j = 0;
        while j < sentence.len() {
            let at = |k: usize, w: &str| matches!(sentence.get(j + k), Some(Token::Word(x)) if *x == w);
            let (bin, len) = if ((at(0, "very") || at(0, "extremely")) && at(1, "close")) || (at(0, "immediate") && at(1, "vicinity")) {
                (Some(0), 2)
            } else if at(0, "close") {
                (Some(1), 1)
            } else if (at(0, "moderate") || at(0, "medium")) && at(1, "distance") {
                (Some(2), 2)
            } else if ((at(0, "further") || at(0, "farther")) && (at(1, "away") || at(1, "out"))) || (at(0, "safe") && at(1, "distance")) {
                (Some(3), 2)
            } else {
                (None, 1)
            };
            match bin {
                Some(b) => result.push(Token::Bin(b)),
                None => result.push(sentence[j]),
            }
            j += len;
        }
    }
    result
}

/// Indices just past each sentence end.
fn sentence_ends(tokens: &[Token]) -> Vec<usize> {
    let mut ends: Vec<usize> = tokens.iter().enumerate().filter(|(_, t)| **t == Token::End).map(|(i, _)| i + 1).collect();
    if ends.last() != Some(&tokens.len()) {
        ends.push(tokens.len());
    }
    ends
}

/// The clause's vehicle (or walker) count: a number, `a` / `an` / `single` / `another` (1),
/// `no` / `none` / `zero` (0).
fn count(clause: &[Token], words: &[&str]) -> Option<u32> {
    if let Some(n) = clause.iter().find_map(|t| if let Token::Number(n) = t { Some(*n) } else { None }) {
        return Some(n);
    }
    let before_noun = |options: &[&str]| {
        words.windows(2).any(|w| options.contains(&w[0]) && (VEHICLE_WORDS.contains(&w[1]) || WALKER_WORDS.contains(&w[1])))
            || words.windows(3).any(|w| options.contains(&w[0]) && (VEHICLE_WORDS.contains(&w[2]) || WALKER_WORDS.contains(&w[2])))
    };
    if words.contains(&"none") || words.contains(&"nobody") || before_noun(&["no", "zero"]) {
        return Some(0);
    }
    if words.contains(&"single") || before_noun(&["a", "an", "another"]) {
        return Some(1);
    }
    None
}

/// The sector a clause names, if any (index into `SECTORS`).
fn sector(words: &[&str]) -> Option<usize> {
    // "right in front of us" means directly: only a `right` that is not such an intensifier is a side.
    let mut words: Vec<&str> = words.to_vec();
    for i in 0..words.len().saturating_sub(1) {
        let after_possessive = i > 0 && ["our", "the", "to", "on", "your", "my"].contains(&words[i - 1]);
        if words[i] == "right" && !after_possessive && ["in", "ahead", "behind", "beside", "alongside", "next", "at"].contains(&words[i + 1]) {
            words[i] = "directly";
        }
    }
    let has = |w: &str| words.contains(&w);
    let any = |options: &[&str]| options.iter().any(|w| has(w));
    let behind = any(&["behind", "back", "rear", "following", "passed"]);
    let ahead = any(&["ahead", "front", "forward"]);
    if any(&["opposing", "oncoming", "opposite"]) || words.windows(2).any(|w| w[0].starts_with("toward") && w[1] == "us") {
        return Some(if behind { 9 } else { 8 });
    }
    if any(&["perpendicular", "intersecting", "crossing", "cross"]) {
        return Some(if behind { 11 } else { 10 });
    }
    let (left, right) = (has("left"), has("right"));
    if left != right {
        let base = if left { 0 } else { 5 };
        return Some(match (ahead, behind) {
            (true, false) => base,
            (false, true) => base + 2,
            _ => base + 1,
        });
    }
    if ahead || behind || any(&["lane", "directly"]) {
        if !ahead && !behind {
            return None;
        }
        return Some(if behind { 4 } else { 3 });
    }
    None
}

/// Traffic sign names in a clause about signs: `no ... signs` is none; otherwise each
/// `a|an NAME sign` (NAME up to three words).
fn signs(words: &[&str]) -> Vec<String> {
    if words.contains(&"no") || words.contains(&"none") || words.contains(&"not") {
        return Vec::new();
    }
    let mut names = Vec::new();
    let mut i = 0;
    while i < words.len() {
        if ["a", "an"].contains(&words[i])
            && let Some(end) = words[i + 1..].iter().position(|w| *w == "sign")
        {
            let name: Vec<&str> = words[i + 1..i + 1 + end].iter().copied().filter(|w| !["traffic", "applicable"].contains(w)).collect();
            if !name.is_empty() && end <= 3 {
                names.push(name.join(" "));
            }
            i += end + 1;
            continue;
        }
        i += 1;
    }
    names
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(json: &str) -> Grid {
        Grid::from_json(&serde_json::from_str(json).unwrap()).unwrap()
    }

    #[test]
    fn the_papers_example_caption_parses_to_the_papers_json() {
        let caption = "As we are driving, I notice that within the very close range of zero to ten meters from our vehicle, there are three vehicles in total, with one vehicle directly ahead of us in the same lane and two vehicles in the right adjacent lane behind us. Looking a bit further ahead, from ten to twenty meters, I see a total of five vehicles, with three vehicles in the right adjacent lane ahead of us, one vehicle in the right adjacent lane behind us, and one vehicle directly behind us in the same lane.  At a moderate distance of twenty to thirty meters, I observe four vehicles in total, all of which are in the opposing lane ahead of us.   Further away, from thirty to forty meters, there are two vehicles in total, with one vehicle in the right adjacent lane ahead of us and one vehicle directly ahead of us in the same lane. I also notice that there are no applicable traffic signs around us, and fortunately, there are no walkers on the road.";
        let expected = grid(
            r#"{"0-10m":{"total_vehicles":3,"in_lane_front_side":1,"right_lane_back_side":2},"10-20m":{"total_vehicles":5,"in_lane_back_side":1,"right_lane_front_side":3,"right_lane_back_side":1},"20-30m":{"total_vehicles":4,"opposing_lane_front":4},"30-40m":{"total_vehicles":2,"in_lane_front_side":1,"right_lane_front_side":1},"traffic_signs":[],"walkers":0}"#,
        );
        let parsed = parse(caption);
        assert_eq!(parsed.grid, expected);
        assert!(parsed.warnings.is_empty(), "{:?}", parsed.warnings);
    }

    /// Captions written by hand in the styles an LLM uses, with the grid each describes.
    #[test]
    fn hand_written_llm_style_captions_parse() {
        let cases = [
            (
                "Very close to us there is a single car directly to our left. Close by, two vehicles are coming toward us in the opposing lane. At a moderate distance there are no vehicles at all. Further away, a truck is in perpendicular or intersecting lanes behind us. There are no pedestrians and no traffic signs.",
                r#"{"0-10m":{"left_side":1},"10-20m":{"opposing_lane_front":2},"30-40m":{"other_lane_back":1},"traffic_signs":[],"walkers":0}"#,
            ),
            (
                "Between 0 and 10 meters: nothing. Between 10 and 20 meters there are 2 cars, both of them in the left adjacent lane ahead of us. Between 20 and 30 meters we have twenty-one vehicles in total, all of which are in the lane to our right, behind us. Between 30 and 40 meters, one car is right in front of us. I can see 3 pedestrians.",
                r#"{"10-20m":{"left_lane_front_side":2},"20-30m":{"right_lane_back_side":21},"30-40m":{"in_lane_front_side":1},"traffic_signs":[],"walkers":3}"#,
            ),
            (
                "In the 0-10m range, there are two vehicles: one is right beside us on the right and one is following us in our lane. From twenty to thirty metres, a vehicle that has passed us in the opposing lane. At thirty to forty meters, three cars are on crossing roads ahead of us. There is a stop sign, and there is one walker.",
                r#"{"0-10m":{"right_side":1,"in_lane_back_side":1},"20-30m":{"opposing_lane_back":1},"30-40m":{"other_lane_front":3},"traffic_signs":["stop"],"walkers":1}"#,
            ),
        ];
        for (caption, json) in cases {
            let parsed = parse(caption);
            assert_eq!(parsed.grid, grid(json), "{caption}\nwarnings: {:?}", parsed.warnings);
        }
    }

    #[test]
    fn counts_that_are_out_of_range_negative_or_not_whole_warn_and_are_skipped() {
        let base = "From ten to twenty meters, there are two cars in our lane ahead of us";
        for bad in ["99999999999999999999999999", "10001", "-5", "1e308", "2.5", "3e-2"] {
            let parsed = parse(&format!("{base}, and {bad} cars in the left adjacent lane ahead of us."));
            assert_eq!(parsed.grid, grid(r#"{"10-20m":{"in_lane_front_side":2},"traffic_signs":[],"walkers":0}"#), "{bad}");
            assert_eq!(parsed.warnings.len(), 1, "{bad}: {:?}", parsed.warnings);
            assert!(parsed.warnings[0].starts_with(&format!("`{bad}` is ")), "{bad}: {:?}", parsed.warnings);
        }
        // The largest count still reads, and ranges with a dash stay ranges.
        let parsed = parse("In the 0-10m range there are 10000 cars in our lane ahead of us.");
        assert_eq!(parsed.grid.get(0, 3), 10_000, "in_lane_front_side");
        assert!(parsed.warnings.is_empty(), "{:?}", parsed.warnings);
    }

    #[test]
    fn garbage_gives_an_empty_grid_and_a_warning() {
        for text in ["", "lorem ipsum dolor sit amet", "!!! 12 -- ?? ,,, 99999999999999999999 to 3", "left right behind ahead 4 4 4"] {
            let parsed = parse(text);
            assert_eq!(parsed.grid, Grid::default(), "{text}");
            assert!(!parsed.warnings.is_empty(), "{text}");
        }
    }
}
