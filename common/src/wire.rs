//! The cluster protocol: framing and messages, with no I/O.
//!
//! Every message travels as one *frame*: a fixed 24-byte header, a bincode-2 encoded
//! `meta` message, and an optional raw `bulk` payload (image pieces, which are already a
//! flat little-endian layout and would only be slowed down by a serializer).
//!
//! ```text
//! offset  size  field
//!      0     4  magic  "STRF"
//!      4     2  protocol version (little-endian u16)
//!      6     2  reserved, must be 0
//!      8     4  meta length (u32)
//!     12     8  bulk length (u64)
//!     20     4  CRC-32C of bytes 0..20
//! ```
//!
//! The header is checked (magic, version, CRC, both lengths against the receiver's
//! [`Limits`]) before a single byte of the body is allocated, so a hostile or broken peer
//! can make a receiver allocate at most its limits. The transport (`strata-net`) reads
//! frames; this module says what they mean.

use crate::composite::{Algorithm, WireFormat};
use crate::kd::Region;
use crate::occlusion::BlockRect;
use crate::scene::Camera;
use serde::{de::DeserializeOwned, Deserialize, Serialize};

/// Frame magic.
pub const MAGIC: [u8; 4] = *b"STRF";
/// Protocol version; bumped on any incompatible change of the header or the messages.
pub const PROTOCOL_VERSION: u16 = 14;
/// Size of the frame header.
pub const HEADER_LEN: usize = 24;
/// Largest meta message any endpoint accepts (control messages are small; the scene text
/// is the biggest).
pub const MAX_META: u32 = 4 << 20;

/// How large a frame a receiver accepts.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct Limits {
    /// Largest meta message.
    pub max_meta: u32,
    /// Largest bulk payload.
    pub max_bulk: u64,
}

impl Limits {
    /// Control messages only, no bulk (e.g. before a peer has authenticated).
    pub const HANDSHAKE: Limits = Limits {
        max_meta: 64 << 10,
        max_bulk: 0,
    };

    /// Control messages plus image pieces of frames with up to `max_pixels` pixels.
    pub fn for_pixels(max_pixels: u64) -> Limits {
        Limits {
            max_meta: MAX_META,
            max_bulk: max_piece_bytes(max_pixels),
        }
    }
}

/// The largest encoded piece of `pixels` pixels: every pixel active at f32 plus the worst
/// case of run lengths (alternating active and inactive pixels) and the piece header.
pub fn max_piece_bytes(pixels: u64) -> u64 {
    pixels * 16 + (pixels + 2) * 4 + 64
}

/// A parsed frame header.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct FrameHeader {
    /// Meta length.
    pub meta_len: u32,
    /// Bulk length.
    pub bulk_len: u64,
}

/// Why a frame was refused.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum WireError {
    /// Not a Strata frame.
    #[error("bad frame magic {0:02x?} (expected \"STRF\"): not a Strata peer")]
    BadMagic([u8; 4]),
    /// Another protocol version.
    #[error("protocol version {got}, this build speaks {PROTOCOL_VERSION}")]
    Version {
        /// The peer's version.
        got: u16,
    },
    /// Header corrupted.
    #[error("frame header checksum mismatch (stored {stored:08x}, computed {computed:08x})")]
    HeaderCrc {
        /// Stored CRC.
        stored: u32,
        /// Computed CRC.
        computed: u32,
    },
    /// Reserved bits set.
    #[error("frame header reserved field is {0}, expected 0")]
    Reserved(u16),
    /// Meta too large.
    #[error("frame meta of {len} bytes exceeds the limit of {limit} bytes")]
    MetaTooLarge {
        /// Announced length.
        len: u32,
        /// The limit.
        limit: u32,
    },
    /// Bulk too large.
    #[error("frame payload of {len} bytes exceeds the limit of {limit} bytes")]
    BulkTooLarge {
        /// Announced length.
        len: u64,
        /// The limit.
        limit: u64,
    },
    /// The meta message did not decode.
    #[error("malformed message: {0}")]
    Decode(String),
}

/// Encodes a frame header for a meta of `meta_len` bytes and a bulk of `bulk_len` bytes.
pub fn encode_header(meta_len: u32, bulk_len: u64) -> [u8; HEADER_LEN] {
    let mut h = [0u8; HEADER_LEN];
    h[0..4].copy_from_slice(&MAGIC);
    h[4..6].copy_from_slice(&PROTOCOL_VERSION.to_le_bytes());
    h[8..12].copy_from_slice(&meta_len.to_le_bytes());
    h[12..20].copy_from_slice(&bulk_len.to_le_bytes());
    let crc = crc32c::crc32c(&h[0..20]);
    h[20..24].copy_from_slice(&crc.to_le_bytes());
    h
}

/// Parses and checks a frame header against `limits`.
pub fn decode_header(h: &[u8; HEADER_LEN], limits: &Limits) -> Result<FrameHeader, WireError> {
    let magic: [u8; 4] = h[0..4].try_into().unwrap();
    if magic != MAGIC {
        return Err(WireError::BadMagic(magic));
    }
    let stored = u32::from_le_bytes(h[20..24].try_into().unwrap());
    let computed = crc32c::crc32c(&h[0..20]);
    if stored != computed {
        return Err(WireError::HeaderCrc { stored, computed });
    }
    let version = u16::from_le_bytes(h[4..6].try_into().unwrap());
    if version != PROTOCOL_VERSION {
        return Err(WireError::Version { got: version });
    }
    let reserved = u16::from_le_bytes(h[6..8].try_into().unwrap());
    if reserved != 0 {
        return Err(WireError::Reserved(reserved));
    }
    let meta_len = u32::from_le_bytes(h[8..12].try_into().unwrap());
    let bulk_len = u64::from_le_bytes(h[12..20].try_into().unwrap());
    if meta_len > limits.max_meta {
        return Err(WireError::MetaTooLarge {
            len: meta_len,
            limit: limits.max_meta,
        });
    }
    if bulk_len > limits.max_bulk {
        return Err(WireError::BulkTooLarge {
            len: bulk_len,
            limit: limits.max_bulk,
        });
    }
    Ok(FrameHeader { meta_len, bulk_len })
}

fn config() -> impl bincode::config::Config {
    // The limit bounds what a length prefix inside a (length-checked) meta may claim.
    bincode::config::standard().with_limit::<{ MAX_META as usize }>()
}

/// Serializes a meta message.
pub fn encode_meta<T: Serialize>(msg: &T) -> Vec<u8> {
    bincode::serde::encode_to_vec(msg, config()).expect("in-memory bincode encoding cannot fail")
}

