//! Active-pixel encoding of an image span, as IceT does it: run lengths plus the data of
//! the active pixels only.
//!
//! A pixel is **inactive** iff all four of its `f32` channels have the bit pattern of
//! `+0.0` (so `-0.0` counts as active; either way is exact, since both are identities
//! of OVER). Inactive pixels are transparent black, the identity of OVER, so skipping
//! them while blending is exact.
//!
//! The wire layout is documented on [`SparsePiece`].

use bytes::Bytes;
use half::f16;
use half::slice::{HalfBitsSliceExt, HalfFloatSliceExt};
use serde::{Deserialize, Serialize};

use super::{Interlace, Span};
use crate::image::{over, Rgba};

/// How active pixels' channels travel on the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum WireFormat {
    /// Little-endian `f32`, 16 bytes per pixel, exact.
    #[default]
    F32,
    /// Little-endian IEEE half floats, 8 bytes per pixel, rounded to nearest.
    F16,
}

impl WireFormat {
    /// Bytes per active pixel.
    pub const fn bytes_per_pixel(self) -> usize {
        match self {
            WireFormat::F32 => 16,
            WireFormat::F16 => 8,
        }
    }

    const fn tag(self) -> u8 {
        match self {
            WireFormat::F32 => 0,
            WireFormat::F16 => 1,
        }
    }
}

/// One span of an image, active pixels only.
///
/// `runs` alternates (inactive count, active count) and covers exactly `span.len()`
/// pixels. [`encode`](Self::encode) writes the canonical form: an empty span has no
/// runs, an all-inactive span is `[len, 0]`, trailing inactive pixels form a final
/// `(count, 0)` pair, and every other pair has a non-zero active count (so leading and
/// trailing inactive ranges cost one number each). [`parse`](Self::parse) accepts any
/// even-length run list (zero counts included) that sums to the span length.
///
/// Wire layout (all little-endian), [`SparsePiece::HEADER_BYTES`] = 16 header bytes:
///
/// | bytes      | content                                             |
/// |------------|-----------------------------------------------------|
/// | 0..2       | magic `b"SP"`                                       |
/// | 2          | layout version, 1                                   |
/// | 3          | format: 0 = `f32`, 1 = `f16`                        |
/// | 4..8       | span start (`u32`)                                  |
/// | 8..12      | span end (`u32`)                                    |
/// | 12..16     | number of run lengths `n` (`u32`, even)             |
/// | 16..16+4n  | run lengths (`u32`): (inactive, active) pairs       |
/// | then       | active pixels' RGBA, 16 B (`f32`) or 8 B (`f16`) each |
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SparsePiece {
    /// The logical pixel range covered.
    pub span: Span,
    /// Channel format of `data`.
    pub format: WireFormat,
    /// (inactive, active) run-length pairs.
    pub runs: Vec<u32>,
    /// The active pixels' RGBA in `format`, little-endian, in order. Shared, not owned:
    /// a piece read from a peer's shared-memory segment borrows the mapping (no copy).
    pub data: Bytes,
}

/// The run lengths of a span's pixels, computed before anything is written, so the
/// piece can be encoded straight into memory of exactly its size (a peer's segment).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PieceLayout {
    /// (inactive, active) run-length pairs, in [`SparsePiece`]'s canonical form.
    pub runs: Vec<u32>,
    /// Active pixels.
    pub active: usize,
}

/// A span's pixels in logical order, in parts: stretches known to be transparent (rows
/// outside a rank's image, never read) and stretches of pixels.
#[derive(Clone, Copy, Debug)]
pub enum Segment<'a> {
    /// This many inactive (transparent black) pixels.
    Zeros(usize),
    /// These pixels.
    Pixels(&'a [Rgba]),
}

impl Segment<'_> {
    /// Pixels covered.
    pub fn len(&self) -> usize {
        match self {
            Segment::Zeros(n) => *n,
            Segment::Pixels(p) => p.len(),
        }
    }

    /// Whether it covers no pixel.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Builds canonical run lengths from inactive and active counts in order.
#[derive(Default)]
struct RunBuilder {
    runs: Vec<u32>,
    zeros: usize,
    act: usize,
    active: usize,
}

impl RunBuilder {
    fn inactive(&mut self, n: usize) {
        if n == 0 {
            return;
        }
        if self.act > 0 {
            self.runs.push(self.zeros as u32);
            self.runs.push(self.act as u32);
            self.zeros = 0;
            self.act = 0;
        }
        self.zeros += n;
    }

    fn active(&mut self, n: usize) {
        self.act += n;
        self.active += n;
    }

    fn finish(mut self) -> PieceLayout {
        if self.zeros > 0 || self.act > 0 {
            self.runs.push(self.zeros as u32);
            self.runs.push(self.act as u32);
        }
        PieceLayout {
            runs: self.runs,
            active: self.active,
        }
    }
}

impl PieceLayout {
    /// The run lengths of `pixels`.
    pub fn of(pixels: &[Rgba]) -> PieceLayout {
        Self::of_segments(&[Segment::Pixels(pixels)])
    }

