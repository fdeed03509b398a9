//! Runs a whole plan in one process: every rank's [`RankCompositor`], round by round,
//! with every piece passed through its wire bytes ([`SparsePiece::write`] then
//! [`SparsePiece::parse`]), then the gather and [`assemble`]. For tests and tools.

use std::sync::Arc;

use super::{assemble, CompositeError, Interlace, Plan, RankCompositor, SparsePiece, WireFormat};
use crate::image::{PartialImage, Rgba};

/// The outcome of [`run_in_memory`].
#[derive(Clone, Debug, PartialEq)]
pub struct MemoryRun {
    /// The composited full image, physical row-major.
    pub image: Vec<Rgba>,
    /// Per position, the wire bytes it sent in the exchange rounds.
    pub bytes_sent: Vec<u64>,
    /// Per position, the wire bytes of its result piece in the final gather.
    pub gather_bytes: Vec<u64>,
}

/// Composites `images` (indexed by position, front-most first) following `plan` and
/// returns the full physical row-major image. Interlacing, when enabled, uses
/// `plan.ranks` groups.
pub fn composite_in_memory(
    plan: &Plan,
    images: &[PartialImage],
    interlace_enabled: bool,
    format: WireFormat,
) -> Result<Vec<Rgba>, CompositeError> {
    run_in_memory(plan, images, interlace_enabled, format).map(|r| r.image)
}

/// [`composite_in_memory`], also reporting the bytes every position sent.
pub fn run_in_memory(
    plan: &Plan,
    images: &[PartialImage],
    interlace_enabled: bool,
    format: WireFormat,
) -> Result<MemoryRun, CompositeError> {
    if images.len() != plan.ranks || images.is_empty() {
        return Err(CompositeError::ImageCount {
            got: images.len(),
            ranks: plan.ranks,
        });
    }
    let (width, height) = (images[0].width, images[0].height);
    let groups = u32::try_from(plan.ranks).unwrap_or(u32::MAX);
    let interlace = Interlace::new(width, height, groups, interlace_enabled);
    let shared = Arc::new(plan.clone());
    let mut ranks = images
        .iter()
        .enumerate()
        // Taking the images (a sparse one stays the image until the first round, as in a
        // worker); `new` is what the exchange simulation uses.
        .map(|(j, img)| RankCompositor::from_image(Arc::clone(&shared), j, img.clone(), &interlace))
        .collect::<Result<Vec<_>, _>>()?;

    let mut bytes_sent = vec![0u64; plan.ranks];
    let mut bytes = Vec::new();
    for _ in 0..plan.rounds.len() {
        let mut mail = Vec::new();
        for (from, rank) in ranks.iter().enumerate() {
            for (to, piece) in rank.outgoing(format) {
                bytes.clear();
                piece.write(&mut bytes);
                bytes_sent[from] += bytes.len() as u64;
                mail.push((to, from, SparsePiece::parse(&bytes, plan.pixels)?));
            }
        }
        for (to, from, piece) in mail {
            ranks[to].receive(from, piece)?;
        }
        for rank in &mut ranks {
            rank.finish_round()?;
        }
    }

    let mut gather_bytes = vec![0u64; plan.ranks];
    let mut pieces = Vec::with_capacity(plan.ranks);
    for (j, rank) in ranks.iter().enumerate() {
        bytes.clear();
        rank.result(format).write(&mut bytes);
        gather_bytes[j] = bytes.len() as u64;
        pieces.push(SparsePiece::parse(&bytes, plan.pixels)?);
    }
    let image = assemble(width, height, &interlace, &pieces)?;
    Ok(MemoryRun {
        image,
        bytes_sent,
        gather_bytes,
    })
}

#[cfg(test)]
mod tests {
    use super::super::{auto_factors, build_plan, Algorithm, PlanError};
    use super::*;
    use crate::image::{composite_front_to_back, Rect};
    use proptest::prelude::*;

