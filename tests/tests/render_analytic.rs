//! The ray caster against analytic references and hard cases: every scene renders on the
//! CPU and, where a wgpu adapter exists (lavapipe in CI), on the GPU too, and the two images
//! agree within 1e-4.

use strata_common::geo::Affine3;
use strata_common::scene::Camera;
use strata_tests::scenes::*;
use tempfile::TempDir;

const N: u64 = 32;
const W: u32 = 65; // odd, so the centre pixel's ray is the optical axis

fn constant_volume(dir: &std::path::Path, value: f32) -> std::path::PathBuf {
    volume_store(
        dir,
        "const",
        [N, N, N],
        vec![value; (N * N * N) as usize],
        Affine3::IDENTITY,
        32,
    )
}

/// A grey volume over the window [0, 2] whose transfer function has the constant opacity
/// `a` (per unit step, before opacity correction).
fn grey_alpha(store: std::path::PathBuf, a: f64) -> strata_common::scene::VolumeLayer {
    volume_layer(store, "grey", [0.0, 2.0], vec![[0.0, a], [1.0, a]])
}

fn axis_camera(eye: [f64; 3], target: [f64; 3]) -> Camera {
    Camera {
        eye,
        target,
        up: [0.0, 1.0, 0.0],
        fov_deg: 35.0,
    }
}

fn centre(px: &[[f32; 4]]) -> [f32; 4] {
    px[(W / 2 * W + W / 2) as usize]
}

/// grey colour map at the middle of its window (value 1 of [0, 2]). Colour maps are
/// interpolated in linear light between their (sRGB-given) control points, and grey's are
/// black and white.
fn grey_mid() -> f32 {
    0.5
}

#[test]
fn homogeneous_slab_transmittance_for_many_steps() {
    let dir = TempDir::new().unwrap();
    let store = constant_volume(dir.path(), 1.0);
    let a = 0.05f64;
    for &step in &[0.01f64, 0.25, 1.0, 3.7, 50.0] {
        let mut r = exact_settings(W, W);
        r.adaptive_step = false;
        r.step = step;
        let s = scene(
            vec![grey_alpha(store.clone(), a)],
            vec![],
            axis_camera([15.5, 15.5, -50.0], [15.5, 15.5, 0.0]),
            r,
        );
        let px = render_on_both(&s, 1e-4, "homogeneous slab transmittance for many steps");
        assert_clean(&px);
        let c = centre(&px);
        // Box faces at -0.5 and 31.5: the ray is inside for t in [49.5, 81.5).
        let n = lattice_count(49.5, 81.5, step as f32);
        let want = 1.0 - (1.0 - a).powf(step * n as f64);
        assert!(
            (c[3] as f64 - want).abs() < 2e-5,
            "step {step}: alpha {} want {want} ({n} samples)",
            c[3]
        );
        // Constant colour: premultiplied colour = colour · alpha.
        assert!((c[0] - grey_mid() * c[3]).abs() < 2e-5, "{c:?}");
        // Opacity correction makes the result converge to the continuous slab 1-(1-a)^L as
        // the step shrinks. Coarser steps (3.7, 50) sample the slab at lattice points whose
        // count times the step is not its length: the assertion above holds them to the
        // lattice's exact value instead.
        if step <= 1.0 {
            let exact = 1.0 - (1.0 - a).powf(32.0);
            let tol = if step < 1.0 { 1.5e-3 } else { 0.051 };
            assert!((c[3] as f64 - exact).abs() < tol, "step {step}");
        }
    }
}

#[test]
fn adaptive_bands_keep_the_optical_depth() {
    // Far away and tiny image: the ray crosses coarse bands (step 2^b); the corrected
    // opacity keeps transmittance near the continuous value.
    let dir = TempDir::new().unwrap();
    let store = constant_volume(dir.path(), 1.0);
    let a = 0.05f64;
    let mut r = exact_settings(9, 9);
    r.adaptive_step = true;
    let s = scene(
        vec![grey_alpha(store, a)],
        vec![],
        axis_camera([15.5, 15.5, -200.0], [15.5, 15.5, 0.0]),
        r,
    );
    let px = render_on_both(&s, 1e-4, "adaptive bands keep the optical depth");
    assert_clean(&px);
    let c = px[(4 * 9 + 4) as usize];
    let exact = 1.0 - (1.0 - a).powf(32.0);
    // At t≈200 the band step is 8 voxels: at most one band step of optical depth off.
    let lo = 1.0 - (1.0 - a).powf(32.0 - 8.0);
    let hi = 1.0 - (1.0 - a).powf(32.0 + 8.0);
    assert!(
        c[3] as f64 > lo && (c[3] as f64) < hi,
        "alpha {} vs {exact}",
        c[3]
    );
}

