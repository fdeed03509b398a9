//! Writing simple rev 1 / rev 2 files for tests and benchmarks.

use super::bytes::{put_i16, put_i32, put_u16};
use super::samples::f32_to_ibm;
use super::text::encode_text_header;
use super::{Endian, BINARY_HEADER_LEN, HEADERS_END, TRACE_HEADER_LEN};
use anyhow::{anyhow, bail, Result};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

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
    /// Offset (trace header byte 37) of the traces written next.
    offset: i32,
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
            offset: 0,
            buf: Vec::new(),
        })
    }

    /// Sets the source-receiver offset (trace header byte 37) of the traces written next,
    /// as in a pre-stack file (0 until set).
    pub fn set_offset(&mut self, offset: i32) {
        self.offset = offset;
    }

    /// Appends one trace. Coordinates are stored in centimetres (scalar -100) as both CDP
    /// and source X/Y; inline/crossline at 189/193 and 9/21.
    #[allow(clippy::needless_late_init)] // one `b` per format arm reads best as a match
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
        put_i32(h, 37, self.offset, e);
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
