//! One rank's side of a compositing plan, as a sans-IO state machine, and the assembly
//! of the final image from the gathered result pieces.
//!
//! Per round the caller sends [`RankCompositor::outgoing`] pieces to their positions,
//! feeds every piece that arrives to [`RankCompositor::receive`] and, once
//! [`RankCompositor::is_ready`], calls [`RankCompositor::finish_round`]. When
//! [`RankCompositor::round`] is `None` the rank's [`result`](RankCompositor::result)
//! is final.

use std::sync::Arc;

use super::canvas::physical_runs;
use super::{
    Interlace, PieceError, PieceLayout, Plan, PlanError, Segment, Span, SparsePiece, WireFormat,
};
use crate::image::{PartialImage, Rgba};

/// Why compositing could not proceed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CompositeError {
    /// The plan is invalid.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// A piece is malformed or does not fit.
    #[error(transparent)]
    Piece(#[from] PieceError),
    /// A position outside the plan.
    #[error("position {position} is outside the plan's {ranks} ranks")]
    PositionOutOfRange {
        /// The position.
        position: usize,
        /// Ranks in the plan.
        ranks: usize,
    },
    /// An image whose size does not match the plan.
    #[error(
        "position {position}: a {width}×{height} image does not have the plan's {pixels} pixels"
    )]
    ImageSize {
        /// The position.
        position: usize,
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// Pixels in the plan.
        pixels: u32,
    },
    /// A partial image whose rectangle or pixel count is wrong.
    #[error("position {position}: bad partial image: {reason}")]
    BadImage {
        /// The position.
        position: usize,
        /// What is wrong.
        reason: String,
    },
    /// An interlace map for a different image size.
    #[error("interlace map is for {il_width}×{il_height}, the image is {width}×{height}")]
    InterlaceMismatch {
        /// Interlace width.
        il_width: u32,
        /// Interlace height.
        il_height: u32,
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
    },
    /// A frame buffer whose length is not the frame's pixel count.
    #[error("a frame buffer of {len} pixels for a frame of {pixels}")]
    FrameLength {
        /// Pixels in the buffer.
        len: usize,
        /// Pixels in the frame.
        pixels: u64,
    },
    /// A span given the wrong number of pixels.
    #[error("span {span} holds {} pixels, {pixels} given", span.len())]
    SpanPixels {
        /// The span.
        span: Span,
        /// Pixels given.
        pixels: usize,
    },
    /// Wrong number of images for the plan.
    #[error("{got} images for a plan of {ranks} ranks")]
    ImageCount {
        /// Images given.
        got: usize,
        /// Ranks in the plan.
        ranks: usize,
    },
    /// A call that needs a round in progress after the last round.
    #[error("position {position} has finished all rounds")]
    Finished {
        /// The position.
        position: usize,
    },
    /// A piece from a position that is not expected to send this round.
    #[error("position {position} expects no piece from position {from} in round {round}")]
    Unexpected {
        /// The receiving position.
        position: usize,
        /// The sender.
        from: usize,
        /// The round.
        round: usize,
    },
    /// A second piece from the same position in one round.
    #[error("position {position} already has the piece from position {from} in round {round}")]
    Duplicate {
        /// The receiving position.
        position: usize,
        /// The sender.
        from: usize,
        /// The round.
        round: usize,
    },
    /// A piece whose span is not the one the plan says.
    #[error("position {position} expects span {expected} from position {from} in round {round}, got {got}")]
    SpanMismatch {
        /// The receiving position.
        position: usize,
        /// The sender.
        from: usize,
        /// The round.
        round: usize,
        /// The span the plan says.
        expected: Span,
        /// The span received.
        got: Span,
    },
    /// `finish_round` before every expected piece arrived.
    #[error(
        "position {position} cannot finish round {round}: still missing pieces from {missing:?}"
    )]
    NotReady {
        /// The position.
        position: usize,
        /// The round.
        round: usize,
        /// Positions whose pieces are missing.
        missing: Vec<usize>,
    },
    /// A gathered piece reaching past the image.
    #[error("piece span {span} reaches past the image's {pixels} pixels")]
    OutOfBounds {
        /// The piece's span.
        span: Span,
        /// Pixels in the image.
        pixels: u64,
    },
    /// Two gathered pieces overlap.
    #[error("gathered pieces {a} and {b} overlap")]
    Overlap {
        /// One span.
        a: Span,
        /// The other.
        b: Span,
    },
}

