//! SEG-Y rev 0/1/2 reading (3D cubes, post-stack or one offset or the stack of a pre-stack
//! file) and writing (synthetic test files).
//!
//! [`open`] runs three steps, one module each:
//! * [`header`]: the textual and binary headers: byte order, sample format, revision,
//!   extended textual headers and the trace length (trusting whatever the file size
//!   confirms);
//! * [`scan`]: the 240-byte trace headers only, in parallel;
//! * [`grid`]: the inline/crossline grid, the trace(s) at each node (a pre-stack file is
//!   refused as such unless one offset is chosen or the gathers are stacked) and the grid's
//!   world placement;
//!
//! and [`vertical`] decides whether traces are in time or depth, in which unit, and their
//! first sample and step. The resulting [`SegyVolume`] is a [`GridSource`]: every trace in
//! a requested box is read with one positional read, so memory stays bounded and reads run
//! in parallel without locks.
//!
//! [`SegyWriter`] writes simple rev 1 files (EBCDIC text header, IBM / int16 / IEEE samples;
//! rev 2 for the three-byte integers) for tests and benchmarks.
//!
//! Byte positions in messages and options follow the SEG-Y convention: 1-based within the
//! file (3200-byte textual header, then 400-byte binary header at 3201) or within the
//! 240-byte trace header. Byte *offsets* (0-based, from the start of the file) are named so.
//! Trace numbers in messages are 1-based, in file order.

mod bytes;
mod grid;
mod header;
mod samples;
mod scan;
#[cfg(test)]
mod tests;
mod text;
mod vertical;
mod writer;

use crate::source::GridSource;
use anyhow::{anyhow, bail, Result};
use grid::TraceTable;
use samples::{decode_strided, Format};
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use strata_common::geo::{AffineFit, SurveyGrid};
use strata_common::sample::SampleType;

pub use samples::{f32_to_ibm, ibm_to_f32};
pub use text::{char_to_ebcdic, decode_text_header, ebcdic_to_char, encode_text_header};
pub use vertical::{VerticalAxis, VerticalDomain, VerticalUnit, ASSUMED_TIME};
pub use writer::SegyWriter;

/// Bytes in the textual header (and in each extended textual header).
pub const TEXT_HEADER_LEN: u64 = 3200;
/// Bytes in the binary header.
pub const BINARY_HEADER_LEN: u64 = 400;
/// Bytes in a trace header.
pub const TRACE_HEADER_LEN: u64 = 240;
/// Grids larger than this many times the number of traces are rejected as garbage headers.
pub const MAX_GRID_CELLS_PER_TRACE: u64 = 16;
/// Sample format codes [`open`] can read.
pub const SUPPORTED_FORMATS: &[u16] = &[1, 2, 3, 5, 6, 7, 8, 9, 10, 11, 12, 15, 16];

/// Offset of the binary header in the file.
const BIN: u64 = TEXT_HEADER_LEN;
/// Offset of the first byte after the binary header.
const HEADERS_END: u64 = TEXT_HEADER_LEN + BINARY_HEADER_LEN;
/// At most this many points go into the affine fit (residuals are still checked on all).
const MAX_FIT_POINTS: usize = 1 << 20;
/// The rev 2 end-of-extended-text stanza.
const END_TEXT: &str = "((SEG: EndText))";

/// Byte order of the binary numbers in a SEG-Y file.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Hash)]
pub enum Endian {
    /// Most significant byte first (the SEG-Y standard).
    Big,
    /// Least significant byte first (common from PC software; allowed by rev 2).
    Little,
}

impl Endian {
    fn name(self) -> &'static str {
        match self {
            Endian::Big => "big-endian",
            Endian::Little => "little-endian",
        }
    }
}

/// How to read a SEG-Y file.
#[derive(Clone, Debug, PartialEq)]
pub struct SegyOptions {
    /// Byte order; `None` detects it.
    pub endian: Option<Endian>,
    /// 1-based byte position of the 4-byte inline number in the trace header (189; 9 is a
    /// common alternative).
    pub inline_byte: u32,
    /// 1-based byte position of the 4-byte crossline number in the trace header (193; 21 is
    /// a common alternative).
    pub xline_byte: u32,
    /// Pre-stack files: read only the traces whose offset (trace header byte 37) is this.
    pub offset: Option<i32>,
    /// Pre-stack files: average the traces that share an inline/crossline node.
    pub stack: bool,
    /// Time or depth; `None` decides from the textual headers (see [`vertical`]).
    pub vertical: Option<VerticalDomain>,
    /// Unit of the vertical axis; `None` decides from the headers.
    pub vertical_unit: Option<VerticalUnit>,
    /// Sample step in the vertical unit, overriding the headers.
    pub z_step: Option<f64>,
}

