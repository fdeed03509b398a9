//! Data shapes: one-voxel-thick volumes, a single trace, anisotropic spacing, non-power-of-two
//! dimensions, page sizes.

use crate::harness::*;
use crate::Case;
use strata_common::geo::Affine3;

pub fn cases() -> Vec<Case> {
    vec![
        Case {
            no: 22,
            name: "one-voxel-thick-volume",
            reference: "analytic 1-(1-a)^(Δs·n) per pixel through the slab z ∈ [-0.5, 0.5)",
            tol: 2e-5,
            why: "f32 rounding of a few blend steps; pixels whose entry or exit lies within 1e-3 \
                  of a lattice point, or within half a voxel of a side face, are left out",
            long_rays: false,
            run: one_voxel_thick,
        },
        Case {
            no: 23,
            name: "single-trace",
            reference:
                "analytic: the centre ray crosses one voxel of a ramp trace; rays that pass \
                        beside it see nothing",
            tol: 2e-5,
            why: "four blend steps in f32",
            long_rays: false,
            run: single_trace,
        },
        Case {
            no: 24,
            name: "spacing-1-to-1000",
            reference: "analytic slabs across (16 m) and along (16 km) the stretched axis",
            tol: 5e-5,
            why: "16 000 blend steps in f32 along the long axis",
            long_rays: false,
            run: anisotropic,
        },
        Case {
            no: 25,
            name: "non-power-of-two-dims",
            reference: "analytic transmittance-weighted ramp along z through 33×47×29 samples in \
                        32-sample pages",
            tol: 1e-5,
            why:
                "the ramp is linear, so trilinear interpolation is exact; f32 rounding of 58 steps",
            long_rays: false,
            run: npot,
        },
        Case {
            no: 26,
            name: "pages-of-32-and-128",
            reference: "the same 70×50×40 volume in 128-sample pages (one brick)",
            tol: 1e-6,
            why:
                "paging does not move samples or taps; 32-, 64- and 128-sample pages give one image",
            long_rays: false,
            run: page_sizes,
        },
    ]
}

fn one_voxel_thick(ctx: &Ctx) -> Res<f64> {
    let (a, step) = (0.3, 0.25);
    let store = volume(
        ctx,
        "thin",
        [32, 32, 1],
        Affine3::IDENTITY,
        32,
        |_, _, _| 1.0,
    );
    let w = 33;
    let eye = [15.5, 15.5, -20.0];
    let s = scene(
        vec![grey(store, [0.0, 2.0], a)],
        vec![],
        camera(eye, [15.5, 15.5, 0.0], [0.0, 1.0, 0.0], 40.0),
        {
            let mut r = settings(w, w);
            r.step = step;
            r
        },
    );
    let img = ctx.render(&s)?;
    slab_error(&s, &img, a, [-0.5, 0.5], [31.5, 31.5], 0.5, 200)
}

fn single_trace(ctx: &Ctx) -> Res<f64> {
    let (a, step) = (0.2, 0.25);
    let store = volume(
        ctx,
        "trace",
        [1, 1, 64],
        Affine3::IDENTITY,
        32,
        |_, _, k| k as f32 / 63.0,
    );
    let w = 33;
    let eye = [-20.0, 0.0, 31.5];
    let s = scene(
        vec![grey(store, [0.0, 1.0], a)],
        vec![],
        camera(eye, [0.0, 0.0, 31.5], [0.0, 0.0, 1.0], 10.0),
        {
            let mut r = settings(w, w);
            r.step = step;
            r
        },
    );
    let img = ctx.render(&s)?;
    // The centre ray: t in [19.5, 20.5), samples at 19.5, 19.75, 20, 20.25, value 0.5.
    let n = lattice_count(19.5, 20.5, step as f32);
    let want = slab(a, step, n);
    let mut err = err4(
        at(&img, w, w / 2, w / 2),
        [0.5 * want, 0.5 * want, 0.5 * want, want],
    );
    // Rays that pass the trace more than 0.6 to the side see nothing.
    let v = view(&s);
    for y in 0..w {
        for x in 0..w {
            let d = dir(&v, x, y);
            let t = -eye[0] / d[0];
            if (t * d[1]).abs() > 0.6 {
                err = err.max(err4(at(&img, w, x, y), [0.0; 4]));
            }
        }
    }
    Ok(err)
}

fn anisotropic(ctx: &Ctx) -> Res<f64> {
    let a = 1e-4;
    let store = volume(
        ctx,
        "stretched",
        [16, 16, 16],
        scale_translate([1.0, 1.0, 1000.0], [0.0; 3]),
        32,
        |_, _, _| 1.0,
    );
    let mut err = 0.0f64;
    // Across x at mid height (16 samples of 1 m), then down z (16 km at the 1 m step).
    let views = [
        ([-20.0, 7.5, 7500.0], [0.0, 7.5, 7500.0], 19.5, 35.5),
        ([7.5, 7.5, -1000.0], [7.5, 7.5, 0.0], 500.0, 16500.0),
    ];
    for (eye, target, t0, t1) in views {
        let s = scene(
            vec![grey(store.clone(), [0.0, 2.0], a)],
            vec![],
            camera(eye, target, [0.0, 1.0, 0.0], 1.0),
            settings(5, 5),
        );
        let img = ctx.render(&s)?;
        let n = lattice_count(t0 as f32, t1 as f32, 1.0);
        let want = slab(a, 1.0, n);
        err = err.max(err4(
            at(&img, 5, 2, 2),
            [0.5 * want, 0.5 * want, 0.5 * want, want],
        ));
    }
    Ok(err)
}

fn npot(ctx: &Ctx) -> Res<f64> {
    let (a, step) = (0.02, 0.5);
    let store = volume(
        ctx,
        "npot",
        [33, 47, 29],
        Affine3::IDENTITY,
        32,
        |_, _, k| 0.5 * k as f32,
    );
    let w = 33;
    let s = scene(
        vec![grey(store, [0.0, 14.0], a)],
        vec![],
        camera(
            [16.0, 23.0, -40.0],
            [16.0, 23.0, 0.0],
            [0.0, 1.0, 0.0],
            30.0,
        ),
        {
            let mut r = settings(w, w);
            r.step = step;
            r
        },
    );
    let img = ctx.render(&s)?;
    let (mut acc, mut al) = (0.0f64, 0.0f64);
    let ac = slab(a, step, 1);
    let mut k = 0i64;
    loop {
        let t = k as f32 * step as f32;
        k += 1;
        if t < 39.5 {
            continue;
        }
        if t >= 68.5 {
            break;
        }
        let z = (t as f64 - 40.0).clamp(0.0, 28.0);
        let col = 0.5 * z / 14.0;
        acc += (1.0 - al) * ac * col;
        al += (1.0 - al) * ac;
    }
    Ok(err4(at(&img, w, w / 2, w / 2), [acc, acc, acc, al]))
}

fn page_sizes(ctx: &Ctx) -> Res<f64> {
    let mk = |page: u32| {
        let store = smooth_volume(ctx, [70, 50, 40], page);
        scene(
            vec![seismic(store, [-1.0, 1.0])],
            vec![],
            camera(
                [-30.0, -45.0, 60.0],
                [35.0, 25.0, 20.0],
                [0.0, 0.0, 1.0],
                40.0,
            ),
            settings(48, 40),
        )
    };
    let reference = ctx.render(&mk(128))?;
    shows(&reference, 0.2, "the volume")?;
    let mut err = 0.0f64;
    for page in [32, 64] {
        err = err.max(diff(&ctx.render(&mk(page))?, &reference)?);
    }
    Ok(err)
}