    /// The run lengths of the pixels `segments` stand for, one after the other; `Zeros`
    /// are taken as they are, without a pixel to read.
    pub fn of_segments(segments: &[Segment<'_>]) -> PieceLayout {
        let mut b = RunBuilder::default();
        for seg in segments {
            match *seg {
                Segment::Zeros(n) => b.inactive(n),
                Segment::Pixels(pixels) => {
                    let bits: &[[u32; 4]] = bytemuck::cast_slice(pixels);
                    let n = bits.len();
                    let mut i = 0usize;
                    while i < n {
                        let s = i;
                        // Whole blocks first (a branch-free test of `SCAN` pixels), then
                        // pixel by pixel to the run's end.
                        while i + SCAN <= n && block_inactive(&bits[i..i + SCAN]) {
                            i += SCAN;
                        }
                        while i < n && is_inactive(&bits[i]) {
                            i += 1;
                        }
                        let a = i;
                        while i + SCAN <= n && block_active(&bits[i..i + SCAN]) {
                            i += SCAN;
                        }
                        while i < n && !is_inactive(&bits[i]) {
                            i += 1;
                        }
                        b.inactive(a - s);
                        b.active(i - a);
                    }
                }
            }
        }
        b.finish()
    }

    /// Calls `f` with the active pixels of `segments` (those this layout was computed
    /// from), run by run, in order.
    ///
    /// # Panics
    /// If the layout was not computed from these segments (a caller bug).
    fn for_each_active_run(&self, segments: &[Segment<'_>], mut f: impl FnMut(&[Rgba])) {
        let (mut k, mut o) = (0usize, 0usize);
        let skip = |mut n: usize, k: &mut usize, o: &mut usize| {
            while n > 0 {
                let left = segments[*k].len() - *o;
                if n < left {
                    *o += n;
                    n = 0;
                } else {
                    n -= left;
                    *k += 1;
                    *o = 0;
                }
            }
        };
        for pair in self.runs.chunks_exact(2) {
            skip(pair[0] as usize, &mut k, &mut o);
            let mut n = pair[1] as usize;
            while n > 0 {
                while segments[k].len() == o {
                    k += 1;
                    o = 0;
                }
                let Segment::Pixels(px) = segments[k] else {
                    panic!("PieceLayout: active pixels in a Zeros segment");
                };
                let take = n.min(px.len() - o);
                f(&px[o..o + take]);
                o += take;
                n -= take;
            }
        }
    }

    /// Bytes of the piece's wire form (header, run lengths, data) in `format`.
    pub fn byte_len(&self, format: WireFormat) -> usize {
        SparsePiece::HEADER_BYTES + 4 * self.runs.len() + self.active * format.bytes_per_pixel()
    }

    /// Writes the wire form of the piece of the pixels `segments` stand for (those this
    /// layout was computed from, covering `span`) into `out`, which must be exactly
    /// [`byte_len`](Self::byte_len) bytes: the same bytes as [`SparsePiece::write`] of
    /// [`SparsePiece::encode`], with no intermediate buffer.
    ///
    /// # Panics
    /// If `out` or the segments have the wrong length (a caller bug).
    pub fn write_segments_into(
        &self,
        segments: &[Segment<'_>],
        span: Span,
        format: WireFormat,
        out: &mut [u8],
    ) {
        assert_eq!(
            segments.iter().map(Segment::len).sum::<usize>(),
            span.len() as usize,
            "PieceLayout::write_segments_into: pixels"
        );
        assert_eq!(
            out.len(),
            self.byte_len(format),
            "PieceLayout::write_segments_into: out"
        );
        let (head, rest) = out.split_at_mut(SparsePiece::HEADER_BYTES);
        head.copy_from_slice(&SparsePiece::header(span, format, self.runs.len()));
        let (runs, mut data) = rest.split_at_mut(4 * self.runs.len());
        for (d, r) in runs.chunks_exact_mut(4).zip(&self.runs) {
            d.copy_from_slice(&r.to_le_bytes());
        }
        let bpp = format.bytes_per_pixel();
        self.for_each_active_run(segments, |px| {
            let (d, tail) = std::mem::take(&mut data).split_at_mut(px.len() * bpp);
            match format {
                WireFormat::F32 => put_f32_le(d, px),
                WireFormat::F16 => put_f16_le(d, px),
            }
            data = tail;
        });
    }
}

/// Why bytes are not a valid [`SparsePiece`], or a piece does not fit where it is used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PieceError {
    /// Fewer bytes left than the layout requires.
    #[error("truncated piece: expected {needed} bytes of {what} at byte offset {offset}, found {available}")]
    Truncated {
        /// Which part of the layout.
        what: &'static str,
        /// Byte offset where it starts.
        offset: usize,
        /// Bytes required.
        needed: u64,
        /// Bytes left.
        available: usize,
    },
    /// The first three bytes are not `b"SP"` and version 1.
    #[error(
        "bad piece header at byte offset 0: expected magic \"SP\" version 1, found {found:02x?}"
    )]
    BadMagic {
        /// The bytes found.
        found: [u8; 3],
    },
    /// Unknown format byte.
    #[error("bad piece format at byte offset 3: expected 0 (f32) or 1 (f16), found {found}")]
    BadFormat {
        /// The byte found.
        found: u8,
    },
    /// `end < start`.
    #[error("bad piece span at byte offset 4: start {start} is after end {end}")]
    InvertedSpan {
        /// Span start.
        start: u32,
        /// Span end.
        end: u32,
    },
    /// The span reaches past the pixel limit.
    #[error("piece span {span} at byte offset 4 exceeds the limit of {max_pixels} pixels")]
    SpanTooLarge {
        /// The span read.
        span: Span,
        /// The limit.
        max_pixels: u32,
    },
    /// An odd number of run lengths.
    #[error("bad run count at byte offset 12: expected an even number, found {count}")]
    OddRuns {
        /// The count read.
        count: u32,
    },
    /// More run lengths than a span of this length can need.
    #[error("bad run count at byte offset 12: at most {max} runs fit a span of {len} pixels, found {count}")]
    TooManyRuns {
        /// The count read.
        count: u32,
        /// The largest count accepted.
        max: u64,
        /// The span length.
        len: u32,
    },
    /// The run lengths do not add up to the span length.
    #[error("run lengths at byte offset {offset} sum to {sum}, expected the span length {len}")]
    RunsSum {
        /// Byte offset of the run lengths (0 for an in-memory piece).
        offset: usize,
        /// Their sum.
        sum: u64,
        /// The span length.
        len: u32,
    },
    /// The data length does not match the active pixel count.
    #[error("pixel data at byte offset {offset}: expected {expected} bytes for {active} active pixels, found {found}")]
    DataLength {
        /// Byte offset of the data (0 for an in-memory piece).
        offset: usize,
        /// Active pixels per the run lengths.
        active: u64,
        /// Bytes expected.
        expected: u64,
        /// Bytes present.
        found: usize,
    },
    /// Bytes after the piece where none were expected.
    #[error("{extra} unexpected bytes after the piece at byte offset {offset}")]
    TrailingBytes {
        /// Where the piece ended.
        offset: usize,
        /// Bytes left over.
        extra: usize,
    },
    /// The piece's span is not inside the destination buffer's span.
    #[error("piece span {span} lies outside the destination span {dst}")]
    OutOfRange {
        /// The piece's span.
        span: Span,
        /// The destination's span (`u32::MAX`-saturated end).
        dst: Span,
    },
    /// An LZ4-compressed piece whose stated size is past the limit or whose block does not
    /// decompress to it.
    #[error("bad LZ4 piece: {0}")]
    Lz4(String),
}

/// Pixels decoded per chunk when the data cannot be used in place.
const CHUNK: usize = 256;

#[inline(always)]
fn is_inactive(p: &[u32; 4]) -> bool {
    (p[0] | p[1] | p[2] | p[3]) == 0
}

/// Pixels tested at once while scanning for runs (one 8-pixel block is 128 bytes).
const SCAN: usize = 8;

/// Whether every pixel of `block` is inactive (all bits zero): one OR over the block, which
/// the compiler vectorises, instead of a branch per pixel.
#[inline(always)]
fn block_inactive(block: &[[u32; 4]]) -> bool {
    block
        .iter()
        .fold(0u32, |acc, p| acc | p[0] | p[1] | p[2] | p[3])
        == 0
}

/// Whether every pixel of `block` is active (some bit set), without a branch per pixel.
#[inline(always)]
fn block_active(block: &[[u32; 4]]) -> bool {
    block
        .iter()
        .fold(true, |acc, p| acc & ((p[0] | p[1] | p[2] | p[3]) != 0))
}

/// The bytes as RGBA `f32` pixels without copying, when layout and alignment allow.
#[cfg(target_endian = "little")]
fn f32_in_place(bytes: &[u8]) -> Option<&[Rgba]> {
    bytemuck::try_cast_slice(bytes).ok()
}

#[cfg(not(target_endian = "little"))]
fn f32_in_place(_bytes: &[u8]) -> Option<&[Rgba]> {
    None
}

