use super::format::{
    decode_payload, IndexEntry, Preamble, StoreHeader, FORMAT_VERSION, INDEX_ENTRY_LEN,
    MAX_HEADER_BYTES, PREAMBLE_LEN,
};
use super::StoreError;
use crate::ids::PageId;
use crate::pyramid::Pyramid;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// A decoded page: `page_samples` values, `NaN` for no-data (volumes) or holes (horizons).
#[derive(Clone, Debug, PartialEq)]
pub struct Page {
    /// Which page.
    pub id: PageId,
    /// Samples, x fastest, border included.
    pub samples: Vec<f32>,
}

/// An open page store. All reads are positional (`pread`), so `&PageStore` can be shared by
/// any number of threads that read pages concurrently.
#[derive(Debug)]
pub struct PageStore {
    path: PathBuf,
    file: File,
    file_len: u64,
    header: StoreHeader,
    pyramid: Pyramid,
    index: Vec<IndexEntry>,
}

fn read_exact_at(file: &File, path: &Path, buf: &mut [u8], offset: u64) -> Result<(), StoreError> {
    file.read_exact_at(buf, offset)
        .map_err(|error| StoreError::Io {
            path: path.to_path_buf(),
            error,
        })
}

impl PageStore {
    /// Opens a store and validates its preamble, header and index. Every size read from the
    /// file is checked against the file's length before anything is allocated.
    pub fn open(path: impl AsRef<Path>) -> Result<Self, StoreError> {
        let path = path.as_ref().to_path_buf();
        let io = |error| StoreError::Io {
            path: path.clone(),
            error,
        };
        let file = File::open(&path).map_err(io)?;
        let file_len = file.metadata().map_err(io)?.len();
        let fmt = |offset: u64, expected: String, found: String| StoreError::Format {
            path: path.clone(),
            offset,
            expected,
            found,
        };
        let truncated = |what: &str, offset: u64, end: u64| StoreError::Truncated {
            path: path.clone(),
            what: what.into(),
            offset,
            end,
            file_len,
        };
        if file_len < PREAMBLE_LEN {
            return Err(truncated("the preamble", 0, PREAMBLE_LEN));
        }
        let mut pre = [0u8; PREAMBLE_LEN as usize];
        read_exact_at(&file, &path, &mut pre, 0)?;
        let pre = Preamble::decode(&path, &pre)?;

        if pre.header_len > MAX_HEADER_BYTES {
            return Err(fmt(
                24,
                format!("a header of at most {MAX_HEADER_BYTES} bytes"),
                format!("{} bytes", pre.header_len),
            ));
        }
        let hend = pre.header_offset.saturating_add(pre.header_len);
        if hend > file_len {
            return Err(truncated("the header", pre.header_offset, hend));
        }
        let mut hb = vec![0u8; pre.header_len as usize];
        read_exact_at(&file, &path, &mut hb, pre.header_offset)?;
        let crc = crc32c::crc32c(&hb);
        if crc != pre.header_crc {
            return Err(fmt(
                pre.header_offset,
                format!("header with crc32c {:08x}", pre.header_crc),
                format!("crc32c {crc:08x}"),
            ));
        }
        // Version 1 ends before `stats`, version 2 before `vertical_domain`: each absent
        // trailing option is bincode's `None` tag.
        hb.resize(hb.len() + (FORMAT_VERSION - pre.version) as usize, 0);
        // A length prefix inside the header is untrusted: bincode claims what a string or
        // list would take before allocating it, and the limit refuses more than a header of
        // at most MAX_HEADER_BYTES can hold (no element decodes from under 1 byte to over 16).
        let limited =
            bincode::config::standard().with_limit::<{ 16 * MAX_HEADER_BYTES as usize }>();
        let (header, _): (StoreHeader, usize) = bincode::serde::decode_from_slice(&hb, limited)
            .map_err(|e| {
                fmt(
                    pre.header_offset,
                    "a bincode-encoded store header".into(),
                    format!("undecodable bytes ({e})"),
                )
            })?;
        let pyramid = header.pyramid().map_err(|e| {
            fmt(
                pre.header_offset,
                "a valid page layout".into(),
                e.to_string(),
            )
        })?;
        // A page of one sample per axis has no interval to interpolate in: the casters'
        // clamps to [0, page − 1) would be empty (ingest writes 32 to 128).
        if header.page_size < 2 {
            return Err(fmt(
                pre.header_offset,
                "pages of at least 2 samples per axis".into(),
                format!("page size {}", header.page_size),
            ));
        }
        // Every ray and region goes through it: a NaN or singular transform would render
        // garbage, not fail.
        // Columns (index → world scales) of 1e-30..1e30: the display's z scale (at most
        // 1e6 either way) then keeps the transform invertible in f64.
        let columns_ok = (0..3).all(|c| {
            let n = (0..3)
                .map(|r| header.transform.rows[r][c].powi(2))
                .sum::<f64>()
                .sqrt();
            (1e-30..=1e30).contains(&n)
        });
        if !header.transform.is_finite() || !columns_ok || header.transform.inverse().is_none() {
            return Err(fmt(
                pre.header_offset,
                "a finite, invertible index→world transform with scales in 1e-30..1e30".into(),
                format!("{:?}", header.transform.rows),
            ));
        }
        // Counts that readers subtract from or index by.
        let samples = header.dims.iter().try_fold(1u64, |a, &d| a.checked_mul(d));
        if samples.is_none_or(|n| header.valid_samples > n) {
            return Err(fmt(
                pre.header_offset,
                format!("at most {samples:?} valid samples for {:?}", header.dims),
                format!("{}", header.valid_samples),
            ));
        }
        if let Some(s) = header
            .survey
            .as_ref()
            .filter(|s| s.n_inline == 0 || s.n_xline == 0)
        {
            return Err(fmt(
                pre.header_offset,
                "a survey grid of at least one inline and one crossline".into(),
                format!("{} inlines, {} crosslines", s.n_inline, s.n_xline),
            ));
        }
        if let Some(v) = header
            .no_data
            .filter(|&v| !header.sample_type.holds_sentinel(v))
        {
            return Err(fmt(
                pre.header_offset,
                format!("a no-data value that {} holds", header.sample_type.name()),
                format!("{v}"),
            ));
        }
        if pyramid.level_count() != header.levels as usize {
            return Err(fmt(
                pre.header_offset,
                format!("{} levels for these dimensions", pyramid.level_count()),
                format!("{} levels", header.levels),
            ));
        }
        if pre.index_count != pyramid.total_pages() {
            return Err(fmt(
                40,
                format!("{} index entries for this layout", pyramid.total_pages()),
                format!("{}", pre.index_count),
            ));
        }
        let ilen = pre.index_count.saturating_mul(INDEX_ENTRY_LEN);
        let iend = pre.index_offset.saturating_add(ilen);
        if iend > file_len {
            return Err(truncated("the index", pre.index_offset, iend));
        }
        // Up to MAX_TOTAL_PAGES entries (10 GiB): allocated fallibly, so a store this
        // machine cannot index is an error, not an abort.
        let mut index = Vec::new();
        if index.try_reserve_exact(pre.index_count as usize).is_err() {
            return Err(fmt(
                40,
                "an index this machine can hold".into(),
                format!("{} entries of {INDEX_ENTRY_LEN} bytes", pre.index_count),
            ));
        }
        index.resize(pre.index_count as usize, IndexEntry::default());
        read_exact_at(
            &file,
            &path,
            bytemuck::cast_slice_mut(&mut index),
            pre.index_offset,
        )?;
        if cfg!(target_endian = "big") {
            unreachable!("page stores are little-endian; big-endian hosts are not supported");
        }
        let crc = crc32c::crc32c(bytemuck::cast_slice(&index));
        if crc != pre.index_crc {
            return Err(fmt(
                pre.index_offset,
                format!("index with crc32c {:08x}", pre.index_crc),
                format!("crc32c {crc:08x}"),
            ));
        }
        // The index must list exactly the layout's pages, in Z-order, with payloads inside the data section.
        let mut k = 0usize;
        for l in 0..pyramid.level_count() {
            for b in pyramid.bricks_in_z_order(l) {
                let e = &index[k];
                let at = pre.index_offset + k as u64 * INDEX_ENTRY_LEN;
                let want = pyramid.id(l, b);
                if e.id != want {
                    return Err(fmt(
                        at,
                        format!("index entry for {want}"),
                        format!("{}", e.id),
                    ));
                }
                if e.has_payload() {
                    // Checked: a crafted offset must not wrap around past the bound.
                    let end = e.offset.saturating_add(e.stored_len as u64);
                    if e.offset < PREAMBLE_LEN || end > pre.header_offset.min(pre.index_offset) {
                        return Err(fmt(
                            at + 8,
                            format!(
                                "payload inside the data section {PREAMBLE_LEN}..{}",
                                pre.header_offset.min(pre.index_offset)
                            ),
                            format!("bytes {}..{end}", e.offset),
                        ));
                    }
                    if e.stored_len as usize
                        > header.page_raw_len() + header.page_raw_len() / 64 + 64
                    {
                        return Err(fmt(
                            at + 16,
                            format!(
                                "a stored length of at most about {} bytes",
                                header.page_raw_len()
                            ),
                            format!("{}", e.stored_len),
                        ));
                    }
                }
                k += 1;
            }
        }
        Ok(PageStore {
            path,
            file,
            file_len,
            header,
            pyramid,
            index,
        })
    }

