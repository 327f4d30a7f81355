//! Caption decoding: greedy and beam search over any model that gives next-token
//! log-probabilities one step at a time. Both stop a sequence at the end token (kept in the
//! output) or after `max_tokens`.
//!
//! Beam search keeps, per input row, the `beam` sequences with the best length-normalised score
//! (the sum of log-probabilities divided by the number of tokens), as ClipCap's
//! `generate_beam`: a finished sequence stays a candidate with its score, an unfinished one is
//! extended by each of its `beam` most likely tokens. The best finished or longest sequence by
//! the same score is returned.

use tch::{Device, Kind, Tensor};

/// A decoder stepped one token at a time.
pub trait StepModel {
    /// Where its weights are: the rows and tokens fed to [`StepModel::next`] are built there.
    fn device(&self) -> Device;
    /// Log-probabilities of each row's first token: (rows, vocab).
    fn start(&mut self) -> Tensor;
    /// Keeps the rows `parents` names (reordered and repeated; `None`: all, as they are), feeds
    /// each its next token (rows, 1), and gives the log-probabilities of the token after.
    fn next(&mut self, parents: Option<&Tensor>, tokens: &Tensor) -> Tensor;
}

fn to_rows(t: &Tensor) -> Vec<Vec<f64>> {
    let t = t.to_device(Device::Cpu).to_kind(Kind::Double);
    (0..t.size()[0]).map(|i| Vec::<f64>::try_from(t.get(i)).expect("a row of numbers")).collect()
}

/// The most likely token at each step.
pub fn greedy(model: &mut impl StepModel, end: i64, max_tokens: usize) -> Vec<Vec<i64>> {
    let mut logp = model.start();
    let rows = logp.size()[0] as usize;
    let mut out = vec![Vec::new(); rows];
    for step in 0..max_tokens {
        let next = logp.argmax(-1, false);
        let ids = Vec::<i64>::try_from(next.to_device(Device::Cpu)).expect("token ids");
        for (seq, &id) in out.iter_mut().zip(&ids) {
            if seq.last() != Some(&end) {
                seq.push(id);
            }
        }
        if step + 1 == max_tokens || out.iter().all(|s| s.last() == Some(&end)) {
            break;
        }
        logp = model.next(None, &next.unsqueeze(1));
    }
    out
}

#[derive(Clone)]
struct Hypothesis {
    tokens: Vec<i64>,
    score: f64,
}

impl Hypothesis {
    fn normalised(&self) -> f64 {
        self.score / self.tokens.len() as f64
    }
}

