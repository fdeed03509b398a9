//! Compositing: one pixel over 16 ranks, all-transparent and all-opaque images, the f16
//! wire at its limits, visibility order reversed at every level of the tree.

use crate::harness::*;
use crate::Case;
use strata_common::composite::{Algorithm, PieceError, Span, SparsePiece, WireFormat};
use strata_common::geo::Affine3;
use strata_common::image::{composite_front_to_back, PartialImage, Rgba};
use strata_common::scene::Scene;
use strata_worker::engine::Engine;

pub fn cases() -> Vec<Case> {
    vec![
        Case {
            no: 27,
            name: "one-pixel-over-16-ranks",
            reference: "the whole scene as one region (in process)",
            tol: 1e-5,
            why: "16 partial images of one pixel composite to the single-region pixel up to float \
                  reassociation",
            long_rays: false,
            run: one_pixel,
        },
        Case {
            no: 28,
            name: "all-transparent",
            reference: "exactly zero in every channel of every pixel",
            tol: 0.0,
            why: "nothing visible must add nothing, not even rounding",
            long_rays: false,
            run: all_transparent,
        },
        Case {
            no: 29,
            name: "all-opaque",
            reference: "exactly the map colour with alpha 1 in every pixel",
            tol: 1e-7,
            why: "the front region's opaque pixel hides the rest: over() with alpha 1 is exact",
            long_rays: false,
            run: all_opaque,
        },
        Case {
            no: 30,
            name: "f16-wire-at-its-limits",
            reference: "the f32 composite; error measured in units of 2^-9·|x| + 2^-23",
            tol: 1.0,
            why: "f16 keeps 11 significant bits and steps of 2^-24 below 2^-14: up to four roundings \
                  per value (exchange rounds and gather) stay within 2^-9 relative plus two \
                  subnormal steps; a flush of small values to zero would not",
            long_rays: false,
            run: f16_limits,
        },
        Case {
            no: 31,
            name: "order-reversed-at-every-round",
            reference: "the whole scene as one region, for direct send, binary swap and radix-k",
            tol: 1e-5,
            why: "the camera looks down the split axis from its far end, so at every level of the \
                  tree the upper region is in front; float reassociation only",
            long_rays: false,
            run: reversed,
        },
    ]
}

fn one_pixel(ctx: &Ctx) -> Res<f64> {
    let store = volume(ctx, "v", [32, 32, 32], Affine3::IDENTITY, 32, smooth);
    let s = scene(
        vec![seismic(store, [-1.0, 1.0])],
        vec![],
        camera(
            [-20.0, -25.0, 40.0],
            [15.5, 15.5, 15.5],
            [0.0, 0.0, 1.0],
            20.0,
        ),
        settings(1, 1),
    );
    let tree = decomposition(&s, 16)?;
    if tree.leaves.len() != 16 {
        return Err(format!("{} leaves: mis-built", tree.leaves.len()));
    }
    let whole = ctx.whole_reference(&s)?;
    let split = ctx.render_regions(&s, &tree)?;
    shows(&whole, 0.05, "the pixel")?;
    diff(&whole, &split)
}

fn all_transparent(ctx: &Ctx) -> Res<f64> {
    let store = volume(ctx, "v", [32, 32, 32], Affine3::IDENTITY, 32, smooth);
    let h = horizon(ctx, "h", [32, 32], Affine3::IDENTITY, |i, j| {
        10.0 + (i + j) as f32 * 0.1
    });
    let mut layer = seismic(store, [-1.0, 1.0]);
    layer.opacity_points = Some(vec![[0.0, 0.0], [1.0, 0.0]]);
    let s = scene(
        vec![layer],
        vec![strata_tests::scenes::horizon_layer(h, [1.0, 1.0, 1.0], 0.0)],
        camera(
            [-20.0, -25.0, 40.0],
            [15.5, 15.5, 15.5],
            [0.0, 0.0, 1.0],
            40.0,
        ),
        settings(40, 30),
    );
    let img = ctx.render(&s)?;
    Ok(img
        .iter()
        .flat_map(|p| p.iter())
        .map(|&c| {
            if c.to_bits() == 0 {
                0.0
            } else {
                c.abs().max(f32::MIN_POSITIVE) as f64
            }
        })
        .fold(0.0, f64::max))
}

fn all_opaque(ctx: &Ctx) -> Res<f64> {
    let store = volume(ctx, "v", [32, 32, 32], Affine3::IDENTITY, 32, |_, _, _| 1.0);
    let mut r = settings(40, 30);
    r.early_termination = 0.99;
    let s = scene(
        vec![grey(store, [0.0, 2.0], 1.0)],
        vec![],
        camera(
            [15.5, 15.5, 15.5],
            [40.0, 30.0, 20.0],
            [0.0, 0.0, 1.0],
            90.0,
        ),
        r,
    );
    let img = ctx.render(&s)?;
    Ok(img
        .iter()
        .map(|p| err4(*p, [0.5, 0.5, 0.5, 1.0]))
        .fold(0.0, f64::max))
}

