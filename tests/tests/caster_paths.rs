//! The CPU caster's faster paths change no pixel: macrocell skipping on against off, and
//! atlas slots in the data's own sample type (u8, i16, u16) against f32 slots. Both are exact
//! by construction (a skipped sample would have had zero opacity; an integer decodes to the
//! same f32), so the images must be identical, not merely close. Under pre-integration
//! cells are crossed (sampled at their first and last lattice points), and the image stays
//! within 1e-6 of the one without cells (0 in these scenes).

use indicatif::ProgressBar;
use std::path::{Path, PathBuf};
use strata_common::camera::View;
use strata_common::image::Rgba;
use strata_common::sample::SampleType;
use strata_common::scene::{Backend, Camera, Scene};
use strata_coordinator::builder::{build_store, BuildOptions};
use strata_coordinator::source::MemorySource;
use strata_tests::scenes::*;
use strata_worker::engine::{Engine, Outcome};
use strata_worker::raycast::CastStats;
use tempfile::TempDir;

const N: u64 = 100;

/// A blobby field on `N`³: mostly empty (value 0) with a few smooth lumps, a thin shell and
/// scattered single bright voxels (the hardest case for a skip that lands a little late: an
/// isolated voxel right past an empty cell), as integers in `0..=max`, so that macrocells
/// inside bricks are often empty.
fn blobs(max: f32) -> Vec<f32> {
    let n = N as usize;
    let centres = [
        [30.0, 40.0, 50.0, 14.0],
        [70.0, 65.0, 30.0, 10.0],
        [55.0, 20.0, 75.0, 8.0],
    ];
    (0..n * n * n)
        .map(|i| {
            let p = [(i % n) as f32, (i / n % n) as f32, (i / (n * n)) as f32];
            let mut v = 0.0f32;
            for c in centres {
                let d =
                    ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2) + (p[2] - c[2]).powi(2)).sqrt();
                v = v.max(1.0 - d / c[3]);
            }
            // A thin shell of radius 45 around the middle.
            let r = ((p[0] - 50.0).powi(2) + (p[1] - 50.0).powi(2) + (p[2] - 50.0).powi(2)).sqrt();
            if (r - 45.0).abs() < 0.8 && p[0] > 70.0 {
                v = v.max(0.6);
            }
            // Thin planes one voxel thick, at depths that fall at different offsets from
            // the macrocell faces of their bricks, with empty space before them.
            if [17.0, 37.0, 48.0, 79.0].contains(&p[2]) && p[0] < 60.0 && p[1] < 50.0 {
                v = v.max(0.7);
            }
            // Isolated voxels, about one in 20000.
            if (i as u64).wrapping_mul(2654435761) % 20000 == 7 {
                v = 0.9;
            }
            (v.max(0.0) * max).round()
        })
        .collect()
}

fn store(dir: &Path, name: &str, t: SampleType, data: Vec<f32>) -> PathBuf {
    store_with(dir, name, t, None, data)
}

fn store_with(
    dir: &Path,
    name: &str,
    t: SampleType,
    no_data: Option<f32>,
    data: Vec<f32>,
) -> PathBuf {
    // Cores of 62: 4 macrocells of 16 per edge, two bricks per axis.
    store_sized(dir, name, t, no_data, N, 64, data)
}

/// A store of `n`³ samples in pages of `page` (border 1).
fn store_sized(
    dir: &Path,
    name: &str,
    t: SampleType,
    no_data: Option<f32>,
    n: u64,
    page: u32,
    data: Vec<f32>,
) -> PathBuf {
    let path = dir.join(format!("{name}.strata"));
    let mut o = BuildOptions::volume(name, t);
    o.page_size = page;
    o.border = 1;
    o.no_data = no_data;
    build_store(
        &MemorySource {
            dims: [n, n, n],
            data,
        },
        &path,
        &o,
        &ProgressBar::hidden(),
    )
    .unwrap();
    path
}

