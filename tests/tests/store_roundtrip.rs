//! Round trips through the page store: level 0 equals the source, borders equal the
//! neighbours' samples, coarse levels equal the filter applied to the finer level, and the
//! index's per-page bounds are conservative.

use indicatif::ProgressBar;
use proptest::prelude::*;
use strata_common::filter::CoarsenFilter;
use strata_common::sample::SampleType;
use strata_common::store::{Compression, PageStore};
use strata_coordinator::builder::{build_store, BuildOptions};
use strata_coordinator::source::{MemorySource, RawSource};
use strata_tests::{check_borders, check_coarse_levels, level_grid, same};

fn synthetic(dims: [u64; 3], t: SampleType, seed: u64) -> Vec<f32> {
    let n = (dims[0] * dims[1] * dims[2]) as usize;
    (0..n)
        .map(|i| {
            let h = strata_common::digest::fmix64(i as u64 ^ seed);
            let (lo, hi) = match t {
                SampleType::F32 => (-5000.0, 5000.0),
                _ => t.range(),
            };
            // Smooth structure plus noise, and constant regions so constant pages appear.
            let x = (i as u64 % dims[0]) as f32;
            if x < 3.0 {
                return t.quantize(lo.max(-100.0).max(lo));
            }
            let v = lo + (hi - lo) * ((h >> 40) as f32 / (1u64 << 24) as f32);
            t.quantize(v)
        })
        .collect()
}

fn build(
    src: &MemorySource,
    t: SampleType,
    page: u32,
    border: u32,
    filter: CoarsenFilter,
    comp: Compression,
    budget: usize,
) -> (tempfile::TempDir, PageStore) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("v.strata");
    let mut o = BuildOptions::volume("t", t);
    o.page_size = page;
    o.border = border;
    o.filter = filter;
    o.compression = comp;
    o.memory_budget = budget;
    build_store(src, &out, &o, &ProgressBar::hidden()).unwrap();
    // Nothing but the store is left in the folder.
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, vec![std::ffi::OsString::from("v.strata")]);
    let s = PageStore::open(&out).unwrap();
    (dir, s)
}

fn assert_round_trip(
    dims: [u64; 3],
    t: SampleType,
    page: u32,
    border: u32,
    filter: CoarsenFilter,
    comp: Compression,
    budget: usize,
) {
    let data = synthetic(dims, t, dims[0] * 31 + dims[2]);
    let src = MemorySource { dims, data };
    let (_d, store) = build(&src, t, page, border, filter, comp, budget);
    let l0 = level_grid(&store, 0).unwrap();
    for (i, (a, b)) in l0.iter().zip(&src.data).enumerate() {
        assert!(same(*a, *b), "level-0 sample {i}: store {a}, source {b}");
    }
    check_borders(&store).unwrap();
    check_coarse_levels(&store).unwrap();
    // Per-page bounds are conservative: they cover every sample the page holds and its children's bounds.
    let pyr = store.pyramid();
    for e in store.index() {
        let p = store.read_page(e.id).unwrap();
        for v in p.samples.iter().filter(|v| !v.is_nan()) {
            assert!(
                *v >= e.min && *v <= e.max,
                "{}: {v} outside [{}, {}]",
                e.id,
                e.min,
                e.max
            );
        }
        let l = e.id.level() as usize;
        if l > 0 {
            for c in pyr.children(l, pyr.brick_of(e.id.morton())) {
                let ce = store.entry(pyr.id(l - 1, c)).unwrap();
                assert!(ce.min >= e.min && ce.max <= e.max);
            }
        }
    }
}

#[test]
fn non_power_of_two_i16_signed_rms_lz4_small_budget() {
    assert_round_trip(
        [37, 20, 45],
        SampleType::I16,
        32,
        1,
        CoarsenFilter::SignedRms,
        Compression::Lz4,
        64 << 10,
    );
}

#[test]
fn u8_mean_border_2() {
    assert_round_trip(
        [70, 33, 31],
        SampleType::U8,
        32,
        2,
        CoarsenFilter::Mean,
        Compression::None,
        1 << 20,
    );
}

#[test]
fn f32_max_abs_page_64() {
    assert_round_trip(
        [130, 65, 9],
        SampleType::F32,
        64,
        1,
        CoarsenFilter::MaxAbs,
        Compression::Lz4,
        256 << 20,
    );
}

