//! Writing final spans straight into the physical frame (a "canvas"), so that the gather
//! needs no assembly afterwards: each rank puts its span of logical pixels at its
//! physical rows (through the interlace map), and whoever owns the frame only checks that
//! the spans are disjoint and clears what none covered.
//!
//! [`super::assemble`] builds the same frame from encoded pieces; the tests hold the two
//! to the same pixels.

use super::{CompositeError, Interlace, Span, SparsePiece};
use crate::image::Rgba;

/// Calls `f(physical index, offset, len)` for the logical pixels `at .. at + n` as they
/// lie in the physical frame: one run per row touched (one run in all without
/// interlacing). `offset` counts from `at`.
pub(super) fn physical_runs(
    interlace: &Interlace,
    at: usize,
    n: usize,
    mut f: impl FnMut(usize, usize, usize),
) {
    if n == 0 {
        return;
    }
    if interlace.is_identity() {
        f(at, 0, n);
        return;
    }
    let w = interlace.width as usize;
    let (mut i, mut off) = (at, 0);
    while off < n {
        let l = i / w;
        let x = i - l * w;
        let take = (n - off).min(w - x);
        f(interlace.physical_row(l as u32) as usize * w + x, off, take);
        off += take;
        i += take;
    }
}

/// Checks that `frame` is the interlace map's frame and `span` lies inside it.
fn check(frame: &[Rgba], interlace: &Interlace, span: Span) -> Result<(), CompositeError> {
    let n = interlace.pixels();
    if frame.len() as u64 != n {
        return Err(CompositeError::FrameLength {
            len: frame.len(),
            pixels: n,
        });
    }
    if span.end as u64 > n || span.start > span.end {
        return Err(CompositeError::OutOfBounds { span, pixels: n });
    }
    Ok(())
}

/// Writes one final span's pixels (`pixels`, logical order, exactly `span.len()` of them)
/// to their physical places in `frame` (row-major, `interlace.width · interlace.height`).
pub fn write_span(
    frame: &mut [Rgba],
    interlace: &Interlace,
    span: Span,
    pixels: &[Rgba],
) -> Result<(), CompositeError> {
    check(frame, interlace, span)?;
    if pixels.len() != span.len() as usize {
        return Err(CompositeError::SpanPixels {
            span,
            pixels: pixels.len(),
        });
    }
    physical_runs(
        interlace,
        span.start as usize,
        pixels.len(),
        |dst, off, len| {
            frame[dst..dst + len].copy_from_slice(&pixels[off..off + len]);
        },
    );
    Ok(())
}

/// Writes a received (checked or not) piece to its physical places in `frame`: its active
/// runs decoded, the rest of its span transparent.
pub fn write_piece(
    frame: &mut [Rgba],
    interlace: &Interlace,
    piece: &SparsePiece,
) -> Result<(), CompositeError> {
    check(frame, interlace, piece.span)?;
    piece.check()?;
    let start = piece.span.start as usize;
    let mut done = 0usize;
    piece.for_each_active(|off, px| {
        clear(frame, interlace, start + done, off - done);
        physical_runs(interlace, start + off, px.len(), |dst, o, len| {
            frame[dst..dst + len].copy_from_slice(&px[o..o + len]);
        });
        done = off + px.len();
    });
    clear(
        frame,
        interlace,
        start + done,
        piece.span.len() as usize - done,
    );
    Ok(())
}

/// Makes the logical pixels `at .. at + n` transparent.
fn clear(frame: &mut [Rgba], interlace: &Interlace, at: usize, n: usize) {
    physical_runs(interlace, at, n, |dst, _, len| {
        frame[dst..dst + len].fill([0.0; 4]);
    });
}

