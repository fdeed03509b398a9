//! Shared-memory segments between processes on one host, as MPI implementations pass
//! messages within a node.
//!
//! A segment is an anonymous memory file (`memfd_create`) of its sender: nothing is ever
//! named in a file system, and the memory goes when both sides have closed it. Each
//! sender owns one segment per receiver; per frame it writes its records from the start
//! of the segment again, so the pages it touched in the first frame serve every later one.
//! Both sides **map** the segment: the sender encodes each piece straight into its
//! mapping ([`ShmWriter::write_with`]), the receiver parses and blends straight from its
//! own read-only mapping ([`ShmReader::read_piece`]). A piece costs one pass over its
//! pixels on each side, the encode and the blend, and no copy in between.
//!
//! **Authorisation** rides on the authenticated QUIC connection: the sender tells the
//! receiver, over it, its process id, the segment's descriptor and the segment's random
//! 128-bit name. The receiver opens `/proc/<pid>/fd/<fd>` (the kernel lets only the same
//! user do so), and keeps it only if the descriptor it got names exactly that memory
//! file, belongs to this user, and is sealed against shrinking (below).
//!
//! **Why a mapping is safe to read.** A mapped file that shrinks under its reader turns
//! reads past the new end into `SIGBUS`. The sender seals the segment against shrinking
//! (`F_SEAL_SHRINK` and `F_SEAL_SEAL` in one call, so no one can undo it) before announcing it, and
//! the receiver refuses a segment without that seal: no one, the sender included, can
//! truncate it, and every byte below the size the receiver mapped stays readable. A
//! sender only grows its segment, with its memory allocated up front (`fallocate`), so a
//! host out of memory fails the write with an error (the piece then goes over QUIC), not
//! with a fault on first touch.
//!
//! **What a peer can still do** is write into its own segment while the receiver reads
//! it. Every record starts with a header ([`strata_common::wire::encode_shm_record`]) that
//! must match the announcing message, every size is checked against the receiver's limit
//! and the size it mapped before anything is used, and the piece's header and run lengths
//! are copied out and checked: a peer rewriting a record it announced can garble pixel
//! values, never make the receiver read outside its mapping. Well-behaved senders never
//! do: a frame completes only once every rank has blended all its pieces, and a sender
//! rewrites its segment only in a later frame.

use std::fs::File;
use std::os::fd::{AsRawFd, FromRawFd};
use std::os::unix::fs::{MetadataExt, OpenOptionsExt};
use std::sync::Arc;

use bytes::Bytes;
use memmap2::{Mmap, MmapMut, MmapOptions};
use strata_common::composite::{PieceLayout, Segment, Span, SparsePiece, WireFormat};
use strata_common::wire::{check_shm_record, encode_shm_record, ShmRef, SHM_RECORD_HEADER};

/// Prefix of every segment's name.
pub const PREFIX: &str = "strata-shm-";

/// Records start on cache-line boundaries.
const ALIGN: u64 = 64;

/// Segments grow to at least this many bytes, then by doubling.
const MIN_SIZE: u64 = 1 << 20;

/// Records one frame may put in a segment, at most (one per compositing round, or the
/// final piece): a reader refuses offsets further than this many largest records.
const MAX_RECORDS: u64 = 64;

