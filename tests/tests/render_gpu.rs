//! The GPU backend against the CPU backend, and the sort-last invariants on the GPU.
//!
//! Both backends read the same atlas bookkeeping, page tables and transfer-function tables
//! (`strata_common::gpu`); the WGSL caster interpolates trilinearly in the shader
//! (`exact` filtering), so its images must match the CPU's to 1e-4 (2.5e-4 for pre-integrated
//! spans with shading on a hardware GPU, measured at 1.05e-4 on an H200), and a region split on the GPU must
//! composite to the whole GPU image within 1e-5. Lavapipe (CI) gives the CPU's images bit for
//! bit; a hardware GPU differs in the last bits (fused multiply-adds, 2.5-ulp division).
//!
//! On a machine without any wgpu adapter these tests print a notice and pass, unless
//! `STRATA_REQUIRE_GPU_ADAPTER=1` (CI sets it, with lavapipe installed): then they fail.

use std::path::Path;
use strata_common::kd::KdTree;
use strata_common::sample::SampleType;
use strata_common::scene::{Backend, Scene};
use strata_tests::scenes::*;
use strata_worker::engine::{Engine, Outcome};
use tempfile::TempDir;

fn on(s: &Scene, b: Backend) -> Scene {
    on_backend(s, b)
}

/// Opens the scene on the GPU backend (asserting it took a GPU adapter) and converges one
/// batch of the whole scene at its render size.
fn gpu_batch(
    s: &Scene,
) -> (
    Engine,
    strata_common::camera::View,
    strata_common::kd::Region,
    strata_worker::engine::BatchResult,
) {
    let mut e = Engine::new(&on(s, Backend::Gpu)).unwrap();
    assert!(
        e.backend_name().starts_with("gpu: "),
        "{}",
        e.backend_name()
    );
    let view = e.view(s.render.width, s.render.height).unwrap();
    let region = e.scene_region();
    let r = e.render_batch(&view, &region).unwrap();
    assert_eq!(r.outcome, Outcome::Converged, "{:?}", r.reports);
    (e, view, region, r)
}

/// A synthetic survey's seismic volume alone (UTM coordinates, z down).
fn survey_volume(dir: &Path, size: [u64; 3], page: u32, w: u32, h: u32) -> Scene {
    let out =
        strata_coordinator::synth::synth(dir, size, 5, false, &indicatif::ProgressBar::hidden())
            .unwrap();
    let mut s = Scene::parse(&out.scene, &std::fs::read_to_string(&out.scene).unwrap()).unwrap();
    s.horizons.clear();
    if page != 64 {
        let vol = dir.join(format!("seismic{page}.strata"));
        use strata_coordinator::builder::{build_store, BuildOptions};
        let model = strata_coordinator::synth::SynthModel::new(size, 5).unwrap();
        let mut o = BuildOptions::volume("seismic", strata_common::sample::SampleType::F32);
        o.page_size = page;
        o.transform = model.transform();
        build_store(&model, &vol, &o, &indicatif::ProgressBar::hidden()).unwrap();
        s.volumes[0].store = vol;
    }
    s.render.width = w;
    s.render.height = h;
    s.render.early_termination = 1.0;
    s.render.max_rounds = 64;
    s.volumes[0].opacity = 0.3;
    s
}

fn assert_gpu_matches_cpu(s: &Scene, tol: f32, what: &str) -> Vec<[f32; 4]> {
    let cpu = render_whole(&on(s, Backend::Cpu));
    let gpu = render_whole(&on(s, Backend::Gpu));
    assert_clean(&gpu);
    let d = max_diff(&cpu, &gpu);
    eprintln!("{what}: GPU differs from CPU by at most {d:e} (tolerance {tol:e})");
    assert!(
        d <= tol,
        "{what}: GPU differs from CPU by {d} (tolerance {tol})"
    );
    assert!(
        gpu.iter().filter(|p| p[3] > 0.02).count() > gpu.len() / 20,
        "{what}: the view shows the data"
    );
    gpu
}