fn cameras() -> Vec<Camera> {
    let c = [49.5, 49.5, 49.5];
    vec![
        // Oblique, from outside.
        Camera {
            eye: [-60.0, -35.0, 140.0],
            target: c,
            up: [0.0, 0.0, 1.0],
            fov_deg: 40.0,
        },
        // Exactly along the grid axis: rays run along macrocell and brick faces.
        Camera {
            eye: [48.0, 48.0, -120.0],
            target: [48.0, 48.0, 50.0],
            up: [0.0, 1.0, 0.0],
            fov_deg: 30.0,
        },
        // Inside the volume, looking out through the shell.
        Camera {
            eye: [50.3, 47.1, 52.9],
            target: [95.0, 80.0, 10.0],
            up: [0.0, 0.0, 1.0],
            fov_deg: 70.0,
        },
        // Far away: coarser levels and steps (the cells of ancestor pages are used).
        Camera {
            eye: [900.0, 700.0, 1200.0],
            target: c,
            up: [0.0, 0.0, 1.0],
            fov_deg: 8.0,
        },
    ]
}

fn scene_for(store: PathBuf, window: [f64; 2], cam: Camera) -> Scene {
    // Zero opacity below 20 % of the window: the low values are empty space.
    scene_with(
        store,
        window,
        cam,
        vec![[0.0, 0.0], [0.2, 0.0], [0.5, 0.3], [1.0, 0.8]],
    )
}

fn scene_with(store: PathBuf, window: [f64; 2], cam: Camera, opacity: Vec<[f64; 2]>) -> Scene {
    let mut s = scene(
        vec![volume_layer(store, "viridis", window, opacity)],
        vec![],
        cam,
        exact_settings(72, 56),
    );
    s.render.backend = Backend::Cpu;
    s.render.tau = 2.0;
    s
}

struct Rendered {
    image: Vec<Rgba>,
    stats: CastStats,
    bytes_per_voxel: usize,
}

fn render(s: &Scene) -> Rendered {
    let mut e = Engine::new(s).unwrap();
    let view = e.view(s.render.width, s.render.height).unwrap();
    let region = e.scene_region();
    let r = e.render_batch(&view, &region).unwrap();
    assert_eq!(r.outcome, Outcome::Converged);
    Rendered {
        image: r.image.to_full(),
        stats: r.last,
        bytes_per_voxel: e.cpu_atlas_bytes_per_voxel().unwrap(),
    }
}

fn identical(a: &[Rgba], b: &[Rgba]) -> bool {
    a.len() == b.len()
        && a.iter()
            .zip(b)
            .all(|(p, q)| p.iter().zip(q).all(|(x, y)| x.to_bits() == y.to_bits()))
}

#[test]
fn macrocell_skipping_takes_fewer_samples_and_changes_no_pixel() {
    let dir = TempDir::new().unwrap();
    let st = store(dir.path(), "blobs", SampleType::F32, blobs(100.0));
    let mut gained = 0;
    for (i, cam) in cameras().into_iter().enumerate() {
        for shading in [false, true] {
            let mut s = scene_for(st.clone(), [0.0, 100.0], cam.clone());
            s.render.volume_shading = shading;
            s.render.macrocells = false;
            let off = render(&s);
            s.render.macrocells = true;
            let on = render(&s);
            assert_clean(&on.image);
            assert!(
                on.image.iter().filter(|p| p[3] > 0.01).count() > 50,
                "camera {i}: the view shows the data"
            );
            assert!(
                identical(&on.image, &off.image),
                "camera {i}, shading {shading}: macrocells change the image by {}",
                max_diff(&on.image, &off.image)
            );
            // Every lattice point is either sampled or skipped, with or without cells.
            assert_eq!(
                on.stats.samples + on.stats.skipped,
                off.stats.samples + off.stats.skipped,
                "camera {i}"
            );
            assert!(on.stats.samples <= off.stats.samples, "camera {i}");
            if on.stats.samples * 10 < off.stats.samples * 9 {
                gained += 1;
            }
        }
    }
    assert!(
        gained >= 4,
        "macrocells saved 10 % of the samples in only {gained} of 8 views"
    );
}

