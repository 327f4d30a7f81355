//! One number across seeds, and instances grouped into rows that differ only in seed.

use serde_json::{Value, json};

use crate::study::Instance;

/// The values of one quantity, one per seed.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Stat(pub Vec<f64>);

impl Stat {
    pub fn of(values: impl IntoIterator<Item = f64>) -> Stat {
        Stat(values.into_iter().collect())
    }

    pub fn mean(&self) -> f64 {
        self.0.iter().sum::<f64>() / self.0.len() as f64
    }

    /// The sample standard deviation (n - 1); 0 for one value.
    pub fn sd(&self) -> f64 {
        let n = self.0.len();
        if n < 2 {
            return 0.0;
        }
        let m = self.mean();
        (self.0.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (n - 1) as f64).sqrt()
    }

    /// `0.512`, or `0.512 ± 0.013` over several seeds; `–` with no value.
    pub fn show(&self) -> String {
        match self.0.len() {
            0 => "–".into(),
            1 => format!("{:.3}", self.0[0]),
            _ => format!("{:.3} ± {:.3}", self.mean(), self.sd()),
        }
    }

    pub fn json(&self) -> Value {
        match self.0.len() {
            0 => Value::Null,
            _ => json!({"mean": self.mean(), "sd": self.sd(), "values": self.0}),
        }
    }
}

/// Items grouped into rows by their instance without its seed, in order of first appearance.
pub fn rows<T>(items: &[T], instance: impl Fn(&T) -> &Instance) -> Vec<(Instance, Vec<&T>)> {
    let mut rows: Vec<(Instance, Vec<&T>)> = Vec::new();
    for item in items {
        let row = instance(item).row();
        match rows.iter_mut().find(|(r, _)| *r == row) {
            Some((_, group)) => group.push(item),
            None => rows.push((row, vec![item])),
        }
    }
    rows
}

/// A row's name: its stage, and its variant when it has one.
pub fn name(row: &Instance) -> String {
    match row.variant() {
        v if v.is_empty() => row.stage.clone(),
        v => format!("{} · {v}", row.stage),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_and_sample_sd_across_seeds() {
        let s = Stat::of([0.5, 0.7, 0.6]);
        assert!((s.mean() - 0.6).abs() < 1e-12);
        assert!((s.sd() - 0.1).abs() < 1e-12);
        assert_eq!(s.show(), "0.600 ± 0.100");
        assert_eq!(Stat::of([0.25]).show(), "0.250");
        assert_eq!(Stat::of([0.25]).sd(), 0.0);
        assert_eq!(Stat::default().show(), "–");
        assert_eq!(s.json()["values"], json!([0.5, 0.7, 0.6]));
    }

    #[test]
    fn seeds_of_one_variant_share_a_row() {
        use crate::study::tests::seeded;
        let items: Vec<Instance> = [("clipcap", "a", 1), ("clipcap", "a", 2), ("clipcap", "b", 1)]
            .iter()
            .map(|&(stage, encoder, seed)| seeded(stage, &[("pretrain", encoder)], seed))
            .chain([seeded("pixels", &[], 1)])
            .collect();
        let rows = rows(&items, |i| i);
        let shape: Vec<(String, usize)> = rows.iter().map(|(r, g)| (name(r), g.len())).collect();
        assert_eq!(shape, [("clipcap · a".to_string(), 2), ("clipcap · b".to_string(), 1), ("pixels".to_string(), 1)]);
    }
}
