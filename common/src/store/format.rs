use super::StoreError;
use crate::filter::CoarsenFilter;
use crate::geo::{Affine3, SurveyGrid};
use crate::ids::PageId;
use crate::pyramid::{Dim, Pyramid};
use crate::sample::SampleType;
use bytemuck::{Pod, Zeroable};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// File magic.
pub const MAGIC: [u8; 8] = *b"STRATAPS";
/// Current format version (2: the header holds [`StoreHeader::stats`]; 3: it also holds
/// [`StoreHeader::vertical_domain`]). Readers accept [`MIN_FORMAT_VERSION`]..=this and
/// refuse other versions with a clear error.
pub const FORMAT_VERSION: u32 = 3;
/// The oldest format version readers accept: version 1 lacks [`StoreHeader::stats`].
pub const MIN_FORMAT_VERSION: u32 = 1;
/// Length of the fixed preamble.
pub const PREAMBLE_LEN: u64 = 64;
/// Upper bound on the encoded header, checked before allocating.
pub const MAX_HEADER_BYTES: u64 = 1 << 20;

/// Page flag: the payload is LZ4-compressed (after a byte shuffle for multi-byte samples).
pub const PAGE_COMPRESSED: u32 = 1;
/// Page flag: every sample equals `min` (== `max`); no payload is stored.
pub const PAGE_CONSTANT: u32 = 2;
/// Page flag: every sample is no-data (volumes) or a hole (horizons); no payload is stored.
pub const PAGE_EMPTY: u32 = 4;

/// What a store holds.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum DataKind {
    /// A scalar volume: an octree of bricks of `sample_type` samples.
    Volume,
    /// A horizon: a quadtree of tiles of f32 heights plus a u8 validity mask.
    Horizon,
}

/// Per-page compression.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Compression {
    /// Pages are stored raw.
    None,
    /// Pages are byte-shuffled and LZ4-compressed when that makes them smaller.
    Lz4,
}

impl Compression {
    /// Command-line name.
    pub fn name(self) -> &'static str {
        match self {
            Compression::None => "none",
            Compression::Lz4 => "lz4",
        }
    }
}

/// Units of the world axes.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Units {
    /// Unit of world x and y (e.g. "m").
    pub lateral: String,
    /// Unit of world z (e.g. "ms" for two-way time, "m" for depth).
    pub vertical: String,
}

impl Default for Units {
    fn default() -> Self {
        Units {
            lateral: "m".into(),
            vertical: "m".into(),
        }
    }
}

/// Whether world z is time or depth (seismic stores; `None` where the source does not say,
/// as for raw grids and stores written before format 3).
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum VerticalDomain {
    /// Two-way travel time.
    Time,
    /// Depth.
    Depth,
}

impl VerticalDomain {
    /// Command-line name.
    pub fn name(self) -> &'static str {
        match self {
            VerticalDomain::Time => "time",
            VerticalDomain::Depth => "depth",
        }
    }
}

/// The versioned header of a store.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StoreHeader {
    /// Volume or horizon.
    pub kind: DataKind,
    /// Human-readable name.
    pub name: String,
    /// Level-0 samples per axis (horizons: `[n_inline, n_xline, 1]`).
    pub dims: [u64; 3],
    /// Stored element type (horizons: always f32 heights).
    pub sample_type: SampleType,
    /// Smallest and largest valid level-0 value (`[NaN, NaN]` if there is none).
    pub value_range: [f64; 2],
    /// Sentinel that marks no-data in integer volumes (f32 uses NaN).
    pub no_data: Option<f32>,
    /// Page size per axis, border included.
    pub page_size: u32,
    /// Border samples per side.
    pub border: u32,
    /// Number of levels.
    pub levels: u32,
    /// Filter that built each coarse level from the one below.
    pub filter: CoarsenFilter,
    /// Page compression.
    pub compression: Compression,
    /// Level-0 sample index `(i, j, k)` to world `(x, y, z)`. Horizons: `(i, j, height)`.
    pub transform: Affine3,
    /// Units of the world axes.
    pub units: Units,
    /// The survey's lateral grid, if known.
    pub survey: Option<SurveyGrid>,
    /// Number of valid (not no-data) level-0 samples.
    pub valid_samples: u64,
    /// Digest of the level-0 samples at ingest (see [`crate::digest`]).
    pub digest: u64,
    /// Where the data came from (file name, text header summary, tool version).
    pub source: String,
    /// Mean, RMS and percentiles of the valid level-0 values, computed at ingest (`None`
    /// in stores of format version 1, and for a store without valid samples). Last, so a
    /// version-1 header decodes with it absent.
    pub stats: Option<crate::stats::ValueStats>,
    /// Whether world z is time or depth, where the source said or the user chose (`None`
    /// in stores of format versions 1 and 2). Last, so older headers decode with it absent.
    pub vertical_domain: Option<VerticalDomain>,
}

