//! Shared-memory segments between processes on one host, as MPI implementations pass
//! messages within a node.
//!
//! A segment is a file in the host's shared-memory folder (`/dev/shm`, a tmpfs): bytes
//! written to it stay in memory and never touch a disk. Each sender owns one segment per
//! receiver; per frame it writes its records from the start of the segment again, so
//! the pages it allocated in the first frame are reused by every later one.
//!
//! Authorisation rides on the authenticated QUIC connection: the sender creates the file
//! with a random 128-bit name, exclusively and readable by its own user only, and tells
//! the receiver the name over the connection. The receiver opens only names of that form,
//! refuses anything that is not a regular file of its own user with no group or other
//! permissions, and unlinks the name as soon as it has the file open, so nothing is
//! left in `/dev/shm` once both have it (and the memory goes when both close it).
//!
//! The receiver reads with `pread`, never through a mapping: a segment that a broken
//! peer truncates yields a short read (an error naming the peer), not a `SIGBUS`. Every
//! record starts with a header ([`strata_common::wire::encode_shm_record`]) that must
//! match the announcing message, and every size is checked against the receiver's limit
//! and the segment's length before anything is allocated.

use std::fs::{File, OpenOptions};
use std::os::unix::fs::{FileExt, MetadataExt, OpenOptionsExt};
use std::path::{Path, PathBuf};
use strata_common::composite::SparsePiece;
use strata_common::wire::{check_shm_record, encode_shm_record, ShmRef, SHM_RECORD_HEADER};

/// The host's shared-memory folder.
pub const SHM_DIR: &str = "/dev/shm";
/// Prefix of every segment's file name.
pub const PREFIX: &str = "strata-shm-";

/// Records start on cache-line boundaries.
const ALIGN: u64 = 64;

/// Why a segment could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ShmError {
    /// The announced name is not one a Strata sender creates.
    #[error("segment name {0:?} is not `{PREFIX}` and 32 hex digits")]
    BadName(String),
    /// Opening or creating failed.
    #[error("segment {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The error.
        source: std::io::Error,
    },
    /// The file is not a private regular file of this user.
    #[error("segment {path}: {why}")]
    NotPrivate {
        /// The file.
        path: String,
        /// What is wrong.
        why: String,
    },
    /// The record is larger than this receiver accepts.
    #[error("record of {len} bytes exceeds the limit of {limit} bytes")]
    TooLarge {
        /// Announced length.
        len: u64,
        /// The limit.
        limit: u64,
    },
    /// The record runs past the segment's end.
    #[error(
        "record at offset {offset} of {len} bytes runs past the segment's end at {size} bytes"
    )]
    PastEnd {
        /// Announced offset.
        offset: u64,
        /// Announced length.
        len: u64,
        /// The segment's length.
        size: u64,
    },
    /// The record is not a valid image piece.
    #[error("record at offset {offset}: {source}")]
    Piece {
        /// Announced offset.
        offset: u64,
        /// What is wrong.
        source: strata_common::composite::PieceError,
    },
    /// The record's header does not match the announcement.
    #[error("record at offset {offset}: {why}")]
    Header {
        /// Announced offset.
        offset: u64,
        /// The mismatch.
        why: String,
    },
}

/// This host's identity for shared memory: the kernel's boot id and the device and inode
/// of [`SHM_DIR`]. Two processes with the same id see the same segments (containers with
/// a private `/dev/shm` differ in the device). `None` where there is no such folder.
pub fn host_id() -> Option<String> {
    let boot = std::fs::read_to_string("/proc/sys/kernel/random/boot_id").ok()?;
    let m = std::fs::metadata(SHM_DIR).ok()?;
    if !m.is_dir() {
        return None;
    }
    Some(format!("{}/{}:{}", boot.trim(), m.dev(), m.ino()))
}

/// Whether `name` has the form a sender creates (no path separators, nothing else).
pub fn valid_name(name: &str) -> bool {
    name.strip_prefix(PREFIX)
        .is_some_and(|h| h.len() == 32 && h.bytes().all(|b| b.is_ascii_hexdigit()))
}

/// The sending side of one segment.
#[derive(Debug)]
pub struct ShmWriter {
    file: File,
    path: PathBuf,
    name: String,
    cursor: u64,
}

