//! The casters' code is specialised to each frame's effect set (`strata_common::effects`):
//! the effects a frame reports are exactly those its scene uses, the specialised code path
//! renders the same image bit for bit as the general one (every effect compiled in) and as
//! every path with one unused effect compiled in, with the same counters; on the CPU (SIMD
//! packets and the scalar march) and on the GPU where an adapter exists.

use strata_common::effects::EffectSet;
use strata_common::geo::Affine3;
use strata_common::scene::{Backend, Camera, CodePath, Scene, SliceAxis, SliceLayer};
use strata_tests::scenes::*;
use strata_worker::engine::{BatchResult, Engine, Outcome};
use tempfile::TempDir;

const N: u64 = 40;
const W: u32 = 48;
const H: u32 = 40;

/// What a scene is built from.
#[derive(Clone, Copy, Default)]
struct Parts {
    volumes: usize,
    shading: bool,
    preintegrated: bool,
    horizon: bool,
    lighting: bool,
    slices: bool,
    /// The first volume's transfer function shows nothing (only its slices do).
    invisible: bool,
    /// Every volume's transfer function shows nothing.
    all_invisible: bool,
}

fn build(dir: &std::path::Path, p: Parts) -> Scene {
    let c = (N - 1) as f64 / 2.0;
    let mut vols = Vec::new();
    for i in 0..p.volumes {
        let data: Vec<f32> = (0..N * N * N)
            .map(|k| {
                let (x, y, z) = ((k % N) as f32, (k / N % N) as f32, (k / (N * N)) as f32);
                ((x * 0.31 + i as f32).sin() + (y * 0.23).cos() * (z * 0.17).sin()) * 0.5
            })
            .collect();
        // The second volume is shifted so the two overlap in part (fragments of one, of
        // both, mixed).
        let t = Affine3::scale_offset([1.0; 3], [i as f64 * 9.0, i as f64 * 4.0, 0.0]);
        let store = volume_store(dir, &format!("v{i}"), [N, N, N], data, t, 32);
        let points = if (p.invisible && i == 0) || p.all_invisible {
            vec![[0.0, 0.0], [1.0, 0.0]]
        } else {
            vec![[0.0, 0.05], [0.5, 0.0], [1.0, 0.08]]
        };
        let mut layer = volume_layer(store, "seismic", [-1.0, 1.0], points);
        if p.slices && i == 0 {
            layer.slices = vec![
                SliceLayer {
                    axis: SliceAxis::Inline,
                    index: 12.5,
                    opacity: 0.7,
                },
                SliceLayer {
                    axis: SliceAxis::Time,
                    index: 30.0,
                    opacity: 1.0,
                },
            ];
        }
        vols.push(layer);
    }
    let mut hors = Vec::new();
    if p.horizon {
        let m = N + 8;
        let heights: Vec<f32> = (0..m * m)
            .map(|k| {
                let (i, j) = ((k % m) as f32, (k / m) as f32);
                18.0 + 4.0 * (i * 0.2).sin() * (j * 0.15).cos()
            })
            .collect();
        let store = horizon_store(
            dir,
            "h",
            [m, m],
            heights,
            Affine3::scale_offset([1.0; 3], [-4.0, -4.0, 0.0]),
            32,
        );
        hors.push(horizon_layer(store, [0.9, 0.6, 0.2], 0.8));
    }
    let camera = Camera {
        eye: [c - 40.0, c - 70.0, 75.0],
        target: [c + 3.0, c, 20.0],
        up: [0.0, 0.0, 1.0],
        fov_deg: 45.0,
    };
    let mut render = exact_settings(W, H);
    render.volume_shading = p.shading;
    render.preintegrated = p.preintegrated;
    render.lighting = p.lighting;
    render.backend = Backend::Cpu;
    scene(vols, hors, camera, render)
}

fn batch(s: &Scene, extra: EffectSet) -> BatchResult {
    let mut e = Engine::new(s).unwrap();
    e.extra_effects = e.extra_effects.union(extra);
    let view = e.view(W, H).unwrap();
    let region = e.scene_region();
    let r = e.render_batch(&view, &region).unwrap();
    assert_eq!(r.outcome, Outcome::Converged);
    r
}