/// One rank's compositing state: its current span's pixels (logical order) and the
/// pieces received in the current round.
#[derive(Debug)]
pub struct RankCompositor {
    plan: Arc<Plan>,
    position: usize,
    round: usize,
    span: Span,
    buf: Vec<Rgba>,
    /// Indexed like the current step's blend list; `None` for this rank itself.
    received: Vec<Option<SparsePiece>>,
    /// Until the first round is blended, the image itself when it is not the whole
    /// frame (`from_image`): the first round's pieces are encoded from its rows (rows
    /// outside it are known transparent, never written nor read), and only the span
    /// kept is laid out. `buf` is empty meanwhile.
    source: Option<Box<(PartialImage, Interlace)>>,
    /// The last round was blended into the caller's place, not into `buf`.
    placed: bool,
}

impl RankCompositor {
    /// Validates the plan and loads `image` (the partial image of the rank at
    /// `position`) into a logical-order buffer over `[0, pixels)`: physical row `y`
    /// becomes logical row `interlace.logical_row(y)`.
    pub fn new(
        plan: Arc<Plan>,
        position: usize,
        image: &PartialImage,
        interlace: &Interlace,
    ) -> Result<Self, CompositeError> {
        Self::check(&plan, position, image, interlace)?;
        let buf = logical_buffer(image, interlace);
        Ok(Self::with_buffer(plan, position, buf))
    }

    /// [`new`](Self::new), taking the image: when it covers the whole frame and the
    /// rows are not interlaced (a dense image), its pixels become the buffer as they are,
    /// without a copy.
    pub fn from_image(
        plan: Arc<Plan>,
        position: usize,
        image: PartialImage,
        interlace: &Interlace,
    ) -> Result<Self, CompositeError> {
        Self::check(&plan, position, &image, interlace)?;
        let r = image.rect;
        let whole =
            interlace.is_identity() && (r.x, r.y, r.w, r.h) == (0, 0, image.width, image.height);
        if whole {
            return Ok(Self::with_buffer(plan, position, image.pixels));
        }
        let pixels = image.width * image.height;
        let mut c = Self::with_buffer(plan, position, Vec::new());
        c.span = Span::new(0, pixels);
        c.source = Some(Box::new((image, *interlace)));
        Ok(c)
    }

    fn with_buffer(plan: Arc<Plan>, position: usize, buf: Vec<Rgba>) -> Self {
        let pixels = buf.len() as u32;
        let mut c = RankCompositor {
            plan,
            position,
            round: 0,
            span: Span::new(0, pixels),
            buf,
            received: Vec::new(),
            source: None,
            placed: false,
        };
        c.reset_received();
        c
    }

    fn check(
        plan: &Plan,
        position: usize,
        image: &PartialImage,
        interlace: &Interlace,
    ) -> Result<(), CompositeError> {
        plan.validate()?;
        if position >= plan.ranks {
            return Err(CompositeError::PositionOutOfRange {
                position,
                ranks: plan.ranks,
            });
        }
        let (w, h) = (image.width, image.height);
        if w as u64 * h as u64 != plan.pixels as u64 {
            return Err(CompositeError::ImageSize {
                position,
                width: w,
                height: h,
                pixels: plan.pixels,
            });
        }
        if (interlace.width, interlace.height) != (w, h) {
            return Err(CompositeError::InterlaceMismatch {
                il_width: interlace.width,
                il_height: interlace.height,
                width: w,
                height: h,
            });
        }
        let r = image.rect;
        let bad = |reason: String| CompositeError::BadImage { position, reason };
        if image.pixels.len() != r.area() {
            return Err(bad(format!(
                "{} pixels for a {}×{} rectangle",
                image.pixels.len(),
                r.w,
                r.h
            )));
        }
        if !r.is_empty()
            && (r.x as u64 + r.w as u64 > w as u64 || r.y as u64 + r.h as u64 > h as u64)
        {
            return Err(bad(format!("rectangle {r:?} exceeds the {w}×{h} image")));
        }
        Ok(())
    }

    fn reset_received(&mut self) {
        self.received = match self.round() {
            Some(r) => vec![None; self.plan.rounds[r].steps[self.position].blend.len()],
            None => Vec::new(),
        };
    }

