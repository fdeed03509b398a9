//! The exchange state machine of every rank, driven through a simulated network in
//! virtual time: random latency (so pieces arrive out of order, and pieces of a later
//! round or frame arrive before the receiver gets there), duplicated deliveries, a silent
//! rank, a rank lying about its position, pieces too far ahead, stale pieces. The
//! composited image must equal the in-memory reference bit for bit whenever the frame
//! completes, and every failure must name the guilty rank.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use strata_common::composite::{
    assemble, build_plan, composite_in_memory, Algorithm, Exchange, ExchangeError, ExchangeEvent,
    ExchangeLimits, Interlace, OutgoingPiece, PieceLayout, PieceSink, RankCompositor, Segment,
    Span, SparsePiece, WireFormat,
};
use strata_common::image::{PartialImage, Rect, Rgba};
use strata_common::wire::ShmRef;

const W: u32 = 37;
const H: u32 = 23;
const TIMEOUT: Duration = Duration::from_secs(5);

/// Deterministic randomness without a dependency: a Weyl sequence through the murmur3
/// finalizer.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        strata_common::digest::fmix64(self.0)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// A rank's partial image: a random rectangle of random premultiplied colours, with
/// transparent holes.
fn image(rng: &mut Rng) -> PartialImage {
    let w = 1 + rng.below(W as u64) as u32;
    let h = 1 + rng.below(H as u64) as u32;
    let x = rng.below((W - w + 1) as u64) as u32;
    let y = rng.below((H - h + 1) as u64) as u32;
    let pixels = (0..w * h)
        .map(|_| {
            if rng.below(4) == 0 {
                [0.0; 4]
            } else {
                let a = rng.unit();
                [a * rng.unit(), a * rng.unit(), a * rng.unit(), a]
            }
        })
        .collect();
    PartialImage {
        width: W,
        height: H,
        rect: Rect { x, y, w, h },
        pixels,
    }
}

enum Ev {
    /// Rank starts its next frame.
    Start(u32),
    /// A piece reaches rank `to` on the connection of rank `sender`.
    Piece {
        to: u32,
        sender: u32,
        frame: u64,
        round: u32,
        from: u32,
        piece: SparsePiece,
    },
}

/// How the network and the ranks misbehave.
#[derive(Clone, Copy, Default)]
struct Faults {
    /// Chance that a delivery is duplicated.
    duplicate: f64,
    /// This rank never sends.
    silent: Option<u32>,
    /// This rank claims position 0 in every piece.
    liar: Option<u32>,
    /// Every rank has a [`PieceSink`] that writes pieces into a shared buffer (as the
    /// worker writes them into a peer's shared-memory segment), declining some.
    sink: bool,
}

/// A sink that writes each placed piece into its rank's buffer, as a shared-memory
/// segment would hold it, and declines pieces to every third rank (those go encoded).
struct BufferSink(Arc<Mutex<Vec<u8>>>);

impl PieceSink for BufferSink {
    fn start_frame(&mut self, _frame: u64) {}

