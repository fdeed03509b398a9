//! Numerics: saturation, tiny opacities over long rays, extreme steps and step ratios, values
//! near the f32 limits, constant data, NaN/Inf samples, denormals.

use crate::harness::*;
use crate::Case;
use strata_common::geo::Affine3;
use strata_common::scene::Scene;

pub fn cases() -> Vec<Case> {
    vec![
        Case {
            no: 14,
            name: "alpha-saturating-to-1",
            reference: "analytic: alpha exactly 1 and the map's colour, with and without early termination \
                        (distributed at t = 0.99: within 1 − t, as regions that each stop at t \
                        may overshoot when a split cuts the slab)",
            tol: 1e-6,
            why: "1 − (1 − 1)·x is exact; a sum that overshot 1 or a colour above alpha would show",
            long_rays: false,
            run: saturating,
        },
        Case {
            no: 15,
            name: "alpha-1e-6-over-1e5-samples",
            reference: "analytic 1-(1-α)^n, n ≈ 10⁵ lattice samples",
            tol: 2e-5,
            why: "f32 rounding of 10⁵ blend steps of about 4e-9 each grows like √n; the step table's \
                  corrected alpha is exact to f32 rounding",
            long_rays: true,
            run: tiny_alpha,
        },
        Case {
            no: 16,
            name: "steps-1e-3-to-1e3-voxels",
            reference: "analytic slab 1-(1-a)^(Δs·n) for Δs = 10⁻³ … 10³",
            tol: 5e-5,
            why: "up to 32 000 blend steps in f32 (Δs = 10⁻³)",
            long_rays: true,
            run: steps,
        },
        Case {
            no: 17,
            name: "opacity-correction-extreme-ratios",
            reference: "analytic relative error of 1-(1-a)^(Δs·n) for a = 0.9 at Δs = 10⁻³ and \
                        a = 10⁻⁷ at Δs = 10³",
            tol: 1e-4,
            why: "the corrected alpha 1-(1-a)^r must keep f32 precision when 1-a rounds to 1 (tiny a) \
                  and when r is tiny; relative 1e-4 allows 2 000 blend steps",
            long_rays: false,
            run: extreme_ratios,
        },
        Case {
            no: 18,
            name: "values-near-f32-limits",
            reference: "the same field scaled down by 10³⁸ with its window",
            tol: 1e-5,
            why: "value → table position must not overflow for windows wider than f32::MAX; \
                  neighbouring samples differ by less than f32::MAX",
            long_rays: false,
            run: f32_limits,
        },
        Case {
            no: 19,
            name: "constant-volume",
            reference: "analytic slab with the opacity at the middle of the colour map",
            tol: 2e-5,
            why: "a constant store has an empty value range; its default window is centred on the \
                  value (32 blend steps in f32)",
            long_rays: false,
            run: constant,
        },
        Case {
            no: 20,
            name: "nan-and-inf-in-data",
            reference: "the same volume with NaN where the data has ±Inf (both are no data)",
            tol: 0.0,
            why: "±Inf samples are stored as no data (NaN), so the two stores are the same",
            long_rays: false,
            run: nan_inf,
        },
        Case {
            no: 21,
            name: "denormals",
            reference: "the volume of zeros (data of 1e-39…1e-41), and alpha ≤ 1e-35 for a \
                        transfer function of alpha 1e-38",
            tol: 1e-6,
            why: "subnormal values map to the window's middle like zero; subnormal opacities must \
                  neither blow up nor turn into NaN",
            long_rays: false,
            run: denormals,
        },
    ]
}

/// A constant 32³ volume seen along +z from `z = eye_z` through its centre.
fn slab_scene(
    ctx: &Ctx,
    name: &str,
    dims: [u64; 3],
    a: f64,
    eye_z: f64,
    w: u32,
    fov: f64,
) -> Scene {
    let store = volume(ctx, name, dims, Affine3::IDENTITY, 32, |_, _, _| 1.0);
    let c = [(dims[0] - 1) as f64 / 2.0, (dims[1] - 1) as f64 / 2.0];
    scene(
        vec![grey(store, [0.0, 2.0], a)],
        vec![],
        camera(
            [c[0], c[1], eye_z],
            [c[0], c[1], eye_z + 100.0],
            [0.0, 1.0, 0.0],
            fov,
        ),
        settings(w, w),
    )
}

