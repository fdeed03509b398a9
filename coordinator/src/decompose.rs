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
//!   empty-space-skipping test (`TransferFunction::page_transparent`, which both call):
//!   with `render.empty_space_skipping`,
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
//! of a view that sees everything at full detail. Across a sequence the workers measure
//! the view's real work and the cluster re-weights the boxes with it: one factor per leaf
//! (`Decomposition::reweighted`), or page by page ([`reweighted_by_pages`], which needs
//! [`SceneCosts::page_boxes`] to find the boxes under a page key).
//!
//! Split planes snap to level-0 brick boundaries of axis-aligned volumes when that costs
//! little balance (see [`Decomposition::balanced`]), so fewer bricks are loaded by two
//! workers.

use anyhow::Result;
use std::cmp::Ordering;
use strata_common::geo::Affine3;
use strata_common::ids::PageId;
use strata_common::kd::{CostBox, Decomposition, Region};
use strata_common::pyramid::Pyramid;
use strata_common::scene::{RebalanceClock, Scene};
use strata_common::wire::WorkerFrameStats;
use strata_worker::dataset::{Horizon, SceneData, Volume};

/// Cost factor of a fully transparent brick relative to an opaque one (traversal only).
pub const TRANSPARENT_FACTOR: f64 = 0.05;

/// Cost of one horizon cell, in volume samples.
pub const HORIZON_CELL_COST: f64 = 1.0;

/// A re-split by measured page work adds this fraction of each box's estimated share to its
/// measured cost: a box the view did not reach (hidden, or outside the frame) still costs a
/// little, so the split does not hand one worker all of it at once. (The leaves model
/// floors each leaf's ratio at the same fraction.)
pub use strata_common::kd::MEASURED_FLOOR;

/// [`DatasetBoxes::level0`] of a level-0 page with no box (a horizon tile without a valid
/// height).
pub const NO_BOX: u32 = u32::MAX;

/// How one data set's pages map onto [`SceneCosts::boxes`].
#[derive(Clone, Debug, PartialEq)]
pub struct DatasetBoxes {
    /// Its page tree (to decode page keys).
    pub pyramid: Pyramid,
    /// The box of each level-0 page, in page-table order (x fastest), or [`NO_BOX`].
    pub level0: Vec<u32>,
}

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
    /// Per data-set number (the workers' numbering: volumes, then horizons), how its page
    /// keys map onto `boxes`.
    pub datasets: Vec<DatasetBoxes>,
}

impl SceneCosts {
    /// Sum of the boxes' costs.
    pub fn total(&self) -> f64 {
        self.boxes.iter().map(|b| b.cost).sum()
    }

    /// Into `out`: the boxes of the level-0 pages under page `key` (a level-0 page's own
    /// box; a level-k page covers 2^k level-0 pages per axis, clipped to the grid). Empty
    /// for a key that names no page of the scene.
    pub fn page_boxes(&self, key: u64, out: &mut Vec<usize>) {
        out.clear();
        let id = PageId(key);
        let Some(d) = self.datasets.get(id.dataset() as usize) else {
            return;
        };
        let (p, level) = (&d.pyramid, id.level() as usize);
        let b = p.brick_of(id.morton());
        if !p.contains(level, b) {
            return;
        }
        let n0 = p.level(0).bricks;
        let lo = [0, 1, 2].map(|a| ((b[a] as u64) << level).min(n0[a] as u64));
        let hi = [0, 1, 2].map(|a| ((b[a] as u64 + 1) << level).min(n0[a] as u64));
        for z in lo[2]..hi[2] {
            for y in lo[1]..hi[1] {
                for x in lo[0]..hi[0] {
                    let i = level0_index(n0, [x as u32, y as u32, z as u32]);
                    match d.level0.get(i) {
                        Some(&bx) if bx != NO_BOX => out.push(bx as usize),
                        _ => {}
                    }
                }
            }
        }
    }
}

