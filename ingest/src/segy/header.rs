//! Header detection: byte order, sample format, revision, extended textual headers,
//! trace length and sample interval, decided from the file's first 3600 bytes, trace 1's
//! header and the file size.

use super::bytes::{contains, rd_i16, rd_u16, rd_u32, read_at};
use super::samples::{is_segy_format, supported_list, Format};
use super::text::{decode_text_header, encode_ebcdic_str};
use super::{Endian, SegyOptions, BIN, END_TEXT, HEADERS_END, TEXT_HEADER_LEN, TRACE_HEADER_LEN};
use anyhow::{anyhow, bail, Result};
use std::fs::File;
use std::path::Path;

/// At most this many extended textual headers are decoded for [`Layout::extended_text`]
/// (they are skipped either way).
const MAX_DECODED_EXTENDED: u64 = 64;

/// What the file's headers and size say about its layout.
pub(crate) struct Layout {
    pub(crate) file: File,
    pub(crate) file_len: u64,
    pub(crate) text_header: String,
    pub(crate) text_ebcdic: bool,
    /// The first [`MAX_DECODED_EXTENDED`] extended textual headers, decoded, 40 lines each
    /// (see [`with_40_lines`]).
    pub(crate) extended_text: String,
    pub(crate) n_ext: u64,
    pub(crate) endian: Endian,
    pub(crate) format: Format,
    pub(crate) format_code: u16,
    pub(crate) revision: (u8, u8),
    pub(crate) fixed_length: bool,
    pub(crate) data_start: u64,
    pub(crate) samples_per_trace: u32,
    pub(crate) trace_bytes: u64,
    pub(crate) trace_count: u64,
    /// The sample-interval field as stored (binary header 3217, else trace 1's 117).
    pub(crate) sample_interval_raw: u32,
    /// Rev 2's extended sample interval (binary header bytes 3273-3280, an IEEE double in
    /// the same unit as 3217), when set.
    pub(crate) extended_interval: Option<f64>,
    /// Binary header bytes 3255-3256: 1 = metres, 2 = feet, anything else unknown.
    pub(crate) measurement_system: u16,
    pub(crate) warnings: Vec<String>,
}

/// Reads and checks the textual and binary headers and decides the trace layout.
pub(crate) fn read_layout(path: &Path, opts: &SegyOptions) -> Result<Layout> {
    let p = path.display();
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
    let mut extended_text = String::new();
    let mut block = vec![0u8; TEXT_HEADER_LEN as usize];
    for k in 0..n_ext.min(MAX_DECODED_EXTENDED) {
        let off = HEADERS_END + k * TEXT_HEADER_LEN;
        read_at(&file, &mut block, off, path, "an extended textual header")?;
        extended_text.push_str(&with_40_lines(&decode_text_header(&block).0));
    }
    let remain = file_len - data_start;
    if remain == 0 {
        bail!("{p}: the file has no traces (it ends at byte {file_len}, where the first trace header would start)");
    }

    // Trace length: binary header vs first trace header, decided by the file size.
    let mut ns_bin = rd_u16(bin, 21, endian) as u64;
    let mut ns_bin_byte = 3221;
    // Rev 2: a non-zero extended count (bytes 3269-3272) overrides the 16-bit one, which a
    // writer may leave saturated at 65535 for longer traces. Before rev 2 those bytes are
    // unassigned, so they are read only where the 16-bit count is zero.
    let ext = rd_u32(bin, 3269 - 3200, endian) as u64;
    if ext != 0 && (ns_bin == 0 || revision.0 == 2) {
        ns_bin = ext;
        ns_bin_byte = 3269;
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

    // Sample interval: binary header, else trace header (its unit is decided with the
    // vertical axis, see `vertical`).
    let sample_interval_raw = match rd_u16(bin, 17, endian) {
        0 => match rd_u16(&first, 117, endian) {
            0 => 0,
            tr => {
                warnings.push(format!(
                    "sample interval is 0 in the binary header (byte 3217); using trace 1's header (byte 117): {tr}"
                ));
                tr as u32
            }
        },
        b => b as u32,
    };
    let extended_interval = if revision.0 == 2 {
        let b: [u8; 8] = bin[72..80].try_into().expect("8 bytes");
        let v = match endian {
            Endian::Big => f64::from_be_bytes(b),
            Endian::Little => f64::from_le_bytes(b),
        };
        (v.is_finite() && v > 0.0).then_some(v)
    } else {
        None
    };
    let measurement_system = rd_u16(bin, 55, endian);
    Ok(Layout {
        file_len,
        text_header,
        text_ebcdic,
        extended_text,
        n_ext,
        endian,
        format,
        format_code,
        revision,
        fixed_length,
        data_start,
        samples_per_trace,
        trace_bytes,
        trace_count,
        sample_interval_raw,
        extended_interval,
        measurement_system,
        warnings,
        file,
    })
}

/// A decoded 3200-byte textual header as exactly 40 lines, each ending in `\n` (decoding
/// drops trailing blank cards), so line numbers count through consecutive headers.
pub(crate) fn with_40_lines(text: &str) -> String {
    let mut out = String::with_capacity(text.len() + 40);
    let mut n = 0;
    for line in text.lines().take(40) {
        out.push_str(line);
        out.push('\n');
        n += 1;
    }
    for _ in n..40 {
        out.push('\n');
    }
    out
}