fn centre(img: &[[f32; 4]], w: u32) -> [f32; 4] {
    at(img, w, w / 2, w / 2)
}

fn saturating(ctx: &Ctx) -> Res<f64> {
    let mut err = 0.0f64;
    for ert in [1.0, 0.99] {
        for a in [1.0, 0.9] {
            let mut s = slab_scene(ctx, &format!("s{a}{ert}"), [32, 32, 32], a, -50.0, 9, 15.0);
            s.render.early_termination = ert;
            let img = ctx.render(&s)?;
            // Each region stops its rays at t on its own: where a split plane cuts the slab,
            // the region behind adds up to 1 − t (the distributed bound; exact at t = 1).
            let allowed = if ctx.in_process() { 0.0 } else { 1.0 - ert };
            for p in &img {
                let want = if a == 1.0 || ert == 1.0 {
                    [0.5, 0.5, 0.5, 1.0]
                } else {
                    // Early termination stops once alpha reaches 0.99: 1 - 0.1^2.
                    [0.495, 0.495, 0.495, 0.99]
                };
                err = err.max((err4(*p, want) - allowed).max(0.0));
            }
        }
    }
    Ok(err)
}

fn tiny_alpha(ctx: &Ctx) -> Res<f64> {
    // Per-sample alpha 1e-6 at a step of 0.01 voxel: 1e-4 per voxel. Where shader loops are
    // cut short, 12 000 samples (120 voxels) instead of 100 000.
    let step = 0.01;
    let a = 1.0 - (1.0f64 - 1e-6).powf(1.0 / step);
    let depth = if ctx.short_loops { 120 } else { 1000 };
    let mut s = slab_scene(ctx, "long", [4, 4, depth], a, -10.0, 3, 1.0);
    s.render.step = step;
    let img = ctx.render(&s)?;
    let n = lattice_count(9.5, 9.5 + depth as f32, step as f32);
    let expected = depth * 100;
    if !(expected * 99 / 100..=expected * 101 / 100).contains(&n) {
        return Err(format!("{n} samples: mis-built"));
    }
    let a32 = a as f32 as f64;
    let want = slab(a32, step, n);
    Ok(err4(
        centre(&img, 3),
        [0.5 * want, 0.5 * want, 0.5 * want, want],
    ))
}

fn steps(ctx: &Ctx) -> Res<f64> {
    let a = 0.05;
    let mut err = 0.0f64;
    // The box spans t in [989, 1021): every step has a lattice point in it.
    for step in [1e-3, 1e-2, 0.37, 1.0, 7.3, 1e2, 1e3] {
        // 32 000 samples: past what llvmpipe's loops allow.
        if ctx.short_loops && step < 1e-2 {
            continue;
        }
        let mut s = slab_scene(ctx, &format!("st{step}"), [32, 32, 32], a, -989.5, 3, 0.5);
        s.render.step = step;
        let img = ctx.render(&s)?;
        let n = lattice_count(989.0, 1021.0, step as f32);
        if n == 0 {
            return Err(format!("step {step}: no sample in the box: mis-built"));
        }
        let want = slab(a, step, n);
        let e = err4(centre(&img, 3), [0.5 * want, 0.5 * want, 0.5 * want, want]);
        err = err.max(e);
    }
    Ok(err)
}

fn extreme_ratios(ctx: &Ctx) -> Res<f64> {
    let mut err = 0.0f64;
    // A 2-voxel-thick slab (z in [-0.5, 1.5)) seen from above.
    for (a, step) in [(0.9, 1e-3), (1e-7, 1e3), (1e-7, 1.0), (0.5, 1e-3)] {
        let eye_z = if step > 1.0 { -999.75 } else { -20.0 };
        let mut s = slab_scene(ctx, &format!("r{a}-{step}"), [8, 8, 2], a, eye_z, 3, 0.5);
        s.render.step = step;
        let img = ctx.render(&s)?;
        let (t0, t1) = ((-0.5 - eye_z) as f32, (1.5 - eye_z) as f32);
        let n = lattice_count(t0, t1, step as f32);
        if n == 0 {
            return Err(format!("a {a}, step {step}: no sample: mis-built"));
        }
        let want = slab(a as f32 as f64, step, n);
        let got = centre(&img, 3)[3] as f64;
        err = err.max((got - want).abs() / want);
    }
    Ok(err)
}

