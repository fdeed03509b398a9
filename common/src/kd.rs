//! Axis-aligned regions of space, k-d trees over them, and their visibility order.
//!
//! Regions are half-open boxes `[lo, hi)` in world coordinates (f64). Sibling regions share
//! their split plane exactly, which is what lets ray casters clip rays to half-open `t`
//! intervals that neither overlap nor leave gaps (see the worker's lattice sampling).

use serde::{Deserialize, Serialize};

/// A re-split by measured times charges each part of the scene at least this fraction of
/// its estimated cost: a part the view did not reach (hidden, or off screen) still costs a
/// little, so a split does not hand one worker all of it at once, and a worker left idle
/// by the view is given work.
pub const MEASURED_FLOOR: f64 = 0.05;

/// A half-open axis-aligned box `[lo, hi)` in world coordinates.
#[derive(Copy, Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Region {
    /// Lower corner (inclusive).
    pub lo: [f64; 3],
    /// Upper corner (exclusive).
    pub hi: [f64; 3],
}

impl Region {
    /// Splits at `pos` on `axis` into `([lo, pos), [pos, hi))`.
    pub fn split(&self, axis: usize, pos: f64) -> (Region, Region) {
        let mut a = *self;
        let mut b = *self;
        a.hi[axis] = pos;
        b.lo[axis] = pos;
        (a, b)
    }

    /// Whether the point lies inside (half-open on every axis).
    pub fn contains(&self, p: [f64; 3]) -> bool {
        (0..3).all(|a| self.lo[a] <= p[a] && p[a] < self.hi[a])
    }

    /// Grows the box by `margin` on every side (relative to its largest extent).
    pub fn padded(&self, margin: f64) -> Region {
        let ext = (0..3)
            .map(|a| self.hi[a] - self.lo[a])
            .fold(0.0f64, f64::max)
            .max(1.0);
        Region {
            lo: self.lo.map(|v| v - margin * ext),
            hi: self.hi.map(|v| v + margin * ext),
        }
    }

    /// The smallest box holding both.
    pub fn union(&self, o: &Region) -> Region {
        Region {
            lo: [0, 1, 2].map(|a| self.lo[a].min(o.lo[a])),
            hi: [0, 1, 2].map(|a| self.hi[a].max(o.hi[a])),
        }
    }
}

/// A k-d tree node: a leaf (an index into the leaf list) or a split.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum KdNode {
    /// Leaf number `i`.
    Leaf(usize),
    /// Split of the parent box at `pos` on `axis`; `lo` holds `[.., pos)`, `hi` holds `[pos, ..)`.
    Split {
        /// Axis 0, 1 or 2.
        axis: usize,
        /// Plane position (world units).
        pos: f64,
        /// The lower side.
        lo: Box<KdNode>,
        /// The upper side.
        hi: Box<KdNode>,
    },
}

/// A k-d tree over a root region; its leaves are the regions that workers render.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct KdTree {
    /// The root box.
    pub root_region: Region,
    /// The tree.
    pub root: KdNode,
    /// Leaf boxes, indexed by leaf number.
    pub leaves: Vec<Region>,
}

impl KdTree {
    /// A tree with a single leaf.
    pub fn single(region: Region) -> Self {
        KdTree {
            root_region: region,
            root: KdNode::Leaf(0),
            leaves: vec![region],
        }
    }

    /// Builds a tree from a list of splits applied in order: each `(leaf, axis, fraction)`
    /// splits that leaf at `fraction` of its extent on `axis` (the new upper half becomes
    /// the last leaf). Used by tests and by simple decompositions.
    pub fn from_splits(region: Region, splits: &[(usize, usize, f64)]) -> Self {
        let mut t = KdTree::single(region);
        for &(leaf, axis, frac) in splits {
            let r = t.leaves[leaf];
            let pos = r.lo[axis] + frac * (r.hi[axis] - r.lo[axis]);
            t.split_leaf(leaf, axis, pos);
        }
        t
    }

    /// Splits leaf `leaf` at `pos` on `axis`; the lower part keeps the leaf number and the
    /// upper part gets the next free one, which is returned.
    pub fn split_leaf(&mut self, leaf: usize, axis: usize, pos: f64) -> usize {
        let (a, b) = self.leaves[leaf].split(axis, pos);
        self.leaves[leaf] = a;
        let new = self.leaves.len();
        self.leaves.push(b);
        fn walk(n: &mut KdNode, leaf: usize, axis: usize, pos: f64, new: usize) -> bool {
            match n {
                KdNode::Leaf(i) if *i == leaf => {
                    *n = KdNode::Split {
                        axis,
                        pos,
                        lo: Box::new(KdNode::Leaf(leaf)),
                        hi: Box::new(KdNode::Leaf(new)),
                    };
                    true
                }
                KdNode::Leaf(_) => false,
                KdNode::Split { lo, hi, .. } => {
                    walk(lo, leaf, axis, pos, new) || walk(hi, leaf, axis, pos, new)
                }
            }
        }
        let found = walk(&mut self.root, leaf, axis, pos, new);
        debug_assert!(found);
        new
    }

    /// Calls `f(leaf, fraction)` for every leaf that holds part of `b`, with the fraction of
    /// `b` in it ([`CostBox::fraction_in`] of the leaf's region, the same number). The box
    /// goes down the tree, to both sides of a plane it straddles, so it meets only the
    /// leaves it may overlap: a re-split over a survey's million bricks and 64 leaves
    /// had clipped every brick against every leaf, several times (seconds a frame).
    pub fn parts(&self, b: &CostBox, mut f: impl FnMut(usize, f64)) {
        fn walk(t: &KdTree, n: &KdNode, b: &CostBox, f: &mut dyn FnMut(usize, f64)) {
            match n {
                KdNode::Leaf(i) => {
                    let frac = t.leaves.get(*i).map_or(0.0, |r| b.fraction_in(r));
                    if frac > 0.0 {
                        f(*i, frac);
                    }
                }
                KdNode::Split { axis, pos, lo, hi } => {
                    let (l, h) = (b.region.lo[*axis], b.region.hi[*axis]);
                    // The sides `clip_box` can find a part on: below the plane where the box
                    // starts below it; above where it ends above it, or lies flat on it or
                    // above (a zero-extent axis counts on the side that holds it). A box
                    // with a NaN corner is in neither (nor in any leaf by `fraction_in`).
                    let flat = !(h > l);
                    if l < *pos {
                        walk(t, lo, b, f);
                    }
                    if h > *pos || (flat && l >= *pos) {
                        walk(t, hi, b, f);
                    }
                }
            }
        }
        walk(self, &self.root, b, &mut f);
    }

    /// Leaves in front-to-back order as seen from `eye`: at each split the side holding
    /// the eye comes first. (A perspective camera sees a k-d split correctly ordered this
    /// way because each split plane separates the two sides completely.)
    pub fn visibility_order(&self, eye: [f64; 3]) -> Vec<usize> {
        let mut out = Vec::with_capacity(self.leaves.len());
        fn walk(n: &KdNode, eye: [f64; 3], out: &mut Vec<usize>) {
            match n {
                KdNode::Leaf(i) => out.push(*i),
                KdNode::Split { axis, pos, lo, hi } => {
                    if eye[*axis] < *pos {
                        walk(lo, eye, out);
                        walk(hi, eye, out);
                    } else {
                        walk(hi, eye, out);
                        walk(lo, eye, out);
                    }
                }
            }
        }
        walk(&self.root, eye, &mut out);
        out
    }
}

