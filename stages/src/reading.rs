//! How the artifact readers read their files: a summary whose format this build must read, and
//! JSON Lines whose errors name the file and line.

/// Reads an artifact's summary (`dir/file`, JSON with a `format` field) and checks that this
/// build reads its format; `artifact` names the type (`Scenes`) and `stage` what to rerun.
pub fn read_summary<T: serde::de::DeserializeOwned>(
    dir: &std::path::Path,
    file: &str,
    artifact: &str,
    stage: &str,
    format: u32,
) -> anyhow::Result<T> {
    use anyhow::Context as _;
    let path = dir.join(file);
    let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    let value: serde_json::Value = serde_json::from_slice(&bytes).with_context(|| format!("{} is not JSON", path.display()))?;
    let found = value.get("format").and_then(serde_json::Value::as_u64);
    if found != Some(u64::from(format)) {
        let found = found.map_or("without a version".to_string(), |f| f.to_string());
        anyhow::bail!("{}: {artifact} format {found} (this build reads {format}); rerun the {stage} stage", path.display());
    }
    serde_json::from_value(value).with_context(|| format!("{} is not a {artifact} summary", path.display()))
}

/// Reads a JSON Lines file, each line with `parse`; errors name the file and line.
pub fn read_lines<T>(path: &std::path::Path, parse: impl Fn(&str) -> Result<T, String>) -> anyhow::Result<Vec<T>> {
    use anyhow::Context as _;
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    text.lines().enumerate().map(|(i, l)| parse(l).map_err(|e| anyhow::anyhow!("{}:{}: {e}", path.display(), i + 1))).collect()
}

#[cfg(test)]
mod tests {
    #[test]
    fn summaries_of_another_format_and_bad_lines_are_named() {
        let dir = std::env::temp_dir().join(format!("rlmflow-stages-summary-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("labels.json"), r#"{"format": 0, "frames": 1}"#).unwrap();
        let e = crate::labels::Labels::open(&dir).err().unwrap().to_string();
        assert!(e.ends_with("labels.json: Labels format 0 (this build reads 2); rerun the labels stage"), "{e}");
        std::fs::write(dir.join("captions.json"), r#"{"format": 2, "frames": 1, "captions": 2, "generator": null}"#).unwrap();
        std::fs::write(
            dir.join("captions.jsonl"),
            "{\"frame\": 0, \"id\": \"a\", \"split\": \"train\", \"caption\": \"a\"}\n{\"frame\": 0, \"id\": \"a\", \"split\": \"dev\", \"caption\": \"b\"}\n",
        )
        .unwrap();
        let e = crate::captions::Captions::open(&dir).err().unwrap().to_string();
        assert!(e.contains("captions.jsonl:2: not a caption line: unknown variant `dev`, expected `train` or `test`"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
