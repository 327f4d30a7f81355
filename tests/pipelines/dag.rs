//! `rlmflow dag`: the plan drawn, its nodes and edges checked against the plan `status` shows.

use super::*;

/// A scenes stage in two shards (run), and labels (will run) and captions (pending) after it:
/// the Mermaid drawing has a node per instance with its state's class and an edge per input;
/// the DOT drawing has the same nodes and edges (and Graphviz, where installed, lays it out);
/// with a remote cache that holds the scenes, a fresh store's drawing shows their shards pulled.
#[test]
fn dag_draws_every_instance_in_its_state_and_every_input_as_an_edge() {
    let dir = scratch(
        "dag",
        "[pipeline]\nname = \"dag\"\n[stages.scenes]\noperator = \"procedural\"\nframes = 8\nshards = 2\nradar = { image = 32 }\n\
         [stages.labels]\noperator = \"ego-grid\"\n[stages.captions]\noperator = \"template\"\n",
    );
    let (ok, out) = rlmflow(&dir, &["run", "p.toml", "--only", "scenes"]);
    assert!(ok, "{out}");
    let (ok, status) = rlmflow(&dir, &["status", "p.toml", "--json"]);
    assert!(ok, "{status}");
    let expected: std::collections::BTreeMap<String, String> = status
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .map(|s| (s["stage"].as_str().unwrap().to_owned(), s["state"].as_str().unwrap().replace("will run", "run")))
        .collect();
    assert_eq!(expected.values().filter(|s| *s == "cached").count(), 3, "{status}");
    let inputs =
        [("scenes#0", "scenes", "scenes"), ("scenes#1", "scenes", "scenes"), ("scenes", "scenes", "labels"), ("labels", "labels", "captions")];

    let (ok, mermaid) = rlmflow(&dir, &["dag", "p.toml"]);
    assert!(ok && mermaid.starts_with("flowchart LR\n"), "{mermaid}");
    let mut labels = std::collections::BTreeMap::new();
    let mut nodes = std::collections::BTreeMap::new();
    let mut edges = Vec::new();
    for line in mermaid.lines().map(str::trim) {
        if let Some((id, rest)) = line.split_once("[\"").filter(|(id, _)| id.starts_with('s')) {
            let (label, class) = rest.split_once("\"]:::").unwrap();
            let (label, _state) = label.split_once("<br>").unwrap();
            labels.insert(id.to_owned(), label.to_owned());
            nodes.insert(label.to_owned(), class.to_owned());
        } else if let Some((from, rest)) = line.split_once(" -->|") {
            let (slot, to) = rest.split_once("| ").unwrap();
            edges.push((from.replacen('a', "s", 1), slot.to_owned(), to.to_owned()));
        }
    }
    assert_eq!(nodes, expected, "{mermaid}");
    let edges: Vec<(String, String, String)> = edges.into_iter().map(|(from, slot, to)| (labels[&from].clone(), slot, labels[&to].clone())).collect();
    assert_eq!(edges, inputs.map(|(a, s, b)| (a.to_owned(), s.to_owned(), b.to_owned())), "{mermaid}");
    // The state in words under each label (GitHub renders no tooltip).
    assert!(mermaid.contains("[\"captions<br>pending: input labels (labels) will be recomputed first\"]:::pending"), "{mermaid}");
    assert!(!mermaid.contains("click "), "{mermaid}");

    let (ok, dot) = rlmflow(&dir, &["dag", "p.toml", "--format", "dot"]);
    assert!(ok && dot.starts_with("digraph \"dag\" {") && dot.ends_with("}\n"), "{dot}");
    for (id, label) in &labels {
        assert!(dot.contains(&format!("  {id} [label=\"{label}\"")), "{id} {label}: {dot}");
    }
    for (id, label) in &labels {
        for (from, slot, to) in &inputs {
            if to == label {
                let provider = labels.iter().find(|(_, l)| l == from).unwrap().0.replacen('s', "a", 1);
                assert!(dot.contains(&format!("  {provider} -> {id} [label=\"{slot}\"];")), "{from} -> {to}: {dot}");
            }
        }
    }
    match Command::new("dot").arg("-Tsvg").stdin(std::process::Stdio::piped()).stdout(std::process::Stdio::piped()).spawn() {
        Ok(mut graphviz) => {
            use std::io::Write;
            graphviz.stdin.take().unwrap().write_all(dot.as_bytes()).unwrap();
            let out = graphviz.wait_with_output().unwrap();
            assert!(out.status.success() && String::from_utf8_lossy(&out.stdout).contains("<svg"), "Graphviz refused: {dot}");
        }
        Err(_) => println!("Graphviz's `dot` is not installed here: the DOT text was checked, not laid out"),
    }

    // What a remote cache holds shows as pulled: the scenes, pushed there, for a fresh store.
    let remote = format!("file://{}", dir.join("remote").display());
    let (ok, out) = rlmflow(&dir, &["push", "p.toml", "--remote", &remote]);
    assert!(ok, "{out}");
    let fresh = scratch("dag-fresh", &std::fs::read_to_string(dir.join("p.toml")).unwrap());
    let (ok, mermaid) = rlmflow(&fresh, &["dag", "p.toml", "--remote", &remote]);
    assert!(ok, "{mermaid}");
    for shard in ["scenes#0", "scenes#1"] {
        assert!(mermaid.contains(&format!("[\"{shard}<br>will be pulled from the remote cache: never run\"]:::pulled")), "{shard}: {mermaid}");
    }
    // The merge's key waits for the shards' outputs.
    assert!(mermaid.contains("[\"scenes<br>pending: ") && mermaid.contains("\"]:::pending") && mermaid.contains("classDef pulled"), "{mermaid}");
}
