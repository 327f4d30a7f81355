//! Claims: `[claims]` checked as the rest of the file is, seeds added until every claim is
//! decided (each look's instances cached as any other), `rlmflow claims` from the store without
//! computing, a required claim as the run's exit status, and `explain CLAIM` naming the change
//! that flipped a verdict. The `score` operator measures a normal draw of its seed around its
//! `mean`, so which claims are true is known by construction.

use rlmflow_engine::event::Event;
use rlmflow_stages::claims::{Decision, Verdict};

use crate::harness::{Scratch, snapshot, text};

/// Two scores a whole unit apart with small noise, and two that are the same distribution.
const SCORES: &str = r#"
[pipeline]
name = "scores"
seeds = { min = 3, max = 8, until = "claims" }

[stages.source]
operator = "write-text"
text = "hello"

[stages.map]
operator = "shout"

[stages.good]
kind = "measure"
operator = "score"
mean = 1.0
sd = 0.1

[stages.bad]
kind = "measure"
operator = "score"
mean = 0.0
sd = 0.1

[stages.same]
kind = "measure"
operator = "score"
mean = 0.001
sd = 0.1

[claims.good_beats_bad]
better = "good.score.value"
than = "bad.score.value"
required = true

[claims.bad_beats_same]
better = "bad.score.value"
than = "same.score.value"
"#;

fn verdicts(events: &[Event]) -> (usize, Vec<Verdict>) {
    match events.iter().rev().find_map(|e| if let Event::Claims { seeds, verdicts } = e { Some((*seeds, verdicts.clone())) } else { None }) {
        Some(found) => found,
        None => panic!("no claims event in {events:?}"),
    }
}

fn verdict<'v>(verdicts: &'v [Verdict], claim: &str) -> &'v Verdict {
    verdicts.iter().find(|v| v.claim == claim).unwrap_or_else(|| panic!("no claim {claim} in {verdicts:?}"))
}

#[test]
fn seeds_are_added_until_every_claim_is_decided_or_the_cap_and_a_rerun_reuses_every_seed() {
    let s = Scratch::new("claims-seeds");
    s.pipeline(SCORES);
    let events = s.run();
    let (seeds, first) = verdicts(&events.1);
    // The true difference holds at the first look; the null one never decides, so the run
    // went to the cap, one seed at a time.
    let good = verdict(&first, "good_beats_bad");
    assert_eq!((good.decision, good.decided_at), (Decision::Holds, Some(3)), "{good:?}");
    assert_eq!(verdict(&first, "bad_beats_same").decision, Decision::Undecided, "{first:?}");
    assert_eq!(seeds, 8);
    let scored: Vec<String> = s.trace().into_iter().filter(|l| l.starts_with("start score good")).collect();
    assert_eq!(scored.len(), 8, "each of good's seeds computed once: {scored:?}");

    // Again: every look is in the store, nothing runs, the same verdicts.
    s.clear_trace();
    let again = s.run();
    assert!(again.finished().iter().all(|(_, status)| status == "reused"), "{:?}", again.finished());
    assert_eq!(verdicts(&again.1), (8, first.clone()));
    assert!(s.trace().is_empty(), "{:?}", s.trace());

    // `rlmflow claims` reads the store and writes nothing into it.
    let before = snapshot(&s.store());
    let out = s.cli(&["claims", "p.toml", "--json"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let line = crate::harness::Events::parse(&out.stdout);
    assert_eq!(verdicts(&line.1), (8, first));
    assert_eq!(snapshot(&s.store()), before, "claims wrote into the store");
    let words = text(&s.cli(&["claims", "p.toml"]).stdout);
    assert!(words.contains("holds      good_beats_bad  at 3 seeds (required)") && words.contains("undecided  bad_beats_same  at 8 seeds"), "{words}");
}

#[test]
fn a_required_claim_that_fails_fails_the_run_and_claims_and_explain_names_the_change() {
    let s = Scratch::new("claims-required");
    s.pipeline(&SCORES.replace("seeds = { min = 3, max = 8, until = \"claims\" }", "seeds = [1, 2, 3]"));
    let (_, held) = verdicts(&s.run().1);
    assert_eq!(verdict(&held, "good_beats_bad").decision, Decision::Holds);
    // The good score now the worse: its required claim fails, and so do the run and `claims`.
    let failed = s.run_expecting(1, &["--set", "good.mean=-1.0"]);
    let (_, after) = verdicts(&failed.1);
    assert_eq!(verdict(&after, "good_beats_bad").decision, Decision::Fails, "{after:?}");
    assert!(failed.finished().iter().all(|(_, status)| status != "failed"), "only the claim fails: {:?}", failed.finished());
    let out = s.cli(&["claims", "p.toml", "--set", "good.mean=-1.0"]);
    assert_eq!(out.status.code(), Some(1), "{}", text(&out.stderr));
    // Which change flipped it, between the two runs.
    let out = s.cli(&["explain", "p.toml", "good_beats_bad", "--set", "good.mean=-1.0"]);
    let said = text(&out.stdout);
    assert!(out.status.success(), "{}", text(&out.stderr));
    assert!(said.contains("claim good_beats_bad: fails at 3 seeds") && said.contains("holds at 3 seeds in run"), "{said}");
    assert!(said.contains("good[seed=1]: good.mean 1.0 -> -1.0"), "{said}");
}

/// A problem in a claim names the file, its line and key, and the nearest valid name.
#[test]
fn a_bad_claim_names_its_line_and_the_nearest_valid_name() {
    let s = Scratch::new("claims-errors");
    let cases: &[(&str, &str, &str)] = &[
        ("good.score.value", "god.score.value", "no stage named `god`"),
        ("good.score.value", "good.score.valeu", "did you mean `score.value`?"),
        ("good.score.value", "good[seed=2].score.value", "leave `seed` out"),
        ("good.score.value", "map.length", "measures nothing a claim can compare"),
    ];
    for (from, to, message) in cases {
        s.pipeline(&SCORES.replacen(&format!("better = \"{from}\""), &format!("better = \"{to}\""), 1));
        let out = s.cli(&["run", "p.toml"]);
        let err = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{err}");
        let line = SCORES.lines().position(|l| l.starts_with("better = \"good")).unwrap() + 1;
        assert!(err.contains(&format!("p.toml:{line}: claims.good_beats_bad.better")) && err.contains(message), "{to}: {err}");
    }
    // Without seeds no claim can be decided; adding seeds needs claims; the level is a rate.
    let unseeded = SCORES.replace("seeds = { min = 3, max = 8, until = \"claims\" }", "");
    let out = s.pipeline(&unseeded).cli(&["run", "p.toml"]);
    assert!(
        text(&out.stderr).contains("cannot be decided: neither `good.score.value` nor `bad.score.value` varies by seed"),
        "{}",
        text(&out.stderr)
    );
    let claimless = &SCORES[..SCORES.find("[claims.").unwrap()];
    let out = s.pipeline(claimless).cli(&["run", "p.toml"]);
    assert!(
        text(&out.stderr).contains("p.toml:4: pipeline.seeds: adds seeds until the claims are decided, and the file has no [claims]"),
        "{}",
        text(&out.stderr)
    );
    let out = s.pipeline(&format!("{SCORES}\n[claims]\nlevel = 2.0\n")).cli(&["run", "p.toml"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("claims.level: must be a number in (0, 0.5]"), "{}", text(&out.stderr));
    assert!(!s.store().exists(), "a config error writes nothing");
}
