//! Volume sampling through the atlas: the per-ray brick cursor and the lattice march.
//!
//! Samples sit at `t = k·Δt` for integer `k`, measured from the eye, with `Δt` a power of two
//! times the base step (a *band*, chosen by distance). Every region that renders part of a
//! ray therefore takes exactly the samples that rendering the ray whole would take.

use crate::atlas::{PageTable, Pool, Samples, Voxel, NOT_RESIDENT, SLOT_MASK};
use strata_common::tf::StepTable;

/// A volume prepared for one frame.
pub struct VolFrame<'a> {
    /// Data-set number.
    pub ds: u16,
    /// Camera-relative → level-0 index, linear part (rows).
    pub m: [[f32; 3]; 3],
    /// Camera-relative → level-0 index, offset.
    pub c: [f32; 3],
    /// Upper bound of the index box (`dims − 0.5`); the lower bound is −0.5.
    pub hi: [f32; 3],
    /// `level_t[l]`: distance from which level `l` is fine enough (`level_t[0] = 0`).
    pub level_t: Vec<f32>,
    /// Core samples per page axis.
    pub core: f32,
    /// Border samples.
    pub border: f32,
    /// Samples per page axis (border included).
    pub page: usize,
    /// Page table.
    pub table: &'a PageTable,
    /// Atlas pool.
    pub pool: &'a Pool,
    /// The pool's samples.
    pub samples: Samples<'a>,
    /// The pool's macrocell visibility (`slot · cells_per_slot + cell`), when the march may
    /// skip invisible macrocells.
    pub cells: Option<&'a [u8]>,
    /// With `cells`: per cell and octant, the side of the cube of invisible cells it
    /// starts ([`MacroCells::reach`](crate::macrocell::MacroCells::reach)).
    pub reach: Option<&'a [[u8; 8]]>,
    /// Macrocells per page edge.
    pub cells_per_axis: usize,
    /// Per page (page-table order): no value in it is visible under the transfer function.
    pub transparent: Vec<bool>,
    /// Per page (page-table order) and octant of ray direction, the side of the largest
    /// cube of transparent pages of its level starting at it ([`transparent_runs`]): the
    /// march jumps over the cube at once. Empty: page by page.
    pub transparent_runs: std::sync::Arc<Vec<[u8; 8]>>,
    /// With empty-space skipping: no value of the volume's range maps to a non-zero
    /// opacity, so its rays are not marched at all.
    pub invisible: bool,
    /// Per band: premultiplied, step-corrected lookup.
    pub tables: Vec<StepTable>,
    /// Per band, with `render.preintegrated`: the pre-integrated segment lookup.
    pub pre: Option<Vec<std::sync::Arc<strata_common::tf::PreintTable>>>,
    /// The same tables laid end to end (for SIMD packets).
    pub flat: crate::packet::FlatTables,
    /// Each page's feedback key, in page-table order.
    pub page_keys: &'a [u64],
    /// Slices through the volume (empty: no slice code runs).
    pub slices: &'a [crate::dataset::Slice],
    /// The transfer function (slices take its colour).
    pub tf: &'a strata_common::tf::TransferFunction,
}

/// Per page of `table` (page-table order) and octant, the side of the largest cube of
/// transparent pages of the page's level that starts at it
/// ([`empty_cubes`](crate::macrocell::empty_cubes) per level).
pub fn transparent_runs(table: &PageTable, transparent: &[bool]) -> Vec<[u8; 8]> {
    let mut out = vec![[0u8; 8]; transparent.len()];
    for li in &table.levels {
        let dims = li.bricks.map(|b| b as usize);
        let first = li.offset as usize;
        let last = first + dims.iter().product::<usize>();
        let t = &transparent[first..last];
        crate::macrocell::empty_cubes(dims, |i| t[i], &mut out[first..last]);
    }
    out
}

/// The octant of index-space direction `md` for [`VolFrame::cell_run_at`]: bit `a` set
/// where the ray descends along axis `a`.
#[inline(always)]
pub fn octant(md: [f32; 3]) -> usize {
    (md[0] < 0.0) as usize | ((md[1] < 0.0) as usize) << 1 | ((md[2] < 0.0) as usize) << 2
}

/// 2^−n, exactly (`0.5f32.powi(n)` without the libm call on the locate path); levels stay
/// far below the exponent's range.
#[inline(always)]
pub fn half_pow(n: usize) -> f32 {
    debug_assert!(n < 127);
    f32::from_bits((127 - n as u32) << 23)
}

