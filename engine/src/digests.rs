//! Output digests for comparing machines: `rlmflow digests` writes, for every instance of a
//! pipeline, its action key and output digest with the machine that computed them;
//! `rlmflow verify --against FILE` looks each of another machine's keys up in this store. Where a
//! key is the same and the output is not, one key gave two machines different bytes: a numeric
//! class that does not hold. Keys change with settings and versions, so only equal keys compare.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::{Context as _, bail};
use rlmflow_cache::{Digest, Store};
use rlmflow_stages::Numerics;
use rlmflow_stages::numerics::{Cpu, Target, class};

use crate::config::Pipeline;
use crate::plan::{Freshness, Plan};

/// One instance's line: `instance key output`.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    pub instance: String,
    pub key: Digest,
    pub output: Digest,
}

/// What this store holds for another machine's row.
#[derive(Debug, PartialEq)]
pub enum Verdict {
    Same,
    /// The same key, another output: this store's.
    Differs(Digest),
    /// No record of the key here (it was not computed here, or its settings or version differ).
    Absent,
}

/// The digests file of `pipeline` as `states` (its plan assessed against the store) hold it:
/// a header naming the pipeline, rlmflow's version, the git commit where there is one, and the
/// CPU with the numeric classes it computes in; then one row per instance. Every instance must
/// be cached: a file of part of a pipeline would compare silently less.
pub fn render(pipeline: &Pipeline, plan: &Plan, states: &[Freshness], cpu: &Cpu) -> anyhow::Result<String> {
    let missing: Vec<&str> =
        states.iter().zip(&plan.instances).filter(|(s, _)| !matches!(s, Freshness::Cached(_))).map(|(_, i)| i.label.as_str()).collect();
    if !missing.is_empty() {
        bail!(
            "{} of {} instances are not computed in this store ({}): run `rlmflow run {}` first",
            missing.len(),
            plan.instances.len(),
            missing.join(", "),
            pipeline.file.display()
        );
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let file = pipeline.file.file_name().map_or_else(|| pipeline.file.display().to_string(), |f| f.to_string_lossy().into_owned());
    let mut out = String::new();
    writeln!(
        out,
        "# Output digests of one run of {file} (pipeline `{}`), for comparing machines: `rlmflow verify --against THIS_FILE`",
        pipeline.name
    )?;
    let commit = crate::history::git_state(&pipeline.file)
        .map(|g| format!("; commit {}{}", &g.commit[..g.commit.len().min(12)], if g.dirty { " (dirty)" } else { "" }))
        .unwrap_or_default();
    writeln!(
        out,
        "# rlmflow {}{commit}; CPU: {} ({}), {}, {cores} cores; extensions: {}",
        env!("CARGO_PKG_VERSION"),
        cpu.model,
        cpu.vendor,
        cpu.arch,
        cpu.extensions.join(" ")
    )?;
    let portable = class(Numerics::Portable, cpu, Target::Cpu, None);
    let native = class(Numerics::Native, cpu, Target::Cpu, None);
    writeln!(out, "# classes: portable {portable}; native {native}")?;
    writeln!(out, "# instance key output")?;
    for (state, instance) in states.iter().zip(&plan.instances) {
        if let Freshness::Cached(record) = state {
            writeln!(out, "{} {} {}", instance.label, record.key, record.output)?;
        }
    }
    Ok(out)
}

/// The rows of the digests file at `path`.
pub fn read(path: &Path) -> anyhow::Result<Vec<Row>> {
    parse(&std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?, path)
}

/// The rows of `text`, the digests file at `path`; `#` lines and blank lines are comments.
fn parse(text: &str, path: &Path) -> anyhow::Result<Vec<Row>> {
    let mut rows = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let at = || format!("{}:{}", path.display(), n + 1);
        let fields: Vec<&str> = line.split_whitespace().collect();
        let [instance, key, output] = fields[..] else {
            bail!("{}: `{line}` is not a row; a row is `instance key output` (two digests of 64 hex digits), as `rlmflow digests` writes", at());
        };
        let digest = |s: &str, what: &str| s.parse::<Digest>().map_err(|e| anyhow::anyhow!("{}: the {what} of `{instance}`: {e}", at()));
        rows.push(Row { instance: instance.to_owned(), key: digest(key, "key")?, output: digest(output, "output")? });
    }
    if rows.is_empty() {
        bail!("{} holds no rows; `rlmflow digests PIPELINE > FILE` writes one", path.display());
    }
    Ok(rows)
}

/// Each row's verdict against the records of `store`.
pub fn compare(store: &Store, rows: &[Row]) -> anyhow::Result<Vec<Verdict>> {
    rows.iter()
        .map(|row| {
            Ok(match store.record(&row.key)? {
                Some(record) if record.output == row.output => Verdict::Same,
                Some(record) => Verdict::Differs(record.output),
                None => Verdict::Absent,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_file_that_is_not_rows_is_refused_naming_its_line() {
        let path = Path::new("x.digests");
        let (a, b) = ("a".repeat(64), "b".repeat(64));
        let rows = parse(&format!("# header\n\nscenes {a} {b}\n"), path).unwrap();
        assert_eq!(rows, vec![Row { instance: "scenes".into(), key: a.parse().unwrap(), output: b.parse().unwrap() }]);
        let err = parse(&format!("# header\nscenes {a} {b}\nlabels {a}\n"), path).unwrap_err().to_string();
        assert!(err.contains("x.digests:3") && err.contains("instance key output"), "{err}");
        let err = parse(&format!("scenes {a} {}\n", "g".repeat(64)), path).unwrap_err().to_string();
        assert!(err.contains("x.digests:1") && err.contains("the output of `scenes`"), "{err}");
        assert!(parse("# only a header\n", path).unwrap_err().to_string().contains("holds no rows"));
    }
}
