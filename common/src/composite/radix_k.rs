//! Radix-k rounds (Peterka, Goodell, Ross, Shen, Thakur, SC09) and the choice of factors.
//!
//! With factors `k_0 … k_{r-1}` (product `p`), a virtual rank `v` has the mixed-radix
//! digits `d_i = (v / (k_0⋯k_{i-1})) mod k_i`, digit 0 least significant. Round `i`
//! groups the ranks that differ only in digit `i`; round-0 groups are therefore runs of
//! consecutive positions, and in every later round each member's accumulated image
//! covers a run of positions adjacent to its neighbours', in digit order. Within a
//! group every member splits its current span into `k_i` even parts, keeps part `d_i`,
//! sends part `e` to the member with digit `e` and blends the group's pieces in digit
//! (= visibility) order.

use super::{PlanError, RankStep, Round, Span, DEFAULT_TARGET_K};

/// Factors `ranks` for radix-k: its prime factors, combined greedily (largest prime
/// first, each into the factor that stays largest without exceeding `target_k`) into
/// factors as close to `target_k` as possible. A prime larger than the target stays on
/// its own (`auto_factors(11, 8) == [11]`, i.e. direct send). The factors come out in
/// non-increasing order, e.g. `auto_factors(16, 8) == [8, 2]`, `auto_factors(12, 8) ==
/// [6, 2]`; `auto_factors(1, _)` is empty (no rounds).
// `is_multiple_of` needs Rust 1.87; the workspace supports 1.85.
#[allow(clippy::manual_is_multiple_of)]
pub fn auto_factors(ranks: usize, target_k: usize) -> Vec<usize> {
    let mut primes = Vec::new();
    let mut n = ranks;
    let mut f = 2usize;
    while n > 1 && f.saturating_mul(f) <= n {
        while n % f == 0 {
            primes.push(f);
            n /= f;
        }
        f += 1;
    }
    if n > 1 {
        primes.push(n);
    }
    primes.sort_unstable_by(|a, b| b.cmp(a));
    let mut bins: Vec<usize> = Vec::new();
    for prime in primes {
        let best = bins
            .iter()
            .enumerate()
            .filter_map(|(i, &b)| b.checked_mul(prime).map(|m| (i, m)))
            .filter(|&(_, m)| m <= target_k)
            .max_by_key(|&(i, m)| (m, std::cmp::Reverse(i)));
        match best {
            Some((i, m)) => bins[i] = m,
            None => bins.push(prime),
        }
    }
    bins.sort_unstable_by(|a, b| b.cmp(a));
    bins
}

/// The product of `factors`, saturating at `u128::MAX` (for error messages).
pub(super) fn product_u128(factors: &[usize]) -> u128 {
    factors
        .iter()
        .try_fold(1u128, |a, &f| a.checked_mul(f as u128))
        .unwrap_or(u128::MAX)
}

/// Turns [`build_plan`](super::build_plan)'s `k` argument into radix factors.
pub(super) fn resolve_factors(ranks: usize, k: Option<&[usize]>) -> Result<Vec<usize>, PlanError> {
    match k {
        None => Ok(auto_factors(ranks, DEFAULT_TARGET_K)),
        Some(&[target]) => {
            if target < 2 {
                return Err(PlanError::TargetTooSmall { target });
            }
            Ok(auto_factors(ranks, target))
        }
        Some(list) => {
            if let Some(&factor) = list.iter().find(|&&f| f < 2) {
                return Err(PlanError::FactorTooSmall { factor });
            }
            let product = product_u128(list);
            if product != ranks as u128 {
                return Err(PlanError::FactorProduct {
                    factors: list.to_vec(),
                    product,
                    ranks,
                });
            }
            Ok(list.to_vec())
        }
    }
}

