//! Sort-last compositing: plans, active-pixel encoding and the rank state machine.
//!
//! Each of `p` ranks holds a premultiplied RGBA partial image of the same `W×H` frame.
//! The final image is `image[0] OVER image[1] OVER … OVER image[p-1]`, where the index
//! is the rank's **position** in the visibility order (position 0 is front-most).
//!
//! * **Why positions.** OVER is associative but not commutative, so every compositing
//!   round must know which data lies in front of which. Numbering ranks by their place in
//!   the visibility order (instead of by worker id) makes every group of a radix-k round a
//!   run of consecutive positions whose accumulated images are themselves contiguous in
//!   visibility order, so "blend in position order" is always the right order. The
//!   caller maps positions to workers (a permutation that changes with the view).
//! * **Plans are pure data.** [`build_plan`] turns `(ranks, pixels, algorithm, k)` into a
//!   [`Plan`]: per round and per position, which spans to send to whom, which span to
//!   keep and whose pieces to blend, front to back. [`Plan::validate`] re-checks a plan
//!   (e.g. one received from the network) by simulating which positions each rank's data
//!   covers, so a validated plan provably composites in the right order.
//!   [Direct send](Algorithm::DirectSend) is radix-k with the single factor `p`,
//!   [binary swap](Algorithm::BinarySwap) is radix-k with all factors 2 (after a
//!   folding round for non-powers of two).
//! * **Why row interlacing.** Spans are ranges of a *logical* pixel index. With
//!   [`Interlace`] on, logical rows list the physical rows `y ≡ 0 (mod p)` first, then
//!   `y ≡ 1`, … so any contiguous logical span of about `N/p` pixels samples rows from the
//!   whole image and the active (non-transparent) pixels, usually clustered in the middle
//!   of the frame, are spread evenly over the ranks (as IceT's interlacing does).
//! * **Why blending in place is exact.** A rank keeps its own data in a buffer `d` and
//!   blends each received piece directly into it: pieces behind it (later in the blend
//!   list, in order) as `d = d OVER piece`, pieces in front (earlier, nearest first) as
//!   `d = piece OVER d`. By associativity of OVER this equals the ordered composite of
//!   the whole blend list, without any temporary image. Transparent black is the
//!   identity of OVER, so inactive (all-zero) pixels are skipped exactly: the
//!   [`SparsePiece`] encoding sends only active pixels, as run lengths plus data.
//!
//! [`RankCompositor`] runs one rank's side of a plan (sans-IO: the caller moves the
//! bytes), [`Exchange`] runs one rank's exchange across frames (early pieces, sender
//! checks, duplicates, bounds, deadlines) around it, [`assemble`] builds the final image from the gathered result pieces and
//! [`composite_in_memory`] runs a whole plan in one process, for tests and tools.
//! Nothing here does I/O, spawns threads or is async.

use std::fmt;

use serde::{Deserialize, Serialize};

mod binary_swap;
pub mod canvas;
mod direct_send;
mod exchange;
mod gather;
mod interlace;
mod memory;
mod radix_k;
mod rank;
mod sparse;

pub use exchange::{
    round_stagger, timeout_margin, Exchange, ExchangeError, ExchangeEvent, ExchangeLimits,
    ExchangeStats, FinalPiece, FinalTarget, Outgoing, OutgoingPiece, PieceSink,
};
pub use interlace::Interlace;
pub use memory::{composite_in_memory, run_in_memory, MemoryRun};
pub use radix_k::auto_factors;
pub use rank::{assemble, CompositeError, RankCompositor};
pub use sparse::{PieceError, PieceLayout, Segment, SparsePiece, WireFormat};

/// The target group size used when radix-k is asked for without an explicit `k`.
pub const DEFAULT_TARGET_K: usize = 8;

