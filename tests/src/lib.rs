//! Shared helpers for Strata's end-to-end tests.

use std::path::PathBuf;
use strata_common::pyramid::Dim;
use strata_common::store::{DataKind, PageStore};

/// The shared real-data folder (`../shared/data/real` beside the checkout).
pub fn real_data(rel: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/data/real")
        .join(rel)
}

pub mod fuzz;

pub use strata_coordinator::inspect::level_grid;

/// Bitwise equality that treats all NaNs as equal.
pub fn same(a: f32, b: f32) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

/// Checks that every page of every level holds, border included, exactly the level's
/// samples at its position (edge replicas for volumes, holes outside a horizon's grid).
/// Returns the first mismatch as a message.
pub fn check_borders(store: &PageStore) -> Result<(), String> {
    let pyr = store.pyramid();
    let horizon = store.header().kind == DataKind::Horizon;
    let pd = pyr.page_dims().map(|v| v as i64);
    for l in 0..pyr.level_count() {
        let grid = level_grid(store, l).map_err(|e| e.to_string())?;
        let dims = pyr.level(l).dims.map(|d| d as i64);
        for br in pyr.bricks_in_z_order(l) {
            let page = store.read_page(pyr.id(l, br)).map_err(|e| e.to_string())?;
            let o = pyr.page_origin(br);
            for pz in 0..pd[2] {
                for py in 0..pd[1] {
                    for px in 0..pd[0] {
                        let g = [o[0] + px, o[1] + py, o[2] + pz];
                        let outside = (0..3).any(|a| g[a] < 0 || g[a] >= dims[a]);
                        let want = if horizon && outside {
                            f32::NAN
                        } else {
                            let c = [0, 1, 2].map(|a| g[a].clamp(0, dims[a] - 1));
                            grid[((c[2] * dims[1] + c[1]) * dims[0] + c[0]) as usize]
                        };
                        let got = page.samples[((pz * pd[1] + py) * pd[0] + px) as usize];
                        if !same(got, want) {
                            return Err(format!("level {l} brick {br:?} local ({px},{py},{pz}) global {g:?}: page has {got}, level has {want}"));
                        }
                    }
                }
            }
        }
        let _ = pyr.dim() == Dim::Two;
    }
    Ok(())
}

/// Checks that every coarse level equals the store's filter applied to the level below
/// (2×2(×2) children, indices clamped at the level's end), quantized to the sample type.
pub fn check_coarse_levels(store: &PageStore) -> Result<(), String> {
    let h = store.header();
    let pyr = store.pyramid();
    let flat = pyr.dim() == Dim::Two;
    for l in 1..pyr.level_count() {
        let fine = level_grid(store, l - 1).map_err(|e| e.to_string())?;
        let coarse = level_grid(store, l).map_err(|e| e.to_string())?;
        let fd = pyr.level(l - 1).dims;
        let cd = pyr.level(l).dims;
        for z in 0..cd[2] {
            for y in 0..cd[1] {
                for x in 0..cd[0] {
                    let mut kids = Vec::with_capacity(8);
                    for dz in if flat { 0..1 } else { 0..2 } {
                        for dy in 0..2 {
                            for dx in 0..2 {
                                let f = [
                                    (2 * x + dx).min(fd[0] - 1),
                                    (2 * y + dy).min(fd[1] - 1),
                                    if flat { 0 } else { (2 * z + dz).min(fd[2] - 1) },
                                ];
                                kids.push(fine[((f[2] * fd[1] + f[1]) * fd[0] + f[0]) as usize]);
                            }
                        }
                    }
                    let want = h
                        .sample_type
                        .quantize_valid(h.filter.apply(&kids), h.no_data);
                    let got = coarse[((z * cd[1] + y) * cd[0] + x) as usize];
                    if !same(got, want) {
                        return Err(format!("level {l} sample ({x},{y},{z}): stored {got}, filter of level {} gives {want}", l - 1));
                    }
                }
            }
        }
    }
    Ok(())
}

