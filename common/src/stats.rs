//! Robust value statistics of a whole data set in one pass and bounded memory: mean, RMS and
//! percentiles (of the values and of their magnitudes), as ingest stores them in the store
//! header so the display can clip at, e.g., the 99.5th percentile of |amplitude| without
//! reading the data again.
//!
//! **Why a histogram of float bit patterns.** An exact percentile of 10¹² samples would need
//! them sorted. Instead every finite value falls in a bin of its f32 bit pattern with the
//! lowest [`DROPPED_BITS`] mantissa bits dropped, ordered so that bins follow the values
//! (negative patterns reversed). Bins are then *relative*: each spans a factor of at most
//! `1 + 2^-10` of its magnitude, at every scale from denormals to 10³⁸, in 2¹⁹ counters (4
//! MiB), so a reported percentile is within [`RELATIVE_RESOLUTION`] of the exact
//! nearest-rank one whatever the data's range. Magnitude percentiles come from the same
//! counts (the bins of `v` and `−v` mirror each other).

use serde::{Deserialize, Serialize};

/// Mantissa bits a bin ignores.
pub const DROPPED_BITS: u32 = 13;
/// Bins: one per kept bit pattern (sign, exponent, 10 mantissa bits).
pub const BINS: usize = 1 << (32 - DROPPED_BITS);
/// A percentile is within this fraction of its magnitude of the exact nearest-rank value
/// (a bin's edge nearer zero is reported, so values with at most 11 significant bits,
/// e.g. 16-bit integers below 2048 in magnitude, come out exact). Below the smallest normal
/// f32 (1.2·10⁻³⁸) bins are 1.2·10⁻⁴¹ wide instead.
pub const RELATIVE_RESOLUTION: f64 = 1.0 / (1u64 << (23 - DROPPED_BITS)) as f64;

/// Percentiles of the values stored at ingest.
pub const PERCENTILES: [f64; 7] = [0.5, 1.0, 5.0, 50.0, 95.0, 99.0, 99.5];
/// Percentiles of the magnitudes stored at ingest.
pub const ABS_PERCENTILES: [f64; 5] = [50.0, 90.0, 99.0, 99.5, 99.9];

