//! Sample formats: the codes SEG-Y defines, IBM floats, decoding into f32.

use super::Endian;
use strata_common::sample::SampleType;

/// Converts an IBM System/360 single-precision float (sign, base-16 exponent biased by 64,
/// 24-bit fraction) to the nearest `f32` (exact for normalized values in `f32` range;
/// beyond it, ±infinity or a rounded subnormal / zero).
pub fn ibm_to_f32(bits: u32) -> f32 {
    let neg = bits >> 31 == 1;
    let frac = bits & 0x00FF_FFFF;
    let mag = if frac == 0 {
        0.0
    } else {
        let exp = ((bits >> 24) & 0x7F) as i32;
        // value = frac · 2^(4·(exp − 64) − 24); the power lies in [−280, 228], exact in f64.
        let e2 = 4 * (exp - 64) - 24;
        (frac as f64 * f64::from_bits(((e2 + 1023) as u64) << 52)) as f32
    };
    if neg {
        -mag
    } else {
        mag
    }
}

/// Converts an `f32` to the nearest normalized IBM float. NaN becomes 0, ±infinity the
/// largest IBM magnitude.
pub fn f32_to_ibm(v: f32) -> u32 {
    if v.is_nan() {
        return 0;
    }
    let sign = if v.is_sign_negative() { 0x8000_0000 } else { 0 };
    let a = (v as f64).abs();
    if a == 0.0 {
        return sign;
    }
    if a.is_infinite() {
        return sign | 0x7FFF_FFFF;
    }
    let bits = a.to_bits();
    let e = ((bits >> 52) & 0x7FF) as i32 - 1023; // every f32 is normal as f64
    let m = (bits & ((1u64 << 52) - 1)) | (1u64 << 52); // a = m · 2^(e − 52) = (m / 2^53) · 2^(e + 1)
    let p = e + 1;
    let mut q = (p + 3).div_euclid(4); // a = (m / 2^53) · 2^(p − 4q) · 16^q, fraction in [1/16, 1)
    let s = 29 + (4 * q - p) as u32;
    let mut f = (m + (1u64 << (s - 1))) >> s;
    if f >= 1 << 24 {
        f >>= 4;
        q += 1;
    }
    let exp = q + 64;
    if exp > 127 {
        return sign | 0x7FFF_FFFF;
    }
    if exp < 0 {
        return sign;
    }
    sign | ((exp as u32) << 24) | f as u32
}

#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub(crate) enum Format {
    Ibm,
    I32,
    I16,
    /// Rev 2 code 7: three-byte two's-complement integer.
    I24,
    /// Rev 2 code 15: three-byte unsigned integer.
    U24,
    F32,
    F64,
    I8,
    I64,
    U32,
    U16,
    U64,
    U8,
}

impl Format {
    pub(crate) fn from_code(c: u16) -> Option<Format> {
        Some(match c {
            1 => Format::Ibm,
            2 => Format::I32,
            3 => Format::I16,
            5 => Format::F32,
            6 => Format::F64,
            7 => Format::I24,
            15 => Format::U24,
            8 => Format::I8,
            9 => Format::I64,
            10 => Format::U32,
            11 => Format::U16,
            12 => Format::U64,
            16 => Format::U8,
            _ => return None,
        })
    }
    pub(crate) fn size(self) -> usize {
        match self {
            Format::I8 | Format::U8 => 1,
            Format::I16 | Format::U16 => 2,
            Format::I24 | Format::U24 => 3,
            Format::Ibm | Format::I32 | Format::F32 | Format::U32 => 4,
            Format::F64 | Format::I64 | Format::U64 => 8,
        }
    }
    pub(crate) fn sample_type(self) -> SampleType {
        match self {
            Format::I16 => SampleType::I16,
            Format::I8 => SampleType::I8,
            Format::U16 => SampleType::U16,
            Format::U8 => SampleType::U8,
            _ => SampleType::F32,
        }
    }
}

/// Every format code defined by SEG-Y rev 2 (used to detect the byte order).
pub(crate) fn is_segy_format(c: u16) -> bool {
    matches!(c, 1..=12 | 15 | 16)
}

pub(crate) fn supported_list() -> &'static str {
    "1 (4-byte IBM float), 2 (int32), 3 (int16), 5 (4-byte IEEE float), 6 (8-byte IEEE float), 7 (int24), \
     8 (int8), 9 (int64), 10 (uint32), 11 (uint16), 12 (uint64), 15 (uint24), 16 (uint8)"
}

/// Decodes the samples in `src` into `out[start]`, `out[start + stride]`, …
pub(crate) fn decode_strided(
    fmt: Format,
    endian: Endian,
    src: &[u8],
    out: &mut [f32],
    start: usize,
    stride: usize,
) {
    let big = endian == Endian::Big;
    macro_rules! run {
        ($n:literal, $ty:ty, $conv:expr) => {{
            let conv = $conv;
            let dst = out[start..].iter_mut().step_by(stride);
            for (o, c) in dst.zip(src.chunks_exact($n)) {
                let mut a = [0u8; $n];
                a.copy_from_slice(c);
                let v = if big {
                    <$ty>::from_be_bytes(a)
                } else {
                    <$ty>::from_le_bytes(a)
                };
                *o = conv(v);
            }
        }};
    }
    match fmt {
        Format::Ibm => run!(4, u32, ibm_to_f32),
        Format::I32 => run!(4, i32, |v: i32| v as f32),
        Format::I16 => run!(2, i16, |v: i16| v as f32),
        Format::F32 => run!(4, f32, |v: f32| v),
        Format::F64 => run!(8, f64, |v: f64| v as f32),
        Format::I8 => run!(1, i8, |v: i8| v as f32),
        Format::I64 => run!(8, i64, |v: i64| v as f32),
        Format::U32 => run!(4, u32, |v: u32| v as f32),
        Format::U16 => run!(2, u16, |v: u16| v as f32),
        Format::U64 => run!(8, u64, |v: u64| v as f32),
        Format::U8 => run!(1, u8, |v: u8| v as f32),
        // Three-byte integers (every one is exact in f32's 24-bit significand).
        Format::I24 | Format::U24 => {
            let dst = out[start..].iter_mut().step_by(stride);
            for (o, c) in dst.zip(src.chunks_exact(3)) {
                let (hi, mid, lo) = if big {
                    (c[0], c[1], c[2])
                } else {
                    (c[2], c[1], c[0])
                };
                let u = u32::from(hi) << 16 | u32::from(mid) << 8 | u32::from(lo);
                *o = if fmt == Format::I24 {
                    // Sign-extend bit 23.
                    ((u << 8) as i32 >> 8) as f32
                } else {
                    u as f32
                };
            }
        }
    }
}