impl ShmWriter {
    /// Creates a fresh segment in [`SHM_DIR`].
    pub fn create() -> Result<ShmWriter, ShmError> {
        Self::create_in(Path::new(SHM_DIR))
    }

    /// Creates a fresh segment in `dir` (exclusively, mode 0600).
    pub fn create_in(dir: &Path) -> Result<ShmWriter, ShmError> {
        let hex: String = crate::secret::random_bytes::<16>()
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        let name = format!("{PREFIX}{hex}");
        let path = dir.join(&name);
        let file = OpenOptions::new()
            .read(true)
            .write(true)
            .create_new(true)
            .mode(0o600)
            .open(&path)
            .map_err(|source| ShmError::Io {
                path: path.display().to_string(),
                source,
            })?;
        Ok(ShmWriter {
            file,
            path,
            name,
            cursor: 0,
        })
    }

    /// The file name to announce to the receiver.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Starts a new frame: records are written from the start again. The receiver has
    /// read every record of the frame before (a frame completes only once every rank has
    /// received all its pieces).
    pub fn reset(&mut self) {
        self.cursor = 0;
    }

    /// Appends one record (header, then `payload`) and returns where it lies.
    pub fn write(
        &mut self,
        frame: u64,
        round: u32,
        from: u32,
        payload: &[u8],
    ) -> Result<ShmRef, ShmError> {
        self.write_parts(frame, round, from, &[payload])
    }

    /// Appends one record whose payload is `parts` one after the other (written straight
    /// from where they lie, never joined first).
    pub fn write_parts(
        &mut self,
        frame: u64,
        round: u32,
        from: u32,
        parts: &[&[u8]],
    ) -> Result<ShmRef, ShmError> {
        let at = ShmRef {
            offset: self.cursor,
            len: parts.iter().map(|p| p.len() as u64).sum(),
        };
        let header = encode_shm_record(frame, round, from, at.len);
        let io = |source| ShmError::Io {
            path: self.path.display().to_string(),
            source,
        };
        self.file.write_all_at(&header, at.offset).map_err(io)?;
        let mut pos = at.offset + SHM_RECORD_HEADER as u64;
        for part in parts {
            self.file.write_all_at(part, pos).map_err(io)?;
            pos += part.len() as u64;
        }
        self.cursor = pos.next_multiple_of(ALIGN);
        Ok(at)
    }
}

impl Drop for ShmWriter {
    fn drop(&mut self) {
        // Normally the receiver unlinked the name already; this covers a receiver that
        // never opened it.
        let _ = std::fs::remove_file(&self.path);
    }
}

/// The receiving side of one segment.
#[derive(Debug)]
pub struct ShmReader {
    file: File,
    path: String,
}

impl ShmReader {
    /// Opens the segment `name` in [`SHM_DIR`] that a peer announced, and unlinks it.
    pub fn open(name: &str) -> Result<ShmReader, ShmError> {
        Self::open_in(Path::new(SHM_DIR), name)
    }

    /// Opens the segment `name` in `dir`: only a regular file owned by this user with no
    /// group or other permissions. The name is unlinked once the file is open.
    pub fn open_in(dir: &Path, name: &str) -> Result<ShmReader, ShmError> {
        if !valid_name(name) {
            return Err(ShmError::BadName(name.chars().take(80).collect()));
        }
        let path = dir.join(name);
        let shown = path.display().to_string();
        let file = OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(&path)
            .map_err(|source| ShmError::Io {
                path: shown.clone(),
                source,
            })?;
        let m = file.metadata().map_err(|source| ShmError::Io {
            path: shown.clone(),
            source,
        })?;
        // SAFETY: geteuid has no preconditions and cannot fail.
        let me = unsafe { libc::geteuid() };
        let why = if !m.is_file() {
            Some("not a regular file".to_string())
        } else if m.uid() != me {
            Some(format!("owned by uid {}, not this user ({me})", m.uid()))
        } else if m.mode() & 0o077 != 0 {
            Some(format!(
                "mode {:o} lets other users in (expected 600)",
                m.mode() & 0o777
            ))
        } else {
            None
        };
        if let Some(why) = why {
            return Err(ShmError::NotPrivate { path: shown, why });
        }
        let _ = std::fs::remove_file(&path);
        Ok(ShmReader { file, path: shown })
    }