/// The radix-k rounds over the virtual ranks `members` (virtual rank → position, in
/// visibility order) with `factors` multiplying to `members.len()`. `cur` holds every
/// position's current span and is updated to the spans kept after the last round;
/// positions not in `members` are idle in every round.
pub(super) fn rounds(
    ranks: usize,
    members: &[usize],
    factors: &[usize],
    cur: &mut [Span],
) -> Vec<Round> {
    debug_assert_eq!(factors.iter().product::<usize>(), members.len());
    let mut out = Vec::with_capacity(factors.len());
    let mut stride = 1usize;
    for &k in factors {
        let mut steps = vec![RankStep::idle(); ranks];
        for (v, &pos) in members.iter().enumerate() {
            let digit = (v / stride) % k;
            let base = v - digit * stride;
            let member = |e: usize| members[base + e * stride];
            let parts = cur[pos].split_even(k);
            let keep = if parts[digit].is_empty() {
                Span::EMPTY
            } else {
                parts[digit]
            };
            let sends = parts
                .iter()
                .enumerate()
                .filter(|&(e, s)| e != digit && !s.is_empty())
                .map(|(e, &s)| (member(e), s))
                .collect();
            let blend = if keep.is_empty() {
                Vec::new()
            } else {
                (0..k).map(member).collect()
            };
            steps[pos] = RankStep { sends, keep, blend };
        }
        for &pos in members {
            cur[pos] = steps[pos].keep;
        }
        out.push(Round { steps });
        stride *= k;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::super::{build_plan, Algorithm};
    use super::*;

    #[test]
    fn auto_factor_examples() {
        assert_eq!(auto_factors(8, 8), [8]);
        assert_eq!(auto_factors(16, 8), [8, 2]);
        assert_eq!(auto_factors(12, 8), [6, 2]);
        assert_eq!(auto_factors(11, 8), [11]);
        assert_eq!(auto_factors(1, 8), Vec::<usize>::new());
        assert_eq!(auto_factors(1, 2), Vec::<usize>::new());
        assert_eq!(auto_factors(64, 8), [8, 8]);
        assert_eq!(auto_factors(16, 2), [2, 2, 2, 2]);
        assert_eq!(auto_factors(22, 8), [11, 2]);
        assert_eq!(auto_factors(72, 8), [6, 6, 2]);
        assert_eq!(auto_factors(7, 4), [7]);
    }

    #[test]
    fn auto_factors_multiply_back_and_respect_target() {
        for p in 1..=300usize {
            for target in 2..=10 {
                let f = auto_factors(p, target);
                assert_eq!(f.iter().product::<usize>(), p, "p={p} target={target}");
                for &x in &f {
                    assert!(x >= 2);
                    // Over the target only for a lone prime.
                    assert!(x <= target || auto_factors(x, 1) == [x], "p={p} f={f:?}");
                }
            }
        }
    }

    #[test]
    fn k_argument_semantics() {
        let p = build_plan(16, 1000, Algorithm::RadixK, None).unwrap();
        assert_eq!(p.factors, [8, 2]);
        let p = build_plan(16, 1000, Algorithm::RadixK, Some(&[4])).unwrap();
        assert_eq!(p.factors, [4, 4]);
        let p = build_plan(16, 1000, Algorithm::RadixK, Some(&[2, 8])).unwrap();
        assert_eq!(p.factors, [2, 8]);
        assert_eq!(p.rounds.len(), 2);
        p.validate().unwrap();
        let p = build_plan(1, 1000, Algorithm::RadixK, Some(&[])).unwrap();
        assert!(p.rounds.is_empty());
        assert_eq!(p.result, [Span::new(0, 1000)]);

        assert!(matches!(
            build_plan(12, 10, Algorithm::RadixK, Some(&[2, 5])),
            Err(PlanError::FactorProduct {
                product: 10,
                ranks: 12,
                ..
            })
        ));
        assert!(matches!(
            build_plan(12, 10, Algorithm::RadixK, Some(&[])),
            Err(PlanError::FactorProduct { product: 1, .. })
        ));
        assert_eq!(
            build_plan(4, 10, Algorithm::RadixK, Some(&[1, 4])),
            Err(PlanError::FactorTooSmall { factor: 1 })
        );
        assert_eq!(
            build_plan(4, 10, Algorithm::RadixK, Some(&[1])),
            Err(PlanError::TargetTooSmall { target: 1 })
        );
        let e = build_plan(12, 10, Algorithm::RadixK, Some(&[2, 5])).unwrap_err();
        assert!(e.to_string().contains("12 ranks"), "{e}");
        // Overflowing products are reported, not wrapped.
        assert!(build_plan(4, 10, Algorithm::RadixK, Some(&[usize::MAX, 2, 2])).is_err());
    }

    #[test]
    fn groups_are_consecutive_in_round_zero() {
        // p = 12 with factors [3, 4]: round 0 groups {0,1,2}, {3,4,5}, ...
        let p = build_plan(12, 1200, Algorithm::RadixK, Some(&[3, 4])).unwrap();
        p.validate().unwrap();
        assert_eq!(p.rounds[0].steps[4].blend, [3, 4, 5]);
        assert_eq!(p.rounds[0].steps[4].keep, Span::new(400, 800));
        assert_eq!(p.rounds[1].steps[4].blend, [1, 4, 7, 10]);
        assert_eq!(p.rounds[1].steps[4].keep, Span::new(500, 600));
        // Every member sends (k-1) parts per round.
        for round in &p.rounds {
            for step in &round.steps {
                assert_eq!(step.sends.len() + 1, step.blend.len());
            }
        }
    }

    #[test]
    fn empty_parts_are_not_sent() {
        // 3 pixels, 8 ranks: most ranks end up with nothing.
        let p = build_plan(8, 3, Algorithm::RadixK, Some(&[2, 2, 2])).unwrap();
        p.validate().unwrap();
        for round in &p.rounds {
            for step in &round.steps {
                assert!(step.sends.iter().all(|(_, s)| !s.is_empty()));
                assert_eq!(step.keep.is_empty(), step.blend.is_empty());
            }
        }
        assert_eq!(p.result.iter().filter(|s| !s.is_empty()).count(), 3);
    }
}
