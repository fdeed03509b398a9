//! Sample types of the page store and their exact conversion to and from `f32`.
//!
//! All stored types (`u8`, `i8`, `u16`, `i16`, `f32`) convert to `f32` exactly, so the
//! builder and the renderers compute in `f32` and only [`SampleType::quantize`] rounds.
//! On disk, samples are little-endian. No-data samples are `NaN` in `f32` form; integer
//! stores that need no-data reserve a sentinel value (see `StoreHeader::no_data`).

use serde::{Deserialize, Serialize};

/// Element type of a stored page.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum SampleType {
    /// Unsigned 8-bit.
    U8,
    /// Signed 8-bit.
    I8,
    /// Unsigned 16-bit.
    U16,
    /// Signed 16-bit.
    I16,
    /// IEEE-754 single precision.
    F32,
}

impl SampleType {
    /// Bytes per sample.
    pub fn size(self) -> usize {
        match self {
            SampleType::U8 | SampleType::I8 => 1,
            SampleType::U16 | SampleType::I16 => 2,
            SampleType::F32 => 4,
        }
    }
    /// The name used on the command line (`u8`, `i8`, `u16`, `i16`, `f32`).
    pub fn name(self) -> &'static str {
        match self {
            SampleType::U8 => "u8",
            SampleType::I8 => "i8",
            SampleType::U16 => "u16",
            SampleType::I16 => "i16",
            SampleType::F32 => "f32",
        }
    }
    /// Parses a command-line name.
    pub fn parse(s: &str) -> Option<Self> {
        Some(match s {
            "u8" => SampleType::U8,
            "i8" => SampleType::I8,
            "u16" => SampleType::U16,
            "i16" => SampleType::I16,
            "f32" => SampleType::F32,
            _ => return None,
        })
    }
    /// Whether the type can hold negative values.
    pub fn is_signed(self) -> bool {
        matches!(self, SampleType::I8 | SampleType::I16 | SampleType::F32)
    }
    /// Whether `v` can be this type's no-data sentinel: for integer types a value the type
    /// holds (a sentinel it cannot hold is written as another value, and holes read back as
    /// data); for `f32`, anything but NaN (NaN is no-data anyway).
    pub fn holds_sentinel(self, v: f32) -> bool {
        if self == SampleType::F32 {
            return !v.is_nan();
        }
        let (lo, hi) = self.range();
        v.is_finite() && v.fract() == 0.0 && lo <= v && v <= hi
    }
    /// Representable range as `f32`.
    pub fn range(self) -> (f32, f32) {
        match self {
            SampleType::U8 => (0.0, 255.0),
            SampleType::I8 => (-128.0, 127.0),
            SampleType::U16 => (0.0, 65535.0),
            SampleType::I16 => (-32768.0, 32767.0),
            SampleType::F32 => (f32::MIN, f32::MAX),
        }
    }
    /// Rounds a computed value to the nearest representable one (integers: round half away
    /// from zero, then clamp). `NaN` stays `NaN`; the encoder maps it to no-data. In `f32`
    /// stores `±Inf` becomes `NaN` too: an infinite amplitude is a broken sample, not a
    /// value, and would poison interpolation (`0·Inf`) and value ranges.
    pub fn quantize(self, v: f32) -> f32 {
        if self == SampleType::F32 {
            return if v.is_infinite() { f32::NAN } else { v };
        }
        if v.is_nan() {
            return v;
        }
        let (lo, hi) = self.range();
        // `+ 0.0` turns -0.0 into 0.0: integers have no negative zero.
        v.round().clamp(lo, hi) + 0.0
    }

    /// [`quantize`](Self::quantize) for a store whose integer samples reserve `no_data` for
    /// holes: a valid value that would round to the sentinel takes the neighbouring integer
    /// inside the type's range instead (one unit away), so it is not read back as a hole.
    /// `NaN` stays `NaN`; `f32` stores and stores without a sentinel are unaffected.
    pub fn quantize_valid(self, v: f32, no_data: Option<f32>) -> f32 {
        let q = self.quantize(v);
        match no_data {
            Some(nd) if self != SampleType::F32 && q == nd => {
                if nd < self.range().1 {
                    nd + 1.0
                } else {
                    nd - 1.0
                }
            }
            _ => q,
        }
    }

    /// Decodes little-endian samples into `out` (which has `bytes.len() / size` elements),
    /// mapping `no_data` to `NaN`.
    pub fn decode_le(self, bytes: &[u8], no_data: Option<f32>, out: &mut [f32]) {
        debug_assert_eq!(bytes.len(), out.len() * self.size());
        match self {
            SampleType::U8 => out.iter_mut().zip(bytes).for_each(|(o, &b)| *o = b as f32),
            SampleType::I8 => out
                .iter_mut()
                .zip(bytes)
                .for_each(|(o, &b)| *o = b as i8 as f32),
            SampleType::U16 => out
                .iter_mut()
                .zip(bytes.chunks_exact(2))
                .for_each(|(o, b)| *o = u16::from_le_bytes([b[0], b[1]]) as f32),
            SampleType::I16 => out
                .iter_mut()
                .zip(bytes.chunks_exact(2))
                .for_each(|(o, b)| *o = i16::from_le_bytes([b[0], b[1]]) as f32),
            SampleType::F32 => out
                .iter_mut()
                .zip(bytes.chunks_exact(4))
                .for_each(|(o, b)| *o = f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        }
        if let Some(nd) = no_data {
            if self != SampleType::F32 {
                out.iter_mut()
                    .filter(|v| **v == nd)
                    .for_each(|v| *v = f32::NAN);
            }
        }
    }

    /// Encodes `values` little-endian, appending to `out`. Values must already be quantized;
    /// `NaN` becomes `no_data` for integer types (0 if the store has no sentinel).
    pub fn encode_le(self, values: &[f32], no_data: Option<f32>, out: &mut Vec<u8>) {
        out.reserve(values.len() * self.size());
        let nd = no_data.unwrap_or(0.0);
        let fix = |v: f32| if v.is_nan() { nd } else { v };
        match self {
            SampleType::U8 => out.extend(values.iter().map(|&v| fix(v) as u8)),
            SampleType::I8 => out.extend(values.iter().map(|&v| fix(v) as i8 as u8)),
            SampleType::U16 => values
                .iter()
                .for_each(|&v| out.extend_from_slice(&(fix(v) as u16).to_le_bytes())),
            SampleType::I16 => values
                .iter()
                .for_each(|&v| out.extend_from_slice(&(fix(v) as i16).to_le_bytes())),
            SampleType::F32 => values
                .iter()
                .for_each(|&v| out.extend_from_slice(&v.to_le_bytes())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_sentinel_must_be_a_value_of_the_type() {
        assert!(SampleType::U8.holds_sentinel(0.0) && SampleType::U8.holds_sentinel(255.0));
        for v in [-1.0, 256.0, 0.5, f32::NAN, f32::INFINITY] {
            assert!(!SampleType::U8.holds_sentinel(v), "{v}");
        }
        assert!(SampleType::I16.holds_sentinel(-32768.0));
        assert!(!SampleType::I16.holds_sentinel(-32769.0));
        assert!(SampleType::F32.holds_sentinel(-999.25));
        assert!(!SampleType::F32.holds_sentinel(f32::NAN));
    }
    use proptest::prelude::*;

    #[test]
    fn quantize_rounds_and_clamps() {
        assert_eq!(SampleType::U8.quantize(254.5), 255.0);
        assert_eq!(SampleType::U8.quantize(300.0), 255.0);
        assert_eq!(SampleType::I16.quantize(-2.5), -3.0);
        assert_eq!(SampleType::I8.quantize(-1000.0), -128.0);
        assert!(SampleType::U16.quantize(f32::NAN).is_nan());
        assert_eq!(SampleType::I16.quantize(-0.4).to_bits(), 0.0f32.to_bits());
    }

    #[test]
    fn valid_values_never_quantize_to_the_no_data_sentinel() {
        assert_eq!(
            SampleType::I16.quantize_valid(-40000.0, Some(-32768.0)),
            -32767.0
        );
        assert_eq!(
            SampleType::I16.quantize_valid(-32768.2, Some(-32768.0)),
            -32767.0
        );
        assert_eq!(SampleType::U8.quantize_valid(0.3, Some(0.0)), 1.0);
        assert_eq!(SampleType::U8.quantize_valid(300.0, Some(255.0)), 254.0);
        assert_eq!(SampleType::U8.quantize_valid(7.0, Some(0.0)), 7.0);
        assert!(SampleType::U16.quantize_valid(f32::NAN, Some(0.0)).is_nan());
        assert_eq!(SampleType::U8.quantize_valid(0.0, None), 0.0);
        assert_eq!(
            SampleType::F32.quantize_valid(-32768.0, Some(-32768.0)),
            -32768.0
        );
    }

    proptest! {
        #[test]
        fn encode_decode_round_trip(vals in prop::collection::vec(-40000.0f32..70000.0, 0..64),
                                    t in prop::sample::select(vec![SampleType::U8, SampleType::I8, SampleType::U16, SampleType::I16, SampleType::F32])) {
            let q: Vec<f32> = vals.iter().map(|&v| t.quantize(v)).collect();
            let mut bytes = Vec::new();
            t.encode_le(&q, None, &mut bytes);
            prop_assert_eq!(bytes.len(), q.len() * t.size());
            let mut back = vec![0.0; q.len()];
            t.decode_le(&bytes, None, &mut back);
            prop_assert_eq!(back, q);
        }
    }

    #[test]
    fn no_data_sentinel_round_trips_as_nan() {
        let mut bytes = Vec::new();
        SampleType::I16.encode_le(&[1.0, f32::NAN, -3.0], Some(-32768.0), &mut bytes);
        let mut back = [0.0; 3];
        SampleType::I16.decode_le(&bytes, Some(-32768.0), &mut back);
        assert_eq!(back[0], 1.0);
        assert!(back[1].is_nan());
        assert_eq!(back[2], -3.0);
    }
}