/// Why a segment could not be used.
#[derive(Debug, thiserror::Error)]
pub enum ShmError {
    /// The announced name is not one a Strata sender creates.
    #[error("segment name {0:?} is not `{PREFIX}` and 32 hex digits")]
    BadName(String),
    /// Opening, creating, growing or mapping failed.
    #[error("segment {path}: {source}")]
    Io {
        /// The segment.
        path: String,
        /// The error.
        source: std::io::Error,
    },
    /// The descriptor is not a private, sealed segment of this user.
    #[error("segment {path}: {why}")]
    NotPrivate {
        /// The segment.
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
    /// The record lies further into the segment than one frame's records can reach.
    #[error("record at offset {offset} lies past the {reach} bytes one frame's records can reach")]
    TooFar {
        /// Announced offset.
        offset: u64,
        /// How far records may reach.
        reach: u64,
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

/// This host's identity for shared memory: the kernel's boot id and this process's pid
/// namespace. Two processes with the same id can open each other's segments through
/// `/proc/<pid>/fd` (containers with their own pid namespace differ). `None` where
/// `/proc` does not say.
pub fn host_id() -> Option<String> {
    let boot = std::fs::read_to_string("/proc/sys/kernel/random/boot_id").ok()?;
    let ns = std::fs::read_link("/proc/self/ns/pid").ok()?;
    Some(format!("{}/{}", boot.trim(), ns.display()))
}

/// Whether `name` has the form a sender creates (no path separators, nothing else).
pub fn valid_name(name: &str) -> bool {
    name.strip_prefix(PREFIX)
        .is_some_and(|h| h.len() == 32 && h.bytes().all(|b| b.is_ascii_hexdigit()))
}

/// What a receiver needs to open a segment, sent over the authenticated connection.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SegmentId {
    /// `strata-shm-` and 32 hex digits.
    pub name: String,
    /// The sender's process id.
    pub pid: u32,
    /// The segment's descriptor in the sender.
    pub fd: i32,
}

pub(crate) fn io_error(path: &str) -> impl Fn(std::io::Error) -> ShmError + '_ {
    move |source| ShmError::Io {
        path: path.to_string(),
        source,
    }
}

/// A fresh anonymous memory file with a random `strata-shm-` name, `len` bytes with their
/// memory allocated (so that a host out of memory fails here, not on first touch of a
/// mapping), carrying `seals` and `F_SEAL_SEAL` (so no one can undo them).
pub(crate) fn create_sealed(len: u64, seals: libc::c_int) -> Result<(File, String), ShmError> {
    let hex: String = crate::secret::random_bytes::<16>()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    let name = format!("{PREFIX}{hex}");
    let c_name = std::ffi::CString::new(name.clone()).expect("no NUL in a hex name");
    // SAFETY: a valid C string and flags; the result is checked.
    let fd =
        unsafe { libc::memfd_create(c_name.as_ptr(), libc::MFD_CLOEXEC | libc::MFD_ALLOW_SEALING) };
    if fd < 0 {
        return Err(io_error(&name)(std::io::Error::last_os_error()));
    }
    // SAFETY: `fd` is a fresh descriptor that nothing else owns.
    let file = unsafe { File::from_raw_fd(fd) };
    if len > 0 {
        let len = libc::off_t::try_from(len).map_err(|_| {
            io_error(&name)(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("a segment of {len} bytes"),
            ))
        })?;
        // SAFETY: fallocate on a descriptor we own; the result is checked.
        if unsafe { libc::fallocate(fd, 0, 0, len) } != 0 {
            return Err(io_error(&name)(std::io::Error::last_os_error()));
        }
    }
    // SAFETY: fcntl on a descriptor we own; the result is checked.
    let r = unsafe { libc::fcntl(fd, libc::F_ADD_SEALS, seals | libc::F_SEAL_SEAL) };
    if r < 0 {
        return Err(io_error(&name)(std::io::Error::last_os_error()));
    }
    Ok((file, name))
}

/// The sending side of one segment.
#[derive(Debug)]
pub struct ShmWriter {
    file: File,
    map: Option<MmapMut>,
    size: u64,
    name: String,
    cursor: u64,
}

impl ShmWriter {
    /// Creates a fresh, empty segment, sealed against shrinking.
    pub fn create() -> Result<ShmWriter, ShmError> {
        let (file, name) = create_sealed(0, libc::F_SEAL_SHRINK)?;
        Ok(ShmWriter {
            file,
            map: None,
            size: 0,
            name,
            cursor: 0,
        })
    }

    /// The name to announce to the receiver.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// What the receiver needs to open this segment.
    pub fn id(&self) -> SegmentId {
        SegmentId {
            name: self.name.clone(),
            pid: std::process::id(),
            fd: self.file.as_raw_fd(),
        }
    }

    /// The segment's size in bytes (it only grows).
    pub fn size(&self) -> u64 {
        self.size
    }

    /// Starts a new frame: records are written from the start again. The receiver has
    /// used every record of the frame before (a frame completes only once every rank has
    /// blended all its pieces).
    pub fn reset(&mut self) {
        self.cursor = 0;
    }

