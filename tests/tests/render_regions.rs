//! Sort-last invariants of the worker engine: a scene rendered as one region equals the
//! same scene rendered as any set of k-d regions (each by its own engine, as separate
//! workers would) composited front to back; and out-of-core batch rendering converges to
//! the image of an unlimited budget.

use proptest::prelude::*;
use std::path::PathBuf;
use strata_common::kd::KdTree;
use strata_common::scene::Scene;
use strata_tests::scenes::*;
use tempfile::TempDir;

/// A small synthetic survey (UTM coordinates, z down, three horizons with holes and a
/// pinch-out), as `coordinator synth` writes it.
fn survey(dir: &std::path::Path, size: [u64; 3]) -> PathBuf {
    let out =
        strata_coordinator::synth::synth(dir, size, 5, false, &indicatif::ProgressBar::hidden())
            .unwrap();
    out.scene
}

fn load(path: &std::path::Path, w: u32, h: u32) -> Scene {
    let mut s = Scene::parse(path, &std::fs::read_to_string(path).unwrap()).unwrap();
    s.render.width = w;
    s.render.height = h;
    s.render.early_termination = 1.0; // exact: a region cannot know what lies in front
    s.render.max_rounds = 64;
    s
}

#[test]
fn region_split_equals_whole_for_2_4_and_7_regions() {
    let dir = TempDir::new().unwrap();
    let path = survey(dir.path(), [72, 56, 48]);
    let mut s = load(&path, 96, 64);
    s.volumes[0].opacity = 0.3;
    s.horizons[1].opacity = 0.6; // a translucent horizon: hits behind it matter too
    let whole = render_whole(&s);
    assert_clean(&whole);
    assert!(
        whole.iter().filter(|p| p[3] > 0.05).count() > 1000,
        "the view shows the data"
    );
    let root = scene_region(&s);
    for sp in SPLITS_2_4_7 {
        let tree = KdTree::from_splits(root, sp);
        let split = render_split(&s, &tree);
        let d = max_diff(&whole, &split);
        assert!(
            d < 1e-5,
            "{} regions: max difference {d}",
            tree.leaves.len()
        );
    }
}

#[test]
fn several_overlapping_volumes_split_seamlessly() {
    // Two volumes of different resolution and orientation overlap: per-sample mixing must
    // also be region-invariant.
    let dir = TempDir::new().unwrap();
    let s = overlapping_volumes(dir.path(), 0);
    let whole = render_whole(&s);
    assert_clean(&whole);
    let tree = KdTree::from_splits(scene_region(&s), &[(0, 0, 0.5), (0, 2, 0.4), (1, 1, 0.55)]);
    let d = max_diff(&whole, &render_split(&s, &tree));
    assert!(d < 1e-5, "max difference {d}");
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 6, ..ProptestConfig::default() })]
    #[test]
    fn any_kd_split_composites_to_the_whole(
        splits in proptest::collection::vec((0usize..8, 0usize..3, 0.05f64..0.95), 1..6),
        eye_side in 0usize..4,
    ) {
        let dir = TempDir::new().unwrap();
        let path = survey(dir.path(), [40, 32, 24]);
        let mut s = load(&path, 40, 32);
        s.volumes[0].opacity = 0.4;
        s.horizons[0].opacity = 0.5;
        // Vary the camera side so the visibility order changes.
        if let Some(c) = &mut s.camera {
            let (dx, dy) = [(1.0, 1.0), (-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0)][eye_side];
            for (k, d) in [(0, dx), (1, dy)] {
                let off = c.eye[k] - c.target[k];
                c.eye[k] = c.target[k] + d * off.abs();
            }
        }
        let whole = render_whole(&s);
        let mut tree = KdTree::single(scene_region(&s));
        for (leaf, axis, frac) in splits {
            let leaf = leaf % tree.leaves.len();
            let r = tree.leaves[leaf];
            tree.split_leaf(leaf, axis, r.lo[axis] + frac * (r.hi[axis] - r.lo[axis]));
        }
        let d = max_diff(&whole, &render_split(&s, &tree));
        prop_assert!(d < 1e-5, "{} regions: max difference {}", tree.leaves.len(), d);
    }
}

