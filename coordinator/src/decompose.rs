//! The cost-balanced k-d decomposition of a scene over workers.
//!
//! The split is computed from the stores' *indexes* only (header, page table and the
//! per-page value bounds): opening a store reads no page payload, so a decomposition of a
//! terabyte survey costs a few milliseconds of I/O.
//!
//! # Cost model
//!
//! The cost of rendering a region is estimated as the number of ray samples it takes, in
//! units of level-0 samples, spread uniformly over boxes of work ([`CostBox`]):
//!
//! * **Volumes.** One box per level-0 brick: the brick's index box (its core samples
//!   `[lo − ½, hi − ½)`, the same cell-centred convention as the volume's bounds) mapped
//!   through the index→world transform (for a rotated transform, the axis-aligned bounding
//!   box of the 8 mapped corners). Its cost is the brick's sample count, times
//!   [`TRANSPARENT_FACTOR`] when the brick is fully transparent: rays skip such bricks in
//!   the renderer, but still pay for traversing them. "Transparent" is the renderer's own
//!   empty-space-skipping test, replicated here because it is inlined in
//!   `Engine::setup`: with `render.empty_space_skipping`,
//!   [`TransferFunction::max_alpha`](strata_common::tf::TransferFunction::max_alpha) of
//!   the page's index `[min, max]` is zero; without it, only pages with no valid sample.
//! * **Horizons.** One box per level-0 tile that holds a valid height: laterally the cells
//!   whose lower node lies in the tile's core (the renderer's tile footprint), clipped to
//!   the grid, vertically the tile's index `[min, max]` height, mapped through the
//!   transform like a brick. Its cost is the tile's cell count × [`HORIZON_CELL_COST`]: one
//!   ray/cell intersection counted as one volume sample. This is an estimate; horizons are
//!   cheap next to any volume of the same footprint.
//!
//! Boxes are clamped into the scene region (an edge tile's border heights may reach
//! slightly past the bounds, which use the root tile's range) keeping their whole cost.
//!
//! The cost ignores the view: the level of detail (far regions sample coarser levels) and
//! early ray termination both make real costs view-dependent. It balances the sample work
//! of a view that sees everything at full detail.
//!
//! Split planes snap to level-0 brick boundaries of axis-aligned volumes when that costs
//! little balance (see [`Decomposition::balanced`]), so fewer bricks are loaded by two
//! workers.

use anyhow::Result;
use std::cmp::Ordering;
use strata_common::geo::Affine3;
use strata_common::kd::{CostBox, Decomposition, Region};
use strata_common::scene::Scene;
use strata_worker::dataset::{Horizon, SceneData, Volume};

/// Cost factor of a fully transparent brick relative to an opaque one (traversal only).
pub const TRANSPARENT_FACTOR: f64 = 0.05;

/// Cost of one horizon cell, in volume samples.
pub const HORIZON_CELL_COST: f64 = 1.0;

/// Boxes of work of a scene, candidate split planes and the scene region.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneCosts {
    /// One box per level-0 brick (volumes) or non-empty tile (horizons).
    pub boxes: Vec<CostBox>,
    /// Level-0 brick boundaries of the axis-aligned volumes, per world axis, sorted and
    /// deduplicated.
    pub planes: [Vec<f64>; 3],
    /// The scene region (the data bounds padded as `Engine::scene_region` pads them).
    pub root: Region,
}

impl SceneCosts {
    /// Sum of the boxes' costs.
    pub fn total(&self) -> f64 {
        self.boxes.iter().map(|b| b.cost).sum()
    }
}

/// Opens the scene's stores (headers and indexes only) and estimates its work.
pub fn scene_costs(scene: &Scene) -> Result<SceneCosts> {
    let data = SceneData::open(scene)?;
    Ok(costs_of(&data, scene.render.empty_space_skipping))
}