/// The light of an unshaded sample: colour times 1, no specular.
pub const NO_LIGHT: [f32; 2] = [1.0, 0.0];

/// A ray's position in one volume's brick structure.
#[derive(Clone)]
pub struct Cursor {
    level: usize,
    /// Samples at `t >= t_exit` need a new lookup (brick or level change).
    pub t_exit: f32,
    /// The current brick has nothing visible.
    pub transparent: bool,
    /// The slot the brick's samples are read from.
    pub slot: u32,
    /// First element of that slot in the pool.
    pub off: usize,
    /// Level-0 index → slot-page coordinate: `q · s + o`.
    pub s: f32,
    /// `1 / s` (exact: `s` is a power of two).
    pub rs: f32,
    /// See `s`.
    pub o: [f32; 3],
    /// The ray's previous sample of this volume (pre-integration's segment front); NaN
    /// when there is none (the start of a span, or after skipped empty space).
    pub prev: f32,
    /// With shading, the light of that sample (`[diffuse factor, specular factor]`), for
    /// the half step after it that ends its span.
    pub prev_light: [f32; 2],
    /// The sample before `prev` (NaN: `prev` began its span).
    pub before: f32,
    /// The sampling band `prev` was taken in (its step is the band's).
    pub prev_band: u8,
    /// `prev` began its span and the half step before it is still to be composited.
    pub lead: bool,
    /// The span (or the next one) begins after skipped empty space: its lead is a whole
    /// step (see `raycast::end_span`).
    pub gap: bool,
    /// The change of the value along the ray over one step at `prev` (central differences),
    /// taken at a span's first sample: a one-sample span's ends are extrapolated by it.
    pub slope: f32,
    /// Where the ray enters and leaves the volume itself (not its part of the region), and
    /// whether the ray has taken a sample of it yet: a region's first sample past the
    /// volume's own entry follows a lattice point, and its last before the volume's own
    /// exit precedes one, that another region may skip as hidden (see `raycast::end_span`).
    pub vol_start: f32,
    /// See `vol_start`.
    pub vol_end: f32,
    /// See `vol_start`.
    pub entered: bool,
    /// Where the ray leaves this volume (within its region): the end of its last span.
    pub span_end: f32,
}

impl Default for Cursor {
    fn default() -> Self {
        Cursor {
            level: 0,
            t_exit: f32::NEG_INFINITY,
            transparent: true,
            slot: 0,
            off: 0,
            s: 1.0,
            rs: 1.0,
            o: [0.0; 3],
            prev: f32::NAN,
            prev_light: NO_LIGHT,
            before: f32::NAN,
            prev_band: 0,
            lead: false,
            gap: false,
            slope: 0.0,
            vol_start: f32::NEG_INFINITY,
            vol_end: f32::INFINITY,
            entered: false,
            span_end: f32::INFINITY,
        }
    }
}

impl<'a> VolFrame<'a> {
    /// The ray's direction in index space.
    #[inline]
    pub fn index_dir(&self, d: [f32; 3]) -> [f32; 3] {
        let m = &self.m;
        [
            m[0][0] * d[0] + m[0][1] * d[1] + m[0][2] * d[2],
            m[1][0] * d[0] + m[1][1] * d[1] + m[1][2] * d[2],
            m[2][0] * d[0] + m[2][1] * d[1] + m[2][2] * d[2],
        ]
    }

    /// `[t0, t1)` of the ray inside the volume's box (empty if `t0 >= t1`).
    pub fn interval(&self, md: [f32; 3]) -> (f32, f32) {
        let mut t0 = f32::NEG_INFINITY;
        let mut t1 = f32::INFINITY;
        for a in 0..3 {
            let (lo, hi) = (-0.5f32, self.hi[a]);
            if md[a] == 0.0 {
                if !(lo <= self.c[a] && self.c[a] < hi) {
                    return (0.0, 0.0);
                }
            } else {
                let ta = (lo - self.c[a]) / md[a];
                let tb = (hi - self.c[a]) / md[a];
                t0 = t0.max(ta.min(tb));
                t1 = t1.min(ta.max(tb));
            }
        }
        (t0, t1)
    }

    /// The level-0 index position of the ray's point at distance `t` (`md`: the ray's
    /// index-space direction).
    #[inline(always)]
    pub fn point(&self, t: f32, md: [f32; 3]) -> [f32; 3] {
        [
            self.c[0] + t * md[0],
            self.c[1] + t * md[1],
            self.c[2] + t * md[2],
        ]
    }