/// Deserializes a meta message; the whole buffer must be consumed.
pub fn decode_meta<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, WireError> {
    let (v, used) = bincode::serde::decode_from_slice::<T, _>(bytes, config())
        .map_err(|e| WireError::Decode(e.to_string()))?;
    if used != bytes.len() {
        return Err(WireError::Decode(format!(
            "{} trailing bytes after the message",
            bytes.len() - used
        )));
    }
    Ok(v)
}

/// A SHA-256 certificate fingerprint.
pub type Fingerprint = [u8; 32];

/// Compositing choices carried with every frame (resolved from `[composite]`).
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct CompositeChoice {
    /// The exchange algorithm.
    pub algorithm: Algorithm,
    /// radix-k: one target k, or the exact factors.
    pub k: Vec<u32>,
    /// Row interlacing of the pixel space.
    pub interlace: bool,
    /// Pixel precision on the wire.
    pub format: WireFormat,
    /// LZ4 on the pieces that travel over QUIC (`composite.lz4`).
    pub lz4: bool,
}

impl CompositeChoice {
    /// The compositing plan of a frame of `ranks` ranks and `pixels` pixels under these
    /// choices (`k` empty: the algorithm's default factors).
    pub fn plan(
        &self,
        ranks: usize,
        pixels: u32,
    ) -> Result<crate::composite::Plan, crate::composite::PlanError> {
        let k: Vec<usize> = self.k.iter().map(|&k| k as usize).collect();
        crate::composite::build_plan(
            ranks,
            pixels,
            self.algorithm,
            (!k.is_empty()).then_some(&k[..]),
        )
    }
}

/// A shared secret's bytes. They travel as the bytes themselves (`serde(transparent)`: the
/// wire format is a plain byte string), and `Debug` shows only their length, so a message,
/// an options struct or an error that prints one with `{:?}` does not print the secret.
#[derive(Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(transparent)]
pub struct Secret(pub Vec<u8>);

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Secret(<{} bytes>)", self.0.len())
    }
}

/// Worker → coordinator.
// Messages are built once per frame or set-up and sent at once: a box per large variant
// would only add an allocation.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum WorkerMsg {
    /// First message on a connection: who the worker is and the shared secret.
    Hello {
        /// Shared secret of the run.
        secret: Secret,
        /// Human-readable name (host:pid by default).
        name: String,
        /// Process id.
        pid: u32,
        /// Fingerprint of the worker's own certificate, which its peers will pin.
        fingerprint: Fingerprint,
        /// Where the worker could share memory: its host's boot id and pid namespace
        /// (`strata_net::shm::host_id`); `None` where it has none. Two processes
        /// with the same id can exchange pieces through shared memory.
        host: Option<String>,
    },
    /// The shared-memory segment (an anonymous memory file, `strata_net::shm`) that this
    /// worker's final pieces will be written to; sent before `Ready` when
    /// `Setup::shm_gather` asks for it.
    ShmSegment {
        /// The segment's name, `strata-shm-` and 32 hex digits.
        name: String,
        /// The worker's process id.
        pid: u32,
        /// The segment's descriptor in the worker.
        fd: i32,
    },
    /// Peer connections are up; ready for frames.
    Ready,
    /// Sent first on taking a set-up: the `ShmSegment`, `Ready` or `Failed` that follow
    /// answer set-up `attempt` (`Setup::attempt`), so the coordinator can tell them from
    /// the answers to a set-up it has since replaced.
    Meshing {
        /// The set-up's attempt number.
        attempt: u32,
    },
    /// A frame's result: the final piece follows as bulk, or lies in the worker's
    /// shared-memory segment at `shm`.
    FrameDone {
        /// Frame number.
        frame: u64,
        /// What it cost.
        stats: WorkerFrameStats,
        /// Where the final piece lies in the segment (`None`: it follows as bulk).
        shm: Option<ShmRef>,
        /// The bulk piece is LZ4-compressed ([`crate::composite::SparsePiece::write_lz4`]).
        lz4: bool,
        /// The final piece was written in place into the frame's canvas
        /// (`FrameRequest::canvas`), covering this span; no piece follows and `shm` is
        /// `None`.
        canvas: Option<crate::composite::Span>,
    },
    /// Cross-worker occlusion (`FrameRequest::occlusion`; not sent by the last worker of the
    /// order, which has no one behind it): this worker's partial image of
    /// the frame reduced to per-block transmittance over `rect`
    /// ([`crate::occlusion::Transmittance`]); the `rect.w · rect.h` levels follow as bulk,
    /// as [`crate::occlusion::encode_levels`] writes them.
    Coverage {
        /// Frame number.
        frame: u64,
        /// The blocks the values cover.
        rect: BlockRect,
        /// Of the low-resolution first pass (one-pixel blocks at
        /// `1/FrameRequest::occlusion_prepass`), not of the frame.
        prepass: bool,
    },
    /// The worker could not do what was asked.
    Failed {
        /// The frame, if any.
        frame: Option<u64>,
        /// Why.
        message: String,
        /// Peers (ranks) the failure is blamed on: lost connections, missing pieces.
        suspects: Vec<u32>,
    },
}

/// Coordinator → worker.
// As `WorkerMsg`: built once and sent at once.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum CoordMsg {
    /// Everything a worker needs before the first frame.
    Setup(Box<Setup>),
    /// Render and composite one frame.
    Frame(FrameRequest),
    /// The coordinator gave up on this worker (rank): frames that include it fail at once.
    PeerLost {
        /// The lost worker's rank.
        rank: u32,
    },
    /// Cross-worker occlusion: per block of the frame's block grid, the transmittance of
    /// what lies in front of this worker ([`crate::occlusion::front_of`]). Not sent to the
    /// first worker of the frame's order, which has nothing in front.
    Occlusion {
        /// Frame number.
        frame: u64,
        /// [`crate::occlusion::FrontTransmittance::q`] as [`crate::occlusion::encode_levels`]
        /// writes it (LZ4 of the shuffled little-endian levels).
        front: Vec<u8>,
        /// Of the low-resolution first pass.
        prepass: bool,
    },
    /// Exit cleanly.
    Shutdown,
    /// The connection is refused (sent before closing it).
    Refused {
        /// Why.
        reason: String,
    },
}

/// A peer worker's address and identity.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PeerInfo {
    /// UDP address its endpoint listens on.
    pub addr: String,
    /// Its certificate fingerprint.
    pub fingerprint: Fingerprint,
    /// Its name.
    pub name: String,
}

