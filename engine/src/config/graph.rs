//! The stage graph: dependency order, cycles, and the plan's size before it is expanded.

use std::collections::HashMap;

use rlmflow_stages::Arity;

use super::checker::Checker;
use super::Stage;

impl Checker {
    /// Refuses, before any instance exists, a plan whose variants, seeds and shards would make
    /// more than `max` instances, naming the stage where the count passes it and its factors.
    pub(super) fn bounded(&mut self, stages: &[Stage], seeds: usize, max: u64) {
        let variants: HashMap<&str, u64> = stages.iter().map(|s| (s.name.as_str(), s.variants.len() as u64)).collect();
        let mut total = 0u64;
        for (stage, dims) in stages.iter().zip(dimensions(stages, seeds > 0)) {
            let parts = 1 + stage.variants.iter().map(|v| v.shards.len() as u64).max().unwrap_or(0);
            let seeds = if dims.seeded { seeds as u64 } else { 1 };
            let count = dims.variants.iter().fold(parts.saturating_mul(seeds), |n, d| n.saturating_mul(variants[d.as_str()]));
            total = total.saturating_add(count);
            if total > max {
                let mut factors: Vec<String> = dims.variants.iter().map(|d| format!("{} variants of `{d}`", variants[d.as_str()])).collect();
                if dims.seeded {
                    factors.push(format!("{seeds} seeds"));
                }
                if parts > 1 {
                    factors.push(format!("{} shards and their merge", parts - 1));
                }
                let path = format!("stages.{}", stage.name);
                let msg = format!(
                    "the plan would have more than {max} instances (`[pipeline] max_instances`): this stage makes {count} ({}), {total} with the stages before it",
                    factors.join(" x ")
                );
                self.error(
                    stage.line,
                    &path,
                    msg,
                    Some("use fewer variants or seeds, or raise `[pipeline] max_instances` if a plan this large is meant".into()),
                );
                return;
            }
        }
    }

    /// Orders stages so every provider comes before its consumers; reports a cycle. A
    /// depth-first walk with its own stack: a chain as long as the file is long cannot overflow
    /// the thread's.
    pub(super) fn topological(&mut self, stages: Vec<Stage>) -> Option<Vec<Stage>> {
        let n = stages.len();
        let mut order = Vec::with_capacity(n);
        let mut mark = vec![0u8; n]; // 0 new, 1 on the current path, 2 done
        let providers = |i: usize| stages[i].bindings.iter().flat_map(|b| b.providers.iter().copied()).collect::<Vec<usize>>();
        for root in 0..n {
            if mark[root] != 0 {
                continue;
            }
            // The current path: each stage with the providers it has yet to visit.
            let mut path: Vec<(usize, std::vec::IntoIter<usize>)> = vec![(root, providers(root).into_iter())];
            mark[root] = 1;
            while let Some((at, pending)) = path.last_mut() {
                let at = *at;
                match pending.next() {
                    Some(p) if mark[p] == 0 => {
                        mark[p] = 1;
                        path.push((p, providers(p).into_iter()));
                    }
                    Some(p) if mark[p] == 1 => {
                        let start = path.iter().position(|(s, _)| *s == p).expect("a stage marked on the path is on it");
                        let mut cycle: Vec<usize> = path[start..].iter().map(|(s, _)| *s).collect();
                        cycle.push(p);
                        let names: Vec<&str> = cycle.iter().rev().map(|&c| stages[c].name.as_str()).collect();
                        let first = &stages[cycle[0]];
                        let msg = format!("the stages form a cycle: {}", names.join(" -> "));
                        self.error(first.line, &format!("stages.{}", first.name), msg, Some("break it by changing one stage's `inputs`".into()));
                        return None;
                    }
                    Some(_) => {}
                    None => {
                        mark[at] = 2;
                        order.push(at);
                        path.pop();
                    }
                }
            }
        }
        let mut new_index = vec![0; n];
        for (pos, &old) in order.iter().enumerate() {
            new_index[old] = pos;
        }
        let mut slots: Vec<Option<Stage>> = stages.into_iter().map(Some).collect();
        let mut sorted: Vec<Stage> = order.iter().map(|&i| slots[i].take().unwrap()).collect();
        for stage in &mut sorted {
            for b in &mut stage.bindings {
                for p in &mut b.providers {
                    *p = new_index[*p];
                }
            }
        }
        Some(sorted)
    }
}

/// What a stage fans out on: the variant dimensions (the stages that declared the variants:
/// its own and its single inputs', sorted) and whether it runs per seed (it does or one of its
/// single inputs does); it has one instance per combination.
#[derive(Clone, Debug, Default)]
pub struct Dims {
    pub variants: Vec<String>,
    pub seeded: bool,
}

/// Each stage's [`Dims`]; `seeded`: the pipeline has seeds. `stages` are in dependency order.
pub fn dimensions(stages: &[Stage], seeded: bool) -> Vec<Dims> {
    let mut dims_of: Vec<Dims> = Vec::with_capacity(stages.len());
    for stage in stages {
        let own = stage.variants.len() > 1 || stage.variants[0].name.is_some();
        let mut dims = Dims { variants: if own { vec![stage.name.clone()] } else { Vec::new() }, seeded: stage.per_seed && seeded };
        for b in stage.bindings.iter().filter(|b| b.arity == Arity::One) {
            let upstream = &dims_of[b.providers[0]];
            dims.variants.extend(upstream.variants.iter().cloned());
            dims.seeded |= upstream.seeded;
        }
        dims.variants.sort();
        dims.variants.dedup();
        dims_of.push(dims);
    }
    dims_of
}
