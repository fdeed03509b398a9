//! One worker's side of the compositing exchange across frames, as a sans-IO state
//! machine in the manner of quinn-proto.
//!
//! [`RankCompositor`] knows one frame's plan. This adds what lives between the network
//! and the plan: which frame is running, which rank stands at which position in it,
//! pieces that arrive early (a peer may already be in the next round, or the next frame),
//! duplicates and stale pieces, bounds on what may be buffered, and the frame deadline.
//! The driver (`strata_worker::node`) only moves bytes and time:
//!
//! * inputs: [`start_frame`](Exchange::start_frame), [`handle_piece`](Exchange::handle_piece)
//!   (a parsed piece and the rank whose connection it came on),
//!   [`handle_timeout`](Exchange::handle_timeout) (the current time),
//!   [`handle_lost`](Exchange::handle_lost) (a peer's connection ended);
//! * outputs: [`poll_send`](Exchange::poll_send) (pieces to send, by rank),
//!   [`poll_event`](Exchange::poll_event) (the frame's result, or why it failed),
//!   [`poll_timeout`](Exchange::poll_timeout) (when to call `handle_timeout`).
//!
//! **Zero-copy sends.** A driver may give the exchange a [`PieceSink`]: each outgoing
//! piece is then offered to it unencoded, and a sink that writes it straight where the
//! peer reads it (the peer's shared-memory segment, `strata_net::shm`) returns where it
//! lies; [`poll_send`](Exchange::poll_send) then hands out an announcement
//! ([`OutgoingPiece::Placed`]) instead of an encoded piece. The final span is handed out
//! unencoded ([`FinalPiece`]), so the driver encodes it once, where it goes.
//!
//! Time is an argument, never read for decisions, so the tests drive many ranks through a
//! simulated network in virtual time (latency, reordering, duplication, a silent rank, a
//! rank lying about its position, pieces of later frames).
//!
//! **Sender checks.** A piece claims a frame, round and sender position; it must come on
//! the connection of the rank at that position in that frame's visibility order. Pieces
//! of the current frame are checked on arrival; pieces of a later frame are buffered and
//! checked when that frame starts (its order is known only then), before any is used.
//! **Bounds.** Pieces may run at most [`ExchangeLimits::frames_ahead`] frames ahead, and
//! the buffer holds at most [`ExchangeLimits::pending_pieces`] pieces and
//! [`ExchangeLimits::pending_bytes`] bytes; a peer past them fails the frame, naming it.
//! **Duplicates** of a piece already received, and pieces of frames that are over, are
//! dropped and counted.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use super::{
    CompositeError, Interlace, PieceLayout, RankCompositor, Segment, Span, SparsePiece, WireFormat,
};
use crate::image::Rgba;
use crate::wire::ShmRef;

/// Where a driver puts outgoing pieces without an intermediate buffer.
pub trait PieceSink: Send {
    /// A frame starts. After a frame that completed, its pieces have all been used by
    /// their receivers (a frame completes only once every rank has blended all its
    /// pieces); after one that failed, a receiver may still be reading one, and the frame's
    /// output is thrown away.
    fn start_frame(&mut self, frame: u64);