#[test]
fn linear_ramp_is_sampled_exactly() {
    // v = z (index), grey map over [0, 31]; tiny constant alpha, so the colour is the
    // transmittance-weighted sum of the ramp values at the lattice points.
    let dir = TempDir::new().unwrap();
    let data: Vec<f32> = (0..N * N * N).map(|i| (i / (N * N)) as f32).collect();
    let store = volume_store(dir.path(), "ramp", [N, N, N], data, Affine3::IDENTITY, 32);
    let a = 0.01f64;
    let mut r = exact_settings(W, W);
    r.adaptive_step = false;
    r.step = 0.5;
    let s = scene(
        vec![volume_layer(
            store,
            "grey",
            [0.0, 31.0],
            vec![[0.0, a], [1.0, a]],
        )],
        vec![],
        axis_camera([16.0, 16.0, -40.0], [16.0, 16.0, 0.0]),
        r,
    );
    let px = render_on_both(&s, 1e-4, "linear ramp is sampled exactly");
    let c = centre(&px);
    // Reference: z = t - 40, clamped to the data range [0, 31] by edge replication.
    let (mut acc, mut al) = (0.0f64, 0.0f64);
    let mut k = 0i64;
    loop {
        let t = k as f32 * 0.5;
        k += 1;
        if t < 39.5 {
            continue;
        }
        if t >= 71.5 {
            break;
        }
        let z = (t as f64 - 40.0).clamp(0.0, 31.0);
        // The grey map is linear (in linear light) between black and white.
        let col = z / 31.0;
        // Opacity corrected for a step of half the reference voxel.
        let ac = 1.0 - (1.0 - a).powf(0.5);
        acc += (1.0 - al) * ac * col;
        al += (1.0 - al) * ac;
    }
    assert!((c[3] as f64 - al).abs() < 1e-5, "{} vs {al}", c[3]);
    assert!((c[0] as f64 - acc).abs() < 1e-5, "{} vs {acc}", c[0]);
}

fn plane(
    dir: &std::path::Path,
    name: &str,
    n: u64,
    f: impl Fn(u64, u64) -> f32,
) -> std::path::PathBuf {
    let h: Vec<f32> = (0..n * n).map(|i| f(i % n, i / n)).collect();
    horizon_store(dir, name, [n, n], h, Affine3::IDENTITY, 16)
}

#[test]
fn opaque_plane_behind_translucent_fog() {
    let dir = TempDir::new().unwrap();
    let fog = constant_volume(dir.path(), 1.0);
    let p = plane(dir.path(), "plane", N, |_, _| 20.3);
    let a = 0.03f64;
    let mut r = exact_settings(W, W);
    r.adaptive_step = false;
    r.lighting = false;
    let s = scene(
        vec![grey_alpha(fog, a)],
        vec![horizon_layer(p, [1.0, 0.0, 0.0], 1.0)],
        axis_camera([15.5, 15.5, 100.0], [15.5, 15.5, 0.0]),
        r,
    );
    let px = render_on_both(&s, 1e-4, "opaque plane behind translucent fog");
    assert_clean(&px);
    let c = centre(&px);
    // Enters the fog at z = 31.5 (t = 68.5), hits the plane at z = 20.3 (t = 79.7).
    let n = lattice_count(68.5, 79.7, 1.0);
    let af = 1.0 - (1.0 - a).powi(n as i32);
    let g = grey_mid() as f64;
    let want = [g * af + (1.0 - af), g * af, g * af, 1.0];
    for k in 0..4 {
        assert!((c[k] as f64 - want[k]).abs() < 2e-5, "{c:?} vs {want:?}");
    }
}

#[test]
fn camera_inside_a_volume_and_saturating_alpha() {
    let dir = TempDir::new().unwrap();
    let store = constant_volume(dir.path(), 1.0);
    let a = 0.1f64;
    let mut r = exact_settings(W, W);
    r.adaptive_step = false;
    let s = scene(
        vec![grey_alpha(store.clone(), a)],
        vec![],
        axis_camera([15.5, 15.5, 10.0], [15.5, 15.5, 40.0]),
        r.clone(),
    );
    let px = render_on_both(&s, 1e-4, "camera inside a volume and saturating alpha");
    assert_clean(&px);
    let n = lattice_count(0.0, 21.5, 1.0);
    assert_eq!(n, 22);
    let want = 1.0 - (1.0 - a).powi(22);
    assert!((centre(&px)[3] as f64 - want).abs() < 2e-5);

    // Alpha 1 per sample: exactly opaque, colour exactly the map colour, nothing above 1.
    let s = scene(
        vec![volume_layer(
            store,
            "grey",
            [0.0, 2.0],
            vec![[0.0, 1.0], [1.0, 1.0]],
        )],
        vec![],
        axis_camera([15.5, 15.5, -50.0], [15.5, 15.5, 0.0]),
        r,
    );
    let px = render_on_both(&s, 1e-4, "camera inside a volume and saturating alpha");
    assert_clean(&px);
    let c = centre(&px);
    assert_eq!(c[3], 1.0);
    assert!((c[0] - grey_mid()).abs() < 1e-6);
}