impl Default for SegyOptions {
    fn default() -> Self {
        SegyOptions {
            endian: None,
            inline_byte: 189,
            xline_byte: 193,
            offset: None,
            stack: false,
            vertical: None,
            vertical_unit: None,
            z_step: None,
        }
    }
}

/// What [`open`] found in a file.
#[derive(Clone, Debug, PartialEq)]
pub struct SegyInfo {
    /// The file.
    pub path: PathBuf,
    /// Its size in bytes.
    pub file_len: u64,
    /// The 3200-byte textual header, decoded: 40 lines of up to 80 characters, trailing
    /// blanks removed, joined with `\n`.
    pub text_header: String,
    /// Whether the textual header was EBCDIC (cp037) rather than ASCII.
    pub text_ebcdic: bool,
    /// Number of 3200-byte extended textual headers skipped.
    pub extended_text_headers: u64,
    /// Byte order of the binary headers and samples.
    pub endian: Endian,
    /// Sample format code (binary header byte 3225).
    pub format_code: u16,
    /// Bytes per sample.
    pub bytes_per_sample: u32,
    /// SEG-Y revision (major, minor), from bytes 3501 and 3502.
    pub revision: (u8, u8),
    /// Fixed-length-trace flag (byte 3503).
    pub fixed_length: bool,
    /// Samples per trace (as confirmed by the file size).
    pub samples_per_trace: u32,
    /// The sample-interval field as stored (binary header byte 3217, else trace 1's byte
    /// 117): microseconds for time data, the step × 1000 for depth data.
    pub sample_interval_us: u32,
    /// The delay recording time field (byte 109) of the first trace used, as stored.
    pub delay_ms: f64,
    /// Time or depth, the unit, the first sample and the step, and why.
    pub vertical: VerticalAxis,
    /// Byte offset of the first trace header.
    pub data_start: u64,
    /// Bytes per trace, header included.
    pub trace_bytes: u64,
    /// Number of traces in the file.
    pub trace_count: u64,
    /// Traces that make the grid: all, or those of [`SegyInfo::offset`].
    pub traces_used: u64,
    /// Most traces at one grid node (1 for a post-stack file or one offset of a pre-stack
    /// one).
    pub max_fold: u32,
    /// Distinct offsets (trace header byte 37) in the file.
    pub distinct_offsets: u64,
    /// The offset read (`--offset`), if one was chosen.
    pub offset: Option<i32>,
    /// Whether each node is the mean of its traces (`--stack`, and more than one per node).
    pub stacked: bool,
    /// Grid nodes without a trace (read as no-data).
    pub missing_traces: u64,
    /// Trace-header byte position the inline numbers were read from.
    pub inline_byte: u32,
    /// Trace-header byte position the crossline numbers were read from.
    pub xline_byte: u32,
    /// Which trace-header coordinates placed the grid: `"CDP"` (181/185), `"source"`
    /// (73/77) or `"none"`.
    pub coordinates: &'static str,
    /// The lateral grid and its world placement.
    pub survey: SurveyGrid,
    /// The fit of grid indices to trace coordinates, when there was one.
    pub fit: Option<AffineFit>,
    /// The page-store sample type that holds this file's samples exactly (or `F32`).
    pub sample_type: SampleType,
    /// Things a user should know (header disagreements, missing traces, poor fits).
    pub warnings: Vec<String>,
}

/// A SEG-Y file opened for reading as a 3D grid `[inline index, crossline index, sample]`.
pub struct SegyVolume {
    file: File,
    info: SegyInfo,
    format: Format,
    /// `(i, j)` → the trace(s) there (0-based, file order), node `i·n_xline + j`.
    table: TraceTable,
}