    /// Encodes the piece of the pixels `segments` stand for (covering `span`, run lengths
    /// `layout`, in `format`) for rank `to_rank` straight where that rank reads it and
    /// returns where it lies, or `None` to have it encoded into an owned [`SparsePiece`]
    /// (a peer without a segment, a full segment).
    #[allow(clippy::too_many_arguments)]
    fn place(
        &mut self,
        to_rank: u32,
        frame: u64,
        round: u32,
        from: u32,
        segments: &[Segment<'_>],
        layout: &PieceLayout,
        span: Span,
        format: WireFormat,
    ) -> Option<ShmRef>;

    /// Rank `rank` is gone for the rest of this set-up (its connection ended, or the
    /// coordinator gave it up): whatever is kept for it (a segment's memory) may go.
    fn forget_peer(&mut self, _rank: u32) {}
}

/// Where this rank's final span lands when the frame's image is shared (the coordinator's
/// canvas, mapped by a worker on its host): the exchange blends the last round straight
/// there ([`RankCompositor::finish_last_round_into`], through the interlace map) and the
/// gather copies nothing. `Any`, so the driver can take its own target back
/// ([`Exchange::take_final_target`]).
pub trait FinalTarget: std::any::Any + Send {
    /// The writable physical frame (row-major) and the frame's interlace map; `None`
    /// keeps the result in the rank's buffer.
    fn frame(&mut self) -> Option<(&mut [Rgba], Interlace)>;
}

/// An outgoing piece: encoded, or already written by the [`PieceSink`].
#[derive(Clone, Debug, PartialEq)]
pub enum OutgoingPiece {
    /// Encoded, for the driver to send.
    Encoded(SparsePiece),
    /// Written by the sink at this place; the driver announces it.
    Placed(ShmRef),
}

/// This rank's final span, composited and not yet encoded.
#[derive(Clone, Debug, PartialEq)]
pub struct FinalPiece {
    /// The span (empty if this rank keeps nothing).
    pub span: Span,
    /// The frame's wire format.
    pub format: WireFormat,
    /// The span's pixels, logical order; empty when `placed`.
    pub pixels: Vec<Rgba>,
    /// The last round was blended into the [`FinalTarget`]: the pixels are there.
    pub placed: bool,
}

impl FinalPiece {
    /// The piece encoded into an owned buffer.
    pub fn encode(&self) -> SparsePiece {
        SparsePiece::encode(&self.pixels, self.span, self.format)
    }
}

/// What a peer may make this rank buffer.
#[derive(Copy, Clone, Debug, PartialEq, Eq)]
pub struct ExchangeLimits {
    /// How many frames past the current (or last) one a piece may belong to.
    pub frames_ahead: u64,
    /// Pieces buffered for later rounds and frames.
    pub pending_pieces: usize,
    /// Bytes (as received) buffered for later rounds and frames.
    pub pending_bytes: u64,
}

impl ExchangeLimits {
    /// Room for two frames of pieces from every peer, each at most `max_piece_bytes`.
    pub fn for_ranks(ranks: usize, max_piece_bytes: u64) -> ExchangeLimits {
        ExchangeLimits {
            frames_ahead: 2,
            pending_pieces: 64 * ranks.max(1) + 64,
            pending_bytes: 2 * max_piece_bytes.saturating_mul(ranks.max(1) as u64),
        }
    }
}

/// A piece to send.
#[derive(Clone, Debug, PartialEq)]
pub struct Outgoing {
    /// The receiving rank (not position).
    pub to_rank: u32,
    /// Frame number.
    pub frame: u64,
    /// Round of the plan.
    pub round: u32,
    /// This rank's position in the frame's visibility order.
    pub from: u32,
    /// The piece, or where the sink put it.
    pub piece: OutgoingPiece,
}

/// What the exchange reports.
#[derive(Clone, Debug, PartialEq)]
pub enum ExchangeEvent {
    /// The frame's rounds are done: this rank's final piece for the gather.
    Done {
        /// Frame number.
        frame: u64,
        /// The final span's pixels (empty span if this rank keeps nothing).
        result: FinalPiece,
    },
    /// The frame cannot complete.
    Failed {
        /// Frame number.
        frame: u64,
        /// Why.
        error: ExchangeError,
    },
}

/// Why a frame failed. Peers are named by rank; the driver maps ranks to names.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ExchangeError {
    /// A piece came on one rank's connection claiming another's position.
    #[error("rank {rank} sent a piece as position {claimed} of frame {frame}, which is not its position")]
    WrongPosition {
        /// The sender.
        rank: u32,
        /// The position it claimed.
        claimed: u32,
        /// The frame.
        frame: u64,
    },
    /// A piece for a frame too far ahead.
    #[error("rank {rank} sent a piece for frame {frame}, more than {ahead} frames after frame {current}")]
    TooFarAhead {
        /// The sender.
        rank: u32,
        /// The piece's frame.
        frame: u64,
        /// The current (or last) frame.
        current: u64,
        /// The limit.
        ahead: u64,
    },
    /// The early-piece buffer is full.
    #[error("rank {rank} sent more early pieces than this rank buffers ({pieces} pieces, {bytes} bytes)")]
    PendingFull {
        /// The sender of the piece that did not fit.
        rank: u32,
        /// Pieces buffered.
        pieces: usize,
        /// Bytes buffered.
        bytes: u64,
    },
    /// A piece that does not fit the plan (unexpected sender, wrong span, inconsistent).
    #[error("a piece from rank {rank}: {source}")]
    BadPiece {
        /// The sender.
        rank: u32,
        /// What is wrong.
        source: CompositeError,
    },
    /// The deadline passed with pieces missing.
    #[error("no piece from ranks {missing:?} (round {round} of frame {frame}) within the frame timeout of {secs:.1} s")]
    Timeout {
        /// The frame.
        frame: u64,
        /// The round waited on.
        round: u32,
        /// Ranks whose piece is missing.
        missing: Vec<u32>,
        /// The timeout.
        secs: f64,
    },
    /// A peer's connection ended.
    #[error("lost the connection to rank {rank}: {error}")]
    PeerLost {
        /// The peer.
        rank: u32,
        /// Why.
        error: String,
    },
    /// The frame request itself does not fit this run.
    #[error("{0}")]
    BadFrame(String),
    /// Compositing failed locally (a bug or a corrupted piece found while blending).
    #[error("{0}")]
    Composite(CompositeError),
}