#[test]
fn nan_samples_are_transparent() {
    let dir = TempDir::new().unwrap();
    let data: Vec<f32> = (0..N * N * N)
        .map(|i| if i / (N * N) < 16 { f32::NAN } else { 1.0 })
        .collect();
    let store = volume_store(dir.path(), "nan", [N, N, N], data, Affine3::IDENTITY, 32);
    let a = 0.05f64;
    let mut r = exact_settings(W, W);
    r.adaptive_step = false;
    let s = scene(
        vec![grey_alpha(store, a)],
        vec![],
        axis_camera([15.5, 15.5, -50.0], [15.5, 15.5, 0.0]),
        r,
    );
    let px = render_on_both(&s, 1e-4, "nan samples are transparent");
    assert_clean(&px);
    // Samples whose trilinear footprint touches z < 16 are NaN and skipped: z in [16, 31.5).
    let n = lattice_count(66.0, 81.5, 1.0);
    let want = 1.0 - (1.0 - a).powi(n as i32);
    assert!(
        (centre(&px)[3] as f64 - want).abs() < 2e-5,
        "{:?} {want}",
        centre(&px)
    );
}

/// A horizon's `color` is linear RGB, as `render.background` is: unlit and opaque, the
/// surface's pixel is that colour exactly (it had been decoded as gamma 2.2, so 0.5 came out
/// as 0.218).
#[test]
fn a_constant_horizon_colour_is_linear_rgb() {
    let dir = TempDir::new().unwrap();
    let p = plane(dir.path(), "plane", N, |_, _| 12.0);
    let mut r = exact_settings(W, W);
    r.lighting = false;
    let colour = [0.5, 0.25, 0.8];
    let s = scene(
        vec![],
        vec![horizon_layer(p, colour, 1.0)],
        axis_camera([15.5, 15.5, 100.0], [15.5, 15.5, 0.0]),
        r,
    );
    let px = render_on_both(&s, 1e-6, "a constant horizon colour");
    let c = centre(&px);
    for k in 0..3 {
        assert!(
            (c[k] as f64 - colour[k]).abs() < 1e-6,
            "{c:?} vs {colour:?}"
        );
    }
    assert_eq!(c[3], 1.0);
}

/// Top-down view of horizons over a 32×32 grid.
fn top_down(w: u32) -> Camera {
    let _ = w;
    axis_camera([15.5, 15.5, 60.0], [15.5, 15.5, 0.0])
}

/// Where the ray of pixel (x, y) of a top-down `W`×`W` view meets the plane z = h.
fn hit_xy(px: u32, py: u32, h: f64) -> [f64; 2] {
    let tan = (35.0f64.to_radians() / 2.0).tan();
    let sx = (2.0 * (px as f64 + 0.5) / W as f64 - 1.0) * tan;
    let sy = (1.0 - 2.0 * (py as f64 + 0.5) / W as f64) * tan;
    // Looking down -z with up = +y: right = forward × up = (0,0,-1)×(0,1,0) = (1,0,0).
    let d = 60.0 - h;
    [15.5 + sx * d, 15.5 + sy * d]
}

