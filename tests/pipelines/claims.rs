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
    let report =
        std::fs::read_to_string(rlmflow_test_support::cli::output_dir(&s.path().join(".rlmflow"), "claims-ci", "report").join("report.md")).unwrap();
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

/// The CI pipeline under one listed seed, with claims on its probes and segmenters: every
/// instance is the CI run's (seed 1 is its seed), only the report (and the table gathering the
/// probes by label) runs again, and it opens with
/// the claims and shows where each claim's instances differ, in the document and the recording.
#[test]
fn the_report_opens_with_the_claims_and_shows_where_their_instances_differ() {
    let run = ci::ci_run();
    let text = std::fs::read_to_string(root().join("examples/ci.toml")).unwrap();
    // Another pipeline name and no results links: the CI run's refs and links stay its own.
    let text = text.replace("seed = 1\n", "seed = 1\nseeds = [1]\nresults = \"\"\n").replace("name = \"ci\"", "name = \"ci-claims\"");
    let claims = "\n[claims.linear_trained]\nbetter = \"linear[clip].patches.f1\"\nthan = \"linear[random].patches.f1\"\n\n\
                  [claims.pup_beats_unet]\nbetter = \"pup[clip].iou\"\nthan = \"unet.iou\"\n";
    std::fs::write(run.dir.join("ci-claims.toml"), text + claims).unwrap();
    let (ok, out) = rlmflow(&run.dir, &["run", "ci-claims.toml", "--json"]);
    assert!(ok, "{out}");
    // The report, and `f1`, whose table names the probes it gathers by their labels (now with
    // the seed), run again; every model instance is the CI run's.
    let ran: Vec<String> = ci::finished(&out, "ran").into_iter().map(|(stage, _)| stage).collect();
    assert_eq!(ran, ["f1", "report"], "only what gathers by label runs again: {out}");
    let verdicts: serde_json::Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
    assert!(verdicts["verdicts"].as_array().unwrap().iter().all(|v| v["decision"] == "undecided" && v["seeds"] == 1), "{verdicts}");

    let report = rlmflow_test_support::cli::output_dir(&run.store(), "ci-claims", "report");
    let markdown = std::fs::read_to_string(report.join("report.md")).unwrap();
    assert_eq!(markdown.lines().find(|l| l.starts_with("## ")), Some("## Claims"), "{markdown}");
    assert!(markdown.contains("| linear_trained | undecided at 1 seeds |"), "{markdown}");
    let contrast = &markdown[markdown.find("## Where the claims' instances differ").expect("a contrast section")..];
    assert!(contrast.contains("**linear_trained**: `linear[pretrain=clip,seed=1]` against `linear[pretrain=random,seed=1]`"), "{contrast}");
    assert!(contrast.contains("**pup_beats_unet**") && contrast.contains("(IoU difference at 0.5)"), "{contrast}");
    assert!(report.join("figures").read_dir().unwrap().any(|f| f.unwrap().file_name().to_string_lossy().starts_with("claim1-frame")));
    let metrics: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(report.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["claims"].as_array().unwrap().len(), 2);
    assert!(!metrics["contrasts"]["linear_trained"]["frames"].as_array().unwrap().is_empty(), "{}", metrics["contrasts"]);

    const ENTITIES: &str = "import sys, warnings\nwarnings.simplefilter('ignore')\nfrom rerun.chunk import RrdReader\n\
                            print('\\n'.join(sorted({c.entity_path for c in RrdReader(sys.argv[1]).stream()})))";
    let env = rlmflow_python::ensure(&mut |_| {}).unwrap();
    let out = Command::new(&env.python).arg("-c").arg(ENTITIES).arg(report.join("report.rrd")).output().unwrap();
    let entities = String::from_utf8_lossy(&out.stdout);
    for entity in
        ["/claims/linear_trained/heatmap", "/claims/linear_trained/output0", "/claims/pup_beats_unet/truth", "/claims/pup_beats_unet/predicted1"]
    {
        assert!(entities.lines().any(|e| e == entity), "{entity} not in {entities}");
    }
}