#[test]
fn single_sample_and_thin_volumes() {
    assert_round_trip(
        [1, 1, 1],
        SampleType::U16,
        32,
        1,
        CoarsenFilter::Mean,
        Compression::None,
        1 << 20,
    );
    assert_round_trip(
        [200, 1, 3],
        SampleType::I8,
        32,
        1,
        CoarsenFilter::SignedRms,
        Compression::None,
        1 << 16,
    );
}

#[test]
fn nan_no_data_in_f32_volume() {
    let dims = [40, 35, 33];
    let mut data = synthetic(dims, SampleType::F32, 5);
    // A whole region of no-data (a missing-trace column) and scattered NaN samples.
    for z in 0..dims[2] {
        for y in 0..10 {
            for x in 0..12 {
                data[((z * dims[1] + y) * dims[0] + x) as usize] = f32::NAN;
            }
        }
    }
    data[999] = f32::NAN;
    let src = MemorySource { dims, data };
    let (_d, store) = build(
        &src,
        SampleType::F32,
        32,
        1,
        CoarsenFilter::SignedRms,
        Compression::Lz4,
        1 << 20,
    );
    let l0 = level_grid(&store, 0).unwrap();
    assert!(l0.iter().zip(&src.data).all(|(a, b)| same(*a, *b)));
    check_borders(&store).unwrap();
    check_coarse_levels(&store).unwrap();
    let nan = src.data.iter().filter(|v| v.is_nan()).count() as u64;
    assert_eq!(store.header().valid_samples, 40 * 35 * 33 - nan);
}

/// A SEG-Y cube with missing traces in an integer type stores its holes as the type's
/// sentinel (the `ingest segy` CLI picks the range's low end). Real samples at that value
/// (clipped amplitudes, the zeros of a u8 cube) must stay values: stored one unit away and
/// counted, not read back as holes, and the recorded digest must still verify.
#[test]
fn valid_samples_at_the_no_data_sentinel_are_not_read_back_as_holes() {
    let dims = [70, 40, 35];
    for (t, nd) in [(SampleType::I16, -32768.0f32), (SampleType::U8, 0.0)] {
        let mut data = synthetic(dims, t, 11);
        // A missing trace (a column of holes), and real samples at the sentinel: a clipped
        // run and scattered ones, some on page borders.
        for z in 0..dims[2] {
            data[((z * dims[1] + 3) * dims[0] + 4) as usize] = f32::NAN;
        }
        let at_sentinel: Vec<usize> = (0..data.len())
            .filter(|i| i % 37 == 5 && !data[*i].is_nan())
            .collect();
        for &i in &at_sentinel {
            data[i] = nd;
        }
        let moved = data.iter().filter(|&&v| v == nd).count() as u64;
        let holes = data.iter().filter(|v| v.is_nan()).count() as u64;
        let src = MemorySource { dims, data };
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("v.strata");
        let mut o = BuildOptions::volume("t", t);
        o.page_size = 32;
        o.no_data = Some(nd);
        let report = build_store(&src, &out, &o, &ProgressBar::hidden()).unwrap();
        assert_eq!(report.moved_off_no_data, moved, "{t:?}");
        let store = PageStore::open(&out).unwrap();
        assert_eq!(
            store.header().valid_samples,
            dims.iter().product::<u64>() - holes
        );
        let l0 = level_grid(&store, 0).unwrap();
        let step = if nd < t.range().1 { 1.0 } else { -1.0 };
        for (i, (a, b)) in l0.iter().zip(&src.data).enumerate() {
            let want = if *b == nd { nd + step } else { *b };
            assert!(same(*a, want), "{t:?} sample {i}: store {a}, want {want}");
        }
        check_borders(&store).unwrap();
        check_coarse_levels(&store).unwrap();
        // Every page of every level decodes, and the level-0 digest is the recorded one.
        strata_coordinator::inspect::inspect(&out, true, &ProgressBar::hidden())
            .unwrap_or_else(|e| panic!("{t:?}: {e:#}"));
    }
}