impl ExchangeError {
    /// The peer the error is about, if any.
    pub fn rank(&self) -> Option<u32> {
        match self {
            ExchangeError::WrongPosition { rank, .. }
            | ExchangeError::TooFarAhead { rank, .. }
            | ExchangeError::PendingFull { rank, .. }
            | ExchangeError::BadPiece { rank, .. }
            | ExchangeError::PeerLost { rank, .. } => Some(*rank),
            ExchangeError::Timeout { missing, .. } => missing.first().copied(),
            _ => None,
        }
    }
}

/// Counters and times of the frame in progress (reset by `start_frame`).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExchangeStats {
    /// Rounds completed.
    pub rounds: u32,
    /// Seconds encoding outgoing pieces (measured, never used for decisions).
    pub encode_s: f64,
    /// Seconds blending received pieces.
    pub blend_s: f64,
    /// Bytes of the pieces used (as received).
    pub bytes_received: u64,
    /// Duplicates dropped.
    pub duplicates: u64,
    /// Pieces of frames that were over, dropped.
    pub stale: u64,
}

struct Pending {
    rank: u32,
    piece: SparsePiece,
    /// Bytes on the wire.
    len: u64,
    /// Bytes it holds here (more than on the wire when it came LZ4-compressed), what
    /// [`ExchangeLimits::pending_bytes`] bounds.
    held: u64,
}

struct Active {
    frame: u64,
    order: Vec<u32>,
    rc: RankCompositor,
    format: WireFormat,
    deadline: Instant,
    timeout: Duration,
    /// How much later each round's deadline lies than the one before ([`round_stagger`]).
    stagger: Duration,
    /// Whether this round's pieces have been handed to `poll_send`.
    sent: bool,
}

impl Active {
    /// The deadline of the round this rank is in: round `r`'s lies `r` staggers after the
    /// frame's.
    fn round_deadline(&self) -> Instant {
        let r = self.rc.round().unwrap_or(0) as u32;
        self.deadline + self.stagger * r
    }
}