    /// This rank's position in the visibility order.
    pub fn position(&self) -> usize {
        self.position
    }

    /// The plan being run.
    pub fn plan(&self) -> &Arc<Plan> {
        &self.plan
    }

    /// The current round, `None` when all rounds are done.
    pub fn round(&self) -> Option<usize> {
        (self.round < self.plan.rounds.len()).then_some(self.round)
    }

    /// The span whose pixels this rank currently holds.
    pub fn current_span(&self) -> Span {
        self.span
    }

    fn step(&self) -> Option<&super::RankStep> {
        self.round()
            .map(|r| &self.plan.rounds[r].steps[self.position])
    }

    /// The pieces to send this round, as `(to position, piece)`; empty when done.
    pub fn outgoing(&self, format: WireFormat) -> Vec<(usize, SparsePiece)> {
        self.outgoing_segments()
            .into_iter()
            .map(|(to, span, segs)| {
                let layout = PieceLayout::of_segments(&segs);
                (
                    to,
                    SparsePiece::encode_segments(&segs, layout, span, format),
                )
            })
            .collect()
    }

    /// The pieces to send this round before encoding, as `(to position, span, pixels in
    /// segments)`, for a driver that encodes each straight where it goes; empty when done.
    pub fn outgoing_segments(&self) -> Vec<(usize, Span, Vec<Segment<'_>>)> {
        let Some(step) = self.step() else {
            return Vec::new();
        };
        step.sends
            .iter()
            .map(|&(to, span)| {
                let segs = match &self.source {
                    Some(src) => segments_of(&src.0, &src.1, span),
                    None => {
                        let off = (span.start - self.span.start) as usize;
                        vec![Segment::Pixels(&self.buf[off..off + span.len() as usize])]
                    }
                };
                (to, span, segs)
            })
            .collect()
    }

    /// The positions this rank must receive a piece from this round.
    pub fn expected(&self) -> Vec<usize> {
        self.step()
            .map(|s| {
                s.blend
                    .iter()
                    .copied()
                    .filter(|&q| q != self.position)
                    .collect()
            })
            .unwrap_or_default()
    }

    /// Accepts the piece sent by position `from` this round. Fails if `from` is not
    /// expected, already delivered, or the span is not the one the plan says, or the
    /// piece is internally inconsistent. Either wire format is accepted.
    pub fn receive(&mut self, from: usize, piece: SparsePiece) -> Result<(), CompositeError> {
        let position = self.position;
        let Some(round) = self.round() else {
            return Err(CompositeError::Finished { position });
        };
        let step = &self.plan.rounds[round].steps[position];
        let Some(i) = step.blend.iter().position(|&q| q == from && q != position) else {
            return Err(CompositeError::Unexpected {
                position,
                from,
                round,
            });
        };
        if self.received[i].is_some() {
            return Err(CompositeError::Duplicate {
                position,
                from,
                round,
            });
        }
        if piece.span != step.keep {
            return Err(CompositeError::SpanMismatch {
                position,
                from,
                round,
                expected: step.keep,
                got: piece.span,
            });
        }
        piece.check()?;
        self.received[i] = Some(piece);
        Ok(())
    }

    /// The positions whose piece for this round has not arrived yet.
    pub fn missing(&self) -> Vec<usize> {
        match self.step() {
            None => Vec::new(),
            Some(step) => step
                .blend
                .iter()
                .zip(&self.received)
                .filter(|&(&q, r)| q != self.position && r.is_none())
                .map(|(&q, _)| q)
                .collect(),
        }
    }

    /// Whether every expected piece of this round has arrived (false when done).
    pub fn is_ready(&self) -> bool {
        match self.step() {
            None => false,
            Some(step) => step
                .blend
                .iter()
                .zip(&self.received)
                .all(|(&q, r)| q == self.position || r.is_some()),
        }
    }

