//! SIMD ray packets: eight rays of a tile marched through one volume in lockstep.
//!
//! Each lane is one ray with its own lattice index, band, brick cursor and macrocell. The
//! control flow of the scalar march ([`crate::raycast`]) runs per lane, in scalar code, up to
//! the point where the lane has the page coordinate of its next sample: locating bricks,
//! jumping over transparent bricks and invisible macrocells, moving to the next band. A
//! lane whose next sample needs none of that (it lies short of the segment's end and the
//! brick's exit, in the same macrocell or a visible next one) takes a lockstep step instead
//! (`Fast`): its `t`, index position, page coordinate and macrocell crossing computed eight
//! wide. What
//! every lane then does alike, the trilinear interpolation (AVX2 gathers from the atlas
//! slots, in the slots' own element type), the transfer-function lookup (all bands' tables
//! laid end to end; a lane's two neighbouring entries are one 32-byte load, and eight such
//! loads are transposed into channels across lanes) and the front-to-back blend, runs
//! eight lanes at a time.
//!
//! **Same image, bit for bit.** Every lane performs the scalar caster's operations in the
//! same order with the same roundings (no fused multiply-adds, truncating conversions as
//! `as` does), so a packet gives exactly the pixels, counters and page requests the scalar
//! march gives; tests compare the two bit for bit. The packet path needs AVX2 (detected at
//! run time); without it, with gradient shading, with several volumes, or with an atlas too
//! large for 32-bit gather indices, the scalar march runs (`render.simd = false` forces it).

use crate::atlas::Samples;
use crate::feedback::Requests;
use crate::raycast::{FrameSetup, RayState};
use crate::volume::{first_k, first_k_near, Cursor, VolFrame};

/// Lanes per packet.
pub const LANES: usize = 8;

/// Elements of padding after a CPU pool's last slot: a lane's gather of two neighbouring
/// 8-bit samples reads a 32-bit word, up to three bytes past the page.
pub const POOL_PAD: usize = 4;

/// All bands' transfer-function tables laid end to end, so that lanes in different bands
/// gather from one array.
#[derive(Clone, Debug, Default)]
pub struct FlatTables {
    /// Premultiplied RGBA, entry after entry, band after band.
    pub rgba: Vec<f32>,
    /// Per band: first entry, value → position scale and offset, last position.
    pub bands: Vec<FlatBand>,
}

/// One band's table in [`FlatTables`].
#[derive(Copy, Clone, Debug, Default)]
pub struct FlatBand {
    /// First entry of the band's table.
    pub base: u32,
    /// Entries.
    pub len: u32,
    /// See `StepTable::scale`.
    pub scale: f32,
    /// See `StepTable::offset`.
    pub offset: f32,
    /// See `StepTable::last`.
    pub last: f32,
}

impl FlatTables {
    /// Lays out the bands' tables.
    pub fn new(tables: &[strata_common::tf::StepTable]) -> Self {
        let mut f = FlatTables::default();
        for t in tables {
            f.bands.push(FlatBand {
                base: (f.rgba.len() / 4) as u32,
                len: t.entries.len() as u32,
                scale: t.scale,
                offset: t.offset,
                last: t.last,
            });
            for e in &t.entries {
                f.rgba.extend_from_slice(e);
            }
        }
        f
    }
}

/// Whether this CPU runs the packet path.
pub fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// A ray's piece of march handed to a packet: the interval and where the ray's march
/// stands afterwards (see [`RayState::pending`]).
#[derive(Copy, Clone, Debug)]
pub struct Pending {
    /// Index of the ray in the tile.
    pub ray: usize,
    /// Start of the volume interval to march.
    pub ta: f32,
    /// End of it.
    pub tb: f32,
    /// Where the ray's `cur_t` goes after the march.
    pub then: f32,
}

/// One lane's scalar state (the locals of the scalar `march_typed`).
struct Lane {
    ray: usize,
    live: bool,
    cur: Cursor,
    md: [f32; 3],
    inv: [f32; 3],
    tb: f32,
    t_start: f32,
    band: usize,
    in_segment: bool,
    dt: f32,
    inv_dt: f32,
    seg_end: f32,
    k: i64,
    cell_exit: f32,
    samples: u64,
    skipped: u64,
    terminated: bool,
}