#[test]
fn gpu_equals_cpu_on_the_survey_with_lod_bands_shading_and_a_camera_inside() {
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    let s = survey_volume(dir.path(), [72, 56, 48], 64, 96, 64);
    assert_gpu_matches_cpu(&s, 1e-4, "survey");
    let mut shaded = s.clone();
    shaded.render.volume_shading = true;
    assert_gpu_matches_cpu(&shaded, 1e-4, "gradient shading");
    let mut ert = s.clone();
    ert.render.early_termination = 0.95;
    ert.volumes[0].opacity = 1.0;
    assert_gpu_matches_cpu(&ert, 1e-4, "early termination");
    let mut noskip = s.clone();
    noskip.render.empty_space_skipping = false;
    assert_gpu_matches_cpu(&noskip, 1e-4, "no empty-space skipping");
    // Pre-integration: one pair of tables per step band, spans across bands and bricks.
    let mut pre = s.clone();
    pre.render.preintegrated = true;
    assert_gpu_matches_cpu(&pre, 1e-4, "pre-integrated");
    let mut pre_shaded = shaded.clone();
    pre_shaded.render.preintegrated = true;
    // Lavapipe gives this image bit for bit, and is held to 1e-4 like every case; an H200
    // (NVIDIA's Vulkan driver contracts a·b + c into fused multiply-adds and divides and
    // takes square roots to the 2.5 ulp that Vulkan allows) differed by 1.05e-4 here, where
    // every other case stays within 1e-4: shading's central differences of pre-integrated
    // spans are the most sensitive to the last bits of the sample values. A hardware
    // adapter (the engine's default pick when there is one) gets 2.5e-4.
    let hardware = strata_worker::gpu::list_adapters().iter().any(|a| !a.3);
    let tol = if hardware { 2.5e-4 } else { 1e-4 };
    assert_gpu_matches_cpu(&pre_shaded, tol, "pre-integrated and shaded");
    // A camera inside the volume: rays start inside the box.
    let e = Engine::new(&s).unwrap();
    let b = e.bounds();
    let mid = [0, 1, 2].map(|a| 0.5 * (b.lo[a] + b.hi[a]));
    let mut inside = s.clone();
    inside.camera = Some(strata_common::scene::Camera {
        eye: mid,
        target: [mid[0] + 100.0, mid[1] + 30.0, mid[2] + 5.0],
        up: [0.0, 0.0, 1.0],
        fov_deg: 70.0,
    });
    assert_gpu_matches_cpu(&inside, 1e-4, "camera inside");
}

#[test]
fn gpu_equals_cpu_for_overlapping_volumes_and_nan_data() {
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    let s = overlapping_volumes(dir.path(), 97); // NaN samples: transparent on both
    let whole = assert_gpu_matches_cpu(&s, 1e-4, "two overlapping volumes");
    // Pre-integrated: spans end at no data and where the mix begins.
    let mut pre = s.clone();
    pre.render.preintegrated = true;
    assert_gpu_matches_cpu(&pre, 1e-4, "two overlapping pre-integrated volumes");
    let gs = on(&s, Backend::Gpu);
    let tree = KdTree::from_splits(scene_region(&gs), &[(0, 0, 0.5), (0, 2, 0.4), (1, 1, 0.55)]);
    let d = max_diff(&whole, &render_split(&gs, &tree));
    assert!(
        d < 1e-5,
        "GPU split of overlapping volumes: max difference {d}"
    );
}

#[test]
fn gpu_region_split_is_seamless_across_lod_levels_and_step_bands() {
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    // 128³ in 32³ bricks seen at 48×36 pixels: the footprint calls for coarse levels.
    let s = on(
        &survey_volume(dir.path(), [128, 128, 128], 32, 48, 36),
        Backend::Gpu,
    );
    let (mut e, view, region, _) = gpu_batch(&s);
    // What the frame provably used: levels from the GPU feedback, bands from the step table.
    let f = e.render_frame(&view, &region).unwrap();
    let levels: std::collections::BTreeSet<u8> = f
        .feedback
        .coverage
        .keys()
        .map(|&k| strata_common::ids::PageId(k).level())
        .collect();
    assert!(levels.len() >= 2, "levels requested: {levels:?}");
    let (start, dt) = e.sampling_bands(&view, &region);
    let b = e.bounds();
    let far = (0..8)
        .map(|c| {
            let p = [0, 1, 2].map(|a| if c >> a & 1 == 0 { b.lo[a] } else { b.hi[a] });
            let rel = view.relative(p);
            (rel[0] * rel[0] + rel[1] * rel[1] + rel[2] * rel[2]).sqrt()
        })
        .fold(0.0f32, f32::max);
    let used = start.iter().filter(|&&t| t < far).count();
    assert!(
        used >= 2,
        "bands within the data: starts {start:?}, steps {dt:?}, far {far}"
    );
    assert!(f.gpu.feedback_bytes > 4 && f.gpu.feedback_bytes < 8 * 1024 * 1024);

    let whole = f.image.to_full();
    assert_clean(&whole);
    let root = scene_region(&s);
    for sp in SPLITS_2_4_7 {
        let tree = KdTree::from_splits(root, sp);
        let d = max_diff(&whole, &render_split(&s, &tree));
        assert!(
            d < 1e-5,
            "{} GPU regions: max difference {d}",
            tree.leaves.len()
        );
    }
    // And the GPU image equals the CPU's.
    let cpu = render_whole(&on(&s, Backend::Cpu));
    let d = max_diff(&cpu, &whole);
    assert!(d <= 1e-4, "GPU vs CPU at coarse levels: {d}");
}