    /// Whether the sample at `t` (index position `q`) lies in a brick the transfer function
    /// hides, at the level its distance calls for: from the page bounds alone, resident or
    /// not, as [`locate`](Self::locate) classifies it.
    pub fn hidden_at(&self, t: f32, q: [f32; 3]) -> bool {
        let nl = self.level_t.len();
        let mut level = 0;
        while level + 1 < nl && t >= self.level_t[level + 1] {
            level += 1;
        }
        let scale = half_pow(level);
        let li = &self.table.levels[level];
        let b = [0, 1, 2].map(|a| {
            let f = (q[a] + 0.5) * scale / self.core;
            (f.max(0.0) as u32).min(li.bricks[a] - 1)
        });
        self.transparent[self.table.index(level, b)]
    }

    /// Moves the cursor to the brick holding the sample at `t` (index position `q`),
    /// recording the page in `feedback` unless it is transparent.
    #[inline(never)]
    pub fn locate(
        &self,
        cur: &mut Cursor,
        t: f32,
        q: [f32; 3],
        md: [f32; 3],
        feedback: &mut crate::feedback::Requests,
    ) {
        self.locate_page(cur, t, q, md, feedback, true)
    }

    /// [`locate`](Self::locate); with `skip_transparent` false, pages invisible under the
    /// transfer function are located (and requested) too: a slice shows every value.
    #[inline(always)]
    fn locate_page(
        &self,
        cur: &mut Cursor,
        t: f32,
        q: [f32; 3],
        md: [f32; 3],
        feedback: &mut crate::feedback::Requests,
        skip_transparent: bool,
    ) {
        let nl = self.level_t.len();
        let mut level = cur.level;
        while level + 1 < nl && t >= self.level_t[level + 1] {
            level += 1;
        }
        cur.level = level;
        let scale = half_pow(level);
        let li = &self.table.levels[level];
        let mut b = [0u32; 3];
        let mut t_exit = if level + 1 < nl {
            self.level_t[level + 1]
        } else {
            f32::INFINITY
        };
        // Brick size in level-0 samples (`core / scale`, exactly: `scale` is a power of two).
        let span = self.core * (1u32 << level) as f32;
        for a in 0..3 {
            // Truncation is the floor here: negative positions clamp to brick 0 either way
            // (and `floor` is a libm call on baseline x86-64).
            let f = (q[a] + 0.5) * scale / self.core;
            let bi = (f.max(0.0) as u32).min(li.bricks[a] - 1);
            b[a] = bi;
            if md[a] != 0.0 {
                let bound = if md[a] > 0.0 {
                    (bi + 1) as f32 * span - 0.5
                } else {
                    bi as f32 * span - 0.5
                };
                t_exit = t_exit.min((bound - self.c[a]) / md[a]);
            }
        }
        // Guard against a non-advancing exit from rounding: the next sample re-locates.
        cur.t_exit = t_exit;
        let idx = self.table.index(level, b);
        cur.transparent = skip_transparent && self.transparent[idx];
        if cur.transparent {
            // A cube of transparent bricks ahead: its exit instead of the brick's (the same
            // expression, so a cube of one gives the brick's exit bit for bit). Computed
            // again rather than with `side` in the loop above: looking the brick up before
            // the exits puts the table reads ahead of the divisions, 1.04x the frame time.
            let side = self
                .transparent_runs
                .get(idx)
                .map_or(1, |r| r[octant(md)] as u32);
            if side > 1 {
                let mut t_exit = if level + 1 < nl {
                    self.level_t[level + 1]
                } else {
                    f32::INFINITY
                };
                for a in 0..3 {
                    if md[a] != 0.0 {
                        let bound = if md[a] > 0.0 {
                            (b[a] + side).min(li.bricks[a]) as f32 * span - 0.5
                        } else {
                            (b[a] + 1).saturating_sub(side) as f32 * span - 0.5
                        };
                        t_exit = t_exit.min((bound - self.c[a]) / md[a]);
                    }
                }
                cur.t_exit = t_exit;
            }
            return;
        }
        feedback.push(self.page_keys[idx]);
        let e = self.table.entries[idx];
        if e == NOT_RESIDENT {
            cur.transparent = true;
            return;
        }
        let r = (e >> 24) as usize;
        let slot = e & SLOT_MASK;
        let sr = half_pow(r);
        let k = (r - level) as u32;
        let ps = self.pool.page_samples;
        assert_eq!(ps, self.page * self.page * self.page);
        cur.slot = slot;
        cur.off = slot as usize * ps;
        // The tap reads rely on this (see `trilinear_at`).
        assert!(cur.off + ps <= self.samples.len());
        cur.s = sr;
        cur.rs = 1.0 / sr;
        for a in 0..3 {
            let br = (b[a] >> k) as f32;
            cur.o[a] = 0.5 * sr - 0.5 - br * self.core + self.border;
        }
    }