/// The run set-up of one worker.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Setup {
    /// This worker's rank.
    pub rank: u32,
    /// The scene as TOML, with every path absolute (workers read the same store paths).
    pub scene_toml: String,
    /// The leaf regions this worker renders (one k-d subtree).
    pub leaves: Vec<Region>,
    /// Every worker by rank (including this one).
    pub peers: Vec<PeerInfo>,
    /// Token peers present to each other (random per run).
    pub run_token: [u8; 32],
    /// Largest frame (pixels) of the run, which bounds the size of image pieces.
    pub max_pixels: u64,
    /// How long to wait for any one peer message.
    pub timeout_ms: u64,
    /// By rank: whether pieces to and from that peer go through shared memory (both on
    /// this host and `cluster.transport` allows it) instead of QUIC.
    pub shm_peers: Vec<bool>,
    /// Whether the final piece goes to the coordinator through shared memory.
    pub shm_gather: bool,
    /// Ranks given up on during set-up: not meshed with, never in a frame. The coordinator
    /// sends a new set-up with them here when a worker is lost before the run is ready.
    pub absent: Vec<u32>,
    /// 0 for the first set-up of the run, counting up with each new one.
    pub attempt: u32,
    /// The number of the next frame the coordinator will request (a set-up during a
    /// sequence starts past 0).
    pub next_frame: u64,
}

/// Where a record lies in a shared-memory segment.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShmRef {
    /// Byte offset of the record header in the segment.
    pub offset: u64,
    /// Length of the payload after the header.
    pub len: u64,
}

/// The round field of a final piece's record in a gather segment (the sender field holds
/// the worker's rank), so writer and reader agree on it.
pub const GATHER_ROUND: u32 = u32::MAX;

/// Size of the header in front of every record in a shared-memory segment.
pub const SHM_RECORD_HEADER: usize = 32;
/// Magic of a shared-memory record.
pub const SHM_MAGIC: [u8; 8] = *b"STRATASH";

/// The header written in front of a record: magic, frame, round, sender position and
/// payload length, so the reader can tell a record from stale or foreign bytes.
pub fn encode_shm_record(frame: u64, round: u32, from: u32, len: u64) -> [u8; SHM_RECORD_HEADER] {
    let mut h = [0u8; SHM_RECORD_HEADER];
    h[0..8].copy_from_slice(&SHM_MAGIC);
    h[8..16].copy_from_slice(&frame.to_le_bytes());
    h[16..20].copy_from_slice(&round.to_le_bytes());
    h[20..24].copy_from_slice(&from.to_le_bytes());
    h[24..32].copy_from_slice(&len.to_le_bytes());
    h
}

/// Checks a record header read from a segment against what the announcing message said.
pub fn check_shm_record(
    h: &[u8; SHM_RECORD_HEADER],
    frame: u64,
    round: u32,
    from: u32,
    len: u64,
) -> Result<(), String> {
    if h[0..8] != SHM_MAGIC {
        return Err(format!(
            "bad record magic {:02x?} (expected \"STRATASH\")",
            &h[0..8]
        ));
    }
    let got = (
        u64::from_le_bytes(h[8..16].try_into().unwrap()),
        u32::from_le_bytes(h[16..20].try_into().unwrap()),
        u32::from_le_bytes(h[20..24].try_into().unwrap()),
        u64::from_le_bytes(h[24..32].try_into().unwrap()),
    );
    if got != (frame, round, from, len) {
        return Err(format!(
            "the record holds frame {}, round {}, position {}, {} bytes; the message announced frame {frame}, round {round}, position {from}, {len} bytes",
            got.0, got.1, got.2, got.3
        ));
    }
    Ok(())
}

/// One frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameRequest {
    /// Frame number (increasing).
    pub frame: u64,
    /// Camera of this frame.
    pub camera: Camera,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Ranks in visibility order (position → rank), front first.
    pub order: Vec<u32>,
    /// This worker's leaves (indices into `Setup::leaves`), front to back.
    pub leaf_order: Vec<u32>,
    /// How to composite.
    pub composite: CompositeChoice,
    /// Where the partial images come from.
    pub source: FrameSource,
    /// This worker's new leaves after a re-split of the k-d tree (from this frame on; at
    /// most [`MAX_LEAVES_PER_WORKER`]); `None` keeps the current ones. `leaf_order`
    /// indexes the leaves in force for the frame.
    pub leaves: Option<Vec<Region>>,
    /// Cross-worker occlusion (`cluster.occlusion`): the side of its screen blocks in pixels
    /// (0: off). After rendering, send [`WorkerMsg::Coverage`] unless last in `order`, and
    /// wait for [`CoordMsg::Occlusion`] unless first, before compositing.
    pub occlusion_block: u32,
    /// Cross-worker occlusion with no prediction from the previous frame (`cluster.occlusion_prepass`):
    /// first render at `1/occlusion_prepass` of the resolution and exchange its coverage
    /// ([`WorkerMsg::Coverage`] and [`CoordMsg::Occlusion`] with `prepass`) as the
    /// prediction; 0: no first pass.
    pub occlusion_prepass: u32,
    /// Cross-worker occlusion (`cluster.occlusion_motion`): how far, in pixels, the scene
    /// moved on screen since the frame whose map this worker predicts from; the worker
    /// raises each block of that map to the largest level within this distance
    /// ([`crate::occlusion::FrontTransmittance::dilated`]). 0: the map as it is.
    pub occlusion_motion: u32,
    /// Report where the frame's render time went, page by page
    /// ([`WorkerFrameStats::page_work`]), for a re-split by the view's measured work
    /// (`cluster.rebalance_model = "pages"`).
    pub page_work: bool,
    /// A powerwall frame: `width × height` is the wall's stacked image, rays follow its
    /// tiles, compositing delivers each tile to its driver, which writes the tile's files;
    /// the final pieces sent to the coordinator are empty.
    pub wall: Option<WallFrame>,
    /// The coordinator's frame-sized image in shared memory (`strata_net::canvas`), given
    /// to workers on its host: write the final span there, in place, and report it in
    /// `WorkerMsg::FrameDone::canvas`. `None`: send the final piece.
    pub canvas: Option<CanvasRef>,
}

/// A shared-memory canvas, as announced over the authenticated connection (what
/// `strata_net::shm::SegmentId` holds).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CanvasRef {
    /// `strata-shm-` and 32 hex digits.
    pub name: String,
    /// The coordinator's process id.
    pub pid: u32,
    /// The canvas's descriptor in the coordinator.
    pub fd: i32,
}