/// The coordinates of a lane's next sample.
#[derive(Copy, Clone)]
struct Ready {
    l: [f32; 3],
    off: usize,
    band: usize,
}

impl Lane {
    /// Runs the scalar march's control flow until the lane's next sample (counted, as the
    /// scalar march counts it before interpolating), or the end of its interval.
    #[inline(always)]
    fn next(&mut self, f: &FrameSetup<'_>, v: &VolFrame<'_>, fb: &mut Requests) -> Option<Ready> {
        let bands = &f.bands;
        let no_cell = if v.cells.is_some() {
            f32::NEG_INFINITY
        } else {
            f32::INFINITY
        };
        let md = self.md;
        loop {
            if !self.in_segment {
                if !(self.t_start < self.tb) {
                    self.live = false;
                    return None;
                }
                self.dt = bands.dt[self.band];
                self.inv_dt = 1.0 / self.dt;
                let band_end = bands
                    .start
                    .get(self.band + 1)
                    .copied()
                    .unwrap_or(f32::INFINITY);
                self.seg_end = self.tb.min(band_end);
                self.k = first_k(self.t_start, self.dt);
                self.cell_exit = no_cell;
                self.in_segment = true;
            }
            let (k, dt, inv_dt, seg_end) = (self.k, self.dt, self.inv_dt, self.seg_end);
            let t = k as f32 * dt;
            if t >= seg_end {
                self.t_start = seg_end;
                self.band += 1;
                self.in_segment = false;
                continue;
            }
            let cur = &mut self.cur;
            if t >= cur.t_exit {
                let q = [v.c[0] + t * md[0], v.c[1] + t * md[1], v.c[2] + t * md[2]];
                v.locate(cur, t, q, md, fb);
                self.cell_exit = no_cell;
            }
            if cur.transparent {
                let nk = first_k_near(cur.t_exit.min(seg_end), dt, inv_dt).max(k + 1);
                self.skipped += (nk - k) as u64;
                self.k = nk;
                continue;
            }
            let q = [v.c[0] + t * md[0], v.c[1] + t * md[1], v.c[2] + t * md[2]];
            let l = v.local(cur, q);
            if t >= self.cell_exit {
                let (visible, exit) = v.cell_at(cur, l, md, self.inv);
                if !visible {
                    let nk = first_k_near(exit.min(cur.t_exit).min(seg_end), dt, inv_dt).max(k + 1);
                    self.skipped += (nk - k) as u64;
                    self.k = nk;
                    continue;
                }
                self.cell_exit = exit;
            }
            self.samples += 1;
            self.k = k + 1;
            return Some(Ready {
                l,
                off: cur.off,
                band: self.band,
            });
        }
    }
}

/// The lanes' state for the lockstep step, in lanes (structure of arrays): a lane whose last
/// sample came from [`Lane::next`] takes its next one here, eight wide, while `k·dt` stays
/// short of `hard` (the segment's end and the brick's exit), crossing into the next
/// macrocell here too when that cell is visible, and goes back to `Lane::next` for the step
/// that reaches a segment end, a brick boundary or an invisible cell.
#[derive(Default)]
struct Fast {
    /// −1 where the lane's state is here (its `Lane::k` is then stale), else 0.
    on: [i32; LANES],
    /// The lattice index of the lane's next sample.
    k: [i32; LANES],
    dt: [f32; LANES],
    /// The lesser of the segment's end and the brick's exit (−∞ if either is NaN: `t < NaN`
    /// fails where `min` would not).
    hard: [f32; LANES],
    /// The macrocell's exit (+∞ without macrocells).
    cell: [f32; LANES],
    md: [[f32; LANES]; 3],
    /// `1 / md`, as the lane's `inv`.
    inv: [[f32; LANES]; 3],
    /// The cursor's index → slot scale, its inverse and offsets, its slot and the slot's
    /// first element.
    s: [f32; LANES],
    rs: [f32; LANES],
    o: [[f32; LANES]; 3],
    slot: [u32; LANES],
    off: [i32; LANES],
    band: [i32; LANES],
    /// Samples taken here (added to the lane's at the end).
    count: [i32; LANES],
}

