//! An order-independent digest of a data set's level-0 samples.
//!
//! Each sample contributes `h(index, value)`; contributions are summed modulo 2⁶⁴ (an
//! additive multiset hash), so the digest can be computed page by page in any order and in
//! parallel, and it does not depend on brick size, border, compression, sample type or the
//! byte order of the source file: two stores holding the same values at the same positions
//! print the same digest.

/// The 64-bit finaliser of MurmurHash3: a bijective mixer with full avalanche.
#[inline]
pub fn fmix64(mut k: u64) -> u64 {
    k ^= k >> 33;
    k = k.wrapping_mul(0xff51_afd7_ed55_8ccd);
    k ^= k >> 33;
    k = k.wrapping_mul(0xc4ce_b9fe_1a85_ec53);
    k ^= k >> 33;
    k
}

/// Canonical bits of a sample value: no-data (`NaN`) has one representation, `-0.0`
/// equals `0.0`, and integers map to the same bits whatever their stored type.
#[inline]
fn value_bits(v: f32) -> u64 {
    if v.is_nan() {
        u64::MAX
    } else if v == 0.0 {
        0
    } else {
        (v as f64).to_bits()
    }
}

/// Contribution of one sample at linear level-0 index `index` (x fastest).
#[inline]
pub fn sample_term(index: u64, v: f32) -> u64 {
    fmix64(fmix64(index.wrapping_add(0x9e37_79b9_7f4a_7c15)) ^ value_bits(v))
}

/// Accumulates sample terms; `combine` merges partial digests computed in parallel.
#[derive(Copy, Clone, Debug, Default, PartialEq, Eq)]
pub struct DigestAcc {
    sum: u64,
    count: u64,
}

impl DigestAcc {
    /// Adds one sample.
    #[inline]
    pub fn add(&mut self, index: u64, v: f32) {
        self.sum = self.sum.wrapping_add(sample_term(index, v));
        self.count += 1;
    }
    /// Merges another partial digest.
    pub fn combine(self, o: DigestAcc) -> DigestAcc {
        DigestAcc {
            sum: self.sum.wrapping_add(o.sum),
            count: self.count + o.count,
        }
    }
    /// Number of samples added.
    pub fn count(&self) -> u64 {
        self.count
    }
    /// The final digest for a data set of `dims` samples.
    pub fn finish(&self, dims: [u64; 3]) -> u64 {
        fmix64(self.sum ^ fmix64(dims[0] ^ fmix64(dims[1] ^ fmix64(dims[2]))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn order_independent_and_value_sensitive() {
        let vals = [1.0f32, -2.0, 3.5, f32::NAN, 0.0];
        let mut a = DigestAcc::default();
        for (i, v) in vals.iter().enumerate() {
            a.add(i as u64, *v);
        }
        let mut b = DigestAcc::default();
        for (i, v) in vals.iter().enumerate().rev() {
            b.add(i as u64, *v);
        }
        assert_eq!(a.finish([5, 1, 1]), b.finish([5, 1, 1]));
        let mut c = DigestAcc::default();
        for (i, v) in vals.iter().enumerate() {
            c.add(i as u64, if i == 2 { 3.25 } else { *v });
        }
        assert_ne!(a.finish([5, 1, 1]), c.finish([5, 1, 1]));
        // A swap of two values changes the digest.
        let mut d = DigestAcc::default();
        d.add(0, -2.0);
        d.add(1, 1.0);
        let mut e = DigestAcc::default();
        e.add(0, 1.0);
        e.add(1, -2.0);
        assert_ne!(d.finish([2, 1, 1]), e.finish([2, 1, 1]));
        assert_eq!(sample_term(3, -0.0), sample_term(3, 0.0));
    }
}
