//! The scan pass: trace headers only, read in parallel with positional reads.

use super::bytes::{rd_i16, rd_i32};
use super::{Endian, SegyOptions, TRACE_HEADER_LEN};
use anyhow::{anyhow, Result};
use rayon::prelude::*;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

/// The fields of one trace header the reader uses.
#[derive(Copy, Clone, Default)]
pub(crate) struct TraceHdr {
    pub(crate) il: i32,
    pub(crate) xl: i32,
    /// CDP X/Y (bytes 181/185).
    pub(crate) cx: i32,
    pub(crate) cy: i32,
    /// Source X/Y (bytes 73/77).
    pub(crate) sx: i32,
    pub(crate) sy: i32,
    /// Coordinate scalar (byte 71).
    pub(crate) scalar: i16,
    /// Delay recording time (byte 109).
    pub(crate) delay: i16,
    /// Source-receiver offset (byte 37): what tells the traces of a pre-stack gather apart.
    pub(crate) offset: i32,
}

pub(crate) fn scan_headers(
    file: &File,
    path: &Path,
    data_start: u64,
    trace_bytes: u64,
    n: u64,
    opts: &SegyOptions,
    e: Endian,
) -> Result<Vec<TraceHdr>> {
    const CHUNK: usize = 1 << 14;
    let (ib, xb) = (opts.inline_byte as usize, opts.xline_byte as usize);
    let mut hdrs = vec![TraceHdr::default(); n as usize];
    hdrs.par_chunks_mut(CHUNK)
        .enumerate()
        .try_for_each(|(c, chunk)| -> Result<()> {
            let mut h = [0u8; TRACE_HEADER_LEN as usize];
            for (k, out) in chunk.iter_mut().enumerate() {
                let t = (c * CHUNK + k) as u64;
                let off = data_start + t * trace_bytes;
                file.read_exact_at(&mut h, off).map_err(|e| {
                    let p = path.display();
                    anyhow!(
                        "{p}: reading trace {}'s header (240 bytes at byte {off}) failed: {e}",
                        t + 1
                    )
                })?;
                *out = TraceHdr {
                    il: rd_i32(&h, ib, e),
                    xl: rd_i32(&h, xb, e),
                    cx: rd_i32(&h, 181, e),
                    cy: rd_i32(&h, 185, e),
                    sx: rd_i32(&h, 73, e),
                    sy: rd_i32(&h, 77, e),
                    scalar: rd_i16(&h, 71, e),
                    delay: rd_i16(&h, 109, e),
                    offset: rd_i32(&h, 37, e),
                };
            }
            Ok(())
        })?;
    Ok(hdrs)
}