/// A box of work: its world region and its estimated cost (expected ray samples).
///
/// The cost is spread uniformly over the box: the part of a box inside a region costs its
/// volume fraction of the whole. A box with zero extent on an axis (a flat horizon tile, a
/// single plane of voxels) counts wholly on the side of a split that holds it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CostBox {
    /// World region (half-open like every [`Region`]).
    pub region: Region,
    /// Estimated cost; NaN, infinite and negative costs count as 0.
    pub cost: f64,
}

impl CostBox {
    /// The fraction of the box (of its cost) that lies in `r`, by the same rule the splits
    /// follow: its volume fraction, a zero-extent axis wholly on the side that holds it.
    pub fn fraction_in(&self, r: &Region) -> f64 {
        let unit = CostBox {
            region: self.region,
            cost: 1.0,
        };
        clip_box(&unit, r).map_or(0.0, |c| c.cost)
    }
}

/// A k-d tree whose leaves are assigned to workers. Every worker owns one whole subtree, so
/// its leaves are contiguous in every visibility order and the workers themselves have a
/// well-defined front-to-back order for any eye (what sort-last compositing needs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Decomposition {
    /// The tree; its leaves are numbered in tree order (depth first, lower side first).
    pub tree: KdTree,
    /// Leaf → worker.
    pub owner: Vec<usize>,
    /// Leaf → estimated cost (the cost of the boxes inside it).
    pub leaf_cost: Vec<f64>,
    /// Number of workers (`0..workers`, numbered in tree order).
    pub workers: usize,
}

/// Largest allowed deviation of a snapped split's cost fraction from its target, before the
/// "one brick's share" term (see [`Decomposition::balanced`]).
pub const SNAP_TOLERANCE: f64 = 0.02;

/// The most a snap may move a split's cost fraction from its target, whatever one brick's
/// share: where a brick holds most of a node's cost (coarse bricks for many workers, one
/// opaque brick among transparent ones) the split goes through it rather than leave one
/// side with nearly all the work (snapping had given 0.95 against 0.05, an imbalance of
/// 1.9 that no re-split could undo).
pub const MAX_SNAP: f64 = 0.1;

/// A box clipped to a node, with the part of its cost that lies in the node.
fn clip_box(b: &CostBox, r: &Region) -> Option<CostBox> {
    let mut out = *b;
    let mut frac = 1.0;
    for a in 0..3 {
        let (lo, hi) = (b.region.lo[a], b.region.hi[a]);
        let ext = hi - lo;
        if ext > 0.0 {
            let clo = lo.max(r.lo[a]);
            let chi = hi.min(r.hi[a]);
            if chi <= clo {
                return None;
            }
            frac *= ((chi - clo) / ext).min(1.0);
            out.region.lo[a] = clo;
            out.region.hi[a] = chi;
        } else if !(r.lo[a] <= lo && lo < r.hi[a]) {
            // Zero extent: wholly in the half-open node or not at all.
            return None;
        }
    }
    out.cost = b.cost * frac;
    (out.cost > 0.0).then_some(out)
}

/// Whether `clip_box(b, r)` is `b` itself: every axis inside `r` (a zero-extent one by the
/// half-open rule). False for a NaN corner.
fn inside(b: &CostBox, r: &Region) -> bool {
    (0..3).all(|a| {
        let (lo, hi) = (b.region.lo[a], b.region.hi[a]);
        if hi > lo {
            r.lo[a] <= lo && hi <= r.hi[a]
        } else {
            r.lo[a] <= lo && lo < r.hi[a]
        }
    })
}

/// A node's boxes clipped to its two sides, `lo` and `hi`: exactly `clip_box` on each, but
/// a box wholly on one side is moved there as it is (most are: only those across the plane
/// are clipped, twice), rather than every box clipped against both sides.
fn split_boxes(boxes: Vec<CostBox>, lo: &Region, hi: &Region) -> (Vec<CostBox>, Vec<CostBox>) {
    let (mut blo, mut bhi) = (Vec::new(), Vec::new());
    for b in boxes {
        if inside(&b, lo) {
            if b.cost > 0.0 {
                blo.push(b);
            }
        } else if inside(&b, hi) {
            if b.cost > 0.0 {
                bhi.push(b);
            }
        } else {
            blo.extend(clip_box(&b, lo));
            bhi.extend(clip_box(&b, hi));
        }
    }
    (blo, bhi)
}

/// Cost of the boxes' parts below `x` on `axis` (all boxes lie inside the node).
fn cost_below(boxes: &[CostBox], axis: usize, x: f64) -> f64 {
    boxes
        .iter()
        .map(|b| part_below(b.region.lo[axis], b.region.hi[axis], b.cost, x))
        .sum()
}

/// The part below `x` of a box's `cost` that spans `[lo, hi]` on the axis: in proportion
/// to its extent, or all of it when it is flat and lies below `x`.
fn part_below(lo: f64, hi: f64, cost: f64, x: f64) -> f64 {
    let ext = hi - lo;
    if ext > 0.0 {
        cost * ((x - lo) / ext).clamp(0.0, 1.0)
    } else if lo < x {
        cost
    } else {
        0.0
    }
}

/// Smallest `x` in `[lo, hi]` (to float resolution) with `cost_below(x) >= want`, or the
/// position just below it when that is closer to `want` (a jump from a zero-extent box).
///
/// A bisection, each step over the boxes that still matter: one wholly below the interval
/// left counts as a constant, one wholly above it as nothing, and both leave the sum for
/// good. The interval halves each step, so the boxes do too, down to those across the
/// plane (a layer of bricks): a million bricks cost a few passes, not one pass a step
/// (200 passes a node had taken most of a second).
fn balanced_position(boxes: &[CostBox], axis: usize, lo: f64, hi: f64, want: f64) -> f64 {
    // (lo, hi, cost) on the axis, and the cost of those pruned as wholly below.
    let mut live: Vec<(f64, f64, f64)> = boxes
        .iter()
        .map(|b| (b.region.lo[axis], b.region.hi[axis], b.cost))
        .collect();
    let mut below = 0.0;
    // `cost_below` of the live boxes.
    let cost = |live: &[(f64, f64, f64)], below: f64, x: f64| -> f64 {
        below
            + live
                .iter()
                .map(|&(l, h, c)| part_below(l, h, c, x))
                .sum::<f64>()
    };
    let (mut a, mut b) = (lo, hi);
    for _ in 0..200 {
        let mid = 0.5 * (a + b);
        if !(mid > a && mid < b) {
            break;
        }
        if cost(&live, below, mid) >= want {
            b = mid;
        } else {
            a = mid;
        }
        // Boxes whose part below is the same everywhere in [a, b]: all of it (ending at or
        // below a; flat, strictly below a) or none (starting at or above b; flat, at or
        // above b). A box with a NaN end stays (it counts as `cost_below` counts it).
        live.retain(|&(l, h, c)| {
            let ext = h - l;
            let (all, none) = if ext > 0.0 {
                (h <= a, l >= b)
            } else {
                (l < a, l >= b)
            };
            if all {
                below += c;
            }
            !(all || none)
        });
    }
    let (ca, cb) = (cost(&live, below, a), cost(&live, below, b));
    if want - ca < cb - want {
        a
    } else {
        b
    }
}

/// Sorted, finite, deduplicated copies of the candidate planes.
fn clean_planes(planes: &[Vec<f64>; 3]) -> [Vec<f64>; 3] {
    [0, 1, 2].map(|a| {
        let mut v: Vec<f64> = planes[a]
            .iter()
            .copied()
            .filter(|p| p.is_finite())
            .collect();
        v.sort_by(f64::total_cmp);
        v.dedup();
        v
    })
}

struct Builder {
    planes: [Vec<f64>; 3],
    leaves: Vec<Region>,
    owner: Vec<usize>,
    leaf_cost: Vec<f64>,
}

