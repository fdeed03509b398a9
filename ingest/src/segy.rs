//! SEG-Y rev 0/1/2 reading (post-stack 3D cubes) and writing (synthetic test files).
//!
//! [`open`] reads the textual and binary headers, works out the byte order, the sample
//! format and the trace length (trusting whatever the file size confirms), then scans only
//! the 240-byte trace headers to build the inline/crossline grid and its world placement.
//! The resulting [`SegyVolume`] is a [`GridSource`]: every trace in a requested box is read
//! with one positional read, so memory stays bounded and reads run in parallel without locks.
//!
//! [`SegyWriter`] writes simple rev 1 files (EBCDIC text header, IBM / int16 / IEEE samples)
//! for tests and benchmarks.
//!
//! Byte positions in messages and options follow the SEG-Y convention: 1-based within the
//! file (3200-byte textual header, then 400-byte binary header at 3201) or within the
//! 240-byte trace header. Byte *offsets* (0-based, from the start of the file) are named so.
//! Trace numbers in messages are 1-based, in file order.

use crate::source::GridSource;
use anyhow::{anyhow, bail, Result};
use rayon::prelude::*;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use strata_common::geo::{fit_affine2, Affine2, AffineFit, SurveyGrid};
use strata_common::sample::SampleType;

/// Bytes in the textual header (and in each extended textual header).
pub const TEXT_HEADER_LEN: u64 = 3200;
/// Bytes in the binary header.
pub const BINARY_HEADER_LEN: u64 = 400;
/// Bytes in a trace header.
pub const TRACE_HEADER_LEN: u64 = 240;
/// Grids larger than this many times the number of traces are rejected as garbage headers.
pub const MAX_GRID_CELLS_PER_TRACE: u64 = 16;
/// Sample format codes [`open`] can read.
pub const SUPPORTED_FORMATS: &[u16] = &[1, 2, 3, 5, 6, 8, 9, 10, 11, 12, 16];

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
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SegyOptions {
    /// Byte order; `None` detects it.
    pub endian: Option<Endian>,
    /// 1-based byte position of the 4-byte inline number in the trace header (189; 9 is a
    /// common alternative).
    pub inline_byte: u32,
    /// 1-based byte position of the 4-byte crossline number in the trace header (193; 21 is
    /// a common alternative).
    pub xline_byte: u32,
}