#[test]
fn gpu_out_of_core_converges_to_the_unlimited_atlas_image() {
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    // 256×256×128 f32 = 32 MiB of level 0 in 32³ bricks; an atlas of 4 MiB holds 1/8.
    let mut s = on(
        &survey_volume(dir.path(), [256, 256, 128], 32, 64, 48),
        Backend::Gpu,
    );
    s.render.upload_pages_per_frame = 16; // several rounds
                                          // The working set of τ = 1 (95 pages at this size) fits the 4 MiB atlas; τ = 0.5's
                                          // does not (the default since the accuracy study; an atlas too small for the working
                                          // set is its own test, `atlas-full`).
    s.render.tau = 1.0;
    let want = render_whole(&s);
    s.render.atlas_mb = 4;
    let mut e = Engine::new(&s).unwrap();
    let view = e.view(64, 48).unwrap();
    let region = e.scene_region();
    let r = e.render_batch(&view, &region).unwrap();
    assert_eq!(r.outcome, Outcome::Converged, "{:?}", r.reports);
    let d = max_diff(&want, &r.image.to_full());
    assert!(d < 1e-6, "limited atlas against unlimited: {d}");
    let slots = strata_worker::atlas::Pool::slots_for(34 * 34 * 34, 4 << 20);
    let uploaded: usize = r.reports.iter().map(|r| r.uploaded).sum();
    assert!(r.rounds > 2, "several rounds: {:?}", r.reports);
    assert!(uploaded > 0 && r.uploaded_bytes > uploaded as u64 * 34 * 34 * 34 * 4 / 2);
    let (used, _) = e.atlas_usage();
    assert!(used <= slots, "{used} of {slots} slots");
    // A batch cut short by the round limit counts the pages its last update wrote: they
    // had gone to the next batch's count, here one of a region off the data, which casts
    // and uploads nothing.
    s.render.max_rounds = 2;
    let mut e = Engine::new(&s).unwrap();
    let r = e.render_batch(&view, &region).unwrap();
    assert_eq!(r.outcome, Outcome::RoundLimit, "{:?}", r.reports);
    assert!(r.reports.last().unwrap().uploaded > 0, "{:?}", r.reports);
    let away = strata_common::kd::Region {
        lo: [region.hi[0] + 1e6; 3],
        hi: [region.hi[0] + 2e6; 3],
    };
    let empty = e.render_batch(&view, &away).unwrap();
    assert_eq!(empty.outcome, Outcome::Converged, "{:?}", empty.reports);
    assert_eq!(empty.uploaded_bytes, 0, "{:?}", empty.reports);
}

/// The synthetic survey as generated: a seismic volume and three horizons.
fn survey_with_horizons(dir: &Path, w: u32, h: u32) -> Scene {
    let out = strata_coordinator::synth::synth(
        dir,
        [64, 48, 40],
        5,
        false,
        &indicatif::ProgressBar::hidden(),
    )
    .unwrap();
    let mut s = Scene::parse(&out.scene, &std::fs::read_to_string(&out.scene).unwrap()).unwrap();
    assert_eq!(s.horizons.len(), 3);
    s.render.width = w;
    s.render.height = h;
    s.render.max_rounds = 64;
    s
}

