//! Geometry: grazing rays, rays along brick faces, split planes and grid lines, cameras in
//! awkward places, horizons that touch, cross or coincide.

use crate::harness::*;
use crate::Case;
use strata_common::geo::Affine3;
use strata_common::scene::{HorizonLayer, Scene};
use strata_tests::scenes::horizon_layer;

pub fn cases() -> Vec<Case> {
    vec![
        Case {
            no: 5,
            name: "ray-grazing-a-horizon-1e-4-rad",
            reference: "analytic ray/plane hits: opaque where the hit lies on the grid, empty elsewhere",
            tol: 1e-6,
            why: "hit or miss is exact for an opaque unlit plane; pixels whose hit lies within half a \
                  cell of the grid's edge are left out",
            long_rays: false,
            run: grazing,
        },
        Case {
            no: 6,
            name: "rays-along-brick-faces-and-grid-lines",
            reference: "the same volume in 128-sample pages (one brick)",
            tol: 1e-6,
            why: "the sample lattice and trilinear taps do not depend on how the data is paged",
            long_rays: false,
            run: brick_faces,
        },
        Case {
            no: 7,
            name: "camera-on-a-split-plane",
            reference: "the whole scene rendered as one region (in process)",
            tol: 1e-5,
            why: "region clipping keeps every lattice sample and horizon hit in exactly one region; \
                  1e-5 allows float reassociation in compositing",
            long_rays: false,
            run: camera_on_split_plane,
        },
        Case {
            no: 8,
            name: "camera-inside-a-volume",
            reference: "analytic 1-(1-a)^n per pixel, n the lattice samples from the eye to the box exit",
            tol: 2e-5,
            why: "f32 rounding of up to 55 blend steps; pixels whose exit lies within 1e-3 of a \
                  lattice point are left out (their count is ambiguous)",
            long_rays: false,
            run: camera_inside_volume,
        },
        Case {
            no: 9,
            name: "camera-inside-a-horizon-hole",
            reference: "analytic: the holed horizon at the eye is never hit, the full one below is where \
                        the ray meets its grid",
            tol: 1e-6,
            why: "hit or miss is exact for opaque unlit planes",
            long_rays: false,
            run: camera_in_hole,
        },
        Case {
            no: 10,
            name: "coincident-horizons",
            reference: "analytic: alpha 1-(1-a1)(1-a2), colour of one consistent order",
            tol: 2e-6,
            why: "two blend steps in f32",
            long_rays: false,
            run: coincident,
        },
        Case {
            no: 11,
            name: "crossing-horizons",
            reference: "analytic: each pixel shows the plane its ray meets first",
            tol: 1e-6,
            why: "opaque unlit planes; pixels within 0.1 of the crossing are left out",
            long_rays: false,
            run: crossing,
        },
        Case {
            no: 12,
            name: "touching-horizons",
            reference: "analytic: a translucent plane over an opaque paraboloid touching it at one \
                        grid point",
            tol: 2e-6,
            why: "two blend steps in f32; at the touching point either order is right",
            long_rays: false,
            run: touching,
        },
        Case {
            no: 13,
            name: "horizon-in-a-split-plane",
            reference: "the whole scene rendered as one region (in process)",
            tol: 1e-5,
            why: "a hit exactly on a split plane belongs to one region only; a double or missing hit \
                  would differ by the horizon's opacity",
            long_rays: false,
            run: horizon_in_split_plane,
        },
    ]
}

/// Cases added after the suite's numbering reached the last group (numbered on).
pub fn later_cases() -> Vec<Case> {
    vec![Case {
        no: 36,
        name: "flat-horizon-5-km-below-the-eye",
        reference: "analytic: the plane z = 0 under a camera 5000 above it, straight down; \
                    inside the grid (0.5 in from its edge) the horizon's colour, outside nothing",
        tol: 1e-6,
        why: "an opaque unlit surface is its colour exactly; the tiles' boxes are padded by \
              8 ulps of the eye's height (their 1e-4 alone is under the rounding of 5000, so \
              each slab had no thickness in t and the horizon vanished), and a crossing on a \
              region face is kept by one region",
        long_rays: false,
        run: flat_far_below,
    }]
}

