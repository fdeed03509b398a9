//! Powerwall views on both casters: every tile of a wall, rendered as one stacked image
//! without its mullion pixels, equals the crop of one render of the wall's whole frustum
//! (mullions included). The CPU's SIMD packets and scalar march, and the GPU (where an
//! adapter exists), all take the tile map.

use strata_common::camera::View;
use strata_common::image::Rgba;
use strata_common::scene::{Backend, Scene};
use strata_common::wall::WallGeometry;
use strata_tests::scenes::*;
use strata_worker::engine::{Engine, Outcome};

fn converge(scene: &Scene, view: &View) -> Vec<Rgba> {
    let mut e = Engine::new(scene).unwrap();
    let region = e.scene_region();
    let r = e.render_batch(view, &region).unwrap();
    assert_eq!(r.outcome, Outcome::Converged, "after {} rounds", r.rounds);
    r.image.to_full()
}

/// The tiles of `plane` (a render of the whole frustum), stacked as a wall view renders them.
fn crops(plane: &[Rgba], g: &WallGeometry) -> Vec<Rgba> {
    let (pw, _) = g.plane_size();
    let mut out = Vec::new();
    for t in 0..g.tiles() {
        let (ox, oy) = g.tile_origin(t);
        for y in 0..g.tile_h {
            let row = ((oy + y) * pw + ox) as usize;
            out.extend_from_slice(&plane[row..row + g.tile_w as usize]);
        }
    }
    out
}

#[test]
fn wall_tiles_equal_crops_of_the_whole_frustum_on_every_caster() {
    let dir = tempfile::tempdir().unwrap();
    let scene = overlapping_volumes(dir.path(), 0);
    let cam = scene.camera.clone().unwrap();
    let g = WallGeometry {
        cols: 3,
        rows: 2,
        tile_w: 21,
        tile_h: 17,
        mullion_x: 5,
        mullion_y: 9,
    };
    let (pw, ph) = g.plane_size();
    let mut casters = vec![("cpu", on_backend(&scene, Backend::Cpu))];
    let mut scalar = on_backend(&scene, Backend::Cpu);
    scalar.render.simd = false;
    casters.push(("cpu scalar", scalar));
    if gpu_available() {
        casters.push(("gpu", on_backend(&scene, Backend::Gpu)));
    }
    let cpu_plane = {
        let s = &casters[0].1;
        converge(s, &View::new(&cam, &s.render, pw, ph).unwrap())
    };
    let alpha: f32 = cpu_plane.iter().map(|p| p[3]).sum();
    assert!(
        alpha > 20.0,
        "the scene must be on the wall (alpha {alpha})"
    );
    for (name, s) in &casters {
        let plane = converge(s, &View::new(&cam, &s.render, pw, ph).unwrap());
        let wall = converge(s, &View::wall(&cam, &s.render, &g).unwrap());
        assert_eq!(wall.len(), (g.tile_w * g.tile_h * g.tiles()) as usize);
        let d = max_diff(&wall, &crops(&plane, &g));
        assert!(
            d <= 1e-5,
            "{name}: wall tiles differ from the frustum's crops by {d}"
        );
        // Across casters, the GPU's usual tolerance.
        let d = max_diff(&wall, &crops(&cpu_plane, &g));
        assert!(
            d <= 1e-4,
            "{name}: wall tiles differ from the CPU frustum by {d}"
        );
    }
}