/// A powerwall frame ([`crate::wall`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WallFrame {
    /// The tile layout.
    pub geometry: crate::wall::WallGeometry,
    /// The rank that drives each tile, row-major (each rank's tiles consecutive).
    pub drivers: Vec<u32>,
    /// Each tile's files, row-major.
    pub files: Vec<crate::wall::TileFiles>,
    /// Background the PNGs are flattened over (linear RGB).
    pub background: [f32; 3],
}

impl WallFrame {
    /// Checks a wall frame from the network against the frame's size and ranks.
    pub fn check(&self, width: u32, height: u32, order: &[u32]) -> Result<(), String> {
        let g = &self.geometry;
        g.check()?;
        if g.stacked_size() != (width, height) {
            return Err(format!(
                "a wall of {}x{} tiles of {}x{} stacks to {:?}, the frame is {width}x{height}",
                g.cols,
                g.rows,
                g.tile_w,
                g.tile_h,
                g.stacked_size()
            ));
        }
        let ranks = order.iter().copied().max().map_or(0, |m| m as usize + 1);
        g.check_drivers(&self.drivers, ranks)
            .map_err(|e| e.to_string())?;
        if let Some(r) = self.drivers.iter().find(|r| !order.contains(r)) {
            return Err(format!(
                "tile driver rank {r} is not in the frame's order {order:?}"
            ));
        }
        let t = g.tiles() as usize;
        if self.files.len() != t {
            return Err(format!("{} tile outputs for {t} tiles", self.files.len()));
        }
        Ok(())
    }
}

/// Leaves one worker may be given.
pub const MAX_LEAVES_PER_WORKER: usize = 64;

/// The most ranks a run may have: a set-up naming more is refused before anything is
/// sized from it.
pub const MAX_RANKS: usize = 4096;

/// Checks leaf regions from the network: 1..=[`MAX_LEAVES_PER_WORKER`] of them, each
/// finite and not empty.
pub fn check_leaves(leaves: &[Region]) -> Result<(), String> {
    if leaves.is_empty() || leaves.len() > MAX_LEAVES_PER_WORKER {
        return Err(format!(
            "{} leaves (expected 1..={MAX_LEAVES_PER_WORKER})",
            leaves.len()
        ));
    }
    for r in leaves {
        if !(0..3).all(|a| r.lo[a].is_finite() && r.hi[a].is_finite() && r.lo[a] < r.hi[a]) {
            return Err(format!("a leaf region {r:?} is empty or not finite"));
        }
    }
    Ok(())
}

impl Setup {
    /// Checks a set-up from the network before a worker sizes anything from it: the run's
    /// ranks (at most [`MAX_RANKS`]), this worker's rank and the absent ones among them,
    /// one transport per peer, a frame limit that fits the `u32` pixel counts frames use,
    /// and the leaves.
    pub fn check(&self) -> Result<(), String> {
        let n = self.peers.len();
        if n == 0 || n > MAX_RANKS {
            return Err(format!("a run of {n} workers (expected 1..={MAX_RANKS})"));
        }
        if self.rank as usize >= n {
            return Err(format!(
                "rank {} is not below the number of workers {n}",
                self.rank
            ));
        }
        let mut seen = vec![false; n];
        for &r in &self.absent {
            if r == self.rank || r as usize >= n || std::mem::replace(&mut seen[r as usize], true) {
                return Err(format!(
                    "the set-up's absent ranks {:?} must be distinct other ranks below {n}",
                    self.absent
                ));
            }
        }
        if self.shm_peers.len() != n {
            return Err(format!(
                "the set-up names the transport of {} peers, the run has {n}",
                self.shm_peers.len()
            ));
        }
        if self.max_pixels == 0 || self.max_pixels > u32::MAX as u64 {
            return Err(format!(
                "a frame limit of {} pixels (expected 1..={})",
                self.max_pixels,
                u32::MAX
            ));
        }
        check_leaves(&self.leaves).map_err(|e| format!("the set-up's leaves: {e}"))
    }
}

impl FrameRequest {
    /// Checks a frame request from the network against the run: `ranks` workers,
    /// `leaves` leaves in force before it (its own re-split, if any, replaces them) and a
    /// frame limit of `max_pixels`. The visibility order names distinct ranks of the run;
    /// `leaf_order` is a permutation of the leaves (a leaf cast twice would double its
    /// opacity, one left out would vanish from the image); the frame fits the limit; the
    /// occlusion blocks, and the first pass's scale, are at most
    /// [`crate::occlusion::MAX_BLOCK`]; a wall frame fits its frame and takes no canvas (its
    /// tiles go to files).
    pub fn check(&self, ranks: usize, leaves: usize, max_pixels: u64) -> Result<(), String> {
        let f = self.frame;
        let leaves = match &self.leaves {
            Some(l) => {
                check_leaves(l).map_err(|e| format!("frame {f}: {e}"))?;
                l.len()
            }
            None => leaves,
        };
        let n = self.order.len();
        if !(1..=ranks).contains(&n) {
            return Err(format!(
                "frame {f}: the visibility order has {n} ranks, the run has {ranks}"
            ));
        }
        let mut seen = vec![false; ranks];
        for &r in &self.order {
            if r as usize >= ranks || std::mem::replace(&mut seen[r as usize], true) {
                return Err(format!(
                    "frame {f}: the visibility order {:?} repeats a rank or names one beyond the {ranks} ranks",
                    self.order
                ));
            }
        }
        let mut seen = vec![false; leaves];
        let permutation = self.leaf_order.len() == leaves
            && self
                .leaf_order
                .iter()
                .all(|&l| (l as usize) < leaves && !std::mem::replace(&mut seen[l as usize], true));
        if !permutation {
            return Err(format!(
                "frame {f}: the leaf order {:?} is not an order of the worker's {leaves} leaves",
                self.leaf_order
            ));
        }
        let pixels = self.width as u64 * self.height as u64;
        if pixels == 0 || pixels > max_pixels.min(u32::MAX as u64) {
            return Err(format!(
                "frame {f}: {}x{} pixels exceed the run's limit of {max_pixels} pixels (or are none)",
                self.width, self.height
            ));
        }
        if self.occlusion_block > crate::occlusion::MAX_BLOCK {
            return Err(format!(
                "frame {f}: occlusion blocks of {} pixels (at most {})",
                self.occlusion_block,
                crate::occlusion::MAX_BLOCK
            ));
        }
        // The first pass renders at 1/scale of the frame, the coordinator's map of it too:
        // a scale the worker would change would give the two different grids.
        if self.occlusion_prepass > crate::occlusion::MAX_BLOCK {
            return Err(format!(
                "frame {f}: an occlusion first pass at 1/{} of the resolution (at most 1/{})",
                self.occlusion_prepass,
                crate::occlusion::MAX_BLOCK
            ));
        }
        // A block's pixel edges are u32 sums: a side within a block of 2³² would overflow.
        let edge = u32::MAX - crate::occlusion::MAX_BLOCK;
        if self.occlusion_block > 0 && (self.width > edge || self.height > edge) {
            return Err(format!(
                "frame {f}: occlusion over a side of more than {edge} pixels ({}x{})",
                self.width, self.height
            ));
        }
        if let Some(w) = &self.wall {
            w.check(self.width, self.height, &self.order)
                .map_err(|e| format!("frame {f}: bad wall: {e}"))?;
            if self.canvas.is_some() {
                return Err(format!(
                    "frame {f}: a wall frame with a canvas (its tiles go to files)"
                ));
            }
        }
        Ok(())
    }
}