fn flat_far_below(ctx: &Ctx) -> Res<f64> {
    let h = flat(ctx, "sea-level", 32, 0.0, |_, _| false);
    let w = 33;
    // 32 nodes seen from 5000 fill about 0.4° of view.
    let s = scene(
        vec![],
        vec![solid(h, [0.2, 0.7, 0.4], 1.0)],
        camera(
            [15.5, 15.5, 5000.0],
            [15.5, 15.5, 0.0],
            [0.0, 1.0, 0.0],
            0.45,
        ),
        settings(w, w),
    );
    let img = ctx.render(&s)?;
    let (mut err, mut inside_px) = (0.0f64, 0);
    for y in 0..w {
        for x in 0..w {
            let Some((_, q)) = plane_hit(&s, x, y, 0.0) else {
                continue;
            };
            match inside(q, 32.0, 0.5) {
                Some(true) => {
                    inside_px += 1;
                    err = err.max(err4(at(&img, w, x, y), [0.2, 0.7, 0.4, 1.0]));
                }
                Some(false) => err = err.max(err4(at(&img, w, x, y), [0.0; 4])),
                None => {}
            }
        }
    }
    if inside_px < 500 {
        return Err(format!("{inside_px} pixels over the grid: mis-built"));
    }
    Ok(err)
}

/// A flat horizon of height `z` over a `n`×`n` grid (holes where `hole(i, j)`).
fn flat(
    ctx: &Ctx,
    name: &str,
    n: u64,
    z: f32,
    hole: impl Fn(u64, u64) -> bool,
) -> std::path::PathBuf {
    horizon(ctx, name, [n, n], Affine3::IDENTITY, |i, j| {
        if hole(i, j) {
            f32::NAN
        } else {
            z
        }
    })
}

fn solid(store: std::path::PathBuf, c: [f64; 3], opacity: f64) -> HorizonLayer {
    horizon_layer(store, c, opacity)
}

/// Where the ray of pixel (x, y) meets the plane z = h, if it does (t > 0).
fn plane_hit(s: &Scene, x: u32, y: u32, h: f64) -> Option<(f64, [f64; 3])> {
    let v = view(s);
    let d = dir(&v, x, y);
    let e = s.camera.as_ref().unwrap().eye;
    let t = (h - e[2]) / d[2];
    (t > 0.0 && t.is_finite()).then(|| (t, [e[0] + t * d[0], e[1] + t * d[1], h]))
}

/// Whether (x, y) lies on the grid `[0, n-1]²` more than `m` inside its edge.
fn inside(p: [f64; 3], n: f64, m: f64) -> Option<bool> {
    let i = p[0] > m && p[0] < n - 1.0 - m && p[1] > m && p[1] < n - 1.0 - m;
    let o = p[0] < -m || p[0] > n - 1.0 + m || p[1] < -m || p[1] > n - 1.0 + m;
    if i {
        Some(true)
    } else if o {
        Some(false)
    } else {
        None
    }
}

fn grazing(ctx: &Ctx) -> Res<f64> {
    let h = 10.3;
    let p = flat(ctx, "plane", 32, h as f32, |_, _| false);
    let th = 1e-4f64;
    let eye = [2.0, 15.5, h + 0.002];
    let target = [eye[0] + 20.0 * th.cos(), eye[1], eye[2] - 20.0 * th.sin()];
    let w = 33;
    let s = scene(
        vec![],
        vec![solid(p, [1.0, 1.0, 1.0], 1.0)],
        camera(eye, target, [0.0, 0.0, 1.0], 10.0),
        settings(w, w),
    );
    let img = ctx.render(&s)?;
    let mut err = 0.0f64;
    let mut grazing_hit = false;
    for y in 0..w {
        for x in 0..w {
            let want = match plane_hit(&s, x, y, h) {
                None => Some(false),
                Some((_, q)) => inside(q, 32.0, 0.5),
            };
            let Some(want) = want else { continue };
            let a = if want { 1.0 } else { 0.0 };
            err = err.max(err4(at(&img, w, x, y), [a, a, a, a]));
            grazing_hit |= want && x == w / 2 && y == w / 2;
        }
    }
    if !grazing_hit {
        return Err(
            "the centre ray (1e-4 rad) does not meet the grid: the case is mis-built".into(),
        );
    }
    Ok(err)
}