#[test]
fn holes_never_hit_and_leave_no_cracks() {
    let dir = TempDir::new().unwrap();
    // A wavy surface with a rectangular hole; tiles of 16 (12 core) put tile borders at 12, 24.
    let p = plane(dir.path(), "holey", N, |i, j| {
        if (8..14).contains(&i) && (18..25).contains(&j) {
            f32::NAN
        } else {
            10.0 + 0.7 * (i as f32 * 0.4).sin() + 0.5 * (j as f32 * 0.3).cos()
        }
    });
    let mut r = exact_settings(W, W);
    r.lighting = false;
    let s = scene(
        vec![],
        vec![horizon_layer(p, [0.0, 1.0, 0.0], 1.0)],
        top_down(W),
        r,
    );
    let px = render_on_both(&s, 1e-4, "holes never hit and leave no cracks");
    assert_clean(&px);
    let mut checked_in = 0;
    let mut checked_hole = 0;
    for y in 0..W {
        for x in 0..W {
            let q = hit_xy(x, y, 10.0);
            let a = px[(y * W + x) as usize][3];
            // Cells [i, i+1]: a cell is valid if all four nodes are; allow a margin of one
            // cell (the surface is not exactly at 10).
            let inside = q[0] > 1.5 && q[0] < 29.5 && q[1] > 1.5 && q[1] < 29.5;
            let near_hole = q[0] > 5.5 && q[0] < 15.5 && q[1] > 15.5 && q[1] < 26.5;
            let in_hole = q[0] > 9.0 && q[0] < 12.0 && q[1] > 19.0 && q[1] < 23.0;
            if inside && !near_hole {
                assert_eq!(a, 1.0, "crack at pixel ({x}, {y}) over {q:?}");
                checked_in += 1;
            }
            if in_hole {
                assert_eq!(a, 0.0, "hit inside the hole at pixel ({x}, {y}) over {q:?}");
                checked_hole += 1;
            }
        }
    }
    assert!(
        checked_in > 1000 && checked_hole > 10,
        "{checked_in} {checked_hole}"
    );
}

#[test]
fn crossing_horizons_show_the_nearer_surface() {
    let dir = TempDir::new().unwrap();
    let a = plane(dir.path(), "flat", N, |_, _| 10.0);
    let b = plane(dir.path(), "tilted", N, |i, _| 5.0 + 0.5 * i as f32); // crosses at i = 10
    let touch = plane(dir.path(), "touch", N, |_, _| 10.0); // coincides with `flat`
    let mut r = exact_settings(W, W);
    r.lighting = false;
    let s = scene(
        vec![],
        vec![
            horizon_layer(a, [1.0, 0.0, 0.0], 1.0),
            horizon_layer(b, [0.0, 0.0, 1.0], 1.0),
            horizon_layer(touch, [1.0, 0.0, 0.0], 1.0),
        ],
        top_down(W),
        r,
    );
    let px = render_on_both(&s, 1e-4, "crossing horizons show the nearer surface");
    assert_clean(&px);
    let mut n = 0;
    for y in 0..W {
        for x in 0..W {
            let q = hit_xy(x, y, 10.0);
            if !(q[0] > 1.0 && q[0] < 30.0 && q[1] > 1.0 && q[1] < 30.0)
                || (q[0] - 10.0).abs() < 2.0
            {
                continue;
            }
            let p = px[(y * W + x) as usize];
            // Seen from above the higher surface is nearer: flat (red) where i < 10.
            let want = if q[0] < 10.0 {
                [1.0, 0.0, 0.0, 1.0]
            } else {
                [0.0, 0.0, 1.0, 1.0]
            };
            assert_eq!(p, want, "pixel ({x}, {y}) over {q:?}");
            n += 1;
        }
    }
    assert!(n > 1000);
}

#[test]
fn grazing_rays_on_a_plane() {
    let dir = TempDir::new().unwrap();
    let n = 128u64;
    let p = plane(dir.path(), "flat", n, |_, _| 10.0);
    let mut r = exact_settings(97, 33);
    r.lighting = false;
    // Eye half a unit above the plane, looking along it: rays meet it at grazing angles.
    let cam = Camera {
        eye: [-5.0, 63.5, 10.5],
        target: [200.0, 63.5, 10.0],
        up: [0.0, 0.0, 1.0],
        fov_deg: 30.0,
    };
    let s = scene(
        vec![],
        vec![horizon_layer(p, [0.0, 1.0, 0.0], 1.0)],
        cam.clone(),
        r,
    );
    let px = render_on_both(&s, 1e-4, "grazing rays on a plane");
    assert_clean(&px);
    // Analytic: the ray hits z = 10 at distance 0.5/(-dz); it counts if that lands on the grid.
    let view = strata_common::camera::View::new(&cam, &s.render, 97, 33).unwrap();
    let mut hits = 0;
    for y in 0..33 {
        for x in 0..97 {
            let d = view.ray_dir(x, y);
            let a = px[(y * 97 + x) as usize][3];
            if d[2] >= -1e-6 {
                assert_eq!(a, 0.0, "pixel ({x},{y}) looks up but hit");
                continue;
            }
            let t = 0.5 / -(d[2] as f64);
            let q = [-5.0 + t * d[0] as f64, 63.5 + t * d[1] as f64];
            let inside = q[0] > 0.5 && q[0] < 126.5 && q[1] > 0.5 && q[1] < 126.5;
            let outside = q[0] < -0.5 || q[0] > 127.5 || q[1] < -0.5 || q[1] > 127.5;
            if inside {
                assert_eq!(a, 1.0, "pixel ({x},{y}) missed the plane at {q:?}");
                hits += 1;
            } else if outside {
                assert_eq!(a, 0.0, "pixel ({x},{y}) hit outside the grid at {q:?}");
            }
        }
    }
    assert!(hits > 300, "{hits}");
}