/// The work of already opened data sets; `skipping` is `render.empty_space_skipping`.
pub fn costs_of(data: &SceneData, skipping: bool) -> SceneCosts {
    // The region workers clip to (`Engine::scene_region` is the same call).
    let root = data.region();
    let mut boxes = Vec::new();
    let mut planes: [Vec<f64>; 3] = [vec![], vec![], vec![]];
    for v in &data.volumes {
        volume_boxes(v, skipping, &mut boxes);
        volume_planes(v, &mut planes);
    }
    for h in &data.horizons {
        horizon_boxes(h, &mut boxes);
    }
    for b in &mut boxes {
        for a in 0..3 {
            b.region.lo[a] = b.region.lo[a].clamp(root.lo[a], root.hi[a]);
            b.region.hi[a] = b.region.hi[a].clamp(root.lo[a], root.hi[a]);
        }
    }
    for p in &mut planes {
        p.sort_by(f64::total_cmp);
        // Boundaries of different volumes that agree to ~1e-9 are one plane.
        p.dedup_by(|b, a| (*b - *a).abs() <= 1e-9 * a.abs().max(1.0));
    }
    SceneCosts {
        boxes,
        planes,
        root,
    }
}

/// Splits the scene over `workers` workers with `leaves_per_worker` leaves each.
pub fn decompose(scene: &Scene, workers: usize, leaves_per_worker: usize) -> Result<Decomposition> {
    let c = scene_costs(scene)?;
    Ok(Decomposition::balanced(
        c.root,
        &c.boxes,
        workers,
        leaves_per_worker,
        &c.planes,
    ))
}

/// The world AABB of the index box `[lo, hi]`.
fn world_box(a: &Affine3, lo: [f64; 3], hi: [f64; 3]) -> Region {
    let mut r = Region {
        lo: [f64::INFINITY; 3],
        hi: [f64::NEG_INFINITY; 3],
    };
    for c in 0..8 {
        let p = [0, 1, 2].map(|k| if c >> k & 1 == 0 { lo[k] } else { hi[k] });
        for (k, v) in a.apply(p).into_iter().enumerate() {
            r.lo[k] = r.lo[k].min(v);
            r.hi[k] = r.hi[k].max(v);
        }
    }
    r
}

/// Whether an index `[min, max]` holds no valid value (NaN range of an empty page).
fn no_values(mn: f32, mx: f32) -> bool {
    matches!(mn.partial_cmp(&mx), None | Some(Ordering::Greater))
}

/// Index of level-0 brick `b` in `Volume::bounds` / `Horizon::bounds` (page-table order:
/// level by level, x fastest; level 0 comes first).
fn level0_index(bricks: [u32; 3], b: [u32; 3]) -> usize {
    ((b[2] as usize * bricks[1] as usize) + b[1] as usize) * bricks[0] as usize + b[0] as usize
}

fn volume_boxes(v: &Volume, skipping: bool, out: &mut Vec<CostBox>) {
    let p = &v.pyramid;
    let bricks = p.level(0).bricks;
    for z in 0..bricks[2] {
        for y in 0..bricks[1] {
            for x in 0..bricks[0] {
                let b = [x, y, z];
                let r = p.core_range(0, b);
                let [mn, mx] = v.bounds[level0_index(bricks, b)];
                // The renderer's own test.
                let transparent = v.tf.page_transparent([mn, mx], skipping);
                let samples: u64 = r.iter().map(|(lo, hi)| hi - lo).product();
                let factor = if transparent { TRANSPARENT_FACTOR } else { 1.0 };
                out.push(CostBox {
                    region: world_box(
                        &v.to_world,
                        r.map(|(lo, _)| lo as f64 - 0.5),
                        r.map(|(_, hi)| hi as f64 - 0.5),
                    ),
                    cost: samples as f64 * factor,
                });
            }
        }
    }
}

fn horizon_boxes(h: &Horizon, out: &mut Vec<CostBox>) {
    let p = &h.pyramid;
    let lev = p.level(0);
    let (bricks, dims) = (lev.bricks, lev.dims);
    for y in 0..bricks[1] {
        for x in 0..bricks[0] {
            let b = [x, y, 0];
            let [mn, mx] = h.bounds[level0_index(bricks, b)];
            if no_values(mn, mx) {
                continue; // no valid height: nothing to intersect
            }
            let r = p.core_range(0, b);
            // Cells whose lower node is in the core; the last node starts no cell.
            let lo = [r[0].0, r[1].0];
            let hi = [0, 1].map(|a| r[a].1.min(dims[a].saturating_sub(1)).max(lo[a]));
            let cells = (hi[0] - lo[0]) * (hi[1] - lo[1]);
            if cells == 0 {
                continue;
            }
            out.push(CostBox {
                region: world_box(
                    &h.to_world,
                    [lo[0] as f64, lo[1] as f64, mn as f64],
                    [hi[0] as f64, hi[1] as f64, mx as f64],
                ),
                cost: cells as f64 * HORIZON_CELL_COST,
            });
        }
    }
}