/// Renders `s` specialised, general and with each unused effect compiled in; all must give
/// the same image and counters, and report `want` as the frame's effects.
fn check(s: &Scene, want: EffectSet, what: &str) {
    let base = batch(s, EffectSet::NONE);
    assert_eq!(base.variant.effects, want, "{what}: effects");
    assert_eq!(base.variant.compiled, want, "{what}: specialised code");
    assert!(
        base.variant_name
            .starts_with(&format!("specialised [{want}]")),
        "{what}: {}",
        base.variant_name
    );
    let img = base.image.to_full();
    assert_clean(&img);
    assert!(
        img.iter().any(|p| p[3] > 0.0),
        "{what}: the scene shows nothing"
    );
    let mut extras = vec![EffectSet::ALL];
    extras.extend(
        EffectSet::NAMED
            .iter()
            .map(|&(e, _)| e)
            .filter(|&e| !want.contains(e)),
    );
    for extra in extras {
        let r = batch(s, extra);
        assert_eq!(r.variant.effects, want, "{what} + {extra}");
        assert!(r.variant.compiled.contains(extra), "{what} + {extra}");
        assert!(
            bit_identical(&img, &r.image.to_full()),
            "{what}: with {extra} compiled in the image differs by {}",
            max_diff(&img, &r.image.to_full())
        );
        assert_eq!(base.last, r.last, "{what} + {extra}: counters");
    }
    // The config key forces the general path.
    let mut general = s.clone();
    general.render.variant = CodePath::General;
    let g = batch(&general, EffectSet::NONE);
    assert!(g.variant.is_general() && g.variant_name.starts_with("general"));
    assert!(
        bit_identical(&img, &g.image.to_full()),
        "{what}: general path"
    );
    // The scalar march, specialised and general.
    let mut scalar = s.clone();
    scalar.render.simd = false;
    for extra in [EffectSet::NONE, EffectSet::ALL] {
        let r = batch(&scalar, extra);
        assert!(r.variant_name.ends_with("scalar"), "{}", r.variant_name);
        assert!(
            bit_identical(&img, &r.image.to_full()),
            "{what}: scalar + {extra} differs by {}",
            max_diff(&img, &r.image.to_full())
        );
    }
    // The GPU: its specialised pipeline and the general one agree bit for bit, and with
    // the CPU within the backends' tolerance.
    if gpu_available() {
        let gs = on_backend(s, Backend::Gpu);
        let a = batch(&gs, EffectSet::NONE);
        let b = batch(&gs, EffectSet::ALL);
        assert_eq!(a.variant.effects, want, "{what}: GPU effects");
        assert!(
            a.variant_name.contains("gpu pipeline"),
            "{}",
            a.variant_name
        );
        let (ia, ib) = (a.image.to_full(), b.image.to_full());
        assert!(
            bit_identical(&ia, &ib),
            "{what}: GPU general pipeline differs by {}",
            max_diff(&ia, &ib)
        );
        assert_eq!(a.last, b.last, "{what}: GPU counters");
        let d = max_diff(&img, &ia);
        assert!(d <= 1e-4, "{what}: GPU differs from CPU by {d}");
    }
}

#[test]
fn every_effect_set_renders_the_same_on_its_specialised_path_as_on_the_general_one() {
    let dir = TempDir::new().unwrap();
    let v = EffectSet::VOLUME;
    let cases: [(Parts, EffectSet, &str); 11] = [
        (
            Parts {
                volumes: 1,
                ..Parts::default()
            },
            v,
            "one volume",
        ),
        (
            Parts {
                volumes: 1,
                shading: true,
                ..Parts::default()
            },
            v.union(EffectSet::SHADING),
            "shaded volume",
        ),
        (
            Parts {
                volumes: 1,
                preintegrated: true,
                ..Parts::default()
            },
            v.union(EffectSet::PREINTEGRATED),
            "pre-integrated volume",
        ),
        (
            Parts {
                volumes: 2,
                ..Parts::default()
            },
            v.union(EffectSet::VOLUMES),
            "two volumes",
        ),
        (
            Parts {
                horizon: true,
                ..Parts::default()
            },
            EffectSet::HORIZONS,
            "an unlit horizon",
        ),
        (
            Parts {
                volumes: 1,
                invisible: true,
                slices: true,
                horizon: true,
                lighting: true,
                ..Parts::default()
            },
            EffectSet::HORIZONS
                .union(EffectSet::LIGHTING)
                .union(EffectSet::SLICES),
            "slices of an invisible volume and a lit horizon",
        ),
        (
            // The demo's shape with pre-integration asked for: the hidden volume is not
            // marched, so neither caster needs (or builds) its tables.
            Parts {
                volumes: 1,
                invisible: true,
                slices: true,
                horizon: true,
                lighting: true,
                preintegrated: true,
                ..Parts::default()
            },
            EffectSet::HORIZONS
                .union(EffectSet::LIGHTING)
                .union(EffectSet::SLICES),
            "slices of an invisible volume, a lit horizon, pre-integration asked for",
        ),
        (
            // Shading asked for, two volumes, but none marched: only the slices show, and
            // neither shading nor mixing is in the code.
            Parts {
                volumes: 2,
                all_invisible: true,
                shading: true,
                slices: true,
                ..Parts::default()
            },
            EffectSet::SLICES,
            "slices of two invisible volumes, shading asked for",
        ),
        (
            Parts {
                volumes: 1,
                horizon: true,
                lighting: true,
                slices: true,
                ..Parts::default()
            },
            v.union(EffectSet::HORIZONS)
                .union(EffectSet::LIGHTING)
                .union(EffectSet::SLICES),
            "volume, slices, lit horizon",
        ),
        (
            Parts {
                volumes: 2,
                shading: true,
                horizon: true,
                slices: true,
                ..Parts::default()
            },
            EffectSet::ALL
                .without(EffectSet::PREINTEGRATED)
                .without(EffectSet::LIGHTING),
            "two shaded volumes, slices, unlit horizon",
        ),
        (
            // Every effect but slices (all of them is the general path): pre-integrated
            // spans end where the volumes' mix and the surfaces begin, each lit by its
            // samples' light.
            Parts {
                volumes: 2,
                shading: true,
                preintegrated: true,
                horizon: true,
                lighting: true,
                ..Parts::default()
            },
            EffectSet::ALL.without(EffectSet::SLICES),
            "two shaded pre-integrated volumes, lit horizon",
        ),
    ];
    for (i, (parts, want, what)) in cases.into_iter().enumerate() {
        let sub = dir.path().join(format!("case{i}"));
        std::fs::create_dir_all(&sub).unwrap();
        check(&build(&sub, parts), want, what);
    }
}