/// `boxes` (the cost field in force, on the regions of `costs.boxes`) re-weighted by where
/// the view's work went (`cluster.rebalance_model = "pages"`).
///
/// `measured` is each leaf's final cast in seconds; `work` holds `(leaf, page key, share)`,
/// the share of that leaf's time its tiles spent in the page (the worker's
/// `feedback::page_shares`). A page's seconds go to the level-0 boxes under it that lie in
/// the leaf, in proportion to their estimated cost there (a coarse page's time falls where
/// the estimate says its samples are); what a leaf's shares leave over (tiles whose rays
/// entered no page) is spread the same way over the whole leaf. Each box then costs
/// [`MEASURED_FLOOR`] of its estimated share plus its measured seconds, converted to the
/// field's units so that the measured leaves keep the cost they had in the field; boxes in
/// leaves without a measurement keep their cost. The result is `(1 − damping)` of the field
/// in force plus `damping` of that.
///
/// Records are untrusted (a worker's stats): records of a leaf not in `d`, of no page of
/// the scene, or with a share that is not positive are ignored, a record repeated for the
/// same leaf and page counts once (its shares added), and a leaf's shares are scaled down
/// when they add up to more than 1.
///
/// Unlike [`Decomposition::reweighted`], which scales all of a leaf's boxes by one factor,
/// this moves cost *within* a leaf: the part of a leaf where rays terminate early, or that
/// lies behind opaque content, costs less than the part they cross in full, and the next
/// split planes go where the work is. Returns `boxes` unchanged when nothing usable was
/// measured.
pub fn reweighted_by_pages(
    costs: &SceneCosts,
    boxes: &[CostBox],
    d: &Decomposition,
    measured: &[f64],
    work: &[(usize, u64, f32)],
    damping: f64,
) -> Vec<CostBox> {
    let ok = |v: f64| v.is_finite() && v > 0.0;
    let (nb, leaves) = (costs.boxes.len(), &d.tree.leaves);
    // A leaf measured at 0 s (off screen) is measured: its boxes take the floor alone, so
    // that an idle worker is given work. `NaN` is no measurement.
    let timed = |l: usize| {
        measured
            .get(l)
            .copied()
            .is_some_and(|v| v.is_finite() && v >= 0.0)
    };
    if boxes.len() != nb || !(0..leaves.len()).any(|l| measured.get(l).copied().is_some_and(ok)) {
        return boxes.to_vec();
    }
    let estimate = |b: usize| {
        let c = costs.boxes[b].cost;
        if ok(c) {
            c
        } else {
            0.0
        }
    };
    // Each leaf's records, merged per page (so a page's boxes are walked once per leaf
    // whatever a worker sent), and each leaf's shares scaled to add up to at most 1.
    let mut merged: Vec<(usize, u64, f64)> = work
        .iter()
        .filter(|&&(leaf, _, share)| leaf < leaves.len() && timed(leaf) && ok(share as f64))
        .map(|&(leaf, key, share)| (leaf, key, share as f64))
        .collect();
    merged.sort_unstable_by_key(|&(leaf, key, _)| (leaf, key));
    merged.dedup_by(|b, a| {
        let same = (a.0, a.1) == (b.0, b.1);
        if same {
            a.2 += b.2;
        }
        same
    });
    let mut total_share = vec![0.0f64; leaves.len()];
    for &(leaf, _, share) in &merged {
        total_share[leaf] += share;
    }
    // Seconds per box, and the share of each leaf's time given to pages.
    let mut secs = vec![0.0; nb];
    let mut attributed = vec![0.0f64; leaves.len()];
    let mut under = Vec::new();
    let mut weights = Vec::new();
    for &(leaf, key, share) in &merged {
        let share = share / total_share[leaf].max(1.0);
        costs.page_boxes(key, &mut under);
        weights.clear();
        weights.extend(
            under
                .iter()
                .map(|&b| estimate(b) * costs.boxes[b].fraction_in(&leaves[leaf])),
        );
        let total: f64 = weights.iter().sum();
        if !ok(total) {
            continue;
        }
        let s = share * measured[leaf];
        for (&b, &w) in under.iter().zip(&weights) {
            secs[b] += s * w / total;
        }
        attributed[leaf] += share;
    }
    // Each box's fraction in the measured leaves (its parts, found down the tree: only
    // the leaves it may overlap), and the leaves' unattributed time spread by estimate.
    let mut in_timed = vec![0.0; nb];
    let mut parts: Vec<(usize, usize, f64)> = Vec::new();
    let mut total = vec![0.0f64; leaves.len()];
    for (b, cb) in costs.boxes.iter().enumerate() {
        d.tree.parts(cb, |l, f| {
            if timed(l) {
                in_timed[b] += f;
                total[l] += estimate(b) * f;
                parts.push((b, l, f));
            }
        });
    }
    for (b, l, f) in parts {
        let rest = (1.0 - attributed[l]).max(0.0) * measured[l];
        if rest > 0.0 && ok(total[l]) {
            secs[b] += rest * estimate(b) * f / total[l];
        }
    }
    let current = |b: usize| {
        let c = boxes[b].cost;
        if ok(c) {
            c
        } else {
            0.0
        }
    };
    let field_timed: f64 = (0..nb).map(|b| current(b) * in_timed[b].min(1.0)).sum();
    let secs_total: f64 = secs.iter().sum();
    let est_total: f64 = (0..nb).map(estimate).sum();
    let field_total: f64 = (0..nb).map(current).sum();
    if !ok(field_timed) || !ok(secs_total) || !ok(est_total) {
        return boxes.to_vec();
    }
    // The floor, in the field's units, then the seconds scaled to what is left of the
    // measured leaves' cost (so that they keep their share of the whole, floor included).
    let est_to_field = field_total / est_total;
    let floor: f64 = (0..nb)
        .map(|b| MEASURED_FLOOR * est_to_field * estimate(b) * in_timed[b].min(1.0))
        .sum();
    let to_field = (field_timed - floor).max(0.5 * field_timed) / secs_total;
    let dmp = if damping.is_finite() {
        damping.clamp(0.0, 1.0)
    } else {
        1.0
    };
    (0..nb)
        .map(|b| {
            let t = in_timed[b].min(1.0);
            let target = to_field * secs[b]
                + MEASURED_FLOOR * est_to_field * estimate(b) * t
                + current(b) * (1.0 - t);
            CostBox {
                region: boxes[b].region,
                cost: (1.0 - dmp) * current(b) + dmp * target,
            }
        })
        .collect()
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
    let mut datasets = Vec::new();
    for v in &data.volumes {
        let level0 = volume_boxes(v, skipping, &mut boxes);
        datasets.push((v.ds, v.pyramid.clone(), level0));
        volume_planes(v, &mut planes);
    }
    for h in &data.horizons {
        let level0 = horizon_boxes(h, &mut boxes);
        datasets.push((h.ds, h.pyramid.clone(), level0));
    }
    datasets.sort_by_key(|d| d.0);
    debug_assert!(datasets.iter().enumerate().all(|(i, d)| d.0 as usize == i));
    let datasets = datasets
        .into_iter()
        .map(|(_, pyramid, level0)| DatasetBoxes { pyramid, level0 })
        .collect();
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
        datasets,
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

/// Appends one box per level-0 brick; returns each brick's box index (page-table order).
fn volume_boxes(v: &Volume, skipping: bool, out: &mut Vec<CostBox>) -> Vec<u32> {
    let p = &v.pyramid;
    let bricks = p.level(0).bricks;
    let first = out.len();
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
    (first..out.len()).map(|i| i as u32).collect()
}

/// Appends one box per level-0 tile with a valid height; returns each tile's box index, or
/// [`NO_BOX`] (page-table order).
fn horizon_boxes(h: &Horizon, out: &mut Vec<CostBox>) -> Vec<u32> {
    let p = &h.pyramid;
    let lev = p.level(0);
    let (bricks, dims) = (lev.bricks, lev.dims);
    let mut level0 = vec![NO_BOX; bricks[0] as usize * bricks[1] as usize];
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
            level0[level0_index(bricks, b)] = out.len() as u32;
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
    level0
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

/// Each leaf's measured render, in `d`'s leaf order, from the workers' frame stats (in the
/// decomposition's slot order), and the clock used: by `clock`, the CPU time of each leaf's
/// cast over its worker's render threads (`leaf_cpu_s`) where every worker reported one for
/// each of its leaves, else the cast's wall time (`leaf_cast_s`), so that the leaves
/// compared were all measured alike. A worker without a CPU clock (GPU backend) reports no
/// CPU times at all; a leaf that cast nothing (off screen) reports 0, a measurement like
/// any other (the re-weighting charges it the floor, `MEASURED_FLOOR`); a leaf a worker
/// reported nothing for is `NaN` (unmeasured).
pub fn measured_leaf_times(
    d: &Decomposition,
    stats: &[WorkerFrameStats],
    clock: RebalanceClock,
) -> (Vec<f64>, &'static str) {
    let leaves: Vec<Vec<usize>> = (0..stats.len()).map(|w| d.worker_leaves(w)).collect();
    let by = |cpu: bool| {
        let mut measured = vec![f64::NAN; d.tree.leaves.len()];
        for (s, mine) in stats.iter().zip(&leaves) {
            let times = if cpu { &s.leaf_cpu_s } else { &s.leaf_cast_s };
            for (i, &l) in mine.iter().enumerate() {
                measured[l] = times.get(i).copied().unwrap_or(f64::NAN);
            }
        }
        measured
    };
    let timed = |s: &WorkerFrameStats, mine: &Vec<usize>| {
        s.leaf_cpu_s.len() >= mine.len() && s.leaf_cpu_s.iter().all(|&t| t >= 0.0 && t.is_finite())
    };
    if clock == RebalanceClock::Cpu
        && stats.len() == d.workers
        && stats.iter().zip(&leaves).all(|(s, mine)| timed(s, mine))
    {
        return (by(true), "cpu");
    }
    (by(false), "wall")
}

/// How much lower (max / mean worker cost, under the undamped re-weighted field) a new
/// split's imbalance must be than the split in force's for a re-split to be made.
pub const MIN_RESPLIT_GAIN: f64 = 0.02;

/// What a frame measured for a re-split: each leaf's time (`NaN`: no report) and, for the
/// page model, where it went (`(leaf, page key, share)`; empty for the per-leaf model).
pub struct Measurement<'a> {
    /// Seconds per leaf of the decomposition in force.
    pub times: &'a [f64],
    /// Page work records.
    pub work: &'a [(usize, u64, f32)],
}

/// A re-split [`resplit`] made.
pub struct Resplit {
    /// The new split.
    pub decomposition: Decomposition,
    /// The cost field it was balanced on (damped), to keep in force with it.
    pub field: Vec<CostBox>,
    /// Its imbalance under the frame's whole (undamped) measurement: what the cost model
    /// expects of it. Above 1 under damping, which corrects only part of the measured one.
    pub expected_imbalance: f64,
}

/// A re-split from a frame's measurement: the cost field in force (`field`, whose
/// `root` and `planes` are the scene's) re-weighted, damped, and the scene balanced over
/// `workers × leaves_per_worker` leaves again. `None` when the planes come out where they
/// are, or the new split would gain too little (below).
///
/// A damped field whose planes snap back to the same brick faces is tried once undamped:
/// an imbalance above the threshold whose damped correction stayed within a brick's
/// snapping tolerance (`MAX_SNAP`) was otherwise left for good, the same tree computed
/// again every frame.
///
/// A new split is taken only when, under the undamped re-weighted field (the frame's whole
/// measurement), its imbalance is lower than the split in force's by
/// [`MIN_RESPLIT_GAIN`]: where the balanced plane lies between two brick faces, timing
/// noise put the re-weighted balance on either side of it, and every frame moved a brick's
/// work (and its pages) back and forth for the same imbalance.
pub fn resplit(
    estimate: &SceneCosts,
    field: &SceneCosts,
    d: &Decomposition,
    m: &Measurement<'_>,
    damping: f64,
    workers: usize,
    leaves_per_worker: usize,
) -> Option<Resplit> {
    let reweight = |damping: f64| {
        if m.work.is_empty() {
            d.reweighted(&estimate.boxes, &field.boxes, m.times, damping)
        } else {
            reweighted_by_pages(estimate, &field.boxes, d, m.times, m.work, damping)
        }
    };
    // Splits are judged on the undamped field, the frame's full measurement: on a damped
    // one the split in force shows only part of the measured imbalance.
    let full = reweight(1.0);
    let current = d.imbalance_under(&full);
    let split = |boxes: &[CostBox]| {
        let new =
            Decomposition::balanced(field.root, boxes, workers, leaves_per_worker, &field.planes);
        let moved = new.tree.leaves != d.tree.leaves || new.owner != d.owner;
        (moved, new)
    };
    let made = |decomposition: Decomposition, field: Vec<CostBox>| {
        let expected_imbalance = decomposition.imbalance_under(&full);
        (expected_imbalance + MIN_RESPLIT_GAIN <= current).then_some(Resplit {
            decomposition,
            field,
            expected_imbalance,
        })
    };
    let damped = if damping < 1.0 {
        reweight(damping)
    } else {
        full.clone()
    };
    let (moved, new) = split(&damped);
    if moved {
        return made(new, damped);
    }
    // Snapped back to the same faces: tried once undamped (not when the damped split moved
    // and gained too little: the noisiest imbalances, near the threshold, would get full
    // corrections).
    if damping < 1.0 {
        let (moved, new) = split(&full);
        if moved {
            return made(new, full.clone());
        }
    }
    None
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

    /// A measured imbalance whose damped correction stays within the snapping tolerance of
    /// the brick face in force is corrected undamped (the same tree had been computed again
    /// every frame, the imbalance left for good).
    #[test]
    fn a_damped_re_split_that_snaps_back_is_tried_undamped() {
        // Four bricks of 25 along x: the estimate splits at the face x = 50.
        let field = slab_costs(4, 25.0, true);
        let root = field.root;
        let d = Decomposition::balanced(root, &field.boxes, 2, 1, &field.planes);
        assert_eq!(d.tree.leaves[0].hi[0], 50.0);
        // 0.62 against 0.38: damped by half, 56 % of the cost lies left of x = 50, within a
        // brick's tolerance of half: the face holds (the premise).
        let m = Measurement {
            times: &[0.62, 0.38],
            work: &[],
        };
        let damped = d.reweighted(&field.boxes, &field.boxes, m.times, 0.5);
        let again = Decomposition::balanced(root, &damped, 2, 1, &field.planes);
        assert_eq!(again.tree.leaves, d.tree.leaves);
        let new = resplit(&field, &field, &d, &m, 0.5, 2, 1)
            .expect("a new split")
            .decomposition;
        let x = new.tree.leaves[0].hi[0];
        assert!((x - 50.0 / 1.24).abs() < 0.5, "split at {x}");
        // Balanced measurements leave the tree as it is.
        let even = Measurement {
            times: &[0.5, 0.5],
            work: &[],
        };
        assert!(resplit(&field, &field, &d, &even, 0.5, 2, 1).is_none());
    }

    /// `n` bricks of side `side` along x (10 × 10 across), each costing 1, with their faces
    /// as split planes when `faces`.
    fn slab_costs(n: usize, side: f64, faces: bool) -> SceneCosts {
        SceneCosts {
            boxes: (0..n)
                .map(|i| CostBox {
                    region: Region {
                        lo: [side * i as f64, 0.0, 0.0],
                        hi: [side * (i + 1) as f64, 10.0, 10.0],
                    },
                    cost: 1.0,
                })
                .collect(),
            planes: [
                if faces {
                    (0..=n).map(|i| side * i as f64).collect()
                } else {
                    vec![]
                },
                vec![],
                vec![],
            ],
            root: Region {
                lo: [0.0; 3],
                hi: [side * n as f64, 10.0, 10.0],
            },
            datasets: Vec::new(),
        }
    }

    /// Where the balanced plane falls between two brick faces, a split on one face is not
    /// replaced by the other face's, which balances no better: timing noise had moved a
    /// brick's work (and pages) back and forth for the same imbalance.
    #[test]
    fn a_re_split_that_balances_no_better_is_not_made() {
        let root = Region {
            lo: [0.0; 3],
            hi: [70.0, 10.0, 10.0],
        };
        let brick = |i: usize, cost: f64| CostBox {
            region: Region {
                lo: [10.0 * i as f64, 0.0, 0.0],
                hi: [10.0 * (i + 1) as f64, 10.0, 10.0],
            },
            cost,
        };
        let uniform = slab_costs(7, 10.0, true);
        let planes = uniform.planes.clone();
        // Seven equal bricks: the balance (3.5) lies between faces 30 and 40.
        let x = Decomposition::balanced(root, &uniform.boxes, 2, 1, &planes);
        let face = x.tree.leaves[0].hi[0];
        assert!(face == 30.0 || face == 40.0, "{face}");
        // The split in force is on the other face (an earlier field put it there), and the
        // frame measured exactly the uniform field's costs of its leaves.
        let other = if face == 30.0 { 40.0 } else { 30.0 };
        let biased: Vec<CostBox> = (0..7)
            .map(|i| brick(i, if (i as f64) < other / 10.0 { 1.0 } else { 1.5 }))
            .collect();
        let mut d = Decomposition::balanced(root, &biased, 2, 1, &planes);
        assert_eq!(d.tree.leaves[0].hi[0], other);
        let left = other / 10.0;
        d.leaf_cost = vec![left, 7.0 - left];
        let m = Measurement {
            times: &[left, 7.0 - left],
            work: &[],
        };
        // The uniform field puts the balance on `face`, which is no better than `other`.
        let (a, b) = (
            d.imbalance_under(&uniform.boxes),
            x.imbalance_under(&uniform.boxes),
        );
        assert!(
            (a - 8.0 / 7.0).abs() < 1e-9 && (b - 8.0 / 7.0).abs() < 1e-9,
            "{a} {b}"
        );
        assert!(resplit(&uniform, &uniform, &d, &m, 1.0, 2, 1).is_none());
        // A measurement that makes the other face better is taken.
        let m = Measurement {
            times: &[left * 2.0, 7.0 - left],
            work: &[],
        };
        let new = resplit(&uniform, &uniform, &d, &m, 1.0, 2, 1)
            .expect("a better split")
            .decomposition;
        assert!(new.tree.leaves[0].hi[0] < other);
    }

    /// A damped re-split that moves and gains enough on the frame's whole measurement is
    /// made as it is (damped), not replaced by the undamped one.
    #[test]
    fn a_damped_re_split_that_gains_enough_stays_damped() {
        let field = slab_costs(100, 1.0, false);
        let root = field.root;
        let d = Decomposition::balanced(root, &field.boxes, 2, 1, &field.planes);
        assert_eq!(d.tree.leaves[0].hi[0], 50.0);
        // Measured 1.12: undamped the balance lies at 50 / 1.12 = 44.6; damped by half at
        // 50 · 1.0583 ... = 47.2.
        let m = Measurement {
            times: &[0.56, 0.44],
            work: &[],
        };
        let r = resplit(&field, &field, &d, &m, 0.5, 2, 1).expect("a re-split");
        let x = r.decomposition.tree.leaves[0].hi[0];
        let (l, rt) = (1.12f64.sqrt(), 0.88f64.sqrt());
        let damped = 50.0 * (l + rt) / 2.0 / l;
        assert!((x - damped).abs() < 1e-6, "split at {x}, damped {damped}");
        // What it expects: the whole measurement (left boxes 1.12, right 0.88) over the
        // damped split leaves the left worker x · 1.12 of a mean 50, not 1 (the damped
        // field's own balance).
        let expected = x * 1.12 / 50.0;
        assert!(
            (r.expected_imbalance - expected).abs() < 1e-9 && expected > 1.05,
            "expected {}, not {expected}",
            r.expected_imbalance
        );
    }

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

    /// A volume store of `dims` samples all of value 1 (opaque under `scene`'s window),
    /// on the identity transform.
    fn opaque_store(dir: &Path, name: &str, dims: [u64; 3]) -> PathBuf {
        volume_store(
            dir,
            name,
            dims,
            field(dims, |_, _, _| 1.0),
            Affine3::IDENTITY,
        )
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
        let opaque = opaque_store(dir.path(), "o", dims);
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

    fn key(c: &SceneCosts, ds: u16, level: usize, brick: [u32; 3]) -> u64 {
        strata_worker::atlas::page_key(ds, &c.datasets[ds as usize].pyramid, level, brick)
    }

    #[test]
    fn page_keys_map_onto_the_level0_boxes_under_them() {
        let dir = tempfile::tempdir().unwrap();
        let dims = [70, 40, 20]; // level 0: 3×2×1 bricks of core 30; level 1: 2×1×1
        let v = opaque_store(dir.path(), "o", dims);
        // 3×2 tiles of core 28 (border 2), the middle column without a valid height.
        let hdims = [60u64, 30];
        let heights = (0..hdims[0] * hdims[1])
            .map(|i| {
                if (25..59).contains(&(i % hdims[0])) {
                    f32::NAN
                } else {
                    5.0
                }
            })
            .collect();
        let h = horizon_store(dir.path(), hdims, heights);
        let c = scene_costs(&scene(dir.path(), &[v], &[h], "")).unwrap();
        assert_eq!(c.datasets.len(), 2);
        let mut out = Vec::new();
        let mut boxes = |k: u64| {
            c.page_boxes(k, &mut out);
            out.sort_unstable();
            out.clone()
        };
        // Level 0: the brick's own box (x fastest).
        assert_eq!(boxes(key(&c, 0, 0, [1, 1, 0])), [4]);
        // Level 1: 2×2 level-0 bricks, clipped to the grid at the high edge.
        assert_eq!(boxes(key(&c, 0, 1, [0, 0, 0])), [0, 1, 3, 4]);
        assert_eq!(boxes(key(&c, 0, 1, [1, 0, 0])), [2, 5]);
        assert_eq!(boxes(key(&c, 0, 2, [0, 0, 0])), [0, 1, 2, 3, 4, 5]);
        // The horizon's boxes follow the volume's; tiles with no height have none.
        let tiles: Vec<usize> = (0..2)
            .flat_map(|y| (0..3).map(move |x| [x, y, 0]))
            .flat_map(|b| boxes(key(&c, 1, 0, b)))
            .collect();
        assert_eq!(tiles, [6, 7, 8, 9]);
        assert_eq!(boxes(key(&c, 1, 0, [1, 0, 0])), Vec::<usize>::new());
        // Keys of no page: another data set, a brick outside the level, a level too deep.
        assert!(boxes(key(&c, 0, 0, [0, 0, 0]) | (7u64 << 48)).is_empty());
        assert!(boxes(strata_common::ids::PageId::new(0, 0, 63).0).is_empty());
        assert!(boxes(strata_common::ids::PageId::new(0, 9, 0).0).is_empty());
    }

    /// A view whose work sits in one brick: re-splitting by the pages the rays entered
    /// puts the plane next to that brick; scaling each leaf by one factor cannot, and
    /// leaves the workers further apart on the real costs.
    #[test]
    fn a_re_split_by_pages_moves_cost_within_a_leaf() {
        let dir = tempfile::tempdir().unwrap();
        let dims = [240, 30, 30]; // 8 bricks of core 30 along x, all opaque
        let v = opaque_store(dir.path(), "o", dims);
        let c = scene_costs(&scene(dir.path(), &[v], &[], "")).unwrap();
        assert_eq!(c.boxes.len(), 8);
        let d = Decomposition::balanced(c.root, &c.boxes, 2, 1, &c.planes);
        assert_eq!(root_split(&d), (0, 119.5));
        // The view's real work per brick: brick 0 ten times any other.
        let truth: Vec<f64> = (0..8).map(|b| if b == 0 { 10.0 } else { 1.0 }).collect();
        let leaf_of = |b: usize| {
            d.tree
                .leaves
                .iter()
                .position(|r| r.lo[0] < 30.0 * b as f64 + 15.0 && 30.0 * b as f64 + 15.0 < r.hi[0])
                .unwrap()
        };
        let mut measured = vec![0.0; 2];
        for b in 0..8 {
            measured[leaf_of(b)] += truth[b];
        }
        // What the workers report: each brick's share of its leaf's time.
        let work: Vec<(usize, u64, f32)> = (0..8u32)
            .map(|b| {
                let l = leaf_of(b as usize);
                (
                    l,
                    key(&c, 0, 0, [b, 0, 0]),
                    (truth[b as usize] / measured[l]) as f32,
                )
            })
            .collect();
        let real = |n: &Decomposition| {
            let mut w = [0.0; 2];
            for (l, r) in n.tree.leaves.iter().enumerate() {
                for (b, t) in truth.iter().enumerate() {
                    w[n.owner[l]] += t * c.boxes[b].fraction_in(r);
                }
            }
            w[0].max(w[1]) / (0.5 * (w[0] + w[1]))
        };
        let split = |boxes: &[CostBox]| Decomposition::balanced(c.root, boxes, 2, 1, &c.planes);
        let by_leaves = split(&d.reweighted(&c.boxes, &c.boxes, &measured, 1.0));
        let by_pages = split(&reweighted_by_pages(
            &c, &c.boxes, &d, &measured, &work, 1.0,
        ));
        let (il, ip) = (real(&by_leaves), real(&by_pages));
        // Pages: the plane after brick 0 (10 against 7); leaves: after brick 2 (12 against 5).
        assert_eq!(root_split(&by_pages), (0, 29.5), "{il} {ip}");
        assert!(ip < 1.2 && ip < il - 0.2, "by pages {ip}, by leaves {il}");
        // The boxes' costs follow the truth, plus the floor, in the field's units.
        let rw = reweighted_by_pages(&c, &c.boxes, &d, &measured, &work, 1.0);
        let unit = rw[1].cost - MEASURED_FLOOR * c.boxes[1].cost;
        for b in 0..8 {
            let want = truth[b] * unit + MEASURED_FLOOR * c.boxes[b].cost;
            assert!(
                (rw[b].cost - want).abs() < 1e-6 * want,
                "box {b}: {} against {want}",
                rw[b].cost
            );
        }
        // Damping 0, nothing measured, or only unusable records: the field as it is. A
        // record of a page in the other leaf, or of an unknown page, gives nothing.
        assert_eq!(
            reweighted_by_pages(&c, &c.boxes, &d, &measured, &work, 0.0),
            c.boxes
        );
        assert_eq!(
            reweighted_by_pages(&c, &c.boxes, &d, &[0.0, 0.0], &work, 1.0),
            c.boxes
        );
        // A leaf that cast nothing (off screen, 0 s) is measured: its boxes cost the floor
        // alone and the next split gives its idle worker part of the busy one's (it had
        // kept its full cost, and the split stayed where it was).
        let busy = leaf_of(0);
        let mut idle_times = vec![0.0; 2];
        idle_times[busy] = measured[busy];
        let busy_work: Vec<_> = work.iter().copied().filter(|w| w.0 == busy).collect();
        let rw_idle = reweighted_by_pages(&c, &c.boxes, &d, &idle_times, &busy_work, 1.0);
        for b in (0..8).filter(|&b| leaf_of(b) != busy) {
            let want = MEASURED_FLOOR * c.boxes[b].cost;
            assert!(
                (rw_idle[b].cost - want).abs() < 1e-9 * want,
                "box {b}: {} against the floor {want}",
                rw_idle[b].cost
            );
        }
        let moved = root_split(&split(&rw_idle)).1;
        assert!(moved < 119.5, "the plane stayed at {moved}");
        let junk = [
            (0, key(&c, 0, 0, [0, 0, 0]), f32::NAN),
            (0, key(&c, 0, 0, [0, 0, 0]), -1.0),
            (5, key(&c, 0, 0, [0, 0, 0]), 0.5),
            (leaf_of(7), key(&c, 0, 0, [0, 0, 0]), 0.5),
            (0, u64::MAX, 0.5),
        ];
        let plain = reweighted_by_pages(&c, &c.boxes, &d, &measured, &[], 1.0);
        assert_eq!(
            reweighted_by_pages(&c, &c.boxes, &d, &measured, &junk, 1.0),
            plain
        );
        // A leaf beyond the tree with a time (more times than leaves) is ignored too.
        let longer = [measured[0], measured[1], 3.0, 4.0];
        let beyond = [(3, key(&c, 0, 0, [0, 0, 0]), 0.5)];
        assert_eq!(
            reweighted_by_pages(&c, &c.boxes, &d, &longer, &beyond, 1.0),
            plain
        );
        // A record sent twice in halves counts as one; shares adding up to more than 1 are
        // scaled down to 1.
        let close = |a: &[CostBox], b: &[CostBox]| {
            a.iter()
                .zip(b)
                .all(|(x, y)| (x.cost - y.cost).abs() <= 1e-9 * y.cost.abs())
        };
        let halves: Vec<(usize, u64, f32)> = work
            .iter()
            .flat_map(|&(l, k, s)| [(l, k, s / 2.0), (l, k, s / 2.0)])
            .collect();
        let doubled: Vec<(usize, u64, f32)> =
            work.iter().map(|&(l, k, s)| (l, k, 2.0 * s)).collect();
        assert!(close(
            &reweighted_by_pages(&c, &c.boxes, &d, &measured, &halves, 1.0),
            &rw
        ));
        assert!(close(
            &reweighted_by_pages(&c, &c.boxes, &d, &measured, &doubled, 1.0),
            &rw
        ));
        // A coarse page's time goes to the level-0 boxes under it in its leaf: all of
        // leaf 0's time in the level-2 page over bricks 0–3 gives those four boxes equal
        // costs, like no page record at all.
        let coarse = [(leaf_of(0), key(&c, 0, 2, [0, 0, 0]), 1.0)];
        let rc = reweighted_by_pages(&c, &c.boxes, &d, &measured, &coarse, 1.0);
        for b in 0..8 {
            assert!(
                (rc[b].cost - plain[b].cost).abs() < 1e-9 * plain[b].cost,
                "box {b}"
            );
        }
    }

    #[test]
    fn leaves_are_measured_by_cpu_time_only_where_every_leaf_has_one() {
        // 8 unit boxes along x, 2 workers with 2 leaves each.
        let boxes: Vec<CostBox> = (0..8)
            .map(|i| CostBox {
                region: Region {
                    lo: [i as f64, 0.0, 0.0],
                    hi: [i as f64 + 1.0, 1.0, 1.0],
                },
                cost: 1.0,
            })
            .collect();
        let root = Region {
            lo: [0.0; 3],
            hi: [8.0, 1.0, 1.0],
        };
        let d = Decomposition::balanced(root, &boxes, 2, 2, &[vec![], vec![], vec![]]);
        let (w0, w1) = (d.worker_leaves(0), d.worker_leaves(1));
        assert_eq!((w0.len(), w1.len()), (2, 2));
        // Wall times say balanced; CPU times (what the casts cost) say worker 1's second
        // leaf is three times the others.
        let stats = |cpu1: Vec<f64>| {
            vec![
                WorkerFrameStats {
                    leaf_cast_s: vec![2.0, 2.0],
                    leaf_cpu_s: vec![1.0, 1.0],
                    ..Default::default()
                },
                WorkerFrameStats {
                    leaf_cast_s: vec![2.0, 2.0],
                    leaf_cpu_s: cpu1,
                    ..Default::default()
                },
            ]
        };
        let want = |a: [f64; 2], b: [f64; 2]| {
            let mut m = vec![0.0; 4];
            for (i, &l) in w0.iter().enumerate() {
                m[l] = a[i];
            }
            for (i, &l) in w1.iter().enumerate() {
                m[l] = b[i];
            }
            m
        };
        let s = stats(vec![1.0, 3.0]);
        assert_eq!(
            measured_leaf_times(&d, &s, RebalanceClock::Cpu),
            (want([1.0, 1.0], [1.0, 3.0]), "cpu")
        );
        assert!(d.measured_imbalance(&measured_leaf_times(&d, &s, RebalanceClock::Cpu).0) > 1.2);
        assert_eq!(
            measured_leaf_times(&d, &s, RebalanceClock::Wall),
            (want([2.0, 2.0], [2.0, 2.0]), "wall")
        );
        // A leaf that cast nothing (off screen) is a measurement of 0 s, not a missing clock.
        assert_eq!(
            measured_leaf_times(&d, &stats(vec![1.0, 0.0]), RebalanceClock::Cpu),
            (want([1.0, 1.0], [1.0, 0.0]), "cpu")
        );
        // A worker without CPU times (GPU backend: none at all), with too few, or a
        // corrupt one: every leaf by wall time, so that none is compared on another clock.
        for cpu1 in [vec![], vec![1.0], vec![1.0, f64::NAN], vec![1.0, -1.0]] {
            assert_eq!(
                measured_leaf_times(&d, &stats(cpu1), RebalanceClock::Cpu),
                (want([2.0, 2.0], [2.0, 2.0]), "wall")
            );
        }
        // Stats of fewer workers than the split has: by wall time too.
        assert_eq!(
            measured_leaf_times(&d, &s[..1], RebalanceClock::Cpu).1,
            "wall"
        );
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
        let full = opaque_store(dir.path(), "full", dims);
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