/// How much later each round of a frame times out than the round before it. In a plan of
/// several rounds a rank waiting in round `r` on a hung peer's partner (stuck in an
/// earlier round) would otherwise time out with the rank waiting on the hung peer itself,
/// and the coordinator, believing whichever report comes first, could give up a healthy
/// worker. Staggered, the ranks waiting on the hung peer report first. The stagger spreads
/// half of the margin by which the coordinator's frame timeout exceeds the workers' over
/// the rounds (the workers' is `cluster.frame_timeout_s` less a fifth of it, at most 10 s:
/// a quarter of theirs, at most 10 s), so the last round still fails before the
/// coordinator gives up on the frame. Zero for one round.
pub fn round_stagger(timeout: Duration, rounds: usize) -> Duration {
    if rounds < 2 {
        return Duration::ZERO;
    }
    timeout_margin(timeout) / (2 * rounds as u32)
}

/// By how much the coordinator's frame timeout exceeds a worker's `timeout` (the workers'
/// is `cluster.frame_timeout_s` less a fifth of it, at most 10 s: a quarter of theirs, at
/// most 10 s). What a worker may add to its own deadlines (the rounds' stagger, a late
/// worker's grace) must stay within it.
pub fn timeout_margin(timeout: Duration) -> Duration {
    (timeout / 4).min(Duration::from_secs(10))
}

/// One rank's exchange state across frames.
pub struct Exchange {
    rank: u32,
    ranks: usize,
    limits: ExchangeLimits,
    active: Option<Active>,
    /// The latest frame started; pieces of earlier frames are stale.
    last: Option<u64>,
    /// Early pieces by (frame, round, sender position).
    pending: BTreeMap<(u64, u32, u32), Pending>,
    pending_bytes: u64,
    /// A violation seen while no frame ran: the next frame fails with it.
    poisoned: Option<ExchangeError>,
    /// Peers whose connection ended, and why: a frame that includes one fails.
    lost: BTreeMap<u32, String>,
    sends: VecDeque<Outgoing>,
    events: VecDeque<ExchangeEvent>,
    stats: ExchangeStats,
    sink: Option<Box<dyn PieceSink>>,
    final_target: Option<Box<dyn FinalTarget>>,
}

impl Exchange {
    /// The exchange of rank `rank` of `ranks`.
    pub fn new(rank: u32, ranks: usize, limits: ExchangeLimits) -> Exchange {
        Exchange {
            rank,
            ranks,
            limits,
            active: None,
            last: None,
            pending: BTreeMap::new(),
            pending_bytes: 0,
            poisoned: None,
            lost: BTreeMap::new(),
            sends: VecDeque::new(),
            events: VecDeque::new(),
            stats: ExchangeStats::default(),
            sink: None,
            final_target: None,
        }
    }

    /// Blends the last round of the frame in progress, or of the next one started, into
    /// `target` where it offers the place (until taken back).
    pub fn set_final_target(&mut self, target: Box<dyn FinalTarget>) {
        self.final_target = Some(target);
    }

    /// Takes the final target back (the frame that used it is over or abandoned).
    pub fn take_final_target(&mut self) -> Option<Box<dyn FinalTarget>> {
        self.final_target.take()
    }

    /// Offers every later outgoing piece to `sink` before encoding it.
    pub fn set_sink(&mut self, sink: Box<dyn PieceSink>) {
        self.sink = Some(sink);
    }

    /// The frame in progress, if any.
    pub fn current_frame(&self) -> Option<u64> {
        self.active.as_ref().map(|a| a.frame)
    }

    /// Counters of the frame in progress (or the last one).
    pub fn stats(&self) -> &ExchangeStats {
        &self.stats
    }