#[test]
fn gpu_equals_cpu_for_volume_and_horizons_in_one_pass() {
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    let s = survey_with_horizons(dir.path(), 96, 64);
    let (mut e, view, region, r) = gpu_batch(&s);
    assert!(r.last.hits > 500, "the horizons are hit: {:?}", r.last);
    // The feedback asked for horizon tiles (data sets after the volume).
    let f = e.render_frame(&view, &region).unwrap();
    let hor_pages = f
        .feedback
        .coverage
        .keys()
        .filter(|&&k| strata_common::ids::PageId(k).dataset() >= 1)
        .count();
    assert!(hor_pages > 0, "horizon tiles in the GPU feedback");

    let mut translucent = s.clone();
    translucent.volumes[0].opacity = 0.4;
    for h in &mut translucent.horizons {
        h.opacity = 0.6;
    }
    translucent.render.early_termination = 1.0;
    for (what, scene) in [
        ("survey as generated", s.clone()),
        ("translucent horizons", translucent.clone()),
    ] {
        assert_gpu_matches_cpu(&scene, 1e-4, what);
    }
    let mut unlit = translucent.clone();
    unlit.render.lighting = false;
    assert_gpu_matches_cpu(&unlit, 1e-4, "horizons without lighting");
    let mut depth = translucent.clone();
    for h in &mut depth.horizons {
        h.color_by = "depth".into();
        h.colormap = "viridis".into();
    }
    assert_gpu_matches_cpu(&depth, 1e-4, "horizons coloured by depth");
    let mut only = translucent;
    only.volumes.clear();
    assert_gpu_matches_cpu(&only, 1e-4, "horizons alone");
}

#[test]
fn gpu_region_split_with_horizons_is_seamless() {
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    let mut s = on(&survey_with_horizons(dir.path(), 64, 48), Backend::Gpu);
    s.volumes[0].opacity = 0.4;
    for h in &mut s.horizons {
        h.opacity = 0.6;
    }
    s.render.early_termination = 1.0;
    let whole = render_whole(&s);
    assert_clean(&whole);
    let root = scene_region(&s);
    for sp in SPLITS_2_4_7 {
        let tree = KdTree::from_splits(root, sp);
        let d = max_diff(&whole, &render_split(&s, &tree));
        assert!(
            d < 1e-5,
            "{} GPU regions with horizons: max difference {d}",
            tree.leaves.len()
        );
    }
}

/// A 40×36×32 volume of type `t`: a smooth pattern over the type's range, quantized, with
/// every 53rd sample no-data when the type has a sentinel.
fn typed_volume(
    dir: &Path,
    name: &str,
    t: SampleType,
    no_data: Option<f32>,
    page: u32,
) -> std::path::PathBuf {
    let dims = [40u64, 36, 32];
    let (lo, hi) = match t {
        SampleType::F32 => (-1.0, 1.0),
        _ => t.range(),
    };
    let data: Vec<f32> = (0..dims.iter().product::<u64>())
        .map(|i| {
            if no_data.is_some() && i % 53 == 7 {
                return f32::NAN;
            }
            let (x, y, z) = (i % 40, i / 40 % 36, i / (40 * 36));
            let u = 0.5
                + 0.45
                    * (x as f32 * 0.31).sin()
                    * (y as f32 * 0.17).cos()
                    * (z as f32 * 0.23 + 0.4).sin();
            let v = lo + (hi - lo) * u;
            if t == SampleType::F32 {
                v
            } else {
                v.round().clamp(lo + 1.0, hi - 1.0) // keep clear of the sentinels
            }
        })
        .collect();
    let path = dir.join(format!("{name}.strata"));
    let mut o = strata_coordinator::builder::BuildOptions::volume(name, t);
    o.page_size = page;
    o.no_data = no_data;
    strata_coordinator::builder::build_store(
        &strata_coordinator::source::MemorySource { dims, data },
        &path,
        &o,
        &indicatif::ProgressBar::hidden(),
    )
    .unwrap();
    path
}

fn typed_scene(stores: Vec<(std::path::PathBuf, [f64; 2])>) -> Scene {
    let camera = strata_common::scene::Camera {
        eye: [-30.0, -45.0, 60.0],
        target: [19.5, 17.5, 15.5],
        up: [0.0, 0.0, 1.0],
        fov_deg: 40.0,
    };
    let vols = stores
        .into_iter()
        .map(|(p, w)| volume_layer(p, "viridis", w, vec![[0.0, 0.0], [0.3, 0.05], [1.0, 0.4]]))
        .collect();
    scene(vols, vec![], camera, exact_settings(64, 48))
}