    /// splitmix64: a tiny deterministic generator for image contents.
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }
        fn unit(&mut self) -> f32 {
            (self.next() >> 40) as f32 / (1u64 << 24) as f32
        }
        fn below(&mut self, n: u32) -> u32 {
            (self.next() % n as u64) as u32
        }
        /// A premultiplied colour with alpha in [0, 1] and colour ≤ alpha.
        fn premultiplied(&mut self) -> Rgba {
            let a = self.unit();
            [self.unit() * a, self.unit() * a, self.unit() * a, a]
        }
    }

    /// Image kinds: 0 empty, 1 fully opaque, 2 random premultiplied with holes,
    /// 3 sparse rectangle.
    fn make_image(w: u32, h: u32, kind: u8, seed: u64) -> PartialImage {
        let mut rng = Rng(seed);
        let n = (w * h) as usize;
        match kind {
            0 => PartialImage::empty(w, h),
            1 => {
                let full: Vec<Rgba> = (0..n)
                    .map(|_| [rng.unit(), rng.unit(), rng.unit(), 1.0])
                    .collect();
                PartialImage::from_full(w, h, &full)
            }
            2 => {
                let full: Vec<Rgba> = (0..n)
                    .map(|_| {
                        if rng.below(3) == 0 {
                            [0.0; 4]
                        } else {
                            rng.premultiplied()
                        }
                    })
                    .collect();
                PartialImage::from_full(w, h, &full)
            }
            _ => {
                let x = rng.below(w);
                let y = rng.below(h);
                let rw = 1 + rng.below(w - x);
                let rh = 1 + rng.below(h - y);
                let pixels = (0..rw * rh).map(|_| rng.premultiplied()).collect();
                PartialImage {
                    width: w,
                    height: h,
                    rect: Rect { x, y, w: rw, h: rh },
                    pixels,
                }
            }
        }
    }

    fn max_error(a: &[Rgba], b: &[Rgba]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .flat_map(|(x, y)| (0..4).map(move |c| (x[c] - y[c]).abs()))
            .fold(
                0.0,
                |m: f32, d: f32| if d.is_nan() { f32::INFINITY } else { m.max(d) },
            )
    }

    /// 0 direct send, 1 binary swap, 2 radix-k auto, 3 radix-k target, 4 radix-k with
    /// exact factors (the auto factors in reverse order), 5 gather.
    fn plan_for(ranks: usize, pixels: u32, choice: u8, target: usize) -> Result<Plan, PlanError> {
        match choice {
            0 => build_plan(ranks, pixels, Algorithm::DirectSend, None),
            1 => build_plan(ranks, pixels, Algorithm::BinarySwap, None),
            2 => build_plan(ranks, pixels, Algorithm::RadixK, None),
            3 => build_plan(ranks, pixels, Algorithm::RadixK, Some(&[target])),
            5 => build_plan(ranks, pixels, Algorithm::Gather, None),
            _ => {
                // (A single factor would read as a target; it gives the same plan.)
                let mut f = auto_factors(ranks, target);
                f.reverse();
                build_plan(ranks, pixels, Algorithm::RadixK, Some(&f))
            }
        }
    }

    fn case_strategy() -> impl Strategy<Value = (u32, u32, Vec<(u8, u64)>, Vec<usize>)> {
        (1usize..=16, 1u32..=9, 1u32..=9).prop_flat_map(|(ranks, w, h)| {
            (
                Just(w),
                Just(h),
                prop::collection::vec((0u8..4, any::<u64>()), ranks),
                Just((0..ranks).collect::<Vec<usize>>()).prop_shuffle(),
            )
        })
    }

    /// [`run_in_memory`], but each rank blends its last round straight into its result
    /// span of one shared physical frame, through the interlace map
    /// ([`RankCompositor::finish_last_round_into`]) where it can.
    fn in_place(
        plan: &Plan,
        images: &[PartialImage],
        interlace: bool,
        format: WireFormat,
    ) -> Vec<Rgba> {
        let (w, h) = (images[0].width, images[0].height);
        let il = Interlace::new(w, h, plan.ranks as u32, interlace);
        let shared = Arc::new(plan.clone());
        let mut ranks: Vec<RankCompositor> = images
            .iter()
            .enumerate()
            .map(|(j, img)| {
                RankCompositor::from_image(shared.clone(), j, img.clone(), &il).unwrap()
            })
            .collect();
        let mut frame = vec![[9.0f32; 4]; (w * h) as usize];
        let mut bytes = Vec::new();
        for r in 0..plan.rounds.len() {
            let mut mail = Vec::new();
            for (from, rank) in ranks.iter().enumerate() {
                for (to, piece) in rank.outgoing(format) {
                    bytes.clear();
                    piece.write(&mut bytes);
                    mail.push((to, from, SparsePiece::parse(&bytes, plan.pixels).unwrap()));
                }
            }
            for (to, from, piece) in mail {
                ranks[to].receive(from, piece).unwrap();
            }
            for rank in &mut ranks {
                let last = r + 1 == plan.rounds.len();
                if !(last && rank.finish_last_round_into(&mut frame, &il).unwrap()) {
                    rank.finish_round().unwrap();
                }
            }
        }
        let mut spans = Vec::new();
        for rank in ranks {
            let placed = rank.placed();
            let (span, px) = rank.into_result();
            if placed {
                assert!(px.is_empty());
            } else {
                crate::composite::canvas::write_span(&mut frame, &il, span, &px).unwrap();
            }
            spans.push(span);
        }
        crate::composite::canvas::finish(&mut frame, &il, &spans).unwrap();
        frame
    }

    fn check_case(
        (w, h, kinds, perm): (u32, u32, Vec<(u8, u64)>, Vec<usize>),
        choice: u8,
        target: usize,
        interlace: bool,
        format: WireFormat,
        tolerance: f32,
    ) -> Result<(), TestCaseError> {
        let ranks = kinds.len();
        let images: Vec<PartialImage> = kinds
            .iter()
            .map(|&(k, seed)| make_image(w, h, k, seed))
            .collect();
        // Position i holds image perm[i].
        let by_position: Vec<PartialImage> = perm.iter().map(|&i| images[i].clone()).collect();
        let plan = plan_for(ranks, w * h, choice, target).unwrap();
        plan.validate().unwrap();
        let refs: Vec<&PartialImage> = by_position.iter().collect();
        let want = composite_front_to_back(w, h, &refs);
        let run = run_in_memory(&plan, &by_position, interlace, format).unwrap();
        // The last round blended straight into the frame (the gather into a shared
        // canvas), interlaced or not: the same pixels, bit for bit where the gather is f32
        // (an f16 gather rounds the result; in place it is not).
        let placed = in_place(&plan, &by_position, interlace, format);
        if format == WireFormat::F32 {
            prop_assert!(placed == run.image, "in place differs from the gather");
        }
        prop_assert!(max_error(&placed, &want) <= tolerance);
        let err = max_error(&run.image, &want);
        prop_assert!(
            err <= tolerance,
            "error {} > {} for {:?} factors {:?}, {}×{}, interlace {}",
            err,
            tolerance,
            plan.algorithm,
            plan.factors,
            w,
            h,
            interlace
        );
        Ok(())
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(160))]

        #[test]
        fn f32_matches_serial_over(
            case in case_strategy(),
            choice in 0u8..6,
            target in 2usize..=8,
            interlace in any::<bool>(),
        ) {
            check_case(case, choice, target, interlace, WireFormat::F32, 1e-5)?;
        }

        #[test]
        fn f16_is_close_to_serial_over(
            case in case_strategy(),
            choice in 0u8..6,
            target in 2usize..=8,
            interlace in any::<bool>(),
        ) {
            check_case(case, choice, target, interlace, WireFormat::F16, 2e-3)?;
        }

        #[test]
        fn every_plan_validates(ranks in 1usize..=64, pixels in 0u32..200, choice in 0u8..6, target in 2usize..=8) {
            let plan = plan_for(ranks, pixels, choice, target).unwrap();
            plan.validate().unwrap();
        }
    }

    fn dense(w: u32, h: u32, seed: u64) -> PartialImage {
        let mut rng = Rng(seed);
        let full: Vec<Rgba> = (0..w * h)
            .map(|_| {
                let a = 0.01 + 0.99 * rng.unit();
                [a * rng.unit(), a * rng.unit(), a * rng.unit(), a]
            })
            .collect();
        let img = PartialImage::from_full(w, h, &full);
        assert_eq!(img.rect.area(), (w * h) as usize);
        img
    }

    #[test]
    fn binary_swap_dense_bytes() {
        let (w, h) = (64u32, 64u32);
        let n = (w * h) as u64;
        let p = 4u64;
        let plan = build_plan(4, w * h, Algorithm::BinarySwap, None).unwrap();
        let images: Vec<PartialImage> = (0..4).map(|s| dense(w, h, s)).collect();
        for (format, bpp) in [(WireFormat::F32, 16u64), (WireFormat::F16, 8)] {
            let run = run_in_memory(&plan, &images, true, format).unwrap();
            // Two pieces per rank, each with a 16-byte header and runs [0, n].
            let headers = 2 * (SparsePiece::HEADER_BYTES as u64 + 8);
            for &b in &run.bytes_sent {
                assert_eq!(b, n * bpp * (p - 1) / p + headers);
            }
            for &b in &run.gather_bytes {
                assert_eq!(b, n / p * bpp + SparsePiece::HEADER_BYTES as u64 + 8);
            }
        }
    }

    #[test]
    fn interlacing_balances_a_centred_band() {
        // Content only in rows 24..40 of 64: without interlacing the outer quarters of
        // the logical index space are empty.
        let (w, h) = (32u32, 64u32);
        let band = |seed| {
            let mut img = dense(w, h, seed);
            for y in 0..h {
                if !(24..40).contains(&y) {
                    for x in 0..w {
                        img.pixels[(y * w + x) as usize] = [0.0; 4];
                    }
                }
            }
            PartialImage::from_full(w, h, &img.to_full())
        };
        let images: Vec<PartialImage> = (0..4).map(band).collect();
        let plan = build_plan(4, w * h, Algorithm::DirectSend, None).unwrap();
        let plain = run_in_memory(&plan, &images, false, WireFormat::F32).unwrap();
        let inter = run_in_memory(&plan, &images, true, WireFormat::F32).unwrap();
        // Same pixels; only the association of OVER (which rank blends) differs.
        assert!(max_error(&plain.image, &inter.image) < 1e-6);
        let spread = |v: &[u64]| v.iter().max().unwrap() - v.iter().min().unwrap();
        // Plain: ranks 0 and 3 gather nothing but headers, ranks 1 and 2 half the band.
        assert!(
            spread(&plain.gather_bytes) > 3000,
            "{:?}",
            plain.gather_bytes
        );
        // Interlaced: every rank gets 4 band rows.
        assert!(
            spread(&inter.gather_bytes) <= 16,
            "{:?}",
            inter.gather_bytes
        );
    }

    #[test]
    fn order_is_respected() {
        // Two opaque images: the front one must win whatever the algorithm.
        let red = PartialImage::from_full(2, 2, &[[1.0, 0.0, 0.0, 1.0]; 4]);
        let blue = PartialImage::from_full(2, 2, &[[0.0, 0.0, 1.0, 1.0]; 4]);
        let none = PartialImage::empty(2, 2);
        for alg in [
            Algorithm::DirectSend,
            Algorithm::BinarySwap,
            Algorithm::RadixK,
            Algorithm::Gather,
        ] {
            let plan = build_plan(3, 4, alg, None).unwrap();
            let img = composite_in_memory(
                &plan,
                &[none.clone(), blue.clone(), red.clone()],
                true,
                WireFormat::F32,
            )
            .unwrap();
            assert!(img.iter().all(|p| *p == [0.0, 0.0, 1.0, 1.0]), "{alg:?}");
        }
    }

    #[test]
    fn wrong_image_count_is_an_error() {
        let plan = build_plan(3, 4, Algorithm::DirectSend, None).unwrap();
        let e = composite_in_memory(&plan, &[PartialImage::empty(2, 2)], false, WireFormat::F32)
            .unwrap_err();
        assert_eq!(e, CompositeError::ImageCount { got: 1, ranks: 3 });
        // Same pixel count, different shape.
        let plan = build_plan(2, 6, Algorithm::DirectSend, None).unwrap();
        let e = composite_in_memory(
            &plan,
            &[PartialImage::empty(2, 3), PartialImage::empty(3, 2)],
            true,
            WireFormat::F32,
        )
        .unwrap_err();
        assert!(matches!(e, CompositeError::InterlaceMismatch { .. }));
    }
}
