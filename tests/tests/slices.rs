//! Inline, crossline and time slices through a volume, on both casters (the GPU where a
//! wgpu adapter exists, lavapipe in CI; GPU == CPU within 1e-4): the analytic colour of the
//! plane, its opacity, slices in depth order, every k-d split giving the whole render, and
//! slices outside the grid refused.

use strata_common::geo::Affine3;
use strata_common::kd::KdTree;
use strata_common::scene::{Camera, SliceAxis, SliceLayer};
use strata_tests::scenes::*;
use tempfile::TempDir;

const N: u64 = 48;
/// The grid's centre coordinate.
const C: f64 = (N - 1) as f64 / 2.0;
const W: u32 = 65; // odd: the centre pixel's ray is the optical axis

/// A volume whose value is its first index (a ramp along the inline axis), grey over
/// [0, N − 1], fully transparent itself: only its slices show.
fn ramp_scene(
    dir: &std::path::Path,
    slices: Vec<SliceLayer>,
    camera: Camera,
) -> strata_common::scene::Scene {
    let data: Vec<f32> = (0..N * N * N).map(|i| (i % N) as f32).collect();
    let store = volume_store(dir, "ramp", [N, N, N], data, Affine3::IDENTITY, 32);
    let mut layer = volume_layer(
        store,
        "grey",
        [0.0, (N - 1) as f64],
        vec![[0.0, 0.0], [1.0, 0.0]],
    );
    layer.slices = slices;
    scene(vec![layer], vec![], camera, exact_settings(W, W))
}

fn slice(axis: SliceAxis, index: f64, opacity: f64) -> SliceLayer {
    SliceLayer {
        axis,
        index,
        opacity,
    }
}

fn centre(px: &[[f32; 4]]) -> [f32; 4] {
    px[(W / 2 * W + W / 2) as usize]
}

fn along_x() -> Camera {
    Camera {
        eye: [-50.0, C, C],
        target: [0.0, C, C],
        up: [0.0, 0.0, 1.0],
        fov_deg: 30.0,
    }
}

#[test]
fn an_inline_slice_shows_the_value_on_its_plane_in_the_volume_colours() {
    let dir = TempDir::new().unwrap();
    for (index, opacity) in [(10.5, 1.0), (0.0, 1.0), (47.0, 1.0), (20.25, 0.4)] {
        let s = ramp_scene(
            dir.path(),
            vec![slice(SliceAxis::Inline, index, opacity)],
            along_x(),
        );
        let px = render_on_both(&s, 1e-4, "slices");
        assert_clean(&px);
        let c = centre(&px);
        // Grey is linear in linear light from black to white over the window.
        let g = (index / (N - 1) as f64) as f32;
        let want = [
            g * opacity as f32,
            g * opacity as f32,
            g * opacity as f32,
            opacity as f32,
        ];
        for k in 0..4 {
            assert!(
                (c[k] - want[k]).abs() < 1e-4,
                "index {index} opacity {opacity}: {c:?}, want {want:?}"
            );
        }
    }
    // Without the slice the volume is invisible.
    let s = ramp_scene(dir.path(), vec![], along_x());
    assert_eq!(centre(&render_on_both(&s, 1e-4, "slices"))[3], 0.0);
}