/// Which compositing algorithm a plan follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Algorithm {
    /// One round: every rank sends its `j`-th image slice to position `j`.
    DirectSend,
    /// `log2 q` rounds of pairwise exchanges (`q` the largest power of two `≤ p`): radix-k
    /// with all factors 2. For `p > q` a folding round first has positions `2i+1`
    /// (`i < p - q`) send their whole image to `2i` and drop out; the `q` remaining
    /// positions, in order, are the virtual ranks of the exchange.
    BinarySwap,
    /// Rounds of all-to-all exchanges within groups of `k_i` ranks (Peterka et al., SC09).
    /// Round `i` groups the positions that differ only in mixed-radix digit `i` (digit 0
    /// least significant, so round-0 groups are runs of consecutive positions); the
    /// member with digit `d` keeps part `d` of the group's current span.
    RadixK,
    /// One round: every rank sends its whole image to position 0, which blends them all
    /// (IceT's direct strategy with a single tile). For sparse images at many ranks: one
    /// piece per rank, and only their active pixels are blended.
    Gather,
}

impl fmt::Display for Algorithm {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Algorithm::DirectSend => "direct-send",
            Algorithm::BinarySwap => "binary-swap",
            Algorithm::RadixK => "radix-k",
            Algorithm::Gather => "gather",
        })
    }
}

/// A half-open range `[start, end)` of logical pixel indices.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
pub struct Span {
    /// First logical pixel index.
    pub start: u32,
    /// One past the last logical pixel index.
    pub end: u32,
}

impl Span {
    /// The canonical empty span `[0, 0)`.
    pub const EMPTY: Span = Span { start: 0, end: 0 };

    /// The span `[start, end)` (not checked; `end < start` reads as empty).
    pub const fn new(start: u32, end: u32) -> Span {
        Span { start, end }
    }

    /// Number of pixels (0 when `end <= start`).
    pub const fn len(&self) -> u32 {
        self.end.saturating_sub(self.start)
    }

    /// Whether the span holds no pixel.
    pub const fn is_empty(&self) -> bool {
        self.end <= self.start
    }

    /// Whether `other` lies inside `self` (an empty `other` always does).
    pub const fn contains(&self, other: &Span) -> bool {
        other.is_empty() || (self.start <= other.start && other.end <= self.end)
    }

    /// Splits into `k` contiguous, nearly equal parts in order; the first `len % k` parts
    /// get one pixel more. Parts may be empty when `len < k`; `k == 0` gives no parts.
    pub fn split_even(&self, k: usize) -> Vec<Span> {
        if k == 0 {
            return Vec::new();
        }
        let len = self.len() as u64;
        let base = len / k as u64;
        let rem = len % k as u64;
        let mut at = self.start as u64;
        (0..k as u64)
            .map(|i| {
                let n = base + u64::from(i < rem);
                let s = Span::new(at as u32, (at + n) as u32);
                at += n;
                s
            })
            .collect()
    }
}

impl fmt::Display for Span {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "[{}, {})", self.start, self.end)
    }
}

/// What one rank does in one round.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct RankStep {
    /// `(to position, span of my current data to send)`; never to itself, never empty.
    pub sends: Vec<(usize, Span)>,
    /// The span this rank owns after the round (empty: the rank is done / inactive).
    pub keep: Span,
    /// Positions, front to back, whose pieces of `keep` are composited; holds this rank
    /// itself whenever `keep` is non-empty. Every other position `q` listed sends exactly
    /// `keep` to this rank in this round.
    pub blend: Vec<usize>,
}

impl RankStep {
    /// The step of a rank that takes no part in the round.
    pub fn idle() -> RankStep {
        RankStep::default()
    }
}

/// One compositing round.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Round {
    /// Index = position; one step per rank.
    pub steps: Vec<RankStep>,
}

/// A complete compositing schedule for `ranks` positions and `pixels` logical pixels.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Plan {
    /// Number of ranks (positions `0..ranks`).
    pub ranks: usize,
    /// Number of logical pixels, `W·H`.
    pub pixels: u32,
    /// The algorithm the plan follows.
    pub algorithm: Algorithm,
    /// Radix factors, one per exchange round (binary swap: all 2; direct send: `[p]`,
    /// or `[]` for one rank). Binary swap's folding round has no factor.
    pub factors: Vec<usize>,
    /// The rounds, in order.
    pub rounds: Vec<Round>,
    /// Per position, the final span it owns (possibly empty); the non-empty ones
    /// partition `[0, pixels)`.
    pub result: Vec<Span>,
}