#[test]
fn out_of_core_converges_to_the_unlimited_image() {
    // 8 MiB of f32 in 32³ bricks (128 KiB each); a 1 MiB cache holds 1/8 of it.
    let dir = TempDir::new().unwrap();
    let path = survey(dir.path(), [128, 128, 128]);
    let mut s = load(&path, 80, 60);
    s.volumes[0].opacity = 0.25;
    // Rebuild the cube with 32³ bricks so the budget is many pages.
    let vol = dir.path().join("seismic32.strata");
    {
        use strata_coordinator::builder::{build_store, BuildOptions};
        let model = strata_coordinator::synth::SynthModel::new([128, 128, 128], 5).unwrap();
        let mut o = BuildOptions::volume("seismic32", strata_common::sample::SampleType::F32);
        o.page_size = 32;
        o.transform = model.transform();
        build_store(&model, &vol, &o, &indicatif::ProgressBar::hidden()).unwrap();
    }
    s.volumes[0].store = vol;
    s.render.upload_pages_per_frame = 64; // several rounds
    let mut unlimited = s.clone();
    unlimited.render.cache_mb = 4096;
    let want = render_whole(&unlimited);

    s.render.cache_mb = 1;
    let mut e = strata_worker::engine::Engine::new(&s).unwrap();
    let view = e.view(80, 60).unwrap();
    let region = e.scene_region();
    let r = e.render_batch(&view, &region).unwrap();
    assert_eq!(r.outcome, strata_worker::engine::Outcome::Converged);
    let got = r.image.to_full();
    assert_eq!(
        max_diff(&want, &got),
        0.0,
        "same pages, same samples, same image"
    );
    let st = e.cache_stats();
    assert!(st.evictions > 0, "the budget forced evictions: {st:?}");
    // Within the budget at every moment: a round locks no more pages than it holds (64
    // pages of 128 KiB had been locked at once, eight times `cache_mb`).
    assert!(
        st.peak_bytes > 0 && st.peak_bytes <= 1 << 20,
        "the cache held more than its budget: {st:?}"
    );
    assert!(
        st.bytes_read > 1 << 20,
        "more than the budget was streamed: {st:?}"
    );
    // The view needs more pages than the cache holds (8 of 128 KiB).
    assert!(r.reports[0].requested > 8, "{:?}", r.reports);
}

#[test]
fn real_ct_volume_splits_seamlessly() {
    // The bonsai CT (256³ u8) from ../shared/data/real, as ParaView's baseline renders it.
    let raw = strata_tests::real_data("volumes/bonsai/bonsai_256x256x256_uint8.raw");
    let dir = TempDir::new().unwrap();
    let store = dir.path().join("bonsai.strata");
    let src = strata_coordinator::source::RawSource::open(
        &raw,
        [256, 256, 256],
        strata_common::sample::SampleType::U8,
        false,
    )
    .unwrap();
    let o = strata_coordinator::builder::BuildOptions::volume(
        "bonsai",
        strata_common::sample::SampleType::U8,
    );
    strata_coordinator::builder::build_store(&src, &store, &o, &indicatif::ProgressBar::hidden())
        .unwrap();
    let cam = strata_common::scene::Camera {
        eye: [892.4, 586.9, 713.4],
        target: [127.5; 3],
        up: [0.0, 0.0, 1.0],
        fov_deg: 30.0,
    };
    let s = scene(
        vec![volume_layer(
            store,
            "viridis",
            [0.0, 255.0],
            vec![[0.0, 0.0], [0.1, 0.0], [1.0, 0.5]],
        )],
        vec![],
        cam,
        exact_settings(72, 72),
    );
    let whole = render_whole(&s);
    assert_clean(&whole);
    assert!(
        whole.iter().filter(|p| p[3] > 0.2).count() > 300,
        "the bonsai is visible"
    );
    let tree = KdTree::from_splits(scene_region(&s), &[(0, 2, 0.5), (0, 0, 0.45), (1, 1, 0.6)]);
    let d = max_diff(&whole, &render_split(&s, &tree));
    assert!(d < 1e-5, "max difference {d}");
}

/// A horizon atlas too small for the view's tiles must not hold back the volume's pages: a
/// round takes only pages whose pool has room, so the volume's pool fills as it would with
/// room for every tile, and the batch ends `atlas-full` only when every page still missing
/// is one no pool can take. (A round once took the most-requested missing pages whatever
/// their pool, so horizon tiles could fill it, upload nothing, and end the batch as
/// atlas-full with the volume half loaded.)
#[test]
fn a_full_horizon_atlas_does_not_hold_back_the_volumes_pages() {
    use strata_worker::engine::{Engine, Outcome};
    let dir = TempDir::new().unwrap();
    let path = survey(dir.path(), [600, 400, 40]);
    let mut s = load(&path, 160, 100);
    // Horizons translucent and no early termination: which volume pages the rays need
    // does not depend on how finely the horizons are drawn.
    for h in &mut s.horizons {
        h.opacity = 0.5;
    }
    s.volumes[0].opacity = 0.2;
    s.render.upload_pages_per_frame = 4;
    s.render.max_rounds = 400;
    let run = |horizon_atlas_mb: u64| {
        let mut s = s.clone();
        s.render.horizon_atlas_mb = horizon_atlas_mb;
        let mut e = Engine::new(&s).unwrap();
        let view = e.view(s.render.width, s.render.height).unwrap();
        let region = e.scene_region();
        let r = e.render_batch(&view, &region).unwrap();
        let f = e.render_frame(&view, &region).unwrap();
        let last = e.update(&f.feedback, true).unwrap();
        (r.outcome, r.rounds, e.atlas_usage(), last)
    };
    let (ample, _, ample_use, _) = run(64);
    assert_eq!(ample, Outcome::Converged);
    let (outcome, rounds, usage, last) = run(1);
    assert_eq!(
        outcome,
        Outcome::AtlasFull,
        "1 MiB must not hold the tiles ({rounds} rounds)"
    );
    assert!(
        ample_use.1 > usage.1,
        "the small horizon atlas holds fewer tiles"
    );
    assert_eq!(
        usage.0, ample_use.0,
        "the volume's pool holds as many pages as with room for every tile"
    );
    assert_eq!(last.uploaded, 0);
    assert_eq!(
        last.no_slot, last.missing,
        "every page still missing lacks a slot: {last:?}"
    );
}