/// Opens a SEG-Y file: reads its headers and scans its trace headers (not its samples).
pub fn open(path: &Path, opts: &SegyOptions) -> Result<SegyVolume> {
    let p = path.display();
    for (what, b) in [("inline", opts.inline_byte), ("crossline", opts.xline_byte)] {
        if !(1..=237).contains(&b) {
            bail!("{p}: {what} byte position {b} is outside the trace header (a 4-byte value needs 1..=237)");
        }
    }
    if opts.offset.is_some() && opts.stack {
        bail!("{p}: --offset and --stack exclude each other: one takes a single offset, the other averages all");
    }
    let mut layout = header::read_layout(path, opts)?;
    let mut warnings = std::mem::take(&mut layout.warnings);
    let hdrs = scan::scan_headers(
        &layout.file,
        path,
        layout.data_start,
        layout.trace_bytes,
        layout.trace_count,
        opts,
        layout.endian,
    )?;
    let grid = grid::fit_grid(
        path,
        &hdrs,
        layout.data_start,
        layout.trace_bytes,
        opts,
        &mut warnings,
    )?;
    // The delay of the first trace used; rev 1 and 2 scale it by bytes 215-216.
    let first = grid.first_used;
    let delay0 = hdrs[first as usize].delay;
    let used = |h: &&scan::TraceHdr| opts.offset.is_none_or(|o| h.offset == o);
    let other_delay = hdrs
        .iter()
        .filter(used)
        .filter(|h| h.delay != delay0)
        .count();
    if other_delay > 0 {
        warnings.push(format!(
            "{other_delay} of {} traces have a delay recording time (byte 109) other than trace {}'s {delay0}; all \
             are read as starting where it does",
            grid.traces_used,
            first + 1
        ));
    }
    let delay_scalar = if matches!(layout.revision.0, 1 | 2) {
        let mut h = [0u8; 2];
        bytes::read_at(
            &layout.file,
            &mut h,
            layout.data_start + first as u64 * layout.trace_bytes + 214,
            path,
            "the time scalar (trace header bytes 215-216)",
        )?;
        bytes::rd_i16(&h, 1, layout.endian)
    } else {
        0
    };
    let vertical = vertical::decide(
        path,
        &layout,
        delay0,
        delay_scalar,
        opts.vertical,
        opts.vertical_unit,
        opts.z_step,
        &mut warnings,
    )?;
    let sample_type = match grid.table {
        TraceTable::Stack { .. } => SampleType::F32,
        TraceTable::One(_) => layout.format.sample_type(),
    };
    let info = SegyInfo {
        path: path.to_path_buf(),
        file_len: layout.file_len,
        text_header: layout.text_header,
        text_ebcdic: layout.text_ebcdic,
        extended_text_headers: layout.n_ext,
        endian: layout.endian,
        format_code: layout.format_code,
        bytes_per_sample: layout.format.size() as u32,
        revision: layout.revision,
        fixed_length: layout.fixed_length,
        samples_per_trace: layout.samples_per_trace,
        sample_interval_us: layout.sample_interval_raw,
        delay_ms: delay0 as f64,
        vertical,
        data_start: layout.data_start,
        trace_bytes: layout.trace_bytes,
        trace_count: layout.trace_count,
        traces_used: grid.traces_used,
        max_fold: grid.max_fold,
        distinct_offsets: grid.distinct_offsets,
        offset: opts.offset,
        stacked: matches!(grid.table, TraceTable::Stack { .. }),
        missing_traces: grid.missing,
        inline_byte: opts.inline_byte,
        xline_byte: opts.xline_byte,
        coordinates: grid.coordinates,
        survey: grid.survey,
        fit: grid.fit,
        sample_type,
        warnings,
    };
    Ok(SegyVolume {
        file: layout.file,
        info,
        format: layout.format,
        table: grid.table,
    })
}

impl SegyVolume {
    /// What the headers said.
    pub fn info(&self) -> &SegyInfo {
        &self.info
    }

    /// z of sample 0 and the step between samples, in [`VerticalAxis::unit`].
    pub fn z_axis(&self) -> (f64, f64) {
        (self.info.vertical.start, self.info.vertical.step)
    }

    /// The trace (0-based, file order) at grid node `(i, j)`, if there is one (the first
    /// of its gather when gathers are stacked).
    pub fn trace_at(&self, i: u64, j: u64) -> Option<u64> {
        let s = &self.info.survey;
        if i >= s.n_inline || j >= s.n_xline {
            return None;
        }
        self.table
            .at((i * s.n_xline + j) as usize)
            .first()
            .map(|&t| t as u64)
    }