/// The median of `v`: the middle value, or the mean of the two middle values of an even
/// count (as Python's `statistics.median`, which the baselines' scripts use); `NaN` for
/// none. NaN entries sort last (`total_cmp`).
pub fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    match n {
        0 => f64::NAN,
        _ if n % 2 == 1 => v[n / 2],
        _ => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// The bin of a finite value: monotone in the value.
#[inline]
pub fn bin(v: f32) -> u32 {
    let b = v.to_bits();
    let ordered = if b >> 31 == 1 { !b } else { b | 0x8000_0000 };
    ordered >> DROPPED_BITS
}

/// The edge of bin `k` nearer zero (the inverse of [`bin`] up to the dropped bits).
pub fn bin_value(k: u32) -> f64 {
    let ordered = k << DROPPED_BITS;
    let b = if ordered >> 31 == 1 {
        ordered & 0x7fff_ffff
    } else {
        !(ordered | ((1 << DROPPED_BITS) - 1))
    };
    f32::from_bits(b) as f64
}

/// A sum with Neumaier's compensation: the rounding of each addition is kept and added
/// back, so that 10¹² values of one constant sum to `n·c` within a few ulps (a plain f64
/// sum drifts linearly once `n·c` needs more than 53 bits: 5·10⁻⁵ relative at 10¹²).
#[derive(Clone, Copy, Default)]
struct CompensatedSum {
    sum: f64,
    lost: f64,
}

impl CompensatedSum {
    #[inline]
    fn add(&mut self, x: f64) {
        let t = self.sum + x;
        self.lost += if self.sum.abs() >= x.abs() {
            (self.sum - t) + x
        } else {
            (x - t) + self.sum
        };
        self.sum = t;
    }

    fn value(self) -> f64 {
        self.sum + self.lost
    }
}

/// Counts of the finite values of a data set, by [`bin`], with their sums.
#[derive(Clone)]
pub struct ValueHistogram {
    counts: Vec<u64>,
    n: u64,
    sum: CompensatedSum,
    sum_sq: CompensatedSum,
}

impl Default for ValueHistogram {
    fn default() -> Self {
        ValueHistogram {
            counts: vec![0; BINS],
            n: 0,
            sum: CompensatedSum::default(),
            sum_sq: CompensatedSum::default(),
        }
    }
}

impl ValueHistogram {
    /// Counts one value (non-finite values are not counted).
    #[inline]
    pub fn add(&mut self, v: f32) {
        if v.is_finite() {
            self.counts[bin(v) as usize] += 1;
            self.n += 1;
            let d = v as f64;
            self.sum.add(d);
            self.sum_sq.add(d * d);
        }
    }

    /// Values counted.
    pub fn count(&self) -> u64 {
        self.n
    }

    /// The nearest-rank `p`th percentile (`0 < p ≤ 100`): the smallest bin holding at least
    /// `⌈p·n/100⌉` values at or below it, as its edge nearer zero ([`bin_value`]); `None`
    /// with no values.
    pub fn percentile(&self, p: f64) -> Option<f64> {
        let rank = self.rank(p)?;
        let mut seen = 0u64;
        for (k, &c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= rank {
                return Some(bin_value(k as u32));
            }
        }
        None
    }

    /// The nearest-rank `p`th percentile of |value|.
    pub fn abs_percentile(&self, p: f64) -> Option<f64> {
        let rank = self.rank(p)?;
        // Magnitude bins in increasing order: positive bin `half + m` and negative bin
        // `half − 1 − m` hold the same magnitudes (the positive one's edge is reported).
        let half = BINS / 2;
        let mut seen = 0u64;
        for m in 0..half {
            seen += self.counts[half + m] + self.counts[half - 1 - m];
            if seen >= rank {
                return Some(bin_value((half + m) as u32));
            }
        }
        None
    }

    fn rank(&self, p: f64) -> Option<u64> {
        if self.n == 0 || !(p > 0.0 && p <= 100.0) {
            return None;
        }
        // (p·n)/100 rather than p/100·n: 0.07·100 is 7.000000000000001, whose ceiling is
        // one rank past the 7th value.
        Some(((p * self.n as f64 / 100.0).ceil() as u64).clamp(1, self.n))
    }

    /// The statistics ingest stores; `None` with no values.
    pub fn stats(&self) -> Option<ValueStats> {
        if self.n == 0 {
            return None;
        }
        let n = self.n as f64;
        Some(ValueStats {
            mean: self.sum.value() / n,
            rms: (self.sum_sq.value() / n).sqrt(),
            percentiles: PERCENTILES
                .iter()
                .map(|&p| [p, self.percentile(p).unwrap_or(f64::NAN)])
                .collect(),
            abs_percentiles: ABS_PERCENTILES
                .iter()
                .map(|&p| [p, self.abs_percentile(p).unwrap_or(f64::NAN)])
                .collect(),
            resolution: RELATIVE_RESOLUTION,
        })
    }
}

/// Value statistics of a store's level-0 samples (the valid ones), computed at ingest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ValueStats {
    /// Mean.
    pub mean: f64,
    /// Root mean square.
    pub rms: f64,
    /// `[p, value]`: nearest-rank percentiles of the values.
    pub percentiles: Vec<[f64; 2]>,
    /// `[p, value]`: nearest-rank percentiles of |value|.
    pub abs_percentiles: Vec<[f64; 2]>,
    /// Relative resolution of the percentile values.
    pub resolution: f64,
}

