//! Binary swap, with folding for a number of ranks that is not a power of two.
//!
//! With `q` the largest power of two `≤ p` and `e = p - q`, a folding round first has
//! positions `2i+1` (`i < e`) send their whole image to `2i`, which blends
//! `[2i, 2i+1]`; the senders are then inactive. The `q` remaining positions, in order,
//! are the virtual ranks of a radix-k exchange with all factors 2, so every virtual
//! rank's data still covers a run of consecutive positions.

use super::{radix_k, RankStep, Round, Span};

/// The largest power of two `≤ n` (`n ≥ 1`).
pub(super) fn pow2_floor(n: usize) -> usize {
    if n == 0 {
        0
    } else {
        1 << (usize::BITS - 1 - n.leading_zeros())
    }
}

/// Factors (all 2) and rounds of binary swap; `cur` is updated to the final spans.
pub(super) fn rounds(ranks: usize, cur: &mut [Span]) -> (Vec<usize>, Vec<Round>) {
    let q = pow2_floor(ranks);
    let e = ranks - q;
    let mut out = Vec::new();
    let mut members: Vec<usize> = (0..ranks).collect();
    if e > 0 {
        let mut steps = vec![RankStep::idle(); ranks];
        for (j, step) in steps.iter_mut().enumerate() {
            let span = cur[j];
            let folds_away = j < 2 * e && j % 2 == 1;
            *step = if folds_away {
                RankStep {
                    sends: if span.is_empty() {
                        Vec::new()
                    } else {
                        vec![(j - 1, span)]
                    },
                    keep: Span::EMPTY,
                    blend: Vec::new(),
                }
            } else if span.is_empty() {
                RankStep::idle()
            } else if j < 2 * e {
                RankStep {
                    sends: Vec::new(),
                    keep: span,
                    blend: vec![j, j + 1],
                }
            } else {
                RankStep {
                    sends: Vec::new(),
                    keep: span,
                    blend: vec![j],
                }
            };
        }
        for (j, step) in steps.iter().enumerate() {
            cur[j] = step.keep;
        }
        out.push(Round { steps });
        members = (0..ranks).filter(|&j| !(j < 2 * e && j % 2 == 1)).collect();
    }
    let factors = vec![2; q.trailing_zeros() as usize];
    out.extend(radix_k::rounds(ranks, &members, &factors, cur));
    (factors, out)
}

#[cfg(test)]
mod tests {
    use super::super::{build_plan, Algorithm};
    use super::*;

    #[test]
    fn powers_of_two() {
        assert_eq!(pow2_floor(1), 1);
        assert_eq!(pow2_floor(6), 4);
        assert_eq!(pow2_floor(8), 8);
        assert_eq!(pow2_floor(17), 16);
    }

    #[test]
    fn eight_ranks_three_rounds() {
        let plan = build_plan(8, 800, Algorithm::BinarySwap, None).unwrap();
        plan.validate().unwrap();
        assert_eq!(plan.rounds.len(), 3);
        assert_eq!(plan.factors, [2, 2, 2]);
        for round in &plan.rounds {
            for step in &round.steps {
                assert_eq!(step.sends.len(), 1);
                assert_eq!(step.blend.len(), 2);
            }
        }
        // Round 0 pairs neighbours, round 2 pairs j and j+4.
        assert_eq!(plan.rounds[0].steps[3].blend, [2, 3]);
        assert_eq!(plan.rounds[2].steps[1].blend, [1, 5]);
        assert_eq!(plan.result.iter().map(Span::len).sum::<u32>(), 800);
    }

    #[test]
    fn six_ranks_fold() {
        let plan = build_plan(6, 600, Algorithm::BinarySwap, None).unwrap();
        plan.validate().unwrap();
        assert_eq!(plan.rounds.len(), 3, "fold + 2 exchange rounds");
        assert_eq!(plan.factors, [2, 2]);
        let fold = &plan.rounds[0];
        assert_eq!(fold.steps[1].sends, [(0, Span::new(0, 600))]);
        assert_eq!(fold.steps[3].sends, [(2, Span::new(0, 600))]);
        assert_eq!(fold.steps[0].blend, [0, 1]);
        assert_eq!(fold.steps[2].blend, [2, 3]);
        assert_eq!(fold.steps[4].blend, [4]);
        assert!(fold.steps[4].sends.is_empty());
        for r in &plan.rounds[1..] {
            for j in [1, 3] {
                assert_eq!(
                    r.steps[j],
                    RankStep::idle(),
                    "rank {j} is inactive after the fold"
                );
            }
        }
        assert!(plan.result[1].is_empty() && plan.result[3].is_empty());
        // Virtual ranks 0..4 are positions [0, 2, 4, 5].
        assert_eq!(plan.rounds[1].steps[0].blend, [0, 2]);
        assert_eq!(plan.rounds[1].steps[4].blend, [4, 5]);
        assert_eq!(plan.rounds[2].steps[0].blend, [0, 4]);
        assert_eq!(plan.rounds[2].steps[2].blend, [2, 5]);
    }

    #[test]
    fn all_sizes_validate() {
        for p in 1..=40 {
            for pixels in [0, 1, 3, 17, 1000] {
                let plan = build_plan(p, pixels, Algorithm::BinarySwap, None).unwrap();
                plan.validate()
                    .unwrap_or_else(|e| panic!("p={p} pixels={pixels}: {e}"));
            }
        }
    }
}
