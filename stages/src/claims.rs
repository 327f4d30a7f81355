//! Claims: what an experiment is meant to show, each a comparison of two metrics paired by seed,
//! and the rule that decides it while seeds are added one at a time.
//!
//! The rule: at every look (after `n` seeds, `n` from [`Looks::first`] to [`Looks::last`]) each
//! comparison's per-seed differences give a two-sided Student-t interval at the level
//! `level / (comparisons of the claim × looks)`. By the union bound, every interval a claim will
//! ever show covers its true mean difference at once with probability at least `1 - level`,
//! whichever look the run stops at: the error rate survives the looking. A comparison is
//! decided once its running interval (the intersection of its intervals so far) lies above the
//! margin (holds) or below it (fails); a claim holds when each of its comparisons does, fails
//! when one does, and is undecided otherwise. So each claim's verdict is wrong with probability
//! at most `level` (its comparisons family-wise). The assumption: a comparison's per-seed
//! differences are independent draws of one normal distribution. docs/guide/claims.md says more.
//!
//! Both the engine (which stops adding seeds once every claim is decided, and `rlmflow claims`)
//! and the report compute verdicts here, from the same values, so they agree by construction.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use statrs::distribution::{ContinuousCDF, StudentsT};

/// The level a pipeline's claims are decided at unless `[claims] level` says otherwise.
pub const DEFAULT_LEVEL: f64 = 0.05;

/// What the rule is, in the words the report and `rlmflow claims` print.
pub const METHOD: &str =
    "paired Student-t intervals, the level spent evenly over every look and comparison (Bonferroni): valid whatever look the run stops at";

/// A pipeline's claims and the looks they are decided at.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Spec {
    /// Each claim's verdict is wrong with at most this probability.
    pub level: f64,
    pub looks: Looks,
    pub claims: Vec<Claim>,
}

/// The seed counts at which verdicts are taken: `first..=last` (both the number of seeds of a
/// fixed `seeds` list where seeds are not added).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Looks {
    pub first: usize,
    pub last: usize,
}