    /// Pieces buffered for later rounds or frames.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Starts `frame`, whose visibility order (position → rank) is `order`, with this
    /// rank's compositor (`rc`, already holding its image). Fails (as an event) if the
    /// frame does not follow the last one, the order does not fit, or an early piece of
    /// this frame came from the wrong rank.
    pub fn start_frame(
        &mut self,
        frame: u64,
        order: Vec<u32>,
        rc: RankCompositor,
        format: WireFormat,
        now: Instant,
        timeout: Duration,
    ) {
        self.stats = ExchangeStats::default();
        self.sends.clear();
        // The events of a frame the driver gave up on: its result must not come out as
        // this frame's.
        self.events.clear();
        if let Some(sink) = self.sink.as_mut() {
            sink.start_frame(frame);
        }
        if let Some(a) = self.active.take() {
            // The driver abandoned a frame (e.g. its request failed): it is over.
            self.last = Some(a.frame);
        }
        let fail = |this: &mut Self, error| {
            this.events
                .push_back(ExchangeEvent::Failed { frame, error });
        };
        if let Some(e) = self.poisoned.take() {
            return fail(self, e);
        }
        if self.last.is_some_and(|l| frame <= l) {
            let last = self.last.unwrap();
            return fail(
                self,
                ExchangeError::BadFrame(format!("frame {frame} does not follow frame {last}")),
            );
        }
        // The order may name fewer ranks than the run has (after lost workers), each once.
        let mut seen = vec![false; self.ranks];
        let distinct = !order.is_empty()
            && order.iter().all(|&r| {
                (r as usize) < self.ranks && !std::mem::replace(&mut seen[r as usize], true)
            });
        if !distinct {
            return fail(
                self,
                ExchangeError::BadFrame(format!(
                    "the visibility order {order:?} repeats a rank or names one beyond the {} ranks",
                    self.ranks
                )),
            );
        }
        if let Some((&rank, error)) = self.lost.iter().find(|(r, _)| order.contains(r)) {
            let error = error.clone();
            return fail(self, ExchangeError::PeerLost { rank, error });
        }
        if order.len() != rc.plan().ranks {
            return fail(
                self,
                ExchangeError::BadFrame(format!(
                    "the visibility order {order:?} has {} ranks, the compositing plan {}",
                    order.len(),
                    rc.plan().ranks
                )),
            );
        }
        if order.get(rc.position()) != Some(&self.rank) {
            return fail(
                self,
                ExchangeError::BadFrame(format!(
                    "rank {} is not at position {} of the order {order:?}",
                    self.rank,
                    rc.position()
                )),
            );
        }
        self.last = Some(frame);
        // Pieces of earlier frames will never be used.
        let stale: Vec<_> = self
            .pending
            .range(..(frame, 0, 0))
            .map(|(k, _)| *k)
            .collect();
        for k in stale {
            let p = self.pending.remove(&k).unwrap();
            self.pending_bytes -= p.held;
            self.stats.stale += 1;
        }
        // Early pieces of this frame: now their senders can be checked.
        let wrong = self
            .pending
            .range((frame, 0, 0)..=(frame, u32::MAX, u32::MAX))
            .find(|(&(_, _, from), p)| order.get(from as usize) != Some(&p.rank))
            .map(|(&(_, _, from), p)| (p.rank, from));
        if let Some((rank, claimed)) = wrong {
            return fail(
                self,
                ExchangeError::WrongPosition {
                    rank,
                    claimed,
                    frame,
                },
            );
        }
        let stagger = round_stagger(timeout, rc.plan().rounds.len());
        self.active = Some(Active {
            frame,
            order,
            rc,
            format,
            deadline: now + timeout,
            timeout,
            stagger,
            sent: false,
        });
        self.advance();
    }

    /// Starts this exchange at frame `next` (a worker set up during a sequence): earlier
    /// frames count as over, and pieces may run `frames_ahead` frames past `next - 1`.
    pub fn skip_to(&mut self, next: u64) {
        if next > 0 && self.active.is_none() {
            self.last = Some(self.last.map_or(next - 1, |l| l.max(next - 1)));
        }
    }