#[test]
fn gpu_pools_keep_8_and_16_bit_samples_narrow_and_equal_the_cpu() {
    if !gpu_available() {
        return;
    }
    use SampleType::*;
    let dir = TempDir::new().unwrap();
    let f32_store = typed_volume(dir.path(), "f32", F32, None, 32);
    let batch = |s: &Scene| {
        let (e, _, _, r) = gpu_batch(s);
        (e.gpu_pool_bits(), r.uploaded_bytes)
    };
    let (bits32, up32) = batch(&typed_scene(vec![(f32_store.clone(), [-1.0, 1.0])]));
    assert_eq!(bits32, Some(32));
    for (t, nd, want_bits) in [
        (U8, None, 8),
        (U8, Some(255.0), 8),
        (I8, Some(-128.0), 8),
        (U16, Some(65535.0), 16),
        (I16, Some(-32768.0), 16),
    ] {
        let name = format!("{t:?}-{}", nd.is_some());
        let store = typed_volume(dir.path(), &name, t, nd, 32);
        let (lo, hi) = t.range();
        let s = typed_scene(vec![(store, [lo as f64, hi as f64])]);
        assert_gpu_matches_cpu(&s, 1e-4, &name);
        let (bits, up) = batch(&s);
        assert_eq!(bits, Some(want_bits), "{name}");
        // Pages dominate the upload: a byte per sample is about a quarter of f32's.
        let ratio = up as f64 / up32 as f64;
        let want = want_bits as f64 / 32.0;
        assert!(
            ratio < want * 1.15 && ratio > want * 0.85,
            "{name}: uploaded {up} bytes against {up32} for f32 ({ratio:.3})"
        );
    }
    // Mixed types share one pool in the widest width, each decoding its own signedness and
    // sentinel: u8 with i16 (16-bit), u8 with f32 (32-bit).
    let u8s = typed_volume(dir.path(), "u8b", U8, Some(0.0), 32);
    let i16s = typed_volume(dir.path(), "i16b", I16, Some(-32768.0), 32);
    let f32b = typed_volume(dir.path(), "f32b", F32, None, 32);
    for (what, stores, bits) in [
        (
            "u8 + i16",
            vec![(u8s.clone(), [0.0, 255.0]), (i16s, [-32768.0, 32767.0])],
            16,
        ),
        (
            "u8 + f32",
            vec![(u8s, [0.0, 255.0]), (f32b, [-1.0, 1.0])],
            32,
        ),
    ] {
        let s = typed_scene(stores);
        assert_gpu_matches_cpu(&s, 1e-4, what);
        assert_eq!(batch(&s).0, Some(bits), "{what}");
    }
}

/// The largest and the mean channel difference between two images.
fn diff_stats(a: &[[f32; 4]], b: &[[f32; 4]]) -> (f32, f64) {
    let max = max_diff(a, b);
    let sum: f64 = a
        .iter()
        .zip(b)
        .flat_map(|(p, q)| (0..4).map(move |c| (p[c] - q[c]).abs() as f64))
        .sum();
    (max, sum / (a.len() * 4) as f64)
}

#[test]
fn gpu_hardware_filter_stays_within_its_bound_of_the_cpu() {
    if !gpu_available() {
        return;
    }
    use strata_common::scene::GpuFilter;
    use SampleType::*;
    let dir = TempDir::new().unwrap();
    let mut cases = vec![(
        "survey f32".to_string(),
        survey_volume(dir.path(), [72, 56, 48], 64, 96, 64),
    )];
    for (t, nd) in [(U8, None), (I8, None), (U16, None), (I16, Some(-32768.0))] {
        let name = format!("{t:?}");
        let store = typed_volume(dir.path(), &name, t, nd, 32);
        let (lo, hi) = t.range();
        cases.push((name, typed_scene(vec![(store, [lo as f64, hi as f64])])));
    }
    for (name, s) in cases {
        let cpu = render_whole(&on(&s, Backend::Cpu));
        let mut hw = on(&s, Backend::Gpu);
        hw.render.gpu_filter = GpuFilter::Hardware;
        let e = Engine::new(&hw).unwrap();
        assert!(
            e.backend_name().ends_with("hardware filter"),
            "{}",
            e.backend_name()
        );
        let img = render_whole(&hw);
        assert_clean(&img);
        let (max, mean) = diff_stats(&cpu, &img);
        eprintln!("{name}: hardware filter vs CPU: max {max:.3e}, mean {mean:.3e}");
        assert!(
            max <= 2e-2 && mean <= 1e-3,
            "{name}: max {max}, mean {mean}"
        );
    }
}