    /// The macrocell of slot-page coordinate `l` (as [`local`](Self::local) gives it) in the
    /// cursor's slot: whether it may hold a visible value, and the `t` at which the ray
    /// leaves its box (`inv` is `1 / md` per axis). Only called with macrocells
    /// (`self.cells` set).
    #[inline(always)]
    pub fn cell_at(&self, cur: &Cursor, l: [f32; 3], md: [f32; 3], inv: [f32; 3]) -> (bool, f32) {
        self.cell_or_run_at(cur, l, md, inv, None)
    }

    /// [`cell_at`](Self::cell_at), except that for an invisible cell the `t` returned is
    /// where the ray leaves the cube of invisible cells the cell starts in the ray's
    /// octant (`oct`, see [`octant`]); the ray may jump there at once.
    #[inline(always)]
    pub fn cell_run_at(
        &self,
        cur: &Cursor,
        l: [f32; 3],
        md: [f32; 3],
        inv: [f32; 3],
        oct: usize,
    ) -> (bool, f32) {
        self.cell_or_run_at(cur, l, md, inv, Some(oct))
    }

    #[inline(always)]
    fn cell_or_run_at(
        &self,
        cur: &Cursor,
        l: [f32; 3],
        md: [f32; 3],
        inv: [f32; 3],
        run: Option<usize>,
    ) -> (bool, f32) {
        use crate::macrocell::CELL;
        let n = self.cells_per_axis;
        // `l` is clamped to [0, p − 1), so the cell is below `n`.
        let c = [0, 1, 2].map(|a| l[a] as usize / CELL);
        let i = cur.slot as usize * n * n * n + (c[2] * n + c[1]) * n + c[0];
        let visible = self.cells.expect("macrocells")[i] != 0;
        // Cells the box spans from `c` in the ray's direction: 1, or the invisible cube's.
        let side = match (visible, run, self.reach) {
            (false, Some(oct), Some(r)) => r[i][oct] as usize,
            _ => 1,
        };
        let mut exit = f32::INFINITY;
        for a in (0..3).rev() {
            let dir = md[a] * cur.s;
            if dir != 0.0 {
                let bound = if dir > 0.0 {
                    (c[a] + side).min(n) * CELL
                } else {
                    (c[a] + 1).saturating_sub(side) * CELL
                } as f32;
                // Slot coordinate `(c + t·md)·s + o` reaches `bound` (`s` is a power of two,
                // so multiplying by `rs = 1 / s` is dividing by it, exactly; `inv = 1 / md` may
                // be off by a rounding, which the cells' one-sample margin absorbs).
                exit = exit.min(((bound - cur.o[a]) * cur.rs - self.c[a]) * inv[a]);
            }
        }
        (visible, exit)
    }

    /// The ray's crossings of this volume's slices inside `[t0, t1)`, as opaque (or
    /// translucent) surface hits in the transfer function's colours at the sampled value.
    /// The page under each crossing is requested at the level the distance calls for; a
    /// crossing whose page is not resident yet, or that holds no data, shows nothing this
    /// round.
    pub fn slice_hits(
        &self,
        md: [f32; 3],
        t0: f32,
        t1: f32,
        hits: &mut Vec<crate::horizon::Hit>,
        feedback: &mut crate::feedback::Requests,
    ) {
        for s in self.slices {
            let a = s.axis;
            if md[a] == 0.0 {
                continue; // parallel to the slice
            }
            let t = (s.index - self.c[a]) / md[a];
            if !(t >= t0 && t < t1) {
                continue;
            }
            let mut q = self.point(t, md);
            q[a] = s.index;
            if (0..3).any(|k| k != a && !(q[k] >= -0.5 && q[k] < self.hi[k])) {
                continue;
            }
            // Not resident yet, or no data: nothing this round.
            let Some(c) = self.straight_at(t, q, md, feedback) else {
                continue;
            };
            let o = s.opacity;
            hits.push(crate::horizon::Hit {
                t,
                rgba: [c[0] * o, c[1] * o, c[2] * o, o],
            });
        }
    }