    /// Makes the segment at least `end` bytes long, its memory allocated.
    fn reserve(&mut self, end: u64) -> Result<(), ShmError> {
        if end <= self.size {
            return Ok(());
        }
        let io = io_error(&self.name);
        let size = end
            .checked_next_power_of_two()
            .filter(|&s| usize::try_from(s).is_ok() && libc::off_t::try_from(s).is_ok())
            .ok_or_else(|| {
                io(std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    format!("a segment of {end} bytes"),
                ))
            })?
            .max(MIN_SIZE);
        // Allocate the memory now, so that a host out of memory is an error here and
        // not a fault on first touch of the mapping.
        // SAFETY: fallocate on a descriptor we own; the result is checked.
        let r = unsafe { libc::fallocate(self.file.as_raw_fd(), 0, 0, size as libc::off_t) };
        if r != 0 {
            return Err(io(std::io::Error::last_os_error()));
        }
        // SAFETY: the file is sealed against shrinking and only this writer writes it;
        // the mapping covers its current size. The old mapping is replaced only once the
        // new one exists: a failed remap leaves the segment as it was, still usable.
        let map =
            unsafe { MmapOptions::new().len(size as usize).map_mut(&self.file) }.map_err(io)?;
        self.map = Some(map);
        self.size = size;
        Ok(())
    }

    /// Appends one record of `len` payload bytes that `fill` writes straight into the
    /// segment (given exactly `len` bytes), and returns where it lies.
    pub fn write_with(
        &mut self,
        frame: u64,
        round: u32,
        from: u32,
        len: u64,
        fill: impl FnOnce(&mut [u8]),
    ) -> Result<ShmRef, ShmError> {
        let at = ShmRef {
            offset: self.cursor,
            len,
        };
        let start = at.offset + SHM_RECORD_HEADER as u64;
        let end = start.checked_add(len).ok_or_else(|| {
            io_error(&self.name)(std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                format!("a record of {len} bytes"),
            ))
        })?;
        self.reserve(end)?;
        let map = self.map.as_mut().expect("reserved");
        map[at.offset as usize..start as usize]
            .copy_from_slice(&encode_shm_record(frame, round, from, len));
        // The header before the payload. A reader checks a record's header when it reads
        // the piece, and again when the piece does not parse ([`ShmReader::read_piece`]),
        // but blends its pixels later, from the mapping: a record rewritten after that
        // (only a failed frame's, announced before this one, whose output is thrown away)
        // is not detected. No finished frame's record is rewritten while a reader may
        // still use it: a frame completes only once every rank has blended its pieces.
        std::sync::atomic::fence(std::sync::atomic::Ordering::Release);
        fill(&mut map[start as usize..end as usize]);
        self.cursor = end.next_multiple_of(ALIGN);
        Ok(at)
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

    /// Appends one record whose payload is `parts` one after the other.
    pub fn write_parts(
        &mut self,
        frame: u64,
        round: u32,
        from: u32,
        parts: &[&[u8]],
    ) -> Result<ShmRef, ShmError> {
        let len = parts.iter().map(|p| p.len() as u64).sum();
        self.write_with(frame, round, from, len, |out| {
            let mut at = 0;
            for p in parts {
                out[at..at + p.len()].copy_from_slice(p);
                at += p.len();
            }
        })
    }

    /// Encodes the piece of the pixels `segments` stand for (covering `span`, run
    /// lengths `layout`) straight into a record: the same bytes as
    /// [`SparsePiece::write`], with no buffer between.
    #[allow(clippy::too_many_arguments)]
    pub fn write_piece(
        &mut self,
        frame: u64,
        round: u32,
        from: u32,
        segments: &[Segment<'_>],
        layout: &PieceLayout,
        span: Span,
        format: WireFormat,
    ) -> Result<ShmRef, ShmError> {
        let len = layout.byte_len(format) as u64;
        self.write_with(frame, round, from, len, |out| {
            layout.write_segments_into(segments, span, format, out)
        })
    }
}