    /// Blends the received pieces in plan order, shrinks the buffer to the kept span
    /// and moves to the next round. Pieces behind this rank (after it in the blend
    /// list) go under the buffer in order, pieces in front go over it nearest first;
    /// by associativity of OVER this is the ordered composite of the blend list.
    pub fn finish_round(&mut self) -> Result<(), CompositeError> {
        let round = self.ready_round()?;
        let plan = Arc::clone(&self.plan);
        let step = &plan.rounds[round].steps[self.position];
        let keep = step.keep;
        let source = self.source.take();
        if keep.is_empty() {
            self.buf = Vec::new();
        } else {
            // `keep` lies inside the current span (the plan is validated).
            let off = (keep.start - self.span.start) as usize;
            let len = keep.len() as usize;
            if let Some(src) = source {
                self.buf = logical_span(&src.0, &src.1, keep);
            } else if 2 * len <= self.buf.capacity() {
                self.buf = self.buf[off..off + len].to_vec();
            } else {
                self.buf.copy_within(off..off + len, 0);
                self.buf.truncate(len);
            }
            let mut buf = std::mem::take(&mut self.buf);
            self.blend_received(step, |piece, in_front| {
                if in_front {
                    piece.blend_over(&mut buf, keep.start)
                } else {
                    piece.blend_under(&mut buf, keep.start)
                }
            })?;
            self.buf = buf;
        }
        self.next_round(keep);
        Ok(())
    }

    /// Blends the last round straight into `frame`, the physical frame (row-major,
    /// `interlace.pixels()` long) where this rank's result span lands through
    /// `interlace`'s row map, instead of into this rank's buffer: the kept pixels are
    /// copied there once and the received pieces blended in place, so the gather copies
    /// nothing afterwards. Returns `false` (nothing done) unless this is the last round, it
    /// keeps exactly the (non-empty) result span and `frame` is the interlace map's frame;
    /// then [`into_result`](Self::into_result) returns no pixels and
    /// [`placed`](Self::placed) is true. Only the result span's pixels are written.
    pub fn finish_last_round_into(
        &mut self,
        frame: &mut [Rgba],
        interlace: &Interlace,
    ) -> Result<bool, CompositeError> {
        let Some(round) = self.round() else {
            return Err(CompositeError::Finished {
                position: self.position,
            });
        };
        let plan = Arc::clone(&self.plan);
        let step = &plan.rounds[round].steps[self.position];
        let keep = step.keep;
        if round + 1 != plan.rounds.len()
            || keep != self.result_span()
            || keep.is_empty()
            || frame.len() as u64 != interlace.pixels()
            || keep.end as u64 > interlace.pixels()
        {
            return Ok(false);
        }
        self.ready_round()?;
        // The kept pixels, in logical order from `keep.start`, to their physical places
        // (one run per row touched; one run in all without interlacing).
        let mut at = keep.start as usize;
        let mut put = |seg: Segment<'_>| match seg {
            Segment::Zeros(n) => {
                physical_runs(interlace, at, n, |d, _, len| {
                    frame[d..d + len].fill([0.0; 4])
                });
                at += n;
            }
            Segment::Pixels(p) => {
                physical_runs(interlace, at, p.len(), |d, o, len| {
                    frame[d..d + len].copy_from_slice(&p[o..o + len])
                });
                at += p.len();
            }
        };
        match self.source.take() {
            Some(src) => for_each_part(&src.0, &src.1, keep, &mut put),
            None => {
                let off = (keep.start - self.span.start) as usize;
                put(Segment::Pixels(&self.buf[off..off + keep.len() as usize]));
            }
        }
        self.blend_received(step, |piece, in_front| {
            piece.blend_in_frame(frame, interlace, keep, in_front)
        })?;
        self.buf = Vec::new();
        self.placed = true;
        self.next_round(keep);
        Ok(true)
    }

    /// Whether the result was blended into the caller's place
    /// ([`finish_last_round_into`](Self::finish_last_round_into)).
    pub fn placed(&self) -> bool {
        self.placed
    }

    /// The current round, once every expected piece of it has arrived.
    fn ready_round(&self) -> Result<usize, CompositeError> {
        let position = self.position;
        let Some(round) = self.round() else {
            return Err(CompositeError::Finished { position });
        };
        if !self.is_ready() {
            return Err(CompositeError::NotReady {
                position,
                round,
                missing: self.missing(),
            });
        }
        Ok(round)
    }

    /// Blends this round's received pieces into the kept span with `blend(piece,
    /// in_front)`: pieces behind this rank (after it in the blend list) go under in order,
    /// pieces in front go over nearest first; by associativity of OVER this is the ordered
    /// composite of the blend list.
    fn blend_received(
        &mut self,
        step: &super::RankStep,
        mut blend: impl FnMut(&SparsePiece, bool) -> Result<(), PieceError>,
    ) -> Result<(), CompositeError> {
        let me = step
            .blend
            .iter()
            .position(|&q| q == self.position)
            .expect("validated plan: a keeping rank blends itself");
        let received = std::mem::take(&mut self.received);
        for piece in received[..me].iter().rev().flatten() {
            blend(piece, true)?;
        }
        for piece in received[me + 1..].iter().flatten() {
            blend(piece, false)?;
        }
        Ok(())
    }

    /// Moves to the next round, the buffer holding `keep`.
    fn next_round(&mut self, keep: Span) {
        self.span = keep;
        self.round += 1;
        self.reset_received();
    }

    /// The span this rank owns when all rounds are done (possibly empty).
    pub fn result_span(&self) -> Span {
        self.plan.result[self.position]
    }

    /// This rank's final span, encoded for the gather. Meaningful once
    /// [`round`](Self::round) is `None`; before that it holds the partial composite.
    pub fn result(&self, format: WireFormat) -> SparsePiece {
        let r = self.result_span();
        if r.is_empty() || !self.span.contains(&r) {
            return SparsePiece::encode(&[], Span::new(r.start, r.start), format);
        }
        if let Some(src) = &self.source {
            return SparsePiece::encode(&logical_span(&src.0, &src.1, r), r, format);
        }
        let off = (r.start - self.span.start) as usize;
        SparsePiece::encode(&self.buf[off..off + r.len() as usize], r, format)
    }

    /// This rank's final span and its pixels, unencoded (the buffer itself, no copy when
    /// the last round kept exactly the result span). Meaningful once
    /// [`round`](Self::round) is `None`, as [`result`](Self::result).
    pub fn into_result(mut self) -> (Span, Vec<Rgba>) {
        let r = self.result_span();
        if self.placed {
            return (r, Vec::new());
        }
        if r.is_empty() || !self.span.contains(&r) {
            return (Span::new(r.start, r.start), Vec::new());
        }
        if let Some(src) = self.source.take() {
            return (r, logical_span(&src.0, &src.1, r));
        }
        let off = (r.start - self.span.start) as usize;
        if off != 0 || self.buf.len() != r.len() as usize {
            self.buf.copy_within(off..off + r.len() as usize, 0);
            self.buf.truncate(r.len() as usize);
        }
        (r, self.buf)
    }
}