#[test]
fn utm_survey_renders_like_the_same_survey_at_the_origin() {
    let dir = TempDir::new().unwrap();
    let data: Vec<f32> = (0..N * N * N)
        .map(|i| {
            let (x, y, z) = (i % N, i / N % N, i / (N * N));
            ((x as f32 * 0.3).sin() + (y as f32 * 0.2).cos()) * (z as f32 * 0.25).sin()
        })
        .collect();
    let off = [605_000.25, 6_075_000.75, 1500.0];
    let make = |name: &str, o: [f64; 3]| {
        let t = Affine3 {
            rows: [
                [25.0 * 0.956, -25.0 * 0.292, 0.0, o[0]],
                [25.0 * 0.292, 25.0 * 0.956, 0.0, o[1]],
                [0.0, 0.0, 4.0, o[2]],
            ],
        };
        let v = volume_store(dir.path(), name, [N, N, N], data.clone(), t, 32);
        let h = horizon_store(
            dir.path(),
            &format!("{name}_h"),
            [N, N],
            (0..N * N).map(|i| 40.0 + (i % N) as f32 * 0.5).collect(),
            Affine3 {
                rows: [
                    [25.0 * 0.956, -25.0 * 0.292, 0.0, o[0]],
                    [25.0 * 0.292, 25.0 * 0.956, 0.0, o[1]],
                    [0.0, 0.0, 4.0, o[2]],
                ],
            },
            16,
        );
        let cam = Camera {
            eye: [o[0] - 500.0, o[1] - 700.0, o[2] + 400.0],
            target: [o[0] + 400.0, o[1] + 400.0, o[2] + 64.0],
            up: [0.0, 0.0, 1.0],
            fov_deg: 40.0,
        };
        let mut r = exact_settings(48, 32);
        r.z_down = true;
        scene(
            vec![volume_layer(
                v,
                "seismic",
                [-2.0, 2.0],
                vec![[0.0, 0.3], [0.5, 0.0], [1.0, 0.3]],
            )],
            vec![horizon_layer(h, [0.9, 0.8, 0.3], 0.7)],
            cam,
            r,
        )
    };
    let utm = render_on_both(
        &make("utm", off),
        1e-4,
        "utm survey renders like the same survey at the origin",
    );
    let origin = render_whole(&make("origin", [0.0; 3]));
    assert_clean(&utm);
    let d = max_diff(&utm, &origin);
    assert!(d < 1e-3, "max difference {d}");
    assert!(
        utm.iter().filter(|p| p[3] > 0.1).count() > 200,
        "the view shows the data"
    );
}

#[test]
fn seismic_default_window_is_symmetric_and_clips_at_the_99_5th_percentile() {
    let dir = TempDir::new().unwrap();
    let out = strata_coordinator::synth::synth(
        dir.path(),
        [96, 80, 48],
        7,
        false,
        &indicatif::ProgressBar::hidden(),
    )
    .unwrap();
    let scene = strata_common::scene::Scene::parse(
        &out.scene,
        &std::fs::read_to_string(&out.scene).unwrap(),
    )
    .unwrap();
    let layer = &scene.volumes[0];
    assert_eq!((layer.colormap.as_str(), layer.window), ("seismic", None));
    let v = strata_worker::dataset::Volume::open(layer, 0).unwrap();
    let range = v.store.header().value_range;
    // White exactly at zero: the window is symmetric.
    assert!(
        v.tf.lo < 0.0 && (v.tf.lo + v.tf.hi).abs() < 1e-6 * v.tf.hi,
        "{} {}",
        v.tf.lo,
        v.tf.hi
    );
    // Clipped inside the amplitude range at the 99.5th percentile of |amplitude| over every
    // level-0 sample, as ingest stored it.
    assert!(
        (v.tf.hi as f64) < range[0].abs().max(range[1]),
        "{} vs {range:?}",
        v.tf.hi
    );
    let stored = v
        .store
        .header()
        .stats
        .as_ref()
        .unwrap()
        .abs_percentile(99.5)
        .unwrap();
    assert_eq!(v.tf.hi as f64, stored as f32 as f64);
    let all = strata_tests::level_grid(&v.store, 0).unwrap();
    let inside = all.iter().filter(|s| s.abs() <= v.tf.hi).count();
    let frac = inside as f64 / all.len() as f64;
    assert!((0.993..0.9999).contains(&frac), "{frac}");
    // An explicit window is kept as given.
    let mut set = layer.clone();
    set.window = Some([-5.0, 7.0]);
    let v = strata_worker::dataset::Volume::open(&set, 0).unwrap();
    assert_eq!((v.tf.lo, v.tf.hi), (-5.0, 7.0));
}

