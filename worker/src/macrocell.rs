//! Macrocells: empty-space skipping finer than a brick.
//!
//! Each atlas slot of the CPU pool is cut into cubes of [`CELL`]³ samples (in the slot's own
//! page coordinates, border included). When a page enters the slot, the value range of every
//! cell is computed, and the cell is classified against its volume's transfer function: a
//! cell is *invisible* when no value in its range maps to a non-zero opacity. The march
//! jumps over invisible cells exactly as it jumps over transparent bricks.
//!
//! **Why the skip is exact.** A trilinear sample at page coordinate `x` reads the samples
//! `⌊x⌋` and `⌊x⌋ + 1`; for `x` in cell `c` (`Nc ≤ x < Nc + N`, `N` = [`CELL`]) those lie in
//! `Nc ..= Nc + N`. The range of a cell is taken over `Nc − 1 ..= Nc + N + 1` (clamped to
//! the page): one sample of margin on each side, so that a sample whose computed cell exit
//! lands a rounding error too late is still covered. A trilinear value lies within the range of its taps, and the
//! transfer function's [`max_alpha`](strata_common::tf::TransferFunction::max_alpha) bounds
//! every value of a range, interpolation between table entries included. NaN samples (no
//! data) are transparent in the march and are left out of the range.
//!
//! **Runs of invisible cells in one jump.** For each invisible cell and each of the eight
//! octants of ray direction, [`reach`](MacroCells::reach) holds the side `R` of the largest
//! cube of invisible cells that has the cell at its corner and extends in that octant's
//! directions (clipped to the slot). A ray in that octant that is in the cell is in the
//! cube until it leaves it, so the march jumps to the cube's exit at once instead of cell
//! by cell. Every lattice point it passes lies in an invisible cell, margin included, so
//! the image is the same.

/// Samples per macrocell edge. 16 rather than 8: on the bonsai (64³ pages) 8³ cells skip
/// more lattice points (76 % against 66 %) but the extra cell exits cost more than the
/// samples they save (docs/BENCHMARKS.md).
pub const CELL: usize = 16;

/// Value ranges and visibility of the macrocells of every slot of a pool.
#[derive(Debug)]
pub struct MacroCells {
    /// Samples per page edge.
    page: usize,
    /// Cells per page edge.
    per_axis: usize,
    /// `[min, max]` per cell, slot after slot (min > max: no valid value).
    range: Vec<[f32; 2]>,
    /// 1 where some value of the cell may be visible, slot after slot.
    visible: Vec<u8>,
    /// Per cell and octant (bit 0: x descending, bit 1: y, bit 2: z), the side of the
    /// largest cube of invisible cells with the cell at its corner extending in the octant's
    /// directions, clipped to the slot; 0 for a visible cell.
    reach: Vec<[u8; 8]>,
}

impl MacroCells {
    /// Cells for `slots` slots of `page`³ samples.
    pub fn new(page: usize, slots: usize) -> Self {
        assert!(page >= 2, "a page has at least two samples per edge");
        let per_axis = (page - 1).div_ceil(CELL);
        let n = per_axis.pow(3) * slots;
        MacroCells {
            page,
            per_axis,
            range: vec![[f32::INFINITY, f32::NEG_INFINITY]; n],
            visible: vec![1; n],
            reach: vec![[0; 8]; n],
        }
    }

    /// Cells per page edge.
    #[inline(always)]
    pub fn per_axis(&self) -> usize {
        self.per_axis
    }

    /// Cells per slot.
    #[inline(always)]
    pub fn per_slot(&self) -> usize {
        self.per_axis * self.per_axis * self.per_axis
    }

    /// The visibility flags of every slot (index `slot · per_slot + cell`).
    #[inline(always)]
    pub fn visible(&self) -> &[u8] {
        &self.visible
    }