impl Looks {
    /// How many looks the rule spends its level over.
    pub fn count(&self) -> usize {
        self.last + 1 - self.first
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Direction {
    /// `better`'s metric is larger than `than`'s by more than the margin.
    Higher,
    /// `better`'s metric is smaller (a loss) by more than the margin.
    Lower,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Claim {
    pub name: String,
    /// Every one must hold for the claim to hold.
    pub comparisons: Vec<Comparison>,
    pub margin: f64,
    pub direction: Direction,
    /// A run whose required claim fails exits non-zero.
    pub required: bool,
    /// The paper's figures for the claim, shown beside the verdict.
    pub paper: Option<String>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Comparison {
    pub better: Metric,
    pub than: Metric,
}

/// One metric of one instance, its seeds pooled: `clipcap[pretrain=alpha1].cls.bins.30-40m.f1`.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Metric {
    pub stage: String,
    /// The instance's variant by dimension, its seed left out.
    pub variant: BTreeMap<String, String>,
    /// The dotted path into the instance's metrics.
    pub path: String,
}

impl Metric {
    /// `stage[dim=v,...].path`, the long form of the instance.
    pub fn label(&self) -> String {
        let variant: Vec<String> = self.variant.iter().map(|(d, v)| format!("{d}={v}")).collect();
        match variant.is_empty() {
            true => format!("{}.{}", self.stage, self.path),
            false => format!("{}[{}].{}", self.stage, variant.join(","), self.path),
        }
    }
}

/// One side's values: per seed, or one value for every seed (an instance that does not vary by
/// seed, such as a baseline run once).
#[derive(Clone, Debug, PartialEq)]
pub enum Values {
    Seeded(BTreeMap<u64, f64>),
    Fixed(f64),
}

impl Values {
    fn at(&self, seed: u64) -> Option<f64> {
        match self {
            Values::Seeded(by) => by.get(&seed).copied(),
            Values::Fixed(v) => Some(*v),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Decision {
    Holds,
    Fails,
    Undecided,
}

/// A claim's verdict after the seeds its comparisons share.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    pub claim: String,
    pub decision: Decision,
    /// The seeds it was decided on (every comparison's), or looked at while undecided.
    pub seeds: usize,
    /// The seed count at which it was decided.
    pub decided_at: Option<usize>,
    pub margin: f64,
    pub direction: Direction,
    pub required: bool,
    pub paper: Option<String>,
    pub comparisons: Vec<ComparisonVerdict>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ComparisonVerdict {
    pub better: String,
    pub than: String,
    pub decision: Decision,
    /// Per paired seed, in seed order: the difference in the claim's direction (better less
    /// than, or than less better for `lower`).
    pub differences: Vec<(u64, f64)>,
    /// Over the seeds looked at.
    pub mean: Option<f64>,
    pub sd: Option<f64>,
    /// The running interval after the last look (none before the first).
    pub interval: Option<(f64, f64)>,
    /// The level of each look's interval.
    pub look_level: f64,
    pub decided_at: Option<usize>,
}

/// The two-sided Student-t interval of `d`'s mean at `level` (`None` under two values).
pub fn t_interval(d: &[f64], level: f64) -> Option<(f64, f64)> {
    let n = d.len();
    if n < 2 {
        return None;
    }
    let (mean, sd) = mean_sd(d);
    let t = StudentsT::new(0.0, 1.0, (n - 1) as f64).expect("n - 1 degrees of freedom").inverse_cdf(1.0 - level / 2.0);
    let half = t * sd / (n as f64).sqrt();
    Some((mean - half, mean + half))
}

fn mean_sd(d: &[f64]) -> (f64, f64) {
    let n = d.len() as f64;
    let mean = d.iter().sum::<f64>() / n;
    let var = if d.len() > 1 { d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0) } else { 0.0 };
    (mean, var.sqrt())
}

/// The verdict of `claim` from each comparison's two sides, looked at at `looks`.
pub fn decide(claim: &Claim, level: f64, looks: Looks, values: &[(Values, Values)]) -> Verdict {
    let look_level = level / (claim.comparisons.len().max(1) * looks.count()) as f64;
    let comparisons: Vec<ComparisonVerdict> =
        claim.comparisons.iter().zip(values).map(|(c, (better, than))| decide_comparison(c, claim, look_level, looks, better, than)).collect();
    let decision = if comparisons.iter().any(|c| c.decision == Decision::Fails) {
        Decision::Fails
    } else if !comparisons.is_empty() && comparisons.iter().all(|c| c.decision == Decision::Holds) {
        Decision::Holds
    } else {
        Decision::Undecided
    };
    // Decided when the last comparison that settles it was: the first failing one's look, or
    // the latest holding one's.
    let decided_at = match decision {
        Decision::Fails => comparisons.iter().filter(|c| c.decision == Decision::Fails).filter_map(|c| c.decided_at).min(),
        Decision::Holds => comparisons.iter().filter_map(|c| c.decided_at).max(),
        Decision::Undecided => None,
    };
    let seeds = comparisons.iter().map(|c| c.differences.len().min(looks.last)).min().unwrap_or(0);
    Verdict {
        claim: claim.name.clone(),
        decision,
        seeds: decided_at.unwrap_or(seeds),
        decided_at,
        margin: claim.margin,
        direction: claim.direction,
        required: claim.required,
        paper: claim.paper.clone(),
        comparisons,
    }
}

fn decide_comparison(c: &Comparison, claim: &Claim, look_level: f64, looks: Looks, better: &Values, than: &Values) -> ComparisonVerdict {
    let seeds: Vec<u64> = match (better, than) {
        (Values::Seeded(b), _) => b.keys().copied().collect(),
        (Values::Fixed(_), Values::Seeded(t)) => t.keys().copied().collect(),
        (Values::Fixed(_), Values::Fixed(_)) => Vec::new(),
    };
    let sign = match claim.direction {
        Direction::Higher => 1.0,
        Direction::Lower => -1.0,
    };
    let differences: Vec<(u64, f64)> = seeds.into_iter().filter_map(|s| Some((s, sign * (better.at(s)? - than.at(s)?)))).take(looks.last).collect();
    let mut interval: Option<(f64, f64)> = None;
    let mut decision = Decision::Undecided;
    let mut decided_at = None;
    for n in looks.first..=differences.len().min(looks.last) {
        let d: Vec<f64> = differences[..n].iter().map(|(_, x)| *x).collect();
        let Some((lo, hi)) = t_interval(&d, look_level) else { continue };
        // Every interval covers the truth at once (the union bound), so their intersection does;
        // an empty one (a look that missed) keeps the latest interval.
        interval = Some(match interval {
            Some((a, b)) if lo.max(a) <= hi.min(b) => (lo.max(a), hi.min(b)),
            _ => (lo, hi),
        });
        let (a, b) = interval.expect("set above");
        if decision == Decision::Undecided {
            if a > claim.margin {
                (decision, decided_at) = (Decision::Holds, Some(n));
            } else if b < claim.margin {
                (decision, decided_at) = (Decision::Fails, Some(n));
            }
        }
    }
    let looked: Vec<f64> = differences.iter().map(|(_, x)| *x).collect();
    let (mean, sd) = match looked.len() {
        0 => (None, None),
        1 => (Some(looked[0]), None),
        _ => {
            let (m, s) = mean_sd(&looked);
            (Some(m), Some(s))
        }
    };
    ComparisonVerdict { better: c.better.label(), than: c.than.label(), decision, differences, mean, sd, interval, look_level, decided_at }
}

/// A difference with its sign, to three decimals: `+0.052`, `-0.004`.
pub fn signed(x: f64) -> String {
    format!("{x:+.3}")
}

/// Whether every verdict is decided: the run adds no more seeds.
pub fn all_decided(verdicts: &[Verdict]) -> bool {
    verdicts.iter().all(|v| v.decision != Decision::Undecided)
}

#[cfg(test)]
mod tests {
    use rand::{RngExt as _, SeedableRng as _};
    use rand_chacha::ChaCha8Rng;

    use super::*;

    fn metric(stage: &str) -> Metric {
        Metric { stage: stage.into(), variant: BTreeMap::new(), path: "f1".into() }
    }

    fn claim(comparisons: usize) -> Claim {
        Claim {
            name: "c".into(),
            comparisons: (0..comparisons).map(|_| Comparison { better: metric("a"), than: metric("b") }).collect(),
            margin: 0.0,
            direction: Direction::Higher,
            required: false,
            paper: None,
        }
    }

    fn seeded(values: &[f64]) -> Values {
        Values::Seeded(values.iter().enumerate().map(|(i, v)| (i as u64 + 1, *v)).collect())
    }

    #[test]
    fn the_t_interval_has_students_quantiles() {
        // t(0.975, 2) = 4.3027, t(0.995, 11) = 3.1058 (every table).
        let (lo, hi) = t_interval(&[1.0, 2.0, 3.0], 0.05).unwrap();
        assert!((hi - 2.0 - 4.3027 / 3f64.sqrt()).abs() < 1e-3 && (lo + hi - 4.0).abs() < 1e-12, "{lo} {hi}");
        let twelve: Vec<f64> = (0..12).map(|i| i as f64).collect();
        let (mean, sd) = mean_sd(&twelve);
        let (_, hi) = t_interval(&twelve, 0.01).unwrap();
        assert!((hi - mean - 3.1058 * sd / 12f64.sqrt()).abs() < 1e-3);
        assert_eq!(t_interval(&[1.0], 0.05), None);
    }

    #[test]
    fn verdicts_hold_fail_or_stay_undecided_on_hand_made_values() {
        let looks = Looks { first: 3, last: 6 };
        let one = claim(1);
        let clear = [(seeded(&[0.9, 0.91, 0.92, 0.9]), seeded(&[0.5, 0.52, 0.5, 0.49]))];
        let v = decide(&one, 0.05, looks, &clear);
        assert_eq!((v.decision, v.decided_at, v.seeds), (Decision::Holds, Some(3), 3), "{v:?}");
        let worse = [(seeded(&[0.5, 0.52, 0.5, 0.49]), seeded(&[0.9, 0.91, 0.92, 0.9]))];
        assert_eq!(decide(&one, 0.05, looks, &worse).decision, Decision::Fails);
        let noise = [(seeded(&[0.5, 0.6, 0.4, 0.55]), seeded(&[0.55, 0.45, 0.6, 0.5]))];
        let v = decide(&one, 0.05, looks, &noise);
        assert_eq!((v.decision, v.seeds), (Decision::Undecided, 4), "{v:?}");
        assert!(v.comparisons[0].interval.unwrap().0 < 0.0 && v.comparisons[0].interval.unwrap().1 > 0.0);
        // Too few seeds for the first look: undecided, no interval.
        let short = [(seeded(&[0.9, 0.91]), seeded(&[0.5, 0.52]))];
        let v = decide(&one, 0.05, looks, &short);
        assert_eq!((v.decision, v.comparisons[0].interval), (Decision::Undecided, None));
        // A margin the difference does not clear.
        let mut wide = claim(1);
        wide.margin = 0.5;
        assert_eq!(decide(&wide, 0.05, looks, &clear).decision, Decision::Fails);
        // Lower is better: the same values, the other way.
        let mut lower = claim(1);
        lower.direction = Direction::Lower;
        assert_eq!(decide(&lower, 0.05, looks, &worse).decision, Decision::Holds);
        // A side that does not vary by seed is every seed's value.
        let fixed = [(seeded(&[0.9, 0.91, 0.92]), Values::Fixed(0.5))];
        assert_eq!(decide(&one, 0.05, looks, &fixed).decision, Decision::Holds);
    }

    #[test]
    fn a_claim_over_several_comparisons_holds_only_if_each_does() {
        let looks = Looks { first: 3, last: 3 };
        let two = claim(2);
        let holds = (seeded(&[0.9, 0.91, 0.92]), seeded(&[0.5, 0.52, 0.5]));
        let undecided = (seeded(&[0.5, 0.6, 0.4]), seeded(&[0.55, 0.45, 0.6]));
        let fails = (seeded(&[0.5, 0.52, 0.5]), seeded(&[0.9, 0.91, 0.92]));
        assert_eq!(decide(&two, 0.05, looks, &[holds.clone(), holds.clone()]).decision, Decision::Holds);
        assert_eq!(decide(&two, 0.05, looks, &[holds.clone(), undecided]).decision, Decision::Undecided);
        assert_eq!(decide(&two, 0.05, looks, &[holds, fails]).decision, Decision::Fails);
    }

    /// A standard normal draw (Box-Muller).
    fn normal(rng: &mut ChaCha8Rng) -> f64 {
        let (u, v): (f64, f64) = (rng.random::<f64>().max(f64::MIN_POSITIVE), rng.random());
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }

    /// Many experiments with no true difference, each adding seeds one at a time from 3 to 12
    /// and stopping as soon as it is decided: the rule's false claims (any verdict but
    /// undecided) stay at or under the level, while stopping at the first t-test with p < 0.05
    /// claims a difference far more often, so the test tells the two apart.
    #[test]
    fn the_stopping_rule_keeps_its_false_claim_rate_under_the_level_where_a_naive_one_does_not() {
        let (experiments, looks, level) = (4000, Looks { first: 3, last: 12 }, 0.05);
        let one = claim(1);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (mut rule, mut naive) = (0usize, 0usize);
        for _ in 0..experiments {
            let d: Vec<f64> = (0..looks.last).map(|_| normal(&mut rng)).collect();
            // The rule: decide walks the looks in order and keeps the first decision, which is
            // what a run that stops at its first decided look ends with.
            let decided = decide(&one, level, looks, &[(seeded(&d), Values::Fixed(0.0))]).decision != Decision::Undecided;
            rule += decided as usize;
            // Naive: a fixed-level t-test at every look, stopping at the first p < 0.05.
            naive += (looks.first..=looks.last).any(|n| t_interval(&d[..n], level).is_some_and(|(lo, hi)| lo > 0.0 || hi < 0.0)) as usize;
        }
        let (rule, naive) = (rule as f64 / experiments as f64, naive as f64 / experiments as f64);
        eprintln!("false-claim rate: rule {rule}, naive {naive}");
        assert!(rule <= level, "the rule claimed a difference in {rule} of experiments with none");
        assert!(naive > 2.0 * level, "the naive rule's rate {naive} should exceed the level clearly");
        // And with a true difference the rule decides, in few seeds.
        let shifted: Vec<f64> = (0..looks.last).map(|_| 3.0 + normal(&mut rng)).collect();
        let v = decide(&one, level, looks, &[(seeded(&shifted), Values::Fixed(0.0))]);
        assert_eq!(v.decision, Decision::Holds, "{v:?}");
    }
}