impl ValueStats {
    /// The stored percentile `p` of |value|, if stored.
    pub fn abs_percentile(&self, p: f64) -> Option<f64> {
        self.abs_percentiles
            .iter()
            .find(|e| e[0] == p)
            .map(|e| e[1])
            .filter(|v| v.is_finite())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_long_constant_sums_to_its_count_times_its_value() {
        // 0.1 in f32 is not a short binary fraction: added to a large sum, every addition
        // rounds, and a plain sum's roundings accumulate.
        let c = 0.1f32;
        let n = 3_000_000u64;
        let mut plain = 0.0f64;
        let mut s = CompensatedSum::default();
        let big = 1.0e12;
        // Start both from a large partial sum, as after 10¹³ values: each addition then
        // rounds.
        plain += big;
        s.add(big);
        for _ in 0..n {
            plain += c as f64;
            s.add(c as f64);
        }
        let exact = big + n as f64 * c as f64;
        assert!(
            (s.value() - exact).abs() <= exact * 4.0 * f64::EPSILON,
            "{} {exact}",
            s.value()
        );
        assert!(
            (plain - exact).abs() > 1e3 * exact * f64::EPSILON,
            "the plain sum rounded too well"
        );
    }

    #[test]
    fn ranks_are_exact_for_whole_percentages() {
        let mut h = ValueHistogram::default();
        for v in 1..=100 {
            h.add(v as f32);
        }
        for p in [1.0, 7.0, 14.0, 28.0, 29.0, 57.0, 99.0, 100.0] {
            assert_eq!(h.rank(p), Some(p as u64), "{p}");
        }
    }

    #[test]
    fn median_averages_the_middle_pair_of_an_even_count() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(median(&[]).is_nan());
        assert_eq!(median(&[7.0]), 7.0);
    }
    use proptest::prelude::*;

    fn nearest_rank(sorted: &[f32], p: f64) -> f64 {
        let n = sorted.len();
        let r = ((p / 100.0 * n as f64).ceil() as usize).clamp(1, n);
        sorted[r - 1] as f64
    }

    fn close(got: f64, want: f64) -> bool {
        (got - want).abs() <= RELATIVE_RESOLUTION * want.abs() + 1.2e-41
    }

    #[test]
    fn bins_are_monotone_and_values_fall_in_their_bins() {
        let vs = [
            -3.0e38f32, -1.5, -1.0, -1e-30, -0.0, 0.0, 1e-40, 1e-30, 0.5, 1.0, 1.0009, 7.0, 3e38,
        ];
        for w in vs.windows(2) {
            assert!(bin(w[0]) <= bin(w[1]), "{} {}", w[0], w[1]);
        }
        for &v in &vs {
            assert!(
                close(bin_value(bin(v)), v as f64),
                "{v}: {}",
                bin_value(bin(v))
            );
        }
        assert_eq!(bin(-0.0), bin(0.0) - 1);
        // Small integers are bin edges: reported exactly.
        for v in [0.0f32, -1.0, 3.0, -2047.0, 1024.0] {
            assert_eq!(bin_value(bin(v)), v as f64);
        }
    }

    #[test]
    fn empty_and_non_finite() {
        let mut h = ValueHistogram::default();
        assert!(h.stats().is_none());
        h.add(f32::NAN);
        h.add(f32::INFINITY);
        assert_eq!(h.count(), 0);
        h.add(2.0);
        let s = h.stats().unwrap();
        assert_eq!((s.mean, s.rms), (2.0, 2.0));
        assert!(close(s.abs_percentile(99.5).unwrap(), 2.0));
        assert!(h.percentile(0.0).is_none() && h.percentile(101.0).is_none());
    }

    proptest! {
        #[test]
        fn percentiles_match_sorting_within_the_resolution(
            vals in prop::collection::vec(
                prop_oneof![-1e6f32..1e6, -1.0f32..1.0, -1e-20f32..1e-20], 1..400),
            p in 0.01f64..100.0,
        ) {
            let mut h = ValueHistogram::default();
            for &v in &vals {
                h.add(v);
            }
            let mut sorted = vals.clone();
            sorted.sort_by(f32::total_cmp);
            let got = h.percentile(p).unwrap();
            let want = nearest_rank(&sorted, p);
            prop_assert!(close(got, want), "p{}: {} vs {}", p, got, want);
            let mut mags: Vec<f32> = vals.iter().map(|v| v.abs()).collect();
            mags.sort_by(f32::total_cmp);
            let got = h.abs_percentile(p).unwrap();
            let want = nearest_rank(&mags, p);
            prop_assert!(close(got, want), "|p{}|: {} vs {}", p, got, want);
        }
    }
}