/// Pre-integration crosses an invisible cell rather than skipping it (its first and last
/// lattice points are sampled, so the segments into and out of it are integrated from real
/// values): the image is the one without cells but for the segments between two values of
/// the cell's range, which cells leave out and the march without them looks up, and which
/// are clear up to the pre-integrated table's bilinear interpolation next to the range.
#[test]
fn preintegrated_macrocells_cross_invisible_cells() {
    let dir = TempDir::new().unwrap();
    let st = store(dir.path(), "blobs", SampleType::F32, blobs(100.0));
    let mut gained = 0;
    for (i, cam) in cameras().into_iter().enumerate() {
        for step in [0.5, 2.0] {
            let mut s = scene_for(st.clone(), [0.0, 100.0], cam.clone());
            s.render.preintegrated = true;
            s.render.step = step;
            s.render.macrocells = false;
            let off = render(&s);
            s.render.macrocells = true;
            let on = render(&s);
            assert_clean(&on.image);
            let d = max_diff(&on.image, &off.image);
            // (0 in every view here: the table is exactly clear over the cells' ranges.)
            assert!(
                d <= 1e-6,
                "camera {i}, step {step}: macrocells change the pre-integrated image by {d}"
            );
            assert_eq!(
                on.stats.samples + on.stats.skipped,
                off.stats.samples + off.stats.skipped,
                "camera {i}"
            );
            if on.stats.samples * 10 < off.stats.samples * 9 {
                gained += 1;
            }
        }
    }
    assert!(
        gained >= 4,
        "crossing cells saved 10 % of the samples in only {gained} of 8 views"
    );
}

/// Crossing a cell must start the segment out of it at the cell's last lattice point: a
/// value that climbs slowly through a cell the transfer function hides and jumps right past
/// it (the blobs' empty cells hold only zeros, where first and last point agree). For every
/// position of the jump against the cells, pre-integration with cells gives the image
/// without them.
#[test]
fn preintegrated_crossing_starts_the_next_segment_at_the_cells_last_point() {
    let dir = TempDir::new().unwrap();
    let mut crossed = 0;
    // Steps 4 and 6 put the cell's last lattice point right before the jump for some zj
    // (the cell's margin sample must stay clear, so at step 2 the next sample is too).
    for (step, zj) in [2.0, 4.0, 6.0]
        .into_iter()
        .flat_map(|s| (14..22u64).map(move |z| (s, z)))
    {
        let st = dir.path().join(format!("jump{zj}.strata"));
        if !st.exists() {
            let data: Vec<f32> = (0..4 * 4 * 48u64)
                .map(|i| {
                    let z = i / 16;
                    if z < zj {
                        0.25 * z as f32 / zj as f32
                    } else {
                        0.9
                    }
                })
                .collect();
            let name = format!("jump{zj}");
            let affine = strata_common::geo::Affine3::IDENTITY;
            volume_store(dir.path(), &name, [4, 4, 48], data, affine, 32);
        }
        let cam = Camera {
            eye: [1.5, 1.5, -50.0],
            target: [1.5, 1.5, 10.0],
            up: [0.0, 1.0, 0.0],
            fov_deg: 0.1,
        };
        let mut s = scene_with(
            st,
            [0.0, 1.0],
            cam,
            vec![[0.0, 0.0], [0.3, 0.0], [0.35, 0.5], [1.0, 0.5]],
        );
        (s.render.width, s.render.height) = (3, 3);
        s.render.step = step;
        s.render.adaptive_step = false;
        s.render.preintegrated = true;
        s.render.macrocells = false;
        let off = render(&s);
        s.render.macrocells = true;
        let on = render(&s);
        let d = max_diff(&on.image, &off.image);
        assert!(
            d <= 1e-6,
            "jump at z = {zj}, step {step}: crossing cells changes the image by {d}"
        );
        assert!(
            off.image[4][3] > 0.3,
            "jump at z = {zj}, step {step}: the ray sees the jump"
        );
        if on.stats.samples < off.stats.samples {
            crossed += 1;
        }
    }
    assert!(crossed >= 4, "only {crossed} rays crossed a cell");
}