/// Largest number of [`PageWork`] records one worker reports per frame (about 1 MB on the
/// wire, a quarter of [`MAX_META`]); a worker that touched more pages reports its largest
/// shares and leaves the rest unattributed.
pub const MAX_PAGE_WORK: usize = 65_536;

/// The share of one leaf's final cast that went into one page: the thread time of each
/// tile, divided among the pages its rays entered in proportion to how many rays entered
/// each, over the thread time of all the leaf's tiles. A leaf's shares add up to at most 1;
/// the rest is time in tiles whose rays entered no page.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PageWork {
    /// The leaf (index into `Setup::leaves` or the last `FrameRequest::leaves`).
    pub leaf: u32,
    /// The page's feedback key (data set, level, Morton index; `strata_common::ids::PageId`).
    pub key: u64,
    /// Its share of the leaf's cast, in `(0, 1]`.
    pub share: f32,
}

/// What a worker composites.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum FrameSource {
    /// Render its leaves of the scene.
    Render,
    /// Benchmark images (no rendering): every rank draws a translucent box covering
    /// `coverage` of the frame (1.0: every pixel active), deterministic in `seed`, so the
    /// exchange can be measured on dense and on sparse images as IceT's `SimpleTiming` does.
    Synthetic {
        /// Fraction of the frame each rank's image covers.
        coverage: f32,
        /// Seed of the colours and box placement.
        seed: u64,
    },
}

/// Peer ↔ peer.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum PeerMsg {
    /// First message of a connector: the run token and its rank.
    Hello {
        /// The run token from `Setup`.
        token: [u8; 32],
        /// The connector's rank.
        rank: u32,
    },
    /// One piece of a compositing round; the encoded piece follows as bulk.
    Piece {
        /// Frame number.
        frame: u64,
        /// Round of the plan.
        round: u32,
        /// Sender's position in the visibility order.
        from: u32,
        /// The bulk is LZ4-compressed ([`crate::composite::SparsePiece::write_lz4`]).
        lz4: bool,
    },
    /// The shared-memory segment this peer writes its pieces for the receiver to (sent
    /// once, before any `ShmPiece`, when `Setup::shm_peers` says so).
    ShmSegment {
        /// The segment's name, `strata-shm-` and 32 hex digits.
        name: String,
        /// The sender's process id.
        pid: u32,
        /// The segment's descriptor in the sender.
        fd: i32,
    },
    /// One piece of a compositing round, written to the sender's segment at `at`.
    ShmPiece {
        /// Frame number.
        frame: u64,
        /// Round of the plan.
        round: u32,
        /// Sender's position in the visibility order.
        from: u32,
        /// Where the record lies.
        at: ShmRef,
    },
    /// The accepting side's answer to a `Hello` it took (token, rank and certificate
    /// right): the connector retries until it hears it, since a peer still on an earlier
    /// set-up refuses the new token.
    Welcome,
}

