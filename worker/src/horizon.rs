//! Stacked-horizon intersection: a min-max quadtree over tiles and exact ray/bilinear-patch
//! intersection per cell.
//!
//! The quadtree is the horizon's own page tree: every tile's `[min, max]` in the store index
//! bounds its heights, its border and all its descendants, so it is known for every tile
//! without loading one. A ray descends front to back into tiles whose box (lateral footprint
//! × height range) it crosses, down to the tile level its footprint calls for (or finer,
//! where that level's tile is resident and fragmented by holes: `ENTRY_FRAGMENTED`), and then
//! walks that tile's cells (of the finest resident level) with a 2D DDA. In each cell the
//! height is the bilinear patch through its four nodes, so `ray_z(t) − H(u(t), v(t))` is a
//! quadratic in `t`: solving it exactly finds every crossing, even two within one cell
//! (a grazing ray). A cell with any hole among its four nodes never produces a hit, so holes
//! neither hit nor leave cracks between valid cells (valid neighbours share edge heights).

use crate::atlas::{entry_level, PageTable, Pool, ENTRY_FRAGMENTED, NOT_RESIDENT, SLOT_MASK};
use strata_common::pyramid::Pyramid;
use strata_common::tf::ColorMap;

/// A horizon prepared for one frame.
pub struct HorFrame<'a> {
    /// Data-set number.
    pub ds: u16,
    /// Camera-relative → index (i, j, height), linear part.
    pub m: [[f32; 3]; 3],
    /// Offset.
    pub c: [f32; 3],
    /// Level-0 node counts (i, j).
    pub dims: [u32; 2],
    /// `level_t[l]`: distance from which level `l` is fine enough.
    pub level_t: Vec<f32>,
    /// Core nodes per tile axis.
    pub core: u32,
    /// Border nodes.
    pub border: u32,
    /// Nodes per tile axis.
    pub page: usize,
    /// Page table.
    pub table: &'a PageTable,
    /// Atlas pool.
    pub pool: &'a Pool,
    /// `[min, max]` per tile (page-table order).
    pub bounds: &'a [[f32; 2]],
    /// The tile tree's boxes ([`tile_boxes`] of `bounds`).
    pub boxes: &'a [TileBox],
    /// Straight linear RGB.
    pub color: [f32; 3],
    /// Colour by height.
    pub depth_map: Option<(&'a ColorMap, [f32; 2])>,
    /// Colour by a volume's value: the volume (index into the frame's volumes) and the
    /// no-data colour. Its hits are shaded white; the caster multiplies in the colour.
    pub attribute: Option<(usize, [f32; 3])>,
    /// Opacity.
    pub opacity: f32,
    /// Lambert shading.
    pub lighting: bool,
    /// The pyramid (for page keys).
    pub pyramid: &'a Pyramid,
}

/// A surface crossing.
#[derive(Copy, Clone, Debug, PartialEq)]
pub struct Hit {
    /// Ray parameter.
    pub t: f32,
    /// Premultiplied shaded colour.
    pub rgba: [f32; 4],
}

/// How far past its cell's exit a crossing is still taken from that cell, relative to its
/// `t` (eight ulps): a crossing on the edge between two cells is solved in each of them
/// relative to a different origin, and the two `t` differ by a rounding. Each cell testing
/// its own `t` against the shared edge could keep such a crossing twice, or (the two
/// roundings the other way round) lose it, a pinhole in an opaque surface. Instead the
/// first cell keeps it up to this far past the edge, and the next one drops a crossing this
/// close to the last one kept ([`Search::last`]).
const EDGE_REL: f32 = 1.0 / (1 << 20) as f32;

/// [`EDGE_REL`] at `t`.
#[inline(always)]
fn edge_tol(t: f32) -> f32 {
    t.abs() * EDGE_REL
}

/// The state of one ray's search of one horizon.
struct Search {
    /// Nothing at or beyond this `t` is visible: the end of the interval, or the nearest
    /// opaque crossing found.
    limit: f32,
    /// The last crossing kept (NaN before the first).
    last: f32,
    /// Padding of tile heights past the rounding of heights relative to the eye
    /// ([`HorFrame::z_pad`]).
    z_pad: f32,
}