    /// Reads the image piece in the record at `at` (checked as [`record`](Self::record)
    /// does, then as [`SparsePiece::parse`] does, with spans up to `max_pixels`): header
    /// and run lengths first, then the pixel data straight into the piece's own buffer,
    /// so the piece costs one copy out of the segment.
    pub fn read_piece(
        &mut self,
        at: ShmRef,
        limit: u64,
        frame: u64,
        round: u32,
        from: u32,
        max_pixels: u32,
    ) -> Result<SparsePiece, ShmError> {
        let mut rec = self.record(at, limit, frame, round, from)?;
        let h = SparsePiece::HEADER_BYTES as u64;
        let header = rec.read(0, h.min(rec.len()))?;
        let bad = |source| ShmError::Piece {
            offset: at.offset,
            source,
        };
        let Ok(header) = <&[u8; SparsePiece::HEADER_BYTES]>::try_from(header.as_slice()) else {
            // Shorter than a header: let the parser say so.
            return SparsePiece::parse(&header, max_pixels).map_err(bad);
        };
        let head_len = h.saturating_add(SparsePiece::runs_bytes_in_header(header));
        if head_len > rec.len() {
            let all = rec.read(0, rec.len())?;
            return SparsePiece::parse(&all, max_pixels).map_err(bad);
        }
        let head = rec.read(0, head_len)?;
        let data = rec.read(head_len, rec.len() - head_len)?;
        SparsePiece::parse_split(&head, data, max_pixels).map_err(bad)
    }

    /// Checks the record at `at` (length against `limit` and the segment's end, header
    /// against the announced frame, round and sender position) and returns it for reading
    /// in parts.
    pub fn record(
        &mut self,
        at: ShmRef,
        limit: u64,
        frame: u64,
        round: u32,
        from: u32,
    ) -> Result<ShmRecord<'_>, ShmError> {
        if at.len > limit {
            return Err(ShmError::TooLarge { len: at.len, limit });
        }
        let size = self
            .file
            .metadata()
            .map_err(|source| ShmError::Io {
                path: self.path.clone(),
                source,
            })?
            .len();
        let end = at
            .offset
            .checked_add(SHM_RECORD_HEADER as u64)
            .and_then(|e| e.checked_add(at.len));
        if !matches!(end, Some(e) if e <= size) {
            return Err(ShmError::PastEnd {
                offset: at.offset,
                len: at.len,
                size,
            });
        }
        let mut rec = ShmRecord {
            reader: self,
            at,
            size,
        };
        let header = rec.read_raw(at.offset, SHM_RECORD_HEADER as u64)?;
        let header: &[u8; SHM_RECORD_HEADER] = header.as_slice().try_into().unwrap();
        check_shm_record(header, frame, round, from, at.len).map_err(|why| ShmError::Header {
            offset: at.offset,
            why,
        })?;
        Ok(rec)
    }
}

/// A checked record of a segment, read in parts.
#[derive(Debug)]
pub struct ShmRecord<'a> {
    reader: &'a mut ShmReader,
    at: ShmRef,
    size: u64,
}

