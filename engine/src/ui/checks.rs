//! What the checks of a store print: `verify`'s look at its objects, files and signatures,
//! `verify --against`'s comparison with another machine's digests, and each finding of
//! `run --check-determinism` and `verify --recompute`.

use std::path::{Path, PathBuf};

use rlmflow_cache::{Digest, VerifyReport};
use rlmflow_remote::signing::Trust;

use crate::digests::{Row, Verdict};
use crate::finding::Finding;

/// A signed record the trusted keys do not vouch for, and where `verify` moved it.
pub(crate) struct Rejected {
    pub key: Digest,
    pub trust: Trust,
    pub quarantined: PathBuf,
}

/// `verify`: a line per damaged object, damaged store file, record left without its output and
/// rejected signature, then the count of each (of `objects` hashed).
pub(crate) fn store_check(report: &VerifyReport, objects: usize, rejected: &[Rejected]) -> String {
    let mut out = String::new();
    for c in &report.objects {
        out += &format!("  corrupt object {}: {} (quarantined; stages using it will recompute)\n", c.digest, c.files.join(", "));
    }
    for f in &report.files {
        out += &format!("  damaged {}: {} (quarantined to {})\n", f.path.display(), f.problem, f.quarantined.display());
    }
    for (key, output) in &report.records_without_output {
        out += &format!("  record {} needs object {}, which is gone: its action reruns when needed\n", key.short(), output.short());
    }
    for r in rejected {
        out += &format!("  record {} is {}: quarantined to {} (its action reruns when needed)\n", r.key.short(), r.trust, r.quarantined.display());
    }
    out + &format!(
        "verify: {objects} objects, {} damaged; {} damaged store files; {} records with a bad signature\n",
        report.objects.len(),
        report.files.len(),
        rejected.len()
    )
}

/// `verify --against FILE`: each row's verdict and a summary line; an error line after them when
/// none of the file's keys is here, so nothing was compared.
pub(crate) fn against(file: &Path, rows: &[Row], verdicts: &[Verdict]) -> (String, Option<String>) {
    let width = rows.iter().map(|r| r.instance.len()).max().unwrap_or(0);
    let mut out = String::new();
    for (row, verdict) in rows.iter().zip(verdicts) {
        out += &match verdict {
            Verdict::Same => format!("  same      {:width$}  key {}\n", row.instance, row.key.short()),
            Verdict::Differs(here) => {
                format!("  DIFFERS   {:width$}  key {}: there {}, here {}\n", row.instance, row.key.short(), row.output.short(), here.short())
            }
            Verdict::Absent => format!("  absent    {:width$}  key {} is not in this store\n", row.instance, row.key.short()),
        };
    }
    let count = |f: fn(&Verdict) -> bool| verdicts.iter().filter(|v| f(v)).count();
    let (same, differ, absent) = (count(|v| *v == Verdict::Same), count(|v| matches!(v, Verdict::Differs(_))), count(|v| *v == Verdict::Absent));
    out += &format!(
        "verify --against {}: {same} the same, {differ} differ, {absent} not in this store (not computed here, or other settings or versions: other keys)\n",
        file.display()
    );
    let error = (same + differ == 0)
        .then(|| format!("none of the {} keys of {} is in this store: nothing was compared", rows.len(), file.display()));
    (out, error)
}

/// What `run --check-determinism` and `verify --recompute` find, one line (or a few) each.
pub(crate) fn finding(found: &Finding) -> String {
    match found {
        Finding::Checking { label, key } => format!("check-determinism {label} (key {})", key.short()),
        Finding::Attempt { number, threads, env, output, seconds } => {
            let threads = if *threads == 1 { "1 thread".to_owned() } else { format!("{threads} threads") };
            let kernels = match env.is_empty() {
                true => String::new(),
                false => format!(", asking for other kernels: {}", env.iter().map(|(k, v)| format!("{k}={v}")).collect::<Vec<_>>().join(" ")),
            };
            format!("  attempt {number} (fresh process, {threads}{kernels}): output {} in {seconds:.1}s", output.short())
        }
        Finding::Same { stored: None } => "  same bytes".to_owned(),
        Finding::Same { stored: Some(stored) } => {
            format!("  same bytes\n  but the stored output {} differs: it was computed by another build or before a fix", stored.short())
        }
        Finding::Differs { files, of, first, kept: [a, b] } => {
            let mut text = format!("  NOT DETERMINISTIC: {} of {of} files differ: {}", files.len(), files.join(", "));
            if let Some(first) = first {
                text += &format!("\n  first difference: {first}");
            }
            text + &format!("\n  outputs kept for inspection: {} and {}", a.display(), b.display())
        }
        Finding::Agrees { label, output } => format!("  agrees     {label}  {}", output.short()),
        Finding::Disagrees { label, recorded, signers, recomputed, kept } => format!(
            "  DISAGREES  {label}  its record names {} ({signers}), recomputed {}; the recomputed output is kept in {}",
            recorded.short(),
            recomputed.short(),
            kept.display()
        ),
    }
}