fn brick_faces(ctx: &Ctx) -> Res<f64> {
    let mk = |page: u32| {
        let store = smooth_volume(ctx, [64, 64, 64], page);
        // 32-sample pages with a border of 1 hold 30 samples: brick faces at x, y = 29.5/30.
        // The centre column of rays lies in the plane x = 29.5 (between samples, on a brick
        // face), the centre row in y = 30 (a grid plane and a brick's first sample).
        scene(
            vec![seismic(store, [-1.0, 1.0])],
            vec![],
            camera(
                [29.5, 30.0, -40.0],
                [29.5, 30.0, 63.0],
                [0.0, 1.0, 0.0],
                50.0,
            ),
            settings(33, 33),
        )
    };
    let a = ctx.render(&mk(32))?;
    let b = ctx.render(&mk(128))?;
    shows(&b, 0.2, "the volume")?;
    diff(&a, &b)
}

/// A volume and a wavy horizon over it, seen by `cam`.
fn volume_and_horizon(
    ctx: &Ctx,
    dims: [u64; 3],
    h_of: impl Fn(u64, u64) -> f32,
) -> (std::path::PathBuf, std::path::PathBuf) {
    let v = volume(ctx, "v", dims, Affine3::IDENTITY, 32, smooth);
    let h = horizon(ctx, "h", [dims[0], dims[1]], Affine3::IDENTITY, h_of);
    (v, h)
}

fn camera_on_split_plane(ctx: &Ctx) -> Res<f64> {
    let (v, h) = volume_and_horizon(ctx, [40, 32, 32], |i, j| {
        12.0 + 3.0 * (i as f32 * 0.2).sin() * (j as f32 * 0.25).cos()
    });
    let mk = |eye: [f64; 3], target: [f64; 3]| {
        let mut r = settings(48, 40);
        r.lighting = true;
        scene(
            vec![seismic(v.clone(), [-1.0, 1.0])],
            vec![solid(h.clone(), [0.8, 0.6, 0.3], 0.7)],
            camera(eye, target, [0.0, 0.0, 1.0], 45.0),
            r,
        )
    };
    let s0 = mk([-30.0, -30.0, 40.0], [20.0, 16.0, 16.0]);
    let tree = decomposition(&s0, WORKERS)?;
    let (axis, pos) = planes(&tree)[0];
    // Eye and target on the root split plane: rays of one image line lie in it.
    let (mut eye, mut target) = ([-30.0, -30.0, 40.0], [20.0, 16.0, 16.0]);
    eye[axis] = pos;
    target[axis] = pos;
    if axis == 2 {
        eye[0] = -40.0;
    }
    let s = mk(eye, target);
    let again = decomposition(&s, WORKERS)?;
    if again != tree {
        return Err("moving the camera changed the decomposition: the case is mis-built".into());
    }
    let whole = ctx.whole_reference(&s)?;
    let split = ctx.render_regions(&s, &tree)?;
    shows(&whole, 0.3, "the scene")?;
    diff(&whole, &split)
}

fn camera_inside_volume(ctx: &Ctx) -> Res<f64> {
    let a = 0.1;
    let store = volume(ctx, "c", [32, 32, 32], Affine3::IDENTITY, 32, |_, _, _| 1.0);
    let w = 33;
    let s = scene(
        vec![grey(store, [0.0, 2.0], a)],
        vec![],
        camera(
            [15.5, 15.5, 10.0],
            [15.5, 15.5, 40.0],
            [0.0, 1.0, 0.0],
            60.0,
        ),
        settings(w, w),
    );
    let img = ctx.render(&s)?;
    let v = view(&s);
    let e = s.camera.as_ref().unwrap().eye;
    let mut err = 0.0f64;
    for y in 0..w {
        for x in 0..w {
            let d = dir(&v, x, y);
            let t_exit = (0..3)
                .map(|k| {
                    let face = if d[k] > 0.0 { 31.5 } else { -0.5 };
                    if d[k] == 0.0 {
                        f64::INFINITY
                    } else {
                        (face - e[k]) / d[k]
                    }
                })
                .fold(f64::INFINITY, f64::min);
            if near_lattice(t_exit, 1.0, 1e-3) {
                continue;
            }
            let n = lattice_count(0.0, t_exit as f32, 1.0);
            let want = slab(a, 1.0, n);
            err = err.max(err4(
                at(&img, w, x, y),
                [0.5 * want, 0.5 * want, 0.5 * want, want],
            ));
        }
    }
    Ok(err)
}