impl StoreHeader {
    /// The tree layout the header describes.
    pub fn pyramid(&self) -> Result<Pyramid, crate::pyramid::PyramidError> {
        let dim = match self.kind {
            DataKind::Volume => Dim::Three,
            DataKind::Horizon => Dim::Two,
        };
        Pyramid::new(dim, self.dims, self.page_size, self.border)
    }
    /// Raw payload bytes of one (non-constant) page.
    pub fn page_raw_len(&self) -> usize {
        let p = self.page_size as usize;
        match self.kind {
            DataKind::Volume => p * p * p * self.sample_type.size(),
            DataKind::Horizon => p * p * 5,
        }
    }
}

/// One entry of the on-disk index. `#[repr(C)]` and `Pod`: the index is read with one
/// `pread` and cast, and the worker hands the same array to its page tables.
#[repr(C)]
#[derive(Copy, Clone, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct IndexEntry {
    /// Page id (data set 0).
    pub id: PageId,
    /// Byte offset of the stored payload (0 for constant and empty pages).
    pub offset: u64,
    /// Stored payload length (0 for constant and empty pages).
    pub stored_len: u32,
    /// CRC-32C of the stored payload.
    pub checksum: u32,
    /// `PAGE_*` flags.
    pub flags: u32,
    /// Number of valid samples in the page (border included).
    pub valid: u32,
    /// Smallest valid value the page holds (border included): a conservative bound for
    /// empty-space skipping against a transfer function and for horizon min-max trees.
    pub min: f32,
    /// Largest valid value the page holds (border included).
    pub max: f32,
}

/// Size of an encoded [`IndexEntry`].
pub(crate) const INDEX_ENTRY_LEN: u64 = std::mem::size_of::<IndexEntry>() as u64;
const _: () = assert!(INDEX_ENTRY_LEN == 40);

impl IndexEntry {
    /// Whether the page has a payload on disk.
    pub fn has_payload(&self) -> bool {
        self.flags & (PAGE_CONSTANT | PAGE_EMPTY) == 0
    }
}

/// The fixed-size preamble at offset 0.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct Preamble {
    /// Format version.
    pub version: u32,
    /// Offset of the encoded header.
    pub header_offset: u64,
    /// Length of the encoded header.
    pub header_len: u64,
    /// Offset of the index.
    pub index_offset: u64,
    /// Number of index entries.
    pub index_count: u64,
    /// CRC-32C of the encoded header.
    pub header_crc: u32,
    /// CRC-32C of the index bytes.
    pub index_crc: u32,
}

impl Preamble {
    /// Encodes the preamble, with its own CRC in the last 4 bytes.
    pub fn encode(&self) -> [u8; PREAMBLE_LEN as usize] {
        let mut b = [0u8; PREAMBLE_LEN as usize];
        b[0..8].copy_from_slice(&MAGIC);
        b[8..12].copy_from_slice(&self.version.to_le_bytes());
        b[16..24].copy_from_slice(&self.header_offset.to_le_bytes());
        b[24..32].copy_from_slice(&self.header_len.to_le_bytes());
        b[32..40].copy_from_slice(&self.index_offset.to_le_bytes());
        b[40..48].copy_from_slice(&self.index_count.to_le_bytes());
        b[48..52].copy_from_slice(&self.header_crc.to_le_bytes());
        b[52..56].copy_from_slice(&self.index_crc.to_le_bytes());
        let crc = crc32c::crc32c(&b[..60]);
        b[60..64].copy_from_slice(&crc.to_le_bytes());
        b
    }