impl Fast {
    /// Takes lane `i` after [`Lane::next`] gave it a sample, where the lockstep step can
    /// reproduce its arithmetic: `k` and the slot offset fit an `i32` (whose conversion to
    /// f32 rounds as `i64 as f32` does), and the direction is finite.
    fn take(&mut self, i: usize, lane: &Lane) {
        let (k, off) = (lane.k, lane.cur.off);
        if k.unsigned_abs() >= 1 << 30 || off >= i32::MAX as usize {
            return;
        }
        // A cell crossing's exits are then never NaN (`min_ps` would not skip a NaN as
        // `f32::min` does).
        let (md, inv) = (lane.md, lane.inv);
        if !(0..3).all(|a| md[a].is_finite() && (md[a] == 0.0 || inv[a].is_finite())) {
            return;
        }
        let (a, b) = (lane.seg_end, lane.cur.t_exit);
        self.on[i] = -1;
        self.k[i] = k as i32;
        self.dt[i] = lane.dt;
        self.hard[i] = if a.is_nan() || b.is_nan() {
            f32::NEG_INFINITY
        } else {
            a.min(b)
        };
        self.cell[i] = lane.cell_exit;
        for ax in 0..3 {
            self.md[ax][i] = lane.md[ax];
            self.inv[ax][i] = lane.inv[ax];
            self.o[ax][i] = lane.cur.o[ax];
        }
        self.s[i] = lane.cur.s;
        self.rs[i] = lane.cur.rs;
        self.slot[i] = lane.cur.slot;
        self.off[i] = off as i32;
        self.band[i] = lane.band as i32;
    }
}

