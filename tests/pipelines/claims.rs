//! `examples/claims-ci.toml`: a claim true by construction (an encoder regressed on the counts
//! predicts them better than the same tower untrained) holds after a few seeds added one at a
//! time; a rerun reuses every seed; the report opens with the verdict.

use super::*;

#[test]
fn a_true_claim_holds_in_few_seeds_a_rerun_reuses_every_seed_and_the_report_opens_with_it() {
    let s = scratch("claims-ci", &std::fs::read_to_string(root().join("examples/claims-ci.toml")).unwrap());
    let (ok, out) = rlmflow(s.path(), &["run", "p.toml", "--json"]);
    assert!(ok, "{out}");
    let claims: serde_json::Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
    let verdict = &claims["verdicts"][0];
    assert_eq!((verdict["claim"].as_str(), verdict["decision"].as_str()), (Some("trained_beats_random"), Some("holds")), "{claims}");
    let seeds = claims["seeds"].as_u64().unwrap();
    assert!((3..=8).contains(&seeds) && verdict["decided_at"] == seeds, "{claims}");
    let pretrained = out
        .lines()
        .filter(|l| l.contains("\"stage_finished\"") && l.contains("\"status\":\"ran\"") && l.contains("\"stage\":\"pretrain[pretrain=counts,seed="))
        .count();
    assert_eq!(pretrained as u64, seeds, "one counts encoder per seed looked at: {out}");
    let report = std::fs::read_to_string(rlmflow_test_support::cli::output_dir(&s.path().join(".rlmflow"), "claims-ci", "report").join("report.md")).unwrap();
    let first = report.lines().find(|l| l.starts_with("## ")).unwrap();
    assert_eq!(first, "## Claims", "{report}");
    assert!(report.contains(&format!("| trained_beats_random (required) | holds (at {seeds} seeds) |")), "{report}");

    let (ok, again) = rlmflow(s.path(), &["run", "p.toml", "--json"]);
    assert!(ok, "{again}");
    assert!(!again.contains("\"status\":\"ran\""), "a rerun computes nothing: {again}");
    assert_eq!(again.lines().last().unwrap(), out.lines().last().unwrap());
}

/// The report is handed the file's claims; a stage that sets them itself is a config error.
#[test]
fn a_stage_may_not_set_the_claims_it_is_handed() {
    let text = std::fs::read_to_string(root().join("examples/claims-ci.toml")).unwrap();
    let text = text.replace("[stages.report]\noperator = \"paper\"", "[stages.report]\noperator = \"paper\"\nclaims = { level = 0.1 }");
    let line = text.lines().position(|l| l.starts_with("claims = ")).unwrap() + 1;
    let s = scratch("claims-set", &text);
    let (ok, out) = rlmflow(s.path(), &["status", "p.toml"]);
    assert!(!ok && out.contains(&format!("p.toml:{line}: stages.report.claims: is filled from the file's [claims]")), "{out}");
}
