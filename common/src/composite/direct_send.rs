//! Direct send: one round in which position `j` gathers slice `j` of every rank's image.
//!
//! It is radix-k with the single factor `p`: each rank sends `p - 1` pieces and blends
//! the `p` pieces of its slice front to back. One rank needs no round at all.

use super::{radix_k, Round, Span};

/// Factors (`[p]`, or `[]` for one rank) and rounds of direct send; `cur` is updated to
/// the final spans.
pub(super) fn rounds(ranks: usize, cur: &mut [Span]) -> (Vec<usize>, Vec<Round>) {
    let factors = if ranks > 1 { vec![ranks] } else { Vec::new() };
    let members: Vec<usize> = (0..ranks).collect();
    let rounds = radix_k::rounds(ranks, &members, &factors, cur);
    (factors, rounds)
}

#[cfg(test)]
mod tests {
    use super::super::{build_plan, Algorithm};
    use super::*;

    #[test]
    fn one_round_and_p_minus_one_sends() {
        for p in 2..=13usize {
            let plan = build_plan(p, 1000, Algorithm::DirectSend, None).unwrap();
            plan.validate().unwrap();
            assert_eq!(plan.rounds.len(), 1);
            assert_eq!(plan.factors, [p]);
            let parts = Span::new(0, 1000).split_even(p);
            for (j, step) in plan.rounds[0].steps.iter().enumerate() {
                assert_eq!(step.sends.len(), p - 1);
                assert_eq!(step.keep, parts[j]);
                assert_eq!(step.blend, (0..p).collect::<Vec<_>>());
                for &(to, span) in &step.sends {
                    assert_ne!(to, j);
                    assert_eq!(span, parts[to]);
                }
            }
            assert_eq!(plan.result, parts);
        }
    }

    #[test]
    fn k_is_ignored_and_one_rank_has_no_round() {
        let a = build_plan(6, 100, Algorithm::DirectSend, Some(&[2, 3])).unwrap();
        let b = build_plan(6, 100, Algorithm::DirectSend, None).unwrap();
        assert_eq!(a, b);
        let one = build_plan(1, 100, Algorithm::DirectSend, None).unwrap();
        one.validate().unwrap();
        assert!(one.rounds.is_empty());
        assert_eq!(one.result, [Span::new(0, 100)]);
    }
}