    /// Computes the value range of every cell of `slot` from its page (`value(i)` is sample
    /// `i`, x fastest) and marks every cell visible until [`classify`](Self::classify).
    pub fn compute(&mut self, slot: u32, value: impl Fn(usize) -> f32) {
        let p = self.page;
        let n = self.per_axis;
        // Separable: min/max over each x-run of a cell's footprint first, then over y, then z.
        // `span(c)` is the sample range cell `c` covers along one axis, margin included.
        let span = |c: usize| (c * CELL).saturating_sub(1)..(c * CELL + CELL + 2).min(p);
        let mut rows = vec![[f32::INFINITY, f32::NEG_INFINITY]; n * p * p];
        for z in 0..p {
            for y in 0..p {
                let base = (z * p + y) * p;
                for cx in 0..n {
                    let mut r = [f32::INFINITY, f32::NEG_INFINITY];
                    for x in span(cx) {
                        let v = value(base + x);
                        // NaN fails both comparisons and stays out of the range.
                        if v < r[0] {
                            r[0] = v;
                        }
                        if v > r[1] {
                            r[1] = v;
                        }
                    }
                    rows[(z * p + y) * n + cx] = r;
                }
            }
        }
        let first = slot as usize * self.per_slot();
        for cz in 0..n {
            for cy in 0..n {
                for cx in 0..n {
                    let mut r = [f32::INFINITY, f32::NEG_INFINITY];
                    for z in span(cz) {
                        for y in span(cy) {
                            let q = rows[(z * p + y) * n + cx];
                            r[0] = r[0].min(q[0]);
                            r[1] = r[1].max(q[1]);
                        }
                    }
                    let i = first + (cz * n + cy) * n + cx;
                    self.range[i] = r;
                    self.visible[i] = 1;
                    self.reach[i] = [0; 8];
                }
            }
        }
    }

    /// Per cell and octant, the side of the largest cube of invisible cells starting at it
    /// (index `slot · per_slot + cell`, see the module's notes).
    #[inline(always)]
    pub fn reach(&self) -> &[[u8; 8]] {
        &self.reach
    }

    /// Classifies the cells of `slot`: `visible(min, max)` says whether a value range may
    /// show (it is not asked about cells with no valid value, which never show).
    pub fn classify(&mut self, slot: u32, visible: impl Fn(f32, f32) -> bool) {
        let first = slot as usize * self.per_slot();
        for i in first..first + self.per_slot() {
            let [lo, hi] = self.range[i];
            self.visible[i] = (lo <= hi && visible(lo, hi)) as u8;
        }
        self.compute_reach(slot);
    }

    /// The cubes of invisible cells of `slot` ([`reach`](Self::reach)).
    fn compute_reach(&mut self, slot: u32) {
        let n = self.per_axis;
        let first = slot as usize * self.per_slot();
        let last = first + self.per_slot();
        let visible = &self.visible[first..last];
        empty_cubes([n; 3], |i| visible[i] == 0, &mut self.reach[first..last]);
    }

    /// Invisible cells of `slot` (for statistics).
    pub fn invisible_in(&self, slot: u32) -> usize {
        let first = slot as usize * self.per_slot();
        self.visible[first..first + self.per_slot()]
            .iter()
            .filter(|&&v| v == 0)
            .count()
    }
}