fn f32_limits(ctx: &Ctx) -> Res<f64> {
    let mk = |name: &str, scale: f32, window: f64| {
        let store = volume(ctx, name, [32, 32, 32], Affine3::IDENTITY, 32, |i, j, k| {
            1.6 * smooth(i, j, k) * scale
        });
        scene(
            vec![seismic(store, [-window, window])],
            vec![],
            oblique_camera(),
            settings(48, 40),
        )
    };
    let big = ctx.render(&mk("big", 1e38, 3.3e38))?;
    let small = ctx.render(&mk("small", 1.0, 3.3))?;
    shows(&small, 0.1, "the volume")?;
    diff(&big, &small)
}

fn constant(ctx: &Ctx) -> Res<f64> {
    let store = volume(
        ctx,
        "seven",
        [32, 32, 32],
        Affine3::IDENTITY,
        32,
        |_, _, _| 7.0,
    );
    let mut layer = grey(store, [0.0, 1.0], 0.0);
    layer.window = None;
    layer.opacity_points = None;
    let s = scene(vec![layer], vec![], head_on_camera(), settings(9, 9));
    let img = ctx.render(&s)?;
    // The default opacity curve for non-seismic maps: 0 up to 0.1, then a ramp to 0.5.
    let a = 0.5 * (0.5 - 0.1) / 0.9;
    slab_error(
        &s,
        &img,
        a as f32 as f64,
        [-0.5, 31.5],
        [31.5, 31.5],
        0.5,
        40,
    )
}

fn nan_inf(ctx: &Ctx) -> Res<f64> {
    let bad = |i: u64, j: u64, k: u64| (i * 7 + j * 13 + k * 29).is_multiple_of(23);
    let field = |inf: bool| {
        move |i: u64, j: u64, k: u64| {
            if bad(i, j, k) {
                match ((i + j + k) % 3, inf) {
                    (0, true) => f32::INFINITY,
                    (1, true) => f32::NEG_INFINITY,
                    _ => f32::NAN,
                }
            } else {
                smooth(i, j, k)
            }
        }
    };
    let mk = |name: &str, inf: bool| {
        let store = volume(ctx, name, [32, 32, 32], Affine3::IDENTITY, 32, field(inf));
        oblique(store)
    };
    let with_inf = ctx.render(&mk("inf", true))?;
    let with_nan = ctx.render(&mk("nan", false))?;
    shows(&with_nan, 0.1, "the volume")?;
    diff(&with_inf, &with_nan)
}

fn denormals(ctx: &Ctx) -> Res<f64> {
    let mk = |name: &str, f: fn(u64, u64, u64) -> f32| {
        let store = volume(ctx, name, [32, 32, 32], Affine3::IDENTITY, 32, f);
        oblique(store)
    };
    let tiny = ctx.render(&mk("tiny", |i, j, k| smooth(i, j, k) * 1e-39))?;
    let zero = ctx.render(&mk("zero", |_, _, _| 0.0))?;
    shows(&zero, 0.01, "the zero volume")?;
    let e = diff(&tiny, &zero)?;
    // Subnormal opacities: alpha 1e-38 per voxel, premultiplied colours below f32's
    // smallest normal.
    let store = volume(
        ctx,
        "faint",
        [32, 32, 32],
        Affine3::IDENTITY,
        32,
        |_, _, _| 1.0,
    );
    let s = scene(
        vec![grey(store, [0.0, 2.0], 1e-38)],
        vec![],
        head_on_camera(),
        settings(9, 9),
    );
    let faint = ctx.render(&s)?;
    let m = max_alpha(&faint);
    if m > 1e-35 {
        return Err(format!("alpha 1e-38 per voxel over 32 voxels gave {m}"));
    }
    Ok(e)
}