impl Default for SegyOptions {
    fn default() -> Self {
        SegyOptions {
            endian: None,
            inline_byte: 189,
            xline_byte: 193,
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
    /// Sample interval in microseconds (milliseconds ×1000 for time data).
    pub sample_interval_us: u32,
    /// Time of sample 0 in ms (trace header delay recording time, byte 109).
    pub delay_ms: f64,
    /// Byte offset of the first trace header.
    pub data_start: u64,
    /// Bytes per trace, header included.
    pub trace_bytes: u64,
    /// Number of traces in the file.
    pub trace_count: u64,
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
    /// `(i, j)` → trace number (0-based, file order), `i·n_xline + j`; `u32::MAX` = missing.
    trace_at: Vec<u32>,
}

/// Opens a SEG-Y file: reads its headers and scans its trace headers (not its samples).
pub fn open(path: &Path, opts: &SegyOptions) -> Result<SegyVolume> {
    let p = path.display();
    for (what, b) in [("inline", opts.inline_byte), ("crossline", opts.xline_byte)] {
        if !(1..=237).contains(&b) {
            bail!("{p}: {what} byte position {b} is outside the trace header (a 4-byte value needs 1..=237)");
        }
    }
    let file = File::open(path).map_err(|e| anyhow!("{p}: cannot open: {e}"))?;
    let file_len = file
        .metadata()
        .map_err(|e| anyhow!("{p}: cannot stat: {e}"))?
        .len();
    if file_len < HEADERS_END {
        bail!(
            "{p}: not a SEG-Y file: it has {file_len} bytes, but the textual and binary headers alone need {HEADERS_END}"
        );
    }
    let mut head = vec![0u8; HEADERS_END as usize];
    read_at(&file, &mut head, 0, path, "the textual and binary headers")?;
    let (text_header, text_ebcdic) = decode_text_header(&head[..TEXT_HEADER_LEN as usize]);
    let bin = &head[BIN as usize..];
    let mut warnings = Vec::new();

    // Byte order: explicit option, then the rev 2 byte-order constant, then the format code.
    let code_be = u16::from_be_bytes([bin[24], bin[25]]);
    let code_le = u16::from_le_bytes([bin[24], bin[25]]);
    let endian = match opts.endian {
        Some(e) => e,
        None => match bin[96..100] {
            [1, 2, 3, 4] => Endian::Big,
            [4, 3, 2, 1] => Endian::Little,
            _ if is_segy_format(code_be) => Endian::Big,
            _ if is_segy_format(code_le) => Endian::Little,
            _ => bail!(
                "{p}: byte offset 3224 (binary header byte 3225): sample format code reads {code_be} big-endian \
                 and {code_le} little-endian, neither is a SEG-Y format code; supported: {}",
                supported_list()
            ),
        },
    };
    let format_code = rd_u16(bin, 25, endian);
    let format = Format::from_code(format_code).ok_or_else(|| {
        anyhow!(
            "{p}: byte offset 3224 (binary header byte 3225): sample format code {format_code} ({}) is not supported; \
             supported: {}",
            endian.name(),
            supported_list()
        )
    })?;
    let bps = format.size() as u64;

    // Revision (bytes 3501/3502 as single bytes; tolerate a little-endian u16 0x0100).
    let mut revision = (bin[300], bin[301]);
    if endian == Endian::Little && revision.0 == 0 && matches!(revision.1, 1 | 2) {
        revision = (revision.1, 0);
    }
    // Bytes 3503.. are only defined from rev 1 on; older files may hold anything there.
    let rev_defined = matches!(revision.0, 1 | 2);
    if revision.0 > 2 {
        warnings.push(format!(
            "binary header bytes 3501-3502 hold revision {}.{}, which does not exist; read as rev 0 (bytes 3503-3510 \
             ignored)",
            revision.0, revision.1
        ));
    }
    let fixed_length = rd_i16(bin, 303, endian) != 0;
    if rev_defined && !fixed_length {
        warnings.push(
            "binary header (byte 3503) says trace lengths may vary; reading every trace with the same length".into(),
        );
    }
    if revision.0 == 2 {
        let extra = rd_u32(bin, 307, endian);
        if extra != 0 {
            bail!(
                "{p}: binary header byte 3507 says traces carry up to {extra} additional 240-byte trace headers (rev 2); \
                 this is not supported"
            );
        }
    }

    // Extended textual headers.
    let n_ext_raw = rd_i16(bin, 305, endian);
    let (n_ext, data_start) = match n_ext_raw {
        0 => (0u64, HEADERS_END),
        _ if !rev_defined => {
            warnings.push(format!(
                "binary header byte 3505 holds {n_ext_raw} but the file is not SEG-Y rev 1 or 2, so it has no \
                 extended textual headers; ignored"
            ));
            (0, HEADERS_END)
        }
        -1 => {
            let marker_ascii = END_TEXT.as_bytes().to_vec();
            let marker_ebcdic = encode_ebcdic_str(END_TEXT);
            let mut block = vec![0u8; TEXT_HEADER_LEN as usize];
            let mut k = 0u64;
            loop {
                let off = HEADERS_END + k * TEXT_HEADER_LEN;
                if off + TEXT_HEADER_LEN > file_len {
                    bail!(
                        "{p}: binary header byte 3505 is -1 (extended textual headers end with '{END_TEXT}'), but no \
                         3200-byte block up to the end of the file ({file_len} bytes) contains that stanza"
                    );
                }
                read_at(&file, &mut block, off, path, "an extended textual header")?;
                k += 1;
                if contains(&block, &marker_ascii) || contains(&block, &marker_ebcdic) {
                    break (k, off + TEXT_HEADER_LEN);
                }
            }
        }
        n if n > 0 => (n as u64, HEADERS_END + n as u64 * TEXT_HEADER_LEN),
        n => bail!(
            "{p}: binary header byte 3505: number of extended textual headers is {n}; expected 0 or more, or -1"
        ),
    };
    if data_start > file_len {
        bail!(
            "{p}: truncated: binary header byte 3505 announces {n_ext} extended textual headers, so traces start at \
             byte {data_start}, but the file has {file_len} bytes"
        );
    }
    let remain = file_len - data_start;
    if remain == 0 {
        bail!("{p}: the file has no traces (it ends at byte {file_len}, where the first trace header would start)");
    }

    // Trace length: binary header vs first trace header, decided by the file size.
    let mut ns_bin = rd_u16(bin, 21, endian) as u64;
    let mut ns_bin_byte = 3221;
    if ns_bin == 0 {
        let ext = rd_u32(bin, 3269 - 3200, endian) as u64;
        if ext != 0 {
            ns_bin = ext;
            ns_bin_byte = 3269;
        }
    }
    let mut first = [0u8; TRACE_HEADER_LEN as usize];
    let have_first = remain >= TRACE_HEADER_LEN;
    if have_first {
        read_at(&file, &mut first, data_start, path, "trace 1's header")?;
    }
    let ns_tr = if have_first {
        rd_u16(&first, 115, endian) as u64
    } else {
        0
    };
    let fits = |ns: u64| ns > 0 && remain % (TRACE_HEADER_LEN + ns * bps) == 0;
    let layout = |ns: u64| {
        let tb = TRACE_HEADER_LEN + ns * bps;
        format!("{data_start} + {} x (240 + {ns} x {bps})", remain / tb)
    };
    let truncation = |ns: u64| {
        let tb = TRACE_HEADER_LEN + ns * bps;
        let full = remain / tb;
        let at = data_start + full * tb;
        format!(
            "truncated: trace {} at byte {at} needs {tb} bytes (240 + {ns} samples x {bps}), file has {} bytes from \
             there ({file_len} in all)",
            full + 1,
            file_len - at
        )
    };
    let ns = if fits(ns_bin) {
        if ns_tr != 0 && ns_tr != ns_bin {
            let why = if fits(ns_tr) {
                format!("both fit the file size ({file_len} bytes); the binary header wins a tie")
            } else {
                format!(
                    "the file size {file_len} = {} bytes confirms it and {ns_tr} does not fit",
                    layout(ns_bin)
                )
            };
            warnings.push(format!(
                "samples per trace: binary header (byte {ns_bin_byte}) says {ns_bin}, trace 1's header (byte 115) \
                 says {ns_tr}; trusted the binary header because {why}"
            ));
        }
        ns_bin
    } else if fits(ns_tr) {
        warnings.push(format!(
            "samples per trace: binary header (byte {ns_bin_byte}) says {ns_bin}, trace 1's header (byte 115) says \
             {ns_tr}; trusted the trace header because the file size {file_len} = {} bytes confirms it{}",
            layout(ns_tr),
            if ns_bin == 0 { String::new() } else { format!(" and {ns_bin} does not fit") }
        ));
        ns_tr
    } else if ns_bin == 0 && ns_tr == 0 {
        bail!("{p}: samples per trace is 0 in the binary header (bytes 3221 and 3269) and in trace 1's header (byte 115)");
    } else if ns_bin != 0 && ns_tr != 0 && ns_bin != ns_tr {
        bail!(
            "{p}: samples per trace: binary header (byte {ns_bin_byte}) says {ns_bin}, trace 1's header (byte 115) says \
             {ns_tr}, and neither fits the file size: {remain} bytes of traces after byte {data_start} are not a \
             multiple of {} or of {} bytes per trace; if the binary header is right, the file is {}",
            TRACE_HEADER_LEN + ns_bin * bps,
            TRACE_HEADER_LEN + ns_tr * bps,
            truncation(ns_bin)
        );
    } else {
        // One candidate, and it leaves a partial trace at the end.
        bail!("{p}: {}", truncation(ns_bin.max(ns_tr)));
    };
    let samples_per_trace =
        u32::try_from(ns).map_err(|_| anyhow!("{p}: {ns} samples per trace is too many"))?;
    let trace_bytes = TRACE_HEADER_LEN + ns * bps;
    let trace_count = remain / trace_bytes;
    if trace_count >= u32::MAX as u64 {
        bail!(
            "{p}: {trace_count} traces is more than this reader supports ({})",
            u32::MAX - 1
        );
    }

    // Sample interval: binary header, else trace header.
    let mut sample_interval_us = rd_u16(bin, 17, endian) as u32;
    if sample_interval_us == 0 {
        let tr = rd_u16(&first, 117, endian) as u32;
        if tr != 0 {
            warnings.push(format!(
                "sample interval is 0 in the binary header (byte 3217); using trace 1's header (byte 117): {tr} us"
            ));
            sample_interval_us = tr;
        } else {
            warnings.push(
                "sample interval is 0 in the binary header (byte 3217) and trace 1's header (byte 117); assuming 1 ms"
                    .into(),
            );
            sample_interval_us = 1000;
        }
    }

    // Scan pass: trace headers only.
    let hdrs = scan_headers(
        &file,
        path,
        data_start,
        trace_bytes,
        trace_count,
        opts,
        endian,
    )?;
    let delay0 = hdrs[0].delay;
    let delay_ms = delay0 as f64;
    let other_delay = hdrs.iter().filter(|h| h.delay != delay0).count();
    if other_delay > 0 {
        warnings.push(format!(
            "{other_delay} of {trace_count} traces have a delay recording time (byte 109) other than trace 1's \
             {delay0} ms; all are read as starting at {delay0} ms"
        ));
    }

    // Geometry.
    let (il0, il_step, n_inline) = axis_of(hdrs.iter().map(|h| h.il));
    let (xl0, xl_step, n_xline) = axis_of(hdrs.iter().map(|h| h.xl));
    let cells = n_inline as u128 * n_xline as u128;
    if cells > MAX_GRID_CELLS_PER_TRACE as u128 * trace_count as u128 {
        let (il1, xl1) = (
            il0 + (n_inline as i64 - 1) * il_step,
            xl0 + (n_xline as i64 - 1) * xl_step,
        );
        bail!(
            "{p}: inline numbers (trace byte {}) {il0}..{il1} step {il_step} and crossline numbers (trace byte {}) \
             {xl0}..{xl1} step {xl_step} span a {n_inline} x {n_xline} grid, more than {MAX_GRID_CELLS_PER_TRACE} \
             times the {trace_count} traces; the numbers are probably not at these byte positions (common choices: \
             189/193 or 9/21)",
            opts.inline_byte,
            opts.xline_byte
        );
    }
    let cells = cells as usize;
    let mut trace_at = vec![u32::MAX; cells];
    for (t, h) in hdrs.iter().enumerate() {
        let i = ((h.il as i64 - il0) / il_step) as usize;
        let j = ((h.xl as i64 - xl0) / xl_step) as usize;
        let slot = &mut trace_at[i * n_xline as usize + j];
        if *slot != u32::MAX {
            let a = *slot as u64;
            bail!(
                "{p}: duplicate trace for inline {} crossline {}: trace {} at byte {} and trace {} at byte {}",
                h.il,
                h.xl,
                a + 1,
                data_start + a * trace_bytes,
                t + 1,
                data_start + t as u64 * trace_bytes
            );
        }
        *slot = t as u32;
    }
    let missing_traces = cells as u64 - trace_count;
    if missing_traces > 0 {
        warnings.push(format!(
            "{missing_traces} of {cells} grid nodes ({n_inline} inlines x {n_xline} crosslines) have no trace; \
             they read as no-data"
        ));
    }

    // World placement.
    let use_cdp = hdrs.iter().any(|h| h.cx != 0 || h.cy != 0);
    let use_src = !use_cdp && hdrs.iter().any(|h| h.sx != 0 || h.sy != 0);
    let coordinates = if use_cdp {
        "CDP"
    } else if use_src {
        warnings.push(
            "CDP X/Y (trace bytes 181/185) are all zero; placed the grid with source X/Y (73/77)"
                .into(),
        );
        "source"
    } else {
        "none"
    };
    let world = |h: &TraceHdr| {
        let (x, y) = if use_cdp { (h.cx, h.cy) } else { (h.sx, h.sy) };
        let s = h.scalar as f64;
        let f = |v: i32| {
            let v = v as f64;
            if s < 0.0 {
                v / -s
            } else if s > 0.0 {
                v * s
            } else {
                v
            }
        };
        [f(x), f(y)]
    };
    let grid_of = |h: &TraceHdr| {
        [
            ((h.il as i64 - il0) / il_step) as f64,
            ((h.xl as i64 - xl0) / xl_step) as f64,
        ]
    };
    let mut fit = None;
    if coordinates == "none" {
        warnings.push(
            "trace coordinates (CDP 181/185 and source 73/77) are all zero; world placement is 1 unit per grid index"
                .into(),
        );
    } else {
        let stride = hdrs.len().div_ceil(MAX_FIT_POINTS).max(1);
        let pts: Vec<([f64; 2], [f64; 2])> = hdrs
            .iter()
            .step_by(stride)
            .map(|h| (grid_of(h), world(h)))
            .collect();
        match fit_affine2(&pts).filter(|f| is_usable_map(&f.map)) {
            None => warnings.push(format!(
                "cannot place the grid in the world from the {coordinates} coordinates ({n_inline} inlines x \
                 {n_xline} crosslines; a single line or coincident points); world placement is 1 unit per grid index"
            )),
            Some(f) => {
                // Residuals over every trace.
                let (mut s2, mut mx) = (0.0f64, 0.0f64);
                for h in &hdrs {
                    let a = f.map.apply(grid_of(h));
                    let w = world(h);
                    let d = (a[0] - w[0]).hypot(a[1] - w[1]);
                    s2 += d * d;
                    mx = mx.max(d);
                }
                let fit_all = AffineFit { map: f.map, rms_residual: (s2 / hdrs.len() as f64).sqrt(), max_residual: mx };
                let r = &f.map.rows;
                let bin = (r[0][0].hypot(r[1][0])).min(r[0][1].hypot(r[1][1]));
                if fit_all.max_residual > 0.25 * bin {
                    warnings.push(format!(
                        "trace coordinates depart from a regular grid by up to {:.3} (rms {:.3}) with bins of {:.3}",
                        fit_all.max_residual, fit_all.rms_residual, bin
                    ));
                }
                fit = Some(fit_all);
            }
        }
    }
    let to_world = fit.map(|f| f.map).unwrap_or(Affine2::IDENTITY);
    let survey = SurveyGrid {
        inline0: il0 as f64,
        inline_step: il_step as f64,
        n_inline,
        xline0: xl0 as f64,
        xline_step: xl_step as f64,
        n_xline,
        to_world,
    };

    let info = SegyInfo {
        path: path.to_path_buf(),
        file_len,
        text_header,
        text_ebcdic,
        extended_text_headers: n_ext,
        endian,
        format_code,
        bytes_per_sample: bps as u32,
        revision,
        fixed_length,
        samples_per_trace,
        sample_interval_us,
        delay_ms,
        data_start,
        trace_bytes,
        trace_count,
        missing_traces,
        inline_byte: opts.inline_byte,
        xline_byte: opts.xline_byte,
        coordinates,
        survey,
        fit,
        sample_type: format.sample_type(),
        warnings,
    };
    Ok(SegyVolume {
        file,
        info,
        format,
        trace_at,
    })
}

impl SegyVolume {
    /// What the headers said.
    pub fn info(&self) -> &SegyInfo {
        &self.info
    }

    /// Time of sample 0 and the sample interval, in ms.
    pub fn z_axis(&self) -> (f64, f64) {
        (
            self.info.delay_ms,
            self.info.sample_interval_us as f64 / 1000.0,
        )
    }

    /// The trace (0-based, file order) at grid node `(i, j)`, if there is one.
    pub fn trace_at(&self, i: u64, j: u64) -> Option<u64> {
        let s = &self.info.survey;
        if i >= s.n_inline || j >= s.n_xline {
            return None;
        }
        let t = self.trace_at[(i * s.n_xline + j) as usize];
        (t != u32::MAX).then_some(t as u64)
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
        read_at(
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
        // Inline-major loops match the usual inline-sorted trace order.
        for ii in 0..s0 {
            for jj in 0..s1 {
                let node = (lo[0] + ii as u64) * n_xline + lo[1] + jj as u64;
                let start = jj * s0 + ii;
                let t = self.trace_at[node as usize];
                if t == u32::MAX {
                    out[start..]
                        .iter_mut()
                        .step_by(plane)
                        .take(s2)
                        .for_each(|v| *v = f32::NAN);
                    continue;
                }
                let off = self.info.data_start
                    + t as u64 * self.info.trace_bytes
                    + TRACE_HEADER_LEN
                    + lo[2] * bps;
                self.file.read_exact_at(&mut buf, off).map_err(|e| {
                    anyhow!(
                        "{p}: reading samples {}..{} of trace {} ({} bytes at byte {off}) failed: {e}",
                        lo[2],
                        lo[2] + size[2],
                        t as u64 + 1,
                        buf.len()
                    )
                })?;
                decode_strided(self.format, self.info.endian, &buf, out, start, plane);
            }
        }
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------
// Writing.

/// Writes a simple rev 1 SEG-Y file trace by trace (for synthetic tests and benchmarks).
pub struct SegyWriter {
    path: PathBuf,
    out: BufWriter<File>,
    n_samples: u32,
    dt_us: u16,
    delay_ms: i16,
    format: u16,
    endian: Endian,
    traces: u64,
    buf: Vec<u8>,
}

impl SegyWriter {
    /// Creates `path` and writes the EBCDIC textual header (from `text`: up to 40 lines of
    /// up to 80 characters) and a rev 1 binary header (rev 2 for the three-byte formats).
    /// `format` is 1 (IBM float), 3 (int16), 5 (IEEE float), 7 (int24) or 15 (uint24);
    /// integers are rounded and clamped to their range, NaN written as 0.
    pub fn create(
        path: &Path,
        text: &str,
        n_samples: u32,
        dt_us: u32,
        delay_ms: i16,
        format: u16,
        endian: Endian,
    ) -> Result<Self> {
        let p = path.display();
        if !matches!(format, 1 | 3 | 5 | 7 | 15) {
            bail!("{p}: cannot write sample format {format}; the writer supports 1 (IBM float), 3 (int16), 5 (IEEE float), 7 (int24), 15 (uint24)");
        }
        if !(1..=u16::MAX as u32).contains(&n_samples) {
            bail!("{p}: {n_samples} samples per trace; a rev 1 file holds 1..=65535");
        }
        let dt = u16::try_from(dt_us)
            .map_err(|_| anyhow!("{p}: sample interval {dt_us} us does not fit in 16 bits"))?;
        let file = File::create(path).map_err(|e| anyhow!("{p}: cannot create: {e}"))?;
        let mut out = BufWriter::with_capacity(1 << 20, file);
        let mut head = encode_text_header(text);
        let mut bin = [0u8; BINARY_HEADER_LEN as usize];
        put_i32(&mut bin, 1, 1, endian); // job id
        put_i32(&mut bin, 5, 1, endian); // line number
        put_i32(&mut bin, 9, 1, endian); // reel number
        put_u16(&mut bin, 17, dt, endian);
        put_u16(&mut bin, 19, dt, endian);
        put_u16(&mut bin, 21, n_samples as u16, endian);
        put_u16(&mut bin, 23, n_samples as u16, endian);
        put_u16(&mut bin, 25, format, endian);
        put_u16(&mut bin, 27, 1, endian); // ensemble fold
        put_u16(&mut bin, 29, 4, endian); // sorting: post-stack
        put_u16(&mut bin, 55, 1, endian); // metres
                                          // Rev 1.0; the three-byte formats are rev 2.0.
        bin[300] = if matches!(format, 7 | 15) { 2 } else { 1 };
        bin[301] = 0;
        put_u16(&mut bin, 303, 1, endian); // fixed-length traces
        put_u16(&mut bin, 305, 0, endian); // no extended textual headers
        head.extend_from_slice(&bin);
        out.write_all(&head)
            .map_err(|e| anyhow!("{p}: write failed at byte 0: {e}"))?;
        Ok(SegyWriter {
            path: path.to_path_buf(),
            out,
            n_samples,
            dt_us: dt,
            delay_ms,
            format,
            endian,
            traces: 0,
            buf: Vec::new(),
        })
    }

    /// Appends one trace. Coordinates are stored in centimetres (scalar -100) as both CDP
    /// and source X/Y; inline/crossline at 189/193 and 9/21.
    pub fn write_trace(
        &mut self,
        inline: i32,
        xline: i32,
        cdp_x: f64,
        cdp_y: f64,
        samples: &[f32],
    ) -> Result<()> {
        let p = self.path.display();
        let e = self.endian;
        if samples.len() != self.n_samples as usize {
            bail!(
                "{p}: trace {} has {} samples, the file has {} per trace",
                self.traces + 1,
                samples.len(),
                self.n_samples
            );
        }
        let cm = |v: f64| -> Result<i32> {
            let c = (v * 100.0).round();
            if !(c.is_finite() && c >= i32::MIN as f64 && c <= i32::MAX as f64) {
                bail!(
                    "{p}: trace {}: coordinate {v} does not fit in a 4-byte centimetre value",
                    self.traces + 1
                );
            }
            Ok(c as i32)
        };
        let (x, y) = (cm(cdp_x)?, cm(cdp_y)?);
        let seq = (self.traces + 1).min(i32::MAX as u64) as i32;
        let h = &mut self.buf;
        h.clear();
        h.resize(TRACE_HEADER_LEN as usize, 0);
        put_i32(h, 1, seq, e); // sequence in line
        put_i32(h, 5, seq, e); // sequence in file
        put_i32(h, 9, inline, e);
        put_i32(h, 13, 1, e);
        put_i32(h, 21, xline, e);
        put_u16(h, 29, 1, e); // seismic data
        put_i16(h, 71, -100, e);
        put_i32(h, 73, x, e);
        put_i32(h, 77, y, e);
        put_u16(h, 89, 1, e); // length units
        put_i16(h, 109, self.delay_ms, e);
        put_u16(h, 115, self.n_samples as u16, e);
        put_u16(h, 117, self.dt_us, e);
        put_i32(h, 181, x, e);
        put_i32(h, 185, y, e);
        put_i32(h, 189, inline, e);
        put_i32(h, 193, xline, e);
        let big = e == Endian::Big;
        for &v in samples {
            let b: [u8; 4];
            match self.format {
                3 => {
                    let q = if v.is_nan() {
                        0
                    } else {
                        v.round().clamp(-32768.0, 32767.0) as i16
                    };
                    h.extend_from_slice(&if big {
                        q.to_be_bytes()
                    } else {
                        q.to_le_bytes()
                    });
                    continue;
                }
                7 | 15 => {
                    let (lo, hi) = if self.format == 7 {
                        (-8_388_608.0, 8_388_607.0)
                    } else {
                        (0.0, 16_777_215.0)
                    };
                    let q = if v.is_nan() {
                        0
                    } else {
                        v.round().clamp(lo, hi) as i32
                    };
                    let w = (q as u32).to_be_bytes();
                    let three = [w[1], w[2], w[3]];
                    h.extend_from_slice(&if big { three } else { [w[3], w[2], w[1]] });
                    continue;
                }
                1 => b = f32_to_ibm(v).to_be_bytes(),
                _ => b = v.to_bits().to_be_bytes(),
            }
            if big {
                h.extend_from_slice(&b);
            } else {
                h.extend_from_slice(&[b[3], b[2], b[1], b[0]]);
            }
        }
        let at = HEADERS_END + self.traces * h.len() as u64;
        self.out.write_all(h).map_err(|err| {
            anyhow!(
                "{p}: writing trace {} at byte {at} failed: {err}",
                self.traces + 1
            )
        })?;
        self.traces += 1;
        Ok(())
    }

    /// Flushes the file.
    pub fn finish(mut self) -> Result<()> {
        let p = self.path.display();
        self.out
            .flush()
            .map_err(|e| anyhow!("{p}: flush failed: {e}"))?;
        self.out
            .get_ref()
            .sync_all()
            .map_err(|e| anyhow!("{p}: sync failed: {e}"))?;
        Ok(())
    }
}

// ---------------------------------------------------------------------------------------
// Text headers.

/// cp037 (EBCDIC, US/Canada) to ISO-8859-1 (= the first 256 Unicode code points).
const CP037_TO_LATIN1: [u8; 256] = [
    0x00, 0x01, 0x02, 0x03, 0x9C, 0x09, 0x86, 0x7F, 0x97, 0x8D, 0x8E, 0x0B, 0x0C, 0x0D, 0x0E,
    0x0F, //
    0x10, 0x11, 0x12, 0x13, 0x9D, 0x85, 0x08, 0x87, 0x18, 0x19, 0x92, 0x8F, 0x1C, 0x1D, 0x1E,
    0x1F, //
    0x80, 0x81, 0x82, 0x83, 0x84, 0x0A, 0x17, 0x1B, 0x88, 0x89, 0x8A, 0x8B, 0x8C, 0x05, 0x06,
    0x07, //
    0x90, 0x91, 0x16, 0x93, 0x94, 0x95, 0x96, 0x04, 0x98, 0x99, 0x9A, 0x9B, 0x14, 0x15, 0x9E,
    0x1A, //
    0x20, 0xA0, 0xE2, 0xE4, 0xE0, 0xE1, 0xE3, 0xE5, 0xE7, 0xF1, 0xA2, 0x2E, 0x3C, 0x28, 0x2B,
    0x7C, //
    0x26, 0xE9, 0xEA, 0xEB, 0xE8, 0xED, 0xEE, 0xEF, 0xEC, 0xDF, 0x21, 0x24, 0x2A, 0x29, 0x3B,
    0xAC, //
    0x2D, 0x2F, 0xC2, 0xC4, 0xC0, 0xC1, 0xC3, 0xC5, 0xC7, 0xD1, 0xA6, 0x2C, 0x25, 0x5F, 0x3E,
    0x3F, //
    0xF8, 0xC9, 0xCA, 0xCB, 0xC8, 0xCD, 0xCE, 0xCF, 0xCC, 0x60, 0x3A, 0x23, 0x40, 0x27, 0x3D,
    0x22, //
    0xD8, 0x61, 0x62, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68, 0x69, 0xAB, 0xBB, 0xF0, 0xFD, 0xFE,
    0xB1, //
    0xB0, 0x6A, 0x6B, 0x6C, 0x6D, 0x6E, 0x6F, 0x70, 0x71, 0x72, 0xAA, 0xBA, 0xE6, 0xB8, 0xC6,
    0xA4, //
    0xB5, 0x7E, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7A, 0xA1, 0xBF, 0xD0, 0xDD, 0xDE,
    0xAE, //
    0x5E, 0xA3, 0xA5, 0xB7, 0xA9, 0xA7, 0xB6, 0xBC, 0xBD, 0xBE, 0x5B, 0x5D, 0xAF, 0xA8, 0xB4,
    0xD7, //
    0x7B, 0x41, 0x42, 0x43, 0x44, 0x45, 0x46, 0x47, 0x48, 0x49, 0xAD, 0xF4, 0xF6, 0xF2, 0xF3,
    0xF5, //
    0x7D, 0x4A, 0x4B, 0x4C, 0x4D, 0x4E, 0x4F, 0x50, 0x51, 0x52, 0xB9, 0xFB, 0xFC, 0xF9, 0xFA,
    0xFF, //
    0x5C, 0xF7, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5A, 0xB2, 0xD4, 0xD6, 0xD2, 0xD3,
    0xD5, //
    0x30, 0x31, 0x32, 0x33, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39, 0xB3, 0xDB, 0xDC, 0xD9, 0xDA,
    0x9F, //
];

/// ISO-8859-1 to cp037 (the inverse permutation).
const LATIN1_TO_CP037: [u8; 256] = {
    let mut inv = [0u8; 256];
    let mut i = 0;
    while i < 256 {
        inv[CP037_TO_LATIN1[i] as usize] = i as u8;
        i += 1;
    }
    inv
};

/// Decodes an EBCDIC (cp037) byte to a character (ISO-8859-1 repertoire).
pub fn ebcdic_to_char(b: u8) -> char {
    CP037_TO_LATIN1[b as usize] as char
}

/// Encodes a character as EBCDIC (cp037); characters outside ISO-8859-1 become `?`.
pub fn char_to_ebcdic(c: char) -> u8 {
    match u8::try_from(c as u32) {
        Ok(l) => LATIN1_TO_CP037[l as usize],
        Err(_) => LATIN1_TO_CP037[b'?' as usize],
    }
}

fn encode_ebcdic_str(s: &str) -> Vec<u8> {
    s.chars().map(char_to_ebcdic).collect()
}

/// Decodes a textual header, detecting EBCDIC (cp037) or ASCII (read as ISO-8859-1) by
/// which interpretation gives more letters, digits and blanks. Returns the text (80-byte
/// cards as lines, control characters as blanks, trailing blanks removed) and whether it
/// was EBCDIC.
pub fn decode_text_header(bytes: &[u8]) -> (String, bool) {
    let plain = |c: u8| c.is_ascii_alphanumeric() || c == b' ';
    let ascii_score = bytes.iter().filter(|&&b| plain(b)).count();
    let ebcdic_score = bytes
        .iter()
        .filter(|&&b| plain(CP037_TO_LATIN1[b as usize]))
        .count();
    let ebcdic = ebcdic_score > ascii_score;
    let mut text = String::with_capacity(bytes.len() + bytes.len() / 80);
    for card in bytes.chunks(80) {
        let line: String = card
            .iter()
            .map(|&b| {
                let l = if ebcdic {
                    CP037_TO_LATIN1[b as usize]
                } else {
                    b
                };
                if l < 0x20 || (0x7F..0xA0).contains(&l) {
                    ' '
                } else {
                    l as char
                }
            })
            .collect();
        text.push_str(line.trim_end());
        text.push('\n');
    }
    let keep = text.trim_end().len();
    text.truncate(keep);
    (text, ebcdic)
}

/// Encodes `text` as a 3200-byte EBCDIC textual header: its first 40 lines, each cut or
/// padded to 80 characters.
pub fn encode_text_header(text: &str) -> Vec<u8> {
    let blank = char_to_ebcdic(' ');
    let mut out = vec![blank; TEXT_HEADER_LEN as usize];
    for (n, line) in text.lines().take(40).enumerate() {
        for (k, c) in line.chars().take(80).enumerate() {
            out[n * 80 + k] = char_to_ebcdic(c);
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// Samples.

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
enum Format {
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
    fn from_code(c: u16) -> Option<Format> {
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
    fn size(self) -> usize {
        match self {
            Format::I8 | Format::U8 => 1,
            Format::I16 | Format::U16 => 2,
            Format::I24 | Format::U24 => 3,
            Format::Ibm | Format::I32 | Format::F32 | Format::U32 => 4,
            Format::F64 | Format::I64 | Format::U64 => 8,
        }
    }
    fn sample_type(self) -> SampleType {
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
fn is_segy_format(c: u16) -> bool {
    matches!(c, 1..=12 | 15 | 16)
}

fn supported_list() -> &'static str {
    "1 (4-byte IBM float), 2 (int32), 3 (int16), 5 (4-byte IEEE float), 6 (8-byte IEEE float), 7 (int24), \
     8 (int8), 9 (int64), 10 (uint32), 11 (uint16), 12 (uint64), 15 (uint24), 16 (uint8)"
}

/// Decodes the samples in `src` into `out[start]`, `out[start + stride]`, …
fn decode_strided(
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

// ---------------------------------------------------------------------------------------
// Trace headers and geometry.

#[derive(Copy, Clone, Default)]
struct TraceHdr {
    il: i32,
    xl: i32,
    cx: i32,
    cy: i32,
    sx: i32,
    sy: i32,
    scalar: i16,
    delay: i16,
}

fn scan_headers(
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
                };
            }
            Ok(())
        })?;
    Ok(hdrs)
}

/// First value, step (gcd of the gaps between distinct values) and count of a line axis.
fn axis_of(values: impl Iterator<Item = i32>) -> (i64, i64, u64) {
    let mut v: Vec<i32> = values.collect();
    v.sort_unstable();
    v.dedup();
    let (first, last) = (v[0] as i64, v[v.len() - 1] as i64);
    let step = v
        .windows(2)
        .fold(0i64, |g, w| gcd(g, w[1] as i64 - w[0] as i64));
    let step = if step == 0 { 1 } else { step };
    (first, step, ((last - first) / step) as u64 + 1)
}

fn gcd(mut a: i64, mut b: i64) -> i64 {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a.abs()
}

/// Whether a grid-to-world map has finite coefficients and two independent, non-zero bins.
fn is_usable_map(m: &Affine2) -> bool {
    let r = &m.rows;
    let (a, b, c, d) = (r[0][0], r[0][1], r[1][0], r[1][1]);
    let (li, lj) = (a.hypot(c), b.hypot(d));
    r.iter().flatten().all(|v| v.is_finite())
        && li > 0.0
        && lj > 0.0
        && (a * d - b * c).abs() > 1e-6 * li * lj
}

// ---------------------------------------------------------------------------------------
// Byte helpers. Positions are 1-based, as in the SEG-Y standard; callers keep them in range.

fn read_at(file: &File, buf: &mut [u8], off: u64, path: &Path, what: &str) -> Result<()> {
    file.read_exact_at(buf, off).map_err(|e| {
        anyhow!(
            "{}: reading {what} ({} bytes at byte {off}) failed: {e}",
            path.display(),
            buf.len()
        )
    })
}

fn contains(hay: &[u8], needle: &[u8]) -> bool {
    hay.windows(needle.len()).any(|w| w == needle)
}

fn bytes<const N: usize>(b: &[u8], pos: usize) -> [u8; N] {
    let mut a = [0u8; N];
    a.copy_from_slice(&b[pos - 1..pos - 1 + N]);
    a
}

fn rd_u16(b: &[u8], pos: usize, e: Endian) -> u16 {
    let a = bytes::<2>(b, pos);
    if e == Endian::Big {
        u16::from_be_bytes(a)
    } else {
        u16::from_le_bytes(a)
    }
}

fn rd_i16(b: &[u8], pos: usize, e: Endian) -> i16 {
    rd_u16(b, pos, e) as i16
}

fn rd_u32(b: &[u8], pos: usize, e: Endian) -> u32 {
    let a = bytes::<4>(b, pos);
    if e == Endian::Big {
        u32::from_be_bytes(a)
    } else {
        u32::from_le_bytes(a)
    }
}

fn rd_i32(b: &[u8], pos: usize, e: Endian) -> i32 {
    rd_u32(b, pos, e) as i32
}

fn put_u16(b: &mut [u8], pos: usize, v: u16, e: Endian) {
    let a = if e == Endian::Big {
        v.to_be_bytes()
    } else {
        v.to_le_bytes()
    };
    b[pos - 1..pos + 1].copy_from_slice(&a);
}

fn put_i16(b: &mut [u8], pos: usize, v: i16, e: Endian) {
    put_u16(b, pos, v as u16, e);
}

fn put_i32(b: &mut [u8], pos: usize, v: i32, e: Endian) {
    let a = if e == Endian::Big {
        v.to_be_bytes()
    } else {
        v.to_le_bytes()
    };
    b[pos - 1..pos + 3].copy_from_slice(&a);
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU64, Ordering};

    const F3_BE: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/real/seismic/f3_segyio/f3.sgy"
    );
    const F3_LE: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/real/seismic/f3_segyio/f3-lsb.sgy"
    );
    const F3_IBM: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/data/real/seismic/f3_opendtect_very_small/F3_very_small.sgy"
    );

    /// A temporary file removed on drop.
    struct Tmp(PathBuf);
    impl Drop for Tmp {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(&self.0);
        }
    }
    fn tmp(name: &str) -> Tmp {
        static N: AtomicU64 = AtomicU64::new(0);
        let n = N.fetch_add(1, Ordering::Relaxed);
        Tmp(std::env::temp_dir().join(format!(
            "strata-segy-test-{}-{n}-{name}",
            std::process::id()
        )))
    }
    fn write_bytes(name: &str, bytes: &[u8]) -> Tmp {
        let t = tmp(name);
        std::fs::write(&t.0, bytes).unwrap();
        t
    }

    fn read_all(v: &SegyVolume) -> Vec<f32> {
        let d = v.dims();
        let mut out = vec![0.0; (d[0] * d[1] * d[2]) as usize];
        v.read_box([0; 3], d, &mut out).unwrap();
        out
    }

    fn stats(v: &[f32]) -> (f64, f64, f64, f64) {
        let n = v.len() as f64;
        let mean = v.iter().map(|&x| x as f64).sum::<f64>() / n;
        let var = v.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / n;
        let min = v.iter().fold(f32::INFINITY, |a, &b| a.min(b)) as f64;
        let max = v.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b)) as f64;
        (min, max, mean, var.sqrt())
    }