/// Opens the memory file a peer announced (`id`, received over the authenticated
/// connection), for reading or also for `write`: only the memory file of that name, of
/// this user, sealed against shrinking. Returns it and the name to show in errors.
pub(crate) fn open_checked(id: &SegmentId, write: bool) -> Result<(File, String), ShmError> {
    if !valid_name(&id.name) {
        return Err(ShmError::BadName(id.name.chars().take(80).collect()));
    }
    let path = format!("/proc/{}/fd/{}", id.pid, id.fd);
    let shown = format!("{} ({path})", id.name);
    let refuse = |why: String| ShmError::NotPrivate {
        path: shown.clone(),
        why,
    };
    let want = format!("/memfd:{} (deleted)", id.name);
    // What the descriptor names, looked at before opening it: opening a named FIFO (or a
    // terminal) that a peer announced would block this thread for good, or give the
    // process a controlling terminal.
    let announced = std::fs::read_link(&path).map_err(io_error(&shown))?;
    if announced.as_os_str() != want.as_str() {
        return Err(refuse(format!(
            "the descriptor is {}, not the announced segment",
            announced.display()
        )));
    }
    // Non-blocking and without a controlling terminal all the same: the descriptor can be
    // replaced between the look and the open (checked again below).
    let file = std::fs::OpenOptions::new()
        .read(true)
        .write(write)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOCTTY)
        .open(&path)
        .map_err(io_error(&shown))?;
    // What this process holds now (the sender's descriptor could have been reused
    // between the announcement and the open).
    let held = std::fs::read_link(format!("/proc/self/fd/{}", file.as_raw_fd()))
        .map_err(io_error(&shown))?;
    if held.as_os_str() != want.as_str() {
        return Err(refuse(format!(
            "the descriptor is {}, not the announced segment",
            held.display()
        )));
    }
    let m = file.metadata().map_err(io_error(&shown))?;
    // SAFETY: geteuid has no preconditions and cannot fail.
    let me = unsafe { libc::geteuid() };
    if !m.is_file() {
        return Err(refuse("not a regular file".into()));
    }
    if m.uid() != me {
        return Err(refuse(format!(
            "owned by uid {}, not this user ({me})",
            m.uid()
        )));
    }
    // SAFETY: fcntl on a descriptor we own; the result is checked.
    let seals = unsafe { libc::fcntl(file.as_raw_fd(), libc::F_GET_SEALS) };
    if seals < 0 || seals & libc::F_SEAL_SHRINK == 0 {
        return Err(refuse(
            "not sealed against shrinking (a mapping of it could fault)".into(),
        ));
    }
    Ok((file, shown))
}

/// The receiving side of one segment.
#[derive(Debug)]
pub struct ShmReader {
    file: File,
    path: String,
    /// The current mapping; pieces read from it share it, so growing maps anew and
    /// leaves the old mapping to the pieces still using it.
    map: Option<Arc<Mmap>>,
}

/// Whether a file (its `meta`) has fewer bytes of memory than `end`: then it has holes below `end`
/// (tmpfs counts the pages `fallocate` gave it; its SEEK_HOLE reports those as holes until
/// written, so it cannot tell a sender's segment from a sparse one). A file with memory
/// elsewhere and holes below `end` passes: populating it then allocates at most as much
/// again as its owner did.
fn hole_below(meta: &std::fs::Metadata, end: u64) -> bool {
    meta.blocks().saturating_mul(512) < end
}

/// Payload bytes of a mapping, owned by a piece.
struct MapSlice {
    map: Arc<Mmap>,
    start: usize,
    end: usize,
}

impl AsRef<[u8]> for MapSlice {
    fn as_ref(&self) -> &[u8] {
        &self.map[self.start..self.end]
    }
}

impl ShmReader {
    /// Opens the segment a peer announced (`id`, as received over the authenticated
    /// connection): only the memory file of that name, of this user, sealed against
    /// shrinking.
    pub fn open(id: &SegmentId) -> Result<ShmReader, ShmError> {
        let (file, shown) = open_checked(id, false)?;
        Ok(ShmReader {
            file,
            path: shown,
            map: None,
        })
    }

    /// A mapping that covers `[0, end)`, or why the segment is shorter.
    fn mapping(&mut self, offset: u64, len: u64, end: u64) -> Result<Arc<Mmap>, ShmError> {
        if let Some(m) = &self.map {
            if m.len() as u64 >= end {
                return Ok(m.clone());
            }
        }
        let meta = self.file.metadata().map_err(io_error(&self.path))?;
        let size = meta.len();
        if end > size {
            return Err(ShmError::PastEnd { offset, len, size });
        }
        // Up to what this record needs (rounded up, so that growth remaps rarely), not
        // the whole file: a peer that grew its segment far costs nothing until a record
        // lies there.
        let want = end
            .checked_next_power_of_two()
            .unwrap_or(end)
            .max(MIN_SIZE)
            .min(size);
        // Faulted in up front where the memory is there (a sender allocates its segment as
        // it grows it), so that blending from it takes no page faults; a segment with less
        // memory than `want` (holes: grown by `ftruncate`, not by a sender) is mapped
        // lazily, or mapping it would allocate every hole up to the record: only the pages
        // read then cost memory.
        let populate = !hole_below(&meta, want);
        let want = usize::try_from(want).map_err(|_| ShmError::PastEnd { offset, len, size })?;
        let mut options = MmapOptions::new();
        options.len(want);
        if populate {
            options.populate();
        }
        // SAFETY: the segment is sealed against shrinking (checked at open), so every
        // byte below `size` stays mapped and readable; see the module docs for what a
        // peer writing while this reads can and cannot do.
        let map = unsafe { options.map(&self.file) }.map_err(io_error(&self.path))?;
        let map = Arc::new(map);
        self.map = Some(map.clone());
        Ok(map)
    }