#[test]
fn compact_slots_give_the_f32_image() {
    let dir = TempDir::new().unwrap();
    for (t, max, bytes) in [
        (SampleType::U8, 255.0, 1),
        (SampleType::U16, 65535.0, 2),
        (SampleType::I16, 32767.0, 2),
        (SampleType::I8, 127.0, 1),
    ] {
        let name = format!("{t:?}");
        let mut data = blobs(max);
        let signed = matches!(t, SampleType::I16 | SampleType::I8);
        if signed {
            // Negative values too: the window spans both signs.
            for (i, v) in data.iter_mut().enumerate() {
                if i % 7 == 0 {
                    *v = -*v;
                }
            }
        }
        let window = if signed {
            [-max as f64, max as f64]
        } else {
            [0.0, max as f64]
        };
        let st = store(dir.path(), &name, t, data);
        for (i, cam) in cameras().into_iter().enumerate().take(3) {
            let mut s = scene_for(st.clone(), window, cam);
            s.render.compact_slots = false;
            let wide = render(&s);
            s.render.compact_slots = true;
            let compact = render(&s);
            assert_eq!(wide.bytes_per_voxel, 4);
            assert_eq!(compact.bytes_per_voxel, bytes, "{name}");
            assert!(compact.image.iter().any(|p| p[3] > 0.01), "{name}: blank");
            assert!(
                identical(&compact.image, &wide.image),
                "{name}, camera {i}: compact slots change the image by {}",
                max_diff(&compact.image, &wide.image)
            );
            assert_eq!(compact.stats, wide.stats, "{name}, camera {i}");
        }
    }
}

#[test]
fn a_volume_with_no_data_values_keeps_f32_slots() {
    let dir = TempDir::new().unwrap();
    let mut data = blobs(255.0);
    for v in data.iter_mut().step_by(5) {
        *v = f32::NAN;
    }
    let path = store_with(dir.path(), "nd", SampleType::U8, Some(0.0), data);
    let s = scene_for(path, [0.0, 255.0], cameras()[0].clone());
    let r = render(&s);
    // A decoded no-data sample is NaN, which no u8 holds: the atlas stays f32.
    assert_eq!(r.bytes_per_voxel, 4);
    assert_clean(&r.image);
}

/// The cell ranges are computed from the page as it enters the atlas: an atlas too small
/// for the working set, whose slots are reused for other pages as the view changes, still
/// gives the images with macrocells that it gives without.
#[test]
fn macrocells_follow_slot_reuse() {
    let dir = TempDir::new().unwrap();
    let st = store(dir.path(), "reuse", SampleType::U8, blobs(255.0));
    let cams = cameras();
    let mut s = scene_for(st, [0.0, 255.0], cams[0].clone());
    // 64³ u8 pages: 256 KiB each, so 1 MiB holds 4 slots, fewer than the views need.
    s.render.atlas_mb = 1;
    s.render.tau = 0.5;
    s.render.max_rounds = 8;
    let run = |cells: bool| {
        let mut s = s.clone();
        s.render.macrocells = cells;
        // One engine throughout (its atlas keeps its slots); only the view changes.
        let mut e = Engine::new(&s).unwrap();
        let region = e.scene_region();
        let mut images = Vec::new();
        let mut full = 0;
        for k in 0..6 {
            let cam = &cams[[0, 2, 1][k % 3]];
            let view = View::new(cam, &s.render, s.render.width, s.render.height).unwrap();
            let r = e.render_batch(&view, &region).unwrap();
            full += (r.outcome == Outcome::AtlasFull) as u32;
            images.push(r.image.to_full());
        }
        (images, full)
    };
    let (on, full) = run(true);
    let (off, _) = run(false);
    assert!(full > 0, "the atlas was large enough: nothing was reused");
    for (k, (a, b)) in on.iter().zip(&off).enumerate() {
        assert!(identical(a, b), "view {k}: differ by {}", max_diff(a, b));
    }
}