/// A ramp volume whose premultiplied values run from below f16's smallest subnormal
/// (2^-24) through its normal range up to 1.
fn faint_scene(ctx: &Ctx) -> Scene {
    let store = volume(
        ctx,
        "ramp",
        [32, 32, 32],
        Affine3::IDENTITY,
        32,
        |i, j, _| (i + 32 * j) as f32 / 1023.0,
    );
    let layer = strata_tests::scenes::volume_layer(
        store,
        "viridis",
        [0.0, 1.0],
        vec![
            [0.0, 1e-10],
            [0.3, 1e-8],
            [0.6, 1e-5],
            [0.8, 1e-3],
            [1.0, 0.5],
        ],
    );
    scene(
        vec![layer],
        vec![],
        camera(
            [15.5, 15.5, -40.0],
            [15.5, 15.5, 15.5],
            [0.0, 1.0, 0.0],
            45.0,
        ),
        settings(48, 40),
    )
}

/// Error of `got` against `want` in units of the f16 bound 2^-9·|x| + 2^-23.
fn f16_units(got: &[Rgba], want: &[Rgba]) -> f64 {
    got.iter()
        .zip(want)
        .flat_map(|(g, w)| (0..4).map(move |c| (g[c], w[c])))
        .map(|(g, w)| {
            (g as f64 - w as f64).abs() / ((w as f64).abs() * 2f64.powi(-9) + 2f64.powi(-23))
        })
        .fold(0.0, f64::max)
}

/// A partial image after a trip over the wire in `format`.
fn over_wire(p: &PartialImage, format: WireFormat) -> Result<PartialImage, PieceError> {
    let full = p.to_full();
    let span = Span {
        start: 0,
        end: full.len() as u32,
    };
    let piece = SparsePiece::encode(&full, span, format);
    let mut back = vec![[0.0f32; 4]; full.len()];
    piece.decode_into(&mut back, 0)?;
    Ok(PartialImage::from_full(p.width, p.height, &back))
}

fn f16_limits(ctx: &Ctx) -> Res<f64> {
    let mut s = faint_scene(ctx);
    let reference = ctx.whole_reference(&s)?;
    // The scene must reach into f16's subnormal range and up to its coarse steps near 1.
    let small = reference
        .iter()
        .flat_map(|p| p.iter())
        .filter(|&&c| c > 0.0 && c < 6.1e-5)
        .count();
    if small < 100 || max_alpha(&reference) < 0.3 {
        return Err(format!(
            "{small} subnormal-range values, max alpha {}: mis-built",
            max_alpha(&reference)
        ));
    }
    if ctx.in_process() {
        // The in-process backends composite three regions after a trip through the f16
        // wire encoding, as the exchange does.
        let tree = decomposition(&s, WORKERS)?;
        let (w, h) = (s.render.width, s.render.height);
        let mut parts = Vec::new();
        let mut eye = [0.0; 3];
        let caster = match ctx.backend {
            Backend::Gpu => strata_common::scene::Backend::Gpu,
            _ => strata_common::scene::Backend::Cpu,
        };
        s.render.backend = caster;
        s.render.simd = ctx.backend != Backend::Scalar;
        for leaf in &tree.leaves {
            let mut e = Engine::new(&s).map_err(|e| format!("{e:#}"))?;
            let view = e.view(w, h).map_err(|e| format!("{e:#}"))?;
            eye = e.camera().eye;
            let r = e.render_batch(&view, leaf).map_err(|e| format!("{e:#}"))?;
            parts.push(over_wire(&r.image, WireFormat::F16).map_err(|e| e.to_string())?);
        }
        let order = tree.visibility_order(eye);
        let ordered: Vec<&PartialImage> = order.iter().map(|&i| &parts[i]).collect();
        let img = composite_front_to_back(w, h, &ordered);
        clean(&img)?;
        Ok(f16_units(&img, &reference))
    } else {
        s.composite.wire = WireFormat::F16;
        let img = ctx.render(&s)?;
        Ok(f16_units(&img, &reference))
    }
}

fn reversed(ctx: &Ctx) -> Res<f64> {
    let store = volume(ctx, "long", [64, 16, 16], Affine3::IDENTITY, 32, smooth);
    let mut s = scene(
        vec![seismic(store, [-1.0, 1.0])],
        vec![],
        camera([130.0, 9.0, 11.0], [31.5, 7.5, 7.5], [0.0, 0.0, 1.0], 25.0),
        settings(48, 40),
    );
    let workers = 4;
    let tree = decomposition(&s, workers)?;
    // Every split across x, and the eye beyond the upper end: the visibility order is the
    // tree order reversed, so at every level (every exchange round) the upper half is in
    // front.
    if planes(&tree).iter().any(|p| p.0 != 0) {
        return Err(format!(
            "splits {:?} are not all across x: mis-built",
            planes(&tree)
        ));
    }
    let order = tree.visibility_order(s.camera.as_ref().unwrap().eye);
    let reversed: Vec<usize> = {
        let mut by_x: Vec<usize> = (0..tree.leaves.len()).collect();
        by_x.sort_by(|&a, &b| tree.leaves[b].lo[0].total_cmp(&tree.leaves[a].lo[0]));
        by_x
    };
    if order != reversed {
        return Err(format!(
            "visibility order {order:?}, not {reversed:?}: mis-built"
        ));
    }
    let whole = ctx.whole_reference(&s)?;
    shows(&whole, 0.2, "the volume")?;
    let mut err = 0.0f64;
    for alg in [
        Algorithm::DirectSend,
        Algorithm::BinarySwap,
        Algorithm::RadixK,
        Algorithm::Gather,
    ] {
        s.composite.algorithm = alg;
        let split = ctx.render_regions(&s, &tree)?;
        err = err.max(diff(&whole, &split)?);
        if ctx.in_process() {
            // The in-process composite does not depend on the algorithm.
            break;
        }
    }
    Ok(err)
}
