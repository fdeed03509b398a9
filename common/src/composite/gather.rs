//! Gather: one round in which every rank sends its whole image to position 0, which blends
//! all of them front to back and holds the final image; the other positions end with
//! nothing.
//!
//! This is IceT's direct strategy with a single tile (one display rank). Each rank sends
//! one piece instead of `p − 1`, and with sparse images only the active pixels travel and
//! are blended, so at many ranks it beats the strategies that spread the blending when
//! images are sparse. With dense images position 0 blends `p` full images alone, and the
//! spreading strategies win.

use super::{direct_send, Round, Span};

/// Factors (`[p]`, or `[]` for one rank) and the round of a gather; `cur` (every rank's
/// whole image on entry) is updated to the final spans: all of it at position 0.
pub(super) fn rounds(ranks: usize, cur: &mut [Span]) -> (Vec<usize>, Vec<Round>) {
    if ranks < 2 {
        return (Vec::new(), Vec::new());
    }
    let whole = cur[0];
    for (j, s) in cur.iter_mut().enumerate() {
        *s = if j == 0 { whole } else { Span::EMPTY };
    }
    (vec![ranks], direct_send::rounds_to(cur))
}

#[cfg(test)]
mod tests {
    use super::super::{build_plan, composite_in_memory, Algorithm, WireFormat};
    use super::*;
    use crate::image::{PartialImage, Rect};

    #[test]
    fn position_zero_receives_one_piece_from_every_rank() {
        for p in 2..=9usize {
            let plan = build_plan(p, 1000, Algorithm::Gather, None).unwrap();
            plan.validate().unwrap();
            assert_eq!(plan.rounds.len(), 1);
            assert_eq!(plan.factors, [p]);
            let steps = &plan.rounds[0].steps;
            assert_eq!(steps[0].keep, Span::new(0, 1000));
            assert_eq!(steps[0].blend, (0..p).collect::<Vec<_>>());
            assert!(steps[0].sends.is_empty());
            for step in &steps[1..] {
                assert_eq!(step.sends, [(0, Span::new(0, 1000))]);
                assert!(step.keep.is_empty() && step.blend.is_empty());
            }
            let mut want = vec![Span::EMPTY; p];
            want[0] = Span::new(0, 1000);
            assert_eq!(plan.result, want);
        }
        let one = build_plan(1, 100, Algorithm::Gather, None).unwrap();
        one.validate().unwrap();
        assert!(one.rounds.is_empty());
        assert_eq!(one.result, [Span::new(0, 100)]);
    }

    /// Sparse and dense layers, composited by gather and by direct send: the same pixels
    /// to rounding, and the analytic front-to-back result.
    #[test]
    fn gather_composites_as_direct_send_does() {
        let (w, h) = (7u32, 5u32);
        let layers: Vec<PartialImage> = (0..5)
            .map(|j| {
                let pixels = (0..w * h)
                    .map(|i| {
                        // Every other layer has holes (inactive pixels).
                        if j % 2 == 1 && (i + j) % 3 == 0 {
                            [0.0; 4]
                        } else {
                            let a = 0.1 + 0.15 * j as f32;
                            [a * 0.5, a * (i as f32 / 40.0), a * 0.25, a]
                        }
                    })
                    .collect();
                PartialImage {
                    width: w,
                    height: h,
                    rect: Rect { x: 0, y: 0, w, h },
                    pixels,
                }
            })
            .collect();
        for format in [WireFormat::F32, WireFormat::F16] {
            let g = build_plan(5, w * h, Algorithm::Gather, None).unwrap();
            let d = build_plan(5, w * h, Algorithm::DirectSend, None).unwrap();
            let a = composite_in_memory(&g, &layers, false, format).unwrap();
            let b = composite_in_memory(&d, &layers, false, format).unwrap();
            // The same layers in the same order; direct send starts each span's blend at
            // the layer of the position that keeps it (which never crosses the wire),
            // gather at the front one: the sums associate differently (ulps), and f16
            // rounds different layers.
            let tol = if format == WireFormat::F32 {
                1e-6
            } else {
                2e-3
            };
            for (p, q) in a.iter().zip(&b) {
                for c in 0..4 {
                    assert!((p[c] - q[c]).abs() <= tol, "{format:?}: {p:?} vs {q:?}");
                }
            }
        }
        let got = composite_in_memory(
            &build_plan(5, w * h, Algorithm::Gather, None).unwrap(),
            &layers,
            false,
            WireFormat::F32,
        )
        .unwrap();
        for (i, px) in got.iter().enumerate() {
            let mut want = [0.0f32; 4];
            for l in layers.iter().rev() {
                let s = l.pixels[i];
                want = [0, 1, 2, 3].map(|c| s[c] + (1.0 - s[3]) * want[c]);
            }
            for c in 0..4 {
                assert!(
                    (px[c] - want[c]).abs() < 1e-6,
                    "pixel {i}: {px:?} vs {want:?}"
                );
            }
        }
    }
}