#[test]
fn empty_space_skipping_changes_samples_not_pixels() {
    let dir = TempDir::new().unwrap();
    // 64³ in 32³ bricks (cores of 30): zero up to z = 30, the border of the lowest bricks,
    // and 100 above, so the lowest bricks are transparent and skipped whole, and the first
    // samples past their exit can already be visible.
    let n = 64u64;
    let data: Vec<f32> = (0..n * n * n)
        .map(|i| if i / (n * n) <= 30 { 0.0 } else { 100.0 })
        .collect();
    let store = volume_store(dir.path(), "step", [n, n, n], data, Affine3::IDENTITY, 32);
    let mut r = exact_settings(W, W);
    r.adaptive_step = false;
    let s = scene(
        vec![volume_layer(
            store,
            "viridis",
            [0.0, 100.0],
            vec![[0.0, 0.0], [0.05, 0.2], [1.0, 0.2]],
        )],
        vec![],
        axis_camera([5.5, 9.5, -60.0], [31.5, 35.5, 40.0]),
        r,
    );
    let run = |skipping: bool| {
        let mut s = s.clone();
        s.render.empty_space_skipping = skipping;
        let px = render_on_both(&s, 1e-4, &format!("skipping {skipping}"));
        let mut e = strata_worker::engine::Engine::new(&s).unwrap();
        let view = e.view(W, W).unwrap();
        let region = e.scene_region();
        (px, e.render_batch(&view, &region).unwrap().last)
    };
    let (on, stats_on) = run(true);
    let (off, stats_off) = run(false);
    assert_clean(&on);
    assert!(
        on.iter().filter(|p| p[3] > 0.01).count() > 100,
        "the view shows the data"
    );
    let d = max_diff(&on, &off);
    assert!(d <= 1e-6, "skipping on and off differ by {d}");
    assert!(
        stats_on.skipped > 0 && stats_on.samples < stats_off.samples,
        "on: {stats_on:?}, off: {stats_off:?}"
    );
}