#[test]
fn slices_are_surfaces_nearest_first_and_parallel_rays_miss_them() {
    let dir = TempDir::new().unwrap();
    // Two translucent inline slices: the nearer composites over the farther.
    let s = ramp_scene(
        dir.path(),
        vec![
            slice(SliceAxis::Inline, 24.0, 0.5),
            slice(SliceAxis::Inline, 8.0, 0.5),
        ],
        along_x(),
    );
    let c = centre(&render_on_both(&s, 1e-4, "slices"));
    let (g1, g2) = (8.0 / (N - 1) as f32, 24.0 / (N - 1) as f32);
    let want = 0.5 * g1 + 0.5 * 0.5 * g2;
    assert!(
        (c[0] - want).abs() < 1e-4 && (c[3] - 0.75).abs() < 1e-4,
        "{c:?}"
    );
    // A time slice is parallel to the centre ray (along x): it never shows there.
    let s = ramp_scene(dir.path(), vec![slice(SliceAxis::Time, C, 1.0)], along_x());
    assert_eq!(centre(&render_on_both(&s, 1e-4, "slices"))[3], 0.0);
    // Seen from above, the same time slice is the ramp itself: colour grows with x.
    let down = Camera {
        eye: [C, C, 120.0],
        target: [C, C, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_deg: 30.0,
    };
    let s = ramp_scene(dir.path(), vec![slice(SliceAxis::Time, C, 1.0)], down);
    let px = render_on_both(&s, 1e-4, "slices");
    let row = (W / 2 * W) as usize;
    let (left, mid, right) = (px[row + 20], px[row + 32], px[row + 44]);
    assert!(
        left[0] < mid[0] && mid[0] < right[0] && (mid[0] - 0.5).abs() < 1e-3,
        "{left:?} {mid:?} {right:?}"
    );
}

#[test]
fn every_k_d_split_gives_the_whole_render_with_slices() {
    let dir = TempDir::new().unwrap();
    let mut s = overlapping_volumes(dir.path(), 0);
    s.volumes[0].slices = vec![
        slice(SliceAxis::Inline, 7.3, 1.0),
        slice(SliceAxis::Crossline, 12.0, 0.7),
        slice(SliceAxis::Time, 16.0, 1.0),
    ];
    let whole = render_on_both(&s, 1e-4, "slices");
    assert_clean(&whole);
    let plain = {
        let mut p = s.clone();
        p.volumes[0].slices.clear();
        render_whole(&p)
    };
    assert!(
        max_diff(&whole, &plain) > 0.1,
        "the slices change the image"
    );
    let region = scene_region(&s);
    for splits in SPLITS_2_4_7 {
        let tree = KdTree::from_splits(region, splits);
        let d = max_diff(&whole, &render_split(&s, &tree));
        assert!(d <= 1e-5, "{} regions differ by {d}", tree.leaves.len());
    }
}

#[test]
fn a_slice_outside_the_grid_is_refused_naming_it() {
    let dir = TempDir::new().unwrap();
    for (sl, what) in [
        (slice(SliceAxis::Time, 47.5, 1.0), "outside the grid"),
        (slice(SliceAxis::Inline, -1.0, 1.0), "outside the grid"),
        (slice(SliceAxis::Inline, 3.0, 1.5), "opacity"),
    ] {
        let s = ramp_scene(dir.path(), vec![sl], along_x());
        let e = match strata_worker::engine::Engine::new(&s) {
            Ok(_) => panic!("accepted a bad slice"),
            Err(e) => format!("{e:#}"),
        };
        assert!(e.contains("slice 0") && e.contains(what), "{e}");
    }
}

/// Many slices per volume (more than the 4 the GPU caster once held in its volume record):
/// ten translucent inline slices composite nearest first to the analytic colour on both
/// casters; more than `MAX_SLICES` are refused.
#[test]
fn ten_slices_composite_in_order_on_both_casters_and_too_many_are_refused() {
    let dir = TempDir::new().unwrap();
    let idx: Vec<f64> = (0..10).map(|k| 2.0 + 4.5 * k as f64).collect();
    let s = ramp_scene(
        dir.path(),
        idx.iter()
            .map(|&i| slice(SliceAxis::Inline, i, 0.2))
            .collect(),
        along_x(),
    );
    let c = centre(&render_on_both(&s, 1e-4, "ten slices"));
    // Seen along +x: the slice at the smallest index is in front.
    let (mut rgb, mut a) = (0.0f64, 0.0f64);
    for &i in &idx {
        let g = i / (N - 1) as f64;
        rgb += (1.0 - a) * 0.2 * g;
        a += (1.0 - a) * 0.2;
    }
    assert!(
        (c[0] as f64 - rgb).abs() < 1e-4 && (c[3] as f64 - a).abs() < 1e-4,
        "{c:?}, want {rgb} / {a}"
    );
    let n = strata_common::gpu::MAX_SLICES + 1;
    let s = ramp_scene(
        dir.path(),
        (0..n)
            .map(|k| slice(SliceAxis::Time, k as f64, 1.0))
            .collect(),
        along_x(),
    );
    let e = match strata_worker::engine::Engine::new(&s) {
        Ok(_) => panic!("accepted {n} slices"),
        Err(e) => format!("{e:#}"),
    };
    assert!(e.contains(&format!("{n} slices")), "{e}");
}

/// More crossings than the GPU caster's list of 32 holds: 16 slices on each axis (one axis
/// per copy of the volume: at most 16 slices per volume are drawn), seen along the
/// diagonal, give the centre ray 48 translucent crossings. Both casters composite every
/// one, nearest first, to the analytic colour (the GPU had kept its nearest 32 and dropped
/// the rest; it now searches again from its 32nd).
#[test]
fn forty_eight_crossings_composite_in_order_on_both_casters() {
    let dir = TempDir::new().unwrap();
    let at = |first: f64| (0..16).map(move |k| first + 2.8 * k as f64);
    let back = 90.0 / 3f64.sqrt();
    let camera = Camera {
        eye: [C - back, C - back, C - back],
        target: [C, C, C],
        up: [0.0, 0.0, 1.0],
        fov_deg: 30.0,
    };
    let mut s = ramp_scene(dir.path(), vec![], camera);
    let layer = s.volumes[0].clone();
    s.volumes.clear();
    for (axis, first) in [
        (SliceAxis::Inline, 1.5),
        (SliceAxis::Crossline, 1.9),
        (SliceAxis::Time, 2.3),
    ] {
        let mut l = layer.clone();
        l.slices = at(first).map(|i| slice(axis, i, 0.04)).collect();
        s.volumes.push(l);
    }
    let c = centre(&render_on_both(&s, 1e-4, "48 crossings"));
    // On the diagonal x = y = z, so each slice is crossed where the ramp's value is the
    // slice's index, in the order of the indexes.
    let mut idx: Vec<f64> = at(1.5).chain(at(1.9)).chain(at(2.3)).collect();
    idx.sort_by(f64::total_cmp);
    let (mut rgb, mut a) = (0.0f64, 0.0f64);
    for &i in &idx {
        rgb += (1.0 - a) * 0.04 * i / (N - 1) as f64;
        a += (1.0 - a) * 0.04;
    }
    assert!(
        (c[0] as f64 - rgb).abs() < 1e-4 && (c[3] as f64 - a).abs() < 1e-4,
        "{c:?}, want {rgb} / {a}"
    );
}