/// Marches up to [`LANES`] rays of a tile (`rays[p.ray]` for each `p` in `work`) through the
/// frame's single volume, each over its pending interval, and leaves every ray exactly as
/// its scalar march would.
pub fn march(
    f: &FrameSetup<'_>,
    rays: &mut [RayState<'_, '_>],
    work: &[Pending],
    fb: &mut Requests,
) {
    debug_assert!(work.len() <= LANES && f.vols.len() == 1 && available());
    let v = &f.vols[0];
    #[cfg(target_arch = "x86_64")]
    // SAFETY: the packet path is only chosen where AVX2 was detected (`available`).
    unsafe {
        match v.samples {
            Samples::F32(d) => avx2::march::<f32>(f, v, d, rays, work, fb),
            Samples::U8(d) => avx2::march::<u8>(f, v, d, rays, work, fb),
            Samples::I8(d) => avx2::march::<i8>(f, v, d, rays, work, fb),
            Samples::U16(d) => avx2::march::<u16>(f, v, d, rays, work, fb),
            Samples::I16(d) => avx2::march::<i16>(f, v, d, rays, work, fb),
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (v, rays, work, fb);
        unreachable!("packets are only chosen where AVX2 exists");
    }
}

#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::*;
    use crate::atlas::Voxel;
    use std::arch::x86_64::*;

    /// Gathers the samples at element `i` and `i + 1` of every lane from a slot array.
    pub(super) trait GatherPair: Voxel {
        /// # Safety
        /// The CPU has AVX2; every `i + 1` (and, for 8-bit types, `i + 3`) is inside the
        /// array `base` points to.
        unsafe fn pair(base: *const Self, i: __m256i) -> (__m256, __m256);
    }

    impl GatherPair for f32 {
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn pair(base: *const f32, i: __m256i) -> (__m256, __m256) {
            unsafe {
                let a = _mm256_i32gather_ps::<4>(base, i);
                let b = _mm256_i32gather_ps::<4>(base, _mm256_add_epi32(i, _mm256_set1_epi32(1)));
                (a, b)
            }
        }
    }

    impl GatherPair for u8 {
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn pair(base: *const u8, i: __m256i) -> (__m256, __m256) {
            unsafe {
                // One 32-bit word holds the sample and its x neighbour.
                let w = _mm256_i32gather_epi32::<1>(base as *const i32, i);
                let m = _mm256_set1_epi32(0xff);
                let a = _mm256_and_si256(w, m);
                let b = _mm256_and_si256(_mm256_srli_epi32::<8>(w), m);
                (_mm256_cvtepi32_ps(a), _mm256_cvtepi32_ps(b))
            }
        }
    }

    impl GatherPair for i8 {
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn pair(base: *const i8, i: __m256i) -> (__m256, __m256) {
            unsafe {
                let w = _mm256_i32gather_epi32::<1>(base as *const i32, i);
                let a = _mm256_srai_epi32::<24>(_mm256_slli_epi32::<24>(w));
                let b = _mm256_srai_epi32::<24>(_mm256_slli_epi32::<16>(w));
                (_mm256_cvtepi32_ps(a), _mm256_cvtepi32_ps(b))
            }
        }
    }

    impl GatherPair for u16 {
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn pair(base: *const u16, i: __m256i) -> (__m256, __m256) {
            unsafe {
                let w = _mm256_i32gather_epi32::<2>(base as *const i32, i);
                let a = _mm256_and_si256(w, _mm256_set1_epi32(0xffff));
                let b = _mm256_srli_epi32::<16>(w);
                (_mm256_cvtepi32_ps(a), _mm256_cvtepi32_ps(b))
            }
        }
    }

    impl GatherPair for i16 {
        #[inline]
        #[target_feature(enable = "avx2")]
        unsafe fn pair(base: *const i16, i: __m256i) -> (__m256, __m256) {
            unsafe {
                let w = _mm256_i32gather_epi32::<2>(base as *const i32, i);
                let a = _mm256_srai_epi32::<16>(_mm256_slli_epi32::<16>(w));
                let b = _mm256_srai_epi32::<16>(w);
                (_mm256_cvtepi32_ps(a), _mm256_cvtepi32_ps(b))
            }
        }
    }

    /// `a + f·(b − a)`, as the scalar code evaluates it.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn lerp(a: __m256, b: __m256, f: __m256) -> __m256 {
        _mm256_add_ps(a, _mm256_mul_ps(f, _mm256_sub_ps(b, a)))
    }

    /// Loads eight i32.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn load_i(a: &[i32; LANES]) -> __m256i {
        // SAFETY: eight i32 are 32 bytes; unaligned load.
        unsafe { _mm256_loadu_si256(a.as_ptr() as *const __m256i) }
    }

    /// Loads eight f32.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn load_f(a: &[f32; LANES]) -> __m256 {
        // SAFETY: eight f32 are 32 bytes; unaligned load.
        unsafe { _mm256_loadu_ps(a.as_ptr()) }
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn march<T: GatherPair>(
        f: &FrameSetup<'_>,
        v: &VolFrame<'_>,
        data: &[T],
        rays: &mut [RayState<'_, '_>],
        work: &[Pending],
        fb: &mut Requests,
    ) {
        let p = v.page;
        // Gathers index with i32: the pool and the tables must fit (the engine chooses the
        // packet path only then).
        assert!(data.len() < i32::MAX as usize && v.flat.rgba.len() < i32::MAX as usize);
        let mut lanes: Vec<Lane> = work
            .iter()
            .map(|w| {
                let r = &rays[w.ray];
                let md = r.md0();
                let bands = &f.bands;
                let mut band = 0;
                while band + 1 < bands.start.len() && w.ta >= bands.start[band + 1] {
                    band += 1;
                }
                Lane {
                    ray: w.ray,
                    live: true,
                    cur: r.cursor().clone(),
                    md,
                    inv: md.map(|m| 1.0 / m),
                    tb: w.tb,
                    t_start: w.ta,
                    band,
                    in_segment: false,
                    dt: 0.0,
                    inv_dt: 0.0,
                    seg_end: 0.0,
                    k: 0,
                    cell_exit: 0.0,
                    samples: 0,
                    skipped: 0,
                    terminated: false,
                }
            })
            .collect();
        let mut acc = [[0.0f32; LANES]; 4];
        // Each lane's own termination threshold (lower under cross-worker occlusion).
        let mut erts = [f.ert; LANES];
        for (i, w) in work.iter().enumerate() {
            let a = rays[w.ray].acc();
            for c in 0..4 {
                acc[c][i] = a[c];
            }
            erts[i] = rays[w.ray].ert();
        }
        // The lockstep state of the lanes whose next sample needs none of the scalar
        // control flow.
        let mut fast = Fast::default();
        // The lanes still marching, a bit each.
        let mut live_bits: i32 = (1 << lanes.len()) - 1;
        // SAFETY (all intrinsics below): AVX2 is enabled for this function; every gather
        // index is in bounds as argued where it is formed.
        unsafe {
            let mut ar = load_f(&acc[0]);
            let mut ag = load_f(&acc[1]);
            let mut ab = load_f(&acc[2]);
            let mut aa = load_f(&acc[3]);
            let ert = load_f(&erts);
            let one = _mm256_set1_ps(1.0);
            let zero = _mm256_setzero_ps();
            let lut = v.flat.rgba.as_ptr();
            let (sy, sz) = (p as i32, (p * p) as i32);
            let vc = [0, 1, 2].map(|a| _mm256_set1_ps(v.c[a]));
            let maxc = _mm256_set1_ps((p - 1) as f32 - 1e-3);
            loop {
                // The fast lanes' next sample: `t = k·dt` short of the segment's end, the
                // brick's exit and the macrocell's exit, so the scalar `Lane::next` would
                // do no more than compute `l` as `VolFrame::local` does (same operations,
                // same order) and count the sample (or, at the cell's exit, also find the
                // next cell visible, below). Lanes outside those bounds run it.
                let kv = load_i(&fast.k);
                let t = _mm256_mul_ps(_mm256_cvtepi32_ps(kv), load_f(&fast.dt));
                let below = _mm256_and_ps(
                    _mm256_castsi256_ps(load_i(&fast.on)),
                    _mm256_cmp_ps::<_CMP_LT_OQ>(t, load_f(&fast.hard)),
                );
                let cell_v = load_f(&fast.cell);
                let mut go = _mm256_and_ps(below, _mm256_cmp_ps::<_CMP_LT_OQ>(t, cell_v));
                let s_v = load_f(&fast.s);
                // (Spelled out per axis: a closure would not inherit this function's AVX2.)
                macro_rules! local {
                    ($a:expr) => {{
                        let q = _mm256_add_ps(vc[$a], _mm256_mul_ps(t, load_f(&fast.md[$a])));
                        let l = _mm256_add_ps(_mm256_mul_ps(q, s_v), load_f(&fast.o[$a]));
                        // `f32::clamp(0, maxc)`: below 0 → 0, then above maxc → maxc.
                        let l = _mm256_blendv_ps(l, zero, _mm256_cmp_ps::<_CMP_LT_OQ>(l, zero));
                        let l = _mm256_blendv_ps(l, maxc, _mm256_cmp_ps::<_CMP_GT_OQ>(l, maxc));
                        l
                    }};
                }
                let l3 = [local!(0), local!(1), local!(2)];
                // Lanes at their macrocell's exit (inside the brick and the segment): the
                // next cell as `VolFrame::cell_at` finds it; into a visible one the lane
                // samples here, an invisible one is skipped by `Lane::next`.
                let cross = _mm256_andnot_ps(_mm256_cmp_ps::<_CMP_LT_OQ>(t, cell_v), below);
                if let (Some(cells), true) = (v.cells, _mm256_movemask_ps(cross) != 0) {
                    let n = v.cells_per_axis;
                    // `l as usize / CELL` (`l` is clamped to [0, p − 1)); CELL is 2⁴.
                    const _: () = assert!(crate::macrocell::CELL == 16);
                    let ci = [
                        _mm256_srli_epi32::<4>(_mm256_cvttps_epi32(l3[0])),
                        _mm256_srli_epi32::<4>(_mm256_cvttps_epi32(l3[1])),
                        _mm256_srli_epi32::<4>(_mm256_cvttps_epi32(l3[2])),
                    ];
                    let vn = _mm256_set1_epi32(n as i32);
                    let idx = _mm256_add_epi32(
                        _mm256_mullo_epi32(
                            _mm256_add_epi32(_mm256_mullo_epi32(ci[2], vn), ci[1]),
                            vn,
                        ),
                        ci[0],
                    );
                    let mut exit = _mm256_set1_ps(f32::INFINITY);
                    let cell = _mm256_set1_epi32(crate::macrocell::CELL as i32);
                    let rs_v = load_f(&fast.rs);
                    for a in (0..3).rev() {
                        let dir = _mm256_mul_ps(load_f(&fast.md[a]), s_v);
                        let lo = _mm256_mullo_epi32(ci[a], cell);
                        let hi = _mm256_add_epi32(lo, cell);
                        let up = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_GT_OQ>(dir, zero));
                        let bound = _mm256_cvtepi32_ps(_mm256_blendv_epi8(lo, hi, up));
                        let e = _mm256_mul_ps(
                            _mm256_sub_ps(
                                _mm256_mul_ps(_mm256_sub_ps(bound, load_f(&fast.o[a])), rs_v),
                                vc[a],
                            ),
                            load_f(&fast.inv[a]),
                        );
                        // `dir != 0.0` as the scalar code has it. Where it holds, `e` is not
                        // NaN (`Fast::take` admits only lanes with finite `md`, and finite
                        // `inv` where `md` is not 0), so `min_ps` is `f32::min` here.
                        let moving = _mm256_cmp_ps::<_CMP_NEQ_UQ>(dir, zero);
                        exit = _mm256_blendv_ps(exit, _mm256_min_ps(exit, e), moving);
                    }
                    let (mut idxs, mut exits) = ([0i32; LANES], [0.0f32; LANES]);
                    _mm256_storeu_si256(idxs.as_mut_ptr() as *mut __m256i, idx);
                    _mm256_storeu_ps(exits.as_mut_ptr(), exit);
                    let bits = _mm256_movemask_ps(cross);
                    let mut into = [0i32; LANES];
                    for i in 0..LANES {
                        if bits >> i & 1 == 1 {
                            let c = fast.slot[i] as usize * n * n * n + idxs[i] as usize;
                            if cells[c] != 0 {
                                fast.cell[i] = exits[i];
                                into[i] = -1;
                            }
                        }
                    }
                    go = _mm256_or_ps(go, _mm256_castsi256_ps(load_i(&into)));
                }
                let go_bits = _mm256_movemask_ps(go);
                let go_i = _mm256_castps_si256(go);
                // k + 1 and one more sample where a fast lane sampled.
                _mm256_storeu_si256(
                    fast.k.as_mut_ptr() as *mut __m256i,
                    _mm256_sub_epi32(kv, go_i),
                );
                _mm256_storeu_si256(
                    fast.count.as_mut_ptr() as *mut __m256i,
                    _mm256_sub_epi32(load_i(&fast.count), go_i),
                );
                // The band of the ready lanes if they share one (`MIXED`: they do not).
                const MIXED: usize = usize::MAX - 1;
                let mut bands = [0usize; LANES];
                // Where every live lane has a lockstep sample (nearly every step), the
                // sample positions stay in registers and no lane runs scalar code.
                let band0 = fast.band[(go_bits.trailing_zeros() as usize).min(LANES - 1)];
                let same_band = _mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(
                    load_i(&fast.band),
                    _mm256_set1_epi32(band0),
                ))) & go_bits
                    == go_bits;
                let (x, y, z, offs, mask, common) =
                    if go_bits != 0 && go_bits == live_bits && same_band {
                        (
                            _mm256_and_ps(l3[0], go),
                            _mm256_and_ps(l3[1], go),
                            _mm256_and_ps(l3[2], go),
                            _mm256_and_si256(load_i(&fast.off), go_i),
                            go,
                            band0 as usize,
                        )
                    } else {
                        let (mut lx, mut ly, mut lz) =
                            ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
                        let mut offs = [0i32; LANES];
                        // Lanes without a lockstep sample read the start of slot 0 (in bounds)
                        // unless the scalar march gives them one below.
                        _mm256_storeu_ps(lx.as_mut_ptr(), _mm256_and_ps(l3[0], go));
                        _mm256_storeu_ps(ly.as_mut_ptr(), _mm256_and_ps(l3[1], go));
                        _mm256_storeu_ps(lz.as_mut_ptr(), _mm256_and_ps(l3[2], go));
                        _mm256_storeu_si256(
                            offs.as_mut_ptr() as *mut __m256i,
                            _mm256_and_si256(load_i(&fast.off), go_i),
                        );
                        let mut on = [0i32; LANES];
                        let mut any = false;
                        // `usize::MAX`: no ready lane yet.
                        let mut common = usize::MAX;
                        for (i, lane) in lanes.iter_mut().enumerate() {
                            let band = if go_bits >> i & 1 == 1 {
                                fast.band[i] as usize
                            } else {
                                if !lane.live {
                                    continue;
                                }
                                if fast.on[i] != 0 {
                                    lane.k = fast.k[i] as i64;
                                    lane.cell_exit = fast.cell[i];
                                    fast.on[i] = 0;
                                }
                                let Some(r) = lane.next(f, v, fb) else {
                                    live_bits &= !(1 << i);
                                    continue;
                                };
                                (lx[i], ly[i], lz[i]) = (r.l[0], r.l[1], r.l[2]);
                                offs[i] = r.off as i32;
                                fast.take(i, lane);
                                r.band
                            };
                            common = if common == usize::MAX || common == band {
                                band
                            } else {
                                MIXED
                            };
                            bands[i] = band;
                            on[i] = -1;
                            any = true;
                        }
                        if !any {
                            break;
                        }
                        (
                            load_f(&lx),
                            load_f(&ly),
                            load_f(&lz),
                            load_i(&offs),
                            _mm256_castsi256_ps(load_i(&on)),
                            common,
                        )
                    };
                // Each lane's band table: one broadcast when the lanes share a band (nearly
                // always), else per lane. Masked lanes take the same (their lookups stay
                // inside that band's table).
                let (base, scale, offset, last, maxi) = if common != MIXED {
                    let b = &v.flat.bands[common];
                    (
                        _mm256_set1_epi32(b.base as i32),
                        _mm256_set1_ps(b.scale),
                        _mm256_set1_ps(b.offset),
                        _mm256_set1_ps(b.last),
                        _mm256_set1_epi32(b.len as i32 - 2),
                    )
                } else {
                    let mut base = [0i32; LANES];
                    let mut scale = [0.0f32; LANES];
                    let mut offset = [0.0f32; LANES];
                    let mut last = [0.0f32; LANES];
                    let mut maxi = [0i32; LANES];
                    for i in 0..LANES {
                        let b = &v.flat.bands[bands[i]];
                        base[i] = b.base as i32;
                        scale[i] = b.scale;
                        offset[i] = b.offset;
                        last[i] = b.last;
                        maxi[i] = b.len as i32 - 2;
                    }
                    (
                        load_i(&base),
                        load_f(&scale),
                        load_f(&offset),
                        load_f(&last),
                        load_i(&maxi),
                    )
                };
                // Trilinear, as `trilinear_at`: coordinates are in [0, p − 1), so every
                // tap index is below off + p³ (and 8-bit pair reads stay within the pool's
                // padding).
                let xi = _mm256_cvttps_epi32(x);
                let yi = _mm256_cvttps_epi32(y);
                let zi = _mm256_cvttps_epi32(z);
                let fx = _mm256_sub_ps(x, _mm256_cvtepi32_ps(xi));
                let fy = _mm256_sub_ps(y, _mm256_cvtepi32_ps(yi));
                let fz = _mm256_sub_ps(z, _mm256_cvtepi32_ps(zi));
                let vp = _mm256_set1_epi32(p as i32);
                let idx = _mm256_add_epi32(
                    offs,
                    _mm256_add_epi32(
                        _mm256_mullo_epi32(_mm256_add_epi32(_mm256_mullo_epi32(zi, vp), yi), vp),
                        xi,
                    ),
                );
                let ptr = data.as_ptr();
                macro_rules! row {
                    ($d:expr) => {{
                        let (a, b) = T::pair(ptr, _mm256_add_epi32(idx, _mm256_set1_epi32($d)));
                        lerp(a, b, fx)
                    }};
                }
                let c00 = row!(0);
                let c10 = row!(sy);
                let c01 = row!(sz);
                let c11 = row!(sz + sy);
                let c0 = lerp(c00, c10, fy);
                let c1 = lerp(c01, c11, fy);
                let s = lerp(c0, c1, fz);
                // A NaN sample (no data) is transparent: masked off, after an in-bounds
                // lookup (max_ps returns its second operand for NaN).
                let valid = _mm256_and_ps(mask, _mm256_cmp_ps::<_CMP_ORD_Q>(s, s));
                // Lookup, as `StepTable::lookup`.
                let pos = _mm256_add_ps(_mm256_mul_ps(s, scale), offset);
                let pos = _mm256_min_ps(_mm256_max_ps(pos, zero), last);
                let e = _mm256_min_epi32(_mm256_cvttps_epi32(pos), maxi);
                let fe = _mm256_sub_ps(pos, _mm256_cvtepi32_ps(e));
                // Entries e and e + 1 of the lane's band (e ≤ len − 2, so e + 1 is in the
                // band's table) are eight consecutive floats: one load per lane, then an
                // 8 × 8 transpose into the entries' channels across lanes (cheaper than
                // eight gathers).
                let mut ei = [0i32; LANES];
                _mm256_storeu_si256(
                    ei.as_mut_ptr() as *mut __m256i,
                    _mm256_slli_epi32::<2>(_mm256_add_epi32(e, base)),
                );
                // (Spelled out: a closure would not inherit this function's AVX2.)
                let r0 = _mm256_loadu_ps(lut.add(ei[0] as usize));
                let r1 = _mm256_loadu_ps(lut.add(ei[1] as usize));
                let r2 = _mm256_loadu_ps(lut.add(ei[2] as usize));
                let r3 = _mm256_loadu_ps(lut.add(ei[3] as usize));
                let r4 = _mm256_loadu_ps(lut.add(ei[4] as usize));
                let r5 = _mm256_loadu_ps(lut.add(ei[5] as usize));
                let r6 = _mm256_loadu_ps(lut.add(ei[6] as usize));
                let r7 = _mm256_loadu_ps(lut.add(ei[7] as usize));
                let (t0, t1) = (_mm256_unpacklo_ps(r0, r1), _mm256_unpackhi_ps(r0, r1));
                let (t2, t3) = (_mm256_unpacklo_ps(r2, r3), _mm256_unpackhi_ps(r2, r3));
                let (t4, t5) = (_mm256_unpacklo_ps(r4, r5), _mm256_unpackhi_ps(r4, r5));
                let (t6, t7) = (_mm256_unpacklo_ps(r6, r7), _mm256_unpackhi_ps(r6, r7));
                let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
                let u1 = _mm256_shuffle_ps::<0xee>(t0, t2);
                let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
                let u3 = _mm256_shuffle_ps::<0xee>(t1, t3);
                let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
                let u5 = _mm256_shuffle_ps::<0xee>(t4, t6);
                let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
                let u7 = _mm256_shuffle_ps::<0xee>(t5, t7);
                // Channel c of entry e in column c, of entry e + 1 in column c + 4.
                macro_rules! ch {
                    ($u:expr, $w:expr) => {{
                        let a = _mm256_permute2f128_ps::<0x20>($u, $w);
                        let b = _mm256_permute2f128_ps::<0x31>($u, $w);
                        _mm256_and_ps(lerp(a, b, fe), valid)
                    }};
                }
                let (sr, sg, sb, sa) = (ch!(u0, u4), ch!(u1, u5), ch!(u2, u6), ch!(u3, u7));
                // Blend, as `blend`: masked lanes add t·0 and keep their value exactly.
                let t = _mm256_sub_ps(one, aa);
                ar = _mm256_add_ps(ar, _mm256_mul_ps(t, sr));
                ag = _mm256_add_ps(ag, _mm256_mul_ps(t, sg));
                ab = _mm256_add_ps(ab, _mm256_mul_ps(t, sb));
                aa = _mm256_add_ps(aa, _mm256_mul_ps(t, sa));
                let done =
                    _mm256_movemask_ps(_mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_GE_OQ>(aa, ert)));
                if done != 0 {
                    for (i, lane) in lanes.iter_mut().enumerate() {
                        if done >> i & 1 == 1 {
                            live_bits &= !(1 << i);
                            lane.live = false;
                            lane.terminated = true;
                            fast.on[i] = 0;
                        }
                    }
                }
            }
            _mm256_storeu_ps(acc[0].as_mut_ptr(), ar);
            _mm256_storeu_ps(acc[1].as_mut_ptr(), ag);
            _mm256_storeu_ps(acc[2].as_mut_ptr(), ab);
            _mm256_storeu_ps(acc[3].as_mut_ptr(), aa);
        }
        for (i, (lane, w)) in lanes.into_iter().zip(work).enumerate() {
            let r = &mut rays[lane.ray];
            r.finish_packet(
                [acc[0][i], acc[1][i], acc[2][i], acc[3][i]],
                lane.cur,
                lane.samples + fast.count[i] as u64,
                lane.skipped,
                lane.terminated,
                w.then,
            );
        }
    }
}