/// `render.f64_accumulation` (the accuracy study's reference): 10⁵ blend steps of α = 10⁻⁶
/// each (hard case 15's ray) accumulated in f64 land on the analytic 1 − (1 − α)ⁿ to f32
/// rounding of the result (measured 3.2·10⁻⁹), where the f32 sum drifts by its rounding
/// per step (5.2·10⁻⁶); on an ordinary frame the two agree to f32 rounding. The GPU caster refuses
/// it (`gpu`) or leaves it to the CPU (`auto`).
#[test]
fn f64_accumulation_keeps_many_tiny_steps_exact() {
    let dir = TempDir::new().unwrap();
    let store = volume_store(
        dir.path(),
        "long",
        [4, 4, 1000],
        vec![1.0; 4 * 4 * 1000],
        Affine3::IDENTITY,
        32,
    );
    let step = 0.01;
    // Per voxel the α that makes 10⁻⁶ per sample at this step.
    let a = 1.0 - (1.0f64 - 1e-6).powf(1.0 / step);
    let mut r = exact_settings(3, 3);
    r.adaptive_step = false;
    r.lighting = false;
    r.tau = 1e-6;
    r.step = step;
    r.backend = strata_common::scene::Backend::Cpu;
    let s = scene(
        vec![grey_alpha(store, a)],
        vec![],
        Camera {
            eye: [1.5, 1.5, -10.0],
            target: [1.5, 1.5, 90.0],
            up: [0.0, 1.0, 0.0],
            fov_deg: 1.0,
        },
        r,
    );
    let n = lattice_count(9.5, 1009.5, step as f32);
    assert!((99_000..=101_000).contains(&n), "{n} samples: mis-built");
    // The transfer function holds α in f32.
    let want = 1.0 - (1.0 - a as f32 as f64).powf(step * n as f64);
    let err = |img: &[[f32; 4]]| {
        let c = img[4];
        (0..4)
            .map(|i| {
                let w = if i == 3 { want } else { 0.5 * want };
                (c[i] as f64 - w).abs()
            })
            .fold(0.0, f64::max)
    };
    let e32 = err(&render_whole(&s));
    let mut s64 = s.clone();
    s64.render.f64_accumulation = true;
    let e64 = err(&render_whole(&s64));
    // f32 rounding of the result (alpha ≈ 0.095) is 4·10⁻⁹; the step table's α per sample
    // is f32 too (relative 6·10⁻⁸, 6·10⁻⁹ over the ray).
    assert!(
        e64 < 5e-8,
        "f64 accumulation: {e64:.2e} from the analytic {want}"
    );
    assert!(
        e32 > 5.0 * e64,
        "f32 accumulation {e32:.2e} should drift further than f64 {e64:.2e}"
    );

    // An ordinary frame: the same image to f32 rounding.
    let store = constant_volume(dir.path(), 1.0);
    let mut r = exact_settings(W, W);
    r.backend = strata_common::scene::Backend::Cpu;
    let s = scene(
        vec![volume_layer(
            store,
            "seismic",
            [0.0, 2.0],
            vec![[0.0, 0.3], [1.0, 0.05]],
        )],
        vec![],
        axis_camera([-20.0, 8.0, -40.0], [15.5, 15.5, 15.5]),
        r,
    );
    let a32 = render_whole(&s);
    let mut s64 = s.clone();
    s64.render.f64_accumulation = true;
    let a64 = render_whole(&s64);
    let d = max_diff(&a32, &a64);
    assert!(
        d < 1e-5 && a32.iter().any(|p| p[3] > 0.5),
        "f32 and f64 differ by {d}"
    );

    // The GPU caster accumulates in f32: `gpu` refuses, `auto` takes the CPU.
    s64.render.backend = strata_common::scene::Backend::Gpu;
    let e = strata_worker::engine::Engine::new(&s64)
        .err()
        .expect("refused");
    assert!(format!("{e:#}").contains("f64_accumulation"), "{e:#}");
    s64.render.backend = strata_common::scene::Backend::Auto;
    let e = strata_worker::engine::Engine::new(&s64).unwrap();
    assert!(e.backend_name().starts_with("cpu"), "{}", e.backend_name());
}