    /// Decodes and validates a preamble read from `path`.
    pub fn decode(path: &Path, b: &[u8]) -> Result<Self, StoreError> {
        let err = |offset: u64, expected: &str, found: String| StoreError::Format {
            path: path.to_path_buf(),
            offset,
            expected: expected.to_string(),
            found,
        };
        if b.len() < PREAMBLE_LEN as usize {
            return Err(err(
                0,
                "a 64-byte Strata page-store preamble",
                format!("{} bytes", b.len()),
            ));
        }
        if b[0..8] != MAGIC {
            return Err(err(
                0,
                "magic \"STRATAPS\" (a Strata page store)",
                format!("{:02x?}", &b[0..8]),
            ));
        }
        let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
        let u64_at = |o: usize| u64::from_le_bytes(b[o..o + 8].try_into().unwrap());
        let version = u32_at(8);
        if !(MIN_FORMAT_VERSION..=FORMAT_VERSION).contains(&version) {
            return Err(err(
                8,
                &format!("format version {MIN_FORMAT_VERSION}..={FORMAT_VERSION}"),
                format!("version {version}"),
            ));
        }
        let crc = crc32c::crc32c(&b[..60]);
        if crc != u32_at(60) {
            return Err(err(
                60,
                &format!("preamble crc32c {crc:08x}"),
                format!("{:08x}", u32_at(60)),
            ));
        }
        Ok(Preamble {
            version,
            header_offset: u64_at(16),
            header_len: u64_at(24),
            index_offset: u64_at(32),
            index_count: u64_at(40),
            header_crc: u32_at(48),
            index_crc: u32_at(52),
        })
    }
}

/// Shuffles bytes so that byte `k` of every element is contiguous (LZ4 then finds the
/// runs in slowly varying high bytes of i16/f32 samples). Bytes past the last whole element
/// follow as they are: a horizon page of odd side (`5·page²` bytes in 4-byte elements)
/// ends in one, its corner's mask byte, which had been dropped (stored as 0, a hole).
pub(crate) fn shuffle(data: &[u8], elem: usize) -> Vec<u8> {
    if elem <= 1 {
        return data.to_vec();
    }
    let n = data.len() / elem;
    let mut out = vec![0u8; data.len()];
    for (i, e) in data.chunks_exact(elem).enumerate() {
        for (k, &byte) in e.iter().enumerate() {
            out[k * n + i] = byte;
        }
    }
    out[n * elem..].copy_from_slice(&data[n * elem..]);
    out
}

/// Undoes [`shuffle`].
pub(crate) fn unshuffle(data: &[u8], elem: usize) -> Vec<u8> {
    if elem <= 1 {
        return data.to_vec();
    }
    let n = data.len() / elem;
    let mut out = vec![0u8; data.len()];
    for (i, e) in out.chunks_exact_mut(elem).enumerate() {
        for (k, byte) in e.iter_mut().enumerate() {
            *byte = data[k * n + i];
        }
    }
    out[n * elem..].copy_from_slice(&data[n * elem..]);
    out
}

/// Encodes one page of `f32` samples (`NaN` = no-data/hole) into its index entry (without
/// offset) and stored bytes (empty for constant and empty pages).
///
/// Samples must already be quantized to the header's sample type.
pub fn encode_page(header: &StoreHeader, id: PageId, samples: &[f32]) -> (IndexEntry, Vec<u8>) {
    encode(header, id, samples, true)
}

/// [`encode_page`] with the samples always stored, even when they are all one value: for a
/// coarse page whose index bounds are then widened to its children's, since a constant
/// page is read back as its entry's `min`.
pub fn encode_page_stored(
    header: &StoreHeader,
    id: PageId,
    samples: &[f32],
) -> (IndexEntry, Vec<u8>) {
    encode(header, id, samples, false)
}

