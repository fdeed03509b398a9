//! The WGSL ray march against a scalar Rust reference of the documented algorithm.
//!
//! Needs a wgpu adapter; lavapipe (`apt-get install mesa-vulkan-drivers libvulkan1`) is
//! enough. Without one every test prints a notice and passes, unless
//! `STRATA_REQUIRE_GPU_ADAPTER=1`, in which case it fails.

use std::io::Write;
use std::time::Instant;

use strata_gpu::{GpuRayMarcher, VolumeJob};

/// Largest accepted |GPU - reference| per channel.
const TOLERANCE: f32 = 2e-4;

fn marcher() -> Option<GpuRayMarcher> {
    match GpuRayMarcher::new() {
        Ok(m) => {
            eprintln!(
                "adapter: {} (software: {})",
                m.adapter_name(),
                m.is_software()
            );
            Some(m)
        }
        Err(e) if std::env::var("STRATA_REQUIRE_GPU_ADAPTER").as_deref() == Ok("1") => {
            panic!("STRATA_REQUIRE_GPU_ADAPTER=1 but no adapter: {e:#}")
        }
        Err(e) => {
            // Straight to stderr, past libtest's capture, so the skip is visible in CI logs.
            let _ = writeln!(std::io::stderr(), "NOTICE: skipping GPU test: {e:#}");
            None
        }
    }
}

// ---------------------------------------------------------------------------------------
// Scalar reference: the crate-level algorithm, operation for operation as in raymarch.wgsl.
// ---------------------------------------------------------------------------------------

type V3 = [f32; 3];

fn lerp(a: f32, b: f32, t: f32) -> f32 {
    a * (1.0 - t) + b * t
}