impl Builder {
    /// Builds the subtree of `region` for workers `first..first + workers`, each with
    /// `per_worker` leaves (`workers == 1`: `per_worker` is the leaves still to make).
    fn node(
        &mut self,
        region: Region,
        boxes: Vec<CostBox>,
        first: usize,
        workers: usize,
        per_worker: usize,
    ) -> KdNode {
        let (n_lo, n) = if workers >= 2 {
            (workers / 2, workers)
        } else if per_worker >= 2 {
            (per_worker / 2, per_worker)
        } else {
            let id = self.leaves.len();
            self.leaves.push(region);
            self.owner.push(first);
            self.leaf_cost.push(boxes.iter().map(|b| b.cost).sum());
            return KdNode::Leaf(id);
        };
        let (axis, pos) = self.split_of(&region, &boxes, n_lo as f64 / n as f64);
        let (rlo, rhi) = region.split(axis, pos);
        let (blo, bhi) = split_boxes(boxes, &rlo, &rhi);
        let (lo, hi) = if workers >= 2 {
            (
                self.node(rlo, blo, first, n_lo, per_worker),
                self.node(rhi, bhi, first + n_lo, n - n_lo, per_worker),
            )
        } else {
            (
                self.node(rlo, blo, first, 1, n_lo),
                self.node(rhi, bhi, first, 1, n - n_lo),
            )
        };
        KdNode::Split {
            axis,
            pos,
            lo: Box::new(lo),
            hi: Box::new(hi),
        }
    }

    /// The split of a node: longest axis, cost-balanced position, snapped to a candidate
    /// plane when that is close enough, and always strictly inside the node.
    fn split_of(&self, r: &Region, boxes: &[CostBox], target: f64) -> (usize, f64) {
        let ext = [0, 1, 2].map(|a| r.hi[a] - r.lo[a]);
        let mut axis = 0;
        for a in 1..3 {
            if ext[a] > ext[axis] {
                axis = a;
            }
        }
        let (lo, hi) = (r.lo[axis], r.hi[axis]);
        let mid = lo + 0.5 * (hi - lo);
        let total: f64 = boxes.iter().map(|b| b.cost).sum();
        if !(total > 0.0 && total.is_finite()) {
            return (axis, mid);
        }
        let want = target * total;
        let mut pos = balanced_position(boxes, axis, lo, hi, want);
        // Snap to the nearest candidate plane strictly inside the node if its cost
        // fraction is within max(SNAP_TOLERANCE, one brick's share) of the target.
        let planes = &self.planes[axis];
        let i = planes.partition_point(|&p| p < pos);
        let nearest = [i.checked_sub(1), Some(i)]
            .into_iter()
            .flatten()
            .filter_map(|k| planes.get(k).copied())
            .filter(|&p| p > lo && p < hi)
            .min_by(|a, b| (a - pos).abs().total_cmp(&(b - pos).abs()));
        if let Some(p) = nearest {
            let brick = boxes.iter().map(|b| b.cost).fold(0.0, f64::max) / total;
            let frac = cost_below(boxes, axis, p) / total;
            if (frac - target).abs() <= SNAP_TOLERANCE.max(brick.min(MAX_SNAP)) {
                pos = p;
            }
        }
        // Never an empty side: keep the plane strictly inside, a hair away from the faces.
        let margin = 1e-6 * (hi - lo);
        if !(pos > lo && pos < hi) {
            pos = pos.clamp(lo + margin, hi - margin);
        }
        if !(pos > lo && pos < hi) {
            pos = mid; // a node too thin to split (degenerate root only)
        }
        (axis, pos)
    }
}

impl Decomposition {
    /// Splits `root` into `workers × leaves_per_worker` leaves of about equal cost.
    ///
    /// Recursive bisection: a node with `w ≥ 2` workers is split into `w / 2` and
    /// `w − w / 2` workers; a node with one worker and `L > 1` leaves is split the same way
    /// by leaf count. The split axis is the node's longest; the position is where the cost
    /// below the plane is `w_lo / w` of the node's (boxes partially inside a side count in
    /// proportion to their overlapped volume; found by bisection to float resolution). If
    /// the node costs nothing, it is split in the middle.
    ///
    /// **Snapping rule.** Among `planes[axis]` (brick boundaries in world coordinates)
    /// strictly inside the node, the one nearest the balanced position is used instead if
    /// the cost fraction below it differs from the target fraction by at most
    /// `max(SNAP_TOLERANCE, min(b, MAX_SNAP))`, where `b` is one brick's share: the largest
    /// cost of a single box inside the node divided by the node's cost. Otherwise the unsnapped
    /// position is kept. Snapped planes keep bricks whole, so fewer pages are loaded twice.
    ///
    /// Every split lies strictly inside its node, so no leaf has an empty extent unless
    /// `root` itself has one. Degenerate inputs do not panic: `workers == 0` and
    /// `leaves_per_worker == 0` count as 1; boxes with NaN, infinite or negative cost count
    /// as costless; boxes with non-finite corners or outside `root` are ignored (a box
    /// partly outside `root` keeps only the cost of its part inside).
    pub fn balanced(
        root: Region,
        boxes: &[CostBox],
        workers: usize,
        leaves_per_worker: usize,
        planes: &[Vec<f64>; 3],
    ) -> Decomposition {
        let workers = workers.max(1);
        let per_worker = leaves_per_worker.max(1);
        let boxes: Vec<CostBox> = boxes
            .iter()
            .filter(|b| {
                (0..3).all(|a| {
                    b.region.lo[a].is_finite()
                        && b.region.hi[a].is_finite()
                        && b.region.lo[a] <= b.region.hi[a]
                })
            })
            .map(|b| CostBox {
                region: b.region,
                cost: if b.cost.is_finite() && b.cost > 0.0 {
                    b.cost
                } else {
                    0.0
                },
            })
            .filter_map(|b| clip_box(&b, &root))
            .collect();
        let mut builder = Builder {
            planes: clean_planes(planes),
            leaves: Vec::with_capacity(workers * per_worker),
            owner: Vec::with_capacity(workers * per_worker),
            leaf_cost: Vec::with_capacity(workers * per_worker),
        };
        let tree_root = builder.node(root, boxes, 0, workers, per_worker);
        Decomposition {
            tree: KdTree {
                root_region: root,
                root: tree_root,
                leaves: builder.leaves,
            },
            owner: builder.owner,
            leaf_cost: builder.leaf_cost,
            workers,
        }
    }

    /// The leaves of `worker`, in tree order.
    pub fn worker_leaves(&self, worker: usize) -> Vec<usize> {
        (0..self.owner.len())
            .filter(|&l| self.owner[l] == worker)
            .collect()
    }

    /// Estimated cost per worker (the sum of its leaves' costs).
    pub fn worker_costs(&self) -> Vec<f64> {
        let mut c = vec![0.0; self.workers];
        for (l, &w) in self.owner.iter().enumerate() {
            if let (Some(s), Some(v)) = (c.get_mut(w), self.leaf_cost.get(l)) {
                *s += v;
            }
        }
        c
    }

    /// Workers front to back as seen from `eye`: the order in which they first appear in
    /// the tree's visibility order. Each worker's leaves are contiguous in that order (one
    /// subtree per worker); debug builds check it.
    pub fn worker_order(&self, eye: [f64; 3]) -> Vec<usize> {
        let mut out = Vec::with_capacity(self.workers);
        let mut seen = vec![false; self.workers];
        for leaf in self.tree.visibility_order(eye) {
            let Some(&w) = self.owner.get(leaf) else {
                continue;
            };
            if out.last() == Some(&w) {
                continue;
            }
            debug_assert!(
                !seen.get(w).copied().unwrap_or(false),
                "worker {w}'s leaves are not contiguous in the visibility order"
            );
            if w < seen.len() && !seen[w] {
                seen[w] = true;
                out.push(w);
            }
        }
        out
    }