/// Gradient shading against its closed form. In a linear ramp (values growing along x
/// only) every sample's gradient points along x, at every level of detail, so a ray's
/// samples all take the same headlight Blinn-Phong factors: `L0 = 0.3 + 0.6·|cos θ|` on the
/// colour and `L1 = 0.25·|cos θ|^24` per unit of opacity, θ between the ray and x. Front to
/// back, `Σ Tᵢ αᵢ (cᵢ L0 + L1) = L0·C + L1·A`: the shaded pixel is the unshaded pixel's
/// colour times L0 plus its alpha times L1, whatever the transfer function, and its alpha is
/// unchanged. The oblique view sweeps θ over the image, a near-axis ray included.
#[test]
fn gradient_shading_of_a_linear_ramp_matches_its_closed_form() {
    let dir = TempDir::new().unwrap();
    let data: Vec<f32> = (0..N * N * N).map(|i| (i % N) as f32 * 0.05).collect();
    let store = volume_store(dir.path(), "ramp", [N, N, N], data, Affine3::IDENTITY, 32);
    let s = scene(
        vec![volume_layer(
            store,
            "viridis",
            [0.0, 1.6],
            vec![[0.0, 0.02], [1.0, 0.08]],
        )],
        vec![],
        axis_camera([-40.0, 20.0, -30.0], [15.5, 15.5, 15.5]),
        exact_settings(W, W),
    );
    let plain = render_on_both(&s, 1e-4, "a linear ramp, unshaded");
    let mut lit = s.clone();
    lit.render.volume_shading = true;
    let shaded = render_on_both(&lit, 1e-4, "a linear ramp, shaded");
    let view =
        strata_common::camera::View::new(s.camera.as_ref().unwrap(), &s.render, W, W).unwrap();
    let (mut seen, mut cos_range) = (0, [1.0f32, 0.0f32]);
    for y in 0..W {
        for x in 0..W {
            let i = (y * W + x) as usize;
            let (p, q) = (plain[i], shaded[i]);
            assert_eq!(p[3], q[3], "({x}, {y}): shading changed the alpha");
            if p[3] < 1e-3 {
                continue;
            }
            let d = view.ray_dir(x, y);
            let cos = d[0].abs() / (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let (l0, l1) = (0.3 + 0.6 * cos, 0.25 * cos.powi(24));
            for c in 0..3 {
                let want = l0 * p[c] + l1 * p[3];
                assert!(
                    (q[c] - want).abs() <= 2e-6 + 1e-5 * want,
                    "({x}, {y}) channel {c}: {} against the closed form {want} (cos θ = {cos})",
                    q[c]
                );
            }
            seen += 1;
            cos_range = [cos_range[0].min(cos), cos_range[1].max(cos)];
        }
    }
    assert!(seen > 1000, "{seen} pixels see the ramp");
    assert!(
        cos_range[0] < 0.6 && cos_range[1] > 0.85,
        "the view sweeps too little of θ: cos θ in {cos_range:?}"
    );
}

/// The mixing of overlapping volumes against its closed form. Two constant volumes fill the
/// same box, `b` at half the resolution of `a`, with different colours and opacities `a`,
/// `b` per unit step of their own voxels. The frame steps by the finer voxel (1), so `b`'s
/// samples carry the corrected opacity `b' = 1 − (1 − b)^(1/2)`. Per sample the mix is
/// `1 − (1 − a)(1 − b')` (independent absorbers) with the opacity-weighted colour
/// `(a·c_a + b'·c_b) / (a + b')`; over the centre ray's `n` lattice points the pixel's alpha
/// is `1 − ((1 − a)(1 − b'))^n` and its colour that mix times the alpha. Each volume's own
/// colour is read from its render alone, where `b` steps by its own voxel (2).
#[test]
fn overlapping_volumes_mix_as_independent_absorbers_with_opacity_weighted_colour() {
    let dir = TempDir::new().unwrap();
    let (a, b) = (0.05f64, 0.08f64);
    let layer = |name: &str, n: u64, colormap: &str, alpha: f64| {
        // n samples per axis over the same box [-0.5, 31.5): cell-centred, scale N / n.
        let k = (N / n) as f64;
        let store = volume_store(
            dir.path(),
            name,
            [n, n, n],
            vec![1.0; (n * n * n) as usize],
            Affine3::scale_offset([k; 3], [(k - 1.0) / 2.0; 3]),
            32,
        );
        volume_layer(
            store,
            colormap,
            [0.0, 2.0],
            vec![[0.0, alpha], [1.0, alpha]],
        )
    };
    let (va, vb) = (layer("a", N, "grey", a), layer("b", N / 2, "viridis", b));
    let mut r = exact_settings(W, W);
    r.adaptive_step = false;
    r.step = 1.0;
    let cam = axis_camera([15.5, 15.5, -50.0], [15.5, 15.5, 0.0]);
    let render = |vols: Vec<strata_common::scene::VolumeLayer>, what: &str| {
        let s = scene(vols, vec![], cam.clone(), r.clone());
        centre(&render_on_both(&s, 1e-4, what))
    };
    let (alone_a, alone_b) = (
        render(vec![va.clone()], "volume a alone"),
        render(vec![vb.clone()], "volume b alone"),
    );
    let both = render(vec![va, vb], "both volumes, mixed");
    // Box faces at -0.5 and 31.5: the ray is inside for t in [49.5, 81.5).
    let (n1, n2) = (
        lattice_count(49.5, 81.5, 1.0),
        lattice_count(49.5, 81.5, 2.0),
    );
    assert_eq!((n1, n2), (32, 16));
    let b1 = 1.0 - (1.0 - b).sqrt();
    let (aa, ab, amix) = (
        1.0 - (1.0 - a).powi(32),
        1.0 - (1.0 - b).powi(16),
        1.0 - ((1.0 - a) * (1.0 - b1)).powi(32),
    );
    assert!(
        (alone_a[3] as f64 - aa).abs() < 2e-5,
        "{alone_a:?} against alpha {aa}"
    );
    assert!(
        (alone_b[3] as f64 - ab).abs() < 2e-5,
        "{alone_b:?} against alpha {ab}"
    );
    assert!(
        (both[3] as f64 - amix).abs() < 2e-5,
        "{both:?} against alpha {amix}"
    );
    for c in 0..3 {
        let (ca, cb) = (alone_a[c] as f64 / aa, alone_b[c] as f64 / ab);
        let want = amix * (a * ca + b1 * cb) / (a + b1);
        assert!(
            (both[c] as f64 - want).abs() < 2e-5,
            "channel {c}: {} against the closed form {want} (colours {ca}, {cb})",
            both[c]
        );
    }
    // The two colours differ, so the weights are tested.
    assert!((0..3).any(|c| (alone_a[c] / alone_a[3] - alone_b[c] / alone_b[3]).abs() > 0.1));
}