    /// The file this store was opened from.
    pub fn path(&self) -> &Path {
        &self.path
    }
    /// File length in bytes.
    pub fn file_len(&self) -> u64 {
        self.file_len
    }
    /// The header.
    pub fn header(&self) -> &StoreHeader {
        &self.header
    }
    /// The tree layout.
    pub fn pyramid(&self) -> &Pyramid {
        &self.pyramid
    }
    /// The whole index, sorted by page id.
    pub fn index(&self) -> &[IndexEntry] {
        &self.index
    }
    /// The index entry of a page (data-set bits are ignored).
    pub fn entry(&self, id: PageId) -> Option<&IndexEntry> {
        let id = id.with_dataset(0);
        self.index
            .binary_search_by_key(&id, |e| e.id)
            .ok()
            .map(|i| &self.index[i])
    }

    /// Reads a page's stored bytes and verifies their checksum.
    pub fn read_stored(&self, entry: &IndexEntry) -> Result<Vec<u8>, StoreError> {
        if !entry.has_payload() {
            return Ok(Vec::new());
        }
        let mut buf = vec![0u8; entry.stored_len as usize];
        read_exact_at(&self.file, &self.path, &mut buf, entry.offset)?;
        let found = crc32c::crc32c(&buf);
        if found != entry.checksum {
            return Err(StoreError::Checksum {
                path: self.path.clone(),
                page: entry.id,
                offset: entry.offset,
                len: entry.stored_len,
                expected: entry.checksum,
                found,
            });
        }
        Ok(buf)
    }