/// SIMD packets of both widths against the scalar march: the same pixels bit for bit, the
/// same counters and the same page requests, for every slot type, with NaN samples, early
/// termination, several sampling bands (the far camera) and macrocells on and off.
#[test]
fn packets_and_the_scalar_march_agree_bit_for_bit() {
    let widest = strata_worker::packet::widest();
    // CI names the width its CPU runs (.ci/run, from /proc/cpuinfo): the run detection must
    // find it, or the 16-lane march would silently be the 8-lane one (or both scalar).
    if let Ok(lanes) = std::env::var("STRATA_REQUIRE_SIMD_LANES") {
        assert_eq!(
            widest.to_string(),
            lanes,
            "STRATA_REQUIRE_SIMD_LANES: this CPU's flags promise {lanes}-lane packets"
        );
    }
    if widest < 16 {
        eprintln!("NOTICE: no AVX-512 here: 16-lane packets run as {widest} lanes (0: scalar)");
    }
    let dir = TempDir::new().unwrap();
    let mut nan = blobs(100.0);
    for v in nan.iter_mut().step_by(11) {
        *v = f32::NAN;
    }
    let empty_low = vec![[0.0, 0.0], [0.2, 0.0], [0.5, 0.3], [1.0, 0.8]];
    // The lowest value shows too: a NaN sample that leaked into the lookup would show.
    let visible_low = vec![[0.0, 0.4], [0.2, 0.0], [0.5, 0.3], [1.0, 0.8]];
    let stores = [
        (
            store(dir.path(), "f", SampleType::F32, nan),
            [0.0, 100.0],
            &visible_low,
        ),
        (
            store(dir.path(), "u", SampleType::U8, blobs(255.0)),
            [0.0, 255.0],
            &empty_low,
        ),
        (
            store(dir.path(), "i", SampleType::I16, blobs(3000.0)),
            [-10.0, 3000.0],
            &empty_low,
        ),
    ];
    for (st, window, opacity) in &stores {
        for (i, cam) in cameras().into_iter().enumerate() {
            for (ert, cells) in [(1.0, true), (0.9, true), (0.95, false)] {
                let mut s = scene_with(st.clone(), *window, cam.clone(), opacity.to_vec());
                s.render.early_termination = ert;
                s.render.macrocells = cells;
                s.render.tau = 1.0;
                // `None`: the scalar march; else packets of that many lanes.
                let run = |lanes: Option<u32>| {
                    let mut s = s.clone();
                    s.render.simd = lanes.is_some();
                    s.render.simd_lanes = lanes.unwrap_or(0);
                    let mut e = Engine::new(&s).unwrap();
                    let view = e.view(s.render.width, s.render.height).unwrap();
                    let region = e.scene_region();
                    let b = e.render_batch(&view, &region).unwrap();
                    assert_eq!(b.outcome, Outcome::Converged);
                    let f = e.render_frame(&view, &region).unwrap();
                    let mut fb: Vec<(u64, u32)> =
                        f.feedback.coverage.iter().map(|(&k, &c)| (k, c)).collect();
                    fb.sort_unstable();
                    let lanes = lanes.map_or(0, strata_worker::packet::lanes_for);
                    let path = if lanes == 8 {
                        " simd".to_string()
                    } else if lanes > 0 {
                        format!(" simd{lanes}")
                    } else {
                        " scalar".to_string()
                    };
                    assert!(f.variant_name.ends_with(&path), "{}", f.variant_name);
                    (f.image.to_full(), f.stats, fb)
                };
                let (si, ss, sf) = run(None);
                for lanes in [8, 16] {
                    let (pi, ps, pf) = run(Some(lanes));
                    let what = format!(
                        "{}, camera {i}, ERT {ert}, cells {cells}, {lanes} lanes",
                        st.display()
                    );
                    assert!(pi.iter().any(|p| p[3] > 0.01), "{what}: blank");
                    assert!(
                        bit_identical(&pi, &si),
                        "{what}: packets differ by {}",
                        max_diff(&pi, &si)
                    );
                    assert_eq!(ps, ss, "{what}: counters");
                    assert_eq!(pf, sf, "{what}: page requests");
                    if ert < 1.0 && i < 3 {
                        assert!(ps.terminated > 0, "{what}: no ray terminated early");
                    }
                }
            }
        }
    }
}

