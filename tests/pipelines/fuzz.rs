//! A fuzzer in the tree: the shipped pipelines and an import recording's manifest, mutated at
//! random from a seed, through the real binary. Every case must end within its bound, never
//! panic, write nothing on a dry run, and name the file of any error. The budget is
//! `RLMFLOW_FUZZ_SECONDS` (12 in the test suite, split between pipelines and manifests) and the
//! seed `RLMFLOW_FUZZ_SEED` (1 unless set, so the suite's cases are the same every run; another
//! seed explores further); a finding prints its case, which replays it. The test prints how
//! many cases it ran.

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use rand::{RngExt, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{root, scratch};

/// Values a setting is set to: bounds, non-numbers, paths that escape, wrong types.
const VALUES: &[&str] = &[
    "0",
    "-1",
    "1",
    "2",
    "3",
    "65536",
    "1e300",
    "-1e-300",
    "9223372036854775807",
    "18446744073709551616",
    "nan",
    "inf",
    "0.5",
    "0.99",
    "true",
    "\"\"",
    "\"/etc/passwd\"",
    "\"/tmp\"",
    "\"../../..\"",
    "\"cuda:7\"",
    "\"x\"",
    "[]",
    "{}",
    "[1, 2]",
    "{ a = {}, b = {} }",
];

/// Lines inserted whole: fan-out, sharding, seeds, bounds, empty inputs.
const LINES: &[&str] = &[
    "variants = { a = {}, b = {}, c = {} }",
    "shards = 3",
    "per_seed = true",
    "inputs = { scenes = [] }",
    "[pipeline]\nseeds = [1, 2, 3]",
    "[pipeline]\nmax_instances = 3",
    "[stages.extra]\nkind = \"labels\"\noperator = \"ego-grid\"",
    "device = \"cuda:3\"",
    "init = \"/dev/zero\"",
    "\"\"\"",
    "[[stages]]",
    // Names that would forge a row, a label or a path, and the instance bound at its largest.
    "[stages.\"s\\n| forged | ran |\"]\nkind = \"labels\"\noperator = \"ego-grid\"",
    "[stages.\"nul\\u0000\"]\nkind = \"labels\"\noperator = \"ego-grid\"",
    "variants = { \".\" = {}, \"..\" = {} }",
    "variants = { \"a[b=c]\" = {} }",
    "[pipeline]\nmax_instances = 9223372036854775807",
];

/// JSON values a manifest field is set to.
const JSON_VALUES: &[&str] = &[
    "0",
    "-1",
    "1e309",
    "null",
    "\"\"",
    "\"../p.toml\"",
    "\"/etc/hostname\"",
    "[]",
    "{}",
    "\"frames/e00-00.npy\"",
    "1e30",
    "NaN",
    "\"frames\"",
    "true",
];

/// Applies one to four random edits to `text`.
fn mutate(text: &str, rng: &mut ChaCha8Rng, values: &[&str], lines: &[&str], separator: &str) -> String {
    let mut out: Vec<String> = text.lines().map(str::to_owned).collect();
    for _ in 0..rng.random_range(1..=4) {
        if out.is_empty() {
            out.push(String::new());
        }
        let at = rng.random_range(0..out.len());
        match rng.random_range(0..8) {
            // A value replaced.
            0 | 1 => {
                if let Some(pos) = out[at].find(separator) {
                    let keep = &out[at][..pos + separator.len()];
                    let value = values[rng.random_range(0..values.len())];
                    // A manifest's value ends at the next comma or brace; a setting's at the line's end.
                    let rest = if separator == "=" {
                        String::new()
                    } else {
                        out[at][pos + separator.len()..].find([',', '}']).map_or(String::new(), |e| out[at][pos + separator.len() + e..].to_owned())
                    };
                    out[at] = format!("{keep} {value}{rest}");
                }
            }
            2 => {
                out.remove(at);
            }
            3 => {
                let line = out[at].clone();
                out.insert(at, line);
            }
            4 => {
                let other = rng.random_range(0..out.len());
                out.swap(at, other);
            }
            5 => out.insert(at, lines[rng.random_range(0..lines.len())].to_owned()),
            // A character replaced by a random printable one.
            6 => {
                let chars: Vec<char> = out[at].chars().collect();
                if !chars.is_empty() {
                    let i = rng.random_range(0..chars.len());
                    let c = char::from(rng.random_range(32u8..127));
                    out[at] = chars[..i].iter().chain(std::iter::once(&c)).chain(&chars[i + 1..]).collect();
                }
            }
            // Cut off mid-line.
            _ => {
                let keep = rng.random_range(0..=out[at].len());
                let cut: String = out[at].chars().take(keep).collect();
                out[at] = cut;
                out.truncate(at + 1);
            }
        }
    }
    out.join("\n") + "\n"
}

/// The lines of `mutated` that `seed` lacks: what a finding shows of its case.
fn changed(seed: &str, mutated: &str) -> String {
    let lines: std::collections::HashSet<&str> = seed.lines().collect();
    mutated.lines().filter(|l| !lines.contains(l)).collect::<Vec<_>>().join("\n")
}

/// Every file below `dir` with its size and modification time.
fn files(dir: &Path) -> Vec<(PathBuf, u64, std::time::SystemTime)> {
    let mut out = Vec::new();
    let mut pending = vec![dir.to_path_buf()];
    while let Some(d) = pending.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let meta = std::fs::symlink_metadata(e.path()).unwrap();
            if meta.is_dir() {
                pending.push(e.path());
            }
            out.push((e.path(), meta.len(), meta.modified().unwrap()));
        }
    }
    out.sort();
    out
}