#[test]
fn integer_store_without_sentinel_refuses_no_data() {
    let dims = [10, 10, 10];
    let mut data = vec![1.0f32; 1000];
    data[5] = f32::NAN;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("v.strata");
    let err = build_store(
        &MemorySource { dims, data },
        &out,
        &BuildOptions::volume("t", SampleType::I16),
        &ProgressBar::hidden(),
    )
    .unwrap_err();
    assert!(format!("{err:#}").contains("no-data"), "{err:#}");
    assert!(
        std::fs::read_dir(dir.path()).unwrap().next().is_none(),
        "nothing half-written may remain"
    );
}

#[test]
fn raw_file_big_endian_equals_little_endian() {
    let dims = [33u64, 17, 29];
    let data = synthetic(dims, SampleType::I16, 9);
    let dir = tempfile::tempdir().unwrap();
    let le: Vec<u8> = data
        .iter()
        .flat_map(|&v| (v as i16).to_le_bytes())
        .collect();
    let be: Vec<u8> = data
        .iter()
        .flat_map(|&v| (v as i16).to_be_bytes())
        .collect();
    std::fs::write(dir.path().join("le.raw"), le).unwrap();
    std::fs::write(dir.path().join("be.raw"), be).unwrap();
    let mut digests = Vec::new();
    for (name, big) in [("le", false), ("be", true)] {
        let src = RawSource::open(
            &dir.path().join(format!("{name}.raw")),
            dims,
            SampleType::I16,
            big,
        )
        .unwrap();
        let out = dir.path().join(format!("{name}.strata"));
        let r = build_store(
            &src,
            &out,
            &BuildOptions::volume(name, SampleType::I16),
            &ProgressBar::hidden(),
        )
        .unwrap();
        let store = PageStore::open(&out).unwrap();
        assert!(level_grid(&store, 0)
            .unwrap()
            .iter()
            .zip(&data)
            .all(|(a, b)| same(*a, *b)));
        digests.push(r.header.unwrap().digest);
    }
    assert_eq!(digests[0], digests[1]);
}

#[test]
fn digest_is_independent_of_brick_size_and_compression() {
    let dims = [50, 40, 30];
    let src = MemorySource {
        dims,
        data: synthetic(dims, SampleType::U16, 3),
    };
    let (_a, s1) = build(
        &src,
        SampleType::U16,
        32,
        1,
        CoarsenFilter::Mean,
        Compression::None,
        1 << 20,
    );
    let (_b, s2) = build(
        &src,
        SampleType::U16,
        64,
        2,
        CoarsenFilter::Mean,
        Compression::Lz4,
        1 << 20,
    );
    assert_eq!(s1.header().digest, s2.header().digest);
    let mut other = src.data.clone();
    other[77] += 1.0;
    let (_c, s3) = build(
        &MemorySource { dims, data: other },
        SampleType::U16,
        32,
        1,
        CoarsenFilter::Mean,
        Compression::None,
        1 << 20,
    );
    assert_ne!(s1.header().digest, s3.header().digest);
}

#[test]
fn horizon_tiles_keep_holes_and_never_invent_heights() {
    let dims = [300u64, 170, 1];
    let mut data: Vec<f32> = (0..dims[0] * dims[1])
        .map(|i| 1000.0 + (i % 300) as f32 * 0.5 + (i / 300) as f32 * 0.25)
        .collect();
    // A round hole and a one-node hole.
    for j in 0..dims[1] {
        for i in 0..dims[0] {
            if (i as f64 - 100.0).powi(2) + (j as f64 - 80.0).powi(2) < 400.0 {
                data[(j * dims[0] + i) as usize] = f32::NAN;
            }
        }
    }
    data[(150 * dims[0] + 250) as usize] = f32::NAN;
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("h.strata");
    let mut o = BuildOptions::horizon("h");
    o.page_size = 32;
    let src = MemorySource { dims, data };
    build_store(&src, &out, &o, &ProgressBar::hidden()).unwrap();
    let store = PageStore::open(&out).unwrap();
    let l0 = level_grid(&store, 0).unwrap();
    assert!(l0.iter().zip(&src.data).all(|(a, b)| same(*a, *b)));
    check_borders(&store).unwrap();
    check_coarse_levels(&store).unwrap();
    // A coarse texel is a hole wherever any fine texel under it is: holes never shrink.
    let l1 = level_grid(&store, 1).unwrap();
    let c = store.pyramid().level(1).dims;
    assert!(l1[(75 * c[0] + 125) as usize].is_nan());
    assert!(l1[(40 * c[0] + 50) as usize].is_nan());
}