fn camera_in_hole(ctx: &Ctx) -> Res<f64> {
    let top = flat(ctx, "top", 32, 10.0, |i, j| {
        (12..20).contains(&i) && (12..20).contains(&j)
    });
    let bottom = flat(ctx, "bottom", 32, 5.0, |_, _| false);
    let w = 33;
    let s = scene(
        vec![],
        vec![
            solid(top, [1.0, 0.0, 0.0], 1.0),
            solid(bottom, [0.0, 0.0, 1.0], 1.0),
        ],
        camera([15.5, 15.5, 10.0], [25.5, 15.5, 4.0], [0.0, 0.0, 1.0], 60.0),
        settings(w, w),
    );
    let img = ctx.render(&s)?;
    let mut err = 0.0f64;
    let mut hits = 0;
    for y in 0..w {
        for x in 0..w {
            let want = match plane_hit(&s, x, y, 5.0) {
                None => Some(false),
                Some((_, q)) => inside(q, 32.0, 0.5),
            };
            let Some(want) = want else { continue };
            hits += want as u32;
            let c = if want { [0.0, 0.0, 1.0, 1.0] } else { [0.0; 4] };
            err = err.max(err4(at(&img, w, x, y), c));
        }
    }
    if hits < 50 {
        return Err(format!(
            "only {hits} pixels should see the lower horizon: mis-built"
        ));
    }
    Ok(err)
}

fn top_down(w: u32, centre: [f64; 2]) -> strata_common::scene::Camera {
    let _ = w;
    camera(
        [centre[0], centre[1], 60.0],
        [centre[0], centre[1], 0.0],
        [0.0, 1.0, 0.0],
        30.0,
    )
}

fn coincident(ctx: &Ctx) -> Res<f64> {
    let a = flat(ctx, "a", 32, 10.3, |_, _| false);
    let b = flat(ctx, "b", 32, 10.3, |_, _| false);
    let w = 33;
    let s = scene(
        vec![],
        vec![
            solid(a, [1.0, 0.0, 0.0], 0.5),
            solid(b, [0.0, 0.0, 1.0], 0.5),
        ],
        top_down(w, [15.5, 15.5]),
        settings(w, w),
    );
    let img = ctx.render(&s)?;
    let red_first = [0.5, 0.0, 0.25, 0.75];
    let blue_first = [0.25, 0.0, 0.5, 0.75];
    let c = at(&img, w, w / 2, w / 2);
    let want = if err4(c, red_first) < err4(c, blue_first) {
        red_first
    } else {
        blue_first
    };
    let mut err = 0.0f64;
    for y in 0..w {
        for x in 0..w {
            let Some((_, q)) = plane_hit(&s, x, y, 10.3) else {
                continue;
            };
            match inside(q, 32.0, 0.5) {
                Some(true) => err = err.max(err4(at(&img, w, x, y), want)),
                Some(false) => err = err.max(err4(at(&img, w, x, y), [0.0; 4])),
                None => {}
            }
        }
    }
    Ok(err)
}

fn crossing(ctx: &Ctx) -> Res<f64> {
    let a = flat(ctx, "a", 32, 10.3, |_, _| false);
    let b = horizon(ctx, "b", [32, 32], Affine3::IDENTITY, |i, _| {
        5.0 + 0.4 * i as f32
    });
    let w = 33;
    let s = scene(
        vec![],
        vec![
            solid(a, [1.0, 0.0, 0.0], 1.0),
            solid(b, [0.0, 0.0, 1.0], 1.0),
        ],
        top_down(w, [15.5, 15.5]),
        settings(w, w),
    );
    let img = ctx.render(&s)?;
    let v = view(&s);
    let e = s.camera.as_ref().unwrap().eye;
    let mut err = 0.0f64;
    let (mut red, mut blue) = (0, 0);
    for y in 0..w {
        for x in 0..w {
            let d = dir(&v, x, y);
            let ta = (10.3 - e[2]) / d[2];
            // z = 5 + 0.4 x along the ray.
            let tb = (5.0 + 0.4 * e[0] - e[2]) / (d[2] - 0.4 * d[0]);
            let pa = [e[0] + ta * d[0], e[1] + ta * d[1], 0.0];
            let pb = [e[0] + tb * d[0], e[1] + tb * d[1], 0.0];
            if (ta - tb).abs() < 0.1 {
                continue;
            }
            let (Some(ia), Some(ib)) = (inside(pa, 32.0, 0.5), inside(pb, 32.0, 0.5)) else {
                continue;
            };
            let want = if ia && (!ib || ta < tb) {
                red += 1;
                [1.0, 0.0, 0.0, 1.0]
            } else if ib {
                blue += 1;
                [0.0, 0.0, 1.0, 1.0]
            } else {
                [0.0; 4]
            };
            err = err.max(err4(at(&img, w, x, y), want));
        }
    }
    if red < 20 || blue < 20 {
        return Err(format!(
            "{red} red and {blue} blue pixels expected: mis-built"
        ));
    }
    Ok(err)
}