    /// The leaves of `worker` front to back as seen from `eye`.
    pub fn leaf_order_of(&self, worker: usize, eye: [f64; 3]) -> Vec<usize> {
        self.tree
            .visibility_order(eye)
            .into_iter()
            .filter(|&l| self.owner.get(l) == Some(&worker))
            .collect()
    }

    /// Largest worker time over the mean, from `measured` seconds per leaf (1 when nothing
    /// was measured).
    pub fn measured_imbalance(&self, measured: &[f64]) -> f64 {
        let mut w = vec![0.0; self.workers];
        for (l, &o) in self.owner.iter().enumerate() {
            if let (Some(s), Some(&m)) = (w.get_mut(o), measured.get(l)) {
                if m.is_finite() && m > 0.0 {
                    *s += m;
                }
            }
        }
        let mean = w.iter().sum::<f64>() / self.workers.max(1) as f64;
        if !(mean > 0.0) {
            return 1.0;
        }
        w.iter().copied().fold(0.0, f64::max) / mean
    }

    /// The cost boxes re-weighted by what the leaves measured: a box's part in leaf `l`
    /// costs its weight in `boxes` times `(measured_l / leaf_cost_l) / (Σ measured /
    /// Σ leaf_cost)` (the leaf's costs count box parts the same way, so a box across several
    /// leaves takes each leaf's factor for its part there, and a leaf that holds no box's
    /// centre is re-weighted too), at least [`MEASURED_FLOOR`] of its `estimate` (the parallel boxes of the
    /// scene's estimate, in the field's units: a floor taken on each re-split's own field had
    /// compounded, so that a leaf off screen for a few re-splits fell far under it and its
    /// worker was handed a huge region), raised to `damping` in (0, 1] so that one noisy
    /// frame moves the split only part of the way. A leaf measured at 0 s (off screen) takes
    /// the floor: otherwise an idle worker would keep its share for good. Leaves with no
    /// estimate or no measurement (`NaN`) keep their weights, as do all when no leaf measured
    /// any time. Balancing these boxes re-splits the tree by the view's real work. (An
    /// `estimate` of another length than `boxes` floors each box at its own weight's
    /// fraction.)
    pub fn reweighted(
        &self,
        estimate: &[CostBox],
        boxes: &[CostBox],
        measured: &[f64],
        damping: f64,
    ) -> Vec<CostBox> {
        let n = self.tree.leaves.len();
        let ok = |v: f64| v.is_finite() && v > 0.0;
        let reported = |v: f64| v.is_finite() && v >= 0.0;
        let (mut sm, mut se) = (0.0, 0.0);
        for l in 0..n {
            let (m, e) = (
                measured.get(l).copied().unwrap_or(f64::NAN),
                self.leaf_cost[l],
            );
            if reported(m) && ok(e) {
                sm += m;
                se += e;
            }
        }
        let d = if damping.is_finite() {
            damping.clamp(0.0, 1.0)
        } else {
            1.0
        };
        // Each leaf's measured ratio (`None`: keeps its weights).
        let ratio: Vec<Option<f64>> = (0..n)
            .map(|l| {
                let (m, e) = (
                    measured.get(l).copied().unwrap_or(f64::NAN),
                    self.leaf_cost[l],
                );
                // (Divided so that extreme but finite times cannot overflow to infinity or
                // vanish: a non-finite ratio is no measurement.)
                (reported(m) && ok(e) && ok(sm) && ok(se))
                    .then(|| (m / sm) * (se / e))
                    .filter(|r| r.is_finite())
            })
            .collect();
        let weight = |b: &CostBox| if ok(b.cost) { b.cost } else { 0.0 };
        let parallel = estimate.len() == boxes.len();
        let (field_total, est_total): (f64, f64) = if parallel {
            (
                boxes.iter().map(weight).sum(),
                estimate.iter().map(weight).sum(),
            )
        } else {
            (1.0, 1.0)
        };
        let est_to_field = if ok(field_total) && ok(est_total) {
            field_total / est_total
        } else {
            1.0
        };
        boxes
            .iter()
            .enumerate()
            .map(|(i, b)| {
                // A box without weight stays without.
                if !ok(b.cost) {
                    return *b;
                }
                let est = if parallel {
                    weight(&estimate[i])
                } else {
                    b.cost
                };
                let floor = MEASURED_FLOOR * est_to_field * est / b.cost;
                // Each leaf's factor over the box's part in it; a part in a leaf without a
                // ratio, or in none, keeps its weight.
                let mut inside = 0.0;
                let mut factor = 0.0;
                self.tree.parts(b, |l, f| {
                    if let Some(ratio) = ratio.get(l).copied().flatten() {
                        inside += f;
                        factor += f * ratio.max(floor).powf(d);
                    }
                });
                factor += (1.0 - inside).max(0.0);
                let cost = b.cost * factor;
                CostBox {
                    region: b.region,
                    cost: if cost.is_finite() { cost } else { b.cost },
                }
            })
            .collect()
    }

    /// [`imbalance`](Self::imbalance) of these leaves and owners under other cost boxes
    /// (each box's part in each leaf, as [`balanced`](Self::balanced) counts it): how well
    /// the split in force fits a re-weighted field.
    pub fn imbalance_under(&self, boxes: &[CostBox]) -> f64 {
        let mut c = vec![0.0; self.workers.max(1)];
        let sane = |b: &&CostBox| {
            b.cost.is_finite()
                && b.cost > 0.0
                && (0..3).all(|a| {
                    b.region.lo[a].is_finite()
                        && b.region.hi[a].is_finite()
                        && b.region.lo[a] <= b.region.hi[a]
                })
        };
        for b in boxes.iter().filter(sane) {
            self.tree.parts(b, |l, frac| {
                if let Some(w) = self.owner.get(l).and_then(|&w| c.get_mut(w)) {
                    *w += b.cost * frac;
                }
            });
        }
        let mean = c.iter().sum::<f64>() / c.len() as f64;
        if !(mean > 0.0 && mean.is_finite()) {
            return 1.0;
        }
        c.iter().copied().fold(0.0, f64::max) / mean
    }

    /// Largest worker cost over the mean worker cost (1 when nothing costs anything).
    pub fn imbalance(&self) -> f64 {
        let c = self.worker_costs();
        let total: f64 = c.iter().sum();
        let mean = total / self.workers.max(1) as f64;
        if !(mean > 0.0 && mean.is_finite()) {
            return 1.0;
        }
        c.iter().copied().fold(0.0, f64::max) / mean
    }