/// A horizon in compressed tiles of odd side: the payload (`5·page²` bytes) ends in a byte
/// past the last 4-byte element, the corner's mask, which the byte shuffle had dropped: the
/// corner node of every compressed tile read back as a hole (a pinhole in each tile).
#[test]
fn compressed_horizon_tiles_of_odd_side_keep_their_corners() {
    let dims = [200u64, 150, 1];
    let data: Vec<f32> = (0..dims[0] * dims[1])
        .map(|i| 1000.0 + (i % 200) as f32 * 0.5 + (i / 200) as f32 * 0.25)
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("h.strata");
    let mut o = BuildOptions::horizon("h");
    o.page_size = 33;
    o.compression = Compression::Lz4;
    let src = MemorySource { dims, data };
    build_store(&src, &out, &o, &ProgressBar::hidden()).unwrap();
    let store = PageStore::open(&out).unwrap();
    assert!(
        store.index().iter().any(|e| e.flags & 1 != 0),
        "no tile was stored compressed"
    );
    let l0 = level_grid(&store, 0).unwrap();
    assert!(l0.iter().zip(&src.data).all(|(a, b)| same(*a, *b)));
    // Every tile's border, its corners included, holds its neighbours' nodes.
    check_borders(&store).unwrap();
    check_coarse_levels(&store).unwrap();
}

/// A no-data value the sample type cannot hold (`-1` or `0.5` in u8) is refused: holes
/// would be written as another value (0) and read back as data, under the pages' bounds.
#[test]
fn a_no_data_value_outside_the_sample_type_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let v = MemorySource {
        dims: [8, 8, 8],
        data: (0..512)
            .map(|i| if i % 7 == 0 { f32::NAN } else { 9.0 })
            .collect(),
    };
    for bad in [-1.0f32, 0.5, 256.0] {
        let out = dir.path().join(format!("v{bad}.strata"));
        let mut o = BuildOptions::volume("v", SampleType::U8);
        o.no_data = Some(bad);
        let e = build_store(&v, &out, &o, &ProgressBar::hidden()).unwrap_err();
        assert!(format!("{e:#}").contains("no-data value"), "{e:#}");
        assert!(!out.exists());
    }
    let out = dir.path().join("v0.strata");
    let mut o = BuildOptions::volume("v", SampleType::U8);
    o.no_data = Some(0.0);
    build_store(&v, &out, &o, &ProgressBar::hidden()).unwrap();
    let s = PageStore::open(&out).unwrap();
    let l0 = level_grid(&s, 0).unwrap();
    assert_eq!(l0.iter().filter(|x| x.is_nan()).count(), 74);
}

/// Each kind of data coarsens with its own filters: the volume filters skip holes, which on
/// a horizon invents heights across them, and the height filter on a volume grows its
/// no-data level by level. Refused with an error naming the filter; nothing is written.
#[test]
fn a_filter_for_the_other_kind_of_data_is_refused() {
    use strata_common::filter::CoarsenFilter;
    let dir = tempfile::tempdir().unwrap();
    let h = MemorySource {
        dims: [8, 8, 1],
        data: vec![1.0; 64],
    };
    for f in [
        CoarsenFilter::Mean,
        CoarsenFilter::SignedRms,
        CoarsenFilter::MaxAbs,
    ] {
        let out = dir.path().join(format!("h-{}.strata", f.name()));
        let mut o = BuildOptions::horizon("h");
        o.filter = f;
        let e = build_store(&h, &out, &o, &ProgressBar::hidden()).unwrap_err();
        assert!(format!("{e:#}").contains(f.name()), "{e:#}");
        assert!(!out.exists());
    }
    let v = MemorySource {
        dims: [8, 8, 8],
        data: vec![1.0; 512],
    };
    let out = dir.path().join("v.strata");
    let mut o = BuildOptions::volume("v", SampleType::F32);
    o.filter = CoarsenFilter::HorizonMean;
    let e = build_store(&v, &out, &o, &ProgressBar::hidden()).unwrap_err();
    assert!(format!("{e:#}").contains("horizon-mean"), "{e:#}");
    assert!(!out.exists());
}