/// A wgpu error raised between casts (an earlier write's, reported at the next readback)
/// fails that frame, and only that frame: the readback buffer is unmapped on the error path
/// too, so the next frame casts (a buffer left mapped had failed every later frame, and the
/// engine's GPU with them).
#[test]
fn gpu_frames_after_an_error_cast_again() {
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    let s = survey_with_horizons(dir.path(), 24, 16);
    let (mut e, view, region, whole) = gpu_batch(&s);
    e.gpu_raise_an_error();
    let failed = e.render_frame(&view, &region);
    let err = format!(
        "{:#}",
        failed.as_ref().err().expect("the error is reported")
    );
    assert!(err.contains("wgpu error"), "{err}");
    for _ in 0..2 {
        let again = e.render_frame(&view, &region).unwrap();
        assert!(bit_identical(&again.image.pixels, &whole.image.pixels));
    }
}

/// A buffer allocation the device refuses (past its largest buffer here; out of memory on a
/// GPU shared by several workers) does not break the engine's GPU: the next frame allocates
/// again. wgpu's invalid buffer reports the size asked for, so it had been taken as large
/// enough for good, and every later frame failed binding it.
#[test]
fn gpu_frames_after_a_refused_allocation_cast_again() {
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    let s = survey_with_horizons(dir.path(), 24, 16);
    let (mut e, view, region, whole) = gpu_batch(&s);
    assert!(
        e.gpu_fail_an_allocation(),
        "the device took a buffer past its limit"
    );
    for _ in 0..2 {
        let again = e.render_frame(&view, &region).unwrap();
        assert!(bit_identical(&again.image.pixels, &whole.image.pixels));
    }
}

/// After one large frame (over 16 MiB of image buffer), a window of small ones makes the
/// image buffer again at their size, exactly at the window's end, and frames before, at and
/// after that point equal a fresh engine's, bit for bit.
#[test]
fn gpu_image_buffer_shrinks_after_a_window_of_small_frames() {
    use strata_worker::gpu::SHRINK_WINDOW;
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    let s = survey_with_horizons(dir.path(), 24, 16);
    let (mut e, small, region, whole) = gpu_batch(&s);
    let big = e.view(1400, 1200).unwrap();
    e.render_frame(&big, &region).unwrap();
    let big_bytes = e.gpu_image_buffer_bytes().unwrap();
    assert!(big_bytes > 20 << 20, "{big_bytes}");
    let mut shrunk_at = None;
    for call in 0..SHRINK_WINDOW + 8 {
        let again = e.render_frame(&small, &region).unwrap();
        assert!(
            bit_identical(&again.image.pixels, &whole.image.pixels),
            "frame {call} after the large one"
        );
        if shrunk_at.is_none() && e.gpu_image_buffer_bytes().unwrap() < big_bytes {
            shrunk_at = Some(call);
        }
    }
    // One image-buffer call per small frame (one band): the window closes at its last.
    assert_eq!(shrunk_at, Some(SHRINK_WINDOW - 1));
    assert!(e.gpu_image_buffer_bytes().unwrap() <= 24 * 16 * 16);
}

