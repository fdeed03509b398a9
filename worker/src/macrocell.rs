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
                }
            }
        }
    }

    /// Classifies the cells of `slot`: `visible(min, max)` says whether a value range may
    /// show (it is not asked about cells with no valid value, which never show).
    pub fn classify(&mut self, slot: u32, visible: impl Fn(f32, f32) -> bool) {
        let first = slot as usize * self.per_slot();
        for i in first..first + self.per_slot() {
            let [lo, hi] = self.range[i];
            self.visible[i] = (lo <= hi && visible(lo, hi)) as u8;
        }
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
                    if h % 97 == 0 {
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
}
