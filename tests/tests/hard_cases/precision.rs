//! Precision: world coordinates far from the origin, far cameras, rotated surveys.

use crate::harness::*;
use crate::Case;
use strata_common::geo::Affine3;

pub fn cases() -> Vec<Case> {
    vec![
        Case {
            no: 1,
            name: "utm-northing-sub-metre",
            reference: "the same survey and camera moved to the origin",
            tol: 1e-5,
            why: "rays are built camera-relative in f64 and only then rounded to f32, so the \
                  offset costs nothing; 1e-5 leaves room for f32 rounding of 0.25 m voxels",
            long_rays: false,
            run: utm_northing,
        },
        Case {
            no: 2,
            name: "camera-1e5-away",
            reference: "analytic slab 1-(1-a)^32 in every pixel",
            tol: 2e-5,
            why: "lattice points k·Δt near t = 10⁵ are exact in f32; 2e-5 is the f32 rounding of \
                  32 blend steps",
            long_rays: false,
            run: far_camera,
        },
        Case {
            no: 3,
            name: "survey-rotated-37.3-degrees",
            reference: "the unrotated survey seen by the unrotated camera",
            tol: 1e-4,
            why: "the rotated index→world map is rounded to f32 (about 1e-7 relative), moving \
                  samples by ~1e-6 voxel; colour changes by slope × that",
            long_rays: false,
            run: rotated,
        },
        Case {
            no: 4,
            name: "translated-1e6",
            reference: "the same volume + horizon scene at the origin",
            tol: 1e-5,
            why: "translations cancel in f64 before rounding; 1e-5 is the suite's equality \
                  tolerance for float reassociation",
            long_rays: false,
            run: translated,
        },
    ]
}

/// A 8 m cube of 0.25 m voxels with a 0.75 m thick bright layer, at `origin`.
fn utm_scene(ctx: &Ctx, name: &str, origin: [f64; 3]) -> strata_common::scene::Scene {
    let store = volume(
        ctx,
        name,
        [32, 32, 32],
        scale_translate([0.25; 3], origin),
        32,
        |i, _, k| {
            if (12..=14).contains(&k) {
                1.0
            } else {
                0.2 * (i as f32 * 0.5).sin().abs()
            }
        },
    );
    let layer =
        strata_tests::scenes::volume_layer(store, "grey", [0.0, 1.0], vec![[0.0, 0.0], [1.0, 0.6]]);
    scene(
        vec![layer],
        vec![],
        camera(
            add(origin, [4.0, 3.0, -10.0]),
            add(origin, [4.0, 4.0, 4.0]),
            [0.0, 1.0, 0.0],
            40.0,
        ),
        settings(48, 40),
    )
}

fn utm_northing(ctx: &Ctx) -> Res<f64> {
    let far = ctx.render(&utm_scene(ctx, "utm", [431_250.0, 6_400_000.0, 1_500.0]))?;
    let near = ctx.render(&utm_scene(ctx, "origin", [0.0; 3]))?;
    shows(&near, 0.3, "the layer")?;
    diff(&far, &near)
}

fn far_camera(ctx: &Ctx) -> Res<f64> {
    let a = 0.05;
    let store = volume(ctx, "c", [32, 32, 32], Affine3::IDENTITY, 32, |_, _, _| 1.0);
    let s = scene(
        vec![grey(store, [0.0, 2.0], a)],
        vec![],
        camera([15.5, 15.5, -1e5], [15.5, 15.5, 0.0], [0.0, 1.0, 0.0], 0.01),
        settings(9, 9),
    );
    let img = ctx.render(&s)?;
    let n = lattice_count((1e5 - 0.5) as f32, (1e5 + 31.5) as f32, 1.0);
    let want = slab(a, 1.0, n);
    // grey at the middle of the window is 0.5 in linear light.
    Ok(img
        .iter()
        .map(|p| err4(*p, [0.5 * want, 0.5 * want, 0.5 * want, want]))
        .fold(0.0, f64::max))
}

fn rotated(ctx: &Ctx) -> Res<f64> {
    let (c, s) = (37.3f64.to_radians().cos(), 37.3f64.to_radians().sin());
    let t = [100.0, -50.0, 7.0];
    let rot = |p: [f64; 3]| {
        [
            c * p[0] - s * p[1] + t[0],
            s * p[0] + c * p[1] + t[1],
            p[2] + t[2],
        ]
    };
    let m = Affine3 {
        rows: [[c, -s, 0.0, t[0]], [s, c, 0.0, t[1]], [0.0, 0.0, 1.0, t[2]]],
    };
    let mk = |name: &str, m: Affine3, eye: [f64; 3], target: [f64; 3]| {
        let store = volume(ctx, name, [32, 32, 32], m, 32, smooth);
        scene(
            vec![seismic(store, [-1.0, 1.0])],
            vec![],
            camera(eye, target, [0.0, 0.0, 1.0], 40.0),
            settings(48, 40),
        )
    };
    let (eye, target) = ([-20.0, -35.0, 45.0], [15.5, 15.5, 15.5]);
    let plain = ctx.render(&mk("plain", Affine3::IDENTITY, eye, target))?;
    let turned = ctx.render(&mk("turned", m, rot(eye), rot(target)))?;
    shows(&plain, 0.2, "the volume")?;
    diff(&plain, &turned)
}

fn translated(ctx: &Ctx) -> Res<f64> {
    let mk = |name: &str, o: [f64; 3]| {
        let v = volume(
            ctx,
            &format!("{name}-v"),
            [32, 32, 32],
            scale_translate([1.0; 3], o),
            32,
            smooth,
        );
        let h = horizon(
            ctx,
            &format!("{name}-h"),
            [32, 32],
            scale_translate([1.0; 3], o),
            |i, j| {
                if (10..14).contains(&i) && (5..9).contains(&j) {
                    f32::NAN
                } else {
                    20.0 + 2.0 * (i as f32 * 0.3).sin() * (j as f32 * 0.2).cos()
                }
            },
        );
        let mut r = settings(48, 40);
        r.lighting = true;
        scene(
            vec![seismic(v, [-1.0, 1.0])],
            vec![strata_tests::scenes::horizon_layer(h, [0.9, 0.7, 0.2], 0.8)],
            camera(
                add(o, [-20.0, -30.0, 50.0]),
                add(o, [15.5, 15.5, 15.5]),
                [0.0, 0.0, 1.0],
                40.0,
            ),
            r,
        )
    };
    let a = ctx.render(&mk("origin", [0.0; 3]))?;
    let b = ctx.render(&mk("far", [1e6, 1e6, 1e6]))?;
    shows(&a, 0.5, "the scene")?;
    diff(&a, &b)
}