    /// Reads all samples of trace `trace` (0-based, file order) into `out`.
    pub fn read_trace(&self, trace: u64, out: &mut [f32]) -> Result<()> {
        let p = self.info.path.display();
        let ns = self.info.samples_per_trace as usize;
        if trace >= self.info.trace_count {
            bail!(
                "{p}: trace {} requested, the file has {}",
                trace + 1,
                self.info.trace_count
            );
        }
        if out.len() != ns {
            bail!(
                "{p}: output for trace {} holds {} samples, expected {ns}",
                trace + 1,
                out.len()
            );
        }
        let mut buf = vec![0u8; ns * self.format.size()];
        let off = self.info.data_start + trace * self.info.trace_bytes + TRACE_HEADER_LEN;
        bytes::read_at(
            &self.file,
            &mut buf,
            off,
            &self.info.path,
            &format!("trace {}'s samples", trace + 1),
        )?;
        decode_strided(self.format, self.info.endian, &buf, out, 0, 1);
        Ok(())
    }
}

impl GridSource for SegyVolume {
    fn dims(&self) -> [u64; 3] {
        let s = &self.info.survey;
        [s.n_inline, s.n_xline, self.info.samples_per_trace as u64]
    }

    fn contiguous_axis(&self) -> usize {
        2
    }

    fn read_box(&self, lo: [u64; 3], size: [u64; 3], out: &mut [f32]) -> Result<()> {
        let p = self.info.path.display();
        let dims = self.dims();
        for a in 0..3 {
            if lo[a].checked_add(size[a]).is_none_or(|e| e > dims[a]) {
                bail!(
                    "{p}: box {lo:?} + {size:?} does not fit in the volume's dimensions {dims:?}"
                );
            }
        }
        let total = size[0] as u128 * size[1] as u128 * size[2] as u128;
        if out.len() as u128 != total {
            bail!(
                "{p}: output buffer holds {} samples, the box {size:?} needs {total}",
                out.len()
            );
        }
        if total == 0 {
            return Ok(());
        }
        let (s0, s1, s2) = (size[0] as usize, size[1] as usize, size[2] as usize);
        let plane = s0 * s1;
        let bps = self.format.size() as u64;
        let mut buf = vec![0u8; s2 * bps as usize];
        let n_xline = dims[1];
        let mut gather = Vec::new();
        // Inline-major loops match the usual inline-sorted trace order.
        for ii in 0..s0 {
            for jj in 0..s1 {
                let node = (lo[0] + ii as u64) * n_xline + lo[1] + jj as u64;
                let start = jj * s0 + ii;
                let traces = self.table.at(node as usize);
                let read = |t: u32, buf: &mut [u8]| -> Result<()> {
                    let off = self.info.data_start
                        + t as u64 * self.info.trace_bytes
                        + TRACE_HEADER_LEN
                        + lo[2] * bps;
                    self.file.read_exact_at(buf, off).map_err(|e| {
                        anyhow!(
                            "{p}: reading samples {}..{} of trace {} ({} bytes at byte {off}) failed: {e}",
                            lo[2],
                            lo[2] + size[2],
                            t as u64 + 1,
                            buf.len()
                        )
                    })
                };
                match traces {
                    [] => out[start..]
                        .iter_mut()
                        .step_by(plane)
                        .take(s2)
                        .for_each(|v| *v = f32::NAN),
                    [t] => {
                        read(*t, &mut buf)?;
                        decode_strided(self.format, self.info.endian, &buf, out, start, plane);
                    }
                    gathered => {
                        // The stack: the mean of the gather's traces.
                        gather.resize(s2, 0.0f32);
                        let mut sum = vec![0.0f64; s2];
                        for &t in gathered {
                            read(t, &mut buf)?;
                            decode_strided(self.format, self.info.endian, &buf, &mut gather, 0, 1);
                            for (a, &v) in sum.iter_mut().zip(&gather) {
                                *a += v as f64;
                            }
                        }
                        let n = gathered.len() as f64;
                        for (o, a) in out[start..].iter_mut().step_by(plane).zip(&sum) {
                            *o = (*a / n) as f32;
                        }
                    }
                }
            }
        }
        Ok(())
    }
}
