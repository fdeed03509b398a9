//! Direct send: one round in which position `j` gathers slice `j` of every rank's image.
//!
//! It is radix-k with the single factor `p`: each rank sends `p - 1` pieces and blends
//! the `p` pieces of its slice front to back. One rank needs no round at all.

use super::{radix_k, RankStep, Round, Span};

/// Factors (`[p]`, or `[]` for one rank) and rounds of direct send; `cur` is updated to
/// the final spans.
pub(super) fn rounds(ranks: usize, cur: &mut [Span]) -> (Vec<usize>, Vec<Round>) {
    let factors = if ranks > 1 { vec![ranks] } else { Vec::new() };
    let members: Vec<usize> = (0..ranks).collect();
    let rounds = radix_k::rounds(ranks, &members, &factors, cur);
    (factors, rounds)
}

/// The one round that delivers `targets[j]` (possibly empty) to position `j`: every
/// position sends its part of each non-empty target to that target's position, and a
/// position with a target blends all ranks' parts of it. No round for one rank.
pub(super) fn rounds_to(targets: &[Span]) -> Vec<Round> {
    let ranks = targets.len();
    if ranks < 2 {
        return Vec::new();
    }
    let steps = (0..ranks)
        .map(|j| RankStep {
            sends: (0..ranks)
                .filter(|&q| q != j && !targets[q].is_empty())
                .map(|q| (q, targets[q]))
                .collect(),
            keep: targets[j],
            blend: if targets[j].is_empty() {
                Vec::new()
            } else {
                (0..ranks).collect()
            },
        })
        .collect();
    vec![Round { steps }]
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

    #[test]
    fn plans_to_given_targets_validate_and_composite_in_order() {
        use super::super::{build_plan_to, composite_in_memory};
        use crate::image::{PartialImage, Rect};
        // Ranks 1 and 3 keep nothing; targets out of position order.
        let targets = [
            Span::new(6, 20),
            Span::EMPTY,
            Span::new(0, 6),
            Span::EMPTY,
            Span::new(20, 24),
        ];
        let plan = build_plan_to(24, &targets).unwrap();
        plan.validate().unwrap();
        assert_eq!(plan.result, targets);
        assert!(plan.rounds[0].steps[1].blend.is_empty());
        for (j, step) in plan.rounds[0].steps.iter().enumerate() {
            let to: Vec<usize> = step.sends.iter().map(|s| s.0).collect();
            let want: Vec<usize> = [0, 2, 4].into_iter().filter(|&q| q != j).collect();
            assert_eq!(to, want);
        }
        let imgs: Vec<PartialImage> = (0..5)
            .map(|j| PartialImage {
                width: 4,
                height: 6,
                rect: Rect {
                    x: 0,
                    y: 0,
                    w: 4,
                    h: 6,
                },
                pixels: vec![[0.1 * j as f32, 0.0, 0.05, 0.2 + 0.1 * j as f32]; 24],
            })
            .collect();
        let got = composite_in_memory(&plan, &imgs, false, super::super::WireFormat::F32).unwrap();
        let mut want = [0.0f32; 4];
        for im in imgs.iter().rev() {
            let s = im.pixels[0];
            want = [0, 1, 2, 3].map(|c| s[c] + (1.0 - s[3]) * want[c]);
        }
        for px in &got {
            for c in 0..4 {
                assert!((px[c] - want[c]).abs() < 1e-6, "{px:?} vs {want:?}");
            }
        }
        // Targets that leave a gap or overlap are refused.
        assert!(build_plan_to(24, &[Span::new(0, 6), Span::new(7, 24)]).is_err());
        assert!(build_plan_to(24, &[Span::new(0, 8), Span::new(6, 24)]).is_err());
        assert!(build_plan_to(24, &[Span::new(0, 20)]).is_err());
        assert!(build_plan_to(24, &[]).is_err());
    }
}