/// Why a plan could not be built or failed validation.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PlanError {
    /// Zero ranks.
    #[error("a compositing plan needs at least one rank, got 0")]
    NoRanks,
    /// An explicit radix factor below 2.
    #[error("radix factor {factor} is invalid: every factor must be at least 2")]
    FactorTooSmall {
        /// The offending factor.
        factor: usize,
    },
    /// A target group size below 2.
    #[error("radix target k = {target} is invalid: the target must be at least 2")]
    TargetTooSmall {
        /// The offending target.
        target: usize,
    },
    /// Explicit factors whose product is not the number of ranks.
    #[error("radix factors {factors:?} multiply to {product} but there are {ranks} ranks")]
    FactorProduct {
        /// The factors given.
        factors: Vec<usize>,
        /// Their product (saturated at `u128::MAX`).
        product: u128,
        /// The number of ranks.
        ranks: usize,
    },
    /// The plan's shape (counts, factors, sizes) does not fit its parameters.
    #[error("malformed plan: {0}")]
    Shape(String),
    /// One rank's step in one round is inconsistent with the rest of the plan.
    #[error("inconsistent plan at round {round}, position {position}: {reason}")]
    Inconsistent {
        /// Round index.
        round: usize,
        /// Position of the rank.
        position: usize,
        /// What is wrong.
        reason: String,
    },
    /// The final spans do not partition the image, or do not hold every rank's data.
    #[error("plan result is wrong: {0}")]
    Result(String),
}

/// Builds the plan for `ranks` positions over `pixels` logical pixels.
///
/// `k` is used by [`Algorithm::RadixK`] only (ignored otherwise): `None` means
/// [`auto_factors`]`(ranks, DEFAULT_TARGET_K)`, a single value is a target group size
/// (`auto_factors(ranks, k)`), a longer list gives the exact factors, which must each be
/// at least 2 and multiply to `ranks` (an empty list is exact too, valid for one rank).
pub fn build_plan(
    ranks: usize,
    pixels: u32,
    algorithm: Algorithm,
    k: Option<&[usize]>,
) -> Result<Plan, PlanError> {
    if ranks == 0 {
        return Err(PlanError::NoRanks);
    }
    let mut cur = vec![Span::new(0, pixels); ranks];
    let (factors, rounds) = match algorithm {
        Algorithm::DirectSend => direct_send::rounds(ranks, &mut cur),
        Algorithm::BinarySwap => binary_swap::rounds(ranks, &mut cur),
        Algorithm::RadixK => {
            let factors = radix_k::resolve_factors(ranks, k)?;
            let members: Vec<usize> = (0..ranks).collect();
            let rounds = radix_k::rounds(ranks, &members, &factors, &mut cur);
            (factors, rounds)
        }
        Algorithm::Gather => gather::rounds(ranks, &mut cur),
    };
    Ok(Plan {
        ranks,
        pixels,
        algorithm,
        factors,
        rounds,
        result: cur,
    })
}

/// A direct-send plan whose final spans are given: position `j` ends holding
/// `targets[j]` (possibly empty), e.g. the tiles of a powerwall that the rank at `j`
/// drives ([`crate::wall`]), as IceT's multi-tile direct compositing delivers each tile's
/// pixels to its display's rank. Every position sends its part of each non-empty target
/// to that target's position; the non-empty targets must partition `[0, pixels)`.
pub fn build_plan_to(pixels: u32, targets: &[Span]) -> Result<Plan, PlanError> {
    let ranks = targets.len();
    if ranks == 0 {
        return Err(PlanError::NoRanks);
    }
    let mut parts: Vec<Span> = targets.iter().copied().filter(|s| !s.is_empty()).collect();
    parts.sort_by_key(|s| s.start);
    let mut at = 0u32;
    for s in &parts {
        if s.start != at || s.end > pixels {
            return Err(PlanError::Shape(format!(
                "target spans must partition [0, {pixels}): {s} follows {at}"
            )));
        }
        at = s.end;
    }
    if at != pixels {
        return Err(PlanError::Shape(format!(
            "target spans must partition [0, {pixels}): they end at {at}"
        )));
    }
    let rounds = direct_send::rounds_to(targets);
    Ok(Plan {
        ranks,
        pixels,
        algorithm: Algorithm::DirectSend,
        factors: if ranks > 1 { vec![ranks] } else { Vec::new() },
        rounds,
        result: targets
            .iter()
            .map(|s| if s.is_empty() { Span::EMPTY } else { *s })
            .collect(),
    })
}