/// Builders of small stores and scenes for rendering tests.
pub mod scenes {
    use indicatif::ProgressBar;
    use std::path::{Path, PathBuf};
    use strata_common::geo::Affine3;
    use strata_common::image::{composite_front_to_back, PartialImage, Rgba};
    use strata_common::kd::{KdTree, Region};
    use strata_common::sample::SampleType;
    use strata_common::scene::{Backend, Camera, HorizonLayer, RenderSettings, Scene, VolumeLayer};
    use strata_coordinator::builder::{build_store, BuildOptions};
    use strata_coordinator::source::MemorySource;
    use strata_worker::engine::{Engine, Outcome};

    /// Writes an f32 volume store (`data` x fastest).
    pub fn volume_store(
        dir: &Path,
        name: &str,
        dims: [u64; 3],
        data: Vec<f32>,
        transform: Affine3,
        page: u32,
    ) -> PathBuf {
        let path = dir.join(format!("{name}.strata"));
        let mut o = BuildOptions::volume(name, SampleType::F32);
        o.page_size = page;
        o.border = 1;
        o.transform = transform;
        build_store(
            &MemorySource { dims, data },
            &path,
            &o,
            &ProgressBar::hidden(),
        )
        .unwrap();
        path
    }

    /// Writes a horizon store (`heights` i fastest, NaN = hole).
    pub fn horizon_store(
        dir: &Path,
        name: &str,
        dims: [u64; 2],
        heights: Vec<f32>,
        transform: Affine3,
        page: u32,
    ) -> PathBuf {
        let path = dir.join(format!("{name}.strata"));
        let mut o = BuildOptions::horizon(name);
        o.page_size = page;
        o.transform = transform;
        build_store(
            &MemorySource {
                dims: [dims[0], dims[1], 1],
                data: heights,
            },
            &path,
            &o,
            &ProgressBar::hidden(),
        )
        .unwrap();
        path
    }

    /// A volume layer with a constant straight-RGBA transfer function over `window`.
    pub fn volume_layer(
        store: PathBuf,
        colormap: &str,
        window: [f64; 2],
        points: Vec<[f64; 2]>,
    ) -> VolumeLayer {
        VolumeLayer {
            store,
            colormap: colormap.into(),
            window: Some(window),
            opacity: 1.0,
            opacity_points: Some(points),
            slices: Vec::new(),
        }
    }

    /// A horizon layer of a constant colour.
    pub fn horizon_layer(store: PathBuf, color: [f64; 3], opacity: f64) -> HorizonLayer {
        HorizonLayer {
            store,
            color,
            opacity,
            color_by: "constant".into(),
            colormap: "viridis".into(),
            volume: 0,
        }
    }

    /// Render settings for exact comparisons: z up, no early termination.
    pub fn exact_settings(w: u32, h: u32) -> RenderSettings {
        RenderSettings {
            width: w,
            height: h,
            z_down: false,
            early_termination: 1.0,
            max_rounds: 64,
            ..RenderSettings::default()
        }
    }

    /// A scene.
    pub fn scene(
        volumes: Vec<VolumeLayer>,
        horizons: Vec<HorizonLayer>,
        camera: Camera,
        render: RenderSettings,
    ) -> Scene {
        Scene {
            volumes,
            horizons,
            camera: Some(camera),
            render,
            synthetic: None,
            composite: Default::default(),
            cluster: Default::default(),
            wall: None,
        }
    }

