//! `runs/<id>/provenance.md`: what one run did with each instance, with its key, output, time
//! and numeric platform. A report cannot hold this (its bytes depend only on its inputs, and a
//! reused input is the same bytes as a recomputed one), so it lives in the run's record.

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use rlmflow_cache::Digest;

use crate::event::Status;
use crate::plan::Instance;

/// The run as its provenance opens.
pub struct RunHeader<'a> {
    pub run: &'a str,
    pub file: &'a Path,
    pub pipeline: &'a str,
    pub executor: &'a str,
    pub wall_s: f64,
    pub cpu: &'a str,
    pub extensions: &'a [String],
    /// `--set` overrides over the file, in order, as typed.
    pub overrides: Vec<String>,
}

/// One instance the run settled.
pub struct Row<'a> {
    pub label: &'a str,
    pub status: Status,
    /// This run's time for an instance that ran, the original computation's for one reused.
    pub seconds: f64,
    pub key: Option<Digest>,
    pub output: Option<Digest>,
    pub platform: Option<&'a str>,
}

pub fn markdown(header: &RunHeader, rows: &[Row]) -> String {
    let RunHeader { run, file, pipeline, executor, wall_s, cpu, .. } = header;
    let mut md = format!(
        "# Run {run}\n\n`{}` (pipeline `{pipeline}`), {executor}, {wall_s:.1} s, planned on {cpu} ({}). Seconds are this run's for an instance that ran, the original computation's for one reused. A model action's numeric platform is the class of machines that compute its bytes (`rlmflow show` prints the CPU, kernels and libraries it ran with).\n\n",
        file.display(),
        header.extensions.join(" "),
    );
    if !header.overrides.is_empty() {
        // So the run can be repeated from this file alone.
        let set: Vec<String> = header.overrides.iter().map(|o| format!("`{o}`")).collect();
        md += &format!("Overrides over the file, in order: {}.\n\n", set.join(", "));
    }
    md += "| instance | status | seconds | key | output | platform |\n|---|---|---|---|---|---|\n";
    let or_dash = |d: Option<Digest>| d.map_or("-".to_owned(), |d| d.to_string());
    for row in rows {
        let (key, output, platform) = (or_dash(row.key), or_dash(row.output), row.platform.unwrap_or("-"));
        md += &format!("| {} | {} | {:.1} | {key} | {output} | {platform} |\n", row.label, row.status.as_str(), row.seconds);
    }
    md
}

pub fn write(run_dir: &Path, header: &RunHeader, rows: &[Row]) -> anyhow::Result<PathBuf> {
    let path = run_dir.join("provenance.md");
    std::fs::write(&path, markdown(header, rows)).with_context(|| format!("writing {}", path.display()))?;
    Ok(path)
}

/// The instances nothing in the plan consumes (the report, say): the run ends by naming their
/// outputs.
pub fn finals(instances: &[Instance]) -> Vec<usize> {
    let mut consumed = vec![false; instances.len()];
    for inst in instances {
        inst.inputs.iter().flat_map(|input| &input.providers).for_each(|&p| consumed[p] = true);
    }
    (0..instances.len()).filter(|&i| !consumed[i]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_table_has_a_row_per_settled_instance_and_the_overrides_to_repeat_it() {
        let key = Digest::of(b"key");
        let output = Digest::of(b"output");
        let extensions = ["avx2".to_owned(), "fma".to_owned()];
        let header = RunHeader {
            run: "r1",
            file: Path::new("pipeline.toml"),
            pipeline: "demo",
            executor: "local",
            wall_s: 12.34,
            cpu: "Some CPU",
            extensions: &extensions,
            overrides: vec!["pretrain.steps=2".to_owned()],
        };
        let rows = [
            Row { label: "scenes", status: Status::Reused, seconds: 3.0, key: Some(key), output: Some(output), platform: None },
            Row { label: "pretrain[clip]", status: Status::Failed, seconds: 0.5, key: Some(key), output: None, platform: Some("cpu/x") },
        ];
        let md = markdown(&header, &rows);
        assert!(md.starts_with("# Run r1\n\n`pipeline.toml` (pipeline `demo`), local, 12.3 s, planned on Some CPU (avx2 fma)."), "{md}");
        assert!(md.contains("Overrides over the file, in order: `pretrain.steps=2`.\n"), "{md}");
        assert!(md.contains(&format!("| scenes | reused | 3.0 | {key} | {output} | - |\n")), "{md}");
        assert!(md.contains(&format!("| pretrain[clip] | failed | 0.5 | {key} | - | cpu/x |\n")), "{md}");

        let plain = markdown(&RunHeader { overrides: vec![], ..header }, &rows[..1]);
        assert!(!plain.contains("Overrides"), "{plain}");
        assert!(!plain.contains("pretrain[clip]"), "{plain}");
    }
}
