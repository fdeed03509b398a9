//! Cross-worker occlusion's per-ray limits (`strata_common::occlusion::RayLimits`) in both
//! casters: each ray is cast with the termination threshold of its screen block, or not at
//! all. The SIMD packets must agree with the scalar march bit for bit, the GPU with the CPU
//! within 1e-4, a re-cast of some blocks must give exactly those blocks' pixels, and what a
//! limit leaves out must stay within `1 − t` once the front is composited over it.

use strata_common::image::Rgba;
use strata_common::occlusion::{BlockGrid, BlockMask, FrontTransmittance, RayLimits, CLEAR};
use strata_common::scene::{Backend, Scene};
use strata_tests::scenes::*;
use strata_worker::engine::{Engine, Outcome};
use tempfile::TempDir;

const T: f32 = 0.99;

/// The synthetic survey (volume and horizons), dense enough that rays terminate.
fn survey(dir: &std::path::Path) -> Scene {
    survey_of(dir, [72, 56, 48])
}

/// A synthetic survey of `size` samples at 96×64 pixels, terminating at `T`.
fn survey_of(dir: &std::path::Path, size: [u64; 3]) -> Scene {
    let out =
        strata_coordinator::synth::synth(dir, size, 5, false, &indicatif::ProgressBar::hidden())
            .unwrap();
    let mut s = Scene::parse(&out.scene, &std::fs::read_to_string(&out.scene).unwrap()).unwrap();
    s.render.width = 96;
    s.render.height = 64;
    s.render.early_termination = T as f64;
    s.volumes[0].opacity = 1.0;
    s
}

/// A front map with every kind of block: exactly opaque, hidden at `T`, limited a lot and a
/// little, and clear.
fn front(grid: BlockGrid) -> FrontTransmittance {
    let q = (0..grid.len())
        .map(|b| match (b * 7 + b / grid.cols() as usize) % 6 {
            0 => 0,
            1 => 300,
            2 => 3000,
            3 => 20000,
            _ => CLEAR,
        })
        .collect();
    FrontTransmittance::checked(grid, q).unwrap()
}

struct Render {
    px: Vec<Rgba>,
    samples: u64,
    rays: u64,
}

/// A re-cast of the blocks of `only` gives exactly `full`'s pixels in them and leaves the
/// rest transparent (both images of `only`'s whole grid, row-major).
fn assert_only_blocks(got: &[[f32; 4]], full: &[[f32; 4]], only: &BlockMask, what: &str) {
    let w = only.grid.width;
    for (i, (g, f)) in got.iter().zip(full).enumerate() {
        let (x, y) = (i as u32 % w, i as u32 / w);
        let want = if only.pixel(x, y) { *f } else { [0.0; 4] };
        assert_eq!(*g, want, "({x}, {y}) of {what}");
    }
    assert_eq!(got.len(), full.len(), "{what}");
}

fn render(s: &Scene, backend: Backend, simd: bool, limits: Option<RayLimits<'_>>) -> Render {
    let mut s = on_backend(s, backend);
    s.render.simd = simd;
    let mut e = Engine::new(&s).unwrap();
    let view = e.view(s.render.width, s.render.height).unwrap();
    let region = e.scene_region();
    let r = e.render_batch_limited(&view, &region, limits).unwrap();
    assert_eq!(r.outcome, Outcome::Converged, "{:?}", r.reports);
    Render {
        px: r.image.to_full(),
        samples: r.last.samples,
        rays: r.last.rays,
    }
}