/// `render.simd_lanes` takes 0, 8 or 16; anything else is refused by name.
#[test]
fn simd_lanes_other_than_0_8_16_are_refused() {
    let dir = TempDir::new().unwrap();
    let st = store(dir.path(), "u", SampleType::U8, blobs(255.0));
    let opacity = vec![[0.0, 0.0], [1.0, 0.8]];
    for (lanes, ok) in [
        (0, true),
        (8, true),
        (16, true),
        (4, false),
        (12, false),
        (32, false),
    ] {
        let mut s = scene_with(
            st.clone(),
            [0.0, 255.0],
            cameras()[0].clone(),
            opacity.clone(),
        );
        s.render.simd_lanes = lanes;
        match Engine::new(&s) {
            Ok(_) => assert!(ok, "{lanes} lanes accepted"),
            Err(e) => {
                assert!(!ok, "{lanes} lanes refused: {e:#}");
                let m = format!("{e:#}");
                assert!(
                    m.contains("render.simd_lanes") && m.contains(&lanes.to_string()),
                    "{m}"
                );
            }
        }
    }
}

/// Runs of transparent bricks are jumped as one cube (`VolFrame::transparent_runs`): on a
/// volume of 5 × 5 × 5 small bricks with one lump in a corner, shells of thin planes and
/// isolated voxels, mostly empty, brick skipping gives the image of no skipping at all,
/// bit for bit, with every lattice point either sampled or skipped, from every camera
/// (one looks exactly along the grid), on the scalar march and on the packets.
#[test]
fn transparent_brick_runs_change_no_pixel() {
    let dir = TempDir::new().unwrap();
    // 150³ in cores of 30: 5 bricks per axis at level 0.
    const M: u64 = 150;
    let n = M as usize;
    let data: Vec<f32> = (0..n * n * n)
        .map(|i| {
            let p = [i % n, i / n % n, i / (n * n)];
            let d2 = p.iter().map(|&x| (x as f32 - 120.0).powi(2)).sum::<f32>();
            let lump = (1.0 - d2.sqrt() / 20.0).max(0.0);
            // A plane one voxel thick past a long empty stretch, and isolated voxels.
            let plane = (p[2] == 70 && p[0] < 40 && p[1] > 90) as u32 as f32 * 0.8;
            let speck = ((i as u64).wrapping_mul(2654435761) % 400000 == 11) as u32 as f32 * 0.9;
            (lump.max(plane).max(speck) * 100.0).round()
        })
        .collect();
    let path = store_sized(dir.path(), "runs", SampleType::F32, None, M, 32, data);
    let opacity = vec![[0.0, 0.0], [0.05, 0.0], [0.5, 0.4], [1.0, 0.9]];
    let (mut jumped, mut shown) = (0, 0);
    // The other tests' cameras, scaled to this volume.
    let cams = cameras().into_iter().map(|c| Camera {
        eye: c.eye.map(|x| x * 1.5),
        target: c.target.map(|x| x * 1.5),
        ..c
    });
    for (i, cam) in cams.enumerate() {
        for simd in [true, false] {
            let mut s = scene_with(path.clone(), [0.0, 100.0], cam.clone(), opacity.clone());
            s.render.simd = simd;
            // Level 0 near the camera: the finest bricks.
            s.render.tau = 0.25;
            s.render.macrocells = false;
            s.render.empty_space_skipping = false;
            let all = render(&s);
            s.render.empty_space_skipping = true;
            let skip = render(&s);
            let what = format!("camera {i}, simd {simd}");
            shown += skip.image.iter().filter(|p| p[3] > 0.01).count();
            assert!(
                identical(&skip.image, &all.image),
                "{what}: brick skipping changes the image by {}",
                max_diff(&skip.image, &all.image)
            );
            assert_eq!(
                skip.stats.samples + skip.stats.skipped,
                all.stats.samples,
                "{what}: lattice points"
            );
            jumped += (skip.stats.skipped > skip.stats.samples) as u32;
        }
    }
    assert!(shown > 500, "the views show little: {shown} pixels");
    assert!(
        jumped >= 4,
        "most of the lattice should be skipped in most views: {jumped}"
    );
}