impl ShmRecord<'_> {
    /// The payload's length.
    pub fn len(&self) -> u64 {
        self.at.len
    }

    /// Whether the payload is empty.
    pub fn is_empty(&self) -> bool {
        self.at.len == 0
    }

    /// Reads `len` payload bytes from `offset` (within the payload) into a new buffer,
    /// without zero-filling it first.
    pub fn read(&mut self, offset: u64, len: u64) -> Result<Vec<u8>, ShmError> {
        match offset.checked_add(len) {
            Some(e) if e <= self.at.len => {}
            _ => {
                return Err(ShmError::PastEnd {
                    offset: (self.at.offset + SHM_RECORD_HEADER as u64).saturating_add(offset),
                    len,
                    size: self.at.offset + SHM_RECORD_HEADER as u64 + self.at.len,
                })
            }
        }
        self.read_raw(self.at.offset + SHM_RECORD_HEADER as u64 + offset, len)
    }

    fn read_raw(&mut self, pos: u64, len: u64) -> Result<Vec<u8>, ShmError> {
        use std::io::{Read, Seek, SeekFrom};
        let io = |source| ShmError::Io {
            path: self.reader.path.clone(),
            source,
        };
        let mut f = &self.reader.file;
        f.seek(SeekFrom::Start(pos)).map_err(io)?;
        // `read_to_end` fills the spare capacity without zeroing it first (a fresh 16 MB
        // zero-fill costs as much as the copy).
        let mut out = Vec::with_capacity(len as usize);
        f.take(len).read_to_end(&mut out).map_err(io)?;
        if out.len() as u64 != len {
            // The segment shrank under us.
            return Err(ShmError::PastEnd {
                offset: pos,
                len,
                size: self.size.min(pos + out.len() as u64),
            });
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A whole record, checked.
    fn read(
        r: &mut ShmReader,
        at: ShmRef,
        limit: u64,
        frame: u64,
        round: u32,
        from: u32,
    ) -> Result<Vec<u8>, ShmError> {
        let mut rec = r.record(at, limit, frame, round, from)?;
        let n = rec.len();
        rec.read(0, n)
    }

    fn pair(dir: &Path) -> (ShmWriter, ShmReader) {
        let w = ShmWriter::create_in(dir).unwrap();
        let r = ShmReader::open_in(dir, w.name()).unwrap();
        (w, r)
    }

    #[test]
    fn records_round_trip_and_the_name_is_gone_once_open() {
        let dir = tempfile::tempdir().unwrap();
        let (mut w, mut r) = pair(dir.path());
        assert!(
            std::fs::read_dir(dir.path()).unwrap().next().is_none(),
            "the receiver unlinks the name"
        );
        let a = w.write(3, 0, 1, b"hello").unwrap();
        let b = w.write(3, 1, 1, &[7u8; 1000]).unwrap();
        assert_eq!(a.offset, 0);
        assert_eq!(b.offset % ALIGN, 0);
        assert_eq!(read(&mut r, a, 1 << 20, 3, 0, 1).unwrap(), b"hello");
        assert_eq!(read(&mut r, b, 1 << 20, 3, 1, 1).unwrap(), vec![7u8; 1000]);
        // The next frame reuses the segment from its start.
        w.reset();
        let c = w.write(4, 0, 1, b"again").unwrap();
        assert_eq!(c.offset, 0);
        assert_eq!(read(&mut r, c, 1 << 20, 4, 0, 1).unwrap(), b"again");
        // The old record's announcement no longer matches what lies there.
        assert!(matches!(
            read(&mut r, a, 1 << 20, 3, 0, 1),
            Err(ShmError::Header { .. })
        ));
    }

    #[test]
    fn sizes_past_the_end_or_the_limit_are_refused_before_allocating() {
        let dir = tempfile::tempdir().unwrap();
        let (mut w, mut r) = pair(dir.path());
        let a = w.write(1, 0, 0, &[1u8; 100]).unwrap();
        let long = ShmRef { len: 101, ..a };
        let e = read(&mut r, long, 1 << 20, 1, 0, 0).unwrap_err();
        assert!(matches!(e, ShmError::PastEnd { .. }), "{e}");
        let huge = ShmRef {
            offset: u64::MAX - 8,
            len: 100,
        };
        assert!(matches!(
            read(&mut r, huge, 1 << 20, 1, 0, 0),
            Err(ShmError::PastEnd { .. })
        ));
        let e = read(&mut r, ShmRef { len: u64::MAX, ..a }, 1 << 20, 1, 0, 0).unwrap_err();
        assert!(matches!(e, ShmError::TooLarge { .. }), "{e}");
        // A segment truncated under the reader: a clear error, no SIGBUS.
        w.file.set_len(50).unwrap();
        let e = read(&mut r, a, 1 << 20, 1, 0, 0).unwrap_err();
        assert!(e.to_string().contains("past the segment's end"), "{e}");
    }

    #[test]
    fn records_read_in_parts_stay_inside_the_record() {
        let dir = tempfile::tempdir().unwrap();
        let (mut w, mut r) = pair(dir.path());
        let payload: Vec<u8> = (0..200u8).collect();
        let a = w.write(1, 0, 0, &payload).unwrap();
        let _next = w.write(1, 1, 0, &[9u8; 64]).unwrap();
        let mut rec = r.record(a, 1 << 20, 1, 0, 0).unwrap();
        assert_eq!(rec.len(), 200);
        assert_eq!(rec.read(10, 5).unwrap(), payload[10..15]);
        assert_eq!(rec.read(0, 200).unwrap(), payload);
        // Not a byte beyond the record, though the segment goes on.
        assert!(matches!(rec.read(150, 51), Err(ShmError::PastEnd { .. })));
        assert!(matches!(
            rec.read(u64::MAX, 2),
            Err(ShmError::PastEnd { .. })
        ));
    }

    #[test]
    fn pieces_read_from_records_equal_the_written_ones_and_bad_ones_are_refused() {
        use strata_common::composite::{Span, WireFormat};
        let dir = tempfile::tempdir().unwrap();
        let (mut w, mut r) = pair(dir.path());
        let z = [0.0f32; 4];
        let px = [0.5f32, 0.25, 0.125, 0.5];
        let piece = SparsePiece::encode(&[z, px, px, z, px], Span::new(10, 15), WireFormat::F32);
        let parts = piece.wire_parts();
        let refs: Vec<&[u8]> = parts.iter().map(|p| &**p).collect();
        let a = w.write_parts(2, 1, 3, &refs).unwrap();
        assert_eq!(r.read_piece(a, 1 << 20, 2, 1, 3, 100).unwrap(), piece);
        // The span must fit the frame.
        let e = r.read_piece(a, 1 << 20, 2, 1, 3, 12).unwrap_err();
        assert!(matches!(e, ShmError::Piece { .. }), "{e}");
        // Not a piece: garbage, a short record, runs announced past the record.
        for junk in [vec![0xEEu8; 40], vec![b'S'; 3], {
            let mut b = Vec::new();
            piece.write(&mut b);
            b[12] = 200;
            b
        }] {
            let a = w.write(2, 2, 3, &junk).unwrap();
            let e = r.read_piece(a, 1 << 20, 2, 2, 3, 100).unwrap_err();
            assert!(matches!(e, ShmError::Piece { .. }), "{e}");
        }
    }

    #[test]
    fn a_malformed_record_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (mut w, mut r) = pair(dir.path());
        let a = w.write(1, 0, 0, &[1u8; 100]).unwrap();
        // Another sender position, round or frame than announced.
        for (f, round, from) in [(2, 0, 0), (1, 1, 0), (1, 0, 1)] {
            assert!(matches!(
                read(&mut r, a, 1 << 20, f, round, from),
                Err(ShmError::Header { .. })
            ));
        }
        // A header overwritten with garbage.
        w.file.write_all_at(&[0xAB; 32], 0).unwrap();
        let e = read(&mut r, a, 1 << 20, 1, 0, 0).unwrap_err();
        assert!(e.to_string().contains("magic"), "{e}");
    }

    #[test]
    fn only_private_files_with_a_sender_name_are_opened() {
        let dir = tempfile::tempdir().unwrap();
        for bad in [
            "../etc/passwd",
            "strata-shm-",
            "strata-shm-0123456789abcdef0123456789abcdeg",
            "strata-shm-0123456789abcdef0123456789abcdef/x",
            "other-0123456789abcdef0123456789abcdef",
        ] {
            assert!(matches!(
                ShmReader::open_in(dir.path(), bad),
                Err(ShmError::BadName(_))
            ));
        }
        let name = format!("{PREFIX}{}", "0".repeat(32));
        // Missing.
        assert!(matches!(
            ShmReader::open_in(dir.path(), &name),
            Err(ShmError::Io { .. })
        ));
        // World-readable.
        let p = dir.path().join(&name);
        std::fs::write(&p, b"x").unwrap();
        std::fs::set_permissions(&p, std::os::unix::fs::PermissionsExt::from_mode(0o644)).unwrap();
        let e = ShmReader::open_in(dir.path(), &name).unwrap_err();
        assert!(matches!(e, ShmError::NotPrivate { .. }), "{e}");
        // A symbolic link to a private file.
        std::fs::remove_file(&p).unwrap();
        let target = dir.path().join("target");
        std::fs::write(&target, b"x").unwrap();
        std::os::unix::fs::symlink(&target, &p).unwrap();
        assert!(ShmReader::open_in(dir.path(), &name).is_err());
    }

    #[test]
    fn the_host_id_is_stable_and_names_the_folder() {
        if let Some(id) = host_id() {
            assert_eq!(host_id().as_deref(), Some(id.as_str()));
            assert!(id.contains('/') && id.contains(':'), "{id}");
        }
    }
}