    /// The straight colour of this volume's value at camera-relative point `t·d` (on a
    /// horizon), through its transfer function; the page is requested at the level the
    /// distance calls for. `None` outside the volume, where the page is not resident yet,
    /// or where it holds no data.
    pub fn color_at(
        &self,
        t: f32,
        d: [f32; 3],
        feedback: &mut crate::feedback::Requests,
    ) -> Option<[f32; 3]> {
        let md = self.index_dir(d);
        let q = self.point(t, md);
        if !(0..3).all(|k| q[k] >= -0.5 && q[k] < self.hi[k]) {
            return None;
        }
        self.straight_at(t, q, md, feedback)
            .map(|c| [c[0], c[1], c[2]])
    }

    /// The straight transfer-function colour of the value at index position `q` (at ray
    /// distance `t`, direction `md`), its page located and requested even where the
    /// transfer function hides it; `None` where the page is not resident yet or holds no
    /// data.
    fn straight_at(
        &self,
        t: f32,
        q: [f32; 3],
        md: [f32; 3],
        feedback: &mut crate::feedback::Requests,
    ) -> Option<[f32; 4]> {
        let mut cur = Cursor::default();
        self.locate_page(&mut cur, t, q, md, feedback, false);
        if cur.transparent {
            return None;
        }
        let c = self.tf.straight(self.sample(&cur, q));
        (!c[0].is_nan()).then_some(c)
    }

    /// The slot-page coordinate of index position `q` through the cursor, clamped to the
    /// page's interpolation range `[0, p − 1)`.
    #[inline(always)]
    pub fn local(&self, cur: &Cursor, q: [f32; 3]) -> [f32; 3] {
        let maxc = (self.page - 1) as f32 - 1e-3;
        // Spelled out: `[_; 3].map` is not always inlined, and this runs per sample.
        [
            (q[0] * cur.s + cur.o[0]).clamp(0.0, maxc),
            (q[1] * cur.s + cur.o[1]).clamp(0.0, maxc),
            (q[2] * cur.s + cur.o[2]).clamp(0.0, maxc),
        ]
    }

    /// Trilinear sample at index position `q` through the cursor's page.
    #[inline(always)]
    pub fn sample(&self, cur: &Cursor, q: [f32; 3]) -> f32 {
        self.sample_local(cur, self.local(cur, q))
    }

    /// Trilinear sample at slot-page coordinate `l`, which must lie in `[0, p − 1)`.
    #[inline(always)]
    fn sample_local(&self, cur: &Cursor, l: [f32; 3]) -> f32 {
        let (p, o) = (self.page, cur.off);
        debug_assert!(l.iter().all(|&c| c >= 0.0 && c < (p - 1) as f32));
        // SAFETY: `locate` checked that the slot's page lies inside the pool, and every
        // caller clamps the coordinates to [0, p − 1).
        unsafe {
            match self.samples {
                Samples::F32(d) => trilinear_at(d, o, p, l),
                Samples::U8(d) => trilinear_at(d, o, p, l),
                Samples::I8(d) => trilinear_at(d, o, p, l),
                Samples::U16(d) => trilinear_at(d, o, p, l),
                Samples::I16(d) => trilinear_at(d, o, p, l),
            }
        }
    }

    /// Gradient (index units of the sampled level) by central differences.
    pub fn gradient(&self, cur: &Cursor, q: [f32; 3]) -> [f32; 3] {
        let p = self.page;
        let maxc = (p - 1) as f32 - 1e-3;
        let l = [
            q[0] * cur.s + cur.o[0],
            q[1] * cur.s + cur.o[1],
            q[2] * cur.s + cur.o[2],
        ];
        let at = |dx: f32, dy: f32, dz: f32| {
            let l = [
                (l[0] + dx).clamp(0.0, maxc),
                (l[1] + dy).clamp(0.0, maxc),
                (l[2] + dz).clamp(0.0, maxc),
            ];
            self.sample_local(cur, l)
        };
        [
            at(1.0, 0.0, 0.0) - at(-1.0, 0.0, 0.0),
            at(0.0, 1.0, 0.0) - at(0.0, -1.0, 0.0),
            at(0.0, 0.0, 1.0) - at(0.0, 0.0, -1.0),
        ]
    }
}

