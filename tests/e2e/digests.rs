//! `rlmflow digests` lists every instance's action key and output digest with the machine that
//! computed them; `rlmflow verify --against FILE` compares another machine's list with this
//! store: the same key with the same output agrees, the same key with another output is named
//! and fails, and other keys (other settings or versions) are not compared.

use std::fs;

use crate::harness::*;

#[test]
fn another_machines_digests_agree_where_keys_match_and_a_differing_output_fails() {
    let s = Scratch::new("digests");
    s.pipeline(CHAIN);
    let before = s.cli(&["digests", "p.toml"]);
    assert!(!before.status.success() && text(&before.stderr).contains("has not run yet"), "{}", text(&before.stderr));
    s.run();

    let out = s.cli(&["digests", "p.toml"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    let listed = text(&out.stdout);
    assert!(listed.contains("# rlmflow ") && listed.contains("CPU: ") && listed.contains("classes: portable cpu/"), "{listed}");
    let rows: Vec<&str> = listed.lines().filter(|l| !l.starts_with('#')).collect();
    let status = text(&s.cli(&["status", "p.toml", "--json"]).stdout);
    let expected: Vec<String> = status
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|v| format!("{} {} {}", v["stage"].as_str().unwrap(), v["key"].as_str().unwrap(), v["output"].as_str().unwrap()))
        .collect();
    assert_eq!(rows, expected, "one row per instance: its label, key and output");

    let verify = |file: &str| {
        fs::write(s.dir.join("there.digests"), file).unwrap();
        let out = s.cli(&["verify", "p.toml", "--against", "there.digests"]);
        (out.status.code(), text(&out.stdout), text(&out.stderr))
    };
    let (code, stdout, _) = verify(&listed);
    assert_eq!(code, Some(0), "{stdout}");
    assert!(stdout.contains(&format!("{} the same, 0 differ, 0 not in this store", rows.len())), "{stdout}");

    // Another machine computed other bytes for `map` under its key, and ran `other` with other
    // settings (another key).
    let changed: Vec<String> = rows
        .iter()
        .map(|row| {
            let [label, key, output] = row.split(' ').collect::<Vec<_>>()[..] else { panic!("{row}") };
            match label {
                "map" => format!("{label} {key} {}", "0".repeat(64)),
                "other" => format!("{label} {} {output}", "1".repeat(64)),
                _ => row.to_string(),
            }
        })
        .collect();
    let (code, stdout, _) = verify(&changed.join("\n"));
    assert_eq!(code, Some(1), "{stdout}");
    assert!(stdout.contains("DIFFERS   map") && stdout.contains("there 000000000000"), "{stdout}");
    assert!(
        stdout.contains("absent    other") && stdout.contains(&format!("{} the same, 1 differ, 1 not in this store", rows.len() - 2)),
        "{stdout}"
    );

    // Nothing comparable is a failure, not a pass; a malformed row names its line.
    let (code, _, stderr) = verify(&format!("map {} {}\n", "1".repeat(64), "2".repeat(64)));
    assert_eq!(code, Some(1));
    assert!(stderr.contains("nothing was compared"), "{stderr}");
    let (code, _, stderr) = verify("# a header\nmap 12\n");
    assert_eq!(code, Some(1));
    assert!(stderr.contains("there.digests:2") && stderr.contains("instance key output"), "{stderr}");

    // A pipeline not wholly computed is refused, naming what is missing.
    fs::write(s.dir.join("p.toml"), CHAIN.replace("suffix = \"!\"", "suffix = \"?\"")).unwrap();
    let out = s.cli(&["digests", "p.toml"]);
    assert!(!out.status.success(), "{}", text(&out.stdout));
    assert!(text(&out.stderr).contains("not computed in this store (map, measure, collect)"), "{}", text(&out.stderr));
}