fn dot(a: V3, b: V3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn slab(c: V3, md: V3, lo: V3, hi: V3) -> (f32, f32) {
    let (mut t0, mut t1) = (-3.0e38f32, 3.0e38f32);
    for a in 0..3 {
        if md[a] == 0.0 {
            if c[a] < lo[a] || c[a] > hi[a] {
                return (1.0, 0.0);
            }
        } else {
            let ta = (lo[a] - c[a]) / md[a];
            let tb = (hi[a] - c[a]) / md[a];
            t0 = t0.max(ta.min(tb));
            t1 = t1.min(ta.max(tb));
        }
    }
    (t0, t1)
}

fn first_lattice_at_or_after(t: f32, step: f32, k_min: u32) -> u32 {
    let mut k = ((t / step).ceil().max(0.0) as u32).max(k_min);
    while k > k_min && (k - 1) as f32 * step >= t {
        k -= 1;
    }
    while (k as f32) * step < t {
        k += 1;
    }
    k
}

fn sample_volume(job: &VolumeJob, qc: V3) -> f32 {
    let [nx, ny, _] = job.dims;
    let f = qc.map(f32::floor);
    let w = [qc[0] - f[0], qc[1] - f[1], qc[2] - f[2]];
    let i0 = f.map(|v| v as u32);
    let i1: [u32; 3] = std::array::from_fn(|a| (i0[a] + 1).min(job.dims[a] - 1));
    let at = |x: u32, y: u32, z: u32| job.voxels[((z * ny + y) * nx + x) as usize];
    let c00 = lerp(at(i0[0], i0[1], i0[2]), at(i1[0], i0[1], i0[2]), w[0]);
    let c10 = lerp(at(i0[0], i1[1], i0[2]), at(i1[0], i1[1], i0[2]), w[0]);
    let c01 = lerp(at(i0[0], i0[1], i1[2]), at(i1[0], i0[1], i1[2]), w[0]);
    let c11 = lerp(at(i0[0], i1[1], i1[2]), at(i1[0], i1[1], i1[2]), w[0]);
    lerp(lerp(c00, c10, w[1]), lerp(c01, c11, w[1]), w[2])
}

fn classify(job: &VolumeJob, v: f32) -> [f32; 4] {
    let n = job.tf.len() as u32;
    if n == 1 {
        return job.tf[0];
    }
    let [lo, hi] = job.tf_range;
    let s = ((v - lo) / (hi - lo)).clamp(0.0, 1.0) * (n - 1) as f32;
    let i = (s.floor() as u32).min(n - 2);
    let f = s - i as f32;
    std::array::from_fn(|c| lerp(job.tf[i as usize][c], job.tf[i as usize + 1][c], f))
}

/// One pixel. The flag says the ray's alpha came within 1e-5 of the early-termination
/// threshold, where one rounding step on either side may legitimately decide whether one
/// more sample is composited.
fn reference_pixel(job: &VolumeJob, x: u32, y: u32) -> ([f32; 4], bool) {
    let fx = x as f32 + 0.5;
    let fy = y as f32 + 0.5;
    let r: V3 = std::array::from_fn(|a| job.dir00[a] + fx * job.du[a] + fy * job.dv[a]);
    let len = dot(r, r).sqrt();
    let d = r.map(|v| v / len);
    let m = job.world_to_index;
    let c: V3 = [m[0][3], m[1][3], m[2][3]];
    let md: V3 = std::array::from_fn(|a| dot([m[a][0], m[a][1], m[a][2]], d));
    let box_lo = [-0.5f32; 3];
    let box_hi = job.dims.map(|n| n as f32 - 0.5);
    let (t0, t1) = slab(c, md, box_lo, box_hi);
    let t0 = t0.max(0.0);
    let mut acc = [0.0f32; 4];
    let mut near_threshold = false;
    if t0 >= t1 {
        return (acc, false);
    }
    let step = job.step;
    let brick = job.brick;
    let cells = job
        .dims
        .map(|n| if brick > 0 { n.div_ceil(brick) } else { 0 });
    let q_max = job.dims.map(|n| n as f32 - 1.0);
    let mut k = first_lattice_at_or_after(t0, step, 0);
    loop {
        let t = k as f32 * step;
        if t >= t1 {
            break;
        }
        let q: V3 = std::array::from_fn(|a| c[a] + t * md[a]);
        let qc: V3 = std::array::from_fn(|a| q[a].max(0.0).min(q_max[a]));
        if brick > 0 {
            let cell: [u32; 3] =
                std::array::from_fn(|a| ((qc[a] / brick as f32).floor() as u32).min(cells[a] - 1));
            if job.transparent[((cell[2] * cells[1] + cell[1]) * cells[0] + cell[0]) as usize] != 0
            {
                let lo: V3 =
                    std::array::from_fn(|a| ((cell[a] * brick) as f32 - 0.5).max(box_lo[a]));
                let hi: V3 =
                    std::array::from_fn(|a| (((cell[a] + 1) * brick) as f32 - 0.5).min(box_hi[a]));
                let t_exit = slab(c, md, lo, hi).1;
                k = first_lattice_at_or_after(t_exit, step, k + 1);
                continue;
            }
        }
        let mut rgba = classify(job, sample_volume(job, qc));
        if rgba[3] > 0.0 {
            if job.alpha_exponent != 1.0 {
                rgba[3] = if rgba[3] >= 1.0 {
                    1.0
                } else {
                    1.0 - (1.0 - rgba[3]).powf(job.alpha_exponent)
                };
            }
            let w = (1.0 - acc[3]) * rgba[3];
            for ch in 0..3 {
                acc[ch] += w * rgba[ch];
            }
            acc[3] += w;
            if job.early_termination < 1.0 && (acc[3] - job.early_termination).abs() < 1e-5 {
                near_threshold = true;
            }
            if acc[3] >= job.early_termination {
                break;
            }
        }
        k += 1;
    }
    (acc, near_threshold)
}

fn reference_image(job: &VolumeJob) -> (Vec<[f32; 4]>, Vec<bool>) {
    (0..job.height)
        .flat_map(|y| (0..job.width).map(move |x| (x, y)))
        .map(|(x, y)| reference_pixel(job, x, y))
        .unzip()
}

/// Number of lattice samples on pixel (x, y)'s ray inside the volume box.
fn lattice_samples(job: &VolumeJob, x: u32, y: u32) -> u64 {
    let r: V3 = std::array::from_fn(|a| {
        job.dir00[a] + (x as f32 + 0.5) * job.du[a] + (y as f32 + 0.5) * job.dv[a]
    });
    let len = dot(r, r).sqrt();
    let d = r.map(|v| v / len);
    let m = job.world_to_index;
    let md: V3 = std::array::from_fn(|a| dot([m[a][0], m[a][1], m[a][2]], d));
    let (t0, t1) = slab(
        [m[0][3], m[1][3], m[2][3]],
        md,
        [-0.5; 3],
        job.dims.map(|n| n as f32 - 0.5),
    );
    let t0 = t0.max(0.0);
    if t0 >= t1 {
        return 0;
    }
    (first_lattice_at_or_after(t1, job.step, 0) - first_lattice_at_or_after(t0, job.step, 0)) as u64
}

// ---------------------------------------------------------------------------------------
// Scene construction
// ---------------------------------------------------------------------------------------

type M3 = [[f64; 3]; 3];

fn mat_mul(a: M3, b: M3) -> M3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

fn mat_vec(a: M3, v: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| (0..3).map(|k| a[i][k] * v[k]).sum())
}

