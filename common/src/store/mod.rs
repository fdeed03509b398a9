//! The page-store file format and its reader.
//!
//! One file per data set (a volume or a horizon). Layout, all little-endian:
//!
//! ```text
//! 0        preamble (64 bytes): magic "STRATAPS", format version, offsets and lengths of the
//!          header and the index, CRC-32C of header, index and preamble
//! 64       data section: page payloads, each checksummed (CRC-32C of the stored bytes) and
//!          optionally LZ4-compressed after a byte shuffle; constant and empty pages store nothing
//! ...      header: bincode 2 (serde) of `StoreHeader` (format 3; formats 1 and 2, still
//!          read, end before the trailing value statistics and vertical domain)
//! ...      index: one 40-byte `IndexEntry` per page, sorted by page id, i.e. by level and then
//!          Z-order (Morton) within the level
//! ```
//!
//! The header and index come last so that the writer can stream pages with bounded memory
//! and write the index once every page's offset is known; the preamble is patched last, and
//! the file is only renamed to its final name after that, so a reader never sees a
//! half-written store under the final name.
//!
//! Pages within a level are written in the order the builder produces them (rows of bricks
//! along the source's fastest axis); the index, not the data order, is Z-ordered.

mod error;
mod format;
mod reader;

pub use error::StoreError;
pub use format::{
    decode_payload, encode_page, encode_page_stored, Compression, DataKind, IndexEntry, Preamble,
    StoreHeader, Units, VerticalDomain, FORMAT_VERSION, MAGIC, MAX_HEADER_BYTES,
    MIN_FORMAT_VERSION, PAGE_COMPRESSED, PAGE_CONSTANT, PAGE_EMPTY, PREAMBLE_LEN,
};
pub(crate) use format::{shuffle, unshuffle};
pub use reader::{Page, PageStore};