fn encode(
    header: &StoreHeader,
    id: PageId,
    samples: &[f32],
    constant: bool,
) -> (IndexEntry, Vec<u8>) {
    let (mut min, mut max, mut valid) = (f32::INFINITY, f32::NEG_INFINITY, 0u32);
    for &v in samples {
        if !v.is_nan() {
            min = min.min(v);
            max = max.max(v);
            valid += 1;
        }
    }
    let mut e = IndexEntry {
        id,
        valid,
        ..Default::default()
    };
    if valid == 0 {
        e.flags = PAGE_EMPTY;
        e.min = f32::NAN;
        e.max = f32::NAN;
        return (e, Vec::new());
    }
    e.min = min;
    e.max = max;
    if constant && valid as usize == samples.len() && min == max {
        e.flags = PAGE_CONSTANT;
        return (e, Vec::new());
    }
    let mut raw = Vec::with_capacity(header.page_raw_len());
    let elem = match header.kind {
        DataKind::Volume => {
            header
                .sample_type
                .encode_le(samples, header.no_data, &mut raw);
            header.sample_type.size()
        }
        DataKind::Horizon => {
            // Heights (holes stored as 0.0, never NaN, so a GPU bilinear fetch cannot be
            // poisoned), then the validity mask, 255 = valid.
            for &v in samples {
                raw.extend_from_slice(&(if v.is_nan() { 0.0f32 } else { v }).to_le_bytes());
            }
            raw.extend(samples.iter().map(|v| if v.is_nan() { 0u8 } else { 255 }));
            4
        }
    };
    let mut stored = raw;
    if header.compression == Compression::Lz4 {
        let c = lz4_flex::compress(&shuffle(&stored, elem));
        if c.len() < stored.len() {
            stored = c;
            e.flags |= PAGE_COMPRESSED;
        }
    }
    e.stored_len = stored.len() as u32;
    e.checksum = crc32c::crc32c(&stored);
    (e, stored)
}