    /// Reads, verifies and decodes a page into `out` (`page_samples` long).
    pub fn read_page_into(&self, id: PageId, out: &mut [f32]) -> Result<(), StoreError> {
        let entry = *self.entry(id).ok_or_else(|| StoreError::NoSuchPage {
            path: self.path.clone(),
            page: id,
        })?;
        let stored = self.read_stored(&entry)?;
        decode_payload(&self.header, &entry, &stored, out).map_err(|expected| StoreError::Format {
            path: self.path.clone(),
            offset: entry.offset,
            expected,
            found: format!("{} stored bytes that do not decode", entry.stored_len),
        })
    }

    /// Reads, verifies and decodes a page.
    pub fn read_page(&self, id: PageId) -> Result<Page, StoreError> {
        let mut samples = vec![0.0; self.pyramid.page_samples()];
        self.read_page_into(id, &mut samples)?;
        Ok(Page { id, samples })
    }

    /// Level-0 sample at `(x, y, z)` read through its page (slow; for tests and tools).
    pub fn sample_level(&self, level: usize, p: [u64; 3]) -> Result<f32, StoreError> {
        let c = self.pyramid.core3();
        let brick = [0, 1, 2].map(|a| (p[a] / c[a] as u64) as u32);
        let page = self.read_page(self.pyramid.id(level, brick))?;
        let o = self.pyramid.page_origin(brick);
        let pd = self.pyramid.page_dims();
        let l = [0, 1, 2].map(|a| (p[a] as i64 - o[a]) as usize);
        Ok(page.samples[(l[2] * pd[1] as usize + l[1]) * pd[0] as usize + l[0]])
    }
}