/// Length-normalised beam search of width `beam` for every row.
pub fn beam_search(model: &mut impl StepModel, beam: usize, end: i64, max_tokens: usize) -> Vec<Vec<i64>> {
    let logp = model.start();
    let (rows, vocab) = (logp.size()[0] as usize, logp.size()[1] as usize);
    let beam = beam.min(vocab).max(1);
    let done = |h: &Hypothesis| h.tokens.last() == Some(&end);
    let (values, indices) = logp.topk(beam as i64, -1, true, true);
    let (values, indices) = (to_rows(&values), to_rows(&indices));
    let mut beams: Vec<Vec<Hypothesis>> =
        (0..rows).map(|r| (0..beam).map(|j| Hypothesis { tokens: vec![indices[r][j] as i64], score: values[r][j] }).collect()).collect();
    // Row r's hypotheses come from the start's row r.
    let mut parents: Vec<i64> = (0..rows as i64).flat_map(|r| std::iter::repeat_n(r, beam)).collect();
    for _ in 1..max_tokens {
        if beams.iter().flatten().all(done) {
            break;
        }
        let last: Vec<i64> = beams.iter().flatten().map(|h| *h.tokens.last().expect("a token")).collect();
        let device = model.device();
        let logp = model.next(Some(&Tensor::from_slice(&parents).to_device(device)), &Tensor::from_slice(&last).to_device(device).unsqueeze(1));
        let (values, indices) = logp.topk(beam as i64, -1, true, true);
        let (values, indices) = (to_rows(&values), to_rows(&indices));
        parents.clear();
        for (r, hypotheses) in beams.iter_mut().enumerate() {
            let mut candidates: Vec<(Hypothesis, i64)> = Vec::new();
            for (j, h) in hypotheses.iter().enumerate() {
                let row = r * beam + j;
                if done(h) {
                    candidates.push((h.clone(), row as i64));
                    continue;
                }
                for c in 0..beam {
                    let mut tokens = h.tokens.clone();
                    tokens.push(indices[row][c] as i64);
                    candidates.push((Hypothesis { tokens, score: h.score + values[row][c] }, row as i64));
                }
            }
            // Stable: equal scores keep the earlier candidate.
            candidates.sort_by(|a, b| b.0.normalised().total_cmp(&a.0.normalised()));
            candidates.truncate(beam);
            parents.extend(candidates.iter().map(|(_, row)| *row));
            *hypotheses = candidates.into_iter().map(|(h, _)| h).collect();
        }
    }
    beams
        .into_iter()
        .map(|hs| hs.into_iter().reduce(|best, h| if h.normalised() > best.normalised() { h } else { best }).expect("a hypothesis").tokens)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A first-order Markov model: row t of `table` holds the probabilities after token t, row
    /// `start` the first token's.
    struct Markov {
        table: Tensor,
        first: Tensor,
        rows: i64,
    }

    impl StepModel for Markov {
        fn device(&self) -> Device {
            self.table.device()
        }
        fn start(&mut self) -> Tensor {
            self.first.log().unsqueeze(0).expand([self.rows, -1], false)
        }
        fn next(&mut self, _parents: Option<&Tensor>, tokens: &Tensor) -> Tensor {
            self.table.index_select(0, &tokens.squeeze_dim(1)).log()
        }
    }

    /// Every sequence up to `max` tokens that ends at `end` or at `max`, scored as beam search
    /// scores; the best.
    fn brute_force(first: &[f64], table: &[[f64; 3]; 3], end: i64, max: usize) -> Vec<i64> {
        let mut best: (f64, Vec<i64>) = (f64::MIN, Vec::new());
        let mut stack: Vec<(Vec<i64>, f64)> = (0..3).map(|t| (vec![t], first[t as usize].ln())).collect();
        while let Some((seq, score)) = stack.pop() {
            let last = *seq.last().unwrap();
            if last == end || seq.len() == max {
                if score / seq.len() as f64 > best.0 {
                    best = (score / seq.len() as f64, seq);
                }
                continue;
            }
            for t in 0..3 {
                let mut s = seq.clone();
                s.push(t);
                stack.push((s, score + table[last as usize][t as usize].ln()));
            }
        }
        best.1
    }

    #[test]
    fn beam_search_finds_the_best_normalised_sequence_where_greedy_does_not() {
        // Tokens a = 0, b = 1, end = 2. Greedy takes `a` (0.6), after which every continuation
        // is poor; `b` (0.4) leads to the end at 0.95.
        let first = [0.6, 0.38, 0.02];
        let table = [[0.4, 0.3, 0.3], [0.03, 0.02, 0.95], [0.1, 0.1, 0.8]];
        let markov = || Markov { table: Tensor::from_slice(&table.concat()).view([3, 3]), first: Tensor::from_slice(&first), rows: 2 };
        let known = brute_force(&first, &table, 2, 5);
        assert_eq!(known, [1, 2], "the model is built so that b, end is the argmax");
        assert_eq!(beam_search(&mut markov(), 5, 2, 5), [known.clone(), known.clone()]);
        let greedy = greedy(&mut markov(), 2, 5);
        assert_eq!(greedy[0], [0, 0, 0, 0, 0], "greedy misses it");
    }
}