/// Trilinear interpolation in a `p³` page at local coordinates within `[0, p − 1)`.
#[inline(always)]
pub fn trilinear(data: &[f32], p: usize, x: f32, y: f32, z: f32) -> f32 {
    assert!(data.len() >= p * p * p);
    assert!([x, y, z].iter().all(|&c| c >= 0.0 && c < (p - 1) as f32));
    // SAFETY: checked just above.
    unsafe { trilinear_at(data, 0, p, [x, y, z]) }
}

/// Trilinear interpolation in the `p³` page starting at element `off` of `data`, at local
/// coordinates `l`, each within `[0, p − 1)`; the taps are decoded to f32 first, so every
/// element type gives the f32 page's result bit for bit.
///
/// # Safety
/// `off + p³ <= data.len()` and every `l[a]` lies in `[0, p − 1)`.
#[inline(always)]
pub unsafe fn trilinear_at<T: Voxel>(data: &[T], off: usize, p: usize, l: [f32; 3]) -> f32 {
    let [x, y, z] = l;
    let (xi, yi, zi) = (x as usize, y as usize, z as usize);
    let (fx, fy, fz) = (x - xi as f32, y - yi as f32, z - zi as f32);
    let i = off + (zi * p + yi) * p + xi;
    let (sy, sz) = (p, p * p);
    debug_assert!(i + sz + sy + 1 < off + p * p * p && off + p * p * p <= data.len());
    // SAFETY (the caller's contract): with coordinates in [0, p − 1) the largest tap index,
    // i + sz + sy + 1, is at most off + p³ − 1 < data.len().
    unsafe {
        let g = |k: usize| data.get_unchecked(k).value();
        let c00 = g(i) + fx * (g(i + 1) - g(i));
        let c10 = g(i + sy) + fx * (g(i + sy + 1) - g(i + sy));
        let c01 = g(i + sz) + fx * (g(i + sz + 1) - g(i + sz));
        let c11 = g(i + sz + sy) + fx * (g(i + sz + sy + 1) - g(i + sz + sy));
        let c0 = c00 + fy * (c10 - c00);
        let c1 = c01 + fy * (c11 - c01);
        c0 + fz * (c1 - c0)
    }
}

/// First lattice index `k` with `k·dt >= t` (as evaluated in f32).
#[inline]
pub fn first_k(t: f32, dt: f32) -> i64 {
    first_k_near(t, dt, 1.0 / dt)
}

/// [`first_k`] with `inv_dt = 1 / dt` precomputed: the same answer (the estimate only
/// starts the exact search).
#[inline]
pub fn first_k_near(t: f32, dt: f32, inv_dt: f32) -> i64 {
    // A start within about one of the answer (truncation, not `ceil`, which is a libm call
    // on baseline x86-64); the loops make it exact.
    let mut k = (t * inv_dt) as i64;
    while k > i64::MIN && ((k - 1) as f32) * dt >= t {
        k -= 1;
    }
    while (k as f32) * dt < t {
        k += 1;
    }
    k
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_pow_is_powi_bit_for_bit() {
        for n in 0..64usize {
            assert_eq!(
                half_pow(n).to_bits(),
                0.5f32.powi(n as i32).to_bits(),
                "2^-{n}"
            );
            // The brick span: `core / 2^-n` is `core · 2^n` exactly.
            if n < 24 {
                for core in [7.0f32, 62.0, 63.0, 126.0] {
                    assert_eq!(core / half_pow(n), core * (1u32 << n) as f32);
                }
            }
        }
    }

    #[test]
    fn lattice_start_is_exact() {
        for &(t, dt) in &[
            (0.0f32, 0.5f32),
            (1.0, 0.1),
            (3.3, 0.7),
            (1e5, 0.37),
            (7.0, 7.0),
        ] {
            let k = first_k(t, dt);
            assert!((k as f32) * dt >= t);
            assert!(((k - 1) as f32) * dt < t);
        }
    }

    #[test]
    fn trilinear_reproduces_linear_fields() {
        let p = 5;
        let data: Vec<f32> = (0..p * p * p)
            .map(|i| {
                let (x, y, z) = (i % p, i / p % p, i / (p * p));
                1.0 + 2.0 * x as f32 - 0.5 * y as f32 + 3.0 * z as f32
            })
            .collect();
        let v = trilinear(&data, p, 1.25, 2.5, 3.75);
        assert!((v - (1.0 + 2.5 - 1.25 + 11.25)).abs() < 1e-5);
    }
}