/// A coarse page whose samples are all one value while its children vary (the RMS of a
/// checkerboard of 0 and 2 is √2 everywhere) keeps its samples: its index bounds widen to
/// the children's [0, 2], and a page stored as constant reads back as its entry's min (it
/// had read back as 0 everywhere, at the root every distant view shows).
#[test]
fn a_constant_coarse_page_under_varying_children_reads_back_its_own_value() {
    let dims = [64u64, 64, 64];
    let data: Vec<f32> = (0..dims.iter().product::<u64>())
        .map(|i| {
            let (x, y, z) = (i % 64, (i / 64) % 64, i / 4096);
            if (x + y + z) % 2 == 0 {
                0.0
            } else {
                2.0
            }
        })
        .collect();
    let src = MemorySource { dims, data };
    let (_d, store) = build(
        &src,
        SampleType::F32,
        32,
        1,
        CoarsenFilter::SignedRms,
        Compression::Lz4,
        1 << 20,
    );
    check_coarse_levels(&store).unwrap();
    for l in 1..store.pyramid().level_count() {
        let g = level_grid(&store, l).unwrap();
        assert!(
            g.iter().all(|v| (v - 2f32.sqrt()).abs() < 1e-6),
            "level {l}: {:?}",
            &g[..4]
        );
    }
    // The entries' bounds still cover the children's.
    let root = store.index().last().unwrap();
    assert_eq!((root.min, root.max), (0.0, 2.0));
}

/// A horizon with a line of holes every fourth line (an interpretation left unpicked
/// there): its tiles from level 2 up are all holes (`HorizonMean` makes a hole wherever a
/// child is one), yet their index bounds cover the heights under them, so the search goes
/// down to them: a close view draws the surface (it had drawn nothing at any distance, and
/// the scene's box had lost its height).
#[test]
fn a_horizon_with_lines_of_holes_is_found_under_its_all_hole_tiles() {
    use strata_common::scene::{Backend, Camera};
    use strata_tests::scenes::{exact_settings, horizon_layer, horizon_store, render_whole, scene};
    let dir = tempfile::tempdir().unwrap();
    let n = 300u64;
    let heights: Vec<f32> = (0..n * n)
        .map(|i| if (i / n) % 4 == 3 { f32::NAN } else { 5.0 })
        .collect();
    let p = horizon_store(
        dir.path(),
        "picked",
        [n, n],
        heights,
        strata_common::geo::Affine3::IDENTITY,
        128,
    );
    let store = PageStore::open(&p).unwrap();
    let root = store.index().last().unwrap();
    assert_eq!(root.valid, 0, "the root tile is all holes (the premise)");
    assert_eq!((root.min, root.max), (5.0, 5.0));
    let mut r = exact_settings(9, 9);
    r.lighting = false;
    r.backend = Backend::Cpu;
    // Close above the middle, looking down: the picked lines fill the view.
    let s = scene(
        vec![],
        vec![horizon_layer(p, [0.2, 0.6, 0.3], 1.0)],
        Camera {
            eye: [150.0, 150.5, 40.0],
            target: [150.0, 150.5, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_deg: 10.0,
        },
        r,
    );
    let img = render_whole(&s);
    let hit = img.iter().filter(|p| p[3] > 0.5).count();
    assert!(hit > 40, "{hit} of 81 pixels of the horizon were drawn");
}

/// The same kind of horizon seen from far away, where its footprint calls for coarse
/// levels: those levels are holes (level 1 keeps isolated lines of nodes, no cell; level 2
/// up keeps nothing), so both casters descend past them to level 0 (`ENTRY_FRAGMENTED`)
/// and the frame is the one drawn with level 0 forced, pixel for pixel. It had drawn
/// nothing: a horizon picked on every fourth line vanished from every distant view.
#[test]
fn a_distant_horizon_with_lines_of_holes_is_drawn_from_its_finest_level() {
    use strata_common::scene::Camera;
    use strata_tests::scenes::{
        bit_identical, exact_settings, horizon_layer, horizon_store, max_diff, render_on_both,
        scene,
    };
    let dir = tempfile::tempdir().unwrap();
    let n = 1200u64;
    let heights: Vec<f32> = (0..n * n)
        .map(|i| {
            let (x, y) = ((i % n) as f32, (i / n) as f32);
            if (i / n) % 4 == 3 {
                f32::NAN
            } else {
                5.0 + 0.01 * x + 0.02 * y
            }
        })
        .collect();
    let p = horizon_store(
        dir.path(),
        "picked",
        [n, n],
        heights,
        strata_common::geo::Affine3::IDENTITY,
        32,
    );
    let levels = PageStore::open(&p).unwrap().pyramid().level_count();
    assert!(levels >= 5, "{levels} levels");
    // 96² pixels of 30°: 16 nodes per pixel at the surface, so level 3 is what τ = 0.5
    // calls for.
    let view = |tau: f64| {
        let mut r = exact_settings(96, 96);
        r.lighting = false;
        r.tau = tau;
        scene(
            vec![],
            vec![horizon_layer(p.clone(), [0.2, 0.6, 0.3], 1.0)],
            Camera {
                eye: [600.0, 600.5, 2866.0],
                target: [600.0, 600.5, 0.0],
                up: [0.0, 1.0, 0.0],
                fov_deg: 30.0,
            },
            r,
        )
    };
    let far = render_on_both(&view(0.5), 1e-5, "lines of holes, far");
    let finest = render_on_both(&view(1e-3), 1e-5, "lines of holes, level 0 forced");
    assert!(
        bit_identical(&far, &finest),
        "the distant frame differs from level 0's by {}",
        max_diff(&far, &finest)
    );
    // Half of the surface's cells are whole (rows 0–1 and 1–2 of every four): about half of
    // the ~75² pixels over it are drawn.
    let hit = far.iter().filter(|p| p[3] > 0.5).count();
    assert!(
        (1800..3900).contains(&hit),
        "{hit} pixels of the horizon drawn"
    );
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, .. ProptestConfig::default() })]
    #[test]
    fn round_trip_any_dims(nx in 1u64..80, ny in 1u64..50, nz in 1u64..70,
                           t in prop::sample::select(vec![SampleType::U8, SampleType::I16, SampleType::F32]),
                           border in 1u32..=2) {
        let f = if t.is_signed() { CoarsenFilter::SignedRms } else { CoarsenFilter::Mean };
        assert_round_trip([nx, ny, nz], t, 32, border, f, Compression::Lz4, 200 << 10);
    }
}

