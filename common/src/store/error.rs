use crate::ids::PageId;
use std::path::PathBuf;

/// An error reading a page store. Every variant names the file; format errors also name the
/// byte offset and what was expected there.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StoreError {
    /// The operating system failed a read.
    #[error("{path}: {error}")]
    Io {
        /// The store.
        path: PathBuf,
        /// The cause: in the message, not a `source` as well (an error chain would print
        /// it twice).
        error: std::io::Error,
    },
    /// The file is not what the format says should be at `offset`.
    #[error("{path}: at byte {offset}: expected {expected}, found {found}")]
    Format {
        /// The store.
        path: PathBuf,
        /// Byte offset of the offending field.
        offset: u64,
        /// What the format requires there.
        expected: String,
        /// What the file holds.
        found: String,
    },
    /// The file ends before a section it declares.
    #[error(
        "{path}: truncated: {what} needs bytes {offset}..{end} but the file has {file_len} bytes"
    )]
    Truncated {
        /// The store.
        path: PathBuf,
        /// The section.
        what: String,
        /// Start of the section.
        offset: u64,
        /// End of the section.
        end: u64,
        /// Actual file length.
        file_len: u64,
    },
    /// A page's stored bytes do not match their checksum.
    #[error("{path}: {page} at byte {offset} ({len} bytes): checksum mismatch: expected crc32c {expected:08x}, found {found:08x}")]
    Checksum {
        /// The store.
        path: PathBuf,
        /// The page.
        page: PageId,
        /// Offset of its payload.
        offset: u64,
        /// Stored length.
        len: u32,
        /// Checksum in the index.
        expected: u32,
        /// Checksum of the bytes read.
        found: u32,
    },
    /// A page id that the store does not hold.
    #[error("{path}: no {page} in this store")]
    NoSuchPage {
        /// The store.
        path: PathBuf,
        /// The page.
        page: PageId,
    },
}