/// World axis → index axis when the transform's linear part is a scaled permutation.
fn axis_map(a: &Affine3) -> Option<[usize; 3]> {
    let mut m = [0; 3];
    for (w, row) in a.rows.iter().enumerate() {
        let mut nz = (0..3).filter(|&k| row[k] != 0.0);
        m[w] = nz.next()?;
        if nz.next().is_some() {
            return None;
        }
    }
    (m[0] != m[1] && m[1] != m[2] && m[0] != m[2]).then_some(m)
}

fn volume_planes(v: &Volume, planes: &mut [Vec<f64>; 3]) {
    let Some(map) = axis_map(&v.to_world) else {
        return; // rotated: brick faces are not world planes
    };
    let p = &v.pyramid;
    let lev = p.level(0);
    let core = p.core() as u64;
    for (w, &k) in map.iter().enumerate() {
        let (s, t) = (v.to_world.rows[w][k], v.to_world.rows[w][3]);
        let faces = (0..lev.bricks[k] as u64)
            .map(|b| b * core)
            .chain(std::iter::once(lev.dims[k]));
        planes[w].extend(faces.map(|i| s * (i as f64 - 0.5) + t));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::builder::{build_store, BuildOptions};
    use crate::source::MemorySource;
    use indicatif::ProgressBar;
    use std::path::{Path, PathBuf};
    use strata_common::kd::KdNode;
    use strata_common::sample::SampleType;

    fn volume_store(dir: &Path, name: &str, dims: [u64; 3], data: Vec<f32>, t: Affine3) -> PathBuf {
        let path = dir.join(format!("{name}.strata"));
        let mut o = BuildOptions::volume(name, SampleType::F32);
        o.page_size = 32; // core 30
        o.border = 1;
        o.transform = t;
        let src = MemorySource { dims, data };
        build_store(&src, &path, &o, &ProgressBar::hidden()).unwrap();
        path
    }

    fn horizon_store(dir: &Path, dims: [u64; 2], heights: Vec<f32>) -> PathBuf {
        let path = dir.join("h.strata");
        let mut o = BuildOptions::horizon("h");
        o.page_size = 32; // core 28
        let src = MemorySource {
            dims: [dims[0], dims[1], 1],
            data: heights,
        };
        build_store(&src, &path, &o, &ProgressBar::hidden()).unwrap();
        path
    }

    /// A scene over `vols` (window [0.5, 1.5]: values ≤ 0.5 are transparent, above opaque)
    /// and `hors`, parsed like a scene file so defaults come from the scene model.
    fn scene(dir: &Path, vols: &[PathBuf], hors: &[PathBuf], extra: &str) -> Scene {
        let mut t = String::new();
        for v in vols {
            t += &format!(
                "[[volume]]\nstore = {:?}\ncolormap = \"grey\"\nwindow = [0.5, 1.5]\n\
                 opacity_points = [[0.0, 0.0], [0.01, 1.0], [1.0, 1.0]]\n",
                v.display().to_string()
            );
        }
        for h in hors {
            t += &format!("[[horizon]]\nstore = {:?}\n", h.display().to_string());
        }
        t += extra;
        Scene::parse(&dir.join("scene.toml"), &t).unwrap()
    }

    fn field(dims: [u64; 3], f: impl Fn(u64, u64, u64) -> f32) -> Vec<f32> {
        let mut v = Vec::new();
        for z in 0..dims[2] {
            for y in 0..dims[1] {
                for x in 0..dims[0] {
                    v.push(f(x, y, z));
                }
            }
        }
        v
    }

    fn root_split(d: &Decomposition) -> (usize, f64) {
        match d.tree.root {
            KdNode::Split { axis, pos, .. } => (axis, pos),
            KdNode::Leaf(_) => panic!("no split"),
        }
    }

    #[test]
    fn costs_sum_to_samples() {
        let dir = tempfile::tempdir().unwrap();
        let dims = [70, 40, 20]; // 3×2×1 bricks of core 30
        let opaque = volume_store(
            dir.path(),
            "o",
            dims,
            field(dims, |_, _, _| 1.0),
            Affine3::IDENTITY,
        );
        let clear = volume_store(
            dir.path(),
            "c",
            dims,
            field(dims, |_, _, _| 0.0),
            Affine3::IDENTITY,
        );
        let hdims = [60, 30]; // 3×2 tiles of core 28
        let h = horizon_store(
            dir.path(),
            hdims,
            (0..hdims[0] * hdims[1])
                .map(|i| 5.0 + (i % 7) as f32)
                .collect(),
        );
        let n = (dims[0] * dims[1] * dims[2]) as f64;
        let cells = ((hdims[0] - 1) * (hdims[1] - 1)) as f64;

        let c = scene_costs(&scene(dir.path(), std::slice::from_ref(&opaque), &[], "")).unwrap();
        assert_eq!(c.boxes.len(), 6);
        assert_eq!(c.total(), n);
        // Identity transform: brick faces at multiples of 30, minus ½.
        assert_eq!(c.planes[0], vec![-0.5, 29.5, 59.5, 69.5]);
        assert_eq!(c.planes[2], vec![-0.5, 19.5]);
        let bounds = SceneData::open(&scene(dir.path(), std::slice::from_ref(&opaque), &[], ""))
            .unwrap()
            .bounds();
        assert_eq!(c.root, bounds.padded(1e-3));

        let c = scene_costs(&scene(dir.path(), std::slice::from_ref(&clear), &[], "")).unwrap();
        assert!((c.total() - TRANSPARENT_FACTOR * n).abs() < 1e-6);
        // Without empty-space skipping every brick with data is sampled.
        let s = scene(
            dir.path(),
            &[clear],
            &[],
            "[render]\nempty_space_skipping = false\n",
        );
        assert_eq!(scene_costs(&s).unwrap().total(), n);

        let c = scene_costs(&scene(dir.path(), &[opaque], &[h], "")).unwrap();
        assert_eq!(c.boxes.len(), 6 + 6);
        assert_eq!(c.total(), n + cells);
        for b in &c.boxes {
            assert!(
                (0..3).all(|a| c.root.lo[a] <= b.region.lo[a] && b.region.hi[a] <= c.root.hi[a])
            );
        }
    }

    #[test]
    fn transforms_place_boxes_and_planes() {
        let dir = tempfile::tempdir().unwrap();
        let dims = [60, 30, 30];
        let data = field(dims, |_, _, _| 1.0);
        // Axis-aligned with a permutation: world x = 2·k + 100, y = i, z = j.
        let mut t = Affine3 {
            rows: [[0.0; 4]; 3],
        };
        t.rows[0] = [0.0, 0.0, 2.0, 100.0];
        t.rows[1] = [1.0, 0.0, 0.0, 0.0];
        t.rows[2] = [0.0, 1.0, 0.0, 0.0];
        let p = volume_store(dir.path(), "p", dims, data.clone(), t);
        let c = scene_costs(&scene(dir.path(), &[p], &[], "")).unwrap();
        assert_eq!(c.planes[0], vec![99.0, 159.0]);
        assert_eq!(c.planes[1], vec![-0.5, 29.5, 59.5]);
        assert_eq!(c.boxes[0].region.lo, [99.0, -0.5, -0.5]);
        assert_eq!(c.boxes[0].region.hi, [159.0, 29.5, 29.5]);
        // Rotated 45° about z: no planes, boxes are the corners' AABBs.
        let (s, co) = (
            std::f64::consts::FRAC_1_SQRT_2,
            std::f64::consts::FRAC_1_SQRT_2,
        );
        let r = Affine3 {
            rows: [[co, -s, 0.0, 0.0], [s, co, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]],
        };
        let q = volume_store(dir.path(), "q", dims, data, r);
        let c = scene_costs(&scene(dir.path(), &[q], &[], "")).unwrap();
        assert!(c.planes.iter().all(|p| p.is_empty()));
        assert_eq!(c.total(), (60 * 30 * 30) as f64);
        let b = c.boxes[0].region;
        assert!((b.hi[0] - b.lo[0] - 30.0 * 2f64.sqrt()).abs() < 1e-9);
    }

    #[test]
    fn transparent_half_pushes_the_split_into_the_opaque_half() {
        let dir = tempfile::tempdir().unwrap();
        // 4×2×2 bricks; x < 60 is transparent (below the window), the rest opaque. Brick
        // column 1 holds x = 60 in its border, so only column 0 is transparent.
        let dims = [120, 60, 60];
        let half = volume_store(
            dir.path(),
            "half",
            dims,
            field(dims, |x, _, _| if x < 60 { 0.0 } else { 1.0 }),
            Affine3::IDENTITY,
        );
        let full = volume_store(
            dir.path(),
            "full",
            dims,
            field(dims, |_, _, _| 1.0),
            Affine3::IDENTITY,
        );
        let mid = 59.5;

        let d = decompose(&scene(dir.path(), &[full], &[], ""), 2, 1).unwrap();
        // Uniform: balanced at the middle, which is a brick face (snapped exactly).
        assert_eq!(root_split(&d), (0, mid));
        assert!(d.imbalance() < 1.0 + 1e-9);

        let d = decompose(&scene(dir.path(), &[half], &[], ""), 2, 1).unwrap();
        let (axis, pos) = root_split(&d);
        assert_eq!(axis, 0);
        // Column 0 costs 4·27000·0.05 = 5400, columns 1–3 cost 108000 each (3600 per
        // unit of x): half of 329400 is reached 14.25 into column 2, at x = 59.5 + 14.25.
        // The nearest brick face (59.5) would leave 0.344 below: too far to snap to.
        assert!(pos > mid + 10.0, "{pos}");
        assert!((pos - 73.75).abs() < 1e-6, "{pos}");
        assert!(d.imbalance() < 1.0 + 1e-6, "{}", d.imbalance());
    }

    #[test]
    fn four_workers_cover_the_scene_region() {
        let dir = tempfile::tempdir().unwrap();
        let dims = [70, 50, 40];
        let v = volume_store(
            dir.path(),
            "v",
            dims,
            field(dims, |x, y, z| ((x * 7 + y * 3 + z) % 11) as f32 / 8.0),
            Affine3::scale_offset([25.0, 25.0, 4.0], [1000.0, 2000.0, 0.0]),
        );
        let hdims = [70, 50];
        let h = horizon_store(
            dir.path(),
            hdims,
            (0..70 * 50).map(|i| 10.0 + (i % 13) as f32).collect(),
        );
        let s = scene(dir.path(), &[v], &[h], "");
        let d = decompose(&s, 4, 1).unwrap();
        assert_eq!(d.validate(), Ok(()));
        assert_eq!(d.tree.leaves.len(), 4);
        let region = SceneData::open(&s).unwrap().bounds().padded(1e-3);
        assert_eq!(d.tree.root_region, region);
        let vol = |r: &Region| (0..3).map(|a| r.hi[a] - r.lo[a]).product::<f64>();
        let sum: f64 = d.tree.leaves.iter().map(vol).sum();
        assert!((sum - vol(&region)).abs() <= 1e-9 * vol(&region));
        for l in &d.tree.leaves {
            assert!((0..3)
                .all(|a| l.lo[a] < l.hi[a] && region.lo[a] <= l.lo[a] && l.hi[a] <= region.hi[a]));
        }
        // A lattice of points: each in exactly one leaf.
        for i in 0..1000 {
            let f = [i % 10, i / 10 % 10, i / 100].map(|k| (k as f64 + 0.5) / 10.0);
            let p = [0, 1, 2].map(|a| region.lo[a] + f[a] * (region.hi[a] - region.lo[a]));
            assert_eq!(d.tree.leaves.iter().filter(|l| l.contains(p)).count(), 1);
        }
        let total: f64 = d.leaf_cost.iter().sum();
        let c = scene_costs(&s).unwrap();
        assert!((total - c.total()).abs() <= 1e-9 * c.total());
    }

    #[test]
    fn missing_store_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let s = scene(dir.path(), &[dir.path().join("nope.strata")], &[], "");
        assert!(decompose(&s, 2, 1).is_err());
    }
}