    fn err_of(r: Result<SegyVolume>) -> String {
        match r {
            Ok(_) => panic!("expected an error"),
            Err(e) => format!("{e}"),
        }
    }

    #[test]
    fn three_byte_integer_formats_read_exactly_in_both_byte_orders() {
        // Rev 2 formats 7 (int24) and 15 (uint24), which segyio cannot read: the extremes,
        // both sides of zero and values past 16 bits come back exactly.
        let dir = tempfile::TempDir::new().unwrap();
        for (format, values) in [
            (
                7u16,
                vec![
                    -8_388_608.0f32,
                    8_388_607.0,
                    -1.0,
                    0.0,
                    1.0,
                    -65_537.0,
                    123_456.0,
                ],
            ),
            (
                15u16,
                vec![
                    0.0f32,
                    16_777_215.0,
                    1.0,
                    65_536.0,
                    8_388_608.0,
                    255.0,
                    70_000.0,
                ],
            ),
        ] {
            for endian in [Endian::Big, Endian::Little] {
                let p = dir.path().join(format!("f{format}-{endian:?}.sgy"));
                let n = values.len() as u32;
                let mut w =
                    SegyWriter::create(&p, "C 1 int24", n, 2000, 0, format, endian).unwrap();
                for i in 0..2 {
                    for j in 0..3 {
                        // Each trace its own rotation of the values.
                        let mut t = values.clone();
                        t.rotate_left(i * 3 + j);
                        w.write_trace(10 + i as i32, 20 + j as i32, i as f64, j as f64, &t)
                            .unwrap();
                    }
                }
                w.finish().unwrap();
                let v = open(&p, &SegyOptions::default()).unwrap();
                assert_eq!(v.info().format_code, format);
                assert_eq!(v.info().bytes_per_sample, 3);
                assert_eq!(v.info().endian, endian);
                let mut out = vec![0.0f32; values.len()];
                for i in 0..2u64 {
                    for j in 0..3u64 {
                        let t = v.trace_at(i, j).unwrap();
                        v.read_trace(t, &mut out).unwrap();
                        let mut want = values.clone();
                        want.rotate_left((i * 3 + j) as usize);
                        assert_eq!(out, want, "format {format} {endian:?} trace ({i}, {j})");
                    }
                }
                // The strided path the store builder reads bricks through: a box of the
                // whole cube against the traces.
                let d = v.dims();
                let mut cube = vec![0.0f32; (d[0] * d[1] * d[2]) as usize];
                v.read_box([0, 0, 0], d, &mut cube).unwrap();
                for i in 0..d[0] {
                    for j in 0..d[1] {
                        let t = v.trace_at(i, j).unwrap();
                        v.read_trace(t, &mut out).unwrap();
                        for k in 0..d[2] {
                            let got = cube[((k * d[1] + j) * d[0] + i) as usize];
                            assert_eq!(got, out[k as usize], "box ({i}, {j}, {k})");
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn ibm_known_values() {
        assert_eq!(ibm_to_f32(0x4264_0000), 100.0);
        assert_eq!(ibm_to_f32(0xC276_A000), -118.625);
        assert_eq!(ibm_to_f32(0x0000_0000), 0.0);
        assert_eq!(ibm_to_f32(0x4110_0000), 1.0);
        assert_eq!(ibm_to_f32(0xC110_0000), -1.0);
        assert_eq!(ibm_to_f32(0x4080_0000), 0.5);
        assert_eq!(ibm_to_f32(0x4010_0000), 1.0 / 16.0);
        assert_eq!(ibm_to_f32(0x3F10_0000), 1.0 / 256.0);
        // Largest IBM value overflows f32; the smallest underflows to zero.
        assert_eq!(ibm_to_f32(0x7FFF_FFFF), f32::INFINITY);
        assert_eq!(ibm_to_f32(0x0010_0000), 0.0);
        // Unnormalized fractions decode too.
        assert_eq!(ibm_to_f32(0x4200_6400), 100.0 / 256.0);
        assert_eq!(f32_to_ibm(100.0), 0x4264_0000);
        assert_eq!(f32_to_ibm(-118.625), 0xC276_A000);
        assert_eq!(f32_to_ibm(0.0), 0);
        assert_eq!(f32_to_ibm(1.0), 0x4110_0000);
    }

    #[test]
    fn ibm_round_trip() {
        // Values with at most 21 significant bits round-trip exactly; the rest within 2^-21.
        let mut s = 0x1234_5678_9abc_def0u64;
        let mut next = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            s
        };
        for k in -100_000i32..100_000 {
            let v = k as f32 * 0.125;
            assert_eq!(ibm_to_f32(f32_to_ibm(v)), v, "{v}");
        }
        let mut n = 0;
        while n < 200_000 {
            let v = f32::from_bits(next() as u32);
            if !v.is_normal() {
                continue;
            }
            n += 1;
            let back = ibm_to_f32(f32_to_ibm(v));
            let rel = ((back as f64 - v as f64) / v as f64).abs();
            assert!(rel <= 2f64.powi(-21), "{v:e} -> {back:e} ({rel:e})");
            let exact = f32::from_bits(v.to_bits() & !0x7); // 21 significant bits
            assert_eq!(ibm_to_f32(f32_to_ibm(exact)), exact, "{exact:e}");
        }
    }

    #[test]
    fn cp037_table_is_a_permutation_and_text_round_trips() {
        let mut seen = [false; 256];
        for b in 0..=255u8 {
            let c = ebcdic_to_char(b);
            assert!(!seen[c as usize]);
            seen[c as usize] = true;
            assert_eq!(char_to_ebcdic(c), b);
        }
        assert_eq!(ebcdic_to_char(0xC3), 'C');
        assert_eq!(ebcdic_to_char(0x40), ' ');
        assert_eq!(ebcdic_to_char(0xF1), '1');
        assert_eq!(ebcdic_to_char(0x81), 'a');
        let text = "C 1 Hello (SEG-Y) world: x=1.5; ~ø\nC 2 second line";
        let enc = encode_text_header(text);
        assert_eq!(enc.len(), 3200);
        assert_eq!(decode_text_header(&enc), (text.to_string(), true));
        let mut ascii = vec![b' '; 3200];
        ascii[..10].copy_from_slice(b"C01 hello!");
        ascii[80..86].copy_from_slice(b"C02 ok");
        assert_eq!(
            decode_text_header(&ascii),
            ("C01 hello!\nC02 ok".to_string(), false)
        );
    }

    #[test]
    fn f3_big_and_little_endian_agree() {
        let be = open(Path::new(F3_BE), &SegyOptions::default()).unwrap();
        let le = open(Path::new(F3_LE), &SegyOptions::default()).unwrap();
        assert_eq!(be.info().endian, Endian::Big);
        assert_eq!(le.info().endian, Endian::Little);
        for v in [&be, &le] {
            let i = v.info();
            assert_eq!(v.dims(), [23, 18, 75]);
            assert_eq!(v.contiguous_axis(), 2);
            assert_eq!(i.format_code, 3);
            assert_eq!(i.sample_type, SampleType::I16);
            assert_eq!(i.revision, (1, 0));
            assert!(i.fixed_length);
            assert_eq!(i.samples_per_trace, 75);
            assert_eq!(i.sample_interval_us, 4000);
            assert_eq!(i.trace_count, 414);
            assert_eq!(i.missing_traces, 0);
            assert_eq!(i.file_len, 165_060);
            assert_eq!(i.data_start, 3600);
            assert_eq!(i.trace_bytes, 240 + 75 * 2);
            assert_eq!(v.z_axis(), (4.0, 4.0));
            assert!(i.text_ebcdic);
            assert!(
                i.text_header
                    .starts_with("C 1 Cropped F3 2-byte integer data set\n"),
                "{}",
                i.text_header
            );
            assert!(i.text_header.contains("C 7     crosslines: 875 .. 892"));
            let s = &i.survey;
            assert_eq!((s.inline0, s.inline_step, s.n_inline), (111.0, 1.0, 23));
            assert_eq!((s.xline0, s.xline_step, s.n_xline), (875.0, 1.0, 18));
            // The 462-vs-75 quirk is resolved by the file size, with a warning.
            assert_eq!(i.warnings.len(), 1, "{:?}", i.warnings);
            let w = &i.warnings[0];
            assert!(
                w.contains("462") && w.contains("75") && w.contains("trusted the binary header"),
                "{w}"
            );
            // Coordinates: CDP with scalar -10; first trace at (620197.2, 6074232.9).
            assert_eq!(i.coordinates, "CDP");
            let fit = i.fit.unwrap();
            let w00 = s.to_world.apply([0.0, 0.0]);
            assert!(
                (w00[0] - 620197.2).abs() <= fit.max_residual + 1e-6,
                "{w00:?} {fit:?}"
            );
            assert!(
                (w00[1] - 6074232.9).abs() <= fit.max_residual + 1e-6,
                "{w00:?} {fit:?}"
            );
            assert!(fit.max_residual < 1.0, "{fit:?}");
            let mut t = vec![0.0; 75];
            v.read_trace(0, &mut t).unwrap();
            let all = read_all(v);
            assert_eq!(
                &t[..],
                &all.iter().step_by(23 * 18).copied().collect::<Vec<_>>()[..]
            );
        }
        let (a, b) = (read_all(&be), read_all(&le));
        assert_eq!(a, b);
        let (min, max, mean, std) = stats(&a);
        assert_eq!((min, max), (-10239.0, 10827.0));
        assert!((mean - 25.13).abs() < 0.01, "{mean}");
        assert!((std - 2160.21).abs() / 2160.21 < 1e-4, "{std}");
        // Every trace identical in both files, trace by trace.
        let mut tb = vec![0.0; 75];
        let mut tl = vec![0.0; 75];
        for t in 0..414 {
            be.read_trace(t, &mut tb).unwrap();
            le.read_trace(t, &mut tl).unwrap();
            assert_eq!(tb, tl, "trace {t}");
        }
    }

    #[test]
    fn f3_sub_boxes_match_the_full_read() {
        let v = open(Path::new(F3_BE), &SegyOptions::default()).unwrap();
        let all = read_all(&v);
        let d = v.dims();
        for (lo, size) in [
            ([0, 0, 0], [1, 1, 1]),
            ([3, 5, 10], [7, 4, 20]),
            ([22, 17, 74], [1, 1, 1]),
            ([0, 2, 0], [23, 1, 75]),
        ] {
            let mut out = vec![0.0; (size[0] * size[1] * size[2]) as usize];
            v.read_box(lo, size, &mut out).unwrap();
            for z in 0..size[2] {
                for y in 0..size[1] {
                    for x in 0..size[0] {
                        let o = ((z * size[1] + y) * size[0] + x) as usize;
                        let a = (((lo[2] + z) * d[1] + lo[1] + y) * d[0] + lo[0] + x) as usize;
                        assert_eq!(out[o], all[a]);
                    }
                }
            }
        }
        // Boxes outside the volume or a wrong buffer size are errors, not panics.
        let mut out = vec![0.0; 8];
        assert!(v.read_box([22, 0, 0], [2, 2, 2], &mut out).is_err());
        assert!(v.read_box([0, 0, 0], [2, 2, 3], &mut out).is_err());
        assert!(v.read_box([u64::MAX, 0, 0], [2, 2, 2], &mut out).is_err());
        fn assert_sync<T: Sync>(_: &T) {}
        assert_sync(&v);
    }

    #[test]
    fn f3_forced_wrong_endian_is_a_clear_error() {
        let opts = SegyOptions {
            endian: Some(Endian::Little),
            ..Default::default()
        };
        let e = err_of(open(Path::new(F3_BE), &opts));
        assert!(
            e.contains("f3.sgy") && e.contains("3224") && e.contains("768"),
            "{e}"
        );
        let opts = SegyOptions {
            endian: Some(Endian::Big),
            ..Default::default()
        };
        assert_eq!(
            open(Path::new(F3_BE), &opts).unwrap().info().endian,
            Endian::Big
        );
    }

    #[test]
    fn f3_ibm_opendtect() {
        let v = open(Path::new(F3_IBM), &SegyOptions::default()).unwrap();
        let i = v.info();
        assert_eq!(v.dims(), [11, 11, 463]);
        assert_eq!(i.endian, Endian::Big);
        assert_eq!(i.format_code, 1);
        assert_eq!(i.sample_type, SampleType::F32);
        assert_eq!(i.revision, (1, 0));
        assert_eq!(v.z_axis(), (0.0, 4.0));
        assert!(!i.text_ebcdic);
        assert!(
            i.text_header.contains("C02  Survey: 'F3 Demo'"),
            "{}",
            i.text_header
        );
        assert!(i.text_header.contains("C40  END TEXTUAL HEADER"));
        assert!(i.warnings.is_empty(), "{:?}", i.warnings);
        let s = &i.survey;
        assert_eq!((s.inline0, s.inline_step, s.n_inline), (200.0, 1.0, 11));
        assert_eq!((s.xline0, s.xline_step, s.n_xline), (400.0, 1.0, 11));
        let w00 = s.to_world.apply([0.0, 0.0]);
        assert!(
            (w00[0] - 608264.7).abs() < 1.0 && (w00[1] - 6076125.2).abs() < 1.0,
            "{w00:?}"
        );
        let (min, max, mean, std) = stats(&read_all(&v));
        assert_eq!((min, max), (-16032.0, 10745.0));
        assert!((mean - 1.368).abs() / 1.368 < 1e-3, "{mean}");
        assert!((std - 2404.42).abs() / 2404.42 < 1e-3, "{std}");
    }

    /// Writes a rotated UTM grid (inline step 2, crossline step 3) with some traces left out.
    fn synth(format: u16, endian: Endian) -> (Tmp, Vec<(u64, u64)>) {
        let t = tmp(&format!("synth-{format}-{endian:?}.sgy"));
        let (ni, nx, ns) = (7u64, 9u64, 50usize);
        let skip = [(1, 1), (2, 5), (3, 3), (6, 0), (6, 1)];
        let text = "C 1 Synthetic test survey\nC 2 rotated 30 degrees";
        let mut w = SegyWriter::create(&t.0, text, ns as u32, 2000, 100, format, endian).unwrap();
        let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
        // Crossline-major order: the reader must not assume inline sorting.
        for j in 0..nx {
            for i in 0..ni {
                if skip.contains(&(i, j)) {
                    continue;
                }
                let (fi, fj) = (i as f64, j as f64);
                let x = 612_345.6 + 25.0 * c * fi - 12.5 * s * fj;
                let y = 6_078_901.2 + 25.0 * s * fi + 12.5 * c * fj;
                let samples: Vec<f32> = (0..ns).map(|k| synth_value(i, j, k as u64)).collect();
                w.write_trace(1000 + 2 * i as i32, 2000 + 3 * j as i32, x, y, &samples)
                    .unwrap();
            }
        }
        w.finish().unwrap();
        (t, skip.to_vec())
    }

    fn synth_value(i: u64, j: u64, k: u64) -> f32 {
        ((i * 31 + j * 17 + k * 7) % 200) as f32 * 13.7 - 1000.0 + 0.3
    }

    #[test]
    fn writer_reader_round_trip() {
        for format in [1u16, 3, 5] {
            for endian in [Endian::Big, Endian::Little] {
                let (t, skip) = synth(format, endian);
                let v = open(&t.0, &SegyOptions::default()).unwrap();
                let i = v.info();
                assert_eq!(v.dims(), [7, 9, 50]);
                assert_eq!(i.endian, endian);
                assert_eq!(i.format_code, format);
                assert_eq!(
                    i.sample_type,
                    if format == 3 {
                        SampleType::I16
                    } else {
                        SampleType::F32
                    }
                );
                assert_eq!(i.revision, (1, 0));
                assert_eq!(v.z_axis(), (100.0, 2.0));
                assert!(i.text_ebcdic);
                assert_eq!(
                    i.text_header,
                    "C 1 Synthetic test survey\nC 2 rotated 30 degrees"
                );
                assert_eq!(i.trace_count, 58);
                assert_eq!(i.missing_traces, 5);
                assert_eq!(i.warnings.len(), 1, "{:?}", i.warnings);
                assert!(i.warnings[0].contains("5 of 63"), "{:?}", i.warnings);
                let s = &i.survey;
                assert_eq!((s.inline0, s.inline_step, s.n_inline), (1000.0, 2.0, 7));
                assert_eq!((s.xline0, s.xline_step, s.n_xline), (2000.0, 3.0, 9));
                assert_eq!(s.index_of(1004.0, 2009.0), Some((2, 3)));
                let fit = i.fit.unwrap();
                assert!(fit.max_residual < 0.01, "{fit:?}"); // centimetre rounding only
                let (c, sn) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
                let w = s.to_world.apply([4.0, 6.0]);
                let truth = [
                    612_345.6 + 100.0 * c - 75.0 * sn,
                    6_078_901.2 + 100.0 * sn + 75.0 * c,
                ];
                assert!(
                    (w[0] - truth[0]).abs() < 0.01 && (w[1] - truth[1]).abs() < 0.01,
                    "{w:?} {truth:?}"
                );
                let all = read_all(&v);
                for k in 0..50u64 {
                    for jj in 0..9u64 {
                        for ii in 0..7u64 {
                            let got = all[((k * 9 + jj) * 7 + ii) as usize];
                            if skip.contains(&(ii, jj)) {
                                assert!(got.is_nan());
                                assert_eq!(v.trace_at(ii, jj), None);
                                continue;
                            }
                            let want = synth_value(ii, jj, k);
                            match format {
                                3 => assert_eq!(got, want.round()),
                                5 => assert_eq!(got, want),
                                _ => assert!(
                                    (got - want).abs() <= want.abs() * 2f32.powi(-20),
                                    "{got} {want}"
                                ),
                            }
                        }
                    }
                }
            }
        }
    }

    #[test]
    fn alternate_line_number_bytes() {
        let (t, _) = synth(5, Endian::Big);
        let a = open(&t.0, &SegyOptions::default()).unwrap();
        let b = open(
            &t.0,
            &SegyOptions {
                inline_byte: 9,
                xline_byte: 21,
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(a.info().survey, b.info().survey);
        assert_eq!(
            read_all(&a).iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            read_all(&b).iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
        let e = err_of(open(
            &t.0,
            &SegyOptions {
                inline_byte: 239,
                ..Default::default()
            },
        ));
        assert!(e.contains("239"), "{e}");
        // Trace sequence numbers (bytes 1 and 5) as line numbers: every trace on one
        // inline and crossline pair → duplicates.
        let e = err_of(open(
            &t.0,
            &SegyOptions {
                inline_byte: 13,
                xline_byte: 13,
                ..Default::default()
            },
        ));
        assert!(
            e.contains("duplicate")
                && e.contains("trace 1 at byte 3600")
                && e.contains("trace 2 at byte"),
            "{e}"
        );
    }

    #[test]
    fn extended_textual_headers_are_skipped() {
        let (t, _) = synth(5, Endian::Little);
        let base = std::fs::read(&t.0).unwrap();
        let want = read_all(&open(&t.0, &SegyOptions::default()).unwrap());
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        // Two extended headers, counted.
        let mut f = base[..3600].to_vec();
        put_i16(&mut f, 3505, 2, Endian::Little);
        f.extend(encode_text_header("extended 1"));
        f.extend(encode_text_header("extended 2"));
        f.extend_from_slice(&base[3600..]);
        let t2 = write_bytes("ext2.sgy", &f);
        let v = open(&t2.0, &SegyOptions::default()).unwrap();
        assert_eq!(v.info().extended_text_headers, 2);
        assert_eq!(v.info().data_start, 3600 + 6400);
        assert_eq!(bits(&read_all(&v)), bits(&want));
        // -1: scan to the EndText stanza (ASCII here).
        let mut f = base[..3600].to_vec();
        put_i16(&mut f, 3505, -1, Endian::Little);
        f.extend(vec![b' '; 3200]);
        let mut last = vec![b' '; 3200];
        last[..END_TEXT.len()].copy_from_slice(END_TEXT.as_bytes());
        f.extend(last);
        f.extend_from_slice(&base[3600..]);
        let t3 = write_bytes("ext-1.sgy", &f);
        let v = open(&t3.0, &SegyOptions::default()).unwrap();
        assert_eq!(v.info().extended_text_headers, 2);
        assert_eq!(bits(&read_all(&v)), bits(&want));
        // -1 without a stanza.
        let mut f = base.clone();
        put_i16(&mut f, 3505, -1, Endian::Little);
        let t4 = write_bytes("ext-none.sgy", &f);
        let e = err_of(open(&t4.0, &SegyOptions::default()));
        assert!(e.contains("ext-none.sgy") && e.contains("EndText"), "{e}");
    }

    #[test]
    fn byte_order_constant_decides() {
        // A big-endian file whose format code would also read as valid little-endian is
        // impossible, so check that the constant wins over an explicit-looking format code:
        // a little-endian file marked with the constant still reads as little-endian.
        let (t, _) = synth(3, Endian::Little);
        let mut f = std::fs::read(&t.0).unwrap();
        f[3296..3300].copy_from_slice(&0x0102_0304u32.to_le_bytes());
        let t2 = write_bytes("bo.sgy", &f);
        assert_eq!(
            open(&t2.0, &SegyOptions::default()).unwrap().info().endian,
            Endian::Little
        );
        // The constant written big-endian on the same file forces big-endian: format code
        // then reads 0x0300 and is rejected.
        f[3296..3300].copy_from_slice(&0x0102_0304u32.to_be_bytes());
        let t3 = write_bytes("bo2.sgy", &f);
        let e = err_of(open(&t3.0, &SegyOptions::default()));
        assert!(e.contains("bo2.sgy") && e.contains("768"), "{e}");
    }

    #[test]
    fn truncated_files_are_errors() {
        let base = std::fs::read(F3_BE).unwrap();
        let t = write_bytes("trunc.sgy", &base[..base.len() - 100]);
        let e = err_of(open(&t.0, &SegyOptions::default()));
        // Trace 414 starts at 3600 + 413 * 390 = 164670.
        assert!(
            e.contains("trunc.sgy")
                && e.contains("truncated")
                && e.contains("trace 414 at byte 164670"),
            "{e}"
        );
        assert!(
            e.contains("needs 390 bytes") && e.contains("file has 290"),
            "{e}"
        );
        assert!(!e.contains('\n'));
        // Headers only; then less than the headers; then empty.
        for (n, what) in [
            (3600usize, "no traces"),
            (3000, "not a SEG-Y"),
            (0, "not a SEG-Y"),
        ] {
            let t = write_bytes("short.sgy", &base[..n]);
            let e = err_of(open(&t.0, &SegyOptions::default()));
            assert!(e.contains("short.sgy") && e.contains(what), "{e}");
        }
        let e = err_of(open(
            Path::new("/nonexistent/dir/x.sgy"),
            &SegyOptions::default(),
        ));
        assert!(e.contains("/nonexistent/dir/x.sgy"), "{e}");
    }

    #[test]
    fn sample_count_disagreement_that_nothing_confirms() {
        let mut f = std::fs::read(F3_BE).unwrap();
        put_u16(&mut f, 3221, 80, Endian::Big);
        let t = write_bytes("ns.sgy", &f);
        let e = err_of(open(&t.0, &SegyOptions::default()));
        assert!(
            e.contains("ns.sgy") && e.contains("80") && e.contains("462") && e.contains("neither"),
            "{e}"
        );
        // Binary header 0: the trace header (462) does not fit either → truncated.
        put_u16(&mut f, 3221, 0, Endian::Big);
        let t = write_bytes("ns0.sgy", &f);
        let e = err_of(open(&t.0, &SegyOptions::default()));
        assert!(e.contains("ns0.sgy") && e.contains("truncated"), "{e}");
        // Binary header 0 and the trace headers right: trusted, with a warning.
        let (t, _) = synth(5, Endian::Big);
        let mut f = std::fs::read(&t.0).unwrap();
        put_u16(&mut f, 3221, 0, Endian::Big);
        let t2 = write_bytes("ns-tr.sgy", &f);
        let v = open(&t2.0, &SegyOptions::default()).unwrap();
        assert_eq!(v.dims(), [7, 9, 50]);
        assert!(
            v.info()
                .warnings
                .iter()
                .any(|w| w.contains("trusted the trace header")),
            "{:?}",
            v.info().warnings
        );
    }

    #[test]
    fn unknown_format_codes_are_errors() {
        for code in [4u16, 99, 0] {
            let mut f = std::fs::read(F3_BE).unwrap();
            put_u16(&mut f, 3225, code, Endian::Big);
            let t = write_bytes(&format!("fmt{code}.sgy"), &f);
            let e = err_of(open(&t.0, &SegyOptions::default()));
            assert!(
                e.contains(&format!("fmt{code}.sgy")) && e.contains("3224"),
                "{e}"
            );
            assert!(
                e.contains(&format!(" {code} ")) && e.contains("supported: 1 (4-byte IBM float)"),
                "{e}"
            );
        }
    }

    #[test]
    fn garbage_headers_are_errors() {
        let base = std::fs::read(F3_BE).unwrap();
        let mut f = base.clone();
        f[3200..3600].fill(0xFF);
        let t = write_bytes("garbage-ff.sgy", &f);
        let e = err_of(open(&t.0, &SegyOptions::default()));
        assert!(e.contains("garbage-ff.sgy") && e.contains("3224"), "{e}");
        let mut s = 0x9E37_79B9_7F4A_7C15u64;
        for b in &mut f[3200..3600] {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *b = (s >> 56) as u8;
        }
        let t = write_bytes("garbage-rand.sgy", &f);
        let e = err_of(open(&t.0, &SegyOptions::default()));
        assert!(e.contains("garbage-rand.sgy"), "{e}");
        // Garbage inline numbers: a huge sparse grid is rejected, not allocated.
        let mut f = base.clone();
        put_i32(&mut f, 3600 + 188 + 1, 2_000_000_000, Endian::Big);
        let t = write_bytes("garbage-il.sgy", &f);
        let e = err_of(open(&t.0, &SegyOptions::default()));
        assert!(
            e.contains("garbage-il.sgy") && e.contains("grid") && e.contains("189"),
            "{e}"
        );
    }

    #[test]
    fn degenerate_geometry_falls_back_to_index_grid() {
        let write = |name: &str, ni: i32, nx: i32, coords: bool| {
            let t = tmp(name);
            let mut w = SegyWriter::create(&t.0, "C 1 x", 4, 4000, 0, 5, Endian::Big).unwrap();
            for i in 0..ni {
                for j in 0..nx {
                    let (x, y) = if coords {
                        (500_000.0 + 25.0 * j as f64, 6_000_000.0 + 10.0 * i as f64)
                    } else {
                        (0.0, 0.0)
                    };
                    w.write_trace(10 + i, 20 + j, x, y, &[1.0, 2.0, 3.0, 4.0])
                        .unwrap();
                }
            }
            w.finish().unwrap();
            t
        };
        // A single inline: no 2D fit.
        let t = write("one-line.sgy", 1, 5, true);
        let v = open(&t.0, &SegyOptions::default()).unwrap();
        assert_eq!(v.dims(), [1, 5, 4]);
        assert!(v.info().fit.is_none());
        assert_eq!(v.info().survey.to_world, Affine2::IDENTITY);
        assert!(
            v.info().warnings.iter().any(|w| w.contains("cannot place")),
            "{:?}",
            v.info().warnings
        );
        // All-zero coordinates.
        let t = write("zero-xy.sgy", 3, 3, false);
        let v = open(&t.0, &SegyOptions::default()).unwrap();
        assert_eq!(v.dims(), [3, 3, 4]);
        assert_eq!(v.info().coordinates, "none");
        assert!(v.info().fit.is_none());
        assert_eq!(v.info().survey.to_world, Affine2::IDENTITY);
        assert!(
            v.info().warnings.iter().any(|w| w.contains("all zero")),
            "{:?}",
            v.info().warnings
        );
        // A regular grid in source X/Y only (CDP zeroed): placed from source coordinates.
        let t = write("src-xy.sgy", 3, 4, true);
        let mut f = std::fs::read(&t.0).unwrap();
        for k in 0..12 {
            let h = 3600 + k * (240 + 16);
            f[h + 180..h + 188].fill(0);
        }
        std::fs::write(&t.0, &f).unwrap();
        let v = open(&t.0, &SegyOptions::default()).unwrap();
        assert_eq!(v.info().coordinates, "source");
        assert!(v.info().fit.unwrap().max_residual < 1e-6);
        assert_eq!(
            v.info().survey.to_world.apply([2.0, 3.0]),
            [500_075.0, 6_000_020.0]
        );
        // A rev 0 file with garbage where rev 1 keeps the extended-header count.
        let mut g = f.clone();
        g[3500] = 0;
        put_i16(&mut g, 3505, 77, Endian::Big);
        std::fs::write(&t.0, &g).unwrap();
        let v = open(&t.0, &SegyOptions::default()).unwrap();
        assert_eq!(
            (v.info().revision, v.info().extended_text_headers, v.dims()),
            ((0, 0), 0, [3, 4, 4])
        );
    }

    #[test]
    fn mutated_files_never_panic() {
        let (t, _) = synth(1, Endian::Big);
        let base = std::fs::read(&t.0).unwrap();
        let mut s = 0x0123_4567_89AB_CDEFu64;
        let mut rnd = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            s >> 33
        };
        let out = tmp("fuzz.sgy");
        let (mut ok, mut err) = (0, 0);
        for it in 0..400 {
            let mut f = base.clone();
            for _ in 0..1 + rnd() % 8 {
                // Mostly the binary header and the first trace headers.
                let pos = match rnd() % 3 {
                    0 => 3200 + rnd() % 400,
                    1 => 3600 + rnd() % 240,
                    _ => rnd() % f.len() as u64,
                } as usize;
                f[pos] = rnd() as u8;
            }
            if it % 5 == 0 {
                f.truncate(rnd() as usize % f.len());
            }
            std::fs::write(&out.0, &f).unwrap();
            match open(&out.0, &SegyOptions::default()) {
                Ok(v) => {
                    ok += 1;
                    let d = v.dims();
                    if d.iter().product::<u64>() < 10_000_000 {
                        let _ = read_all(&v);
                    }
                }
                Err(e) => {
                    err += 1;
                    let m = format!("{e}");
                    assert!(m.contains("fuzz.sgy") && !m.contains('\n'), "{m}");
                }
            }
        }
        assert!(ok > 0 && err > 0, "{ok} {err}");
    }
}
