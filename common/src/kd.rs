//! Axis-aligned regions of space, k-d trees over them, and their visibility order.
//!
//! Regions are half-open boxes `[lo, hi)` in world coordinates (f64). Sibling regions share
//! their split plane exactly, which is what lets ray casters clip rays to half-open `t`
//! intervals that neither overlap nor leave gaps (see the worker's lattice sampling).

use serde::{Deserialize, Serialize};

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

#[cfg(test)]
mod tests {
    use super::*;

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
}
