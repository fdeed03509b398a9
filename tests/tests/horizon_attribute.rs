//! Horizons coloured by a volume (`color_by = "volume"`): at every pixel the surface shows
//! the co-registered volume's value where the ray meets it, in the volume's colours, and
//! the no-data colour where the volume does not reach; on both casters (GPU == CPU within
//! 1e-4 where an adapter exists) and seamless across k-d splits.

use strata_common::camera::View;
use strata_common::geo::Affine3;
use strata_common::kd::KdTree;
use strata_common::scene::{Camera, Scene};
use strata_tests::scenes::*;
use tempfile::TempDir;

const N: u64 = 48;
const W: u32 = 64;
/// The flat horizon's height.
const Z0: f64 = 20.5;
/// The horizon grid starts this far before the volume on x and y, and runs as far past it.
const RIM: f64 = 8.0;

/// A ramp volume (value = x index, grey over [0, N − 1], itself transparent) and a flat
/// horizon at z = Z0 over a grid RIM larger than the volume on each side, coloured by the
/// volume, red (no data) outside it; no lighting, so a pixel is the colour itself.
fn attribute_scene(dir: &std::path::Path) -> Scene {
    let data: Vec<f32> = (0..N * N * N).map(|i| (i % N) as f32).collect();
    let vol = volume_store(dir, "ramp", [N, N, N], data, Affine3::IDENTITY, 32);
    let layer = volume_layer(
        vol,
        "grey",
        [0.0, (N - 1) as f64],
        vec![[0.0, 0.0], [1.0, 0.0]],
    );
    let m = N + 2 * RIM as u64;
    let hor = horizon_store(
        dir,
        "flat",
        [m, m],
        vec![Z0 as f32; (m * m) as usize],
        Affine3::scale_offset([1.0, 1.0, 1.0], [-RIM, -RIM, 0.0]),
        32,
    );
    let mut h = horizon_layer(hor, [1.0, 0.0, 0.0], 1.0);
    h.color_by = "volume".into();
    let c = (N - 1) as f64 / 2.0;
    let camera = Camera {
        eye: [c + 10.0, c - 45.0, 95.0],
        target: [c, c, Z0],
        up: [0.0, 0.0, 1.0],
        fov_deg: 60.0,
    };
    let mut render = exact_settings(W, W);
    render.lighting = false;
    scene(vec![layer], vec![h], camera, render)
}

#[test]
fn a_horizon_coloured_by_a_volume_shows_its_value_at_the_surface() {
    let dir = TempDir::new().unwrap();
    let s = attribute_scene(dir.path());
    let px = render_on_both(&s, 1e-4, "horizon by volume");
    assert_clean(&px);
    let cam = s.camera.clone().unwrap();
    let view = View::new(&cam, &s.render, W, W).unwrap();
    let (mut inside, mut outside) = (0, 0);
    for y in 0..W {
        for x in 0..W {
            let d = view.ray_dir(x, y).map(|v| v as f64);
            let t = (Z0 - cam.eye[2]) / d[2];
            let (hx, hy) = (cam.eye[0] + t * d[0], cam.eye[1] + t * d[1]);
            let got = px[(y * W + x) as usize];
            let on_grid = |v: f64| v > -RIM + 1.0 && v < N as f64 + RIM - 2.0;
            let in_vol = |v: f64| v > 1.0 && v < N as f64 - 2.0;
            let off_vol = |v: f64| v < -1.5 || v > N as f64 - 0.5;
            if !(t > 0.0 && on_grid(hx) && on_grid(hy)) {
                continue;
            }
            if in_vol(hx) && in_vol(hy) {
                // Grey is linear in linear light over the window: value x → x / (N − 1).
                let g = (hx / (N - 1) as f64) as f32;
                for k in 0..3 {
                    assert!(
                        (got[k] - g).abs() < 2e-3,
                        "pixel ({x}, {y}) hits x = {hx:.3}: {got:?}, want grey {g}"
                    );
                }
                assert_eq!(got[3], 1.0);
                inside += 1;
            } else if off_vol(hx) || off_vol(hy) {
                assert_eq!(got, [1.0, 0.0, 0.0, 1.0], "pixel ({x}, {y}) off the volume");
                outside += 1;
            }
        }
    }
    assert!(
        inside > 500 && outside > 200,
        "{inside} inside, {outside} outside"
    );
    // The same surface coloured by its constant colour is red everywhere.
    let mut red = s.clone();
    red.horizons[0].color_by = "constant".into();
    assert!(max_diff(&px, &render_whole(&red)) > 0.5);
    // Seamless across regions: every split composites to the whole image.
    let region = scene_region(&s);
    for splits in SPLITS_2_4_7 {
        let tree = KdTree::from_splits(region, splits);
        let d = max_diff(&px, &render_split(&s, &tree));
        assert!(d <= 1e-5, "{} regions differ by {d}", tree.leaves.len());
    }
}

#[test]
fn a_horizon_coloured_by_a_missing_volume_is_refused() {
    let dir = TempDir::new().unwrap();
    let mut s = attribute_scene(dir.path());
    s.horizons[0].volume = 1;
    let e = strata_worker::engine::Engine::new(&s)
        .err()
        .expect("refused");
    let msg = format!("{e:#}");
    assert!(
        msg.contains("volume 1") && msg.contains("1 volume(s)"),
        "{msg}"
    );
}
