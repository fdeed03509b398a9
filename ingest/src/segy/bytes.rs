//! Byte helpers. Positions are 1-based, as in the SEG-Y standard; callers keep them in range.

use super::Endian;
use anyhow::{anyhow, Result};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

pub(crate) fn read_at(
    file: &File,
    buf: &mut [u8],
    off: u64,
    path: &Path,
    what: &str,
) -> Result<()> {
    file.read_exact_at(buf, off).map_err(|e| {
        anyhow!(
            "{}: reading {what} ({} bytes at byte {off}) failed: {e}",
            path.display(),
            buf.len()
        )
    })
}

pub(crate) fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

fn bytes<const N: usize>(b: &[u8], pos: usize) -> [u8; N] {
    let mut a = [0u8; N];
    a.copy_from_slice(&b[pos - 1..pos - 1 + N]);
    a
}

pub(crate) fn rd_u16(b: &[u8], pos: usize, e: Endian) -> u16 {
    let a = bytes::<2>(b, pos);
    if e == Endian::Big {
        u16::from_be_bytes(a)
    } else {
        u16::from_le_bytes(a)
    }
}

pub(crate) fn rd_i16(b: &[u8], pos: usize, e: Endian) -> i16 {
    rd_u16(b, pos, e) as i16
}

pub(crate) fn rd_u32(b: &[u8], pos: usize, e: Endian) -> u32 {
    let a = bytes::<4>(b, pos);
    if e == Endian::Big {
        u32::from_be_bytes(a)
    } else {
        u32::from_le_bytes(a)
    }
}

pub(crate) fn rd_i32(b: &[u8], pos: usize, e: Endian) -> i32 {
    rd_u32(b, pos, e) as i32
}

pub(crate) fn put_u16(b: &mut [u8], pos: usize, v: u16, e: Endian) {
    let a = if e == Endian::Big {
        v.to_be_bytes()
    } else {
        v.to_le_bytes()
    };
    b[pos - 1..pos + 1].copy_from_slice(&a);
}

pub(crate) fn put_i16(b: &mut [u8], pos: usize, v: i16, e: Endian) {
    put_u16(b, pos, v as u16, e);
}

pub(crate) fn put_i32(b: &mut [u8], pos: usize, v: i32, e: Endian) {
    let a = if e == Endian::Big {
        v.to_be_bytes()
    } else {
        v.to_le_bytes()
    };
    b[pos - 1..pos + 3].copy_from_slice(&a);
}