    /// The payload of the record at `at`, checked (length against `limit` and the
    /// segment's end, header against the announced frame, round and sender position),
    /// shared with the mapping (no copy).
    pub fn read(
        &mut self,
        at: ShmRef,
        limit: u64,
        frame: u64,
        round: u32,
        from: u32,
    ) -> Result<Bytes, ShmError> {
        if at.len > limit {
            return Err(ShmError::TooLarge { len: at.len, limit });
        }
        let end = at
            .offset
            .checked_add(SHM_RECORD_HEADER as u64)
            .and_then(|e| e.checked_add(at.len));
        let Some(end) = end.filter(|&e| usize::try_from(e).is_ok()) else {
            return Err(ShmError::PastEnd {
                offset: at.offset,
                len: at.len,
                size: self.map.as_ref().map_or(0, |m| m.len() as u64),
            });
        };
        // A sender writes one frame's records from the start of its segment, each at
        // most `limit` bytes: a record reaching further is refused before anything is
        // mapped (the segment may only grow, and mapping it costs memory).
        let reach = limit
            .saturating_add(SHM_RECORD_HEADER as u64 + ALIGN)
            .saturating_mul(MAX_RECORDS);
        if end > reach {
            return Err(ShmError::TooFar {
                offset: at.offset,
                reach,
            });
        }
        let map = self.mapping(at.offset, at.len, end)?;
        let start = at.offset as usize + SHM_RECORD_HEADER;
        let header: [u8; SHM_RECORD_HEADER] = map[at.offset as usize..start]
            .try_into()
            .expect("a header's length");
        check_shm_record(&header, frame, round, from, at.len).map_err(|why| ShmError::Header {
            offset: at.offset,
            why,
        })?;
        Ok(Bytes::from_owner(MapSlice {
            map,
            start,
            end: end as usize,
        }))
    }

    /// Reads the image piece in the record at `at` (checked as [`read`](Self::read)
    /// does, then as [`SparsePiece::parse`] does, with spans up to `max_pixels`): the
    /// header and run lengths are copied out and checked, the pixel data stays in the
    /// mapping and is blended from there.
    pub fn read_piece(
        &mut self,
        at: ShmRef,
        limit: u64,
        frame: u64,
        round: u32,
        from: u32,
        max_pixels: u32,
    ) -> Result<SparsePiece, ShmError> {
        let payload = self.read(at, limit, frame, round, from)?;
        let parsed = parse_piece(&payload, max_pixels);
        self.piece_or_stale(parsed, at, limit, frame, round, from)
    }

    /// A piece parsed from the record at `at`, or, where it did not parse, why: the record
    /// is stale if its header no longer is the announced one (its sender rewrote it for a
    /// later frame while this reader still read the failed frame's announcement: a benign
    /// race, not a bad peer), else the piece is bad.
    fn piece_or_stale(
        &mut self,
        parsed: Result<SparsePiece, strata_common::composite::PieceError>,
        at: ShmRef,
        limit: u64,
        frame: u64,
        round: u32,
        from: u32,
    ) -> Result<SparsePiece, ShmError> {
        let source = match parsed {
            Ok(p) => return Ok(p),
            Err(e) => e,
        };
        // Pairs with the writer's fence between a record's header and its payload.
        std::sync::atomic::fence(std::sync::atomic::Ordering::Acquire);
        self.read(at, limit, frame, round, from)?;
        Err(ShmError::Piece {
            offset: at.offset,
            source,
        })
    }
}