    /// A parsed piece that came on the connection of rank `sender`, claiming frame,
    /// round and sender position `from`; `len` is what it took on the wire.
    pub fn handle_piece(
        &mut self,
        sender: u32,
        frame: u64,
        round: u32,
        from: u32,
        piece: SparsePiece,
        len: u64,
    ) {
        let current = self.active.as_ref().map(|a| a.frame);
        if Some(frame) == current {
            let a = self.active.as_mut().unwrap();
            if a.order.get(from as usize) != Some(&sender) {
                return self.fail(ExchangeError::WrongPosition {
                    rank: sender,
                    claimed: from,
                    frame,
                });
            }
            let now_round = a.rc.round().map_or(u32::MAX, |r| r as u32);
            if round < now_round {
                // A round already blended: a duplicate.
                self.stats.duplicates += 1;
                return;
            }
            if round == now_round {
                return self.receive(sender, from as usize, piece, len);
            }
            // A later round of this frame: keep it (its sender is checked already).
        } else if self.last.is_some_and(|l| frame <= l) {
            // A frame that is over (or failed).
            self.stats.stale += 1;
            return;
        } else {
            let base = self.last.unwrap_or(0);
            if frame > base + self.limits.frames_ahead {
                return self.fail(ExchangeError::TooFarAhead {
                    rank: sender,
                    frame,
                    current: base,
                    ahead: self.limits.frames_ahead,
                });
            }
        }
        let key = (frame, round, from);
        if self.pending.contains_key(&key) {
            self.stats.duplicates += 1;
            return;
        }
        // What the piece holds in memory, not what it took on the wire: an LZ4 piece
        // decompressed on arrival can be hundreds of times larger.
        let held = len.max(piece.byte_len() as u64);
        if self.pending.len() >= self.limits.pending_pieces
            || self.pending_bytes + held > self.limits.pending_bytes
        {
            return self.fail(ExchangeError::PendingFull {
                rank: sender,
                pieces: self.pending.len(),
                bytes: self.pending_bytes,
            });
        }
        self.pending_bytes += held;
        self.pending.insert(
            key,
            Pending {
                rank: sender,
                piece,
                len,
                held,
            },
        );
    }

    /// The time is `now`: fails the frame if its deadline has passed (the frame's,
    /// staggered by its round: [`round_stagger`]).
    pub fn handle_timeout(&mut self, now: Instant) {
        let Some(a) = &self.active else { return };
        if now < a.round_deadline() {
            return;
        }
        let missing = a.rc.missing().into_iter().map(|q| a.order[q]).collect();
        let error = ExchangeError::Timeout {
            frame: a.frame,
            round: a.rc.round().map_or(0, |r| r as u32),
            missing,
            secs: a.timeout.as_secs_f64(),
        };
        self.fail(error);
    }

    /// The connection to rank `rank` ended: the frame in progress fails if that rank is
    /// in it, and so does any later frame that includes it. Frames without it go on.
    pub fn handle_lost(&mut self, rank: u32, error: String) {
        self.lost.insert(rank, error.clone());
        if let Some(sink) = self.sink.as_mut() {
            sink.forget_peer(rank);
        }
        if self
            .active
            .as_ref()
            .is_some_and(|a| a.order.contains(&rank))
        {
            self.fail(ExchangeError::PeerLost { rank, error });
        }
    }

    /// The next piece to send.
    pub fn poll_send(&mut self) -> Option<Outgoing> {
        self.sends.pop_front()
    }

    /// The next result or failure.
    pub fn poll_event(&mut self) -> Option<ExchangeEvent> {
        self.events.pop_front()
    }