    fn place(
        &mut self,
        to_rank: u32,
        _frame: u64,
        _round: u32,
        _from: u32,
        segments: &[Segment<'_>],
        layout: &PieceLayout,
        span: Span,
        format: WireFormat,
    ) -> Option<ShmRef> {
        if to_rank % 3 == 2 {
            return None;
        }
        let mut buf = self.0.lock().unwrap();
        let offset = buf.len();
        let len = layout.byte_len(format);
        buf.resize(offset + len, 0xEE);
        layout.write_segments_into(segments, span, format, &mut buf[offset..]);
        Some(ShmRef {
            offset: offset as u64,
            len: len as u64,
        })
    }
}

struct Outcome {
    /// Per frame, per rank: the result piece or the error.
    results: Vec<Vec<Option<Result<SparsePiece, ExchangeError>>>>,
    /// Per frame, per rank: virtual time of the outcome.
    when: Vec<Vec<Duration>>,
    /// Per frame, per rank: virtual time the rank started the frame.
    started: Vec<Vec<Duration>>,
    references: Vec<Vec<Rgba>>,
    interlaces: Vec<Interlace>,
    duplicates: u64,
    /// Deliveries after which the receiver held early pieces (a later round or frame).
    buffered: u64,
    /// Pieces the sinks placed.
    placed: u64,
}

/// Runs `frames` frames of `p` ranks through the simulated network.
fn simulate(p: usize, algorithm: Algorithm, frames: u64, faults: Faults, seed: u64) -> Outcome {
    let mut rng = Rng(seed);
    let t0 = Instant::now();
    let px = W * H;
    let plan = Arc::new(build_plan(p, px, algorithm, Some(&[2])).unwrap());
    // Per frame: an order and every rank's image, and the in-memory reference.
    let mut orders = Vec::new();
    let mut images = Vec::new();
    let mut references = Vec::new();
    let mut interlaces = Vec::new();
    for f in 0..frames {
        let mut order: Vec<u32> = (0..p as u32).collect();
        for i in (1..p).rev() {
            order.swap(i, rng.below(i as u64 + 1) as usize);
        }
        let by_rank: Vec<PartialImage> = (0..p).map(|_| image(&mut rng)).collect();
        let by_position: Vec<PartialImage> =
            order.iter().map(|&r| by_rank[r as usize].clone()).collect();
        let interlace = f % 2 == 1;
        references
            .push(composite_in_memory(&plan, &by_position, interlace, WireFormat::F32).unwrap());
        interlaces.push(Interlace::new(W, H, p as u32, interlace));
        orders.push(order);
        images.push(by_rank);
    }
    let limits = ExchangeLimits::for_ranks(p, strata_common::wire::max_piece_bytes(px as u64));
    let mut ex: Vec<Exchange> = (0..p as u32).map(|r| Exchange::new(r, p, limits)).collect();
    let buffers: Vec<Arc<Mutex<Vec<u8>>>> = (0..p).map(|_| Arc::default()).collect();
    let mut placed = 0u64;
    if faults.sink {
        for (e, b) in ex.iter_mut().zip(&buffers) {
            e.set_sink(Box::new(BufferSink(b.clone())));
        }
    }
    let mut next_frame = vec![0u64; p];
    let mut results = vec![vec![None; p]; frames as usize];
    let mut when = vec![vec![Duration::ZERO; p]; frames as usize];
    let mut started = vec![vec![Duration::ZERO; p]; frames as usize];
    let mut queue: BTreeMap<(Duration, u64), Ev> = BTreeMap::new();
    let mut seq = 0u64;
    let mut now;
    for r in 0..p as u32 {
        let at = Duration::from_micros(rng.below(3000));
        queue.insert((at, seq), Ev::Start(r));
        seq += 1;
    }
    let mut duplicates = 0;
    let mut buffered = 0;
    loop {
        let next = queue.pop_first().map(|((t, _), ev)| (t, ev));
        let touched: Vec<u32> = match next {
            Some((t, Ev::Start(r))) => {
                now = t;
                let f = next_frame[r as usize];
                let order = orders[f as usize].clone();
                let position = order.iter().position(|&x| x == r).unwrap();
                let rc = RankCompositor::new(
                    plan.clone(),
                    position,
                    &images[f as usize][r as usize],
                    &interlaces[f as usize],
                )
                .unwrap();
                started[f as usize][r as usize] = now;
                ex[r as usize].start_frame(f, order, rc, WireFormat::F32, t0 + now, TIMEOUT);
                vec![r]
            }
            Some((
                t,
                Ev::Piece {
                    to,
                    sender,
                    frame,
                    round,
                    from,
                    piece,
                },
            )) => {
                now = t;
                let len = piece.byte_len() as u64;
                ex[to as usize].handle_piece(sender, frame, round, from, piece, len);
                buffered += (ex[to as usize].pending() > 0) as u64;
                vec![to]
            }
            None => {
                // Nothing in flight: time jumps to the earliest deadline.
                let Some(t) = ex.iter().filter_map(|e| e.poll_timeout()).min() else {
                    break;
                };
                now = t - t0;
                for e in &mut ex {
                    e.handle_timeout(t);
                }
                (0..p as u32).collect()
            }
        };
        for r in touched {
            let e = &mut ex[r as usize];
            while let Some(mut out) = e.poll_send() {
                if faults.silent == Some(r) {
                    continue;
                }
                if faults.liar == Some(r) {
                    out.from = 0;
                }
                let copies = if rng.unit() < faults.duplicate as f32 {
                    2
                } else {
                    1
                };
                for _ in 0..copies {
                    let at = now + Duration::from_micros(10 + rng.below(5000));
                    queue.insert(
                        (at, seq),
                        Ev::Piece {
                            to: out.to_rank,
                            sender: r,
                            frame: out.frame,
                            round: out.round,
                            from: out.from,
                            piece: match &out.piece {
                                OutgoingPiece::Encoded(p) => p.clone(),
                                OutgoingPiece::Placed(at) => {
                                    placed += 1;
                                    let buf = buffers[r as usize].lock().unwrap();
                                    let bytes =
                                        &buf[at.offset as usize..(at.offset + at.len) as usize];
                                    SparsePiece::parse(bytes, W * H).unwrap()
                                }
                            },
                        },
                    );
                    seq += 1;
                }
            }
            while let Some(ev) = e.poll_event() {
                let (frame, res) = match ev {
                    ExchangeEvent::Done { frame, result } => (frame, Ok(result.encode())),
                    ExchangeEvent::Failed { frame, error } => (frame, Err(error)),
                };
                results[frame as usize][r as usize] = Some(res);
                when[frame as usize][r as usize] = now;
                next_frame[r as usize] = frame + 1;
                if frame + 1 < frames {
                    // The next frame starts a little later (ranks drift apart). Under
                    // gather the ranks that only send are done at once and would run any
                    // number of frames ahead of position 0; the coordinator's frame
                    // requests (one frame at a time) keep them within one, so here the
                    // next frame starts once every rank has ended this one.
                    let starts: Vec<u32> = if algorithm == Algorithm::Gather {
                        let f = frame as usize;
                        if results[f].iter().all(|x| x.is_some()) {
                            (0..p as u32).collect()
                        } else {
                            Vec::new()
                        }
                    } else {
                        vec![r]
                    };
                    for q in starts {
                        let at = now + Duration::from_micros(rng.below(4000));
                        queue.insert((at, seq), Ev::Start(q));
                        seq += 1;
                    }
                }
            }
        }
    }
    for e in &ex {
        duplicates += e.stats().duplicates;
    }
    Outcome {
        results,
        when,
        started,
        references,
        interlaces,
        duplicates,
        buffered,
        placed,
    }
}

#[test]
fn latency_reordering_and_duplication_leave_every_frame_exact() {
    let mut duplicates = 0;
    let mut buffered = 0;
    let mut placed = 0;
    for p in [1usize, 2, 3, 4, 5, 8] {
        for algorithm in [
            Algorithm::DirectSend,
            Algorithm::BinarySwap,
            Algorithm::RadixK,
            Algorithm::Gather,
        ] {
            for seed in 0..4u64 {
                // Every other seed with sinks (pieces written where the peer reads them).
                let faults = Faults {
                    duplicate: 0.3,
                    sink: seed % 2 == 1,
                    ..Faults::default()
                };
                let o = simulate(p, algorithm, 4, faults, seed * 1000 + p as u64);
                for (f, per_rank) in o.results.iter().enumerate() {
                    let pieces: Vec<SparsePiece> = per_rank
                        .iter()
                        .enumerate()
                        .map(|(r, res)| match res {
                            Some(Ok(piece)) => piece.clone(),
                            other => panic!(
                                "p={p} {algorithm:?} seed {seed}: rank {r} frame {f}: {:?}",
                                other.as_ref().map(|r| r.as_ref().err())
                            ),
                        })
                        .collect();
                    let image = assemble(W, H, &o.interlaces[f], &pieces).unwrap();
                    assert!(
                        image == o.references[f],
                        "p={p} {algorithm:?} seed {seed} frame {f}: differs from the in-memory composite"
                    );
                }
                duplicates += o.duplicates;
                buffered += o.buffered;
                placed += o.placed;
            }
        }
    }
    assert!(duplicates > 0, "the simulation never duplicated a delivery");
    assert!(buffered > 0, "no piece ever arrived early");
    assert!(placed > 0, "no sink ever placed a piece");
}

#[test]
fn a_silent_rank_times_out_the_ranks_waiting_on_it_naming_it() {
    for algorithm in [Algorithm::DirectSend, Algorithm::BinarySwap] {
        let faults = Faults {
            silent: Some(2),
            ..Faults::default()
        };
        let o = simulate(4, algorithm, 1, faults, 7);
        let mut named = Vec::new();
        let rounds = build_plan(4, W * H, algorithm, Some(&[2]))
            .unwrap()
            .rounds
            .len();
        let stagger = strata_common::composite::round_stagger(TIMEOUT, rounds);
        for r in 0..4 {
            match &o.results[0][r] {
                Some(Err(ExchangeError::Timeout { missing, round, .. })) => {
                    // At its round's deadline, not before, not after: the frame's, one
                    // stagger later per round.
                    assert_eq!(
                        o.when[0][r],
                        o.started[0][r] + TIMEOUT + stagger * *round,
                        "rank {r}"
                    );
                    named.push((r, missing.clone()));
                }
                Some(Ok(_)) => assert_eq!(r, 2, "rank {r} completed without rank 2's piece"),
                other => panic!("rank {r}: {other:?}"),
            }
        }
        match algorithm {
            // One round: every other rank waits on rank 2 itself.
            Algorithm::DirectSend => {
                assert_eq!(named.len(), 3);
                assert!(named.iter().all(|(_, m)| m == &vec![2]), "{named:?}");
            }
            // Later rounds wait on partners stuck behind rank 2: each names the rank it
            // waits on, and those waiting in the first round name rank 2. Those report
            // first (the coordinator believes the first report): every rank that times out
            // at the earliest time names rank 2.
            _ => {
                assert!(stagger > Duration::ZERO);
                assert!(named.len() >= 3, "{named:?}");
                let first = named.iter().map(|&(r, _)| o.when[0][r]).min().unwrap();
                let earliest: Vec<_> = named
                    .iter()
                    .filter(|&&(r, _)| o.when[0][r] < first + stagger / 2)
                    .collect();
                assert!(!earliest.is_empty());
                assert!(earliest.iter().all(|(_, m)| m == &vec![2]), "{named:?}");
            }
        }
    }
}

#[test]
fn a_rank_lying_about_its_position_fails_the_frame_naming_it() {
    let faults = Faults {
        liar: Some(1),
        ..Faults::default()
    };
    let o = simulate(3, Algorithm::DirectSend, 2, faults, 11);
    let mut caught = 0;
    for r in 0..3 {
        for f in 0..o.results.len() {
            if let Some(Err(e)) = &o.results[f][r] {
                assert!(
                    matches!(e, ExchangeError::WrongPosition { rank: 1, .. })
                        || matches!(e, ExchangeError::Timeout { .. }),
                    "rank {r} frame {f}: {e}"
                );
                caught += matches!(e, ExchangeError::WrongPosition { .. }) as u32;
            }
        }
    }
    assert!(caught > 0, "nobody noticed the liar");
}

fn piece(span_start: u32, len: u32) -> SparsePiece {
    let px = vec![[0.5f32, 0.25, 0.125, 0.5]; len as usize];
    SparsePiece::encode(
        &px,
        strata_common::composite::Span::new(span_start, span_start + len),
        WireFormat::F32,
    )
}

fn one_rank_frame(ex: &mut Exchange, frame: u64, order: Vec<u32>, now: Instant) {
    let plan = Arc::new(build_plan(2, 4, Algorithm::DirectSend, None).unwrap());
    let position = order.iter().position(|&r| r == 0).unwrap();
    let img = PartialImage::empty(2, 2);
    let rc = RankCompositor::new(plan, position, &img, &Interlace::new(2, 2, 2, false)).unwrap();
    ex.start_frame(frame, order, rc, WireFormat::F32, now, TIMEOUT);
}

#[test]
fn early_pieces_are_checked_when_their_frame_starts_and_bounded() {
    let t = Instant::now();
    let limits = ExchangeLimits {
        frames_ahead: 2,
        pending_pieces: 4,
        pending_bytes: 1 << 20,
    };
    // 1. Rank 1 sends a piece of frame 1 as position 1 before rank 0 starts frame 1; in
    //    frame 1 rank 1 turns out to be at position 0: the piece is refused, naming it.
    let mut ex = Exchange::new(0, 2, limits);
    ex.handle_piece(1, 1, 0, 1, piece(0, 2), 100);
    assert_eq!(ex.pending(), 1);
    one_rank_frame(&mut ex, 1, vec![1, 0], t);
    match ex.poll_event() {
        Some(ExchangeEvent::Failed {
            frame: 1,
            error:
                ExchangeError::WrongPosition {
                    rank: 1,
                    claimed: 1,
                    ..
                },
        }) => {}
        other => panic!("{other:?}"),
    }

    // 2. Too far ahead: refused (the next frame fails, naming the sender).
    let mut ex = Exchange::new(0, 2, limits);
    one_rank_frame(&mut ex, 0, vec![0, 1], t);
    ex.handle_piece(1, 3, 0, 1, piece(0, 2), 100);
    match ex.poll_event() {
        Some(ExchangeEvent::Failed {
            frame: 0,
            error: ExchangeError::TooFarAhead {
                rank: 1, frame: 3, ..
            },
        }) => {}
        other => panic!("{other:?}"),
    }

    // 3. A full buffer: refused, naming the sender.
    let mut ex = Exchange::new(0, 2, limits);
    for round in 0..5 {
        ex.handle_piece(1, 1, round, 1, piece(0, 2), 100);
    }
    one_rank_frame(&mut ex, 1, vec![0, 1], t);
    match ex.poll_event() {
        Some(ExchangeEvent::Failed {
            error: ExchangeError::PendingFull {
                rank: 1, pieces: 4, ..
            },
            ..
        }) => {}
        other => panic!("{other:?}"),
    }

    // 3b. The buffer bounds the bytes a piece holds, not what it took on the wire: an
    //     LZ4 piece of 10 bytes that decompressed to 100 pixels (1.6 KB) does not fit
    //     in 1 KB.
    let mut ex = Exchange::new(
        0,
        2,
        ExchangeLimits {
            pending_bytes: 1000,
            ..limits
        },
    );
    ex.handle_piece(1, 1, 0, 1, piece(0, 100), 10);
    one_rank_frame(&mut ex, 0, vec![0, 1], t);
    match ex.poll_event() {
        Some(ExchangeEvent::Failed {
            error: ExchangeError::PendingFull {
                rank: 1, pieces: 0, ..
            },
            ..
        }) => {}
        other => panic!("{other:?}"),
    }

    // 4. Duplicates and stale pieces are dropped and counted, and the frame completes.
    let mut ex = Exchange::new(0, 2, limits);
    one_rank_frame(&mut ex, 5, vec![0, 1], t);
    // Direct send over 4 pixels: position 0 keeps [0, 2) and receives it from position 1.
    ex.handle_piece(1, 4, 0, 1, piece(0, 2), 100);
    assert_eq!(ex.stats().stale, 1);
    ex.handle_piece(1, 5, 0, 1, piece(0, 2), 100);
    match ex.poll_event() {
        Some(ExchangeEvent::Done { frame: 5, .. }) => {}
        other => panic!("{other:?}"),
    }
    ex.handle_piece(1, 5, 0, 1, piece(0, 2), 100);
    assert_eq!(ex.stats().stale, 2, "a piece of a finished frame is stale");
    assert!(ex.poll_event().is_none());
    // A frame that does not follow the last one is refused.
    one_rank_frame(&mut ex, 5, vec![0, 1], t);
    assert!(matches!(
        ex.poll_event(),
        Some(ExchangeEvent::Failed {
            error: ExchangeError::BadFrame(_),
            ..
        })
    ));
}

#[test]
fn an_exchange_set_up_mid_sequence_takes_pieces_of_its_first_frame_and_drops_older_ones() {
    // A worker set up again before frame 10: a peer already in frame 10 sends early, and
    // a piece of frame 9 (over before this worker joined) is stale, not a failure.
    let t = Instant::now();
    let mut ex = Exchange::new(0, 2, ExchangeLimits::for_ranks(2, 1 << 20));
    ex.skip_to(10);
    ex.handle_piece(1, 10, 0, 1, piece(0, 2), 100);
    ex.handle_piece(1, 9, 0, 1, piece(0, 2), 100);
    assert_eq!(ex.pending(), 1);
    assert_eq!(ex.stats().stale, 1);
    assert!(ex.poll_event().is_none());
    one_rank_frame(&mut ex, 10, vec![0, 1], t);
    match ex.poll_event() {
        Some(ExchangeEvent::Done { frame: 10, .. }) => {}
        other => panic!("{other:?}"),
    }
    // Without it, the same early piece is too far ahead of frame 0.
    let mut ex = Exchange::new(0, 2, ExchangeLimits::for_ranks(2, 1 << 20));
    ex.handle_piece(1, 10, 0, 1, piece(0, 2), 100);
    one_rank_frame(&mut ex, 10, vec![0, 1], t);
    assert!(matches!(
        ex.poll_event(),
        Some(ExchangeEvent::Failed {
            error: ExchangeError::TooFarAhead { .. },
            ..
        })
    ));
}

#[test]
fn a_lost_peer_fails_the_frames_that_include_it_and_only_those() {
    let t = Instant::now();
    let limits = ExchangeLimits::for_ranks(3, 1 << 16);
    let mut ex = Exchange::new(0, 3, limits);
    // Lost between frames: nothing to fail yet.
    ex.handle_lost(1, "connection reset".into());
    assert!(ex.poll_event().is_none());
    // A frame that still includes rank 1 fails at once, naming it.
    one_rank_frame(&mut ex, 0, vec![0, 1], t);
    match ex.poll_event() {
        Some(ExchangeEvent::Failed {
            error: ExchangeError::PeerLost { rank: 1, .. },
            ..
        }) => {}
        other => panic!("{other:?}"),
    }
    // The re-run without it (ranks 0 and 2 of the 3) completes.
    one_rank_frame(&mut ex, 1, vec![0, 2], t);
    ex.handle_piece(2, 1, 0, 1, piece(0, 2), 100);
    match ex.poll_event() {
        Some(ExchangeEvent::Done { frame: 1, .. }) => {}
        other => panic!("{other:?}"),
    }
    // Losing a rank that is not in the frame in progress does not fail it.
    one_rank_frame(&mut ex, 2, vec![2, 0], t);
    ex.handle_lost(1, "again".into());
    assert!(ex.poll_event().is_none());
    assert_eq!(ex.current_frame(), Some(2));
}

/// A lost peer's sink state may go: the sink hears of every loss (the worker's drops that
/// peer's shared-memory segment, which had stayed for the rest of the set-up).
#[test]
fn the_sink_forgets_a_lost_peer() {
    struct Forgetful(Arc<Mutex<Vec<u32>>>);
    impl PieceSink for Forgetful {
        fn start_frame(&mut self, _frame: u64) {}
        fn place(
            &mut self,
            _to_rank: u32,
            _frame: u64,
            _round: u32,
            _from: u32,
            _segments: &[Segment<'_>],
            _layout: &PieceLayout,
            _span: Span,
            _format: WireFormat,
        ) -> Option<ShmRef> {
            None
        }
        fn forget_peer(&mut self, rank: u32) {
            self.0.lock().unwrap().push(rank);
        }
    }
    let forgotten = Arc::new(Mutex::new(Vec::new()));
    let mut ex = Exchange::new(0, 3, ExchangeLimits::for_ranks(3, 1 << 16));
    ex.set_sink(Box::new(Forgetful(forgotten.clone())));
    ex.handle_lost(2, "given up".into());
    ex.handle_lost(1, "connection reset".into());
    assert_eq!(*forgotten.lock().unwrap(), vec![2, 1]);
}

/// An order of fewer ranks than the compositing plan is refused as a bad frame (the
/// exchange had indexed past the order and panicked when it advanced).
#[test]
fn an_order_that_does_not_fit_the_plan_fails_the_frame() {
    let t = Instant::now();
    let limits = ExchangeLimits {
        frames_ahead: 2,
        pending_pieces: 4,
        pending_bytes: 1 << 20,
    };
    let plan = Arc::new(build_plan(3, 12, Algorithm::DirectSend, None).unwrap());
    let img = PartialImage::empty(4, 3);
    let rc = RankCompositor::new(plan, 0, &img, &Interlace::new(4, 3, 3, false)).unwrap();
    let mut ex = Exchange::new(0, 3, limits);
    ex.start_frame(1, vec![0, 1], rc, WireFormat::F32, t, TIMEOUT);
    match ex.poll_event() {
        Some(ExchangeEvent::Failed {
            error: ExchangeError::BadFrame(why),
            ..
        }) => assert!(why.contains("plan"), "{why}"),
        other => panic!("{other:?}"),
    }
}

/// A frame's result left unread (its driver gave up on the frame between the last round's
/// sends and reading its events) is not the next frame's: `start_frame` drops the events
/// of the frame before, which had come out as the next frame's result, and shifted every
/// later frame's by one.
#[test]
fn a_result_left_unread_is_not_the_next_frames() {
    let t = Instant::now();
    let frame = |ex: &mut Exchange, n: u64| {
        let plan = Arc::new(build_plan(1, 4, Algorithm::DirectSend, None).unwrap());
        let img = PartialImage::empty(2, 2);
        let rc = RankCompositor::new(plan, 0, &img, &Interlace::new(2, 2, 1, false)).unwrap();
        ex.start_frame(n, vec![0], rc, WireFormat::F32, t, TIMEOUT);
    };
    let mut ex = Exchange::new(0, 1, ExchangeLimits::for_ranks(1, 1 << 20));
    // One rank: a frame is done as soon as it starts.
    frame(&mut ex, 0);
    frame(&mut ex, 1);
    match ex.poll_event() {
        Some(ExchangeEvent::Done { frame: 1, .. }) => {}
        other => panic!("{other:?}"),
    }
    assert!(ex.poll_event().is_none());
}