#[test]
fn rays_stop_at_their_block_limits_on_both_casters() {
    let dir = TempDir::new().unwrap();
    let s = survey(dir.path());
    let (w, h) = (s.render.width, s.render.height);
    let grid = BlockGrid::new(w, h, 3);
    let f = front(grid);
    let limits = RayLimits {
        front: &f,
        only: None,
        threshold: T,
    };
    let full = render(&s, Backend::Cpu, true, None);
    let lim = render(&s, Backend::Cpu, true, Some(limits));
    let scalar = render(&s, Backend::Cpu, false, Some(limits));
    assert!(
        bit_identical(&lim.px, &scalar.px),
        "packets and the scalar march differ under limits by {}",
        max_diff(&lim.px, &scalar.px)
    );
    assert_eq!(lim.samples, scalar.samples);
    assert!(
        lim.samples < full.samples * 3 / 4,
        "limits cast {} samples, the full frame {}",
        lim.samples,
        full.samples
    );
    assert!(
        lim.rays < full.rays,
        "rays behind opaque blocks are not cast"
    );
    // What a limit leaves out, seen through the front, is at most 1 − t per channel; rays
    // not cast are transparent.
    let mut limited = 0;
    for y in 0..h {
        for x in 0..w {
            let i = (y * w + x) as usize;
            let b = grid.block_of(x, y);
            let through = f.q[b] as f32 / CLEAR as f32;
            match f.ray_threshold(b, T) {
                None => assert_eq!(lim.px[i], [0.0; 4], "({x}, {y}) is not cast"),
                Some(e) if e < T => limited += (lim.px[i] != full.px[i]) as u32,
                Some(_) => assert_eq!(lim.px[i], full.px[i], "({x}, {y}) has no limit"),
            }
            for c in 0..4 {
                let lost = through * (full.px[i][c] - lim.px[i][c]);
                assert!(
                    (-1e-6..=1.0 - T + 1e-5).contains(&lost),
                    "({x}, {y}) channel {c}: {lost} lost behind a front passing {through}"
                );
            }
        }
    }
    assert!(
        limited > 0,
        "no limited ray stopped early: the scene tests nothing"
    );

    // A re-cast of some blocks gives exactly their pixels and leaves the rest transparent.
    let mut only = BlockMask::empty(grid);
    for b in (0..grid.len()).step_by(5) {
        only.set(b);
    }
    let again = render(
        &s,
        Backend::Cpu,
        true,
        Some(RayLimits {
            only: Some(&only),
            ..limits
        }),
    );
    assert_only_blocks(&again.px, &lim.px, &only, "the re-cast");
    // A re-cast of a few neighbouring blocks casts only the part of the region's rectangle
    // that holds them (`BlockMask::pixel_bounds`): still exactly their pixels.
    // Four blocks with something in them, in a corner of a 4 × 4 patch of blocks.
    let cols = grid.cols() as usize;
    let lit = |bx: usize, by: usize| {
        let (x0, y0, x1, y1) = grid.pixels_of(by * cols + bx);
        (y0..y1).all(|y| (x0..x1).all(|x| lim.px[(y * w + x) as usize][3] > 0.0))
    };
    let (bx, by) = (0..grid.rows() as usize - 3)
        .flat_map(|by| (0..cols - 3).map(move |bx| (bx, by)))
        .find(|&(bx, by)| lit(bx, by) && lit(bx + 3, by) && lit(bx, by + 3) && lit(bx + 3, by + 3))
        .expect("a patch of blocks with content at its corners");
    let mut corner = BlockMask::empty(grid);
    for (x, y) in [(bx, by), (bx + 3, by), (bx, by + 3), (bx + 3, by + 3)] {
        corner.set(y * cols + x);
    }
    let bounds = corner.pixel_bounds().expect("blocks set");
    assert!(
        bounds.area() * 4 < (w * h) as usize,
        "{bounds:?} is no part of the frame"
    );
    let corner_limits = RayLimits {
        only: Some(&corner),
        ..limits
    };
    let part = render(&s, Backend::Cpu, true, Some(corner_limits));
    assert_only_blocks(&part.px, &lim.px, &corner, "the re-cast of four blocks");

    if gpu_available() {
        let gpu = render(&s, Backend::Gpu, true, Some(limits));
        assert_clean(&gpu.px);
        let d = max_diff(&gpu.px, &lim.px);
        assert!(d <= 1e-4, "GPU differs from CPU under limits by {d}");
        assert_eq!(gpu.rays, lim.rays, "the GPU leaves out the same rays");
        for (i, p) in gpu.px.iter().enumerate() {
            let (x, y) = (i as u32 % w, i as u32 / w);
            if f.ray_threshold(grid.block_of(x, y), T).is_none() {
                assert_eq!(*p, [0.0; 4], "GPU ({x}, {y}) is not cast");
            }
        }
        let gpu_again = render(
            &s,
            Backend::Gpu,
            true,
            Some(RayLimits {
                only: Some(&only),
                ..limits
            }),
        );
        let d = max_diff(&gpu_again.px, &again.px);
        assert!(d <= 1e-4, "GPU re-cast differs from CPU by {d}");
        let gpu_part = render(&s, Backend::Gpu, true, Some(corner_limits));
        let d = max_diff(&gpu_part.px, &part.px);
        assert!(
            d <= 1e-4,
            "GPU re-cast of four blocks differs from CPU by {d}"
        );
    }
}