    /// Two overlapping 24³ volumes of different resolution and orientation (seismic and
    /// viridis maps), seen from outside both; every `nan_every`-th sample of the first is NaN
    /// (no data) when `nan_every > 0`.
    pub fn overlapping_volumes(dir: &Path, nan_every: u64) -> Scene {
        let n = 24u64;
        let a: Vec<f32> = (0..n * n * n)
            .map(|i| {
                if nan_every > 0 && i % nan_every == 0 {
                    f32::NAN
                } else {
                    ((i % n) as f32 * 0.5).sin() * ((i / (n * n)) as f32 * 0.3).cos()
                }
            })
            .collect();
        let b: Vec<f32> = (0..n * n * n)
            .map(|i| ((i / n % n) as f32 * 0.4).cos())
            .collect();
        let va = volume_store(dir, "a", [n, n, n], a, Affine3::IDENTITY, 32);
        let (c, s_) = (0.8f64, 0.6f64);
        let vb = volume_store(
            dir,
            "b",
            [n, n, n],
            b,
            Affine3 {
                rows: [
                    [0.7 * c, -0.7 * s_, 0.0, 8.0],
                    [0.7 * s_, 0.7 * c, 0.0, 2.0],
                    [0.0, 0.0, 0.9, 5.0],
                ],
            },
            32,
        );
        let cam = Camera {
            eye: [-30.0, -40.0, 50.0],
            target: [12.0, 12.0, 12.0],
            up: [0.0, 0.0, 1.0],
            fov_deg: 40.0,
        };
        scene(
            vec![
                volume_layer(
                    va,
                    "seismic",
                    [-1.0, 1.0],
                    vec![[0.0, 0.2], [0.5, 0.0], [1.0, 0.2]],
                ),
                volume_layer(vb, "viridis", [-1.0, 1.0], vec![[0.0, 0.0], [1.0, 0.15]]),
            ],
            vec![],
            cam,
            exact_settings(64, 48),
        )
    }

    /// k-d splits of 2, 4 and 7 regions (`(leaf, axis, fraction)`, see `KdTree::from_splits`).
    pub const SPLITS_2_4_7: [&[(usize, usize, f64)]; 3] = [
        &[(0, 0, 0.43)],
        &[(0, 2, 0.5), (0, 0, 0.3), (1, 1, 0.61)],
        &[
            (0, 0, 0.37),
            (0, 1, 0.6),
            (1, 2, 0.45),
            (2, 0, 0.5),
            (3, 1, 0.3),
            (1, 0, 0.71),
        ],
    ];

    /// Renders the whole scene in batch mode (asserting convergence); full-frame pixels.
    pub fn render_whole(scene: &Scene) -> Vec<Rgba> {
        let mut e = Engine::new(scene).unwrap();
        let view = e.view(scene.render.width, scene.render.height).unwrap();
        let region = e.scene_region();
        let r = e.render_batch(&view, &region).unwrap();
        assert_eq!(r.outcome, Outcome::Converged, "after {} rounds", r.rounds);
        r.image.to_full()
    }

    /// Whether a wgpu adapter (software included) exists, so the GPU backend can be tested.
    /// Without one this prints a notice and returns false, unless
    /// `STRATA_REQUIRE_GPU_ADAPTER=1` (CI sets it, with lavapipe installed): then it panics.
    /// Once an adapter exists, the caster must build on it (a shader error panics).
    pub fn gpu_available() -> bool {
        use strata_worker::gpu::{list_adapters, AdapterChoice, GpuCaster};
        if list_adapters().is_empty() {
            if std::env::var("STRATA_REQUIRE_GPU_ADAPTER").as_deref() == Ok("1") {
                panic!("STRATA_REQUIRE_GPU_ADAPTER=1 but wgpu finds no adapter");
            }
            eprintln!("NOTICE: GPU comparison skipped, no wgpu adapter");
            return false;
        }
        if let Err(e) = GpuCaster::new(&AdapterChoice {
            adapter: None,
            allow_software: true,
            spread: None,
        }) {
            panic!("an adapter exists but the GPU caster does not open on it: {e:#}");
        }
        true
    }

    /// The scene with `render.backend` set.
    pub fn on_backend(s: &Scene, b: Backend) -> Scene {
        let mut s = s.clone();
        s.render.backend = b;
        s
    }

    /// Renders the scene on the CPU and, where an adapter exists, on the GPU too, asserting
    /// that the two images agree within `tol` (largest channel difference) and that the GPU
    /// image is clean; returns the CPU image. The CPU renders twice, with its SIMD packets
    /// (where the CPU has AVX2) on the code specialised to its effects, and with the scalar
    /// march on the general code path (`render.variant = "general"`), and the two must agree
    /// bit for bit: every scene that goes through here checks the packet path, the scalar
    /// fallback and the general path.
    pub fn render_on_both(scene: &Scene, tol: f32, what: &str) -> Vec<Rgba> {
        let cpu = render_whole(&on_backend(scene, Backend::Cpu));
        let mut scalar = on_backend(scene, Backend::Cpu);
        scalar.render.simd = false;
        scalar.render.variant = strata_common::scene::CodePath::General;
        let scalar = render_whole(&scalar);
        assert!(
            bit_identical(&cpu, &scalar),
            "{what}: SIMD packets on the specialised path and the scalar march on the general \
             path differ by {}",
            max_diff(&cpu, &scalar)
        );
        if gpu_available() {
            let gpu = render_whole(&on_backend(scene, Backend::Gpu));
            assert_clean(&gpu);
            let d = max_diff(&cpu, &gpu);
            assert!(
                d <= tol,
                "{what}: GPU differs from CPU by {d} (tolerance {tol})"
            );
        }
        cpu
    }