/// `a.min(b)` for numbers that are not NaN, without `f32::min`'s NaN handling (one
/// instruction instead of four on x86; equal results when neither is NaN).
#[inline(always)]
fn fmin(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// `a.max(b)` for numbers that are not NaN (see [`fmin`]).
#[inline(always)]
fn fmax(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// [`slab`] with `inv = 1 / d` precomputed (multiplications instead of divisions; the
/// result may differ from `slab`'s by a rounding).
#[inline(always)]
fn slab_inv(c: [f32; 3], d: [f32; 3], inv: [f32; 3], lo: [f32; 3], hi: [f32; 3]) -> (f32, f32) {
    slab_by(c, d, lo, hi, |x, a| x * inv[a])
}

/// `[t0, t1]` of the ray `c + t·d` in the box `[lo, hi]` (empty when `t0 > t1`). The box
/// and the ray are finite (bounds of tiles with no valid height are never tested).
#[inline(always)]
fn slab(c: [f32; 3], d: [f32; 3], lo: [f32; 3], hi: [f32; 3]) -> (f32, f32) {
    slab_by(c, d, lo, hi, |x, a| x / d[a])
}

/// The slab test with `per_d(x, a)` = `x / d[a]`, however computed.
#[inline(always)]
fn slab_by(
    c: [f32; 3],
    d: [f32; 3],
    lo: [f32; 3],
    hi: [f32; 3],
    per_d: impl Fn(f32, usize) -> f32,
) -> (f32, f32) {
    let mut t0 = f32::NEG_INFINITY;
    let mut t1 = f32::INFINITY;
    for a in 0..3 {
        if d[a] == 0.0 {
            if !(lo[a] <= c[a] && c[a] <= hi[a]) {
                return (1.0, 0.0);
            }
        } else {
            let ta = per_d(lo[a] - c[a], a);
            let tb = per_d(hi[a] - c[a], a);
            t0 = fmax(t0, fmin(ta, tb));
            t1 = fmin(t1, fmax(ta, tb));
        }
    }
    (t0, t1)
}

/// Real roots of `a s² + b s + c = 0` in `[lo, hi)`, ascending.
fn roots_in(a: f32, b: f32, c: f32, lo: f32, hi: f32, out: &mut [f32; 2]) -> usize {
    let mut n = 0;
    let mut push = |s: f32, out: &mut [f32; 2]| {
        if s.is_finite() && s >= lo && s < hi {
            out[n] = s;
            n += 1;
        }
    };
    // Linear only when it is: the stable pair below is exact however small `a` is against
    // `b` (its far root `q/a` overflows or falls out of range), while dropping a small `a`
    // drops `a·s²`, which over a long step (a nearly vertical ray crossing a twisted cell)
    // is not small.
    if a == 0.0 {
        if b != 0.0 {
            push(-c / b, out);
        }
    } else {
        let disc = b * b - 4.0 * a * c;
        if disc < 0.0 {
            return 0;
        }
        // The numerically stable pair (no cancellation between b and the root).
        let q = -0.5 * (b + b.signum() * disc.sqrt());
        let (s1, s2) = if q != 0.0 {
            (q / a, c / q)
        } else if c == 0.0 {
            (0.0, 0.0)
        } else {
            return 0; // b = 0 and a·c underflowed: roots ±√(−c/a), far out of any cell
        };
        let (s1, s2) = if s1 <= s2 { (s1, s2) } else { (s2, s1) };
        push(s1, out);
        if s2 != s1 {
            push(s2, out);
        }
    }
    n
}

/// Lateral footprint of tile `b` at `level` (tiles of `core` nodes) in level-0 node
/// coordinates: `[b·core·2^level, (b + 1)·core·2^level)` per axis.
///
/// The same expression at every level, so a tile's footprint is exactly the union of its
/// four children's: where neighbouring tiles are drawn at different levels, the surface
/// has neither a gap nor a strip drawn twice between them. (Level-`l` node `n` lies at
/// level-0 position `(n + ½)·2^l − ½`, so a footprint bounded by the tile's own nodes, the
/// cells whose lower node lies in its core, is shifted by `2^l/4 − ¼` against its children's
/// and leaves half a child cell uncovered on one side and covered twice on the other.) At
/// level 0 these are the cells whose lower node lies in the tile's core; at a coarser level
/// the footprint cuts the tile's first and last cells, whose outer nodes are the tile's
/// border (one node suffices).
#[inline(always)]
fn footprint(core: u32, level: usize, b: [u32; 3]) -> ([f32; 2], [f32; 2]) {
    let w = core as f32 * (1u64 << level) as f32;
    let at = |i: u32| i as f32 * w;
    ([at(b[0]), at(b[1])], [at(b[0] + 1), at(b[1] + 1)])
}

/// What the tile-tree descent tests at a tile, computed once per horizon (it depends on the
/// tile's index and height bounds only): the padded box and where its children meet.
#[derive(Copy, Clone, Debug, Default, PartialEq)]
pub struct TileBox {
    /// Lower corner: the footprint padded by one cell of the tile's level, `zmin − eps`.
    pub lo: [f32; 3],
    /// Upper corner.
    pub hi: [f32; 3],
    /// Where the four children meet (the lower corner of child (1, 1)); unused at level 0.
    pub split: [f32; 2],
}

/// The [`TileBox`] of every tile of a horizon's tree, in page-table order (`bounds` is the
/// store's `[min, max]` per tile; all-hole tiles get a default box and are never tested).
pub fn tile_boxes(pyramid: &Pyramid, bounds: &[[f32; 2]]) -> Vec<TileBox> {
    let table = PageTable::new(pyramid);
    let core = pyramid.core();
    let mut out = vec![TileBox::default(); table.entries.len()];
    for (level, li) in table.levels.iter().enumerate() {
        for y in 0..li.bricks[1] {
            for x in 0..li.bricks[0] {
                let b = [x, y, 0];
                let i = table.index(level, b);
                let Some(&[zmin, zmax]) = bounds.get(i) else {
                    continue;
                };
                if !(zmin <= zmax) {
                    continue;
                }
                let s = (1u64 << level) as f32;
                let (flo, fhi) = footprint(core, level, b);
                // Pad by one cell of this level, so that no rounding of this slab test
                // culls a ray the leaf's exact clip keeps (the level-of-detail choice reads
                // this padded box's entry). A flat tile has zmin == zmax: give the box a
                // little thickness so the slab test cannot lose it to rounding.
                let eps = 1e-4 * (1.0 + zmin.abs().max(zmax.abs()));
                let split = if level > 0 {
                    footprint(core, level - 1, [2 * x + 1, 2 * y + 1, 0]).0
                } else {
                    [0.0; 2]
                };
                out[i] = TileBox {
                    lo: [flo[0] - s, flo[1] - s, zmin - eps],
                    hi: [fhi[0] + s, fhi[1] + s, zmax + eps],
                    split,
                };
            }
        }
    }
    out
}

impl<'a> HorFrame<'a> {
    /// Index-space direction of a camera-relative ray direction.
    #[inline]
    pub fn index_dir(&self, d: [f32; 3]) -> [f32; 3] {
        let m = &self.m;
        [
            m[0][0] * d[0] + m[0][1] * d[1] + m[0][2] * d[2],
            m[1][0] * d[0] + m[1][1] * d[1] + m[1][2] * d[2],
            m[2][0] * d[0] + m[2][1] * d[1] + m[2][2] * d[2],
        ]
    }

    /// 8 ulps of the eye's height in index space: heights relative to the eye round by
    /// up to half an ulp of it, so tile boxes and clips padded by this keep a thickness in t
    /// however far the eye is (a flat tile seen from far above had a slab of none).
    #[inline]
    fn z_pad(&self) -> f32 {
        self.c[2].abs() * (1.0 / 1_048_576.0)
    }

    fn level_at(&self, t: f32) -> usize {
        let mut l = 0;
        while l + 1 < self.level_t.len() && t >= self.level_t[l + 1] {
            l += 1;
        }
        l
    }

    /// Lateral footprint of tile `b` at `level` in level-0 node coordinates (the free
    /// function [`footprint`]).
    #[inline(always)]
    fn footprint(&self, level: usize, b: [u32; 3]) -> ([f32; 2], [f32; 2]) {
        footprint(self.core, level, b)
    }

    /// All crossings of the ray `p(t) = t·d` with `t` in `[ta, tb)`, appended to `hits`
    /// unsorted; requested tiles go to `feedback`. Returns the `t` beyond which nothing is
    /// visible any more: the nearest opaque crossing found, or `tb` (callers pass it on as
    /// the next surface's `tb`, so a surface hidden behind an opaque one is not searched).
    pub fn intersect(
        &self,
        d: [f32; 3],
        ta: f32,
        tb: f32,
        hits: &mut Vec<Hit>,
        feedback: &mut crate::feedback::Requests,
    ) -> f32 {
        self.intersect_with::<true>(d, ta, tb, hits, feedback)
    }

    /// [`intersect`](Self::intersect) compiled with (`LIT`) or without the lighting code;
    /// without it, hits take the unlit colour whatever [`lighting`](Self::lighting) says.
    pub fn intersect_with<const LIT: bool>(
        &self,
        d: [f32; 3],
        ta: f32,
        tb: f32,
        hits: &mut Vec<Hit>,
        feedback: &mut crate::feedback::Requests,
    ) -> f32 {
        let md = self.index_dir(d);
        let top = self.pyramid.level_count() - 1;
        let mut search = Search {
            limit: tb,
            last: f32::NAN,
            z_pad: self.z_pad(),
        };
        let inv = md.map(|m| 1.0 / m);
        // Every crossing is kept, however many (the GPU caster searches again in batches).
        self.visit::<LIT>(top, [0, 0, 0], d, md, inv, ta, &mut search, hits, feedback);
        search.limit
    }

    #[allow(clippy::too_many_arguments)]
    fn visit<const LIT: bool>(
        &self,
        level: usize,
        b: [u32; 3],
        d: [f32; 3],
        md: [f32; 3],
        inv: [f32; 3],
        ta: f32,
        search: &mut Search,
        hits: &mut Vec<Hit>,
        feedback: &mut crate::feedback::Requests,
    ) {
        let idx = self.table.index(level, b);
        let [zmin, zmax] = self.bounds[idx];
        if !(zmin <= zmax) {
            return; // all holes
        }
        let tb = &self.boxes[idx];
        // The box's heights padded past the rounding of heights relative to the eye too
        // (as the leaf's clip): the leaf's crossing, computed otherwise, then lies inside
        // the slab whatever the eye's height, and a region face between the two cannot
        // lose it to both regions.
        let (mut lo, mut hi) = (tb.lo, tb.hi);
        lo[2] -= search.z_pad;
        hi[2] += search.z_pad;
        let (e0, e1) = slab_inv(self.c, md, inv, lo, hi);
        // Strict: a flat tile's box seen from far away has a slab of no thickness in t
        // (its padding below the rounding of the eye's height), which must not cull it.
        if fmax(e0, ta) > fmin(e1, search.limit) || e1 < 0.0 {
            return;
        }
        // The LOD decision uses the unclipped entry, so it does not depend on the region.
        let want = self.level_at(e0.max(0.0));
        if level == 0 || level <= want {
            feedback.push(self.pyramid.id(level, b).with_dataset(self.ds).0);
            // A tile whose own cells are mostly holes is not drawn at its level: its
            // children are (it stays requested, so that its flag stays known).
            if level == 0 || self.table.entries[idx] & ENTRY_FRAGMENTED == 0 {
                self.leaf::<LIT>(level, b, d, md, ta, search, hits);
                return;
            }
        }
        // Children front to back, ordered by where the ray crosses the two split lines
        // (two divisions instead of a slab per child; the order only decides how soon an
        // opaque crossing prunes the rest, never which crossings are found).
        let lb = &self.table.levels[level - 1].bricks;
        let split = tb.split;
        let crossing = |a: usize| {
            if md[a] == 0.0 {
                f32::INFINITY
            } else {
                (split[a] - self.c[a]) / md[a]
            }
        };
        let cross = [crossing(0), crossing(1)];
        // The child on the far side of a split line is entered where the ray crosses it.
        let key = |a: usize, half: u32| {
            let far = if md[a] >= 0.0 { half == 1 } else { half == 0 };
            if far {
                cross[a]
            } else {
                f32::NEG_INFINITY
            }
        };
        let mut kids: [(f32, [u32; 3]); 4] = [(f32::INFINITY, [0; 3]); 4];
        let mut n = 0;
        for dy in 0..2 {
            for dx in 0..2 {
                let cb = [2 * b[0] + dx, 2 * b[1] + dy, 0];
                if cb[0] < lb[0] && cb[1] < lb[1] {
                    kids[n] = (fmax(key(0, dx), key(1, dy)), cb);
                    n += 1;
                }
            }
        }
        // Stable insertion sort of at most four (keys are never NaN).
        for i in 1..n {
            let mut j = i;
            while j > 0 && kids[j - 1].0 > kids[j].0 {
                kids.swap(j - 1, j);
                j -= 1;
            }
        }
        for &(_, cb) in &kids[..n] {
            self.visit::<LIT>(level - 1, cb, d, md, inv, ta, search, hits, feedback);
        }
    }

    /// Walks the cells of tile `b` at `level`, using the finest resident data. Not inlined
    /// into `visit`: a ray reaches a leaf on about one visit in fifteen, and inlined, its
    /// locals gave every (recursive) visit a 664-byte frame instead of 136 (the demo frame
    /// 2.5–4 % faster without it).
    #[allow(clippy::too_many_arguments)]
    #[inline(never)]
    fn leaf<const LIT: bool>(
        &self,
        level: usize,
        b: [u32; 3],
        d: [f32; 3],
        md: [f32; 3],
        ta: f32,
        search: &mut Search,
        hits: &mut Vec<Hit>,
    ) {
        let e = self.table.entries[self.table.index(level, b)];
        if e == NOT_RESIDENT {
            return;
        }
        let r = entry_level(e) as usize;
        let data = self.pool.slot_data(e & SLOT_MASK);
        let k = (r - level) as u32;
        let br = [b[0] >> k, b[1] >> k];
        // Clip to this tile's own footprint (exact, not padded), within the data.
        let (mut flo, mut fhi) = self.footprint(level, b);
        for a in 0..2 {
            let last = self.dims[a] as f32 - 1.0;
            // A ray with no motion along this axis is in the tile or not: half-open, so one
            // lying on the edge between two tiles is walked by one of them (the slab test
            // below is closed; tiles drawn at different levels would give two crossings).
            if md[a] == 0.0 && fhi[a] < last && self.c[a] >= fhi[a] {
                return;
            }
            flo[a] = flo[a].max(0.0);
            fhi[a] = fhi[a].min(last);
        }
        // Also clip to the height range of the data used, so steep rays walk few cells.
        let [zmin, zmax] = self.bounds[self.table.index(r, [br[0], br[1], 0])];
        if !(zmin <= zmax) {
            return;
        }
        // Padded past the rounding of heights relative to the eye too: a flat tile far
        // below the eye is otherwise a clip of no thickness, which holds no crossing.
        let eps = 1e-4 * (1.0 + zmin.abs().max(zmax.abs())) + self.z_pad();
        let (u0, u1) = slab(
            self.c,
            md,
            [flo[0], flo[1], zmin - eps],
            [fhi[0], fhi[1], zmax + eps],
        );
        let t_lo = u0.max(ta).max(0.0);
        let t_hi = u1.min(search.limit);
        if t_lo >= t_hi {
            return;
        }
        // Ray in level-r node coordinates.
        let sr = (0.5f32).powi(r as i32);
        let cr = [
            (self.c[0] + 0.5) * sr - 0.5,
            (self.c[1] + 0.5) * sr - 0.5,
            self.c[2],
        ];
        let dr = [md[0] * sr, md[1] * sr, md[2]];
        let nodes_r = [
            self.pyramid.level(r).dims[0] as i64,
            self.pyramid.level(r).dims[1] as i64,
        ];
        let p = self.page as i64;
        let off = [
            br[0] as i64 * self.core as i64 - self.border as i64,
            br[1] as i64 * self.core as i64 - self.border as i64,
        ];
        let at = |i: i64, j: i64| -> f32 {
            let (li, lj) = (i - off[0], j - off[1]);
            if li < 0 || lj < 0 || li >= p || lj >= p {
                return f32::NAN;
            }
            data[(lj * p + li) as usize]
        };
        // 2D DDA over level-r cells.
        let pos = [cr[0] + t_lo * dr[0], cr[1] + t_lo * dr[1]];
        let mut cell = [pos[0].floor() as i64, pos[1].floor() as i64];
        let step = [0, 1].map(|a| if dr[a] > 0.0 { 1i64 } else { -1 });
        let next_t = |a: usize, c: i64| -> f32 {
            if dr[a] == 0.0 {
                f32::INFINITY
            } else {
                let bound = if dr[a] > 0.0 { c + 1 } else { c } as f32;
                (bound - cr[a]) / dr[a]
            }
        };
        let mut t_cell = t_lo;
        let mut guard = 0usize;
        let lighting = LIT && self.lighting;
        // Each axis's exit is recomputed (by the same formula) only when the DDA steps on
        // that axis.
        let mut tx = next_t(0, cell[0]);
        let mut ty = next_t(1, cell[1]);
        while t_cell < t_hi && guard < 1 << 20 {
            guard += 1;
            let t_next = fmin(fmin(tx, ty), t_hi);
            let (i, j) = (cell[0], cell[1]);
            if i >= 0 && j >= 0 && i + 1 < nodes_r[0] && j + 1 < nodes_r[1] && t_next > t_cell {
                let h00 = at(i, j);
                let h10 = at(i + 1, j);
                let h01 = at(i, j + 1);
                let h11 = at(i + 1, j + 1);
                if !(h00.is_nan() || h10.is_nan() || h01.is_nan() || h11.is_nan()) {
                    let z0 = cr[2] + t_cell * dr[2];
                    let z1 = cr[2] + t_next * dr[2];
                    let hmin = fmin(fmin(h00, h10), fmin(h01, h11));
                    let hmax = fmax(fmax(h00, h10), fmax(h01, h11));
                    // A cull only, padded like the height clip above: z0 and z1 come from
                    // region-clipped t, so a crossing on a region's face (a flat horizon in
                    // a split plane) could fall a rounding outside [hmin, hmax] in both
                    // regions and be lost; the exact test is the one on t below.
                    if fmin(z0, z1) <= hmax + eps && fmax(z0, z1) >= hmin - eps {
                        // Solve relative to where the ray enters this cell, a value that
                        // depends only on the cell and the ray, not on where the region
                        // clipped it: the same crossing gets the same t in every region.
                        let entry = |a: usize, c: i64| -> f32 {
                            if dr[a] == 0.0 {
                                f32::NEG_INFINITY
                            } else {
                                let bound = if dr[a] > 0.0 { c } else { c + 1 } as f32;
                                (bound - cr[a]) / dr[a]
                            }
                        };
                        // Never before the ray's origin, which no region moves either: a
                        // vertical ray (no lateral component) enters no cell, and a nearly
                        // vertical one enters its cells far behind the eye, so t = t_org + s
                        // would carry that large t's rounding.
                        let t_org = entry(0, i).max(entry(1, j));
                        let t_org = if t_org.is_finite() {
                            t_org.max(0.0)
                        } else {
                            0.0
                        };
                        let z0 = cr[2] + t_org * dr[2];
                        let u0 = cr[0] + t_org * dr[0] - i as f32;
                        let v0 = cr[1] + t_org * dr[1] - j as f32;
                        let a = h10 - h00;
                        let bb = h01 - h00;
                        let c = h00 - h10 - h01 + h11;
                        let qa = -c * dr[0] * dr[1];
                        let qb = dr[2] - a * dr[0] - bb * dr[1] - c * (u0 * dr[1] + v0 * dr[0]);
                        let qc = z0 - h00 - a * u0 - bb * v0 - c * u0 * v0;
                        // Every root, then one test on the crossing's absolute t. Testing the
                        // root against bounds relative to t_org and then forming t_org + s can
                        // disagree by a rounding: a crossing on a region's face was then
                        // rejected by both regions (or, the other way round, kept by both).
                        // t itself is the same in every region, and so is the face value two
                        // adjacent regions compare it with, so exactly one of them keeps it.
                        let mut roots = [0.0f32; 2];
                        let n = roots_in(qa, qb, qc, f32::NEG_INFINITY, f32::INFINITY, &mut roots);
                        // Crossings of an earlier cell (not this one's: a grazing ray's two).
                        let prev = search.last;
                        let end = t_next + edge_tol(t_next);
                        for &sroot in &roots[..n] {
                            let t = t_org + sroot;
                            if t < t_cell || t >= end || t < ta || t >= search.limit {
                                continue;
                            }
                            if (t - prev).abs() <= edge_tol(t) {
                                continue; // the last cell kept it (see EDGE_REL)
                            }
                            let u = (u0 + sroot * dr[0]).clamp(0.0, 1.0);
                            let v = (v0 + sroot * dr[1]).clamp(0.0, 1.0);
                            let h = h00 + a * u + bb * v + c * u * v;
                            let rgb = self.shade(d, a + c * v, bb + c * u, sr, h, lighting);
                            let al = self.opacity;
                            hits.push(Hit {
                                t,
                                rgba: [rgb[0] * al, rgb[1] * al, rgb[2] * al, al],
                            });
                            search.last = t;
                            if al >= 1.0 {
                                // Nothing behind an opaque surface is visible.
                                search.limit = search.limit.min(t);
                            }
                        }
                    }
                }
            }
            t_cell = t_next;
            if tx <= ty {
                cell[0] += step[0];
                tx = next_t(0, cell[0]);
            } else {
                cell[1] += step[1];
                ty = next_t(1, cell[1]);
            }
        }
    }

    fn shade(&self, d: [f32; 3], hu: f32, hv: f32, sr: f32, h: f32, lighting: bool) -> [f32; 3] {
        let base = match &self.depth_map {
            Some((map, [lo, hi])) => {
                let x = if hi > lo { (h - lo) / (hi - lo) } else { 0.5 };
                map.at(x)
            }
            None => self.color,
        };
        if !lighting {
            return base;
        }
        // Normal in index space (per level-0 node), then to camera space by Mᵀ.
        let ni = [-hu * sr, -hv * sr, 1.0];
        let m = &self.m;
        let n = [
            m[0][0] * ni[0] + m[1][0] * ni[1] + m[2][0] * ni[2],
            m[0][1] * ni[0] + m[1][1] * ni[1] + m[2][1] * ni[2],
            m[0][2] * ni[0] + m[1][2] * ni[1] + m[2][2] * ni[2],
        ];
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        let cosv = if len > 0.0 && len.is_finite() {
            ((n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / len).abs()
        } else {
            1.0
        };
        let k = 0.25 + 0.75 * cosv;
        base.map(|c| c * k)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;
    use strata_common::pyramid::Dim;

    /// A wavy horizon of `n`×`n` nodes, every tile of every level resident, seen from `eye`
    /// (index coordinates; camera-relative space is index space moved by the eye).
    struct Fixture {
        pyramid: Pyramid,
        table: PageTable,
        pool: Pool,
        bounds: Vec<[f32; 2]>,
        boxes: Vec<TileBox>,
        eye: [f32; 3],
    }

    fn height(i: f64, j: f64) -> f32 {
        (10.0 + 1.5 * (i * 0.37).sin() + 1.1 * (j * 0.23 + 0.5).cos() + 0.013 * i * j) as f32
    }

    fn fixture(n: u64, eye: [f32; 3]) -> Fixture {
        fixture_of(n, eye, height)
    }

    /// [`fixture`] of the surface `height(i, j)` (level-0 node coordinates).
    fn fixture_of(n: u64, eye: [f32; 3], height: fn(f64, f64) -> f32) -> Fixture {
        fixture_without(n, eye, height, &[])
    }

    /// [`fixture_of`] with the tiles `(level, x, y)` of `missing` not resident.
    fn fixture_without(
        n: u64,
        eye: [f32; 3],
        height: fn(f64, f64) -> f32,
        missing: &[(usize, u32, u32)],
    ) -> Fixture {
        let pyramid = Pyramid::new(Dim::Two, [n, n, 1], 16, 1).unwrap();
        let (p, core, border) = (16i64, pyramid.core() as i64, 1i64);
        let mut pool = Pool::new(pyramid.page_samples(), 64 << 20);
        let mut bounds = Vec::new();
        let keep = HashSet::new();
        // The whole surface's range (level-0 nodes), which every tile's bounds hold: a
        // coarse tile must bound its descendants, whose heights its own nodes need not reach.
        let (mut all_lo, mut all_hi) = (f32::INFINITY, f32::NEG_INFINITY);
        for j in 0..n {
            for i in 0..n {
                let h = height(i as f64, j as f64);
                (all_lo, all_hi) = (all_lo.min(h), all_hi.max(h));
            }
        }
        for (l, lev) in pyramid.levels().iter().enumerate() {
            let dims = lev.dims;
            for by in 0..lev.bricks[1] {
                for bx in 0..lev.bricks[0] {
                    // Level-l node (i, j) sits at level-0 position (i + ½)·2^l − ½.
                    let s = (1u64 << l) as f64;
                    let mut page = vec![f32::NAN; (p * p) as usize];
                    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                    for lj in 0..p {
                        for li in 0..p {
                            let i = bx as i64 * core - border + li;
                            let j = by as i64 * core - border + lj;
                            if i < 0 || j < 0 || i >= dims[0] as i64 || j >= dims[1] as i64 {
                                continue;
                            }
                            let h = height((i as f64 + 0.5) * s - 0.5, (j as f64 + 0.5) * s - 0.5);
                            page[(lj * p + li) as usize] = h;
                            lo = lo.min(h);
                            hi = hi.max(h);
                        }
                    }
                    bounds.push([lo.min(all_lo), hi.max(all_hi)]);
                    let key = pyramid.id(l, [bx, by, 0]).with_dataset(0).0;
                    if !missing.contains(&(l, bx, by)) {
                        pool.place(key, &page, 0, true, &keep).unwrap();
                    }
                }
            }
        }
        let mut table = PageTable::new(&pyramid);
        table.rebuild(pool.resident_of(0, &pyramid));
        Fixture {
            boxes: tile_boxes(&pyramid, &bounds),
            pyramid,
            table,
            pool,
            bounds,
            eye,
        }
    }

    impl Fixture {
        fn frame(&self) -> HorFrame<'_> {
            let mut level_t = vec![0.0f32; self.pyramid.level_count()];
            for t in level_t.iter_mut().skip(1) {
                *t = f32::INFINITY; // level 0 everywhere
            }
            let d = self.pyramid.level(0).dims;
            HorFrame {
                ds: 0,
                m: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                c: self.eye,
                dims: [d[0] as u32, d[1] as u32],
                level_t,
                core: self.pyramid.core(),
                border: self.pyramid.border(),
                page: self.pyramid.page() as usize,
                table: &self.table,
                pool: &self.pool,
                bounds: &self.bounds,
                boxes: &self.boxes,
                color: [1.0, 0.0, 0.0],
                depth_map: None,
                attribute: None,
                opacity: 0.5,
                lighting: false,
                pyramid: &self.pyramid,
            }
        }
    }

    fn next_f32(t: f32, k: i32) -> f32 {
        f32::from_bits((t.to_bits() as i64 + k as i64) as u32)
    }

    /// Regression (issue 10): a crossing that lies on a region's face, within a few ulps,
    /// must be kept by exactly one of the two regions. The demo at 1920×1080 lost such a
    /// crossing to both at pixel (910, 469): each region tested the root against its bounds
    /// relative to the cell's entry and then rounded t_org + s to the other side.
    #[test]
    fn a_crossing_on_a_region_face_is_kept_by_exactly_one_region() {
        let f = fixture(64, [-20.0, -13.0, 40.0]);
        let (crossings, splits) = each_crossing_kept_once_at_any_face(&f, 10.0);
        assert!(crossings > 300 && splits > 2700, "{crossings} crossings");
    }

    /// The same for a flat surface at height 0 seen from 5000 above (nearly straight down):
    /// its tiles' slabs are padded by 8 ulps of the eye's height, so the leaf's crossing,
    /// rounded otherwise, lies inside them and a face between the two cannot lose it.
    #[test]
    fn a_crossing_of_a_flat_surface_far_below_is_kept_by_exactly_one_region() {
        let f = fixture_of(64, [31.3, 30.7, 5000.0], |_, _| 0.0);
        let (crossings, splits) = each_crossing_kept_once_at_any_face(&f, 0.0);
        assert!(crossings == 400 && splits == 3600, "{crossings} crossings");
    }

    /// Rays from the eye to 400 random points of the grid at height `z`: each crossing of
    /// the whole ray is kept exactly once by the two halves of the ray split at every face
    /// within 4 ulps of it. Returns the crossings and splits checked.
    fn each_crossing_kept_once_at_any_face(f: &Fixture, z: f64) -> (usize, usize) {
        let h = f.frame();
        let mut rng = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            rng ^= rng << 13;
            rng ^= rng >> 7;
            rng ^= rng << 17;
            (rng >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut crossings, mut splits) = (0, 0);
        for _ in 0..400 {
            // A ray from the eye towards a random point of the grid.
            let target = [next() * 63.0, next() * 63.0, z];
            let d = [
                target[0] as f32 - f.eye[0],
                target[1] as f32 - f.eye[1],
                target[2] as f32 - f.eye[2],
            ];
            let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            let d = d.map(|v| v / l);
            let (mut whole, mut fb) = (Vec::new(), crate::feedback::Requests::new());
            h.intersect(d, 0.0, f32::INFINITY, &mut whole, &mut fb);
            for hit in whole.clone() {
                crossings += 1;
                for k in -4..=4 {
                    let split = next_f32(hit.t, k);
                    let (mut a, mut b) = (Vec::new(), Vec::new());
                    h.intersect(d, 0.0, split, &mut a, &mut fb);
                    h.intersect(d, split, f32::INFINITY, &mut b, &mut fb);
                    let near = |v: &[Hit]| {
                        v.iter()
                            .filter(|x| (x.t - hit.t).abs() < 1e-3 * (1.0 + hit.t))
                            .count()
                    };
                    assert_eq!(
                        near(&a) + near(&b),
                        near(&whole),
                        "ray {d:?}: crossing at t = {} split at {split} ({k} ulps): kept {} times \
                         in front, {} behind",
                        hit.t,
                        near(&a),
                        near(&b)
                    );
                    splits += 1;
                }
            }
        }
        (crossings, splits)
    }

    /// Regression: a coarse tile's footprint was shifted against its children's by a
    /// quarter of its own cell, so where neighbouring tiles were drawn at different levels
    /// a strip of the surface had no tile (rays through it missed the surface) and the
    /// strip beside it two (they composited it twice). A flat surface is the same at every
    /// level, so each ray aimed at it, whatever mix of levels it meets, crosses it once,
    /// where the plane says.
    #[test]
    fn tiles_drawn_at_different_levels_leave_no_gap_and_no_overlap() {
        let eye = [-10.0f32, 131.0, 34.0];
        let f = fixture_of(256, eye, |_, _| 10.0);
        let mut h = f.frame();
        // Level l from 25·2^l on: four levels change across the view (levels 4 and up stay
        // unused, so every target below lies inside every used level's nodes).
        for (l, t) in h.level_t.iter_mut().enumerate().skip(1) {
            *t = if l <= 3 {
                25.0 * (1u32 << l) as f32
            } else {
                f32::INFINITY
            };
        }
        let mut fb = crate::feedback::Requests::new();
        let (mut rays, mut bad, mut levels) = (0, Vec::new(), HashSet::new());
        let mut y = 20.0f32;
        while y < 236.0 {
            let mut x = 20.0f32;
            while x < 236.0 {
                let d = [x - eye[0], y - eye[1], 10.0 - eye[2]];
                let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                let d = d.map(|v| v / l);
                let mut hits = Vec::new();
                h.intersect(d, 0.0, f32::INFINITY, &mut hits, &mut fb);
                let near = hits.iter().filter(|k| (k.t - l).abs() < 1e-3 * l).count();
                if hits.len() != 1 || near != 1 {
                    bad.push((x, y, hits.len()));
                    if bad.len() < 4 {
                        eprintln!("DBG {x} {y} l={l} {hits:?} want {}", h.level_at(l));
                    }
                }
                levels.insert(h.level_at(l));
                rays += 1;
                x += 0.37;
            }
            y += 1.13;
        }
        assert!(
            rays > 100_000 && levels.len() == 4,
            "{rays} rays, levels {levels:?}"
        );
        assert!(
            bad.is_empty(),
            "{} of {rays} rays crossed the plane other than once, e.g. (x, y, hits) {:?}",
            bad.len(),
            &bad[..bad.len().min(8)]
        );
    }

    /// A vertical ray's crossing is solved relative to its origin, not to where the region
    /// clipped it: a crossing on a region's face is kept by exactly one of the two regions.
    #[test]
    fn a_vertical_ray_keeps_a_crossing_on_a_region_face_in_one_region() {
        // Above the surface everywhere (its heights are 7 to 53).
        let f = fixture(64, [0.0, 0.0, 100.0]);
        let mut h = f.frame();
        let mut fb = crate::feedback::Requests::new();
        let d = [0.0f32, 0.0, -1.0];
        let mut checked = 0;
        for k in 0..200 {
            // The eye above node-space point (x, y), camera-relative space moved with it.
            let (x, y) = (1.3 + 0.301 * k as f32, 2.1 + 0.287 * k as f32);
            h.c = [x, y, 100.0];
            let mut whole = Vec::new();
            h.intersect(d, 0.0, f32::INFINITY, &mut whole, &mut fb);
            assert_eq!(whole.len(), 1, "ray at ({x}, {y})");
            let t = whole[0].t;
            for u in -4..=4 {
                let split = next_f32(t, u);
                let (mut a, mut b) = (Vec::new(), Vec::new());
                h.intersect(d, 0.0, split, &mut a, &mut fb);
                h.intersect(d, split, f32::INFINITY, &mut b, &mut fb);
                assert_eq!(
                    a.len() + b.len(),
                    1,
                    "ray at ({x}, {y}), crossing at t = {t}, split at {split} ({u} ulps): kept \
                     {} times in front, {} behind",
                    a.len(),
                    b.len()
                );
                checked += 1;
            }
        }
        assert_eq!(checked, 1800);
    }

    /// A ray crossing a surface more than 32 times keeps every crossing (the CPU caster
    /// kept only a horizon's nearest 32, the GPU a ray's: both now take them all). A
    /// horizontal ray at height 10 over `10 + 3·sin(1.3·i)` crosses it once in each cell
    /// whose two nodes lie on either side of 10.
    #[test]
    fn a_ray_keeps_every_crossing_however_many() {
        let wave = |i: f64, _: f64| (10.0 + 3.0 * (1.3 * i).sin()) as f32;
        let f = fixture_of(128, [-5.0, 40.5, 10.0], wave);
        let h = f.frame();
        let want = (0..127)
            .filter(|&i| (wave(i as f64, 0.0) > 10.0) != (wave(i as f64 + 1.0, 0.0) > 10.0))
            .count();
        let (mut hits, mut fb) = (Vec::new(), crate::feedback::Requests::new());
        h.intersect([1.0, 0.0, 0.0], 0.0, f32::INFINITY, &mut hits, &mut fb);
        assert!(want > 40, "{want}");
        assert_eq!(hits.len(), want);
    }

    /// A ray with no motion along an axis that lies on the edge between two tiles is walked
    /// by one of them. Here the tile on one side is drawn from its parent's data (its own
    /// is not resident), so the two tiles' crossings differ and both were kept.
    #[test]
    fn a_vertical_ray_on_a_tile_edge_crosses_once() {
        // Level-0 tiles are 14 nodes wide: x = 28 is the edge between tiles 1 and 2.
        let f = fixture_without(64, [28.0, 20.3, 100.0], height, &[(0, 1, 1)]);
        let h = f.frame();
        let mut fb = crate::feedback::Requests::new();
        for d in [[0.0f32, 0.0, -1.0], [0.0, 0.2, -0.98]] {
            let mut hits = Vec::new();
            h.intersect(d, 0.0, f32::INFINITY, &mut hits, &mut fb);
            assert_eq!(hits.len(), 1, "direction {d:?}: {hits:?}");
        }
    }

    /// A nearly vertical ray enters its cells far behind the eye: solved from there, its
    /// crossing carried that large t's rounding (hundredths of a node here).
    #[test]
    fn a_nearly_vertical_ray_crosses_where_the_plane_says() {
        let plane = |i: f64, j: f64| (10.0 + 0.3 * i + 0.2 * j) as f32;
        let eye = [31.3f32, 30.7, 100.0];
        let f = fixture_of(64, eye, plane);
        let h = f.frame();
        let mut fb = crate::feedback::Requests::new();
        for tilt in [1e-6f32, -3e-7, 2e-5, 7e-4] {
            let d = [tilt, -0.5 * tilt, -1.0];
            let mut hits = Vec::new();
            h.intersect(d, 0.0, f32::INFINITY, &mut hits, &mut fb);
            // 100 − t = 10 + 0.3·(x + t·dx) + 0.2·(y + t·dy), in f64.
            let (x, y, dx, dy) = (eye[0] as f64, eye[1] as f64, d[0] as f64, d[1] as f64);
            let want = (90.0 - 0.3 * x - 0.2 * y) / (1.0 + 0.3 * dx + 0.2 * dy);
            assert_eq!(hits.len(), 1, "tilt {tilt}");
            let err = (hits[0].t as f64 - want).abs();
            assert!(err < 1e-4, "tilt {tilt}: t = {}, want {want}", hits[0].t);
        }
    }

    /// A twisted surface (h = 10 + k·(i − 32)·(j − 32): bilinear in every cell, each cell
    /// twisted by k) seen nearly straight down from high above: the ray's quadratic term
    /// is tiny against its linear one, yet over a step of hundreds of nodes along the ray
    /// it moves the crossing by a node. Solved as linear below a relative threshold, the
    /// crossings were off by up to 0.9 and some were lost to both cells beside an edge, or
    /// kept by both (pinholes and double hits in a map view).
    #[test]
    fn nearly_vertical_rays_cross_a_twisted_surface_where_it_says() {
        const K: f64 = 0.05;
        let twisted = |i: f64, j: f64| (10.0 + K * (i - 32.0) * (j - 32.0)) as f32;
        let eye = [31.3f32, 30.7, 500.0];
        let f = fixture_of(64, eye, twisted);
        let h = f.frame();
        let mut fb = crate::feedback::Requests::new();
        let (mut worst, mut bad) = (0.0f64, Vec::new());
        for a in -12..=12 {
            for b in -12..=12 {
                let d = [a as f32 * 4e-3 + 1e-4, b as f32 * 4e-3 - 3e-5, -1.0f32];
                // 500 − t = 10 + K·(x + t·dx − 32)·(y + t·dy − 32), in f64: the nearest root.
                let (x, y, dx, dy) = (
                    eye[0] as f64 - 32.0,
                    eye[1] as f64 - 32.0,
                    d[0] as f64,
                    d[1] as f64,
                );
                let (qa, qb, qc) = (K * dx * dy, K * (x * dy + y * dx) + 1.0, K * x * y - 490.0);
                let q = -0.5 * (qb + qb.signum() * (qb * qb - 4.0 * qa * qc).sqrt());
                let want = [q / qa, qc / q]
                    .into_iter()
                    .filter(|t| t.is_finite() && *t > 0.0)
                    .fold(f64::INFINITY, f64::min);
                let mut hits = Vec::new();
                h.intersect(d, 0.0, f32::INFINITY, &mut hits, &mut fb);
                if hits.len() != 1 {
                    bad.push((d, hits.len()));
                    continue;
                }
                worst = worst.max((hits[0].t as f64 - want).abs());
            }
        }
        assert!(
            bad.is_empty(),
            "{} rays crossed other than once: {bad:?}",
            bad.len()
        );
        assert!(worst < 1e-3, "a crossing off by {worst} (t ≈ 490)");
    }

    /// A flat surface at height 0 seen straight down from 5000 above: its tiles' boxes,
    /// padded by 1e-4, are flat to within the rounding of the eye's height, so their slabs
    /// have no thickness in t. They had been culled, and the whole surface vanished.
    #[test]
    fn a_flat_surface_far_below_the_eye_is_found() {
        let f = fixture_of(64, [31.3, 30.7, 5000.0], |_, _| 0.0);
        let h = f.frame();
        let mut fb = crate::feedback::Requests::new();
        for (dx, dy) in [(0.0f32, 0.0f32), (1e-3, -2e-3), (-4e-3, 3e-3)] {
            let mut hits = Vec::new();
            h.intersect([dx, dy, -1.0], 0.0, f32::INFINITY, &mut hits, &mut fb);
            assert_eq!(hits.len(), 1, "direction ({dx}, {dy})");
            assert!((hits[0].t - 5000.0).abs() < 1e-3, "t = {}", hits[0].t);
        }
    }

    #[test]
    fn quadratic_roots() {
        let mut r = [0.0; 2];
        // (s-1)(s-3) = s² - 4s + 3
        assert_eq!(roots_in(1.0, -4.0, 3.0, 0.0, 10.0, &mut r), 2);
        assert!((r[0] - 1.0).abs() < 1e-6 && (r[1] - 3.0).abs() < 1e-6);
        assert_eq!(roots_in(1.0, -4.0, 3.0, 0.0, 2.0, &mut r), 1);
        assert_eq!(roots_in(0.0, 2.0, -1.0, 0.0, 1.0, &mut r), 1);
        assert!((r[0] - 0.5).abs() < 1e-7);
        assert_eq!(roots_in(1.0, 0.0, 1.0, -5.0, 5.0, &mut r), 0);
        assert_eq!(roots_in(0.0, 0.0, 1.0, -5.0, 5.0, &mut r), 0);
    }
}