fn touching(ctx: &Ctx) -> Res<f64> {
    let top = flat(ctx, "top", 32, 10.0, |_, _| false);
    let bowl = horizon(ctx, "bowl", [32, 32], Affine3::IDENTITY, |i, j| {
        let (x, y) = (i as f32 - 16.0, j as f32 - 16.0);
        10.0 - (x * x + y * y) / 40.0
    });
    let w = 33;
    let s = scene(
        vec![],
        vec![
            solid(top, [1.0, 0.0, 0.0], 0.5),
            solid(bowl, [0.0, 0.0, 1.0], 1.0),
        ],
        top_down(w, [16.0, 16.0]),
        settings(w, w),
    );
    let img = ctx.render(&s)?;
    let mut err = 0.0f64;
    for y in 0..w {
        for x in 0..w {
            let Some((_, q)) = plane_hit(&s, x, y, 10.0) else {
                continue;
            };
            // Far enough inside that the ray meets the bowl on the grid too.
            if inside(q, 32.0, 4.0) != Some(true) {
                continue;
            }
            let p = at(&img, w, x, y);
            let over = [0.5, 0.0, 0.5, 1.0];
            let e = if x == w / 2 && y == w / 2 {
                // The touching point: the hits tie, either order is right.
                err4(p, over).min(err4(p, [0.0, 0.0, 1.0, 1.0]))
            } else {
                err4(p, over)
            };
            err = err.max(e);
        }
    }
    Ok(err)
}

fn horizon_in_split_plane(ctx: &Ctx) -> Res<f64> {
    // Four bricks deep, so that the coordinator's split across z snaps to a brick face (an
    // f32 the horizon can lie on exactly): with two, each brick is more than a split's
    // snapping allows, and the plane goes through one.
    let v = volume(ctx, "v", [16, 16, 120], Affine3::IDENTITY, 32, smooth);
    let mk = |h: f32| {
        let p = flat(ctx, &format!("h{h}"), 16, h, |_, _| false);
        let mut r = settings(48, 40);
        r.lighting = true;
        scene(
            vec![seismic(v.clone(), [-1.0, 1.0])],
            vec![solid(p, [0.9, 0.8, 0.2], 0.6)],
            camera(
                [-25.0, -20.0, 96.0],
                [7.5, 7.5, 59.5],
                [0.0, 0.0, 1.0],
                45.0,
            ),
            r,
        )
    };
    // Put the horizon on the coordinator's split across z, then check the split stayed.
    let tree0 = decomposition(&mk(20.0), WORKERS)?;
    let Some(&(_, z)) = planes(&tree0).iter().find(|p| p.0 == 2) else {
        return Err(format!(
            "no split across z in {:?}: mis-built",
            planes(&tree0)
        ));
    };
    let s = mk(z as f32);
    let tree = decomposition(&s, WORKERS)?;
    if !planes(&tree).contains(&(2, z)) || z as f32 as f64 != z {
        return Err(format!(
            "the horizon at z = {z} is not on a split plane of {:?}",
            planes(&tree)
        ));
    }
    let whole = ctx.whole_reference(&s)?;
    let split = ctx.render_regions(&s, &tree)?;
    shows(&whole, 0.5, "the scene")?;
    diff(&whole, &split)
}