/// What one frame cost one worker.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WorkerFrameStats {
    /// Rank.
    pub rank: u32,
    /// Position in this frame's visibility order.
    pub position: u32,
    /// Seconds rendering (all feedback rounds, all leaves, loads included): the frame's
    /// render, after occlusion's first pass (`prepass_s`) and before its fix-up
    /// (`fixup_s`); `cast_s` and `load_s` include both of those too.
    pub render_s: f64,
    /// When rendering ended (µs since the Unix epoch, this worker's clock). A timestamp for
    /// logs only: no duration is computed across two hosts' clocks.
    pub render_end_us: u64,
    /// Seconds casting rays over all feedback rounds (all leaves).
    pub cast_s: f64,
    /// CPU seconds (user and system, every thread of the worker process) from the frame
    /// request to the end of rendering: the render's work, which sharing cores with other
    /// processes does not inflate as it does `render_s`.
    pub render_cpu_s: f64,
    /// CPU seconds of the worker process over the whole frame (render, occlusion, exchange,
    /// final piece).
    pub cpu_s: f64,
    /// Seconds loading pages and updating the atlas between rounds.
    pub load_s: f64,
    /// Seconds of each feedback round's cast, summed over the worker's leaves (round `k` of
    /// every leaf's batch, and of an occlusion fix-up's, in entry `k`; the first pass is
    /// not in it).
    pub round_cast_s: Vec<f64>,
    /// Seconds of each feedback round's loads and atlas update, summed as `round_cast_s`.
    pub round_load_s: Vec<f64>,
    /// Seconds of the final round's cast (all leaves): the converged frame's cost, what the
    /// in-process summary calls the last frame. Where that round re-cast only some tiles
    /// (selective rounds), the last full round's time scaled by the converged tiles' thread
    /// time; an occlusion fix-up's cast is added.
    pub last_round_s: f64,
    /// Pages read from disk since this worker first opened the scene (its root pages
    /// included; the engines of earlier set-ups too, after a lost worker's re-mesh), as the
    /// in-process engine counts them.
    pub pages_read: u64,
    /// Stored bytes read from disk, counted as `pages_read`.
    pub bytes_read: u64,
    /// Page-cache lookups that hit, counted as `pages_read`.
    pub cache_hits: u64,
    /// Page-cache lookups, counted as `pages_read`.
    pub cache_lookups: u64,
    /// Seconds from the end of rendering to the final piece written for the coordinator
    /// (encode, exchange, blend, final encode), on this worker's clock.
    pub composite_s: f64,
    /// Seconds of each leaf's final-round cast, in the order of this worker's leaves (for
    /// re-splitting by measured cost).
    pub leaf_cast_s: Vec<f64>,
    /// The CPUs this worker's process may run on, as Linux lists them (`0-3,8`): its
    /// binding by `cluster.pin_workers` or by a launcher (`srun --cpu-bind`); empty where
    /// the system will not say.
    #[serde(default)]
    pub cpus: String,
    /// The CPU time of each leaf's final-round cast (a whole cast of its converged tiles:
    /// their threads' CPU seconds) over this worker's render threads, in the order of its
    /// leaves: about what the cast would take with the threads to itself (a lower bound:
    /// serial set-up and uneven tile tails are not in it), which more processes than
    /// cores do not inflate. 0 for a leaf that cast nothing (off screen); empty where the
    /// worker cannot say (GPU backend, no per-thread clock).
    #[serde(default)]
    pub leaf_cpu_s: Vec<f64>,
    /// Where each leaf's final cast went, page by page (only when the frame request asked
    /// for `page_work`; at most [`MAX_PAGE_WORK`] records; empty on the GPU backend, which
    /// times no tiles).
    pub page_work: Vec<PageWork>,
    /// Seconds encoding outgoing pieces (active-pixel runs, f16 conversion); the final
    /// piece's encoding is in `gather_s`.
    pub encode_s: f64,
    /// Seconds in the exchange: sending and waiting for pieces.
    pub exchange_s: f64,
    /// Seconds blending received pieces.
    pub blend_s: f64,
    /// Seconds encoding the final piece and handing it to the coordinator's transport
    /// (written to the shared-memory segment or canvas, or serialized for QUIC).
    pub gather_s: f64,
    /// Bytes sent to peers (both transports).
    pub bytes_sent: u64,
    /// Of these, bytes that went through shared memory.
    pub shm_bytes_sent: u64,
    /// Bytes received from peers.
    pub bytes_received: u64,
    /// Bytes of the final piece sent to the coordinator (written into its canvas: the
    /// f32 pixels of the span).
    pub gather_bytes: u64,
    /// The last compositing round was blended straight into the coordinator's canvas,
    /// so the gather copied nothing.
    #[serde(default)]
    pub blended_in_canvas: bool,
    /// Compositing rounds.
    pub rounds: u32,
    /// Feedback rounds of the renderer.
    pub render_rounds: u32,
    /// Ray samples of the last render round, of the occlusion fix-up's last round and of
    /// the occlusion first pass when the frame had one: the work the frame's image took.
    pub samples: u64,
    /// Rays of the last render round (and of the occlusion fix-up's last round): every
    /// pixel of each leaf's screen rectangle that was cast, whether or not it met the leaf.
    pub rays: u64,
    /// Cross-worker occlusion: screen blocks left uncast because the previous frame
    /// predicted content in front of this worker hides them.
    pub occluded_blocks: u64,
    /// Screen blocks cast with a lower termination threshold because the previous frame
    /// predicted content in front of this worker lets only part of the light through.
    pub limited_blocks: u64,
    /// Blocks this frame's front transmittance did not confirm (the prediction promised
    /// less light than there is), cast again with this frame's thresholds.
    pub fixup_blocks: u64,
    /// How far, in blocks `(x, y)`, the prediction from the last frame was moved with
    /// this worker's region on screen (new position − old, y down; `(0, 0)` when the camera
    /// did not move, when the map was widened by `cluster.occlusion_motion` instead, and
    /// when a first pass replaced the prediction).
    pub occlusion_shift: [i32; 2],
    /// Seconds from sending the coverage to receiving the front transmittance.
    pub occlusion_s: f64,
    /// Seconds of the fix-up render.
    pub fixup_s: f64,
    /// Seconds of occlusion's low-resolution first pass, its map exchange included.
    pub prepass_s: f64,
    /// Wall frames: tiles this worker drives and wrote.
    pub tiles_written: u32,
    /// Wall frames: seconds writing them.
    pub tile_write_s: f64,
    /// "converged", "round-limit" or "atlas-full".
    pub outcome: String,
    /// The backend and adapter that rendered, e.g. `gpu: NVIDIA H100 (Vulkan)` or `cpu (8 threads)`.
    pub backend: String,
    /// The effects of the frame's final renders (`strata_common::effects`), e.g.
    /// `volume+horizons`; leaves that differ are joined by `; `.
    pub effects: String,
    /// Their code paths, e.g. `specialised [volume+horizons] simd`.
    pub variant: String,
}

