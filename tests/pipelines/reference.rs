//! `docs/reference/operators.md` is generated from `rlmflow operators --json`: this test renders
//! it and fails when the file in the repository differs. `RLMFLOW_BLESS=1` rewrites the file.

use super::*;

const REFERENCE: &str = "docs/reference/operators.md";

/// Each setting as a dotted key with its default, nested tables flattened.
fn flatten(prefix: &str, value: &serde_json::Value, out: &mut Vec<(String, serde_json::Value)>) {
    match value.as_object() {
        Some(table) if !table.is_empty() => {
            for (key, value) in table {
                flatten(&if prefix.is_empty() { key.clone() } else { format!("{prefix}.{key}") }, value, out);
            }
        }
        _ => out.push((prefix.to_owned(), value.clone())),
    }
}

/// The reference page for the operators `rlmflow operators --json` lists, in its order.
fn render(operators: &[serde_json::Value]) -> String {
    let mut page = String::from(
        "# Operator settings\n\n\
         <!-- Generated from `rlmflow operators --json` by tests/pipelines/reference.rs; do not edit. Regenerate with\n     \
         RLMFLOW_BLESS=1 cargo xtask test -p rlmflow --test pipelines -- operator_reference -->\n\n\
         Every operator the `rlmflow` binary ships, with every setting a stage of it may set in `pipeline.toml` and its\n\
         default. A setting marked *not in the key* cannot change the result (how many frames are rendered at once, an\n\
         endpoint's retries and timeouts), so changing it reuses what is cached; a *tracked* path enters the key by the\n\
         content of the files it names, not by its text.\n\
         Nested tables are written here as dotted keys (`radar.image`); in `pipeline.toml` they are TOML tables\n\
         (`radar = { image = 32 }`).\n",
    );
    for op in operators {
        let name = op["name"].as_str().unwrap();
        let summary = op["summary"].as_str().unwrap();
        let summary = summary[..1].to_uppercase() + &summary[1..];
        page += &format!("\n## `{name}`\n\n{summary} (kind `{}`, version {}).\n\n", op["kind"].as_str().unwrap(), op["version"]);
        let inputs: Vec<String> =
            op["inputs"].as_object().unwrap().iter().map(|(slot, artifact)| format!("`{slot}` ({})", artifact.as_str().unwrap())).collect();
        page += &format!(
            "Reads {}; writes {}.",
            if inputs.is_empty() { "no input".to_owned() } else { inputs.join(", ") },
            op["produces"].as_str().unwrap()
        );
        if let Some(merge) = op["merge"].as_str() {
            page += &format!(" Shardable: its parts are joined by `{merge}`.");
        }
        page += "\n\n| setting | default | |\n|---|---|---|\n";
        let listed = |list: &str, key: &str| {
            op[list].as_array().unwrap().iter().filter_map(|k| k.as_str()).any(|k| key == k || key.starts_with(&format!("{k}.")))
        };
        let mut settings = Vec::new();
        flatten("", &op["defaults"], &mut settings);
        for (key, default) in settings {
            let note = match (listed("non_result", &key), listed("tracked", &key)) {
                (true, _) => "not in the key",
                (_, true) => "tracked",
                _ if op["claims"] == key.as_str() => "filled from `[claims]`",
                _ => "",
            };
            page += &format!("| `{key}` | `{}` | {note} |\n", default.to_string().replace('|', "\\|"));
        }
    }
    page
}

#[test]
fn operator_reference_is_the_one_the_binary_generates() {
    let (ok, listing) = rlmflow(&root(), &["operators", "--json"]);
    assert!(ok, "{listing}");
    let operators: Vec<serde_json::Value> = listing.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    let page = render(&operators);
    let path = root().join(REFERENCE);
    if std::env::var_os("RLMFLOW_BLESS").is_some() {
        std::fs::write(&path, &page).unwrap();
    }
    let shipped = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        shipped == page,
        "{REFERENCE} is stale: regenerate it with `RLMFLOW_BLESS=1 cargo xtask test -p rlmflow --test pipelines -- operator_reference`"
    );
    for op in &operators {
        assert!(page.contains(&format!("## `{}`", op["name"].as_str().unwrap())), "every operator has its section");
    }
}
