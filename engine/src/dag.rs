//! `rlmflow dag`: the plan drawn as Mermaid (which GitHub renders) or Graphviz DOT. Each stage
//! instance is a node coloured by its state (cached, will run, will be pulled from the remote
//! cache, pending) with the reason under its label (Mermaid; GitHub shows no tooltips) or in its
//! tooltip (DOT); each instance's output artifact is a node of its own, with an edge to every
//! instance that reads it, labelled with the input slot.

use std::fmt::Write as _;

use rlmflow_remote::Remote;

use crate::plan::{Freshness, Plan};
use crate::preflight::Checked;
use crate::ui::words;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    Mermaid,
    Dot,
}

/// The states a node is coloured by: (name, fill, stroke).
const STATES: [(&str, &str, &str); 4] =
    [("cached", "#d8f0d8", "#2e7d32"), ("run", "#fff1c9", "#b58900"), ("pulled", "#dbe9fb", "#1565c0"), ("pending", "#e8e8e8", "#777777")];

/// The state a node is coloured by, and its tooltip: an instance that would run and whose
/// result the remote cache holds will be pulled instead.
fn state(freshness: &Freshness, remote: Option<&Remote>) -> (&'static str, String) {
    match freshness {
        Freshness::Cached(r) => ("cached", format!("cached: ran {:.1}s at {}", r.duration_s, r.started)),
        Freshness::Stale { key, reasons, .. } if remote.is_some_and(|r| r.holds(key)) => {
            ("pulled", format!("will be pulled from the remote cache: {}", words(reasons)))
        }
        Freshness::Stale { reasons, .. } => ("run", format!("will run: {}", words(reasons))),
        Freshness::Pending(waiting) => ("pending", format!("pending: {waiting}")),
    }
}

/// The edges of the drawing: (provider, slot, consumer), providers in plan order.
fn edges(plan: &Plan) -> Vec<(usize, &'static str, usize)> {
    let mut edges = Vec::new();
    for (consumer, inst) in plan.instances.iter().enumerate() {
        for input in &inst.inputs {
            edges.extend(input.providers.iter().map(|&provider| (provider, input.slot, consumer)));
        }
    }
    edges
}

/// The plan with every instance's freshness (`states`, in plan order) in `format`; with a
/// `remote`, what it holds shows as pulled.
pub fn draw(plan: &Plan, checked: &[Checked], remote: Option<&Remote>, format: Format) -> String {
    match format {
        Format::Mermaid => mermaid(plan, checked, remote),
        Format::Dot => dot(plan, checked, remote),
    }
}

fn mermaid(plan: &Plan, checked: &[Checked], remote: Option<&Remote>) -> String {
    // Mermaid has no escape for `"` inside a quoted label but its `#quot;` entity; `<` and `>`
    // become entities too, so a reason's `->` is not read as markup.
    let text = |s: &str| s.replace('"', "#quot;").replace('<', "#lt;").replace('>', "#gt;");
    let mut out = String::from("flowchart LR\n");
    for (name, fill, stroke) in STATES {
        let _ = writeln!(out, "  classDef {name} fill:{fill},stroke:{stroke}");
    }
    for (i, inst) in plan.instances.iter().enumerate() {
        let (class, tooltip) = state(&checked[i].state, remote);
        let produces = plan.pipeline.stages[inst.stage].kind.produces;
        // The state's words under the label: GitHub renders no tooltip (`click` is disabled there).
        let _ = writeln!(out, "  s{i}[\"{}<br>{}\"]:::{class}", text(&inst.label), text(&tooltip));
        let _ = writeln!(out, "  a{i}[/\"{produces}\"/]");
        let _ = writeln!(out, "  s{i} --> a{i}");
    }
    for (provider, slot, consumer) in edges(plan) {
        let _ = writeln!(out, "  a{provider} -->|{slot}| s{consumer}");
    }
    out
}

fn dot(plan: &Plan, checked: &[Checked], remote: Option<&Remote>) -> String {
    let text = |s: &str| s.replace('\\', "\\\\").replace('"', "\\\"");
    let mut out = format!("digraph \"{}\" {{\n  rankdir=LR;\n  node [fontname=\"sans-serif\"];\n", text(&plan.pipeline.name));
    for (i, inst) in plan.instances.iter().enumerate() {
        let (class, tooltip) = state(&checked[i].state, remote);
        let (_, fill, stroke) = STATES.iter().find(|(name, ..)| *name == class).expect("every state has colours");
        let produces = plan.pipeline.stages[inst.stage].kind.produces;
        let _ = writeln!(
            out,
            "  s{i} [label=\"{}\", shape=box, style=filled, fillcolor=\"{fill}\", color=\"{stroke}\", tooltip=\"{}\"];",
            text(&inst.label),
            text(&tooltip)
        );
        let _ = writeln!(out, "  a{i} [label=\"{produces}\", shape=note];");
        let _ = writeln!(out, "  s{i} -> a{i};");
    }
    for (provider, slot, consumer) in edges(plan) {
        let _ = writeln!(out, "  a{provider} -> s{consumer} [label=\"{slot}\"];");
    }
    out.push_str("}\n");
    out
}