impl Plan {
    /// Re-checks the plan's consistency: every expected receive matches a send of the
    /// same span, sends come from the sender's current span, blend lists are front to
    /// back and hold adjacent runs of positions, and the final spans partition
    /// `[0, pixels)` with each holding the composite of all ranks.
    pub fn validate(&self) -> Result<(), PlanError> {
        let p = self.ranks;
        if p == 0 {
            return Err(PlanError::NoRanks);
        }
        self.validate_factors()?;
        if self.result.len() != p {
            return Err(PlanError::Shape(format!(
                "{} result spans for {p} ranks",
                self.result.len()
            )));
        }
        let full = Span::new(0, self.pixels);
        let mut cur = vec![full; p];
        // Positions `[lo, hi)` whose images a rank's current data is the composite of.
        let mut acc: Vec<Option<(usize, usize)>> = (0..p).map(|j| Some((j, j + 1))).collect();
        for (r, round) in self.rounds.iter().enumerate() {
            if round.steps.len() != p {
                return Err(PlanError::Shape(format!(
                    "round {r} has {} steps for {p} ranks",
                    round.steps.len()
                )));
            }
            let bad = |position: usize, reason: String| PlanError::Inconsistent {
                round: r,
                position,
                reason,
            };
            // Every send lands in the receiver's inbox; each receiver's sorted inbox must
            // match its blend list (less itself) one to one, with the kept span.
            let mut inbox: Vec<Vec<(usize, Span)>> = vec![Vec::new(); p];
            for (j, step) in round.steps.iter().enumerate() {
                for &(to, span) in &step.sends {
                    if to >= p {
                        return Err(bad(j, format!("sends to position {to} of {p}")));
                    }
                    if to == j {
                        return Err(bad(j, "sends to itself".into()));
                    }
                    if span.is_empty() {
                        return Err(bad(j, format!("sends the empty span {span} to {to}")));
                    }
                    if !cur[j].contains(&span) {
                        return Err(bad(
                            j,
                            format!("sends {span} to {to} but holds only {}", cur[j]),
                        ));
                    }
                    inbox[to].push((j, span));
                }
            }
            for (j, step) in round.steps.iter().enumerate() {
                let keep = step.keep;
                if keep.start > keep.end || keep.end > self.pixels {
                    return Err(bad(j, format!("keeps the malformed span {keep}")));
                }
                if !cur[j].contains(&keep) {
                    return Err(bad(j, format!("keeps {keep} but holds only {}", cur[j])));
                }
                let mut inb = std::mem::take(&mut inbox[j]);
                inb.sort_unstable_by_key(|e| e.0);
                if let Some(w) = inb.windows(2).find(|w| w[0].0 == w[1].0) {
                    return Err(bad(w[0].0, format!("sends twice to {j}")));
                }
                if keep.is_empty() && !step.blend.is_empty() {
                    return Err(bad(j, "blends although it keeps nothing".into()));
                }
                if !keep.is_empty() && !step.blend.contains(&j) {
                    return Err(bad(j, format!("keeps {keep} but does not blend itself")));
                }
                if let Some(&q) = step.blend.iter().find(|&&q| q >= p) {
                    return Err(bad(j, format!("blends position {q} of {p}")));
                }
                let mut others: Vec<usize> =
                    step.blend.iter().copied().filter(|&q| q != j).collect();
                others.sort_unstable();
                let (mut a, mut b) = (0, 0);
                while a < others.len() || b < inb.len() {
                    let q = others.get(a).copied().unwrap_or(usize::MAX);
                    let (from, span) = inb.get(b).copied().unwrap_or((usize::MAX, keep));
                    if q < from || (q == from && a > 0 && others[a - 1] == q) {
                        return Err(bad(
                            j,
                            format!(
                                "expects {keep} from {q}, which does not send it \
                                 (or is listed twice)"
                            ),
                        ));
                    }
                    if from < q {
                        return Err(bad(
                            from,
                            format!("sends {span} to {j}, which does not expect it"),
                        ));
                    }
                    if span != keep {
                        return Err(bad(
                            j,
                            format!("expects {keep} from {q}, which sends {span}"),
                        ));
                    }
                    a += 1;
                    b += 1;
                }
            }
            // Blend lists must concatenate adjacent position ranges, front to back.
            let mut next = acc.clone();
            for (j, step) in round.steps.iter().enumerate() {
                if step.keep.is_empty() {
                    next[j] = None;
                    continue;
                }
                let mut range: Option<(usize, usize)> = None;
                for &q in &step.blend {
                    let Some((lo, hi)) = acc[q] else {
                        return Err(bad(j, format!("blends {q}, which holds no data")));
                    };
                    range = match range {
                        None => Some((lo, hi)),
                        Some((a, b)) if b == lo => Some((a, hi)),
                        Some((a, b)) => {
                            return Err(bad(
                                j,
                                format!(
                                    "blend order {:?} is not front to back: positions \
                                     [{a}, {b}) are followed by [{lo}, {hi})",
                                    step.blend
                                ),
                            ))
                        }
                    };
                }
                next[j] = range;
            }
            acc = next;
            for (j, step) in round.steps.iter().enumerate() {
                cur[j] = step.keep;
            }
        }
        let mut owned = Vec::new();
        for j in 0..p {
            let (got, want) = (self.result[j], cur[j]);
            if got != want && !(got.is_empty() && want.is_empty()) {
                return Err(PlanError::Result(format!(
                    "position {j} is listed with {got} but ends the rounds with {want}"
                )));
            }
            if want.is_empty() {
                continue;
            }
            if acc[j] != Some((0, p)) {
                return Err(PlanError::Result(format!(
                    "position {j} ends with {want} holding positions {:?}, not all [0, {p})",
                    acc[j]
                )));
            }
            owned.push(want);
        }
        owned.sort_by_key(|s| s.start);
        let mut at = 0u32;
        for s in &owned {
            if s.start != at {
                return Err(PlanError::Result(format!(
                    "final spans do not partition [0, {}): {s} follows pixel {at}",
                    self.pixels
                )));
            }
            at = s.end;
        }
        if at != self.pixels {
            return Err(PlanError::Result(format!(
                "final spans cover [0, {at}) of [0, {})",
                self.pixels
            )));
        }
        Ok(())
    }