impl WorkerFrameStats {
    /// Checks the durations a worker reports: each finite and not negative (a NaN or an
    /// infinity from a faulty worker would reach the run's summary and `--stats` as
    /// `NaN`, `inf` or `null`). Names the first field that is not.
    pub fn check_times(&self) -> Result<(), String> {
        let one = [
            ("render_s", self.render_s),
            ("cast_s", self.cast_s),
            ("render_cpu_s", self.render_cpu_s),
            ("cpu_s", self.cpu_s),
            ("load_s", self.load_s),
            ("last_round_s", self.last_round_s),
            ("composite_s", self.composite_s),
            ("encode_s", self.encode_s),
            ("exchange_s", self.exchange_s),
            ("blend_s", self.blend_s),
            ("gather_s", self.gather_s),
            ("occlusion_s", self.occlusion_s),
            ("fixup_s", self.fixup_s),
            ("prepass_s", self.prepass_s),
            ("tile_write_s", self.tile_write_s),
        ];
        let many = [
            ("round_cast_s", &self.round_cast_s),
            ("round_load_s", &self.round_load_s),
            ("leaf_cast_s", &self.leaf_cast_s),
            ("leaf_cpu_s", &self.leaf_cpu_s),
        ];
        let bad = |v: f64| !(v.is_finite() && v >= 0.0);
        if let Some((name, v)) = one.into_iter().find(|&(_, v)| bad(v)) {
            return Err(format!(
                "{name} = {v} (expected a finite time of 0 s or more)"
            ));
        }
        for (name, list) in many {
            if let Some((i, v)) = list.iter().enumerate().find(|&(_, &v)| bad(v)) {
                return Err(format!(
                    "{name}[{i}] = {v} (expected a finite time of 0 s or more)"
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A hello's secret travels as a plain byte string (the same bytes as a `Vec<u8>`
    /// field) and never shows in `Debug`.
    #[test]
    fn a_secret_travels_as_bytes_and_is_not_debug_printed() {
        let secret = b"correct-horse-battery-staple-42".to_vec();
        let hello = WorkerMsg::Hello {
            secret: Secret(secret.clone()),
            name: "w".into(),
            pid: 7,
            fingerprint: [3; 32],
            host: None,
        };
        assert!(!format!("{hello:?}").contains("correct-horse"), "{hello:?}");
        assert!(format!("{hello:?}").contains("<31 bytes>"), "{hello:?}");
        let plain = bincode::serde::encode_to_vec(&secret, config()).unwrap();
        let wrapped = bincode::serde::encode_to_vec(Secret(secret.clone()), config()).unwrap();
        assert_eq!(plain, wrapped);
        assert_eq!(
            decode_meta::<WorkerMsg>(&encode_meta(&hello)).unwrap(),
            hello
        );
    }
    use proptest::prelude::*;

    fn region(x0: f64) -> Region {
        Region {
            lo: [x0, 0.0, 0.0],
            hi: [x0 + 1.0, 1.0, 1.0],
        }
    }

    fn setup() -> Setup {
        let peer = |i: u8| PeerInfo {
            addr: format!("127.0.0.1:{}", 7000 + i as u16),
            fingerprint: [i; 32],
            name: format!("w{i}"),
        };
        Setup {
            rank: 1,
            scene_toml: String::new(),
            leaves: vec![region(0.0), region(1.0)],
            peers: vec![peer(0), peer(1), peer(2)],
            run_token: [7; 32],
            max_pixels: 64 * 48,
            timeout_ms: 1000,
            shm_peers: vec![true; 3],
            shm_gather: true,
            absent: vec![2],
            attempt: 0,
            next_frame: 0,
        }
    }

    fn request() -> FrameRequest {
        FrameRequest {
            frame: 3,
            camera: Camera {
                eye: [0.0, -10.0, 5.0],
                target: [0.0; 3],
                up: [0.0, 0.0, 1.0],
                fov_deg: 30.0,
            },
            width: 64,
            height: 48,
            order: vec![2, 0, 1],
            leaf_order: vec![1, 0],
            composite: CompositeChoice {
                algorithm: Algorithm::RadixK,
                k: vec![],
                interlace: true,
                format: WireFormat::F32,
                lz4: false,
            },
            source: FrameSource::Render,
            leaves: None,
            occlusion_block: 2,
            occlusion_prepass: 4,
            occlusion_motion: 0,
            page_work: false,
            wall: None,
            canvas: None,
        }
    }

    /// What a worker sizes or indexes from a set-up or a frame request is checked first;
    /// each bad value is refused with what was wrong.
    #[test]
    fn set_ups_and_frame_requests_from_the_network_are_checked() {
        assert_eq!(setup().check(), Ok(()));
        let bad_setup = |f: &dyn Fn(&mut Setup), needle: &str| {
            let mut s = setup();
            f(&mut s);
            let e = s.check().unwrap_err();
            assert!(e.contains(needle), "{needle:?} not in {e:?}");
        };
        bad_setup(&|s| s.rank = 3, "rank 3");
        bad_setup(&|s| s.absent = vec![1], "absent");
        bad_setup(&|s| s.absent = vec![2, 2], "absent");
        bad_setup(
            &|s| {
                s.shm_peers.pop();
            },
            "transport",
        );
        bad_setup(&|s| s.max_pixels = 1 << 40, "frame limit");
        bad_setup(&|s| s.max_pixels = 0, "frame limit");
        bad_setup(&|s| s.leaves.clear(), "0 leaves");
        bad_setup(&|s| s.leaves = vec![region(0.0); 65], "65 leaves");
        bad_setup(&|s| s.leaves[1].hi[2] = f64::NAN, "not finite");
        bad_setup(&|s| s.leaves[0].hi[0] = s.leaves[0].lo[0], "empty");
        bad_setup(
            &|s| s.peers = vec![s.peers[0].clone(); MAX_RANKS + 1],
            "workers",
        );

        let (ranks, leaves, max) = (3, 2, 64 * 48);
        assert_eq!(request().check(ranks, leaves, max), Ok(()));
        let bad = |f: &dyn Fn(&mut FrameRequest), needle: &str| {
            let mut r = request();
            f(&mut r);
            let e = r.check(ranks, leaves, max).unwrap_err();
            assert!(e.contains(needle), "{needle:?} not in {e:?}");
            assert!(e.starts_with("frame 3:"), "{e}");
        };
        // A leaf twice (double opacity), one left out (missing from the image), one
        // beyond the worker's leaves, a million of them.
        bad(&|r| r.leaf_order = vec![0, 0], "leaf order");
        bad(&|r| r.leaf_order = vec![0], "leaf order");
        bad(&|r| r.leaf_order = vec![0, 2], "leaf order");
        bad(&|r| r.leaf_order = vec![0; 1_000_000], "leaf order");
        // A re-split's leaves replace the ones in force: the order follows them.
        let mut r = request();
        r.leaves = Some(vec![region(0.0)]);
        r.leaf_order = vec![0];
        assert_eq!(r.check(ranks, leaves, max), Ok(()));
        bad(&|r| r.leaves = Some(vec![]), "0 leaves");
        bad(&|r| r.order = vec![0, 0, 1], "repeats a rank");
        bad(&|r| r.order = vec![0, 3], "repeats a rank");
        bad(&|r| r.order = vec![], "0 ranks");
        bad(&|r| r.width = 65, "limit");
        bad(&|r| r.width = 0, "limit");
        bad(&|r| r.occlusion_block = 65, "occlusion blocks");
        bad(&|r| r.occlusion_prepass = 65, "first pass at 1/65");
        // Times a worker reports are finite and not negative.
        let mut st = WorkerFrameStats {
            render_s: 0.5,
            round_cast_s: vec![0.25, 0.25],
            ..Default::default()
        };
        assert_eq!(st.check_times(), Ok(()));
        st.exchange_s = f64::NAN;
        assert!(st
            .check_times()
            .unwrap_err()
            .starts_with("exchange_s = NaN"));
        st.exchange_s = 0.0;
        st.round_cast_s[1] = f64::INFINITY;
        assert!(st
            .check_times()
            .unwrap_err()
            .starts_with("round_cast_s[1] = inf"));
        st.round_cast_s[1] = -1e-3;
        assert!(st
            .check_times()
            .unwrap_err()
            .starts_with("round_cast_s[1] = -0.001"));
        // A frame within a huge limit, with a side whose last block edge would overflow.
        let mut wide = request();
        (wide.width, wide.height) = (u32::MAX, 1);
        let e = wide.check(3, 2, u32::MAX as u64).unwrap_err();
        assert!(e.contains("occlusion over a side"), "{e}");
        wide.occlusion_block = 0;
        assert_eq!(wide.check(3, 2, u32::MAX as u64), Ok(()));
        // A wall frame takes no canvas (its last round would land there, not in its
        // tiles' files).
        let wall = WallFrame {
            geometry: crate::wall::WallGeometry {
                cols: 2,
                rows: 1,
                tile_w: 64,
                tile_h: 24,
                mullion_x: 0,
                mullion_y: 0,
            },
            drivers: vec![0, 1],
            files: vec![
                crate::wall::TileFiles {
                    png: "a.png".into(),
                    exr: None,
                };
                2
            ],
            background: [0.0; 3],
        };
        let mut r = request();
        r.wall = Some(wall.clone());
        assert_eq!(r.check(ranks, leaves, max), Ok(()));
        bad(
            &|r| {
                r.wall = Some(wall.clone());
                r.canvas = Some(CanvasRef {
                    name: format!("strata-shm-{}", "0f".repeat(16)),
                    pid: 1,
                    fd: 3,
                })
            },
            "canvas",
        );
    }

    #[test]
    fn header_round_trip_and_limits() {
        let l = Limits {
            max_meta: 100,
            max_bulk: 1000,
        };
        let h = encode_header(10, 1000);
        assert_eq!(
            decode_header(&h, &l).unwrap(),
            FrameHeader {
                meta_len: 10,
                bulk_len: 1000
            }
        );
        assert!(matches!(
            decode_header(&encode_header(101, 0), &l),
            Err(WireError::MetaTooLarge { len: 101, .. })
        ));
        assert!(matches!(
            decode_header(&encode_header(1, u64::MAX), &l),
            Err(WireError::BulkTooLarge { .. })
        ));
        let mut bad = h;
        bad[0] = b'X';
        assert!(matches!(
            decode_header(&bad, &l),
            Err(WireError::BadMagic(_))
        ));
        let mut bad = h;
        bad[9] ^= 1;
        assert!(matches!(
            decode_header(&bad, &l),
            Err(WireError::HeaderCrc { .. })
        ));
    }

    #[test]
    fn messages_round_trip() {
        let m = PeerMsg::Piece {
            frame: 7,
            round: 2,
            from: 3,
            lz4: true,
        };
        assert_eq!(decode_meta::<PeerMsg>(&encode_meta(&m)).unwrap(), m);
        let w = WorkerMsg::FrameDone {
            frame: 1,
            stats: WorkerFrameStats {
                outcome: "converged".into(),
                backend: "cpu (2 threads)".into(),
                ..Default::default()
            },
            shm: Some(ShmRef {
                offset: 64,
                len: 1000,
            }),
            lz4: false,
            canvas: None,
        };
        assert_eq!(decode_meta::<WorkerMsg>(&encode_meta(&w)).unwrap(), w);
        let c = WorkerMsg::FrameDone {
            frame: 2,
            stats: WorkerFrameStats::default(),
            shm: None,
            lz4: false,
            canvas: Some(crate::composite::Span { start: 10, end: 99 }),
        };
        assert_eq!(decode_meta::<WorkerMsg>(&encode_meta(&c)).unwrap(), c);
        let mut bytes = encode_meta(&m);
        bytes.push(0);
        assert!(decode_meta::<PeerMsg>(&bytes).is_err());
    }

    #[test]
    fn shm_record_headers_are_checked_field_by_field() {
        let h = encode_shm_record(7, 2, 3, 1000);
        assert_eq!(check_shm_record(&h, 7, 2, 3, 1000), Ok(()));
        assert!(check_shm_record(&h, 8, 2, 3, 1000)
            .unwrap_err()
            .contains("frame 7"));
        assert!(check_shm_record(&h, 7, 1, 3, 1000).is_err());
        assert!(check_shm_record(&h, 7, 2, 4, 1000).is_err());
        assert!(check_shm_record(&h, 7, 2, 3, 999).is_err());
        let mut bad = h;
        bad[0] = b'X';
        assert!(check_shm_record(&bad, 7, 2, 3, 1000)
            .unwrap_err()
            .contains("magic"));
    }

    proptest! {
        /// Arbitrary bytes never panic the decoders.
        #[test]
        fn garbage_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..200)) {
            let _ = decode_meta::<CoordMsg>(&bytes);
            let _ = decode_meta::<WorkerMsg>(&bytes);
            let _ = decode_meta::<PeerMsg>(&bytes);
            if bytes.len() >= HEADER_LEN {
                let h: [u8; HEADER_LEN] = bytes[..HEADER_LEN].try_into().unwrap();
                let _ = decode_header(&h, &Limits::HANDSHAKE);
            }
        }

        /// Sealed headers (magic and CRC right) with arbitrary version, reserved bytes and
        /// lengths reach every check past the first two: a header passes exactly when it
        /// holds this protocol's version, zero reserved bytes and lengths within the limits,
        /// and is refused by the first check it fails, with that check's error.
        #[test]
        fn sealed_headers_are_checked_past_the_crc(
            version in prop_oneof![Just(PROTOCOL_VERSION), any::<u16>()],
            reserved in prop_oneof![Just([0u8; 2]), any::<[u8; 2]>()],
            meta in prop_oneof![0u32..64, any::<u32>()],
            bulk in prop_oneof![0u64..64, any::<u64>()],
        ) {
            let mut h = [0u8; HEADER_LEN];
            h[0..4].copy_from_slice(&MAGIC);
            h[4..6].copy_from_slice(&version.to_le_bytes());
            h[6..8].copy_from_slice(&reserved);
            h[8..12].copy_from_slice(&meta.to_le_bytes());
            h[12..20].copy_from_slice(&bulk.to_le_bytes());
            let crc = crc32c::crc32c(&h[0..20]);
            h[20..24].copy_from_slice(&crc.to_le_bytes());
            let limits = Limits { max_meta: 32, max_bulk: 32 };
            let r = decode_header(&h, &limits);
            if version != PROTOCOL_VERSION {
                prop_assert!(matches!(r, Err(WireError::Version { got }) if got == version), "{:?}", r);
            } else if reserved != [0, 0] {
                prop_assert!(matches!(r, Err(WireError::Reserved(v)) if v == u16::from_le_bytes(reserved)), "{:?}", r);
            } else if meta > 32 {
                prop_assert!(matches!(r, Err(WireError::MetaTooLarge { len, limit: 32 }) if len == meta), "{:?}", r);
            } else if bulk > 32 {
                prop_assert!(matches!(r, Err(WireError::BulkTooLarge { len, limit: 32 }) if len == bulk), "{:?}", r);
            } else {
                let f = r.unwrap();
                prop_assert_eq!((f.meta_len, f.bulk_len), (meta, bulk));
            }
        }
    }
}