/// Selective feedback rounds (`render.selective_rounds`), with and without early loads
/// (`render.early_loads`): after a round that loads pages,
/// only the tiles whose rays asked for a missing page are cast again. With 4 uploads per
/// round the batch takes many rounds, in which most tiles already had their pages: the
/// converged image, its counters, the rounds and the outcome are those of casting every
/// tile each round, bit for bit, for less work. A mask that marks too few tiles fails it
/// (tried: the tiles all of whose pages were missing instead of any); one that marks all
/// fails the check on the work saved.
#[test]
fn selective_rounds_cast_less_and_change_no_pixel() {
    let dir = TempDir::new().unwrap();
    let st = store_sized(
        dir.path(),
        "blobs32",
        SampleType::F32,
        None,
        N,
        32,
        blobs(100.0),
    );
    // A wavy opaque horizon through the blobs (its tiles are pages too).
    let n = N as usize;
    let heights: Vec<f32> = (0..n * n)
        .map(|i| 50.0 + 12.0 * ((i % n) as f32 * 0.11).sin() * ((i / n) as f32 * 0.07).cos())
        .collect();
    let hor = horizon_store(
        dir.path(),
        "wave",
        [N, N],
        heights,
        strata_common::geo::Affine3::IDENTITY,
        32,
    );
    let mut saved = 0;
    for (i, cam) in cameras().into_iter().enumerate() {
        // simd, shading (the scalar march), a horizon (surfaces and the volume together).
        for (simd, shading, horizon) in [
            (true, false, false),
            (false, false, false),
            (false, true, false),
            (true, false, true),
        ] {
            let mut s = scene_for(st.clone(), [0.0, 100.0], cam.clone());
            s.render.width = 160;
            s.render.height = 120;
            s.render.simd = simd;
            s.render.volume_shading = shading;
            if horizon {
                s.horizons = vec![horizon_layer(hor.clone(), [0.9, 0.6, 0.2], 1.0)];
            }
            s.render.upload_pages_per_frame = 4;
            s.render.max_rounds = 400;
            let run = |selective: bool, early: bool| {
                let mut s = s.clone();
                s.render.selective_rounds = selective;
                s.render.early_loads = early;
                let mut e = Engine::new(&s).unwrap();
                let view = e.view(s.render.width, s.render.height).unwrap();
                let region = e.scene_region();
                e.render_batch(&view, &region).unwrap()
            };
            let what = format!("camera {i}, simd {simd}, shading {shading}, horizon {horizon}");
            let all = run(false, false);
            let sel = run(true, false);
            // Loads started while the frame is cast (`render.early_loads`) change nothing
            // either: the atlas changes only between rounds.
            let early = run(true, true);
            assert!(
                identical(&early.image.to_full(), &sel.image.to_full())
                    && early.last == sel.last
                    && early.rounds == sel.rounds
                    && early.outcome == sel.outcome,
                "{what}: early loads change the frame"
            );
            assert_eq!(all.outcome, Outcome::Converged, "camera {i}");
            assert!(all.rounds >= 3, "camera {i}: {} rounds", all.rounds);
            eprintln!(
                "{what}: {} rounds, {} samples cast against {}",
                all.rounds, sel.total.samples, all.total.samples
            );
            let (a, b) = (all.image.to_full(), sel.image.to_full());
            assert!(
                b.iter().filter(|p| p[3] > 0.01).count() > 200,
                "camera {i}: the view shows the data"
            );
            assert!(
                identical(&a, &b),
                "{what}: selective rounds change the image by {}",
                max_diff(&a, &b)
            );
            assert_eq!(sel.last, all.last, "{what}");
            assert_eq!(
                (sel.rounds, sel.outcome),
                (all.rounds, all.outcome),
                "camera {i}"
            );
            assert!(sel.total.samples <= all.total.samples, "camera {i}");
            if sel.total.samples * 10 < all.total.samples * 9 {
                saved += 1;
            }
        }
    }
    assert!(
        saved >= 8,
        "selective rounds saved 10 % of the samples in only {saved} of 16 batches"
    );
}

