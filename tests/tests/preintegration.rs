//! Pre-integration's segment convention: a span of samples covers half a step before its
//! first sample and half a step after its last, as post-classification's point samples
//! do, and the value runs linearly through each step, so a value linear along the ray is
//! integrated exactly. A ray along a linear ramp with value-dependent opacity, whose
//! samples cover the volume exactly (half a step of the first sample lies at its front
//! face), must come out nearer a fine reference than point samples; the former
//! convention, which composited each segment at its far end and a span's first sample as
//! a whole step, was further off than point samples.

use strata_common::geo::Affine3;
use strata_common::image::Rgba;
use strata_common::scene::{Backend, Camera, Scene};
use strata_tests::scenes::{
    exact_settings, horizon_layer, horizon_store, render_on_both, render_whole, scene,
    volume_layer, volume_store,
};

const N: u64 = 64;

/// A 4 × 4 × 64 volume whose value rises linearly from 0 to 1 along z, grey, clear below
/// 1/8 and then with opacity rising linearly to 0.2 per voxel at 1 (the kink lies between
/// samples, where point samples cannot see it; the clear front keeps the volume's clamped
/// border out of the way), seen down the z axis (3 × 3 pixels, the centre ray through the
/// middle of the x-y section); `step` voxels, pre-integrated or not. The eye sits so that
/// the samples' steps tile the volume's extent [−0.5, 63.5] exactly (a lattice point at
/// z = step/2 − 0.5).
fn ramp(dir: &std::path::Path, step: f64, pre: bool) -> Scene {
    let data: Vec<f32> = (0..4 * 4 * N)
        .map(|i| (i / 16) as f32 / (N - 1) as f32)
        .collect();
    let store = dir.join("ramp.strata");
    if !store.exists() {
        volume_store(dir, "ramp", [4, 4, N], data, Affine3::IDENTITY, 32);
    }
    let layer = volume_layer(
        store,
        "grey",
        [0.0, 1.0],
        vec![[0.0, 0.0], [0.125, 0.0], [1.0, 0.2]],
    );
    let mut s = exact_settings(3, 3);
    s.step = step;
    s.adaptive_step = false;
    s.lighting = false;
    s.tau = 1e-6;
    s.preintegrated = pre;
    s.backend = Backend::Cpu;
    let camera = Camera {
        eye: [1.5, 1.5, step / 2.0 - 0.5 - 64.0 * step.max(4.0)],
        target: [1.5, 1.5, 31.5],
        up: [0.0, 1.0, 0.0],
        fov_deg: 0.1,
    };
    scene(vec![layer], vec![], camera, s)
}

/// The ramp with an opaque red horizon across it at z = `at` (the ray meets it head on).
fn ramp_onto_surface(dir: &std::path::Path, step: f64, pre: bool, at: f32) -> Scene {
    let mut s = ramp(dir, step, pre);
    let store = dir.join(format!("flat-{at}.strata"));
    if !store.exists() {
        horizon_store(
            dir,
            &format!("flat-{at}"),
            [4, 4],
            vec![at; 16],
            Affine3::IDENTITY,
            32,
        );
    }
    s.horizons = vec![horizon_layer(store, [1.0, 0.0, 0.0], 1.0)];
    s
}

/// Largest channel difference allowed between the GPU's pre-integration and the CPU's: the
/// same tables and the same segment convention, evaluated in f32 on both (fused
/// multiply-adds and the GPU's own rounding of the bilinear lookups aside).
const GPU_TOL: f32 = 1e-5;

/// A pre-integrated render on the CPU and, where an adapter exists, on the GPU, which must
/// agree within [`GPU_TOL`]; the CPU image.
fn pre_both(s: &Scene, what: &str) -> Vec<Rgba> {
    assert!(s.render.preintegrated);
    render_on_both(s, GPU_TOL, what)
}

fn centre(img: &[Rgba]) -> Rgba {
    img[4]
}

fn err(a: Rgba, b: Rgba) -> f32 {
    (0..4).map(|c| (a[c] - b[c]).abs()).fold(
        0.0,
        |m: f32, d: f32| if d.is_nan() { f32::INFINITY } else { m.max(d) },
    )
}