    /// Checks the structure (for a decomposition that arrived from elsewhere): every leaf
    /// appears once in the tree, the per-leaf vectors match the leaves, every worker owns
    /// at least one leaf, and every worker's leaves form one whole subtree.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.tree.leaves.len();
        if self.owner.len() != n || self.leaf_cost.len() != n {
            return Err(format!(
                "{n} leaves but {} owners and {} costs",
                self.owner.len(),
                self.leaf_cost.len()
            ));
        }
        if let Some(&w) = self.owner.iter().find(|&&w| w >= self.workers) {
            return Err(format!(
                "owner {w} out of range for {} workers",
                self.workers
            ));
        }
        let mut count = vec![0usize; self.workers];
        for &w in &self.owner {
            count[w] += 1;
        }
        if let Some(w) = count.iter().position(|&c| c == 0) {
            return Err(format!("worker {w} owns no leaf"));
        }
        /// Owners below a node (sorted) and its leaf count; marks `whole[w]` where a
        /// subtree holds exactly the leaves of worker `w`.
        fn walk(
            n: &KdNode,
            d: &Decomposition,
            count: &[usize],
            hit: &mut [bool],
            whole: &mut [bool],
        ) -> Result<(Vec<usize>, usize), String> {
            let (owners, leaves) = match n {
                KdNode::Leaf(i) => {
                    if *i >= hit.len() || hit[*i] {
                        return Err(format!("leaf {i} is missing or appears twice"));
                    }
                    hit[*i] = true;
                    (vec![d.owner[*i]], 1)
                }
                KdNode::Split { axis, lo, hi, .. } => {
                    if *axis > 2 {
                        return Err(format!("split axis {axis}"));
                    }
                    let (mut a, na) = walk(lo, d, count, hit, whole)?;
                    let (b, nb) = walk(hi, d, count, hit, whole)?;
                    a.extend(b);
                    a.sort_unstable();
                    a.dedup();
                    (a, na + nb)
                }
            };
            if let [w] = owners[..] {
                if count[w] == leaves {
                    whole[w] = true;
                }
            }
            Ok((owners, leaves))
        }
        let mut hit = vec![false; n];
        let mut whole = vec![false; self.workers];
        walk(&self.tree.root, self, &count, &mut hit, &mut whole)?;
        if let Some(w) = whole.iter().position(|h| !h) {
            return Err(format!("worker {w}'s leaves are not one whole subtree"));
        }
        if let Some(i) = hit.iter().position(|h| !h) {
            return Err(format!("leaf {i} is not in the tree"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A slab 100 × 10 × 10 of 100 unit boxes along x, each costing 1.
    fn unit_slab() -> (Region, Vec<CostBox>) {
        let root = Region {
            lo: [0.0; 3],
            hi: [100.0, 10.0, 10.0],
        };
        let boxes = (0..100)
            .map(|i| CostBox {
                region: Region {
                    lo: [i as f64, 0.0, 0.0],
                    hi: [i as f64 + 1.0, 10.0, 10.0],
                },
                cost: 1.0,
            })
            .collect();
        (root, boxes)
    }

    /// A box across several leaves takes each leaf's factor for its part there, as the
    /// leaves' own costs count it: by the box's centre alone, a leaf that held no centre
    /// was never re-weighted and the measured imbalance could stay for good.
    #[test]
    fn reweighting_weighs_each_part_of_a_box_by_its_own_leaf() {
        // Two bricks, [0, 2) and [2, 4) along x, over 2 workers × 2 leaves of width 1:
        // each brick's centre lies in the second leaf of its worker.
        let root = Region {
            lo: [0.0, 0.0, 0.0],
            hi: [4.0, 1.0, 1.0],
        };
        let brick = |x: f64| CostBox {
            region: Region {
                lo: [x, 0.0, 0.0],
                hi: [x + 2.0, 1.0, 1.0],
            },
            cost: 1.0,
        };
        let boxes = [brick(0.0), brick(2.0)];
        let none = [vec![], vec![], vec![]];
        let d = Decomposition::balanced(root, &boxes, 2, 2, &none);
        let edges: Vec<f64> = d.tree.leaves.iter().map(|l| l.hi[0]).collect();
        assert_eq!(edges, [1.0, 2.0, 3.0, 4.0]);
        // The first leaf took 3 s, the others 1 s each: worker 0 did 4 s against 2.
        let measured = [3.0, 1.0, 1.0, 1.0];
        assert!((d.measured_imbalance(&measured) - 4.0 / 3.0).abs() < 1e-12);
        let w = d.reweighted(&boxes, &boxes, &measured, 1.0);
        // Ratios 2, 2/3, 2/3, 2/3: the first brick costs (2 + 2/3) / 2, the second 2/3.
        assert!((w[0].cost - 4.0 / 3.0).abs() < 1e-12, "{w:?}");
        assert!((w[1].cost - 2.0 / 3.0).abs() < 1e-12, "{w:?}");
        // So the split in force shows the measured imbalance under the new field.
        assert!((d.imbalance_under(&w) - 4.0 / 3.0).abs() < 1e-9);
        // Times at the ends of f64's range (finite, so accepted from a worker): `m / e`
        // subnormal while `Σm / Σe` underflows to 0 had made the ratio infinite, and the
        // box's cost with it. Ratios are finite or no measurement.
        let mut skewed = d.clone();
        skewed.leaf_cost = vec![100.0, 1e6, 1e6, 1e6];
        let w = skewed.reweighted(&boxes, &boxes, &[1e-320, 0.0, 0.0, 0.0], 1.0);
        assert!(
            w.iter().all(|b| b.cost.is_finite() && b.cost > 0.0),
            "{w:?}"
        );
    }

    #[test]
    fn reweighting_by_measured_time_moves_the_split_toward_the_slow_side() {
        // A uniform slab of 100 unit boxes along x: the estimate splits it at x = 50.
        let (root, boxes) = unit_slab();
        let none = [vec![], vec![], vec![]];
        let d = Decomposition::balanced(root, &boxes, 2, 1, &none);
        let split = |d: &Decomposition| d.tree.leaves[0].hi[0];
        assert!((split(&d) - 50.0).abs() < 1e-9);
        // The left half measured 3× slower than the right (say, it is where the view looks):
        // densities 3:1, so half the work lies left of x = 100/3.
        let measured = [3.0, 1.0];
        assert!((d.measured_imbalance(&measured) - 1.5).abs() < 1e-12);
        let full = Decomposition::balanced(
            root,
            &d.reweighted(&boxes, &boxes, &measured, 1.0),
            2,
            1,
            &none,
        );
        assert!(
            (split(&full) - 100.0 / 3.0).abs() < 1e-6,
            "{}",
            split(&full)
        );
        // Damped: part of the way.
        let half = Decomposition::balanced(
            root,
            &d.reweighted(&boxes, &boxes, &measured, 0.5),
            2,
            1,
            &none,
        );
        assert!(
            split(&half) > 100.0 / 3.0 + 1.0 && split(&half) < 49.0,
            "{}",
            split(&half)
        );
        // Nothing measured: unchanged weights.
        assert_eq!(d.reweighted(&boxes, &boxes, &[0.0, 0.0], 1.0), boxes);
        assert_eq!(
            d.reweighted(&boxes, &boxes, &[f64::NAN, f64::NAN], 1.0),
            boxes
        );
        assert_eq!(d.measured_imbalance(&[]), 1.0);
        // The right leaf cast nothing (off screen): 0 s is a measurement. Its boxes take
        // the floor, and the idle worker is given most of the busy one's half (the split
        // had stayed at 50 for good, with the idle leaf's ratio left at 1).
        let idle = Decomposition::balanced(
            root,
            &d.reweighted(&boxes, &boxes, &[3.0, 0.0], 1.0),
            2,
            1,
            &none,
        );
        // Left boxes cost 2 (ratio (3/50)/(3/100)), right ones the floor 0.05: half the
        // 102.5 lies left of 51.25 / 2.
        assert!(
            (split(&idle) - 51.25 / 2.0).abs() < 1e-6,
            "{}",
            split(&idle)
        );
        // A leaf without a measurement (NaN) keeps its weights.
        let unknown = d.reweighted(&boxes, &boxes, &[3.0, f64::NAN], 1.0);
        assert!(
            unknown[99].cost == 1.0 && unknown[0].cost == 1.0,
            "{unknown:?}"
        );
    }

    /// A leaf off screen for several re-splits in a row takes the floor of its estimate, not
    /// the floor of each re-split's field again (0.05^d per re-split had compounded: after
    /// five, a fifth of a percent of the estimate, and its worker handed most of the scene).
    #[test]
    fn the_measured_floor_does_not_compound_across_re_splits() {
        let (root, estimate) = unit_slab();
        let none = [vec![], vec![], vec![]];
        let mut field = estimate.clone();
        for round in 0..6 {
            let d = Decomposition::balanced(root, &field, 2, 1, &none);
            // The right leaf sees nothing, every time.
            field = d.reweighted(&estimate, &field, &[1.0, 0.0], 0.5);
            let to_field = field.iter().map(|b| b.cost).sum::<f64>() / 100.0;
            let lowest = field.iter().map(|b| b.cost).fold(f64::INFINITY, f64::min);
            assert!(
                lowest >= MEASURED_FLOOR * to_field * (1.0 - 1e-9),
                "round {round}: {lowest} under the floor {}",
                MEASURED_FLOOR * to_field
            );
        }
    }

    /// One brick holding most of a node's cost does not pull the split to its face: the
    /// plane goes through it, and the two sides cost about the same.
    #[test]
    fn a_dominant_brick_is_split_rather_than_left_to_one_side() {
        let root = Region {
            lo: [0.0; 3],
            hi: [2.0, 1.0, 1.0],
        };
        let boxes = [(0.0, 1.0, 1.0), (1.0, 2.0, 0.05)].map(|(a, b, cost)| CostBox {
            region: Region {
                lo: [a, 0.0, 0.0],
                hi: [b, 1.0, 1.0],
            },
            cost,
        });
        let planes = [vec![0.0, 1.0, 2.0], vec![], vec![]];
        let d = Decomposition::balanced(root, &boxes, 2, 1, &planes);
        assert!(
            d.imbalance() < 1.01,
            "{} at {:?}",
            d.imbalance(),
            d.tree.leaves
        );
        // A brick's share within MAX_SNAP still snaps (bricks kept whole).
        let even = [(0.0, 1.0, 1.0), (1.0, 2.0, 0.85)].map(|(a, b, cost)| CostBox {
            region: Region {
                lo: [a, 0.0, 0.0],
                hi: [b, 1.0, 1.0],
            },
            cost,
        });
        let d = Decomposition::balanced(root, &even, 2, 1, &planes);
        assert_eq!(d.tree.leaves[0].hi[0], 1.0);
    }

    #[test]
    fn splits_and_order() {
        let r = Region {
            lo: [0.0; 3],
            hi: [10.0; 3],
        };
        let t = KdTree::from_splits(r, &[(0, 0, 0.5), (0, 1, 0.3), (1, 2, 0.5)]);
        assert_eq!(t.leaves.len(), 4);
        assert_eq!(t.leaves[0].hi, [5.0, 3.0, 10.0]);
        assert_eq!(t.leaves[2].lo, [0.0, 3.0, 0.0]);
        // Eye at high x: the x>=5 side comes first.
        let o = t.visibility_order([20.0, 0.0, 0.0]);
        assert_eq!(o, vec![1, 3, 0, 2]);
        let o = t.visibility_order([-1.0, 5.0, 20.0]);
        assert_eq!(o, vec![2, 0, 3, 1]);
    }

    fn cube(lo: [f64; 3], hi: [f64; 3]) -> Region {
        Region { lo, hi }
    }

    fn volume(r: &Region) -> f64 {
        (0..3).map(|a| r.hi[a] - r.lo[a]).product()
    }

    /// A grid of `n` equal boxes of cost `c` each tiling `r`.
    fn grid(r: &Region, n: [usize; 3], c: f64) -> Vec<CostBox> {
        let mut out = Vec::new();
        for z in 0..n[2] {
            for y in 0..n[1] {
                for x in 0..n[0] {
                    let i = [x, y, z];
                    let at =
                        |a: usize, k: usize| r.lo[a] + (r.hi[a] - r.lo[a]) * k as f64 / n[a] as f64;
                    out.push(CostBox {
                        region: Region {
                            lo: [0, 1, 2].map(|a| at(a, i[a])),
                            hi: [0, 1, 2].map(|a| at(a, i[a] + 1)),
                        },
                        cost: c,
                    });
                }
            }
        }
        out
    }

    fn no_planes() -> [Vec<f64>; 3] {
        [vec![], vec![], vec![]]
    }

    fn first_split(d: &Decomposition) -> (usize, f64) {
        match d.tree.root {
            KdNode::Split { axis, pos, .. } => (axis, pos),
            KdNode::Leaf(_) => panic!("no split"),
        }
    }

    /// Every structural property a decomposition promises.
    fn check(d: &Decomposition, root: &Region, workers: usize, per: usize, total: f64) {
        assert_eq!(d.validate(), Ok(()));
        assert_eq!(d.workers, workers.max(1));
        assert_eq!(d.tree.leaves.len(), d.workers * per.max(1));
        for w in 0..d.workers {
            let l = d.worker_leaves(w);
            assert_eq!(l.len(), per.max(1), "worker {w}");
            assert!(l.windows(2).all(|p| p[1] == p[0] + 1), "tree order: {l:?}");
        }
        let vol: f64 = d.tree.leaves.iter().map(volume).sum();
        assert!(
            (vol - volume(root)).abs() <= 1e-9 * volume(root),
            "{vol} vs {}",
            volume(root)
        );
        for l in &d.tree.leaves {
            assert!((0..3).all(|a| l.lo[a] < l.hi[a]), "empty leaf {l:?}");
        }
        let sum: f64 = d.leaf_cost.iter().sum();
        assert!(
            (sum - total).abs() <= 1e-9 * total.max(1.0),
            "{sum} vs {total}"
        );
    }

    fn in_exactly_one(d: &Decomposition, p: [f64; 3]) {
        let n = d.tree.leaves.iter().filter(|l| l.contains(p)).count();
        assert_eq!(n, 1, "{p:?}");
    }

    fn contiguous(d: &Decomposition, eye: [f64; 3]) {
        let order = d.worker_order(eye);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..d.workers).collect::<Vec<_>>());
        let leaves = d.tree.visibility_order(eye);
        let by_worker: Vec<usize> = order
            .iter()
            .flat_map(|&w| d.leaf_order_of(w, eye))
            .collect();
        assert_eq!(by_worker, leaves, "workers' leaves are not contiguous");
    }

    #[test]
    fn uniform_halves_and_quarters() {
        let r = cube([0.0; 3], [8.0, 4.0, 2.0]);
        let boxes = [CostBox {
            region: r,
            cost: 64.0,
        }];
        let d = Decomposition::balanced(r, &boxes, 4, 1, &no_planes());
        check(&d, &r, 4, 1, 64.0);
        assert_eq!(first_split(&d), (0, 4.0));
        assert!(d.imbalance() < 1.0 + 1e-9);
        assert_eq!(d.leaf_cost, vec![16.0; 4]);
        // Three workers: one third on the low side.
        let d = Decomposition::balanced(r, &boxes, 3, 1, &no_planes());
        let (axis, pos) = first_split(&d);
        assert_eq!(axis, 0);
        assert!((pos - 8.0 / 3.0).abs() < 1e-9, "{pos}");
        assert!(d.imbalance() < 1.0 + 1e-9);
    }

    #[test]
    fn cost_concentration_moves_the_split() {
        let r = cube([0.0; 3], [10.0, 1.0, 1.0]);
        let boxes = [
            CostBox {
                region: r,
                cost: 10.0,
            },
            CostBox {
                region: cube([0.0; 3], [1.0, 1.0, 1.0]),
                cost: 90.0,
            },
        ];
        let d = Decomposition::balanced(r, &boxes, 2, 1, &no_planes());
        let (_, pos) = first_split(&d);
        // Below x: 91·x for x ≤ 1, so the half (50) is at x = 50/91.
        assert!((pos - 50.0 / 91.0).abs() < 1e-9, "{pos}");
        assert!(d.imbalance() < 1.0 + 1e-9);
    }

    #[test]
    fn flat_boxes_count_wholly_on_one_side() {
        let r = cube([0.0; 3], [10.0, 1.0, 1.0]);
        let boxes = [
            CostBox {
                region: cube([3.0, 0.0, 0.0], [3.0, 1.0, 1.0]),
                cost: 5.0,
            },
            CostBox {
                region: r,
                cost: 20.0,
            },
        ];
        let d = Decomposition::balanced(r, &boxes, 2, 1, &no_planes());
        check(&d, &r, 2, 1, 25.0);
        let (_, pos) = first_split(&d);
        // 12.5 below: 2 per unit of x, plus the flat box's 5 past x = 3 → x = 3.75.
        assert!((pos - 3.75).abs() < 1e-9, "{pos}");
        // A plane exactly on a flat box puts it on the upper side (half-open).
        assert_eq!(cost_below(&boxes, 0, 3.0), 6.0);
        // A plane there is not used although the big box is one brick worth 80% of the
        // node: its fraction (0.24) is further than MAX_SNAP from the half.
        let d = Decomposition::balanced(r, &boxes, 2, 1, &[vec![3.0], vec![], vec![]]);
        let (_, pos) = first_split(&d);
        assert!((pos - 3.75).abs() < 1e-9, "{pos}");
        assert_eq!(d.leaf_cost, vec![12.5, 12.5]);
        // A jump that overshoots: the closer side of it is taken (just past x = 3: 8 of
        // 15 below, against 3 of 15 just before it).
        let boxes = [
            boxes[0],
            CostBox {
                region: r,
                cost: 10.0,
            },
        ];
        let d = Decomposition::balanced(r, &boxes, 2, 1, &no_planes());
        check(&d, &r, 2, 1, 15.0);
        let (_, pos) = first_split(&d);
        assert!(pos > 3.0 && pos < 3.0 + 1e-9, "{pos}");
        assert_eq!(d.leaf_cost, vec![8.0, 7.0]);
    }

    #[test]
    fn snapping_uses_close_planes_only() {
        let r = cube([0.0; 3], [10.0, 5.0, 5.0]);
        let boxes = grid(&r, [100, 1, 1], 1.0);
        // 4.9: fraction 0.49, within 0.02 of 0.5 → used.
        let d = Decomposition::balanced(r, &boxes, 2, 1, &[vec![1.0, 4.9, 7.0], vec![], vec![]]);
        assert_eq!(first_split(&d), (0, 4.9));
        // 4.0: fraction 0.4 → not used (one box is 1% of the node).
        let d = Decomposition::balanced(r, &boxes, 2, 1, &[vec![4.0, 6.1], vec![], vec![]]);
        let (_, pos) = first_split(&d);
        assert!((pos - 5.0).abs() < 1e-9, "{pos}");
        // Planes on the node's faces or outside are never used; NaN planes are ignored.
        let d = Decomposition::balanced(
            r,
            &boxes,
            2,
            1,
            &[vec![0.0, 10.0, -3.0, f64::NAN], vec![], vec![]],
        );
        let (_, pos) = first_split(&d);
        assert!((pos - 5.0).abs() < 1e-9, "{pos}");
        // Coarse bricks: one brick's share widens the tolerance.
        let boxes = grid(&r, [4, 1, 1], 1.0);
        let d = Decomposition::balanced(r, &boxes, 3, 1, &[vec![2.5, 5.0, 7.5], vec![], vec![]]);
        assert_eq!(first_split(&d), (0, 2.5));
        // Brick-aligned planes on a uniform grid: snapping is exact.
        let r = cube([0.0; 3], [8.0, 8.0, 8.0]);
        let boxes = grid(&r, [8, 8, 8], 1.0);
        let planes = [0, 1, 2].map(|_| (0..=8).map(f64::from).collect::<Vec<_>>());
        let d = Decomposition::balanced(r, &boxes, 8, 1, &planes);
        check(&d, &r, 8, 1, 512.0);
        assert!(d.imbalance() < 1.0 + 1e-9);
        for l in &d.tree.leaves {
            assert!(l.lo.iter().chain(&l.hi).all(|v| v.fract() == 0.0), "{l:?}");
        }
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        let r = cube([0.0; 3], [1.0; 3]);
        let d = Decomposition::balanced(r, &[], 0, 0, &no_planes());
        check(&d, &r, 1, 1, 0.0);
        assert_eq!(d.tree, KdTree::single(r));
        assert_eq!(d.worker_order([5.0; 3]), vec![0]);
        assert_eq!(d.imbalance(), 1.0);
        let d = Decomposition::balanced(r, &[], 5, 2, &no_planes());
        check(&d, &r, 5, 2, 0.0);
        let nan = [
            CostBox {
                region: r,
                cost: f64::NAN,
            },
            CostBox {
                region: r,
                cost: f64::INFINITY,
            },
            CostBox {
                region: r,
                cost: -3.0,
            },
            CostBox {
                region: cube([f64::NAN; 3], [1.0; 3]),
                cost: 1.0,
            },
            CostBox {
                region: cube([5.0; 3], [6.0; 3]),
                cost: 1.0,
            },
            CostBox {
                region: cube([0.5; 3], [0.5; 3]),
                cost: 2.0,
            },
        ];
        let d = Decomposition::balanced(r, &nan, 7, 3, &no_planes());
        check(&d, &r, 7, 3, 2.0);
        // A point-like root: leaves are empty but the structure holds.
        let p = cube([1.0; 3], [1.0; 3]);
        let d = Decomposition::balanced(p, &nan, 3, 2, &no_planes());
        assert_eq!(d.validate(), Ok(()));
        assert_eq!(d.tree.leaves.len(), 6);
        assert_eq!(d.worker_order([0.0; 3]).len(), 3);
        // Boxes partly outside the root keep the cost of their inside part.
        let half = [CostBox {
            region: cube([0.5, 0.0, 0.0], [1.5, 1.0, 1.0]),
            cost: 4.0,
        }];
        let d = Decomposition::balanced(r, &half, 2, 1, &no_planes());
        check(&d, &r, 2, 1, 2.0);
    }

    #[test]
    fn orders_and_serde() {
        let r = cube([0.0; 3], [4.0, 4.0, 4.0]);
        let boxes = grid(&r, [4, 4, 4], 1.0);
        let d = Decomposition::balanced(r, &boxes, 4, 2, &no_planes());
        check(&d, &r, 4, 2, 64.0);
        for eye in [[-1.0, -1.0, -1.0], [5.0, 5.0, 5.0], [2.1, -3.0, 1.0]] {
            contiguous(&d, eye);
            for w in 0..4 {
                let mut a = d.leaf_order_of(w, eye);
                a.sort_unstable();
                assert_eq!(a, d.worker_leaves(w));
            }
        }
        // Eye at low x and y: the low sides come first, so worker 0 is in front. (Not on a
        // plane: at y = 2, on the second split, the order depends on the plane's last bit.)
        assert_eq!(d.worker_order([-1.0, 1.0, 1.0])[0], 0);
        let bytes = bincode::serde::encode_to_vec(&d, bincode::config::standard()).unwrap();
        let (back, _): (Decomposition, usize) =
            bincode::serde::decode_from_slice(&bytes, bincode::config::standard()).unwrap();
        assert_eq!(back, d);
    }

    #[test]
    fn validate_rejects_split_workers() {
        let r = cube([0.0; 3], [4.0, 4.0, 4.0]);
        let mut d = Decomposition::balanced(r, &[], 2, 2, &no_planes());
        assert_eq!(d.owner, vec![0, 0, 1, 1]);
        d.owner = vec![0, 1, 0, 1];
        assert!(d.validate().is_err());
        d.owner = vec![0, 0, 0, 0];
        assert!(d.validate().is_err(), "worker 1 owns nothing");
        d.owner = vec![1, 1, 0, 0];
        assert_eq!(d.validate(), Ok(()));
    }

    mod props {
        use super::*;
        use proptest::prelude::*;

        fn region() -> impl Strategy<Value = Region> {
            (
                prop::array::uniform3(-100.0f64..100.0),
                prop::array::uniform3(0.5f64..50.0),
            )
                .prop_map(|(lo, ext)| Region {
                    lo,
                    hi: [0, 1, 2].map(|a| lo[a] + ext[a]),
                })
        }

        /// A box in unit coordinates of the root: corner, extent, flat axes, cost.
        type UnitBox = ([f64; 3], [f64; 3], [bool; 3], f64);

        fn boxes() -> impl Strategy<Value = Vec<UnitBox>> {
            prop::collection::vec(
                (
                    prop::array::uniform3(-0.2f64..1.0),
                    prop::array::uniform3(0.0f64..0.8),
                    prop::array::uniform3(prop::bool::weighted(0.1)),
                    prop_oneof![8 => 0.0f64..100.0, 1 => Just(f64::NAN), 1 => Just(0.0)],
                ),
                0..40,
            )
        }

        fn place(r: &Region, b: &[UnitBox]) -> Vec<CostBox> {
            b.iter()
                .map(|(u, e, flat, c)| {
                    let at = |a: usize, t: f64| r.lo[a] + t * (r.hi[a] - r.lo[a]);
                    CostBox {
                        region: Region {
                            lo: [0, 1, 2].map(|a| at(a, u[a])),
                            hi: [0, 1, 2].map(|a| at(a, if flat[a] { u[a] } else { u[a] + e[a] })),
                        },
                        cost: *c,
                    }
                })
                .collect()
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(200))]

            #[test]
            fn partitions_and_orders(
                r in region(),
                b in boxes(),
                workers in 1usize..=16,
                per in 1usize..=3,
                planes in prop::collection::vec((0usize..3, 0.0f64..1.0), 0..30),
                points in prop::collection::vec(prop::array::uniform3(0.0f64..1.0), 20),
                eyes in prop::collection::vec(prop::array::uniform3(-1.0f64..2.0), 4),
            ) {
                let boxes = place(&r, &b);
                let mut pl: [Vec<f64>; 3] = [vec![], vec![], vec![]];
                for (a, t) in planes {
                    pl[a].push(r.lo[a] + t * (r.hi[a] - r.lo[a]));
                }
                let d = Decomposition::balanced(r, &boxes, workers, per, &pl);
                // The cost inside the root, computed independently.
                let total: f64 = boxes
                    .iter()
                    .filter(|b| b.cost > 0.0)
                    .filter_map(|b| clip_box(b, &r))
                    .map(|b| b.cost)
                    .sum();
                check(&d, &r, workers, per, total);
                let at = |p: [f64; 3]| [0, 1, 2].map(|a| r.lo[a] + p[a] * (r.hi[a] - r.lo[a]));
                for p in points {
                    in_exactly_one(&d, at(p));
                }
                // Split planes are themselves points of exactly one leaf.
                for l in &d.tree.leaves {
                    in_exactly_one(&d, l.lo);
                }
                for e in eyes {
                    contiguous(&d, at(e));
                }
            }

            /// A box's parts found down the tree are its fractions in every leaf, each
            /// leaf once (boxes across planes, flat on them, partly or wholly outside the
            /// root, with NaN costs).
            #[test]
            fn a_box_meets_exactly_the_leaves_it_overlaps(
                r in region(),
                b in boxes(),
                probes in boxes(),
                workers in 1usize..=16,
                per in 1usize..=3,
            ) {
                let d = Decomposition::balanced(r, &place(&r, &b), workers, per, &no_planes());
                for p in place(&r, &probes) {
                    let mut found = vec![0.0; d.tree.leaves.len()];
                    let mut seen = vec![0; d.tree.leaves.len()];
                    d.tree.parts(&p, |l, f| {
                        found[l] = f;
                        seen[l] += 1;
                    });
                    for (l, leaf) in d.tree.leaves.iter().enumerate() {
                        prop_assert_eq!(found[l], p.fraction_in(leaf), "leaf {} of {:?}", l, p);
                        prop_assert!(seen[l] <= 1);
                    }
                }
            }

            /// A node's boxes split to its sides are `clip_box` on each side, box for box.
            #[test]
            fn split_boxes_is_clip_box_on_each_side(
                r in region(),
                b in boxes(),
                axis in 0usize..3,
                t in 0.0f64..1.0,
            ) {
                let boxes = place(&r, &b);
                let (lo, hi) = r.split(axis, r.lo[axis] + t * (r.hi[axis] - r.lo[axis]));
                let want = (
                    boxes.iter().filter_map(|b| clip_box(b, &lo)).collect::<Vec<_>>(),
                    boxes.iter().filter_map(|b| clip_box(b, &hi)).collect::<Vec<_>>(),
                );
                prop_assert_eq!(split_boxes(boxes, &lo, &hi), want);
            }

            /// The split's bisection over the boxes that still matter lands where one over
            /// all of them, `cost_below` at every step, does (the same cost below it).
            #[test]
            fn pruned_bisection_finds_the_plain_ones_balance(
                r in region(),
                b in boxes(),
                axis in 0usize..3,
                target in 0.0f64..1.0,
            ) {
                let boxes: Vec<CostBox> = place(&r, &b)
                    .into_iter()
                    .filter_map(|mut b| {
                        if !(b.cost >= 0.0) {
                            b.cost = 0.0; // as `balanced` hands them over
                        }
                        clip_box(&b, &r).or(Some(CostBox { cost: 0.0, ..b }))
                    })
                    .collect();
                let (lo, hi) = (r.lo[axis], r.hi[axis]);
                let total: f64 = boxes.iter().map(|b| b.cost).sum();
                let want = target * total;
                let plain = {
                    let (mut a, mut b) = (lo, hi);
                    for _ in 0..200 {
                        let mid = 0.5 * (a + b);
                        if !(mid > a && mid < b) {
                            break;
                        }
                        if cost_below(&boxes, axis, mid) >= want {
                            b = mid;
                        } else {
                            a = mid;
                        }
                    }
                    let (ca, cb) = (cost_below(&boxes, axis, a), cost_below(&boxes, axis, b));
                    if want - ca < cb - want { a } else { b }
                };
                let pruned = balanced_position(&boxes, axis, lo, hi, want);
                prop_assert!(pruned >= lo && pruned <= hi);
                let (cp, cq) = (cost_below(&boxes, axis, plain), cost_below(&boxes, axis, pruned));
                prop_assert!(
                    (cp - cq).abs() <= 1e-9 * total.max(1.0),
                    "{} (cost below {}) against {} ({})", pruned, cq, plain, cp
                );
            }

            #[test]
            fn uniform_density_is_balanced(
                r in region(),
                n in prop::array::uniform3(1usize..6),
                workers in 1usize..=16,
                per in 1usize..=3,
            ) {
                let boxes = grid(&r, n, 1.0);
                let d = Decomposition::balanced(r, &boxes, workers, per, &no_planes());
                let total = (n[0] * n[1] * n[2]) as f64;
                check(&d, &r, workers, per, total);
                prop_assert!(d.imbalance() < 1.05, "imbalance {}", d.imbalance());
            }
        }
    }
}