/// With `render.rounds_per_frame` set, a region's first frame still converges, and so does
/// occlusion's re-cast of some of its blocks in that frame: the re-cast takes the first
/// cast's round budget. (It had been given the budget of a region seen before, one round
/// here, and stopped at the round limit without the pages its rays had been hidden from.)
#[test]
fn the_recast_of_a_regions_first_frame_converges_under_rounds_per_frame() {
    let dir = TempDir::new().unwrap();
    // Wider than `survey`'s, so the two halves of the screen see different bricks.
    let mut s = survey_of(dir.path(), [320, 240, 48]);
    s.render.max_rounds = 64;
    let mut s = on_backend(&s, Backend::Cpu);
    s.render.rounds_per_frame = 1;
    let (w, h) = (s.render.width, s.render.height);
    let grid = BlockGrid::new(w, h, 4);
    // The first cast: the left half hidden behind an opaque front, the right half clear.
    let q: Vec<u16> = (0..grid.len())
        .map(|b| {
            if (b % grid.cols() as usize) < grid.cols() as usize / 2 {
                0
            } else {
                CLEAR
            }
        })
        .collect();
    let hidden = FrontTransmittance::checked(grid, q).unwrap();
    let mut e = Engine::new(&s).unwrap();
    let view = e.view(w, h).unwrap();
    let region = e.scene_region();
    let first = RayLimits {
        front: &hidden,
        only: None,
        threshold: T,
    };
    let r = e.render_batch_limited(&view, &region, Some(first)).unwrap();
    assert_eq!(r.outcome, Outcome::Converged, "{:?}", r.reports);
    // The re-cast: the hidden half turns out clear.
    let clear = FrontTransmittance::checked(grid, vec![CLEAR; grid.len()]).unwrap();
    let mut only = BlockMask::empty(grid);
    for b in 0..grid.len() {
        if (b % grid.cols() as usize) < grid.cols() as usize / 2 {
            only.set(b);
        }
    }
    let again = RayLimits {
        front: &clear,
        only: Some(&only),
        threshold: T,
    };
    let r = e.render_batch_limited(&view, &region, Some(again)).unwrap();
    assert_eq!(r.outcome, Outcome::Converged, "{:?}", r.reports);
    assert!(
        r.rounds > 1,
        "the re-cast needed no page: the test shows nothing"
    );
    // A later frame of the same region takes the budget of a seen region.
    let r = e.render_batch_limited(&view, &region, None).unwrap();
    assert_eq!(r.rounds, 1);

    // A worker with two leaves casts both, then re-casts the first: its re-cast takes that
    // leaf's first-frame budget too, not the seen budget the other leaf's cast left behind
    // (it had stopped at the round limit).
    let mut e = Engine::new(&s).unwrap();
    let halves = {
        let mut t = strata_common::kd::KdTree::single(region);
        t.split_leaf(0, 0, 0.5 * (region.lo[0] + region.hi[0]));
        t.leaves
    };
    for leaf in &halves {
        let r = e.render_batch_limited(&view, leaf, Some(first)).unwrap();
        assert_eq!(r.outcome, Outcome::Converged, "{:?}", r.reports);
    }
    let r = e
        .render_batch_limited(&view, &halves[0], Some(again))
        .unwrap();
    assert_eq!(r.outcome, Outcome::Converged, "{:?}", r.reports);
    assert!(
        r.rounds > 1,
        "the re-cast needed no page: the test shows nothing"
    );
}