/// Finishes a frame whose pieces were written in place, covering `spans` (in any order;
/// empty ones ignored): fails if two overlap or one reaches past the frame, and makes
/// every pixel no span covers transparent.
pub fn finish(
    frame: &mut [Rgba],
    interlace: &Interlace,
    spans: &[Span],
) -> Result<(), CompositeError> {
    let mut spans: Vec<Span> = spans.iter().copied().filter(|s| !s.is_empty()).collect();
    for &s in &spans {
        check(frame, interlace, s)?;
    }
    spans.sort_by_key(|s| s.start);
    for w in spans.windows(2) {
        if w[1].start < w[0].end {
            return Err(CompositeError::Overlap { a: w[0], b: w[1] });
        }
    }
    let mut at = 0usize;
    for s in spans {
        clear(frame, interlace, at, s.start as usize - at);
        at = s.end as usize;
    }
    clear(frame, interlace, at, frame.len() - at);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::super::{assemble, WireFormat};
    use super::*;
    use proptest::prelude::*;

    fn pixel(i: usize, seed: u32) -> Rgba {
        // Every third pixel transparent, so pieces have runs.
        if (i as u32 + seed).is_multiple_of(3) {
            [0.0; 4]
        } else {
            let v = (i as f32 + 1.0) * 0.001 + seed as f32;
            [v, v + 0.25, v + 0.5, 1.0]
        }
    }

    /// Splits `n` logical pixels into `k` spans at the given cut fractions.
    fn spans(n: u32, cuts: &[f64]) -> Vec<Span> {
        let mut at: Vec<u32> = cuts.iter().map(|c| (c * n as f64) as u32).collect();
        at.push(0);
        at.push(n);
        at.sort_unstable();
        at.windows(2)
            .map(|w| Span {
                start: w[0],
                end: w[1],
            })
            .collect()
    }

    proptest! {
        /// Spans written in place (raw or as received pieces, in any order, over a
        /// frame full of garbage) give exactly the frame `assemble` builds from the
        /// same pieces, and the frame placed pixel by pixel, with and without interlacing,
        /// and with a span left out.
        #[test]
        fn in_place_equals_assembly(
            w in 1u32..40,
            h in 1u32..30,
            groups in 1u32..6,
            interlaced in any::<bool>(),
            cuts in proptest::collection::vec(0.0f64..1.0, 0..5),
            drop_one in any::<bool>(),
            seed in 0u32..3,
        ) {
            let il = Interlace::new(w, h, groups, interlaced);
            let n = w * h;
            let mut all = spans(n, &cuts);
            if drop_one && all.len() > 1 {
                all.remove(all.len() / 2);
            }
            let logical: Vec<Rgba> = (0..n as usize).map(|i| pixel(i, seed)).collect();
            let pieces: Vec<SparsePiece> = all
                .iter()
                .map(|s| {
                    SparsePiece::encode(
                        &logical[s.start as usize..s.end as usize],
                        *s,
                        WireFormat::F32,
                    )
                })
                .collect();
            let want = assemble(w, h, &il, &pieces).unwrap();
            // Pixel by pixel, the plain way.
            let mut plain = vec![[0.0f32; 4]; n as usize];
            for s in &all {
                for i in s.start..s.end {
                    let (l, x) = (i / w, i % w);
                    plain[(il.physical_row(l) * w + x) as usize] = logical[i as usize];
                }
            }
            prop_assert_eq!(&want, &plain);
            let mut raw = vec![[7.0f32; 4]; n as usize];
            let mut decoded = vec![[-3.0f32; 4]; n as usize];
            for (s, p) in all.iter().zip(&pieces).rev() {
                write_span(&mut raw, &il, *s, &logical[s.start as usize..s.end as usize]).unwrap();
                write_piece(&mut decoded, &il, p).unwrap();
            }
            finish(&mut raw, &il, &all).unwrap();
            finish(&mut decoded, &il, &all).unwrap();
            prop_assert_eq!(&raw, &want);
            prop_assert_eq!(&decoded, &want);
        }
    }

    #[test]
    fn bad_spans_frames_and_overlaps_are_refused() {
        let il = Interlace::new(4, 3, 2, true);
        let mut frame = vec![[0.0f32; 4]; 12];
        let s = |start, end| Span { start, end };
        assert!(matches!(
            write_span(&mut frame, &il, s(10, 13), &[[0.0; 4]; 3]),
            Err(CompositeError::OutOfBounds { .. })
        ));
        assert!(matches!(
            write_span(&mut frame, &il, s(2, 5), &[[0.0; 4]; 2]),
            Err(CompositeError::SpanPixels { .. })
        ));
        assert!(matches!(
            write_span(&mut frame[..11], &il, s(0, 1), &[[0.0; 4]]),
            Err(CompositeError::FrameLength { .. })
        ));
        assert!(matches!(
            finish(&mut frame, &il, &[s(0, 5), s(4, 8)]),
            Err(CompositeError::Overlap { .. })
        ));
        assert!(matches!(
            finish(&mut frame, &il, &[s(0, 13)]),
            Err(CompositeError::OutOfBounds { .. })
        ));
        finish(&mut frame, &il, &[s(0, 5), s(5, 12), s(3, 3)]).unwrap();
    }
}