/// A region larger than one dispatch may cast (one storage binding of the adapter: 8.4 M
/// pixels on lavapipe, about 134 M on NVIDIA) is cast in bands. Here the band is capped far
/// below the adapter's limit: rows of 8, rows of 3, then columns of 40 in rows of 1. Every
/// band casts its pixels' own rays, so the banded frame equals the whole one bit for bit:
/// image, counters and page requests, with and without occlusion's per-ray limits; and a
/// batch that loads its pages through banded feedback converges to the same image.
#[test]
fn gpu_casts_a_region_past_one_binding_in_bands_bit_for_bit() {
    use strata_common::occlusion::{BlockGrid, FrontTransmittance, RayLimits, CLEAR};
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    let (w, h) = (61, 37);
    let mut s = survey_with_horizons(dir.path(), w, h);
    s.volumes[0].opacity = 0.4;
    for hz in &mut s.horizons {
        hz.opacity = 0.6;
    }
    let (mut e, view, region, whole) = gpu_batch(&s);
    assert_eq!(e.gpu_banded_regions(), Some(0));
    let grid = BlockGrid::new(w, h, 4);
    let q: Vec<u16> = (0..grid.len())
        .map(|b| match b % 4 {
            0 => 0,
            1 => 300,
            2 => 3000,
            _ => CLEAR,
        })
        .collect();
    let front = FrontTransmittance::checked(grid, q).unwrap();
    let limits = RayLimits {
        front: &front,
        only: None,
        threshold: 0.99,
    };
    let reference = e.render_frame(&view, &region).unwrap();
    let reference_limited = e
        .render_frame_limited(&view, &region, Some(limits))
        .unwrap();
    assert!(reference.stats.hits > 0 && reference.stats.samples > 0);
    assert!(reference_limited.stats.rays < reference.stats.rays);
    let mut banded = 0;
    for cap in [w as u64 * 8 + 3, w as u64 * 3, 40] {
        e.set_gpu_band_pixels(Some(cap));
        for limited in [false, true] {
            let (f, want, what) = if limited {
                let f = e
                    .render_frame_limited(&view, &region, Some(limits))
                    .unwrap();
                (f, &reference_limited, "limited")
            } else {
                (e.render_frame(&view, &region).unwrap(), &reference, "whole")
            };
            let now = e.gpu_banded_regions().unwrap();
            assert!(now > banded, "cap {cap}, {what}: not banded");
            banded = now;
            assert!(
                bit_identical(&f.image.pixels, &want.image.pixels),
                "cap {cap}, {what}: the bands differ from the whole by {}",
                max_diff(&f.image.pixels, &want.image.pixels)
            );
            assert_eq!(f.stats, want.stats, "cap {cap}, {what}");
            assert_eq!(
                f.feedback.coverage, want.feedback.coverage,
                "cap {cap}, {what}"
            );
        }
    }
    // A batch that starts cold and loads its pages through banded feedback.
    let mut cold = Engine::new(&on(&s, Backend::Gpu)).unwrap();
    cold.set_gpu_band_pixels(Some(100));
    let r = cold.render_batch(&view, &region).unwrap();
    assert_eq!(r.outcome, Outcome::Converged, "{:?}", r.reports);
    assert_eq!(r.rounds, whole.rounds);
    assert!(bit_identical(&r.image.pixels, &whole.image.pixels));
}

/// A region whose pixels exceed one storage binding of the adapter (8.4 M pixels on
/// lavapipe, about 134 M on NVIDIA) is cast in bands at the adapter's own limit (the driver
/// had refused it mid-frame), and the bands are seamless: every row equals the CPU's.
#[test]
fn gpu_casts_a_region_past_the_adapters_largest_binding() {
    if !gpu_available() {
        return;
    }
    let dir = TempDir::new().unwrap();
    let mut s = survey_volume(dir.path(), [40, 32, 24], 64, 4096, 4096);
    // The eye close to the data's centre, so that the region covers the whole frame.
    let c = s.camera.as_mut().expect("the survey has a camera");
    for a in 0..3 {
        c.eye[a] = c.target[a] + 0.1 * (c.eye[a] - c.target[a]);
    }
    let mut e = Engine::new(&on(&s, Backend::Gpu)).unwrap();
    let limit = e.gpu_max_frame_pixels().expect("the GPU backend");
    // Just past one binding.
    let h = (limit / 4096 + 1).min(4096) as u32;
    if 4096 * h as u64 <= limit {
        eprintln!("skipped: this adapter binds {limit} pixels at once");
        return;
    }
    let t = std::time::Instant::now();
    let view = e.view(4096, h).unwrap();
    let region = e.scene_region();
    let r = e.render_batch(&view, &region).unwrap();
    eprintln!("4096x{h} on the GPU in {:?}", t.elapsed());
    assert_eq!(r.outcome, Outcome::Converged, "{:?}", r.reports);
    assert!(e.gpu_banded_regions().unwrap() > 0);
    let gpu = r.image.to_full();
    assert_clean(&gpu);
    let mut c = on(&s, Backend::Cpu);
    c.render.height = h;
    let t = std::time::Instant::now();
    let cpu = render_whole(&c);
    eprintln!("on the CPU in {:?}", t.elapsed());
    assert!(max_diff(&cpu, &gpu) <= 1e-4, "{}", max_diff(&cpu, &gpu));
}