fn invert(m: M3) -> M3 {
    let c =
        |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let det = m[0][0] * c(1, 2, 1, 2) - m[0][1] * c(1, 2, 0, 2) + m[0][2] * c(1, 2, 0, 1);
    [
        [
            c(1, 2, 1, 2) / det,
            -c(0, 2, 1, 2) / det,
            c(0, 1, 1, 2) / det,
        ],
        [
            -c(1, 2, 0, 2) / det,
            c(0, 2, 0, 2) / det,
            -c(0, 1, 0, 2) / det,
        ],
        [
            c(1, 2, 0, 1) / det,
            -c(0, 2, 0, 1) / det,
            c(0, 1, 0, 1) / det,
        ],
    ]
}

/// Rotation by `angle` about `axis` (Rodrigues).
fn rotation(axis: [f64; 3], angle: f64) -> M3 {
    let n = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
    let [x, y, z] = axis.map(|v| v / n);
    let (s, c) = angle.sin_cos();
    let t = 1.0 - c;
    [
        [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
    ]
}

/// `world_to_index` rows for a volume whose voxel axes are `index_to_world` (columns = voxel
/// steps in camera space) and whose centre voxel lies at `centre` (camera-relative).
fn world_to_index(dims: [u32; 3], index_to_world: M3, centre: [f64; 3]) -> [[f32; 4]; 3] {
    let qc = dims.map(|n| (n as f64 - 1.0) / 2.0);
    let aq = mat_vec(index_to_world, qc);
    let b: [f64; 3] = std::array::from_fn(|i| centre[i] - aq[i]);
    let m = invert(index_to_world);
    let c = mat_vec(m, b);
    std::array::from_fn(|i| [m[i][0] as f32, m[i][1] as f32, m[i][2] as f32, -c[i] as f32])
}

/// Pinhole camera at the origin looking down +z, +y up, vertical half-angle tan = `tan_half`.
fn camera(width: u32, height: u32, tan_half: f64) -> ([f32; 3], [f32; 3], [f32; 3]) {
    let aspect = width as f64 / height as f64;
    let dir00 = [-tan_half * aspect, tan_half, 1.0].map(|v| v as f32);
    let du = [2.0 * tan_half * aspect / width as f64, 0.0, 0.0].map(|v| v as f32);
    let dv = [0.0, -2.0 * tan_half / height as f64, 0.0].map(|v| v as f32);
    (dir00, du, dv)
}

fn analytic_field(dims: [u32; 3]) -> Vec<f32> {
    let [nx, ny, nz] = dims;
    let mut v = Vec::with_capacity((nx * ny * nz) as usize);
    for z in 0..nz {
        for y in 0..ny {
            for x in 0..nx {
                let (x, y, z) = (x as f64, y as f64, z as f64);
                let blob = |cx: f64, cy: f64, cz: f64, r2: f64| {
                    (-((x - cx).powi(2) + (y - cy).powi(2) + (z - cz).powi(2)) / r2).exp()
                };
                let f = blob(14.0, 12.0, 13.0, 150.0)
                    + 0.8 * blob(29.0, 22.0, 10.0, 100.0)
                    + 0.15 * (0.7 * x).sin() * (0.5 * y).cos() * (0.9 * z + 0.3).sin();
                v.push(f as f32);
            }
        }
    }
    v
}

/// 16 entries over [0, 1.2]: transparent below 0.4, then rising alpha and shifting colour.
fn test_tf() -> Vec<[f32; 4]> {
    (0..16)
        .map(|i| {
            let u = i as f32 / 15.0;
            let a = if i < 5 {
                0.0
            } else {
                0.6 * ((i - 4) as f32 / 11.0).powf(1.5)
            };
            [u, 1.0 - 0.5 * u, 0.3 + 0.4 * (6.0 * u).sin().abs(), a]
        })
        .collect()
}

/// Conservative transparency flags: a cell is transparent if the table is zero-alpha over the
/// whole value range of the voxels a sample in the cell's box can touch (one voxel beyond the
/// box for the trilinear footprint, plus one more as margin against rounding at the faces).
fn transparency_flags(
    dims: [u32; 3],
    voxels: &[f32],
    brick: u32,
    tf: &[[f32; 4]],
    tf_range: [f32; 2],
) -> Vec<u32> {
    let cells = dims.map(|n| n.div_ceil(brick));
    let n = tf.len();
    let position =
        |v: f32| ((v - tf_range[0]) / (tf_range[1] - tf_range[0])).clamp(0.0, 1.0) * (n - 1) as f32;
    let mut flags = Vec::new();
    for cz in 0..cells[2] {
        for cy in 0..cells[1] {
            for cx in 0..cells[0] {
                let cell = [cx, cy, cz];
                let range = |a: usize| {
                    let lo = (cell[a] * brick).saturating_sub(2);
                    let hi = ((cell[a] + 1) * brick + 1).min(dims[a] - 1);
                    lo..=hi
                };
                let (mut min, mut max) = (f32::INFINITY, f32::NEG_INFINITY);
                for z in range(2) {
                    for y in range(1) {
                        for x in range(0) {
                            let v = voxels[((z * dims[1] + y) * dims[0] + x) as usize];
                            min = min.min(v);
                            max = max.max(v);
                        }
                    }
                }
                let (first, last) = (
                    position(min).floor() as usize,
                    (position(max).ceil() as usize).min(n - 1),
                );
                flags.push(tf[first..=last].iter().all(|e| e[3] == 0.0) as u32);
            }
        }
    }
    flags
}

struct Scene {
    dims: [u32; 3],
    voxels: Vec<f32>,
    tf: Vec<[f32; 4]>,
    tf_range: [f32; 2],
    world_to_index: [[f32; 4]; 3],
}

impl Scene {
    fn analytic() -> Self {
        let dims = [40, 33, 27];
        let spacing = [0.9, 1.3, 1.1];
        let r = rotation([1.0, 2.0, 0.5], 35f64.to_radians());
        let scale: M3 = [
            [spacing[0], 0.0, 0.0],
            [0.0, spacing[1], 0.0],
            [0.0, 0.0, spacing[2]],
        ];
        Self {
            dims,
            voxels: analytic_field(dims),
            tf: test_tf(),
            tf_range: [0.0, 1.2],
            world_to_index: world_to_index(dims, mat_mul(r, scale), [2.0, -1.5, 75.0]),
        }
    }

    fn job<'a>(&'a self, brick: u32, flags: &'a [u32], early_termination: f32) -> VolumeJob<'a> {
        let (width, height) = (64, 48);
        let (dir00, du, dv) = camera(width, height, 0.25);
        VolumeJob {
            dims: self.dims,
            voxels: &self.voxels,
            world_to_index: self.world_to_index,
            tf: &self.tf,
            tf_range: self.tf_range,
            width,
            height,
            dir00,
            du,
            dv,
            step: 0.5,
            alpha_exponent: 0.5 / 0.8,
            early_termination,
            brick,
            transparent: flags,
        }
    }
}

/// Largest channel difference, skipping pixels marked ambiguous; also returns how many were.
fn compare(gpu: &[[f32; 4]], reference: &[[f32; 4]], ambiguous: &[bool]) -> (f32, usize) {
    assert_eq!(gpu.len(), reference.len());
    let mut worst = 0.0f32;
    let mut skipped = 0;
    for ((g, r), &amb) in gpu.iter().zip(reference).zip(ambiguous) {
        if amb {
            skipped += 1;
            continue;
        }
        for c in 0..4 {
            let d = (g[c] - r[c]).abs();
            assert!(d.is_finite(), "non-finite pixel: gpu {g:?} reference {r:?}");
            worst = worst.max(d);
        }
    }
    (worst, skipped)
}

#[test]
fn analytic_volume_matches_reference() {
    let Some(mut gpu) = marcher() else { return };
    let scene = Scene::analytic();

    // Unskipped reference without early termination, to check the scene is a real test.
    let baseline_job = scene.job(0, &[], 1.0);
    let (baseline, _) = reference_image(&baseline_job);
    let missed = baseline.iter().filter(|p| p[3] == 0.0).count();
    let opaque = baseline.iter().filter(|p| p[3] > 0.95).count();
    let total = baseline.len();
    eprintln!("scene: {missed}/{total} pixels empty, {opaque} with alpha > 0.95");
    assert!(
        missed > 0 && missed < total * 3 / 4,
        "camera should see the volume and some background"
    );
    assert!(
        opaque > 0,
        "early termination at 0.95 must matter for some pixels"
    );

    for brick in [0u32, 8, 5] {
        let flags = if brick > 0 {
            transparency_flags(scene.dims, &scene.voxels, brick, &scene.tf, scene.tf_range)
        } else {
            Vec::new()
        };
        let transparent = flags.iter().filter(|&&f| f != 0).count();
        if brick > 0 {
            eprintln!(
                "brick {brick}: {transparent}/{} cells transparent",
                flags.len()
            );
            assert!(
                transparent > 0 && transparent < flags.len(),
                "skipping must be exercised"
            );
        }
        for et in [1.0f32, 0.95] {
            let job = scene.job(brick, &flags, et);
            let (reference, ambiguous) = reference_image(&job);
            if brick > 0 {
                // Skipping only jumps over zero-alpha samples, so it may not change the image.
                let (unskipped, _) = reference_image(&scene.job(0, &[], et));
                let (d, _) = compare(&reference, &unskipped, &ambiguous);
                assert!(
                    d <= 1e-6,
                    "reference with skipping differs from without by {d}"
                );
            }
            let frame = gpu.render(&job).expect("render");
            let (worst, skipped) = compare(&frame.rgba, &reference, &ambiguous);
            eprintln!(
                "brick {brick} et {et}: max |gpu - ref| = {worst:.2e} ({skipped} pixels at the threshold skipped); \
                 upload {:.2} ms kernel {:.2} ms readback {:.2} ms",
                frame.upload_ms, frame.kernel_ms, frame.readback_ms
            );
            assert!(
                skipped * 100 <= total,
                "too many pixels at the early-termination threshold"
            );
            assert!(
                worst <= TOLERANCE,
                "brick {brick} et {et}: max difference {worst} > {TOLERANCE}"
            );
        }
    }
}

/// Honest flags only ever skip zero-alpha samples, so a wrong exit distance or lattice jump
/// could hide in them. Deliberately false flags (a checkerboard of cells, most of them
/// visible) make every jump change the image, so the GPU must follow the same skipping rule
/// as the reference sample for sample.
#[test]
fn checkerboard_skipping_matches_reference() {
    let Some(mut gpu) = marcher() else { return };
    let scene = Scene::analytic();
    let (unskipped, _) = reference_image(&scene.job(0, &[], 1.0));
    for brick in [8u32, 5] {
        let cells = scene.dims.map(|n| n.div_ceil(brick));
        let mut flags = Vec::new();
        for z in 0..cells[2] {
            for y in 0..cells[1] {
                for x in 0..cells[0] {
                    flags.push((x + y + z) % 2);
                }
            }
        }
        for et in [1.0f32, 0.95] {
            let job = scene.job(brick, &flags, et);
            let (reference, ambiguous) = reference_image(&job);
            let changed = reference
                .iter()
                .zip(&unskipped)
                .filter(|(a, b)| (a[3] - b[3]).abs() > 1e-3)
                .count();
            assert!(
                changed > reference.len() / 10,
                "the false flags should change the image ({changed} pixels)"
            );
            let frame = gpu.render(&job).expect("render");
            let (worst, skipped) = compare(&frame.rgba, &reference, &ambiguous);
            eprintln!("checkerboard brick {brick} et {et}: {changed} pixels changed by skipping, max |gpu - ref| = {worst:.2e} ({skipped} at the threshold)");
            assert!(
                worst <= TOLERANCE,
                "brick {brick} et {et}: max difference {worst} > {TOLERANCE}"
            );
        }
    }
    // All cells flagged: nothing is ever sampled.
    let all = vec![1u32; 100];
    let frame = gpu.render(&scene.job(8, &all, 1.0)).expect("render");
    assert!(
        frame.rgba.iter().all(|p| *p == [0.0; 4]),
        "all-transparent flags must give an empty image"
    );
}

/// Constant value, constant alpha: a ray with n samples must have A = 1 - (1 - a')^n where
/// a' = 1 - (1 - a)^e, i.e. A = 1 - (1 - a)^(e n), and C = rgb * A.
#[test]
fn homogeneous_slab_has_exact_transmittance() {
    let Some(mut gpu) = marcher() else { return };
    let dims = [16u32, 16, 8];
    let voxels = vec![0.7f32; (dims[0] * dims[1] * dims[2]) as usize];
    // Index = p + c: the slab spans world z in [9.75, 17.75) and is wide in x and y, so every
    // ray of the narrow camera enters and leaves through the z faces.
    let world_to_index = [
        [1.0, 0.0, 0.0, 7.5],
        [0.0, 1.0, 0.0, 7.5],
        [0.0, 0.0, 1.0, -10.25],
    ];
    let (a, rgb) = (0.2f64, [0.9f64, 0.5, 0.25]);
    let tf = [[rgb[0] as f32, rgb[1] as f32, rgb[2] as f32, a as f32]];
    let (width, height) = (5u32, 5u32);
    // The middle pixel looks exactly down +z (zero x and y direction components).
    // Powers of two keep dir00 + 2.5 * du exactly 0.
    let (dir00, du, dv) = (
        [-0.01953125f32, -0.01953125, 1.0],
        [0.0078125f32, 0.0, 0.0],
        [0.0f32, 0.0078125, 0.0],
    );
    let (step, e) = (0.5f32, 0.5f32);
    for et in [1.0f32, 0.5] {
        let job = VolumeJob {
            dims,
            voxels: &voxels,
            world_to_index,
            tf: &tf,
            tf_range: [0.0, 1.0],
            width,
            height,
            dir00,
            du,
            dv,
            step,
            alpha_exponent: e,
            early_termination: et,
            brick: 0,
            transparent: &[],
        };
        let frame = gpu.render(&job).expect("render");
        for y in 0..height {
            for x in 0..width {
                // Samples in [9.75 / dz, 17.75 / dz) on the lattice k * step, counted in f64.
                let r = [
                    dir00[0] as f64 + (x as f64 + 0.5) * du[0] as f64,
                    dir00[1] as f64 + (y as f64 + 0.5) * dv[1] as f64,
                    1.0,
                ];
                let dz = 1.0 / (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
                let (t0, t1) = (9.75 / dz, 17.75 / dz);
                let (k0, k1) = ((t0 / step as f64).ceil(), (t1 / step as f64).ceil());
                for t in [t0, t1] {
                    let off = (t / step as f64 - (t / step as f64).round()).abs();
                    assert!(
                        off > 1e-4 || (x, y) == (2, 2),
                        "pixel ({x}, {y}) is ambiguous"
                    );
                }
                let mut n = k1 - k0;
                // With early termination the march stops at the first n with A >= et.
                let transmittance = |n: f64| (1.0 - a).powf(e as f64 * n);
                if et < 1.0 {
                    let stop = ((1.0 - et as f64).ln() / (e as f64 * (1.0 - a).ln())).ceil();
                    n = n.min(stop);
                }
                let alpha = 1.0 - transmittance(n);
                let expect = [rgb[0] * alpha, rgb[1] * alpha, rgb[2] * alpha, alpha];
                let got = frame.rgba[(y * width + x) as usize];
                for c in 0..4 {
                    assert!(
                        (got[c] as f64 - expect[c]).abs() < 2e-5,
                        "pixel ({x}, {y}) et {et}: n = {n}, got {got:?}, expected {expect:?}"
                    );
                }
            }
        }
        let centre = frame.rgba[(2 * width + 2) as usize];
        eprintln!("slab et {et}: centre pixel {centre:?}");
    }
}

#[test]
fn invalid_jobs_are_errors_not_panics() {
    let Some(mut gpu) = marcher() else { return };
    let scene = Scene::analytic();
    let good = scene.job(0, &[], 1.0);
    gpu.render(&good).expect("the valid job renders");

    let short = &scene.voxels[1..];
    let bad_flags = [0u32; 3];
    let nan_voxels: Vec<f32> = scene
        .voxels
        .iter()
        .enumerate()
        .map(|(i, &v)| if i == 7 { f32::NAN } else { v })
        .collect();
    let cases: Vec<(&str, VolumeJob)> = vec![
        (
            "voxel count",
            VolumeJob {
                voxels: short,
                ..good
            },
        ),
        ("empty tf", VolumeJob { tf: &[], ..good }),
        ("zero width", VolumeJob { width: 0, ..good }),
        (
            "flag count",
            VolumeJob {
                brick: 8,
                transparent: &bad_flags,
                ..good
            },
        ),
        ("zero step", VolumeJob { step: 0.0, ..good }),
        (
            "empty tf range",
            VolumeJob {
                tf_range: [1.0, 1.0],
                ..good
            },
        ),
        (
            "singular matrix",
            VolumeJob {
                world_to_index: [[0.0; 4]; 3],
                ..good
            },
        ),
        (
            "NaN voxel",
            VolumeJob {
                voxels: &nan_voxels,
                ..good
            },
        ),
        (
            "early termination 0",
            VolumeJob {
                early_termination: 0.0,
                ..good
            },
        ),
    ];
    for (what, job) in cases {
        let err = gpu
            .render(&job)
            .err()
            .unwrap_or_else(|| panic!("{what}: expected an error"));
        eprintln!("{what}: {err:#}");
    }
    // The marcher still works after the errors.
    gpu.render(&good)
        .expect("the valid job renders after errors");
}

/// Not a correctness test: one 1920x1080 frame of a 256^3 volume, for the numbers in the
/// benchmark notes. `cargo test -p strata-gpu --test wgsl_matches_reference -- --ignored --nocapture`
#[test]
#[ignore]
fn timing_1080p_256_cubed() {
    let Some(mut gpu) = marcher() else { return };
    let n = 256u32;
    let dims = [n; 3];
    let clock = Instant::now();
    let mut voxels = Vec::with_capacity((n * n * n) as usize);
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                let p = [x, y, z].map(|v| v as f32 / n as f32 - 0.5);
                let r2 = p[0] * p[0] + p[1] * p[1] + p[2] * p[2];
                voxels.push(
                    (-r2 * 8.0).exp()
                        + 0.2 * (20.0 * p[0]).sin() * (17.0 * p[1]).cos() * (13.0 * p[2]).sin(),
                );
            }
        }
    }
    let tf = test_tf();
    let tf_range = [0.0f32, 1.2];
    eprintln!(
        "volume generated in {:.0} ms",
        clock.elapsed().as_secs_f64() * 1e3
    );
    let r = rotation([0.3, 1.0, 0.2], 25f64.to_radians());
    let world_to_index = world_to_index(dims, r, [0.0, 0.0, 330.0]);
    let (width, height) = (1920u32, 1080u32);
    let (dir00, du, dv) = camera(width, height, 0.5);
    let flags = transparency_flags(dims, &voxels, 8, &tf, tf_range);
    let transparent = flags.iter().filter(|&&f| f != 0).count();
    let job = |brick: u32, early_termination: f32| VolumeJob {
        dims,
        voxels: &voxels,
        world_to_index,
        tf: &tf,
        tf_range,
        width,
        height,
        dir00,
        du,
        dv,
        step: 1.0,
        alpha_exponent: 1.0,
        early_termination,
        brick,
        transparent: if brick > 0 { &flags } else { &[] },
    };
    // Samples a full march takes (no skipping, no early termination), for a throughput figure.
    let full = job(0, 1.0);
    let samples: u64 = (0..height)
        .flat_map(|y| (0..width).map(move |x| (x, y)))
        .map(|(x, y)| lattice_samples(&full, x, y))
        .sum();
    eprintln!(
        "{}: {:.1} M samples in a full march",
        gpu.adapter_name(),
        samples as f64 / 1e6
    );
    for (brick, et) in [(0u32, 1.0f32), (0, 0.99), (8, 0.99)] {
        for _ in 0..2 {
            let clock = Instant::now();
            let frame = gpu.render(&job(brick, et)).expect("render");
            let total_ms = clock.elapsed().as_secs_f64() * 1e3;
            let covered = frame.rgba.iter().filter(|p| p[3] > 0.0).count();
            eprintln!(
                "1920x1080 256^3 brick {brick} et {et}: total {total_ms:.0} ms = upload {:.1} + kernel {:.1} + readback {:.1} ms \
                 ({:.1} M full-march samples/s; {covered} pixels covered, {transparent}/{} cells transparent)",
                frame.upload_ms,
                frame.kernel_ms,
                frame.readback_ms,
                samples as f64 / frame.kernel_ms / 1e3,
                flags.len(),
            );
        }
    }
}