    /// When to call [`handle_timeout`](Self::handle_timeout) next.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.active.as_ref().map(Active::round_deadline)
    }

    /// Fails the frame in progress, or (between frames) the next one.
    fn fail(&mut self, error: ExchangeError) {
        match self.active.take() {
            Some(a) => self.events.push_back(ExchangeEvent::Failed {
                frame: a.frame,
                error,
            }),
            None => {
                if self.poisoned.is_none() {
                    self.poisoned = Some(error);
                }
            }
        }
    }

    /// Hands one piece of the current round to the compositor.
    fn receive(&mut self, sender: u32, from: usize, piece: SparsePiece, len: u64) {
        let a = self.active.as_mut().unwrap();
        match a.rc.receive(from, piece) {
            Ok(()) => {
                self.stats.bytes_received += len;
                self.advance();
            }
            Err(CompositeError::Duplicate { .. }) => self.stats.duplicates += 1,
            Err(source) => self.fail(ExchangeError::BadPiece {
                rank: sender,
                source,
            }),
        }
    }

    /// Moves the frame as far as the pieces at hand allow: sends a round's pieces once,
    /// feeds early pieces of the round, blends when all are in, and reports the result.
    fn advance(&mut self) {
        while let Some(a) = self.active.as_mut() {
            let Some(round) = a.rc.round() else {
                let a = self.active.take().unwrap();
                let placed = a.rc.placed();
                let (span, pixels) = a.rc.into_result();
                self.events.push_back(ExchangeEvent::Done {
                    frame: a.frame,
                    result: FinalPiece {
                        span,
                        format: a.format,
                        pixels,
                        placed,
                    },
                });
                return;
            };
            if !a.sent {
                a.sent = true;
                let t = Instant::now();
                let from = a.rc.position() as u32;
                for (to, span, segments) in a.rc.outgoing_segments() {
                    let to_rank = a.order[to];
                    let layout = PieceLayout::of_segments(&segments);
                    let placed = self.sink.as_mut().and_then(|s| {
                        s.place(
                            to_rank,
                            a.frame,
                            round as u32,
                            from,
                            &segments,
                            &layout,
                            span,
                            a.format,
                        )
                    });
                    let piece = match placed {
                        Some(at) => OutgoingPiece::Placed(at),
                        None => OutgoingPiece::Encoded(SparsePiece::encode_segments(
                            &segments, layout, span, a.format,
                        )),
                    };
                    self.sends.push_back(Outgoing {
                        to_rank,
                        frame: a.frame,
                        round: round as u32,
                        from,
                        piece,
                    });
                }
                self.stats.encode_s += t.elapsed().as_secs_f64();
                // Early pieces of this round (their senders were checked).
                let keys: Vec<_> = self
                    .pending
                    .range((a.frame, round as u32, 0)..=(a.frame, round as u32, u32::MAX))
                    .map(|(k, _)| *k)
                    .collect();
                for k in keys {
                    let p = self.pending.remove(&k).unwrap();
                    self.pending_bytes -= p.held;
                    let a = self.active.as_mut().unwrap();
                    match a.rc.receive(k.2 as usize, p.piece) {
                        Ok(()) => self.stats.bytes_received += p.len,
                        Err(CompositeError::Duplicate { .. }) => self.stats.duplicates += 1,
                        Err(source) => {
                            return self.fail(ExchangeError::BadPiece {
                                rank: p.rank,
                                source,
                            })
                        }
                    }
                }
            }
            let a = self.active.as_mut().unwrap();
            if !a.rc.is_ready() {
                return;
            }
            let t = Instant::now();
            // The last round straight into the final target where it offers the place.
            let last =
                a.rc.round()
                    .is_some_and(|r| r + 1 == a.rc.plan().rounds.len());
            let placed = match self.final_target.as_mut().filter(|_| last) {
                Some(target) => match target.frame() {
                    Some((frame, interlace)) => a.rc.finish_last_round_into(frame, &interlace),
                    None => Ok(false),
                },
                None => Ok(false),
            };
            let finished = match placed {
                Ok(true) => Ok(()),
                Ok(false) => a.rc.finish_round(),
                Err(e) => Err(e),
            };
            if let Err(e) = finished {
                return self.fail(ExchangeError::Composite(e));
            }
            a.sent = false;
            self.stats.blend_s += t.elapsed().as_secs_f64();
            self.stats.rounds += 1;
        }
    }
}