/// A scene past the GPU caster's limits (4 volumes, 16 horizons) is refused by
/// `render.backend = "gpu"` with an error that names the limit and what to use, and goes to
/// the CPU under `auto`. Decided before any adapter is asked for, so this runs anywhere.
#[test]
fn scenes_past_the_gpu_casters_limits_are_refused_by_gpu_and_go_to_the_cpu_under_auto() {
    use strata_common::geo::Affine3;
    let dir = TempDir::new().unwrap();
    let n = 8u64;
    let vol = |i: usize| {
        let store = volume_store(
            dir.path(),
            &format!("v{i}"),
            [n, n, n],
            vec![i as f32; (n * n * n) as usize],
            Affine3::IDENTITY,
            32,
        );
        volume_layer(store, "grey", [0.0, 8.0], vec![[0.0, 0.1], [1.0, 0.1]])
    };
    let hor = |i: usize| {
        let store = horizon_store(
            dir.path(),
            &format!("h{i}"),
            [n, n],
            vec![i as f32 * 0.4; (n * n) as usize],
            Affine3::IDENTITY,
            32,
        );
        horizon_layer(store, [0.5, 0.5, 0.5], 0.3)
    };
    let camera = strata_common::scene::Camera {
        eye: [3.5, 3.5, -30.0],
        target: [3.5, 3.5, 3.5],
        up: [0.0, 1.0, 0.0],
        fov_deg: 35.0,
    };
    for (vols, hors, limit) in [(5, 0, "at most 4 volumes"), (1, 17, "at most 16 horizons")] {
        let s = scene(
            (0..vols).map(vol).collect(),
            (0..hors).map(hor).collect(),
            camera.clone(),
            exact_settings(16, 12),
        );
        let err = Engine::new(&on(&s, Backend::Gpu)).err().expect("refused");
        let msg = format!("{err:#}");
        assert!(
            msg.contains(limit) && msg.contains("use \"cpu\" or \"auto\""),
            "{msg}"
        );
        let e = Engine::new(&on(&s, Backend::Auto)).unwrap();
        assert!(e.backend_name().starts_with("cpu"), "{}", e.backend_name());
        assert!(!render_whole(&on(&s, Backend::Auto)).is_empty());
    }
}

/// A ray crossing one translucent horizon more often than the GPU's list of 32 holds: a
/// horizontal ray at height 10 over `10 + 3·sin(1.3·i + 0.4)` crosses it in every cell whose
/// two nodes lie on either side of 10, 52 times over 128 nodes. Both casters composite every
/// crossing (the CPU had kept 32 per horizon, the GPU 32 per ray; the GPU now searches again
/// from its 32nd), so the centre ray's alpha is `1 − 0.97^52`, and GPU == CPU.
#[test]
fn a_horizon_crossed_52_times_composites_every_crossing_on_both_casters() {
    use strata_common::scene::Camera;
    let dir = TempDir::new().unwrap();
    let (nx, ny) = (128u64, 64u64);
    let wave = |i: u64| (10.0 + 3.0 * (1.3 * i as f64 + 0.4).sin()) as f32;
    let heights: Vec<f32> = (0..nx * ny).map(|k| wave(k % nx)).collect();
    let crossings = (0..nx - 1)
        .filter(|&i| (wave(i) > 10.0) != (wave(i + 1) > 10.0))
        .count();
    assert_eq!(crossings, 52);
    let p = horizon_store(
        dir.path(),
        "wave",
        [nx, ny],
        heights,
        strata_common::geo::Affine3::IDENTITY,
        32,
    );
    let mut r = exact_settings(33, 33);
    r.lighting = false;
    let s = scene(
        vec![],
        vec![horizon_layer(p, [0.2, 0.6, 0.3], 0.03)],
        Camera {
            eye: [-20.0, 31.5, 10.0],
            target: [127.0, 31.5, 10.0],
            up: [0.0, 0.0, 1.0],
            fov_deg: 10.0,
        },
        r,
    );
    let px = render_on_both(&s, 1e-4, "a horizon crossed 52 times");
    let c = px[(16 * 33 + 16) as usize];
    let a = 1.0 - 0.97f64.powi(crossings as i32);
    assert!((c[3] as f64 - a).abs() < 1e-4, "{c:?}, want alpha {a}");
    assert!(
        (c[1] as f64 - 0.6 * a).abs() < 1e-4,
        "{c:?}, want green {}",
        0.6 * a
    );
}