/// The piece in a record's payload: the header and run lengths are copied out and
/// checked, the pixel data stays in the mapping.
fn parse_piece(
    payload: &Bytes,
    max_pixels: u32,
) -> Result<SparsePiece, strata_common::composite::PieceError> {
    let h = SparsePiece::HEADER_BYTES;
    let Some(header) = payload.first_chunk::<{ SparsePiece::HEADER_BYTES }>() else {
        // Shorter than a header: let the parser say so.
        return SparsePiece::parse(payload, max_pixels);
    };
    let head_len = (h as u64).saturating_add(SparsePiece::runs_bytes_in_header(header));
    if head_len > payload.len() as u64 {
        return SparsePiece::parse(payload, max_pixels);
    }
    let head_len = head_len as usize;
    let head = payload[..head_len].to_vec();
    SparsePiece::parse_split(&head, payload.slice(head_len..), max_pixels)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::unix::fs::FileExt;

    /// A whole record, checked.
    fn read(
        r: &mut ShmReader,
        at: ShmRef,
        limit: u64,
        frame: u64,
        round: u32,
        from: u32,
    ) -> Result<Vec<u8>, ShmError> {
        r.read(at, limit, frame, round, from).map(|b| b.to_vec())
    }

    fn pair() -> (ShmWriter, ShmReader) {
        let w = ShmWriter::create().unwrap();
        let r = ShmReader::open(&w.id()).unwrap();
        (w, r)
    }

    #[test]
    fn records_round_trip_across_frames_and_growth() {
        let (mut w, mut r) = pair();
        let a = w.write(3, 0, 1, b"hello").unwrap();
        let b = w.write(3, 1, 1, &[7u8; 1000]).unwrap();
        assert_eq!(a.offset, 0);
        assert_eq!(b.offset % ALIGN, 0);
        assert_eq!(read(&mut r, a, 1 << 20, 3, 0, 1).unwrap(), b"hello");
        assert_eq!(read(&mut r, b, 1 << 20, 3, 1, 1).unwrap(), vec![7u8; 1000]);
        // A record past the first mapping: the segment grows, the reader maps anew, and
        // what it read before stays valid.
        let held = r.read(b, 1 << 20, 3, 1, 1).unwrap();
        let big: Vec<u8> = (0..3 << 20).map(|i| (i % 251) as u8).collect();
        let c = w.write(3, 2, 1, &big).unwrap();
        assert!(w.size() >= 4 << 20);
        assert_eq!(read(&mut r, c, 1 << 30, 3, 2, 1).unwrap(), big);
        assert_eq!(&held[..], &[7u8; 1000][..]);
        // The next frame reuses the segment from its start.
        w.reset();
        let d = w.write(4, 0, 1, b"again").unwrap();
        assert_eq!(d.offset, 0);
        assert_eq!(read(&mut r, d, 1 << 20, 4, 0, 1).unwrap(), b"again");
        // The old record's announcement no longer matches what lies there.
        assert!(matches!(
            read(&mut r, a, 1 << 20, 3, 0, 1),
            Err(ShmError::Header { .. })
        ));
    }

    #[test]
    fn a_piece_rewritten_while_read_is_stale_not_bad() {
        let (mut w, mut r) = pair();
        let junk = [0xA5u8; 96];
        let at = w.write(1, 0, 1, &junk).unwrap();
        // A piece that does not parse under its own, unchanged header: the peer's fault.
        let payload = r.read(at, 1 << 20, 1, 0, 1).unwrap();
        let e = r
            .piece_or_stale(parse_piece(&payload, 1 << 20), at, 1 << 20, 1, 0, 1)
            .unwrap_err();
        assert!(matches!(e, ShmError::Piece { .. }), "{e}");
        assert!(matches!(
            r.read_piece(at, 1 << 20, 1, 0, 1, 1 << 20),
            Err(ShmError::Piece { .. })
        ));
        // The same bytes read while the sender rewrote the record for its next frame (its
        // header first): stale, which the reader drops, not a bad peer to disconnect.
        w.reset();
        let again = w.write(2, 0, 1, &[0x5Au8; 96]).unwrap();
        assert_eq!(again.offset, at.offset);
        let e = r
            .piece_or_stale(parse_piece(&payload, 1 << 20), at, 1 << 20, 1, 0, 1)
            .unwrap_err();
        assert!(matches!(e, ShmError::Header { .. }), "{e}");
    }

    /// A peer announcing a descriptor that is a FIFO without a writer: opening it for
    /// reading would block until a writer came, so it is looked at before it is opened.
    #[test]
    fn an_announced_fifo_is_refused_without_blocking() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("f");
        let c = std::ffi::CString::new(fifo.as_os_str().as_encoded_bytes()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let held = std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NONBLOCK)
            .open(&fifo)
            .unwrap();
        let id = SegmentId {
            name: format!("{PREFIX}{}", "0".repeat(32)),
            pid: std::process::id(),
            fd: held.as_raw_fd(),
        };
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(ShmReader::open(&id).map(|_| ()));
        });
        let got = rx
            .recv_timeout(std::time::Duration::from_secs(10))
            .expect("opening an announced FIFO blocked");
        assert!(matches!(got, Err(ShmError::NotPrivate { .. })), "{got:?}");
        drop(held);
    }

    #[test]
    fn sizes_past_the_end_or_the_limit_are_refused_before_allocating() {
        let (mut w, mut r) = pair();
        let a = w.write(1, 0, 0, &[1u8; 100]).unwrap();
        let past = ShmRef {
            offset: w.size() - 16,
            len: 100,
        };
        let e = read(&mut r, past, 1 << 20, 1, 0, 0).unwrap_err();
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
        // Further into the segment than a frame's records can reach: refused before the
        // segment's size is even looked at.
        let far = ShmRef {
            offset: 10 << 30,
            len: 100,
        };
        let e = read(&mut r, far, 1 << 20, 1, 0, 0).unwrap_err();
        assert!(matches!(e, ShmError::TooFar { .. }), "{e}");
        // A record longer than announced reads as its header says, not further.
        let long = ShmRef { len: 101, ..a };
        let e = read(&mut r, long, 1 << 20, 1, 0, 0).unwrap_err();
        assert!(matches!(e, ShmError::Header { .. }), "{e}");
    }

    /// A peer that grows its segment with holes (`ftruncate`, where a sender allocates)
    /// and announces a record far into it costs the reader the pages it reads, not every
    /// hole up to the record (a populated mapping allocated them all: 48 MiB here).
    #[test]
    fn a_segment_with_holes_is_not_allocated_by_its_reader() {
        use std::os::unix::fs::FileExt;
        let (w, mut r) = pair();
        let limit = 1u64 << 20;
        let offset = 48u64 << 20;
        let len = 4096u64;
        w.file.set_len(offset + (64 << 10)).unwrap();
        let header = strata_common::wire::encode_shm_record(1, 0, 0, len);
        w.file.write_all_at(&header, offset).unwrap();
        w.file
            .write_all_at(&[7u8; 4096], offset + SHM_RECORD_HEADER as u64)
            .unwrap();
        assert!(hole_below(&w.file.metadata().unwrap(), offset + 64));
        let allocated = |f: &File| f.metadata().unwrap().blocks() * 512;
        let before = allocated(&w.file);
        assert!(before < 8 << 20, "{before}");
        let at = ShmRef { offset, len };
        let got = read(&mut r, at, limit, 1, 0, 0).unwrap();
        assert_eq!(got, vec![7u8; 4096]);
        let after = allocated(&w.file);
        assert!(
            after < before + (1 << 20),
            "reading one record allocated {} bytes of the segment",
            after - before
        );
    }

    /// A sender's segment has its memory (`fallocate`): it is mapped populated.
    #[test]
    fn a_senders_segment_has_no_hole() {
        let (mut w, _r) = pair();
        let a = w.write(1, 0, 0, &[5u8; 100_000]).unwrap();
        let size = w.file.metadata().unwrap().len();
        assert!(size >= a.offset + a.len, "{size}");
        assert!(!hole_below(&w.file.metadata().unwrap(), size));
    }

    #[test]
    fn the_segment_cannot_shrink_under_its_reader() {
        let (mut w, mut r) = pair();
        let a = w.write(1, 0, 0, &[5u8; 4096]).unwrap();
        let held = r.read(a, 1 << 20, 1, 0, 0).unwrap();
        // Not even its sender can truncate it: a mapping of it never faults.
        let e = w.file.set_len(10).unwrap_err();
        assert_eq!(e.raw_os_error(), Some(libc::EPERM), "{e}");
        // Nor lift the seal.
        // SAFETY: fcntl on a descriptor the writer owns.
        let lifted = unsafe { libc::fcntl(w.file.as_raw_fd(), libc::F_ADD_SEALS, 0) };
        assert!(lifted < 0);
        assert_eq!(&held[..], &[5u8; 4096][..]);
    }

    #[test]
    fn pieces_read_from_records_equal_the_written_ones_and_bad_ones_are_refused() {
        let (mut w, mut r) = pair();
        let z = [0.0f32; 4];
        let px = [0.5f32, 0.25, 0.125, 0.5];
        let pixels = [z, px, px, z, px];
        for format in [WireFormat::F32, WireFormat::F16] {
            let piece = SparsePiece::encode(&pixels, Span::new(10, 15), format);
            let parts = piece.wire_parts();
            let refs: Vec<&[u8]> = parts.iter().map(|p| &**p).collect();
            let a = w.write_parts(2, 1, 3, &refs).unwrap();
            assert_eq!(r.read_piece(a, 1 << 20, 2, 1, 3, 100).unwrap(), piece);
            // Encoded straight into the segment: the same piece.
            let layout = PieceLayout::of(&pixels);
            let segs = [Segment::Pixels(&pixels)];
            let b = w
                .write_piece(2, 1, 3, &segs, &layout, Span::new(10, 15), format)
                .unwrap();
            assert_eq!(b.len, piece.byte_len() as u64);
            assert_eq!(r.read_piece(b, 1 << 20, 2, 1, 3, 100).unwrap(), piece);
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
    }

    #[test]
    fn a_malformed_record_is_refused() {
        let (mut w, mut r) = pair();
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
    fn only_the_announced_sealed_segment_of_this_user_is_opened() {
        let w = ShmWriter::create().unwrap();
        let id = w.id();
        for bad in [
            "../etc/passwd",
            "strata-shm-",
            "strata-shm-0123456789abcdef0123456789abcdeg",
            "strata-shm-0123456789abcdef0123456789abcdef/x",
            "other-0123456789abcdef0123456789abcdef",
        ] {
            let e = ShmReader::open(&SegmentId {
                name: bad.into(),
                ..id.clone()
            });
            assert!(matches!(e, Err(ShmError::BadName(_))));
        }
        // Another segment's name for this descriptor.
        let other = ShmWriter::create().unwrap();
        let e = ShmReader::open(&SegmentId {
            name: other.name().into(),
            ..id.clone()
        })
        .unwrap_err();
        assert!(e.to_string().contains("not the announced segment"), "{e}");
        // A descriptor that is not open, or not a segment (this test's stdin or a file).
        let e = ShmReader::open(&SegmentId {
            fd: 1 << 20,
            ..id.clone()
        })
        .unwrap_err();
        assert!(matches!(e, ShmError::Io { .. }), "{e}");
        let plain = tempfile::tempfile().unwrap();
        let e = ShmReader::open(&SegmentId {
            fd: plain.as_raw_fd(),
            ..id.clone()
        })
        .unwrap_err();
        assert!(matches!(e, ShmError::NotPrivate { .. }), "{e}");
        // A memory file of the right name without the seal.
        let name = format!("{PREFIX}{}", "0".repeat(32));
        let c = std::ffi::CString::new(name.clone()).unwrap();
        // SAFETY: a valid C string; the descriptor is owned by the File below.
        let fd = unsafe { libc::memfd_create(c.as_ptr(), libc::MFD_CLOEXEC) };
        assert!(fd >= 0);
        // SAFETY: a fresh descriptor nothing else owns.
        let unsealed = unsafe { File::from_raw_fd(fd) };
        let e = ShmReader::open(&SegmentId {
            name,
            pid: std::process::id(),
            fd: unsealed.as_raw_fd(),
        })
        .unwrap_err();
        assert!(
            e.to_string().contains("not sealed against shrinking"),
            "{e}"
        );
        // The real one opens.
        assert!(ShmReader::open(&id).is_ok());
    }

    /// On Linux there is always a host id (without one shared memory turns itself off, and
    /// every test comparing it with QUIC would pass on QUIC alone).
    #[test]
    fn the_host_id_is_stable_and_names_the_namespace() {
        let id = host_id();
        #[cfg(target_os = "linux")]
        assert!(
            id.is_some(),
            "no host id: /proc/sys/kernel/random/boot_id or /proc/self/ns/pid unreadable"
        );
        if let Some(id) = id {
            assert_eq!(host_id().as_deref(), Some(id.as_str()));
            assert!(id.contains("pid:["), "{id}");
        }
    }
}