fn extend_f32_le(out: &mut Vec<u8>, px: &[Rgba]) {
    if cfg!(target_endian = "little") {
        out.extend_from_slice(bytemuck::cast_slice(px));
    } else {
        for v in px.iter().flatten() {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
}

fn put_f32_le(out: &mut [u8], px: &[Rgba]) {
    if cfg!(target_endian = "little") {
        out.copy_from_slice(bytemuck::cast_slice(px));
    } else {
        for (d, v) in out.chunks_exact_mut(4).zip(px.iter().flatten()) {
            d.copy_from_slice(&v.to_le_bytes());
        }
    }
}

fn put_f16_le(out: &mut [u8], px: &[Rgba]) {
    let mut halves = [f16::ZERO; CHUNK * 4];
    for (chunk, out) in px.chunks(CHUNK).zip(out.chunks_mut(CHUNK * 8)) {
        let src: &[f32] = bytemuck::cast_slice(chunk);
        let h = &mut halves[..src.len()];
        h.convert_from_f32_slice(src);
        let bits: &[u16] = h.reinterpret_cast();
        for (d, b) in out.chunks_exact_mut(2).zip(bits) {
            d.copy_from_slice(&b.to_le_bytes());
        }
    }
}

fn extend_f16_le(out: &mut Vec<u8>, px: &[Rgba]) {
    let mut halves = [f16::ZERO; CHUNK * 4];
    for chunk in px.chunks(CHUNK) {
        let src: &[f32] = bytemuck::cast_slice(chunk);
        let h = &mut halves[..src.len()];
        h.convert_from_f32_slice(src);
        let bits: &[u16] = h.reinterpret_cast();
        if cfg!(target_endian = "little") {
            out.extend_from_slice(bytemuck::cast_slice(bits));
        } else {
            for b in bits {
                out.extend_from_slice(&b.to_le_bytes());
            }
        }
    }
}

fn read_u32(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

impl SparsePiece {
    /// Header bytes before the run lengths.
    pub const HEADER_BYTES: usize = 16;

    /// Encodes `pixels`, exactly the pixels of `span` in logical order.
    ///
    /// # Panics
    /// If `pixels.len() != span.len()` (a caller bug, not a data error).
    pub fn encode(pixels: &[Rgba], span: Span, format: WireFormat) -> SparsePiece {
        assert_eq!(
            pixels.len(),
            span.len() as usize,
            "SparsePiece::encode: {} pixels for span {span}",
            pixels.len()
        );
        Self::encode_with(pixels, PieceLayout::of(pixels), span, format)
    }

    /// [`encode`](Self::encode) with the run lengths already computed (`layout`, of
    /// these `pixels`).
    pub fn encode_with(
        pixels: &[Rgba],
        layout: PieceLayout,
        span: Span,
        format: WireFormat,
    ) -> SparsePiece {
        Self::encode_segments(&[Segment::Pixels(pixels)], layout, span, format)
    }

    /// [`encode_with`](Self::encode_with) of the pixels `segments` stand for.
    pub fn encode_segments(
        segments: &[Segment<'_>],
        layout: PieceLayout,
        span: Span,
        format: WireFormat,
    ) -> SparsePiece {
        assert_eq!(
            segments.iter().map(Segment::len).sum::<usize>(),
            span.len() as usize,
            "SparsePiece::encode_segments"
        );
        let mut data = Vec::with_capacity(layout.active * format.bytes_per_pixel());
        layout.for_each_active_run(segments, |px| match format {
            WireFormat::F32 => extend_f32_le(&mut data, px),
            WireFormat::F16 => extend_f16_le(&mut data, px),
        });
        SparsePiece {
            span,
            format,
            runs: layout.runs,
            data: data.into(),
        }
    }

    /// The 16 header bytes of a piece (layout in the [type docs](SparsePiece)).
    fn header(span: Span, format: WireFormat, runs: usize) -> [u8; Self::HEADER_BYTES] {
        let mut h = [0u8; Self::HEADER_BYTES];
        h[..4].copy_from_slice(&[b'S', b'P', 1, format.tag()]);
        h[4..8].copy_from_slice(&span.start.to_le_bytes());
        h[8..12].copy_from_slice(&span.end.to_le_bytes());
        h[12..16].copy_from_slice(&(runs as u32).to_le_bytes());
        h
    }

    /// Number of active pixels (from the data length).
    pub fn active_pixels(&self) -> usize {
        self.data.len() / self.format.bytes_per_pixel()
    }

    /// Bytes on the wire: header, run lengths and data.
    pub fn byte_len(&self) -> usize {
        Self::HEADER_BYTES + 4 * self.runs.len() + self.data.len()
    }

    /// Appends the wire form (layout in the [type docs](SparsePiece)) to `out`.
    pub fn write(&self, out: &mut Vec<u8>) {
        out.reserve(self.byte_len());
        for part in self.wire_parts() {
            out.extend_from_slice(&part);
        }
    }

    /// The wire form in three parts (header, run lengths, pixel data), to be written one
    /// after the other without first joining them (a shared-memory segment takes them
    /// straight from the piece).
    pub fn wire_parts(&self) -> [std::borrow::Cow<'_, [u8]>; 3] {
        use std::borrow::Cow;
        let head = Self::header(self.span, self.format, self.runs.len()).to_vec();
        let runs: Cow<'_, [u8]> = if cfg!(target_endian = "little") {
            Cow::Borrowed(bytemuck::cast_slice(&self.runs))
        } else {
            Cow::Owned(self.runs.iter().flat_map(|r| r.to_le_bytes()).collect())
        };
        [Cow::Owned(head), runs, Cow::Borrowed(&self.data)]
    }

    /// The wire form in three shared chunks (header, run lengths, pixel data), the pixel
    /// data not copied: for a transport that sends chunks as they are (QUIC streams do).
    pub fn wire_chunks(&self) -> [Bytes; 3] {
        let [head, runs, _] = self.wire_parts();
        [
            Bytes::copy_from_slice(&head),
            Bytes::copy_from_slice(&runs),
            self.data.clone(),
        ]
    }

    /// Bytes of run lengths announced by a piece's header (the first
    /// [`HEADER_BYTES`](Self::HEADER_BYTES) bytes), so a reader can fetch header and runs
    /// first and the pixel data straight into its own buffer. Unchecked: the parse that
    /// follows checks everything.
    pub fn runs_bytes_in_header(header: &[u8; Self::HEADER_BYTES]) -> u64 {
        4 * read_u32(header, 12) as u64
    }

    /// Parses a piece whose header and run lengths are `head` (exactly) and whose pixel
    /// data is `data` (exactly), taking `data` as the piece's without a copy (a buffer
    /// read for it, or a shared-memory mapping's bytes). The same checks as
    /// [`parse`](Self::parse).
    pub fn parse_split(
        head: &[u8],
        data: Bytes,
        max_pixels: u32,
    ) -> Result<SparsePiece, PieceError> {
        let (span, format, runs, active, used) = Self::parse_head(head, max_pixels)?;
        if used != head.len() {
            return Err(PieceError::TrailingBytes {
                offset: used,
                extra: head.len() - used,
            });
        }
        let data_bytes = active * format.bytes_per_pixel() as u64;
        if data.len() as u64 != data_bytes {
            return Err(PieceError::Truncated {
                what: "pixel data",
                offset: used,
                needed: data_bytes,
                available: data.len(),
            });
        }
        Ok(SparsePiece {
            span,
            format,
            runs,
            data,
        })
    }

    /// The wire form compressed for slow links (`composite.lz4`): the uncompressed length
    /// (`u32`, little-endian), then one LZ4 block of the wire form with the pixel data
    /// byte-shuffled (the k-th byte of every channel value together, as the page store
    /// does), which lets LZ4 find the runs in exponents and high mantissa bytes.
    ///
    /// `None` for a piece whose wire form is 4 GiB or more, which the length cannot state:
    /// such a piece travels uncompressed.
    pub fn write_lz4(&self) -> Option<Vec<u8>> {
        if self.byte_len() > u32::MAX as usize {
            return None;
        }
        let mut raw = Vec::with_capacity(self.byte_len());
        for part in &self.wire_parts()[..2] {
            raw.extend_from_slice(part);
        }
        let elem = self.format.bytes_per_pixel() / 4;
        raw.extend_from_slice(&crate::store::shuffle(&self.data, elem));
        let block = lz4_flex::block::compress(&raw);
        let mut out = Vec::with_capacity(4 + block.len());
        out.extend_from_slice(&(raw.len() as u32).to_le_bytes());
        out.extend_from_slice(&block);
        Some(out)
    }

    /// Parses a piece written by [`write_lz4`](Self::write_lz4) (untrusted input): the
    /// stated size is checked against the largest piece of `max_pixels` pixels before
    /// anything is allocated, the block must decompress to exactly that size, and the
    /// result is then checked as [`parse`](Self::parse) checks it.
    pub fn parse_lz4(bytes: &[u8], max_pixels: u32) -> Result<SparsePiece, PieceError> {
        let Some((len, block)) = bytes.split_first_chunk::<4>() else {
            return Err(PieceError::Truncated {
                what: "LZ4 piece length",
                offset: 0,
                needed: 4,
                available: bytes.len(),
            });
        };
        let len = u32::from_le_bytes(*len) as u64;
        let limit = crate::wire::max_piece_bytes(max_pixels as u64);
        if len > limit {
            return Err(PieceError::Lz4(format!(
                "it states {len} bytes, more than the {limit} a piece of {max_pixels} pixels can take"
            )));
        }
        let mut raw = lz4_flex::block::decompress(block, len as usize)
            .map_err(|e| PieceError::Lz4(format!("the block does not decompress: {e}")))?;
        if raw.len() as u64 != len {
            return Err(PieceError::Lz4(format!(
                "the block decompresses to {} bytes, not the {len} stated",
                raw.len()
            )));
        }
        // Undo the shuffle of the pixel data (the header says where it starts and how wide
        // its values are; a header `parse` refuses is passed through for it to refuse).
        if raw.len() >= Self::HEADER_BYTES {
            let n = u32::from_le_bytes([raw[12], raw[13], raw[14], raw[15]]) as u64;
            let at = Self::HEADER_BYTES as u64 + 4 * n;
            let elem = match raw[3] {
                0 => 4,
                1 => 2,
                _ => 1,
            };
            if at <= raw.len() as u64 && elem > 1 {
                let at = at as usize;
                let data = crate::store::unshuffle(&raw[at..], elem);
                raw[at..].copy_from_slice(&data);
            }
        }
        Self::parse_shared(raw.into(), max_pixels)
    }

    /// Parses exactly one piece from `bytes` (untrusted input): every count is checked
    /// against the bytes left and against `max_pixels` (the span must end at or before
    /// it) before anything is allocated. Trailing bytes are an error.
    pub fn parse(bytes: &[u8], max_pixels: u32) -> Result<SparsePiece, PieceError> {
        let (piece, used) = Self::parse_prefix(bytes, max_pixels)?;
        if used != bytes.len() {
            return Err(PieceError::TrailingBytes {
                offset: used,
                extra: bytes.len() - used,
            });
        }
        Ok(piece)
    }

    /// [`parse`](Self::parse) of a received buffer the piece takes over: its pixel data
    /// is a slice of `bytes`, not a copy (a piece received over QUIC is blended from the
    /// buffer it arrived in).
    pub fn parse_shared(bytes: Bytes, max_pixels: u32) -> Result<SparsePiece, PieceError> {
        let (span, format, runs, active, data_at) = Self::parse_head(&bytes, max_pixels)?;
        let data_bytes = active * format.bytes_per_pixel() as u64;
        let available = bytes.len() - data_at;
        if data_bytes > available as u64 {
            return Err(PieceError::Truncated {
                what: "pixel data",
                offset: data_at,
                needed: data_bytes,
                available,
            });
        }
        let used = data_at + data_bytes as usize;
        if used != bytes.len() {
            return Err(PieceError::TrailingBytes {
                offset: used,
                extra: bytes.len() - used,
            });
        }
        Ok(SparsePiece {
            span,
            format,
            runs,
            data: bytes.slice(data_at..used),
        })
    }

    /// Parses one piece from the start of `bytes`, returning it and the bytes it used.
    pub fn parse_prefix(bytes: &[u8], max_pixels: u32) -> Result<(SparsePiece, usize), PieceError> {
        let (span, format, runs, active, data_at) = Self::parse_head(bytes, max_pixels)?;
        let rest = &bytes[data_at..];
        let data_bytes = active * format.bytes_per_pixel() as u64;
        if data_bytes > rest.len() as u64 {
            return Err(PieceError::Truncated {
                what: "pixel data",
                offset: data_at,
                needed: data_bytes,
                available: rest.len(),
            });
        }
        let data = Bytes::copy_from_slice(&rest[..data_bytes as usize]);
        Ok((
            SparsePiece {
                span,
                format,
                runs,
                data,
            },
            data_at + data_bytes as usize,
        ))
    }

    /// Checks the header and run lengths at the start of `bytes`: span, format, runs,
    /// active pixel count, and where the pixel data starts.
    #[allow(clippy::type_complexity)]
    fn parse_head(
        bytes: &[u8],
        max_pixels: u32,
    ) -> Result<(Span, WireFormat, Vec<u32>, u64, usize), PieceError> {
        let h = Self::HEADER_BYTES;
        if bytes.len() < h {
            return Err(PieceError::Truncated {
                what: "header",
                offset: 0,
                needed: h as u64,
                available: bytes.len(),
            });
        }
        if bytes[..3] != [b'S', b'P', 1] {
            return Err(PieceError::BadMagic {
                found: [bytes[0], bytes[1], bytes[2]],
            });
        }
        let format = match bytes[3] {
            0 => WireFormat::F32,
            1 => WireFormat::F16,
            found => return Err(PieceError::BadFormat { found }),
        };
        let (start, end) = (read_u32(bytes, 4), read_u32(bytes, 8));
        if end < start {
            return Err(PieceError::InvertedSpan { start, end });
        }
        let span = Span::new(start, end);
        if end > max_pixels {
            return Err(PieceError::SpanTooLarge { span, max_pixels });
        }
        let len = span.len();
        let count = read_u32(bytes, 12);
        if count & 1 != 0 {
            return Err(PieceError::OddRuns { count });
        }
        let max = 2 * len as u64 + 2;
        if count as u64 > max {
            return Err(PieceError::TooManyRuns { count, max, len });
        }
        let runs_bytes = 4 * count as u64;
        let rest = &bytes[h..];
        if runs_bytes > rest.len() as u64 {
            return Err(PieceError::Truncated {
                what: "run lengths",
                offset: h,
                needed: runs_bytes,
                available: rest.len(),
            });
        }
        let runs: Vec<u32> = rest[..runs_bytes as usize]
            .chunks_exact(4)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let (sum, active) = runs.chunks_exact(2).fold((0u64, 0u64), |(s, a), p| {
            (s + p[0] as u64 + p[1] as u64, a + p[1] as u64)
        });
        if sum != len as u64 {
            return Err(PieceError::RunsSum {
                offset: h,
                sum,
                len,
            });
        }
        Ok((span, format, runs, active, h + runs_bytes as usize))
    }

    /// Checks an in-memory piece's invariants (even run list summing to the span
    /// length, data length matching the active count); offsets in errors are 0.
    pub fn check(&self) -> Result<(), PieceError> {
        if self.span.end < self.span.start {
            return Err(PieceError::InvertedSpan {
                start: self.span.start,
                end: self.span.end,
            });
        }
        if self.runs.len() & 1 != 0 {
            return Err(PieceError::OddRuns {
                count: self.runs.len() as u32,
            });
        }
        let (sum, active) = self.runs.chunks_exact(2).fold((0u64, 0u64), |(s, a), p| {
            (s + p[0] as u64 + p[1] as u64, a + p[1] as u64)
        });
        if sum != self.span.len() as u64 {
            return Err(PieceError::RunsSum {
                offset: 0,
                sum,
                len: self.span.len(),
            });
        }
        let expected = active * self.format.bytes_per_pixel() as u64;
        if expected != self.data.len() as u64 {
            return Err(PieceError::DataLength {
                offset: 0,
                active,
                expected,
                found: self.data.len(),
            });
        }
        Ok(())
    }

    /// Checks the piece and that its span lies inside `[dst_start, dst_start + dst_len)`;
    /// returns the piece's offset in the destination.
    fn locate(&self, dst_len: usize, dst_start: u32) -> Result<usize, PieceError> {
        self.check()?;
        let dst_end = (dst_start as u64 + dst_len as u64).min(u32::MAX as u64) as u32;
        let inside = dst_start as u64 + dst_len as u64 >= self.span.end as u64;
        if self.span.is_empty() {
            return Ok(0);
        }
        if self.span.start < dst_start || !inside {
            return Err(PieceError::OutOfRange {
                span: self.span,
                dst: Span::new(dst_start, dst_end),
            });
        }
        Ok((self.span.start - dst_start) as usize)
    }

    /// Calls `f(offset in span, pixels)` for the active pixels, run by run (long runs
    /// in chunks when they must be decoded). The piece must have passed [`check`](Self::check).
    pub(super) fn for_each_active(&self, mut f: impl FnMut(usize, &[Rgba])) {
        let bpp = self.format.bytes_per_pixel();
        let mut scratch = [[0f32; 4]; CHUNK];
        let mut pos = 0usize;
        let mut byte = 0usize;
        for pair in self.runs.chunks_exact(2) {
            pos += pair[0] as usize;
            let n = pair[1] as usize;
            let bytes = &self.data[byte..byte + n * bpp];
            match self.format {
                WireFormat::F32 => {
                    if let Some(px) = f32_in_place(bytes) {
                        f(pos, px);
                    } else {
                        for (i, chunk) in bytes.chunks(CHUNK * 16).enumerate() {
                            let m = chunk.len() / 16;
                            let floats: &mut [f32] = bytemuck::cast_slice_mut(&mut scratch[..m]);
                            for (d, s) in floats.iter_mut().zip(chunk.chunks_exact(4)) {
                                *d = f32::from_le_bytes([s[0], s[1], s[2], s[3]]);
                            }
                            f(pos + i * CHUNK, &scratch[..m]);
                        }
                    }
                }
                WireFormat::F16 => {
                    let mut bits = [0u16; CHUNK * 4];
                    for (i, chunk) in bytes.chunks(CHUNK * 8).enumerate() {
                        let m = chunk.len() / 8;
                        for (b, s) in bits[..4 * m].iter_mut().zip(chunk.chunks_exact(2)) {
                            *b = u16::from_le_bytes([s[0], s[1]]);
                        }
                        let halves: &[f16] = bits[..4 * m].reinterpret_cast();
                        halves.convert_to_f32_slice(bytemuck::cast_slice_mut(&mut scratch[..m]));
                        f(pos + i * CHUNK, &scratch[..m]);
                    }
                }
            }
            pos += n;
            byte += n * bpp;
        }
    }

    /// `dst = piece OVER dst` (the piece in front) over the piece's span, where `dst`
    /// holds the pixels from logical index `dst_span_start` on.
    pub fn blend_over(&self, dst: &mut [Rgba], dst_span_start: u32) -> Result<(), PieceError> {
        let base = self.locate(dst.len(), dst_span_start)?;
        self.for_each_active(|off, px| {
            let d = &mut dst[base + off..base + off + px.len()];
            for (d, s) in d.iter_mut().zip(px) {
                *d = over(*s, *d);
            }
        });
        Ok(())
    }

    /// `dst = dst OVER piece` (the piece behind) over the piece's span, where `dst`
    /// holds the pixels from logical index `dst_span_start` on.
    pub fn blend_under(&self, dst: &mut [Rgba], dst_span_start: u32) -> Result<(), PieceError> {
        let base = self.locate(dst.len(), dst_span_start)?;
        self.for_each_active(|off, px| {
            let d = &mut dst[base + off..base + off + px.len()];
            for (d, s) in d.iter_mut().zip(px) {
                *d = over(*d, *s);
            }
        });
        Ok(())
    }

    /// `OVER` of the piece into the physical `frame` where logical span `keep` lies
    /// (through `interlace`'s row map): `in_front` puts the piece over what is there,
    /// else under it. The piece must lie inside `keep`, and `keep` inside the frame.
    pub(super) fn blend_in_frame(
        &self,
        frame: &mut [Rgba],
        interlace: &Interlace,
        keep: Span,
        in_front: bool,
    ) -> Result<(), PieceError> {
        // The same check as a contiguous destination holding `keep`.
        self.locate(keep.len() as usize, keep.start)?;
        if keep.end as u64 > interlace.pixels() || frame.len() as u64 != interlace.pixels() {
            return Err(PieceError::OutOfRange {
                span: keep,
                dst: Span::new(0, frame.len().min(u32::MAX as usize) as u32),
            });
        }
        let start = self.span.start as usize;
        self.for_each_active(|off, px| {
            super::canvas::physical_runs(interlace, start + off, px.len(), |d, o, len| {
                let dst = &mut frame[d..d + len];
                if in_front {
                    for (d, s) in dst.iter_mut().zip(&px[o..o + len]) {
                        *d = over(*s, *d);
                    }
                } else {
                    for (d, s) in dst.iter_mut().zip(&px[o..o + len]) {
                        *d = over(*d, *s);
                    }
                }
            });
        });
        Ok(())
    }

    /// Writes the piece's pixels (inactive ones as transparent black) into `dst`,
    /// which holds the pixels from logical index `dst_span_start` on.
    pub fn decode_into(&self, dst: &mut [Rgba], dst_span_start: u32) -> Result<(), PieceError> {
        let base = self.locate(dst.len(), dst_span_start)?;
        dst[base..base + self.span.len() as usize].fill([0.0; 4]);
        self.for_each_active(|off, px| {
            dst[base + off..base + off + px.len()].copy_from_slice(px);
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn px(v: f32) -> Rgba {
        [v * 0.5, v * 0.25, 0.0, v]
    }

    fn roundtrip(p: &SparsePiece, max: u32) -> SparsePiece {
        let mut bytes = Vec::new();
        p.write(&mut bytes);
        assert_eq!(bytes.len(), p.byte_len());
        SparsePiece::parse(&bytes, max).unwrap()
    }

    #[test]
    fn lz4_pieces_round_trip_shrink_smooth_data_and_refuse_lies() {
        // A smooth translucent gradient with holes, as a rendered span looks.
        let pixels: Vec<Rgba> = (0..4000)
            .map(|i| {
                if i % 97 < 30 {
                    [0.0; 4]
                } else {
                    px(0.2 + 0.6 * (i as f32 / 4000.0))
                }
            })
            .collect();
        for format in [WireFormat::F32, WireFormat::F16] {
            let p = SparsePiece::encode(&pixels, Span::new(100, 4100), format);
            let z = p.write_lz4().unwrap();
            assert_eq!(SparsePiece::parse_lz4(&z, 4100).unwrap(), p);
            assert!(
                z.len() * 2 < p.byte_len(),
                "{format:?}: {} compressed bytes of {}",
                z.len(),
                p.byte_len()
            );
            // The span must still fit the receiver's limit.
            assert!(SparsePiece::parse_lz4(&z, 4099).is_err());
        }
        let p = SparsePiece::encode(&pixels, Span::new(0, 4000), WireFormat::F32);
        let z = p.write_lz4().unwrap();
        // A stated size past what any piece of the limit can take: refused before
        // allocating.
        let mut lie = z.clone();
        lie[..4].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            SparsePiece::parse_lz4(&lie, 4000),
            Err(PieceError::Lz4(_))
        ));
        // A size that does not match the block, a cut block, garbage, nothing.
        let mut off = z.clone();
        let n = u32::from_le_bytes([z[0], z[1], z[2], z[3]]) - 1;
        off[..4].copy_from_slice(&n.to_le_bytes());
        assert!(SparsePiece::parse_lz4(&off, 4000).is_err());
        assert!(SparsePiece::parse_lz4(&z[..z.len() / 2], 4000).is_err());
        assert!(SparsePiece::parse_lz4(&[9, 0, 0, 0, 1, 2, 3], 4000).is_err());
        assert!(SparsePiece::parse_lz4(&[1, 2], 4000).is_err());
    }

    #[test]
    fn canonical_runs() {
        let z = [0.0; 4];
        let pixels = [z, z, px(1.0), px(0.5), z, z, z];
        let p = SparsePiece::encode(&pixels, Span::new(10, 17), WireFormat::F32);
        assert_eq!(p.runs, [2, 2, 3, 0]);
        assert_eq!(p.active_pixels(), 2);
        assert_eq!(p.data.len(), 32);
        assert_eq!(p.byte_len(), 16 + 16 + 32);

        let p = SparsePiece::encode(&[z; 5], Span::new(0, 5), WireFormat::F16);
        assert_eq!(p.runs, [5, 0]);
        assert!(p.data.is_empty());
        let p = SparsePiece::encode(&[], Span::new(3, 3), WireFormat::F32);
        assert!(p.runs.is_empty());
        assert_eq!(roundtrip(&p, 3), p);

        let p = SparsePiece::encode(&[px(1.0), px(1.0)], Span::new(0, 2), WireFormat::F16);
        assert_eq!(p.runs, [0, 2]);
        assert_eq!(p.data.len(), 16);
        // -0.0 is active (bitwise test).
        let p = SparsePiece::encode(&[[0.0, -0.0, 0.0, 0.0]], Span::new(0, 1), WireFormat::F32);
        assert_eq!(p.runs, [0, 1]);
    }

    #[test]
    fn f32_layout_is_little_endian() {
        let p = SparsePiece::encode(&[[1.0, 2.0, 3.0, 4.0]], Span::new(7, 8), WireFormat::F32);
        let mut b = Vec::new();
        p.write(&mut b);
        assert_eq!(&b[..4], b"SP\x01\x00");
        assert_eq!(&b[4..16], &[7, 0, 0, 0, 8, 0, 0, 0, 2, 0, 0, 0]);
        assert_eq!(&b[16..24], &[0, 0, 0, 0, 1, 0, 0, 0]);
        assert_eq!(&b[24..28], &1.0f32.to_le_bytes());
        assert_eq!(&b[36..40], &4.0f32.to_le_bytes());
        let h = SparsePiece::encode(&[[1.0, 2.0, 3.0, 4.0]], Span::new(7, 8), WireFormat::F16);
        let mut b = Vec::new();
        h.write(&mut b);
        assert_eq!(b[3], 1);
        assert_eq!(&b[24..26], &f16::from_f32(1.0).to_bits().to_le_bytes());
    }

    #[test]
    fn blends_match_scalar_over() {
        let z = [0.0; 4];
        let src = [z, [0.1, 0.2, 0.3, 0.5], z, [0.4, 0.0, 0.0, 0.4]];
        let p = SparsePiece::encode(&src, Span::new(5, 9), WireFormat::F32);
        let back = [[0.2, 0.2, 0.2, 0.6]; 6]; // logical [4, 10)
        let mut a = back;
        p.blend_over(&mut a, 4).unwrap();
        let mut b = back;
        p.blend_under(&mut b, 4).unwrap();
        for i in 0..6 {
            let s = if (1..5).contains(&i) { src[i - 1] } else { z };
            assert_eq!(a[i], over(s, back[i]));
            assert_eq!(b[i], over(back[i], s));
        }
        let mut c = [[9.0; 4]; 6];
        p.decode_into(&mut c, 4).unwrap();
        assert_eq!(c[0], [9.0; 4]);
        assert_eq!(&c[1..5], &src);
        assert_eq!(c[5], [9.0; 4]);
    }

    #[test]
    fn long_runs_cross_chunks() {
        let n = 3 * CHUNK + 17;
        let src: Vec<Rgba> = (0..n)
            .map(|i| {
                if i % 700 == 3 {
                    [0.0; 4]
                } else {
                    px((i % 97) as f32 / 97.0 + 0.01)
                }
            })
            .collect();
        for format in [WireFormat::F32, WireFormat::F16] {
            let p = SparsePiece::encode(&src, Span::new(0, n as u32), format);
            let mut out = vec![[0.0; 4]; n];
            p.decode_into(&mut out, 0).unwrap();
            for (a, b) in out.iter().zip(&src) {
                for c in 0..4 {
                    assert!((a[c] - b[c]).abs() <= 1e-3 * b[c].abs(), "{a:?} {b:?}");
                }
            }
            // A misaligned copy of the data takes the decoding path.
            let mut bytes = vec![0u8];
            p.write(&mut bytes);
            let q = SparsePiece::parse(&bytes[1..], n as u32).unwrap();
            let mut out2 = vec![[0.0; 4]; n];
            q.decode_into(&mut out2, 0).unwrap();
            assert_eq!(out, out2);
        }
    }

    #[test]
    fn out_of_range_is_an_error() {
        let p = SparsePiece::encode(&[px(1.0); 4], Span::new(5, 9), WireFormat::F32);
        let mut dst = [[0.0; 4]; 4];
        assert!(matches!(
            p.blend_over(&mut dst, 6),
            Err(PieceError::OutOfRange { .. })
        ));
        assert!(p.blend_under(&mut dst, 4).is_err());
        assert!(p.decode_into(&mut dst[..3], 5).is_err());
        p.blend_over(&mut dst, 5).unwrap();
        let e = p.blend_over(&mut dst, u32::MAX).unwrap_err();
        assert!(e.to_string().contains("[5, 9)"), "{e}");
        // An inconsistent in-memory piece is refused, not indexed out of bounds.
        let mut bad = p.clone();
        bad.data.truncate(bad.data.len() - 1);
        assert!(matches!(
            bad.blend_over(&mut dst, 5),
            Err(PieceError::DataLength { .. })
        ));
        let mut bad = p;
        bad.runs = vec![0, 9];
        assert!(matches!(
            bad.blend_over(&mut dst, 5),
            Err(PieceError::RunsSum { .. })
        ));
    }

    fn valid_bytes() -> Vec<u8> {
        let z = [0.0; 4];
        let p = SparsePiece::encode(&[z, px(0.5), px(0.25), z], Span::new(2, 6), WireFormat::F32);
        let mut b = Vec::new();
        p.write(&mut b);
        b
    }

    #[test]
    fn parse_rejects_malformed_input() {
        let good = valid_bytes();
        SparsePiece::parse(&good, 6).unwrap();
        for cut in 0..good.len() {
            let e = SparsePiece::parse(&good[..cut], 6).unwrap_err();
            assert!(matches!(e, PieceError::Truncated { .. }), "cut {cut}: {e}");
        }
        let mut b = good.clone();
        b.push(0);
        assert_eq!(
            SparsePiece::parse(&b, 6),
            Err(PieceError::TrailingBytes {
                offset: good.len(),
                extra: 1
            })
        );
        let (_, used) = SparsePiece::parse_prefix(&b, 6).unwrap();
        assert_eq!(used, good.len());

        // Span beyond the limit.
        assert!(matches!(
            SparsePiece::parse(&good, 5),
            Err(PieceError::SpanTooLarge { .. })
        ));
        // Magic, format.
        let mut b = good.clone();
        b[0] = b'X';
        assert!(matches!(
            SparsePiece::parse(&b, 6),
            Err(PieceError::BadMagic { .. })
        ));
        let mut b = good.clone();
        b[3] = 7;
        assert_eq!(
            SparsePiece::parse(&b, 6),
            Err(PieceError::BadFormat { found: 7 })
        );
        // Inverted span.
        let mut b = good.clone();
        b[4..8].copy_from_slice(&9u32.to_le_bytes());
        assert!(matches!(
            SparsePiece::parse(&b, 100),
            Err(PieceError::InvertedSpan { .. })
        ));
        // Runs not summing to the span: [1, 2, 1, 0] → [1, 2, 2, 0].
        let mut b = good.clone();
        b[16 + 8..16 + 12].copy_from_slice(&2u32.to_le_bytes());
        let e = SparsePiece::parse(&b, 6).unwrap_err();
        assert_eq!(
            e,
            PieceError::RunsSum {
                offset: 16,
                sum: 5,
                len: 4
            }
        );
        assert!(e.to_string().contains("byte offset 16"), "{e}");
        // More active pixels than data: [1, 2, 1, 0] → [1, 3, 0, 0].
        let mut b = good.clone();
        b[16 + 4..16 + 8].copy_from_slice(&3u32.to_le_bytes());
        b[16 + 8..16 + 12].copy_from_slice(&0u32.to_le_bytes());
        assert!(matches!(
            SparsePiece::parse(&b, 6),
            Err(PieceError::Truncated {
                what: "pixel data",
                ..
            })
        ));
        // Fewer active pixels than data: leftover bytes.
        let mut b = good.clone();
        b[16 + 4..16 + 8].copy_from_slice(&1u32.to_le_bytes());
        b[16 + 8..16 + 12].copy_from_slice(&2u32.to_le_bytes());
        assert!(matches!(
            SparsePiece::parse(&b, 6),
            Err(PieceError::TrailingBytes { .. })
        ));
        // Odd run count.
        let mut b = good.clone();
        b[12..16].copy_from_slice(&3u32.to_le_bytes());
        assert_eq!(
            SparsePiece::parse(&b, 6),
            Err(PieceError::OddRuns { count: 3 })
        );
    }

    #[test]
    fn absurd_counts_do_not_allocate() {
        // Runs count u32::MAX - 1 in a 20-byte buffer, with a huge span allowed.
        let mut b = Vec::new();
        b.extend_from_slice(b"SP\x01\x00");
        b.extend_from_slice(&0u32.to_le_bytes());
        b.extend_from_slice(&u32::MAX.to_le_bytes());
        b.extend_from_slice(&(u32::MAX - 1).to_le_bytes());
        b.extend_from_slice(&[0; 4]);
        assert_eq!(b.len(), 20);
        let e = SparsePiece::parse(&b, u32::MAX).unwrap_err();
        assert!(
            matches!(
                e,
                PieceError::Truncated {
                    what: "run lengths",
                    ..
                }
            ),
            "{e}"
        );
        // Same count, small span: rejected by the run bound.
        b[8..12].copy_from_slice(&10u32.to_le_bytes());
        assert!(matches!(
            SparsePiece::parse(&b, u32::MAX),
            Err(PieceError::TooManyRuns { .. })
        ));
        // Two runs claiming u32::MAX active pixels: data check, no allocation.
        let mut b = Vec::new();
        b.extend_from_slice(b"SP\x01\x01");
        b.extend_from_slice(&0u32.to_le_bytes());
        b.extend_from_slice(&u32::MAX.to_le_bytes());
        b.extend_from_slice(&2u32.to_le_bytes());
        b.extend_from_slice(&0u32.to_le_bytes());
        b.extend_from_slice(&u32::MAX.to_le_bytes());
        let e = SparsePiece::parse(&b, u32::MAX).unwrap_err();
        assert!(
            matches!(e, PieceError::Truncated { what: "pixel data", needed, .. } if needed == u32::MAX as u64 * 8),
            "{e}"
        );
    }

    fn pixels_strategy() -> impl Strategy<Value = Vec<Rgba>> {
        prop::collection::vec(
            prop_oneof![
                3 => Just([0.0f32; 4]),
                2 => (0.0f32..=1.0, 0.0f32..=1.0, 0.0f32..=1.0, 0.0f32..=1.0)
                    .prop_map(|(a, r, g, b)| [r * a, g * a, b * a, a]),
                1 => any::<[f32; 4]>(),
            ],
            0..300,
        )
    }

    #[test]
    fn shared_parse_matches_the_copying_parse_and_refuses_alike() {
        let bytes = valid_bytes();
        let whole = SparsePiece::parse(&bytes, 1 << 20).unwrap();
        let shared = SparsePiece::parse_shared(Bytes::from(bytes.clone()), 1 << 20).unwrap();
        assert_eq!(shared, whole);
        for cut in [0, 3, 15, 17, bytes.len() - 1] {
            let a = SparsePiece::parse(&bytes[..cut], 1 << 20).unwrap_err();
            let b = SparsePiece::parse_shared(Bytes::copy_from_slice(&bytes[..cut]), 1 << 20)
                .unwrap_err();
            assert_eq!(a, b, "cut at {cut}");
        }
        let mut long = bytes.clone();
        long.push(0);
        assert_eq!(
            SparsePiece::parse(&long, 1 << 20).unwrap_err(),
            SparsePiece::parse_shared(long.into(), 1 << 20).unwrap_err()
        );
    }

    #[test]
    fn split_parse_matches_the_whole_parse() {
        let bytes = valid_bytes();
        let whole = SparsePiece::parse(&bytes, 1 << 20).unwrap();
        let head_len = SparsePiece::HEADER_BYTES
            + SparsePiece::runs_bytes_in_header(&bytes[..16].try_into().unwrap()) as usize;
        let data = bytes[head_len..].to_vec();
        let split =
            SparsePiece::parse_split(&bytes[..head_len], data.clone().into(), 1 << 20).unwrap();
        assert_eq!(split, whole);
        // Data one byte short or long, or head with a trailing byte: refused.
        let short = data[..data.len() - 1].to_vec();
        assert!(SparsePiece::parse_split(&bytes[..head_len], short.into(), 1 << 20).is_err());
        let mut long = data.clone();
        long.push(0);
        assert!(SparsePiece::parse_split(&bytes[..head_len], long.into(), 1 << 20).is_err());
        assert!(SparsePiece::parse_split(&bytes[..head_len + 1], data.into(), 1 << 20).is_err());
    }

    /// Pixels in runs of 0..40 alike pixels, active ones including `-0.0` and denormals
    /// (bits set, values ~0): the layouts' block scan sees whole blocks and run ends at
    /// every offset within a block.
    fn runs_strategy() -> impl Strategy<Value = Vec<Rgba>> {
        let active = prop_oneof![
            Just([-0.0f32, 0.0, 0.0, 0.0]),
            Just([0.0f32, 0.0, 0.0, f32::from_bits(1)]),
            (0.0f32..=1.0).prop_map(|a| [a, a, a, a]),
        ];
        prop::collection::vec((any::<bool>(), 0usize..40, active), 0..40).prop_map(|runs| {
            runs.into_iter()
                .flat_map(|(on, n, px)| std::iter::repeat_n(if on { px } else { [0.0; 4] }, n))
                .collect()
        })
    }

    /// The layout as a plain pixel-by-pixel scan finds it.
    fn reference_runs(pixels: &[Rgba]) -> Vec<u32> {
        let mut b = RunBuilder::default();
        for p in pixels {
            if p.iter().all(|c| c.to_bits() == 0) {
                b.inactive(1);
            } else {
                b.active(1);
            }
        }
        b.finish().runs
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]

        /// The block scan finds the runs a pixel-by-pixel scan does, also across segments.
        #[test]
        fn layouts_match_a_pixel_by_pixel_scan(pixels in runs_strategy(), zeros in 0usize..20, cut in 0usize..400) {
            let layout = PieceLayout::of(&pixels);
            prop_assert_eq!(&layout.runs, &reference_runs(&pixels));
            prop_assert_eq!(
                layout.active,
                pixels.iter().filter(|p| p.iter().any(|c| c.to_bits() != 0)).count()
            );
            let cut = cut.min(pixels.len());
            let (a, b) = pixels.split_at(cut);
            let parts = PieceLayout::of_segments(&[
                Segment::Pixels(a),
                Segment::Zeros(zeros),
                Segment::Pixels(b),
            ]);
            let mut joined = a.to_vec();
            joined.extend(std::iter::repeat_n([0.0f32; 4], zeros));
            joined.extend_from_slice(b);
            prop_assert_eq!(&parts.runs, &reference_runs(&joined));
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        /// Encoding straight into memory of the layout's size gives the very bytes of
        /// encoding into a piece and writing it, in both formats.
        #[test]
        fn write_into_equals_encode_then_write(pixels in pixels_strategy(), start in 0u32..1000) {
            let span = Span::new(start, start + pixels.len() as u32);
            for format in [WireFormat::F32, WireFormat::F16] {
                let mut want = Vec::new();
                SparsePiece::encode(&pixels, span, format).write(&mut want);
                let layout = PieceLayout::of(&pixels);
                let mut got = vec![0xAAu8; layout.byte_len(format)];
                layout.write_segments_into(&[Segment::Pixels(&pixels)], span, format, &mut got);
                prop_assert_eq!(got, want);
            }
        }

        #[test]
        fn lz4_roundtrip_is_exact_and_random_bytes_never_panic(
            pixels in pixels_strategy(),
            start in 0u32..1000,
            f16 in any::<bool>(),
            junk in prop::collection::vec(any::<u8>(), 0..200),
        ) {
            let span = Span::new(start, start + pixels.len() as u32);
            let format = if f16 { WireFormat::F16 } else { WireFormat::F32 };
            let p = SparsePiece::encode(&pixels, span, format);
            prop_assert_eq!(SparsePiece::parse_lz4(&p.write_lz4().unwrap(), span.end).unwrap(), p);
            let _ = SparsePiece::parse_lz4(&junk, 1 << 20);
        }

        #[test]
        fn roundtrip_f32_is_exact(pixels in pixels_strategy(), start in 0u32..1000) {
            let span = Span::new(start, start + pixels.len() as u32);
            let p = SparsePiece::encode(&pixels, span, WireFormat::F32);
            p.check().unwrap();
            let q = roundtrip(&p, span.end);
            prop_assert_eq!(&q, &p);
            let active = pixels.iter().filter(|x| x.iter().any(|c| c.to_bits() != 0)).count();
            prop_assert_eq!(q.active_pixels(), active);
            let mut out = vec![[1.0; 4]; pixels.len()];
            q.decode_into(&mut out, start).unwrap();
            let same = out.iter().zip(&pixels).all(|(a, b)| {
                a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
            });
            prop_assert!(same);
        }

        #[test]
        fn roundtrip_f16_rounds_to_nearest(pixels in pixels_strategy()) {
            let span = Span::new(0, pixels.len() as u32);
            let p = SparsePiece::encode(&pixels, span, WireFormat::F16);
            let q = roundtrip(&p, span.end);
            prop_assert_eq!(&q, &p);
            let mut out = vec![[1.0; 4]; pixels.len()];
            q.decode_into(&mut out, 0).unwrap();
            for (a, b) in out.iter().zip(&pixels) {
                for c in 0..4 {
                    let want = f16::from_f32(b[c]).to_f32();
                    prop_assert!(a[c].to_bits() == want.to_bits() || (a[c].is_nan() && want.is_nan()));
                }
            }
        }

        #[test]
        fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..200), max in any::<u32>()) {
            let _ = SparsePiece::parse(&bytes, max);
            // With a valid header in front, the deeper checks get exercised too.
            let mut b = b"SP\x01".to_vec();
            b.push(bytes.first().copied().unwrap_or(0) % 2);
            b.extend_from_slice(&bytes);
            if let Ok(p) = SparsePiece::parse(&b, max) {
                p.check().unwrap();
                // Pieces with data are small; only all-inactive ones can claim big spans.
                prop_assert!(p.active_pixels() <= bytes.len() / 8);
                let mut dst = vec![[0.0; 4]; p.span.len().min(1 << 16) as usize];
                let r = p.blend_over(&mut dst, p.span.start);
                prop_assert_eq!(r.is_ok(), p.span.len() <= 1 << 16);
            }
        }

        #[test]
        fn corrupted_valid_pieces_never_panic(flip in 0usize..64, val in any::<u8>()) {
            let mut b = valid_bytes();
            let i = flip % b.len();
            b[i] = val;
            if let Ok(p) = SparsePiece::parse(&b, 64) {
                p.check().unwrap();
                let mut dst = vec![[0.0; 4]; 64];
                p.blend_under(&mut dst, 0).unwrap();
            }
        }
    }
}