#[test]
fn a_preintegrated_ramp_matches_the_fine_reference_better_than_point_samples() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // The reference: point samples 1/16 voxel apart.
    let reference = centre(&render_whole(&ramp(d, 1.0 / 16.0, false)));
    assert!(
        reference[3] > 0.5 && reference[3] < 0.999,
        "the ramp should be neither clear nor opaque: {reference:?}"
    );
    for (step, factor) in [(2.0, 0.25), (4.0, 0.5), (8.0, 0.8)] {
        let post = centre(&render_whole(&ramp(d, step, false)));
        let pre = centre(&pre_both(
            &ramp(d, step, true),
            &format!("ramp, step {step}"),
        ));
        let (e_post, e_pre) = (err(post, reference), err(pre, reference));
        // The value is linear along the ray, so each step is exact up to the 256² table
        // and the far end, where the volume's values stop at 1 (at a transmittance of
        // 0.3 %; more of the error the coarser the step).
        assert!(
            e_pre < factor * e_post,
            "step {step}: pre-integrated {pre:?} is {e_pre:.2e} from the reference \
             {reference:?}, point samples {post:?} {e_post:.2e}"
        );
    }
}

/// An opaque surface between samples: the volume's pre-integrated span in front of it is
/// closed before the surface is blended (its half step after the last sample counted, as
/// point samples count their last sample's whole step), so the volume in front of the
/// surface is integrated over the same depth either way. Were the span left open, its last
/// half step would be blended behind the opaque surface, i.e. lost.
#[test]
fn a_preintegrated_span_ends_at_a_surface() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for step in [2.0f64, 4.0] {
        // Between lattice points at this step (they lie at step/2 − 0.5 + k·step).
        let lattice = |k: f64| step / 2.0 - 0.5 + k * step;
        let at = (lattice((40.0 / step).floor() - 1.0) + 0.3 * step) as f32;
        let post = centre(&render_whole(&ramp_onto_surface(d, step, false, at)));
        let pre = centre(&pre_both(
            &ramp_onto_surface(d, step, true, at),
            &format!("ramp onto a surface, step {step}"),
        ));
        let open = centre(&render_whole(&ramp(d, step, true)));
        eprintln!("step {step}: surface at {at}: post {post:?} pre {pre:?} ramp alone {open:?}");
        assert!(pre[3] > 0.999 && post[3] > 0.999, "the surface is opaque");
        // The volume in front covers the same depth: the surface's share (red, less the
        // green and blue the grey volume adds) is the same to within the pre-integration
        // of a ramp against point samples of it.
        let (red_post, red_pre) = (post[0] - post[1], pre[0] - pre[1]);
        assert!(
            (red_post - red_pre).abs() < 0.005,
            "step {step}: the surface shows {red_pre} through the pre-integrated volume, \
             {red_post} through point samples"
        );
    }
}

/// The same with adaptive steps (1 voxel, then 2 from the second band on), the surface
/// moved across the second band's start: at z = 40.3 it lies in the first band, at 41.0 and
/// 41.9 past the second band's start (z = 40.5) but before that band's first lattice point
/// (z = 42). All three cut the same segment, from the last fine sample (z = 40) to the first
/// coarse one, which is one coarse step (`band_start`): the span ends with half of it in each
/// case, and the three frames are one. The band at the surface's distance had been used:
/// half a fine step at 40.3, half a coarse one at 41.0. And the ramp without a surface, split
/// into two regions at the same places, equals the undivided ramp: region faces cut that
/// segment into halves of it too (a face before the band's start had ended its region's span
/// with half a fine step, its neighbour's began with half a coarse one).
#[test]
fn a_preintegrated_span_ends_alike_on_either_side_of_a_band_start() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let with_bands = |at: f32| {
        let mut s = ramp_onto_surface(d, 1.0, true, at);
        s.render.adaptive_step = true;
        // The second band's start, vmin · 2 / (τ · pixel angle), 297 from the eye (which
        // sits at z = −256), 0.1° over 3 pixels; bands begin half a fine step past an even
        // multiple of it: at 296.5, z = 40.5.
        s.render.tau = 2.0 / (297.0 * (2.0 * 0.05f64.to_radians().tan() / 3.0));
        s
    };
    let before = centre(&pre_both(&with_bands(40.3), "surface at 40.3, bands"));
    for at in [41.0f32, 41.9] {
        let past = centre(&pre_both(
            &with_bands(at),
            &format!("surface at {at}, bands"),
        ));
        assert!(before[3] > 0.999, "the surface is opaque");
        assert_eq!(
            before, past,
            "the surface at z = 40.3 and at {at} follow the same samples"
        );
    }
    // The premise: a surface past the second band's first lattice point does see more.
    let later = centre(&render_whole(&with_bands(42.1)));
    assert_ne!(before, later);
    // Region faces at the same places, without a surface.
    use strata_common::kd::KdTree;
    use strata_tests::scenes::{render_split, scene_region};
    let mut s = with_bands(40.3);
    s.horizons.clear();
    let whole = centre(&render_whole(&s));
    for faces in [&[40.3f64][..], &[41.0], &[41.9], &[39.7], &[39.7, 41.0]] {
        // (39.7: the second region's first sample, z = 40, is the first band's last, and
        // its next the second band's first: its lead is half a fine step. 39.7 and 41.0:
        // the middle region holds that one sample: its end is half the coarse segment.)
        let mut tree = KdTree::single(scene_region(&s));
        let mut leaf = 0;
        for &f in faces {
            leaf = tree.split_leaf(leaf, 2, f);
        }
        let face = faces;
        let split = centre(&render_split(&s, &tree));
        // The halves are extrapolated lookups of the 256² table where the whole ray looks
        // the segment up at once: its bilinear interpolation differs by 5·10⁻⁵ here.
        assert!(
            err(split, whole) < 2e-4,
            "split at z = {face:?}: {split:?} against {whole:?}"
        );
    }
}