/// With `Engine::tile_cpu_clock` on (as worker nodes have it), each tile reports its
/// thread's CPU time besides its wall time, and the batch sums the converged tiles' CPU time
/// (what a re-split by `cluster.rebalance_clock = "cpu"` measures); off, none. A thread's CPU time over an interval cannot exceed that interval's wall time:
/// the process's CPU time (every thread's) would, with tiles cast in parallel.
#[test]
fn tiles_report_their_threads_cpu_time() {
    assert!(strata_worker::raycast::thread_cpu_seconds().is_some());
    let dir = TempDir::new().unwrap();
    let st = store(dir.path(), "blobs", SampleType::F32, blobs(100.0));
    let mut s = scene_for(st, [0.0, 100.0], cameras().remove(0));
    s.render.width = 192;
    s.render.height = 160;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let (r, untimed) = pool.install(|| {
        let mut e = Engine::new(&s).unwrap();
        let view = e.view(s.render.width, s.render.height).unwrap();
        let region = e.scene_region();
        // Off unless asked for (two system calls per tile): no CPU time.
        let untimed = e.render_batch(&view, &region).unwrap();
        // A second batch with everything resident: one round, every tile cast.
        e.tile_cpu_clock = true;
        (e.render_batch(&view, &region).unwrap(), untimed)
    });
    assert_eq!(untimed.last_cpu_seconds, None);
    assert!(untimed.tiles.iter().all(|t| t.cpu_seconds == 0.0));
    assert_eq!(r.rounds, 1);
    assert!(r.tiles.len() >= 4, "{} tiles", r.tiles.len());
    let sum: f64 = r.tiles.iter().map(|t| t.cpu_seconds).sum();
    // The CPU backend with a thread clock says how much: the tiles' sum.
    assert!(
        sum > 0.0 && r.last_cpu_seconds == Some(sum),
        "{:?} against {sum}",
        r.last_cpu_seconds
    );
    // A region behind the camera casts no tile: 0 s of CPU, a measurement (not `None`, which
    // says that nothing timed the cast and sends a re-split to wall time).
    let behind = pool.install(|| {
        let mut e = Engine::new(&s).unwrap();
        e.tile_cpu_clock = true;
        let view = e.view(s.render.width, s.render.height).unwrap();
        let region = strata_common::kd::Region {
            lo: [-300.0, -200.0, 250.0],
            hi: [-250.0, -150.0, 300.0],
        };
        e.render_batch(&view, &region).unwrap()
    });
    assert!(behind.tiles.iter().all(|t| t.cpu_seconds == 0.0));
    assert_eq!(behind.last_cpu_seconds, Some(0.0));
    for (i, t) in r.tiles.iter().enumerate() {
        // 50 µs for the two clocks' reads not being one instant.
        assert!(
            t.cpu_seconds >= 0.0 && t.cpu_seconds <= t.seconds + 5e-5,
            "tile {i}: {} s of CPU in {} s",
            t.cpu_seconds,
            t.seconds
        );
    }
}