#[test]
fn singular_transforms_are_refused_at_build_and_at_open() {
    use std::io::{Seek, SeekFrom, Write};
    use strata_common::geo::Affine3;
    use strata_common::store::Preamble;
    let dims = [8, 8, 8];
    let src = MemorySource {
        dims,
        data: vec![1.0; 512],
    };
    let dir = tempfile::tempdir().unwrap();
    // A zero sample step makes the grid flat: the builder refuses it, leaving nothing.
    let mut o = BuildOptions::volume("t", SampleType::F32);
    o.transform = Affine3::from_lateral(&strata_common::geo::Affine2::IDENTITY, 0.0, 0.0);
    let err = build_store(
        &src,
        &dir.path().join("flat.strata"),
        &o,
        &ProgressBar::hidden(),
    )
    .unwrap_err();
    assert!(format!("{err:#}").contains("invertible"), "{err:#}");
    assert!(std::fs::read_dir(dir.path()).unwrap().next().is_none());

    // A crafted store (CRCs right) with such a transform: the store reader refuses it, so
    // the worker never gets to invert the transform for its rays.
    let path = dir.path().join("v.strata");
    build_store(
        &src,
        &path,
        &BuildOptions::volume("t", SampleType::F32),
        &ProgressBar::hidden(),
    )
    .unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let mut pre = Preamble::decode(&path, &bytes[..64]).unwrap();
    let mut h = PageStore::open(&path).unwrap().header().clone();
    h.transform.rows[2][2] = 0.0;
    let hb = bincode::serde::encode_to_vec(&h, bincode::config::standard()).unwrap();
    assert_eq!(hb.len() as u64, pre.header_len);
    pre.header_crc = crc32c::crc32c(&hb);
    let mut f = std::fs::OpenOptions::new().write(true).open(&path).unwrap();
    f.write_all(&pre.encode()).unwrap();
    f.seek(SeekFrom::Start(pre.header_offset)).unwrap();
    f.write_all(&hb).unwrap();
    drop(f);
    let layer: strata_common::scene::VolumeLayer =
        toml::from_str(&format!("store = {:?}", path.display().to_string())).unwrap();
    let err = strata_worker::dataset::Volume::open(&layer, 0)
        .err()
        .expect("refused");
    let e = format!("{err:#}");
    assert!(e.contains("v.strata") && e.contains("invertible"), "{e}");
}