    /// Renders each leaf of `tree` with its own engine (as separate workers would) and
    /// composites the partial images front to back in the tree's visibility order.
    pub fn render_split(scene: &Scene, tree: &KdTree) -> Vec<Rgba> {
        let (w, h) = (scene.render.width, scene.render.height);
        let mut parts = Vec::new();
        let mut eye = [0.0; 3];
        for leaf in &tree.leaves {
            let mut e = Engine::new(scene).unwrap();
            let view = e.view(w, h).unwrap();
            eye = e.camera().eye;
            let r = e.render_batch(&view, leaf).unwrap();
            assert_eq!(r.outcome, Outcome::Converged);
            parts.push(r.image);
        }
        let order = tree.visibility_order(eye);
        let ordered: Vec<&PartialImage> = order.iter().map(|&i| &parts[i]).collect();
        composite_front_to_back(w, h, &ordered)
    }

    /// The region of a scene (as the engine sees it).
    pub fn scene_region(scene: &Scene) -> Region {
        Engine::new(scene).unwrap().scene_region()
    }

    /// Lattice samples `k·dt` in `[t0, t1)`, counted with the caster's f32 arithmetic.
    pub fn lattice_count(t0: f32, t1: f32, dt: f32) -> u64 {
        let mut n = 0;
        let mut k = (t0 / dt).floor() as i64 - 2;
        loop {
            let t = k as f32 * dt;
            if t >= t1 {
                return n;
            }
            if t >= t0 {
                n += 1;
            }
            k += 1;
        }
    }

    /// Whether two images are equal bit for bit.
    pub fn bit_identical(a: &[Rgba], b: &[Rgba]) -> bool {
        a.len() == b.len()
            && a.iter()
                .zip(b)
                .all(|(p, q)| p.iter().zip(q).all(|(x, y)| x.to_bits() == y.to_bits()))
    }

    /// Largest absolute channel difference; infinite where either image holds a NaN (a
    /// plain `f32::max` fold skips NaN, so a NaN pixel would pass every tolerance).
    pub fn max_diff(a: &[Rgba], b: &[Rgba]) -> f32 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .flat_map(|(p, q)| (0..4).map(move |c| (p[c] - q[c]).abs()))
            .fold(
                0.0,
                |m: f32, d: f32| if d.is_nan() { f32::INFINITY } else { m.max(d) },
            )
    }

    /// Asserts that no pixel holds NaN/Inf and alpha stays within [0, 1].
    pub fn assert_clean(px: &[Rgba]) {
        for (i, p) in px.iter().enumerate() {
            assert!(p.iter().all(|v| v.is_finite()), "pixel {i} = {p:?}");
            assert!(p[3] >= 0.0 && p[3] <= 1.0, "pixel {i} alpha {}", p[3]);
            for c in 0..3 {
                assert!(p[c] >= 0.0 && p[c] <= 1.0 + 1e-5, "pixel {i} = {p:?}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::scenes::max_diff;

    #[test]
    fn a_nan_pixel_is_an_infinite_difference() {
        let a = [[0.5, 0.25, 0.0, 1.0]; 3];
        let mut b = a;
        assert_eq!(max_diff(&a, &b), 0.0);
        b[1][2] = 0.125;
        assert_eq!(max_diff(&a, &b), 0.125);
        b[2][0] = f32::NAN;
        assert_eq!(max_diff(&a, &b), f32::INFINITY);
        assert_eq!(max_diff(&b, &a), f32::INFINITY);
    }
}