/// `rlmflow ARGS` in `dir`, killed after `limit`: `None` when it had to be.
fn bounded(dir: &Path, args: &[&str], limit: Duration) -> Option<Output> {
    let mut child =
        Command::new(env!("CARGO_BIN_EXE_rlmflow")).current_dir(dir).args(args).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    let t0 = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            return None;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    Some(child.wait_with_output().unwrap())
}

/// What is wrong with one case's outcome, if anything: a hang, a crash, a panic, an error that
/// names no file (`names`: the files an error may name).
fn problem(out: Option<&Output>, names: &[&str]) -> Option<String> {
    let Some(out) = out else { return Some("did not end within its bound (a hang)".into()) };
    // A run prints a failed stage's error with the stage (stdout), the summary on stderr.
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned() + &String::from_utf8_lossy(&out.stdout);
    match out.status.code() {
        None => return Some(format!("killed by a signal: {}", out.status)),
        Some(101) => return Some(format!("panicked: {stderr}")),
        _ if stderr.contains("panicked") => return Some(format!("an operator panicked: {stderr}")),
        Some(0) => return None,
        Some(_) => {}
    }
    (!names.iter().any(|n| stderr.contains(n))).then(|| format!("an error that names no file ({}): {stderr}", names.join(" or ")))
}

fn budget() -> Duration {
    Duration::from_secs_f64(std::env::var("RLMFLOW_FUZZ_SECONDS").ok().and_then(|s| s.parse().ok()).unwrap_or(12.0))
}

fn seed() -> u64 {
    std::env::var("RLMFLOW_FUZZ_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or(1)
}

#[test]
fn mutated_pipelines_and_manifests_never_hang_crash_write_or_mislead() {
    let (budget, first) = (budget(), seed());
    let mut seeds: Vec<(String, String)> = vec![("pipeline.toml".into(), std::fs::read_to_string(root().join("pipeline.toml")).unwrap())];
    for e in std::fs::read_dir(root().join("examples")).unwrap().flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if name.ends_with(".toml") && name != "paper.toml" {
            seeds.push((name, std::fs::read_to_string(e.path()).unwrap()));
        }
    }
    let mut findings = Vec::new();

    // Pipelines, each a dry run next to an import recording (for import.toml's `path`).
    let dir = scratch("fuzz-pipelines", "");
    super::import::write_recording_into(&dir.join("recording"));
    // Cases that passed (exit 0) and that were refused with an error, for the summary.
    let mut passed = [0u64; 2];
    let (t0, mut cases) = (Instant::now(), 0u64);
    while t0.elapsed() < budget * 2 / 3 {
        let case = first.wrapping_mul(1_000_003).wrapping_add(cases);
        let mut rng = ChaCha8Rng::seed_from_u64(case);
        let (name, text) = &seeds[rng.random_range(0..seeds.len())];
        let mutated = mutate(text, &mut rng, VALUES, LINES, "=");
        std::fs::write(dir.join("p.toml"), &mutated).unwrap();
        let before = files(&dir);
        let out = bounded(&dir, &["run", "p.toml", "--dry-run"], Duration::from_secs(20));
        let wrote = (files(&dir) != before).then(|| "a dry run wrote a file".to_owned());
        passed[0] += u64::from(out.as_ref().is_some_and(|o| o.status.success()));
        if let Some(p) = problem(out.as_ref(), &["p.toml"]).or(wrote) {
            findings.push(format!("pipeline case {case} ({name}; new or changed lines:)\n{}\n=> {p}", changed(text, &mutated)));
        }
        cases += 1;
    }
    let pipeline_cases = cases;

    // Manifests, each imported for real (an import-only pipeline): the recording rewritten per case.
    let import = "[pipeline]\nname = \"fuzz\"\n[stages.scenes]\noperator = \"import\"\npath = \"recording\"\nimage = 32\n";
    let dir = scratch("fuzz-manifests", import);
    let (t0, mut cases) = (Instant::now(), 0u64);
    while t0.elapsed() < budget / 3 {
        let case = first.wrapping_mul(1_000_033).wrapping_add(cases);
        let mut rng = ChaCha8Rng::seed_from_u64(case);
        let recording = dir.join("recording");
        let _ = std::fs::remove_dir_all(&recording);
        super::import::write_recording_into(&recording);
        let manifest = std::fs::read_to_string(recording.join("manifest.jsonl")).unwrap();
        let mutated = mutate(&manifest, &mut rng, JSON_VALUES, &["{}", "{\"image\": \"frames\", \"actors\": []}", "not json"], "\":");
        std::fs::write(recording.join("manifest.jsonl"), &mutated).unwrap();
        let out = bounded(&dir, &["run", "p.toml"], Duration::from_secs(30));
        passed[1] += u64::from(out.as_ref().is_some_and(|o| o.status.success()));
        if let Some(p) = problem(out.as_ref(), &["manifest.jsonl", "recording"]) {
            findings.push(format!("manifest case {case} (new or changed lines:)\n{}\n=> {p}", changed(&manifest, &mutated)));
        }
        cases += 1;
    }
    println!(
        "fuzz: {pipeline_cases} mutated pipelines ({} planned, the rest refused) and {cases} mutated manifests ({} imported) from seed {first}; {} findings",
        passed[0],
        passed[1],
        findings.len()
    );
    assert!(findings.is_empty(), "{} findings (replay with RLMFLOW_FUZZ_SEED={first}):\n\n{}", findings.len(), findings.join("\n\n"));
}
