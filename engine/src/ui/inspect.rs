//! What `show` and `explain` print about an instance: where its output and record are and where
//! the record came from, or why it would run, with its preimage.

use rlmflow_cache::{ActionRecord, Change, Digest, PulledFrom, Store, canonical_json};
use rlmflow_stages::numerics::PlatformRecord;

use super::{describe, words};
use crate::plan::Freshness;

/// `show`: an instance's record, or why it is not computed yet. `store` holds a cached one.
pub(crate) fn shown(label: &str, state: &Freshness, store: Option<&Store>) -> String {
    match (state, store) {
        (Freshness::Cached(r), Some(s)) => record(label, r, s),
        (Freshness::Stale { reasons, .. }, _) => format!("{label}: not computed yet ({})\n", words(reasons)),
        (Freshness::Pending(waiting), _) => format!("{label}: not computed yet ({waiting})\n"),
        (Freshness::Cached(_), None) => unreachable!("cached without a store"),
    }
}

fn record(label: &str, r: &ActionRecord, s: &Store) -> String {
    let mut out = format!("{label}: cached\n");
    out += &format!("  output:  {}\n", s.object_dir(&r.output).display());
    out += &format!("  files:   {} ({:.1} MB)\n", r.files, r.bytes as f64 / 1e6);
    out += &format!("  key:     {}\n", r.key);
    out += &format!("  ran:     {} for {:.1}s\n", r.started, r.duration_s);
    out += &match &r.pulled {
        None => "  origin:  computed here\n".to_owned(),
        Some(PulledFrom { remote, signed_by: Some(key) }) => format!("  origin:  pulled from {remote}, signed by {key}\n"),
        Some(PulledFrom { remote, signed_by: None }) => {
            format!("  origin:  pulled from {remote} UNVERIFIED (no trusted keys): its summary and metrics are the remote's word\n")
        }
    };
    let unverified = if r.unverified_origin().is_some() { " (unverified)" } else { "" };
    if !r.summary.is_empty() {
        out += &format!("  summary{unverified}: {}\n", r.summary);
    }
    if !r.metrics.is_null() {
        out += &format!("  metrics{unverified}: {}\n", canonical_json(&r.metrics));
    }
    // A record from before its operator kept one, or a damaged one, shows none.
    if let Some(platform) = r.platform.clone().and_then(|p| serde_json::from_value::<PlatformRecord>(p).ok()) {
        platform.to_string().lines().for_each(|line| out += &format!("  {line}\n"));
    }
    out
}

/// What `explain` says of one instance.
pub(crate) struct Explained<'a> {
    pub label: &'a str,
    pub stage: &'a str,
    pub state: &'a Freshness,
    /// The key the pipeline's last run used for it.
    pub last: Option<Digest>,
    /// For a pending instance: what changed since its last run, its inputs aside (their keys are
    /// not known yet).
    pub changes: Vec<Change>,
}

/// `explain`: the instance's key against the last run's, why it runs, and its preimage.
pub(crate) fn explained(e: &Explained) -> String {
    let last = e.last.map_or("none".into(), |k| k.to_string());
    let mut out = format!("{}\n", e.label);
    match e.state {
        Freshness::Cached(r) => {
            out += &format!("  cached: key {} (ran {:.1}s, {})\n", r.key, r.duration_s, r.started);
            if e.last != Some(r.key) {
                out += &format!("  (the last run used another key: {last})\n");
            }
            out += &preimage(&r.preimage);
        }
        Freshness::Stale { key, reasons, preimage: now } => {
            out += &format!("  will run: key {key}\n  last run: {last}\n");
            reasons.iter().for_each(|r| out += &format!("    {r}\n"));
            out += &preimage(now);
        }
        Freshness::Pending(waiting) => {
            out += &format!("  pending: {waiting}; its key is known once that input is\n");
            e.changes.iter().for_each(|change| out += &format!("    {}\n", describe(e.stage, change)));
        }
    }
    out
}

fn preimage(p: &rlmflow_cache::Preimage) -> String {
    let text = serde_json::to_string_pretty(p).expect("a preimage is JSON");
    format!("  preimage:\n{}\n", text.lines().map(|l| format!("    {l}")).collect::<Vec<_>>().join("\n"))
}