/// The whole frame in logical order (physical row `y` at logical row
/// `interlace.logical_row(y)`), transparent outside the image's rectangle.
fn logical_buffer(image: &PartialImage, interlace: &Interlace) -> Vec<Rgba> {
    logical_span(image, interlace, Span::new(0, image.width * image.height))
}

/// The pixels of logical span `span` of the frame, each written once (no zero-fill first:
/// a fresh frame-sized buffer costs a page fault per 4 KiB, a second pass as much again).
fn logical_span(image: &PartialImage, interlace: &Interlace, span: Span) -> Vec<Rgba> {
    let mut buf: Vec<Rgba> = Vec::with_capacity(span.len() as usize);
    for_each_part(image, interlace, span, |seg| match seg {
        Segment::Zeros(n) => buf.resize(buf.len() + n, [0.0; 4]),
        Segment::Pixels(p) => buf.extend_from_slice(p),
    });
    buf
}

/// The pixels of logical span `span` as segments: the image's row pieces, and the rest as
/// (merged) runs of zeros.
fn segments_of<'a>(image: &'a PartialImage, interlace: &Interlace, span: Span) -> Vec<Segment<'a>> {
    let mut out: Vec<Segment<'a>> = Vec::new();
    for_each_part(image, interlace, span, |seg| match (out.last_mut(), seg) {
        (Some(Segment::Zeros(a)), Segment::Zeros(b)) => *a += b,
        (_, seg) => out.push(seg),
    });
    out
}