/// A second, all but transparent volume overlapping the back of the ramp from between two
/// samples on: where the two overlap their mix is post-classified, so the ramp's
/// pre-integrated span ends where the overlap begins (its half step after the last sample
/// counted). The image stays that of the ramp alone, up to the second volume's own
/// 2·10⁻⁴ of opacity and pre-integration against point samples over the overlap (≤ 4·10⁻⁴
/// here, against 2–5·10⁻³ with the span left open); were the
/// span left open, its last half step would be lost.
#[test]
fn a_preintegrated_span_ends_where_another_volume_begins() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ghost = volume_store(
        d,
        "ghost",
        [4, 4, 24],
        vec![0.5; 4 * 4 * 24],
        Affine3 {
            rows: [
                [1.0, 0.0, 0.0, 0.0],
                [0.0, 1.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 40.2],
            ],
        },
        32,
    );
    for step in [2.0f64, 4.0] {
        let alone = centre(&render_whole(&ramp(d, step, true)));
        let mut s = ramp(d, step, true);
        s.volumes.push(volume_layer(
            ghost.clone(),
            "grey",
            [0.0, 1.0],
            vec![[0.0, 1e-5], [1.0, 1e-5]],
        ));
        let both = centre(&pre_both(
            &s,
            &format!("ramp and a second volume, step {step}"),
        ));
        eprintln!("step {step}: ramp alone {alone:?}, with the overlapping volume {both:?}");
        assert!(
            both != alone,
            "step {step}: the second volume was not marched"
        );
        assert!(
            err(both, alone) < 0.001,
            "step {step}: the overlap changed the ramp from {alone:?} to {both:?}"
        );
    }
}

/// With empty-space skipping off, a brick with no valid sample is still skipped (it has
/// nothing to sample), so a pre-integrated span after it starts with a whole step. A region
/// whose face lies at that brick's far face must do the same: split equals whole, at and
/// around the face, and the GPU casts what the CPU does (it had looked at the brick beyond a
/// region only with skipping on, so the region's span started with a half step).
#[test]
fn a_span_after_a_no_data_brick_starts_alike_in_every_region_without_skipping() {
    use strata_common::kd::KdTree;
    use strata_tests::scenes::{render_split, scene_region};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Page 0 (32 samples, core 30, border 1: z 0..=30) holds no valid sample.
    let data: Vec<f32> = (0..4 * 4 * N)
        .map(|i| {
            let z = i / 16;
            if z <= 30 {
                f32::NAN
            } else {
                z as f32 / (N - 1) as f32
            }
        })
        .collect();
    let store = volume_store(d, "holey", [4, 4, N], data, Affine3::IDENTITY, 32);
    // Step 1 on the ramp's lattice (z = 0, 1, …: 30 is a no-data sample of page 1 that
    // ends the span itself); step 2 with the lattice on odd z, so that the sample before
    // the first valid one (z = 31) lies in page 0 and the span's lead is a whole step only
    // because that page is skipped.
    for (step, shift) in [(1.0f64, 0.0), (2.0, -1.5)] {
        let mut s = ramp(d, step, true);
        s.volumes[0].store = store.clone();
        s.render.empty_space_skipping = false;
        if let Some(c) = s.camera.as_mut() {
            c.eye[2] += shift;
        }
        let whole = render_whole(&s);
        assert!(centre(&whole)[3] > 0.05, "step {step}: nothing visible");
        for face in [29.5, 29.7, 30.0, 30.5, 31.5] {
            let mut tree = KdTree::single(scene_region(&s));
            tree.split_leaf(0, 2, face);
            let split = render_split(&s, &tree);
            let e = err(centre(&split), centre(&whole));
            assert!(
                e < 1e-5,
                "step {step}, split at z = {face}: {:?} against {:?}",
                centre(&split),
                centre(&whole)
            );
        }
        render_on_both(&s, 1e-4, &format!("no-data brick, step {step}"));
    }
}