/// Decodes a page's stored bytes (already checksum-verified) or its constant/empty flag into
/// `out` (`page_samples` long, `NaN` = no-data/hole).
pub fn decode_payload(
    header: &StoreHeader,
    entry: &IndexEntry,
    stored: &[u8],
    out: &mut [f32],
) -> Result<(), String> {
    if entry.flags & PAGE_EMPTY != 0 {
        out.fill(f32::NAN);
        return Ok(());
    }
    if entry.flags & PAGE_CONSTANT != 0 {
        out.fill(entry.min);
        return Ok(());
    }
    let raw_len = header.page_raw_len();
    let elem = match header.kind {
        DataKind::Volume => header.sample_type.size(),
        DataKind::Horizon => 4,
    };
    let raw;
    let bytes: &[u8] = if entry.flags & PAGE_COMPRESSED != 0 {
        let d = lz4_flex::decompress(stored, raw_len).map_err(|e| format!("LZ4 payload ({e})"))?;
        if d.len() != raw_len {
            return Err(format!("{raw_len} decompressed bytes, got {}", d.len()));
        }
        raw = unshuffle(&d, elem);
        &raw
    } else {
        stored
    };
    if bytes.len() != raw_len {
        return Err(format!(
            "a {raw_len}-byte payload, got {} bytes",
            bytes.len()
        ));
    }
    match header.kind {
        DataKind::Volume => header.sample_type.decode_le(bytes, header.no_data, out),
        DataKind::Horizon => {
            let n = out.len();
            let (h, m) = bytes.split_at(n * 4);
            for (i, o) in out.iter_mut().enumerate() {
                *o = if m[i] == 0 {
                    f32::NAN
                } else {
                    f32::from_le_bytes([h[4 * i], h[4 * i + 1], h[4 * i + 2], h[4 * i + 3]])
                };
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn shuffle_round_trip() {
        // Lengths that are not a multiple of the element too (a horizon page of odd side).
        for len in [40u8, 41, 42, 43, 125] {
            let d: Vec<u8> = (1..=len).collect();
            for e in [1, 2, 4] {
                assert_eq!(
                    unshuffle(&shuffle(&d, e), e),
                    d,
                    "{len} bytes, {e}-byte elements"
                );
            }
        }
    }

    #[test]
    fn preamble_round_trip_and_corruption() {
        let p = Preamble {
            version: FORMAT_VERSION,
            header_offset: 1000,
            header_len: 77,
            index_offset: 1077,
            index_count: 9,
            header_crc: 1,
            index_crc: 2,
        };
        let b = p.encode();
        assert_eq!(Preamble::decode(Path::new("x"), &b).unwrap(), p);
        let mut c = b;
        c[30] ^= 1;
        let e = Preamble::decode(Path::new("x"), &c)
            .unwrap_err()
            .to_string();
        assert!(e.contains("at byte 60"), "{e}");
        let mut c = b;
        c[0] = b'X';
        assert!(Preamble::decode(Path::new("x"), &c)
            .unwrap_err()
            .to_string()
            .contains("magic"));
    }

    fn header(kind: DataKind, t: SampleType, comp: Compression) -> StoreHeader {
        StoreHeader {
            kind,
            name: "t".into(),
            dims: [8, 8, if kind == DataKind::Volume { 8 } else { 1 }],
            sample_type: t,
            value_range: [0.0, 1.0],
            no_data: None,
            page_size: 4,
            border: 1,
            levels: 1,
            filter: CoarsenFilter::Mean,
            compression: comp,
            transform: Affine3::IDENTITY,
            units: Units::default(),
            survey: None,
            valid_samples: 0,
            digest: 0,
            source: String::new(),
            stats: None,
            vertical_domain: None,
        }
    }

    proptest! {
        #[test]
        fn page_codec_round_trip(vals in prop::collection::vec(prop::option::weighted(0.9, -300i32..300), 64),
                                 comp in prop::sample::select(vec![Compression::None, Compression::Lz4]),
                                 t in prop::sample::select(vec![SampleType::I16, SampleType::F32])) {
            let h = header(DataKind::Volume, t, comp);
            let samples: Vec<f32> = vals.iter().map(|v| v.map_or(f32::NAN, |x| x as f32)).collect();
            let h = StoreHeader { no_data: Some(-32768.0), ..h };
            let (e, stored) = encode_page(&h, PageId(5), &samples);
            prop_assert_eq!(e.checksum, if e.has_payload() { crc32c::crc32c(&stored) } else { 0 });
            let mut out = vec![0.0; 64];
            decode_payload(&h, &e, &stored, &mut out).unwrap();
            for (a, b) in samples.iter().zip(&out) {
                prop_assert!(a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()));
            }
        }

        #[test]
        fn horizon_codec_round_trip(vals in prop::collection::vec(prop::option::weighted(0.8, -1e4f32..1e4), 16),
                                    comp in prop::sample::select(vec![Compression::None, Compression::Lz4])) {
            let h = header(DataKind::Horizon, SampleType::F32, comp);
            let samples: Vec<f32> = vals.iter().map(|v| v.unwrap_or(f32::NAN)).collect();
            let (e, stored) = encode_page(&h, PageId(1), &samples);
            let mut out = vec![0.0; 16];
            decode_payload(&h, &e, &stored, &mut out).unwrap();
            for (a, b) in samples.iter().zip(&out) {
                prop_assert!(a == b || (a.is_nan() && b.is_nan()));
            }
        }
    }

    #[test]
    fn constant_and_empty_pages_store_nothing() {
        let h = header(DataKind::Volume, SampleType::U8, Compression::None);
        let (e, s) = encode_page(&h, PageId(0), &[7.0; 64]);
        assert!(s.is_empty() && e.flags == PAGE_CONSTANT && e.min == 7.0);
        let (e, s) = encode_page(&h, PageId(0), &[f32::NAN; 64]);
        assert!(s.is_empty() && e.flags == PAGE_EMPTY);
    }
}