/// Calls `f` with the parts of logical span `span` in order: `Zeros` where the image's
/// rectangle does not reach, `Pixels` (slices of the image's rows) where it does.
fn for_each_part<'a>(
    image: &'a PartialImage,
    interlace: &Interlace,
    span: Span,
    mut f: impl FnMut(Segment<'a>),
) {
    if span.is_empty() {
        return;
    }
    let w = image.width as usize;
    let r = image.rect;
    let (a, b) = (span.start as usize, span.end as usize);
    let (x0, x1) = (r.x as usize, r.x as usize + r.w as usize);
    for l in a / w..=(b - 1) / w {
        let row = l * w;
        let (lo, hi) = (a.max(row) - row, b.min(row + w) - row);
        let y = interlace.physical_row(l as u32);
        if r.w == 0 || y < r.y || y >= r.y + r.h {
            f(Segment::Zeros(hi - lo));
            continue;
        }
        let src = &image.pixels[(y - r.y) as usize * r.w as usize..][..r.w as usize];
        let (p0, p1) = (lo.max(x0), hi.min(x1));
        if p0 >= p1 {
            f(Segment::Zeros(hi - lo));
            continue;
        }
        if p0 > lo {
            f(Segment::Zeros(p0 - lo));
        }
        f(Segment::Pixels(&src[p0 - x0..p1 - x0]));
        if hi > p1 {
            f(Segment::Zeros(hi - p1));
        }
    }
}