    fn validate_factors(&self) -> Result<(), PlanError> {
        let p = self.ranks;
        if let Some(&f) = self.factors.iter().find(|&&f| f < 2) {
            return Err(PlanError::FactorTooSmall { factor: f });
        }
        let product = self
            .factors
            .iter()
            .try_fold(1usize, |a, &f| a.checked_mul(f));
        let (virtual_ranks, extra_rounds) = match self.algorithm {
            Algorithm::DirectSend | Algorithm::RadixK | Algorithm::Gather => (p, 0),
            Algorithm::BinarySwap => {
                if self.factors.iter().any(|&f| f != 2) {
                    return Err(PlanError::Shape(format!(
                        "binary swap with factors {:?}",
                        self.factors
                    )));
                }
                let q = binary_swap::pow2_floor(p);
                (q, usize::from(q != p))
            }
        };
        if product != Some(virtual_ranks) {
            return Err(PlanError::FactorProduct {
                factors: self.factors.clone(),
                product: radix_k::product_u128(&self.factors),
                ranks: virtual_ranks,
            });
        }
        if matches!(self.algorithm, Algorithm::DirectSend | Algorithm::Gather)
            && self.factors.len() > 1
        {
            return Err(PlanError::Shape(format!(
                "direct send with factors {:?}",
                self.factors
            )));
        }
        if self.rounds.len() != self.factors.len() + extra_rounds {
            return Err(PlanError::Shape(format!(
                "{} rounds for factors {:?}",
                self.rounds.len(),
                self.factors
            )));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_even_gives_remainder_to_first_parts() {
        let parts = Span::new(10, 21).split_even(4);
        assert_eq!(
            parts,
            vec![
                Span::new(10, 13),
                Span::new(13, 16),
                Span::new(16, 19),
                Span::new(19, 21)
            ]
        );
        let parts = Span::new(3, 5).split_even(4);
        assert_eq!(
            parts.iter().map(Span::len).collect::<Vec<_>>(),
            [1, 1, 0, 0]
        );
        assert_eq!(parts[3].start, 5);
        assert!(Span::new(0, 7).split_even(0).is_empty());
        assert_eq!(Span::new(5, 3).len(), 0);
        assert!(Span::new(5, 3).is_empty());
    }

    #[test]
    fn zero_ranks_is_an_error() {
        for a in [
            Algorithm::DirectSend,
            Algorithm::BinarySwap,
            Algorithm::RadixK,
            Algorithm::Gather,
        ] {
            assert_eq!(build_plan(0, 10, a, None), Err(PlanError::NoRanks));
        }
    }

    #[test]
    fn algorithm_serde_names() {
        let v: Vec<Algorithm> =
            toml::from_str::<std::collections::BTreeMap<String, Vec<Algorithm>>>(
                "a = [\"direct-send\", \"binary-swap\", \"radix-k\", \"gather\"]",
            )
            .unwrap()
            .remove("a")
            .unwrap();
        assert_eq!(
            v,
            [
                Algorithm::DirectSend,
                Algorithm::BinarySwap,
                Algorithm::RadixK,
                Algorithm::Gather
            ]
        );
    }

    #[test]
    fn validate_catches_tampering() {
        let good = build_plan(4, 100, Algorithm::BinarySwap, None).unwrap();
        good.validate().unwrap();

        // Wrong span in a send.
        let mut p = good.clone();
        p.rounds[0].steps[1].sends[0].1.end -= 1;
        assert!(matches!(p.validate(), Err(PlanError::Inconsistent { .. })));

        // A send nobody expects.
        let mut p = good.clone();
        p.rounds[0].steps[0].sends.push((2, Span::new(0, 50)));
        let e = p.validate().unwrap_err();
        assert!(e.to_string().contains("does not expect it"), "{e}");

        // A blend entry without its send.
        let mut p = good.clone();
        p.rounds[0].steps[1].sends.clear();
        let e = p.validate().unwrap_err();
        assert!(e.to_string().contains("does not send it"), "{e}");

        // Blend order reversed.
        let mut p = good.clone();
        p.rounds[0].steps[0].blend.reverse();
        let e = p.validate().unwrap_err();
        assert!(e.to_string().contains("front to back"), "{e}");

        // Sending data the rank no longer holds.
        let mut p = good.clone();
        let keep = p.rounds[0].steps[0].keep;
        p.rounds[1].steps[0].sends[0].1 = Span::new(keep.end, keep.end + 1);
        assert!(p.validate().is_err());

        // Result not matching.
        let mut p = good.clone();
        p.result.swap(0, 1);
        assert!(matches!(p.validate(), Err(PlanError::Result(_))));

        // A dropped round leaves spans holding only part of the ranks.
        let mut p = good.clone();
        p.rounds.pop();
        p.factors.pop();
        assert!(p.validate().is_err());

        // Wrong factors.
        let mut p = good;
        p.factors = vec![4];
        assert!(p.validate().is_err());
    }
}