/// For a grid of `dims` cells (x fastest) of which `empty(i)` are empty, writes to `out`
/// per cell and octant of direction (bit `a` set: descending along axis `a`) the side of
/// the largest cube of empty cells that has the cell at its corner and extends in the
/// octant's directions, clipped to the grid (capped at 255, which is safe: a smaller cube
/// is all empty too); 0 for a cell that is not empty.
///
/// Per octant, from the far corner back: `R(c) = 1 + min R` over the cell's seven forward
/// neighbours, a neighbour outside the grid counting as unbounded (the cube is clipped to
/// the grid where it is used), as the largest-square recurrence in three dimensions.
pub fn empty_cubes(dims: [usize; 3], empty: impl Fn(usize) -> bool, out: &mut [[u8; 8]]) {
    assert_eq!(out.len(), dims.iter().product::<usize>());
    let cap = dims.into_iter().max().unwrap_or(0).min(255) as u8;
    let at = |c: [usize; 3]| (c[2] * dims[1] + c[1]) * dims[0] + c[0];
    for oct in 0..8 {
        let back = [oct & 1 != 0, oct & 2 != 0, oct & 4 != 0];
        // Visit every cell after its forward neighbours.
        let order = |a: usize, i: usize| if back[a] { i } else { dims[a] - 1 - i };
        for iz in 0..dims[2] {
            for iy in 0..dims[1] {
                for ix in 0..dims[0] {
                    let c = [order(0, ix), order(1, iy), order(2, iz)];
                    let i = at(c);
                    if !empty(i) {
                        out[i][oct] = 0;
                        continue;
                    }
                    let mut m = u8::MAX;
                    for nb in 1..8usize {
                        let mut q = c;
                        let mut inside = true;
                        for a in 0..3 {
                            if nb >> a & 1 == 1 {
                                if back[a] {
                                    inside &= q[a] > 0;
                                    q[a] = q[a].wrapping_sub(1);
                                } else {
                                    inside &= q[a] + 1 < dims[a];
                                    q[a] += 1;
                                }
                            }
                        }
                        if inside {
                            m = m.min(out[at(q)][oct]);
                        }
                    }
                    out[i][oct] = m.saturating_add(1).min(cap);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The range of every cell equals a brute-force min/max over its footprint with margin.
    #[test]
    fn ranges_match_brute_force() {
        for p in [10usize, 17, 34] {
            let data: Vec<f32> = (0..p * p * p)
                .map(|i| {
                    let h = (i as u32).wrapping_mul(2654435761) >> 8;
                    if h.is_multiple_of(97) {
                        f32::NAN
                    } else {
                        (h % 1000) as f32 - 500.0
                    }
                })
                .collect();
            let mut mc = MacroCells::new(p, 2);
            mc.compute(1, |i| data[i]);
            let n = mc.per_axis();
            assert_eq!(n, (p - 1).div_ceil(CELL));
            for cz in 0..n {
                for cy in 0..n {
                    for cx in 0..n {
                        let mut r = [f32::INFINITY, f32::NEG_INFINITY];
                        let lo = |c: usize| (c * CELL).saturating_sub(1);
                        let hi = |c: usize| (c * CELL + CELL + 1).min(p - 1);
                        for z in lo(cz)..=hi(cz) {
                            for y in lo(cy)..=hi(cy) {
                                for x in lo(cx)..=hi(cx) {
                                    let v = data[(z * p + y) * p + x];
                                    if !v.is_nan() {
                                        r[0] = r[0].min(v);
                                        r[1] = r[1].max(v);
                                    }
                                }
                            }
                        }
                        let i = mc.per_slot() + (cz * n + cy) * n + cx;
                        assert_eq!(mc.range[i], r, "page {p}, cell {cx} {cy} {cz}");
                    }
                }
            }
            // Slot 0 was never computed: no valid value, so never visible.
            mc.classify(0, |_, _| true);
            assert_eq!(mc.invisible_in(0), mc.per_slot());
            mc.classify(1, |lo, _| lo > 400.0);
            assert!(mc.invisible_in(1) > 0);
        }
    }

    /// Every cell's cube of invisible cells, per octant, holds only invisible cells of the
    /// slot, and one cell more on each side would take in a visible one (unless the cube
    /// already reaches the slot's far faces), against a brute-force search, for random
    /// visibility patterns at several densities.
    #[test]
    fn reach_is_the_largest_invisible_cube_per_octant() {
        let p = 64;
        let mut mc = MacroCells::new(p, 2);
        let n = mc.per_axis();
        let ps = mc.per_slot();
        let mut jumps = 0;
        for seed in 0..200u32 {
            let slot = seed % 2;
            // Visible fractions from 0 to about 60 %.
            let dense = seed % 7;
            for i in 0..ps {
                let h = (i as u32 ^ seed.wrapping_mul(0x9e37_79b9)).wrapping_mul(2654435761) >> 7;
                let visible = h % 10 < dense;
                mc.range[slot as usize * ps + i] = if visible { [1.0, 1.0] } else { [0.0, 0.0] };
            }
            mc.classify(slot, |_, hi| hi > 0.5);
            let vis = |c: [isize; 3]| {
                let i =
                    slot as usize * ps + ((c[2] * n as isize + c[1]) * n as isize + c[0]) as usize;
                mc.visible[i] != 0
            };
            // The cells of the cube of `side` from `c` in octant `oct`, clipped to the slot.
            let cube = |c: [usize; 3], oct: usize, side: usize| {
                let mut cells = Vec::new();
                for dz in 0..side as isize {
                    for dy in 0..side as isize {
                        for dx in 0..side as isize {
                            let d = [dx, dy, dz];
                            let q: [isize; 3] = std::array::from_fn(|a| {
                                c[a] as isize + if oct >> a & 1 == 1 { -d[a] } else { d[a] }
                            });
                            if q.iter().all(|&x| (0..n as isize).contains(&x)) {
                                cells.push(q);
                            }
                        }
                    }
                }
                cells
            };
            for cz in 0..n {
                for cy in 0..n {
                    for cx in 0..n {
                        let c = [cx, cy, cz];
                        let i = slot as usize * ps + (cz * n + cy) * n + cx;
                        for oct in 0..8 {
                            let r = mc.reach()[i][oct] as usize;
                            if mc.visible[i] != 0 {
                                assert_eq!(r, 0);
                                continue;
                            }
                            assert!((1..=n).contains(&r), "seed {seed}: reach {r}");
                            assert!(cube(c, oct, r).into_iter().all(|q| !vis(q)), "seed {seed}");
                            let bigger = cube(c, oct, r + 1);
                            if r < n && bigger.len() > cube(c, oct, r).len() {
                                assert!(bigger.into_iter().any(vis), "seed {seed}: not largest");
                            }
                            jumps += (r > 1) as u32;
                        }
                    }
                }
            }
        }
        assert!(jumps > 1000, "too few cubes of more than one cell: {jumps}");
    }
}