/// Builds the full physical row-major `width × height` image from gathered pieces
/// (logical spans, mapped back through `interlace`); pixels no piece covers are
/// transparent black. Fails if pieces overlap or reach past the image.
pub fn assemble(
    width: u32,
    height: u32,
    interlace: &Interlace,
    pieces: &[SparsePiece],
) -> Result<Vec<Rgba>, CompositeError> {
    if (interlace.width, interlace.height) != (width, height) {
        return Err(CompositeError::InterlaceMismatch {
            il_width: interlace.width,
            il_height: interlace.height,
            width,
            height,
        });
    }
    let n = width as u64 * height as u64;
    let mut spans: Vec<Span> = Vec::with_capacity(pieces.len());
    for p in pieces {
        if p.span.end as u64 > n || p.span.start > p.span.end {
            return Err(CompositeError::OutOfBounds {
                span: p.span,
                pixels: n,
            });
        }
        p.check()?;
        if !p.span.is_empty() {
            spans.push(p.span);
        }
    }
    spans.sort_by_key(|s| s.start);
    for w in spans.windows(2) {
        if w[1].start < w[0].end {
            return Err(CompositeError::Overlap { a: w[0], b: w[1] });
        }
    }
    // Each pixel of the frame is written once: no zero-fill first (a fresh frame-sized
    // buffer costs a page fault per 4 KiB, a second pass over it as much again).
    let mut out: Vec<Rgba> = Vec::with_capacity(n as usize);
    let mut order: Vec<&SparsePiece> = pieces.iter().filter(|p| !p.span.is_empty()).collect();
    order.sort_by_key(|p| p.span.start);
    if interlace.is_identity() {
        for p in order {
            let base = p.span.start as usize;
            out.resize(base, [0.0; 4]);
            p.for_each_active(|off, px| {
                out.resize(base + off, [0.0; 4]);
                out.extend_from_slice(px);
            });
        }
        out.resize(n as usize, [0.0; 4]);
        return Ok(out);
    }
    // Interlaced: logical row l is physical row `physical_row(l)`; every active run is
    // copied straight to its rows.
    out.resize(n as usize, [0.0; 4]);
    for p in order {
        let start = p.span.start as usize;
        p.for_each_active(|off, px| {
            super::canvas::physical_runs(interlace, start + off, px.len(), |dst, o, len| {
                out[dst..dst + len].copy_from_slice(&px[o..o + len]);
            });
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::super::{build_plan, Algorithm};
    use super::*;
    use crate::image::Rect;

    /// The logical buffer built the plain way: zeros, then each row copied in place.
    fn reference_buffer(image: &PartialImage, il: &Interlace) -> Vec<Rgba> {
        let (w, h) = (image.width, image.height);
        let r = image.rect;
        let mut buf = vec![[0.0f32; 4]; (w * h) as usize];
        if !r.is_empty() {
            for (row, src) in image.pixels.chunks_exact(r.w as usize).enumerate() {
                let l = il.logical_row(r.y + row as u32) as usize;
                let at = l * w as usize + r.x as usize;
                buf[at..at + src.len()].copy_from_slice(src);
            }
        }
        buf
    }

    #[test]
    fn the_buffer_holds_every_row_at_its_logical_place_built_or_taken() {
        let (w, h) = (13u32, 11u32);
        let plan = Arc::new(build_plan(3, w * h, Algorithm::BinarySwap, None).unwrap());
        let rects = [
            Rect { x: 0, y: 0, w, h },
            Rect {
                x: 2,
                y: 3,
                w: 7,
                h: 5,
            },
            Rect {
                x: 0,
                y: 10,
                w: 13,
                h: 1,
            },
            Rect {
                x: 12,
                y: 0,
                w: 1,
                h: 11,
            },
            Rect {
                x: 4,
                y: 4,
                w: 0,
                h: 0,
            },
        ];
        for rect in rects {
            for interlaced in [false, true] {
                let il = Interlace::new(w, h, 3, interlaced);
                let pixels = (0..rect.area())
                    .map(|i| [i as f32 + 1.0, 0.5, -0.0, 1.0])
                    .collect();
                let image = PartialImage {
                    width: w,
                    height: h,
                    rect,
                    pixels,
                };
                let want = reference_buffer(&image, &il);
                let bits = |b: &[Rgba]| b.iter().flatten().map(|v| v.to_bits()).collect::<Vec<_>>();
                // Every sub-span, laid out or as segments, is that part of the frame.
                let n = w * h;
                for (a, b) in [
                    (0, n),
                    (0, 1),
                    (5, 40),
                    (13, 26),
                    (27, 27),
                    (60, n),
                    (n - 1, n),
                ] {
                    let span = Span::new(a, b);
                    let part = &want[a as usize..b as usize];
                    let laid = logical_span(&image, &il, span);
                    assert_eq!(bits(&laid), bits(part), "{rect:?} {interlaced} {span}");
                    let mut flat = Vec::new();
                    for seg in segments_of(&image, &il, span) {
                        match seg {
                            Segment::Zeros(k) => flat.resize(flat.len() + k, [0.0f32; 4]),
                            Segment::Pixels(p) => flat.extend_from_slice(p),
                        }
                    }
                    assert_eq!(bits(&flat), bits(part), "{rect:?} {interlaced} {span}");
                }
                let built = RankCompositor::new(plan.clone(), 1, &image, &il).unwrap();
                assert_eq!(
                    bits(&built.buf),
                    bits(&want),
                    "{rect:?} interlaced {interlaced}"
                );
                // Taken: the whole frame becomes the buffer; anything else stays the
                // image until the first round.
                let whole = !interlaced && rect == Rect { x: 0, y: 0, w, h };
                let taken = RankCompositor::from_image(plan.clone(), 1, image, &il).unwrap();
                assert_eq!(taken.source.is_none(), whole);
                if whole {
                    assert_eq!(bits(&taken.buf), bits(&want));
                }
            }
        }
    }

    fn solid(w: u32, h: u32, c: Rgba) -> PartialImage {
        PartialImage {
            width: w,
            height: h,
            rect: Rect { x: 0, y: 0, w, h },
            pixels: vec![c; (w * h) as usize],
        }
    }

    #[test]
    fn receive_checks_sender_span_and_duplicates() {
        let plan = Arc::new(build_plan(2, 8, Algorithm::BinarySwap, None).unwrap());
        let il = Interlace::new(4, 2, 2, false);
        let img = solid(4, 2, [0.1, 0.1, 0.1, 0.5]);
        let mut a = RankCompositor::new(plan.clone(), 0, &img, &il).unwrap();
        let b = RankCompositor::new(plan.clone(), 1, &img, &il).unwrap();
        assert_eq!(a.expected(), [1]);
        assert!(!a.is_ready());
        let e = a.finish_round().unwrap_err();
        assert!(matches!(e, CompositeError::NotReady { ref missing, .. } if missing == &[1]));

        let mut out_b = b.outgoing(WireFormat::F32);
        assert_eq!(out_b.len(), 1);
        let (to, piece) = out_b.pop().unwrap();
        assert_eq!(to, 0);
        // Self and unknown positions are not expected.
        assert!(matches!(
            a.receive(0, piece.clone()),
            Err(CompositeError::Unexpected { .. })
        ));
        assert!(matches!(
            a.receive(5, piece.clone()),
            Err(CompositeError::Unexpected { .. })
        ));
        // Wrong span.
        let wrong = SparsePiece::encode(&[[0.0; 4]; 4], Span::new(4, 8), WireFormat::F32);
        let e = a.receive(1, wrong).unwrap_err();
        assert!(e.to_string().contains("expects span [0, 4)"), "{e}");
        a.receive(1, piece.clone()).unwrap();
        assert!(matches!(
            a.receive(1, piece),
            Err(CompositeError::Duplicate { .. })
        ));
        assert!(a.is_ready());
        a.finish_round().unwrap();
        assert_eq!(a.round(), None);
        assert!(matches!(
            a.finish_round(),
            Err(CompositeError::Finished { .. })
        ));
        assert!(a.outgoing(WireFormat::F32).is_empty());
        let r = a.result(WireFormat::F32);
        assert_eq!(r.span, Span::new(0, 4));
        let mut px = vec![[0.0; 4]; 4];
        r.decode_into(&mut px, 0).unwrap();
        // 0.5 alpha over 0.5 alpha.
        assert!((px[0][3] - 0.75).abs() < 1e-6 && (px[0][0] - 0.15).abs() < 1e-6);
    }

    #[test]
    fn new_checks_the_image() {
        let plan = Arc::new(build_plan(2, 8, Algorithm::DirectSend, None).unwrap());
        let il = Interlace::new(4, 2, 2, true);
        let e = RankCompositor::new(plan.clone(), 2, &solid(4, 2, [0.0; 4]), &il).unwrap_err();
        assert!(matches!(e, CompositeError::PositionOutOfRange { .. }));
        let e = RankCompositor::new(plan.clone(), 0, &solid(3, 2, [0.0; 4]), &il).unwrap_err();
        assert!(matches!(e, CompositeError::ImageSize { .. }));
        let e = RankCompositor::new(plan.clone(), 0, &solid(2, 4, [0.0; 4]), &il).unwrap_err();
        assert!(matches!(e, CompositeError::InterlaceMismatch { .. }));
        let mut img = solid(4, 2, [0.0; 4]);
        img.rect.x = 1;
        assert!(matches!(
            RankCompositor::new(plan.clone(), 0, &img, &il),
            Err(CompositeError::BadImage { .. })
        ));
        img.rect.x = 0;
        img.pixels.pop();
        assert!(matches!(
            RankCompositor::new(plan.clone(), 0, &img, &il),
            Err(CompositeError::BadImage { .. })
        ));
        let mut bad_plan = (*plan).clone();
        bad_plan.result.pop();
        assert!(matches!(
            RankCompositor::new(Arc::new(bad_plan), 0, &solid(4, 2, [0.0; 4]), &il),
            Err(CompositeError::Plan(_))
        ));
    }

    #[test]
    fn assemble_checks_overlap_and_bounds() {
        let il = Interlace::new(3, 3, 3, true);
        let f = WireFormat::F32;
        let a = SparsePiece::encode(&[[1.0; 4]; 4], Span::new(0, 4), f);
        let b = SparsePiece::encode(&[[0.5; 4]; 3], Span::new(3, 6), f);
        let c = SparsePiece::encode(&[[0.5; 4]; 3], Span::new(7, 10), f);
        assert!(matches!(
            assemble(3, 3, &il, &[a.clone(), b]),
            Err(CompositeError::Overlap { .. })
        ));
        assert!(matches!(
            assemble(3, 3, &il, &[c]),
            Err(CompositeError::OutOfBounds { .. })
        ));
        assert!(matches!(
            assemble(3, 2, &il, &[]),
            Err(CompositeError::InterlaceMismatch { .. })
        ));
        let il = Interlace::new(3, 4, 2, true); // logical rows: 0, 2, 1, 3
        let d = SparsePiece::encode(&[[2.0; 4]; 2], Span::new(5, 7), f);
        let img = assemble(3, 4, &il, &[a, d]).unwrap();
        let lit: Vec<usize> = (0..12).filter(|&i| img[i][0] != 0.0).collect();
        // Logical 0..4: row 0 (physical 0) and x=0 of logical row 1 (physical 2);
        // logical 5..7: x=2 of logical row 1 (physical 2) and x=0 of logical row 2
        // (physical 1).
        assert_eq!(lit, [0, 1, 2, 3, 6, 8]);
        assert_eq!(img[8], [2.0; 4]);
    }
}
