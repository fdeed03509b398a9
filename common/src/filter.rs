//! Coarsening filters: how one sample of level `l + 1` is made from the 2×2×2 (volumes) or
//! 2×2 (horizons) samples of level `l` below it.
//!
//! Seismic amplitudes are signed and oscillate around zero within a wavelength. A box filter
//! (Lux's choice) averages a reflection's positive and negative lobes toward zero, so coarse
//! levels look empty after the transfer function: the digest of Lux calls this the biggest
//! practical artifact of multi-resolution seismic rendering (§8 item 4). Strata therefore
//! offers, and uses by default for signed data:
//!
//! * [`CoarsenFilter::SignedRms`]: `sign(mean) · sqrt(mean(v²))`. It keeps the local
//!   amplitude (energy) of the children, so a reflector stays as bright at coarse levels as at
//!   level 0, and keeps the polarity of the dominant lobe where there is one. Where the lobes
//!   cancel exactly (`mean == 0`), the sign of the largest-magnitude child is used. The cost is
//!   that it is not a low-pass filter: coarse values are biased toward larger magnitudes than a
//!   band-limited resampling would give. `bench-store --filters` measures both effects.
//! * [`CoarsenFilter::MaxAbs`]: the child with the largest magnitude (peak-preserving, sign kept).
//! * [`CoarsenFilter::Mean`]: the box filter; the default for unsigned data (CT, MRI), where
//!   averaging is what a mip pyramid should do.
//! * [`CoarsenFilter::HorizonMean`]: for height fields, the mean of the 2×2 heights if all are
//!   valid and a hole otherwise, so coarse levels never invent heights across holes
//!   (holes grow by at most one coarse texel per level; they never shrink).
//!
//! Volume filters skip no-data (`NaN`) children; a coarse sample is no-data only if all its
//! children are. Sums are accumulated in `f64` so the result does not depend on summation
//! order beyond the last bit of `f32`.

use serde::{Deserialize, Serialize};

/// A coarsening filter.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum CoarsenFilter {
    /// Arithmetic mean (box filter) of the valid children.
    Mean,
    /// `sign(mean) · rms` of the valid children.
    SignedRms,
    /// The valid child with the largest magnitude.
    MaxAbs,
    /// Mean if every child is valid, else a hole (height fields).
    HorizonMean,
}

impl CoarsenFilter {
    /// Command-line name.
    pub fn name(self) -> &'static str {
        match self {
            CoarsenFilter::Mean => "mean",
            CoarsenFilter::SignedRms => "signed-rms",
            CoarsenFilter::MaxAbs => "max-abs",
            CoarsenFilter::HorizonMean => "horizon-mean",
        }
    }
    /// Parses a command-line name.
    pub fn parse(s: &str) -> Option<Self> {
        [Self::Mean, Self::SignedRms, Self::MaxAbs, Self::HorizonMean]
            .into_iter()
            .find(|f| f.name() == s)
    }

    /// Applies the filter to the children (2, 4 or 8 values; `NaN` = no-data).
    pub fn apply(self, children: &[f32]) -> f32 {
        match self {
            CoarsenFilter::HorizonMean => {
                let mut s = 0.0f64;
                for &v in children {
                    if v.is_nan() {
                        return f32::NAN;
                    }
                    s += v as f64;
                }
                (s / children.len() as f64) as f32
            }
            CoarsenFilter::Mean => {
                let (mut s, mut n) = (0.0f64, 0u32);
                for &v in children.iter().filter(|v| !v.is_nan()) {
                    s += v as f64;
                    n += 1;
                }
                if n == 0 {
                    f32::NAN
                } else {
                    (s / n as f64) as f32
                }
            }
            CoarsenFilter::SignedRms => {
                let (mut s, mut s2, mut n) = (0.0f64, 0.0f64, 0u32);
                let mut peak = 0.0f32;
                for &v in children.iter().filter(|v| !v.is_nan()) {
                    s += v as f64;
                    s2 += (v as f64) * (v as f64);
                    n += 1;
                    if v.abs() > peak.abs() {
                        peak = v;
                    }
                }
                if n == 0 {
                    return f32::NAN;
                }
                let rms = (s2 / n as f64).sqrt();
                // The mean's sign; where the mean is 0, the sign of the largest magnitude.
                let sign = if s > 0.0 {
                    1.0
                } else if s < 0.0 || peak < 0.0 {
                    -1.0
                } else {
                    1.0
                };
                (sign * rms) as f32
            }
            CoarsenFilter::MaxAbs => {
                let mut best = f32::NAN;
                for &v in children.iter().filter(|v| !v.is_nan()) {
                    if best.is_nan() || v.abs() > best.abs() {
                        best = v;
                    }
                }
                best
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mean_of_wavelet_lobes_vanishes_but_signed_rms_keeps_amplitude() {
        let lobes = [100.0, -100.0, 100.0, -100.0, 100.0, -100.0, 100.0, -100.0];
        assert_eq!(CoarsenFilter::Mean.apply(&lobes), 0.0);
        assert_eq!(CoarsenFilter::SignedRms.apply(&lobes).abs(), 100.0);
        assert_eq!(CoarsenFilter::MaxAbs.apply(&lobes).abs(), 100.0);
    }

    #[test]
    fn signed_rms_keeps_dominant_polarity() {
        let v = [-50.0, -40.0, -60.0, 10.0, -50.0, -40.0, -60.0, 10.0];
        let r = CoarsenFilter::SignedRms.apply(&v);
        assert!(r < -40.0, "{r}");
    }

    #[test]
    fn constant_is_fixed_point_of_every_filter() {
        for f in [
            CoarsenFilter::Mean,
            CoarsenFilter::SignedRms,
            CoarsenFilter::MaxAbs,
            CoarsenFilter::HorizonMean,
        ] {
            assert_eq!(f.apply(&[-7.5; 8]), -7.5, "{f:?}");
            assert_eq!(f.apply(&[3.0; 4]), 3.0, "{f:?}");
        }
    }

    #[test]
    fn no_data_handling() {
        let v = [f32::NAN, 2.0, 4.0, f32::NAN];
        assert_eq!(CoarsenFilter::Mean.apply(&v), 3.0);
        assert!(CoarsenFilter::HorizonMean.apply(&v).is_nan());
        assert!(CoarsenFilter::Mean.apply(&[f32::NAN; 8]).is_nan());
        assert!(CoarsenFilter::SignedRms.apply(&[f32::NAN; 8]).is_nan());
        assert!(CoarsenFilter::MaxAbs.apply(&[f32::NAN; 8]).is_nan());
    }

    #[test]
    fn names_round_trip() {
        for f in [
            CoarsenFilter::Mean,
            CoarsenFilter::SignedRms,
            CoarsenFilter::MaxAbs,
            CoarsenFilter::HorizonMean,
        ] {
            assert_eq!(CoarsenFilter::parse(f.name()), Some(f));
        }
    }
}
